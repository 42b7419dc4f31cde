// Memory layout (reorder.hpp): re-sorting the particles along the Morton curve changes where they
// are stored, never the physics. Forces, torques and tangential histories, looked up by particle
// id, are the same after a sort as without it, step after step (to round-off: sums run in
// another order).
#include <gtest/gtest.h>
#include <omp.h>

#include <map>
#include <tuple>

#include "qsdem/generate.hpp"
#include "qsdem/model.hpp"
#include "qsdem/reorder.hpp"
#include "qsdem/step.hpp"

using namespace qsdem;

namespace {

State random_sample(std::uint64_t seed) {
  Random rng(seed);
  State st;
  st.cell = make_cell(Vec3(24e-3, 26e-3, 25e-3).asDiagonal());
  const std::vector<Vec3> shapes = {Vec3(1.5e-3, 1e-3, 1e-3), Vec3::Constant(1.2e-3), Vec3(4e-3, 3e-3, 3e-3),
                                    Vec3(1.6e-3, 1.2e-3, 0.9e-3)};
  for (std::uint32_t id = 0; id < 220; ++id) {
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
  m.friction = 0.5;
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
    Vec3 f = st.pairs.shear[k];  // on j
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
