// Ellipsoid-ellipsoid narrow phase (SPEC 4): Perram-Wertheim detection, overlap along the PW
// normal, Greenwood effective radius.
//
// The independent reference used here does not use Perram-Wertheim at all. For convex bodies
// the signed overlap (penetration depth when > 0, minus the gap when < 0) is
//   delta_ref = min over unit m of  g(m) = h_i(m) + h_j(m) - m . l,   h_k(m) = sqrt(m^T Q_k m)
// (support functions of the two ellipsoids, Q_k = R_k diag(a^2, b^2, c^2) R_k^T; for a gap this is
// minus the distance from l to the Minkowski sum, for an overlap the distance to its boundary).
// Its stationary points are the common-normal solutions: grad g = p_i - p_j with
// p_i = c_i + Q_i m / h_i, p_j = c_j - Q_j m / h_j, parallel to m. It is minimised by dense
// sampling of the sphere then Riemannian Newton with the analytic Hessian. The reference
// curvature comes from the Hessian of the support function (the radii-of-curvature tensor),
// not from the implicit-surface formula the code uses.
#include "qsdem/engine/ellipsoid_contact.hpp"

#include <gtest/gtest.h>

#include <algorithm>
#include <cmath>
#include <iostream>
#include <limits>
#include <random>
#include <vector>

#include "qsdem/engine/contact/geometry.hpp"

using namespace qsdem;

namespace {

constexpr double kEps = std::numeric_limits<double>::epsilon();
constexpr double kMm = 1e-3;

struct Rng {
  std::mt19937_64 engine;
  explicit Rng(std::uint64_t seed) : engine(seed) {}
  double uniform() { return std::uniform_real_distribution<double>(0, 1)(engine); }
  double normal() { return std::normal_distribution<double>(0, 1)(engine); }
  Vec3 direction() { return Vec3(normal(), normal(), normal()).normalized(); }
  Quat rotation() { return Quat(normal(), normal(), normal(), normal()).normalized(); }
  double log_uniform(double lo, double hi) { return lo * std::pow(hi / lo, uniform()); }
};

// Q = R diag(axes^2) R^T, written out here (independent of the code's helper).
Mat3 shape_Q(const Vec3& axes, const Quat& q) {
  const Mat3 R = q.normalized().toRotationMatrix();
  return R * Vec3(axes.array().square()).asDiagonal() * R.transpose();
}

// Orthonormal basis of the plane normal to the unit vector m (3x2).
Eigen::Matrix<double, 3, 2> tangent_basis(const Vec3& m) {
  const Vec3 helper = std::abs(m.x()) < 0.6 ? Vec3::UnitX() : Vec3::UnitY();
  const Vec3 t1 = m.cross(helper).normalized();
  Eigen::Matrix<double, 3, 2> T;
  T.col(0) = t1;
  T.col(1) = m.cross(t1);
  return T;
}

struct Reference {
  double overlap;  // delta_ref (> 0 overlap, < 0 gap)
  Vec3 normal;     // common normal m, from i to j
  Vec3 p_i, p_j;   // surface points relative to c_i
  double radius;   // Greenwood R_e from support-function Hessians
  int iterations;
};

double support(const Mat3& Q, const Vec3& m) { return std::sqrt(m.dot(Q * m)); }
double g_value(const Vec3& l, const Mat3& Qi, const Mat3& Qj, const Vec3& m) {
  return support(Qi, m) + support(Qj, m) - m.dot(l);
}
// Hessian of the support function h(x) = sqrt(x^T Q x) at unit x: Q/h - (Q x)(Q x)^T / h^3.
Mat3 support_hessian(const Mat3& Q, const Vec3& m) {
  const double h = support(Q, m);
  const Vec3 Qm = Q * m;
  return Q / h - Qm * Qm.transpose() / (h * h * h);
}

// Start direction: the best of ~2000 quasi-uniform (Fibonacci) directions.
Vec3 sampled_start(const Vec3& l, const Mat3& Qi, const Mat3& Qj, int samples = 2000) {
  Vec3 best = Vec3::UnitZ();
  double best_g = std::numeric_limits<double>::infinity();
  const double golden = pi * (3 - std::sqrt(5.0));
  for (int k = 0; k < samples; ++k) {
    const double z = 1 - (2 * k + 1.0) / samples;
    const double r = std::sqrt(1 - z * z);
    const Vec3 m(r * std::cos(golden * k), r * std::sin(golden * k), z);
    const double gv = g_value(l, Qi, Qj, m);
    if (gv < best_g) best_g = gv, best = m;
  }
  return best;
}

Reference reference(const Vec3& l, const Mat3& Qi, const Mat3& Qj, Vec3 m) {
  Reference ref{};
  for (int it = 0; it < 100; ++it) {
    ref.iterations = it + 1;
    const double hi = support(Qi, m), hj = support(Qj, m);
    const double gv = hi + hj - m.dot(l);
    const Vec3 grad = Qi * m / hi + Qj * m / hj - l;  // = p_i - p_j
    const auto T = tangent_basis(m);
    const Eigen::Vector2d r = T.transpose() * grad;
    // Riemannian Hessian of a degree-1 homogeneous function on the sphere: P hess P - g P.
    const Eigen::Matrix2d H =
        T.transpose() * (support_hessian(Qi, m) + support_hessian(Qj, m)) * T - gv * Eigen::Matrix2d::Identity();
    Eigen::Vector2d xi;
    const Eigen::LLT<Eigen::Matrix2d> llt(H);
    if (llt.info() == Eigen::Success) xi = -llt.solve(r); else xi = -r / (hi + hj);
    if (xi.norm() > 0.2) xi *= 0.2 / xi.norm();
    // Backtracking on g (descent), tolerant to round-off at convergence.
    Vec3 trial = (m + T * xi).normalized();
    for (int k = 0; k < 40 && g_value(l, Qi, Qj, trial) > gv + 4 * kEps * (hi + hj); ++k) {
      xi *= 0.5;
      trial = (m + T * xi).normalized();
    }
    m = trial;
    if (xi.norm() < 1e-14) break;
  }
  const double hi = support(Qi, m), hj = support(Qj, m);
  ref.normal = m;
  ref.overlap = hi + hj - m.dot(l);
  ref.p_i = Qi * m / hi;
  ref.p_j = l - Qj * m / hj;
  const auto T = tangent_basis(m);
  // Radii-of-curvature tensors (support-function Hessians restricted to the tangent plane);
  // curvature tensors are their inverses. h_j is even, so its Hessian at -m equals that at m.
  const Eigen::Matrix2d Wi = T.transpose() * support_hessian(Qi, m) * T;
  const Eigen::Matrix2d Wj = T.transpose() * support_hessian(Qj, m) * T;
  ref.radius = 1 / std::sqrt((Wi.inverse() + Wj.inverse()).determinant());
  return ref;
}

Reference reference(const Vec3& l, const Mat3& Qi, const Mat3& Qj) {
  return reference(l, Qi, Qj, sampled_start(l, Qi, Qj));
}

struct Pair {
  Vec3 axes_i, axes_j;
  Quat q_i, q_j;
  Vec3 l;
  Reference ref;
  double target;  // wanted signed overlap
};

// Aspect 1-3: prolate (a = k b, b, b) half the time, triaxial otherwise; `size` scales it.
Vec3 random_axes(Rng& rng, double size) {
  if (rng.uniform() < 0.5) return size * Vec3(1 + 2 * rng.uniform(), 1, 1);
  double f[3] = {1, 1 + 2 * rng.uniform(), 1 + 2 * rng.uniform()};
  std::sort(f, f + 3, std::greater<>());
  return size * Vec3(f[0], f[1], f[2]);
}

// Places j along a random direction u at the distance where the reference signed overlap equals
// `target`: Newton on d, with d delta_ref / dd = -m . u (envelope theorem; delta_ref is concave in
// d and decreasing through the root).
Pair make_pair(Rng& rng, double size_ratio_max, double target_rel, bool gap) {
  Pair p;
  p.axes_i = random_axes(rng, kMm);
  p.axes_j = random_axes(rng, kMm * rng.log_uniform(1 / size_ratio_max, size_ratio_max));
  p.q_i = rng.rotation();
  p.q_j = rng.rotation();
  const double c_min = std::min(p.axes_i.minCoeff(), p.axes_j.minCoeff());
  p.target = (gap ? -1 : 1) * target_rel * c_min;
  const Mat3 Qi = shape_Q(p.axes_i, p.q_i), Qj = shape_Q(p.axes_j, p.q_j);
  const Vec3 u = rng.direction();
  double d = support(Qi, u) + support(Qj, u);  // the touching distance for spheres
  Reference ref = reference(d * u, Qi, Qj);
  for (int it = 0; it < 60; ++it) {
    const double step = (ref.overlap - p.target) / ref.normal.dot(u);
    d += step;
    ref = reference(d * u, Qi, Qj, ref.normal);
    if (std::abs(ref.overlap - p.target) <= 1e-6 * std::abs(p.target)) break;
  }
  p.l = d * u;
  p.ref = ref;
  return p;
}

bool run(const Pair& p, ContactGeometry& g, double& lambda, EllipsoidContactStats& stats) {
  return ellipsoid_contact(p.l, p.axes_i, p.q_i, p.axes_j, p.q_j, lambda, g, stats);
}

bool all_finite(const ContactGeometry& g) {
  return g.normal.allFinite() && std::isfinite(g.overlap) && g.arm_i.allFinite() && g.arm_j.allFinite() &&
         std::isfinite(g.radius);
}

}  // namespace

// The reference itself: at the touching distance of two spheres it returns zero overlap, the
// line of centres and R1 R2/(R1 + R2); a fresh sampling agrees with the warm-started Newton
// (no other local minimum near touch). Guards test 1 against a wrong reference.
TEST(EllipsoidContactReference, SpheresAndRestartAgree) {
  const double r1 = 1.3e-3, r2 = 0.4e-3;
  const Vec3 u = Vec3(1, 2, -2).normalized();
  const Mat3 Q1 = r1 * r1 * Mat3::Identity(), Q2 = r2 * r2 * Mat3::Identity();
  const Reference ref = reference((r1 + r2 - 1e-6) * u, Q1, Q2);
  EXPECT_NEAR(ref.overlap, 1e-6, 1e-18);
  EXPECT_LT((ref.normal - u).norm(), 1e-12);
  EXPECT_NEAR(ref.radius, r1 * r2 / (r1 + r2), 1e-12 * r2);

  Rng rng(11);
  for (int k = 0; k < 50; ++k) {
    const Pair p = make_pair(rng, 10, rng.log_uniform(1e-9, 5e-2), k % 2 == 1);
    const Mat3 Qi = shape_Q(p.axes_i, p.q_i), Qj = shape_Q(p.axes_j, p.q_j);
    const Reference fresh = reference(p.l, Qi, Qj);
    // Round-off floor of h_i + h_j - m.l: a few ulp of the sizes.
    EXPECT_NEAR(fresh.overlap, p.ref.overlap, 16 * kEps * (p.axes_i.maxCoeff() + p.axes_j.maxCoeff()));
    EXPECT_NEAR(p.ref.overlap, p.target, 1e-6 * std::abs(p.target));
  }
}

// SPEC 4, test 1: against the common-normal reference, thousands of random pairs (aspect 1-3,
// size ratio up to 10, random orientations), signed overlaps 1e-9 .. 5e-2 of the smallest semi-axis.
TEST(EllipsoidContact, MatchesCommonNormalReference) {
  Rng rng(2024);
  const int n_pairs = 3000;
  double worst_delta = 0, worst_normal = 0, worst_arm = 0, worst_radius = 0, worst_tiny = 0;
  long total_iter = 0, calls = 0;
  int max_iter = 0, missed = 0, phantom = 0;
  for (int k = 0; k < n_pairs; ++k) {
    const bool gap = k % 2 == 1;
    // Every third pair sits exactly at the detection limit asked for, |delta| = 1e-9 c_min.
    const Pair p = make_pair(rng, 10, k % 3 == 0 ? 1e-9 : rng.log_uniform(1e-9, 5e-2), gap);
    ContactGeometry g{};
    double lambda = -1;
    EllipsoidContactStats st;
    const bool hit = run(p, g, lambda, st);
    max_iter = std::max(max_iter, st.iterations);
    total_iter += st.iterations;
    ++calls;
    if (gap) {
      phantom += hit;
      continue;
    }
    missed += !hit;
    if (!hit) continue;
    ASSERT_TRUE(all_finite(g));
    const double delta = p.ref.overlap;
    const double r_small = std::min(p.axes_i.minCoeff(), p.axes_j.minCoeff());
    const double size = p.axes_i.maxCoeff() + p.axes_j.maxCoeff();
    const double rel = delta / r_small;
    // delta: the PW line differs from the common normal by an angle O(delta/R) and the overlap is
    // stationary w.r.t. the direction, so the difference is O(delta^2/R); plus round-off eps*size.
    const double e_delta = std::abs(g.overlap - delta);
    // (The allowances subtracted below are round-off floors: eps x size for lengths, ~1e-13 for
    // unit vectors and ratios.)
    worst_delta = std::max(worst_delta, (e_delta - 32 * kEps * size) / (delta * rel));
    if (rel < 1e-8) worst_tiny = std::max(worst_tiny, e_delta / delta);
    // Normal: PW is exact at touch, angle O(delta/R).
    worst_normal = std::max(worst_normal, ((g.normal - p.ref.normal).norm() - 1e-13) / rel);
    const Vec3 mid_ref = 0.5 * (p.ref.p_i + p.ref.p_j);
    worst_arm = std::max(worst_arm, ((g.arm_i - mid_ref).norm() - 1e-13 * size) / delta);
    worst_radius = std::max(worst_radius, (std::abs(g.radius / p.ref.radius - 1) - 1e-12) / rel);
  }
  std::cout << "3000 pairs: cold iterations mean " << double(total_iter) / double(calls) << " max " << max_iter
            << "; max |d delta|/(delta^2/c) " << worst_delta << ", |d n|/(delta/c) " << worst_normal
            << ", |d arm|/delta " << worst_arm << ", |d R_e/R_e|/(delta/c) " << worst_radius
            << "; relative delta error below 1e-8 c: " << worst_tiny << "\n";
  // Detection is exact: |target| >= 1e-9 c while mu^2 and the reference carry round-off ~1e-15 c.
  EXPECT_EQ(missed, 0);
  EXPECT_EQ(phantom, 0);
  // Orders from theory (above), constants of order one: measured 0.13 / 0.32 / 0.51 / 0.32 on this
  // seed (0.12 / 0.39 / 0.56 / 0.40 on another); the bounds allow about 4x.
  EXPECT_LT(worst_delta, 0.5);
  EXPECT_LT(worst_normal, 1.5);
  EXPECT_LT(worst_arm, 2.0);
  EXPECT_LT(worst_radius, 1.5);
  // Safeguarded Halley from the support-function cold start: a handful of iterations, never the cap.
  EXPECT_LE(max_iter, 12);
}

// SPEC 4, test 2: a = b = c reproduces the exact sphere geometry of sphere_sphere (normal on the
// line of centres, delta = R1 + R2 - |l|, contact point in the middle of the overlap,
// R_e = R1 R2/(R1 + R2)), for any orientation of the "ellipsoids".
TEST(EllipsoidContact, SphereLimitReproducesSphereSphere) {
  Rng rng(5);
  for (const double rel : {1e-9, 1e-6, 1e-4, 1e-3, 1e-2}) {
    double e_n = 0, e_delta = 0, e_arm = 0, e_radius = 0;
    for (int k = 0; k < 300; ++k) {
      const double ri = kMm * (0.5 + rng.uniform()), rj = ri * rng.log_uniform(0.1, 10);
      const Vec3 l = (ri + rj - rel * std::min(ri, rj)) * rng.direction();
      const ContactGeometry want = sphere_sphere(l, ri, rj);
      ContactGeometry g{};
      double lambda = -1;
      ASSERT_TRUE(ellipsoid_contact(l, Vec3::Constant(ri), rng.rotation(), Vec3::Constant(rj), rng.rotation(), lambda, g));
      ASSERT_TRUE(all_finite(g));
      e_n = std::max(e_n, (g.normal - want.normal).norm());
      e_delta = std::max(e_delta, std::abs(g.overlap - want.overlap) / (kEps * (ri + rj)));
      e_arm = std::max(e_arm, std::max((g.arm_i - want.arm_i).norm(), (g.arm_j - want.arm_j).norm()) / (ri + rj));
      e_radius = std::max(e_radius, std::abs(g.radius / want.radius - 1));
      // PW maximiser for spheres: lambda = R_i/(R_i + R_j) (hand derivation: F' = 0 there).
      EXPECT_NEAR(lambda, ri / (ri + rj), 1e-12);
    }
    std::cout << "spheres, delta = " << rel << " R_min: |d n| " << e_n << ", |d delta| " << e_delta
              << " eps (R_i+R_j) (relative <= " << e_delta * kEps * 11 / rel << "), |d arm|/(R_i+R_j) " << e_arm
              << ", |d R_e|/R_e " << e_radius << "\n";
    // Normal, arms and radius do not depend on the overlap's size: round-off of Q = R diag R^T
    // and the 3x3 solve, a few ulp.
    EXPECT_LT(e_n, 1e-14);
    EXPECT_LT(e_arm, 1e-14);
    EXPECT_LT(e_radius, 1e-14);
    // delta = R_i + R_j - |l| cannot be known better than the rounding of the input l (eps/2 |l|),
    // in either code: the error is absolute, a few eps (R_i + R_j) (measured < 3.5), i.e. relative
    // 1e-12 from delta ~ 1e-3 (R_i + R_j) on, 1e-6 at 1e-9 R (printed above).
    EXPECT_LT(e_delta, 8);
  }
}

// SPEC 4, test 3: closed forms for aligned spheroids (hand-computed). For a prolate spheroid
// (a, b, b) the tip has both principal curvature radii b^2/a; at the equator the radii are b
// (around the axis) and a^2/b (along the meridian). Greenwood: R_e = (k' k'')^-1/2 with k', k''
// the principal curvatures of K_i + K_j. All configurations are symmetric, so the PW normal, the
// overlap and the contact points are exact.
TEST(EllipsoidContact, ClosedFormsForAlignedSpheroids) {
  const double a = 1.5 * kMm, b = kMm;
  const Vec3 prolate(a, b, b);
  const Quat along_x = Quat::Identity();
  const Quat along_z(Eigen::AngleAxisd(pi / 2, Vec3::UnitY()));  // body x -> world -z
  const Quat along_y(Eigen::AngleAxisd(pi / 2, Vec3::UnitZ()));  // body x -> world y
  struct Case {
    const char* name;
    Vec3 axes_i;
    Quat q_i;
    Vec3 axes_j;
    Quat q_j;
    Vec3 dir;        // unit branch direction = expected normal
    double reach;    // centre distance at touch
    double radius;   // R_e by hand
    double extent_i; // distance from c_i to its surface point along dir
  };
  const double a2 = 3.9 * kMm, b2 = 3.0 * kMm, r = 0.8 * kMm;  // a second spheroid, a sphere
  const std::vector<Case> cases = {
      // pole to pole, equal: K = a/b^2 each, sum 2a/b^2 in both directions -> R_e = b^2/(2a)
      {"pole-pole", prolate, along_x, prolate, along_x, Vec3::UnitX(), 2 * a, b * b / (2 * a), a},
      // pole to pole, unequal coaxial: R_e = 1/(a/b^2 + a2/b2^2)
      {"pole-pole unequal", prolate, along_x, Vec3(a2, b2, b2), along_x, Vec3::UnitX(), a + a2,
       1 / (a / (b * b) + a2 / (b2 * b2)), a},
      // side by side, parallel axes: curvatures b/a^2 (x) and 1/b (z) each; det = (2b/a^2)(2/b) = 4/a^2
      {"parallel", prolate, along_x, prolate, along_x, Vec3::UnitY(), 2 * b, a / 2, b},
      // crossed at 90 degrees: i long along x, j along z; curvature sums b/a^2 + 1/b in x and in z
      {"crossed", prolate, along_x, prolate, along_z, Vec3::UnitY(), 2 * b, a * a * b / (a * a + b * b), b},
      // i's tip against the equator of j (long along z): tangent plane (y, z); i: a/b^2 in both,
      // j: 1/b around its axis (y), b/a^2 along its meridian (z)
      {"tip-side", prolate, along_x, prolate, along_z, Vec3::UnitX(), a + b,
       1 / std::sqrt((a / (b * b) + 1 / b) * (a / (b * b) + b / (a * a))), a},
      // sphere on the equator of a spheroid long along y: tangent (x, y): 1/r + 1/b, 1/r + b/a^2
      {"sphere-side", Vec3::Constant(r), along_x, prolate, along_y, Vec3::UnitZ(), r + b,
       1 / std::sqrt((1 / r + 1 / b) * (1 / r + b / (a * a))), r},
  };
  for (const Case& c : cases) {
    for (const double rel : {1e-6, 1e-3, 1e-2}) {
      SCOPED_TRACE(std::string(c.name) + " delta/b = " + std::to_string(rel));
      const double delta = rel * b;
      const Vec3 l = (c.reach - delta) * c.dir;
      ContactGeometry g{};
      double lambda = -1;
      ASSERT_TRUE(ellipsoid_contact(l, c.axes_i, c.q_i, c.axes_j, c.q_j, lambda, g));
      // Round-off: the rotation matrices of 90-degree quaternions carry ~1e-16 off-diagonals.
      EXPECT_LT((g.normal - c.dir).norm(), 1e-14);
      // delta = reach - |l| by symmetry (the PW line is the symmetry axis); absolute round-off of
      // a few ulp of the reach, as for spheres.
      EXPECT_NEAR(g.overlap, delta, 1e-12 * delta + 16 * kEps * c.reach);
      // Contact point: the middle of the overlap on the axis, extent_i - delta/2 from c_i.
      EXPECT_LT((g.arm_i - (c.extent_i - delta / 2) * c.dir).norm(), 1e-14 * c.reach);
      EXPECT_LT((g.arm_j - (g.arm_i - l)).norm(), 1e-14 * c.reach);
      // The surface points are exactly the tips/equator points whose curvatures are quoted.
      EXPECT_NEAR(g.radius, c.radius, 1e-12 * c.radius);
    }
  }
}

// SPEC 4, test 4: warm start (lambda from the previous step) gives the cold-start result and
// fewer iterations. A DEM step moves a pair by far less than 1e-6 of a particle size.
TEST(EllipsoidContact, WarmStartMatchesColdStartWithFewerIterations) {
  Rng rng(77);
  // move = 0: a contact that did not move since the last step (a warm start on the maximiser
  // itself, whose step rounds to nothing) must not fall back to bisection.
  for (const double move : {0.0, 1e-9, 1e-6, 1e-3}) {
    long cold_iter = 0, warm_iter = 0;
    int warm_max = 0;
    double e_n = 0, e_delta = 0, e_arm = 0, e_radius = 0, e_lambda = 0;
    for (int k = 0; k < 300; ++k) {
      Pair p = make_pair(rng, 10, rng.log_uniform(1e-6, 5e-2), false);
      ContactGeometry g0{};
      double lambda_prev = -1;
      EllipsoidContactStats s0;
      ASSERT_TRUE(run(p, g0, lambda_prev, s0));
      // One step: translation of `move` c_min, rotations of `move` rad.
      const double c_min = std::min(p.axes_i.minCoeff(), p.axes_j.minCoeff());
      p.l += move * c_min * rng.direction();
      p.q_i = (Quat(Eigen::AngleAxisd(move, rng.direction())) * p.q_i).normalized();
      p.q_j = (Quat(Eigen::AngleAxisd(move, rng.direction())) * p.q_j).normalized();
      ContactGeometry gc{}, gw{};
      double lc = -1, lw = lambda_prev;
      EllipsoidContactStats sc, sw;
      const bool hc = run(p, gc, lc, sc), hw = run(p, gw, lw, sw);
      ASSERT_EQ(hc, hw);
      cold_iter += sc.iterations;
      warm_iter += sw.iterations;
      warm_max = std::max(warm_max, sw.iterations);
      if (!hc) continue;
      const double size = p.axes_i.maxCoeff() + p.axes_j.maxCoeff();
      e_lambda = std::max(e_lambda, std::abs(lc - lw));
      e_n = std::max(e_n, (gc.normal - gw.normal).norm());
      e_delta = std::max(e_delta, std::abs(gc.overlap - gw.overlap) / (kEps * size));
      e_arm = std::max(e_arm, (gc.arm_i - gw.arm_i).norm() / size);
      e_radius = std::max(e_radius, std::abs(gc.radius / gw.radius - 1));
    }
    std::cout << "step " << move << ": iterations cold " << double(cold_iter) / 300 << " warm "
              << double(warm_iter) / 300 << " (max " << warm_max << "); warm-cold: lambda " << e_lambda << ", n "
              << e_n << ", delta " << e_delta << ", arm " << e_arm << ", R_e " << e_radius << "\n";
    // Both runs converge to machine precision (see kStepTol in ellipsoid_contact.cpp); the overlap
    // (absolute, in eps x size) differs by its round-off floor only (measured 0.5-1.1).
    EXPECT_LT(e_lambda, 1e-12);
    EXPECT_LT(e_n, 1e-12);
    EXPECT_LT(e_delta, 4);
    EXPECT_LT(e_arm, 1e-12);
    EXPECT_LT(e_radius, 1e-12);
    EXPECT_LT(warm_iter, cold_iter);
    // Halley from an O(move) error, stopped once the step's relative effect on s is below 1e-5
    // (ellipsoid_contact.cpp, 2.): one iteration up to move = 1e-6 (measured max 1; 2 at 1e-3).
    if (move <= 1e-6) {
      EXPECT_EQ(warm_max, 1);
    }
    if (move <= 1e-9) {
      EXPECT_EQ(warm_iter, 300);  // one factorisation per call
    }
  }
}

// SPEC 4, test 5: degenerate inputs give finite results and no exception.
TEST(EllipsoidContact, DegenerateInputsAreFinite) {
  const Vec3 prolate(1.2 * kMm, kMm, kMm);
  const Vec3 big(10.5 * kMm, 7 * kMm, 7 * kMm);
  ContactGeometry g{};
  double lambda = 0.3;

  // Coincident centres: documented choice, normal +z, x0 = c_i, delta = sum of the extents along z.
  // Aligned spheroids long along x: extents along z are b and b'.
  ASSERT_TRUE(ellipsoid_contact(Vec3::Zero(), prolate, Quat::Identity(), big, Quat::Identity(), lambda, g));
  EXPECT_EQ(g.normal, Vec3::UnitZ());
  EXPECT_NEAR(g.overlap, kMm + 7 * kMm, 1e-15);
  EXPECT_LT((g.arm_i - 0.5 * (kMm - 7 * kMm) * Vec3::UnitZ()).norm(), 1e-18);  // midpoint of -7 mm .. 1 mm
  EXPECT_TRUE(all_finite(g));
  EXPECT_GT(g.radius, 0);
  EXPECT_EQ(lambda, 0.3);  // left as it was

  // Warm values that are not in (0, 1) are cold starts, including NaN and the end points.
  Rng rng(3);
  for (const double bad : {0.0, 1.0, -1.0, 2.0, std::numeric_limits<double>::quiet_NaN()}) {
    const Vec3 l = 1.9 * kMm * Vec3(1, 0.2, 0.1).normalized();
    double lw = bad, lc = -1;
    ContactGeometry gw{}, gc{};
    ASSERT_EQ(ellipsoid_contact(l, prolate, Quat::Identity(), prolate, Quat::Identity(), lw, gw),
              ellipsoid_contact(l, prolate, Quat::Identity(), prolate, Quat::Identity(), lc, gc));
    EXPECT_EQ(lw, lc);
  }

  // Tiny, deep and extreme branch vectors, random orientations, size ratio 10, aspect 3: every
  // output finite, overlap > 0, unit normal pointing from i to j, R_e > 0.
  const Vec3 needle(3 * kMm, kMm, kMm), small(0.3 * kMm, 0.1 * kMm, 0.1 * kMm);
  for (int k = 0; k < 2000; ++k) {
    const Vec3& ai = k % 2 ? needle : big;
    const Vec3& aj = k % 3 ? small : prolate;
    const double scale = std::pow(10.0, -300 + 297 * rng.uniform());  // 1e-300 .. 1e-3 m
    const Vec3 l = scale * rng.direction();
    double lam = k % 4 ? -1 : rng.uniform();
    ASSERT_TRUE(ellipsoid_contact(l, ai, rng.rotation(), aj, rng.rotation(), lam, g)) << scale;
    ASSERT_TRUE(all_finite(g)) << scale;
    EXPECT_GT(g.overlap, 0);
    EXPECT_GT(g.radius, 0);
    EXPECT_NEAR(g.normal.norm(), 1, 1e-14);
    EXPECT_GE(g.normal.dot(l), 0);
  }

  // Non-finite branch: no contact, no exception.
  double lam = -1;
  EXPECT_FALSE(ellipsoid_contact(Vec3::Constant(std::numeric_limits<double>::quiet_NaN()), prolate,
                                 Quat::Identity(), prolate, Quat::Identity(), lam, g));

  // Exactly touching and within an ulp of touching (pole to pole, |l| = 2a (1 + k eps)): either
  // answer is acceptable at mu^2 = 1 +- ulp, but a contact must have 0 < delta <= a few ulp of 2a.
  for (int ulps = -4; ulps <= 4; ++ulps) {
    const double d = 2.4 * kMm * (1 + ulps * kEps);
    lam = -1;
    if (ellipsoid_contact(d * Vec3::UnitX(), prolate, Quat::Identity(), prolate, Quat::Identity(), lam, g)) {
      EXPECT_TRUE(all_finite(g));
      EXPECT_GT(g.overlap, 0);
      EXPECT_LT(g.overlap, 16 * kEps * 2.4 * kMm);
    }
  }
  // Random orientations at |target| = 1e-14 c_min: decisions may go either way within round-off,
  // outputs must be finite and consistent.
  for (int k = 0; k < 200; ++k) {
    const Pair p = make_pair(rng, 10, 1e-14, k % 2 == 1);
    EllipsoidContactStats st;
    lam = -1;
    if (run(p, g, lam, st)) {
      EXPECT_TRUE(all_finite(g));
      EXPECT_GT(g.overlap, 0);
      EXPECT_LT(g.overlap, 1e-12 * kMm);
    }
  }
}

// SPEC 4, test 6: frame invariance and the i <-> j symmetry.
TEST(EllipsoidContact, RotationAndSwapInvariance) {
  Rng rng(99);
  double e_rot = 0, e_rot_delta = 0, e_swap = 0, e_swap_delta = 0;
  for (int k = 0; k < 400; ++k) {
    const Pair p = make_pair(rng, 10, rng.log_uniform(1e-4, 5e-2), false);
    const double size = p.axes_i.maxCoeff() + p.axes_j.maxCoeff();
    ContactGeometry g{};
    double lambda = -1;
    EllipsoidContactStats st;
    ASSERT_TRUE(run(p, g, lambda, st));

    // Rigid rotation G of the whole pair: l -> G l, q -> G q.
    const Quat G = rng.rotation();
    const Mat3 Gm = G.toRotationMatrix();
    ContactGeometry gr{};
    double lr = -1;
    ASSERT_TRUE(ellipsoid_contact(Gm * p.l, p.axes_i, (G * p.q_i).normalized(), p.axes_j, (G * p.q_j).normalized(), lr, gr));
    e_rot = std::max({e_rot, (gr.normal - Gm * g.normal).norm(), (gr.arm_i - Gm * g.arm_i).norm() / size,
                      (gr.arm_j - Gm * g.arm_j).norm() / size, std::abs(gr.radius / g.radius - 1), std::abs(lr - lambda)});
    e_rot_delta = std::max(e_rot_delta, std::abs(gr.overlap - g.overlap) / (kEps * size));

    // Swap: j becomes i, the branch flips; lambda weights the other shape (1 - lambda).
    ContactGeometry gs{};
    double ls = -1;
    ASSERT_TRUE(ellipsoid_contact(-p.l, p.axes_j, p.q_j, p.axes_i, p.q_i, ls, gs));
    e_swap = std::max({e_swap, (gs.normal + g.normal).norm(), (gs.arm_i - g.arm_j).norm() / size,
                       (gs.arm_j - g.arm_i).norm() / size, std::abs(gs.radius / g.radius - 1), std::abs(ls - (1 - lambda))});
    e_swap_delta = std::max(e_swap_delta, std::abs(gs.overlap - g.overlap) / (kEps * size));
  }
  std::cout << "rotation: " << e_rot << " (delta " << e_rot_delta << " eps size); swap: " << e_swap << " (delta "
            << e_swap_delta << " eps size)\n";
  // Exact in exact arithmetic; round-off of rotating the inputs is ~1e-16 relative, amplified by
  // the conditioning of Q(lambda) (aspect^2 x size ratio^2 <= 900) at most.
  EXPECT_LT(e_rot, 1e-12);
  EXPECT_LT(e_swap, 1e-12);
  // delta = R_i + R_j - |l|-like difference: absolute round-off floor of a few eps x size.
  EXPECT_LT(e_rot_delta, 8);
  EXPECT_LT(e_swap_delta, 8);
}

// SPEC 4: the returned lambda maximises the PW function, checked with an independent LDLT
// evaluation of F (pw_contact_function) on a fine grid and by finite differences; mu^2 = max F
// is < 1 for the overlapping pairs and >= 1 for the separated ones.
TEST(EllipsoidContact, LambdaMaximisesPerramWertheimFunction) {
  Rng rng(31);
  for (int k = 0; k < 200; ++k) {
    const Pair p = make_pair(rng, 10, rng.log_uniform(1e-6, 5e-2), k % 2 == 1);
    const Mat3 Qi = shape_Q(p.axes_i, p.q_i), Qj = shape_Q(p.axes_j, p.q_j);
    ContactGeometry g{};
    double lambda = -1;
    EllipsoidContactStats st;
    const bool hit = run(p, g, lambda, st);
    double f_grid = 0;  // max of F on a grid of spacing 1e-3
    for (int m = 1; m < 1000; ++m) f_grid = std::max(f_grid, pw_contact_function(p.l, Qi, Qj, m * 1e-3));
    if (!hit) {
      // A separated pair has max F >= 1; the grid misses the maximum by O(F'' 1e-6) < 1e-3.
      EXPECT_GE(f_grid, 1 - 1e-3);
      continue;
    }
    const double f_star = pw_contact_function(p.l, Qi, Qj, lambda);
    // Converged maximum: the code's mu^2 equals F(lambda) to round-off (relative ~cond eps), is
    // < 1, and no grid point beats it (F is concave).
    EXPECT_NEAR(st.mu2, f_star, 1e-13);
    EXPECT_LT(f_star, 1);
    EXPECT_GE(f_star, f_grid * (1 - 1e-14));
    // Stationarity: the central difference of F at lambda (step 1e-5 of the distance to the
    // nearer end) vanishes up to O(h^2) truncation and round-off eps F / h.
    const double h = 1e-5 * std::min(lambda, 1 - lambda);
    const double slope =
        (pw_contact_function(p.l, Qi, Qj, lambda + h) - pw_contact_function(p.l, Qi, Qj, lambda - h)) / (2 * h);
    EXPECT_LT(std::abs(slope) * std::min(lambda, 1 - lambda), 1e-8);
  }
}

// The gap bound that lets the force stage skip apart pairs (EllipsoidContactStats::gap_bound)
// never exceeds the true distance of the surfaces (the common-normal reference), from a cold
// start, a warm start and every early exit; for spheres it is the distance itself.
TEST(EllipsoidContact, GapBoundNeverExceedsTheDistance) {
  Rng rng(77);
  int with_bound = 0;
  double worst_excess = -1, ratio_sum = 0;
  for (int k = 0; k < 3000; ++k) {
    const Pair p = make_pair(rng, 10, rng.log_uniform(1e-9, 0.5), true);
    const double distance = -p.ref.overlap;
    for (const double start : {-1.0, 0.5, rng.uniform()}) {
      double lambda = start;
      ContactGeometry g{};
      EllipsoidContactStats st;
      ASSERT_FALSE(run(p, g, lambda, st));
      // The reference's own accuracy: 1e-6 of the distance (make_pair) plus round-off.
      const double excess = (st.gap_bound - distance) / distance;
      worst_excess = std::max(worst_excess, excess);
      EXPECT_LE(st.gap_bound, distance * (1 + 2e-6) + 1e-15) << "pair " << k << " start " << start;
      if (st.gap_bound > 0) ++with_bound, ratio_sum += st.gap_bound / distance;
    }
  }
  std::cout << "gap bound / distance: mean " << ratio_sum / with_bound << " over " << with_bound
            << " calls with a bound; worst excess " << worst_excess << "\n";
  EXPECT_GT(with_bound, 9000 / 2) << "most apart pairs get a usable bound";

  // Spheres (any orientation): the bound is the distance.
  for (const double gap : {1e-9, 1e-6, 1e-3}) {
    const Vec3 ai = Vec3::Constant(2 * kMm), aj = Vec3::Constant(0.5 * kMm);
    const Vec3 l = (2.5 * kMm + gap) * Vec3(1, 2, -2).normalized();
    for (const double start : {-1.0, 0.3}) {
      double lambda = start;
      ContactGeometry g{};
      EllipsoidContactStats st;
      ASSERT_FALSE(ellipsoid_contact(l, ai, rng.rotation(), aj, rng.rotation(), lambda, g, st));
      EXPECT_NEAR(st.gap_bound, gap, 1e-12 * kMm + 1e-6 * gap) << "gap " << gap << " start " << start;
    }
  }
}

// The batch (EllipsoidContactBatch, what the force stage uses) gives every lane exactly what the
// pair gives alone, whatever the other lanes do: lanes that converge at once, iterate long, bisect,
// stop early as apart, are rejected by their bounding spheres or by support planes, or have
// coincident centres, mixed in one batch and in shuffled order. Bit for bit: the lanes leave the
// iteration at different passes, so a slip in the bookkeeping would show as a different bit.
TEST(EllipsoidContact, BatchLanesMatchLonePairs) {
  Rng rng(2026113001);
  struct Case {
    Vec3 l;
    EllipsoidShape si, sj;
    double lambda;
  };
  std::vector<Case> cases;
  for (int k = 0; k < 600; ++k) {
    const int kind = k % 6;
    Pair p = make_pair(rng, 4.0, rng.log_uniform(1e-6, 0.3), kind == 1);
    if (kind == 2) p.l *= 1.5;                 // well apart: bounding spheres or support planes
    if (kind == 3 && k % 36 == 3) p.l.setZero();  // coincident centres
    const double warm[] = {-1.0, 0.5, rng.uniform(), 1e-9, 1 - 1e-9, std::numeric_limits<double>::quiet_NaN()};
    cases.push_back({p.l, ellipsoid_shape(p.axes_i, p.q_i), ellipsoid_shape(p.axes_j, p.q_j), warm[k % 6]});
  }
  // The converged lambda as warm start too (the common case in a run).
  for (int k = 0; k < 100; ++k) {
    Case c = cases[static_cast<std::size_t>(k)];
    ContactGeometry g;
    ellipsoid_contact(c.l, c.si, c.sj, c.lambda, g);
    cases.push_back(c);
  }
  std::shuffle(cases.begin(), cases.end(), rng.engine);

  int long_runs = 0, bisecting = 0, separated = 0, touching = 0, rejected = 0, batches = 0;
  for (std::size_t first = 0; first < cases.size(); first += EllipsoidContactBatch::capacity) {
    EllipsoidContactBatch batch;
    const std::size_t last = std::min(cases.size(), first + EllipsoidContactBatch::capacity);
    for (std::size_t c = first; c < last; ++c) batch.add(cases[c].l, cases[c].si, cases[c].sj, cases[c].lambda);
    ellipsoid_contacts(batch);
    ++batches;
    for (std::size_t c = first; c < last; ++c) {
      const int a = static_cast<int>(c - first);
      double lambda = cases[c].lambda;
      ContactGeometry g;
      EllipsoidContactStats st;
      const bool alone = ellipsoid_contact(cases[c].l, cases[c].si, cases[c].sj, lambda, g, st);
      const EllipsoidContactStats& sb = batch.stats[a];
      ASSERT_EQ(batch.touching[a], alone) << "case " << c;
      // Same bits (NaN only as a NaN warm start left unchanged by a rejection).
      EXPECT_TRUE(batch.lambda[a] == lambda || (std::isnan(lambda) && std::isnan(batch.lambda[a]))) << "case " << c;
      EXPECT_EQ(sb.iterations, st.iterations);
      EXPECT_EQ(sb.bisections, st.bisections);
      EXPECT_EQ(sb.early_exit, st.early_exit);
      EXPECT_EQ(sb.mu2, st.mu2);
      EXPECT_EQ(sb.gap_bound, st.gap_bound);
      if (alone) {
        const ContactGeometry gb = batch.contact(a);
        EXPECT_EQ(gb.normal, g.normal);
        EXPECT_EQ(gb.overlap, g.overlap);
        EXPECT_EQ(gb.arm_i, g.arm_i);
        EXPECT_EQ(gb.arm_j, g.arm_j);
        EXPECT_EQ(gb.radius, g.radius);
      }
      long_runs += st.iterations >= 3;
      bisecting += st.bisections > 0;
      separated += !alone && st.iterations > 0;
      touching += alone;
      rejected += !alone && st.iterations == 0;
    }
  }
  // The mix this test is about did occur.
  std::cout << batches << " batches: " << touching << " touching, " << separated << " apart after PW, " << rejected
            << " rejected before, " << long_runs << " with >= 3 iterations, " << bisecting << " bisecting\n";
  EXPECT_GT(touching, 100);
  EXPECT_GT(separated, 20);
  EXPECT_GT(rejected, 20);
  EXPECT_GT(long_runs, 20);
  EXPECT_GT(bisecting, 0);
}
