#include "qsdem/run/bench.hpp"

#include <fmt/format.h>
#include <omp.h>

#include <algorithm>
#include <chrono>

#include "qsdem/engine/damping/stage.hpp"
#include "qsdem/engine/forces.hpp"
#include "qsdem/engine/measures.hpp"
#include "qsdem/engine/neighbor.hpp"
#include "qsdem/engine/schedule.hpp"
#include "qsdem/engine/step.hpp"
#include "qsdem/run/checkpoint.hpp"
#include "qsdem/run/config.hpp"
#include "qsdem/run/packing_io.hpp"
#include "qsdem/run/phase_model.hpp"
#include "qsdem/run/protocol.hpp"
#include "qsdem/run/run_directory.hpp"
#include "qsdem/run/summary.hpp"

namespace qsdem {

namespace {

template <class T, class A>
double kib(const std::vector<T, A>& v) {
  return static_cast<double>(v.capacity() * sizeof(T)) / 1024;
}

// Heap held by the state's arrays (KiB), by structure: what `peak_rss_kib` is made of besides
// the binary, its libraries and transient build buffers.
nlohmann::json memory_kib(const State& st, const Schedule& schedule) {
  const Particles& p = st.particles;
  const PairList& q = st.pairs;
  const double particles = static_cast<double>(p.heap_bytes()) / 1024;
  double history = kib(q.i) + kib(q.j) + kib(q.image);
  for_each_pair_field([&](const HistoryLayout&, PairField, const std::vector<double>& values) { history += kib(values); },
                      q);
  const double results = kib(q.contact_force) + kib(q.contact_torque_j) + kib(q.contact_pairs) + kib(q.contact_j);
  const double lists = kib(q.first_i) + kib(q.block_first) +
                       kib(st.neighbor.s_at_build) + kib(st.neighbor.surface_path);
  const Schedule& s = schedule;
  const double scratch = kib(st.blocks) + kib(st.shapes) + kib(s.block_seconds) + kib(s.block_weight) +
                         kib(s.block_cut) + kib(s.block_claimed) + kib(s.thread_busy) + kib(s.owner_first) +
                         kib(s.contact_owner_first);
  return {{"particles", particles},
          {"pair_keys_and_history", history},
          {"pair_results", results},
          {"lists", lists},
          {"scratch", scratch},
          {"total", particles + history + results + lists + scratch}};
}


// What `qsdem bench` steps: the state, the case, and which phase's friction and damping apply.
struct BenchInput {
  State state;
  Params params;
  std::string source;  // "packing" or "checkpoint"
  std::string phase;   // "compaction" or "triaxial"
  std::filesystem::path file;
};

BenchInput bench_input(const std::filesystem::path& source, const std::string& case_path,
                       const std::vector<std::string>& overrides) {
  namespace fs = std::filesystem;
  fs::path file = source;
  if (fs::is_directory(source)) {
    file = source / prepared_sample_file;
    if (!fs::exists(file)) file = source / checkpoint_file;
    if (!fs::exists(file))
      throw InputError(fmt::format("'{}' holds neither {} (a prepared sample) nor {} (an unfinished run)",
                                   source.string(), prepared_sample_file, checkpoint_file));
  } else if (!fs::is_regular_file(source)) {
    throw InputError(fmt::format("'{}': no such packing file, checkpoint or run directory", source.string()));
  }
  BenchInput in;
  in.file = file;
  if (file.extension() != ".qsck") {
    if (case_path.empty())
      throw InputError(fmt::format("'{}' is a packing: give the case it is stepped with (--case)", file.string()));
    in.params = load_case(case_path, overrides);
    in.state = read_packing(file, in.params.material.density);
    in.source = "packing";
    in.phase = in.params.protocol.back().name;
    return in;
  }
  Checkpoint c = load_checkpoint(file);
  const Params own = parse_case(c.case_text, c.case_source, case_path.empty() ? overrides : std::vector<std::string>{});
  check_checkpoint_case(c, own, file.string());
  in.params = case_path.empty() ? own : load_case(case_path, overrides);
  const auto& a = own.material;
  const auto& b = in.params.material;
  // The masses and contacts of the state were made with the checkpoint's material and time step.
  if (a.density != b.density || a.young_modulus != b.young_modulus || a.poisson_ratio != b.poisson_ratio ||
      own.step_ratio != in.params.step_ratio)
    throw InputError(fmt::format("'{}' was made with density {} kg/m^3, E {} Pa, nu {}, time.step_ratio {}; the case "
                                 "has {}, {}, {}, {}: they must be equal",
                                 file.string(), a.density, a.young_modulus, a.poisson_ratio, own.step_ratio, b.density,
                                 b.young_modulus, b.poisson_ratio, in.params.step_ratio));
  in.state = std::move(c.state);
  in.source = "checkpoint";
  in.phase = phase_name(in.params, c.run.phase);
  return in;
}

long contact_count(const State& st) {
  long n = 0;
  for (const ForceBlock& b : st.blocks) n += b.contacts;
  return n;
}

}  // namespace

nlohmann::json bench_packing(const std::filesystem::path& source, const std::string& case_path,
                             const std::vector<std::string>& overrides, long steps, bool as_spheres,
                             std::optional<bool> prefetch_j_ends) {
  BenchInput in = bench_input(source, case_path, overrides);
  State& st = in.state;
  const Params& params = in.params;
  if (as_spheres) {
    State spheres;
    spheres.cell = st.cell;
    const Particles& p = st.particles;
    for (std::size_t i = 0; i < p.size(); ++i)
      spheres.particles.add(p.id[i], ShapeKind::sphere, Vec3::Constant(p.equiv_radius[i]), params.material.density,
                            p.s[i], Quat::Identity());
    st = std::move(spheres);
    in.source = "packing";
  }
  long ellipsoids = 0;
  for (ShapeKind k : st.particles.shape) ellipsoids += k == ShapeKind::ellipsoid;
  // The phase's friction and damping in a fixed cell: a peer code runs the same physics on the
  // same packing in a fixed periodic box.
  const Phase& phase = *std::find_if(params.protocol.begin(), params.protocol.end(),
                                     [&](const Phase& p) { return p.name == in.phase; });
  Model model = phase_model(params, phase, phase.controls, st.particles, st.cell.h);
  for (auto& c : model.control) c = {};
  assign_damping(model, st.particles);
  model.prefetch_j_ends = prefetch_j_ends;
  // A packing's first list build is set-up, not stepping (LIGGGHTS' loop time leaves its own
  // out); at rest it changes no history. A checkpoint's list and history are stepped as they are.
  // The threads are started first: a run's rebuilds find them running, so first_build_s is the
  // cost of a rebuild, not of the threads' creation.
#pragma omp parallel
  {
  }
  if (in.source == "packing") evaluate_forces(model, st);
  const double first_build = st.timers.seconds[static_cast<std::size_t>(Stage::neighbor)];
  st.timers = {};
  const long builds_before = st.neighbor.builds;
  long narrow_tests = 0, pw_iterations = 0, contacts_start = 0;
  double wall = 0;
  Schedule schedule;
  for (long n = 0; n < steps; ++n) {
    const auto t0 = std::chrono::steady_clock::now();
    step(model, st, schedule);
    wall += std::chrono::duration<double>(std::chrono::steady_clock::now() - t0).count();
    if (n == 0) contacts_start = contact_count(st);  // at the first step's force evaluation
    narrow_tests += st.narrow_tests;
    pw_iterations += st.pw_iterations;
  }
  const Measures m = measure(st);
  const double np = static_cast<double>(st.particles.size());
  return {{"source", in.source},
          {"file", in.file.string()},
          {"phase", in.phase},
          {"particles", st.particles.size()},
          {"ellipsoids", ellipsoids},
          {"contacts_start", contacts_start},
          {"contacts_end", m.contacts},
          {"pairs", st.pairs.size()},
          {"narrow_tests_per_step", static_cast<double>(narrow_tests) / static_cast<double>(std::max(1L, steps))},
          {"pw_iterations_per_step", static_cast<double>(pw_iterations) / static_cast<double>(std::max(1L, steps))},
          // whether the pair loops fetched the j ends ahead, and whether the engine would by itself
          {"prefetch_j_ends",
           {{"used", prefetches_j_ends(model, st.particles)},
            {"engine_choice", beyond_cache(st.particles)}}},
          {"ekin_J", m.ekin_trans + m.ekin_rot},
          {"ekin_trans_J", m.ekin_trans},
          {"steps", steps},
          {"threads", omp_get_max_threads()},
          {"wall_s", wall},
          {"particle_steps_per_s", np * static_cast<double>(steps) / wall},
          // mean / largest thread time in the force stage (1: balanced; null on one thread)
          {"force_stage_balance", st.timers.force_thread_max > 0
                                      ? nlohmann::json(st.timers.force_thread_mean / st.timers.force_thread_max)
                                      : nlohmann::json(nullptr)},
          {"peak_rss_kib", peak_rss_kib()},
          {"state_kib", memory_kib(st, schedule)},
          {"dt_s", model.dt},
          {"density_kg_m3", model.material.density},
          {"young_modulus_Pa", model.material.young_modulus},
          {"poisson_ratio", model.material.poisson_ratio},
          {"friction", phase.friction},
          {"damping_model", phase.damping.model},
          {"damping_ratio", phase.damping.ratio},
          {"neighbor_builds", st.neighbor.builds - builds_before},
          // a packing's set-up build (sort and list), the cost of one rebuild from scratch
          {"first_build_s", in.source == "packing" ? nlohmann::json(first_build) : nlohmann::json(nullptr)},
          {"stages", stage_json(st.timers, steps)}};
}

}  // namespace qsdem
