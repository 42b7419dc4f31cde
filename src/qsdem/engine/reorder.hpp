// Memory layout: particles re-sorted along a space-filling curve (Morton order of their wrapped
// fractional position) at every neighbour-list rebuild, so that neighbours in space are
// neighbours in memory: the pair loop then finds its partners in cache, and each thread works on
// a compact region. The contact history moves with the particles.
#pragma once
#include "qsdem/engine/state.hpp"

namespace qsdem {

// Permutes every particle array into Morton order and remaps the pair list (keys, orientation,
// every per-pair array of the pair registry: contact history, PW warm start, ...) to the new
// indices. Returns false if the order was already right (nothing changed).
bool sort_particles(State& state);

// Morton key of a fractional position wrapped into [0, 1)^3, 10 bits per axis.
std::uint32_t morton_key(const Vec3& s);

}  // namespace qsdem
