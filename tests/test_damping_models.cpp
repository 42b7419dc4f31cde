// The damping models beyond the paper's (SPEC 6: local, stiffness, contact) against closed forms: the energy a
// one-degree-of-freedom oscillator loses per cycle, the restitution of a binary Hertz collision,
// and what a model leaves alone when damping.acts_on excludes a motion.
#include <gtest/gtest.h>

#include <array>
#include <cmath>
#include <cstdio>
#include <string>
#include <vector>

#include "case_errors.hpp"
#include "collision.hpp"
#include "qsdem/engine/damping/stage.hpp"
#include "qsdem/engine/integrator.hpp"
#include "qsdem/engine/model.hpp"
#include "qsdem/engine/step.hpp"
#include "qsdem/run/config.hpp"
#include "test_support.hpp"

using namespace qsdem;

namespace {

constexpr double kRho = 2650, kE = 7.8e10, kNu = 0.3;

// Damping ratio from the logarithmic decrement of a free oscillation's maxima (parabolic vertex
// through the three samples around each): xi = Lambda / sqrt(4 pi^2 + Lambda^2) (test_integrator.cpp).
double decrement_ratio(const std::vector<double>& x) {
  std::vector<double> p;
  for (std::size_t k = 1; k + 1 < x.size(); ++k) {
    if (!(x[k] > x[k - 1] && x[k] >= x[k + 1] && x[k] > 0)) continue;
    const double curv = x[k + 1] - 2 * x[k] + x[k - 1];
    p.push_back(curv < 0 ? x[k] - (x[k + 1] - x[k - 1]) * (x[k + 1] - x[k - 1]) / (8 * curv) : x[k]);
  }
  EXPECT_GE(p.size(), 3u) << "too few periods for a decrement";
  if (p.size() < 2) return NAN;
  const double lambda = std::log(p.front() / p.back()) / static_cast<double>(p.size() - 1);
  return lambda / std::sqrt(4 * pi * pi + lambda * lambda);
}

Model local_model(double alpha, double dt, DampedMotion acts_on = DampedMotion::both) {
  Model m;
  m.material = {kRho, kE, kNu};
  m.dt = dt;
  m.damping = resolve_damping("local", {alpha, m.material.wave_speed(), 0}, acts_on);
  return m;
}

// |x| at the turning points of a linear oscillator x'' = -w^2 x (one sphere, the spring force
// set here, the engine's kick with local damping alpha, then x += dt v), from x = 1 at rest.
std::vector<double> local_oscillator_extremes(double alpha, double w_dt, int half_cycles) {
  Particles p;
  p.add(0, ShapeKind::sphere, Vec3::Constant(1e-3), kRho, Vec3::Zero(), Quat::Identity());
  const double dt = 1e-7, w = w_dt / dt, k = p.mass[0] * w * w;
  const Model model = local_model(alpha, dt);
  assign_damping(model, p);
  double x = 1.0;
  std::vector<double> extremes{x};
  while (static_cast<int>(extremes.size()) <= half_cycles) {
    p.force[0] = Vec3(-k * x, 0, 0);
    const double before = p.v[0].x();
    integrate_velocities(model, p);
    x += dt * p.v[0].x();
    if (before != 0 && (before > 0) != (p.v[0].x() > 0)) extremes.push_back(std::abs(x));
  }
  return extremes;
}

}  // namespace

// Cundall's local damping on a linear oscillator (SPEC 6 `local`). The damped force is
// -k (1 + alpha) x while |x| grows and -k (1 - alpha) x while it shrinks, so each half-cycle is
// undamped motion on one of two springs and energy gives the amplitudes exactly:
// A_{n+1}^2 / A_n^2 = (1 - alpha) / (1 + alpha) per half-cycle, at any amplitude. Per cycle the
// oscillator keeps ((1 - alpha)/(1 + alpha))^2 of E = k A^2 / 2 and loses 4 alpha / (1 + alpha)^2 E,
// which is PFC's 4 alpha E to first order (viscous damping loses 4 pi xi E: alpha = pi xi).
// The leapfrog's turning points are sampled to (w dt)^2 / 8 relative and the sign of v is
// predicted at t (YADE's form), so the sign switches within a step of the true turning point
// where the work of one step is O((w dt)^2) of E: at w dt = 0.005, (w dt)^2 = 2.5e-5; measured
// 6.2e-5 of the ratio, allowed 8 (w dt)^2 = 2e-4.
// Against PFC's first-order 4 alpha: within its second-order term 8 alpha^2.
TEST(LocalDamping, LinearOscillatorLosesTheClosedFormEnergyPerCycle) {
  const qsdem_test::SingleThread one_thread;
  double worst = 0;
  for (const double alpha : {0.01, 0.05, 0.2, 0.5}) {
    const std::vector<double> a = local_oscillator_extremes(alpha, 0.005, 8);
    const double half = (1 - alpha) / (1 + alpha);
    for (std::size_t n = 0; n + 1 < a.size(); ++n) {
      const double kept = a[n + 1] * a[n + 1] / (a[n] * a[n]);
      worst = std::max(worst, std::abs(kept / half - 1));
      EXPECT_NEAR(kept, half, 2e-4 * half) << "alpha " << alpha << ", half-cycle " << n;
    }
    for (std::size_t n = 0; n + 2 < a.size(); n += 2) {
      const double lost = 1 - a[n + 2] * a[n + 2] / (a[n] * a[n]);  // of E = k A_n^2 / 2, one cycle
      EXPECT_NEAR(lost, 4 * alpha / ((1 + alpha) * (1 + alpha)), 4e-4) << "alpha " << alpha << ", cycle " << n / 2;
      EXPECT_NEAR(lost, 4 * alpha, 8 * alpha * alpha + 1e-4) << "PFC's 4 alpha E, to first order in alpha";
    }
  }
  std::printf("[ info ] energy kept per half-cycle: within %.2g of (1 - alpha)/(1 + alpha)\n", worst);
}

namespace {

// Two spheres closing head-on along n, the centre of mass at rest, frictionless Hertz-Mindlin,
// local damping alpha; stepped until apart. Returns the normal relative speed after over before.
double local_rebound(double alpha, double r1, double r2, double speed, double step_ratio) {
  Model m = local_model(alpha, 0);
  m.contact_law = make_contact_law(m.material, 0);
  m.r_min = std::min(r1, r2);
  m.critical_time = 2 * m.r_min * std::sqrt(kRho / kE);
  m.dt = step_ratio * m.critical_time;
  m.skin = 0.2 * m.r_min;
  State st;
  st.cell = make_cell(0.03 * Mat3::Identity());
  const Vec3 n = Vec3(1, 0.5, -0.25).normalized();
  st.particles.add(0, ShapeKind::sphere, Vec3::Constant(r1), kRho, Vec3::Zero(), Quat::Identity());
  st.particles.add(1, ShapeKind::sphere, Vec3::Constant(r2), kRho, st.cell.h_inv * ((r1 + r2 + 0.02 * r1) * n),
                   Quat::Identity());
  Particles& p = st.particles;
  const double m1 = p.mass[0], m2 = p.mass[1];
  p.v[0] = m2 / (m1 + m2) * speed * n;
  p.v[1] = -m1 / (m1 + m2) * speed * n;
  assign_damping(m, p);
  const double before = (p.v[1] - p.v[0]).dot(n);
  EXPECT_GT(qsdem_test::step_through_collision(m, st, 200000), 0) << "touched";
  return -(p.v[1] - p.v[0]).dot(n) / before;
}

}  // namespace

// The Hertz one: a binary collision with the centre of mass at rest. Both particles reverse at
// the same instant (their momenta are opposite), so the contact force is scaled by (1 + alpha)
// while the overlap grows and by (1 - alpha) while it shrinks, for any force law of the overlap:
// the elastic energy stored at the deepest overlap U gives (1 + alpha) U = m* v_in^2 / 2 and
// (1 - alpha) U = m* v_out^2 / 2, so e = sqrt((1 - alpha) / (1 + alpha)) exactly, at any speed and
// mass ratio. The leapfrog's error (the switch within a step of the turning point, the
// contact's start and end within a step): measured 5.1e-4 at most over these impacts (c_t = 0.32);
// allowed 1e-3.
TEST(LocalDamping, BinaryHertzCollisionReboundsWithTheClosedForm) {
  const qsdem_test::SingleThread one_thread;
  double worst = 0;
  for (const double alpha : {0.05, 0.2, 0.5})
    for (const double speed : {0.05, 0.5})
      for (const auto& [r1, r2] : {std::pair{1.0e-3, 1.0e-3}, std::pair{1.0e-3, 2.2e-3}}) {
        const double e = std::sqrt((1 - alpha) / (1 + alpha)), measured = local_rebound(alpha, r1, r2, speed, 0.32);
        worst = std::max(worst, std::abs(measured - e));
        EXPECT_NEAR(measured, e, 1e-3) << "alpha " << alpha << ", speed " << speed << ", r2 " << r2;
      }
  std::printf("[ info ] restitution within %.2g of sqrt((1 - alpha)/(1 + alpha))\n", worst);
}

// damping.acts_on with `local`: the kick of a sphere and a spheroid under a force and a torque.
// With translation only, the angular momentum is the undamped L + dt T to the bit, and with
// rotation only the velocity is v + dt F/m; the damped one differs from the undamped kick by
// exactly the closed form (alpha |F_k| against the velocity, per component).
TEST(LocalDamping, ActsOnLeavesTheOtherMotionUntouched) {
  for (const DampedMotion acts_on : {DampedMotion::translation, DampedMotion::rotation, DampedMotion::both}) {
    Particles p;
    p.add(0, ShapeKind::sphere, Vec3::Constant(1e-3), kRho, Vec3::Zero(), Quat::Identity());
    p.add(1, ShapeKind::ellipsoid, Vec3(1.5e-3, 1e-3, 1e-3), kRho, Vec3::Zero(),
          Quat(Eigen::AngleAxisd(0.4, Vec3(1, 2, 3).normalized())));
    const double dt = 1e-8, alpha = 0.3;
    const Model model = local_model(alpha, dt, acts_on);
    assign_damping(model, p);
    for (std::size_t k = 0; k < 2; ++k) {
      p.v[k] = Vec3(0.01, -0.02, 0.005);
      p.angmom.set(k, p.inertia[k].cwiseProduct(Vec3(30, 10, -20)));
      p.omega[k] = angular_velocity(p.q[k], p.inertia[k], p.angmom[k]);
      p.force[k] = Vec3(-2.0, -1.0, 3.0);  // against v in x, along v in y and z
      p.torque[k] = Vec3(-1e-4, 2e-4, 3e-4);
    }
    const std::vector<Vec3> v0 = p.v, l0 = p.angmom.interleaved(), w0 = p.omega;
    integrate_velocities(model, p);
    for (std::size_t k = 0; k < 2; ++k) {
      const Vec3 free_v = v0[k] + dt * (p.force[k] * p.inv_mass[k]);
      const Vec3 free_l = l0[k] + dt * p.torque[k];
      const auto damped = [&](const Vec3& f, const Vec3& v) {
        Vec3 out;
        for (int c = 0; c < 3; ++c) out[c] = f[c] - alpha * std::abs(f[c]) * (v[c] > 0 ? 1 : -1);
        return out;
      };
      if (acts_on == DampedMotion::rotation) {
        EXPECT_TRUE(p.v[k] == free_v) << "particle " << k << ": velocity undamped";
      } else {
        const Vec3 expect = v0[k] + dt * damped(p.force[k], v0[k]) * p.inv_mass[k];
        EXPECT_LE((p.v[k] - expect).norm(), 1e-14 * expect.norm()) << "particle " << k;
        EXPECT_GT((p.v[k] - free_v).norm(), 1e-3 * (free_v - v0[k]).norm()) << "damped";
      }
      if (acts_on == DampedMotion::translation) {
        EXPECT_TRUE(p.angmom[k] == free_l) << "particle " << k << ": spin undamped";
      } else {
        // The sign of omega (the sphere's L, the spheroid's omega at q(t)); none changes in a step.
        const Vec3 expect = l0[k] + dt * damped(p.torque[k], w0[k]);
        EXPECT_LE((p.angmom[k] - expect).norm(), 1e-14 * expect.norm()) << "particle " << k;
        EXPECT_GT((p.angmom[k] - free_l).norm(), 1e-3 * (free_l - l0[k]).norm()) << "damped";
      }
    }
  }
}

// The local kick, in vector lanes or with the energy terms, is the plain formula of SPEC 6 bit for
// bit: each component a (1 - alpha sign(a) sign(v)), with v the velocity predicted at t (v + dt/2
// a; a sphere's L + dt/2 M, an ellipsoid's omega at q(t)). Components of both signs and zeros, of
// the force and of the velocity, on spheres alone and with ellipsoids. With the energy terms, they
// are the identity of physics.md 12 bit for bit (in lanes of four, and the last particles of 35).
TEST(LocalDamping, KickIsThePlainSignFormulaBitForBit) {
  const auto sign = [](double x) { return x > 0 ? 1.0 : (x < 0 ? -1.0 : 0.0); };
  const auto damped = [&](const Vec3& f, const Vec3& v, double alpha) {
    Vec3 out;
    for (int c = 0; c < 3; ++c) out[c] = f[c] * (1 - alpha * (sign(f[c]) * sign(v[c])));
    return out;
  };
  const double values[] = {0.0, -0.0, 1.5, -2.25, 3e-3, -7e-5};
  for (const bool ellipsoids : {false, true}) {
    for (const bool track : {false, true}) {
      Particles p;
      const std::size_t n = 6 * 6;
      for (std::size_t k = 0; k < n; ++k) {
        const bool spheroid = ellipsoids && k % 3 == 1;
        p.add(static_cast<int>(k), spheroid ? ShapeKind::ellipsoid : ShapeKind::sphere,
              spheroid ? Vec3(1.5e-3, 1e-3, 1e-3) : Vec3::Constant(1e-3), kRho, Vec3::Zero(),
              Quat(Eigen::AngleAxisd(0.1 * double(k), Vec3(1, 2, 3).normalized())));
      }
      const double dt = 1e-6, alpha = 0.3;
      const Model model = local_model(alpha, dt, DampedMotion::both);
      assign_damping(model, p);
      for (std::size_t k = 0; k < n; ++k) {
        const double f = values[k % 6], v = values[k / 6];
        p.force[k] = Vec3(f, -f, v) * 1e-3;
        p.v[k] = Vec3(v, v, -f) * 1e-2;
        p.torque[k] = Vec3(f, v, -v) * 1e-9;
        p.angmom.set(k, Vec3(-v, v, f) * 1e-12);
        p.omega[k] = angular_velocity(p.q[k], p.inertia[k], p.angmom[k]);
      }
      const Particles before = p;
      std::vector<double> dissipated(n, -1.0), kinetic(n, -1.0);
      // Particles 1-35: groups of four, then three one at a time.
      integrate_velocities(model, p, 1, SIZE_MAX, track ? KickEnergy{dissipated.data(), kinetic.data()} : KickEnergy{});
      EXPECT_TRUE(dissipated[0] == -1.0 && kinetic[0] == -1.0) << "outside the range";
      for (std::size_t k = 1; k < n; ++k) {
        const Vec3 a = before.force[k] * before.inv_mass[k];
        const Vec3 v = before.v[k] + dt * damped(a, Vec3(before.v[k] + 0.5 * dt * a), alpha);
        const bool sphere = before.shape[k] == ShapeKind::sphere;
        const Vec3 spin = sphere ? Vec3(before.angmom[k] + 0.5 * dt * before.torque[k]) : before.omega[k];
        const Vec3 l = before.angmom[k] + dt * damped(before.torque[k], spin, alpha);
        EXPECT_TRUE(p.v[k] == v) << "particle " << k << " ellipsoids " << ellipsoids << " track " << track;
        EXPECT_TRUE(p.angmom[k] == l) << "particle " << k << " ellipsoids " << ellipsoids << " track " << track;
        if (!track) continue;
        // The energy identity (physics.md 12): what the damping took, and the kinetic energy after.
        const auto omega = [&](const Vec3& x) {
          return sphere ? Vec3(x * before.inv_transverse_moment[k])
                        : angular_velocity(before.q[k], before.inertia[k], x);
        };
        const double m = 1 / before.inv_mass[k];
        const Vec3 v_mid = 0.5 * (before.v[k] + v), l_mid = 0.5 * (before.angmom[k] + l);
        EXPECT_EQ(dissipated[k], (dt * before.force[k] - m * (v - before.v[k])).dot(v_mid) +
                                     (dt * before.torque[k] - (l - before.angmom[k])).dot(omega(l_mid)))
            << "particle " << k << " ellipsoids " << ellipsoids;
        EXPECT_EQ(kinetic[k], 0.5 * m * v.squaredNorm() + 0.5 * l.dot(omega(l))) << "particle " << k;
      }
    }
  }
}

// damping.model = "local" in both phases; its ratio is alpha, refused at 1 and above.
TEST(LocalDamping, CaseKeys) {
  const std::string base =
      "[material]\ndensity = \"2650 kg/m^3\"\nyoung_modulus = \"78 GPa\"\npoisson_ratio = 0.3\n"
      "[[sample.particles]]\ndiameter = \"2 mm\"\ncount = 100\n";
  const Params p = parse_case(base + "[damping]\nmodel = \"local\"\nratio = 0.1\n[compaction]\ndamping_model = "
                                     "\"local\"\ndamping_ratio = 0.7\n",
                              "case.toml");
  EXPECT_EQ(p.protocol[1].damping.model, "local");
  EXPECT_EQ(p.protocol[1].damping.ratio, 0.1);
  EXPECT_EQ(p.protocol[0].damping.model, "local");
  EXPECT_EQ(p.protocol[0].damping.ratio, 0.7);
  for (const char* bad : {"[damping]\nmodel = \"local\"\nratio = 1\n",
                          "[compaction]\ndamping_model = \"local\"\ndamping_ratio = \"120 %\"\n"}) {
    try {
      parse_case(base + bad, "case.toml");
      ADD_FAILURE() << "accepted " << bad;
    } catch (const InputError& e) {
      const std::string why = e.what();
      EXPECT_NE(why.find("case.toml:10"), std::string::npos) << why;
      EXPECT_NE(why.find("[0, 1)"), std::string::npos) << why;
    }
  }
  EXPECT_EQ(parse_case(base + "[damping]\nmodel = \"nd\"\nratio = 1.5\n", "case.toml").protocol[1].damping.ratio, 1.5)
      << "the viscous models' ratio is not bounded by 1";
}

namespace {

// Four equal spheres in a ring along x (a periodic cell of 4 spacings d = 2R - delta0), each
// pressed on its two neighbours with the overlap delta0; frictionless, the cell fixed.
struct Ring {
  Model model;
  State state;
  double spacing;
};

Ring preloaded_ring(const char* damping, double ratio, DampedMotion acts_on, double delta0_ratio) {
  constexpr double r = 1e-3;
  Ring ring;
  Model& m = ring.model;
  m.material = {kRho, kE, kNu};
  m.contact_law = make_contact_law(m.material, 0);
  m.r_min = r;
  m.critical_time = 2 * r * std::sqrt(kRho / kE);
  m.dt = 0.32 * m.critical_time;
  m.skin = 0.2 * r;
  m.damping = resolve_damping(damping, {ratio, m.material.wave_speed(), r}, acts_on);
  ring.spacing = 2 * r - delta0_ratio * r;
  Mat3 h = Mat3::Identity() * 10 * r;
  h(0, 0) = 4 * ring.spacing;
  ring.state.cell = make_cell(h);
  for (std::uint32_t k = 0; k < 4; ++k)
    ring.state.particles.add(k, ShapeKind::sphere, Vec3::Constant(r), kRho, Vec3((k + 0.5) / 4, 0.5, 0.5),
                             Quat::Identity());
  assign_damping(m, ring.state.particles);
  return ring;
}

// Moves sphere k by u_k along x.
void displace(Ring& ring, const std::array<double, 4>& u) {
  for (std::size_t k = 0; k < 4; ++k) ring.state.particles.s[k].x() += u[k] / ring.state.cell.h(0, 0);
}

}  // namespace

// `stiffness` damping (SPEC 6.3) on the ring's two modes along x. Each sphere has two contacts of
// stiffness k = 2 E* sqrt(R_e delta0) (R_e = R/2), so the model gives A = 2 xi_0 sqrt(2k/m). The
// mode (u, 0, -u, 0) has omega^2 = 2k/m: the ratio A/(2 omega) = xi_0 exactly; the mode
// (u, -u, u, -u) has omega^2 = 4k/m: xi_0 / sqrt(2). Measured from the logarithmic decrement of
// sphere 0 (test_integrator.cpp's method, whose discretisation error is (w dt)^2/24 ~ 2e-4 here)
// at an amplitude of 1 % of delta0, where Hertz's nonlinearity changes k and A by ~1 % within a
// cycle but their means by O(1e-4) (the two contacts' overlaps change in opposite senses).
// Allowed 0.5 % of the ratio.
TEST(StiffnessDamping, RingModesGetTheirClosedFormRatios) {
  const qsdem_test::SingleThread one_thread;
  constexpr double delta0 = 1e-3;  // of R
  for (const double xi0 : {0.01, 0.05}) {
    for (const int mode : {1, 2}) {
      Ring ring = preloaded_ring("stiffness", xi0, DampedMotion::both, delta0);
      const double u = 0.01 * delta0 * 1e-3;
      displace(ring, mode == 1 ? std::array<double, 4>{u, 0, -u, 0} : std::array<double, 4>{u, -u, u, -u});
      const double x0 = ring.state.particles.s[0].x() - u / ring.state.cell.h(0, 0);
      const double k = 2 * (kE / (2 * (1 - kNu * kNu))) * std::sqrt(0.5e-3 * delta0 * 1e-3);
      const double m = ring.state.particles.mass[0];
      const double omega = std::sqrt((mode == 1 ? 2 : 4) * k / m);
      const int steps = static_cast<int>(std::min(12.0, 3.0 / (2 * pi * xi0)) * 2 * pi / (omega * ring.model.dt));
      std::vector<double> x;
      for (int n = 0; n < steps; ++n) {
        step(ring.model, ring.state);
        x.push_back((ring.state.particles.s[0].x() - x0) * ring.state.cell.h(0, 0));
      }
      ASSERT_EQ(ring.state.pairs.size(), 4u);
      // A_i of the model at the preload, against the formula.
      const double a = ring.state.particles.damping_translation[0];
      EXPECT_NEAR(a, 2 * xi0 * std::sqrt(2 * k / m), 0.02 * a) << "A_i = 2 xi0 sqrt(sum k_n / m)";
      const double expected = mode == 1 ? xi0 : xi0 / std::sqrt(2.0), measured = decrement_ratio(x);
      EXPECT_NEAR(measured, expected, 5e-3 * expected) << "xi0 " << xi0 << ", mode " << mode;
      std::printf("[ info ] xi0 %g, mode %d: ratio %.5g, closed form %.5g (%+.2g)\n", xi0, mode, measured, expected,
                  measured / expected - 1);
    }
  }
}

// What `stiffness` leaves alone. A rattler (no contact) keeps its velocity and spin to the bit (it
// gets 0: SPEC 6.3). In the ring, spinning spheres with no friction feel no torque: with
// translation only damped their spins stay to the bit; with rotation damped they decay by the
// kick's factor ((1 - B dt/2)/(1 + B dt/2))^N, B = 2 xi_0 sqrt(2 k_t (R - delta0/2)^2 / I),
// k_t = 8 G* sqrt(R_e delta0) (the ring at rest: B is constant); with rotation only damped the
// ring's oscillation keeps its amplitude.
TEST(StiffnessDamping, ActsOnAndRattlers) {
  const qsdem_test::SingleThread one_thread;
  constexpr double delta0 = 1e-3, xi0 = 0.05;
  for (const DampedMotion acts_on : {DampedMotion::translation, DampedMotion::rotation, DampedMotion::both}) {
    Ring ring = preloaded_ring("stiffness", xi0, acts_on, delta0);
    Particles& p = ring.state.particles;
    p.add(4, ShapeKind::sphere, Vec3::Constant(1e-3), kRho, Vec3(0.5, 0.1, 0.1), Quat::Identity());  // a rattler
    p.v[4] = Vec3(1e-4, -2e-4, 0);
    for (std::size_t k = 0; k < 5; ++k) {
      p.angmom.set(k, p.inertia[k].cwiseProduct(Vec3(30, -10, 20)));
      p.omega[k] = p.angmom[k] * p.inv_transverse_moment[k];
    }
    const Vec3 rattler_x = p.s[4], rattler_l = p.angmom[4];
    const std::vector<Vec3> l0 = p.angmom.interleaved();
    constexpr int steps = 400;
    for (int n = 0; n < steps; ++n) step(ring.model, ring.state);
    ASSERT_EQ(ring.state.pairs.size(), 4u) << "the ring's contacts; none for the rattler";
    EXPECT_TRUE(p.v[4] == Vec3(1e-4, -2e-4, 0)) << "the rattler's velocity, undamped";
    EXPECT_TRUE(p.angmom[4] == rattler_l) << "the rattler's spin, undamped";
    EXPECT_NE(p.s[4], rattler_x);
    const double r = 1e-3, g_star = kE / (2 * (1 + kNu)) / (2 * (2 - kNu));
    const double kt = 8 * g_star * std::sqrt(0.5 * r * delta0 * r);
    const double arm = r - 0.5 * delta0 * r;
    for (std::size_t k = 0; k < 4; ++k) {
      if (acts_on == DampedMotion::translation) {
        EXPECT_TRUE(p.angmom[k] == l0[k]) << "sphere " << k << ": spin undamped";
      } else {
        const double b = 2 * xi0 * std::sqrt(2 * kt * arm * arm / p.inertia[k].x());
        const double decay = std::pow((1 - 0.5 * b * ring.model.dt) / (1 + 0.5 * b * ring.model.dt), steps);
        ASSERT_LT(decay, 0.9);
        EXPECT_LE((p.angmom[k] - decay * l0[k]).norm(), 1e-9 * l0[k].norm()) << "sphere " << k;
      }
    }
  }
  // Rotation only: the ring's translation oscillates undamped.
  Ring ring = preloaded_ring("stiffness", xi0, DampedMotion::rotation, delta0);
  const double u = 1e-2 * delta0 * 1e-3;
  displace(ring, {u, 0, -u, 0});
  const double x0 = ring.state.particles.s[0].x() - u / ring.state.cell.h(0, 0);
  std::vector<double> x;
  for (int n = 0; n < 3000; ++n) {
    step(ring.model, ring.state);
    x.push_back((ring.state.particles.s[0].x() - x0) * ring.state.cell.h(0, 0));
  }
  EXPECT_LT(std::abs(decrement_ratio(x)), 1e-4) << "translation undamped";
}

// `contact` damping (SPEC 6.4): the phase's law becomes hertz_mindlin_dashpot with damping ratio
// zeta = damping.ratio, and the particles get no damping. A head-on impact of two spheres then
// rebounds with the law's restitution e = exp(-pi zeta / sqrt(1 - zeta^2)) (beta = -zeta, the
// inverse of beta = ln e / sqrt(ln^2 e + pi^2)), up to the leapfrog's first-order error of the
// dashpot law itself (test_contact_dashpot.cpp: measured <= 0.0033 at c_t = 0.32; allowed 0.004).
TEST(ContactDampingModel, ImpactReboundsWithTheRestitutionOfItsRatio) {
  const qsdem_test::SingleThread one_thread;
  for (const double zeta : {0.05, 0.2, 0.45}) {
    Model m;
    m.material = {kRho, kE, kNu};
    const ContactSettings law = phase_contact_settings("contact", zeta, {});
    EXPECT_EQ(law.law, "hertz_mindlin_dashpot");
    EXPECT_EQ(law.value("damping_ratio"), zeta);
    EXPECT_EQ(phase_contact_settings("nd", zeta, {}).law, "hertz_mindlin") << "other models keep the case's law";
    m.contact_law = make_contact_law(m.material, 0.5, law);
    m.damping = resolve_damping("contact", {zeta, m.material.wave_speed(), 1e-3});
    const double r1 = 1e-3, r2 = 1.6e-3;
    m.r_min = r1;
    m.critical_time = 2 * r1 * std::sqrt(kRho / kE);
    m.dt = 0.32 * m.critical_time;
    m.skin = 0.2 * r1;
    State st;
    st.cell = make_cell(0.03 * Mat3::Identity());
    const Vec3 n = Vec3(1, 0.5, -0.25).normalized();
    st.particles.add(0, ShapeKind::sphere, Vec3::Constant(r1), kRho, Vec3::Zero(), Quat::Identity());
    st.particles.add(1, ShapeKind::sphere, Vec3::Constant(r2), kRho, st.cell.h_inv * ((r1 + r2 + 0.02 * r1) * n),
                     Quat::Identity());
    Particles& p = st.particles;
    p.v[0] = 0.1 * n;
    p.v[1] = -0.2 * n;
    assign_damping(m, p);
    EXPECT_EQ(p.damping_translation[0], 0.0);
    EXPECT_EQ(p.damping_rotation[1], 0.0);
    const double before = (p.v[1] - p.v[0]).dot(n);
    ASSERT_GT(qsdem_test::step_through_collision(m, st, 200000), 0) << "touched";
    const double e = std::exp(-pi * zeta / std::sqrt(1 - zeta * zeta)), measured = -(p.v[1] - p.v[0]).dot(n) / before;
    EXPECT_NEAR(measured, e, 0.004) << "zeta " << zeta;
    std::printf("[ info ] zeta %g: e %.5f, closed form %.5f\n", zeta, measured, e);
  }
}

// The keys: `contact` on the default law only, its ratio in [0, 1).
TEST(ContactDampingModel, CaseKeys) {
  const std::string base =
      "[material]\ndensity = \"2650 kg/m^3\"\nyoung_modulus = \"78 GPa\"\npoisson_ratio = 0.3\n"
      "[[sample.particles]]\ndiameter = \"2 mm\"\ncount = 100\n";
  const Params p = parse_case(base + "[damping]\nmodel = \"contact\"\nratio = \"20 %\"\n", "case.toml");
  EXPECT_EQ(p.protocol[1].damping.model, "contact");
  EXPECT_EQ(p.protocol[1].damping.ratio, 0.2);
  const auto error_of = [&](const std::string& extra) { return qsdem_test::error_of(base + extra); };
  const std::string ratio = error_of("[damping]\nmodel = \"contact\"\nratio = 1\n");
  EXPECT_NE(ratio.find("case.toml:10"), std::string::npos) << ratio;
  EXPECT_NE(ratio.find("[0, 1)"), std::string::npos) << ratio;
  const std::string both = error_of("[contact]\nlaw = \"hertz_mindlin_dashpot\"\nrestitution = 0.5\n"
                                    "[compaction]\ndamping_model = \"contact\"\n");
  EXPECT_NE(both.find("compaction.damping_model"), std::string::npos) << both;
  EXPECT_NE(both.find("not both"), std::string::npos) << both;
}
