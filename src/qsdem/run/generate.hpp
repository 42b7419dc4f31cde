// Sample generation (SPEC 8): a particle-size table becomes a seeded random loose packing.
#pragma once
#include <cstdint>
#include <functional>
#include <random>
#include <vector>

#include "qsdem/engine/state.hpp"
#include "qsdem/run/config.hpp"

namespace qsdem {

// Reproducible uniform numbers in [0, 1) from the standard's fully specified mt19937_64
// (std::uniform_real_distribution is implementation-defined, this is not).
class Random {
 public:
  explicit Random(std::uint64_t seed) : engine_(seed) {}
  double uniform() { return static_cast<double>(engine_() >> 11) * 0x1.0p-53; }
  Quat orientation();  // uniform on SO(3) (Shoemake 1992)

 private:
  std::mt19937_64 engine_;
};

// The table with counts rescaled to about `total_particles` (keeping the count ratios, hence
// the mass fractions) when that is set; otherwise the table as written. With a grading, its
// total_particles drawn from the sieve curve (grading_table).
std::vector<SizeClass> resolve_table(const Params::Sample& sample);

// Peak memory of a run of `particles` particles (bytes), estimated from the measured 1.9 KiB per
// particle of a whole run's peak (docs/benchmarks.md) plus the serialised copy a checkpoint makes.
double run_memory_bytes(double particles);

// Memory this process can still use (bytes): the least of the system's MemAvailable, the room
// left under the cgroup's memory.max and the address-space limit (ulimit -v).
double available_memory_bytes();

// Particles of the table placed at random without overlap (bounding spheres), largest first,
// in a cubic cell whose solid fraction is sample.initial_solid_fraction. Refuses (InputError) a
// table whose run would not fit in the available memory, before allocating. `stop`, polled
// while placing, ends the generation early (it returns an empty State).
State generate_loose_sample(const Params& params, const std::function<bool()>& stop = {});

}  // namespace qsdem
