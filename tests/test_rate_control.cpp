// The rate controller (docs/physics.md 8.5) on a 200-sphere sample: the index it holds stays in a
// band set by the index's own noise, measured at a constant rate; the rates stay within their
// bounds and change by at most the allowed factor per point; a stopped and resumed run gives the
// same bits; summary.json's figures are those of series.csv.
#include <gtest/gtest.h>
#include <signal.h>
#include <unistd.h>

#include <chrono>
#include <cmath>
#include <filesystem>
#include <fstream>
#include <nlohmann/json.hpp>
#include <sstream>
#include <string>
#include <thread>
#include <vector>

#include "qsdem/config.hpp"
#include "qsdem/types.hpp"
#include <fmt/format.h>
#include <iostream>
#include "test_support.hpp"

using namespace qsdem;
namespace fs = std::filesystem;
using qsdem_test::slurp;

namespace {

// 200 spheres (as tests/test_phases.cpp), compacted fast; a 3 % triaxial test of 60 rows.
const char* head = R"(
name = "rate"
[material]
density = "2650 kg/m^3"
young_modulus = "78 GPa"
poisson_ratio = 0.3
[sample]
seed = 3
[[sample.particles]]
diameter = "2 mm"
count = 150
[[sample.particles]]
diameter = "2.4 mm"
count = 50
[compaction]
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

struct Csv {
  std::vector<std::string> header;
  std::vector<std::vector<double>> rows;
  std::size_t col(const std::string& name) const {
    for (std::size_t k = 0; k < header.size(); ++k)
      if (header[k] == name) return k;
    ADD_FAILURE() << "no column " << name;
    return 0;
  }
  std::vector<double> column(const std::string& name) const {
    std::vector<double> v;
    const std::size_t c = col(name);
    for (const auto& r : rows) v.push_back(r.at(c));
    return v;
  }
};

Csv read_csv(const fs::path& p) {
  Csv t;
  std::istringstream in(slurp(p));
  std::string line;
  if (std::getline(in, line)) {
    std::stringstream s(line);
    for (std::string cell; std::getline(s, cell, ',');) t.header.push_back(cell);
  }
  while (std::getline(in, line)) {
    std::vector<double> row;
    std::stringstream s(line);
    for (std::string cell; std::getline(s, cell, ',');) row.push_back(std::stod(cell));
    t.rows.push_back(row);
  }
  return t;
}

long lines(const fs::path& p) {
  std::ifstream in(p);
  long n = 0;
  for (std::string l; std::getline(in, l);) ++n;
  return n;
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
  const fs::path case_path = case_file("controlled", controlled());
  const fs::path ref = scratch("controlled"), stopped = scratch("controlled-stopped");
  run(case_path, ref);
  run(case_path, stopped, 22);
  for (const char* f : {"series.csv", "final.packing"})
    EXPECT_EQ(slurp(ref / f), slurp(stopped / f)) << f << " differs after a stop and resume";
  EXPECT_EQ(summary(ref)["triaxial"]["controller"], summary(stopped)["triaxial"]["controller"]);

  const Csv s = read_csv(ref / "series.csv");
  ASSERT_EQ(s.header.back(), "strain_rate");
  ASSERT_EQ(s.rows.size(), 60u);
  const std::vector<double> imom = s.column("imom"), rate = s.column("strain_rate"), e1 = s.column("e1");
  const double target = 0.03, band = 1.5;
  for (std::size_t k = 0; k < rate.size(); ++k) {
    EXPECT_GE(rate[k], 1e-6) << "row " << k + 1;
    EXPECT_LE(rate[k], 1e-3) << "row " << k + 1;
    if (k > 0) {
      EXPECT_LE(std::abs(std::log(rate[k] / rate[k - 1])), std::log(2.0) + 1e-9) << "row " << k + 1;
    }
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
