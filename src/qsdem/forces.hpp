// The force stages of the step: per-pair contact forces (narrow phase + contact law), then a
// per-particle gather of resultants. Both are deterministic for any thread count.
#pragma once
#include "qsdem/model.hpp"
#include "qsdem/state.hpp"

namespace qsdem {

// Evaluates every listed pair at the current positions: pair forces and torques, overlaps,
// tangential history, and State::stress / affine_stiffness (SPEC 4, 7).
void compute_contact_forces(const Model& model, State& state);

// Sums pair forces and torques into Particles::force / torque (SPEC 7: contact forces only).
void gather_resultants(State& state);

}  // namespace qsdem
