// Protocols (SPEC 8): loose sample -> isotropic compaction -> drained triaxial compression.
#pragma once
#include <filesystem>
#include <functional>

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

// The phase models of SPEC 8.
Model compaction_model(const Params& params, const State& state);
Model triaxial_model(const Params& params, const State& state);

// Number of steps to the final axial strain: final / (c_t eps') (SPEC 8).
long triaxial_steps(const Params& params);

// Isotropic compaction with friction mu_0 to the target stress until the stress is within
// tolerance on every axis and UFR is below its tolerance. Appends its history to `log`
// (compaction.csv) when given.
CompactionResult compact(const Params& params, State& state, Progress& progress, SeriesWriter* log);

// Drained triaxial compression to the final axial strain with sample points written to `series`.
TriaxialResult shear(const Params& params, State& state, SeriesWriter& series, Progress& progress);

// Refuses what this build cannot run yet (ellipsoid contacts).
void check_supported(const State& state);

}  // namespace qsdem
