// Damped leapfrog (SPEC 5, paper Eq. 10) and the particle damping models (SPEC 6, paper
// Eq. 11, 13-15, 17-19), measured on one-degree-of-freedom oscillators of known frequency.
//
// The damping ratio is measured from the logarithmic decrement of the free oscillation:
// Lambda = ln(x_k / x_{k+1}) per period, xi = Lambda / sqrt(4 pi^2 + Lambda^2) (exact inverse of
// Lambda = 2 pi xi / sqrt(1 - xi^2) for a linear damped oscillator).
//
// Tolerance, for every ratio below: 0.1 % relative. The discrete scheme
//   (1 + a) x_{n+1} - (2 - w^2 dt^2) x_n + (1 - a) x_{n-1} = 0,  a = A dt / 2
// decays by |z| = sqrt((1 - a)/(1 + a)) per step and turns by theta with
// cos theta = (1 - w^2 dt^2 / 2) / sqrt(1 - a^2); both equal the continuous values to relative
// O((w dt)^2 / 24 + (A dt)^2 / 12), i.e. <= 2e-4 at w dt = 0.02 and xi <= 0.4. Peaks are located
// by a parabola through the three samples around each maximum (error ~ (w dt)^4 per peak) and
// the decrement is averaged over many periods. Observed: -1.7e-5 relative = -(w dt)^2 / 24.
// 0.1 % leaves a wide margin over that and catches any factor error (A dt instead of A dt / 2
// is 100 %, R_i for R_min 650 %) and even a 0.2 % error in the moment of inertia.
#include <gtest/gtest.h>
#include <omp.h>

#include <cmath>
#include <string>
#include <vector>

#include "qsdem/engine/damping/stage.hpp"
#include "qsdem/engine/integrator.hpp"
#include "qsdem/engine/model.hpp"
#include "qsdem/engine/particles.hpp"
#include "qsdem/engine/step.hpp"
#include "test_support.hpp"

using namespace qsdem;

namespace {

constexpr double kRho = 2650;
constexpr double kE = 7.8e10;
constexpr double kNu = 0.3;
constexpr double kRmin = 1.0627e-3;  // Sample A (SPEC 9)
constexpr double kRelTol = 1e-3;     // see the header comment

Material paper_material() { return {kRho, kE, kNu}; }
double wave_speed() { return std::sqrt(kE / kRho); }  // by hand, not Material::wave_speed()

// The Model of damping model `name` at ratio xi0 on Sample A's smallest radius (the registry's).
Model damped_model(const char* name, double xi0, DampedMotion acts_on = DampedMotion::both) {
  Model model;
  model.material = paper_material();
  model.r_min = kRmin;
  model.damping = resolve_damping(name, {xi0, model.material.wave_speed(), kRmin}, acts_on);
  return model;
}

// A_i that the damping stage gives a sphere of `radius` under damping model `name` at ratio xi0.
double engine_factor(const char* name, double xi0, double radius) {
  Particles p;
  p.add(0, ShapeKind::sphere, Vec3::Constant(radius), kRho, Vec3::Zero(), Quat::Identity());
  assign_damping(damped_model(name, xi0), p);
  return p.damping_translation[0];
}

// The systems here have 1-5 particles: OpenMP fork/join per stage costs far more than the work
// and, on a loaded 2-core machine, a second thread waiting for a time slice can make 10^4 steps
// take tens of seconds. Physics does not depend on the thread count (deterministic block sums),
// so the long loops run on one thread; the previous setting is restored.
using qsdem_test::SingleThread;

// Values at maxima of a sampled signal (parabolic vertex through the three samples).
std::vector<double> peaks(const std::vector<double>& x) {
  std::vector<double> out;
  for (std::size_t k = 1; k + 1 < x.size(); ++k) {
    if (!(x[k] > x[k - 1] && x[k] >= x[k + 1] && x[k] > 0)) continue;
    const double curv = x[k + 1] - 2 * x[k] + x[k - 1];
    out.push_back(curv < 0 ? x[k] - (x[k + 1] - x[k - 1]) * (x[k + 1] - x[k - 1]) / (8 * curv) : x[k]);
  }
  return out;
}

// Damping ratio from the mean logarithmic decrement between the first and the last peak.
double measured_ratio(const std::vector<double>& x) {
  const std::vector<double> p = peaks(x);
  EXPECT_GE(p.size(), 3u) << "too few periods for a decrement";
  if (p.size() < 2) return NAN;
  const double lambda = std::log(p.front() / p.back()) / static_cast<double>(p.size() - 1);
  return lambda / std::sqrt(4 * pi * pi + lambda * lambda);
}

// Number of steps for `periods` periods at natural frequency w with w dt given, capped so that
// a strongly damped signal does not decay into round-off (amplitude stays above 1e-10).
int steps_for(double periods, double w_dt, double xi) {
  const double decay_periods = 23.0 / (2 * pi * std::max(xi, 1e-9));  // e^-23 ~ 1e-10
  return static_cast<int>(std::min(periods, decay_periods) * 2 * pi / w_dt) + 2;
}

// Translation with the engine's damped_kick (paper Eq. 10) and a drift x += dt v.
std::vector<double> kick_oscillator(double w, double a, double w_dt, double periods) {
  const double dt = w_dt / w, m = 1.7, k = m * w * w;
  const int n = steps_for(periods, w_dt, a / (2 * w));
  Vec3 x(1.0, 0, 0), v = Vec3::Zero();
  std::vector<double> trace;
  trace.reserve(static_cast<std::size_t>(n));
  for (int s = 0; s < n; ++s) {
    trace.push_back(x.x());
    v = damped_kick(v, -k * x / m, a, dt);
    x += dt * v;
  }
  return trace;
}

// One sphere in Particles driven through the engine's integrate_velocities: a linear spring on
// translation (force -k x along e) and a torsional spring on rotation (torque -kappa theta about
// axis u), both with natural frequency w. We advance our own scalars x and theta with the
// resulting v and omega.
struct Traces {
  std::vector<double> x, theta;
};
Traces particle_oscillator(double radius, double damping, double w, double w_dt, double periods) {
  Particles p;
  p.add(0, ShapeKind::sphere, Vec3::Constant(radius), kRho, Vec3::Zero(), Quat::Identity());
  p.damping_translation[0] = p.damping_rotation[0] = damping;
  const double m = p.mass[0];
  const double inertia = 0.4 * m * radius * radius;  // solid sphere, by hand
  const double k = m * w * w, kappa = inertia * w * w;
  const Vec3 e = Vec3(1, 2, 2) / 3.0, u = Vec3(2, -1, 2) / 3.0;  // unit, arbitrary
  Model model;
  model.material = paper_material();
  model.dt = w_dt / w;
  const int n = steps_for(periods, w_dt, damping / (2 * w));
  double x = 1e-6, theta = 1e-3;
  Traces t;
  for (int s = 0; s < n; ++s) {
    t.x.push_back(x);
    t.theta.push_back(theta);
    p.force[0] = -k * x * e;
    p.torque[0] = -kappa * theta * u;
    integrate_velocities(model, p);
    x += model.dt * p.v[0].dot(e);
    theta += model.dt * p.omega[0].dot(u);
  }
  return t;
}

}  // namespace

// Paper Eq. 10-11: the central-difference update with damping factor A gives an oscillator of
// natural frequency w the damping ratio xi = A / (2 w).
TEST(Integrator, DampedKickGivesRatioAOverTwoOmega) {
  for (double w : {1.0, 3.0e5}) {
    for (double xi : {0.001, 0.005, 0.05, 0.2, 0.4}) {
      const double a = 2 * xi * w;
      const double measured = measured_ratio(kick_oscillator(w, a, 0.02, 30));
      EXPECT_NEAR(measured, xi, kRelTol * xi) << "omega " << w << " xi " << xi;
    }
  }
}

// SPEC 6 `none`: A = 0, leapfrog is exactly amplitude-preserving (|z| = 1 for w dt < 2); the
// parabolic peak estimate of a pure sampled sinusoid is within ~(w dt)^4 ~ 1.6e-7 (observed
// 2e-9); a decay of xi = 1e-6 over 50 periods would already be 3e-4.
TEST(Integrator, NoDampingKeepsAmplitude) {
  const SingleThread one_thread;
  for (double radius : {kRmin, 7.5 * kRmin}) {
    const double a = engine_factor("none", 0.05, radius);
    EXPECT_EQ(a, 0.0);
    const double w = wave_speed() / radius;
    const Traces t = particle_oscillator(radius, a, w, 0.02, 50);
    for (const auto* trace : {&t.x, &t.theta}) {
      const std::vector<double> p = peaks(*trace);
      ASSERT_GE(p.size(), 49u);
      for (double pk : p) EXPECT_NEAR(pk / p.front(), 1.0, 1e-6);
    }
  }
}

// SPEC 6 `nd` (paper Eq. 17-19): A_i = B_i = 2 xi0 omega#_i with omega#_i = sqrt(E/rho) / R_i,
// so an oscillator at omega#_i has exactly the ratio xi0, for every particle size: translation
// (A_i / (2 omega)) and rotation (B_i / (2 Omega)) alike.
TEST(Integrator, NdGivesNominalRatioForEverySize) {
  const SingleThread one_thread;
  for (double xi0 : {0.005, 0.05}) {
    for (double radius : {kRmin, 7.5 * kRmin}) {
      const double a = engine_factor("nd", xi0, radius);
      const double w = wave_speed() / radius;  // omega#_i, Eq. 17
      EXPECT_NEAR(a / (2 * w), xi0, 1e-12 * xi0) << "Eq. 19: A_i = 2 xi0 omega#_i";
      const Traces t = particle_oscillator(radius, a, w, 0.02, 30);
      EXPECT_NEAR(measured_ratio(t.x), xi0, kRelTol * xi0) << "translation, R = " << radius;
      EXPECT_NEAR(measured_ratio(t.theta), xi0, kRelTol * xi0) << "rotation, R = " << radius;
    }
  }
}

// SPEC 6 `od` (paper Eq. 13-15): A = 2 xi0 omega_max for all particles, omega_max = omega# of the
// smallest one, so a particle at omega#_i gets xi0 omega_max / omega#_i = xi0 R_i / R_min
// (paper Eq. 14): xi0 for the smallest and 7.5 xi0 for the largest of Sample A.
TEST(Integrator, OdOverdampsLargeParticles) {
  const SingleThread one_thread;
  for (double xi0 : {0.005, 0.05}) {
    for (double size_ratio : {1.0, 7.5}) {
      const double radius = size_ratio * kRmin;
      const double a = engine_factor("od", xi0, radius);
      const double w = wave_speed() / radius;
      EXPECT_NEAR(a, 2 * xi0 * wave_speed() / kRmin, 1e-12 * a) << "Eq. 15: A = 2 xi0 omega_max";
      const double expected = xi0 * size_ratio;
      const Traces t = particle_oscillator(radius, a, w, 0.02, 30);
      EXPECT_NEAR(measured_ratio(t.x), expected, kRelTol * expected) << "translation, R/Rmin = " << size_ratio;
      EXPECT_NEAR(measured_ratio(t.theta), expected, kRelTol * expected) << "rotation, R/Rmin = " << size_ratio;
    }
  }
}

// assign_damping fills A_i = B_i per particle with the model's law (SPEC 6): Eq. 19 for nd,
// Eq. 15 for od, 0 without damping.
TEST(Integrator, AssignDampingPerParticle) {
  Particles p;
  p.add(0, ShapeKind::sphere, Vec3::Constant(kRmin), kRho, Vec3::Zero(), Quat::Identity());
  p.add(1, ShapeKind::sphere, Vec3::Constant(7.5 * kRmin), kRho, Vec3::Zero(), Quat::Identity());
  Model model = damped_model("nd", 0.005);
  assign_damping(model, p);
  EXPECT_NEAR(p.damping_translation[0], 2 * 0.005 * wave_speed() / kRmin, 1e-12 * p.damping_translation[0]);
  EXPECT_NEAR(p.damping_translation[1], 2 * 0.005 * wave_speed() / (7.5 * kRmin), 1e-12 * p.damping_translation[1]);
  model = damped_model("od", 0.005);
  assign_damping(model, p);
  EXPECT_NEAR(p.damping_translation[0], 2 * 0.005 * wave_speed() / kRmin, 1e-12 * p.damping_translation[0]);
  EXPECT_NEAR(p.damping_translation[1], p.damping_translation[0], 1e-12 * p.damping_translation[0])
      << "od: one factor for all sizes";
  EXPECT_EQ(p.damping_rotation, p.damping_translation) << "B_i = A_i (acts on both)";
  model = damped_model("none", 0.005);
  assign_damping(model, p);
  EXPECT_EQ(p.damping_translation[0], 0.0);
  EXPECT_EQ(p.damping_translation[1], 0.0);
}

// What is damped is data of the phase (ResolvedDamping::acts_on, the case key damping.acts_on): a
// sphere and a spheroid, free (no contact), moving and spinning, stepped through the engine with
// nd damping: with only translation damped each keeps its angular momentum to the bit, with only
// rotation its velocity; damped, either decays by the kick's factor (1 - A dt/2) / (1 + A dt/2)
// per step (paper Eq. 10), and with both (the paper's) both do.
TEST(Integrator, DampingActsOnTranslationRotationOrBoth) {
  const qsdem_test::SingleThread one_thread;
  for (const DampedMotion acts_on : {DampedMotion::translation, DampedMotion::rotation, DampedMotion::both}) {
    State st;
    st.cell = make_cell(0.05 * Mat3::Identity());
    st.particles.add(0, ShapeKind::sphere, Vec3::Constant(kRmin), kRho, Vec3(0.2, 0.2, 0.2), Quat::Identity());
    st.particles.add(1, ShapeKind::ellipsoid, Vec3(1.5, 1.0, 1.0) * kRmin, kRho, Vec3(0.7, 0.6, 0.7),
                     Quat(Eigen::AngleAxisd(0.4, Vec3(1, 2, 3).normalized())));
    Particles& p = st.particles;
    for (std::size_t k = 0; k < 2; ++k) {
      p.v[k] = Vec3(0.01, -0.02, 0.005);
      p.angmom.set(k, p.inertia[k].cwiseProduct(Vec3(30, 10, -20)));
      p.omega[k] = angular_velocity(p.q[k], p.inertia[k], p.angmom[k]);
    }
    const std::vector<Vec3> v0 = p.v, l0 = p.angmom.interleaved();
    Model model = damped_model("nd", 0.05, acts_on);
    model.contact_law = make_contact_law(model.material, 0.5);
    model.dt = 0.32 * 2 * kRmin * std::sqrt(kRho / paper_material().young_modulus);
    model.skin = 0.2 * kRmin;
    assign_damping(model, p);
    constexpr int steps = 200;
    for (int n = 0; n < steps; ++n) step(model, st);
    ASSERT_EQ(st.pairs.size(), 0u) << "free particles";
    const bool translation = acts_on != DampedMotion::rotation, rotation = acts_on != DampedMotion::translation;
    for (std::size_t k = 0; k < 2; ++k) {
      const double a = 2 * 0.05 * wave_speed() / p.equiv_radius[k];  // Eq. 19
      const double decay = std::pow((1 - 0.5 * a * model.dt) / (1 + 0.5 * a * model.dt), steps);
      ASSERT_LT(decay, 0.9) << "a visible decay";
      if (translation)
        EXPECT_LE((p.v[k] - decay * v0[k]).norm(), 1e-12 * v0[k].norm()) << "particle " << k;
      else
        EXPECT_TRUE(p.v[k] == v0[k]) << "particle " << k << ": its velocity, undamped, is untouched";
      if (rotation)
        EXPECT_LE((p.angmom[k] - decay * l0[k]).norm(), 1e-12 * l0[k].norm()) << "particle " << k;
      else
        EXPECT_TRUE(p.angmom[k] == l0[k]) << "particle " << k << ": its spin, undamped, is untouched";
    }
  }
}

// SPEC 5.2: a rattler's momenta decay geometrically under viscous damping; once every component
// of v (of L) is below 2^-540 the kick sets it to zero, so they never pass through the subnormal
// numbers. Above the bound the kick is the plain one, bit for bit, also with a subnormal component
// beside a normal one. Every kick path: viscous, local (in vector lanes), and either with energy
// tracking.
TEST(Integrator, RattlerMomentaSettleToZeroWithoutSubnormals) {
  const auto subnormal = [](const Vec3& x) {
    return std::fpclassify(x.x()) == FP_SUBNORMAL || std::fpclassify(x.y()) == FP_SUBNORMAL ||
           std::fpclassify(x.z()) == FP_SUBNORMAL;
  };
  for (const bool local : {false, true}) {
    for (const bool track : {false, true}) {
      Particles p;
      p.add(0, ShapeKind::sphere, Vec3::Constant(kRmin), kRho, Vec3::Constant(0.5), Quat::Identity());
      p.add(1, ShapeKind::ellipsoid, Vec3(1.5, 1.0, 1.0) * kRmin, kRho, Vec3::Constant(0.5), Quat::Identity());
      p.add(2, ShapeKind::sphere, Vec3::Constant(kRmin), kRho, Vec3::Constant(0.5), Quat::Identity());
      Model model;
      model.dt = 1e-7;
      if (local) model.damping.cundall_translation = model.damping.cundall_rotation = 0.1;
      // Viscous: A dt = 2/3 halves the momenta at each kick; local: no force, no change.
      const double a = local ? 0.0 : (2.0 / 3) / model.dt;
      for (std::size_t i = 0; i < 3; ++i) {
        p.damping_translation[i] = p.damping_rotation[i] = a;
        p.v[i] = 0x1p-500 * Vec3(1, -0.5, 0.25);
        p.angmom.set(i, 0x1p-500 * Vec3(-0.25, 1, 0.5));
      }
      p.v[2] = Vec3(1e-310, 0.1, 0);  // a normal component beside a subnormal one: not settled
      p.angmom.set(2, Vec3(0, 1e-310, 1e-6));
      if (local) p.v[0] = Vec3(0x1p-541, 0, -0x1p-541), p.angmom.set(1, Vec3(0, 0x1p-541, 0));  // kept as they are
      std::vector<double> dissipated(3), kinetic(3);
      const KickEnergy energy = track ? KickEnergy{dissipated.data(), kinetic.data()} : KickEnergy{};
      bool settled_v = false, settled_l = false;
      for (int n = 0; n < 60; ++n) {
        const Particles before = p;
        integrate_velocities(model, p, 0, SIZE_MAX, energy);
        for (std::size_t i = 0; i < 2; ++i) {
          EXPECT_FALSE(subnormal(p.v[i]) || subnormal(p.angmom[i]) || (i == 0 && subnormal(p.omega[i])))
              << "kick " << n << ", particle " << i;
          const Vec3 v = damped_kick(before.v[i], Vec3::Zero(), a, model.dt);
          const Vec3 l = damped_kick(before.angmom[i], Vec3::Zero(), a, model.dt);
          // Only the viscous kick settles: local damping leaves a free momentum as it is.
          const bool v_small = !local && v.cwiseAbs().maxCoeff() < 0x1p-540,
                     l_small = !local && l.cwiseAbs().maxCoeff() < 0x1p-540;
          EXPECT_EQ(p.v[i], v_small ? Vec3::Zero() : v) << "kick " << n << ", particle " << i;
          EXPECT_EQ(p.angmom[i], l_small ? Vec3::Zero() : l) << "kick " << n << ", particle " << i;
          settled_v |= v_small && before.v[i] != Vec3::Zero();
          settled_l |= l_small && before.angmom[i] != Vec3::Zero();
        }
        EXPECT_NE(p.v[2].y(), 0.0) << "kick " << n;
        EXPECT_NE(p.angmom[2].z(), 0.0) << "kick " << n;
      }
      EXPECT_EQ(settled_v, !local) << "local " << local << " track " << track;
      EXPECT_EQ(settled_l, !local) << "local " << local << " track " << track;
      if (!local) {
        EXPECT_EQ(p.v[0], Vec3::Zero()) << "60 halvings from 2^-500";
      }
    }
  }
}

// The step has the kick translate the particles too (integrate_velocities' `move`, in the viscous
// kick's own pass, with the surface path's dt |v|) and then turns the ellipsoids
// (turn_orientations): bit for bit the kick and then advance_positions, with every kick (the
// viscous one, Cundall's local one, which leaves a subnormal v as it is, and the one that tracks
// energy), over ranges whose last particles go one at a time, spheres and spheroids mixed, in a
// sheared cell, with velocities that settle to zeros, stay subnormal or stay normal; particles
// outside the range untouched.
TEST(Integrator, KickThatTranslatesIsTheKickThenTheDrift) {
  const std::size_t n = 23;
  Particles p;
  for (std::size_t k = 0; k < n; ++k) {
    const bool spheroid = k % 4 == 1;
    p.add(static_cast<std::uint32_t>(k), spheroid ? ShapeKind::ellipsoid : ShapeKind::sphere,
          (spheroid ? Vec3(1.5, 1.0, 1.0) : Vec3::Ones()) * kRmin * (1 + 0.1 * double(k % 7)), kRho,
          Vec3(0.1 + 0.03 * double(k), 0.9 - 0.02 * double(k), 1e-3 * double(k + 1)),
          Quat(1, 0.1 * double(k), -0.2, 0.05 * double(k)).normalized());
  }
  for (std::size_t k = 0; k < n; ++k) {
    const double x = double(k) - 11.0;
    p.damping_translation[k] = k % 3 == 0 ? 0.0 : 3.7e5;
    p.damping_rotation[k] = k % 3 == 0 ? 0.0 : 2.1e6;
    p.force[k] = Vec3(0.3 * x, -1e-3 * x * x, 2.5) * 1e-2;
    p.torque[k] = Vec3(-x, 0.5, 1e-2 * x * x) * 1e-7;
    p.v[k] = Vec3(1e-4 * x, 2e-3, -3e-4 * x);
    p.angmom.set(k, Vec3(2e-12, -1e-13 * x, 5e-12));
    // s as small as the step, so that s + dt h^-1 v keeps the step's round-off (its order of sums).
    p.s[k] = 1e-9 * Vec3(1 + 0.1 * x, -0.5 + 0.01 * x * x, 0.3 * x);
  }
  for (const std::size_t k : {2u, 9u, 14u}) {  // no force: v settles to zeros, or stays subnormal (local)
    p.force[k] = p.torque[k] = Vec3::Zero();
    p.v[k] = k == 14 ? Vec3(Vec3::Zero()) : Vec3(1e-310 * Vec3(1, -1, 0.5));
  }
  Mat3 h;
  h << 0.08, 0.004, -0.002, 0.001, 0.081, 0.003, -0.0005, 0.002, 0.083;
  const Cell cell = make_cell(h);
  const CellMap move(1e-7 * cell.h_inv);
  std::vector<double> dissipated(n), kinetic(n), dissipated2(n), kinetic2(n), path0(n);
  for (std::size_t k = 0; k < n; ++k) path0[k] = 1e-7 * double(k);
  for (const char* kick : {"viscous", "local", "energy"}) {
    Model model;
    model.dt = 1e-7;
    if (kick == std::string("local")) model.damping.cundall_translation = model.damping.cundall_rotation = 0.2;
    const bool energy = kick == std::string("energy");
    for (const auto& [lo, hi] : {std::pair<std::size_t, std::size_t>{0, n}, {1, n}, {2, 11}, {5, 8}}) {
      Particles together = p, apart = p;
      std::vector<double> path_together = path0, path_apart = path0;
      const double v2 = integrate_velocities(model, together, lo, hi,
                                             energy ? KickEnergy{dissipated.data(), kinetic.data()} : KickEnergy{},
                                             &move, path_together.data());
      turn_orientations(model, together, path_together, lo, hi, kick_settles(model), true);
      const double v2_apart = integrate_velocities(
          model, apart, lo, hi, energy ? KickEnergy{dissipated2.data(), kinetic2.data()} : KickEnergy{});
      advance_positions(model, cell, apart, path_apart, lo, hi, kick_settles(model));
      EXPECT_EQ(v2, v2_apart) << kick;
      for (std::size_t k = 0; k < n; ++k) {
        EXPECT_TRUE(together.s[k] == apart.s[k]) << kick << " kick, particle " << k << " of [" << lo << ", " << hi << ")";
        EXPECT_TRUE(together.v[k] == apart.v[k] && together.angmom[k] == apart.angmom[k] &&
                    together.omega[k] == apart.omega[k] && together.q[k].coeffs() == apart.q[k].coeffs())
            << kick << " kick, particle " << k;
        EXPECT_EQ(path_together[k], path_apart[k]) << kick << " kick, particle " << k;
        if (k < lo || k >= hi) {
          EXPECT_TRUE(together.s[k] == p.s[k]) << "outside the range: " << k;
        }
      }
      std::size_t moving = 0;
      for (std::size_t k = lo; k < hi; ++k) moving += together.s[k] == p.s[k] ? 0 : 1;
      EXPECT_GE(moving + 3, hi - lo) << "test setup: all but the three still particles move";
    }
  }
}

namespace {

// The particles of the kick's lane tests: 27 (six groups of four and three left), spheres and
// spheroids mixed within groups of four, one group of four spheroids and one of spheres; with
// `all_bodies` also ellipsoids of three moments and turned bodies. Each lane its own damping
// factors: none in the first group, one value from particle 16 on (the lanes keep their factors).
// Particles 2, 9 and 17 have no force: their momenta settle (below 2^-540), or keep a normal
// component. Omega is a marker that the viscous kick leaves an ellipsoid's alone.
Particles kick_lane_particles(bool all_bodies) {
  const std::size_t n = 27;
  Particles p;
  for (std::size_t k = 0; k < n; ++k) {
    const bool spheroid = k % 5 == 2 || (k >= 12 && k < 16), three = all_bodies && k % 7 == 3;
    const Vec3 axes = three ? Vec3(1.5, 1.2, 1.0) : spheroid ? Vec3(1.5, 1.0, 1.0) : Vec3::Ones();
    p.add(static_cast<std::uint32_t>(k), spheroid || three ? ShapeKind::ellipsoid : ShapeKind::sphere,
          axes * kRmin * (1 + 0.1 * double(k % 7)), kRho, Vec3::Constant(0.5),
          all_bodies ? Quat(Quat(1, 0.1 * double(k), -0.2, 0.05 * double(k)).normalized()) : Quat::Identity());
  }
  const double factors[] = {0.0, 1e4, 3.7e5, 1e4, 2.1e6};
  for (std::size_t k = 0; k < n; ++k) {
    const double x = double(k) - 13.0;
    p.damping_translation[k] = k < 4 ? 0.0 : k >= 16 ? 3.7e5 : factors[k % 5];
    p.damping_rotation[k] = k < 4 ? 0.0 : k >= 16 ? 2.1e6 : factors[(k + 2) % 5];
    p.force[k] = Vec3(0.3 * x, -1e-3 * x * x, 2.5) * 1e-2;
    p.torque[k] = Vec3(-x, 0.5, 1e-2 * x * x) * 1e-7;
    p.v[k] = Vec3(1e-4 * x, 2e-3, -3e-4 * x);
    p.angmom.set(k, Vec3(2e-12, -1e-13 * x, 5e-12 + 1e-13 * x));
    p.omega[k] = Vec3(7, 8, 9);
  }
  for (const std::size_t k : {2u, 9u, 17u}) {
    p.force[k] = p.torque[k] = Vec3::Zero();
    p.v[k] = 0x1p-545 * Vec3(1, -1, 0.5);
    p.angmom.set(k, k == 9 ? Vec3(0x1p-545, 1e-9, 0) : Vec3(-0x1p-545, 0, 0x1p-546));
  }
  return p;
}

}  // namespace

// The viscous kick that tracks energy runs in the same lanes: its dissipation and kinetic energy
// are bit for bit the plain formula of one particle at a time (the energy identity, physics.md 12,
// with a sphere's omega = L / I and any other body's R I^-1 R^T L at its orientation), for any
// range (the last particles go one at a time), spheres, spheroids and ellipsoids of three moments
// mixed within a group of four, turned bodies, and momenta that settle; and the kick itself is the
// kick without the ledger.
TEST(Integrator, EnergyKickInLanesIsTheFormulaBitForBit) {
  const Particles p = kick_lane_particles(true);
  const std::size_t n = p.size();
  Model model;
  model.dt = 1e-7;
  std::size_t bodies = 0;
  for (const auto& [lo, hi] : {std::pair<std::size_t, std::size_t>{0, n}, {1, n}, {2, 11}, {5, 8}, {6, 26}}) {
    Particles tracked = p, plain = p;
    std::vector<double> dissipated(n, -1.0), kinetic(n, -1.0);
    const double v2max = integrate_velocities(model, tracked, lo, hi, KickEnergy{dissipated.data(), kinetic.data()});
    EXPECT_EQ(v2max, integrate_velocities(model, plain, lo, hi)) << "[" << lo << ", " << hi << ")";
    EXPECT_TRUE(tracked.v == plain.v && tracked.angmom == plain.angmom && tracked.omega == plain.omega);
    for (std::size_t k = 0; k < n; ++k) {
      if (k < lo || k >= hi) {
        EXPECT_TRUE(dissipated[k] == -1.0 && kinetic[k] == -1.0) << "outside the range: " << k;
        continue;
      }
      const Vec3 v_old = p.v[k], l_old = p.angmom[k], v = tracked.v[k], l = tracked.angmom[k];
      const bool sphere = p.shape[k] == ShapeKind::sphere;
      bodies += sphere ? 0 : 1;
      const auto spin = [&](const Vec3& x) {
        return sphere ? Vec3(x * p.inv_transverse_moment[k]) : angular_velocity(p.q[k], p.inertia[k], x);
      };
      const double mass = 1 / p.inv_mass[k];
      const Vec3 v_mid = 0.5 * (v_old + v), l_mid = 0.5 * (l_old + l);
      const double lost = (model.dt * p.force[k] - mass * (v - v_old)).dot(v_mid) +
                          (model.dt * p.torque[k] - (l - l_old)).dot(spin(l_mid));
      EXPECT_EQ(dissipated[k], lost) << "particle " << k << " of [" << lo << ", " << hi << ")";
      EXPECT_EQ(kinetic[k], 0.5 * mass * v.squaredNorm() + 0.5 * l.dot(spin(l)))
          << "particle " << k << " of [" << lo << ", " << hi << ")";
    }
  }
  EXPECT_GT(bodies, 20u) << "test setup: turned bodies in the lanes";
}

// The viscous kick runs four particles at a time in vector lanes, each lane with its own damping
// factors (kept from group to group while the damping is the same): bit for bit the plain formula
// of one particle at a time (DampedKick, the settling of
// SPEC 5.2, omega = L / I for a sphere; an ellipsoid's omega is left to the drift), for any range
// [lo, hi) (the lanes' groups start at lo; the last particles go one at a time), spheres and
// ellipsoids mixed within a group of four, and momenta that settle beside ones that do not.
TEST(Integrator, ViscousKickInLanesIsTheFormulaBitForBit) {
  const Particles p = kick_lane_particles(false);
  const std::size_t n = p.size();
  Model model;
  model.dt = 1e-7;
  for (const auto& [lo, hi] : {std::pair<std::size_t, std::size_t>{0, n}, {1, n}, {2, 11}, {5, 8}, {6, 26}}) {
    Particles q = p;
    const double v2max = integrate_velocities(model, q, lo, hi);
    double expected_v2max = 0;
    for (std::size_t k = 0; k < n; ++k) {
      if (k < lo || k >= hi) {
        EXPECT_TRUE(q.v[k] == p.v[k] && q.angmom[k] == p.angmom[k] && q.omega[k] == p.omega[k]) << k;
        continue;
      }
      const auto settle = [](const Vec3& x) { return x.cwiseAbs().maxCoeff() < 0x1p-540 ? Vec3::Zero() : x; };
      const Vec3 v = settle(damped_kick(p.v[k], p.force[k] * p.inv_mass[k], p.damping_translation[k], model.dt));
      const Vec3 l = settle(damped_kick(p.angmom[k], p.torque[k], p.damping_rotation[k], model.dt));
      const Vec3 omega = p.shape[k] == ShapeKind::sphere ? Vec3(l * p.inv_transverse_moment[k]) : p.omega[k];
      EXPECT_TRUE(q.v[k] == v) << "particle " << k << " of [" << lo << ", " << hi << ")";
      EXPECT_TRUE(q.angmom[k] == l) << "particle " << k << " of [" << lo << ", " << hi << ")";
      EXPECT_TRUE(q.omega[k] == omega) << "particle " << k << " of [" << lo << ", " << hi << ")";
      expected_v2max = std::max(expected_v2max, v.squaredNorm());
    }
    EXPECT_EQ(v2max, expected_v2max) << "[" << lo << ", " << hi << ")";
  }
}
