// The phase loop (SPEC 8): runs one phase of a protocol (phase.hpp) step by step, watches it for a
// blow-up, takes its sample points when its row schedule (row_schedule.hpp) or its measures say,
// hands them to its recorder (phase_recorder.hpp), ends it by its stop criteria, and calls its
// controller. The loop owns the phase's control values and builds the immutable Model of the step
// from them (again when a controller changes them). It is resumable: everything it needs to
// continue exactly where it stopped is in RunProgress (run_progress.hpp), which checkpoints save
// with the State.
#pragma once
#include <array>
#include <cstdint>
#include <functional>
#include <optional>
#include <string>
#include <vector>

#include "qsdem/engine/measures.hpp"
#include "qsdem/engine/model.hpp"
#include "qsdem/engine/state.hpp"
#include "qsdem/run/config.hpp"
#include "qsdem/run/output.hpp"
#include "qsdem/run/phase.hpp"
#include "qsdem/run/phase_model.hpp"
#include "qsdem/run/phase_recorder.hpp"
#include "qsdem/run/progress.hpp"
#include "qsdem/run/run_progress.hpp"

namespace qsdem {

// The blow-up watch (docs/runs.md), checked after every step. A numerical instability (a time
// step too large for the contact stiffness) makes the largest overlap grow geometrically from
// step to step, then the state NaN; a fine particle pinched in a force chain has a large but
// steady overlap and runs on. Stops the run (RunError) when the state is not finite, when the
// largest overlap exceeds limits.max_overlap (the bound beyond which the contact geometry is
// meaningless), or when, above watch_level, it is at least twice the smallest of the last
// `window` steps (of the steps so far, in the phase's first ones).
class BlowUpWatch {
 public:
  static constexpr double watch_level = 0.05;  // overlap / smaller radius
  static constexpr long window = 20;           // steps
  // `step`: the phase's step number, counted from 0 as in the rows of its file.
  void check(const State& st, const Params& params, const char* phase, long step);

 private:
  std::array<double, window> recent_{};
  long seen_ = 0;
};

// Called after every step; `sample_point` is true when a row was just written. It may save a
// checkpoint or stop the run (by throwing).
using StepHook = std::function<void(bool sample_point)>;

// The name of phase p of the protocol (the last one's once all are done), for messages.
const std::string& phase_name(const Params& params, std::int32_t p);

// Runs phase run.phase of params.protocol, from its start or on from where `run` stopped, to its
// end. Throws RunError when it cannot end (a step limit, a blow-up).
void run_phase(const Params& params, State& state, RunProgress& run, const RowSink& rows, Progress& progress,
               const StepHook& hook);

// Phase `index` from its start, without hooks (tests, tools); its file's strains from its start.
PhaseRecord run_phase(const Params& params, std::size_t index, State& state, Progress& progress, SeriesWriter* rows);

}  // namespace qsdem
