// Protocols (SPEC 8): loose sample -> isotropic compaction -> drained triaxial compression.
// The phase loops are resumable: everything they need to continue exactly where they stopped is in
// RunProgress, which checkpoints save with the State.
#pragma once
#include <array>
#include <cstdint>
#include <functional>
#include <string>

#include "qsdem/config.hpp"
#include "qsdem/measures.hpp"
#include "qsdem/model.hpp"
#include "qsdem/output.hpp"
#include "qsdem/progress.hpp"
#include "qsdem/state.hpp"

namespace qsdem {

struct CompactionResult {
  long steps = 0;
  double wall_s = 0;
  Measures final;  // at the step that met the criteria
};

struct TriaxialResult {
  long steps = 0;
  double wall_s = 0;
  int rows = 0;
  double peak_phi_deg = 0;
  double peak_phi_e1 = 0;
  double mean_ufr = 0, mean_iuf = 0, mean_imom = 0;
  double final_ev = 0, final_e1 = 0;
  double max_lateral_stress_error = 0;   // max |sigma_kk / sigma_c - 1| over the rows, k = 1, 2
  double mean_lateral_stress_error = 0;
};

// Running sums over the rows of series.csv, and the phase's wall time over every process that ran it.
struct TriaxialSums {
  int rows = 0;
  double ufr = 0, iuf = 0, imom = 0, lateral_error = 0, max_lateral_error = 0;
  double peak_phi_deg = 0, peak_phi_e1 = 0, final_ev = 0, final_e1 = 0;
  double wall_s = 0;
};

// Where a run is.
struct RunProgress {
  enum class Phase : std::int32_t { compaction = 0, triaxial = 1, done = 2 };
  Phase phase = Phase::compaction;
  bool phase_started = false;  // v0, h0 and the damping of the phase are set
  long phase_steps = 0;        // steps taken in the current phase
  long rows = 0;               // rows written to the current phase's CSV file
  double v0 = 0;               // cell volume at the start of the phase (m^3)
  Mat3 h0 = Mat3::Identity();  // cell matrix at the start of the phase (m)
  CompactionResult compaction; // set when compaction ends
  TriaxialSums sums;
  double wall_s = 0;           // wall time of the processes that ran it before (s)
  long first_step = 0;         // State::step when this run's own work began (a prepared
                               // sample's compaction steps are not this run's)
  bool prepare_only = false;   // `qsdem prepare`: the run ends with the compacted sample
  std::string changes;         // `resume --set` changes, one "from triaxial step N: key=value" a line
};

// The triaxial result of the rows summed so far (SPEC 10's summary).
TriaxialResult triaxial_result(const RunProgress& run);

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
  // `step`: the phase's step number, counted from 0 as in compaction.csv and series.csv.
  void check(const State& st, const Params& params, const char* phase, long step);

 private:
  std::array<double, window> recent_{};
  long seen_ = 0;
};

// Called after every step; `sample_point` is true when a CSV row was just written. It may save a
// checkpoint or stop the run (by throwing).
using StepHook = std::function<void(bool sample_point)>;

// The phase models of SPEC 8. The triaxial model's axial reference length H0 = h33 at e1 = 0.
Model compaction_model(const Params& params, const State& state);
Model triaxial_model(const Params& params, const State& state, double axial_reference_length);
Model triaxial_model(const Params& params, const State& state);  // H0 = the current h33

// Number of steps to the final axial strain: final / (c_t eps') (SPEC 8).
long triaxial_steps(const Params& params);

// Isotropic compaction with friction mu_0 to the target stress until the stress is within
// tolerance and UFR below its tolerance. Continues from `run` (phase_steps, rows); writes its
// history to `log` (compaction.csv) when given.
CompactionResult compact(const Params& params, State& state, RunProgress& run, Progress& progress, SeriesWriter* log,
                         const StepHook& hook);
// Drained triaxial compression to the final axial strain, sample points written to `series`.
TriaxialResult shear(const Params& params, State& state, RunProgress& run, SeriesWriter& series, Progress& progress,
                     const StepHook& hook);

// A fresh phase without hooks (tests, tools).
CompactionResult compact(const Params& params, State& state, Progress& progress, SeriesWriter* log);
TriaxialResult shear(const Params& params, State& state, SeriesWriter& series, Progress& progress);

}  // namespace qsdem
