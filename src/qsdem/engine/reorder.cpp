#include "qsdem/engine/reorder.hpp"

#include <algorithm>
#include <cmath>
#include <numeric>
#include <tuple>

#include "qsdem/engine/parallel_algorithms.hpp"

namespace qsdem {
namespace {

// Spreads the 10 low bits of x to every third bit.
std::uint32_t spread3(std::uint32_t x) {
  x &= 0x3ffu;
  x = (x | (x << 16)) & 0x030000ffu;
  x = (x | (x << 8)) & 0x0300f00fu;
  x = (x | (x << 4)) & 0x030c30c3u;
  x = (x | (x << 2)) & 0x09249249u;
  return x;
}

template <class T, class A>
void permute(std::vector<T, A>& v, const std::vector<std::uint32_t>& order) {
  std::vector<T, A> out(v.size());
  const std::size_t n = order.size();
#pragma omp parallel for schedule(static) if (n > parallel_threshold)
  for (std::size_t k = 0; k < n; ++k) out[k] = v[order[k]];
  v.swap(out);
}

template <class T>
void permute(ComponentArrays<T>& v, const std::vector<std::uint32_t>& order) {
  for (auto& c : v.components()) permute(c, order);
}

// The same for w values per element.
void permute(std::vector<double>& v, const std::vector<std::uint32_t>& order, std::size_t w) {
  std::vector<double> out(v.size());
  const std::size_t n = order.size();
#pragma omp parallel for schedule(static) if (n > parallel_threshold)
  for (std::size_t k = 0; k < n; ++k) std::copy_n(v.data() + w * order[k], w, out.data() + w * k);
  v.swap(out);
}

// What exchanging the ends of a pair does to its w values (HistoryLayout::on_swap).
void swap_ends(const HistoryLayout& layout, double* x) {
  for (int c = 0; c < layout.width; ++c) switch (layout.on_swap[c]) {
      case OnSwap::keep: break;
      case OnSwap::negate: x[c] = -x[c]; break;
      case OnSwap::mirror_unit:
        if (x[c] > 0 && x[c] < 1) x[c] = 1 - x[c];
        break;
    }
}

}  // namespace

std::uint32_t morton_key(const Vec3& s) {
  std::uint32_t key = 0;
  for (int k = 0; k < 3; ++k) {
    const double w = s[k] - std::floor(s[k]);
    const auto cell = static_cast<std::uint32_t>(std::min(1023.0, w * 1024.0));
    key |= spread3(cell) << k;
  }
  return key;
}

bool sort_particles(State& st) {
  Particles& p = st.particles;
  const std::size_t n = p.size();
  std::vector<std::uint32_t> key(n), order(n);
#pragma omp parallel for schedule(static) if (n > parallel_threshold)
  for (std::size_t i = 0; i < n; ++i) key[i] = morton_key(p.s[i]);
  std::iota(order.begin(), order.end(), 0u);
  parallel_stable_sort(order.begin(), order.end(), [&](std::uint32_t a, std::uint32_t b) { return key[a] < key[b]; });
  bool identity = true;
  for (std::size_t k = 0; k < n && identity; ++k) identity = order[k] == k;
  if (identity) return false;

  for_each_field(p, [&](auto& array, ParticleField) { permute(array, order); });
  if (st.neighbor.s_at_build.size() == n) permute(st.neighbor.s_at_build, order);
  if (st.neighbor.surface_path.size() == n) permute(st.neighbor.surface_path, order);

  // Pair keys in the new indices, i < j. Swapping the ends of a pair reverses its image, and
  // each per-pair array's values as its layout says (the pair registry, neighbor.hpp): e.g. the
  // stored tangential force on j becomes the force on the other end, and the PW parameter lambda
  // (weight of j's shape) 1 - lambda.
  std::vector<std::uint32_t> inverse(n);
#pragma omp parallel for schedule(static) if (n > parallel_threshold)
  for (std::size_t k = 0; k < n; ++k) inverse[order[k]] = static_cast<std::uint32_t>(k);
  PairList& pairs = st.pairs;
  const std::size_t np = pairs.size();
#pragma omp parallel for schedule(static) if (np > parallel_threshold)
  for (std::size_t k = 0; k < np; ++k) {
    std::uint32_t i = inverse[pairs.i[k]], j = inverse[pairs.j[k]];
    if (i > j) {
      std::swap(i, j);
      pairs.image[k] = -pairs.image[k];
      for_each_pair_field([&](const HistoryLayout& layout, PairField, std::vector<double>& values) {
        const std::size_t w = static_cast<std::size_t>(layout.width);
        if (values.size() == np * w) swap_ends(layout, values.data() + w * k);
      }, pairs);
    }
    pairs.i[k] = i;
    pairs.j[k] = j;
  }
  std::vector<std::uint32_t> by_key(np);
  std::iota(by_key.begin(), by_key.end(), 0u);
  parallel_sort(by_key.begin(), by_key.end(), [&](std::uint32_t a, std::uint32_t b) {  // a pair's key is unique
    return key_less(pairs.i[a], pairs.j[a], pairs.image[a], pairs.i[b], pairs.j[b], pairs.image[b]);
  });
  permute(pairs.i, by_key);
  permute(pairs.j, by_key);
  permute(pairs.image, by_key);
  for_each_pair_field([&](const HistoryLayout& layout, PairField, std::vector<double>& values) {
    const std::size_t w = static_cast<std::size_t>(layout.width);
    if (values.size() == np * w) permute(values, by_key, w);
  }, pairs);
  build_incidence(pairs, n);
  return true;
}

}  // namespace qsdem
