// The force stages of the step: per-pair contact forces (narrow phase + contact law), then a
// per-particle gather of resultants. Both are deterministic for any thread count.
#pragma once
#include <cstdint>
#include <vector>

#include "qsdem/engine/model.hpp"
#include "qsdem/engine/schedule.hpp"
#include "qsdem/engine/state.hpp"

namespace qsdem {

// Evaluates every listed pair at the current positions: pair forces and torques, overlaps,
// tangential history, and State::stress / affine_stiffness (SPEC 4, 7). Writes each particle's
// resultant over the pairs where it is the i end into Particles::force / torque. Shares the
// blocks among the threads by `schedule` and sets its owners for the update region.
void compute_contact_forces(const Model& model, State& state, Schedule& schedule);

// Whether the particles' arrays take more than half the last-level cache.
bool beyond_cache(const Particles& p);

// Whether compute_contact_forces fetches the j ends' data ahead: Model::prefetch_j_ends, or when
// unset, beyond the cache (within it the prefetches gain nothing: docs/benchmarks.md, "Large
// samples"; beyond it a j end far from i in Morton order is in no cache).
inline bool prefetches_j_ends(const Model& model, const Particles& p) {
  return model.prefetch_j_ends.value_or(beyond_cache(p));
}

// The contact forces on the j ends of the last evaluation by pair (PairList keeps them by
// contact), zero for a pair that is not a contact: each pair's slot in PairList::contact_force,
// 4 bytes a pair where a copy of the forces would take 24. For measures and checks; it allocates.
class ContactForceByPair {
 public:
  explicit ContactForceByPair(const State& state);
  Vec3 operator[](std::size_t k) const { return slot_[k] == none ? Vec3(Vec3::Zero()) : force_[slot_[k]]; }

 private:
  static constexpr std::uint32_t none = ~0u;  // the pair is not a contact
  std::vector<std::uint32_t> slot_;
  const Vec3* force_;
};

// The same as a copy, one force per pair.
std::vector<Vec3> contact_forces_by_pair(const State& state);

// Adds the pairs where each particle is the j end, after compute_contact_forces with the same
// schedule: Particles::force / torque are then the contact resultants (SPEC 7: contact forces only).
void gather_resultants(State& state, const Schedule& schedule);

// The same for the particles that owner t of the schedule holds (Schedule::owner_first): one
// thread's part of the step's particle pass (step.cpp). Reads only their contacts
// (Schedule::contact_owner_first), each particle's in pair order, so the sums do not depend on the
// threads.
void gather_resultants(const PairList& pairs, const Schedule& schedule, Particles& p, std::size_t t);

// The same for State::contact_stiffness and contact_rotational_stiffness (when they are summed):
// the j ends' terms of the contacts of owner t's particles.
void gather_contact_stiffness(const PairList& pairs, const Schedule& schedule, State& state, std::size_t t);

}  // namespace qsdem
