// The damping stage of the step (SPEC 6): before the kick, every particle's viscous factors from
// the phase's model (Model::damping), A_i for translation (Particles::damping_translation) and B_i
// for rotation (damping_rotation), which the kick applies (paper Eq. 10, integrator.hpp). What is
// damped, translation, rotation or both, is data of the phase (ResolvedDamping::acts_on): the
// other factor is 0. Cundall's damping acts in the kick itself (ResolvedDamping::cundall_*).
#pragma once
#include <cstddef>

#include "qsdem/engine/model.hpp"
#include "qsdem/engine/particles.hpp"
#include "qsdem/engine/state.hpp"

namespace qsdem {

// The damping stage at the start of a phase: every particle's factors. InputError when a factor
// would reverse velocities (A dt/2 >= 1).
void assign_damping(const Model& model, Particles& particles);

// The damping stage before the kick, particles [lo, hi): the factors of a model whose factors
// change during the phase (per_step, from the state's contact stiffnesses); nothing for the others
// (assign_damping set them).
void update_damping(const Model& model, State& state, std::size_t lo, std::size_t hi);

}  // namespace qsdem
