// The measures per size class (docs/physics.md 10.3) on a hand-built arrangement of spheres of two sizes,
// every expected value counted or computed here from the Hertz force of each contact (SPEC 4).
#include <gtest/gtest.h>

#include <cmath>
#include <vector>

#include "qsdem/engine/forces.hpp"
#include "qsdem/engine/measures.hpp"
#include "qsdem/engine/model.hpp"
#include "qsdem/engine/state.hpp"
#include "qsdem/engine/step.hpp"

using namespace qsdem;

namespace {

constexpr double mm = 1e-3;

// Hertz normal force F_n = 4/3 E* sqrt(R_e) delta^(3/2) (SPEC 4).
double hertz(const Material& mat, double ri, double rj, double delta) {
  return 4.0 / 3.0 * mat.effective_modulus() * std::sqrt(ri * rj / (ri + rj)) * std::pow(delta, 1.5);
}

struct Ball {
  Vec3 x;  // centre (m)
  double r;
  Vec3 v = Vec3::Zero(), w = Vec3::Zero();
};

}  // namespace

// Three big spheres (R = 2 mm: A, B, C) and four small ones (r = 1 mm: s1..s4) in a 30 mm cell:
// A touches B (x), s1 (y) and s2 (-z); s2 touches s3 below it, across the cell's z = 0 face;
// C and s4 touch nothing and move. Contacts per particle: A 3, B 1, C 0; s1 1, s2 2, s3 1, s4 0.
TEST(ClassMeasures, TwoSizesInAKnownArrangement) {
  const double box = 30 * mm, R = 2 * mm, r = 1 * mm;
  const double dAB = 0.010 * mm, dA1 = 0.004 * mm, dA2 = 0.007 * mm, d23 = 0.002 * mm;
  const Vec3 a(10 * mm, 10 * mm, 3 * mm);
  const Vec3 s2 = a - Vec3(0, 0, R + r - dA2);                 // z = dA2: just above the face
  const Vec3 s3 = s2 - Vec3(0, 0, 2 * r - d23) + Vec3(0, 0, box);  // stored across the face
  const std::vector<Ball> balls = {
      {a, R},
      {a + Vec3(2 * R - dAB, 0, 0), R},
      {Vec3(22 * mm, 22 * mm, 20 * mm), R, Vec3::Zero(), Vec3(0, 6, 8)},  // C: |omega| = 10 1/s
      {a + Vec3(0, R + r - dA1, 0), r},
      {s2, r},
      {s3, r},
      {Vec3(22 * mm, 8 * mm, 12 * mm), r, Vec3(3e-3, 4e-3, 0), Vec3(0, 0, 2)},  // s4: |v| = 5 mm/s
  };
  State st;
  st.cell = make_cell(Vec3::Constant(box).asDiagonal());
  for (std::size_t k = 0; k < balls.size(); ++k) {
    const Ball& b = balls[k];
    st.particles.add(static_cast<std::uint32_t>(k), ShapeKind::sphere, Vec3::Constant(b.r), 2650.0, b.x / box,
                     Quat::Identity());
    st.particles.v[k] = b.v;
    st.particles.omega[k] = b.w;
    st.particles.angmom.set(k, 0.4 * st.particles.mass[k] * b.r * b.r * b.w);
  }
  Model model;
  model.contact_law = make_contact_law(model.material, 0.5);
  model.r_min = r;
  model.critical_time = critical_time(model.material, r);
  model.dt = 0.32 * model.critical_time;
  model.skin = 0.2 * r;
  evaluate_forces(model, st);

  const std::vector<double> classes = size_classes(st.particles);
  ASSERT_EQ(classes.size(), 2u);
  EXPECT_DOUBLE_EQ(classes[0], r);
  EXPECT_DOUBLE_EQ(classes[1], R);
  const std::vector<ClassMeasures> c = class_measures(st, classes);
  ASSERT_EQ(c.size(), 2u);
  const ClassMeasures &small = c[0], &big = c[1];
  EXPECT_EQ(small.count, 4);
  EXPECT_EQ(big.count, 3);
  EXPECT_DOUBLE_EQ(small.contacts, 4.0 / 4);  // 1 + 2 + 1 + 0
  EXPECT_DOUBLE_EQ(big.contacts, 4.0 / 3);    // 3 + 1 + 0
  EXPECT_DOUBLE_EQ(small.in_contact, 3.0 / 4);
  EXPECT_DOUBLE_EQ(small.in_contact_2, 1.0 / 4);
  EXPECT_DOUBLE_EQ(big.in_contact, 2.0 / 3);
  EXPECT_DOUBLE_EQ(big.in_contact_2, 1.0 / 3);
  // Spheres at rest in contact: f_c . l_c = F_n |l| (a tangential force, if any, is normal to l).
  const Material& mat = model.material;
  const double wAB = hertz(mat, R, R, dAB) * (2 * R - dAB), wA1 = hertz(mat, R, r, dA1) * (R + r - dA1),
               wA2 = hertz(mat, R, r, dA2) * (R + r - dA2), w23 = hertz(mat, r, r, d23) * (2 * r - d23);
  const double total = wAB + wA1 + wA2 + w23;
  const double tol = 1e-9;  // the overlaps are differences of lengths 1e3 times larger
  EXPECT_NEAR(big.stress_share, (wAB + 0.5 * wA1 + 0.5 * wA2) / total, tol);
  EXPECT_NEAR(small.stress_share, (0.5 * wA1 + 0.5 * wA2 + w23) / total, tol);
  EXPECT_NEAR(big.stress_share + small.stress_share, 1.0, 1e-15);
  // The shares are of SPEC 7's Love-Weber p = sum f . l / (3 V).
  EXPECT_NEAR(measure(st).mean_stress, total / (3 * box * box * box), tol * total / (3 * box * box * box));
  EXPECT_DOUBLE_EQ(small.speed, 5e-3 / 4);
  EXPECT_DOUBLE_EQ(big.speed, 0.0);
  EXPECT_DOUBLE_EQ(small.spin, 2.0 / 4);
  EXPECT_DOUBLE_EQ(big.spin, 10.0 / 3);
}

// Radii within a relative 1e-9 are one class (a packing file's rounding); classes ascend.
TEST(ClassMeasures, SizeClassesMergeRoundedRadii) {
  Particles p;
  for (double rad : {3e-3, 1e-3, 1e-3 * (1 + 1e-12), 3e-3 * (1 - 1e-12), 2e-3})
    p.add(0, ShapeKind::sphere, Vec3::Constant(rad), 2650.0, Vec3::Zero(), Quat::Identity());
  const std::vector<double> classes = size_classes(p);
  ASSERT_EQ(classes.size(), 3u);
  // A class is named by its smallest radius: 3e-3 (1 - 1e-12) for the third.
  EXPECT_DOUBLE_EQ(classes[0], 1e-3);
  EXPECT_DOUBLE_EQ(classes[1], 2e-3);
  EXPECT_NEAR(classes[2], 3e-3 * (1 - 1e-12), 1e-18);
  State st;  // no pairs: only the counts
  st.particles = p;
  const std::vector<ClassMeasures> c = class_measures(st, classes);
  ASSERT_EQ(c.size(), 3u);
  EXPECT_EQ(c[0].count, 2);
  EXPECT_EQ(c[1].count, 1);
  EXPECT_EQ(c[2].count, 2);
  EXPECT_EQ(c[0].in_contact, 0.0);
}
