// Google Benchmark micro-benchmarks: one contact evaluation, one full step.
// The full-step benchmark runs on an FCC lattice of overlapping spheres (built here, no input
// needed) and, when QSDEM_BENCH_PACKING names a packing file (e.g. runs/spheres-A/compacted.packing)
// and QSDEM_BENCH_CASE its case, on that packing. Items per second = particle-steps per second.
#include <benchmark/benchmark.h>
#include <omp.h>

#include <cstdlib>
#include <optional>
#include <utility>

#include "qsdem/engine/contact/hertz_mindlin.hpp"
#include "qsdem/engine/damping/stage.hpp"
#include "qsdem/engine/integrator.hpp"
#include "qsdem/engine/neighbor.hpp"
#include "qsdem/engine/step.hpp"
#include "qsdem/run/config.hpp"
#include "qsdem/run/generate.hpp"
#include "qsdem/run/packing_io.hpp"
#include "qsdem/run/protocol.hpp"

using namespace qsdem;

namespace {

Material paper_material() { return {2650, 7.8e10, 0.3}; }

// n^3 unit cells of FCC (4 n^3 spheres of radius r) with a relative overlap of 1e-3.
State fcc_state(int n, double r) {
  State st;
  const double a = 2 * std::sqrt(2.0) * r * (1 - 1e-3);  // nearest distance 2r(1 - 1e-3)
  st.cell = make_cell(n * a * Mat3::Identity());
  const Vec3 basis[4] = {{0, 0, 0}, {0.5, 0.5, 0}, {0.5, 0, 0.5}, {0, 0.5, 0.5}};
  Random rng(7);
  std::uint32_t id = 0;
  for (int x = 0; x < n; ++x)
    for (int y = 0; y < n; ++y)
      for (int z = 0; z < n; ++z)
        for (const Vec3& b : basis) {
          const Vec3 s = (Vec3(x, y, z) + b) / n + 1e-4 * Vec3(rng.uniform(), rng.uniform(), rng.uniform()) / n;
          st.particles.add(id++, ShapeKind::sphere, Vec3::Constant(r), 2650, s, Quat::Identity());
        }
  return st;
}

Model bench_model(const State& st) {
  Model m;
  m.material = paper_material();
  m.contact_law = make_contact_law(m.material, 0.5);
  m.r_min = smallest_equiv_radius(st.particles);
  m.critical_time = critical_time(m.material, m.r_min);
  m.dt = 0.32 * m.critical_time;
  m.damping = resolve_damping("nd", {0.005, m.material.wave_speed(), m.r_min});
  m.skin = 0.2 * m.r_min;
  return m;
}

void BM_HertzMindlinEvaluate(benchmark::State& bs) {
  const Material mat = paper_material();
  const HertzMindlin law{mat.effective_modulus(), mat.effective_shear_modulus(), 0.5};
  Random rng(1);
  std::vector<ContactGeometry> geo(1024);
  std::vector<Vec3> vel(1024), shear(1024, Vec3::Zero());
  for (std::size_t k = 0; k < geo.size(); ++k) {
    const Vec3 l = Vec3(rng.uniform() - 0.5, rng.uniform() - 0.5, rng.uniform() - 0.5).normalized() * 1.998e-3;
    geo[k] = sphere_sphere(l, 1e-3, 1e-3);
    vel[k] = 1e-3 * Vec3(rng.uniform(), rng.uniform(), rng.uniform());
  }
  std::size_t k = 0;
  for (auto _ : bs) {
    benchmark::DoNotOptimize(evaluate_contact(law, geo[k], vel[k], Vec3::Zero(), 0, 1e-7, shear[k].data()));
    k = (k + 1) & 1023;
  }
  bs.SetItemsProcessed(bs.iterations());
}
BENCHMARK(BM_HertzMindlinEvaluate);

void run_steps(benchmark::State& bs, State st, const Model& model) {
  assign_damping(model, st.particles);
  evaluate_forces(model, st);
  for (auto _ : bs) step(model, st);
  bs.SetItemsProcessed(bs.iterations() * static_cast<long>(st.particles.size()));
  bs.counters["pairs_per_particle"] = static_cast<double>(st.pairs.size()) / static_cast<double>(st.particles.size());
  bs.counters["threads"] = omp_get_max_threads();
}

void BM_StepFCC(benchmark::State& bs) {
  omp_set_num_threads(static_cast<int>(bs.range(1)));
  State st = fcc_state(static_cast<int>(bs.range(0)), 1e-3);
  const Model model = bench_model(st);
  run_steps(bs, std::move(st), model);
}
BENCHMARK(BM_StepFCC)->Args({8, 1})->Args({8, 2})->Args({13, 1})->Args({13, 2})->Unit(benchmark::kMillisecond);

// The packing QSDEM_BENCH_PACKING with the triaxial model of the case QSDEM_BENCH_CASE; none (and
// the benchmark skipped) when either is unset.
std::optional<std::pair<State, Model>> env_packing(benchmark::State& bs) {
  const char* packing = std::getenv("QSDEM_BENCH_PACKING");
  const char* case_file = std::getenv("QSDEM_BENCH_CASE");
  if (!packing || !case_file) {
    bs.SkipWithError("set QSDEM_BENCH_PACKING and QSDEM_BENCH_CASE");
    return std::nullopt;
  }
  const Params params = load_case(case_file);
  State st = read_packing(packing, params.material.density);
  Model model = triaxial_model(params, st);
  return std::pair{std::move(st), std::move(model)};
}

void BM_StepPacking(benchmark::State& bs) {
  omp_set_num_threads(static_cast<int>(bs.range(0)));
  auto loaded = env_packing(bs);
  if (!loaded) return;
  run_steps(bs, std::move(loaded->first), loaded->second);
}
BENCHMARK(BM_StepPacking)->Arg(1)->Arg(2)->Unit(benchmark::kMillisecond);

// The kick alone (integrate_velocities, one thread) on the packing after 200 steps, with nd 0.5 %
// (arg 0) or local damping 0.1 (arg 1): the two kicks on the same forces and velocities.
void BM_KickPacking(benchmark::State& bs) {
  omp_set_num_threads(1);
  auto loaded = env_packing(bs);
  if (!loaded) return;
  auto& [st, model] = *loaded;
  if (bs.range(0) == 1) model.damping = resolve_damping("local", {0.1, model.material.wave_speed(), model.r_min});
  assign_damping(model, st.particles);
  evaluate_forces(model, st);
  for (int n = 0; n < 200; ++n) step(model, st);
  for (auto _ : bs) benchmark::DoNotOptimize(integrate_velocities(model, st.particles));
  bs.SetItemsProcessed(bs.iterations() * static_cast<long>(st.particles.size()));
  bs.SetLabel(bs.range(0) == 1 ? "local 0.1" : "nd");
}
BENCHMARK(BM_KickPacking)->Arg(0)->Arg(1);

// The neighbour-list rebuild alone (build_pairs on the packing's positions, the list of the last
// build carried over: its history merged), one thread; items per second = particles listed per second.
void BM_BuildPairsPacking(benchmark::State& bs) {
  omp_set_num_threads(1);
  auto loaded = env_packing(bs);
  if (!loaded) return;
  auto& [st, model] = *loaded;
  build_pairs(st.particles, st.cell, model.skin, st.pairs, st.neighbor);
  for (auto _ : bs) build_pairs(st.particles, st.cell, model.skin, st.pairs, st.neighbor);
  bs.SetItemsProcessed(bs.iterations() * static_cast<long>(st.particles.size()));
  bs.counters["distance_checks"] = static_cast<double>(st.neighbor.distance_checks);
  bs.counters["pairs"] = static_cast<double>(st.pairs.size());
}
BENCHMARK(BM_BuildPairsPacking);

}  // namespace

BENCHMARK_MAIN();
