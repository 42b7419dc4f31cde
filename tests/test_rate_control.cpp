// The rate controller (docs/physics.md 8.5) on a 200-sphere sample: the index it holds stays in a
// band set by the index's own noise, measured at a constant rate; the rates stay within their
// bounds and change by at most the allowed factor per point; a stopped and resumed run gives the
// same bits; summary.json's figures are those of series.csv.
#include <gtest/gtest.h>
#include <signal.h>
#include <unistd.h>

#include <chrono>
#include <cmath>
#include <algorithm>
#include <filesystem>
#include <fstream>
#include <nlohmann/json.hpp>
#include <sstream>
#include <string>
#include <thread>
#include <utility>
#include <vector>

#include "qsdem/engine/types.hpp"
#include "qsdem/run/config.hpp"
#include <fmt/format.h>
#include <iostream>
#include "test_support.hpp"

using namespace qsdem;
namespace fs = std::filesystem;
using qsdem_test::Csv;
using qsdem_test::lines;
using qsdem_test::read_csv;
using qsdem_test::slurp;

namespace {

// 200 spheres (as tests/test_phases.cpp): the sample, and the phase lists' first phase.
const std::string sample = qsdem_test::sample_200("rate");
const char* compaction_phase = R"(
[[phase]]
name = "compaction"
friction = 0.2
stress = { 11 = "390 kPa", 22 = "390 kPa", 33 = "390 kPa", 12 = "0 Pa", 13 = "0 Pa", 23 = "0 Pa" }
servo = { max_strain_rate = 1e-4 }
stop = { equilibrium = { ufr = "1 %" } }
output = { file = "compaction.csv", clock = "run" }
)";

// The sample compacted fast; a 3 % triaxial test of 60 rows.
const std::string head = sample + R"([compaction]
max_strain_rate = 1e-4
[checkpoint]
every_sample_points = 4
[triaxial]
final_axial_strain = "3 %"
sample_points = 60
)";

fs::path scratch(const std::string& name) {
  const fs::path d = fs::temp_directory_path() / ("qsdem-rate-" + std::to_string(::getpid())) / name;
  fs::remove_all(d);
  fs::create_directories(d.parent_path());
  return d;
}

fs::path case_file(const std::string& name, const std::string& text) {
  const fs::path f = scratch(name + ".toml");
  std::ofstream(f) << text;
  return f;
}

// Runs `case_path` in `dir`; with kill_at_rows > 0, stops it by SIGTERM once series.csv.partial
// holds that many rows and resumes it.
void run(const fs::path& case_path, const fs::path& dir, long kill_at_rows = 0) {
  std::vector<std::string> args{QSDEM_BINARY, "run", case_path.string(), "--out", dir.string(), "--threads", "1", "--quiet"};
  const fs::path log = dir.string() + "-log";
  if (kill_at_rows > 0) {
    const pid_t pid = qsdem_test::spawn_logged(args, log);
    ASSERT_GT(pid, 0);
    const auto deadline = std::chrono::steady_clock::now() + std::chrono::seconds(300);
    bool reached = false;
    while (!reached && std::chrono::steady_clock::now() < deadline) {
      reached = fs::exists(dir / "series.csv.partial") && lines(dir / "series.csv.partial") >= kill_at_rows + 1;
      if (!reached) std::this_thread::sleep_for(std::chrono::milliseconds(2));
    }
    ASSERT_TRUE(reached) << slurp(log.string() + ".err");
    ::kill(pid, SIGTERM);
    ASSERT_EQ(qsdem_test::wait_exit(pid), 128 + SIGTERM) << slurp(log.string() + ".err");
    args = {QSDEM_BINARY, "resume", dir.string(), "--threads", "1", "--quiet"};
  }
  const pid_t pid = qsdem_test::spawn_logged(args, log);
  ASSERT_GT(pid, 0);
  ASSERT_EQ(qsdem_test::wait_exit(pid), 0) << slurp(log.string() + ".err");
}

std::string fmt_rate(double eps) { return fmt::format("strain_rate = {:.3g}\n", eps); }

nlohmann::json summary(const fs::path& dir) { return nlohmann::json::parse(slurp(dir / "summary.json")); }

// [triaxial.rate_control]: IMom held at 3 %, from eps' = 1e-4 (where IMom is about 11 %).
std::string controlled(const std::string& target = "3 %", double max_rate = 1e-3) {
  return std::string(head) + "strain_rate = 1e-4\n[triaxial.rate_control]\n" +
         fmt::format("target = \"{}\"\nmin_rate = 1e-6\nmax_rate = {}\n", target, max_rate);
}

// Runs a case uninterrupted and again stopped by SIGTERM after `kill_at_rows` rows and resumed;
// both must give the same series.csv and final.packing. Returns the two directories, uninterrupted first.
std::pair<fs::path, fs::path> run_and_resume(const std::string& name, const std::string& text, long kill_at_rows) {
  const fs::path case_path = case_file(name, text);
  const fs::path ref = scratch(name), stopped = scratch(name + "-stopped");
  run(case_path, ref);
  run(case_path, stopped, kill_at_rows);
  for (const char* f : {"series.csv", "final.packing"})
    EXPECT_EQ(slurp(ref / f), slurp(stopped / f)) << f << " differs after a stop and resume";
  return {ref, stopped};
}

// Every row's rate within [lo, hi], and at most a factor 2 (max_factor_per_point) from the row before.
void expect_rates_within_bounds(const std::vector<double>& rate, double lo, double hi) {
  for (std::size_t k = 0; k < rate.size(); ++k) {
    EXPECT_GE(rate[k], lo) << "row " << k + 1;
    EXPECT_LE(rate[k], hi) << "row " << k + 1;
    if (k > 0) {
      EXPECT_LE(std::abs(std::log(rate[k] / rate[k - 1])), std::log(2.0) + 1e-9) << "row " << k + 1;
    }
  }
}

double log_sd(const std::vector<double>& v, std::size_t from) {
  double mean = 0, sq = 0;
  for (std::size_t k = from; k < v.size(); ++k) mean += std::log(v[k]);
  mean /= static_cast<double>(v.size() - from);
  for (std::size_t k = from; k < v.size(); ++k) sq += std::pow(std::log(v[k]) - mean, 2);
  return std::sqrt(sq / static_cast<double>(v.size() - from));
}

}  // namespace

// The controlled IMom stays within a factor 1.5 of its 3 % target in at least 2/3 of the rows after
// the start-up (the rows until it first falls to the target). Why these numbers: at a constant
// rate the index scatters about its mean with a sd of log IMom of 0.05-0.10 on this sample (rates
// 1e-5 to 1e-4 and the controlled run's mean rate, the last 3/4 of the rows each; the test
// measures it again at the controlled run's mean rate): log 1.5 = 0.405 is more than 3 such sd, so that noise alone would keep nearly all rows in
// the band; what leaves it is the loop's tracking error, as the index answers a rate change
// after some 800 steps (10 rows here). Two thirds is "most" with room for one undershoot after
// the start-up. The rates stay within their bounds and change by at most the factor 2 per row;
// summary.json's figures are those of series.csv; a stopped and resumed run gives the same bits.
TEST(RateControl, HoldsTheIndexInItsBandWithinBoundsAndResumesToTheSameBits) {
  const auto [ref, stopped] = run_and_resume("controlled", controlled(), 22);
  EXPECT_EQ(summary(ref)["triaxial"]["controller"], summary(stopped)["triaxial"]["controller"]);

  const Csv s = read_csv(ref / "series.csv");
  ASSERT_TRUE(s.has("strain_rate"));
  ASSERT_EQ(s.rows.size(), 60u);
  const std::vector<double> imom = s.column("imom"), rate = s.column("strain_rate"), e1 = s.column("e1");
  const double target = 0.03, band = 1.5;
  expect_rates_within_bounds(rate, 1e-6, 1e-3);
  for (std::size_t k = 0; k < rate.size(); ++k) {
    // The rows are equal increments of axial strain (3 % / 60) within a step at the row's rate.
    EXPECT_NEAR(e1[k], 0.0005 * static_cast<double>(k + 1), 0.32 * rate[k] + 1e-9) << "row " << k + 1;
  }
  EXPECT_DOUBLE_EQ(rate.front(), 1e-4);
  EXPECT_GT(imom.front(), band * target) << "the start rate is too fast for the target: a start-up to follow";
  std::size_t start = 0;
  while (start < imom.size() && imom[start] > target) ++start;
  ASSERT_LT(start, imom.size() / 4) << "the index did not reach its target in the first quarter of the test";
  long within = 0, within_all = 0;
  double sum = 0;
  for (std::size_t k = 0; k < imom.size(); ++k) {
    const bool in = imom[k] >= target / band && imom[k] <= target * band;
    within_all += in;
    if (k >= start) within += in;
    sum += rate[k];
  }
  const double share = static_cast<double>(within) / static_cast<double>(imom.size() - start);
  EXPECT_GE(share, 2.0 / 3) << "rows within a factor 1.5 of the target after the start-up (row " << start + 1 << ")";

  const nlohmann::json c = summary(ref)["triaxial"]["controller"];
  EXPECT_NEAR(c["mean_strain_rate"].get<double>(), sum / 60, 1e-9 * sum / 60);
  EXPECT_NEAR(c["share_within_band"].get<double>(), static_cast<double>(within_all) / 60, 1e-12);
  EXPECT_NEAR(c["final_strain_rate"].get<double>(), rate.back(), 1e-9 * rate.back());
  EXPECT_EQ(c["constant_rate_steps_at_final"].get<double>(), std::round(0.03 / (0.32 * c["final_strain_rate"].get<double>())));

  // The index's noise at a constant rate, the controlled run's mean: the band is wider than 3 sd.
  const fs::path constant = scratch("constant");
  run(case_file("constant", std::string(head) + fmt_rate(sum / 60)), constant);
  const Csv sc = read_csv(constant / "series.csv");
  const double sd = log_sd(sc.column("imom"), sc.rows.size() / 4);
  EXPECT_GT(std::log(band), 3 * sd) << "sd of log IMom at a constant eps' " << sum / 60 << ": " << sd;
  std::cout << "[ measured ] controlled: start-up " << start << " rows, share within 1.5x " << share
            << ", mean eps' " << sum / 60 << "; constant rate: sd of log IMom " << sd << "\n";
}

// A target the sample cannot reach below max_rate (IMom is about 11 % at 1e-4): the rate rises to
// max_rate and stays there.
TEST(RateControl, RateStopsAtItsUpperBound) {
  const fs::path dir = scratch("capped");
  run(case_file("capped", controlled("60 %", 2e-4)), dir);
  const std::vector<double> rate = read_csv(dir / "series.csv").column("strain_rate");
  for (double r : rate) EXPECT_LE(r, 2e-4);
  EXPECT_EQ(rate.back(), 2e-4) << "IMom reached 60 % at 2e-4? then the test's premise is wrong";
}

namespace {

// Compaction, then load1 (IMom held at 3 %, from eps' = 1e-4, to 1.5 %); `second`: then load2
// (1 % from the rate load1 ended at, to 3 %), into the same series.csv.
std::string two_targets(const std::string& second) {
  std::string text = sample + compaction_phase + R"(
[[phase]]
name = "load1"
friction = 0.5
stress = { 11 = "390 kPa", 22 = "390 kPa" }
strain_rate = { 33 = 1e-4 }
stop = { strain = { 33 = "1.5 %" } }
output = { every_strain = { 33 = "0.05 %" } }
controller = { kind = "rate", component = "33", target = "3 %", min_rate = 1e-7, max_rate = 1e-3 }
)";
  return text + second;
}

}  // namespace

// A step of the target from 3 % to 1 % at 1.5 % strain, the rate continuous across it (load2
// starts at the rate load1 ended at, read from the run without load2, whose load1 is the same
// bits). Followed without oscillation, defined as: the log of eps' reverses its direction at most
// twice (one overshoot and its correction) by swings larger than log 1.25 (a noise-driven drift
// over the filter's 4 rows is about 4 g/b 0.1 = 0.1, log 1.1, with the measured sd 0.1 of log IMom);
// and the second half of load2 holds the new target as the first test holds its own (2/3 of its
// rows within a factor 1.5).
TEST(RateControl, FollowsAStepOfTheTargetWithoutOscillation) {
  const fs::path first = scratch("target-first"), both = scratch("target-both");
  run(case_file("target-first", two_targets("")), first);
  const double r1 = summary(first)["phases"][1]["controller"]["final_strain_rate"].get<double>();
  run(case_file("target-both", two_targets(fmt::format(R"(
[[phase]]
name = "load2"
friction = 0.5
stress = {{ 11 = "390 kPa", 22 = "390 kPa" }}
strain_rate = {{ 33 = {:.17g} }}
stop = {{ strain = {{ 33 = "1.5 %" }} }}
output = {{ every_strain = {{ 33 = "0.05 %" }} }}
controller = {{ kind = "rate", component = "33", target = "1 %", min_rate = 1e-7, max_rate = 1e-3 }}
)",
                                                                        r1))),
      both);
  // The file has a phase column: its rows of load2.
  const Csv s = read_csv(both / "series.csv");
  ASSERT_TRUE(s.has("phase"));
  ASSERT_TRUE(s.has("strain_rate"));
  const std::size_t phase = s.col("phase");
  std::vector<double> rate, imom;
  for (std::size_t k = 0; k < s.rows.size(); ++k) {
    if (s.rows[k].at(phase) != "load2") continue;
    rate.push_back(s.at(k, "strain_rate"));
    imom.push_back(s.at(k, "imom"));
  }
  ASSERT_EQ(rate.size(), 30u);
  EXPECT_NEAR(rate.front(), r1, 1e-9 * r1) << "load2 starts at the rate load1 ended at (10 digits in the file)";
  // Reversals of log eps' by swings larger than log 1.25: from the last extremum, a move of more
  // than that against the current direction.
  const double swing = std::log(1.25);
  int reversals = 0, direction = 0;  // 0: none yet; a first swing sets it without counting
  double extremum = std::log(r1);
  for (double r : rate) {
    const double l = std::log(r);
    if (direction >= 0) {
      if (l > extremum) {
        extremum = l;
        if (direction == 0 && l - std::log(r1) > swing) direction = 1;
      } else if (extremum - l > swing) reversals += direction > 0, direction = -1, extremum = l;
    } else {
      if (l < extremum) extremum = l;
      else if (l - extremum > swing) ++reversals, direction = 1, extremum = l;
    }
  }
  EXPECT_LE(reversals, 2) << "log eps' reversed " << reversals << " times after the step";
  long within = 0;
  for (std::size_t k = imom.size() / 2; k < imom.size(); ++k) within += imom[k] >= 0.01 / 1.5 && imom[k] <= 0.01 * 1.5;
  EXPECT_GE(static_cast<double>(within) / static_cast<double>(imom.size() - imom.size() / 2), 2.0 / 3);
  std::cout << "[ measured ] target step 3 % -> 1 %: eps' " << r1 << " -> " << rate.back() << ", " << reversals
            << " reversals, " << within << "/" << imom.size() - imom.size() / 2 << " rows of the second half within 1.5x\n";
}

// Bad keys of a rate controller name the key, its value and what is allowed.
TEST(RateControl, BadKeysNameKeyAndWhatIsAllowed) {
  const std::string phase = "[[phase]]\nfriction = 0.5\nstress = { 11 = \"1 kPa\", 22 = \"1 kPa\" }\n"
                            "strain_rate = { 33 = 1e-5 }\nstop = { strain = { 33 = \"1 %\" } }\n";
  const std::string every = "output = { every_strain = { 33 = \"0.1 %\" } }\n";
  const auto error = [](const std::string& text) -> std::string {
    try {
      parse_case(text, "bad.toml");
    } catch (const InputError& e) {
      return e.what();
    }
    return "(no error)";
  };
  const struct {
    std::string text, expected;
  } cases[] = {
      {sample + phase + every + "controller = { kind = \"rate\", component = \"33\", min_rate = 1e-6, max_rate = 1e-4 }\n",
       "'phase.0.controller.target'"},
      {sample + phase + every +
           "controller = { kind = \"rate\", component = \"33\", target = \"1 %\", min_rate = 1e-4, max_rate = 1e-3 }\n",
       "must be within [min_rate, max_rate]"},
      {sample + phase + every +
           "controller = { kind = \"rate\", component = \"11\", target = \"1 %\", min_rate = 1e-6, max_rate = 1e-3 }\n",
       "must be strain-rate controlled"},
      {sample + phase + "controller = { kind = \"rate\", component = \"33\", target = \"1 %\", min_rate = 1e-6, max_rate = 1e-3 }\n",
       "output.every_strain.33"},
      {sample + phase + every +
           "controller = { kind = \"rate\", component = \"33\", target = \"1 %\", min_rate = 1e-6, max_rate = 1e-3, "
           "index = \"energy\" }\n",
       "'phase.0.controller.index' = \"energy\""},
      {std::string(head) + "[triaxial.rate_control]\ntarget = \"1 %\"\nmin_rate = 1e-6\nmax_rate = 2e-6\n",
       "'triaxial.rate_control.max_rate'"},
      {std::string(head) + "[triaxial.rate_control]\ntarget = \"1 %\"\nmin_rate = 1e-6\nmax_rate = 1e-4\ngain = 2\n",
       "'triaxial.rate_control.gain' = 2"},
  };
  for (const auto& c : cases) EXPECT_NE(error(c.text).find(c.expected), std::string::npos) << error(c.text);
}

namespace {

// Compaction to 390 kPa, then simple shear at constant normal stress s33 (docs/loading-paths.md)
// with the shear rate L13 driven by the controller: IMom held at 3 %, from gamma' = 1e-4, to
// gamma_13 = 2 %, a row every 0.05 % of gamma_13 (40 rows).
std::string controlled_shear() {
  return sample + compaction_phase + R"(
[[phase]]
name = "shear"
friction = 0.5
strain_rate = { 13 = 1e-4 }
stress = { 33 = "390 kPa" }
stop = { strain = { 13 = "2 %" } }
output = { every_strain = { 13 = "0.05 %" } }
controller = { kind = "rate", component = "13", target = "3 %", min_rate = 1e-6, max_rate = 1e-3 }
)";
}

}  // namespace

// The controller drives a shear component as it drives a normal one. A shear strain is measured
// (the normal strain 33 moves under the servo), so a row is the first force evaluation at which
// gamma_13 has passed the next multiple of 0.05 %: it lies within one step's increment of it,
// c_t gamma' (1 + |e33|) at most. The rates keep their bounds and their factor per row, the
// controller acts (the rate leaves its start), and a stopped and resumed run gives the same bits.
TEST(RateControl, DrivesAShearStrainRate) {
  const fs::path ref = run_and_resume("shear", controlled_shear(), 15).first;

  const Csv s = read_csv(ref / "series.csv");
  ASSERT_TRUE(s.has("strain_rate"));
  const std::vector<double> g13 = s.column("g13"), rate = s.column("strain_rate"), s33 = s.column("s33_Pa");
  ASSERT_EQ(g13.size(), 40u);
  expect_rates_within_bounds(rate, 1e-6, 1e-3);
  double lowest = rate.front(), highest = rate.front();
  for (std::size_t k = 0; k < rate.size(); ++k) {
    const double mark = 0.0005 * static_cast<double>(k + 1);
    if (k + 1 < g13.size()) {  // the last row is the phase's end, at or past 2 %
      EXPECT_GE(g13[k], mark) << "row " << k + 1;
      EXPECT_LE(g13[k], mark + 0.32 * rate[k] * 1.05) << "row " << k + 1;
    }
    EXPECT_NEAR(s33[k], 390e3, 0.05 * 390e3) << "row " << k + 1 << ": the servo holds s33";
    lowest = std::min(lowest, rate[k]);
    highest = std::max(highest, rate[k]);
  }
  EXPECT_GE(g13.back(), 0.02);
  EXPECT_DOUBLE_EQ(rate.front(), 1e-4);
  EXPECT_GT(highest / lowest, 2.0) << "the controller never moved the shear rate";
  const nlohmann::json c = summary(ref)["phases"].back()["controller"];
  EXPECT_NEAR(c["final_strain_rate"].get<double>(), rate.back(), 1e-9 * rate.back());
  std::cout << "[ measured ] controlled shear: eps' " << lowest << " to " << highest << ", final " << rate.back()
            << "\n";
}
