#include "qsdem/engine/neighbor.hpp"

#include <fmt/format.h>
#include <omp.h>

#include <algorithm>
#include <cmath>
#include <functional>
#include <limits>
#include <numeric>
#include <tuple>

#include "qsdem/engine/parallel_algorithms.hpp"

namespace qsdem {
namespace {

struct Candidate {
  std::uint32_t i, j;
  Vec3i image;
};


int floor_div(int a, int n) { return (a >= 0) ? a / n : -((-a + n - 1) / n); }

// One linked-cell grid over the fractional cell for the particles of one size class.
struct Grid {
  Eigen::Vector3i n = Eigen::Vector3i::Ones();   // bins per axis
  double r_max = 0;                              // largest bounding radius in the class
  std::size_t first_bin = 0;                     // its bins' place in the numbering of all (Grids)

  std::size_t bins() const { return std::size_t(n.x()) * std::size_t(n.y()) * std::size_t(n.z()); }
  std::size_t bin_index(const Eigen::Vector3i& b) const {
    return first_bin +
           (std::size_t(b.z()) * std::size_t(n.y()) + std::size_t(b.y())) * std::size_t(n.x()) + std::size_t(b.x());
  }
};

// The grids of the size classes, their bins numbered class after class, with one CSR of all bins.
struct Grids {
  std::vector<Grid> classes;
  std::vector<std::uint32_t> start, members;  // bin b holds members[start[b], start[b + 1]), ascending
  // The members' wrapped positions and bounding radii in the same order: a row of bins along x
  // is one contiguous range, which the search reads in sequence.
  std::vector<double> x, y, z, radius;
};

// Bins per axis of a class's grid: at least 2 r_max + skin wide, so that a bin's neighbours hold
// every partner, and no more than one per member of the class, so that a few small particles
// among large ones (a wide grading) cost one bin each, not (cell / r_max)^3 bins in all. Coarser
// bins only put more members in each.
Eigen::Vector3i grid_bins(const Vec3& w, double r_max, double skin, std::size_t members) {
  const double per_length = std::cbrt(static_cast<double>(members) / (w.x() * w.y() * w.z()));
  Eigen::Vector3i n;
  for (int k = 0; k < 3; ++k) {
    const double fine = w[k] / (2 * r_max + skin), sparse = w[k] * per_length;
    n[k] = static_cast<int>(std::clamp(std::floor(std::min(fine, sparse)), 1.0, double(std::numeric_limits<int>::max())));
  }
  // An axis raised to one bin in a flat cell may leave more bins than members: coarsen the others.
  const auto bins = [&] { return std::size_t(n.x()) * std::size_t(n.y()) * std::size_t(n.z()); };
  while (bins() > std::max<std::size_t>(members, 1)) {
    int k = 0;
    n.maxCoeff(&k);
    n[k] = std::max(1, n[k] / 2);
  }
  return n;
}

// Size classes: greedy groups of bounding radii within a factor 2, smallest first.
std::vector<int> size_classes(const Particles& p, std::vector<double>& class_rmax) {
  std::vector<double> radii = p.bound_radius;
  parallel_sort(radii.begin(), radii.end(), std::less<>());
  radii.erase(std::unique(radii.begin(), radii.end()), radii.end());
  std::vector<double> lower;  // lower bound of each class
  class_rmax.clear();         // the largest radius of each class: its last in ascending order
  for (double r : radii) {
    if (lower.empty() || r > 2 * lower.back()) lower.push_back(r), class_rmax.push_back(r);
    class_rmax.back() = r;
  }
  const std::size_t n = p.size();
  std::vector<int> cls(n);
#pragma omp parallel for schedule(static) if (n > parallel_threshold)
  for (std::size_t i = 0; i < n; ++i)
    cls[i] = static_cast<int>(std::upper_bound(lower.begin(), lower.end(), p.bound_radius[i]) - lower.begin()) - 1;
  return cls;
}

}  // namespace

void check_cell_size(const Particles& p, const Cell& cell, double skin) {
  double rmax = 0;
  for (double r : p.bound_radius) rmax = std::max(rmax, r);
  const double wmin = cell.widths().minCoeff();
  // A particle must stay smaller than half the cell (SPEC 3); the skin keeps the list exact.
  if (2 * rmax + skin >= 0.5 * wmin)
    throw CellTooSmall(fmt::format("the largest particle (diameter {:.4g} mm, plus skin {:.3g} mm) is not smaller "
                                   "than half the smallest cell width ({:.4g} mm)",
                                   2e3 * rmax, 1e3 * skin, 1e3 * wmin),
                       "use more particles (sample.total_particles) or smaller ones");
}

void NeighborState::restart_motion(const Particles& p) {
  ellipsoids = p.has_ellipsoids();
  if (ellipsoids)
    surface_path.assign(p.size(), 0.0);
  else
    surface_path.clear();
  fluctuation_path = 0;
  strain_path = 0;
  checked_displacement = checked_fluctuation = checked_strain = 0;
}

// Stretch of any listed branch by the cell deformation F = h h0^-1 (Frobenius bounds the 2-norm).
static double branch_stretch(const NeighborState& ns, const Cell& cell) {
  const double strain = (cell.h * ns.h_at_build.inverse() - Mat3::Identity()).norm();
  return strain * (2 * ns.max_bound_radius + ns.skin);
}

// Since the last pass over the particles (or the build), which measured twice the
// largest displacement D_c, no particle has moved by more than sum dt max|v| = (fluctuation_path
// - checked_fluctuation) / 2 in the frame of its step, which the cell has since turned and
// stretched by at most exp(strain_path - checked_strain) (h_n h_m^-1 = prod (I + dt L)); D_c too.
// So twice the displacement is below exp(strain since) (D_c + fluctuation since). The margins
// cover the round-off of the positions.
static bool bound_rules_out_rebuild(const NeighborState& ns, double stretch) {
  const double moved = ns.checked_displacement + (ns.fluctuation_path - ns.checked_fluctuation);
  return ns.valid &&
         std::exp(ns.strain_path - ns.checked_strain) * moved * (1 + 1e-6) + stretch < ns.skin * (1 - 1e-6);
}

bool motion_bound_rules_out_rebuild(const NeighborState& ns, const Cell& cell) {
  return bound_rules_out_rebuild(ns, branch_stretch(ns, cell));
}

bool needs_rebuild(NeighborState& ns, const Particles& p, const Cell& cell, bool use_motion_bound) {
  if (!ns.valid) return true;
  const double stretch = branch_stretch(ns, cell);
  if (use_motion_bound && bound_rules_out_rebuild(ns, stretch)) return false;  // no pass over particles
  double d2max = 0;
  const std::size_t n = p.size();
#pragma omp parallel for reduction(max : d2max) schedule(static) if (n > parallel_threshold)
  for (std::size_t i = 0; i < n; ++i) d2max = std::max(d2max, (cell.h * (p.s[i] - ns.s_at_build[i])).squaredNorm());
  const double displacement = 2 * std::sqrt(d2max);
  if (use_motion_bound) {  // the bound restarts from here (the paths are kept by step())
    ns.checked_displacement = displacement;
    ns.checked_fluctuation = ns.fluctuation_path;
    ns.checked_strain = ns.strain_path;
  }
  return displacement + stretch > ns.skin;
}

void build_incidence(PairList& pairs, std::size_t n) {
  const std::size_t np = pairs.size();
  pairs.first_i.resize(n + 1);
  const std::uint32_t* const pair_i = pairs.i.data();
  std::uint32_t* const first = pairs.first_i.data();
  // The pairs are in key order, so in order of i: pair k (or the end, k = np) is the first of
  // every particle a in (i[k - 1], i[k]] (from 0 for the first pair, to n for the end). Each a is
  // written once.
#pragma omp parallel for schedule(static) if (np > parallel_threshold)
  for (std::size_t k = 0; k <= np; ++k) {
    const std::size_t from = k == 0 ? 0 : std::size_t(pair_i[k - 1]) + 1, to = k == np ? n : pair_i[k];
    for (std::size_t a = from; a <= to; ++a) first[a] = static_cast<std::uint32_t>(k);
  }
  // Blocks of whole particles (as i) holding at least pairs_per_block pairs: each block owns the
  // i-side sums of its particles, and the blocks depend on the list only, not on the threads. A
  // block starting at particle b ends at the first particle m with first_i[m] >= first_i[b] +
  // pairs_per_block (a search in first_i, which rises with m), or at n.
  pairs.block_first.assign(1, 0);
  for (;;) {
    const std::uint32_t b = pairs.block_first.back();
    const auto m = std::lower_bound(pairs.first_i.begin() + b + 1, pairs.first_i.end(), first[b] + pairs_per_block);
    if (m == pairs.first_i.end()) break;
    pairs.block_first.push_back(static_cast<std::uint32_t>(m - pairs.first_i.begin()));
    if (pairs.block_first.back() == n) break;
  }
  if (pairs.block_first.back() != n) pairs.block_first.push_back(static_cast<std::uint32_t>(n));
}

namespace {

// Fractional positions wrapped into [0, 1)^3 and their integer offsets: s = wrapped + wrap.
struct WrappedPositions {
  std::vector<Vec3> s;
  std::vector<Vec3i> wrap;
};
WrappedPositions wrap_positions(const Particles& p) {
  const std::size_t n = p.size();
  WrappedPositions w{std::vector<Vec3>(n), std::vector<Vec3i>(n)};
  constexpr double reach = std::numeric_limits<int>::max();
  std::size_t blown = n;  // the first particle whose position is not one
#pragma omp parallel for schedule(static) reduction(min : blown) if (n > parallel_threshold)
  for (std::size_t i = 0; i < n; ++i) {
    const Vec3 f = p.s[i].array().floor();
    // An image count beyond int (or NaN) is a blown-up state, not a position: stop before the cast.
    if (!(f.array().abs() < reach).all()) {
      blown = std::min(blown, i);
      continue;
    }
    w.wrap[i] = f.cast<int>();
    w.s[i] = p.s[i] - f;
  }
  if (blown < n)
    throw RunError(fmt::format("particle id {} is at ({}, {}, {}) in cell coordinates: the state has blown up "
                               "and cannot be stepped",
                               p.id[blown], p.s[blown].x(), p.s[blown].y(), p.s[blown].z()));
  return w;
}

// One grid per size class (size_classes), bins as grid_bins sizes them, filled by a counting sort
// on the threads: each particle's bin, the bins' counts and their prefix sums, each particle put
// in its bin's next slot. Those slots follow the threads' timing, so each bin's members are then
// sorted (a bin holds a few): the grids do not depend on the thread count.
Grids make_grids(const Particles& p, const std::vector<Vec3>& sw, const std::vector<int>& cls,
                 const std::vector<double>& class_rmax, const Vec3& w, double skin) {
  const std::size_t n = p.size();
  const std::size_t nclass = class_rmax.size();
  std::vector<std::size_t> members(nclass, 0);
#pragma omp parallel if (n > parallel_threshold)
  {
    std::vector<std::size_t> mine(nclass, 0);
#pragma omp for schedule(static) nowait
    for (std::size_t i = 0; i < n; ++i) ++mine[static_cast<std::size_t>(cls[i])];
#pragma omp critical(qsdem_grid_members)
    for (std::size_t c = 0; c < nclass; ++c) members[c] += mine[c];
  }
  Grids grids;
  grids.classes.resize(nclass);
  std::size_t bins = 0;
  for (std::size_t c = 0; c < nclass; ++c) {
    Grid& g = grids.classes[c];
    g.r_max = class_rmax[c];
    g.n = grid_bins(w, g.r_max, skin, members[c]);
    g.first_bin = bins;
    bins += g.bins();
  }
  std::vector<std::uint32_t> bin_of(n), count(bins + 1, 0);
#pragma omp parallel for schedule(static) if (n > parallel_threshold)
  for (std::size_t i = 0; i < n; ++i) {
    const Grid& g = grids.classes[static_cast<std::size_t>(cls[i])];
    Eigen::Vector3i b;
    for (int k = 0; k < 3; ++k) b[k] = std::min(g.n[k] - 1, static_cast<int>(sw[i][k] * g.n[k]));
    const std::size_t at = g.bin_index(b);
    bin_of[i] = static_cast<std::uint32_t>(at);
#pragma omp atomic
    ++count[at + 1];
  }
  grids.start.resize(bins + 1);
  parallel_partial_sum(count.begin(), count.end(), grids.start.begin());
  std::vector<std::uint32_t>& next = count;  // each bin's next slot
#pragma omp parallel for schedule(static) if (bins > parallel_threshold)
  for (std::size_t b = 0; b < bins; ++b) next[b] = grids.start[b];
  grids.members.resize(n);
#pragma omp parallel for schedule(static) if (n > parallel_threshold)
  for (std::size_t i = 0; i < n; ++i) {
    std::uint32_t slot;
#pragma omp atomic capture
    slot = next[bin_of[i]]++;
    grids.members[slot] = static_cast<std::uint32_t>(i);
  }
#pragma omp parallel for schedule(static) if (bins > parallel_threshold)
  for (std::size_t b = 0; b < bins; ++b)
    if (grids.start[b + 1] - grids.start[b] > 1)
      std::sort(grids.members.begin() + grids.start[b], grids.members.begin() + grids.start[b + 1]);
  grids.x.resize(n), grids.y.resize(n), grids.z.resize(n), grids.radius.resize(n);
#pragma omp parallel for schedule(static) if (n > parallel_threshold)
  for (std::size_t m = 0; m < n; ++m) {
    const std::uint32_t j = grids.members[m];
    grids.x[m] = sw[j].x(), grids.y[m] = sw[j].y(), grids.z[m] = sw[j].z(), grids.radius[m] = p.bound_radius[j];
  }
  return grids;
}

// Every pair whose bounding spheres are closer than the skin, sorted by key. Each particle searches
// its own class (partners of higher index) and every smaller class, so that each pair is found
// once, from the side of the larger particle. `checked` counts the distances computed.
std::vector<Candidate> find_candidates(const Particles& p, const Cell& cell, double skin, const WrappedPositions& wp,
                                       const std::vector<int>& cls, const Grids& grids, long& checked) {
  const std::size_t n = p.size();
  const Vec3 w = cell.widths();
  const std::vector<Vec3>& sw = wp.s;
  const CellMap h(cell.h);
  // Through local pointers: through the vectors GCC reloaded them after every push_back.
  const std::uint32_t* const start = grids.start.data();
  const std::uint32_t* const members = grids.members.data();
  const double *const gx = grids.x.data(), *const gy = grids.y.data(), *const gz = grids.z.data();
  const double* const radius = grids.radius.data();
  std::vector<std::vector<Candidate>> found(static_cast<std::size_t>(omp_get_max_threads()));
  long count = 0;
#pragma omp parallel if (n > parallel_threshold) reduction(+ : count)
  {
    auto& out = found[static_cast<std::size_t>(omp_get_thread_num())];
#pragma omp for schedule(dynamic, 256)
    for (std::size_t i = 0; i < n; ++i) {
      const double ri = p.bound_radius[i];
      const double six = sw[i].x(), siy = sw[i].y(), siz = sw[i].z();
      for (int c = 0; c <= cls[i]; ++c) {
        const Grid& g = grids.classes[static_cast<std::size_t>(c)];
        const double reach = ri + g.r_max + skin;
        Eigen::Vector3i lo, hi;
        for (int k = 0; k < 3; ++k) {
          lo[k] = static_cast<int>(std::floor((sw[i][k] - reach / w[k]) * g.n[k]));
          hi[k] = static_cast<int>(std::floor((sw[i][k] + reach / w[k]) * g.n[k]));
        }
        for (int uz = lo.z(); uz <= hi.z(); ++uz) {
          const int iz = floor_div(uz, g.n.z()), bz = uz - iz * g.n.z();
          for (int uy = lo.y(); uy <= hi.y(); ++uy) {
            const int iy = floor_div(uy, g.n.y()), by = uy - iy * g.n.y();
            // The row's bins along x in runs of one periodic image: each run's members are one
            // contiguous range of the grid's arrays.
            for (int ux = lo.x(); ux <= hi.x();) {
              const int ix = floor_div(ux, g.n.x()), bx = ux - ix * g.n.x();
              const int last = std::min(hi.x(), (ix + 1) * g.n.x() - 1);  // the run's last ux
              const std::uint32_t m0 = start[g.bin_index({bx, by, bz})];
              const std::uint32_t m1 = start[g.bin_index({bx + (last - ux), by, bz}) + 1];
              ux = last + 1;
              const Vec3i img(ix, iy, iz);
              for (std::uint32_t m = m0; m < m1; ++m) {
                const std::uint32_t j = members[m];
                if (c == cls[i] && j <= i) continue;
                ++count;
                // l = h (s_j + image - s_i), summed as Eigen sums it
                double lx, ly, lz;
                h.apply((gx[m] + ix) - six, (gy[m] + iy) - siy, (gz[m] + iz) - siz, lx, ly, lz);
                const double cut = ri + radius[m] + skin;
                if ((lx * lx + ly * ly) + lz * lz >= cut * cut) continue;
                const Vec3i k = img + wp.wrap[i] - wp.wrap[j];  // image in unwrapped coordinates
                if (i < j)
                  out.push_back({static_cast<std::uint32_t>(i), j, k});
                else
                  out.push_back({j, static_cast<std::uint32_t>(i), Vec3i(-k)});
              }
            }
          }
        }
      }
    }
  }
  checked = count;
  std::vector<Candidate> all;
  for (auto& f : found) all.insert(all.end(), f.begin(), f.end());
  parallel_sort(all.begin(), all.end(), [](const Candidate& a, const Candidate& b) {  // each pair found once
    return key_less(a.i, a.j, a.image, b.i, b.j, b.image);
  });
  return all;
}

// The list of the candidates (sorted by key), with the history of the pairs that `pairs` lists
// under the same key (both sorted): each per-pair array of the registry copied for those pairs
// when it is kept, else released.
PairList list_with_history(const std::vector<Candidate>& all, const PairList& pairs) {
  PairList next;
  const std::size_t np = all.size();
  next.i.resize(np);
  next.j.resize(np);
  next.image.resize(np);
  next.history.layout = pairs.history.layout;
  for_each_pair_field([&](const HistoryLayout& layout, PairField, std::vector<double>& values) {
    values = released_values(layout, np);
  }, next);
  // The old pair of each new pair that was listed before (or none): both lists merged by key, in
  // chunks of the new list, each from the first old pair not below its first key.
  constexpr std::size_t none = SIZE_MAX;
  std::vector<std::size_t> before(np, none);
  const std::size_t old_np = pairs.size();
  const std::size_t chunks = np > parallel_threshold ? 4 * static_cast<std::size_t>(omp_get_max_threads()) : 1;
#pragma omp parallel for schedule(static) if (chunks > 1)
  for (std::size_t chunk = 0; chunk < chunks; ++chunk) {
    const std::size_t k0 = np * chunk / chunks, k1 = np * (chunk + 1) / chunks;
    if (k0 == k1) continue;
    // The first old key not below all[k0], by bisection (std::ranges::partition_point over an
    // iota view does not build with the fuzzer's clang and libstdc++ 12).
    std::size_t o = 0, count = old_np;
    while (count > 0) {
      const std::size_t half = count / 2, m = o + half;
      if (key_less(pairs.i[m], pairs.j[m], pairs.image[m], all[k0].i, all[k0].j, all[k0].image))
        o = m + 1, count -= half + 1;
      else
        count = half;
    }
    for (std::size_t k = k0; k < k1; ++k) {
      const Candidate& c = all[k];
      next.i[k] = c.i;
      next.j[k] = c.j;
      next.image[k] = c.image;
      while (o < old_np && key_less(pairs.i[o], pairs.j[o], pairs.image[o], c.i, c.j, c.image)) ++o;
      if (o < old_np && pairs.i[o] == c.i && pairs.j[o] == c.j && pairs.image[o] == c.image) before[k] = o;
    }
  }
  for_each_pair_field(
      [&](const HistoryLayout& layout, PairField field, std::vector<double>& values, const std::vector<double>& old) {
        const std::size_t w = static_cast<std::size_t>(layout.width);
        if (!field.kept || old.size() != old_np * w) return;  // not sized on the old list: none to keep
#pragma omp parallel for schedule(static) if (np > parallel_threshold)
        for (std::size_t k = 0; k < np; ++k)
          if (before[k] != none) std::copy_n(old.data() + w * before[k], w, values.data() + w * k);
      },
      next, pairs);
  next.overlap_known = pairs.overlap_known && pairs.overlap.size() == pairs.size();
  return next;
}

}  // namespace

std::vector<double> released_values(const HistoryLayout& layout, std::size_t np) {
  const std::size_t w = static_cast<std::size_t>(layout.width);
  std::vector<double> values(w * np);
#pragma omp parallel for schedule(static) if (np > parallel_threshold)
  for (std::size_t k = 0; k < np; ++k) std::copy_n(layout.released.begin(), w, values.begin() + w * k);
  return values;
}

void adopt_history(PairList& pairs, const HistoryLayout& layout) {
  PairHistory& h = pairs.history;
  const bool same = h.layout->name == layout.name && h.layout->width == layout.width;
  if (!same || h.values.size() != pairs.size() * static_cast<std::size_t>(layout.width))
    h.values = released_values(layout, pairs.size());
  h.layout = &layout;
}

void build_pairs(const Particles& p, const Cell& cell, double skin, PairList& pairs, NeighborState& ns) {
  check_cell_size(p, cell, skin);
  const WrappedPositions wp = wrap_positions(p);
  std::vector<double> class_rmax;
  const std::vector<int> cls = size_classes(p, class_rmax);
  const Grids grids = make_grids(p, wp.s, cls, class_rmax, cell.widths(), skin);
  const std::size_t bins = grids.start.size() - 1;
  long checked = 0;
  const std::vector<Candidate> all = find_candidates(p, cell, skin, wp, cls, grids, checked);
  PairList next = list_with_history(all, pairs);
  build_incidence(next, p.size());
  pairs = std::move(next);

  ns.s_at_build = p.s;
  ns.h_at_build = cell.h;
  ns.skin = skin;
  ns.max_bound_radius = *std::max_element(p.bound_radius.begin(), p.bound_radius.end());
  ns.restart_motion(p);
  ns.valid = true;
  ns.distance_checks = checked;
  ns.grid_bins = static_cast<long>(bins);
  ++ns.builds;
}

}  // namespace qsdem
