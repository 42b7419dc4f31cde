// Where a run is (SPEC 8.4): the record of each phase, the current phase's own state, and the run's
// own; everything a run needs to continue exactly, which checkpoints save with the State.
#pragma once
#include <array>
#include <concepts>
#include <cstdint>
#include <optional>
#include <string>
#include <string_view>
#include <type_traits>
#include <vector>

#include "qsdem/engine/measures.hpp"
#include "qsdem/engine/state.hpp"
#include "qsdem/run/output.hpp"
#include "qsdem/run/phase.hpp"

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

// f(name, value) for a number, and for each component of a Mat3 (name_11 ... name_33) or a Vec3
// (name_1 ... name_3).
template <class F, class V>
void for_each_number(const std::string& name, V& value, F&& f) {
  if constexpr (std::is_arithmetic_v<std::remove_const_t<V>>) {
    f(std::string_view(name), value);
  } else {
    for (Eigen::Index i = 0; i < value.rows(); ++i)
      for (Eigen::Index j = 0; j < value.cols(); ++j) {
        std::string n = name + '_' + static_cast<char>('1' + i);
        if (value.cols() > 1) n += static_cast<char>('1' + j);
        f(std::string_view(n), value(i, j));
      }
  }
}

// Every number of a PhaseRecord by name, in one order: f(name, value), value a double& or a long&;
// h0's components as h0_11 ... h0_33, the last row's measures as final.<measure>
// (for_each_measure: final.stress_11, final.void_ratio, ...), the ledgers' terms as
// energy_start.<term> and energy_end.<term>. Checkpoints save the records by name through it
// (format 13 on): a new member, measure or ledger term costs no new format, and a checkpoint
// without it leaves it at its default.
template <class R, class F>
  requires std::same_as<std::remove_const_t<R>, PhaseRecord>
void for_each_record_value(R& r, F&& f) {
  for_each_number("h0", r.h0, f);
  f("v0", r.v0);
  f("steps", r.steps);
  f("rows", r.rows);
  f("wall_s", r.wall_s);
  f("ufr", r.ufr);
  f("iuf", r.iuf);
  f("imom", r.imom);
  f("stress_error", r.stress_error);
  f("max_stress_error", r.max_stress_error);
  f("max_shear_stress", r.max_shear_stress);
  f("peak_phi_deg", r.peak_phi_deg);
  f("peak_phi_e1", r.peak_phi_e1);
  f("final_e1", r.final_e1);
  f("final_ev", r.final_ev);
  for_each_measure(r.final, [&](std::string_view name, auto& v) { for_each_number("final." + std::string(name), v, f); });
  for (const EnergyTerm& term : energy_ledger_terms) {
    f(std::string("energy_start.") + term.name, r.energy_start.*term.field);
    f(std::string("energy_end.") + term.name, r.energy_end.*term.field);
  }
}

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

}  // namespace qsdem
