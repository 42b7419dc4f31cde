// Protocols as phase lists ([[phase]], phase.hpp): the parser's errors, a controller's change of
// the strain rate followed exactly, and runs of two and three phases resumed to the same bits.
#include <gtest/gtest.h>
#include <signal.h>
#include <unistd.h>

#include <chrono>
#include <cmath>
#include <filesystem>
#include <fstream>
#include <sstream>
#include <string>
#include <thread>
#include <vector>

#include "qsdem/engine/types.hpp"
#include "qsdem/run/config.hpp"
#include "qsdem/run/generate.hpp"
#include "qsdem/run/protocol.hpp"
#include "test_support.hpp"

using namespace qsdem;
namespace fs = std::filesystem;
using qsdem_test::Csv;
using qsdem_test::lines;
using qsdem_test::read_csv;
using qsdem_test::slurp;

extern char** environ;

namespace {

// 200 spheres (as tests/test_checkpoint.cpp's small case), a checkpoint every 4 rows.
const std::string head = qsdem_test::sample_200("phases") + "[checkpoint]\nevery_sample_points = 4\n";

// Compaction, then axial loading at eps' = 1e-5 to 1 %, 20 rows, the rate doubled after row 10.
const char* two_phases = R"(
[[phase]]
name = "compaction"
friction = 0.2
stress = { 11 = "390 kPa", 22 = "390 kPa", 33 = "390 kPa", 12 = "0 Pa", 13 = "0 Pa", 23 = "0 Pa" }
stop = { equilibrium = { ufr = "1 %" } }
output = { file = "compaction.csv", clock = "run" }

[[phase]]
name = "load"
friction = 0.5
stress = { 11 = "390 kPa", 22 = "390 kPa" }
strain_rate = { 33 = 1e-5 }
stop = { strain = { 33 = "1 %" } }
output = { points = 20 }
controller = { kind = "schedule", component = "33", at_sample = [10], values = [2e-5] }
)";

// ... then unloading at eps' = -1e-5 for 3000 steps, a row every 150, into the same series.csv.
const char* third_phase = R"(
[[phase]]
name = "unload"
friction = 0.5
damping = { model = "od", ratio = "1 %" }
stress = { 11 = "390 kPa", 22 = "390 kPa" }
strain_rate = { 33 = -1e-5 }
stop = { steps = 3000 }
output = { every_steps = 150 }
)";

fs::path scratch(const std::string& name) {
  const fs::path d = fs::temp_directory_path() / ("qsdem-phases-" + std::to_string(::getpid())) / name;
  fs::remove_all(d);
  fs::create_directories(d.parent_path());
  return d;
}

fs::path case_file(const std::string& name, const std::string& text) {
  const fs::path f = scratch(name + ".toml");
  std::ofstream(f) << text;
  return f;
}

std::string input_error(const std::string& phases) {
  try {
    parse_case(std::string(head) + phases, "bad.toml");
  } catch (const InputError& e) {
    return e.what();
  }
  return "(no error)";
}

// Runs `case_path` to the end in `dir`, or, with `kill_at_rows` > 0, stops it by SIGTERM once
// series.csv.partial holds that many rows and resumes it (twice when given two counts).
void run_stopped(const fs::path& case_path, const fs::path& dir, const std::vector<long>& kill_at_rows) {
  std::vector<std::string> args{QSDEM_BINARY, "run", case_path.string(), "--out", dir.string(), "--threads", "1", "--quiet"};
  for (std::size_t k = 0; k <= kill_at_rows.size(); ++k) {
    const fs::path log = dir.string() + "-" + std::to_string(k);
    const pid_t pid = qsdem_test::spawn_logged(args, log);
    ASSERT_GT(pid, 0);
    if (k == kill_at_rows.size()) {
      ASSERT_EQ(qsdem_test::wait_exit(pid), 0) << slurp(log.string() + ".err");
      return;
    }
    const auto deadline = std::chrono::steady_clock::now() + std::chrono::seconds(300);
    bool reached = false;
    while (!reached && std::chrono::steady_clock::now() < deadline) {
      reached = fs::exists(dir / "series.csv.partial") && lines(dir / "series.csv.partial") >= kill_at_rows[k] + 1;
      if (!reached) std::this_thread::sleep_for(std::chrono::milliseconds(2));
    }
    ASSERT_TRUE(reached) << "the run did not reach " << kill_at_rows[k] << " rows: " << slurp(log.string() + ".err");
    ::kill(pid, SIGTERM);
    ASSERT_EQ(qsdem_test::wait_exit(pid), 128 + SIGTERM) << slurp(log.string() + ".err");
    args = {QSDEM_BINARY, "resume", dir.string(), "--threads", "1", "--quiet"};
  }
}

void expect_same_files(const fs::path& a, const fs::path& b) {
  for (const char* f : {"compaction.csv", "series.csv", "compacted.packing", "final.packing"}) {
    ASSERT_TRUE(fs::exists(a / f)) << a / f;
    EXPECT_EQ(slurp(a / f), slurp(b / f)) << f << " differs between " << a << " and " << b;
  }
}

}  // namespace

TEST(PhaseList, BadKeysNameFileLineKeyValueAndWhatIsAllowed) {
  const std::string base = "[[phase]]\nfriction = 0.5\nstress = { 11 = \"1 kPa\", 22 = \"1 kPa\" }\n";
  const struct {
    std::string text, expected;
  } cases[] = {
      {"[compaction]\nfriction = 0.2\n" + base + "stop = { steps = 10 }\n", "[compaction] with [[phase]]"},
      {base + "strain_rate = { 11 = 1e-5 }\nstop = { steps = 10 }\n", "'phase.0.stress.11'"},
      {base, "give at least one end"},
      {base + "stop = { steps = 10, stepz = 10 }\n", "unknown key 'phase.0.stop.stepz'"},
      {base + "strain_rate = { 33 = 0.5 }\nstop = { steps = 10 }\n", "'phase.0.strain_rate.33' = 0.5"},
      {base + "strain_rate = { 33 = 1e-5 }\nstop = { strain = { 33 = \"-1 %\" } }\n", "never reaches it"},
      {base + "strain_rate = { 33 = 1e-5 }\nstop = { strain = { 33 = \"1 %\", 12 = \"1 %\" } }\n",
       "'phase.0.stop.strain.12' = \"1 %\": component 12 is fixed"},
      {base + "strain_rate = { 33 = 1e-21 }\nstop = { strain = { 33 = \"10 %\" } }\n",
       "'phase.0.strain_rate.33' = 1e-21: the phase would take"},
      {base + "stop = { steps = 10 }\noutput = { file = \"classes.csv\" }\n", "the run's per-class file"},
      {base + "stop = { equilibrium = { ufr = 0.01 } }\noutput = { points = 10 }\n", "'phase.0.output.points'"},
      {base + "stop = { steps = 10 }\noutput = { file = \"a/b.csv\" }\n", "must be a file name ending in .csv"},
      {base + "stop = { steps = 10 }\noutput = { every_strain = { 11 = \"1 %\" } }\n", "must be strain-rate controlled"},
      {"[[phase]]\nstress = { 11 = \"1 kPa\" }\nstop = { steps = 10 }\n", "'phase.0.friction'"},
      {base + "strain_rate = { 33 = 1e-5 }\nstop = { steps = 10 }\n"
              "controller = { kind = \"schedule\", component = \"33\", at_sample = [2, 4], values = [2e-5] }\n",
       "give one value per entry of at_sample (2)"},
      {base + "stop = { steps = 10 }\ncontroller = { kind = \"pid\" }\n", "'phase.0.controller.kind' = \"pid\""},
      {base + "stop = { steps = 10 }\ndamping = { acts_on = \"spin\" }\n", "'phase.0.damping.acts_on' = \"spin\""},
      {base + "stop = { steps = 10 }\n[[phase]]\nname = \"phase-0\"\nfriction = 0.5\nstop = { steps = 10 }\n",
       "each phase needs its own"},
  };
  for (const auto& c : cases) {
    const std::string what = input_error(c.text);
    EXPECT_NE(what.find("bad.toml:"), std::string::npos) << "no file and line: " << what << "\nfor\n" << c.text;
    EXPECT_NE(what.find(c.expected), std::string::npos) << "expected '" << c.expected << "' in: " << what;
  }
  // The error of an unknown controller kind names the allowed ones.
  EXPECT_NE(input_error(base + "stop = { steps = 10 }\ncontroller = { kind = \"pid\" }\n").find("schedule"),
            std::string::npos);
}

// A phase's model has the case's contact law and the phase's damping.acts_on; the default protocol
// damps both motions in compaction and what damping.acts_on says in the triaxial test.
TEST(PhaseList, ContactLawAndDampedMotionReachEachPhasesModel) {
  const std::string contact = "[contact]\nlaw = \"hertz_mindlin_dashpot\"\nrestitution = 0.5\n";
  std::string unload = third_phase;
  const std::string od = "ratio = \"1 %\"";
  unload.insert(unload.find(od) + od.size(), ", acts_on = \"rotation\"");
  const Params p = parse_case(std::string(head) + contact + two_phases + unload, "phases.toml");
  ASSERT_EQ(p.protocol.size(), 3u);
  const State st = generate_loose_sample(p);
  for (std::size_t k = 0; k < 3; ++k) {
    const Phase& ph = p.protocol[k];
    const Model m = phase_model(p, ph, ph.controls, st.particles, st.cell.h);
    ASSERT_TRUE(m.contact_law && std::holds_alternative<HertzMindlinDashpot>(*m.contact_law)) << ph.name;
    const double log_e = std::log(0.5), beta = log_e / std::sqrt(log_e * log_e + pi * pi);
    EXPECT_DOUBLE_EQ(std::get<HertzMindlinDashpot>(*m.contact_law).dashpot, -2 * std::sqrt(5.0 / 6.0) * beta)
        << ph.name << ": restitution 0.5";
    EXPECT_EQ(m.damping.acts_on, k == 2 ? DampedMotion::rotation : DampedMotion::both) << ph.name;
  }
  EXPECT_EQ(p.protocol[2].damping.model, "od");

  const Params d = parse_case(std::string(head) + "[damping]\nacts_on = \"translation\"\n", "default.toml");
  ASSERT_EQ(d.protocol.size(), 2u);
  EXPECT_EQ(compaction_model(d, st).damping.acts_on, DampedMotion::both);
  EXPECT_EQ(triaxial_model(d, st).damping.acts_on, DampedMotion::translation);
  EXPECT_TRUE(std::holds_alternative<HertzMindlin>(*triaxial_model(d, st).contact_law));
}

// A run of two phases and one of three, each stopped by SIGTERM in its phases after the first
// (after the controller changed the rate, and in the third phase) and resumed, writes the same
// bytes as the run left alone. The rows of the load phase follow the controller's rate exactly.
TEST(PhaseList, TwoAndThreePhasesResumeBitIdenticalAndFollowTheController) {
  const fs::path two = case_file("two", std::string(head) + two_phases);
  const fs::path three = case_file("three", std::string(head) + two_phases + third_phase);
  const fs::path ref2 = scratch("two-ref"), ref3 = scratch("three-ref");
  run_stopped(two, ref2, {});
  run_stopped(three, ref3, {});
  const fs::path stop2 = scratch("two-stopped"), stop3 = scratch("three-stopped");
  run_stopped(two, stop2, {14});       // in the load phase, after the rate change at row 10
  run_stopped(three, stop3, {6, 27});  // in the load phase before the change, then in the unload phase
  expect_same_files(ref2, stop2);
  expect_same_files(ref3, stop3);

  // The load phase: compaction.csv and series.csv as the default protocol names them; the
  // three-phase file has a phase column.
  const Csv s2 = read_csv(ref2 / "series.csv"), s3 = read_csv(ref3 / "series.csv");
  ASSERT_EQ(s2.rows.size(), 20u);
  EXPECT_FALSE(s2.has("phase")) << "one phase writes series.csv: no phase column";
  ASSERT_TRUE(s3.has("phase"));
  ASSERT_EQ(s3.rows.size(), 40u);
  const std::size_t phase = s3.col("phase");
  for (std::size_t k = 0; k < s3.rows.size(); ++k) {
    EXPECT_EQ(s3.rows[k].at(phase), k < 20 ? "load" : "unload") << "row " << k;
    for (std::size_t c = 0; c < s2.header.size() && k < 20; ++c)
      EXPECT_EQ(s3.rows[k].at(s3.col(s2.header[c])), s2.rows[k][c]) << "row " << k << " " << s2.header[c];
  }

  // Axial strain at force evaluation n of the load phase (SPEC 3.4, exact for a diagonal L):
  // n c_t eps' up to the row after the controller's sample point 10 (force evaluation n10), whose
  // new rate acts from n10 + 1: (n10 + 1) c_t eps' + (n - n10 - 1) c_t eps'_new.
  const double ct = 0.32, eps = 1e-5, eps_new = 2e-5;
  const std::size_t cs = s2.col("step"), ce = s2.col("e1");
  const long n10 = std::stol(s2.rows[9][cs]);
  for (std::size_t k = 0; k < s2.rows.size(); ++k) {
    const long n = std::stol(s2.rows[k][cs]);
    const double expected = n <= n10 ? static_cast<double>(n) * ct * eps
                                     : static_cast<double>(n10 + 1) * ct * eps + static_cast<double>(n - n10 - 1) * ct * eps_new;
    // e1 is printed with 10 significant digits; the cell's round-off over 10^3 steps is ~1e-15.
    EXPECT_NEAR(std::stod(s2.rows[k][ce]), expected, 1e-9 * 0.01) << "row " << k + 1 << " at n = " << n;
  }
  // The rows after the change are spread over the rest of the phase at the new rate, and the last
  // one is at the phase's end, e1 = 1 % within half a step of the new rate.
  const long last = std::stol(s2.rows.back()[cs]);
  EXPECT_NEAR(std::stod(s2.rows.back()[ce]), 0.01, 0.5 * ct * eps_new + 1e-11);
  EXPECT_LT(last, static_cast<long>(0.01 / (ct * eps))) << "the faster rate ends the phase sooner";
  // The unload phase: every 150 steps for 3000 steps, its step column counted from its own start.
  // Its e1 is counted from the start of the load phase (the first phase writing series.csv): the
  // unload starts one load step after the load's last row, at h33 = H0 (1 - e_last - c_t eps'_new),
  // and stretches h33 by c_t 1e-5 of that per step.
  for (std::size_t k = 20; k < 40; ++k)
    EXPECT_EQ(std::stol(s3.rows[k][cs]), static_cast<long>(150 * (k - 19) - 1)) << "row " << k;
  const double start = 1 - std::stod(s3.rows[19][ce]) - ct * eps_new;  // h33 / H0 at the unload's start
  EXPECT_NEAR(std::stod(s3.rows.back()[ce]), 1 - start * (1 + 2999 * ct * 1e-5), 1e-9);
}

// The default protocol written as a [[phase]] list (docs/config.md) runs the same bits as the
// case with [compaction] and [triaxial].
TEST(PhaseList, DefaultProtocolAsPhasesGivesTheSameBits) {
  const std::string tables = R"(
[compaction]
max_strain_rate = 1e-4
[triaxial]
strain_rate = 1e-4
final_axial_strain = "1 %"
sample_points = 10
)";
  const std::string phases = R"(
[[phase]]
name = "compaction"
friction = 0.2
stress = { 11 = "390 kPa", 22 = "390 kPa", 33 = "390 kPa", 12 = "0 Pa", 13 = "0 Pa", 23 = "0 Pa" }
servo = { max_strain_rate = 1e-4 }
stop = { equilibrium = { ufr = "1 %", stress_tolerance = "1 %", every = 200 }, max_steps = 2000000 }
output = { file = "compaction.csv", every_steps = 200, clock = "run" }

[[phase]]
name = "triaxial"
friction = 0.5
stress = { 11 = "390 kPa", 22 = "390 kPa" }
strain_rate = { 33 = 1e-4 }
servo = { rate_factor = 10 }
stop = { strain = { 33 = "1 %" } }
output = { points = 10 }
)";
  const fs::path a = scratch("default-tables"), b = scratch("default-phases");
  run_stopped(case_file("tables", std::string(head) + tables), a, {});
  run_stopped(case_file("phases", std::string(head) + phases), b, {});
  expect_same_files(a, b);
}
