// `qsdem converge` (docs/analysis.md section 11): the ladder of rates of a tiny case, run with real
// processes to a certificate: stopped at the first converged rung pair, at its last rung, or at
// the step budget; continued in its directory; bad options refused.
#include <gtest/gtest.h>
#include <unistd.h>

#include <algorithm>
#include <filesystem>
#include <fstream>
#include <string>
#include <vector>

#include <nlohmann/json.hpp>

#include "test_support.hpp"

namespace fs = std::filesystem;
using nlohmann::json;

namespace {

const std::string binary = QSDEM_BINARY;

using Result = qsdem_test::Cli;

Result run(const std::vector<std::string>& args, const fs::path& log) {
  return qsdem_test::finish(qsdem_test::spawn_logged(args, log), log);
}

class Converge : public ::testing::Test {
 protected:
  void SetUp() override {
    dir_ = fs::temp_directory_path() /
           ("qsdem_converge_" + std::string(::testing::UnitTest::GetInstance()->current_test_info()->name()) + "_" +
            std::to_string(::getpid()));
    fs::remove_all(dir_);
    fs::create_directories(dir_);
    case_ = dir_ / "tiny.toml";
    std::ofstream(case_) << qsdem_test::tiny_case("converge-tiny");
  }
  void TearDown() override { fs::remove_all(dir_); }

  // The tiny case's ladder: two seeds, eps' = 1.25e-4 / 2^k (250, 500, 1000, ... steps a run).
  Result ladder(const std::string& out, std::vector<std::string> extra) {
    std::vector<std::string> args{binary, "converge", case_.string(), "--out", (dir_ / out).string(), "--seeds", "2",
                                  "--quiet", "-j", "2"};
    if (std::find(extra.begin(), extra.end(), "--factor") == extra.end()) args.insert(args.end(), {"--factor", "2"});
    args.insert(args.end(), extra.begin(), extra.end());
    return run(args, dir_ / (out + ".log"));
  }
  json certificate(const std::string& out) { return json::parse(qsdem_test::slurp(dir_ / out / "certificate.json")); }
  int runs_made(const std::string& out) {
    int n = 0;
    for (const auto& e : fs::recursive_directory_iterator(dir_ / out / "runs"))
      n += e.path().filename() == "summary.json";
    return n;
  }

  fs::path dir_, case_;
};

}  // namespace

// Tolerances no response can miss: the first two rungs agree, the ladder stops there (exit 0),
// and the fastest rung is the certified one.
TEST_F(Converge, StopsAtTheFirstConvergedRungs) {
  const Result r = ladder("wide", {"--rungs", "4", "--phi-tolerance", "90", "--ev-tolerance", "1", "--no-seed-scatter",
                                   "--ev-end-tolerance", "1"});
  ASSERT_EQ(r.code, 0) << r.err << r.out;
  const json c = certificate("wide");
  EXPECT_EQ(c["status"], "converged");
  EXPECT_EQ(c["stopped_by"], "converged");
  EXPECT_EQ(c["certified_rate"].get<double>(), 1.25e-4);
  EXPECT_EQ(c["rates_run"], json::array({1.25e-4, 6.25e-5}));
  EXPECT_EQ(c["rates_planned"].size(), 4u);
  EXPECT_EQ(c["steps"].get<double>(), 2 * (251 + 501));  // the runs' own counts, step 0 included
  EXPECT_EQ(runs_made("wide"), 4);
  EXPECT_TRUE(fs::exists(dir_ / "wide" / "report.html"));
  EXPECT_TRUE(fs::exists(dir_ / "wide" / "analysis" / "convergence.csv"));
  EXPECT_TRUE(fs::exists(dir_ / "wide" / "analysis" / "figures" / "ladder_case_nd_0_5.png"));
  EXPECT_NE(r.out.find("certificate: converged at eps' = 0.000125"), std::string::npos) << r.out;
  // The certificate's page: the verdict, one row per rung, the limits and the ladder's figure.
  EXPECT_EQ(c["page"], "certificate.html");
  const std::string page = qsdem_test::slurp(dir_ / "wide" / "certificate.html");
  EXPECT_NE(page.find("<h2>converged at ε′ = 0.000125</h2>"), std::string::npos) << page;
  EXPECT_NE(page.find("<td>6.25e-05</td><td>0 (the slowest)</td>"), std::string::npos) << page;
  EXPECT_NE(page.find("<td>peak_phi_deg</td>"), std::string::npos) << page;
  EXPECT_NE(page.find("src=\"analysis/figures/ladder_case_nd_0_5.png\""), std::string::npos) << page;
  // The end tolerance, set: in the ladder's study file, the certificate, its page and convergence.csv.
  EXPECT_NE(qsdem_test::slurp(dir_ / "wide" / "study.toml").find("ev_end_tolerance = 1"), std::string::npos);
  EXPECT_EQ(c["ladder"]["tolerances"]["ev_end_tolerance"].get<double>(), 1.0);
  EXPECT_TRUE(c["ladder"]["rungs"][0]["ev_end_to_slowest"]["rms"].is_number());
  EXPECT_NE(page.find("Δεv at the end to the slowest (%)"), std::string::npos) << page;
  const std::string csv = qsdem_test::slurp(dir_ / "wide" / "analysis" / "convergence.csv");
  EXPECT_NE(csv.substr(0, csv.find('\n')).find(",ev_end_to_slowest,ev_end_to_slowest_error,ev_end_to_slowest_excess"),
            std::string::npos)
      << csv;
}

// Tolerances no two rates meet: every rung runs, the certificate is "not converged" (exit 4),
// and running the same command again continues the directory without a new run.
TEST_F(Converge, RunsToTheLastRungWhenNotConvergedAndContinues) {
  const std::vector<std::string> opts{"--rungs", "3", "--phi-tolerance", "1e-9", "--ev-tolerance", "1e-12"};
  const Result r = ladder("tight", opts);
  ASSERT_EQ(r.code, 4) << r.err << r.out;
  json c = certificate("tight");
  EXPECT_EQ(c["status"], "not converged");
  EXPECT_EQ(c["stopped_by"], "the last rung");
  EXPECT_TRUE(c["certified_rate"].is_null());
  EXPECT_EQ(c["rates_run"].size(), 3u);
  EXPECT_EQ(runs_made("tight"), 6);
  const auto stamp = fs::last_write_time(dir_ / "tight" / "runs" / "case-seed1" / "nd" / "xi-0.5%" / "rate-3.125e-05" /
                                         "summary.json");
  const Result again = ladder("tight", opts);
  EXPECT_EQ(again.code, 4) << again.err;
  EXPECT_EQ(fs::last_write_time(dir_ / "tight" / "runs" / "case-seed1" / "nd" / "xi-0.5%" / "rate-3.125e-05" /
                                "summary.json"),
            stamp);
  EXPECT_EQ(certificate("tight")["ladder"]["rungs"], c["ladder"]["rungs"]);
  // Other options in the same directory would mix two ladders.
  const Result other = ladder("tight", {"--rungs", "4"});
  EXPECT_EQ(other.code, 2);
  EXPECT_NE(other.err.find("holds another ladder or study"), std::string::npos) << other.err;
}

// A budget that holds two rungs (2 x (250 + 500) steps) but not the third (2 x 1000 more) stops the
// ladder after two with an honest "not converged"; one that cannot hold two is refused up front.
TEST_F(Converge, StepBudgetStopsTheLadder) {
  const Result r = ladder("budget", {"--rungs", "4", "--phi-tolerance", "1e-9", "--max-steps", "3000"});
  ASSERT_EQ(r.code, 4) << r.err << r.out;
  const json c = certificate("budget");
  EXPECT_EQ(c["stopped_by"], "the step budget");
  EXPECT_EQ(c["rates_run"].size(), 2u);
  EXPECT_NE(c["reason"].get<std::string>().find("--max-steps"), std::string::npos) << c["reason"];
  const Result small = ladder("small", {"--max-steps", "1000"});
  EXPECT_EQ(small.code, 2);
  EXPECT_NE(small.err.find("--max-steps = 1000: the first two rungs alone take 1500 steps"), std::string::npos)
      << small.err;
  EXPECT_FALSE(fs::exists(dir_ / "small"));
}

TEST_F(Converge, BadOptionsAreRefusedNamingTheOption) {
  for (const auto& [opts, says] : std::vector<std::pair<std::vector<std::string>, std::string>>{
           {{"--factor", "1"}, "--factor = 1: allowed: a number > 1"},
           {{"--rungs", "1"}, "--rungs = 1: allowed: an integer in [2, 30]"},
           {{"--phi-tolerance", "0"}, "--phi-tolerance = 0"},
           {{"--start-rate=-1"}, "--start-rate = -1"},
           {{"--ev-end-tolerance", "0"}, "--ev-end-tolerance = 0: allowed: a ratio > 0"}}) {
    const Result r = ladder("bad", opts);
    EXPECT_EQ(r.code, 2) << opts[0];
    EXPECT_NE(r.err.find(says), std::string::npos) << r.err;
  }
  EXPECT_FALSE(fs::exists(dir_ / "bad"));
}

// The tiny case written as its two [[phase]] tables: the ladder varies the last phase's keys
// (phase.1.damping.*, phase.1.strain_rate.33) and its runs are those of the [compaction] and
// [triaxial] case bit for bit, so the two certificates agree to the last digit.
TEST_F(Converge, APhaseListCaseGivesTheCertificateOfItsTables) {
  std::string text = qsdem_test::tiny_case("converge-tiny");
  text = text.substr(0, text.find("[damping]")) + R"([[phase]]
name = "compaction"
friction = 0.2
damping = { model = "nd", ratio = "0.5 %" }
stress = { 11 = "390 kPa", 22 = "390 kPa", 33 = "390 kPa", 12 = "0 Pa", 13 = "0 Pa", 23 = "0 Pa" }
servo = { max_strain_rate = 1e-3 }
stop = { max_steps = 2000000, equilibrium = { stress_tolerance = 0.01, ufr = 0.01, every = 200 } }
output = { file = "compaction.csv", clock = "run", every_steps = 200 }
[[phase]]
name = "triaxial"
friction = 0.5
damping = { model = "nd", ratio = "0.5 %" }
stress = { 11 = "390 kPa", 22 = "390 kPa" }
strain_rate = { 33 = 1.25e-4 }
servo = { rate_factor = 10 }
stop = { strain = { 33 = "1 %" } }
output = { file = "series.csv", points = 10 }
)";
  const std::vector<std::string> opts{"--rungs", "2", "--phi-tolerance", "1e-9", "--ev-tolerance", "1e-12"};
  ASSERT_EQ(ladder("tables", opts).code, 4);
  case_ = dir_ / "phases.toml";
  std::ofstream(case_) << text;
  const Result r = ladder("phases", opts);
  ASSERT_EQ(r.code, 4) << r.err << r.out;
  json phases = certificate("phases")["ladder"]["rungs"], tables = certificate("tables")["ladder"]["rungs"];
  for (json* rungs : {&phases, &tables})
    for (json& rung : *rungs) rung.erase("wall_s");  // the runs' wall time, their only difference
  EXPECT_EQ(phases, tables);
  const fs::path run = fs::path("runs") / "case-seed2" / "nd" / "xi-0.5%" / "rate-6.25e-05";
  EXPECT_EQ(qsdem_test::slurp(dir_ / "phases" / run / "series.csv"), qsdem_test::slurp(dir_ / "tables" / run / "series.csv"));
  // The rung's rate went in through the phase's own key.
  const json written = json::parse(qsdem_test::slurp(dir_ / "phases" / run / "summary.json"))["config"]["as_written"];
  EXPECT_EQ(written["phase"][1]["strain_rate"]["33"].get<double>(), 6.25e-5) << written.dump();
}
