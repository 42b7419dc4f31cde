// One time step, as a pipeline of named, timed stages that reads top to bottom.
#pragma once
#include "qsdem/engine/damping/stage.hpp"
#include "qsdem/engine/model.hpp"
#include "qsdem/engine/schedule.hpp"
#include "qsdem/engine/state.hpp"

namespace qsdem {

// Advances the state from t to t + dt:
//   1. neighbor        rebuild the Verlet list if the skin test fails (SPEC 4)
//   2. contact forces  pair forces at t, stress and affine stiffness (SPEC 4, 7)
//   3. servo           velocity gradient L of the cell for this step (SPEC 3); deform the cell
//   then, in one pass over the particles (each thread its own range, step.cpp):
//   4. gather          per-particle contact resultants f_p, M_p (SPEC 7)
//   5. integrate       the damping stage's factors (damping/stage.hpp), then the damped leapfrog kick
//                      to t + dt/2 (SPEC 5, 6)
//   6. advance         drift positions and orientations to t + dt in the deformed cell
// `schedule` shares the work among the threads (no result depends on it); a run keeps one from
// step to step, so that the blocks' times of the last steps set the next cut.
void step(const Model& model, State& state, Schedule& schedule);
// The same with a schedule of its own (the blocks then shared by their pair counts).
void step(const Model& model, State& state);

// Stages 1 and 2 only: the neighbour list when the skin test asks for it, and the pair forces at the
// current positions with each particle's i-side sums (gather_resultants adds the j ends).
void pair_forces(const Model& model, State& state, Schedule& schedule);

// Stages 1, 2 and 4 only: forces and resultants at the current positions (used at start-up and by
// tools that need the forces of a given configuration).
void evaluate_forces(const Model& model, State& state);

// Stages 4-6 (step() runs them after the force stage and the servo): the particles' gather, kick
// and drift, each thread on the range of particles the schedule gives it. When the schedule's
// owners are not those of the state's last force evaluation, one thread updates them all.
// Returns the largest |v|^2 after the kick.
double update_particles(const Model& model, State& state, Schedule& schedule);

}  // namespace qsdem
