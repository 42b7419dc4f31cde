// The phase loop (SPEC 8): runs one phase of a protocol (phase.hpp) step by step, takes its sample
// points, writes its rows, ends it by its stop criteria, and calls its controller. The loop owns
// the phase's control values and builds the immutable Model of the step from them (again when a
// controller changes them). It is resumable: everything it needs to continue exactly where it
// stopped is in RunProgress, which checkpoints save with the State.
#pragma once
#include <array>
#include <cstdint>
#include <functional>
#include <optional>
#include <string>
#include <vector>

#include "qsdem/config.hpp"
#include "qsdem/measures.hpp"
#include "qsdem/model.hpp"
#include "qsdem/output.hpp"
#include "qsdem/phase.hpp"
#include "qsdem/phase_model.hpp"
#include "qsdem/progress.hpp"
#include "qsdem/state.hpp"

namespace qsdem {

// What a run keeps of a phase: its start, the sums over its rows (SPEC 8.4) and its end.
struct PhaseRecord {
  Mat3 h0 = Mat3::Identity();  // cell matrix at the start of the phase (m)
  double v0 = 0;               // cell volume at the start (m^3)
  long steps = 0;              // steps taken
  long rows = 0;               // rows written to its file
  double wall_s = 0;           // wall time of every process that ran it (s)
  double ufr = 0, iuf = 0, imom = 0;  // sums over the rows
  // |sigma_kk / target - 1| over the rows and the stress-controlled normal components: sum, largest
  double stress_error = 0, max_stress_error = 0;
  // The largest |sigma_ab - target| / p over the rows and the shear components (target 0 unless
  // the component is stress-controlled).
  double max_shear_stress = 0;
  double peak_phi_deg = 0, peak_phi_e1 = 0;  // the largest phi over the rows and the e1 of its row
  double final_e1 = 0, final_ev = 0;         // of the last row
  Measures final;                            // the measures of the last row
  // The run's energy ledger at the phase's start and at its last row (output.energy).
  EnergyLedger energy_start, energy_end;
};

// The current phase's own state besides its record: what it needs to continue exactly.
struct PhaseState {
  bool live = false;  // set at the phase's start (a checkpoint of format < 6 has none: the phase's own values)
  PhaseControls controls;  // the control values now (a controller may have changed them)
  // A planned strain (phase.hpp) of normal component k: its rate is constant from force evaluation
  // segment_step[k], at nominal strain segment_strain[k].
  std::array<long, 3> segment_step{};
  std::array<double, 3> segment_strain{};
  // `points` cadence: the rows still to come are spread evenly from this force evaluation and
  // row count to the phase's end.
  long row_base_step = 0, row_base_rows = 0;
  long last_row_step = -1;  // force evaluation of the last row
  // stop.stress of component c: +1 when reached from below, -1 from above (0 until the first step)
  std::array<std::int8_t, component_count> stress_side{};
  std::vector<double> controller;  // Controller::save() after its last call
};

// Where a run is.
struct RunProgress {
  std::int32_t phase = 0;      // the current phase of the protocol; its size once all are done
  bool phase_started = false;  // its record's start and the servo's memory are set
  PhaseState state;
  std::vector<PhaseRecord> phases;  // one per phase of the protocol
  double wall_s = 0;           // wall time of the processes that ran it before (s)
  long first_step = 0;         // State::step when this run's own work began (a prepared
                               // sample's first phase is not this run's)
  bool prepare_only = false;   // `qsdem prepare`: the run ends with its first phase
  std::string changes;         // `resume --set` changes, one "from PHASE step N: key=value" a line
  // Per phase that ended: its controller's saved state at its end (Controller::figures()).
  std::vector<std::vector<double>> controller_end;
  // The run's directory as the checkpoint counts it (none in checkpoints before format 10): the
  // digest of the case.toml the run wrote, and of the rows so far of each file it appends to.
  // `resume` refuses a directory that holds other files (from another run).
  std::optional<std::uint64_t> case_digest;
  std::vector<FileDigest> files;
  // The builds of the processes that ran it, in order, each once in a row: a build record
  // (summary.json's `build`) as JSON text. Empty in checkpoints before format 12.
  std::vector<std::string> builds;

  PhaseRecord& current() { return phases.at(static_cast<std::size_t>(phase)); }
  const PhaseRecord& current() const { return phases.at(static_cast<std::size_t>(phase)); }
};

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

// Where a phase's rows go: the writer of its file (none: rows are counted, not written), the
// phase whose starting cell the file's strains are measured from, and the file's optional columns
// (those asked for by any phase writing to it: holds_volume, shears, a rate controller).
struct RowSink {
  SeriesWriter* writer = nullptr;
  int reference_phase = 0;
  SeriesColumns columns;
  // classes.csv (docs/physics.md 10.3) and the sample's size classes (size_classes), when it is written.
  SeriesWriter* classes = nullptr;
  const std::vector<double>* size_classes = nullptr;
};

// The strain components of the cell h against the cell h0 (StopCriteria): e_kk = 1 - h_kk/h0_kk,
// gamma_ab = F_ab + F_ba with F = h h0^-1.
std::array<double, component_count> phase_strain(const Mat3& h, const Mat3& h0);

// The name of phase p of the protocol (the last one's once all are done), for messages.
const std::string& phase_name(const Params& params, std::int32_t p);

// Runs phase run.phase of params.protocol, from its start or on from where `run` stopped, to its
// end. Throws RunError when it cannot end (a step limit, a blow-up).
void run_phase(const Params& params, State& state, RunProgress& run, const RowSink& rows, Progress& progress,
               const StepHook& hook);

// Phase `index` from its start, without hooks (tests, tools); its file's strains from its start.
PhaseRecord run_phase(const Params& params, std::size_t index, State& state, Progress& progress, SeriesWriter* rows);

}  // namespace qsdem
