// Memory layout (reorder.hpp): re-sorting the particles along the Morton curve changes where they
// are stored, never the physics. Forces, torques and tangential histories, looked up by particle
// id, are the same after a sort as without it, step after step (to round-off: sums run in
// another order).
#include <gtest/gtest.h>
#include <omp.h>

#include <array>
#include <cmath>
#include <map>
#include <tuple>

#include "qsdem/engine/contact/hertz_mindlin.hpp"
#include "qsdem/engine/model.hpp"
#include "qsdem/engine/neighbor.hpp"
#include "qsdem/engine/reorder.hpp"
#include "qsdem/engine/step.hpp"
#include "qsdem/run/generate.hpp"

using namespace qsdem;

namespace {

// The tangential force on j that pair k stores (the Hertz-Mindlin history).
Vec3 stored_shear(const State& st, std::size_t k) { return HertzMindlin::tangential_force(st.pairs.history.of(k)); }

// `count` particles at random in a cell sized for 220 of them per 24 x 26 x 25 mm.
State random_sample(std::uint64_t seed, std::uint32_t count = 220) {
  Random rng(seed);
  State st;
  st.cell = make_cell((std::cbrt(count / 220.0) * Vec3(24e-3, 26e-3, 25e-3)).asDiagonal());
  const std::vector<Vec3> shapes = {Vec3(1.5e-3, 1e-3, 1e-3), Vec3::Constant(1.2e-3), Vec3(4e-3, 3e-3, 3e-3),
                                    Vec3(1.6e-3, 1.2e-3, 0.9e-3)};
  for (std::uint32_t id = 0; id < count; ++id) {
    const Vec3& ax = shapes[id % shapes.size()];
    st.particles.add(id, ax.x() == ax.z() ? ShapeKind::sphere : ShapeKind::ellipsoid, ax, 2650,
                     Vec3(rng.uniform(), rng.uniform(), rng.uniform()) + Vec3(id % 3 == 0 ? 1 : 0, 0, 0),
                     rng.orientation());
    st.particles.v.back() = 0.05 * Vec3(rng.uniform() - 0.5, rng.uniform() - 0.5, rng.uniform() - 0.5);
  }
  return st;
}

Model model_for(const State& st) {
  Model m;
  m.material = {2650, 7.8e10, 0.3};
  m.contact_law = make_contact_law(m.material, 0.5);
  m.r_min = smallest_equiv_radius(st.particles);
  m.critical_time = critical_time(m.material, m.r_min);
  m.dt = 0.32 * m.critical_time;
  m.skin = 0.2 * m.r_min;
  return m;
}

using PairKey = std::tuple<std::uint32_t, std::uint32_t, int, int, int>;

// Tangential force on the particle with the larger id, per pair of ids and image (orientation free).
std::map<PairKey, Vec3> shear_by_id(const State& st) {
  std::map<PairKey, Vec3> out;
  for (std::size_t k = 0; k < st.pairs.size(); ++k) {
    if (st.pairs.overlap[k] <= 0) continue;
    std::uint32_t a = st.particles.id[st.pairs.i[k]], b = st.particles.id[st.pairs.j[k]];
    Vec3i img = st.pairs.image[k];
    Vec3 f = stored_shear(st, k);  // on j
    if (a > b) {
      std::swap(a, b);
      img = -img;
      f = -f;
    }
    out[{a, b, img.x(), img.y(), img.z()}] = f;
  }
  return out;
}

}  // namespace

TEST(Reorder, SortingChangesStorageNotPhysics) {
  const int saved = omp_get_max_threads();
  omp_set_num_threads(1);
  State plain = random_sample(3);
  const Model model = model_for(plain);
  for (int n = 0; n < 5; ++n) step(model, plain);  // contacts with tangential history
  State sorted = plain;
  ASSERT_TRUE(sort_particles(sorted)) << "a random sample is not in Morton order";
  EXPECT_FALSE(sort_particles(sorted)) << "sorting is idempotent";
  for (std::size_t k = 1; k < sorted.particles.size(); ++k)
    EXPECT_LE(morton_key(sorted.particles.s[k - 1]), morton_key(sorted.particles.s[k]));
  EXPECT_EQ(shear_by_id(sorted).size(), shear_by_id(plain).size());
  for (const auto& [key, f] : shear_by_id(plain)) EXPECT_EQ(shear_by_id(sorted).at(key), f);

  for (int n = 0; n < 10; ++n) {
    step(model, plain);
    step(model, sorted);
    std::map<std::uint32_t, std::size_t> where;
    for (std::size_t i = 0; i < sorted.particles.size(); ++i) where[sorted.particles.id[i]] = i;
    double fscale = 0;
    for (const Vec3& f : plain.particles.force) fscale = std::max(fscale, f.norm());
    ASSERT_GT(fscale, 0);
    for (std::size_t i = 0; i < plain.particles.size(); ++i) {
      const std::size_t j = where.at(plain.particles.id[i]);
      // Same contacts summed in another order: round-off of the largest forces, 1e-12 of them.
      EXPECT_LE((sorted.particles.force[j] - plain.particles.force[i]).norm(), 1e-12 * fscale);
      EXPECT_LE((sorted.particles.s[j] - plain.particles.s[i]).norm(), 1e-14);
    }
    EXPECT_LE((sorted.stress - plain.stress).cwiseAbs().maxCoeff(), 1e-12 * plain.stress.cwiseAbs().maxCoeff());
  }
  omp_set_num_threads(saved);
}

// The pair registry's rules (neighbor.hpp) for any history layout (contact/law.hpp): a layout of
// four values per pair, one of each swap rule, holding functions of the ids of the pair's ends in
// their stored order (i, j): w_i + w_j (symmetric: kept), w_i - w_j (antisymmetric: negated),
// w_j / (w_i + w_j) (j's weight: mirrored, 1 - x) and -1 (outside (0, 1): left as it is), w =
// id + 1. After a sort each pair must hold the functions of its ends in their new order; after a
// list build, the pairs listed before keep them and new pairs get the released values.
TEST(Reorder, PairValuesFollowTheirLayoutsRules) {
  static constexpr HistoryLayout layout{
      "test", 4, {7, 8, 9, 10}, {OnSwap::keep, OnSwap::negate, OnSwap::mirror_unit, OnSwap::mirror_unit}};
  State st = random_sample(5);
  const Model model = model_for(st);
  build_pairs(st.particles, st.cell, model.skin, st.pairs, st.neighbor);
  const auto expected = [&](std::size_t k) {
    const double wi = st.particles.id[st.pairs.i[k]] + 1.0, wj = st.particles.id[st.pairs.j[k]] + 1.0;
    return std::array<double, 4>{wi + wj, wi - wj, wj / (wi + wj), -1};
  };
  st.pairs.history.layout = &layout;
  st.pairs.history.values.resize(4 * st.pairs.size());
  for (std::size_t k = 0; k < st.pairs.size(); ++k) {
    const auto e = expected(k);
    std::copy(e.begin(), e.end(), st.pairs.history.of(k).begin());
  }
  ASSERT_GT(st.pairs.size(), 100u);
  ASSERT_TRUE(sort_particles(st));
  for (std::size_t k = 0; k < st.pairs.size(); ++k) {
    const auto e = expected(k);
    const auto h = st.pairs.history.of(k);
    EXPECT_EQ(h[0], e[0]) << "pair " << k;
    EXPECT_EQ(h[1], e[1]) << "pair " << k;
    EXPECT_NEAR(h[2], e[2], 1e-15) << "pair " << k;  // 1 - x rounds
    EXPECT_EQ(h[3], e[3]) << "pair " << k;
  }
  // The ids were in storage order before the sort (i < j had id_i < id_j): the pairs whose i end
  // now has the larger id are those whose ends it swapped.
  std::size_t reversed = 0;
  for (std::size_t k = 0; k < st.pairs.size(); ++k)
    reversed += st.particles.id[st.pairs.i[k]] > st.particles.id[st.pairs.j[k]] ? 1 : 0;
  EXPECT_GT(reversed, 10u) << "the sort swapped the ends of some pairs";

  // A list build with a wider skin after a rigid translation: the pairs listed before (the same
  // keys) keep their values, the new ones get the released values.
  const std::size_t before = st.pairs.size();
  for (Vec3& s : st.particles.s) s += Vec3(1e-4, -2e-4, 1e-4);
  build_pairs(st.particles, st.cell, 3 * model.skin, st.pairs, st.neighbor);
  ASSERT_GT(st.pairs.size(), before) << "a wider skin lists more pairs";
  std::size_t kept = 0, fresh = 0;
  for (std::size_t k = 0; k < st.pairs.size(); ++k) {
    const auto h = st.pairs.history.of(k);
    if (h[0] == 7) {
      ++fresh;
      EXPECT_EQ(h[1], 8);
      EXPECT_EQ(h[2], 9);
      EXPECT_EQ(h[3], 10);
    } else {
      ++kept;
      EXPECT_EQ(h[0], expected(k)[0]) << "pair " << k;
    }
    EXPECT_EQ(st.pairs.apart_until[k], -1) << "the skip restarts at a build";
  }
  EXPECT_EQ(kept, before);
  EXPECT_EQ(fresh, st.pairs.size() - before);
}

// Above parallel_threshold the sorts (particles by Morton key, candidates and pairs by key), the
// permutations and the merge of the old list's values run on the threads (parallel_algorithms.hpp,
// list_with_history): the list, its values and the particles' order must be those of one thread,
// bit for bit, through a sort with values to carry and a build that keeps them.
TEST(Reorder, ThreadsGiveTheOneThreadListAndOrder) {
  static constexpr HistoryLayout layout{"test", 2, {7, 8}, {OnSwap::negate, OnSwap::mirror_unit}};
  const State start = random_sample(11, 6000);
  const Model model = model_for(start);
  const auto run = [&](int threads) {
    const int saved = omp_get_max_threads();
    omp_set_num_threads(threads);
    State st = start;
    build_pairs(st.particles, st.cell, model.skin, st.pairs, st.neighbor);
    st.pairs.history.layout = &layout;
    st.pairs.history.values.resize(2 * st.pairs.size());
    for (std::size_t k = 0; k < st.pairs.size(); ++k) {
      const double wi = st.particles.id[st.pairs.i[k]] + 1.0, wj = st.particles.id[st.pairs.j[k]] + 1.0;
      st.pairs.history.of(k)[0] = wi - wj;
      st.pairs.history.of(k)[1] = wj / (wi + wj);
    }
    EXPECT_TRUE(sort_particles(st));
    for (Vec3& s : st.particles.s) s += Vec3(1e-4, -2e-4, 1e-4);
    build_pairs(st.particles, st.cell, 2 * model.skin, st.pairs, st.neighbor);
    omp_set_num_threads(saved);
    return st;
  };
  const State one = run(1), two = run(2);
  ASSERT_GT(one.pairs.size(), parallel_threshold) << "the pair sorts and the merge must run in parallel";
  EXPECT_EQ(one.particles.id, two.particles.id);
  EXPECT_EQ(one.pairs.i, two.pairs.i);
  EXPECT_EQ(one.pairs.j, two.pairs.j);
  EXPECT_TRUE(one.pairs.image == two.pairs.image);
  EXPECT_EQ(one.pairs.history.values, two.pairs.history.values);
  EXPECT_EQ(one.pairs.first_i, two.pairs.first_i);
  std::size_t kept = 0;
  for (std::size_t k = 0; k < two.pairs.size(); ++k) {
    if (k > 0) {
      EXPECT_TRUE(key_less(two.pairs.i[k - 1], two.pairs.j[k - 1], two.pairs.image[k - 1], two.pairs.i[k],
                           two.pairs.j[k], two.pairs.image[k]))
          << "pair " << k;
    }
    const double wi = two.particles.id[two.pairs.i[k]] + 1.0, wj = two.particles.id[two.pairs.j[k]] + 1.0;
    if (two.pairs.history.of(k)[0] != 7) {  // listed before the wider build: its values followed it
      ++kept;
      EXPECT_EQ(two.pairs.history.of(k)[0], wi - wj) << "pair " << k;
      EXPECT_NEAR(two.pairs.history.of(k)[1], wj / (wi + wj), 1e-15) << "pair " << k;
    }
  }
  EXPECT_GT(kept, parallel_threshold);
  EXPECT_LT(kept, two.pairs.size());
}

// The incidence (build_incidence, on the threads from parallel_threshold pairs) against a plain
// count: first_i[a] is the number of pairs whose i is below a, and the blocks are cut greedily,
// each at the first particle that brings it to pairs_per_block pairs. Lists with particles without
// pairs at either end and in runs, one particle with more pairs than a block, and no pairs.
TEST(Reorder, IncidenceIsThePlainCount) {
  const auto reference = [](const PairList& pairs, std::size_t n) {
    std::vector<std::uint32_t> first(n + 1, 0);
    for (std::uint32_t i : pairs.i) ++first[i + 1];
    for (std::size_t a = 0; a < n; ++a) first[a + 1] += first[a];
    std::vector<std::uint32_t> blocks{0};
    for (std::size_t a = 0; a < n; ++a)
      if (first[a + 1] - first[blocks.back()] >= pairs_per_block) blocks.push_back(static_cast<std::uint32_t>(a + 1));
    if (blocks.back() != n) blocks.push_back(static_cast<std::uint32_t>(n));
    return std::pair{first, blocks};
  };
  const auto list = [](const std::vector<std::uint32_t>& pairs_of) {
    PairList pairs;
    for (std::uint32_t a = 0; a < pairs_of.size(); ++a)
      for (std::uint32_t m = 0; m < pairs_of[a]; ++m) {
        pairs.i.push_back(a);
        pairs.j.push_back(a + m + 1);
        pairs.image.push_back(Vec3i::Zero());
      }
    return pairs;
  };
  std::vector<std::uint32_t> pairs_of(5000);
  for (std::uint32_t a = 0; a < pairs_of.size(); ++a) pairs_of[a] = a < 40 || a > 4950 ? 0 : (a * 7) % 13 % 9;
  pairs_of[2500] = 3 * pairs_per_block;  // a particle alone fills three blocks
  const std::vector<std::vector<std::uint32_t>> cases{pairs_of, std::vector<std::uint32_t>(300, 0),
                                                      std::vector<std::uint32_t>(10, 2)};
  for (const auto& c : cases)
    for (int threads : {1, 2}) {
      PairList pairs = list(c);
      const int saved = omp_get_max_threads();
      omp_set_num_threads(threads);
      build_incidence(pairs, c.size());
      omp_set_num_threads(saved);
      const auto [first, blocks] = reference(pairs, c.size());
      EXPECT_EQ(pairs.first_i, first) << c.size() << " particles, " << threads << " threads";
      EXPECT_EQ(pairs.block_first, blocks) << c.size() << " particles, " << threads << " threads";
    }
  EXPECT_GT(list(pairs_of).size(), parallel_threshold) << "the parallel loop must run";
}
