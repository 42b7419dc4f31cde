// Sample generation (SPEC 8): a particle-size table becomes a seeded random loose packing.
#pragma once
#include <cstdint>
#include <random>
#include <vector>

#include "qsdem/config.hpp"
#include "qsdem/state.hpp"

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
// the mass fractions) when that is set; otherwise the table as written.
std::vector<SizeClass> resolve_table(const Params::Sample& sample);

// Particles of the table placed at random without overlap (bounding spheres), largest first,
// in a cubic cell whose solid fraction is sample.initial_solid_fraction.
State generate_loose_sample(const Params& params);

}  // namespace qsdem
