// `qsdem study` (docs/study.md): the study file's checks, the directory layout (the contract with
// the analysis), resuming after SIGTERM, failed runs, and MPI ranks; all with real processes.
#include <fcntl.h>
#include <gtest/gtest.h>
#include <spawn.h>
#include <sys/file.h>
#include <sys/stat.h>
#include <sys/wait.h>
#include <unistd.h>

#include <algorithm>
#include <chrono>
#include <csignal>
#include <cstdlib>
#include <filesystem>
#include <fstream>
#include <map>
#include <optional>
#include <regex>
#include <set>
#include <nlohmann/json.hpp>
#include <sstream>
#include <string>
#include <thread>
#include <vector>

#include <fmt/format.h>

#include "qsdem/engine/types.hpp"
#include "qsdem/study/study.hpp"
#include "qsdem/study/study_analysis.hpp"
#include "qsdem/version.hpp"
#include "test_support.hpp"

extern char** environ;

namespace fs = std::filesystem;

namespace {

const std::string binary = QSDEM_BINARY;
const fs::path source_dir = QSDEM_SOURCE_DIR;
const fs::path tiny_study = source_dir / "studies" / "tiny.toml";

using qsdem_test::slurp;

void write(const fs::path& p, const std::string& text) {
  std::ofstream out(p, std::ios::binary);
  out << text;
}

fs::path fresh_dir(const std::string& name) {
  const fs::path dir = fs::temp_directory_path() / ("qsdem_study_" + name + "_" + std::to_string(::getpid()));
  fs::remove_all(dir);
  fs::create_directories(dir);
  return dir;
}

using Result = qsdem_test::Cli;
using qsdem_test::finish;

// Starts `args` (args[0] is looked up in PATH) with stdout and stderr in files next to `log`.
pid_t spawn(const std::vector<std::string>& args, const fs::path& log) { return qsdem_test::spawn_logged(args, log); }

Result run(const std::vector<std::string>& args, const fs::path& log) { return finish(spawn(args, log), log); }

Result study(const fs::path& file, const fs::path& out, const fs::path& log, bool quiet = true) {
  std::vector<std::string> args{binary, "study", file.string(), "--out", out.string()};
  if (quiet) args.push_back("--quiet");
  return run(args, log);
}

// A study that completed: every run finished and the analysis succeeded.
bool completed(const Result& r) { return r.code == 0; }

nlohmann::json manifest(const fs::path& dir) { return nlohmann::json::parse(slurp(dir / "study.json")); }

// The analysis tables without their wall-time columns (wall time is not reproducible).
std::map<std::string, std::string> analysis_tables(const fs::path& dir) {
  std::map<std::string, std::string> out;
  if (!fs::exists(dir / "analysis")) return out;
  for (const auto& e : fs::directory_iterator(dir / "analysis")) {
    if (e.path().extension() != ".csv") continue;
    std::ifstream in(e.path());
    std::string table;
    std::vector<bool> keep;
    for (std::string line; std::getline(in, line);) {
      std::vector<std::string> cells;
      std::stringstream ss(line);
      for (std::string c; std::getline(ss, c, ',');) cells.push_back(c);
      if (keep.empty())
        for (const auto& c : cells) keep.push_back(c.find("wall") == std::string::npos);
      for (std::size_t k = 0; k < cells.size(); ++k)
        if (k >= keep.size() || keep[k]) table += cells[k] + ",";
      table += "\n";
    }
    out[e.path().filename().string()] = table;
  }
  return out;
}

// An uninterrupted study of a shipped file, run once per build and shared by the tests (and by the
// processes of a parallel ctest, under a lock): DIR, the exit code and stderr.
struct Reference {
  fs::path dir;
  Result result;
};

Reference run_reference(const fs::path& file) {
  struct stat st {};
  ::stat(binary.c_str(), &st);
  const fs::path base = fs::temp_directory_path() /
                        ("qsdem_study_reference_" + std::to_string(::getuid()) + "_" + file.stem().string() + "_" +
                         std::to_string(std::hash<std::string>{}(slurp(file))) + "_" +
                         std::to_string(st.st_mtim.tv_sec) + "_" + std::to_string(st.st_mtim.tv_nsec) + "_" +
                         std::to_string(st.st_size));
  fs::create_directories(base);
  const int lock = ::open((base / "lock").c_str(), O_RDWR | O_CREAT, 0644);
  ::flock(lock, LOCK_EX);
  Reference r;
  r.dir = base / "study";
  const fs::path done = base / "done.json";
  if (fs::exists(done)) {
    const auto j = nlohmann::json::parse(slurp(done));
    r.result.code = j["code"];
    r.result.err = j["err"];
  } else {
    fs::remove_all(r.dir);
    r.result = study(file, r.dir, base / "log", false);
    write(done, nlohmann::json{{"code", r.result.code}, {"err", r.result.err}}.dump());
  }
  ::flock(lock, LOCK_UN);
  ::close(lock);
  return r;
}

const Reference& reference() {
  static const Reference ref = run_reference(tiny_study);
  return ref;
}

const fs::path staged_study = source_dir / "studies" / "tiny-staged.toml";

const Reference& staged_reference() {
  static const Reference ref = run_reference(staged_study);
  return ref;
}

}  // namespace

// Bad study files: exit code 2 and one message naming the file, the key and the value.
TEST(StudyCli, BadStudyFilesExitTwoNamingKeyAndValue) {
  const fs::path dir = fresh_dir("bad");
  const std::string sample = "[[sample]]\nname = \"s\"\ncase = \"" + (source_dir / "examples/spheres-A-small.toml").string() +
                             "\"\n";
  const std::string design = "[design]\nmodels = [\"nd\"]\ndamping_ratios = [\"0.5 %\"]\nstrain_rates = [1e-5]\n";
  const std::string stage_design = "[design]\nmodels = [\"nd\"]\n";
  const std::string sweep = "[[stage]]\nname = \"sweep\"\ndamping_ratios = [\"0.5 %\", \"1 %\"]\nstrain_rates = [1e-5]\n";
  const std::string sweep_nd =
      "[[stage]]\nname = \"sweep\"\nmodels = [\"nd\"]\ndamping_ratios = [\"0.5 %\"]\nstrain_rates = [1e-5]\n";
  struct Case {
    const char* what;
    std::string text;
    std::vector<std::string> expect;
  };
  const std::vector<Case> cases = {
      {"unknown key", sample + design + "model = \"od\"\n", {"unknown key 'design.model'"}},
      {"unknown section", sample + design + "[executon]\n", {"unknown key 'executon'"}},
      {"wrong type", sample + "[design]\nmodels = [\"nd\"]\ndamping_ratios = [\"0.5 %\"]\nstrain_rates = \"1e-5\"\n",
       {"design.strain_rates", "\"1e-5\"", "expected an array"}},
      {"bad model", sample + "[design]\nmodels = [\"xd\"]\ndamping_ratios = [\"0.5 %\"]\nstrain_rates = [1e-5]\n",
       {"design.models.0", "\"xd\"", "\"od\""}},
      {"negative damping ratio",
       sample + "[design]\nmodels = [\"nd\"]\ndamping_ratios = [\"0.5 %\", -0.001]\nstrain_rates = [1e-5]\n",
       {"design.damping_ratios.1", "-0.001", ">= 0"}},
      {"zero rate", sample + "[design]\nmodels = [\"nd\"]\ndamping_ratios = [\"0.5 %\"]\nstrain_rates = [0.0]\n",
       {"design.strain_rates.0", "= 0", "(0, 0.01)"}},
      {"negative rate", sample + "[design]\nmodels = [\"nd\"]\ndamping_ratios = [\"0.5 %\"]\nstrain_rates = [-1e-5]\n",
       {"design.strain_rates.0", "-1e-05", "(0, 0.01)"}},
      {"missing case file", "[[sample]]\nname = \"s\"\ncase = \"nowhere/missing.toml\"\n" + design,
       {"sample.0.case", "\"nowhere/missing.toml\"", "no such case file"}},
      {"wrong type of parallel_runs", sample + design + "[execution]\nparallel_runs = \"2\"\n",
       {"execution.parallel_runs", "\"2\"", "expected an integer"}},
      {"an order that is not one", sample + design + "[execution]\norder = \"random\"\n",
       {"execution.order", "\"random\"", "longest_first", "shortest_first"}},
      {"a key the study sets", sample + design + "set = [\"damping.ratio=0.3 %\"]\n",
       {"design.set.0", "damping.ratio", "set by the study"}},
      {"a bad override, caught by the case's own checks", sample + design + "set = [\"triaxial.sample_points=0\"]\n",
       {"triaxial.sample_points", "out of range"}},
      {"a bad sample name", "[[sample]]\nname = \"a/b\"\ncase = \"x.toml\"\n" + design, {"sample.0.name", "\"a/b\""}},
      {"no design", sample, {"'design'", "required"}},
      // The model axis: names go through the case parser; a labelled entry names directories.
      {"a model the case parser refuses",
       sample + "[design]\nmodels = [\"nd\", \"local2\"]\ndamping_ratios = [\"0.5 %\"]\nstrain_rates = [1e-5]\n",
       {"design.models.1", "\"local2\"", "refuses it", "damping.model"}},
      {"a labelled entry without a label",
       sample + "[design]\nmodels = [{ set = [\"damping.model=nd\"] }]\ndamping_ratios = [\"0.5 %\"]\nstrain_rates = [1e-5]\n",
       {"design.models.0.label", "required"}},
      {"a label that is no directory name",
       sample + "[design]\nmodels = [{ label = \"a b\" }]\ndamping_ratios = [\"0.5 %\"]\nstrain_rates = [1e-5]\n",
       {"design.models.0.label", "\"a b\"", "names directories"}},
      {"a labelled entry setting the ratio",
       sample + "[design]\nmodels = [{ label = \"x\", set = [\"damping.ratio=1 %\"] }]\ndamping_ratios = [\"0.5 %\"]\n"
                "strain_rates = [1e-5]\n",
       {"design.models.0.set.0", "set by the study"}},
      {"a labelled entry with a bad override",
       sample + "[design]\nmodels = [{ label = \"x\", set = [\"damping.model=xd\"] }]\ndamping_ratios = [\"0.5 %\"]\n"
                "strain_rates = [1e-5]\n",
       {"design.models.0", "refuses it", "\"xd\""}},
      {"two entries with one label",
       sample + "[design]\nmodels = [\"nd\", { label = \"nd\", set = [\"damping.model=od\"] }]\n"
                "damping_ratios = [\"0.5 %\"]\nstrain_rates = [1e-5]\n",
       {"design.models.1", "listed twice"}},
      // Stages.
      {"ratios in [design] and stages", sample + design + "[[stage]]\nname = \"a\"\ndamping_ratios = [0.005]\nstrain_rates = [1e-5]\n",
       {"design.damping_ratios", "each stage gives its own"}},
      {"a stage picking from a stage that does not come before",
       sample + stage_design + "[[stage]]\nname = \"slow\"\ndamping_ratios = { from = \"sweep\" }\nstrain_rates = [1e-6]\n"
                "[[stage]]\nname = \"sweep\"\ndamping_ratios = [0.005]\nstrain_rates = [1e-5]\n",
       {"stage.0.damping_ratios.from", "\"sweep\"", "earlier stage", "there is none"}},
      {"a stage picking from an unknown stage",
       sample + stage_design + sweep + "[[stage]]\nname = \"slow\"\ndamping_ratios = { from = \"swep\" }\nstrain_rates = [1e-6]\n",
       {"stage.1.damping_ratios.from", "\"swep\"", "earlier: \"sweep\""}},
      {"an unknown pick",
       sample + stage_design + sweep +
           "[[stage]]\nname = \"slow\"\ndamping_ratios = { from = \"sweep\", pick = \"best\" }\nstrain_rates = [1e-6]\n",
       {"stage.1.damping_ratios.pick", "\"best\"", "\"optimum+neighbours\""}},
      {"an optimum at a rate the source did not run",
       sample + stage_design + sweep +
           "[[stage]]\nname = \"slow\"\ndamping_ratios = { from = \"sweep\", at_rate = 3e-6 }\nstrain_rates = [1e-6]\n",
       {"stage.1.damping_ratios.at_rate", "no run at this rate"}},
      {"a bad rate of a picking stage",
       sample + stage_design + sweep + "[[stage]]\nname = \"slow\"\ndamping_ratios = { from = \"sweep\" }\nstrain_rates = [0.5]\n",
       {"stage.1.strain_rates.0", "(0, 0.01)"}},
      {"a picking stage with a model its source lacks",
       sample + "[design]\nmodels = [\"nd\", \"od\"]\n" + sweep_nd +
           "[[stage]]\nname = \"slow\"\ndamping_ratios = { from = \"sweep\" }\nstrain_rates = [1e-6]\n",
       {"stage.1.damping_ratios.from", "does not run every model"}},
      {"a stage with a model not in the design",
       sample + stage_design + "[[stage]]\nname = \"a\"\nmodels = [\"od\"]\ndamping_ratios = [0.005]\nstrain_rates = [1e-5]\n",
       {"stage.0.models.0", "\"od\"", "\"nd\""}},
      {"a stage with runs and a grid",
       sample + stage_design + "[[stage]]\nname = \"a\"\nstrain_rates = [1e-5]\nruns = [{ model = \"nd\", ratio = 0, rate = 1e-5 }]\n",
       {"stage.0.strain_rates", "not both"}},
      {"one run in two stages",
       sample + stage_design + sweep + "[[stage]]\nname = \"again\"\nruns = [{ model = \"nd\", ratio = \"0.5 %\", rate = 1e-5 }]\n",
       {"stage 'again' lists the run", "of stage 'sweep'"}},
      // [analysis].
      {"an unknown baseline", sample + design + "[analysis]\nbaseline = \"od\"\n", {"analysis.baseline", "\"od\""}},
      {"a reference with an unknown model", sample + design + "[analysis]\nreference = { model = \"none\" }\n",
       {"analysis.reference.model", "\"none\""}},
      {"a reference matching no run", sample + design + "[analysis]\nreference = { rate = 1e-6 }\n",
       {"analysis.reference", "matches no run of sample 's'"}},
      {"a reference rule misspelt", sample + design + "[analysis]\nreference = \"least damped\"\n",
       {"analysis.reference", "\"least-damped\""}},
      {"a tolerance of zero", sample + design + "[analysis]\nphi_tolerance_deg = 0\n", {"analysis.phi_tolerance_deg", "> 0"}},
      {"a convergence tolerance below zero", sample + design + "[analysis]\nconvergence = { phi_tolerance_deg = -1 }\n",
       {"analysis.convergence.phi_tolerance_deg", "> 0"}},
      {"an end tolerance of zero", sample + design + "[analysis]\nconvergence = { ev_end_tolerance = 0 }\n",
       {"analysis.convergence.ev_end_tolerance", "> 0"}},
      {"a convergence key misspelt", sample + design + "[analysis]\nconvergence = { phi_tol = 1 }\n",
       {"analysis.convergence.phi_tol"}},
      {"convergence not a table", sample + design + "[analysis]\nconvergence = 0.5\n",
       {"analysis.convergence", "expected a table"}},
      // rate_control: the keys of [triaxial.rate_control], checked by the case parser at this key.
      {"rate_control not a table", sample + design + "rate_control = \"imom\"\n",
       {"design.rate_control", "\"imom\"", "expected a table", "target"}},
      {"rate_control with an unknown index",
       sample + design + "rate_control = { index = \"xyz\", target = \"1 %\", min_rate = 1e-7, max_rate = 1e-4 }\n",
       {"design.rate_control", "refuses it", "\"xyz\"", "\"imom\""}},
      {"rate_control without a target", sample + design + "rate_control = { min_rate = 1e-7, max_rate = 1e-4 }\n",
       {"design.rate_control", "refuses it", "target"}},
      {"rate_control whose bounds exclude the start rate",
       sample + design + "rate_control = { target = \"1 %\", min_rate = 1e-7, max_rate = 5e-6 }\n",
       {"design.rate_control", "start rate 1e-05", "[min_rate, max_rate]"}},
      {"rate_control with an array value", sample + design + "rate_control = { target = [\"1 %\"] }\n",
       {"design.rate_control.target", "expected a string or a number"}},
      {"rate_control in [design] with stages",
       sample + stage_design + "rate_control = { target = \"1 %\", min_rate = 1e-7, max_rate = 1e-4 }\n" + sweep,
       {"design.rate_control", "each stage gives its own"}},
      {"rate_control in design.set", sample + design + "set = [\"triaxial.rate_control={target=\\\"1 %\\\"}\"]\n",
       {"design.set.0", "triaxial.rate_control", "set by the study"}},
      {"a stage's rate_control refused by the case",
       sample + stage_design + sweep + "[[stage]]\nname = \"c\"\ndamping_ratios = [\"0.5 %\"]\nstrain_rates = [1e-5]\n"
                                       "rate_control = { target = \"150 %\", min_rate = 1e-7, max_rate = 1e-4 }\n",
       {"stage.1.rate_control", "refuses it", "target", "(0, 100 %)"}},
      {"a confining stress without a unit", sample + design + "confining_stresses = [\"100 kPa\", \"200\"]\n",
       {"design.confining_stresses.1", "\"200\"", "unit"}},
      {"a confining stress listed twice", sample + design + "confining_stresses = [\"100 kPa\", 100000]\n",
       {"design.confining_stresses.1", "listed twice", "p100kPa"}},
      {"a negative compaction friction", sample + design + "compaction_frictions = [0.1, -0.2]\n",
       {"design.compaction_frictions.1", "-0.2", ">= 0"}},
      {"the axis' key in sample.set",
       "[[sample]]\nname = \"s\"\ncase = \"" + (source_dir / "examples/spheres-A-small.toml").string() +
           "\"\nset = [\"compaction.friction=0.3\"]\n" + design + "compaction_frictions = [0.1]\n",
       {"sample.0.set.0", "compaction.friction", "set by the study"}},
      {"the axis' key in design.set", sample + design + "confining_stresses = [\"1 MPa\"]\nset = [\"triaxial.confining_stress=\\\"2 MPa\\\"\"]\n",
       {"design.set.0", "triaxial.confining_stress", "set by the study"}},
      {"critical_state window out of range", sample + design + "[analysis]\ncritical_state = { from = \"60 %\" }\n",
       {"analysis.critical_state.from", "(0, 50 %)"}},
      {"critical_state key misspelt", sample + design + "[analysis]\ncritical_state = { ev_slop = 0.1 }\n",
       {"analysis.critical_state.ev_slop"}},
      {"two controllers of one index and target at one start rate",
       sample + stage_design +
           "[[stage]]\nname = \"c1\"\ndamping_ratios = [\"0.5 %\"]\nstrain_rates = [1e-5]\n"
           "rate_control = { target = \"1 %\", min_rate = 1e-7, max_rate = 1e-4 }\n"
           "[[stage]]\nname = \"c2\"\ndamping_ratios = [\"0.5 %\"]\nstrain_rates = [1e-5]\n"
           "rate_control = { target = \"1 %\", min_rate = 1e-8, max_rate = 1e-4 }\n",
       {"stage 'c2'", "another rate_control", "rate-1e-05-control-imom-1%"}},
  };
  for (const auto& c : cases) {
    SCOPED_TRACE(c.what);
    const fs::path file = dir / "bad.toml";
    write(file, c.text);
    const Result r = study(file, dir / "out", dir / "log");
    EXPECT_EQ(r.code, 2) << r.err;
    EXPECT_NE(r.err.find("bad.toml"), std::string::npos) << r.err;
    for (const auto& e : c.expect) EXPECT_NE(r.err.find(e), std::string::npos) << "expected '" << e << "' in: " << r.err;
    EXPECT_FALSE(fs::exists(dir / "out")) << "nothing is written for bad input";
  }
  fs::remove_all(dir);
}

// The shipped studies are valid: every case and every override of every run is checked.
TEST(StudyCli, ShippedStudiesAreValid) {
  for (const char* name : {"paper.toml", "paper-small.toml", "tiny.toml", "paper-full.toml", "tiny-staged.toml", "damping-small.toml",
                           "critical-state-small.toml", "tiny-critical-state.toml",
                           "damping-small-B.toml", "damping-seeds.toml", "adaptive-small.toml"}) {
    SCOPED_TRACE(name);
    qsdem::Study s;
    ASSERT_NO_THROW(s = qsdem::load_study(source_dir / "studies" / name));
    EXPECT_FALSE(s.runs.empty());
  }
  const qsdem::Study paper = qsdem::load_study(source_dir / "studies/paper.toml");
  EXPECT_EQ(paper.samples.size(), 2u);
  EXPECT_EQ(paper.runs.size(), 224u);  // 2 samples x 2 models x 14 ratios x 4 rates (SPEC 9)
  const qsdem::Study tiny = qsdem::load_study(tiny_study);
  EXPECT_EQ(tiny.runs.size(), 8u);
  EXPECT_EQ(tiny.runs[0].id, "tiny-seed1/od/xi-0.2%/rate-5e-06");
  EXPECT_DOUBLE_EQ(tiny.runs[0].xi, 0.002);
  EXPECT_DOUBLE_EQ(tiny.runs[0].expected_steps, 6250);  // 1 % / (0.32 x 5e-6)
}

// Seeds multiply the samples; the manifest names every sample and run with its directory.
TEST(StudyCli, SeedsAndManifest) {
  const fs::path dir = fresh_dir("seeds");
  write(dir / "s.toml", "name = \"seeds\"\n[[sample]]\nname = \"A\"\ncase = \"" +
                            (source_dir / "examples/spheres-A-small.toml").string() +
                            "\"\n[design]\nmodels = [\"od\", \"nd\"]\ndamping_ratios = [\"0.5 %\", 0.0012]\n"
                            "strain_rates = [1e-5]\nseeds = [3, 7]\n");
  const qsdem::Study s = qsdem::load_study(dir / "s.toml");
  const auto m = qsdem::study_manifest(s);
  ASSERT_EQ(m["samples"].size(), 2u);
  EXPECT_EQ(m["samples"][1]["dir"], "samples/A-seed7");
  EXPECT_EQ(m["samples"][1]["seed"], 7);
  ASSERT_EQ(m["runs"].size(), 8u);
  EXPECT_EQ(m["runs"][1]["id"], "A-seed3/od/xi-0.12%/rate-1e-05");
  EXPECT_EQ(m["runs"][1]["dir"], "runs/A-seed3/od/xi-0.12%/rate-1e-05");
  EXPECT_EQ(m["runs"][1]["xi"], 0.0012);
  EXPECT_EQ(m["runs"][1]["rate"], 1e-5);
  EXPECT_EQ(s.samples[1].sets.front(), "sample.seed=7");
  fs::remove_all(dir);
}

// The sample axes: every [[sample]] is prepared at each confining stress and compaction friction,
// named by them, with both stresses and the friction set for `qsdem prepare` and for the runs.
TEST(StudyCli, SampleAxesNameSamplesAndSetTheirKeys) {
  const fs::path dir = fresh_dir("axes");
  write(dir / "s.toml", "[[sample]]\nname = \"A\"\ncase = \"" + (source_dir / "examples/spheres-A-small.toml").string() +
                            "\"\n[design]\nmodels = [\"nd\"]\ndamping_ratios = [\"0.5 %\"]\nstrain_rates = [1e-5]\n"
                            "confining_stresses = [\"100 kPa\", 1.6e6]\ncompaction_frictions = [0, 0.25]\nseeds = [2]\n");
  const qsdem::Study s = qsdem::load_study(dir / "s.toml");
  const std::vector<std::string> names = {"A-p100kPa-cf0", "A-p100kPa-cf0.25", "A-p1600kPa-cf0", "A-p1600kPa-cf0.25"};
  EXPECT_EQ(s.sample_names, names);
  ASSERT_EQ(s.samples.size(), 4u);
  const qsdem::StudySample& last = s.samples[3];
  EXPECT_EQ(last.dir, "samples/A-p1600kPa-cf0.25-seed2");
  EXPECT_EQ(last.confining_stress, 1.6e6);
  EXPECT_EQ(last.compaction_friction, 0.25);
  const std::vector<std::string> sets = {"sample.seed=2", "compaction.stress=\"1600000 Pa\"",
                                         "triaxial.confining_stress=\"1600000 Pa\"", "compaction.friction=0.25"};
  EXPECT_EQ(last.sets, sets);
  ASSERT_EQ(s.runs.size(), 4u);
  EXPECT_EQ(s.runs[3].id, "A-p1600kPa-cf0.25-seed2/nd/xi-0.5%/rate-1e-05");
  const auto m = qsdem::study_manifest(s);
  EXPECT_EQ(m["samples"][3]["confining_stress_Pa"], 1.6e6);
  EXPECT_EQ(m["samples"][3]["compaction_friction"], 0.25);
  EXPECT_FALSE(qsdem::study_manifest(qsdem::load_study(tiny_study))["samples"][0].contains("confining_stress_Pa"))
      << "a study without the axes keeps its manifest";
  fs::remove_all(dir);
}

// The tiny critical-state study from start to end: each sample compacted to its own stress and
// sheared at it, and the analysis' window means are those of the runs' own series.csv.
TEST(Study, TinyCriticalStateStudyEndToEnd) {
  const fs::path dir = fresh_dir("critical");
  const Result r = study(source_dir / "studies" / "tiny-critical-state.toml", dir / "out", dir / "log");
  ASSERT_TRUE(completed(r)) << r.err;
  const auto m = manifest(dir / "out");
  ASSERT_EQ(m["runs"].size(), 4u);
  const auto a = nlohmann::json::parse(slurp(dir / "out" / "analysis" / "analysis.json"));
  ASSERT_EQ(a["critical_state"]["groups"].size(), 1u);
  const auto& g = a["critical_state"]["groups"][0];
  ASSERT_EQ(g["runs"].size(), 4u);
  for (const auto& run : g["runs"]) {
    SCOPED_TRACE(run["id"].get<std::string>());
    const auto entry = std::find_if(m["runs"].begin(), m["runs"].end(), [&](const auto& e) { return e["id"] == run["id"]; });
    ASSERT_NE(entry, m["runs"].end());
    const fs::path rd = dir / "out" / (*entry)["dir"].get<std::string>();
    const auto summary = nlohmann::json::parse(slurp(rd / "summary.json"));
    const double sigma = run["confining_stress_Pa"];
    EXPECT_NEAR(summary["compaction"]["final"]["p_Pa"].get<double>(), sigma, 0.02 * sigma) << "prepared at its stress";
    EXPECT_EQ(summary["config"]["resolved_si"]["protocol"][1]["control"]["11"]["stress_Pa"].get<double>(), sigma)
        << "sheared at it";
    EXPECT_EQ(run["p0_Pa"], summary["compaction"]["final"]["p_Pa"]);
    // The window means, from series.csv by a plain loop.
    std::istringstream in(slurp(rd / "series.csv"));
    std::string line;
    std::getline(in, line);
    std::map<std::string, std::size_t> col;
    {
      std::stringstream ss(line);
      std::string name;
      for (std::size_t i = 0; std::getline(ss, name, ','); ++i) col[name] = i;
    }
    double sum_e = 0, sum_p = 0, sum_ratio = 0;
    int n = 0;
    while (std::getline(in, line)) {
      std::vector<double> v;
      std::stringstream ss(line);
      for (std::string c; std::getline(ss, c, ',');) v.push_back(std::stod(c));
      if (v[col["e1"]] < 0.3) continue;
      sum_e += v[col["void_ratio"]], sum_p += v[col["p_Pa"]], sum_ratio += v[col["q_Pa"]] / v[col["p_Pa"]], ++n;
    }
    ASSERT_GT(n, 2);
    EXPECT_EQ(run["window_rows"], n);
    EXPECT_NEAR(run["void_ratio"].get<double>(), sum_e / n, 1e-12);
    EXPECT_NEAR(run["p_Pa"].get<double>(), sum_p / n, 1e-6);
    EXPECT_NEAR(run["stress_ratio"].get<double>(), sum_ratio / n, 1e-12);
  }
  EXPECT_TRUE(fs::exists(dir / "out" / "analysis" / "critical_state.csv"));
  EXPECT_NE(slurp(dir / "out" / "analysis" / "tables.md").find("Critical state lines"), std::string::npos);
  EXPECT_TRUE(fs::exists(dir / "out" / "analysis" / "figures" / "critical_state_nd_0_5_0_0001.png"));
  fs::remove_all(dir);
}

// The tiny study from start to end: the manifest lists every run, every run directory holds its
// results, the sample was prepared once.
TEST(Study, TinyStudyEndToEnd) {
  const Reference& ref = reference();
  ASSERT_TRUE(completed(ref.result)) << "exit code " << ref.result.code << "\n" << ref.result.err;
  const auto m = manifest(ref.dir);
  EXPECT_EQ(m["name"], "tiny");
  EXPECT_EQ(m["study_file"], "study.toml");
  EXPECT_EQ(slurp(ref.dir / "study.toml"), slurp(tiny_study));
  ASSERT_EQ(m["samples"].size(), 1u);
  EXPECT_TRUE(fs::exists(ref.dir / m["samples"][0]["dir"].get<std::string>() / "sample.qsck"));
  ASSERT_EQ(m["runs"].size(), 8u);
  std::set<std::string> ids;
  for (const auto& r : m["runs"]) {
    const fs::path d = ref.dir / r["dir"].get<std::string>();
    SCOPED_TRACE(d.string());
    ids.insert(r["id"].get<std::string>());
    EXPECT_TRUE(fs::exists(d / "summary.json"));
    EXPECT_TRUE(fs::exists(d / "series.csv"));
    EXPECT_FALSE(fs::exists(d / "checkpoint.qsck"));
    EXPECT_TRUE(fs::exists(d / "run.log"));
    // The run sheared the prepared sample with the design's values.
    const auto s = nlohmann::json::parse(slurp(d / "summary.json"));
    const auto& cfg = s["config"]["resolved_si"]["protocol"][1];
    EXPECT_EQ(cfg["damping"]["model"], r["model"]) << cfg.dump();
    EXPECT_EQ(cfg["damping"]["ratio"], r["xi"]);
    EXPECT_EQ(cfg["control"]["33"]["strain_rate"], r["rate"]);
    EXPECT_EQ(s["triaxial"]["rows"], 10);
  }
  EXPECT_EQ(ids.size(), 8u);
  EXPECT_FALSE(fs::exists(ref.dir / "failures.json"));
  EXPECT_TRUE(fs::exists(ref.dir / "analysis" / "per_run.csv")) << "the study ends with the analysis";
  EXPECT_EQ(nlohmann::json::parse(slurp(ref.dir / "analysis" / "analysis.json"))["study"]["qsdem_version"],
            QSDEM_VERSION)
      << "the exact source version (docs/runs.md)";
}

// A study file's comments and layout are not its study: a directory continues with a file whose
// tables and values are the same (its copy then takes the new text); a changed value is another.
TEST(StudyFile, CommentsAndLayoutDoNotMakeAnotherStudy) {
  const std::string text = slurp(tiny_study);
  EXPECT_TRUE(qsdem::same_study_values(text, "# a note on the design\n" + text + "\n# and one after it\n"));
  EXPECT_TRUE(qsdem::same_study_values("name = \"x\"\n[design]\nmodels = [\"od\", \"nd\"]\n",
                                       "name=\"x\"  # the study\n\n[design]\nmodels = [ \"od\",\n  \"nd\" ]\n"));
  EXPECT_FALSE(qsdem::same_study_values("name = \"x\"\n[design]\nmodels = [\"od\", \"nd\"]\n",
                                        "name = \"x\"\n[design]\nmodels = [\"nd\", \"od\"]\n"));
  EXPECT_FALSE(qsdem::same_study_values(text, "this is [not toml"));

}

// A study grows when its new file only adds runs: every run and sample of the study a directory
// holds is still defined, with the same resolved case (an override that sets a key to the value
// it had is no change). A run gone, a run or sample defined otherwise, another name or analysis
// is refused, naming it.
TEST(StudyFile, GrowthOnlyAddsRuns) {
  const std::string text = slurp(tiny_study);
  const qsdem::Study held = qsdem::load_study(tiny_study);
  ASSERT_EQ(held.runs.size(), 8u);
  const auto edited = [&](std::vector<std::pair<std::string, std::string>> edits) {
    std::string t = text;
    for (const auto& [from, to] : edits) {
      const auto at = t.find(from);
      EXPECT_NE(at, std::string::npos) << from;
      if (at != std::string::npos) t.replace(at, from.size(), to);
    }
    return qsdem::load_study_text(t, tiny_study);  // beside tiny.toml: its relative case path
  };
  // Another rate, model and seed (the case's seed 1 given as design.seeds: the same sample), and
  // other [execution] values.
  const qsdem::Study grown =
      edited({{"models = [\"od\", \"nd\"]", "models = [\"od\", \"nd\", \"none\"]\nseeds = [1, 2]"},
              {"strain_rates = [5e-6, 2.5e-6]", "strain_rates = [5e-6, 2.5e-6, 1.25e-6]"},
              {"parallel_runs = 2", "parallel_runs = 1"}});
  EXPECT_EQ(qsdem::growth_refusal(held, grown), "");
  EXPECT_EQ(grown.runs.size(), 2u * 3u * 2u * 3u);
  EXPECT_EQ(qsdem::growth_refusal(held, held), "");

  const auto refusal = [&](std::vector<std::pair<std::string, std::string>> edits) {
    return qsdem::growth_refusal(held, edited(std::move(edits)));
  };
  EXPECT_EQ(refusal({{"strain_rates = [5e-6, 2.5e-6]", "strain_rates = [5e-6, 1.25e-6]"}}),
            "the run 'tiny-seed1/od/xi-0.2%/rate-2.5e-06' is not in it");
  const std::string changed = refusal({{"strain_rates = [5e-6, 2.5e-6]", "strain_rates = [5e-6, 2.5e-6, 1.25e-6]"},
                                       {"final_axial_strain=1 %", "final_axial_strain=2 %"}});
  EXPECT_NE(changed.find("the run 'tiny-seed1/od/xi-0.2%/rate-5e-06' changes: --set triaxial.final_axial_strain was "
                         "'1 %' and is now '2 %'"),
            std::string::npos)
      << changed;
  const std::string sample = refusal({{"count=60}]", "count=61}]"}});
  EXPECT_NE(sample.find("the sample 'tiny-seed1' is prepared otherwise: --set sample.particles"), std::string::npos)
      << sample;
  EXPECT_NE(refusal({{"models = [\"od\", \"nd\"]", "models = [\"none\", \"od\", \"nd\"]"}})
                .find("its analysis.baseline was \"od\" and is now \"none\""),
            std::string::npos)
      << "the first model is the default baseline";
  EXPECT_NE(refusal({{"[execution]", "[analysis]\nimom_target = \"1 %\"\n[execution]"}})
                .find("its analysis.imom_target was 0.001 and is now 0.01"),
            std::string::npos);
  EXPECT_EQ(refusal({{"name = \"tiny\"\n", "name = \"small\"\n"}}), "its name was 'tiny' and is now 'small'");
}

// Another study file for the same directory is refused before anything is touched.
TEST(StudyCli, RefusesADirectoryOfAnotherStudy) {
  const fs::path dir = fresh_dir("other");
  fs::create_directories(dir / "out");
  const std::string text = slurp(tiny_study);
  write(dir / "out" / "study.toml", std::regex_replace(text, std::regex("count=60\\}\\]"), "count=61}]", std::regex_constants::format_first_only));
  ASSERT_NE(slurp(dir / "out" / "study.toml"), text);
  Result r = study(tiny_study, dir / "out", dir / "log");
  EXPECT_EQ(r.code, 2);
  EXPECT_NE(r.err.find("holds another study"), std::string::npos) << r.err;
  fs::remove(dir / "out" / "study.toml");
  write(dir / "out" / "notes.txt", "mine");
  r = study(tiny_study, dir / "out", dir / "log");
  EXPECT_EQ(r.code, 2);
  EXPECT_NE(r.err.find("not empty"), std::string::npos) << r.err;
  // A study at work in a directory holds its lock: a second one is refused.
  fs::remove(dir / "out" / "notes.txt");
  write(dir / "out" / "study.toml", slurp(tiny_study));
  const int fd = ::open((dir / "out" / ".study.lock").c_str(), O_RDWR | O_CREAT, 0644);
  ASSERT_EQ(::flock(fd, LOCK_EX | LOCK_NB), 0);
  r = study(tiny_study, dir / "out", dir / "log");
  ::close(fd);
  EXPECT_EQ(r.code, 2);
  EXPECT_NE(r.err.find("another `qsdem study` is working"), std::string::npos) << r.err;
  EXPECT_FALSE(fs::exists(dir / "out" / "samples"));
  fs::remove_all(dir);
}

// SIGTERM while runs are in progress: exit 143 and checkpoints; `qsdem study` again finishes the
// study without repeating finished runs, to the same series.csv as the uninterrupted study.
TEST(Study, KilledStudyResumesToTheSameResults) {
  const Reference& ref = reference();
  ASSERT_TRUE(completed(ref.result)) << ref.result.err;
  const fs::path dir = fresh_dir("killed");
  const fs::path out = dir / "study";
  const pid_t pid = spawn({binary, "study", tiny_study.string(), "--out", out.string()}, dir / "first");
  ASSERT_GT(pid, 0);
  const auto m = manifest(ref.dir);
  const auto finished_runs = [&] {
    std::vector<fs::path> done;
    for (const auto& r : m["runs"])
      if (fs::exists(out / r["dir"].get<std::string>() / "summary.json")) done.push_back(out / r["dir"].get<std::string>());
    return done;
  };
  // A run that has just begun shearing: its series.csv.partial exists (written after its signal
  // handlers are in place) and holds at most the header and the first of 10 rows, so at least 80 %
  // of the run is still ahead when the signal arrives. (Taking any run in progress failed in CI:
  // both running children were in their last sample points and finished before the signal.)
  const auto in_progress = [&]() -> std::optional<fs::path> {
    for (const auto& r : m["runs"]) {
      const fs::path d = out / r["dir"].get<std::string>();
      if (!fs::exists(d / "series.csv.partial") || fs::exists(d / "summary.json")) continue;
      const std::string rows = slurp(d / "series.csv.partial");
      if (std::count(rows.begin(), rows.end(), '\n') <= 2) return d;
    }
    return std::nullopt;
  };
  // Stop it as soon as a run has finished and another has just begun. A tiny run lasts only a few
  // hundred milliseconds on a quiet machine, so poll fast and signal at once (no settling sleep:
  // that made the test miss every window when runs were quick). If no run has finished after
  // 20 s (a very slow machine), any run just begun will do.
  bool ready = false;
  const auto start = std::chrono::steady_clock::now();
  const auto deadline = start + std::chrono::minutes(3);
  while (!ready && std::chrono::steady_clock::now() < deadline) {
    std::this_thread::sleep_for(std::chrono::milliseconds(2));
    const bool waited = std::chrono::steady_clock::now() - start > std::chrono::seconds(20);
    ready = in_progress().has_value() && (waited || !finished_runs().empty());
  }
  ASSERT_TRUE(ready) << "no run finished while another was in progress";
  ASSERT_EQ(::kill(pid, SIGTERM), 0);
  const Result first = finish(pid, dir / "first");
  EXPECT_EQ(first.code, 143) << first.err;
  EXPECT_NE(first.err.find("stopped by SIGTERM"), std::string::npos) << first.err;
  EXPECT_NE(first.err.find("again continues"), std::string::npos) << first.err;
  EXPECT_NE(first.err.find("runs 0/8 done"), std::string::npos) << "progress lines on a non-terminal\n" << first.err;

  const std::vector<fs::path> done = finished_runs();
  ASSERT_LT(done.size(), 8u) << "the study ended before it could be interrupted";
  std::map<fs::path, fs::file_time_type> mtimes;
  for (const auto& d : done) mtimes[d] = fs::last_write_time(d / "summary.json");
  std::vector<fs::path> interrupted;  // runs stopped mid-way, holding a checkpoint
  for (const auto& r : m["runs"])
    if (fs::exists(out / r["dir"].get<std::string>() / "checkpoint.qsck"))
      interrupted.push_back(out / r["dir"].get<std::string>());
  EXPECT_FALSE(interrupted.empty()) << "a run in progress writes a checkpoint when the study is stopped\n" << first.err;

  const Result second = study(tiny_study, out, dir / "second");
  EXPECT_TRUE(completed(second)) << second.err;
  for (const auto& [d, t] : mtimes) EXPECT_EQ(fs::last_write_time(d / "summary.json"), t) << d << " was run again";
  for (const auto& d : interrupted)
    EXPECT_NE(slurp(d / "run.log").find("=== qsdem 'resume'"), std::string::npos) << d << " was not resumed";
  for (const auto& r : m["runs"]) {
    const std::string rel = r["dir"].get<std::string>() + "/series.csv";
    ASSERT_TRUE(fs::exists(out / rel)) << rel;
    EXPECT_EQ(slurp(out / rel), slurp(ref.dir / rel)) << rel;
  }
  EXPECT_EQ(slurp(out / "study.json"), slurp(ref.dir / "study.json"));
  // The analysis of the resumed study is that of the uninterrupted one.
  const auto tables = analysis_tables(ref.dir);
  EXPECT_FALSE(tables.empty());
  EXPECT_EQ(analysis_tables(out), tables);

  // A finished study run again repeats nothing (only the analysis).
  for (const auto& r : m["runs"])
    mtimes[out / r["dir"].get<std::string>()] = fs::last_write_time(out / r["dir"].get<std::string>() / "summary.json");
  const Result third = study(tiny_study, out, dir / "third", false);
  EXPECT_TRUE(completed(third)) << third.err;
  EXPECT_NE(third.err.find("runs 8/8 done, 0 running"), std::string::npos) << third.err;
  for (const auto& [d, t] : mtimes) EXPECT_EQ(fs::last_write_time(d / "summary.json"), t) << d << " was run again";
  fs::remove_all(dir);
}

// A study continues from what a repository keeps of it (docs/results/*/): study.toml, study.json
// and the finished runs' summary.json, series.csv and classes.csv, without the prepared samples,
// checkpoints or logs. The sample is prepared again (to its recorded hash), the kept runs are not
// repeated, and the others give the uninterrupted study's series.
TEST(Study, ContinuesFromTheFilesARepositoryKeeps) {
  const Reference& ref = reference();
  ASSERT_TRUE(completed(ref.result)) << ref.result.err;
  const auto m = manifest(ref.dir);
  const fs::path dir = fresh_dir("kept");
  const fs::path out = dir / "study";
  fs::create_directories(out);
  fs::copy_file(ref.dir / "study.toml", out / "study.toml");
  fs::copy_file(ref.dir / "study.json", out / "study.json");
  std::vector<std::string> kept;
  for (std::size_t k = 0; k < m["runs"].size(); k += 2) {
    const std::string rel = m["runs"][k]["dir"].get<std::string>();
    fs::create_directories(out / rel);
    for (const char* f : {"summary.json", "series.csv", "classes.csv"}) fs::copy_file(ref.dir / rel / f, out / rel / f);
    kept.push_back(rel);
  }
  ASSERT_FALSE(fs::exists(out / "samples"));
  std::map<std::string, fs::file_time_type> mtimes;
  for (const auto& rel : kept) mtimes[rel] = fs::last_write_time(out / rel / "summary.json");

  const Result r = study(tiny_study, out, dir / "continued", false);
  EXPECT_TRUE(completed(r)) << r.err;
  std::smatch first;
  ASSERT_TRUE(std::regex_search(r.err, first, std::regex("runs[^\n]*? (\\d+)/8 done"))) << r.err;
  EXPECT_EQ(first[1], "4") << "the progress counts the kept runs from the start (the ETA leaves them out)\n" << r.err;
  EXPECT_TRUE(fs::exists(out / m["samples"][0]["dir"].get<std::string>() / "sample.qsck")) << "prepared again";
  EXPECT_EQ(slurp(out / "study.json"), slurp(ref.dir / "study.json")) << "the same prepared sample's hash";
  for (const auto& [rel, t] : mtimes) {
    EXPECT_EQ(fs::last_write_time(out / rel / "summary.json"), t) << rel << " was run again";
    EXPECT_FALSE(fs::exists(out / rel / "run.log")) << rel << " was run again";
  }
  for (const auto& run : m["runs"]) {
    const std::string rel = run["dir"].get<std::string>() + "/series.csv";
    ASSERT_TRUE(fs::exists(out / rel)) << rel;
    EXPECT_EQ(slurp(out / rel), slurp(ref.dir / rel)) << rel;
  }
  EXPECT_EQ(analysis_tables(out), analysis_tables(ref.dir));

  // Prepared again to another packing than the kept runs sheared (here: the recorded hash altered):
  // refused, naming the sample, before any run.
  const fs::path other = dir / "other";
  fs::create_directories(other);
  fs::copy_file(ref.dir / "study.toml", other / "study.toml");
  auto altered = m;
  altered["samples"][0]["compacted_fnv1a64"] = "0123456789abcdef";
  write(other / "study.json", altered.dump(2) + "\n");
  const Result refused = study(tiny_study, other, dir / "refused");
  EXPECT_EQ(refused.code, 2) << refused.err;
  EXPECT_NE(refused.err.find("the prepared sample"), std::string::npos) << refused.err;
  EXPECT_NE(refused.err.find("0123456789abcdef"), std::string::npos) << refused.err;
  EXPECT_FALSE(fs::exists(other / "runs")) << "no run sheared the other packing";
  fs::remove_all(dir);
}

// A run that resumes from a checkpoint has only the steps after its last row left (the pool's
// order and the ETA); one without a checkpoint starts afresh, whatever its partial series says.
TEST(StudyCli, StepsLeftOfAResumedRun) {
  const fs::path dir = fresh_dir("left");
  EXPECT_EQ(qsdem::steps_left(dir, 7.8e6), 7.8e6) << "nothing there";
  write(dir / "series.csv.partial", "step,time_s,e1\n31250,0.0039,0.0004\n2031250,0.25,0.026\n");
  EXPECT_EQ(qsdem::steps_left(dir, 7.8e6), 7.8e6) << "no checkpoint: a fresh start";
  write(dir / "checkpoint.qsck", "");
  EXPECT_EQ(qsdem::steps_left(dir, 7.8e6), 7.8e6 - 2031250);
  write(dir / "series.csv.partial", "step,time_s,e1\n");
  EXPECT_EQ(qsdem::steps_left(dir, 7.8e6), 7.8e6) << "a checkpoint before the first row";
  write(dir / "series.csv.partial", "step,time_s,e1\n7800001,1,0.1\n");
  EXPECT_EQ(qsdem::steps_left(dir, 7.8e6), 1.0) << "never below one step";
  fs::remove_all(dir);
}

// A run that blows up is recorded in failures.json and reported; the others finish; exit code 3.
TEST(Study, FailedRunIsRecordedAndTheOthersFinish) {
  const fs::path dir = fresh_dir("failed");
  const std::string tiny_sets =
      "'sample.particles=[{shape=\"sphere\", diameter=\"2.4 mm\", count=60}, {shape=\"sphere\", diameter=\"2.0 mm\", "
      "count=60}]', \"sample.total_particles=0\", \"sample.initial_solid_fraction=0.2\", "
      "\"compaction.max_strain_rate=1e-3\"";
  const std::string case_file = (source_dir / "examples/spheres-A-small.toml").string();
  write(dir / "f.toml", "[[sample]]\nname = \"good\"\ncase = \"" + case_file + "\"\nset = [" + tiny_sets +
                            "]\n[[sample]]\nname = \"bad\"\ncase = \"" + case_file + "\"\nset = [" + tiny_sets +
                            ", \"limits.max_kinetic_ratio=1e-30\"]\n"
                            "[design]\nmodels = [\"nd\"]\ndamping_ratios = [\"0.5 %\"]\nstrain_rates = [2e-5]\n"
                            "set = [\"triaxial.final_axial_strain=1 %\", \"triaxial.sample_points=10\"]\n"
                            "[execution]\nparallel_runs = 2\n");
  const Result r = study(dir / "f.toml", dir / "out", dir / "log");
  EXPECT_EQ(r.code, 3) << r.err;
  EXPECT_NE(r.err.find("bad-seed1/nd/xi-0.5%/rate-2e-05 failed (exit code 3)"), std::string::npos) << r.err;
  EXPECT_NE(r.err.find("max_kinetic_ratio"), std::string::npos) << "the child's diagnostic is shown\n" << r.err;
  const auto f = nlohmann::json::parse(slurp(dir / "out" / "failures.json"));
  ASSERT_EQ(f.size(), 1u);
  EXPECT_EQ(f[0]["id"], "bad-seed1/nd/xi-0.5%/rate-2e-05");
  EXPECT_EQ(f[0]["exit_code"], 3);
  EXPECT_TRUE(fs::exists(dir / "out" / f[0]["log"].get<std::string>()));
  EXPECT_TRUE(fs::exists(dir / "out/runs/good-seed1/nd/xi-0.5%/rate-2e-05/series.csv"));
  EXPECT_TRUE(fs::exists(dir / "out/analysis/per_run.csv")) << "the analysis runs on what finished\n" << r.err;
  fs::remove_all(dir);
}

// `mpirun -np 2` spreads samples and runs over two ranks: the same manifest and byte-identical
// series (every run is deterministic for its thread count, which the study file fixes).
TEST(Study, MpiRanksGiveTheSameResults) {
  if (std::system("command -v mpirun > /dev/null 2>&1") != 0) GTEST_SKIP() << "mpirun is not installed";
  const Reference& ref = reference();
  ASSERT_TRUE(completed(ref.result)) << ref.result.err;
  const fs::path dir = fresh_dir("mpi");
  ::setenv("OMPI_ALLOW_RUN_AS_ROOT", "1", 1);
  ::setenv("OMPI_ALLOW_RUN_AS_ROOT_CONFIRM", "1", 1);
  const Result r = run({"mpirun", "-np", "2", "--oversubscribe", binary, "study", tiny_study.string(), "--out",
                        (dir / "study").string()},
                       dir / "log");
  ASSERT_TRUE(completed(r)) << "exit code " << r.code << "\n" << r.err << r.out;
  EXPECT_NE(r.err.find("[rank 1/2]"), std::string::npos) << r.err;
  EXPECT_EQ(slurp(dir / "study/study.json"), slurp(ref.dir / "study.json"));
  const auto m = manifest(ref.dir);  // named: a range over a temporary's member would dangle
  ASSERT_EQ(m["runs"].size(), 8u);
  for (const auto& run : m["runs"]) {
    const std::string rel = run["dir"].get<std::string>() + "/series.csv";
    ASSERT_TRUE(fs::exists(dir / "study" / rel)) << rel;
    EXPECT_EQ(slurp(dir / "study" / rel), slurp(ref.dir / rel)) << rel;
    // The children were plain processes, not MPI ranks.
    EXPECT_EQ(slurp(dir / "study" / run["dir"].get<std::string>() / "run.log").find("OMPI"), std::string::npos);
  }
  const auto tables = analysis_tables(ref.dir);
  EXPECT_FALSE(tables.empty());
  EXPECT_EQ(analysis_tables(dir / "study"), tables);
  fs::remove_all(dir);
}

namespace {

// A one-run study of a copy of the tiny study's case, in `dir` (study.toml and case.toml).
fs::path one_run_study(const fs::path& dir) {
  write(dir / "case.toml", slurp(source_dir / "examples" / "spheres-A-small.toml"));
  std::string text = slurp(tiny_study);
  const auto replace = [&](const std::string& from, const std::string& to) {
    const auto at = text.find(from);
    if (at != std::string::npos) text.replace(at, from.size(), to);
  };
  replace("case = \"../examples/spheres-A-small.toml\"", "case = \"case.toml\"");
  replace("models = [\"od\", \"nd\"]", "models = [\"nd\"]");
  replace("damping_ratios = [\"0.2 %\", \"1 %\"]", "damping_ratios = [\"1 %\"]");
  replace("strain_rates = [5e-6, 2.5e-6]", "strain_rates = [5e-6]");
  write(dir / "study.toml", text);
  return dir / "study.toml";
}

}  // namespace

// A study continued after its case file or a prepared sample changed is refused: its runs would
// mix two cases in one analysis. study.json records their FNV-1a hashes.
TEST(StudyCli, RefusesAChangedCaseFileOrSample) {
  const fs::path dir = fresh_dir("changed");
  const fs::path file = one_run_study(dir);
  const fs::path out = dir / "out";
  Result r = study(file, out, dir / "log");
  ASSERT_EQ(r.code, 0) << r.err;
  const auto m = manifest(out);
  ASSERT_EQ(m["samples"].size(), 1u);
  EXPECT_EQ(m["samples"][0]["case"], fs::weakly_canonical(dir / "case.toml").string());
  EXPECT_EQ(m["samples"][0]["case_fnv1a64"].get<std::string>().size(), 16u);
  ASSERT_TRUE(m["samples"][0].contains("compacted_fnv1a64"));
  // The build that made it, once however often it worked on the study.
  ASSERT_EQ(m["builds"].size(), 1u) << m["builds"];
  EXPECT_EQ(m["builds"][0]["version"], QSDEM_VERSION);
  EXPECT_TRUE(m["builds"][0].contains("commit") && m["builds"][0].contains("tree_clean")) << m["builds"];
  const std::string case_text = slurp(dir / "case.toml");
  write(dir / "case.toml", case_text + "# edited\n");
  r = study(file, out, dir / "log");
  EXPECT_EQ(r.code, 2);
  EXPECT_NE(r.err.find("case.toml"), std::string::npos) << r.err;
  EXPECT_NE(r.err.find("changed since this study recorded it"), std::string::npos) << r.err;
  write(dir / "case.toml", case_text);
  r = study(file, out, dir / "log");
  EXPECT_EQ(r.code, 0) << "restored: " << r.err;
  EXPECT_EQ(manifest(out)["builds"].size(), 1u) << "the same build again is not listed twice";
  // The sample prepared anew with another seed, by hand.
  const fs::path sample = out / m["samples"][0]["dir"].get<std::string>();
  const Result again = run({binary, "prepare", (dir / "case.toml").string(), "--out", sample.string(), "--force",
                            "--quiet", "--set",
                            "sample.particles=[{shape=\"sphere\", diameter=\"2.4 mm\", count=60}, "
                            "{shape=\"sphere\", diameter=\"2.0 mm\", count=60}]",
                            "--set", "sample.total_particles=0", "--set", "sample.initial_solid_fraction=0.2", "--set",
                            "compaction.max_strain_rate=1e-3", "--set", "sample.seed=2"},
                           dir / "again");
  ASSERT_EQ(again.code, 0) << again.err;
  r = study(file, out, dir / "log");
  EXPECT_EQ(r.code, 2);
  EXPECT_NE(r.err.find("the prepared sample"), std::string::npos) << r.err;
  fs::remove_all(dir);
}

// A study grown by a rate (the next rung of a ladder) keeps its finished run and its prepared
// sample to the byte and the mtime, runs only the new rate, and takes the new file as its
// study.toml. A file that then changes the value of a run it holds is refused, naming the run
// and the key, and changes nothing.
TEST(Study, GrowsByAnAddedRateKeepingItsFinishedRuns) {
  const fs::path dir = fresh_dir("grow");
  const fs::path file = one_run_study(dir);
  const fs::path out = dir / "out";
  Result r = study(file, out, dir / "first");
  ASSERT_EQ(r.code, 0) << r.err;
  const auto before = manifest(out);
  ASSERT_EQ(before["runs"].size(), 1u);
  std::map<fs::path, std::pair<std::string, fs::file_time_type>> kept;  // every file of the run and sample
  for (const auto& e : fs::recursive_directory_iterator(out))
    if (e.is_regular_file() && (e.path().string().find("/runs/") != std::string::npos ||
                                e.path().string().find("/samples/") != std::string::npos))
      kept[e.path()] = {slurp(e.path()), fs::last_write_time(e.path())};
  ASSERT_GT(kept.size(), 8u);

  std::string text = slurp(file);
  const std::string rates = "strain_rates = [5e-6]";
  ASSERT_NE(text.find(rates), std::string::npos);
  text.replace(text.find(rates), rates.size(), "strain_rates = [5e-6, 1e-5]   # the next rung");
  write(dir / "grown.toml", text);
  r = study(dir / "grown.toml", out, dir / "grown", false);
  ASSERT_EQ(r.code, 0) << r.err;
  EXPECT_NE(r.err.find("grows by 1 run (1 kept)"), std::string::npos) << r.err;
  EXPECT_NE(r.err.find("runs 1/2 done"), std::string::npos) << "the kept run is counted as done\n" << r.err;
  for (const auto& [p, was] : kept) {
    EXPECT_EQ(slurp(p), was.first) << p;
    EXPECT_EQ(fs::last_write_time(p), was.second) << p << " was written again";
  }
  const fs::path added = out / "runs/tiny-seed1/nd/xi-1%/rate-1e-05";
  EXPECT_TRUE(fs::exists(added / "summary.json"));
  const std::string log = slurp(added / "run.log");
  EXPECT_EQ(log.find("=== qsdem", 1), std::string::npos) << "one start\n" << log;
  EXPECT_EQ(slurp(out / "study.toml"), text);
  const auto after = manifest(out);
  ASSERT_EQ(after["runs"].size(), 2u);
  EXPECT_EQ(after["runs"][0], before["runs"][0]);
  EXPECT_EQ(after["runs"][1]["rate"], 1e-5);
  EXPECT_EQ(after["samples"], before["samples"]) << "the recorded hashes are kept";

  // The kept run changed (its final strain) and the added one dropped: refused, naming them.
  std::string other = text;
  other.replace(other.find("final_axial_strain=1 %"), 22, "final_axial_strain=2 %");
  write(dir / "other.toml", other);
  r = study(dir / "other.toml", out, dir / "other");
  EXPECT_EQ(r.code, 2);
  EXPECT_NE(r.err.find("holds another study"), std::string::npos) << r.err;
  EXPECT_NE(r.err.find("the run 'tiny-seed1/nd/xi-1%/rate-5e-06' changes: --set triaxial.final_axial_strain was '1 %' "
                       "and is now '2 %'"),
            std::string::npos)
      << r.err;
  r = study(file, out, dir / "fewer");
  EXPECT_EQ(r.code, 2);
  EXPECT_NE(r.err.find("the run 'tiny-seed1/nd/xi-1%/rate-1e-05' is not in it"), std::string::npos) << r.err;
  EXPECT_EQ(slurp(out / "study.toml"), text) << "a refused file changes nothing";
  EXPECT_EQ(manifest(out)["runs"], after["runs"]);
  fs::remove_all(dir);
}

// The study's own copy of a case file: one edited (here: made unreadable) while the study runs
// reaches none of its runs, which finish with the uninterrupted study's series.
TEST(Study, ACaseFileEditedDuringTheStudyReachesNoRun) {
  const Reference& ref = reference();
  ASSERT_TRUE(completed(ref.result)) << ref.result.err;
  const fs::path dir = fresh_dir("edited");
  write(dir / "case.toml", slurp(source_dir / "examples" / "spheres-A-small.toml"));
  std::string text = slurp(tiny_study);
  const std::string from = "case = \"../examples/spheres-A-small.toml\"";
  text.replace(text.find(from), from.size(), "case = \"case.toml\"");
  write(dir / "study.toml", text);
  const fs::path out = dir / "out";
  const pid_t pid = spawn({binary, "study", (dir / "study.toml").string(), "--out", out.string(), "--quiet"}, dir / "log");
  ASSERT_GT(pid, 0);
  const auto m = manifest(ref.dir);
  const auto any_run_begun = [&] {
    for (const auto& r : m["runs"])
      if (fs::exists(out / r["dir"].get<std::string>() / "run.log")) return true;
    return false;
  };
  const auto deadline = std::chrono::steady_clock::now() + std::chrono::minutes(3);
  while (!any_run_begun() && std::chrono::steady_clock::now() < deadline)
    std::this_thread::sleep_for(std::chrono::milliseconds(2));
  ASSERT_TRUE(any_run_begun());
  write(dir / "case.toml", "this is [ not a case\n");
  const Result r = finish(pid, dir / "log");
  EXPECT_EQ(r.code, 0) << r.err;
  EXPECT_EQ(slurp(out / "cases" / "tiny.toml"), slurp(source_dir / "examples" / "spheres-A-small.toml"));
  for (const auto& run : m["runs"]) {
    const std::string rel = run["dir"].get<std::string>() + "/series.csv";
    ASSERT_TRUE(fs::exists(out / rel)) << rel << "\n" << r.err;
    EXPECT_EQ(slurp(out / rel), slurp(ref.dir / rel)) << rel;
  }
  fs::remove_all(dir);
}

// A child killed by a signal the study did not send (SIGKILL, as the OOM killer sends) is
// continued, not failed: the study ends with every run and the uninterrupted study's series.
TEST(Study, AChildKilledBySignalIsContinuedNotFailed) {
  const Reference& ref = reference();
  ASSERT_TRUE(completed(ref.result)) << ref.result.err;
  const fs::path dir = fresh_dir("sigkill");
  const fs::path out = dir / "study";
  const pid_t pid = spawn({binary, "study", tiny_study.string(), "--out", out.string(), "--quiet"}, dir / "log");
  ASSERT_GT(pid, 0);
  const auto m = manifest(ref.dir);
  // The pid of the child whose arguments name `run_dir` (run --out DIR, or resume DIR).
  const auto child_of = [](const fs::path& run_dir) -> pid_t {
    for (const auto& e : fs::directory_iterator("/proc")) {
      const std::string name = e.path().filename().string();
      if (name.find_first_not_of("0123456789") != std::string::npos) continue;
      std::ifstream in(e.path() / "cmdline", std::ios::binary);
      std::string arg;
      bool study_child = false, names_dir = false;
      while (std::getline(in, arg, '\0')) {
        study_child = study_child || arg == "run" || arg == "resume";
        names_dir = names_dir || arg == run_dir.string();
      }
      if (study_child && names_dir) return static_cast<pid_t>(std::stol(name));
    }
    return -1;
  };
  std::string killed;
  const auto deadline = std::chrono::steady_clock::now() + std::chrono::minutes(3);
  while (killed.empty() && std::chrono::steady_clock::now() < deadline) {
    std::this_thread::sleep_for(std::chrono::milliseconds(2));
    for (const auto& run : m["runs"]) {
      const fs::path d = out / run["dir"].get<std::string>();
      if (!fs::exists(d / "series.csv.partial") || fs::exists(d / "summary.json")) continue;
      const std::string rows = slurp(d / "series.csv.partial");
      if (std::count(rows.begin(), rows.end(), '\n') > 4) continue;  // most of the run still ahead
      if (const pid_t child = child_of(d); child > 0 && ::kill(child, SIGKILL) == 0) {
        killed = run["id"].get<std::string>();
        break;
      }
    }
  }
  ASSERT_FALSE(killed.empty()) << "no run was caught in progress";
  const Result r = finish(pid, dir / "log");
  EXPECT_EQ(r.code, 0) << r.err;
  EXPECT_NE(r.err.find("run " + killed + " was stopped by signal 9 (not by the study): continued"), std::string::npos)
      << r.err;
  EXPECT_FALSE(fs::exists(out / "failures.json"));
  for (const auto& run : m["runs"]) {
    const std::string rel = run["dir"].get<std::string>() + "/series.csv";
    ASSERT_TRUE(fs::exists(out / rel)) << rel << "\n" << r.err;
    EXPECT_EQ(slurp(out / rel), slurp(ref.dir / rel)) << rel;
  }
  fs::remove_all(dir);
}

// Two studies started at the same instant in one directory: one runs, the other is told that
// another study is working there (not that the directory "holds no study.toml").
TEST(StudyCli, TwoStudiesStartedAtOnce) {
  const fs::path dir = fresh_dir("at-once");
  const fs::path file = one_run_study(dir);
  for (int trial = 0; trial < 2; ++trial) {
    const fs::path out = dir / ("out" + std::to_string(trial));
    const pid_t a = spawn({binary, "study", file.string(), "--out", out.string(), "--quiet"}, dir / "a");
    const pid_t b = spawn({binary, "study", file.string(), "--out", out.string(), "--quiet"}, dir / "b");
    const Result ra = finish(a, dir / "a"), rb = finish(b, dir / "b");
    SCOPED_TRACE(ra.err + "\n" + rb.err);
    EXPECT_EQ(std::min(ra.code, rb.code), 0);
    EXPECT_EQ(std::max(ra.code, rb.code), 2);
    const std::string& loser = ra.code == 2 ? ra.err : rb.err;
    EXPECT_NE(loser.find("another `qsdem study` is working"), std::string::npos) << loser;
  }
  fs::remove_all(dir);
}

// A sample name names directories: one longer than a file name can be is refused at once.
TEST(StudyCli, TooLongSampleNameIsRefused) {
  const fs::path dir = fresh_dir("long-name");
  const fs::path file = one_run_study(dir);
  std::string text = slurp(file);
  const std::string name = std::string(260, 'n');
  text.replace(text.find("name = \"tiny\"\ncase"), std::string("name = \"tiny\"").size(), "name = \"" + name + "\"");
  write(file, text);
  try {
    qsdem::load_study(file);
    ADD_FAILURE() << "a 260-character sample name was accepted";
  } catch (const qsdem::InputError& e) {
    const std::string what = e.what();
    EXPECT_NE(what.find("sample.0.name"), std::string::npos) << what;
    EXPECT_NE(what.find("260 characters: at most 200"), std::string::npos) << what;
  }
  fs::remove_all(dir);
}

// The model axis: a name as before (study.json unchanged), or a label with overrides, which come
// after design.set; the manifest records the label, the case's damping model and the overrides.
TEST(StudyCli, ModelEntriesWithLabelsAndOverrides) {
  const fs::path dir = fresh_dir("labels");
  write(dir / "s.toml", "[[sample]]\nname = \"A\"\ncase = \"" + (source_dir / "examples/spheres-A-small.toml").string() +
                            "\"\n[design]\nmodels = [\"nd\", { label = \"nd-fast-sides\", set = [\"damping.model=nd\", "
                            "\"triaxial.lateral_rate_factor=20\"] }, { label = \"case\" }]\n"
                            "damping_ratios = [\"0.5 %\"]\nstrain_rates = [1e-5]\n"
                            "set = [\"triaxial.lateral_rate_factor=5\"]\n");
  const qsdem::Study s = qsdem::load_study(dir / "s.toml");
  ASSERT_EQ(s.runs.size(), 3u);
  const auto m = qsdem::study_manifest(s);
  EXPECT_FALSE(m.contains("analysis")) << "no [analysis], no stages: study.json as before";
  EXPECT_FALSE(m.contains("stages"));
  EXPECT_EQ(m["runs"][0]["id"], "A-seed1/nd/xi-0.5%/rate-1e-05");
  EXPECT_FALSE(m["runs"][0].contains("damping_model"));
  EXPECT_EQ(m["runs"][1]["id"], "A-seed1/nd-fast-sides/xi-0.5%/rate-1e-05");
  EXPECT_EQ(m["runs"][1]["model"], "nd-fast-sides");
  EXPECT_EQ(m["runs"][1]["damping_model"], "nd");
  EXPECT_EQ(m["runs"][1]["set"], nlohmann::json({"damping.model=nd", "triaxial.lateral_rate_factor=20"}));
  EXPECT_EQ(m["runs"][2]["damping_model"], "nd") << "a label without overrides runs the case's own damping";
  // The named model's override sits where it always did; the labelled entry's come last.
  EXPECT_EQ(s.runs[0].sets, (std::vector<std::string>{"damping.model=nd", "damping.ratio=0.005",
                                                      "triaxial.strain_rate=1e-05", "triaxial.lateral_rate_factor=5"}));
  EXPECT_EQ(s.runs[1].sets.back(), "triaxial.lateral_rate_factor=20");
  fs::remove_all(dir);
}

// The shipped staged study: its runs and steps as its header says.
TEST(StudyCli, PaperFullStudyIsWhatItsHeaderSays) {
  const qsdem::Study s = qsdem::load_study(source_dir / "studies/paper-full.toml");
  ASSERT_EQ(s.stages.size(), 5u);
  double steps0 = 0;
  for (const auto& r : s.runs) steps0 += r.expected_steps;
  EXPECT_EQ(s.runs.size(), 100u);  // sweep 96, table5 2, reference 2; slow and slowest are picked later
  EXPECT_DOUBLE_EQ(steps0, 28'062'500);
  // The sweep, which the slow stages pick from, first; every other stage with the picked ones, so
  // that Table 5's long runs share the pool with them.
  EXPECT_EQ(s.stages[0].level, 0);
  for (std::size_t k = 1; k < 5; ++k) EXPECT_EQ(s.stages[k].level, 1) << s.stages[k].name;
  EXPECT_EQ(s.analysis.baseline, "od");
  EXPECT_TRUE(s.analysis.has_reference);
}

namespace {

// A column of a series.csv, by header name.
std::vector<double> column(const fs::path& csv, const std::string& name) {
  std::ifstream in(csv);
  std::string line;
  std::getline(in, line);
  std::stringstream hs(line);
  std::size_t at = 0, k = 0;
  for (std::string c; std::getline(hs, c, ','); ++k)
    if (c == name) at = k;
  std::vector<double> v;
  while (std::getline(in, line)) {
    std::stringstream ls(line);
    std::string c;
    for (std::size_t i = 0; i <= at; ++i) std::getline(ls, c, ',');
    v.push_back(std::stod(c));
  }
  return v;
}

std::vector<std::string> stage_run_dirs(const nlohmann::json& m, const std::string& stage) {
  std::vector<std::string> dirs;
  for (const auto& r : m["runs"])
    if (r.value("stage", std::string()) == stage) dirs.push_back(r["dir"]);
  return dirs;
}

}  // namespace

// studies/tiny-staged.toml: the sweep (and the reference) run first; then the optimum of each model
// is picked from the sweep's finished runs, recorded in study.json, and run at the slower rate.
TEST(StudyStages, PicksTheOptimumOfTheFinishedSweep) {
  const Reference& ref = staged_reference();
  ASSERT_TRUE(completed(ref.result)) << ref.result.err;
  const auto m = manifest(ref.dir);
  ASSERT_EQ(m["stages"].size(), 3u);
  const auto& slow = m["stages"][1];
  EXPECT_EQ(slow["from"], "sweep");
  ASSERT_EQ(slow["picks"].size(), 2u);
  for (const auto& p : slow["picks"]) {
    const std::string model = p["model"];
    SCOPED_TRACE(model);
    EXPECT_EQ(p["runs_used"], 3) << "the pick waits for the whole sweep";
    // The sweep's mean IMom at its three ratios, through the optimum fit, to 2 significant digits.
    std::vector<double> xi, imom;
    for (const char* x : {"0.2", "0.5", "1"}) {
      const auto s = nlohmann::json::parse(
          slurp(ref.dir / fmt::format("runs/tiny-seed1/{}/xi-{}%/rate-5e-06/summary.json", model, x)));
      xi.push_back(std::stod(x) / 100), imom.push_back(s["mean_imom"].get<double>());
    }
    const double opt = qsdem::fit_optimum(xi, imom).xi_opt;
    EXPECT_DOUBLE_EQ(p["xi_opt"].get<double>(), opt);
    const double picked = std::stod(fmt::format("{:.2g}", opt));
    ASSERT_EQ(p["ratios"], nlohmann::json::array({picked}));
    // The run at the picked ratio, at the stage's rate, with exactly that ratio.
    const fs::path run = ref.dir / fmt::format("runs/tiny-seed1/{}/xi-{:g}%/rate-2.5e-06", model, 100 * picked);
    ASSERT_TRUE(fs::exists(run / "summary.json")) << run;
    const auto cfg = nlohmann::json::parse(slurp(run / "summary.json"))["config"]["resolved_si"]["protocol"][1];
    EXPECT_EQ(cfg["damping"]["ratio"].get<double>(), picked);
    EXPECT_EQ(cfg["damping"]["model"], model);
  }
  // The order on stderr: the first level finished, then the picks, then the second level.
  const std::string& err = ref.result.err;
  const auto first_done = err.find("runs of stage sweep: 6/6 done, 0 running");
  const auto picked = err.find("stage slow: tiny od: ");
  const auto second = err.find("runs of stage slow, reference: 0/3 done");
  ASSERT_NE(first_done, std::string::npos) << err;
  ASSERT_NE(picked, std::string::npos) << err;
  EXPECT_LT(first_done, picked);
  EXPECT_LT(picked, second);
  // The labelled entry ran the case undamped.
  const auto undamped = std::find_if(m["runs"].begin(), m["runs"].end(), [](const auto& r) { return r["model"] == "undamped"; });
  ASSERT_NE(undamped, m["runs"].end());
  EXPECT_EQ((*undamped)["damping_model"], "none");
  EXPECT_EQ((*undamped)["stage"], "reference");
  const fs::path ref_run = ref.dir / (*undamped)["dir"].get<std::string>();
  EXPECT_EQ(nlohmann::json::parse(slurp(ref_run / "summary.json"))["config"]["resolved_si"]["protocol"][1]["damping"]["model"],
            "none");
  // The damping dependence against the undamped run: one row per run; one RMS dphi by hand (both
  // runs sample the same strains, so no interpolation is needed).
  const std::string dev = slurp(ref.dir / "analysis" / "deviation.csv");
  EXPECT_EQ(std::count(dev.begin(), dev.end(), '\n'), 10);
  const fs::path run = ref.dir / "runs/tiny-seed1/od/xi-1%/rate-5e-06";
  const auto e_ref = column(ref_run / "series.csv", "e1"), e_run = column(run / "series.csv", "e1");
  ASSERT_EQ(e_ref, e_run);
  const auto p_ref = column(ref_run / "series.csv", "phi_deg"), p_run = column(run / "series.csv", "phi_deg");
  double sum = 0;
  for (std::size_t k = 0; k < p_ref.size(); ++k) sum += (p_run[k] - p_ref[k]) * (p_run[k] - p_ref[k]);
  const std::string row = dev.substr(dev.find("tiny-seed1/od/xi-1%/rate-5e-06,"));
  std::vector<std::string> cells;
  std::stringstream rs(row.substr(0, row.find('\n')));
  for (std::string c; std::getline(rs, c, ',');) cells.push_back(c);
  ASSERT_GT(cells.size(), 8u);
  EXPECT_NEAR(std::stod(cells[8]), std::sqrt(sum / double(p_ref.size())), 1e-8 * std::stod(cells[8]));
  const std::string md = slurp(ref.dir / "analysis" / "tables.md");
  EXPECT_NE(md.find("### Stages of the design"), std::string::npos);
  EXPECT_NE(md.find("### Damping ratios picked by later stages"), std::string::npos);
  EXPECT_TRUE(fs::exists(ref.dir / "analysis/figures/stage_slow_tiny.png"));
}

// SIGTERM while the second stage runs: `qsdem study` again keeps the recorded picks, finishes the
// stage and gives the uninterrupted study's study.json and series.
TEST(StudyStages, KilledInTheSecondStageResumesToTheSameResults) {
  const Reference& ref = staged_reference();
  ASSERT_TRUE(completed(ref.result)) << ref.result.err;
  const auto m = manifest(ref.dir);
  const std::vector<std::string> slow = stage_run_dirs(m, "slow");
  ASSERT_EQ(slow.size(), 2u);
  const fs::path dir = fresh_dir("staged-killed");
  const fs::path out = dir / "study";
  const pid_t pid = spawn({binary, "study", staged_study.string(), "--out", out.string()}, dir / "first");
  const auto started = [&] {
    for (const auto& d : slow) {
      const fs::path p = out / d / "series.csv.partial";
      if (!fs::exists(p) || fs::exists(out / d / "summary.json")) continue;
      const std::string rows = slurp(p);
      if (std::count(rows.begin(), rows.end(), '\n') <= 2) return true;
    }
    return false;
  };
  const auto deadline = std::chrono::steady_clock::now() + std::chrono::minutes(3);
  while (!started() && std::chrono::steady_clock::now() < deadline) std::this_thread::sleep_for(std::chrono::milliseconds(2));
  ASSERT_TRUE(started()) << "the second stage never began";
  ASSERT_EQ(::kill(pid, SIGTERM), 0);
  const Result first = finish(pid, dir / "first");
  EXPECT_EQ(first.code, 143) << first.err;
  ASSERT_TRUE(manifest(out)["stages"][1].contains("picks"));
  EXPECT_EQ(manifest(out)["stages"][1]["picks"], m["stages"][1]["picks"]) << "picked before the stage began";

  // The study file's header was edited meanwhile (same tables and values): the study continues, and
  // its copy takes the new text.
  write(out / "study.toml", "# an older header of the same study\n" + slurp(staged_study));
  const Result second = study(staged_study, out, dir / "second", false);
  EXPECT_TRUE(completed(second)) << second.err;
  EXPECT_EQ(slurp(out / "study.toml"), slurp(staged_study));
  EXPECT_EQ(second.err.find("now gives"), std::string::npos) << second.err;
  EXPECT_EQ(slurp(out / "study.json"), slurp(ref.dir / "study.json"));
  for (const auto& r : m["runs"]) {
    const std::string rel = r["dir"].get<std::string>() + "/series.csv";
    ASSERT_TRUE(fs::exists(out / rel)) << rel;
    EXPECT_EQ(slurp(out / rel), slurp(ref.dir / rel)) << rel;
  }
  EXPECT_EQ(analysis_tables(out), analysis_tables(ref.dir));
  fs::remove_all(dir);
}

// A re-analysis whose optimum moved after the later stage ran (here: a sweep result edited) does
// not mix: the stage keeps its recorded ratios and runs, `qsdem study` says so, the report flags it.
TEST(StudyStages, ChangedOptimumIsFlaggedNotMixed) {
  const Reference& ref = staged_reference();
  ASSERT_TRUE(completed(ref.result)) << ref.result.err;
  const fs::path dir = fresh_dir("staged-changed");
  const fs::path out = dir / "study";
  fs::copy(ref.dir, out, fs::copy_options::recursive);
  const auto m = manifest(out);
  std::map<std::string, fs::file_time_type> mtimes;
  for (const auto& r : m["runs"]) mtimes[r["dir"]] = fs::last_write_time(out / r["dir"].get<std::string>() / "summary.json");
  // od's lowest index now at the smallest ratio: its optimum moves to the edge, 0.2 %.
  const fs::path edited = out / "runs/tiny-seed1/od/xi-0.2%/rate-5e-06/summary.json";
  auto s = nlohmann::json::parse(slurp(edited));
  s["mean_imom"] = 1e-6;
  write(edited, s.dump());
  mtimes["runs/tiny-seed1/od/xi-0.2%/rate-5e-06"] = fs::last_write_time(edited);

  const Result r = study(staged_study, out, dir / "log", false);
  EXPECT_TRUE(completed(r)) << r.err;
  EXPECT_NE(r.err.find("stage slow: the optimum of stage sweep for tiny od now gives 0.2 % (picked before: "),
            std::string::npos)
      << r.err;
  EXPECT_EQ(manifest(out)["stages"][1]["picks"], m["stages"][1]["picks"]);
  EXPECT_EQ(manifest(out)["runs"], m["runs"]) << "no run added or dropped";
  for (const auto& [d, t] : mtimes) EXPECT_EQ(fs::last_write_time(out / d / "summary.json"), t) << d << " was run again";
  const std::string md = slurp(out / "analysis" / "tables.md");
  EXPECT_NE(md.find("CHANGED: the optimum now gives 0.2 %"), std::string::npos) << md;
  fs::remove_all(dir);
}

// `mpirun -np 2` on a staged study: every rank takes the picks rank 0 made, and the results are
// those of one process.
TEST(StudyStages, MpiRanksRunTheStagesAlike) {
  if (std::system("command -v mpirun > /dev/null 2>&1") != 0) GTEST_SKIP() << "mpirun is not installed";
  const Reference& ref = staged_reference();
  ASSERT_TRUE(completed(ref.result)) << ref.result.err;
  const fs::path dir = fresh_dir("staged-mpi");
  ::setenv("OMPI_ALLOW_RUN_AS_ROOT", "1", 1);
  ::setenv("OMPI_ALLOW_RUN_AS_ROOT_CONFIRM", "1", 1);
  const Result r = run({"mpirun", "-np", "2", "--oversubscribe", binary, "study", staged_study.string(), "--out",
                        (dir / "study").string()},
                       dir / "log");
  ASSERT_TRUE(completed(r)) << "exit code " << r.code << "\n" << r.err << r.out;
  EXPECT_EQ(slurp(dir / "study/study.json"), slurp(ref.dir / "study.json"));
  const auto m = manifest(ref.dir);  // named: a range over a temporary's member would dangle
  ASSERT_EQ(m["runs"].size(), 9u);
  for (const auto& run : m["runs"]) {
    const std::string rel = run["dir"].get<std::string>() + "/series.csv";
    ASSERT_TRUE(fs::exists(dir / "study" / rel)) << rel;
    EXPECT_EQ(slurp(dir / "study" / rel), slurp(ref.dir / rel)) << rel;
    // Run once, by one rank: one start in its log.
    const std::string log = slurp(dir / "study" / run["dir"].get<std::string>() / "run.log");
    EXPECT_EQ(log.find("=== qsdem"), log.rfind("=== qsdem")) << rel << " started more than once";
    EXPECT_NE(log.find("=== qsdem"), std::string::npos) << rel;
  }
  fs::remove_all(dir);
}

// studies/damping-small.toml: its runs as its header says, and its design runs: the
// same [design], stages and [analysis] on 120 spheres sheared to 0.2 %, every run to its end with
// its model's damping, then the analysis with the damping dependence against the undamped runs.
TEST(Study, DampingSmallStudyRunsOnATinySample) {
  const fs::path file = source_dir / "studies" / "damping-small.toml";
  const qsdem::Study shipped = qsdem::load_study(file);
  EXPECT_EQ(shipped.samples.size(), 2u);
  EXPECT_EQ(shipped.runs.size(), 36u) << "2 samples x 9 runs x 2 rates";
  std::string design = slurp(file);
  design = design.substr(design.find("[design]\n") + 9);
  const fs::path dir = fresh_dir("damping_small");
  write(dir / "s.toml", "name = \"damping-tiny\"\n[[sample]]\nname = \"tiny\"\ncase = \"" +
                            (source_dir / "examples/spheres-A-small.toml").string() +
                            "\"\nset = ['sample.particles=[{shape=\"sphere\", diameter=\"2.4 mm\", count=60}, "
                            "{shape=\"sphere\", diameter=\"2.0 mm\", count=60}]', \"sample.total_particles=0\", "
                            "\"sample.initial_solid_fraction=0.2\", \"compaction.max_strain_rate=1e-3\"]\n"
                            "[design]\nset = [\"triaxial.final_axial_strain=0.2 %\", \"triaxial.sample_points=5\"]\n" +
                            design);
  const Result r = study(dir / "s.toml", dir / "out", dir / "log");
  ASSERT_TRUE(completed(r)) << "exit code " << r.code << "\n" << r.err;
  const auto m = manifest(dir / "out");
  ASSERT_EQ(m["runs"].size(), 18u);
  std::set<std::string> models;
  for (const auto& run : m["runs"]) {
    const fs::path d = dir / "out" / run["dir"].get<std::string>();
    SCOPED_TRACE(d.string());
    const auto s = nlohmann::json::parse(slurp(d / "summary.json"));
    const auto& cfg = s["config"]["resolved_si"]["protocol"][1];
    EXPECT_EQ(cfg["damping"]["model"], run.contains("damping_model") ? run["damping_model"] : run["model"]);
    EXPECT_EQ(cfg["damping"]["ratio"], run["xi"]);
    EXPECT_EQ(s["triaxial"]["rows"], 5);
    if (run["model"] == "nd-translation") {
      EXPECT_EQ(cfg["damping"]["acts_on"], "translation");
    } else if (run["model"] == "nd-rotation") {
      EXPECT_EQ(cfg["damping"]["acts_on"], "rotation");
    }
    models.insert(run["model"].get<std::string>());
  }
  EXPECT_EQ(models, (std::set<std::string>{"none", "od", "nd", "stiffness", "local", "contact", "nd-translation",
                                           "nd-rotation"}));
  EXPECT_TRUE(fs::exists(dir / "out" / "analysis" / "per_run.csv"));
  fs::remove_all(dir);
}

// rate_control in a stage: one controlled run per (sample, model, ratio, start rate), its own id,
// the override after the study's keys, and the controller in study.json.
TEST(StudyCli, RateControlStageRunsAndManifest) {
  const fs::path dir = fresh_dir("control_parse");
  write(dir / "s.toml", "[[sample]]\nname = \"A\"\ncase = \"" + (source_dir / "examples/spheres-A-small.toml").string() +
                            "\"\n[design]\nmodels = [\"nd\"]\n"
                            "[[stage]]\nname = \"sweep\"\ndamping_ratios = [\"0.5 %\"]\nstrain_rates = [1e-5, 3e-6]\n"
                            "[[stage]]\nname = \"control\"\ndamping_ratios = [\"0.5 %\"]\nstrain_rates = [1e-5]\n"
                            "rate_control = { index = \"imom\", target = \"0.1 %\", min_rate = 1e-8, max_rate = 2e-5, "
                            "gain = 0.3, filter_points = 3 }\n");
  const qsdem::Study s = qsdem::load_study(dir / "s.toml");
  ASSERT_EQ(s.runs.size(), 3u);
  const qsdem::StudyRun& c = s.runs[2];
  EXPECT_EQ(c.id, "A-seed1/nd/xi-0.5%/rate-1e-05-control-imom-0.1%") << "not the directory of the constant 1e-5 run";
  EXPECT_EQ(s.runs[0].id, "A-seed1/nd/xi-0.5%/rate-1e-05");
  EXPECT_FALSE(s.runs[0].control.on());
  EXPECT_EQ(c.dir, "runs/" + c.id);
  EXPECT_DOUBLE_EQ(c.rate, 1e-5);
  EXPECT_EQ(c.control.index, "imom");
  EXPECT_DOUBLE_EQ(c.control.target, 0.001);
  const std::string table = "{ filter_points = 3, gain = 0.3, index = \"imom\", max_rate = 2e-05, min_rate = 1e-08, "
                            "target = \"0.1 %\" }";
  EXPECT_EQ(c.sets, (std::vector<std::string>{"damping.model=nd", "damping.ratio=0.005", "triaxial.strain_rate=1e-05",
                                              "triaxial.rate_control=" + table}));
  // The ETA's guess: the steps at the geometric mean of the start rate and min_rate (10 % / (0.32 x 3.16e-7)).
  EXPECT_NEAR(c.expected_steps, std::round(0.1 / (0.32 * std::sqrt(1e-5 * 1e-8))), 0.5);
  const auto m = qsdem::study_manifest(s);
  EXPECT_EQ(m["stages"][1]["rate_control"]["index"], "imom");
  EXPECT_FALSE(m["stages"][0].contains("rate_control"));
  const auto& run = m["runs"][2];
  EXPECT_EQ(run["stage"], "control");
  EXPECT_EQ(run["rate"], 1e-5);
  EXPECT_EQ(run["rate_control"]["index"], "imom");
  EXPECT_EQ(run["rate_control"]["target"], 0.001);
  EXPECT_EQ(run["rate_control"]["set"], "triaxial.rate_control=" + table);
  EXPECT_FALSE(m["runs"][0].contains("rate_control"));

  // The one-stage [design]: every run controlled.
  write(dir / "d.toml", "[[sample]]\nname = \"A\"\ncase = \"" + (source_dir / "examples/spheres-A-small.toml").string() +
                            "\"\n[design]\nmodels = [\"od\", \"nd\"]\ndamping_ratios = [\"0.5 %\"]\nstrain_rates = [1e-5]\n"
                            "rate_control = { index = \"ufr\", target = \"2 %\", min_rate = 1e-7, max_rate = 1e-5 }\n");
  const qsdem::Study d = qsdem::load_study(dir / "d.toml");
  ASSERT_EQ(d.runs.size(), 2u);
  EXPECT_EQ(d.runs[1].id, "A-seed1/nd/xi-0.5%/rate-1e-05-control-ufr-2%");
  EXPECT_EQ(qsdem::study_manifest(d)["runs"][0]["rate_control"]["index"], "ufr");
  fs::remove_all(dir);
}

// A tiny study with a constant-rate stage and a controlled stage (200 spheres, 3 % strain): the
// controlled run lands in its own directory, runs under the controller (its strain_rate column and
// summary record), is kept out of the power law of the constant-rate runs, and the analysis holds
// the controller's record beside the constant-rate fit's rate at the same target.
TEST(Study, ControlledStageRunsBesideTheSweep) {
  const fs::path dir = fresh_dir("control_run");
  write(dir / "s.toml", "name = \"control-tiny\"\n[[sample]]\nname = \"tiny\"\ncase = \"" +
                            (source_dir / "examples/spheres-A-small.toml").string() +
                            "\"\nset = ['sample.particles=[{shape=\"sphere\", diameter=\"2 mm\", count=150}, "
                            "{shape=\"sphere\", diameter=\"2.4 mm\", count=50}]', \"sample.total_particles=0\", "
                            "\"sample.seed=3\", \"compaction.max_strain_rate=1e-4\"]\n"
                            "[design]\nmodels = [\"nd\"]\n"
                            "set = [\"triaxial.final_axial_strain=3 %\", \"triaxial.sample_points=60\"]\n"
                            "[[stage]]\nname = \"sweep\"\ndamping_ratios = [\"0.5 %\"]\nstrain_rates = [1e-4, 3e-5]\n"
                            "[[stage]]\nname = \"control\"\ndamping_ratios = [\"0.5 %\"]\nstrain_rates = [1e-4]\n"
                            "rate_control = { target = \"3 %\", min_rate = 1e-6, max_rate = 1e-3 }\n"
                            "[execution]\nparallel_runs = 2\n");
  const Result r = study(dir / "s.toml", dir / "out", dir / "log");
  ASSERT_TRUE(completed(r)) << "exit code " << r.code << "\n" << r.err;
  const fs::path out = dir / "out";
  const std::string cid = "tiny-seed3/nd/xi-0.5%/rate-0.0001-control-imom-3%";
  const fs::path cdir = out / "runs" / cid;
  ASSERT_TRUE(fs::exists(cdir / "summary.json"));
  ASSERT_TRUE(fs::exists(out / "runs/tiny-seed3/nd/xi-0.5%/rate-0.0001/summary.json")) << "the constant run, apart";
  const auto summary = nlohmann::json::parse(slurp(cdir / "summary.json"));
  ASSERT_TRUE(summary["triaxial"].contains("controller"));
  const auto& ctl = summary["triaxial"]["controller"];
  const std::vector<double> rate = column(cdir / "series.csv", "strain_rate");
  ASSERT_EQ(rate.size(), 60u);
  EXPECT_LT(*std::min_element(rate.begin(), rate.end()), 1e-4) << "the controller lowered the rate";

  const auto a = nlohmann::json::parse(slurp(out / "analysis/analysis.json"));
  ASSERT_EQ(a["power_laws"].size(), 1u);
  EXPECT_EQ(a["power_laws"][0]["n_rates"], 2) << "the fit holds the two constant-rate runs only";
  ASSERT_EQ(a["controlled_runs"].size(), 1u);
  const auto& c = a["controlled_runs"][0];
  EXPECT_EQ(c["id"], cid);
  EXPECT_EQ(c["finished"], true);
  EXPECT_EQ(c["index"], "imom");
  EXPECT_DOUBLE_EQ(c["target"].get<double>(), 0.03);
  for (const char* k : {"mean_strain_rate", "final_strain_rate", "min_strain_rate", "max_strain_rate", "share_within_band",
                        "band_factor", "constant_rate_steps_at_final", "constant_rate_steps_at_mean", "rows"})
    EXPECT_EQ(c[k], ctl[k]) << k;
  EXPECT_EQ(c["mean_index"], summary["mean_imom"]);
  EXPECT_EQ(c["steps"], summary["steps"]);
  EXPECT_EQ(c["wall_s"], summary["wall_s"]);
  EXPECT_EQ(c["constant_rate_fit"]["n"], 2);
  const auto& law = a["power_laws"][0];
  const double eps_qs = std::pow(0.03 / law["a"].get<double>(), 1 / law["b"].get<double>());
  EXPECT_NEAR(c["constant_rate_fit"]["eps_qs_at_target"].get<double>(), eps_qs, 1e-9 * eps_qs)
      << "one ratio: the law at the optimum is the fit of the same runs";
  EXPECT_NEAR(c["mean_over_eps_qs"].get<double>(), ctl["mean_strain_rate"].get<double>() / eps_qs, 1e-9);
  EXPECT_NE(slurp(out / "report.html").find("Controlled runs"), std::string::npos);
  fs::remove_all(dir);
}
