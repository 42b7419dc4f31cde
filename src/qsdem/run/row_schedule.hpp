// A phase's row schedule (SPEC 8.4): the force evaluation of its next row by its cadence, its end
// as planned now, and both planned anew when a controller changes the control values.
#pragma once
#include "qsdem/engine/state.hpp"
#include "qsdem/run/phase.hpp"
#include "qsdem/run/run_progress.hpp"

namespace qsdem {

// The last force evaluation of the phase as planned now (-1: it ends on measured criteria only).
long planned_end(const Phase& phase, const PhaseState& s, double step_ratio);

// The force evaluation of the phase's next sample point by its cadence (the end is one too).
long next_sample(const Phase& phase, const PhaseState& s, long rows, long end, double step_ratio);

// Whether the next row of a cadence by the strain of a shear component (not planned: the cell's
// normal components may move under it) is due at the state's last force evaluation: its strain
// gamma_ab (phase_strain) has passed the next multiple of the interval, in the rate's direction.
bool measured_row(const Phase& phase, const PhaseState& s, long rows, const State& st, const Mat3& h0);

// After a controller changed the control values at force evaluation n (they apply from n + 1):
// a planned strain's segment restarts at n + 1 with its nominal strain there, and the rows still
// to come are spread from the last one.
void controls_changed(const PhaseControls& before, PhaseState& s, long n, long rows, double step_ratio);

}  // namespace qsdem
