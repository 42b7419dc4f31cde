// The fabric measures of SPEC 7.1 on hand-built configurations whose tensors are known: contact
// normals on one axis, the simple cubic lattice, a constructed strong/weak split, aligned
// ellipsoids, rattlers for Z_m; the statistics of random isotropic normals; a random packing of
// ellipsoids and spheres against the directions of its contact forces, rotated, and on 1 and 2
// threads.
#include <gtest/gtest.h>
#include <omp.h>

#include <cmath>
#include <vector>

#include "qsdem/engine/forces.hpp"
#include "qsdem/engine/measures.hpp"
#include "qsdem/engine/model.hpp"
#include "qsdem/engine/step.hpp"
#include "qsdem/run/generate.hpp"

using namespace qsdem;

namespace {

constexpr double mm = 1e-3;

// Material of SPEC 9, no damping, fixed cell (as test_measures.cpp).
Model make_model(double r_min) {
  Model m;
  m.contact_law = make_contact_law(m.material, 0.5);
  m.r_min = r_min;
  m.critical_time = critical_time(m.material, r_min);
  m.dt = 0.32 * m.critical_time;
  m.skin = 0.2 * r_min;
  return m;
}

// Spheres of radius r at rest at Cartesian centres x in an orthorhombic cell `box`, forces evaluated.
State spheres(const Vec3& box, const std::vector<Vec3>& x, double r) {
  State st;
  st.cell = make_cell(box.asDiagonal());
  for (std::size_t k = 0; k < x.size(); ++k)
    st.particles.add(static_cast<std::uint32_t>(k), ShapeKind::sphere, Vec3::Constant(r), 2650.0, x[k].cwiseQuotient(box),
                     Quat::Identity());
  evaluate_forces(make_model(r), st);
  return st;
}

// sqrt(3/2 phi':phi') of diag(d) by hand.
double dev_of(const Vec3& d) {
  const Vec3 p = d - Vec3::Constant(d.sum() / 3);
  return std::sqrt(1.5 * p.squaredNorm());
}

}  // namespace

// Four spheres in a periodic row along x, each touching both neighbours: every normal is e1, so
// phi = e1 e1^T, sqrt(3/2 phi':phi') = sqrt(3/2 (4/9 + 1/9 + 1/9)) = 1 = phi_1 - phi_3, the major
// direction at 90 degrees to x3. Spheres: no orientation fabric (NaN). Z_m = 2 C / N = 2.
TEST(Fabric, NormalsOnOneAxisGiveTheirDyad) {
  const double r = 1 * mm, a = 1.99 * mm;
  const State st = spheres(Vec3(4 * a, 10 * mm, 10 * mm), {{0.5 * a, 5 * mm, 5 * mm}, {1.5 * a, 5 * mm, 5 * mm},
                                                          {2.5 * a, 5 * mm, 5 * mm}, {3.5 * a, 5 * mm, 5 * mm}},
                           r);
  const Measures m = measure(st);
  ASSERT_EQ(m.contacts, 4);
  for (int i = 0; i < 3; ++i)
    for (int j = 0; j < 3; ++j) EXPECT_NEAR(m.fabric(i, j), i == 0 && j == 0 ? 1.0 : 0.0, 1e-15) << i << j;
  EXPECT_NEAR(m.fabric_dev, 1.0, 1e-15);
  EXPECT_NEAR(m.fabric_major, 1.0, 1e-15);
  EXPECT_NEAR(m.fabric_tilt_deg, 90.0, 1e-9);
  EXPECT_NEAR(m.fabric_force_dev, 1.0, 1e-15);
  EXPECT_NEAR(m.fabric_force_33, 0.0, 1e-15);
  EXPECT_TRUE(std::isnan(m.orient_dev)) << "spheres have no major axis";
  EXPECT_TRUE(std::isnan(m.orient_33));
  EXPECT_DOUBLE_EQ(m.z_mech, 2.0);
}

// The simple cubic lattice (3 x 3 x 3, 81 contacts, 27 per axis) under isotropic compression:
// phi = I/3 and the f_n-weighted fabric too (equal forces), deviators 0 (round-off: the normals
// are exact axes up to 1e-16, so 1e-14 is ample), Z_m = C_n = 6 (no rattler).
TEST(Fabric, CubicLatticeIsIsotropic) {
  const double r = 1 * mm, a = 2 * r - 0.01 * mm;
  std::vector<Vec3> x;
  for (int iz = 0; iz < 3; ++iz)
    for (int iy = 0; iy < 3; ++iy)
      for (int ix = 0; ix < 3; ++ix) x.push_back(a * Vec3(ix + 0.5, iy + 0.5, iz + 0.5));
  const Measures m = measure(spheres(Vec3::Constant(3 * a), x, r));
  ASSERT_EQ(m.contacts, 81);
  for (int i = 0; i < 3; ++i)
    for (int j = 0; j < 3; ++j) EXPECT_NEAR(m.fabric(i, j), i == j ? 1.0 / 3 : 0.0, 1e-15) << i << j;
  EXPECT_NEAR(m.fabric_dev, 0.0, 1e-14);
  EXPECT_NEAR(m.fabric_major, 1.0 / 3, 1e-15);
  EXPECT_NEAR(m.fabric_force_dev, 0.0, 1e-14);
  EXPECT_NEAR(m.fabric_force_33, 1.0 / 3, 1e-14);
  EXPECT_DOUBLE_EQ(m.z_mech, 6.0);
  EXPECT_DOUBLE_EQ(m.z_mech, m.coordination);
}

// n independent directions uniform on the sphere: with X_k = n_k n_k^T - I/3 (|X_k|^2 = 2/3 for
// every unit vector), n D^2 = (3/(2n)) |sum X_k|^2 = 1 + (3/(2n)) sum_{k != l} ((n_k.n_l)^2 - 1/3).
// (n_k.n_l) is uniform on [-1, 1], so each term has mean 0 and variance 1/5 - 1/9 = 4/45, and the
// terms are pairwise uncorrelated: E[n D^2] = 1 and Var[n D^2] = (2/5)(1 - 1/n) exactly. D shrinks
// as 1/sqrt(n) in mean square. Over M seeds the mean of n D^2 is within 4 standard deviations,
// 4 sqrt(0.4 (1 - 1/n) / M), of 1 (a chance of 6e-5 of failing for a correct code).
TEST(Fabric, RandomIsotropicNormalsHaveDeviatorOneOverSqrtN) {
  Random rng(20261204);
  const auto trial = [&](int n) {
    Mat3 phi = Mat3::Zero();
    for (int k = 0; k < n; ++k) {
      const double z = 2 * rng.uniform() - 1, az = 2 * pi * rng.uniform(), s = std::sqrt(1 - z * z);
      const Vec3 d(s * std::cos(az), s * std::sin(az), z);
      phi += d * d.transpose();
    }
    const double dev = fabric_deviator(phi / n);
    return n * dev * dev;
  };
  for (const auto& [n, seeds] : {std::pair{100, 400}, std::pair{10000, 100}}) {
    double mean = 0;
    for (int s = 0; s < seeds; ++s) mean += trial(n) / seeds;
    const double sd = std::sqrt(0.4 * (1 - 1.0 / n) / seeds);
    EXPECT_NEAR(mean, 1.0, 4 * sd) << "n = " << n;
    std::printf("[ info ] n = %d: mean n D^2 = %.4f over %d seeds (1 +- %.3f)\n", n, mean, seeds, 4 * sd);
  }
}

// Six isolated pairs of spheres: two along x3 with overlap 4 um, two along x1 and two along x2
// with 1 um. Hertz F ~ delta^(3/2): the axial pairs carry F = 8 F_1, the mean is 20/6 F_1, so the
// strong network is the two axial contacts (phi = e3 e3^T: 33 = 1, deviator 1), the weak one the
// four lateral ones (diag(1/2, 1/2, 0): 33 = 0, deviator 1/2), strong share 1/3; the f_n-weighted
// fabric is diag(2, 2, 16)/20 (33 = 0.8, deviator 0.7), while phi over all contacts is I/3. Every
// particle has one contact: all are rattlers for Z_m, which is then undefined (NaN).
TEST(Fabric, StrongAndWeakNetworksOfKnownForces) {
  const double r = 1 * mm;
  std::vector<Vec3> x;
  const Vec3 axes[3] = {Vec3::UnitX(), Vec3::UnitY(), Vec3::UnitZ()};
  for (int k = 0; k < 6; ++k) {
    const int axis = k / 2 == 0 ? 2 : k / 2 == 1 ? 0 : 1;
    const double delta = axis == 2 ? 4e-6 : 1e-6;
    const Vec3 c(5 * mm + 10 * mm * (k % 3), 5 * mm + 10 * mm * (k / 3), 10 * mm);
    x.push_back(c);
    x.push_back(c + (2 * r - delta) * axes[axis]);
  }
  const Measures m = measure(spheres(Vec3(30 * mm, 20 * mm, 20 * mm), x, r));
  ASSERT_EQ(m.contacts, 6);
  // Overlaps of 1e-6 of r are differences of mm lengths: relative 1e-10 on the forces, less on the
  // normals (exact axes).
  for (int i = 0; i < 3; ++i) EXPECT_NEAR(m.fabric(i, i), 1.0 / 3, 1e-15);
  EXPECT_NEAR(m.fabric_dev, 0.0, 1e-14);
  EXPECT_NEAR(m.fabric_strong_33, 1.0, 1e-15);
  EXPECT_NEAR(m.fabric_strong_dev, 1.0, 1e-15);
  EXPECT_NEAR(m.fabric_weak_33, 0.0, 1e-15);
  EXPECT_NEAR(m.fabric_weak_dev, 0.5, 1e-15);
  EXPECT_DOUBLE_EQ(m.strong_fraction, 2.0 / 6);
  EXPECT_NEAR(m.fabric_force_33, 0.8, 1e-8);
  EXPECT_NEAR(m.fabric_force_dev, dev_of(Vec3(0.1, 0.1, 0.8)), 1e-8);
  EXPECT_NEAR(dev_of(Vec3(0.1, 0.1, 0.8)), 0.7, 1e-15);
  EXPECT_TRUE(std::isnan(m.z_mech));
}

// Z_m = (2 C - N_1)/(N - N_0 - N_1): a triangle A, B, C of touching spheres, D touching A only,
// E touching nothing. C = 4, N = 5, N_0 = 1 (E), N_1 = 1 (D): Z_m = 7/3, against C_n = 8/5.
TEST(Fabric, MechanicalCoordinationLeavesRattlersOut) {
  const double r = 1 * mm, a = 1.99 * mm;
  const Vec3 A(8 * mm, 8 * mm, 8 * mm);
  const std::vector<Vec3> x{A, A + a * Vec3::UnitX(), A + a * Vec3(0.5, std::sqrt(0.75), 0), A - a * Vec3::UnitX(),
                            A + Vec3(3, -4, 6) * mm};
  const Measures m = measure(spheres(Vec3::Constant(20 * mm), x, r));
  ASSERT_EQ(m.contacts, 4);
  EXPECT_DOUBLE_EQ(m.coordination, 8.0 / 5);
  EXPECT_DOUBLE_EQ(m.z_mech, 7.0 / 3);
}

// Prolate spheroids (2, 1, 1) mm: four with the body x axis on x1, four turned onto x3, and a
// sphere and an oblate (1.5, 1.5, 1) mm spheroid, which have no major axis and are left out:
// <a a^T> = diag(1/2, 0, 1/2), 33 = 1/2, deviator 1/2. Turned all onto x1: a a^T = e1 e1^T.
TEST(Fabric, OrientationOfAlignedEllipsoids) {
  const auto sample = [](const Quat& second) {
    State st;
    const Vec3 box = Vec3::Constant(40 * mm);
    st.cell = make_cell(box.asDiagonal());
    for (std::uint32_t k = 0; k < 8; ++k) {
      const Vec3 x(5 * mm + 10 * mm * (k % 4), 5 * mm + 10 * mm * (k / 4), 20 * mm);
      st.particles.add(k, ShapeKind::ellipsoid, Vec3(2, 1, 1) * mm, 2650, x.cwiseQuotient(box),
                       k < 4 ? Quat::Identity() : second);
    }
    st.particles.add(8, ShapeKind::sphere, Vec3::Constant(1 * mm), 2650, Vec3(0.2, 0.2, 0.8), Quat::Identity());
    st.particles.add(9, ShapeKind::ellipsoid, Vec3(1.5, 1.5, 1) * mm, 2650, Vec3(0.7, 0.7, 0.8),
                     Quat(Eigen::AngleAxisd(0.7, Vec3(1, 2, 3).normalized())));
    evaluate_forces(make_model(1 * mm), st);
    return measure(st);
  };
  const Measures half = sample(Quat(Eigen::AngleAxisd(pi / 2, Vec3::UnitY())));  // x -> -z
  EXPECT_EQ(half.contacts, 0);
  EXPECT_NEAR(half.orient_33, 0.5, 1e-15);
  EXPECT_NEAR(half.orient_dev, 0.5, 1e-15);
  EXPECT_TRUE(std::isnan(half.fabric_dev)) << "no contacts: no contact fabric";
  const Measures aligned = sample(Quat::Identity());
  EXPECT_NEAR(aligned.orient_33, 0.0, 1e-15);
  EXPECT_NEAR(aligned.orient_dev, 1.0, 1e-15);
}

namespace {

// Overlapping spheroids, ellipsoids and spheres at rest in a triclinic cell (as test_invariance),
// a fresh list: every contact's force is its normal force, F = F_n n (no history, no motion).
State random_sample(std::uint64_t seed, std::uint32_t count, const Mat3& rotation = Mat3::Identity()) {
  Random rng(seed);
  State st;
  Mat3 h;
  h << 30e-3, 3e-3, -2e-3, 1e-3, 28e-3, 2.5e-3, -1.5e-3, 0.5e-3, 32e-3;
  const double scale = std::cbrt(count / 260.0);
  st.cell = make_cell(rotation * h * scale);
  const std::vector<Vec3> shapes = {Vec3(1.5e-3, 1e-3, 1e-3), Vec3(2e-3, 1.5e-3, 1e-3), Vec3::Constant(1.2e-3),
                                    Vec3(5e-3, 3.5e-3, 3.5e-3), Vec3(1.3e-3, 1.3e-3, 0.8e-3)};
  const Quat qr(rotation);
  for (std::uint32_t id = 0; id < count; ++id) {
    const Vec3& ax = shapes[id % shapes.size()];
    const ShapeKind kind = ax.x() == ax.z() ? ShapeKind::sphere : ShapeKind::ellipsoid;
    const Vec3 s(rng.uniform(), rng.uniform(), rng.uniform());
    st.particles.add(id, kind, ax, 2650, s, (qr * rng.orientation()).normalized());
  }
  Model m = make_model(smallest_equiv_radius(st.particles));
  evaluate_forces(m, st);
  return st;
}

}  // namespace

// On a random packing with ellipsoid contacts (Perram-Wertheim normals, SPEC 4.5): each contact's
// force is F_n n, so its direction is the normal and |F| = f_n. The tensors of SPEC 7.1 built here
// from the force directions must equal the measured ones (round-off of the normals: 1e-14 of a
// normal, amplified by the sums to far less than 1e-12).
TEST(Fabric, EllipsoidContactsMatchTheirForceDirections) {
  const State st = random_sample(5, 260);
  const Measures m = measure(st);
  const std::vector<Vec3> force = contact_forces_by_pair(st);
  Mat3 all = Mat3::Zero(), strong = Mat3::Zero(), weak = Mat3::Zero(), weighted = Mat3::Zero();
  double nc = 0, ns = 0, sum_f = 0;
  int ellipsoid_contacts = 0;
  for (std::size_t k = 0; k < st.pairs.size(); ++k)
    if (st.pairs.overlap[k] > 0) ++nc, sum_f += force[k].norm();
  for (std::size_t k = 0; k < st.pairs.size(); ++k) {
    if (st.pairs.overlap[k] <= 0) continue;
    const Vec3 n = force[k].normalized();
    const Mat3 nn = n * n.transpose();
    all += nn;
    (force[k].norm() > sum_f / nc ? strong : weak) += nn;
    ns += force[k].norm() > sum_f / nc;
    weighted += force[k].norm() * nn;
    ellipsoid_contacts += st.particles.shape[st.pairs.i[k]] == ShapeKind::ellipsoid ||
                          st.particles.shape[st.pairs.j[k]] == ShapeKind::ellipsoid;
  }
  ASSERT_GE(ellipsoid_contacts, 50) << "the test must exercise the Perram-Wertheim normals";
  EXPECT_LE((m.fabric - all / nc).cwiseAbs().maxCoeff(), 1e-12);
  EXPECT_NEAR(m.fabric_dev, fabric_deviator(all / nc), 1e-12);
  EXPECT_GT(m.fabric_dev, 0.01) << "a random packing of 260 has an anisotropy of order 1/sqrt(n_c)";
  EXPECT_NEAR(m.fabric_strong_dev, fabric_deviator(strong / ns), 1e-12);
  EXPECT_NEAR(m.fabric_strong_33, strong(2, 2) / ns, 1e-12);
  EXPECT_NEAR(m.fabric_weak_dev, fabric_deviator(weak / (nc - ns)), 1e-12);
  EXPECT_NEAR(m.fabric_weak_33, weak(2, 2) / (nc - ns), 1e-12);
  EXPECT_DOUBLE_EQ(m.strong_fraction, ns / nc);
  EXPECT_NEAR(m.fabric_force_dev, fabric_deviator(weighted / sum_f), 1e-12);
  EXPECT_NEAR(m.fabric_force_33, weighted(2, 2) / sum_f, 1e-12);
  std::printf("[ info ] %g contacts (%d with an ellipsoid), fabric_dev %.4f, strong %.4f, weak %.4f\n", nc,
              ellipsoid_contacts, m.fabric_dev, m.fabric_strong_dev, m.fabric_weak_dev);
}

// The same packing rotated as a whole (cell h -> R h, orientations q -> R q): phi -> R phi R^T and
// the orientation fabric likewise, every invariant unchanged (round-off of the narrow phase, as in
// test_invariance: 1e-12), the same rattlers.
TEST(Fabric, RotatingTheSampleRotatesTheTensors) {
  const Mat3 R = Quat(0.3, -0.5, 0.7, 0.4).normalized().toRotationMatrix();
  const Measures a = measure(random_sample(5, 260)), b = measure(random_sample(5, 260, R));
  ASSERT_EQ(a.contacts, b.contacts);
  EXPECT_LE((b.fabric - R * a.fabric * R.transpose()).cwiseAbs().maxCoeff(), 1e-12);
  for (auto f : {&Measures::fabric_dev, &Measures::fabric_major, &Measures::fabric_strong_dev,
                 &Measures::fabric_weak_dev, &Measures::fabric_force_dev, &Measures::orient_dev})
    EXPECT_NEAR(b.*f, a.*f, 1e-12);
  EXPECT_EQ(b.strong_fraction, a.strong_fraction);
  EXPECT_EQ(b.z_mech, a.z_mech);
  EXPECT_GT(a.orient_dev, 0.0);
}

// Over 4096 pairs the normals are computed in parallel and every sum is blocked (blocked_sum): 1
// and 2 threads give the same bits.
TEST(Fabric, OneAndTwoThreadsGiveTheSameBits) {
  const State st = random_sample(9, 2600);
  ASSERT_GT(st.pairs.size(), parallel_threshold) << "the normals' loop must run in parallel";
  const int saved = omp_get_max_threads();
  omp_set_num_threads(1);
  const Measures one = measure(st);
  omp_set_num_threads(2);
  const Measures two = measure(st);
  omp_set_num_threads(saved);
  EXPECT_GT(one.contacts, 2048);
  for (int i = 0; i < 3; ++i)
    for (int j = 0; j < 3; ++j) EXPECT_EQ(one.fabric(i, j), two.fabric(i, j));
  for (auto f : {&Measures::fabric_dev, &Measures::fabric_major, &Measures::fabric_tilt_deg,
                 &Measures::fabric_strong_33, &Measures::fabric_strong_dev, &Measures::fabric_weak_33,
                 &Measures::fabric_weak_dev, &Measures::strong_fraction, &Measures::fabric_force_33,
                 &Measures::fabric_force_dev, &Measures::orient_33, &Measures::orient_dev, &Measures::z_mech})
    EXPECT_EQ(one.*f, two.*f);
}
