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

#include "qsdem/run/config.hpp"

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

// Continues the run in `dir` from its newest good checkpoint (and finishes a run stopped while
// writing its results), with options.sets applied.
nlohmann::json resume_run(const std::filesystem::path& dir, const RunOptions& options);

}  // namespace qsdem
