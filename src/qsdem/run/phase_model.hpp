// A phase compiled into the Model of its steps (MuJoCo's mjModel: resolved numbers and made laws,
// no names): the only place where a Phase (phase.hpp) and its control values become a Model.
// The phase loop makes one when a phase starts and again when a controller changes a control value.
#pragma once
#include "qsdem/engine/model.hpp"
#include "qsdem/engine/state.hpp"
#include "qsdem/run/config.hpp"
#include "qsdem/run/phase.hpp"

namespace qsdem {

// The model of a phase with the given control values: material, time step, servo gains and skin
// of the case (SPEC 3, 5), the phase's contact law made with its friction (or the law its damping
// implies), its damping resolved, and the control of each cell component (strain-rate axes measured
// from the cell h0).
Model phase_model(const Params& params, const Phase& phase, const PhaseControls& controls, const Particles& particles,
                  const Mat3& h0);

// The first and the last phase's model in the current cell (of the default protocol: compaction
// and triaxial test), for tools that step a state.
Model compaction_model(const Params& params, const State& state);
Model triaxial_model(const Params& params, const State& state);

}  // namespace qsdem
