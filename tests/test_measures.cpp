// The measures of SPEC 7 (paper Eq. 2-5) on small hand-built packings in a periodic cell.
// Every expected value is computed here from the analytic Hertz(-Mindlin) force of each contact,
// the positions and the branch vectors (brute force over all pairs and periodic images),
// independently of the engine's broad phase, pair list and gather.
#include <gtest/gtest.h>

#include <algorithm>
#include <array>
#include <cmath>
#include <stdexcept>
#include <string>
#include <string_view>
#include <vector>

#include "qsdem/engine/forces.hpp"
#include "qsdem/engine/measures.hpp"
#include "qsdem/engine/model.hpp"
#include "qsdem/engine/neighbor.hpp"
#include "qsdem/engine/state.hpp"
#include "qsdem/engine/step.hpp"

using namespace qsdem;

namespace {

constexpr double mm = 1e-3;

struct Sphere {
  Vec3 x;                      // Cartesian centre (m), any periodic copy
  double r;                    // radius (m)
  Vec3 v = Vec3::Zero();       // fluctuation velocity (m/s)
  Vec3 w = Vec3::Zero();       // angular velocity (rad/s)
};

constexpr double kFriction = 0.5;

// Material of SPEC 9 (E = 78 GPa, nu = 0.3, rho = 2650 kg/m^3), no damping, fixed cell.
Model make_model(double r_min) {
  Model m;
  m.contact_law = make_contact_law(m.material, kFriction);
  m.r_min = r_min;
  m.critical_time = critical_time(m.material, r_min);
  m.dt = 0.32 * m.critical_time;
  m.skin = 0.2 * r_min;
  return m;
}

double mass_of(double r) { return 2650.0 * 4.0 / 3.0 * pi * r * r * r; }
double inertia_of(double r) { return 0.4 * mass_of(r) * r * r; }

State make_state(const Vec3& box, const std::vector<Sphere>& spheres) {
  State st;
  st.cell = make_cell(box.asDiagonal());
  for (std::size_t k = 0; k < spheres.size(); ++k) {
    const Sphere& s = spheres[k];
    st.particles.add(static_cast<std::uint32_t>(k), ShapeKind::sphere, Vec3::Constant(s.r), 2650.0,
                     s.x.cwiseQuotient(box), Quat::Identity());
    st.particles.v[k] = s.v;
    st.particles.omega[k] = s.w;
    st.particles.angmom.set(k, inertia_of(s.r) * s.w);  // L = I omega for a sphere
  }
  return st;
}

// Hertz normal force F_n = 4/3 E* sqrt(R_e) delta^(3/2) (SPEC 4).
double hertz(const Material& mat, double re, double delta) {
  return 4.0 / 3.0 * mat.effective_modulus() * std::sqrt(re) * std::pow(delta, 1.5);
}

// Principal values s1 >= s2 >= s3 of a symmetric 3x3 matrix, closed form (trigonometric
// solution of the characteristic cubic), independent of the engine's Eigen solver.
Vec3 principal_values(const Mat3& a) {
  const double p1 = a(0, 1) * a(0, 1) + a(0, 2) * a(0, 2) + a(1, 2) * a(1, 2);
  const double q = a.trace() / 3;
  const double p2 = (a(0, 0) - q) * (a(0, 0) - q) + (a(1, 1) - q) * (a(1, 1) - q) +
                    (a(2, 2) - q) * (a(2, 2) - q) + 2 * p1;
  const double p = std::sqrt(p2 / 6);
  if (p == 0) return Vec3::Constant(q);
  const Mat3 b = (a - q * Mat3::Identity()) / p;
  const double r = std::clamp(b.determinant() / 2, -1.0, 1.0);
  const double phi = std::acos(r) / 3;
  const double e1 = q + 2 * p * std::cos(phi);
  const double e3 = q + 2 * p * std::cos(phi + 2 * pi / 3);
  return Vec3(e1, 3 * q - e1 - e3, e3);
}

struct Expected {
  Mat3 stress = Mat3::Zero();     // symmetric part of (1/V) sum f (x) l
  std::vector<Vec3> f, moment;    // resultants per particle
  long contacts = 0;
  double sum_fc = 0, sum_fc2 = 0;  // sum |f_c|, sum |f_c|^2 over contacts
  double max_tangential_ratio = 0; // max |F_t| / (mu F_n): must stay < 1 (no sliding)
};

// SPEC 4 and 7 by hand: every pair in every neighbouring periodic image; a contact has
// delta = r_i + r_j - |l| > 0; force on j = F_n n + F_t with F_t = -k_t dt v_t (a new contact,
// no history yet), arms from the centres to the midpoint of the overlap.
Expected by_hand(const Model& model, const Vec3& box, const std::vector<Sphere>& sp) {
  const Material& mat = model.material;
  Expected e;
  e.f.assign(sp.size(), Vec3::Zero());
  e.moment.assign(sp.size(), Vec3::Zero());
  Mat3 sum = Mat3::Zero();
  for (std::size_t i = 0; i < sp.size(); ++i)
    for (std::size_t j = i + 1; j < sp.size(); ++j)
      for (int kx = -1; kx <= 1; ++kx)
        for (int ky = -1; ky <= 1; ++ky)
          for (int kz = -1; kz <= 1; ++kz) {
            const Vec3 l = sp[j].x + Vec3(kx, ky, kz).cwiseProduct(box) - sp[i].x;
            const double d = l.norm();
            const double delta = sp[i].r + sp[j].r - d;
            if (delta <= 0) continue;
            const Vec3 n = l / d;
            const double re = sp[i].r * sp[j].r / (sp[i].r + sp[j].r);
            const double fn = hertz(mat, re, delta);
            const Vec3 arm_i = (sp[i].r - delta / 2) * n, arm_j = -(sp[j].r - delta / 2) * n;
            const Vec3 vrel = sp[j].v + sp[j].w.cross(arm_j) - sp[i].v - sp[i].w.cross(arm_i);
            const Vec3 vt = vrel - vrel.dot(n) * n;
            const double kt = 8 * mat.effective_shear_modulus() * std::sqrt(re * delta);
            const Vec3 ft = -kt * model.dt * vt;
            e.max_tangential_ratio = std::max(e.max_tangential_ratio, ft.norm() / (kFriction * fn));
            const Vec3 f = fn * n + ft;
            sum += f * l.transpose();
            e.f[j] += f;
            e.f[i] -= f;
            e.moment[j] += arm_j.cross(f);
            e.moment[i] += arm_i.cross(-f);
            ++e.contacts;
            e.sum_fc += f.norm();
            e.sum_fc2 += f.squaredNorm();
          }
  const double volume = box.prod();
  e.stress = 0.5 * (sum + sum.transpose()) / volume;
  return e;
}

// SPEC 7's indices from hand-computed resultants.
struct Indices {
  double ufr, iuf, imom, oct;
};
Indices indices(const Expected& e, double volume) {
  const double np = static_cast<double>(e.f.size()), nc = static_cast<double>(e.contacts);
  double sf = 0, sf2 = 0, sm = 0;
  for (std::size_t p = 0; p < e.f.size(); ++p) {
    sf += e.f[p].norm();
    sf2 += e.f[p].squaredNorm();
    sm += e.moment[p].norm();
  }
  const Vec3 s = principal_values(e.stress);
  const double oct = std::sqrt(s.squaredNorm()) / std::sqrt(3.0);  // paper Eq. 5
  return {(sf / np) / (e.sum_fc / nc),                              // Eq. 3
          std::sqrt(sf2 / np) / std::sqrt(e.sum_fc2 / nc),          // Eq. 2
          sm / (volume * oct), oct};                                // Eq. 4
}

double solid_volume(const std::vector<Sphere>& sp) {
  double v = 0;
  for (const auto& s : sp) v += 4.0 / 3.0 * pi * s.r * s.r * s.r;
  return v;
}

// A 3 x 3 x 3 simple cubic lattice of spheres of radius R, spacing a < 2R (overlap 2R - a),
// in a cubic cell of side 3a (27 particles: the smallest lattice the cell-size rule of SPEC 3
// admits). Particle (ix, iy, iz) has index 9 iz + 3 iy + ix.
std::vector<Sphere> cubic_lattice(double radius, double a) {
  std::vector<Sphere> sp;
  for (int iz = 0; iz < 3; ++iz)
    for (int iy = 0; iy < 3; ++iy)
      for (int ix = 0; ix < 3; ++ix) sp.push_back({a * Vec3(ix + 0.5, iy + 0.5, iz + 0.5), radius});
  return sp;
}

}  // namespace

// SPEC 7 on the simple cubic lattice under isotropic compression: each cell holds 27 contacts
// per axis, each carrying F = 4/3 E* sqrt(R/2) delta^(3/2) over a branch of length a = 2R - delta,
// so sigma = 27 F a / V I exactly; every particle is balanced (UFR = Iuf = 0) and, with normal
// forces only, no particle carries a moment (IMom = 0).
TEST(Measures, SimpleCubicLatticeIsIsotropicAndBalanced) {
  const double radius = 1 * mm, delta = 0.01 * mm, a = 2 * radius - delta;
  const auto sp = cubic_lattice(radius, a);
  const Vec3 box = Vec3::Constant(3 * a);
  State st = make_state(box, sp);
  const Model model = make_model(radius);
  evaluate_forces(model, st);
  const Measures m = measure(st);

  const double volume = 27 * a * a * a;
  const double force = hertz(model.material, radius / 2, delta);
  const double sigma = 27 * force * a / volume;
  // Round-off only: each diagonal entry sums 27 terms of relative error ~1e-15 (the overlap is
  // a difference of two lengths 200 times larger, hence 1e-12).
  const double tol = 1e-12 * sigma;
  for (int r = 0; r < 3; ++r)
    for (int c = 0; c < 3; ++c) EXPECT_NEAR(m.stress(r, c), r == c ? sigma : 0.0, tol) << r << c;
  for (int k = 0; k < 3; ++k) EXPECT_NEAR(m.principal[k], sigma, tol);
  EXPECT_NEAR(m.mean_stress, sigma, tol);
  EXPECT_NEAR(m.deviator, 0.0, 1e-6 * sigma);  // sqrt of round-off: sqrt(1e-24) relative ~ 1e-12
  EXPECT_NEAR(m.octahedral, sigma, tol);  // sqrt(3 s^2)/sqrt(3) = s (paper Eq. 5)
  EXPECT_NEAR(m.friction_angle_deg, 0.0, 1e-9);
  EXPECT_EQ(m.contacts, 81);                 // 3 per particle
  EXPECT_DOUBLE_EQ(m.coordination, 6.0);     // 2 n_c / n_p = 162 / 27
  // Balanced: resultants are differences of equal forces, zero up to round-off (1e-12 of F).
  EXPECT_LT(m.ufr, 1e-12);
  EXPECT_LT(m.iuf, 1e-12);
  EXPECT_LT(m.imom, 1e-12);
  const double vs = 27 * 4.0 / 3.0 * pi * radius * radius * radius;
  EXPECT_NEAR(m.solid_volume, vs, 1e-14 * vs);
  EXPECT_NEAR(m.volume, volume, 1e-14 * volume);
  EXPECT_NEAR(m.void_ratio, (volume - vs) / vs, 1e-13);
  EXPECT_EQ(m.ekin_trans, 0.0);
  EXPECT_EQ(m.ekin_rot, 0.0);
}

// Paper Eq. 2 and 3 with a known non-zero imbalance: the centre particle P of the lattice is moved
// by dx along x. Newton's third law makes the resultants sum to zero, so P cannot be the only
// unbalanced particle; the closed form below covers all of them:
//   P:                 F(delta - dx) - F(delta + dx) + 4 F' dx/d'           (along x)
//   right neighbour:   F(delta + dx) - F(delta);   left neighbour: F(delta) - F(delta - dx)
//   4 lateral ones:    |(F' dx/d', F - F' a/d')|,  d' = sqrt(a^2 + dx^2), F' = F(2R - d')
// The other 20 particles are balanced; of the 81 contacts, 75 do not touch P and carry F(delta).
TEST(Measures, DisplacedParticleGivesKnownUfrAndIuf) {
  const double radius = 1 * mm, delta = 0.01 * mm, a = 2 * radius - delta, dx = 0.2 * delta;
  auto sp = cubic_lattice(radius, a);
  sp[13].x.x() += dx;  // the centre particle (1, 1, 1)
  const Vec3 box = Vec3::Constant(3 * a);
  State st = make_state(box, sp);
  const Model model = make_model(radius);
  evaluate_forces(model, st);
  const Measures m = measure(st);

  auto F = [&](double overlap) { return hertz(model.material, radius / 2, overlap); };
  const double d2 = std::sqrt(a * a + dx * dx), f0 = F(delta), fp = F(delta + dx), fm = F(delta - dx),
               f2 = F(2 * radius - d2);
  const double fP = std::abs(fm - fp + 4 * f2 * dx / d2);
  const double fR = fp - f0, fL = f0 - fm;
  const double fLat2 = std::pow(f2 * dx / d2, 2) + std::pow(f0 - f2 * a / d2, 2);
  const double sum_fp = fP + fR + fL + 4 * std::sqrt(fLat2);
  const double sum_fp2 = fP * fP + fR * fR + fL * fL + 4 * fLat2;
  const double sum_fc = 75 * f0 + fp + fm + 4 * f2;
  const double sum_fc2 = 75 * f0 * f0 + fp * fp + fm * fm + 4 * f2 * f2;
  const double ufr = (sum_fp / 27) / (sum_fc / 81);                       // Eq. 3
  const double iuf = std::sqrt(sum_fp2 / 27) / std::sqrt(sum_fc2 / 81);  // Eq. 2
  ASSERT_GT(ufr, 1e-3);  // the configuration really is unbalanced
  EXPECT_EQ(m.contacts, 81);
  // The imbalances are differences of forces ~ 30 % apart: round-off ~1e-13 relative.
  EXPECT_NEAR(m.ufr, ufr, 1e-10 * ufr);
  EXPECT_NEAR(m.iuf, iuf, 1e-10 * iuf);
  // Normal forces of spheres have no lever arm: still no moments.
  EXPECT_LT(m.imom, 1e-12);
}

namespace {

// Six spheres of four sizes in an orthorhombic 10 x 11 x 12 mm cell, placed near a corner so that
// contacts cross the x, y and z faces: 0-1, 0-2, 2-3 overlap; 3-4 are 0.1 mm apart (inside the
// 0.2 mm skin: a listed pair that is not a contact); 5 is a rattler.
std::vector<Sphere> corner_cluster(const Vec3& box) {
  auto place = [](const Sphere& from, double r, const Vec3& dir, double gap) {
    return Sphere{from.x + dir.normalized() * (from.r + r + gap), r};
  };
  std::vector<Sphere> sp;
  sp.push_back({Vec3(0.8, 0.9, 11.4) * mm, 2.0 * mm});
  sp.push_back(place(sp[0], 1.5 * mm, Vec3(-1, 0.3, 0.2), -0.012 * mm));
  sp.push_back(place(sp[0], 1.2 * mm, Vec3(0.4, -1, 0.5), -0.008 * mm));
  sp.push_back(place(sp[2], 1.0 * mm, Vec3(0.3, -0.2, -1), -0.005 * mm));
  sp.push_back(place(sp[3], 1.0 * mm, Vec3(1, 0.5, -0.2), 0.1 * mm));
  sp.push_back({Vec3(5.5, 6.0, 5.0) * mm, 1.1 * mm});
  for (auto& s : sp)  // store a wrapped copy: the test must not rely on unwrapped input
    for (int k = 0; k < 3; ++k) s.x[k] -= std::floor(s.x[k] / box[k]) * box[k];
  return sp;
}

void expect_measures(const Measures& m, const Expected& e, const Vec3& box, const std::vector<Sphere>& sp,
                     double imom_floor) {
  const double volume = box.prod();
  const Indices ix = indices(e, volume);
  const double scale = e.stress.norm();
  // Round-off: a few contacts, overlaps 1/400 of the branch length: relative 1e-12 is ample.
  for (int r = 0; r < 3; ++r)
    for (int c = 0; c < 3; ++c) EXPECT_NEAR(m.stress(r, c), e.stress(r, c), 1e-12 * scale) << r << c;
  const Vec3 s = principal_values(e.stress);
  for (int k = 0; k < 3; ++k) EXPECT_NEAR(m.principal[k], s[k], 1e-11 * scale) << k;
  EXPECT_GE(m.principal[0], m.principal[1]);
  EXPECT_GE(m.principal[1], m.principal[2]);
  EXPECT_NEAR(m.mean_stress, e.stress.trace() / 3, 1e-12 * scale);
  const double q = std::sqrt(0.5 * (std::pow(s[0] - s[1], 2) + std::pow(s[1] - s[2], 2) + std::pow(s[2] - s[0], 2)));
  EXPECT_NEAR(m.deviator, q, 1e-10 * scale);
  EXPECT_NEAR(m.octahedral, ix.oct, 1e-11 * scale);
  EXPECT_NEAR(m.friction_angle_deg, std::asin((s[0] - s[2]) / (s[0] + s[2])) * 180 / pi, 1e-8);
  EXPECT_EQ(m.contacts, e.contacts);
  EXPECT_DOUBLE_EQ(m.coordination, 2.0 * static_cast<double>(e.contacts) / static_cast<double>(sp.size()));
  EXPECT_NEAR(m.ufr, ix.ufr, 1e-11 * ix.ufr);
  EXPECT_NEAR(m.iuf, ix.iuf, 1e-11 * ix.iuf);
  EXPECT_NEAR(m.imom, ix.imom, 1e-10 * ix.imom + imom_floor);
  const double vs = solid_volume(sp);
  EXPECT_NEAR(m.void_ratio, (volume - vs) / vs, 1e-12);
}

}  // namespace

// SPEC 7 on a general (anisotropic, polydisperse) configuration with contacts through three cell
// faces, a rattler (counted in n_p) and a pair inside the Verlet skin that does not overlap (listed,
// but not counted in n_c). Normal forces only.
TEST(Measures, CornerClusterMatchesHandComputation) {
  const Vec3 box = Vec3(10, 11, 12) * mm;
  const auto sp = corner_cluster(box);
  State st = make_state(box, sp);
  const Model model = make_model(1.0 * mm);
  evaluate_forces(model, st);
  const Measures m = measure(st);
  const Expected e = by_hand(model, box, sp);
  ASSERT_EQ(e.contacts, 3) << "the cluster was designed with three contacts";

  // The skin pair must be in the engine's list, otherwise the n_c check below proves nothing.
  bool skin_pair_listed = false;
  for (std::size_t k = 0; k < st.pairs.size(); ++k)
    if (st.pairs.i[k] == 3 && st.pairs.j[k] == 4) {
      skin_pair_listed = true;
      EXPECT_LE(st.pairs.overlap[k], 0.0);
    }
  EXPECT_TRUE(skin_pair_listed);
  EXPECT_EQ(m.contacts, 3);
  EXPECT_DOUBLE_EQ(m.coordination, 1.0);  // 2 * 3 / 6

  // With normal forces only every moment vanishes up to round-off (1e-16 relative).
  expect_measures(m, e, box, sp, 1e-12);
  EXPECT_LT(m.imom, 1e-12);
  EXPECT_GT(m.ufr, 0.1);  // a loose cluster is far from balanced
}

// Paper Eq. 4 with tangential forces: the particles spin and slide, so each new contact carries
// F_t = -k_t dt v_t (k_t = 8 G* sqrt(R_e delta), SPEC 4) and each particle a moment
// sum (x_c - x_p) x f_c about its centre. Kinetic energies are 1/2 m v^2 and 1/2 L.omega.
TEST(Measures, SpinningClusterGivesKnownImomAndKineticEnergy) {
  const Vec3 box = Vec3(10, 11, 12) * mm;
  auto sp = corner_cluster(box);
  const std::array<Vec3, 6> v{Vec3(0.3, -0.2, 0.1), Vec3(-0.4, 0.1, 0.5), Vec3(0.2, 0.6, -0.3),
                              Vec3(-0.5, 0.2, 0.2), Vec3(0.1, 0.1, 0.1), Vec3(0.0, -0.3, 0.4)};
  const std::array<Vec3, 6> w{Vec3(900, -300, 500), Vec3(-200, 800, 100), Vec3(400, 300, -700),
                              Vec3(-600, 200, 900), Vec3(50, 0, 0), Vec3(0, 100, -100)};
  for (std::size_t k = 0; k < sp.size(); ++k) {
    sp[k].v = v[k];
    sp[k].w = w[k];
  }
  State st = make_state(box, sp);
  const Model model = make_model(1.0 * mm);
  evaluate_forces(model, st);
  const Measures m = measure(st);
  const Expected e = by_hand(model, box, sp);
  ASSERT_EQ(e.contacts, 3);
  ASSERT_LT(e.max_tangential_ratio, 0.9) << "stay below Coulomb so F_t = -k_t dt v_t holds";
  const Indices ix = indices(e, box.prod());
  ASSERT_GT(ix.imom, 1e-4) << "the moments must be significant for the test to mean something";

  expect_measures(m, e, box, sp, 0.0);
  double et = 0, er = 0;
  for (const auto& s : sp) {
    et += 0.5 * mass_of(s.r) * s.v.squaredNorm();
    er += 0.5 * inertia_of(s.r) * s.w.squaredNorm();  // 1/2 L.omega = 1/2 I omega^2
  }
  EXPECT_NEAR(m.ekin_trans, et, 1e-13 * et);
  EXPECT_NEAR(m.ekin_rot, er, 1e-13 * er);
}

// Paper Eq. 4 after a full step: measure() must use the forces of the last force evaluation (time
// t, stored per pair) with the geometry of time t, even though step() has since moved the
// particles. Expected values are rebuilt from the contact forces and the positions saved at t.
TEST(Measures, AfterAStepUsesTheLastForceEvaluation) {
  const Vec3 box = Vec3(10, 11, 12) * mm;
  auto sp = corner_cluster(box);
  sp[0].w = Vec3(800, -400, 300);
  sp[2].w = Vec3(-300, 600, 500);
  sp[3].v = Vec3(0.3, 0.4, -0.2);
  State st = make_state(box, sp);
  const Model model = make_model(1.0 * mm);
  const std::vector<Vec3> s_at_t = st.particles.s;
  const Cell cell_at_t = st.cell;
  step(model, st);
  const Measures m = measure(st);

  const std::size_t n = sp.size();
  std::vector<Vec3> f(n, Vec3::Zero()), mom(n, Vec3::Zero());
  Mat3 sum = Mat3::Zero();
  long nc = 0;
  double sfc = 0, sfc2 = 0, max_ft = 0;
  const std::vector<Vec3> force = contact_forces_by_pair(st);
  for (std::size_t k = 0; k < st.pairs.size(); ++k) {
    const std::uint32_t i = st.pairs.i[k], j = st.pairs.j[k];
    const Vec3 l = branch_vector(cell_at_t, s_at_t[i], s_at_t[j], st.pairs.image[k]);
    const double delta = sp[i].r + sp[j].r - l.norm();
    if (delta <= 0) continue;
    const Vec3 nrm = l.normalized();
    const Vec3 fc = force[k];
    max_ft = std::max(max_ft, (fc - fc.dot(nrm) * nrm).norm() / fc.norm());
    sum += fc * l.transpose();
    f[j] += fc;
    f[i] -= fc;
    mom[j] += (-(sp[j].r - delta / 2) * nrm).cross(fc);
    mom[i] += ((sp[i].r - delta / 2) * nrm).cross(-fc);
    ++nc;
    sfc += fc.norm();
    sfc2 += fc.squaredNorm();
  }
  ASSERT_EQ(nc, 3);
  ASSERT_GT(max_ft, 1e-3) << "tangential forces are needed for non-zero moments";
  const double volume = box.prod();
  const Mat3 stress = 0.5 * (sum + sum.transpose()) / volume;
  const double oct = principal_values(stress).norm() / std::sqrt(3.0);
  double sf = 0, sf2 = 0, sm = 0, et = 0, er = 0;
  for (std::size_t p = 0; p < n; ++p) {
    sf += f[p].norm();
    sf2 += f[p].squaredNorm();
    sm += mom[p].norm();
    et += 0.5 * st.particles.mass[p] * st.particles.v[p].squaredNorm();  // v at t + dt/2
    er += 0.5 * st.particles.angmom[p].dot(st.particles.omega[p]);
  }
  const double np = static_cast<double>(n);
  // Same round-off budget as above.
  EXPECT_NEAR(m.stress.norm(), stress.norm(), 1e-12 * stress.norm());
  EXPECT_NEAR(m.octahedral, oct, 1e-11 * oct);
  EXPECT_NEAR(m.ufr, (sf / np) / (sfc / 3), 1e-11 * m.ufr);
  EXPECT_NEAR(m.iuf, std::sqrt(sf2 / np) / std::sqrt(sfc2 / 3), 1e-11 * m.iuf);
  const double imom = sm / (volume * oct);
  EXPECT_GT(imom, 1e-6);
  EXPECT_NEAR(m.imom, imom, 1e-10 * imom);
  EXPECT_NEAR(m.ekin_trans, et, 1e-13 * et);
  EXPECT_NEAR(m.ekin_rot, er, 1e-13 * er);
}

// The forces are kept by contact slot (PairList::contact_force); contact_forces_by_pair gives them
// by pair: each contact's force on j once, zero elsewhere, so that the pairs' forces summed on
// both ends are the particles' resultants. On a list built since the evaluation it refuses.
TEST(Measures, ContactForcesByPairAreTheLastEvaluationsContacts) {
  const Vec3 box = Vec3(10, 11, 12) * mm;
  State st = make_state(box, corner_cluster(box));
  const Model model = make_model(1.0 * mm);
  evaluate_forces(model, st);
  const std::vector<Vec3> by_pair = contact_forces_by_pair(st);
  ASSERT_EQ(by_pair.size(), st.pairs.size());
  const std::size_t n = st.particles.size();
  std::vector<Vec3> resultant(n, Vec3::Zero());
  int contacts = 0;
  double scale = 0;
  for (std::size_t k = 0; k < st.pairs.size(); ++k) {
    if (st.pairs.overlap[k] <= 0) {
      EXPECT_TRUE(by_pair[k].isZero()) << "pair " << k;
      continue;
    }
    ++contacts;
    EXPECT_GT(by_pair[k].norm(), 0) << "pair " << k;
    resultant[st.pairs.j[k]] += by_pair[k];
    resultant[st.pairs.i[k]] -= by_pair[k];
    scale += by_pair[k].norm();
  }
  ASSERT_EQ(contacts, 3);
  for (std::size_t a = 0; a < n; ++a)
    EXPECT_LE((resultant[a] - st.particles.force[a]).norm(), 1e-14 * scale) << "particle " << a;
  build_pairs(st.particles, st.cell, model.skin, st.pairs, st.neighbor);
  EXPECT_THROW(contact_forces_by_pair(st), std::logic_error);
}

// The registry of Measures' numbers (for_each_measure) names every member once: its values cover
// the struct's bytes (every member is a multiple of 8 bytes wide, so there is no padding), and no
// name repeats.
TEST(MeasuresRegistry, NamesEveryMemberOnce) {
  Measures m;
  std::size_t bytes = 0;
  std::vector<std::string> names;
  for_each_measure(m, [&](std::string_view name, auto& v) {
    bytes += sizeof(v);
    names.emplace_back(name);
  });
  EXPECT_EQ(bytes, sizeof(Measures)) << "a member of Measures is not in for_each_measure";
  std::sort(names.begin(), names.end());
  EXPECT_EQ(std::adjacent_find(names.begin(), names.end()), names.end()) << "a name repeats";
  EXPECT_TRUE(std::binary_search(names.begin(), names.end(), "stress"));
  EXPECT_TRUE(std::binary_search(names.begin(), names.end(), "z_mech"));
}
