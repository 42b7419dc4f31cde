// `qsdem plot DIR` and the page `qsdem run` draws at its end (docs/runs.md): every figure of a run's
// files written, non-empty, its SVG well-formed XML with a plotted path per curve, the page naming
// every figure; a missing column skips its figures with a note; a directory that is not a run's is
// refused naming what is missing; a run without gnuplot still succeeds and says how to draw later.
#include <gtest/gtest.h>
#include <unistd.h>

#include <algorithm>
#include <cstdio>
#include <cstdlib>
#include <filesystem>
#include <fstream>
#include <map>
#include <regex>
#include <sstream>
#include <string>
#include <vector>

#include <fmt/format.h>

#include "test_support.hpp"

namespace fs = std::filesystem;
using qsdem_test::Cli;
using qsdem_test::slurp;

namespace {

const std::string binary = QSDEM_BINARY;

fs::path scratch(const std::string& name) {
  const fs::path d = fs::temp_directory_path() / ("qsdem_plot_" + name + "_" + std::to_string(::getpid()));
  fs::remove_all(d);
  fs::create_directories(d);
  return d;
}

Cli qsdem(const std::vector<std::string>& args, const fs::path& log) {
  std::vector<std::string> all{binary};
  all.insert(all.end(), args.begin(), args.end());
  return qsdem_test::finish(qsdem_test::spawn_logged(all, log), log);
}

// The tiny case of the process tests (120 spheres, 10 rows) with a cyclic phase and a monotonic one
// after its compaction, both writing series.csv (so it gets a `phase` column): two cycles between
// e1 = 0.1 % and 0.3 %, then 1 % of axial strain.
std::string phase_case() {
  return "name = \"plot-phases\"\n" + qsdem_test::small_case_material + R"([sample]
seed = 1
initial_solid_fraction = 0.2
[[sample.particles]]
diameter = "2.4 mm"
count = 60
[[sample.particles]]
diameter = "2.0 mm"
count = 60
[[phase]]
name = "compaction"
friction = 0.2
stress = { 11 = "200 kPa", 22 = "200 kPa", 33 = "200 kPa", 12 = "0 Pa", 13 = "0 Pa", 23 = "0 Pa" }
servo = { max_strain_rate = 1e-3 }
stop = { equilibrium = { ufr = "1 %" } }
output = { file = "compaction.csv", clock = "run" }
[[phase]]
name = "cyclic"
friction = 0.5
strain_rate = { 33 = 1e-4 }
stress = { 11 = "200 kPa", 22 = "200 kPa" }
controller = { kind = "cyclic", strain_mean = 0.002, strain_amplitude = 0.001, cycles = 2 }
output = { every_steps = 5 }
[[phase]]
name = "shear"
friction = 0.5
strain_rate = { 33 = 1e-4 }
stress = { 11 = "200 kPa", 22 = "200 kPa" }
stop = { strain = { 33 = "1 %" } }
output = { points = 20 }
)";
}

// Each SVG's paths with at least `min_segments` line-to commands (a curve of that many points
// plus one; the frame has 4, grid lines and key samples 1), by Python's XML parser, which fails
// on a file that is not well-formed: "NAME COUNT" per file, or "NAME not XML: why".
std::map<std::string, int> plotted_paths(const std::vector<fs::path>& svgs, int min_segments) {
  std::string cmd = fmt::format(
      "python3 -c 'import sys, xml.etree.ElementTree as E\n"
      "for f in sys.argv[2:]:\n"
      "  try:\n"
      "    t = E.parse(f)\n"
      "  except Exception as e:\n"
      "    print(f, \"not XML:\", e); continue\n"
      "  print(f, sum(1 for p in t.iter(\"{{http://www.w3.org/2000/svg}}path\") if p.get(\"d\", \"\").count(\"L\") >= "
      "int(sys.argv[1])))' {}",
      min_segments);
  for (const fs::path& s : svgs) cmd += " '" + s.string() + "'";
  std::map<std::string, int> counts;
  if (FILE* p = ::popen((cmd + " 2>&1").c_str(), "r")) {
    char line[4096];
    while (std::fgets(line, sizeof line, p)) {
      const std::string l = line;
      const auto space = l.find(' ');
      const std::string name = fs::path(l.substr(0, space)).filename().string();
      try {
        counts[name] = std::stoi(l.substr(space + 1));
      } catch (...) {
        ADD_FAILURE() << l;
      }
    }
    ::pclose(p);
  }
  return counts;
}

// The curves of a figure's data file with at least `points` points (blocks of NAME.dat).
int curves_with(const fs::path& dat, int points) {
  std::istringstream in(slurp(dat));
  int curves = 0, n = 0;
  for (std::string line; std::getline(in, line);) {
    if (line.rfind("# ", 0) == 0) {
      curves += n >= points, n = 0;
    } else if (!line.empty()) {
      ++n;
    }
  }
  return curves + (n >= points);
}

bool has_python() { return std::system("python3 -c 'import xml.etree.ElementTree' > /dev/null 2>&1") == 0; }
bool has_gnuplot() { return std::system("gnuplot --version > /dev/null 2>&1") == 0; }

// One run of the tiny case by the CLI, which draws its page at its end; shared by the tests.
class PlotRun : public ::testing::Test {
 protected:
  static void SetUpTestSuite() {
    root_ = new fs::path(scratch("run"));
    std::ofstream(*root_ / "tiny.toml") << qsdem_test::tiny_case("plot-tiny");
    *cli_ = qsdem({"run", (*root_ / "tiny.toml").string(), "--out", (*root_ / "run").string(), "--quiet", "-t", "1"},
                  *root_ / "run-log");
  }
  static void TearDownTestSuite() {
    fs::remove_all(*root_);
    delete root_;
  }
  static fs::path* root_;
  static Cli* cli_;
};
fs::path* PlotRun::root_ = nullptr;
Cli* PlotRun::cli_ = new Cli;

const std::vector<std::string> tiny_figures = {
    "compaction_stress_strain", "compaction_stress_path", "compaction_equilibrium", "compaction_fabric",
    "series_stress_strain",     "series_stress_path",     "series_equilibrium",     "series_fabric",
    "classes_compaction",       "classes_triaxial"};

}  // namespace

TEST_F(PlotRun, RunDrawsEveryFigureAndItsPage) {
  if (!has_gnuplot()) GTEST_SKIP() << "gnuplot absent (scripts/install-deps installs it)";
  ASSERT_EQ(cli_->code, 0) << cli_->err;
  const fs::path plot = *root_ / "run" / "plot";
  EXPECT_NE(cli_->out.find("Figures in " + (plot / "index.html").string()), std::string::npos) << cli_->out;
  const std::string html = slurp(plot / "index.html");
  std::vector<fs::path> svgs;
  for (const std::string& f : tiny_figures) {
    for (const char* ext : {".png", ".svg", ".dat", ".gp"})
      EXPECT_GT(fs::file_size(plot / (f + ext)), 100u) << f << ext;
    EXPECT_EQ(slurp(plot / (f + ".png")).substr(0, 8), "\x89PNG\r\n\x1a\n") << f;
    EXPECT_NE(html.find("<img src=\"" + f + ".png\""), std::string::npos) << f;
    EXPECT_NE(html.find("<a href=\"" + f + ".svg\">SVG</a>"), std::string::npos) << f;
    svgs.push_back(plot / (f + ".svg"));
  }
  // Exactly these figures: the page shows every image of the directory, no more.
  int pngs = 0;
  for (const auto& e : fs::directory_iterator(plot)) pngs += e.path().extension() == ".png";
  EXPECT_EQ(pngs, static_cast<int>(tiny_figures.size()));
  // The 10 rows of series.csv: each curve of 10 points is a path of 9 line-tos in its SVG.
  if (!has_python()) GTEST_SKIP() << "python3 absent: the SVGs are not parsed";
  const auto counts = plotted_paths(svgs, 9);
  for (const std::string& f : tiny_figures) {
    ASSERT_TRUE(counts.count(f + ".svg")) << f;
    const int curves = curves_with(plot / (f + ".dat"), 10);
    EXPECT_GT(curves, 0) << f;
    EXPECT_GE(counts.at(f + ".svg"), curves) << f;
  }
  // The q/p panel of series.csv is q_Pa / p_Pa of its rows.
  const qsdem_test::Csv s = qsdem_test::read_csv(*root_ / "run" / "series.csv");
  const std::string dat = slurp(plot / "series_stress_strain.dat");
  EXPECT_NE(dat.find(fmt::format("{:.9g} {:.9g}\n", 100 * s.at(3, "e1"), s.at(3, "q_Pa") / s.at(3, "p_Pa"))),
            std::string::npos);
}

// The page a browser renders with every figure decoded (as the study's report).
TEST_F(PlotRun, PageRendersInHeadlessChromium) {
  if (!fs::exists("/usr/bin/chromium")) GTEST_SKIP() << "/usr/bin/chromium absent (scripts/install-deps installs it)";
  if (!has_gnuplot()) GTEST_SKIP() << "gnuplot absent";
  ASSERT_EQ(cli_->code, 0) << cli_->err;
  const fs::path profile = scratch("chromium-profile");
  const std::string cmd = fmt::format(
      "timeout 120 /usr/bin/chromium --headless --no-sandbox --disable-gpu --disable-quic --no-first-run "
      "--disable-background-networking --disable-component-update --disable-sync --user-data-dir='{}' "
      "--virtual-time-budget=10000 --dump-dom 'file://{}' 2>/dev/null",
      profile.string(), fs::absolute(*root_ / "run" / "plot" / "index.html").string());
  std::string dom;
  if (FILE* p = ::popen(cmd.c_str(), "r")) {
    char buf[4096];
    std::size_t n;
    while ((n = std::fread(buf, 1, sizeof buf, p)) > 0) dom.append(buf, n);
    ::pclose(p);
  }
  fs::remove_all(profile);
  std::smatch loaded, total;
  ASSERT_TRUE(std::regex_search(dom, loaded, std::regex("data-images-loaded=\"([0-9]+)\"")))
      << "no count in the DOM (script did not run?): " << dom.substr(0, 400);
  ASSERT_TRUE(std::regex_search(dom, total, std::regex("data-images-total=\"([0-9]+)\"")));
  EXPECT_EQ(std::stoi(total[1]), static_cast<int>(tiny_figures.size()));
  EXPECT_EQ(loaded[1], total[1]);
}

// A file without some columns (of an older or another writer): the figures that need them are left
// out, named on the page and by the command, and the others drawn, each from its own columns.
TEST_F(PlotRun, AMissingColumnSkipsItsFigureWithANote) {
  if (!has_gnuplot()) GTEST_SKIP() << "gnuplot absent";
  ASSERT_EQ(cli_->code, 0) << cli_->err;
  const fs::path d = *root_ / "edited";
  fs::create_directories(d);
  const qsdem_test::Csv s = qsdem_test::read_csv(*root_ / "run" / "series.csv");
  std::string text;
  const auto keep = [](const std::string& name) { return name != "q_Pa" && name != "cn" && name != "fabric_22"; };
  for (std::size_t k = 0; k < s.header.size(); ++k)
    if (keep(s.header[k])) text += (text.empty() ? "" : ",") + s.header[k];
  text += "\n";
  for (std::size_t r = 0; r < s.rows.size(); ++r) {
    std::string row;
    for (std::size_t k = 0; k < s.header.size(); ++k) {
      if (!keep(s.header[k])) continue;
      // fabric_11 replaced by known values, to find in the figure's data
      const std::string v = s.header[k] == "fabric_11" ? fmt::format("{}", 0.3 + 0.01 * static_cast<double>(r)) : s.rows[r][k];
      row += (row.empty() ? "" : ",") + v;
    }
    text += row + "\n";
  }
  std::ofstream(d / "series.csv") << text;
  const Cli c = qsdem({"plot", d.string()}, *root_ / "edited-log");
  ASSERT_EQ(c.code, 0) << c.err;
  EXPECT_NE(c.out.find("not drawn: series.csv: q/p: no column q/p"), std::string::npos) << c.out;
  EXPECT_NE(c.out.find("coordination number: no column cn"), std::string::npos) << c.out;
  EXPECT_NE(c.out.find("series.csv (triaxial): stress path: no column q_Pa"), std::string::npos) << c.out;
  EXPECT_NE(c.out.find("φ22: no column fabric_22"), std::string::npos) << c.out;
  const fs::path plot = d / "plot";
  EXPECT_FALSE(fs::exists(plot / "series_stress_path.png"));  // its only panel needs q_Pa
  for (const char* f : {"series_stress_strain", "series_equilibrium", "series_fabric"})
    EXPECT_GT(fs::file_size(plot / (std::string(f) + ".png")), 100u) << f;
  EXPECT_NE(slurp(plot / "series_fabric.dat").find(fmt::format("{:.9g} 0.3\n", 100 * s.at(0, "e1"))),
            std::string::npos);  // the first row
  const std::string html = slurp(plot / "index.html");
  EXPECT_NE(html.find("no column cn"), std::string::npos);
  EXPECT_NE(html.find("No summary.json"), std::string::npos);
}

// A directory that is not a run's is refused (exit 2), naming what it lacks; nothing is written.
TEST(Plot, ADirectoryWithoutSeriesIsRefused) {
  const fs::path d = scratch("empty");
  std::ofstream(d / "notes.txt") << "not a run\n";
  Cli c = qsdem({"plot", d.string()}, d / "log");
  EXPECT_EQ(c.code, 2);
  EXPECT_NE(c.err.find("'" + d.string() + "' is not a run directory"), std::string::npos) << c.err;
  EXPECT_NE(c.err.find("series.csv: not in the directory"), std::string::npos) << c.err;
  EXPECT_NE(c.err.find("no summary.json"), std::string::npos) << c.err;
  EXPECT_FALSE(fs::exists(d / "plot"));
  c = qsdem({"plot", (d / "absent").string()}, d / "log2");
  EXPECT_EQ(c.code, 2);
  EXPECT_NE(c.err.find("is not a directory"), std::string::npos) << c.err;
  c = qsdem({"plot"}, d / "log3");
  EXPECT_EQ(c.code, 1);
  EXPECT_NE(c.err.find("dir is required"), std::string::npos) << c.err;
  fs::remove_all(d);
}

// Without gnuplot a run still ends well (exit 0) and says how to draw its figures later, and
// `qsdem plot` names the package; a run with --force removes the page of the run it replaces, and
// with --no-plot draws none and says how to.
TEST(Plot, ARunWithoutGnuplotSaysHowToDrawItLater) {
  const fs::path d = scratch("nognuplot");
  std::ofstream(d / "tiny.toml") << qsdem_test::tiny_case("plot-nognuplot");
  const std::string saved = std::getenv("PATH") ? std::getenv("PATH") : "";
  ::setenv("PATH", "/nonexistent-qsdem-test", 1);
  const Cli c = qsdem({"run", (d / "tiny.toml").string(), "--out", (d / "run").string(), "--quiet", "-t", "1"},
                      d / "run-log");
  const Cli p = qsdem({"plot", (d / "run").string()}, d / "plot-log");
  ::setenv("PATH", saved.c_str(), 1);
  ASSERT_EQ(c.code, 0) << c.err;
  EXPECT_NE(c.out.find("gnuplot is not installed"), std::string::npos) << c.out;
  EXPECT_NE(c.out.find("qsdem plot " + (d / "run").string()), std::string::npos) << c.out;
  EXPECT_FALSE(fs::exists(d / "run" / "plot"));
  EXPECT_EQ(p.code, 3);
  EXPECT_NE(p.err.find("gnuplot-nox"), std::string::npos) << p.err;
  if (!has_gnuplot()) GTEST_SKIP() << "gnuplot absent";
  ASSERT_EQ(qsdem({"plot", (d / "run").string()}, d / "plot-log2").code, 0);
  ASSERT_TRUE(fs::exists(d / "run" / "plot" / "index.html"));
  const Cli n = qsdem({"run", (d / "tiny.toml").string(), "--out", (d / "run").string(), "--quiet", "-t", "1",
                       "--force", "--no-plot"},
                      d / "no-plot-log");
  ASSERT_EQ(n.code, 0) << n.err;
  EXPECT_NE(n.out.find("Figures: qsdem plot " + (d / "run").string()), std::string::npos) << n.out;
  EXPECT_FALSE(fs::exists(d / "run" / "plot"));
  fs::remove_all(d);
}

// A [[phase]] run whose cyclic and monotonic phases share series.csv: a curve per phase in each
// figure of the file, and the loops of the cyclic phase, a curve per cycle, cut at its top corners.
TEST(Plot, PhasesShareAFigureAndACyclicPhaseItsLoops) {
  if (!has_gnuplot()) GTEST_SKIP() << "gnuplot absent";
  const fs::path d = scratch("phases");
  std::ofstream(d / "phases.toml") << phase_case();
  const Cli c = qsdem({"run", (d / "phases.toml").string(), "--out", (d / "run").string(), "--quiet", "-t", "1"},
                      d / "run-log");
  ASSERT_EQ(c.code, 0) << c.err;
  const fs::path plot = d / "run" / "plot";
  const std::string dat = slurp(plot / "series_stress_strain.dat");
  EXPECT_NE(dat.find("# cyclic\n"), std::string::npos);
  EXPECT_NE(dat.find("# shear\n"), std::string::npos);
  const std::string loops = slurp(plot / "series_loops_cyclic.dat");
  for (const char* k : {"# loading\n", "# cycle 1\n", "# cycle 2\n"}) EXPECT_NE(loops.find(k), std::string::npos) << k;
  EXPECT_EQ(loops.find("# cycle 3\n"), std::string::npos);
  // Each cycle starts and ends at a top corner, e1 = 0.3 %, within the 5 steps of 0.0032 % between rows.
  std::istringstream in(loops);
  std::vector<std::pair<double, double>> cycle1;
  bool in1 = false;
  for (std::string line; std::getline(in, line);) {
    if (line.rfind("# ", 0) == 0) in1 = line == "# cycle 1";
    else if (in1 && !line.empty()) cycle1.emplace_back(std::stod(line), std::stod(line.substr(line.find(' '))));
  }
  ASSERT_GT(cycle1.size(), 20u);
  EXPECT_NEAR(cycle1.front().first, 0.3, 0.017);
  EXPECT_NEAR(cycle1.back().first, 0.3, 0.017);
  double lo = 1;
  for (const auto& [e1, q] : cycle1) lo = std::min(lo, e1);
  EXPECT_NEAR(lo, 0.1, 0.017);  // its bottom corner
  const std::string html = slurp(plot / "index.html");
  EXPECT_NE(html.find("Cycles of phase cyclic"), std::string::npos);
  EXPECT_NE(html.find("series_loops_cyclic.png"), std::string::npos);
  fs::remove_all(d);
}
