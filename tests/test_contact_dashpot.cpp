// Hertz-Mindlin with viscous dashpots (contact/hertz_mindlin_dashpot.hpp, SPEC 6 `contact`): the
// force against a hand computation, the restitution coefficient of head-on impacts through the
// whole engine, and the case keys.
#include <gtest/gtest.h>

#include <cmath>
#include <string>

#include "case_errors.hpp"
#include "collision.hpp"
#include "qsdem/engine/contact/laws.hpp"
#include "qsdem/engine/model.hpp"
#include "qsdem/engine/step.hpp"
#include "qsdem/run/config.hpp"
#include "test_support.hpp"

using namespace qsdem;

namespace {

constexpr double kRho = 2650, kE = 7.8e10, kNu = 0.3;
double e_star() { return kE / (2 * (1 - kNu * kNu)); }
double g_star() { return kE / (2 * (1 + kNu)) / (2 * (2 - kNu)); }
double sphere_mass(double r) { return kRho * 4.0 / 3.0 * pi * r * r * r; }
// beta of a restitution coefficient (LIGGGHTS, LAMMPS): ln e / sqrt(ln^2 e + pi^2).
double beta_of(double e) { return std::log(e) / std::sqrt(std::log(e) * std::log(e) + pi * pi); }

ContactSettings dashpot_settings(const char* key, double value) {
  ContactSettings s;
  s.law = "hertz_mindlin_dashpot";
  s.values[key] = value;
  return s;
}

HertzMindlinDashpot make_law(const ContactSettings& s, double friction) {
  return std::get<HertzMindlinDashpot>(make_contact_law({e_star(), g_star(), friction, s}));
}

// Two spheres closing head-on along n at relative speed `speed` (j towards i), in a big cell,
// with the dashpot law of restitution e, frictionless, undamped otherwise; stepped until they are
// apart again. Returns the relative normal speed after over before, and the impact's steps.
std::pair<double, int> rebound(double e, double r1, double r2, double speed, double step_ratio) {
  Model m;
  m.material = {kRho, kE, kNu};
  m.contact_law = make_contact_law(m.material, 0, dashpot_settings("restitution", e));
  m.r_min = std::min(r1, r2);
  m.critical_time = 2 * m.r_min * std::sqrt(kRho / kE);
  m.dt = step_ratio * m.critical_time;
  m.skin = 0.2 * m.r_min;
  State st;
  st.cell = make_cell(0.03 * Mat3::Identity());
  const Vec3 n = Vec3(1, 0.5, -0.25).normalized();
  const double gap = 0.02 * r1;
  st.particles.add(0, ShapeKind::sphere, Vec3::Constant(r1), kRho, Vec3::Zero(), Quat::Identity());
  st.particles.add(1, ShapeKind::sphere, Vec3::Constant(r2), kRho, st.cell.h_inv * ((r1 + r2 + gap) * n),
                   Quat::Identity());
  st.particles.v[0] = 0.3 * speed * n;  // a moving centre of mass
  st.particles.v[1] = -0.7 * speed * n;
  const double before = (st.particles.v[1] - st.particles.v[0]).dot(n);
  const long contact_steps = qsdem_test::step_through_collision(m, st, 200000);
  EXPECT_GT(contact_steps, 0) << "touched";
  return {-(st.particles.v[1] - st.particles.v[0]).dot(n) / before, static_cast<int>(contact_steps)};
}

// The same impact as a plain one-dimensional leapfrog of the relative normal motion, written from
// the law's formulas: overlap delta, closing speed u (< 0), reduced mass m*; at each step the force
// at the current overlap with the dashpot on the velocity of half a step before, then the kick and
// the drift (the engine's order, step.cpp). Returns the rebound's e and its contact steps.
std::pair<double, int> rebound_1d(double e, double r1, double r2, double speed, double step_ratio) {
  const double r_min = std::min(r1, r2), dt = step_ratio * 2 * r_min * std::sqrt(kRho / kE);
  const double m = sphere_mass(r1) * sphere_mass(r2) / (sphere_mass(r1) + sphere_mass(r2));
  const double re = r1 * r2 / (r1 + r2), dashpot = -2 * std::sqrt(5.0 / 6.0) * beta_of(e);
  double gap = 0.02 * r1, u = -speed;
  int contact_steps = 0;
  bool touched = false;
  for (int k = 0; k < 200000; ++k) {
    const double delta = -gap;
    double f = 0;
    if (delta > 0) {
      const double a = std::sqrt(re * delta), kn = 2 * e_star() * a;
      f = 4.0 / 3.0 * e_star() * a * delta - dashpot * std::sqrt(kn * m) * u;
      ++contact_steps;
    }
    touched = touched || delta > 0;
    u += f / m * dt;
    gap += u * dt;
    if (touched && !(delta > 0)) break;
  }
  return {u / speed, contact_steps};
}

}  // namespace

// The law on one contact against the formulas of contact/hertz_mindlin_dashpot.hpp computed here:
// a sticking contact (dashpots in both directions) and a sliding one (the spring capped at
// mu |F_n|, no tangential dashpot); the damping ratio zeta = -beta gives the same law.
TEST(DashpotLaw, ForceMatchesHandComputation) {
  const double r1 = 1.0e-3, r2 = 1.6e-3, m1 = sphere_mass(r1), m2 = sphere_mass(r2);
  const double mstar = m1 * m2 / (m1 + m2), re = r1 * r2 / (r1 + r2), delta = 2e-6, dt = 1e-7, e = 0.4;
  ContactGeometry g;
  g.normal = Vec3(0.36, -0.48, 0.8);  // unit
  g.overlap = delta;
  g.radius = re;
  g.arm_i = g.arm_j = Vec3::Zero();
  const Vec3 t1 = Vec3(0.8, 0.6, 0), t2 = g.normal.cross(t1);  // tangent plane
  const Vec3 v = -0.02 * g.normal + 0.015 * t1 - 0.01 * t2;     // closing, and sliding sideways
  const Vec3 spring0 = 0.3 * t1 + 0.2 * t2;                      // stored, in the tangent plane (N)

  const double a = std::sqrt(re * delta), kn = 2 * e_star() * a, kt = 8 * g_star() * a;
  const double gamma_n = -2 * std::sqrt(5.0 / 6.0) * beta_of(e) * std::sqrt(kn * mstar);
  const double gamma_t = -2 * std::sqrt(5.0 / 6.0) * beta_of(e) * std::sqrt(kt * mstar);
  const double vn = v.dot(g.normal);
  const Vec3 vt = v - vn * g.normal;
  const double fn = 4.0 / 3.0 * e_star() * std::sqrt(re) * std::pow(delta, 1.5) - gamma_n * vn;
  const Vec3 spring = spring0 - kt * dt * vt;
  ASSERT_GT(gamma_n, 0);
  ASSERT_GT(fn, 0);

  for (const double mu : {10.0, 0.05}) {
    const bool sliding = spring.norm() > mu * fn;
    ASSERT_EQ(sliding, mu < 1) << "the two cases";
    const Vec3 stored = sliding ? Vec3(spring * (mu * fn / spring.norm())) : spring;
    const Vec3 expected = fn * g.normal + (sliding ? stored : Vec3(spring - gamma_t * vt));
    for (const ContactSettings& s :
         {dashpot_settings("restitution", e), dashpot_settings("damping_ratio", -beta_of(e))}) {
      Vec3 h = spring0;
      const ContactOutput out = evaluate_contact(make_law(s, mu), g, v, Vec3::Zero(), mstar, dt, h.data());
      const Vec3 f(out.fx, out.fy, out.fz);
      EXPECT_LE((f - expected).norm(), 1e-13 * expected.norm()) << "mu " << mu << ", " << s.values.begin()->first;
      EXPECT_LE((h - stored).norm(), 1e-13 * stored.norm()) << "the stored spring, mu " << mu;
      EXPECT_NEAR(out.kn, kn, 1e-14 * kn);
      EXPECT_NEAR(out.kt, kt, 1e-14 * kt);
      const double energy = 8.0 / 15.0 * e_star() * std::sqrt(re) * std::pow(delta, 2.5) +
                            stored.squaredNorm() / (2 * kt);
      EXPECT_NEAR(out.energy, energy, 1e-13 * energy);
    }
  }
}

// e = 1 (no dashpot) is Hertz-Mindlin, to the bit.
TEST(DashpotLaw, RestitutionOneIsHertzMindlin) {
  ContactGeometry g;
  g.normal = Vec3(0.6, 0, 0.8);
  g.overlap = 3e-6;
  g.radius = 0.7e-3;
  g.arm_i = g.arm_j = Vec3::Zero();
  const Vec3 v(0.01, -0.02, 0.005);
  for (const double mu : {0.5, 0.01}) {
    Vec3 h1(0.2, 0.1, -0.15), h2 = h1;
    const ContactOutput a = evaluate_contact(make_law(dashpot_settings("restitution", 1), mu), g, v, Vec3::Zero(),
                                             1e-5, 1e-7, h1.data());
    const ContactOutput b =
        evaluate_contact(HertzMindlin{e_star(), g_star(), mu}, g, v, Vec3::Zero(), 0, 1e-7, h2.data());
    EXPECT_TRUE(Vec3(a.fx, a.fy, a.fz) == Vec3(b.fx, b.fy, b.fz)) << "mu " << mu;
    EXPECT_TRUE(h1 == h2) << "mu " << mu;
  }
}

// A head-on impact of two spheres through the whole engine rebounds with the requested e, for
// any impact speed and masses: the model's damping scales as delta^(1/4), so its restitution is
// e exactly (the impact's equation in its own units, x'' + sqrt(5) |beta| x^(1/4) x' + x^(3/2) = 0,
// integrated numerically, gives e to 5e-7). The engine's leapfrog takes the impact in 45-140
// steps and its dashpot reads the velocity of half a step before (v(t - dt/2)): a first-order
// error in dt. The exact reference of the engine's e is the plain one-dimensional leapfrog of the
// same impact (rebound_1d): the same contact steps and e to 1e-9 (measured 1.7e-11 at most: the
// engine's positions are rounded in the cell's fractional coordinates, ~1e-17 m against overlaps
// of ~1e-7 m). Against the law's e: |e_measured - e| <= 0.0033 at c_t = 0.32 and <= 0.0010 at c_t
// = 0.08 (largest at e = 0.2, the leapfrog's error); allowed 0.004 and 0.0015.
TEST(DashpotLaw, HeadOnImpactReboundsWithTheRestitutionCoefficient) {
  const qsdem_test::SingleThread one_thread;
  for (const double e : {0.2, 0.5, 0.9})
    for (const double speed : {0.05, 0.5})
      for (const auto& [r1, r2] : {std::pair{1.0e-3, 1.0e-3}, std::pair{1.0e-3, 2.2e-3}})
        for (const auto& [step_ratio, tolerance] : {std::pair{0.32, 0.004}, std::pair{0.08, 0.0015}}) {
          const auto [measured, steps] = rebound(e, r1, r2, speed, step_ratio);
          const auto [leapfrog, leapfrog_steps] = rebound_1d(e, r1, r2, speed, step_ratio);
          EXPECT_EQ(steps, leapfrog_steps) << "e " << e << ", speed " << speed << ", r2 " << r2;
          EXPECT_NEAR(measured, leapfrog, 1e-9) << "e " << e << ", speed " << speed << ", r2 " << r2 << ", c_t "
                                                << step_ratio;
          EXPECT_GT(steps, 40) << "the impact spans steps";
          EXPECT_NEAR(measured, e, tolerance) << "e " << e << ", speed " << speed << ", r2 " << r2 << ", c_t "
                                              << step_ratio << ", " << steps << " steps";
        }
}

// The keys: exactly one of restitution in (0, 1] and damping_ratio in [0, 1), named in the message.
TEST(DashpotLaw, CaseKeysAreChecked) {
  const std::string base =
      "[material]\ndensity = \"2650 kg/m^3\"\nyoung_modulus = \"78 GPa\"\npoisson_ratio = 0.3\n"
      "[[sample.particles]]\ndiameter = \"2 mm\"\ncount = 100\n[contact]\nlaw = \"hertz_mindlin_dashpot\"\n";
  const auto error_of = [&](const std::string& extra) { return qsdem_test::error_of(base + extra); };
  const Params p = parse_case(base + "restitution = 0.5\n", "case.toml");
  EXPECT_EQ(p.contact.law, "hertz_mindlin_dashpot");
  EXPECT_EQ(p.contact.value("restitution"), 0.5);
  EXPECT_EQ(parse_case(base + "damping_ratio = \"20 %\"\n", "case.toml").contact.value("damping_ratio"), 0.2);
  EXPECT_NE(error_of("").find("needs restitution"), std::string::npos) << error_of("");
  const std::string both = error_of("restitution = 0.5\ndamping_ratio = 0.1\n");
  EXPECT_NE(both.find("not both"), std::string::npos) << both;
  for (const char* bad :
       {"restitution = 0\n", "restitution = 1.5\n", "damping_ratio = 1\n", "damping_ratio = -0.1\n"}) {
    const std::string why = error_of(bad);
    EXPECT_NE(why.find("case.toml:10"), std::string::npos) << why;
    EXPECT_NE(why.find("out of range"), std::string::npos) << why;
  }
  const std::string other = error_of("stiffness = 0.5\n");
  EXPECT_NE(other.find("contact.stiffness"), std::string::npos) << other;
  EXPECT_NE(other.find("restitution"), std::string::npos) << "names the law's keys: " << other;
}
