// Runs that survive (checkpoints, resume, prepared samples, blow-ups, output safety), tested with
// real processes and real signals on the qsdem binary where the behaviour is the process's.
#include <gtest/gtest.h>
#include <nlohmann/json.hpp>
#include <signal.h>
#include <spawn.h>
#include <fcntl.h>
#include <sys/stat.h>
#include <sys/wait.h>
#include <unistd.h>

#include <algorithm>
#include <chrono>
#include <cmath>
#include <cstddef>
#include <cstdlib>
#include <cstring>
#include <filesystem>
#include <fstream>
#include <functional>
#include <limits>
#include <sstream>
#include <string>
#include <thread>
#include <vector>

#include "qsdem/engine/model.hpp"
#include "qsdem/engine/neighbor.hpp"
#include "qsdem/engine/step.hpp"
#include "qsdem/run/checkpoint.hpp"
#include "qsdem/run/config.hpp"
#include "qsdem/run/generate.hpp"
#include "qsdem/run/output.hpp"
#include "qsdem/run/protocol.hpp"
#include "qsdem/run/run.hpp"
#include "qsdem/run/run_directory.hpp"
#include "qsdem/version.hpp"
#include "test_support.hpp"

using namespace qsdem;
namespace fs = std::filesystem;
using qsdem_test::lines;

extern char** environ;

namespace {

// 200 spheres, eps' = 1e-4 to 2 % strain: 625 triaxial steps, 40 rows, a checkpoint every 4 rows.
const std::string small_case = qsdem_test::sample_200("checkpoint-small") + R"([triaxial]
strain_rate = 1e-4
final_axial_strain = "2 %"
sample_points = 40
[checkpoint]
every_sample_points = 4
)";

fs::path scratch(const std::string& name) {
  const fs::path d = fs::temp_directory_path() / ("qsdem-ckpt-" + std::to_string(::getpid())) / name;
  fs::remove_all(d);
  fs::create_directories(d.parent_path());
  return d;
}

fs::path case_file() {
  const fs::path f = fs::temp_directory_path() / ("qsdem-ckpt-" + std::to_string(::getpid())) / "case.toml";
  fs::create_directories(f.parent_path());
  std::ofstream(f) << small_case;
  return f;
}

std::string read(const fs::path& p) {
  std::ifstream in(p, std::ios::binary);
  std::stringstream ss;
  ss << in.rdbuf();
  return ss.str();
}

// Starts the qsdem binary with arguments; stdout and stderr go to files in `log`.
pid_t spawn(const std::vector<std::string>& args, const fs::path& log) {
  std::vector<std::string> all{QSDEM_BINARY};
  all.insert(all.end(), args.begin(), args.end());
  const pid_t pid = qsdem_test::spawn_logged(all, log);
  EXPECT_GT(pid, 0);
  return pid;
}

using qsdem_test::wait_exit;

int run_cli(const std::vector<std::string>& args, const fs::path& log) { return wait_exit(spawn(args, log)); }

// Waits until the run's series.csv.partial holds at least `rows` rows (or the process ended).
bool wait_rows(const fs::path& dir, long rows, pid_t pid) {
  const auto deadline = std::chrono::steady_clock::now() + std::chrono::seconds(120);
  while (std::chrono::steady_clock::now() < deadline) {
    if (fs::exists(dir / "series.csv.partial") && lines(dir / "series.csv.partial") >= rows + 1) return true;
    int status = 0;
    if (waitpid(pid, &status, WNOHANG) == pid) return false;
    std::this_thread::sleep_for(std::chrono::milliseconds(5));
  }
  return false;
}

// The uninterrupted reference run, made once.
const fs::path& reference() {
  static const fs::path dir = [] {
    const fs::path d = scratch("reference");
    EXPECT_EQ(run_cli({"run", case_file().string(), "--out", d.string(), "--threads", "1", "--quiet"}, d.string()), 0)
        << read(d.string() + ".err");
    return d;
  }();
  return dir;
}

void kill_and_resume(int sig) {
  const fs::path ref = reference();
  const fs::path d = scratch(std::string("killed-") + std::to_string(sig));
  const pid_t pid = spawn({"run", case_file().string(), "--out", d.string(), "--threads", "1", "--quiet"}, d.string());
  ASSERT_TRUE(wait_rows(d, 14, pid)) << "the run ended before it could be killed";
  ::kill(pid, sig);
  const int code = wait_exit(pid);
  if (sig == SIGKILL) {
    EXPECT_EQ(code, 128 + SIGKILL);
    // Killed between checkpoints: rows written after the last checkpoint are dropped on resume.
    const Checkpoint c = load_checkpoint(d / checkpoint_file);
    std::printf("[ info ] SIGKILL with %ld rows on disk, checkpoint at %ld rows\n",
                lines(d / "series.csv.partial") - 1, c.run.current().rows);
    EXPECT_LE(c.run.current().rows, lines(d / "series.csv.partial") - 1);
  } else {
    EXPECT_EQ(code, 128 + sig) << read(d.string() + ".err");  // 143 for SIGTERM, 130 for SIGINT
    EXPECT_NE(read(d.string() + ".err").find("qsdem resume"), std::string::npos) << "says how to continue";
  }
  EXPECT_FALSE(fs::exists(d / "summary.json")) << "no result that could be mistaken for a finished run";
  EXPECT_FALSE(fs::exists(d / "series.csv"));
  ASSERT_EQ(run_cli({"resume", d.string(), "--threads", "1", "--quiet"}, d.string() + "-resume"), 0)
      << read(d.string() + "-resume.err");
  EXPECT_EQ(read(d / "series.csv"), read(ref / "series.csv")) << "resumed series.csv equals the uninterrupted one";
  EXPECT_EQ(read(d / "compaction.csv"), read(ref / "compaction.csv"));
  ASSERT_TRUE(fs::exists(ref / "classes.csv"));
  EXPECT_EQ(read(d / "classes.csv"), read(ref / "classes.csv")) << "resumed classes.csv equals the uninterrupted one";
  EXPECT_FALSE(fs::exists(d / checkpoint_file)) << "a finished run drops its checkpoint";
}

}  // namespace

TEST(CheckpointProcess, SigtermResumesToTheSameSeries) { kill_and_resume(SIGTERM); }
TEST(CheckpointProcess, SigkillBetweenCheckpointsResumesToTheSameSeries) { kill_and_resume(SIGKILL); }

// Inertia scaling in both phases (SPEC 5.6: compaction factor 2, cap 4; triaxial to the coarser
// class, s = 2.4/2): a run stopped by SIGTERM in the triaxial test and resumed writes the same
// bits as the uninterrupted one, and the test takes c_t s eps' of strain per step.
TEST(CheckpointProcess, ScaledInertiaResumesToTheSameSeries) {
  const std::string scaled = qsdem_test::sample_200("checkpoint-scaled") + R"([compaction]
inertia_scaling = { factor = 2, cap = 4 }
[triaxial]
strain_rate = 1e-4
final_axial_strain = "2 %"
sample_points = 40
inertia_scaling = { target = "coarsest" }
[checkpoint]
every_sample_points = 4
)";
  const fs::path f = scratch("scaled-case") / "case.toml";
  fs::create_directories(f.parent_path());
  std::ofstream(f) << scaled;
  const fs::path ref = scratch("scaled-reference"), d = scratch("scaled-killed");
  ASSERT_EQ(run_cli({"run", f.string(), "--out", ref.string(), "--threads", "1", "--quiet"}, ref.string()), 0)
      << read(ref.string() + ".err");
  const pid_t pid = spawn({"run", f.string(), "--out", d.string(), "--threads", "1", "--quiet"}, d.string());
  ASSERT_TRUE(wait_rows(d, 14, pid)) << "the run ended before it could be killed";
  ::kill(pid, SIGTERM);
  EXPECT_EQ(wait_exit(pid), 128 + SIGTERM) << read(d.string() + ".err");
  ASSERT_EQ(run_cli({"resume", d.string(), "--threads", "1", "--quiet"}, d.string() + "-resume"), 0)
      << read(d.string() + "-resume.err");
  EXPECT_EQ(read(d / "series.csv"), read(ref / "series.csv"));
  EXPECT_EQ(read(d / "compaction.csv"), read(ref / "compaction.csv"));
  const auto scaled_summary = nlohmann::json::parse(read(ref / "summary.json"));
  const auto plain_summary = nlohmann::json::parse(read(reference() / "summary.json"));
  const long scaled_steps = scaled_summary["phases"][1]["steps"], plain_steps = plain_summary["phases"][1]["steps"];
  EXPECT_EQ(scaled_steps - std::lround(0.02 / (0.32 * 1.2 * 1e-4)), plain_steps - std::lround(0.02 / (0.32 * 1e-4)));
  EXPECT_EQ(scaled_summary["config"]["resolved_si"]["protocol"][1]["inertia_scaling"]["target"], "coarsest");
}

// SIGINT during compaction: compaction.csv continues from the checkpoint too.
// A run begun by an engine that wrote no classes.csv (its checkpoint has rows, its directory no
// classes.csv.partial) continues without it: the same series.csv, no classes.csv, and the summary
// records the change.
TEST(CheckpointProcess, RunBegunWithoutClassesCsvResumesWithoutIt) {
  const fs::path ref = reference();
  const fs::path d = scratch("no-classes");
  const pid_t pid = spawn({"run", case_file().string(), "--out", d.string(), "--threads", "1", "--quiet"}, d.string());
  ASSERT_TRUE(wait_rows(d, 14, pid)) << "the run ended before it could be stopped";
  ::kill(pid, SIGTERM);
  ASSERT_EQ(wait_exit(pid), 128 + SIGTERM) << read(d.string() + ".err");
  {
    // As that engine left it: a checkpoint of format 9, which counts no files (from format 10 on, a
    // missing classes.csv.partial is a damaged directory, not an older engine's).
    const Checkpoint c = load_checkpoint(d / checkpoint_file);
    ASSERT_GT(c.run.current().rows, 0);
    save_checkpoint(d / checkpoint_file, c.case_text, c.case_source, c.state, c.run, 9);
  }
  ASSERT_TRUE(fs::remove(d / "classes.csv.partial"));
  ASSERT_EQ(run_cli({"resume", d.string(), "--threads", "1", "--quiet"}, d.string() + "-resume"), 0)
      << read(d.string() + "-resume.err");
  EXPECT_NE(read(d.string() + "-resume.err").find("continues without it"), std::string::npos)
      << read(d.string() + "-resume.err");
  EXPECT_EQ(read(d / "series.csv"), read(ref / "series.csv"));
  EXPECT_FALSE(fs::exists(d / "classes.csv"));
  EXPECT_FALSE(fs::exists(d / "classes.csv.partial"));
  const auto summary = nlohmann::json::parse(read(d / "summary.json"));
  EXPECT_NE(summary.dump().find("output.classes=false (begun without classes.csv)"), std::string::npos)
      << summary.dump();
}

// A run begun by one build and finished by another records both, in order, in summary.json's
// `builds` (the other build stands in as a record written into the checkpoint); `build` is the
// finishing one.
TEST(CheckpointProcess, RunResumedByAnotherBuildRecordsBoth) {
  const fs::path d = scratch("two-builds");
  const pid_t pid = spawn({"run", case_file().string(), "--out", d.string(), "--threads", "1", "--quiet"}, d.string());
  ASSERT_TRUE(wait_rows(d, 14, pid)) << "the run ended before it could be stopped";
  ::kill(pid, SIGTERM);
  ASSERT_EQ(wait_exit(pid), 128 + SIGTERM) << read(d.string() + ".err");
  const nlohmann::json other = {{"version", "0.0.9+0123abc"}, {"commit", "0123abc"}, {"tree_clean", true}};
  {
    Checkpoint c = load_checkpoint(d / checkpoint_file);
    ASSERT_EQ(c.run.builds.size(), 1u) << "the build that began it";
    EXPECT_EQ(nlohmann::json::parse(c.run.builds[0])["version"], QSDEM_VERSION);
    c.run.builds = {other.dump()};
    save_checkpoint(d / checkpoint_file, c.case_text, c.case_source, c.state, c.run);
  }
  ASSERT_EQ(run_cli({"resume", d.string(), "--threads", "1", "--quiet"}, d.string() + "-resume"), 0)
      << read(d.string() + "-resume.err");
  const auto summary = nlohmann::json::parse(read(d / "summary.json"));
  ASSERT_EQ(summary["builds"].size(), 2u) << summary["builds"];
  EXPECT_EQ(summary["builds"][0], other);
  EXPECT_EQ(summary["builds"][1], summary["build"]);
  EXPECT_EQ(summary["build"]["version"], QSDEM_VERSION);
  const auto ref = nlohmann::json::parse(read(reference() / "summary.json"));
  ASSERT_EQ(ref["builds"].size(), 1u) << "a run of one process: its own build";
  EXPECT_EQ(ref["builds"][0], ref["build"]);
}

TEST(CheckpointProcess, SigintDuringCompactionResumes) {
  const fs::path ref = reference();
  const fs::path d = scratch("sigint");
  const pid_t pid = spawn({"run", case_file().string(), "--out", d.string(), "--threads", "1", "--quiet"}, d.string());
  const auto deadline = std::chrono::steady_clock::now() + std::chrono::seconds(60);
  while (!(fs::exists(d / "compaction.csv.partial") && lines(d / "compaction.csv.partial") > 5) &&
         std::chrono::steady_clock::now() < deadline)
    std::this_thread::sleep_for(std::chrono::milliseconds(5));
  ::kill(pid, SIGINT);
  ASSERT_EQ(wait_exit(pid), 130);
  ASSERT_TRUE(fs::exists(d / checkpoint_file));
  EXPECT_EQ(load_checkpoint(d / checkpoint_file).run.phase, 0) << "stopped in the compaction";
  ASSERT_EQ(run_cli({"resume", d.string(), "--threads", "1", "--quiet"}, d.string() + "-resume"), 0);
  EXPECT_EQ(read(d / "compaction.csv"), read(ref / "compaction.csv"));
  EXPECT_EQ(read(d / "series.csv"), read(ref / "series.csv"));
  EXPECT_EQ(read(d / "classes.csv"), read(ref / "classes.csv"));
}

// A flipped byte is detected by the checksum and the previous checkpoint is used; a truncated
// file is refused with a clear message when there is no previous one.
TEST(CheckpointFile, FlippedByteAndTruncationAreDetected) {
  const fs::path ref = reference();
  const fs::path d = scratch("flipped");
  const pid_t pid = spawn({"run", case_file().string(), "--out", d.string(), "--threads", "1", "--quiet"}, d.string());
  ASSERT_TRUE(wait_rows(d, 14, pid));
  ::kill(pid, SIGTERM);
  ASSERT_EQ(wait_exit(pid), 143);
  ASSERT_TRUE(fs::exists(d / "checkpoint.qsck.prev"));
  {
    std::string bytes = read(d / checkpoint_file);
    bytes[bytes.size() / 2] = static_cast<char>(bytes[bytes.size() / 2] ^ 0x10);
    std::ofstream(d / checkpoint_file, std::ios::binary) << bytes;
  }
  try {
    load_checkpoint(d / checkpoint_file);
    ADD_FAILURE() << "a flipped byte was not detected";
  } catch (const InputError& e) {
    EXPECT_NE(std::string(e.what()).find("checksum"), std::string::npos) << e.what();
  }
  ASSERT_EQ(run_cli({"resume", d.string(), "--threads", "1", "--quiet"}, d.string() + "-resume"), 0);
  EXPECT_NE(read(d.string() + "-resume.err").find("using the previous checkpoint"), std::string::npos);
  EXPECT_EQ(read(d / "series.csv"), read(ref / "series.csv"));

  // Truncated, no previous one.
  const fs::path t = scratch("truncated");
  fs::create_directories(t);
  std::ofstream(t / checkpoint_file, std::ios::binary) << std::string("QSDEMCKP") + std::string(10, '\0');
  EXPECT_EQ(run_cli({"resume", t.string(), "--quiet"}, t.string()), 2);
  EXPECT_NE(read(t.string() + ".err").find("truncated"), std::string::npos) << read(t.string() + ".err");
}

// Round trip of the state through a checkpoint is exact.
TEST(CheckpointFile, RoundTripIsExact) {
  const Params params = parse_case(small_case, "small.toml");
  State st = generate_loose_sample(params);
  RunProgress run;
  run.phases.resize(params.protocol.size());
  Progress quiet(Progress::Mode::quiet);
  Params short_params = params;
  short_params.protocol[0].stop.max_steps = 3000;
  short_params.protocol[0].inertia.target = InertiaScaling::Target::coarsest;  // mu_i and masses kept (SPEC 5.6)
  try {
    run_phase(short_params, st, run, {}, quiet, {});
  } catch (const RunError&) {
    // stopped by the step budget: a mid-compaction state with contacts and history
  }
  const fs::path f = scratch("roundtrip.qsck");
  save_checkpoint(f, params.case_text, params.source, st, run);
  const Checkpoint c = load_checkpoint(f);
  EXPECT_EQ(c.case_text, params.case_text);
  EXPECT_EQ(c.run.current().steps, 3000);
  EXPECT_EQ(c.run.current().rows, run.current().rows);
  EXPECT_EQ(c.run.current().h0, run.current().h0);
  EXPECT_EQ(c.run.state.controls.component[0].value, run.state.controls.component[0].value);
  EXPECT_TRUE(c.run.state.live);
  EXPECT_EQ(c.state.step, st.step);
  EXPECT_EQ(c.state.particles.s, st.particles.s);
  EXPECT_EQ(c.state.particles.v, st.particles.v);
  EXPECT_EQ(c.state.particles.angmom, st.particles.angmom);
  EXPECT_EQ(c.state.particles.inertia_scale, st.particles.inertia_scale);
  EXPECT_EQ(c.state.particles.mass, st.particles.mass);
  EXPECT_EQ(c.state.particles.symmetry_axis, st.particles.symmetry_axis);
  EXPECT_EQ(c.state.particles.inv_axial_moment, st.particles.inv_axial_moment);
  EXPECT_EQ(c.state.particles.inv_transverse_moment, st.particles.inv_transverse_moment);
  EXPECT_GT(*std::max_element(st.particles.inertia_scale.begin(), st.particles.inertia_scale.end()), 1.4);
  EXPECT_EQ(c.state.pairs.history.values, st.pairs.history.values);
  EXPECT_EQ(c.state.pairs.history.layout, st.pairs.history.layout);
  EXPECT_EQ(c.state.pairs.image, st.pairs.image);
  EXPECT_EQ(c.state.cell.h, st.cell.h);
  EXPECT_EQ(c.state.cell.L, st.cell.L);
  EXPECT_EQ(c.state.pairs.first_i, st.pairs.first_i);
  EXPECT_EQ(c.state.pairs.block_first, st.pairs.block_first);
  ASSERT_GT(st.pairs.size(), 0u);
}

// The checkpoint names the contact history by its layout (contact/law.hpp): one that no law of
// this build declares is refused by name, not read as another.
TEST(CheckpointFile, UnknownContactHistoryIsRefused) {
  static constexpr HistoryLayout unknown{"rolling_spring", 6, {}, {}};
  const Params params = parse_case(small_case, "small.toml");
  State st = generate_loose_sample(params);
  const Model model = compaction_model(params, st);
  evaluate_forces(model, st);
  ASSERT_GT(st.pairs.size(), 0u);
  st.pairs.history.layout = &unknown;
  st.pairs.history.values.assign(6 * st.pairs.size(), 0.25);
  const fs::path f = scratch("unknown-history.qsck");
  save_checkpoint(f, params.case_text, params.source, st, RunProgress{});
  try {
    load_checkpoint(f);
    FAIL() << "expected an InputError";
  } catch (const InputError& e) {
    EXPECT_NE(std::string(e.what()).find("\"rolling_spring\""), std::string::npos) << e.what();
    EXPECT_NE(std::string(e.what()).find(f.string()), std::string::npos) << e.what();
  }
}

// A prepared sample is sheared without compacting again, and gives the full run's series exactly.
TEST(PreparedSample, ShearingAPreparedSampleEqualsTheFullRun) {
  const fs::path ref = reference();
  const fs::path p = scratch("prepared");
  ASSERT_EQ(run_cli({"prepare", case_file().string(), "--out", p.string(), "--threads", "1", "--quiet"}, p.string()), 0);
  EXPECT_TRUE(fs::exists(p / prepared_sample_file));
  EXPECT_FALSE(fs::exists(p / "series.csv"));
  const fs::path r = scratch("from-prepared");
  ASSERT_EQ(run_cli({"run", case_file().string(), "--out", r.string(), "--threads", "1", "--quiet", "--set",
                     "sample.from=" + p.string()},
                    r.string()),
            0)
      << read(r.string() + ".err");
  EXPECT_EQ(read(r / "series.csv"), read(ref / "series.csv"));
  EXPECT_FALSE(fs::exists(r / "compaction.csv")) << "no compaction was run";
  // Its summary counts its own steps and time only (not the sample's compaction): the triaxial
  // steps, and particle-steps per second over its own wall time.
  {
    const auto full = nlohmann::json::parse(read(ref / "summary.json"));
    const auto own = nlohmann::json::parse(read(r / "summary.json"));
    EXPECT_EQ(own["steps"].get<long>(), own["triaxial"]["steps"].get<long>());
    EXPECT_EQ(full["steps"].get<long>(), full["compaction"]["steps"].get<long>() + full["triaxial"]["steps"].get<long>());
    EXPECT_EQ(own["steps_cover"], "triaxial of a prepared sample");
    EXPECT_NEAR(own["particle_steps_per_s"].get<double>(),
                own["derived"]["particles"].get<double>() * own["steps"].get<double>() / own["wall_s"].get<double>(),
                1e-9 * own["particle_steps_per_s"].get<double>());
  }
  // The same sample at another damping ratio: a different series from the same start.
  const fs::path o = scratch("from-prepared-od");
  ASSERT_EQ(run_cli({"run", case_file().string(), "--out", o.string(), "--threads", "1", "--quiet", "--set",
                     "sample.from=" + p.string(), "--set", "damping.model=od"},
                    o.string()),
            0);
  EXPECT_NE(read(o / "series.csv"), read(ref / "series.csv"));
  // A different material is refused.
  const fs::path bad = scratch("from-prepared-bad");
  EXPECT_EQ(run_cli({"run", case_file().string(), "--out", bad.string(), "--quiet", "--set",
                     "sample.from=" + p.string(), "--set", "material.young_modulus=\"70 GPa\""},
                    bad.string()),
            2);
  EXPECT_NE(read(bad.string() + ".err").find("prepared with"), std::string::npos);
}

// A [[phase]] case whose compaction writes into series.csv too: a run of its prepared sample holds
// the shear's rows only (the compaction's are in the sample's directory), the full run's rows of
// that phase bit for bit.
TEST(PreparedSample, APhaseListSharingItsFileShearsThePreparedSample) {
  const std::string text = qsdem_test::sample_200("prepared-phases") + R"([[phase]]
name = "compaction"
friction = 0.2
stress = { 11 = "200 kPa", 22 = "200 kPa", 33 = "200 kPa" }
servo = { max_strain_rate = 1e-4 }
stop = { equilibrium = { ufr = "1 %" } }
[[phase]]
name = "triaxial"
friction = 0.5
strain_rate = { 33 = 1e-4 }
stress = { 11 = "200 kPa", 22 = "200 kPa" }
stop = { strain = { 33 = "0.5 %" } }
output = { points = 10 }
)";
  const fs::path f = scratch("prepared-phases-case") / "case.toml";
  fs::create_directories(f.parent_path());
  std::ofstream(f) << text;
  const fs::path full = scratch("prepared-phases-full"), p = scratch("prepared-phases-sample"),
                 r = scratch("prepared-phases-shear");
  ASSERT_EQ(run_cli({"run", f.string(), "--out", full.string(), "--threads", "1", "--quiet"}, full.string()), 0)
      << read(full.string() + ".err");
  ASSERT_EQ(run_cli({"prepare", f.string(), "--out", p.string(), "--threads", "1", "--quiet"}, p.string()), 0)
      << read(p.string() + ".err");
  ASSERT_EQ(run_cli({"run", f.string(), "--out", r.string(), "--threads", "1", "--quiet", "--set",
                     "sample.from=" + p.string()},
                    r.string()),
            0)
      << read(r.string() + ".err");
  std::istringstream in(read(full / "series.csv"));
  std::string line, header, shear;
  std::getline(in, header);
  const auto phase_col = [&] {
    std::istringstream h(header);
    std::size_t k = 0;
    for (std::string field; std::getline(h, field, ','); ++k)
      if (field == "phase") return k;
    return std::string::npos;
  }();
  ASSERT_NE(phase_col, std::string::npos) << "a file of two phases has the phase column";
  long rows = 0;
  while (std::getline(in, line)) {
    std::istringstream row(line);
    std::string field;
    for (std::size_t k = 0; k <= phase_col; ++k) std::getline(row, field, ',');
    if (field == "triaxial") shear += line + "\n", ++rows;
  }
  EXPECT_EQ(rows, 10) << "0.5 % in rows of 0.05 %";
  EXPECT_EQ(read(r / "series.csv"), header + "\n" + shear);
}

namespace {

// A run stopped in its compaction (compaction.max_steps): checkpoints, compaction.csv.partial and
// classes.csv.partial of 200 spheres, made once; each test resumes a copy.
const fs::path& stopped_run() {
  static const fs::path dir = [] {
    const fs::path d = scratch("stopped");
    EXPECT_EQ(run_cli({"run", case_file().string(), "--out", d.string(), "--threads", "1", "--quiet", "--set",
                       "compaction.max_steps=3000"},
                      d.string()),
              3)
        << read(d.string() + ".err");
    return d;
  }();
  return dir;
}

fs::path copy_of(const fs::path& from, const std::string& name) {
  const fs::path d = scratch(name);
  fs::copy(from, d, fs::copy_options::recursive);
  return d;
}

// `resume DIR` to the end of the compaction, with a deadline (a hang fails): the exit code and stderr.
std::pair<int, std::string> resume_within(const fs::path& d, double seconds) {
  const pid_t pid = spawn({"resume", d.string(), "--threads", "1", "--quiet", "--set", "compaction.max_steps=2000000"},
                          d.string() + "-resume");
  const int code = qsdem_test::wait_exit_within(pid, seconds);
  return {code, read(d.string() + "-resume.err")};
}

}  // namespace

// A checkpoint whose checksum is valid but whose contents do not fit together (edited and resealed,
// or written by a faulty build) is refused on load with a message naming the file and what is
// wrong: resume exits with 2, never steps it (out-of-range indices crashed the neighbour list or
// the force stage; a NaN ran on into every later row). Each case changes one thing of a real
// checkpoint and saves it again, which reseals it.
TEST(CheckpointFile, InconsistentContentsAreRefused) {
  struct Case {
    const char* name;
    std::function<void(Checkpoint&)> change;
    const char* says;
  };
  const std::vector<Case> cases{
      {"pair index", [](Checkpoint& c) { c.state.pairs.j[3] = static_cast<std::uint32_t>(c.state.particles.size() + 5); },
       "joins particles"},
      {"pair order i < j", [](Checkpoint& c) { c.state.pairs.j[0] = c.state.pairs.i[0]; }, "joins particles"},
      {"pair image", [](Checkpoint& c) { c.state.pairs.image[2].x() += 1000; }, "cell lengths apart"},
      {"pair keys sorted", [](Checkpoint& c) {
         auto& q = c.state.pairs;
         std::swap(q.i[0], q.i.back()), std::swap(q.j[0], q.j.back()), std::swap(q.image[0], q.image.back());
       }, "in the order of the keys"},
      {"history length", [](Checkpoint& c) {
         auto& h = c.state.pairs.history;
         h.values.resize(h.values.size() - static_cast<std::size_t>(h.layout->width));  // one pair short
       }, "contact history has"},
      {"NaN velocity", [](Checkpoint& c) { c.state.particles.v[3].x() = std::nan(""); },
       "the velocity of particle 3 is not finite"},
      {"far centre", [](Checkpoint& c) { c.state.particles.s[4].y() = 1e9; }, "10^6 cell lengths"},
      {"quaternion", [](Checkpoint& c) { c.state.particles.q.set(2, Quat(2 * c.state.particles.q[2].coeffs())); }, "unit quaternion"},
      {"semi-axes", [](Checkpoint& c) { c.state.particles.semi_axes[5].setZero(); }, "semi-axes"},
      {"array length", [](Checkpoint& c) { c.state.particles.mass.pop_back(); }, "the particles' mass has"},
      {"inertia scale", [](Checkpoint& c) { c.state.particles.inertia_scale[2] = 0.5; },
       "particle 2 has an inertia scale that is not finite and >= 1"},
      {"ids", [](Checkpoint& c) { c.state.particles.id[1] = c.state.particles.id[0]; }, "the ids are not 0 to"},
      {"singular cell", [](Checkpoint& c) { c.state.cell.h.col(0).setZero(); }, "the cell matrix is not finite"},
      {"list reference", [](Checkpoint& c) { c.state.neighbor.s_at_build.resize(5); }, "reference holds 5 positions"},
      {"phase index", [](Checkpoint& c) { c.run.phase = 7; }, "it stands at phase 7"},
      {"row count", [](Checkpoint& c) { c.run.phases[0].rows = -3; }, "row count is -3"},
      {"rows beyond steps", [](Checkpoint& c) { c.run.phases[0].rows = c.run.phases[0].steps + 1; }, "rows in"},
      {"first step", [](Checkpoint& c) { c.run.first_step = c.state.step + 1; }, "first step"},
      {"record value", [](Checkpoint& c) { c.run.phases[0].final.void_ratio = std::nan(""); }, "final.void_ratio = nan"},
      {"record fabric", [](Checkpoint& c) { c.run.phases[0].final.fabric_dev = HUGE_VAL; }, "final.fabric_dev = inf"},
      {"phase count", [](Checkpoint& c) { c.run.phases.resize(3); }, "it holds 3 phases, the case has 2"},
      {"control value", [](Checkpoint& c) { c.run.state.controls.component[0].value *= 2; },
       "controlled by other values than its case's"},
  };
  const Checkpoint good = load_checkpoint(stopped_run() / checkpoint_file);
  ASSERT_EQ(good.run.phase, 0);
  ASSERT_TRUE(good.run.phase_started);
  ASSERT_GT(good.state.pairs.size(), 10u);
  for (std::size_t k = 0; k < cases.size(); ++k) {
    SCOPED_TRACE(cases[k].name);
    const fs::path d = copy_of(stopped_run(), "inconsistent-" + std::to_string(k));
    Checkpoint c = good;
    cases[k].change(c);
    save_checkpoint(d / checkpoint_file, c.case_text, c.case_source, c.state, c.run);
    fs::remove(d / "checkpoint.qsck.prev");  // no good one to fall back on
    const auto [code, err] = resume_within(d, 120);
    EXPECT_EQ(code, 2) << err;
    EXPECT_NE(err.find((d / checkpoint_file).string()), std::string::npos) << err;
    EXPECT_NE(err.find(cases[k].says), std::string::npos) << err;
  }
  // The untouched checkpoint resumes.
  const fs::path d = copy_of(stopped_run(), "consistent");
  EXPECT_EQ(resume_within(d, 300).first, 0);

  // A prepared sample the same (`sample.from`): refused before the run's directory is made.
  for (const bool nan : {false, true}) {
    const fs::path p = scratch(nan ? "sample-nan" : "sample-index");
    fs::create_directories(p);
    Checkpoint c = load_checkpoint(reference() / prepared_sample_file);
    if (nan)
      c.state.particles.s[7].z() = std::numeric_limits<double>::infinity();
    else
      c.state.pairs.i[1] = static_cast<std::uint32_t>(c.state.particles.size());
    save_checkpoint(p / prepared_sample_file, c.case_text, c.case_source, c.state, c.run);
    const fs::path out = scratch(nan ? "from-sample-nan" : "from-sample-index");
    const pid_t pid = spawn({"run", case_file().string(), "--out", out.string(), "--threads", "1", "--quiet", "--set",
                             "sample.from=" + p.string()},
                            out.string());
    EXPECT_EQ(qsdem_test::wait_exit_within(pid, 120), 2) << read(out.string() + ".err");
    const std::string err = read(out.string() + ".err");
    EXPECT_NE(err.find((p / prepared_sample_file).string()), std::string::npos) << err;
    EXPECT_NE(err.find(nan ? "its centre not finite" : "joins particles"), std::string::npos) << err;
    EXPECT_FALSE(fs::exists(out));
  }
}

// Checkpoints, prepared samples and the rows a resume continues are read from regular files only,
// no further than their headers' length: a FIFO (which blocked the reader for ever) or a device
// such as /dev/zero (read until the memory ran out) is refused at once with exit code 2.
TEST(CheckpointFile, OnlyRegularFilesAreRead) {
  for (const std::string what : {"fifo", "dev-zero", "partial-fifo"}) {
    SCOPED_TRACE(what);
    const fs::path d = copy_of(stopped_run(), "special-" + what);
    if (what == "partial-fifo") {
      fs::remove(d / "compaction.csv.partial");
      ASSERT_EQ(::mkfifo((d / "compaction.csv.partial").c_str(), 0644), 0);
    } else {
      fs::remove(d / checkpoint_file);
      fs::remove(d / "checkpoint.qsck.prev");
      if (what == "fifo")
        ASSERT_EQ(::mkfifo((d / checkpoint_file).c_str(), 0644), 0);
      else
        fs::create_symlink("/dev/zero", d / checkpoint_file);
    }
    const auto [code, err] = resume_within(d, 30);
    EXPECT_EQ(code, 2) << err;
    EXPECT_NE(err.find("not a regular file"), std::string::npos) << err;
  }
  // A header that claims more bytes than the file holds: truncated, nothing allocated for it.
  const fs::path d = copy_of(stopped_run(), "long-header");
  fs::remove(d / "checkpoint.qsck.prev");
  std::string bytes = read(d / checkpoint_file);
  const std::uint64_t claimed = std::uint64_t{1} << 60;
  std::memcpy(bytes.data() + 16, &claimed, 8);
  std::ofstream(d / checkpoint_file, std::ios::binary) << bytes;
  const auto [code, err] = resume_within(d, 30);
  EXPECT_EQ(code, 2) << err;
  EXPECT_NE(err.find("truncated"), std::string::npos) << err;
  // sample.from naming a directory whose sample.qsck is a FIFO.
  const fs::path p = scratch("fifo-sample");
  fs::create_directories(p);
  ASSERT_EQ(::mkfifo((p / prepared_sample_file).c_str(), 0644), 0);
  const fs::path out = scratch("from-fifo-sample");
  const pid_t pid = spawn({"run", case_file().string(), "--out", out.string(), "--quiet", "--set", "sample.from=" + p.string()},
                          out.string());
  EXPECT_EQ(qsdem_test::wait_exit_within(pid, 30), 2) << read(out.string() + ".err");
  EXPECT_NE(read(out.string() + ".err").find("not a regular file"), std::string::npos) << read(out.string() + ".err");
}

// A flag of a checkpoint (here: whether the current phase has started) is the byte 0 or 1; any
// other byte, resealed, is refused as damage instead of being copied into a bool (undefined
// behaviour, which the fuzz target's sanitizer reported).
TEST(CheckpointFile, AFlagThatIsNeitherZeroNorOneIsRefused) {
  const fs::path d = copy_of(stopped_run(), "flag");
  const Checkpoint c = load_checkpoint(d / checkpoint_file);
  std::string bytes = read(d / checkpoint_file);
  // The header (32 bytes), the case and its source (each a 64-bit length and its bytes), the
  // current phase (32 bits), then the flag.
  constexpr std::size_t header = 32;
  const std::size_t flag = header + 8 + c.case_text.size() + 8 + c.case_source.size() + 4;
  ASSERT_EQ(bytes[flag], 1) << "the stopped run's compaction has started";
  bytes[flag] = 2;
  const std::uint64_t sum = fnv1a64(bytes.data() + header, bytes.size() - header);
  std::memcpy(bytes.data() + 24, &sum, 8);
  std::ofstream(d / checkpoint_file, std::ios::binary | std::ios::trunc) << bytes;
  try {
    load_checkpoint(d / checkpoint_file);
    ADD_FAILURE() << "a flag of 2 was read";
  } catch (const InputError& e) {
    EXPECT_NE(std::string(e.what()).find("a flag holds 2, not 0 or 1"), std::string::npos) << e.what();
  }
}

// A finished run is not overwritten without --force; an unfinished one points to resume.
TEST(OutputSafety, RefusesToOverwriteARunUnlessForced) {
  const fs::path ref = reference();
  const fs::path d = scratch("safety");
  fs::copy(ref, d, fs::copy_options::recursive);
  const std::string before = read(d / "series.csv");
  EXPECT_EQ(run_cli({"run", case_file().string(), "--out", d.string(), "--quiet"}, d.string()), 2);
  EXPECT_NE(read(d.string() + ".err").find("finished run"), std::string::npos);
  EXPECT_EQ(read(d / "series.csv"), before);
  EXPECT_EQ(run_cli({"run", case_file().string(), "--out", d.string(), "--quiet", "--force", "--threads", "1"},
                    d.string()),
            0);
  std::ofstream(d / checkpoint_file) << "x";
  fs::remove(d / "summary.json");
  EXPECT_EQ(run_cli({"run", case_file().string(), "--out", d.string(), "--quiet"}, d.string()), 2);
  EXPECT_NE(read(d.string() + ".err").find("qsdem resume"), std::string::npos);
}

// An injected NaN stops the run with a diagnostic naming the step, the particle and the cause.
TEST(BlowUp, InjectedNanStopsWithDiagnostic) {
  const Params params = parse_case(small_case, "small.toml");
  State st = generate_loose_sample(params);
  st.particles.v[17] = Vec3(std::nan(""), 0, 0);
  const std::uint32_t id = st.particles.id[17];  // the engine may re-sort particles: names them by id
  Progress quiet(Progress::Mode::quiet);
  try {
    run_phase(params, 0, st, quiet, nullptr);
    ADD_FAILURE() << "a NaN did not stop the run";
  } catch (const RunError& e) {
    const std::string what = e.what();
    EXPECT_NE(what.find("blow-up"), std::string::npos) << what;
    EXPECT_NE(what.find("particle id " + std::to_string(id)), std::string::npos) << what;
    EXPECT_NE(what.find("step"), std::string::npos) << what;
    EXPECT_NE(what.find("time.step_ratio"), std::string::npos) << "suggests a remedy: " << what;
  }
}

// An overlap beyond limits.max_overlap stops the process with exit code 3 and names the pair;
// the last good checkpoint is kept.
TEST(BlowUp, ExcessiveOverlapStopsTheProcess) {
  const fs::path d = scratch("overlap");
  EXPECT_EQ(run_cli({"run", case_file().string(), "--out", d.string(), "--quiet", "--set", "limits.max_overlap=1e-5"},
                    d.string()),
            3);
  const std::string err = read(d.string() + ".err");
  EXPECT_NE(err.find("blow-up"), std::string::npos) << err;
  EXPECT_NE(err.find("overlap"), std::string::npos) << err;
  EXPECT_NE(err.find("particles id"), std::string::npos) << err;
  EXPECT_FALSE(fs::exists(d / "summary.json"));
}

namespace {

// Three fine spheres (R = 0.2 mm) each pinched between two big ones (R = 2 mm) along a line
// through a fixed periodic cell, overlapping by 8 % of the fine radius (~50 N each): a steady
// force chain. The fine spheres start with 1 m/s along the chain.
std::pair<State, Model> pinched_chain(double dt_factor) {
  const Params params = parse_case(small_case, "small.toml");
  const double rb = 2e-3, rs = 2e-4, overlap = 0.08 * rs, d = rb + rs - overlap, side = 6 * d;
  State st;
  st.cell = make_cell(side * Mat3::Identity());
  for (int k = 0; k < 6; ++k) {
    const double r = k % 2 == 0 ? rb : rs;
    st.particles.add(static_cast<std::uint32_t>(k), ShapeKind::sphere, Vec3::Constant(r), 2650,
                     Vec3(0.5, 0.5, k * d / side), Quat::Identity());
    if (k % 2 == 1) st.particles.v.back() = Vec3(0, 0, 1.0);
  }
  Model m = triaxial_model(params, st);
  for (auto& c : m.control) c = {};  // a fixed cell
  m.dt *= dt_factor;
  assign_damping(m, st.particles);
  return {std::move(st), m};
}

}  // namespace

// A fine particle pinched by a large force (overlap above the old 5 % stop, steady) runs on.
TEST(BlowUp, PinchedFineParticleRunsOn) {
  auto [st, model] = pinched_chain(1.0);
  const Params params = parse_case(small_case, "small.toml");
  BlowUpWatch watch;
  double low = 1, high = 0;
  for (long n = 0; n < 3000; ++n) {
    step(model, st);
    ASSERT_NO_THROW(watch.check(st, params, "test", n)) << "step " << n;
    low = std::min(low, st.max_overlap);
    high = std::max(high, st.max_overlap);
  }
  EXPECT_GT(low, BlowUpWatch::watch_level) << "the old 5 % limit would have stopped this healthy chain";
  EXPECT_LT(high - low, 0.01) << "steady: " << low << " to " << high;
}

// A time step far too large (10 times the stable one) on the same chain: the overlap grows
// geometrically and the watch stops it, saying that the time step is too large.
TEST(BlowUp, TimeStepFarTooLargeIsStopped) {
  auto [st, model] = pinched_chain(10.0);
  const Params params = parse_case(small_case, "small.toml");
  BlowUpWatch watch;
  try {
    for (long n = 0; n < 3000; ++n) {
      step(model, st);
      watch.check(st, params, "test", n);
    }
    ADD_FAILURE() << "no blow-up detected";
  } catch (const RunError& e) {
    const std::string what = e.what();
    EXPECT_NE(what.find("numerical instability"), std::string::npos) << what;
    EXPECT_NE(what.find("time step is too large"), std::string::npos) << what;
    EXPECT_NE(what.find("time.step_ratio"), std::string::npos) << what;
  }
}

// A whole run with time.step_ratio twenty times the largest the case file allows stops as a
// blow-up at run time (exit 3 in the CLI), naming the time step.
TEST(BlowUp, RunWithAFarTooLargeTimeStepIsStopped) {
  Params params = parse_case(small_case, "small.toml");
  params.step_ratio = 10;  // the case file refuses > 0.5
  const fs::path d = scratch("dt-too-large");
  RunOptions o;
  o.out = d;
  o.quiet = true;
  try {
    run_case(params, o);
    ADD_FAILURE() << "no blow-up detected";
  } catch (const RunError& e) {
    const std::string what = e.what();
    std::printf("[ info ] %s\n", what.c_str());
    EXPECT_NE(what.find("blow-up"), std::string::npos) << what;
    EXPECT_NE(what.find("numerical instability"), std::string::npos) << what;
    EXPECT_NE(what.find("time.step_ratio"), std::string::npos) << what;
  }
}

// Format 3 summed fluctuation_path (the skin test's bound of the motion) in runs of spheres only:
// read into a run with ellipsoids it is unknown, not zero (a zero would rule out every list
// rebuild).
TEST(CheckpointFile, Format3LeavesEllipsoidRunsWithoutAMotionBound) {
  const auto reload_as = [](const State& st, std::uint32_t version, const char* name) {
    EXPECT_EQ(st.pairs.size(), 0u);
    const fs::path f = scratch(name);
    save_checkpoint(f, "", "", st, RunProgress{}, version);
    return load_checkpoint(f).state.neighbor.fluctuation_path;
  };
  const fs::path spheroid_case = fs::path(QSDEM_SOURCE_DIR) / "examples" / "paper-A-small.toml";
  State spheroids = generate_loose_sample(parse_case(qsdem_test::slurp(spheroid_case), spheroid_case.string()));
  ASSERT_TRUE(spheroids.particles.has_ellipsoids());
  spheroids.neighbor.fluctuation_path = 3e-9;
  EXPECT_TRUE(std::isinf(reload_as(spheroids, 3, "format3-spheroids.qsck")));
  EXPECT_EQ(reload_as(spheroids, 4, "format4-spheroids.qsck"), 3e-9);
  State spheres = generate_loose_sample(parse_case(small_case, "small.toml"));
  spheres.neighbor.fluctuation_path = 3e-9;
  EXPECT_EQ(reload_as(spheres, 3, "format3-spheres.qsck"), 3e-9);
}

// A checkpoint does not store NeighborState::ellipsoids: the load takes it from the particles, so
// that a run resumed with its list valid steps spheroids as spheroids (has_ellipsoids of a State,
// which the step asks instead of passing over the particles).
TEST(CheckpointFile, RestoredListKnowsWhetherItsParticlesIncludeEllipsoids) {
  const fs::path spheroid_case = fs::path(QSDEM_SOURCE_DIR) / "examples" / "paper-A-small.toml";
  for (const bool spheroids : {true, false}) {
    SCOPED_TRACE(spheroids ? "spheroids" : "spheres");
    const Params params = spheroids ? parse_case(qsdem_test::slurp(spheroid_case), spheroid_case.string())
                                    : parse_case(small_case, "small.toml");
    State st = generate_loose_sample(params);
    ASSERT_EQ(st.particles.has_ellipsoids(), spheroids);
    build_pairs(st.particles, st.cell, 0.2 * smallest_equiv_radius(st.particles), st.pairs, st.neighbor);
    EXPECT_EQ(has_ellipsoids(st), spheroids) << "as the build recorded it";
    const fs::path f = scratch(spheroids ? "list-spheroids.qsck" : "list-spheres.qsck");
    RunProgress run;
    run.phases.resize(params.protocol.size());
    save_checkpoint(f, params.case_text, params.source, st, run);
    const State back = load_checkpoint(f).state;
    ASSERT_TRUE(back.neighbor.valid);
    EXPECT_EQ(back.neighbor.ellipsoids, spheroids);
    EXPECT_EQ(has_ellipsoids(back), spheroids);
  }
}

// A prepared sample of checkpoint format 1 (written before apart pairs were skipped: no skip
// state) still loads and shears, to the series the build that wrote it gives: 120 spheroids,
// tests/golden/format1-sample (made by the build of 7240daa, see tests/golden/README.md).
TEST(CheckpointFile, Format1PreparedSampleStillShears) {
  const fs::path golden = fs::path(QSDEM_SOURCE_DIR) / "tests" / "golden" / "format1-sample";
  EXPECT_NO_THROW(load_checkpoint(golden / "sample.qsck"));
  {
    // The motion since the last list build was not kept before format 3: the skin test must not
    // be answered by the motion bound (a run of spheres would otherwise take it as zero).
    Checkpoint c = load_checkpoint(golden / "sample.qsck");
    EXPECT_TRUE(std::isinf(c.state.neighbor.fluctuation_path));
    c.state.neighbor.surface_path.clear();  // as in a run of spheres
    EXPECT_FALSE(motion_bound_rules_out_rebuild(c.state.neighbor, c.state.cell));
  }
  const fs::path d = scratch("format1");
  ASSERT_EQ(run_cli({"run", (fs::path(QSDEM_SOURCE_DIR) / "examples" / "paper-A-small.toml").string(), "--out",
                     d.string(), "--quiet", "--set", "sample.from=" + golden.string(), "--set",
                     "triaxial.final_axial_strain=1 %", "--set", "triaxial.sample_points=10"},
                    d.string()),
            0)
      << read(d.string() + ".err");
  const qsdem_test::Csv got = qsdem_test::read_csv(d / "series.csv");
  const qsdem_test::Csv want = qsdem_test::read_csv(golden / "series-by-7240daa.csv");
  ASSERT_EQ(got.rows.size(), 10u);
  ASSERT_EQ(got.rows.size(), want.rows.size());
  // Same physics, other round-off (the force loop now sums in another order): 1e-6 of each
  // column's largest magnitude, as the golden test.
  for (const std::string& name : want.header) {
    const std::vector<double> g = got.column(name), w = want.column(name);
    double scale = 0;
    for (double v : w) scale = std::max(scale, std::abs(v));
    for (std::size_t k = 0; k < w.size(); ++k)
      EXPECT_NEAR(g[k], w[k], 1e-6 * scale + 1e-300) << "row " << k << " column " << name;
  }
}

// The records of the phases are written field by field (formats 1 to 4 wrote the triaxial sums as
// a struct's raw bytes, padding included): a checkpoint's bytes are the same whatever the memory
// around the fields held, and a file of the default protocol in any older format still reads back.
TEST(CheckpointFile, PhaseRecordsAreWrittenFieldByField) {
  const State st = generate_loose_sample(parse_case(small_case, "small.toml"));
  const auto save = [&](unsigned char fill, const fs::path& f, std::uint32_t format) {
    RunProgress run;
    run.phase = 1;
    run.phases.resize(2);
    // Fill the records' bytes, then set every field: what a compiler's padding would hold differs.
    std::memset(static_cast<void*>(run.phases.data()), fill, 2 * sizeof(PhaseRecord));
    for (PhaseRecord& r : run.phases) r = PhaseRecord{};
    run.phases[0].v0 = 1e-6;  // the compaction's start, as a run at its second phase has one
    run.phases[1].steps = 250;
    run.phases[1].rows = 7;
    run.phases[1].ufr = 0.25;
    run.phases[1].peak_phi_deg = 31.5;
    run.phases[1].final_e1 = 0.02;
    run.phases[1].wall_s = 12.5;
    run.changes = "triaxial step 4: limits.max_kinetic_ratio=2\n";
    save_checkpoint(f, "", "", st, run, format);
  };
  const fs::path a = scratch("sums-a.qsck"), b = scratch("sums-b.qsck");
  save(0x00, a, checkpoint_format_version);
  save(0xff, b, checkpoint_format_version);
  EXPECT_EQ(read(a), read(b));
  for (std::uint32_t format = checkpoint_format_version; format >= 1; --format) {
    SCOPED_TRACE("format " + std::to_string(format));
    const fs::path f = scratch("sums-" + std::to_string(format) + ".qsck");
    save(0xff, f, format);
    const Checkpoint c = load_checkpoint(f);
    ASSERT_EQ(c.run.phases.size(), 2u);
    EXPECT_EQ(c.run.phase, 1);
    EXPECT_EQ(c.run.phases[1].rows, 7);
    EXPECT_EQ(c.run.phases[1].ufr, 0.25);
    EXPECT_EQ(c.run.phases[1].peak_phi_deg, 31.5);
    EXPECT_EQ(c.run.phases[1].final_e1, 0.02);
    EXPECT_EQ(c.run.phases[1].wall_s, format < 5 ? 0.0 : 12.5) << "formats 1 to 4 kept no triaxial wall time";
    EXPECT_EQ(c.run.changes, format < 5 ? "" : "triaxial step 4: limits.max_kinetic_ratio=2\n");
  }
}

// The phases' records are saved by name (format 13 on, for_each_record_value): every value comes
// back bit for bit, the registry covers PhaseRecord's bytes, and a checkpoint that holds a value
// under a name this build does not know (a measure of another build) loads, with that value
// skipped and the member this build expected at its default.
TEST(CheckpointFile, PhaseRecordsAreSavedByName) {
  std::size_t bytes = 0;
  const PhaseRecord blank;
  for_each_record_value(blank, [&](std::string_view, auto& v) { bytes += sizeof(v); });
  EXPECT_EQ(bytes, sizeof(PhaseRecord)) << "a member of PhaseRecord is not in for_each_record_value";

  const State st = generate_loose_sample(parse_case(small_case, "small.toml"));
  RunProgress run;
  run.phase = 1;
  run.phases.resize(2);
  double next = 1;
  for (PhaseRecord& r : run.phases) {
    for_each_record_value(r, [&](std::string_view, auto& v) { v = static_cast<std::remove_reference_t<decltype(v)>>(next++); });
    r.h0 = Mat3::Identity() * (0.01 * next++);  // what the load checks: a cell, at most a row a step
    r.rows = r.steps / 2;
  }
  run.phases[1].final.z_mech = 0.125;
  const fs::path f = scratch("records-by-name.qsck");
  save_checkpoint(f, "", "", st, run, checkpoint_format_version);
  const Checkpoint c = load_checkpoint(f);
  ASSERT_EQ(c.run.phases.size(), 2u);
  for (std::size_t p = 0; p < 2; ++p) {
    std::vector<double> saved, loaded;
    for_each_record_value(run.phases[p], [&](std::string_view, auto& v) { saved.push_back(static_cast<double>(v)); });
    for_each_record_value(c.run.phases[p], [&](std::string_view, auto& v) { loaded.push_back(static_cast<double>(v)); });
    EXPECT_EQ(loaded, saved) << "phase " << p;
  }

  // The name final.z_mech becomes final.zzmech (same length), and the file is resealed.
  std::string bytes_of = read(f);
  const std::string name = "final.z_mech";
  const std::size_t at = bytes_of.find(name);
  ASSERT_NE(at, std::string::npos);
  bytes_of.replace(at, name.size(), "final.zzmech");
  constexpr std::size_t header = 32;
  const std::uint64_t sum = fnv1a64(bytes_of.data() + header, bytes_of.size() - header);
  std::memcpy(bytes_of.data() + 24, &sum, 8);
  std::ofstream(f, std::ios::binary | std::ios::trunc) << bytes_of;
  const Checkpoint renamed = load_checkpoint(f);
  EXPECT_TRUE(std::isnan(renamed.run.phases[1].final.z_mech)) << "not in the file: its default (undefined)";
  EXPECT_EQ(renamed.run.phases[1].final.void_ratio, c.run.phases[1].final.void_ratio);
  EXPECT_EQ(renamed.run.phases[1].energy_end.kinetic, c.run.phases[1].energy_end.kinetic);
}

// A FIRE phase (docs/physics.md 5.7) stopped by SIGTERM between increments and resumed writes the
// same bits as the uninterrupted run; every increment is relaxed to its tolerances (UFR, the
// lateral stresses), and the last one ends exactly at the strain stop.
TEST(CheckpointProcess, FireIncrementsResumeToTheSameSeries) {
  const std::string fire_case = qsdem_test::sample_200("checkpoint-fire") + R"([[phase]]
name = "compaction"
friction = 0.2
stress = { 11 = "200 kPa", 22 = "200 kPa", 33 = "200 kPa" }
servo = { max_strain_rate = 1e-4 }
stop = { equilibrium = { ufr = "1 %" } }
output = { file = "compaction.csv", clock = "run" }
[[phase]]
name = "triaxial"
friction = 0.5
strain_rate = { 33 = 1e-5 }
stress = { 11 = "200 kPa", 22 = "200 kPa" }
solver = { kind = "fire", strain_increment = "0.025 %", ufr = "0.5 %", stress_tolerance = "0.2 %" }
stop = { strain = { 33 = "0.6 %" } }
[checkpoint]
every_sample_points = 3
)";
  const fs::path f = scratch("fire-case") / "case.toml";
  fs::create_directories(f.parent_path());
  std::ofstream(f) << fire_case;
  const fs::path ref = scratch("fire-reference"), d = scratch("fire-killed");
  ASSERT_EQ(run_cli({"run", f.string(), "--out", ref.string(), "--threads", "1", "--quiet"}, ref.string()), 0)
      << read(ref.string() + ".err");
  const pid_t pid = spawn({"run", f.string(), "--out", d.string(), "--threads", "1", "--quiet"}, d.string());
  ASSERT_TRUE(wait_rows(d, 10, pid)) << "the run ended before it could be killed";
  ::kill(pid, SIGTERM);
  EXPECT_EQ(wait_exit(pid), 128 + SIGTERM) << read(d.string() + ".err");
  ASSERT_EQ(run_cli({"resume", d.string(), "--threads", "1", "--quiet"}, d.string() + "-resume"), 0)
      << read(d.string() + "-resume.err");
  EXPECT_EQ(read(d / "series.csv"), read(ref / "series.csv"));
  std::istringstream in(read(ref / "series.csv"));
  std::string line;
  std::getline(in, line);
  std::vector<std::string> names;
  {
    std::istringstream h(line);
    for (std::string field; std::getline(h, field, ',');) names.push_back(field);
  }
  const auto col = [&](const std::string& n) {
    return static_cast<std::size_t>(std::find(names.begin(), names.end(), n) - names.begin());
  };
  ASSERT_LT(col("relaxed"), names.size());
  long rows = 0;
  double e1 = 0;
  while (std::getline(in, line)) {
    std::vector<std::string> v;
    std::istringstream r(line);
    for (std::string field; std::getline(r, field, ',');) v.push_back(field);
    ++rows;
    EXPECT_EQ(v.at(col("relaxed")), "1") << "row " << rows;
    EXPECT_LT(std::stod(v.at(col("ufr"))), 0.005) << "row " << rows;
    EXPECT_NEAR(std::stod(v.at(col("s11_Pa"))), 200e3, 0.002 * 200e3) << "row " << rows;
    EXPECT_GT(std::stol(v.at(col("iterations"))), 0);
    e1 = std::stod(v.at(col("e1")));
  }
  EXPECT_EQ(rows, 24) << "0.6 % in increments of 0.025 %";
  EXPECT_NEAR(e1, 0.006, 1e-12);
}
