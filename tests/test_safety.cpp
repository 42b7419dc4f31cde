// Run safety (docs/runs.md): nothing lost, nothing mixed. A crash at every instant of the end of a
// run, two processes in one directory, what a run refuses before it touches its directory,
// `resume --set`, and the messages of bad input; real processes where the behaviour is the
// process's.
#include <dlfcn.h>
#include <gtest/gtest.h>
#include <signal.h>
#include <unistd.h>

#include <chrono>
#include <cmath>
#include <cstdio>
#include <filesystem>
#include <functional>
#include <fstream>
#include <map>
#include <mutex>
#include <nlohmann/json.hpp>
#include <sstream>
#include <string>
#include <thread>
#include <vector>

#include "qsdem/run/checkpoint.hpp"
#include "qsdem/run/config.hpp"
#include "qsdem/run/generate.hpp"
#include "qsdem/run/packing_io.hpp"
#include "qsdem/run/run.hpp"
#include "qsdem/run/run_directory.hpp"
#include "qsdem/version.hpp"
#include "test_support.hpp"

// Every fsync of this test program, recorded by file name while `record_fsyncs` is set, then passed
// on to the C library's (the engine is linked into this program, so its calls come here).
namespace {
std::mutex fsync_mutex;
bool record_fsyncs = false;
std::vector<std::string> fsynced;
}  // namespace

extern "C" int fsync(int fd) {
  using Fsync = int (*)(int);
  static const Fsync libc_fsync = reinterpret_cast<Fsync>(::dlsym(RTLD_NEXT, "fsync"));
  {
    const std::lock_guard<std::mutex> lock(fsync_mutex);
    if (record_fsyncs) {
      char target[4096];
      const std::string link = "/proc/self/fd/" + std::to_string(fd);
      const ssize_t n = ::readlink(link.c_str(), target, sizeof target - 1);
      fsynced.push_back(n > 0 ? std::filesystem::path(std::string(target, static_cast<std::size_t>(n))).filename().string()
                              : std::string("?"));
    }
  }
  return libc_fsync(fd);
}

using namespace qsdem;
namespace fs = std::filesystem;
using qsdem_test::slurp;

namespace {

// 120 spheres of 2.0 and 2.4 mm to 1 % axial strain: 250 triaxial steps, a row every 25 steps
// (10 rows), about 15000 compaction steps (~1 s).
const std::string tiny_case = qsdem_test::tiny_case("safety-tiny") + "[checkpoint]\nevery_sample_points = 4\n";

const fs::path root = fs::temp_directory_path() / ("qsdem_safety_" + std::to_string(::getpid()));

fs::path fresh(const std::string& name) {
  const fs::path d = root / name;
  fs::remove_all(d);
  fs::create_directories(root);
  return d;
}

Params tiny(const std::vector<std::string>& overrides = {}) { return parse_case(tiny_case, "tiny.toml", overrides); }

fs::path tiny_file() {
  const fs::path f = root / "tiny.toml";
  fs::create_directories(root);
  std::ofstream(f) << tiny_case;
  return f;
}

RunOptions to(const fs::path& dir, bool prepare_only = false) {
  RunOptions o;
  o.out = dir;
  o.quiet = true;
  o.prepare_only = prepare_only;
  return o;
}

// The message of the InputError `f` throws ("" if none).
template <class F>
std::string input_error(F&& f) {
  try {
    f();
  } catch (const InputError& e) {
    return e.what();
  }
  return "";
}

using qsdem_test::Cli;
using qsdem_test::finish;

pid_t spawn(const std::vector<std::string>& args, const fs::path& log) {
  std::vector<std::string> all{QSDEM_BINARY};
  all.insert(all.end(), args.begin(), args.end());
  return qsdem_test::spawn_logged(all, log);
}

Cli cli(const std::vector<std::string>& args, const std::string& log_name) {
  const fs::path log = root / log_name;
  fs::create_directories(root);
  return finish(spawn(args, log), log);
}

bool wait_for(const std::function<bool()>& cond, pid_t pid) {
  const auto deadline = std::chrono::steady_clock::now() + std::chrono::seconds(120);
  while (std::chrono::steady_clock::now() < deadline) {
    if (cond()) return true;
    int status = 0;
    if (pid > 0 && ::waitpid(pid, &status, WNOHANG) == pid) return false;
    std::this_thread::sleep_for(std::chrono::milliseconds(2));
  }
  return false;
}

long lines(const fs::path& p) {
  std::ifstream in(p);
  long n = 0;
  for (std::string l; std::getline(in, l);) ++n;
  return n;
}

// The uninterrupted tiny run, made once.
const fs::path& reference() {
  static const fs::path dir = [] {
    const fs::path d = fresh("reference");
    run_case(tiny(), to(d));
    return d;
  }();
  return dir;
}

}  // namespace

// The files of a run directory (relative paths) and a comparable form of each: the bytes, but for
// what legitimately differs between an uninterrupted run and a resumed one, the time it took.
// summary.json without its wall times, speed, peak memory and stage timings (each process measures
// its own); a checkpoint (sample.qsck) re-saved with its wall times and stage timers zeroed.
std::map<std::string, std::string> comparable_files(const fs::path& dir) {
  std::map<std::string, std::string> files;
  for (const auto& e : fs::recursive_directory_iterator(dir)) {
    if (!e.is_regular_file()) continue;
    const std::string name = fs::relative(e.path(), dir).string();
    std::string& text = files[name];
    if (name == "summary.json") {
      nlohmann::json s = nlohmann::json::parse(slurp(e.path()));
      for (const char* key : {"wall_s", "particle_steps_per_s", "peak_rss_kib", "stages", "stage_table"}) s.erase(key);
      for (const char* part : {"compaction", "triaxial"})
        if (s.contains(part)) s[part].erase("wall_s");
      for (auto& phase : s["phases"]) phase.erase("wall_s");
      text = s.dump(1);
    } else if (e.path().extension() == ".qsck") {
      Checkpoint c = load_checkpoint(e.path());
      c.state.timers = {};
      c.run.wall_s = 0;
      for (PhaseRecord& r : c.run.phases) r.wall_s = 0;
      const fs::path f = root / "comparable.qsck";
      save_checkpoint(f, c.case_text, c.case_source, c.state, c.run);
      text = slurp(f);
    } else {
      text = slurp(e.path());
    }
  }
  return files;
}

// A crash at any instant of the end of a phase (SIGKILL, or no room for the next file) leaves a
// directory that `resume` finishes to the uninterrupted run's results: every file the same
// (comparable_files: but the time taken). The run copies its directory after every write and
// rename of the end of compaction and of the triaxial test: each copy is what a SIGKILL at that
// instant leaves (every write before it is synchronous and flushed).
TEST(RunSafety, EveryInstantOfTheEndOfARunResumes) {
  const fs::path ref = reference();
  ASSERT_TRUE(fs::exists(ref / "classes.csv"));
  const fs::path live = fresh("end-live");
  std::vector<std::pair<std::string, fs::path>> copies;
  RunOptions o = to(live);
  o.after_write = [&](const std::string& what) {
    const fs::path copy = fresh("end-copy-" + std::to_string(copies.size()));
    fs::copy(live, copy, fs::copy_options::recursive);
    copies.emplace_back(what, copy);
  };
  run_case(tiny(), o);
  ASSERT_GE(copies.size(), 12u);
  for (const auto& [what, dir] : copies) {
    SCOPED_TRACE("crash after: " + what);
    const bool finished = fs::exists(dir / "summary.json") && !fs::exists(dir / checkpoint_file);
    if (!finished) {
      EXPECT_NO_THROW(resume_run(dir, to(dir)));
    }
    for (const char* f : {"series.csv", "compaction.csv", "classes.csv", "compacted.packing", "final.packing"})
      EXPECT_EQ(slurp(dir / f), slurp(ref / f)) << f;
    const auto got = comparable_files(dir), want = comparable_files(ref);
    for (const auto& [name, text] : want) {
      ASSERT_TRUE(got.count(name)) << name << " is missing";
      EXPECT_EQ(got.at(name), text) << name;
    }
    for (const auto& [name, text] : got) EXPECT_TRUE(want.count(name)) << name << ": not in the uninterrupted run";
    EXPECT_TRUE(fs::exists(dir / "summary.json"));
    EXPECT_TRUE(fs::exists(dir / prepared_sample_file)) << "a run that compacted leaves its prepared sample";
    EXPECT_FALSE(fs::exists(dir / checkpoint_file));
    EXPECT_FALSE(fs::exists(dir / "checkpoint.qsck.prev"));
    EXPECT_FALSE(fs::exists(dir / "series.csv.partial"));
    EXPECT_FALSE(fs::exists(dir / "classes.csv.partial"));
    EXPECT_THROW(resume_run(dir, to(dir)), InputError) << "finished: nothing to resume";
  }
}

// Two processes in one run directory: the second is refused with a message naming the directory
// and the other qsdem, and the first finishes with its own files only.
TEST(RunSafety, TwoProcessesInOneDirectory) {
  const fs::path d = fresh("two");
  const fs::path file = tiny_file();
  // 500 particles: the first run lasts long enough for three attempts of a second one
  const pid_t first = spawn({"run", file.string(), "--out", d.string(), "--quiet", "--set", "name=\"first\"", "--set",
                             "sample.total_particles=500"},
                            root / "two-first");
  ASSERT_TRUE(wait_for([&] { return fs::exists(d / "case.toml"); }, first));
  for (const auto& args : std::vector<std::vector<std::string>>{
           {"run", file.string(), "--out", d.string(), "--quiet", "--force", "--set", "name=\"second\""},
           {"prepare", file.string(), "--out", d.string(), "--quiet", "--force"},
           {"resume", d.string(), "--quiet"}}) {
    SCOPED_TRACE(args[0]);
    const Cli second = cli(args, "two-second");
    EXPECT_EQ(second.code, 2) << second.err;
    EXPECT_NE(second.err.find("another qsdem"), std::string::npos) << second.err;
    EXPECT_NE(second.err.find(d.string()), std::string::npos) << second.err;
  }
  const Cli one = finish(first, root / "two-first");
  ASSERT_EQ(one.code, 0) << one.err;
  EXPECT_NE(slurp(d / "case.toml").find("first"), std::string::npos);
  const auto summary = nlohmann::json::parse(slurp(d / "summary.json"));
  EXPECT_EQ(summary["case"], "first");
  EXPECT_EQ(summary["triaxial"]["rows"], 10);
  EXPECT_EQ(lines(d / "series.csv"), 11);
}

// `run --force` into the prepared sample it shears is refused before anything is removed.
TEST(RunSafety, ForceDoesNotRemoveTheSampleARunShears) {
  const fs::path d = fresh("self");
  run_case(tiny(), to(d, true));
  const std::string sample = slurp(d / prepared_sample_file);
  RunOptions o = to(d);
  o.force = true;
  const std::string e = input_error([&] { run_case(tiny({"sample.from=" + d.string()}), o); });
  EXPECT_NE(e.find("is the --out directory"), std::string::npos) << e;
  EXPECT_EQ(slurp(d / prepared_sample_file), sample);
}

// A `prepare` stopped by SIGTERM resumes to a prepared sample (no shearing), equal to the
// uninterrupted prepare's.
TEST(RunSafety, StoppedPrepareResumesToAPreparedSample) {
  const fs::path ref = fresh("prepare-ref");
  run_case(tiny(), to(ref, true));
  const fs::path d = fresh("prepare-stopped");
  const pid_t pid = spawn({"prepare", tiny_file().string(), "--out", d.string(), "--quiet", "--threads", "1"},
                          root / "prepare-stopped");
  ASSERT_TRUE(wait_for([&] { return lines(d / "compaction.csv.partial") > 10; }, pid));
  ::kill(pid, SIGTERM);
  ASSERT_EQ(finish(pid, root / "prepare-stopped").code, 143);
  const Cli resumed = cli({"resume", d.string(), "--quiet"}, "prepare-resume");
  ASSERT_EQ(resumed.code, 0) << resumed.err;
  EXPECT_TRUE(fs::exists(d / prepared_sample_file));
  EXPECT_FALSE(fs::exists(d / "series.csv"));
  EXPECT_FALSE(fs::exists(d / "series.csv.partial")) << "a prepare never shears";
  EXPECT_FALSE(fs::exists(d / checkpoint_file));
  EXPECT_FALSE(nlohmann::json::parse(slurp(d / "summary.json")).contains("triaxial"));
  EXPECT_EQ(slurp(d / "compacted.packing"), slurp(ref / "compacted.packing"));
  EXPECT_EQ(slurp(d / "compaction.csv"), slurp(ref / "compaction.csv"));
  const Checkpoint a = load_checkpoint(d / prepared_sample_file), b = load_checkpoint(ref / prepared_sample_file);
  EXPECT_EQ(a.state.step, b.state.step);
  EXPECT_EQ(a.state.particles.s, b.state.particles.s);
}

// A non-empty directory that holds no qsdem run is refused without --force; with it, only the
// files a run writes are removed.
TEST(RunSafety, ADirectoryOfOtherFilesIsNotOverwritten) {
  const fs::path d = fresh("foreign");
  fs::create_directories(d);
  std::ofstream(d / "series.csv") << "my own data\n";
  std::ofstream(d / "notes.txt") << "mine\n";
  const std::string e = input_error([&] { run_case(tiny(), to(d)); });
  EXPECT_NE(e.find("holds no qsdem run"), std::string::npos) << e;
  EXPECT_NE(e.find("--force"), std::string::npos) << e;
  EXPECT_EQ(slurp(d / "series.csv"), "my own data\n");
  RunOptions o = to(d, true);
  o.force = true;
  run_case(tiny(), o);
  EXPECT_EQ(slurp(d / "notes.txt"), "mine\n");
  EXPECT_FALSE(fs::exists(d / "series.csv"));
}

// Input errors found after the case is read leave no directory behind; the resolved path of
// sample.from is named.
TEST(RunSafety, InputErrorsLeaveNoDirectory) {
  const fs::path d = fresh("no-dir");
  std::string e = input_error([&] { run_case(tiny({"sample.from=no/such/sample"}), to(d)); });
  EXPECT_NE(e.find((fs::current_path() / "no/such/sample").string()), std::string::npos) << e;
  EXPECT_FALSE(fs::exists(d));
  // A packing whose largest particle is not smaller than half the cell (SPEC 3): named.
  const fs::path packing = root / "too-small.packing";
  std::ofstream(packing) << "format qsdem-packing 1\ncell 0.004 0 0 0 0.004 0 0 0 0.004\nparticles 1\n"
                            "0.001 0.001 0.001 0.001 0.001 0.001 1 0 0 0\n";
  e = input_error([&] { run_case(tiny({"sample.from=" + packing.string()}), to(d)); });
  EXPECT_NE(e.find(packing.string()), std::string::npos) << e;
  EXPECT_NE(e.find("half the smallest cell width"), std::string::npos) << e;
  EXPECT_FALSE(fs::exists(d));
  // A sample that would not fit in memory is refused before it is generated.
  e = input_error([&] { run_case(tiny({"sample.total_particles=100000000"}), to(d)); });
  EXPECT_NE(e.find("needs about"), std::string::npos) << e;
  EXPECT_NE(e.find("GiB"), std::string::npos) << e;
  EXPECT_NE(e.find("available"), std::string::npos) << e;
  EXPECT_NE(e.find("sample.total_particles"), std::string::npos) << e;
  EXPECT_FALSE(fs::exists(d));
}

// After a stop at run time, `resume --set` changes what may change without invalidating the
// state, records it in summary.json, and ends on the results of the run that never stopped (a
// limit decides when to stop, not what is computed).
TEST(RunSafety, ResumeSetContinuesAStoppedRun) {
  const fs::path ref = reference();
  const fs::path d = fresh("resume-set");
  try {
    run_case(tiny({"limits.max_kinetic_ratio=1e-30"}), to(d));
    ADD_FAILURE() << "the kinetic limit did not stop the run";
  } catch (const RunError& e) {
    // Step numbers are the phase's, as in series.csv: the first row's step.
    const std::string first_row = [&] {
      std::ifstream in(ref / "series.csv");
      std::string l;
      std::getline(in, l);
      std::getline(in, l);
      return l.substr(0, l.find(','));
    }();
    EXPECT_NE(std::string(e.what()).find("at triaxial step " + first_row + ":"), std::string::npos) << e.what();
  }
  ASSERT_TRUE(fs::exists(d / checkpoint_file));
  std::string e = input_error([&] {
    RunOptions o = to(d);
    o.sets = {"triaxial.friction=0.3"};
    resume_run(d, o);
  });
  EXPECT_NE(e.find("triaxial.friction"), std::string::npos) << e;
  for (const auto& key : resume_keys) EXPECT_NE(e.find(key), std::string::npos) << key << ": " << e;
  e = input_error([&] {
    RunOptions o = to(d);
    o.sets = {"time.step_ratio=0.2"};
    resume_run(d, o);
  });
  EXPECT_NE(e.find("only during compaction"), std::string::npos) << e;
  RunOptions o = to(d);
  o.sets = {"limits.max_kinetic_ratio=1"};
  const auto summary = resume_run(d, o);
  EXPECT_EQ(slurp(d / "series.csv"), slurp(ref / "series.csv"));
  ASSERT_TRUE(summary.contains("resume_changes"));
  EXPECT_EQ(summary["resume_changes"], nlohmann::json::array({"from triaxial step 0: limits.max_kinetic_ratio=1"}));
  EXPECT_EQ(summary["config"]["resolved_si"]["limits"]["max_kinetic_ratio"], 1.0);
  EXPECT_EQ(nlohmann::json::parse(slurp(d / "summary.json"))["resume_changes"], summary["resume_changes"]);
  // The run's compacted state is a prepared sample: shearing it again gives the same series.
  const fs::path again = fresh("resume-set-again");
  run_case(tiny({"sample.from=" + d.string()}), to(again));
  EXPECT_EQ(slurp(again / "series.csv"), slurp(ref / "series.csv"));
}

// A compaction stopped by compaction.max_steps continues with a larger one.
TEST(RunSafety, ResumeSetRaisesCompactionMaxSteps) {
  const fs::path ref = reference();
  const fs::path d = fresh("max-steps");
  // Compaction rows every 200 steps, a checkpoint every 4 rows: the last one at step 5600.
  EXPECT_THROW(run_case(tiny({"compaction.max_steps=6000"}), to(d)), RunError);
  ASSERT_TRUE(fs::exists(d / checkpoint_file));
  RunOptions o = to(d);
  o.sets = {"compaction.max_steps=2000000"};
  resume_run(d, o);
  EXPECT_EQ(slurp(d / "compaction.csv"), slurp(ref / "compaction.csv"));
  EXPECT_EQ(slurp(d / "series.csv"), slurp(ref / "series.csv"));
}

// The triaxial wall time in summary.json covers every process that worked on a resumed run.
// A run directory whose checkpoint, case.toml or rows come from another run is not resumed
// (rows of one run were followed by those of the other, exit 0): the checkpoint holds the digests
// of the case.toml the run wrote and of the rows it counts, and resume refuses a directory whose
// files differ, saying what to do. Nothing in it is changed.
TEST(RunSafety, ACheckpointOrRowsOfAnotherRunAreRefused) {
  const fs::path file = tiny_file();
  const auto stopped = [&](const std::string& name, const std::string& seed) {
    const fs::path d = fresh(name);
    const Cli c = cli({"run", file.string(), "--out", d.string(), "--quiet", "--set", "compaction.max_steps=3000",
                       "--set", "sample.seed=" + seed},
                      name);
    EXPECT_EQ(c.code, 3) << c.err;
    return d;
  };
  const fs::path a = stopped("mix-a", "1"), b = stopped("mix-b", "2");
  const auto mixed = [&](const std::string& name, const std::vector<std::string>& from_b) {
    const fs::path d = fresh(name);
    fs::copy(a, d, fs::copy_options::recursive);
    for (const std::string& f : from_b) fs::copy_file(b / f, d / f, fs::copy_options::overwrite_existing);
    return d;
  };
  const auto resume = [&](const fs::path& d) {
    return cli({"resume", d.string(), "--quiet", "--set", "compaction.max_steps=2000000"}, d.filename().string() + "-resume");
  };
  const struct {
    const char* name;
    std::vector<std::string> from_b;
    std::string says;
  } cases[] = {
      {"mix-checkpoint", {checkpoint_file, "checkpoint.qsck.prev"}, "is not the case.toml of the run that wrote"},
      {"mix-checkpoint-and-case", {checkpoint_file, "checkpoint.qsck.prev", "case.toml"}, "compaction.csv.partial' are not the rows the checkpoint counts"},
      {"mix-rows", {"compaction.csv.partial"}, "compaction.csv.partial' are not the rows the checkpoint counts"},
      {"mix-classes", {"classes.csv.partial"}, "classes.csv.partial' are not the rows the checkpoint counts"},
  };
  for (const auto& c : cases) {
    SCOPED_TRACE(c.name);
    const fs::path d = mixed(c.name, c.from_b);
    const std::string rows = slurp(d / "compaction.csv.partial");
    const Cli r = resume(d);
    EXPECT_EQ(r.code, 2) << r.err;
    EXPECT_NE(r.err.find(c.says), std::string::npos) << r.err;
    EXPECT_NE(r.err.find("put back the run's own files, or start it anew"), std::string::npos) << r.err;
    EXPECT_EQ(slurp(d / "compaction.csv.partial"), rows) << "nothing is written";
    EXPECT_FALSE(fs::exists(d / "compaction.csv"));
  }
  const Cli r = resume(a);  // its own files: resumed
  EXPECT_EQ(r.code, 0) << r.err;
}

// A file begun by another version of qsdem with other columns (one that wrote none from phi_al_deg,
// tilt_deg on) is continued with its own columns: every row as wide as the header, the rows those of
// an uninterrupted run without the columns the file lacks, and summary.json says so. Before, the
// rows after the resume were wider than the header. A column this version does not write is refused.
TEST(RunSafety, AResumedFileKeepsTheColumnsItWasBegunWith) {
  const fs::path ref = reference();
  const auto older = [&](const std::string& name, const std::function<std::string(const std::string&)>& line) {
    const fs::path d = fresh(name);
    EXPECT_THROW(run_case(tiny({"compaction.max_steps=3000"}), to(d)), RunError);
    std::istringstream in(slurp(d / "compaction.csv.partial"));
    std::string text;
    for (std::string l; std::getline(in, l);) text += line(l) + "\n";
    std::ofstream(d / "compaction.csv.partial") << text;
    // As that version left it: a checkpoint of format 9, which counts no files' bytes.
    const Checkpoint c = load_checkpoint(d / checkpoint_file);
    save_checkpoint(d / checkpoint_file, c.case_text, c.case_source, c.state, c.run, 9);
    fs::remove(d / "checkpoint.qsck.prev");
    return d;
  };
  const auto before_phi_al = [](const std::string& l) {  // the first 18 columns, up to ekin_rot_J
    std::size_t cut = 0;
    for (int k = 0; k < 18; ++k) cut = l.find(',', cut) + 1;
    return l.substr(0, cut - 1);
  };
  const fs::path d = older("old-columns", before_phi_al);
  RunOptions o = to(d);
  o.sets = {"compaction.max_steps=2000000"};
  const nlohmann::json s = resume_run(d, o);
  const qsdem_test::Csv got = qsdem_test::read_csv(d / "compaction.csv"), want = qsdem_test::read_csv(ref / "compaction.csv");
  ASSERT_EQ(got.header.size(), 18u);
  ASSERT_GT(want.header.size(), got.header.size() + 1);
  EXPECT_EQ(want.header[18], "phi_al_deg");
  EXPECT_EQ(want.header[19], "tilt_deg");
  std::string omitted;  // the columns the file lacks, in the order this version writes them
  for (std::size_t c = 18; c < want.header.size(); ++c) omitted += (c > 18 ? "," : "") + want.header[c];
  ASSERT_EQ(got.rows.size(), want.rows.size());
  for (std::size_t k = 0; k < got.rows.size(); ++k)
    EXPECT_EQ(got.rows[k], std::vector<std::string>(want.rows[k].begin(), want.rows[k].begin() + 18)) << "row " << k;
  EXPECT_EQ(slurp(d / "series.csv"), slurp(ref / "series.csv")) << "a file begun after the resume has every column";
  EXPECT_NE(s.dump().find("compaction.csv keeps the columns it was begun with, without " + omitted), std::string::npos)
      << s["resume_changes"].dump();

  const fs::path e = older("unknown-column", [](const std::string& l) {
    return l.rfind("step,", 0) == 0 ? l + ",old_column" : l + ",0";
  });
  const std::string why = input_error([&] { resume_run(e, o); });
  EXPECT_NE(why.find("has the column 'old_column', which this qsdem does not write"), std::string::npos) << why;
}

TEST(RunSafety, TriaxialWallTimeCoversEveryProcess) {
  const fs::path d = fresh("wall");
  const pid_t pid = spawn({"run", tiny_file().string(), "--out", d.string(), "--quiet", "--threads", "1"},
                          root / "wall");
  ASSERT_TRUE(wait_for([&] { return lines(d / "series.csv.partial") >= 3; }, pid));
  ::kill(pid, SIGTERM);
  ASSERT_EQ(finish(pid, root / "wall").code, 143);
  const double before = load_checkpoint(d / checkpoint_file).run.phases.at(1).wall_s;
  EXPECT_GT(before, 0);
  const Cli r = cli({"resume", d.string(), "--quiet", "--threads", "1"}, "wall-resume");
  ASSERT_EQ(r.code, 0) << r.err;
  const auto s = nlohmann::json::parse(slurp(d / "summary.json"));
  EXPECT_GT(s["triaxial"]["wall_s"].get<double>(), before);
  EXPECT_GE(s["wall_s"].get<double>(), s["triaxial"]["wall_s"].get<double>());
}

// A checkpoint counts the rows of the phase's CSV file: that file reaches the disk before the
// checkpoint does (fsync of compaction.csv.partial or series.csv.partial, then of the checkpoint's
// temporary file), so after a power loss the file holds every row the checkpoint expects.
TEST(RunSafety, RowsReachTheDiskBeforeTheCheckpointThatCountsThem) {
  const fs::path d = fresh("fsync");
  {
    const std::lock_guard<std::mutex> lock(fsync_mutex);
    fsynced.clear();
    record_fsyncs = true;
  }
  run_case(tiny(), to(d));
  std::vector<std::string> seen;
  {
    const std::lock_guard<std::mutex> lock(fsync_mutex);
    record_fsyncs = false;
    seen = fsynced;
  }
  long checkpoints = 0, series_syncs = 0;
  bool rows_synced = false;  // since the last checkpoint
  for (const std::string& f : seen) {
    if (f == "compaction.csv.partial" || f == "series.csv.partial") {
      rows_synced = true;
      series_syncs += f == "series.csv.partial";
    } else if (f == std::string(checkpoint_file) + ".tmp") {
      ++checkpoints;
      EXPECT_TRUE(rows_synced) << "checkpoint " << checkpoints << " reached the disk before the rows it counts";
      rows_synced = false;
    }
  }
  // 10 rows, a checkpoint every 4: the triaxial phase saves at least twice, each after a sync.
  EXPECT_GE(checkpoints, 2);
  EXPECT_GE(series_syncs, 2);
}

// Packings are written in id order, ids being the input's order: line k of compacted.packing and
// of final.packing is the same particle, the k-th generated (largest first).
TEST(RunSafety, PackingsKeepTheParticlesOrder) {
  const fs::path ref = reference();
  const State compacted = read_packing(ref / "compacted.packing", 2650);
  const State final = read_packing(ref / "final.packing", 2650);
  const State generated = generate_loose_sample(tiny());
  ASSERT_EQ(compacted.particles.size(), 120u);
  for (std::size_t k = 0; k < 120; ++k) {
    EXPECT_EQ(compacted.particles.semi_axes[k], generated.particles.semi_axes[k]) << k;
    // 1 % axial strain moves a particle far less than its radius (the cell is periodic).
    Vec3 ds = final.particles.s[k] - compacted.particles.s[k];
    ds -= ds.array().round().matrix();
    EXPECT_LT((final.cell.h * ds).norm(), compacted.particles.equiv_radius[k]) << "particle " << k;
  }
}

// Bad packing files: a count that is not a whole number, centres far outside the cell.
TEST(RunSafety, PackingReaderRefusesBadCountsAndCoordinates) {
  const auto error = [](const std::string& text) {
    std::istringstream in(text);
    return input_error([&] { parse_packing(in, "p.packing", 2650); });
  };
  const std::string head = "format qsdem-packing 1\ncell 0.01 0 0 0 0.01 0 0 0 0.01\n";
  const std::string sphere = "0.001 0.001 0.001 0.001 0.001 0.001 1 0 0 0\n";
  std::string e = error(head + "particles 1.5\n" + sphere);
  EXPECT_NE(e.find("p.packing:3"), std::string::npos) << e;
  EXPECT_NE(e.find("whole number"), std::string::npos) << e;
  e = error(head + "particles 1\n1e300 0.001 0.001 0.001 0.001 0.001 1 0 0 0\n");
  EXPECT_NE(e.find("p.packing:4"), std::string::npos) << e;
  EXPECT_NE(e.find("1000 cell lengths"), std::string::npos) << e;
  e = error(head + "particles 1\n0.001 0.001 0.001 1e-320 1e-320 1e-320 1 0 0 0\n");
  EXPECT_NE(e.find("from 1 nm to 1 km"), std::string::npos) << e;
  EXPECT_EQ(error(head + "particles 1\n" + sphere), "");
}

// Messages of the command line: each names what is wrong and what is allowed; nothing is written.
TEST(RunSafety, CommandLineMessages) {
  Cli c = cli({"frobnicate"}, "msg-sub");
  EXPECT_EQ(c.code, 1);
  EXPECT_NE(c.err.find("unknown subcommand 'frobnicate'"), std::string::npos) << c.err;
  EXPECT_NE(c.err.find("run, prepare, resume"), std::string::npos) << c.err;
  c = cli({"run", root.string(), "--out", (root / "x").string()}, "msg-dir-case");
  EXPECT_EQ(c.code, 2);
  EXPECT_NE(c.err.find("is a directory"), std::string::npos) << c.err;
  c = cli({"run", tiny_file().string(), "--out", ""}, "msg-empty-out");
  EXPECT_EQ(c.code, 2);
  EXPECT_NE(c.err.find("--out is empty"), std::string::npos) << c.err;
  const fs::path file = root / "a-file";
  std::ofstream(file) << "x";
  c = cli({"run", tiny_file().string(), "--out", (file / "sub").string()}, "msg-file-parent");
  EXPECT_EQ(c.code, 2);
  EXPECT_NE(c.err.find("is not a directory"), std::string::npos) << c.err;
  EXPECT_EQ(c.err.find("filesystem error"), std::string::npos) << c.err;
  c = cli({"run", tiny_file().string(), "--out", (root / std::string(300, 'n')).string()}, "msg-long");
  EXPECT_EQ(c.code, 2);
  EXPECT_NE(c.err.find("longer than 255 bytes"), std::string::npos) << c.err;
  c = cli({"run", tiny_file().string(), "--out", (root / "big").string(), "--set", "sample.total_particles=100000000"},
          "msg-memory");
  EXPECT_EQ(c.code, 2);
  EXPECT_NE(c.err.find("GiB"), std::string::npos) << c.err;
  EXPECT_FALSE(fs::exists(root / "big"));
  c = cli({"--version"}, "msg-version");
  EXPECT_EQ(c.code, 0);
  EXPECT_NE(c.out.find(QSDEM_VERSION), std::string::npos) << c.out;
}

// SIGINT while the sample is generated: exit 130 with a message, and no directory.
TEST(RunSafety, SigintDuringGenerationSaysSo) {
  const fs::path d = fresh("gen-sigint");
  const pid_t pid = spawn({"run", tiny_file().string(), "--out", d.string(), "--set", "sample.total_particles=2000000",
                           "--set", "sample.initial_solid_fraction=0.05"},
                          root / "gen-sigint");
  std::this_thread::sleep_for(std::chrono::milliseconds(500));
  ::kill(pid, SIGINT);
  const Cli c = finish(pid, root / "gen-sigint");
  EXPECT_EQ(c.code, 130) << c.err;
  EXPECT_NE(c.err.find("stopped by SIGINT while generating the sample; nothing was written"), std::string::npos)
      << c.err;
  EXPECT_FALSE(fs::exists(d));
}

// Write errors carry the system's reason; a failed first checkpoint does not claim a previous one.
TEST(RunSafety, WriteErrorsSayWhy) {
  const State st = generate_loose_sample(tiny());
  try {
    save_checkpoint(root / "no-such-dir" / "checkpoint.qsck", "", "", st, RunProgress{});
    ADD_FAILURE() << "no error";
  } catch (const RunError& e) {
    const std::string what = e.what();
    EXPECT_NE(what.find("No such file or directory"), std::string::npos) << what;
    EXPECT_NE(what.find("there is no earlier checkpoint"), std::string::npos) << what;
    EXPECT_EQ(what.find("previous checkpoint is kept"), std::string::npos) << what;
  }
}

// The exact source version: the project version and, in a git checkout, `git describe`.
TEST(RunSafety, VersionNamesTheSource) {
  const std::string version = QSDEM_VERSION;
  EXPECT_EQ(version.rfind("0.1.0", 0), 0u) << version;
  const std::string cmd = std::string("git -C '") + QSDEM_SOURCE_DIR + "' describe --always 2>/dev/null";
  std::string describe;
  if (std::FILE* p = ::popen(cmd.c_str(), "r")) {
    char buf[256];
    while (std::fgets(buf, sizeof buf, p)) describe += buf;
    if (::pclose(p) != 0) describe.clear();
  }
  while (!describe.empty() && describe.back() == '\n') describe.pop_back();
  if (describe.empty()) {
    EXPECT_EQ(version, "0.1.0") << "no git: the project version";
  } else {
    EXPECT_EQ(version.rfind("0.1.0+" + describe, 0), 0u) << version << " vs " << describe;
  }
  EXPECT_EQ(nlohmann::json::parse(slurp(reference() / "summary.json"))["version"], version);
}

// summary.json's build: the version, the full commit of the source (git rev-parse HEAD) and
// whether the tree was clean (as the version's "-dirty" says); nulls without git.
TEST(RunSafety, SummaryNamesItsBuild) {
  const auto shell = [](const std::string& cmd) {
    std::string out;
    if (std::FILE* p = ::popen(cmd.c_str(), "r")) {
      char buf[256];
      while (std::fgets(buf, sizeof buf, p)) out += buf;
      if (::pclose(p) != 0) out.clear();
    }
    while (!out.empty() && out.back() == '\n') out.pop_back();
    return out;
  };
  const std::string head = shell(std::string("git -C '") + QSDEM_SOURCE_DIR + "' rev-parse HEAD 2>/dev/null");
  const nlohmann::json build = nlohmann::json::parse(slurp(reference() / "summary.json"))["build"];
  const std::string version = QSDEM_VERSION;
  EXPECT_EQ(build["version"], version);
  if (head.empty()) {
    EXPECT_TRUE(build["commit"].is_null()) << build;
    EXPECT_TRUE(build["tree_clean"].is_null()) << build;
  } else {
    EXPECT_EQ(build["commit"], head);
    const bool dirty = version.size() > 6 && version.substr(version.size() - 6) == "-dirty";
    EXPECT_EQ(build["tree_clean"], !dirty) << build;
  }
}

// A cell that shrinks below the size rule of SPEC 3 during compaction is a stop at run time
// (RunError, exit 3) that keeps the checkpoints, not an input error that left them behind.
TEST(RunSafety, CellShrinkingBelowTheSizeRuleIsARunTimeStop) {
  const fs::path example = fs::path(QSDEM_SOURCE_DIR) / "examples" / "spheres-A-small.toml";
  // 120 particles of Sample A's grading: the 16 mm spheres fit the loose cell, not the dense one.
  const Params params = parse_case(slurp(example), example.string(),
                                   {"sample.total_particles=120", "checkpoint.every_sample_points=1"});
  const fs::path d = fresh("shrink");
  try {
    run_case(params, to(d));
    ADD_FAILURE() << "the cell did not shrink below the size rule";
  } catch (const RunError& e) {
    const std::string what = e.what();
    EXPECT_NE(what.find("compaction stopped after compaction step"), std::string::npos) << what;
    EXPECT_NE(what.find("half the smallest cell width"), std::string::npos) << what;
    EXPECT_NE(what.find("before the phase reached its stops (equilibrium)"), std::string::npos) << what;
    EXPECT_EQ(what.find("sample.total_particles"), std::string::npos) << "advice for a case before its run: " << what;
  }
  EXPECT_TRUE(fs::exists(d / checkpoint_file));
}

// A stress stop the loading moves away from (axis 33 extended while its stop is a compression of
// 1 MPa) ends in a run-time stop naming the stop and the stress now, not a cell-size input error.
TEST(RunSafety, AStopTheLoadingMovesAwayFromIsNamedWhenTheCellGivesOut) {
  const fs::path d = fresh("away");
  fs::create_directories(root);
  const fs::path case_file = root / "away.toml";
  std::ofstream(case_file) << "name = \"away\"\n[material]\ndensity = \"2650 kg/m^3\"\nyoung_modulus = \"78 GPa\"\n"
                              "poisson_ratio = 0.3\n[sample]\nseed = 1\n"
                              "[[sample.particles]]\ndiameter = \"2 mm\"\ncount = 120\n"
                              "[[phase]]\nname = \"extension\"\nfriction = 0.5\nstrain_rate = { 33 = -1e-3 }\n"
                              "stress = { 11 = \"200 kPa\", 22 = \"200 kPa\" }\n"
                              "stop = { stress = { 33 = \"1 MPa\" } }\noutput = { every_steps = 1000 }\n";
  const Cli r = cli({"run", case_file.string(), "--out", d.string(), "--threads", "1", "--quiet"}, "away");
  EXPECT_EQ(r.code, 3) << r.err;
  EXPECT_NE(r.err.find("extension stopped after extension step"), std::string::npos) << r.err;
  EXPECT_NE(r.err.find("before the phase reached its stops (stress 33 = 1000 kPa (now"), std::string::npos) << r.err;
  EXPECT_EQ(r.err.find("sample.total_particles"), std::string::npos) << r.err;
}

// A legal wide grading (size ratio 1000: 300 spheres of 2 mm and 5 of 2 um) runs: the broad phase
// sized by the smallest particles once overflowed int and took gigabytes (a segfault).
TEST(RunSafety, AWideGradingRuns) {
  const fs::path d = fresh("wide");
  fs::create_directories(root);
  const fs::path case_file = root / "wide.toml";
  std::ofstream(case_file) << "name = \"wide\"\n[material]\ndensity = \"2650 kg/m^3\"\nyoung_modulus = \"78 GPa\"\n"
                              "poisson_ratio = 0.3\n[sample]\nseed = 1\n"
                              "[[sample.particles]]\ndiameter = \"2 mm\"\ncount = 300\n"
                              "[[sample.particles]]\ndiameter = \"0.002 mm\"\ncount = 5\n"
                              "[[phase]]\nname = \"compaction\"\nfriction = 0.2\n"
                              "stress = { 11 = \"200 kPa\", 22 = \"200 kPa\", 33 = \"200 kPa\" }\n"
                              "stop = { steps = 50 }\noutput = { every_steps = 10 }\n";
  const Cli r = cli({"run", case_file.string(), "--out", d.string(), "--threads", "1", "--quiet"}, "wide");
  EXPECT_EQ(r.code, 0) << r.err;
  EXPECT_TRUE(fs::exists(d / "series.csv")) << r.err;
}
