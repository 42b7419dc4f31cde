// A whole run, as the CLI calls it: generate, compact, shear, write the results.
#pragma once
#include <filesystem>
#include <string>

#include <nlohmann/json.hpp>

#include "qsdem/config.hpp"

namespace qsdem {

struct RunOptions {
  std::filesystem::path out;
  bool quiet = false;
  bool prepare_only = false;  // stop after compaction (`qsdem prepare`)
};

// Runs the case and writes DIR/series.csv, DIR/compaction.csv, DIR/compacted.packing,
// DIR/final.packing and DIR/summary.json (with prepare_only: compaction.csv,
// compacted.packing and summary.json). Returns the summary.
nlohmann::json run_case(const Params& params, const RunOptions& options);

// The short table the CLI prints at the end of a run.
std::string format_run_table(const nlohmann::json& summary);

// Steps a packing for `steps` steps at the triaxial settings of `params` (no output) and
// returns the machine-readable speed record of `qsdem bench`.
nlohmann::json bench_packing(const Params& params, const std::filesystem::path& packing, long steps);

}  // namespace qsdem
