// A whole run, as the CLI calls it: generate (or load) a sample, compact, shear, write the
// results; checkpoints on the way, and resume from them.
#pragma once
#include <csignal>
#include <filesystem>
#include <functional>
#include <stdexcept>
#include <string>
#include <vector>

#include <nlohmann/json.hpp>

#include "qsdem/config.hpp"

namespace qsdem {

struct RunProgress;
struct State;

struct RunOptions {
  std::filesystem::path out;
  bool quiet = false;
  bool prepare_only = false;  // stop after compaction (`qsdem prepare`): DIR/sample.qsck
  bool force = false;         // overwrite a directory holding a finished or unfinished run
  std::vector<std::string> sets = {};  // resume: `--set key=value` changes (resume_keys)
  // Called after each write and rename at the end of a phase, naming it: lets a test take the
  // directory as a crash at that instant would leave it. Unset in the CLI.
  std::function<void(const std::string& what)> after_write = {};
};

// The case keys `qsdem resume --set` may change: they decide when to stop, what to save and how
// often, not the state a checkpoint holds. time.step_ratio only before the triaxial test has begun
// (its rows are taken at fixed step numbers).
inline const std::vector<std::string> resume_keys{
    "limits.max_overlap",       "limits.max_kinetic_ratio", "checkpoint.every_sample_points",
    "checkpoint.every_minutes", "output.vtk_every",         "compaction.max_steps",
    "time.step_ratio"};

// A run stopped by SIGINT or SIGTERM after writing a checkpoint.
struct Interrupted : std::runtime_error {
  Interrupted(const std::string& what, int sig) : std::runtime_error(what), signal(sig) {}
  int signal;
};

// File names inside a run directory.
inline constexpr const char* checkpoint_file = "checkpoint.qsck";
inline constexpr const char* prepared_sample_file = "sample.qsck";
inline constexpr const char* run_lock_file = ".run.lock";

// Runs the case and writes DIR/series.csv, DIR/compaction.csv, DIR/compacted.packing,
// DIR/sample.qsck, DIR/final.packing, DIR/case.toml and DIR/summary.json (with prepare_only: no
// series.csv nor final.packing; a run of a prepared sample does not compact: no compaction files).
// Checkpoints go to DIR/checkpoint.qsck. Input errors are found before DIR is touched; DIR is
// locked (DIR/.run.lock) while the run lasts. Returns the summary.
nlohmann::json run_case(const Params& params, const RunOptions& options);

// The sample a new run of `params` starts from, as run_case makes it: generated, or read from
// sample.from (a prepared sample sets `run` to continue after its first phase). Throws InputError
// when it cannot run (too big for the memory, its largest particle not smaller than half the cell,
// a bad sample.from).
State new_sample(const Params& params, RunProgress& run);

// The engine's build, as summary.json and study.json record it: version (QSDEM_VERSION), commit
// (the full hash of the source's HEAD; null without git) and tree_clean (false when a tracked file
// differed from that commit, as a "-dirty" version says; null without git).
nlohmann::json build_record();

// Continues the run in `dir` from its newest good checkpoint (and finishes a run stopped while
// writing its results), with options.sets applied.
nlohmann::json resume_run(const std::filesystem::path& dir, const RunOptions& options);

// The short table the CLI prints at the end of a run.
std::string format_run_table(const nlohmann::json& summary);

// `qsdem bench`: steps a state `steps` times in a fixed cell, with no output, and returns the
// machine-readable speed record (docs/benchmarks.md). `source` is
//   - a packing file (docs/packing-format.md): particles at rest, no contact history, stepped with
//     the triaxial friction and damping of the case `case_path` (required);
//   - a checkpoint file (*.qsck) or a run directory holding one (DIR/sample.qsck of `qsdem
//     prepare`, else DIR/checkpoint.qsck): the state a run steps, with its velocities and contact
//     history, stepped with the friction and damping of the phase it is in. The case is the
//     checkpoint's own, or `case_path` when given (its material and time.step_ratio must equal it).
// `overrides` are --set strings applied to the case. With `as_spheres`, every ellipsoid is first
// replaced by its equal-volume sphere at the same centre, at rest and without contact history.
nlohmann::json bench_packing(const std::filesystem::path& source, const std::string& case_path,
                             const std::vector<std::string>& overrides, long steps, bool as_spheres = false);

}  // namespace qsdem
