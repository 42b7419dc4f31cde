// Rigid-body rotation of ellipsoids (SPEC 5): the damped kick of the world angular momentum L
// (integrate_velocities) and the orientation drift at constant L (advance_positions), checked
// against the analytic free motion of a rigid body (Euler's equations: Landau & Lifshitz,
// Mechanics, sections 33 and 37), the order of accuracy of the scheme, and the damping ratio of
// a torsional oscillator (SPEC 6, paper Eq. 11, 17-19).
//
// Conventions: semi-axes a >= b >= c along body x, y, z; principal moments (SPEC 2)
// I_a = m(b^2+c^2)/5 <= I_b = m(a^2+c^2)/5 <= I_c = m(a^2+b^2)/5, computed here by hand.
// "omega dt" is |omega| dt, the angle turned per step.
#include <gtest/gtest.h>
#include <omp.h>

#include <algorithm>
#include <array>
#include <cmath>
#include <random>
#include <iomanip>
#include <iostream>
#include <sstream>
#include <string>
#include <vector>

#include "qsdem/engine/cell.hpp"
#include "qsdem/engine/damping/stage.hpp"
#include "qsdem/engine/integrator.hpp"
#include "qsdem/engine/model.hpp"
#include "qsdem/engine/particles.hpp"
#include "test_support.hpp"

using namespace qsdem;

namespace {

constexpr double kRho = 2650;
constexpr double kE = 7.8e10;
constexpr double kNu = 0.3;

// One particle: OpenMP fork/join per call would cost far more than the work (see
// test_integrator.cpp); physics does not depend on the thread count.
using qsdem_test::SingleThread;

// Principal moments of a solid ellipsoid, by hand (SPEC 2).
Vec3 moments(const Vec3& ax) {
  const double m = kRho * 4.0 / 3.0 * pi * ax.x() * ax.y() * ax.z();
  return m / 5 *
         Vec3(ax.y() * ax.y() + ax.z() * ax.z(), ax.x() * ax.x() + ax.z() * ax.z(),
              ax.x() * ax.x() + ax.y() * ax.y());
}

// World angular velocity R I^-1 R^T L with the rotation matrix (independent of the engine's
// quaternion route).
Vec3 omega_of(const Quat& q, const Vec3& inertia, const Vec3& angmom) {
  const Mat3 r = q.toRotationMatrix();
  return r * inertia.cwiseInverse().asDiagonal() * r.transpose() * angmom;
}

// One ellipsoid in a large cell, driven through the engine's integrate_velocities and
// advance_positions (the order of step(): kick with the torque at t, then drift, which
// normalises the orientation at the steps step() has it do so).
struct Body {
  Particles p;
  Model model;
  Cell cell = make_cell(Mat3::Identity());  // 1 m cell: positions do not matter here
  Vec3 inertia;                             // by hand
  long steps = 0;

  // Starts at orientation q0 with body-frame angular velocity omega_body; dt = w_dt / |omega|.
  Body(const Vec3& axes, const Quat& q0, const Vec3& omega_body, double w_dt) {
    p.add(0, ShapeKind::ellipsoid, axes, kRho, Vec3::Constant(0.5), q0);
    inertia = moments(axes);
    p.angmom.set(0, q0 * Vec3(inertia.cwiseProduct(omega_body)));
    model.material = {kRho, kE, kNu};
    model.dt = omega_body.norm() > 0 ? w_dt / omega_body.norm() : 0;
  }
  void step(const Vec3& torque = Vec3::Zero()) {
    p.torque[0] = torque;
    integrate_velocities(model, p);
    advance_positions(model, cell, p, {}, 0, SIZE_MAX, false, normalizes_orientations(steps++));
  }
  Vec3 body_angmom() const { return p.q[0].conjugate() * p.angmom[0]; }
  double energy() const { return 0.5 * p.angmom[0].dot(p.omega[0]); }  // 1/2 L.omega
};

// Angle of the rotation from a to b (atan2 form: accurate for tiny angles, unlike acos).
double quat_angle(const Quat& a, const Quat& b) {
  const Quat d = a.conjugate() * b;
  return 2 * std::atan2(d.vec().norm(), std::abs(d.w()));
}

std::string sci(double x) {
  std::ostringstream os;
  os << std::scientific << std::setprecision(3) << x;
  return os.str();
}

const Vec3 kAxes321(3e-3, 2e-3, 1e-3);  // asymmetric a > b > c, 3:2:1
const Quat kQ0(Eigen::AngleAxisd(0.7, Vec3(1, 2, 3).normalized()));  // arbitrary start
constexpr double kSpin = 100;  // rad/s, any scale: only omega dt matters for the scheme

// Spinning about body axis k, perturbed by 5 % and 3 % about the two others.
Vec3 near_axis(int k) {
  Vec3 w;
  w[k] = kSpin;
  w[(k + 1) % 3] = 0.05 * kSpin;
  w[(k + 2) % 3] = 0.03 * kSpin;
  return w;
}

// Period of the body-frame angular velocity of a free asymmetric body, I1 < I2 < I3, angular
// momentum M and energy E (Landau & Lifshitz section 37, Eq. 37.10-37.12 and the swap 1 <-> 3
// for M^2 < 2 E I2): T = 4 K(k) sqrt(I1 I2 I3 / ((I3 - I2)(M^2 - 2E I1))),
// k^2 = (I2 - I1)(2E I3 - M^2) / ((I3 - I2)(M^2 - 2E I1)) for M^2 > 2E I2.
double euler_period(const Vec3& inertia, double m2, double e) {
  double i1 = inertia.x(), i3 = inertia.z();
  const double i2 = inertia.y();
  if (m2 < 2 * e * i2) std::swap(i1, i3);
  const double k2 = (i2 - i1) * (2 * e * i3 - m2) / ((i3 - i2) * (m2 - 2 * e * i1));
  return 4 * std::comp_ellint_1(std::sqrt(k2)) * std::sqrt(i1 * i2 * i3 / ((i3 - i2) * (m2 - 2 * e * i1)));
}

}  // namespace

// SPEC 5, free rigid body (no torque, no damping), started near the unstable intermediate axis
// (the body tumbles: the b axis flips relative to L) and near the stable major axis a.
// - L: the kick with T = 0 and A = 0 is ((1 - 0) L + 0) / 1 = L bit for bit, and the drift does
//   not touch L: exactly constant.
// - Energy 1/2 L.omega: the drift is a symplectic splitting of the free-body Hamiltonian, so it
//   conserves a modified energy H + O(dt^2) (backward error analysis; Hairer, Lubich & Wanner,
//   Geometric Numerical Integration, IX.8): the error is O((omega dt)^2) with a coefficient made
//   of double Poisson brackets of the split terms, each ~1/12-1/24 times the anisotropy
//   (|1 - I_i/I_j| <= 1.6 here). Bound: (omega dt)^2 / 4 (1e-4 at omega dt = 0.02). Observed:
//   2.8e-5 and 1.8e-4 (intermediate axis, omega dt = 0.02 and 0.05), 3.7e-7 and 2.3e-6 (major).
// - No drift: the error is a function of the body-frame L only (the modified energy is), so its
//   maximum over the last 10 % of the run equals that over the first 10 % (each spans many
//   tumbling periods). A secular drift makes the last window ~10x the first (Richardson: linear,
//   2.5e-4 at the end, 8x its first window; the former first-order update: O(1)). Bound: 1.25x.
TEST(Rotation, FreeAsymmetricBodyConservesMomentumAndEnergy) {
  const SingleThread one_thread;
  for (int axis : {1, 0}) {
    for (double w_dt : {0.02, 0.05}) {
      Body b(kAxes321, kQ0, near_axis(axis), w_dt);
      const Vec3 l0 = b.p.angmom[0];
      const double e0 = 0.5 * l0.dot(omega_of(kQ0, b.inertia, l0));
      const int n = 100000, window = n / 10;
      double first = 0, last = 0, all = 0, min_b_along_l = 1;
      for (int s = 0; s < n; ++s) {
        b.step();
        const double err = std::abs(b.energy() / e0 - 1);
        all = std::max(all, err);
        if (s < window) first = std::max(first, err);
        if (s >= n - window) last = std::max(last, err);
        min_b_along_l = std::min(min_b_along_l, (b.p.q[0] * Vec3::UnitY()).dot(l0.normalized()));
      }
      const std::string what =
          (axis == 1 ? "intermediate" : "major") + std::string(" axis, omega dt ") + std::to_string(w_dt);
      EXPECT_EQ(b.p.angmom[0], l0) << what << ": world L must not change without torque";
      EXPECT_LT(all, w_dt * w_dt / 4) << what;
      EXPECT_LT(last, 1.25 * first + 1e-14) << what << ": energy drifts";
      // The physics is really gyroscopic: near the intermediate axis the b axis turns over
      // (Dzhanibekov effect); near the major axis it stays within the small cone.
      if (axis == 1) {
        EXPECT_LT(min_b_along_l, -0.9) << what;
      } else {
        EXPECT_GT(min_b_along_l, -0.2) << what;
      }
      RecordProperty(
          "energy_err_axis" + std::to_string(axis) + "_wdt" + std::to_string(static_cast<int>(w_dt * 100)),
          sci(all));
    }
  }
}

// Landau & Lifshitz 37: the body-frame angular velocity of a free asymmetric top is periodic in
// Jacobi elliptic functions with period 4 K(k) (...). Measured from the zero crossings of the
// body component pi_b = (R^T L)_b (sn or cn, crossings every half period; linear interpolation
// of a crossing is exact to O(dt^3) since sn, cn are odd about their zeros). Tolerance: the
// modified Hamiltonian of the splitting has frequencies within O((omega dt)^2); near the
// separatrix (intermediate axis, k -> 1) the period is log-sensitive to the energy, so the
// bound is (omega dt)^2 = 4e-4 at omega dt = 0.02. Observed: see RecordProperty / report.
TEST(Rotation, FreeAsymmetricBodyEulerPeriod) {
  const SingleThread one_thread;
  for (int axis : {1, 0}) {
    const double w_dt = 0.02;
    Body b(kAxes321, kQ0, near_axis(axis), w_dt);
    const Vec3 l0 = b.p.angmom[0];
    const Vec3 w0 = near_axis(axis);
    const double e = 0.5 * w0.dot(b.inertia.cwiseProduct(w0));
    const double expected = euler_period(b.inertia, l0.squaredNorm(), e);
    std::vector<double> crossings;
    double prev = b.body_angmom().y();
    const int n = 100000;
    for (int s = 1; s <= n; ++s) {
      b.step();
      const double cur = b.body_angmom().y();
      if ((prev < 0) != (cur < 0)) crossings.push_back(b.model.dt * (s - 1 + prev / (prev - cur)));
      prev = cur;
    }
    ASSERT_GE(crossings.size(), 20u) << "too few periods";
    const double measured =
        2 * (crossings.back() - crossings.front()) / static_cast<double>(crossings.size() - 1);
    EXPECT_NEAR(measured / expected, 1.0, w_dt * w_dt) << (axis == 1 ? "intermediate" : "major") << " axis";
    RecordProperty("period_rel_error_" + std::to_string(axis), sci(measured / expected - 1));
  }
}

// Global error O(dt^2) (SPEC 5: second-order orientation scheme): the orientation after
// t = 200 / |omega| (~30 rad of rotation, a full tumble near the intermediate axis) at omega dt =
// 0.04, 0.02, 0.01 against a reference at omega dt = 0.001 (10x the finest). The order
// p = log2(e(2h) / e(h)) must be 2 within 0.1: the next term of the error is O((omega dt)^2) <=
// 2e-3 relative and the reference's own error is e(0.01) / 100, i.e. p off by <= 0.015; a first-
// order scheme gives 1, a third-order one 3. Observed: p = 2.00, e(0.02) = 2.9e-3 rad.
TEST(Rotation, OrientationConvergesAtSecondOrder) {
  const SingleThread one_thread;
  for (int axis : {1, 0}) {
    auto final_q = [&](double w_dt) {
      const int n = static_cast<int>(std::lround(200 / w_dt));
      Body b(kAxes321, kQ0, near_axis(axis), 200.0 / n);
      for (int s = 0; s < n; ++s) b.step();
      return b.p.q[0];
    };
    const Quat ref = final_q(0.001);
    const double e4 = quat_angle(final_q(0.04), ref), e2 = quat_angle(final_q(0.02), ref),
                 e1 = quat_angle(final_q(0.01), ref);
    EXPECT_NEAR(std::log2(e4 / e2), 2.0, 0.1) << "axis " << axis << ": " << e4 << " " << e2 << " " << e1;
    EXPECT_NEAR(std::log2(e2 / e1), 2.0, 0.1) << "axis " << axis << ": " << e4 << " " << e2 << " " << e1;
    // The constant matters too: the scheme must be accurate, not only of order 2. 1 % of a
    // radian after 30 rad at omega dt = 0.02 (Richardson: 0.19 rad near the intermediate axis).
    EXPECT_LT(e2, 1e-2) << "axis " << axis;
    RecordProperty("errors_axis" + std::to_string(axis), sci(e4) + " " + sci(e2) + " " + sci(e1));
  }
}

// The drift is time-reversible (a symmetric scheme: no secular drift of invariants): flipping L
// and stepping back returns the start orientation to round-off. 1e4 steps each way at
// omega dt = 0.05 and 0.3 (large half angles: the libm branch of the sines), ~1e-16 rounding per
// step, amplified near the separatrix (intermediate axis) where neighbouring orbits separate
// linearly in time (omega t up to 3000): bound 1e-9 rad. Richardson: 2.9 rad at omega dt = 0.05.
TEST(Rotation, DriftIsTimeReversible) {
  const SingleThread one_thread;
  for (const Vec3& axes : {kAxes321, Vec3(1.5e-3, 1e-3, 1e-3)}) {
    for (double w_dt : {0.05, 0.3}) {
      Body b(axes, kQ0, near_axis(1), w_dt);
      for (int s = 0; s < 10000; ++s) b.step();
      b.p.angmom.set(0, -b.p.angmom[0]);
      for (int s = 0; s < 10000; ++s) b.step();
      EXPECT_LT(quat_angle(b.p.q[0], kQ0), 1e-9) << "axes " << axes.transpose() << " omega dt " << w_dt;
      RecordProperty("reversal_" + std::to_string(axes.y() > 1.5e-3) + "_" + std::to_string(w_dt > 0.1),
                     sci(quat_angle(b.p.q[0], kQ0)));
    }
  }
}

// A spheroid's orientation is normalised every kNormalizeEvery steps (SPEC 5.4); between them it
// is the product of the step's unit turns, whose norm departs from 1 by the round-off of the
// products, a few ulps a step. Over 5e4 steps at omega dt from 1e-5 to 0.1 (the Taylor
// polynomials and libm), prolate and oblate: | |q| - 1 | stays below 1e-14 (kNormalizeEvery steps
// of a few ulps each), and the orientation within 1e-9 rad of a run normalised at every step
// (a precession: round-off differences grow linearly, ~1e-16 a step).
TEST(Rotation, SpheroidNormStaysUnitBetweenNormalizations) {
  const SingleThread one_thread;
  double worst_norm = 0, worst_angle = 0;
  for (const Vec3& axes : {Vec3(1.5e-3, 1e-3, 1e-3), Vec3(1.5e-3, 1.5e-3, 1e-3)}) {
    for (double w_dt : {1e-5, 1e-3, 0.1}) {
      Body b(axes, kQ0, near_axis(1), w_dt), always(axes, kQ0, near_axis(1), w_dt);
      double off_unit = 0, skipped = 0;
      for (int s = 0; s < 50000; ++s) {
        skipped += normalizes_orientations(b.steps) ? 0 : 1;
        b.step();
        off_unit = std::max(off_unit, std::abs(b.p.q[0].norm() - 1));
        integrate_velocities(always.model, always.p);
        advance_positions(always.model, always.cell, always.p);  // normalised at every step
      }
      EXPECT_GT(skipped, 40000) << "test setup: most steps leave the norm";
      EXPECT_LT(off_unit, 1e-14) << "axes " << axes.transpose() << " omega dt " << w_dt;
      const double angle = quat_angle(b.p.q[0], always.p.q[0]);
      EXPECT_LT(angle, 1e-9) << "axes " << axes.transpose() << " omega dt " << w_dt;
      worst_norm = std::max(worst_norm, off_unit), worst_angle = std::max(worst_angle, angle);
    }
  }
  RecordProperty("largest_norm_error", sci(worst_norm));
  RecordProperty("largest_angle_to_normalised", sci(worst_angle));
}

// After advance_positions, omega is R(t+dt) I^-1 R(t+dt)^T L (the next contact forces read it):
// at constant L a turned body has a different omega (gyroscopic). An asymmetric body (general
// route) and a spheroid (I^-1 = inv_perp 1 + (inv_s - inv_perp) e e^T). Tolerance 1e-13
// relative: two routes (quaternion vs matrix) to the same product, a few ulps each.
TEST(Rotation, OmegaFollowsTheNewOrientation) {
  for (const Vec3& axes : {kAxes321, Vec3(1.5e-3, 1e-3, 1e-3)}) {
    Body b(axes, kQ0, near_axis(1), 0.05);
    b.p.torque[0] = Vec3::Zero();
    integrate_velocities(b.model, b.p);  // (leaves an ellipsoid's omega to advance_positions)
    const Vec3 before = omega_of(kQ0, b.inertia, b.p.angmom[0]);
    advance_positions(b.model, b.cell, b.p);
    EXPECT_GT(quat_angle(b.p.q[0], kQ0), 0.04) << "the body turned by ~omega dt";
    const Vec3 after = omega_of(b.p.q[0], b.inertia, b.p.angmom[0]);
    EXPECT_LT((b.p.omega[0] - after).norm(), 1e-13 * after.norm()) << axes.transpose();
    EXPECT_GT((after - before).norm(), 1e-4 * after.norm()) << "test setup: omega should change";
  }
}

// Free symmetric top (Landau & Lifshitz 33): the symmetry axis e_s precesses about L at
// Omega_p = |L| / I_perp on a cone of constant angle, and the spin omega.e_s = pi_s / I_s is
// constant. Bodies: the paper's prolate spheroid a = 1.5 b, b = c (symmetry axis a), an oblate
// one a = b = 1.5 c (symmetry axis c), and the prolate body with I_b, I_c distinct by ~1e-12
// relative (general three-moment path; physically the same top to < 1e-8 over this run).
// Tolerances: two equal moments are integrated by the exact free-top flow, whatever dt:
// round-off only, 1e-10 (relative period, cone cosine, spin) over 2e4 steps, also at
// omega dt = 0.3. The general path (NO_SQUISH) has a precession-rate error O((omega dt)^2)
// (modified Hamiltonian), and the cone and spin oscillate at the same order: bounds
// (omega dt)^2 / 4 = 1e-4 at omega dt = 0.02.
TEST(Rotation, SymmetricTopPrecession) {
  const SingleThread one_thread;
  struct Case {
    const char* name;
    Vec3 axes;
    int sym;  // body index of the symmetry axis
    double w_dt;
    bool exact;
  };
  const Case cases[] = {
      {"prolate", Vec3(1.5e-3, 1e-3, 1e-3), 0, 0.02, true},
      {"prolate, large step", Vec3(1.5e-3, 1e-3, 1e-3), 0, 0.3, true},
      {"oblate", Vec3(1.5e-3, 1.5e-3, 1e-3), 2, 0.02, true},
      {"prolate, I_b != I_c by 1e-12", Vec3(1.5e-3, 1e-3, 1e-3 * (1 - 1e-12)), 0, 0.02, false}};
  for (const Case& c : cases) {
    Vec3 w0 = kSpin * Vec3(0.5, 0.2, 0.5);  // tilted spin: 1 about the symmetry axis
    w0[c.sym] = kSpin;
    Body b(c.axes, kQ0, w0, c.w_dt);
    const Vec3 l = b.p.angmom[0];
    const Vec3 lhat = l.normalized();
    const double i_perp = b.inertia[(c.sym + 1) % 3];
    const double omega_p = l.norm() / i_perp;
    const double spin = w0[c.sym];                                    // pi_s / I_s, Euler: constant
    const double cos_cone = b.inertia[c.sym] * w0[c.sym] / l.norm();  // e_s.L / |L|
    const Vec3 u = lhat.unitOrthogonal(), v = lhat.cross(u);          // basis of the plane normal to L
    auto sym_axis = [&] { return Vec3(b.p.q[0] * Vec3::Unit(c.sym)); };
    auto phase = [&] { return std::atan2(sym_axis().dot(v), sym_axis().dot(u)); };
    double angle = 0, prev = phase(), cone_err = 0, spin_err = 0;
    const int n = 20000;
    for (int s = 0; s < n; ++s) {
      b.step();
      const double cur = phase();
      angle += std::remainder(cur - prev, 2 * pi);  // unwrap (steps turn by < 0.3 rad)
      prev = cur;
      const Vec3 es = sym_axis();
      cone_err = std::max(cone_err, std::abs(es.dot(lhat) - cos_cone));
      spin_err = std::max(spin_err, std::abs(b.p.omega[0].dot(es) / spin - 1));
    }
    const double period = 2 * pi * n * b.model.dt / angle;
    const double expected = 2 * pi / omega_p;
    const double tol = c.exact ? 1e-10 : c.w_dt * c.w_dt / 4;
    EXPECT_NEAR(period / expected, 1.0, tol) << c.name;
    EXPECT_LT(cone_err, tol) << c.name << ": cone angle";
    EXPECT_LT(spin_err, tol) << c.name << ": spin about the symmetry axis";
    EXPECT_GT(angle, 20 * 2 * pi) << "test setup: many precession periods";
    RecordProperty(
        c.name, "period " + sci(period / expected - 1) + " cone " + sci(cone_err) + " spin " + sci(spin_err));
  }
}

// SPEC 5/6 (paper Eq. 11, 17-19): a torsional spring about a principal axis n of an ellipsoid,
// T = -kappa theta n (theta the rotation angle about n, read from q), kappa = I_n Omega^2 with
// Omega = omega#_i = sqrt(E/rho) / R_i, R_i = (abc)^(1/3): with `nd` damping B_i = 2 xi0 omega#_i
// the ratio from the logarithmic decrement is B_i / (2 Omega) = xi0 about every principal axis
// (the damping D_i = B_i I_i scales with the moment about that axis).
// Tolerance 0.1 % relative, as in test_integrator.cpp: L stays along n (the torque is along n
// and a principal axis has omega || L), every sub-rotation about the other axes is by zero, so
// theta follows exactly the central-difference recursion analysed there (error (Omega dt)^2 / 24
// = 1.7e-5 at Omega dt = 0.02). Amplitude 0.3 rad: a large rotation, exact in theta.
// Axes: a and c of a 3:2:1 ellipsoid (the stable ones: about b, round-off grows through the
// tumbling instability) and a and b of the paper's 1.5:1:1 spheroid.
TEST(Rotation, TorsionalOscillatorNdDampingRatio) {
  const SingleThread one_thread;
  struct Case {
    Vec3 axes;
    int axis;
  };
  const Case cases[] = {
      {kAxes321, 0}, {kAxes321, 2}, {Vec3(1.5e-3, 1e-3, 1e-3), 0}, {Vec3(1.5e-3, 1e-3, 1e-3), 1}};
  for (double xi0 : {0.005, 0.05}) {
    for (const Case& c : cases) {
      const double radius = std::cbrt(c.axes.prod());
      const double big_omega = std::sqrt(kE / kRho) / radius;  // omega#_i, Eq. 17
      Body b(c.axes, kQ0, Vec3::Zero(), 0);
      b.model.dt = 0.02 / big_omega;
      b.model.r_min = radius;
      b.model.damping = resolve_damping("nd", {xi0, b.model.material.wave_speed(), radius});
      assign_damping(b.model, b.p);
      ASSERT_NEAR(b.p.damping_rotation[0], 2 * xi0 * big_omega, 1e-12 * b.p.damping_rotation[0])
          << "Eq. 19 with R_i = (abc)^1/3";
      const double kappa = b.inertia[c.axis] * big_omega * big_omega;
      const Vec3 n = kQ0 * Vec3::Unit(c.axis);
      const double theta0 = 0.3;
      b.p.q.set(0, Quat(Eigen::AngleAxisd(theta0, n)) * kQ0);
      auto theta = [&] {
        const Quat r = b.p.q[0] * kQ0.conjugate();  // rotation from the rest orientation
        return 2 * std::atan2(r.vec().dot(n), r.w());
      };
      // 30 periods, or until the amplitude has decayed to ~1e-10 (e^-23).
      const double periods = std::min(30.0, 23.0 / (2 * pi * xi0));
      const int steps = static_cast<int>(periods * 2 * pi / 0.02) + 2;
      std::vector<double> trace;
      trace.reserve(static_cast<std::size_t>(steps));
      double off_axis = 0;
      for (int s = 0; s < steps; ++s) {
        const double th = theta();
        trace.push_back(th);
        b.step(-kappa * th * n);
        off_axis =
            std::max(off_axis, b.p.angmom[0].cross(n).norm() / (b.inertia[c.axis] * big_omega * theta0));
      }
      // Peaks by a parabola through the three samples around each maximum.
      std::vector<double> pk;
      for (std::size_t k = 1; k + 1 < trace.size(); ++k) {
        if (!(trace[k] > trace[k - 1] && trace[k] >= trace[k + 1] && trace[k] > 0)) continue;
        const double curv = trace[k + 1] - 2 * trace[k] + trace[k - 1];
        const double d = trace[k + 1] - trace[k - 1];
        pk.push_back(curv < 0 ? trace[k] - d * d / (8 * curv) : trace[k]);
      }
      ASSERT_GE(pk.size(), 3u);
      const double lambda = std::log(pk.front() / pk.back()) / static_cast<double>(pk.size() - 1);
      const double xi = lambda / std::sqrt(4 * pi * pi + lambda * lambda);
      EXPECT_NEAR(xi, xi0, 1e-3 * xi0) << "axes " << c.axes.transpose() << " axis " << c.axis;
      // L stays on the axis (no spurious gyroscopic coupling): round-off only.
      EXPECT_LT(off_axis, 1e-9) << "axes " << c.axes.transpose() << " axis " << c.axis;
      RecordProperty("xi_rel_err_" + std::to_string(c.axes.x() > 2e-3) + std::to_string(c.axis) + "_" +
                         std::to_string(xi0 > 0.01),
                     sci(xi / xi0 - 1) + " off " + sci(off_axis));
    }
  }
}

// SPEC 5 for spheres is unchanged: L is kicked by the damped update, omega = L / I with the
// scalar moment I = 2/5 m R^2, and advance_positions leaves q (and omega) untouched. Bit-exact
// where the engine must do exactly this arithmetic; the hand formula (different association of
// the same operations) within 4 ulps (EXPECT_DOUBLE_EQ).
TEST(Rotation, SphereFastPathUnchanged) {
  const double radius = 1.3e-3, a = 850.0, dt = 2e-7;
  Particles p;
  const Quat q0(Eigen::AngleAxisd(1.1, Vec3(-1, 2, 0.5).normalized()));
  p.add(0, ShapeKind::sphere, Vec3::Constant(radius), kRho, Vec3(0.1, 0.2, 0.3), q0);
  p.damping_translation[0] = p.damping_rotation[0] = a;
  const Vec3 l0(3e-9, -1e-9, 2e-9), torque(1e-4, 2e-4, -5e-5), vel(0.01, -0.02, 0.03);
  p.angmom.set(0, l0);
  p.torque[0] = torque;
  p.v[0] = vel;
  Model model;
  model.dt = dt;
  integrate_velocities(model, p);
  const double m = kRho * 4.0 / 3.0 * pi * radius * radius * radius;
  const double inertia = 0.4 * m * radius * radius;
  for (int k = 0; k < 3; ++k) {
    const double lk = ((1 - a * dt / 2) * l0[k] + dt * torque[k]) / (1 + a * dt / 2);  // SPEC 5
    EXPECT_DOUBLE_EQ(p.angmom[0][k], lk);
    EXPECT_DOUBLE_EQ(p.omega[0][k], lk / inertia);
  }
  EXPECT_EQ(p.angmom[0], damped_kick(l0, torque, a, dt));
  for (int k = 0; k < 3; ++k) EXPECT_DOUBLE_EQ(p.omega[0][k], p.angmom[0][k] / p.inertia[0].x());
  const Vec3 omega = p.omega[0];
  Cell cell = make_cell(Mat3(Vec3(0.02, 0.03, 0.04).asDiagonal()));
  advance_positions(model, cell, p);
  EXPECT_EQ(p.q[0].coeffs(), q0.normalized().coeffs()) << "a sphere's orientation is not integrated";
  EXPECT_EQ(p.omega[0], omega);
  const Vec3 v_half = p.v[0];  // v(t+dt/2), paper Eq. 10 with F = 0
  for (int k = 0; k < 3; ++k) EXPECT_DOUBLE_EQ(v_half[k], (1 - a * dt / 2) * vel[k] / (1 + a * dt / 2));
  const Vec3 s_expected =
      Vec3(0.1, 0.2, 0.3) + dt * Vec3(v_half.x() / 0.02, v_half.y() / 0.03, v_half.z() / 0.04);
  for (int k = 0; k < 3; ++k) EXPECT_NEAR(p.s[0][k], s_expected[k], 1e-15) << "SPEC 3: s += dt h^-1 v";
}

// advance_positions turns the spheroids in lanes, several per vector instruction, with the sine
// and cosine of the half angles by their Taylor polynomials and the lanes beyond the polynomials'
// range run again one at a time. Every spheroid must get exactly what free_rotation (one body,
// no lanes) gives it, at a step that normalises the orientations and at one that does not: prolate and oblate ones (symmetry axes 0 and 2), with turns per step from
// 1e-8 rad to beyond the Taylor range, some without angular momentum or with a subnormal one (a
// rattler's), mixed with spheres and an asymmetric body, more of them than one set of lanes; then
// stretches of prolate and of oblate spheroids only, turning or without angular momentum, which
// the drift turns in place (runs of 64 consecutive spheroids of one symmetry axis), with lanes
// beyond the Taylor range among them, and a run of spheres only. Bit for bit, as are the surface
// path dt |v| + 2 a |q_new - q_old| (both parts are summed apart from the turn: Eigen's norm())
// and s + dt h^-1 v (Eigen's product, in a sheared cell), also at subnormal velocities.
TEST(Rotation, SpheroidLanesMatchOneAtATime) {
  std::mt19937_64 rng(20261130);
  std::uniform_real_distribution<double> uniform(0, 1);
  std::normal_distribution<double> normal(0, 1);
  Particles p;
  const double dt = 1e-6;
  int beyond_taylor = 0, within_taylor = 0, off_unit = 0, tiny = 0;
  for (std::uint32_t i = 0; i < 700; ++i) {
    // Runs in place: [320, 448) prolate, [448, 576) oblate spheroids; spheres only in [576, 640).
    const bool prolate = i >= 300 && i < 448, oblate = i >= 448 && i < 576, spheres = i >= 576 && i < 640;
    const bool in_place = prolate || oblate;  // every particle a turning spheroid
    const double c = 1e-3 * (0.5 + uniform(rng)), a = c * (1.2 + uniform(rng));
    const Vec3 axes = prolate       ? Vec3(a, c, c)
                      : oblate      ? Vec3(a, a, c)
                      : spheres     ? Vec3::Constant(c)
                      : i % 37 == 5 ? Vec3::Constant(c)
                      : i % 41 == 7 ? kAxes321
                      : i % 2       ? Vec3(a, c, c)
                                    : Vec3(a, a, c);
    const Quat q(normal(rng), normal(rng), normal(rng), normal(rng));
    p.add(i, axes == Vec3::Constant(c) ? ShapeKind::sphere : ShapeKind::ellipsoid, axes, kRho, Vec3::Constant(0.5),
          q.normalized());
    const double turn = i % 23 == 0 ? 0 : 1e-8 * std::pow(0.4 / 1e-8, uniform(rng));  // omega dt
    p.angmom.set(i, p.inertia[i].minCoeff() * turn / dt * Vec3(normal(rng), normal(rng), normal(rng)).normalized());
    // A rattler's L decayed by damping, to subnormal and just around 2^-540 (below it a spheroid
    // skips the lanes: |L|^2 rounds to 0).
    if (i % 19 == 4 && !in_place) {
      const double scale[] = {1e-310, 0x1p-541, 0x1p-539, 1e-200};
      p.angmom.set(i, scale[(i / 19) % 4] * Vec3(normal(rng), normal(rng), normal(rng)).normalized());
      ++tiny;
    }
    p.v[i] = 0.1 * Vec3(normal(rng), normal(rng), normal(rng));  // (the translation part of the path)
    // s as small as the step, so that s + dt h^-1 v keeps the step's round-off (its order of sums).
    p.s[i] = 1e-7 * Vec3(normal(rng), normal(rng), normal(rng));
    // A rattler's v decayed to subnormal, and just around the bound below which s is left alone.
    if (i % 17 == 6) p.v[i] *= std::array{1e-310, 0x1p-560, 0x1p-530, 1e-150}[(i / 17) % 4];
    (0.5 * turn > 0.004 ? beyond_taylor : within_taylor)++;  // (SPEC 5.4's Taylor range)
    // |q|^2 = 1 + 1e-6: beyond the lanes' Newton step for the norm (they run such a lane again).
    if (i % 29 == 3) p.q.set(i, Quat((1 + 5e-7) * p.q[i].coeffs())), ++off_unit;
  }
  const Particles before = p;
  Model model;
  model.dt = dt;
  Mat3 h;
  h << 1.0, 0.2, 0.1, 0.05, 1.1, 0.3, 0.02, 0.04, 0.9;
  const Cell cell = make_cell(h);
  int spheroids = 0;
  for (const bool normalize : {true, false}) {
    p = before;
    spheroids = 0;
    std::vector<double> path(p.size(), 0.0);
    advance_positions(model, cell, p, path, 0, SIZE_MAX, false, normalize);
    for (std::size_t i = 0; i < p.size(); ++i) {
      const double moved = dt * before.v[i].norm();
      const Vec3 s_expected = before.s[i] + (dt * cell.h_inv) * before.v[i];
      EXPECT_EQ(p.s[i], s_expected) << "particle " << i;
      if (p.shape[i] == ShapeKind::sphere) {
        EXPECT_EQ(p.q[i].coeffs(), before.q[i].coeffs());
        EXPECT_EQ(path[i], moved) << "particle " << i;
        continue;
      }
      const Quat expected = free_rotation(before.q[i], p.inertia[i], p.angmom[i], dt, normalize);
      ASSERT_EQ(p.q[i].coeffs(), expected.coeffs()) << "particle " << i << (normalize ? "" : ", not normalised");
      const double chord2 = std::min((expected.coeffs() - before.q[i].coeffs()).squaredNorm(),
                                     (expected.coeffs() + before.q[i].coeffs()).squaredNorm());
      EXPECT_EQ(path[i], moved + 2 * p.bound_radius[i] * std::sqrt(chord2)) << "particle " << i;
      // (R(q) of a q off the unit sphere by e is a rotation to within ~2e, and omega takes e.L
      // from the old q, the free flow keeping it: those set off by 5e-7 are so off.)
      const Vec3 omega = omega_of(expected.normalized(), p.inertia[i], p.angmom[i]);
      const double off_unit_by =
          std::abs(expected.squaredNorm() - 1) + std::abs(before.q[i].squaredNorm() - 1);
      EXPECT_LE((p.omega[i] - omega).norm(), (1e-12 + 4 * off_unit_by) * omega.norm()) << "particle " << i;
      if (p.angmom[i].norm() < 1e-100) {
        EXPECT_EQ(p.q[i].coeffs(), before.q[i].coeffs()) << "particle " << i;
      }
      const Vec3& m = p.inertia[i];
      spheroids += m.x() != m.z() && (m.x() == m.y() || m.y() == m.z());
    }
  }
  EXPECT_GT(spheroids, 2 * 64) << "more than one set of lanes";
  EXPECT_GT(beyond_taylor, 20);
  EXPECT_GT(within_taylor, 100);
  EXPECT_GT(off_unit, 5);
  EXPECT_GT(tiny, 10);
}

// What the drift reads of a body's inertia (Particles::symmetry_axis and the inverse moments
// about that axis and across it), and 1 / I_min, follow its shape and moments: a sphere, prolate and oblate
// spheroids (axes 0 and 2), three distinct moments; and again after the moments are scaled.
TEST(Rotation, BodiesKnowTheirSymmetryAxis) {
  Particles p;
  const Vec3 sphere = Vec3::Constant(1e-3), prolate(2e-3, 1e-3, 1e-3), oblate(2e-3, 2e-3, 1e-3);
  p.add(0, ShapeKind::sphere, sphere, kRho, Vec3::Zero(), Quat::Identity());
  p.add(1, ShapeKind::ellipsoid, prolate, kRho, Vec3::Zero(), Quat::Identity());
  p.add(2, ShapeKind::ellipsoid, oblate, kRho, Vec3::Zero(), Quat::Identity());
  p.add(3, ShapeKind::ellipsoid, kAxes321, kRho, Vec3::Zero(), Quat::Identity());
  const auto check = [&p](const char* when) {
    SCOPED_TRACE(when);
    EXPECT_EQ(p.symmetry_axis, (std::vector<std::int8_t>{kSphereBody, 0, 2, kThreeMoments}));
    const std::array<std::array<int, 2>, 3> axes{{{0, 1}, {0, 1}, {2, 0}}};  // axial, transverse
    for (std::size_t i = 0; i < 3; ++i) {
      EXPECT_EQ(p.inv_axial_moment[i], 1 / p.inertia[i][axes[i][0]]) << "particle " << i;
      EXPECT_EQ(p.inv_transverse_moment[i], 1 / p.inertia[i][axes[i][1]]) << "particle " << i;
    }
    EXPECT_EQ(p.inertia[0].x(), p.inertia[0].z());  // a sphere's 1 / I, whichever moment
    for (std::size_t i = 0; i < 4; ++i)  // what stiffness damping reads, of any body
      EXPECT_EQ(inv_smallest_moment(p, i), p.inertia[i].cwiseInverse().maxCoeff()) << "particle " << i;
  };
  check("as added");
  InertiaScaling scaling;
  scaling.target = InertiaScaling::Target::coarsest;
  scale_inertia(p, scaling, kRho);
  ASSERT_GT(p.inertia_scale[0], 1);
  check("scaled");
}

// A viscous kick settles every momentum below 2^-540 to zero (SPEC 5.2), so the step's drift
// does not look for a subnormal L (advance_positions' `settled`): after the kick, the drift told so
// turns runs of spheroids, among them some whose L the kick settled, to the bits of the drift
// that looks. Cundall's local damping settles nothing: kick_settles says so.
TEST(Rotation, DriftTrustsTheKicksSettle) {
  std::mt19937_64 rng(20261207);
  std::normal_distribution<double> normal(0, 1);
  Particles p;
  int tiny = 0;
  for (std::uint32_t i = 0; i < 256; ++i) {
    const Vec3 axes = i < 128 ? Vec3(2e-3, 1e-3, 1e-3) : Vec3(2e-3, 2e-3, 1e-3);  // two runs of each axis
    p.add(i, ShapeKind::ellipsoid, axes, kRho, Vec3::Constant(0.5),
          Quat(normal(rng), normal(rng), normal(rng), normal(rng)).normalized());
    const double size = i % 13 == 2 ? (++tiny, std::array{1e-310, 0x1p-541, 1e-200}[i % 3]) : 1e-9;
    p.angmom.set(i, size * Vec3(normal(rng), normal(rng), normal(rng)));
    p.v[i] = 0.1 * Vec3(normal(rng), normal(rng), normal(rng));
  }
  Model model;
  model.dt = 1e-6;
  ASSERT_TRUE(kick_settles(model));
  integrate_velocities(model, p);  // no torque: L kept, or settled to zeros
  int zeroed = 0;
  for (std::size_t i = 0; i < p.size(); ++i) zeroed += p.angmom[i] == Vec3::Zero();
  EXPECT_EQ(zeroed, tiny) << "the kick settles the L below 2^-540, and only those";
  Particles looked = p, trusted = p;
  std::vector<double> path_looked(p.size(), 0.0), path_trusted(p.size(), 0.0);
  const Cell cell = make_cell(Mat3::Identity());
  advance_positions(model, cell, looked, path_looked, 0, SIZE_MAX, false);
  advance_positions(model, cell, trusted, path_trusted, 0, SIZE_MAX, true);
  for (std::size_t i = 0; i < p.size(); ++i) {
    ASSERT_EQ(trusted.q[i].coeffs(), looked.q[i].coeffs()) << "particle " << i;
    ASSERT_EQ(trusted.omega[i], looked.omega[i]) << "particle " << i;
    ASSERT_EQ(path_trusted[i], path_looked[i]) << "particle " << i;
    ASSERT_EQ(trusted.s[i], looked.s[i]) << "particle " << i;
  }
  model.damping.cundall_rotation = 0.2;
  EXPECT_FALSE(kick_settles(model));
}

// The spheroid's turn (SPEC 5.4) takes the sine and cosine of half angles below 0.004 from Taylor
// polynomials to x^5 and x^4 (libm above). Against the closed form with libm's trigonometry
// (Eigen's AngleAxis), over turns per step from 1e-9 rad to beyond the switch, just below, at
// and just above it (precession half angle 0.004): the polynomials' remainders are below
// 0.004^7/7! = 3.3e-21 (sine, 8e-19 of it) and 0.004^6/6! = 5.7e-18 (cosine), so what is left
// is the round-off of the two products and the normalisation, a few ulps of a unit quaternion:
// 2e-15 is ten of them (a Taylor series one term short would miss it at 0.004 by 0.004^5/5! = 8.5e-15).
TEST(Rotation, SpheroidTurnMatchesLibmTrigonometry) {
  std::mt19937_64 rng(20261206);
  std::normal_distribution<double> normal(0, 1);
  const double dt = 1e-6;
  const Vec3 inertia = moments(Vec3(1.5e-3, 1e-3, 1e-3));  // prolate: symmetry axis x
  const double i_s = inertia.x(), i_perp = inertia.y();
  std::vector<double> half_angles;  // of the precession, 0.5 dt |L| / I_perp
  for (double h = 1e-9; h < 0.2; h *= 1.7) half_angles.push_back(h);
  for (double h : {0.004 * (1 - 1e-12), 0.004, 0.004 * (1 + 1e-12)}) half_angles.push_back(h);
  double worst = 0;
  for (double h : half_angles) {
    for (int trial = 0; trial < 8; ++trial) {
      const Quat q = Quat(normal(rng), normal(rng), normal(rng), normal(rng)).normalized();
      const Vec3 l = 2 * h * i_perp / dt * Vec3(normal(rng), normal(rng), normal(rng)).normalized();
      const Vec3 e = q * Vec3::UnitX();
      const double spin = dt * l.dot(e) * (1 / i_s - 1 / i_perp);
      const Quat expected = (Eigen::AngleAxisd(dt * l.norm() / i_perp, l.normalized()) * q *
                             Eigen::AngleAxisd(spin, Vec3::UnitX()))
                                .normalized();
      // Both ends of the lanes: one body (free_rotation) and advance_positions.
      Particles p;
      p.add(0, ShapeKind::ellipsoid, Vec3(1.5e-3, 1e-3, 1e-3), kRho, Vec3::Constant(0.5), q);
      p.angmom.set(0, l);
      Model model;
      model.dt = dt;
      advance_positions(model, make_cell(Mat3::Identity()), p);
      for (const Quat& got : {free_rotation(q, p.inertia[0], l, dt), p.q[0]}) {
        const double error = std::min((got.coeffs() - expected.coeffs()).norm(), (got.coeffs() + expected.coeffs()).norm());
        EXPECT_LE(error, 2e-15) << "precession half angle " << h;
        worst = std::max(worst, error);
      }
    }
  }
  std::cout << "largest |q - q_libm|: " << worst << "\n";
}
