// Narrow-phase cost per pair: Perram-Wertheim ellipsoid contact (SPEC 4), warm-started as in a
// DEM run and cold, against sphere_sphere on the equal-volume spheres.
//
// Shapes (SPEC 9): arg 0 = (1.2, 1, 1) mm with itself, 1 = (10.5, 7, 7) mm with (1.2, 1, 1) mm,
// 2 = (10.5, 7, 7) mm with itself, 3 = random pairs of Sample B's four shapes. 1024 pairs with
// random orientations and directions, overlap ~1e-3 of the smaller b. Warm: each call sees the
// pair moved by one "step" (1e-7 b and 1e-7 rad, more than a quasi-static step) from the previous
// call on it and starts from its lambda. The "apart" variant has a gap of 0.1 b (a pair of the
// Verlet list that does not touch).
#include <benchmark/benchmark.h>

#include <array>
#include <cmath>
#include <random>
#include <vector>

#include "qsdem/engine/contact/geometry.hpp"
#include "qsdem/engine/ellipsoid_contact.hpp"

using namespace qsdem;

namespace {

constexpr std::size_t kPairs = 1024;

struct BenchPair {
  Vec3 axes_i, axes_j;
  std::array<Quat, 2> q_i, q_j;  // two consecutive "steps"
  std::array<Vec3, 2> l;
  double lambda = -1;
  double r_i = 0, r_j = 0;  // equal-volume sphere radii
};

Vec3 shape(int set, int which, std::mt19937_64& rng) {
  const Vec3 small(1.2e-3, 1e-3, 1e-3), large(10.5e-3, 7e-3, 7e-3);
  switch (set) {
    case 0: return small;
    case 1: return which == 0 ? large : small;
    case 2: return large;
    default: {
      const std::array<Vec3, 4> b = {Vec3(6.6e-3, 5.5e-3, 5.5e-3), Vec3(7.8e-3, 6e-3, 6e-3), Vec3(9.1e-3, 6.5e-3, 6.5e-3),
                                     Vec3(10.5e-3, 7e-3, 7e-3)};
      return b[rng() % 4];
    }
  }
}

// Centre distance along u at which the pair touches (bisection on the contact test).
double touching_distance(const Vec3& u, const Vec3& ai, const Quat& qi, const Vec3& aj, const Quat& qj) {
  double lo = 0, hi = ai.maxCoeff() + aj.maxCoeff();
  ContactGeometry g;
  for (int k = 0; k < 80; ++k) {
    const double mid = 0.5 * (lo + hi);
    double lambda = -1;
    (ellipsoid_contact(mid * u, ai, qi, aj, qj, lambda, g) ? lo : hi) = mid;
  }
  return lo;
}

std::vector<BenchPair> make_pairs(int set, double rel_overlap) {
  std::mt19937_64 rng(42 + static_cast<unsigned>(set));
  std::normal_distribution<double> normal;
  auto dir = [&] { return Vec3(normal(rng), normal(rng), normal(rng)).normalized(); };
  auto rot = [&] { return Quat(normal(rng), normal(rng), normal(rng), normal(rng)).normalized(); };
  std::vector<BenchPair> pairs(kPairs);
  for (BenchPair& p : pairs) {
    p.axes_i = shape(set, 0, rng);
    p.axes_j = shape(set, 1, rng);
    p.q_i[0] = rot();
    p.q_j[0] = rot();
    const Vec3 u = dir();
    const double b = std::min(p.axes_i.minCoeff(), p.axes_j.minCoeff());
    const double d = touching_distance(u, p.axes_i, p.q_i[0], p.axes_j, p.q_j[0]);
    // Overlap along the normal n ~ (d_touch - d) n.u; n.u taken from a just-touching call.
    ContactGeometry g;
    double lambda = -1;
    ellipsoid_contact((d - 1e-9 * b) * u, p.axes_i, p.q_i[0], p.axes_j, p.q_j[0], lambda, g);
    p.l[0] = (d - rel_overlap * b / g.normal.dot(u)) * u;
    const double step = 1e-7;
    p.l[1] = p.l[0] + step * b * dir();
    p.q_i[1] = (Quat(Eigen::AngleAxisd(step, dir())) * p.q_i[0]).normalized();
    p.q_j[1] = (Quat(Eigen::AngleAxisd(step, dir())) * p.q_j[0]).normalized();
    p.r_i = std::cbrt(p.axes_i.prod());
    p.r_j = std::cbrt(p.axes_j.prod());
    ellipsoid_contact(p.l[1], p.axes_i, p.q_i[1], p.axes_j, p.q_j[1], p.lambda, g);  // warm state
  }
  return pairs;
}

void run_ellipsoid(benchmark::State& bs, double rel_overlap, bool warm) {
  std::vector<BenchPair> pairs = make_pairs(static_cast<int>(bs.range(0)), rel_overlap);
  ContactGeometry g;
  std::size_t k = 0, state = 0, contacts = 0;
  for (auto _ : bs) {
    BenchPair& p = pairs[k];
    double cold = -1;
    double& lambda = warm ? p.lambda : cold;
    contacts += ellipsoid_contact(p.l[state], p.axes_i, p.q_i[state], p.axes_j, p.q_j[state], lambda, g);
    benchmark::DoNotOptimize(g);
    if (++k == kPairs) k = 0, state ^= 1;
  }
  bs.SetItemsProcessed(bs.iterations());
  bs.counters["contact_fraction"] = static_cast<double>(contacts) / static_cast<double>(bs.iterations());
}

void BM_EllipsoidContactWarm(benchmark::State& bs) { run_ellipsoid(bs, 1e-3, true); }
void BM_EllipsoidContactCold(benchmark::State& bs) { run_ellipsoid(bs, 1e-3, false); }
void BM_EllipsoidApartWarm(benchmark::State& bs) { run_ellipsoid(bs, -0.1, true); }
BENCHMARK(BM_EllipsoidContactWarm)->DenseRange(0, 3);
BENCHMARK(BM_EllipsoidContactCold)->DenseRange(0, 3);
BENCHMARK(BM_EllipsoidApartWarm)->DenseRange(0, 3);

// The same warm pairs, a batch of 64 at a time (EllipsoidContactBatch, what the force stage runs),
// from shapes computed once per particle and step as the force stage does: time per pair.
void BM_EllipsoidContactBatchWarm(benchmark::State& bs) {
  std::vector<BenchPair> pairs = make_pairs(static_cast<int>(bs.range(0)), 1e-3);
  std::vector<std::array<EllipsoidShape, 2>> shape_i(kPairs), shape_j(kPairs);
  for (std::size_t k = 0; k < kPairs; ++k)
    for (int state = 0; state < 2; ++state) {
      shape_i[k][state] = ellipsoid_shape(pairs[k].axes_i, pairs[k].q_i[state]);
      shape_j[k][state] = ellipsoid_shape(pairs[k].axes_j, pairs[k].q_j[state]);
    }
  EllipsoidContactBatch batch;
  std::size_t first = 0, state = 0, contacts = 0;
  for (auto _ : bs) {
    batch.size = 0;
    for (std::size_t k = first; k < first + EllipsoidContactBatch::capacity; ++k)
      batch.add(pairs[k].l[state], shape_i[k][state], shape_j[k][state], pairs[k].lambda);
    ellipsoid_contacts(batch);
    for (int a = 0; a < batch.size; ++a) {
      pairs[first + static_cast<std::size_t>(a)].lambda = batch.lambda[a];
      contacts += batch.touching[a];
    }
    benchmark::DoNotOptimize(batch.geometry);
    first += EllipsoidContactBatch::capacity;
    if (first == kPairs) first = 0, state ^= 1;
  }
  const auto n = static_cast<double>(bs.iterations()) * EllipsoidContactBatch::capacity;
  bs.SetItemsProcessed(static_cast<std::int64_t>(n));
  bs.counters["contact_fraction"] = static_cast<double>(contacts) / n;
}
BENCHMARK(BM_EllipsoidContactBatchWarm)->DenseRange(0, 3);

// Iterations per call (not a time): warm and cold averages over the pair set.
void BM_EllipsoidIterations(benchmark::State& bs) {
  std::vector<BenchPair> pairs = make_pairs(static_cast<int>(bs.range(0)), 1e-3);
  ContactGeometry g;
  double warm = 0, cold = 0;
  for (auto _ : bs) {
    warm = cold = 0;
    for (BenchPair& p : pairs) {
      EllipsoidContactStats s;
      double lc = -1;
      ellipsoid_contact(p.l[0], p.axes_i, p.q_i[0], p.axes_j, p.q_j[0], p.lambda, g, s);
      warm += s.iterations;
      ellipsoid_contact(p.l[0], p.axes_i, p.q_i[0], p.axes_j, p.q_j[0], lc, g, s);
      cold += s.iterations;
      std::swap(p.l[0], p.l[1]), std::swap(p.q_i[0], p.q_i[1]), std::swap(p.q_j[0], p.q_j[1]);
    }
  }
  bs.counters["warm_iterations"] = warm / kPairs;
  bs.counters["cold_iterations"] = cold / kPairs;
}
BENCHMARK(BM_EllipsoidIterations)->DenseRange(0, 3)->Iterations(2);

// The sphere narrow phase on the equal-volume spheres of the same pairs.
void BM_SphereSphereEqualVolume(benchmark::State& bs) {
  std::vector<BenchPair> pairs = make_pairs(static_cast<int>(bs.range(0)), 1e-3);
  std::vector<Vec3> l(kPairs);
  for (std::size_t k = 0; k < kPairs; ++k)
    l[k] = pairs[k].l[0].normalized() * (pairs[k].r_i + pairs[k].r_j) * (1 - 1e-3);
  std::size_t k = 0;
  for (auto _ : bs) {
    const ContactGeometry g = sphere_sphere(l[k], pairs[k].r_i, pairs[k].r_j);
    benchmark::DoNotOptimize(g);
    if (++k == kPairs) k = 0;
  }
  bs.SetItemsProcessed(bs.iterations());
}
BENCHMARK(BM_SphereSphereEqualVolume)->DenseRange(0, 3);

}  // namespace
