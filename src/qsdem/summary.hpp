// summary.json (docs/physics.md 10.2) and its parts: the build that ran, a phase's figures, the
// measures, the size table and the stages' times; and the table the CLI prints from it.
#pragma once
#include <cstddef>
#include <string>
#include <vector>

#include <nlohmann/json.hpp>

#include "qsdem/config.hpp"
#include "qsdem/measures.hpp"
#include "qsdem/protocol.hpp"
#include "qsdem/timers.hpp"

namespace qsdem {

// The engine's build, as summary.json and study.json record it: version (QSDEM_VERSION), commit
// (the full hash of the source's HEAD; null without git) and tree_clean (false when a tracked file
// differed from that commit, as a "-dirty" version says; null without git).
nlohmann::json build_record();

// The short table the CLI prints at the end of a run.
std::string format_run_table(const nlohmann::json& summary);

// Each stage's seconds and microseconds per step over `steps` steps.
nlohmann::json stage_json(const StageTimers& t, long steps);

// Peak resident set of this process (KiB).
long peak_rss_kib();

nlohmann::json measures_json(const Measures& m);

// The size table of a generated sample: each class's shape, semi-axes, count and mass fraction.
nlohmann::json size_table_json(const Params& params);

// Phase p, which has ended, as summary.json's `phases` entry. `records`: those of the protocol's
// phases; `controller`: the phase's controller's state at its end (RunProgress::controller_end),
// or none; `energy`: the run keeps the energy ledger (output.energy).
nlohmann::json phase_json(const Protocol& protocol, const std::vector<PhaseRecord>& records, std::size_t p,
                          const std::vector<double>* controller, bool energy);

}  // namespace qsdem
