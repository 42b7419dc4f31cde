#include "qsdem/run/generate.hpp"

#include <fmt/format.h>
#include <sys/resource.h>

#include <algorithm>
#include <cmath>
#include <fstream>
#include <limits>
#include <string>
#include <numeric>

#include "qsdem/run/grading.hpp"

namespace qsdem {

Quat Random::orientation() {
  const double u1 = uniform(), u2 = uniform(), u3 = uniform();
  const double a = std::sqrt(1 - u1), b = std::sqrt(u1);
  return Quat(a * std::sin(2 * pi * u2), a * std::cos(2 * pi * u2), b * std::sin(2 * pi * u3),
              b * std::cos(2 * pi * u3));
}

std::vector<SizeClass> resolve_table(const Params::Sample& sample) {
  if (!sample.grading.empty()) return grading_table(sample.grading, sample.total_particles, sample.seed);
  std::vector<SizeClass> table = sample.table;
  if (sample.total_particles <= 0) return table;
  const double written = std::accumulate(table.begin(), table.end(), 0.0,
                                         [](double s, const SizeClass& c) { return s + static_cast<double>(c.count); });
  for (auto& c : table)
    c.count = std::max(1L, std::lround(static_cast<double>(c.count) * static_cast<double>(sample.total_particles) / written));
  return table;
}

double run_memory_bytes(double particles) {
  // 1.9 KiB peak + 0.9 KiB state serialised, rounded up; the broad phase's grids are in the peak
  // at any size ratio (at most one bin per particle and class, neighbor.cpp grid_bins).
  constexpr double bytes_per_particle = 3 * 1024.0;
  return particles * bytes_per_particle;
}

double available_memory_bytes() {
  double have = std::numeric_limits<double>::infinity();
  if (std::ifstream in("/proc/meminfo"); in)
    for (std::string key; in >> key;) {
      double kib = 0;
      in >> kib;
      if (key == "MemAvailable:") have = std::min(have, 1024 * kib);
      in.ignore(std::numeric_limits<std::streamsize>::max(), '\n');
    }
  double max = 0, current = 0;
  if (std::ifstream in("/sys/fs/cgroup/memory.max"); in >> max)  // "max": no limit, not read
    if (std::ifstream cur("/sys/fs/cgroup/memory.current"); cur >> current) have = std::min(have, max - current);
  rlimit lim{};
  if (getrlimit(RLIMIT_AS, &lim) == 0 && lim.rlim_cur != RLIM_INFINITY)
    have = std::min(have, static_cast<double>(lim.rlim_cur));
  return std::max(have, 0.0);
}

State generate_loose_sample(const Params& params, const std::function<bool()>& stop) {
  const std::vector<SizeClass> table = resolve_table(params.sample);
  double count = 0;
  for (const auto& c : table) count += static_cast<double>(c.count);
  const double need = run_memory_bytes(count), have = available_memory_bytes();
  if (need > have)
    throw InputError(fmt::format(
        "a run of {:.0f} particles needs about {:.3g} GiB of memory ({:.0f} KiB per particle); {:.3g} GiB are "
        "available (the least of MemAvailable, the cgroup's memory.max and ulimit -v): lower "
        "sample.total_particles or the counts of sample.particles",
        count, need / 0x1p30, run_memory_bytes(1) / 1024, have / 0x1p30));
  Random rng(params.sample.seed);

  std::vector<const SizeClass*> order;
  double solid = 0;
  for (const auto& c : table) {
    for (long k = 0; k < c.count; ++k) order.push_back(&c);
    solid += static_cast<double>(c.count) * ellipsoid_volume(c.semi_axes);
  }
  // Largest first: they are the hardest to place.
  std::stable_sort(order.begin(), order.end(),
                   [](const SizeClass* a, const SizeClass* b) { return a->semi_axes[0] > b->semi_axes[0]; });
  const double side = std::cbrt(solid / params.sample.initial_solid_fraction);
  const std::size_t n = order.size();

  State st;
  st.cell = make_cell(side * Mat3::Identity());
  Particles& p = st.particles;

  // Uniform grid of bins no smaller than the largest diameter: a new particle can only overlap
  // particles in its own and the 26 neighbouring bins.
  const double rmax = order.front()->semi_axes[0];
  const int nb = std::max(1, static_cast<int>(side / (2 * rmax)));
  std::vector<std::vector<std::uint32_t>> bins(static_cast<std::size_t>(nb * nb * nb));
  auto bin_of = [&](const Vec3& s) {
    Eigen::Vector3i b;
    for (int k = 0; k < 3; ++k) b[k] = std::min(nb - 1, static_cast<int>(s[k] * nb));
    return b;
  };
  auto flat = [&](const Eigen::Vector3i& b) {
    return static_cast<std::size_t>(((b.z() + nb) % nb * nb + (b.y() + nb) % nb) * nb + (b.x() + nb) % nb);
  };

  constexpr long max_attempts = 100000;
  for (std::size_t k = 0; k < n; ++k) {
    if (stop && k % 1024 == 0 && stop()) return State{};
    const SizeClass& c = *order[k];
    const double r = c.semi_axes[0];
    bool placed = false;
    for (long attempt = 0; attempt < max_attempts && !placed; ++attempt) {
      const Vec3 s(rng.uniform(), rng.uniform(), rng.uniform());
      const Eigen::Vector3i b = bin_of(s);
      bool free = true;
      for (int dz = -1; dz <= 1 && free; ++dz)
        for (int dy = -1; dy <= 1 && free; ++dy)
          for (int dx = -1; dx <= 1 && free; ++dx) {
            if (nb == 1 && (dx != 0 || dy != 0 || dz != 0)) continue;  // one bin: visit it once
            for (std::uint32_t o : bins[flat(b + Eigen::Vector3i(dx, dy, dz))]) {
              Vec3 d = p.s[o] - s;
              d -= d.array().round().matrix();  // minimum image (cubic cell)
              const double gap = side * d.norm() - r - p.bound_radius[o];
              if (gap < 0) {
                free = false;
                break;
              }
            }
          }
      if (!free) continue;
      p.add(static_cast<std::uint32_t>(k), c.shape, c.semi_axes, params.material.density, s,
            c.shape == ShapeKind::sphere ? Quat::Identity() : rng.orientation());
      bins[flat(b)].push_back(static_cast<std::uint32_t>(k));
      placed = true;
    }
    if (!placed)
      throw InputError(fmt::format(
          "could not place particle {} of {} without overlap after {} attempts: lower "
          "sample.initial_solid_fraction (now {})",
          k + 1, n, max_attempts, params.sample.initial_solid_fraction));
  }
  return st;
}

}  // namespace qsdem
