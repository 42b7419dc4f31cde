// Per-particle inertia scaling (docs/physics.md 5.6) against closed forms and known configurations:
// the multipliers and the step gain of a two-size system, a frictionless lattice in static
// equilibrium that stays in it under any scaling, the largest stable step of the vibrating
// lattice with and without scaling, the same equilibrium reached from a perturbed lattice with and without scaling, a
// binary collision that conserves the momentum of the scaled masses, and a uniform scaling that is a change of rate.
#include <gtest/gtest.h>

#include <algorithm>
#include <cmath>
#include <random>

#include "collision.hpp"
#include "qsdem/engine/damping/stage.hpp"
#include "qsdem/engine/model.hpp"
#include "qsdem/engine/step.hpp"
#include "qsdem/run/config.hpp"
#include "qsdem/run/phase.hpp"
#include "qsdem/run/phase_model.hpp"
#include "test_support.hpp"

using namespace qsdem;

namespace {

constexpr double kRho = 2650, kE = 7.8e10, kNu = 0.3;
using Target = InertiaScaling::Target;

InertiaScaling scaling(Target target, double factor, double cap) {
  InertiaScaling s;
  s.target = target, s.factor = factor, s.cap = cap;
  return s;
}

// The phase's Model as a run makes it (phase_model): fixed cell, the given friction, damping and
// inertia scaling (which `p` must have been given).
Model model_of(const Particles& p, const Mat3& h, const std::string& damping, double ratio, double friction,
               const InertiaScaling& s = {}) {
  Params params;
  params.material = {kRho, kE, kNu};
  Phase phase;
  phase.inertia = s;
  phase.friction = friction;
  phase.damping = {damping, ratio, DampedMotion::both};
  Model m = phase_model(params, phase, phase.controls, p, h);
  m.sort_particles = false;  // keep the order: the tests compare particle by particle
  return m;
}

// CsCl lattice of n^3 cells of side a: a big sphere (R_b) at each corner, a small one (R_s) at each
// centre, every big-big and big-small contact with overlap 2 um. Every particle is a centre of
// cubic symmetry: its contact forces cancel, so the lattice is in static equilibrium.
constexpr double kA = 1.998e-3, kRb = 1e-3;
const double kRs = kA * std::sqrt(3.0) / 2 - kRb + 2e-6;

State lattice(int n) {
  State st;
  st.cell = make_cell(n * kA * Mat3::Identity());
  std::uint32_t id = 0;
  for (int x = 0; x < n; ++x)
    for (int y = 0; y < n; ++y)
      for (int z = 0; z < n; ++z) {
        const Vec3 s(x, y, z);
        st.particles.add(id++, ShapeKind::sphere, Vec3::Constant(kRb), kRho, s / n, Quat::Identity());
        st.particles.add(id++, ShapeKind::sphere, Vec3::Constant(kRs), kRho, (s + Vec3::Constant(0.5)) / n,
                         Quat::Identity());
      }
  return st;
}

// Largest distance of a particle from where it started (m).
double largest_move(const State& st, const std::vector<Vec3>& s0) {
  double d = 0;
  for (std::size_t i = 0; i < s0.size(); ++i) d = std::max(d, (st.cell.h * (st.particles.s[i] - s0[i])).norm());
  return d;
}

}  // namespace

// mu_i = min(cap, (R*/R_i)^2), R* = R_max or F R_min; the step gain s = min_i R_i sqrt(mu_i) / R_min
// is then min(sqrt(cap), R_max/R_min) or min(sqrt(cap), F) (two sizes, F R_min <= R_max), and
// dt = c_t s t_c.
TEST(InertiaScaling, StepGrowsByThePredictedFactor) {
  const double ratio = kRb / kRs;  // 1.3656
  struct Case {
    InertiaScaling s;
    double mu_small, mu_big, gain;
  };
  const Case cases[] = {
      {InertiaScaling{}, 1, 1, 1},
      {scaling(Target::coarsest, 1, 100), ratio * ratio, 1, ratio},
      {scaling(Target::coarsest, 1, 1.5), 1.5, 1, std::sqrt(1.5)},
      {scaling(Target::factor, 1.2, 100), 1.44, 1, 1.2},
      {scaling(Target::factor, 3, 4), 4, 4, 2},  // (3 R_s / R_b)^2 = 4.83 on the big ones, capped
  };
  for (const Case& c : cases) {
    SCOPED_TRACE(std::to_string(static_cast<int>(c.s.target)) + " factor " + std::to_string(c.s.factor) + " cap " +
                 std::to_string(c.s.cap));
    State st = lattice(3);
    const Particles unscaled = st.particles;
    const Model before = model_of(st.particles, st.cell.h, "nd", 0.005, 0);
    scale_inertia(st.particles, c.s, kRho);
    const Particles& p = st.particles;
    for (std::size_t i = 0; i < p.size(); ++i) {
      const double mu = p.equiv_radius[i] > 1.1 * kRs ? c.mu_big : c.mu_small;
      EXPECT_NEAR(p.inertia_scale[i], mu, 1e-14 * mu);
      EXPECT_NEAR(p.mass[i], mu * unscaled.mass[i], 1e-14 * p.mass[i]);
      EXPECT_NEAR(p.inertia[i].x(), mu * unscaled.inertia[i].x(), 1e-14 * p.inertia[i].x());
      EXPECT_EQ(p.inv_mass[i], 1 / p.mass[i]);
      // Its own critical step 2 R_i sqrt(mu_i rho / E) is at least the scaled one.
      EXPECT_GE(critical_time({mu * kRho, kE, kNu}, p.equiv_radius[i]), c.gain * before.critical_time * (1 - 1e-14));
    }
    const Model after = model_of(p, st.cell.h, "nd", 0.005, 0, c.s);
    EXPECT_NEAR(step_gain(p), c.gain, 1e-14 * c.gain);
    EXPECT_NEAR(after.dt, 0.32 * c.gain * after.critical_time, 1e-14 * after.dt);
    EXPECT_EQ(after.critical_time, before.critical_time) << "t_c, the unit of eps', is the unscaled one";
    if (!c.s.on()) {
      EXPECT_EQ(after.dt, before.dt) << "unscaled: the step's bits unchanged";
    }
    // od: the scaled sample's highest frequency sqrt(E/rho) / (s R_min) (SPEC 5.6).
    const Model od = model_of(p, st.cell.h, "od", 0.1, 0, c.s);
    EXPECT_NEAR(std::get<GlobalMassDamping>(od.damping.law).alpha, 0.2 * std::sqrt(kE / kRho) / (c.gain * kRs),
                1e-12 * std::get<GlobalMassDamping>(od.damping.law).alpha);
  }
}

// A phase without scaling after one with it gives every particle back the solid's mass, to the bit.
TEST(InertiaScaling, OffRestoresTheSolidMassesExactly) {
  State st = lattice(3);
  const Particles solid = st.particles;
  scale_inertia(st.particles, scaling(Target::coarsest, 1, 100), kRho);
  EXPECT_NE(st.particles.mass, solid.mass);
  scale_inertia(st.particles, InertiaScaling{}, kRho);
  EXPECT_EQ(st.particles.mass, solid.mass);
  EXPECT_EQ(st.particles.inertia, solid.inertia);
  EXPECT_EQ(st.particles.inv_mass, solid.inv_mass);
  EXPECT_EQ(st.particles.inv_axial_moment, solid.inv_axial_moment);
  EXPECT_EQ(st.particles.inv_transverse_moment, solid.inv_transverse_moment);
  EXPECT_EQ(st.particles.inertia_scale, std::vector<double>(solid.size(), 1.0));
}

// The lattice in equilibrium stays there, to round-off, under every scaling at its own scaled
// step (nd damping at its scaled frequencies), over 3000 steps.
TEST(InertiaScaling, LatticeInStaticEquilibriumStaysThereUnderAnyScaling) {
  const qsdem_test::SingleThread one_thread;
  const double bound = 1e-6 * 2e-6;  // a millionth of the contacts' overlap (m)
  for (const InertiaScaling& s : {InertiaScaling{}, scaling(Target::coarsest, 1, 100), scaling(Target::factor, 1.2, 100),
                                  scaling(Target::factor, 3, 4)}) {
    SCOPED_TRACE("gain " + std::to_string(s.factor));
    State st = lattice(3);
    scale_inertia(st.particles, s, kRho);
    const Model m = model_of(st.particles, st.cell.h, "nd", 0.05, 0, s);
    assign_damping(m, st.particles);
    const std::vector<Vec3> s0 = st.particles.s;
    for (int k = 0; k < 3000; ++k) step(m, st);
    EXPECT_LT(largest_move(st, s0), bound);
    EXPECT_GT(st.pairs.size(), 0u);
  }
}

namespace {

// Whether the leapfrog (5.5) of the undamped, frictionless lattice, every particle moved by ~1 nm
// (a small vibration of its contacts), stays bounded at step dt over 1500 steps: a step beyond the
// highest mode's bound 2/omega_max makes the vibration grow exponentially past 100 nm.
bool stable(const InertiaScaling& s, double dt) {
  State st = lattice(3);
  for (std::size_t i = 0; i < st.particles.size(); ++i) {
    const double k = static_cast<double>(i);
    st.particles.s[i] += st.cell.h_inv * (1e-9 * Vec3(std::sin(1.3 * k), std::sin(2.1 * k + 1), std::sin(0.7 * k + 2)));
  }
  scale_inertia(st.particles, s, kRho);
  Model m = model_of(st.particles, st.cell.h, "none", 0, 0, s);
  m.dt = dt;
  assign_damping(m, st.particles);
  const std::vector<Vec3> s0 = st.particles.s;
  for (int k = 0; k < 1500; ++k) {
    step(m, st);
    if (!(largest_move(st, s0) < 1e-7)) return false;
  }
  return true;
}

// The largest stable step of the lattice (bisection to 1e-4 of it), from a stable guess up.
double largest_stable_step(const InertiaScaling& s, double guess) {
  EXPECT_TRUE(stable(s, guess)) << "the guess " << guess << " s is stable";
  double lo = guess, hi = guess;
  while (stable(s, hi)) lo = hi, hi *= 1.5;
  while (hi - lo > 1e-4 * lo) {
    const double mid = 0.5 * (lo + hi);
    (stable(s, mid) ? lo : hi) = mid;
  }
  return lo;
}

}  // namespace

// The stable step, measured on the vibrating lattice: the same mu = 4 on every particle (factor 3,
// cap 4) divides every eigenfrequency of M^-1 K by sqrt(mu), so the largest stable step grows by
// exactly s = 2. The scaling to the coarsest (mu = 1.86 on the small spheres only) has
// M <= M' <= mu_max M, so omega_max / sqrt(mu_max) <= omega'_max <= omega_max (Rayleigh quotient):
// the step grows by between 1 and sqrt(mu_max) = R_b/R_s, the per-particle estimate s; where in
// that range the lattice's modes put it is measured (1.146 of 1.366: the big spheres' 14 contacts
// bound it). The rule's step c_t t_c is far below the unscaled bound (4.8 t_c).
TEST(InertiaScaling, StableStepGrowsByThePredictedFactor) {
  const qsdem_test::SingleThread one_thread;
  const State st = lattice(3);
  const double t_c = model_of(st.particles, st.cell.h, "none", 0, 0).critical_time;
  const double plain = largest_stable_step(InertiaScaling{}, 0.32 * t_c);
  const double uniform = largest_stable_step(scaling(Target::factor, 3, 4), 0.32 * 2 * t_c);
  const double coarsest = largest_stable_step(scaling(Target::coarsest, 1, 100), 0.32 * (kRb / kRs) * t_c);
  std::printf("[ info ] largest stable step %.4g t_c; gain %.5f with mu = 4 on all, %.5f to the coarsest "
              "(estimate %.5f)\n", plain / t_c, uniform / plain, coarsest / plain, kRb / kRs);
  EXPECT_NEAR(uniform / plain, 2.0, 2e-3 * 2);
  EXPECT_GT(coarsest / plain, 1 + 1e-3) << "heavier small spheres lower the highest frequency";
  EXPECT_LE(coarsest / plain, kRb / kRs * (1 + 2e-4));
  EXPECT_GT(plain, 0.32 * t_c);
}

// Statics do not depend on mass (Cundall & Strack 1979; Thornton 2000): the perturbed lattice,
// damped (nd 30 %) to rest, reaches the same configuration, up to a rigid translation, with
// masses scaled or not, and the same stress.
TEST(InertiaScaling, PerturbedLatticeRelaxesToTheSameEquilibrium) {
  const qsdem_test::SingleThread one_thread;
  const auto relaxed = [](const InertiaScaling& s) {
    State st = lattice(3);
    st.particles.s[1] += st.cell.h_inv * Vec3(0.4e-6, -0.3e-6, 0.2e-6);
    st.particles.s[6] += st.cell.h_inv * Vec3(-0.2e-6, 0.1e-6, 0.3e-6);
    scale_inertia(st.particles, s, kRho);
    const Model m = model_of(st.particles, st.cell.h, "nd", 0.3, 0, s);
    assign_damping(m, st.particles);
    for (int k = 0; k < 20000; ++k) step(m, st);
    return st;
  };
  const State a = relaxed(InertiaScaling{}), b = relaxed(scaling(Target::factor, 3, 4));
  double force = 0, typical = 0, apart = 0;
  for (const State* st : {&a, &b})
    for (std::size_t i = 0; i < st->particles.size(); ++i) force = std::max(force, st->particles.force[i].norm());
  typical = a.stress.trace() / 3 * kA * kA;  // the mean stress on a cell face
  const Vec3 shift = a.cell.h * (b.particles.s[0] - a.particles.s[0]);
  for (std::size_t i = 0; i < a.particles.size(); ++i)
    apart = std::max(apart, (a.cell.h * (b.particles.s[i] - a.particles.s[i]) - shift).norm());
  std::printf("[ info ] residual force %.2e of the face force, configurations %.2e m apart\n", force / typical, apart);
  EXPECT_LT(force, 1e-9 * typical) << "both at rest";
  EXPECT_LT(apart, 1e-15) << "the same equilibrium (overlaps 2e-6 m)";
  EXPECT_NEAR(b.stress(0, 0), a.stress(0, 0), 1e-9 * a.stress(0, 0));
  EXPECT_NEAR(b.stress(0, 1), a.stress(0, 1), 1e-9 * a.stress(0, 0));
}

// Two spheres (1 and 1.3 mm) colliding obliquely with friction, no damping, in a fixed cell:
// the momentum of the scaled masses, sum mu_i m_i v_i, is conserved to round-off; that of the
// true masses is not (the dynamics is that of the scaled ones).
TEST(InertiaScaling, BinaryCollisionConservesTheScaledMomentum) {
  const qsdem_test::SingleThread one_thread;
  const double r1 = 1e-3, r2 = 1.3e-3;
  State st;
  st.cell = make_cell(0.03 * Mat3::Identity());
  const Vec3 n = Vec3(1, 0.5, -0.25).normalized(), t = n.cross(Vec3(0, 0, 1)).normalized();
  st.particles.add(0, ShapeKind::sphere, Vec3::Constant(r1), kRho, Vec3::Zero(), Quat::Identity());
  st.particles.add(1, ShapeKind::sphere, Vec3::Constant(r2), kRho, st.cell.h_inv * ((r1 + r2 + 1e-3 * r1) * n),
                   Quat::Identity());
  Particles& p = st.particles;
  const Particles solid = p;
  scale_inertia(p, scaling(Target::coarsest, 1, 100), kRho);
  EXPECT_NEAR(p.inertia_scale[0], 1.69, 1e-14);
  p.v[0] = 0.1 * n + 0.05 * t;
  p.v[1] = -0.2 * n - 0.04 * t;
  Model m = model_of(p, st.cell.h, "none", 0, 0.3, scaling(Target::coarsest, 1, 100));
  m.track_energy = true;  // keeps each pair's overlap
  const auto momentum = [&](const Particles& masses) { return masses.mass[0] * p.v[0] + masses.mass[1] * p.v[1]; };
  const Vec3 scaled0 = momentum(p), true0 = momentum(solid);
  ASSERT_GT(qsdem_test::step_through_collision(m, st, 100000), 0) << "touched";
  EXPECT_LT((momentum(p) - scaled0).norm(), 1e-13 * scaled0.norm());
  EXPECT_GT((momentum(solid) - true0).norm(), 1e-2 * true0.norm());
}

// physics.md 5.6: one mu for every particle is a change of rate and nothing else. With mu = 4 (a
// power of two: the factors are exact), a triaxial test at eps' is the unscaled test at 2 eps'
// step for step: the same positions, cell and stresses, velocities halved. A perturbed frictional
// lattice of equal spheres, damped by nd, od or local damping, axis 3 strained, axes 1 and 2 on
// the stress servo.
TEST(InertiaScaling, UniformScalingIsAChangeOfRate) {
  const qsdem_test::SingleThread one_thread;
  const double radius = 1e-3, a = 1.996e-3;
  const int n = 4;
  State base;
  base.cell = make_cell(n * a * Mat3::Identity());
  std::mt19937 rng(7);
  std::uniform_real_distribution<double> jitter(-3e-6, 3e-6);
  std::uint32_t id = 0;
  for (int x = 0; x < n; ++x)
    for (int y = 0; y < n; ++y)
      for (int z = 0; z < n; ++z) {
        const Vec3 at = a * Vec3(x + 0.5, y + 0.5, z + 0.5) + Vec3(jitter(rng), jitter(rng), jitter(rng));
        base.particles.add(id++, ShapeKind::sphere, Vec3::Constant(radius), kRho, base.cell.h_inv * at,
                           Quat::Identity());
      }
  const auto sheared = [&](const std::string& damping, double rate, const InertiaScaling& s, long steps) {
    State st = base;
    scale_inertia(st.particles, s, kRho);
    Params params;
    params.material = {kRho, kE, kNu};
    Phase phase;
    phase.inertia = s;
    phase.friction = 0.5;
    phase.damping = {damping, 0.05, DampedMotion::both};
    phase.controls.component[0] = phase.controls.component[1] = {ControlKind::stress, 3e6};
    phase.controls.component[2] = {ControlKind::strain_rate, rate};
    phase.controls.rate_factor = 10;
    Model m = phase_model(params, phase, phase.controls, st.particles, st.cell.h);
    m.sort_particles = false;
    assign_damping(m, st.particles);
    for (long k = 0; k < steps; ++k) step(m, st);
    return std::pair{m.dt, st};
  };
  const long steps = 4000;
  for (const std::string damping : {"nd", "od", "local"}) {
    SCOPED_TRACE(damping);
    const auto [dt_u, u] = sheared(damping, 1e-5, InertiaScaling{}, steps);
    const auto [dt_s, s] = sheared(damping, 5e-6, scaling(Target::factor, 2, 4), steps);
    ASSERT_EQ(dt_s, 2 * dt_u);
    ASSERT_EQ(s.particles.inertia_scale[0], 4.0);
    EXPECT_GT((u.cell.h - base.cell.h).norm(), 1e-3 * base.cell.h.norm()) << "the cell deformed";
    double dx = 0, dv = 0, vmax = 0;
    for (std::size_t i = 0; i < u.particles.size(); ++i) {
      dx = std::max(dx, (u.cell.h * (s.particles.s[i] - u.particles.s[i])).norm());
      dv = std::max(dv, (2 * s.particles.v[i] - u.particles.v[i]).norm());
      vmax = std::max(vmax, u.particles.v[i].norm());
    }
    std::printf("[ info ] %s, %ld steps: positions %.3g m apart, velocities %.3g of %.3g m/s, stress %.6g / %.6g Pa\n",
                damping.c_str(), steps, dx, dv, vmax, s.stress(2, 2), u.stress(2, 2));
    EXPECT_GT(vmax, 0);
    EXPECT_EQ(dx, 0);
    EXPECT_EQ(dv, 0);
    EXPECT_EQ((s.cell.h - u.cell.h).norm(), 0);
    EXPECT_EQ((s.stress - u.stress).norm(), 0);
  }
}
