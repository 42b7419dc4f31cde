// Loading paths (docs/loading-paths.md): the constraint each path holds, checked over a whole phase
// of its shipped example, and the cell control behind it.
#include <gtest/gtest.h>
#include <signal.h>
#include <unistd.h>

#include <Eigen/LU>
#include <algorithm>
#include <cmath>
#include <cstdlib>
#include <chrono>
#include <cstdio>
#include <filesystem>
#include <fstream>
#include <nlohmann/json.hpp>
#include <numbers>
#include <sstream>
#include <string>
#include <thread>
#include <vector>

#include "qsdem/engine/cell.hpp"
#include "qsdem/engine/model.hpp"
#include "qsdem/engine/servo.hpp"
#include "qsdem/engine/state.hpp"
#include "qsdem/run/config.hpp"
#include "test_support.hpp"

using namespace qsdem;
namespace fs = std::filesystem;
using qsdem_test::Csv;
using qsdem_test::read_csv;
using qsdem_test::slurp;

namespace {

const fs::path examples = fs::path(QSDEM_SOURCE_DIR) / "examples";

fs::path scratch(const std::string& name) {
  const fs::path d = fs::temp_directory_path() / ("qsdem-paths-" + std::to_string(::getpid())) / name;
  fs::remove_all(d);
  fs::create_directories(d.parent_path());
  return d;
}

// Runs an example case (with overrides) to its end in a fresh directory.
fs::path run_example(const std::string& file, const std::string& dir_name, const std::vector<std::string>& set = {}) {
  const fs::path dir = scratch(dir_name);
  std::string cmd = std::string("'") + QSDEM_BINARY + "' run '" + (examples / file).string() + "' --out '" +
                    dir.string() + "' --threads 1 --quiet";
  for (const std::string& s : set) cmd += " --set '" + s + "'";
  cmd += " > '" + dir.string() + ".log' 2>&1";
  EXPECT_EQ(std::system(cmd.c_str()), 0) << cmd << "\n" << slurp(dir.string() + ".log");
  return dir;
}

}  // namespace

// The constant-volume components' rate (servo.hpp, SPEC 3.7): with an axial rate and a simple
// shear rate set, the two lateral components take one rate r with det(I + dt L) = 1 to round-off,
// r = -L33/2 to first order; 10^4 steps of h <- (I + dt L) h then keep det h to 1e-12 relative
// (measured 1.9e-13, the round-off of the steps), where the rate form L11 = L22 = -L33/2 alone
// loses 3/4 (dt L33)^2 per step (8.3e-7 over them).
TEST(LoadingPaths, ConstantVolumeRateKeepsTheCellVolume) {
  Model m;
  m.dt = 1e-7;
  m.control[2] = {ControlKind::strain_rate, 1e2, 1.0};  // de/dt = 100 /s: dt L33 = -1e-5
  m.control[0].kind = m.control[1].kind = ControlKind::constant_volume;
  m.control[4] = {ControlKind::strain_rate, 50.0, 0.0};  // L13
  State st;
  st.cell = make_cell(Mat3::Identity());
  const double v0 = st.cell.volume;
  double rate_form = 1;  // the volume ratio the rate form would give
  for (int n = 0; n < 10000; ++n) {
    servo_update(m, st);
    const Mat3& L = st.cell.L;
    ASSERT_EQ(L(0, 0), L(1, 1));
    EXPECT_NEAR((Mat3::Identity() + m.dt * L).determinant(), 1.0, 4e-16) << "step " << n;
    EXPECT_NEAR(L(0, 0), -0.5 * L(2, 2), 2 * m.dt * L(2, 2) * L(2, 2)) << "step " << n;
    EXPECT_EQ(L(0, 2), 50.0);
    const double a = m.dt * L(2, 2);
    rate_form *= (1 - a / 2) * (1 - a / 2) * (1 + a);
    deform(st.cell, m.dt);
  }
  EXPECT_NEAR(st.cell.volume / v0, 1.0, 1e-12);
  EXPECT_GT(1 - rate_form, 5e-7) << "the rate form's loss this test tells apart";
  EXPECT_NEAR(1 - st.cell.h(2, 2), 10000 * 1e-5, 1e-12) << "the axial strain is the strain-rate component's";
}

// A constant_volume list is checked: normal components only, one control per component, and
// something else must drive the cell.
TEST(LoadingPaths, ConstantVolumeKeysAreChecked) {
  const std::string head = R"(
[material]
density = "2650 kg/m^3"
young_modulus = "78 GPa"
poisson_ratio = 0.3
[[sample.particles]]
diameter = "2 mm"
count = 10
[[phase]]
friction = 0.5
stop = { steps = 10 }
)";
  const struct {
    std::string text, expected;
  } cases[] = {
      {"constant_volume = [\"11\", \"13\"]\nstrain_rate = { 33 = 1e-5 }\n", "must be \"11\", \"22\" or \"33\""},
      {"constant_volume = [\"11\", \"22\"]\nstrain_rate = { 22 = 1e-5 }\n", "one control per component"},
      {"constant_volume = [\"11\", \"11\"]\nstrain_rate = { 33 = 1e-5 }\n", "listed twice"},
      {"constant_volume = [\"11\", \"22\"]\n", "another component must be driven"},
      {"constant_volume = []\nstrain_rate = { 33 = 1e-5 }\n", "at least one normal component"},
      {"constant_volume = [\"11\", \"22\"]\nstrain_rate = { 33 = 1e-5 }\n"
       "controller = { kind = \"schedule\", component = \"11\", at_sample = [1], values = [\"1 kPa\"] }\n",
       "does not drive this component by a value"},
  };
  for (const auto& c : cases) {
    std::string what = "(no error)";
    try {
      parse_case(head + c.text, "bad.toml");
    } catch (const InputError& e) {
      what = e.what();
    }
    EXPECT_NE(what.find("bad.toml"), std::string::npos) << what;
    EXPECT_NE(what.find("key 'phase.0."), std::string::npos) << "the key is not named: " << what;
    EXPECT_NE(what.find(c.expected), std::string::npos) << "expected '" << c.expected << "' in: " << what;
  }
}

// examples/undrained-triaxial.toml: every row of the undrained phase keeps the volume of its start,
// |V/V0 - 1| <= 1e-11 (measured 2.5e-13 over its 3126 steps: round-off; the rate form would lose
// 3/4 e1 c_t eps' = 9.6e-8 by e1 = 2 %), reaches e1 = 2 %, and its dp_Pa column is p minus the
// mean stress at the phase's start (the compaction's last row).
TEST(LoadingPaths, UndrainedTriaxialHoldsTheVolume) {
  const fs::path dir = run_example("undrained-triaxial.toml", "undrained");
  const Csv s = read_csv(dir / "series.csv");
  const Csv c = read_csv(dir / "compaction.csv");
  ASSERT_EQ(s.rows.size(), 100u);
  ASSERT_FALSE(c.rows.empty());
  const double p0 = c.at(c.rows.size() - 1, "p_Pa");
  for (std::size_t k = 0; k < s.rows.size(); ++k) {
    EXPECT_LE(std::abs(s.at(k, "ev")), 1e-11) << "row " << k;
    EXPECT_NEAR(s.at(k, "dp_Pa"), s.at(k, "p_Pa") - p0, 1e-9 * s.at(k, "p_Pa")) << "row " << k;
  }
  EXPECT_NEAR(s.at(s.rows.size() - 1, "e1"), 0.02, 0.32 * 2e-5);
  // Loaded at constant volume the mean stress changes (the sample's dilatancy turned into
  // stress): a path that kept p would not be an undrained one.
  EXPECT_GT(std::abs(s.at(s.rows.size() - 1, "dp_Pa")), 0.1 * p0);
  EXPECT_TRUE(s.has("dp_Pa"));
  EXPECT_FALSE(c.has("dp_Pa")) << "a file no constant-volume phase writes to has no dp_Pa column";
}

// examples/simple-shear.toml: gamma_13 grows at the given rate (L13 = gamma' / t_c, dgamma_13/dt =
// L13 F33: 0.32 gamma' per step, times F33 = h33/H0 = 1 - e1), the servo holds s33 within 1 % of
// 200 kPa at every row (measured 0.67 %, at the first row), the fixed components stay put
// (e11 = e22 = 0, gamma_12 = gamma_23 = 0 to round-off) and the phase ends at gamma_13 = 5 %.
TEST(LoadingPaths, SimpleShearHoldsTheNormalStress) {
  const fs::path dir = run_example("simple-shear.toml", "simple-shear");
  const Csv s = read_csv(dir / "series.csv");
  ASSERT_GT(s.rows.size(), 50u);
  double before = 0;
  long step_before = 0;  // force evaluation n is at n steps of shear (as e1, SPEC 3.4)
  for (std::size_t k = 0; k < s.rows.size(); ++k) {
    EXPECT_LE(std::abs(s.at(k, "s33_Pa") / 200e3 - 1), 0.01) << "row " << k;
    EXPECT_LE(std::abs(s.at(k, "g12")), 1e-15) << "row " << k;
    EXPECT_LE(std::abs(s.at(k, "g23")), 1e-15) << "row " << k;
    // ev = V/V0 - 1 = h33/H0 - 1 when h11, h22 are fixed: e1 = -ev (to the printed digits).
    EXPECT_NEAR(s.at(k, "e1"), -s.at(k, "ev"), 1e-12) << "row " << k;
    const double g = s.at(k, "g13");
    const long step = std::stol(s.rows[k][s.col("step")]);
    const double steps = static_cast<double>(step - step_before);
    // F33 changes by < 0.1 % between rows: the mean of its two ends is exact to 1e-6 of the increment.
    const double f33 = 1 - 0.5 * (s.at(k, "e1") + (k > 0 ? s.at(k - 1, "e1") : 0.0));
    EXPECT_NEAR(g - before, steps * 0.32 * 2e-5 * f33, 1e-3 * steps * 0.32 * 2e-5) << "row " << k;
    before = g;
    step_before = step;
    EXPECT_LT(s.at(k, "s13_Pa"), 0) << "compression positive: the shear resists gamma_13 > 0";
  }
  const double last = s.at(s.rows.size() - 1, "g13");
  EXPECT_GE(last, 0.05);
  EXPECT_LT(last, 0.05 + 0.32 * 2e-5 * 1.01);
}

// examples/isotropic-cycle.toml: each branch (load to 400 kPa, unload to 100 kPa, reload to
// 400 kPa) ends with every normal stress within its 0.5 % equilibrium tolerance of the named
// stress, the normal stresses stay equal within 1 % of p at every row (measured 0.49 %, the servo
// moving each axis at its cap), and the volume follows the load: loading and reloading compress,
// unloading dilates. Each branch's `isotropic` record in summary.json is the same computation on the
// rows, from the last row of the phase before (compaction.csv's for the load) to its own last row:
// p at both ends, volume_strain = -(V_end - V_start)/V_start, K = dp/volume_strain > 0, and for the
// unload and the reload, which return to the start stress of the branch before, the volume strain
// the pair leaves, -(V_end/V_start of the branch before - 1). V/V_load in series.csv is 1 + ev; the
// load's start, in compaction.csv, comes into that reference by the void ratios: V = V_s (1 + e).
// Tolerances from the rows' digits, which round each value by half a unit of its last digit: p_Pa
// and ev have 10 significant digits (p to a relative 5e-10; ev, |ev| < 1e-2, to 5e-13), void_ratio
// 8 (e, 0.1 <= e < 1, to 5e-9; a ratio (1 + e)/(1 + e') to 1e-8): a volume strain between rows of
// series.csv to 1e-12 (two ev's), one from the load's start to 2e-8 (the ratio, then two ev's), each
// doubled for the arithmetic; K to the sum of the relative errors of dp and of the volume strain.
TEST(LoadingPaths, IsotropicCycleReachesTheNamedStressesAndMeasuresItsBranches) {
  const fs::path dir = run_example("isotropic-cycle.toml", "isotropic-cycle");
  const Csv s = read_csv(dir / "series.csv");
  const Csv compaction = read_csv(dir / "compaction.csv");
  const nlohmann::json summary = nlohmann::json::parse(slurp(dir / "summary.json"));
  ASSERT_FALSE(s.rows.empty());
  ASSERT_FALSE(compaction.rows.empty());
  const std::size_t phase = s.col("phase");
  const std::vector<std::pair<std::string, double>> branches{{"load", 400e3}, {"unload", 100e3}, {"reload", 400e3}};
  const nlohmann::json& phases = summary["phases"];
  ASSERT_EQ(phases.size(), 4u);
  EXPECT_FALSE(phases[0].contains("isotropic")) << "the compaction is no branch";
  // The end of the phase before the branch (first: the compaction's, brought into series.csv's reference).
  ASSERT_EQ(s.rows[0][phase], "load");
  const std::size_t c_last = compaction.rows.size() - 1;
  const std::size_t l_last = [&] {
    std::size_t k = 0;
    while (k + 1 < s.rows.size() && s.rows[k + 1][phase] == "load") ++k;
    return k;
  }();
  double p_before = compaction.at(c_last, "p_Pa");
  double ev_before = (1 + compaction.at(c_last, "void_ratio")) / (1 + s.at(l_last, "void_ratio")) * (1 + s.at(l_last, "ev")) - 1;
  // The ranges the tolerances above assume.
  for (std::size_t k = 0; k < s.rows.size(); ++k) {
    ASSERT_LT(std::abs(s.at(k, "ev")), 1e-2) << "row " << k;
    ASSERT_TRUE(s.at(k, "void_ratio") >= 0.1 && s.at(k, "void_ratio") < 1) << "row " << k;
  }
  ASSERT_TRUE(compaction.at(c_last, "void_ratio") >= 0.1 && compaction.at(c_last, "void_ratio") < 1);
  double tol = 2e-8;  // of a volume strain from this start
  double p_start_before = 0, ev_start_before = 0;  // the start of the branch before (none for the load)
  for (std::size_t b = 0; b < branches.size(); ++b) {
    const auto& [name, target] = branches[b];
    std::size_t last = s.rows.size();
    for (std::size_t k = 0; k < s.rows.size(); ++k) {
      if (s.rows[k][phase] != name) continue;
      last = k;
      const double p = s.at(k, "p_Pa");
      for (const char* c : {"s11_Pa", "s22_Pa", "s33_Pa"})
        EXPECT_LE(std::abs(s.at(k, c) - p), 0.01 * p) << name << " row " << k << " " << c;
    }
    ASSERT_LT(last, s.rows.size()) << "no rows of " << name;
    for (const char* c : {"s11_Pa", "s22_Pa", "s33_Pa"})
      EXPECT_LE(std::abs(s.at(last, c) / target - 1), 0.005) << name << " " << c;
    const double ev = s.at(last, "ev"), p = s.at(last, "p_Pa");
    if (target > 200e3) EXPECT_LT(ev, ev_before) << name << " compresses";
    else EXPECT_GT(ev, ev_before) << name << " dilates";

    const nlohmann::json& rec = phases[b + 1];
    ASSERT_EQ(rec["name"], name);
    ASSERT_TRUE(rec.contains("isotropic")) << name;
    const nlohmann::json& iso = rec["isotropic"];
    const double volume_strain = -(ev - ev_before) / (1 + ev_before);
    EXPECT_NEAR(iso["p_start_Pa"].get<double>(), p_before, 1e-9 * p_before) << name;
    EXPECT_NEAR(iso["p_end_Pa"].get<double>(), p, 1e-9 * p) << name;
    EXPECT_NEAR(iso["volume_strain"].get<double>(), volume_strain, tol) << name;
    const double k_bulk = iso["bulk_modulus_Pa"].get<double>();
    EXPECT_GT(k_bulk, 0) << name;
    const double k_rows = (p - p_before) / volume_strain;  // relative error: that of volume_strain
    const double k_tol = 1e-9 * (p + p_before) / std::abs(p - p_before) + tol / std::abs(volume_strain);
    EXPECT_NEAR(k_bulk, k_rows, std::abs(k_rows) * k_tol) << name;
    if (b == 0) {
      EXPECT_FALSE(iso.contains("residual_volume_strain")) << "no isotropic branch before the load";
    } else {
      ASSERT_LE(std::abs(target / p_start_before - 1), 0.01) << name << " returns to the start of the branch before";
      ASSERT_TRUE(iso.contains("residual_volume_strain")) << name;
      // The unload's: ev at its end minus ev at the start of the load (the hysteresis of the cycle).
      EXPECT_NEAR(iso["residual_volume_strain"].get<double>(), -(ev - ev_start_before) / (1 + ev_start_before),
                  b == 1 ? 2e-8 : 2e-12)
          << name;
    }
    p_start_before = p_before, ev_start_before = ev_before;
    p_before = p, ev_before = ev, tol = 2e-12;
  }
}

// examples/cyclic-triaxial.toml (drained, q = s33 - (s11 + s22)/2 between 50 and 150 kPa, 5 cycles,
// a row per step). The corners of the loops are the rows where e1 turns; the test finds them in the
// rows and checks, against the rows alone:
// - each turn was caused by the bound: the row before a top corner is the first at or above
//   150 kPa since the last corner (below 50 kPa for a bottom); the cell moves one more step at the
//   old rate, so q overshoots a bound by at most two steps' increments of q (2 max |dq| over the
//   rows, measured 2 x 0.6 kPa);
// - 2 x 5 turns, the phase ending at the 11th corner, and summary.json's 5 cycles;
// - each cycle's figures (top -> bottom -> top): E_sec = dq / de1 between its bottom and closing top,
//   W_loop = the trapezoid sum of q de1 over its rows minus the chord (q0 + q2)/2 (e2 - e0),
//   D = W_loop / (4 pi dq de1 / 8), e1 and ev at the closing corner, to 1e-6 (the rows' 10 digits);
// - no `isotropic` record: the compaction is the first phase, the cyclic one drives 33 at a rate.
TEST(LoadingPaths, CyclicTriaxialTurnsAtTheBoundsAndMeasuresItsLoops) {
  const fs::path dir = run_example("cyclic-triaxial.toml", "cyclic-triaxial");
  const Csv s = read_csv(dir / "series.csv");
  const nlohmann::json summary = nlohmann::json::parse(slurp(dir / "summary.json"));
  const std::size_t rows = s.rows.size();
  ASSERT_GT(rows, 1000u);
  std::vector<double> q(rows), e(rows);
  double step_dq = 0;  // the largest change of q from one force evaluation to the next
  for (std::size_t k = 0; k < rows; ++k) {
    ASSERT_EQ(std::stol(s.rows[k][s.col("step")]), static_cast<long>(k)) << "a row per step";
    q[k] = s.at(k, "s33_Pa") - 0.5 * (s.at(k, "s11_Pa") + s.at(k, "s22_Pa"));
    e[k] = s.at(k, "e1");
    if (k > 0) step_dq = std::max(step_dq, std::abs(q[k] - q[k - 1]));
  }
  const double lower = 50e3, upper = 150e3, tol = 2 * step_dq;
  std::vector<std::size_t> corner;
  for (std::size_t k = 1; k + 1 < rows; ++k)
    if ((e[k] - e[k - 1]) * (e[k + 1] - e[k]) < 0) corner.push_back(k);
  ASSERT_EQ(corner.size(), 10u) << "5 cycles: 2 turns each";
  corner.push_back(rows - 1);  // the phase ends at the closing corner of the last cycle
  EXPECT_GT(e[rows - 1], e[rows - 2]) << "the last cycle ends on reloading";
  std::size_t from = 0;
  for (std::size_t c = 0; c < corner.size(); ++c) {
    const bool top = c % 2 == 0;
    const std::size_t k = corner[c];
    EXPECT_EQ(e[k] > e[k - 1], top) << "corner " << c;
    // The crossing: the row before the corner reached the bound, none between the last corner and it.
    EXPECT_TRUE(top ? q[k - 1] >= upper : q[k - 1] <= lower) << "corner " << c << " q " << q[k - 1];
    for (std::size_t j = from; j + 1 < k; ++j)
      EXPECT_TRUE(top ? q[j] < upper : q[j] > lower) << "corner " << c << " row " << j << " q " << q[j];
    from = k;
  }
  EXPECT_LT(step_dq, 1e3) << "steps of q small against the 100 kPa range";
  for (std::size_t k = 0; k < rows; ++k) {
    EXPECT_LE(q[k], upper + tol) << "row " << k;
    if (k >= corner[0]) {
      EXPECT_GE(q[k], lower - tol) << "row " << k;
    }
  }
  for (const nlohmann::json& rec : summary["phases"])
    EXPECT_FALSE(rec.contains("isotropic")) << rec["name"];
  const nlohmann::json& cycles = summary["phases"][1]["controller"]["cycles"];
  ASSERT_EQ(cycles.size(), 5u);
  for (std::size_t n = 0; n < 5; ++n) {
    const std::size_t c0 = corner[2 * n], c1 = corner[2 * n + 1], c2 = corner[2 * n + 2];
    double work = 0;
    for (std::size_t k = c0 + 1; k <= c2; ++k) work += 0.5 * (q[k] + q[k - 1]) * (e[k] - e[k - 1]);
    work -= 0.5 * (q[c0] + q[c2]) * (e[c2] - e[c0]);
    const double dq = q[c2] - q[c1], de = e[c2] - e[c1];
    const nlohmann::json& f = cycles[n];
    EXPECT_EQ(f["cycle"].get<long>(), static_cast<long>(n + 1));
    EXPECT_NEAR(f["q_max_Pa"].get<double>(), q[c2], 1e-6 * q[c2]);
    EXPECT_NEAR(f["q_min_Pa"].get<double>(), q[c1], 1e-6 * q[c2]);
    EXPECT_NEAR(f["secant_modulus_Pa"].get<double>(), dq / de, 1e-6 * dq / de) << "cycle " << n + 1;
    EXPECT_NEAR(f["loop_work_J_m3"].get<double>(), work, 1e-6 * std::abs(work)) << "cycle " << n + 1;
    const double d = work / (4 * std::numbers::pi * dq * de / 8);
    EXPECT_NEAR(f["damping_ratio"].get<double>(), d, 1e-6 * std::abs(d)) << "cycle " << n + 1;
    EXPECT_GT(d, 0) << "a loop dissipates";
    EXPECT_NEAR(f["e1"].get<double>(), e[c2], 1e-12);
    EXPECT_NEAR(f["ev"].get<double>(), s.at(c2, "ev"), 1e-12);
  }
}

// The path controllers' keys are checked: what drives the phase, one kind of bounds, their ranges.
TEST(LoadingPaths, PathControllerKeysAreChecked) {
  const std::string head = R"(
[material]
density = "2650 kg/m^3"
young_modulus = "78 GPa"
poisson_ratio = 0.3
[[sample.particles]]
diameter = "2 mm"
count = 10
[[phase]]
friction = 0.5
)";
  const std::string lateral = "stress = { 11 = \"100 kPa\", 22 = \"100 kPa\" }\n";
  const struct {
    std::string text, key, expected;
  } cases[] = {
      {"strain_rate = { 33 = -1e-5 }\ncontroller = { kind = \"cyclic\", q_mean = \"1 kPa\", q_amplitude = \"1 kPa\" }\n",
       "controller.kind", "loads axis 3 first"},
      {"strain_rate = { 33 = 1e-5 }\nstop = { strain = { 33 = \"1 %\" } }\n"
       "controller = { kind = \"cyclic\", q_mean = \"1 kPa\", q_amplitude = \"1 kPa\" }\n",
       "controller.kind", "remove stop.strain.33"},
      {"strain_rate = { 33 = 1e-5 }\ncontroller = { kind = \"cyclic\", q_mean = \"1 kPa\" }\n", "controller.q_amplitude",
       "one of them"},
      {"strain_rate = { 33 = 1e-5 }\n"
       "controller = { kind = \"cyclic\", q_mean = \"1 kPa\", q_amplitude = \"1 kPa\", strain_amplitude = 0.01 }\n",
       "controller.q_amplitude", "one of them"},
      {"strain_rate = { 33 = 1e-5 }\ncontroller = { kind = \"cyclic\", q_mean = \"1 kPa\", q_amplitude = \"-1 kPa\" }\n",
       "controller.q_amplitude", "must be > 0"},
      {"strain_rate = { 33 = 1e-5 }\ncontroller = { kind = \"cyclic\", strain_mean = -0.02, strain_amplitude = 0.01 }\n",
       "controller.strain_mean", "must be > 0"},
      {"strain_rate = { 33 = 1e-5 }\ncontroller = { kind = \"cyclic\", strain_amplitude = 0.01, cycles = 0 }\n",
       "controller.cycles", "[1, 100000]"},
      {"strain_rate = { 33 = 1e-5 }\nstop = { strain = { 33 = \"1 %\" } }\n"
       "controller = { kind = \"true_triaxial\", p = \"100 kPa\", b = 1.5 }\n",
       "controller.b", "[0, 1]"},
      {"strain_rate = { 33 = 1e-5, 22 = 1e-5 }\nstress = { 11 = \"100 kPa\" }\nstop = { strain = { 33 = \"1 %\" } }\n"
       "controller = { kind = \"true_triaxial\", p = \"100 kPa\", b = 0.5 }\n",
       "controller.kind", "axes 1 and 2"},
  };
  for (const auto& c : cases) {
    std::string what = "(no error)";
    try {
      parse_case(head + (c.text.find("stress = {") == std::string::npos ? lateral : "") + c.text, "bad.toml");
    } catch (const InputError& e) {
      what = e.what();
    }
    EXPECT_NE(what.find("bad.toml"), std::string::npos) << what;
    EXPECT_NE(what.find("key 'phase.0." + c.key + "'"), std::string::npos) << "the key is not named: " << what;
    EXPECT_NE(what.find(c.expected), std::string::npos) << "expected '" << c.expected << "' in: " << what;
  }
}

// examples/true-triaxial.toml: s1 = s33 loaded to e1 = 2 %, s2 = s11 and s3 = s22 servo-held at the
// targets that keep p = 200 kPa and b = 0.5. After the servo's start-up (the rows from e1 = 0.1 %,
// about 100 steps; at the first row, step 31, p is 5.8 % high), every row holds p within 1 %
// (measured 0.41 %) and b within 0.03 (measured 0.016, 0.8 % of s1 - s3 in s2), and s1 - s3 has
// grown to more than 0.2 p (b is defined); the path ends at e1 = 2 % at its planned step.
TEST(LoadingPaths, TrueTriaxialHoldsPAndB) {
  const fs::path dir = run_example("true-triaxial.toml", "true-triaxial");
  const Csv s = read_csv(dir / "series.csv");
  ASSERT_EQ(s.rows.size(), 100u);
  std::size_t held = 0;
  for (std::size_t k = 0; k < s.rows.size(); ++k) {
    if (s.at(k, "e1") < 1e-3) continue;
    ++held;
    const double s1 = s.at(k, "s33_Pa"), s2 = s.at(k, "s11_Pa"), s3 = s.at(k, "s22_Pa");
    const double p = (s1 + s2 + s3) / 3;
    EXPECT_LE(std::abs(p / 200e3 - 1), 0.01) << "row " << k;
    ASSERT_GT(s1 - s3, 0.2 * p) << "row " << k;
    EXPECT_NEAR((s2 - s3) / (s1 - s3), 0.5, 0.03) << "row " << k;
    EXPECT_NEAR(s.at(k, "p_Pa"), p, 1e-6 * p) << "p_Pa is the mean of the normal stresses";
  }
  EXPECT_GE(held, 90u);
  EXPECT_NEAR(s.at(s.rows.size() - 1, "e1"), 0.02, 0.32 * 2e-5);
}

// A simple cubic lattice of equal Hertz spheres (radius R, n^3 in a periodic cube, spacing
// a0 = 2R - delta0) against its closed-form small-strain moduli (docs/loading-paths.md, "Hertz
// lattice moduli"). Each sphere has 6 contacts along the axes; per sphere (volume a^3) one contact
// per axis with branch vector a along it, so the Love-Weber stress (SPEC 7) is
//   sigma_kk = F(delta_k) a_k / (a_1 a_2 a_3) = F(delta_k) / (a_i a_j)   (i, j the other axes),
//   F(delta) = (4/3) E* sqrt(R_e) delta^(3/2), R_e = R/2, delta_k = 2R - a_k   (SPEC 4.7),
// and p0 = F(delta0) / a0^2. Under an affine strain (every sphere is a centre of symmetry: the
// forces on it cancel, it stays at its lattice site) with a_k = a0 (1 - e_k), d delta_k = a0 de_k:
//   uniaxial strain e_3:  d sigma_33 / d e_3 = k_n a0 / a0^2 = k_n / a0 = C11,
//                         d sigma_11 / d e_3 = F / a0^2 = p0 = C12 (the area a_1 a_3 shrinks);
//   isotropic strain e:   d sigma_kk / d e = k_n / a0 + 2 p0, d eps_v / d e = 3:
//                         K = (k_n / a0 + 2 p0) / 3 = (C11 + 2 C12) / 3,
// with k_n = dF/d delta = 2 E* sqrt(R_e delta0) = 3 F / (2 delta0). The contacts' normals stay
// on the axes, so no tangential displacement arises: friction (here 0.5) plays no part.
// Measured: the secant over the first step (e grows by c_t eps' = 3.2e-7): Hertz stiffening makes
// it exceed the tangent by d delta / (4 delta0) = a0 c_t eps' / (4 delta0) (1.6e-4 here) to first
// order; the tolerance is 1.5 times that.
TEST(LoadingPaths, HertzLatticeModuliMatchTheClosedForm) {
  const int n = 6;
  const double R = 1e-3, delta0 = 1e-3 * R, a0 = 2 * R - delta0;
  const double E = 78e9, nu = 0.3, Es = E / (2 * (1 - nu * nu)), Re = R / 2;
  const double F = 4.0 / 3 * Es * std::sqrt(Re) * std::pow(delta0, 1.5);
  const double kn = 2 * Es * std::sqrt(Re * delta0);
  const double p0 = F / (a0 * a0), c11 = kn / a0, c12 = p0, bulk = (c11 + 2 * c12) / 3;
  const double eps = 1e-6, de = 0.32 * eps;
  const double tol = 1.5 * a0 * de / (4 * delta0);
  const fs::path dir = scratch("lattice");
  fs::create_directories(dir);
  {
    std::ostringstream p;
    p.precision(17);
    p << "format qsdem-packing 1\ncell " << n * a0 << " 0 0 0 " << n * a0 << " 0 0 0 " << n * a0 << "\nparticles "
      << n * n * n << "\n";
    for (int i = 0; i < n; ++i)
      for (int j = 0; j < n; ++j)
        for (int k = 0; k < n; ++k)
          p << (i + 0.5) * a0 << ' ' << (j + 0.5) * a0 << ' ' << (k + 0.5) * a0 << ' ' << R << ' ' << R << ' ' << R
            << " 1 0 0 0\n";
    std::ofstream(dir / "lattice.packing") << p.str();
    std::ofstream(dir / "lattice.toml") << R"(
[material]
density = "2650 kg/m^3"
young_modulus = "78 GPa"
poisson_ratio = 0.3
[sample]
from = "lattice.packing"
[[phase]]
name = "strain"
friction = 0.5
strain_rate = { 33 = 1e-6 }
stop = { steps = 2 }
output = { every_steps = 1 }
)";
  }
  const auto run = [&](const std::string& name, const std::string& set) {
    const fs::path out = dir / name;
    std::string cmd = std::string("'") + QSDEM_BINARY + "' run '" + (dir / "lattice.toml").string() + "' --out '" +
                      out.string() + "' --threads 1 --quiet" + set + " > '" + out.string() + ".log' 2>&1";
    EXPECT_EQ(std::system(cmd.c_str()), 0) << cmd << "\n" << slurp(out.string() + ".log");
    return read_csv(out / "series.csv");
  };
  const Csv u = run("uniaxial", "");
  ASSERT_EQ(u.rows.size(), 2u);
  for (const char* c : {"s11_Pa", "s22_Pa", "s33_Pa"})
    EXPECT_NEAR(u.at(0, c), p0, 1e-9 * p0) << c << ": the lattice's stress at rest is p0";
  ASSERT_NEAR(u.at(1, "e1"), de, 1e-8 * de) << "one step of c_t eps' (the row's 10 digits)";
  const double c11_measured = (u.at(1, "s33_Pa") - u.at(0, "s33_Pa")) / de;
  const double c12_measured = (u.at(1, "s11_Pa") - u.at(0, "s11_Pa")) / de;
  EXPECT_NEAR(c11_measured / c11, 1, tol) << "C11 " << c11_measured << " closed form " << c11;
  // sigma_33 = F(delta0 + a0 e) / a0^2 exactly (a_1, a_2 fixed): the excess of the secant is the
  // Hertz curvature's, a0 de / (4 delta0) (the next order, -(a0 de / delta0)^2 / 24, is 2e-8).
  EXPECT_NEAR(c11_measured / c11 - 1, a0 * de / (4 * delta0), 0.02 * a0 * de / (4 * delta0))
      << "the secant's excess over the tangent is Hertz's delta^(3/2) stiffening";
  // d sigma_11 is 0.064 Pa, the rows' 10 digits of sigma_11 (2e5 Pa) resolve it to 1.6e-4.
  EXPECT_NEAR(c12_measured / c12, 1, 1e-3) << "C12 " << c12_measured << " closed form " << c12;
  const Csv iso = run("isotropic", " --set 'phase.0.strain_rate.11=1e-6' --set 'phase.0.strain_rate.22=1e-6'");
  ASSERT_EQ(iso.rows.size(), 2u);
  const double bulk_measured = (iso.at(1, "p_Pa") - iso.at(0, "p_Pa")) / -(iso.at(1, "ev") - iso.at(0, "ev"));
  EXPECT_NEAR(bulk_measured / bulk, 1, tol) << "K " << bulk_measured << " closed form " << bulk;
  std::printf("Hertz lattice: p0 %.6g Pa, C11 %.6g (closed form %.6g), C12 %.6g (%.6g), K %.6g (%.6g) Pa\n", p0,
              c11_measured, c11, c12_measured, c12, bulk_measured, bulk);
}

// examples/cyclic-triaxial.toml stopped by SIGTERM in its second cycle (series.csv.partial at
// 4000 rows: after the corners at rows ~2730 and ~3640) and resumed writes the same series.csv and
// the same cycles in summary.json as the run left alone: the controller's corners and work sums are
// in the checkpoint.
TEST(LoadingPaths, CyclicTriaxialResumesToTheSameBits) {
  const fs::path ref = run_example("cyclic-triaxial.toml", "cyclic-ref");
  const fs::path dir = scratch("cyclic-stopped");
  const fs::path log = dir.string() + "-run";
  const pid_t pid = qsdem_test::spawn_logged({QSDEM_BINARY, "run", (examples / "cyclic-triaxial.toml").string(), "--out",
                                              dir.string(), "--threads", "1", "--quiet"},
                                             log);
  ASSERT_GT(pid, 0);
  const auto rows = [&] {
    std::ifstream in(dir / "series.csv.partial");
    long n = 0;
    for (std::string l; std::getline(in, l);) ++n;
    return n;
  };
  const auto deadline = std::chrono::steady_clock::now() + std::chrono::seconds(300);
  while (rows() < 4001 && std::chrono::steady_clock::now() < deadline)
    std::this_thread::sleep_for(std::chrono::milliseconds(2));
  ASSERT_GE(rows(), 4001) << slurp(log.string() + ".err");
  ::kill(pid, SIGTERM);
  ASSERT_EQ(qsdem_test::wait_exit(pid), 128 + SIGTERM) << slurp(log.string() + ".err");
  const pid_t again = qsdem_test::spawn_logged({QSDEM_BINARY, "resume", dir.string(), "--threads", "1", "--quiet"},
                                               dir.string() + "-resume");
  ASSERT_EQ(qsdem_test::wait_exit(again), 0) << slurp(dir.string() + "-resume.err");
  EXPECT_EQ(slurp(ref / "series.csv"), slurp(dir / "series.csv"));
  const auto cycles = [](const fs::path& d) {
    return nlohmann::json::parse(slurp(d / "summary.json"))["phases"][1]["controller"].dump();
  };
  EXPECT_EQ(cycles(ref), cycles(dir));
}

// examples/cyclic-triaxial.toml keeps the energy ledger (output.energy, docs/physics.md 12). In
// each of its 5 cycles the cell's work plus the contact law's stiffness change equals the
// dissipations plus the changes of the stored and kinetic energies to 1e-3 of the work (measured
// <= 2.2e-4: the leapfrog's error, which falls with the rate); without the stiffness change the
// balance would miss by more (measured 2.3e-3 to 2.9e-3 of the work). Sliding and the particle
// damping both dissipate, no dashpot does. The ledger changes no result: the run without it writes
// the same rows (its columns less the ledger's) and the same cycle figures.
TEST(LoadingPaths, CyclicLoopsBalanceTheirEnergy) {
  const fs::path on = run_example("cyclic-triaxial.toml", "cyclic-energy");
  const fs::path off = run_example("cyclic-triaxial.toml", "cyclic-no-energy", {"output.energy=false"});
  const auto cycles = [](const fs::path& d) {
    return nlohmann::json::parse(slurp(d / "summary.json"))["phases"][1]["controller"]["cycles"];
  };
  nlohmann::json with = cycles(on);
  const nlohmann::json without = cycles(off);
  ASSERT_EQ(with.size(), 5u);
  for (nlohmann::json& c : with) {
    SCOPED_TRACE("cycle " + c["cycle"].dump());
    ASSERT_TRUE(c.contains("energy"));
    const nlohmann::json& e = c["energy"];
    const double work = e["work_J"], stiffness = e["stiffness_change_J"];
    ASSERT_GT(work, 0.0) << "a loop takes work";
    const double lhs = work + stiffness;
    const double rhs = e["friction_J"].get<double>() + e["contact_damping_J"].get<double>() +
                       e["damping_J"].get<double>() + e["elastic_change_J"].get<double>() +
                       e["kinetic_change_J"].get<double>();
    EXPECT_NEAR(e["balance_error_J"].get<double>(), lhs - rhs, 1e-12 * work);
    EXPECT_LE(std::abs(lhs - rhs), 1e-3 * work);
    EXPECT_GT(std::abs(stiffness), 1e-3 * work) << "the incremental Mindlin law makes energy";
    EXPECT_GT(e["friction_J"].get<double>(), 0.0);
    EXPECT_GT(e["damping_J"].get<double>(), 0.0);
    EXPECT_EQ(e["contact_damping_J"].get<double>(), 0.0);
    c.erase("energy");
  }
  EXPECT_EQ(with.dump(), without.dump()) << "the ledger changes no cycle figure";
  // Each phase's record has the ledger's change over the phase (compaction measured 1.6e-4 of its
  // work, the cyclic phase 7.9e-5); the run without the ledger has none.
  const nlohmann::json phases_on = nlohmann::json::parse(slurp(on / "summary.json"))["phases"];
  const nlohmann::json phases_off = nlohmann::json::parse(slurp(off / "summary.json"))["phases"];
  ASSERT_EQ(phases_on.size(), 2u);
  for (std::size_t k = 0; k < 2; ++k) {
    ASSERT_TRUE(phases_on[k].contains("energy")) << k;
    const double work = phases_on[k]["energy"]["work_J"];
    EXPECT_GT(work, 0.0);
    EXPECT_LE(std::abs(phases_on[k]["energy"]["balance_error_J"].get<double>()), 1e-3 * work) << k;
    EXPECT_FALSE(phases_off[k].contains("energy")) << k;
  }
  const std::string rows_on = slurp(on / "series.csv"), rows_off = slurp(off / "series.csv");
  std::istringstream a(rows_on), b(rows_off);
  long rows = 0;
  for (std::string x, y; std::getline(b, y);) {
    ASSERT_TRUE(std::getline(a, x));
    ASSERT_EQ(x.substr(0, y.size() + 1), y + ",") << "row " << rows << ": the ledger's columns come last";
    ++rows;
  }
  EXPECT_GT(rows, 1000);
}
