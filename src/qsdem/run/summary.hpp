// summary.json of a run (docs/physics.md 10.2), the record of the build that ran it and the
// stages' times (which `qsdem bench` reports too); and the table the CLI prints from it.
#pragma once
#include <cstddef>
#include <string>
#include <vector>

#include <nlohmann/json.hpp>

#include "qsdem/engine/state.hpp"
#include "qsdem/engine/timers.hpp"
#include "qsdem/run/config.hpp"
#include "qsdem/run/run_progress.hpp"

namespace qsdem {

// The engine's build, as summary.json and study.json record it: version (QSDEM_VERSION), commit
// (the full hash of the source's HEAD; null without git) and tree_clean (false when a tracked file
// differed from that commit, as a "-dirty" version says; null without git).
nlohmann::json build_record();

// summary.json of a run that has ended (docs/physics.md 10.2): the case, the sample, each phase's
// figures, the steps, times and speed. `wall`: the wall time of every process that ran it (s);
// `note`: what resume said of the checkpoint it continued from, or "".
nlohmann::json run_summary(const Params& params, const State& st, const RunProgress& run, double wall,
                           const std::string& note);

// The short table the CLI prints at the end of a run.
std::string format_run_table(const nlohmann::json& summary);

// Each stage's seconds and microseconds per step over `steps` steps.
nlohmann::json stage_json(const StageTimers& t, long steps);

// Peak resident set of this process (KiB).
long peak_rss_kib();

}  // namespace qsdem
