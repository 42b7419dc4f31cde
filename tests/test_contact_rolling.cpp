// Rolling resistance (contact/hertz_mindlin_rolling.hpp, docs/physics.md 4.7.1): the elastic
// rolling moment of small rotations, its cap mu_r R_e F_n, the hysteresis of a closed rolling path
// against the elastic-perfectly-plastic loop, the dashpot's decay of a rolling oscillation, the
// forces left as Hertz-Mindlin's, and the case keys.
#include <gtest/gtest.h>

#include <cmath>
#include <string>
#include <vector>

#include "case_errors.hpp"
#include "qsdem/engine/contact/laws.hpp"
#include "qsdem/run/config.hpp"

using namespace qsdem;

namespace {

constexpr double kE = 7.8e10, kNu = 0.3;
double e_star() { return kE / (2 * (1 - kNu * kNu)); }
double g_star() { return kE / (2 * (1 + kNu)) / (2 * (2 - kNu)); }

ContactSettings rolling_settings(double mu_r, double stiffness = -1, double damping = -1) {
  ContactSettings s;
  s.law = "hertz_mindlin_rolling";
  s.values["rolling_friction"] = mu_r;
  if (stiffness > 0) s.values["rolling_stiffness"] = stiffness;
  if (damping >= 0) s.values["rolling_damping_ratio"] = damping;
  return s;
}

HertzMindlinRolling make_law(const ContactSettings& s, double friction = 0.5) {
  return std::get<HertzMindlinRolling>(make_contact_law({e_star(), g_star(), friction, s}));
}

// A contact of normal z, overlap delta held fixed (previous overlap the same), radius R_e, at rest
// but for the relative spin w; m* for the dashpot.
struct Contact {
  double delta = 1e-6, radius = 5e-4, mass = 1e-5;
  std::vector<double> history = std::vector<double>(6, 0.0);
  ContactOutput turn(const HertzMindlinRolling& law, const Vec3& w, double dt) {
    ContactInput c{};
    c.nz = 1, c.overlap = delta, c.radius = radius, c.mass = mass, c.previous_overlap = delta;
    c.wx = w.x(), c.wy = w.y(), c.wz = w.z();
    ContactOutput out;
    law.evaluate(c, dt, HistoryView{history.data()}, out);
    return out;
  }
  double kn() const { return 2 * e_star() * std::sqrt(radius * delta); }
  double fn() const { return 4.0 / 3.0 * e_star() * std::sqrt(radius) * std::pow(delta, 1.5); }
};

}  // namespace

// Below the cap the moment on j is -k_r theta_t, k_r = eta_k k_n R_e^2 with Ai et al.'s default
// eta_k = 2.25 mu_r^2, theta_t the rolling part of the relative rotation: the twist about n is not
// resisted. The forces are Hertz-Mindlin's, bit for bit.
TEST(RollingLaw, SmallRotationsAreElastic) {
  const double mu_r = 0.2;
  const HertzMindlinRolling law = make_law(rolling_settings(mu_r));
  Contact c;
  const double kr = 2.25 * mu_r * mu_r * c.kn() * c.radius * c.radius, cap = mu_r * c.radius * c.fn();
  const double dt = 1e-8;
  const Vec3 w(30, -20, 500);  // rad/s: a roll about (3, -2, 0) and a twist about z = n
  ContactOutput out;
  for (int k = 1; k <= 10; ++k) {
    out = c.turn(law, w, dt);
    const Vec3 expected = -kr * Vec3(30, -20, 0) * dt * k;
    ASSERT_LT(expected.norm(), cap) << "still elastic";
    EXPECT_NEAR(out.tx, expected.x(), 1e-12 * cap);
    EXPECT_NEAR(out.ty, expected.y(), 1e-12 * cap);
    EXPECT_EQ(out.tz, 0.0) << "no moment about the normal";
    EXPECT_EQ(out.slip_work, 0.0);
    EXPECT_NEAR(out.energy - 0.4 * c.fn() * c.delta, expected.squaredNorm() / (2 * kr), 1e-9 * out.energy);
  }
  // The forces and stiffnesses of Hertz-Mindlin on the same contact.
  const HertzMindlin hm = HertzMindlin::make({e_star(), g_star(), 0.5, rolling_settings(mu_r)});
  std::vector<double> shear(3, 0.0);
  ContactInput in{};
  in.nz = 1, in.overlap = c.delta, in.radius = c.radius, in.previous_overlap = c.delta;
  ContactOutput plain;
  hm.evaluate(in, dt, HistoryView{shear.data()}, plain);
  EXPECT_EQ(out.fz, plain.fz);
  EXPECT_EQ(out.kn, plain.kn);
  EXPECT_EQ(out.kt, plain.kt);
}

// Rolling on, the moment grows to the full mobilisation mu_r R_e F_n and stays there, pointing
// against the rolling; the slide dissipates the cap times the excess rotation, cap (|M_trial| -
// cap) / k_r, each step.
TEST(RollingLaw, MomentIsCappedAtFullMobilisation) {
  const double mu_r = 0.1, eta_k = 0.5;
  const HertzMindlinRolling law = make_law(rolling_settings(mu_r, eta_k));
  Contact c;
  const double kr = eta_k * c.kn() * c.radius * c.radius, cap = mu_r * c.radius * c.fn();
  const Vec3 w(0, 40, 0);
  const double dt = 2e-7, per_step = kr * 40 * dt;
  const int elastic_steps = static_cast<int>(std::floor(cap / per_step));
  ASSERT_GT(elastic_steps, 5);
  double dissipated = 0;
  for (int k = 1; k <= 3 * elastic_steps; ++k) {
    const ContactOutput out = c.turn(law, w, dt);
    const double m = std::hypot(out.tx, out.ty, out.tz);
    dissipated += out.slip_work;
    if (k <= elastic_steps) {
      EXPECT_NEAR(out.ty, -per_step * k, 1e-12 * cap);
    } else {
      EXPECT_NEAR(m, cap, 1e-12 * cap) << k;
      EXPECT_LT(out.ty, 0.0);
    }
  }
  // Rotated by theta = 3 n_e w dt in all: the slide took theta - cap/k_r at the cap.
  const double theta = 3 * elastic_steps * 40 * dt;
  EXPECT_NEAR(dissipated, cap * (theta - cap / kr), 1e-9 * cap * theta);
}

// A closed rolling path theta: 0 -> T -> -T -> T, T four times the elastic limit M_c / k_r: on the
// loop from T back to T the stored energy returns to its value, so the work of the rotation against
// the moment (the trapezoid of the moments at both ends of each step times the rotation) is the
// law's dissipation, and both are the elastic-perfectly-plastic loop's 4 M_c (T - M_c / k_r).
TEST(RollingLaw, ClosedRollingPathDissipatesTheHysteresisLoop) {
  const double mu_r = 0.1;
  const HertzMindlinRolling law = make_law(rolling_settings(mu_r));
  Contact c;
  const double kr = 2.25 * mu_r * mu_r * c.kn() * c.radius * c.radius, cap = mu_r * c.radius * c.fn();
  const double amplitude = 4 * cap / kr, dt = 1e-7;
  const int quarter = 2000;
  const double speed = amplitude / (quarter * dt);
  double loop_work = 0, loop_dissipation = 0, before = 0, stored_at_start = 0, stored_at_end = 0;
  int step = 0;
  for (const int leg : {1, -2, 2}) {  // in quarters: up to T, down to -T, up to T
    const double w = leg > 0 ? speed : -speed;
    for (int k = 0; k < std::abs(leg) * quarter; ++k, ++step) {
      const ContactOutput out = c.turn(law, Vec3(w, 0, 0), dt);
      if (step >= quarter) {
        loop_work += -0.5 * (before + out.tx) * w * dt;  // -M . dtheta: M the moment on j resists
        loop_dissipation += out.slip_work;
      }
      if (step == quarter - 1) stored_at_start = out.energy;
      stored_at_end = out.energy;
      before = out.tx;
    }
  }
  EXPECT_NEAR(stored_at_end, stored_at_start, 1e-9 * stored_at_start);
  const double loop = 4 * cap * (amplitude - cap / kr);
  EXPECT_NEAR(loop_dissipation, loop, 2e-3 * loop);
  EXPECT_NEAR(loop_work, loop_dissipation, 2e-3 * loop);
}

// The rolling dashpot on the inertia I* = m* R_e^2: a free rolling oscillation, I* theta'' = M,
// integrated with the symplectic Euler steps of the engine, decays between successive maxima by exp(-2 pi zeta/sqrt(1 - zeta^2)),
// its period 2 pi / (omega_0 sqrt(1 - zeta^2)), omega_0 = sqrt(k_r / I*).
TEST(RollingLaw, DashpotDampsARollingOscillationByItsRatio) {
  for (const double zeta : {0.05, 0.2}) {
    const double mu_r = 1;
    const HertzMindlinRolling law = make_law(rolling_settings(mu_r, 1e-3, zeta));
    Contact c;
    const double kr = 1e-3 * c.kn() * c.radius * c.radius, inertia = c.mass * c.radius * c.radius;
    const double omega0 = std::sqrt(kr / inertia), period = 2 * pi / omega0;
    const double dt = period / 4000;
    double spin = 1e-2 * omega0 * c.radius * c.fn() * mu_r / kr;  // amplitude ~1 % of the cap's angle
    double theta = 0, previous = 0;
    std::vector<double> peaks, times;
    for (int k = 1; k < 4 * 4000; ++k) {
      // The law turns its spring by spin dt (theta, the rotation it resists: the same sum here),
      // then the moment kicks the spin.
      const ContactOutput out = c.turn(law, Vec3(spin, 0, 0), dt);
      ASSERT_EQ(out.slip_work, 0.0) << "never at the cap";
      theta += spin * dt;
      spin += out.tx / inertia * dt;
      if (k > 1 && previous > 0 && spin <= 0) peaks.push_back(theta), times.push_back(k * dt);
      previous = spin;
    }
    ASSERT_GE(peaks.size(), 3u) << zeta;
    const double decay = std::exp(-2 * pi * zeta / std::sqrt(1 - zeta * zeta));
    EXPECT_NEAR(peaks[2] / peaks[1], decay, 2e-3 * decay) << zeta;  // the steps' error: 2e-4
    EXPECT_NEAR(times[2] - times[1], period / std::sqrt(1 - zeta * zeta), 2e-3 * period) << zeta;
  }
}

// The keys: rolling_friction required in (0, 1]; rolling_stiffness in (0, 100]; rolling_damping_ratio
// in [0, 1); each refused naming the key and its line.
TEST(RollingLaw, CaseKeysAreChecked) {
  const std::string base =
      "[material]\ndensity = \"2650 kg/m^3\"\nyoung_modulus = \"78 GPa\"\npoisson_ratio = 0.3\n"
      "[[sample.particles]]\ndiameter = \"2 mm\"\ncount = 100\n[contact]\nlaw = \"hertz_mindlin_rolling\"\n";
  const auto error_of = [&](const std::string& extra) { return qsdem_test::error_of(base + extra); };
  const Params p = parse_case(base + "rolling_friction = 0.1\nrolling_damping_ratio = \"30 %\"\n", "case.toml");
  EXPECT_EQ(p.contact.law, "hertz_mindlin_rolling");
  EXPECT_EQ(p.contact.value("rolling_friction"), 0.1);
  EXPECT_EQ(p.contact.value("rolling_damping_ratio"), 0.3);
  const HertzMindlinRolling law = make_law(p.contact);
  EXPECT_DOUBLE_EQ(law.rolling_stiffness, 2.25 * 0.01);
  EXPECT_NE(error_of("").find("needs rolling_friction"), std::string::npos) << error_of("");
  for (const auto& [bad, key] : {std::pair{"rolling_friction = 0\n", "contact.rolling_friction"},
                                 std::pair{"rolling_friction = 1.5\n", "contact.rolling_friction"},
                                 std::pair{"rolling_friction = 0.1\nrolling_stiffness = 0\n", "contact.rolling_stiffness"},
                                 std::pair{"rolling_friction = 0.1\nrolling_damping_ratio = 1\n",
                                           "contact.rolling_damping_ratio"}}) {
    const std::string why = error_of(bad);
    EXPECT_NE(why.find(key), std::string::npos) << why;
    EXPECT_NE(why.find("out of range"), std::string::npos) << why;
  }
  const std::string foreign = error_of("rolling_friction = 0.1\nrestitution = 0.5\n");
  EXPECT_NE(foreign.find("not a key of contact law \"hertz_mindlin_rolling\""), std::string::npos) << foreign;
}
