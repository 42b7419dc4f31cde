#include "qsdem/run.hpp"

#include <fmt/format.h>
#include <omp.h>
#include <sys/resource.h>

#include <algorithm>
#include <chrono>
#include <csignal>
#include <cstdio>

#include "qsdem/checkpoint.hpp"
#include "qsdem/generate.hpp"
#include "qsdem/measures.hpp"
#include "qsdem/packing_io.hpp"
#include "qsdem/protocol.hpp"
#include "qsdem/step.hpp"
#include "qsdem/vtk.hpp"

namespace qsdem {
namespace {

nlohmann::json stage_json(const StageTimers& t, long steps) {
  nlohmann::json j = nlohmann::json::object();
  for (std::size_t k = 0; k < t.seconds.size(); ++k)
    j[stage_names[k]] = {{"seconds", t.seconds[k]},
                         {"us_per_step", steps > 0 ? 1e6 * t.seconds[k] / static_cast<double>(steps) : 0.0}};
  return j;
}

// Peak resident set of this process (KiB): VmHWM of /proc/self/status, which starts afresh at
// exec. getrusage's ru_maxrss does not: Linux carries the larger peak of the process image before
// exec over, so when launched by a bigger parent (a Python harness: 75 MB measured against 15 MB
// from a shell) it reported the parent's. getrusage only where /proc is not readable.
long peak_rss_kib() {
  if (std::FILE* f = std::fopen("/proc/self/status", "r")) {
    char line[256];
    long kib = -1;
    while (std::fgets(line, sizeof line, f))
      if (std::sscanf(line, "VmHWM: %ld kB", &kib) == 1) break;
    std::fclose(f);
    if (kib >= 0) return kib;
  }
  rusage u{};
  getrusage(RUSAGE_SELF, &u);
  return u.ru_maxrss;
}

nlohmann::json measures_json(const Measures& m) {
  return {{"p_Pa", m.mean_stress},  {"q_Pa", m.deviator},       {"s11_Pa", m.stress(0, 0)},
          {"s22_Pa", m.stress(1, 1)}, {"s33_Pa", m.stress(2, 2)}, {"void_ratio", m.void_ratio},
          {"ufr", m.ufr},           {"iuf", m.iuf},             {"imom", m.imom},
          {"cn", m.coordination},   {"contacts", m.contacts},  {"ekin_J", m.ekin_trans + m.ekin_rot}};
}

volatile std::sig_atomic_t stop_signal = 0;

extern "C" void on_stop_signal(int sig) { stop_signal = sig; }

// SIGINT and SIGTERM ask the step loop to checkpoint and stop; the old handlers come back after.
class SignalGuard {
 public:
  SignalGuard() {
    stop_signal = 0;
    struct sigaction sa {};
    sa.sa_handler = on_stop_signal;
    sigemptyset(&sa.sa_mask);
    sigaction(SIGINT, &sa, &old_int_);
    sigaction(SIGTERM, &sa, &old_term_);
  }
  ~SignalGuard() {
    sigaction(SIGINT, &old_int_, nullptr);
    sigaction(SIGTERM, &old_term_, nullptr);
  }
  SignalGuard(const SignalGuard&) = delete;
  SignalGuard& operator=(const SignalGuard&) = delete;

 private:
  struct sigaction old_int_ {}, old_term_ {};
};

nlohmann::json size_table_json(const Params& params) {
  nlohmann::json counts = nlohmann::json::array();
  const auto table = resolve_table(params.sample);
  double solid = 0;
  for (const auto& c : table) solid += static_cast<double>(c.count) * ellipsoid_volume(c.semi_axes);
  for (const auto& c : table)
    counts.push_back({{"shape", to_string(c.shape)},
                      {"semi_axes_m", {c.semi_axes.x(), c.semi_axes.y(), c.semi_axes.z()}},
                      {"count", c.count},
                      {"mass_fraction", static_cast<double>(c.count) * ellipsoid_volume(c.semi_axes) / solid}});
  return counts;
}

// Refuses to overwrite results unless forced; with force, removes what a new run would leave stale.
void prepare_directory(const std::filesystem::path& dir, bool force) {
  namespace fs = std::filesystem;
  fs::create_directories(dir);
  const bool finished = fs::exists(dir / "summary.json");
  const bool unfinished = fs::exists(dir / checkpoint_file);
  if (!force && finished)
    throw InputError(fmt::format("'{}' holds a finished run (summary.json): choose another --out or add --force",
                                 dir.string()));
  if (!force && unfinished)
    throw InputError(fmt::format("'{}' holds an unfinished run: continue it with `qsdem resume {}`, or add --force to "
                                 "start over",
                                 dir.string(), dir.string()));
  for (const char* f : {"summary.json", "series.csv", "series.csv.partial", "compaction.csv", "compaction.csv.partial",
                        "compacted.packing", "final.packing", checkpoint_file, "checkpoint.qsck.prev",
                        prepared_sample_file})
    fs::remove(dir / f);
  fs::remove_all(dir / "vtk");
}

// Snapshot k (0: the compacted sample, k: after row k of series.csv) and the .pvd of all snapshots
// on disk, whose time is each snapshot's nominal axial strain (so a resumed run rebuilds it).
void write_snapshot(const std::filesystem::path& dir, const Params& params, const State& st, long k) {
  namespace fs = std::filesystem;
  const fs::path vtk = dir / "vtk";
  fs::create_directories(vtk);
  write_vtu(vtk / fmt::format("snapshot-{:04}.vtu", k), st);
  std::vector<std::pair<long, fs::path>> files;
  for (const auto& e : fs::directory_iterator(vtk)) {
    const std::string name = e.path().filename().string();
    if (name.size() == 17 && name.rfind("snapshot-", 0) == 0 && e.path().extension() == ".vtu")
      files.emplace_back(std::stol(name.substr(9, 4)), e.path().filename());
  }
  std::sort(files.begin(), files.end());
  std::vector<PvdEntry> entries;
  const double strain_per_row = params.triaxial.final_axial_strain / params.triaxial.sample_points;
  for (const auto& [row, file] : files) entries.push_back({static_cast<double>(row) * strain_per_row, file});
  write_pvd(vtk / "series.pvd", entries);
}

// Everything after the sample exists: the phases from wherever `run` stands, checkpoints, results.
nlohmann::json execute(const Params& params, State& st, RunProgress& run, const RunOptions& options,
                       const std::string& note) {
  namespace fs = std::filesystem;
  const auto t0 = std::chrono::steady_clock::now();
  const fs::path dir = options.out;
  Progress progress(Progress::detect(options.quiet));
  const SignalGuard signals;
  const double wall_before = run.wall_s;
  auto session_s = [&] { return std::chrono::duration<double>(std::chrono::steady_clock::now() - t0).count(); };
  auto last_save = std::chrono::steady_clock::now();
  auto save = [&](const fs::path& file) {
    run.wall_s = wall_before + session_s();
    ScopedStage t(st.timers, Stage::output);
    save_checkpoint(file, params.case_text, params.source, st, run);
    last_save = std::chrono::steady_clock::now();
  };
  // After every step: stop on a signal, checkpoint every N sample points or M minutes.
  const StepHook hook = [&](bool sample_point) {
    if (stop_signal != 0) {
      const int sig = stop_signal;
      save(dir / checkpoint_file);
      throw Interrupted(fmt::format("stopped by {} at step {}; checkpoint written: continue with `qsdem resume {}`",
                                    sig == SIGINT ? "SIGINT" : "SIGTERM", st.step, dir.string()),
                        sig);
    }
    const auto& c = params.checkpoint;
    const bool by_points = sample_point && c.every_sample_points > 0 && run.rows % c.every_sample_points == 0;
    const bool by_time =
        c.every_minutes > 0 &&
        std::chrono::duration<double>(std::chrono::steady_clock::now() - last_save).count() > 60 * c.every_minutes;
    if (by_points || by_time) save(dir / checkpoint_file);
    const int vtk = params.output.vtk_every;
    if (sample_point && vtk > 0 && run.phase == RunProgress::Phase::triaxial && run.rows % vtk == 0)
      write_snapshot(dir, params, st, run.rows);
  };

  const Model m0 = compaction_model(params, st);
  if (run.phase == RunProgress::Phase::compaction) {
    SeriesWriter log(dir / "compaction.csv", run.phase_started ? run.rows : -1);
    compact(params, st, run, progress, &log, hook);
    log.commit();
    write_packing(dir / "compacted.packing", st.particles, st.cell);
    if (params.output.vtk_every > 0) write_snapshot(dir, params, st, 0);
    run.phase = RunProgress::Phase::triaxial;
    run.phase_started = false;
    run.phase_steps = 0;
    run.rows = 0;
    if (options.prepare_only) {
      save(dir / prepared_sample_file);
    } else {
      save(dir / checkpoint_file);
    }
  }
  TriaxialResult tri;
  if (!options.prepare_only && run.phase == RunProgress::Phase::triaxial) {
    SeriesWriter series(dir / "series.csv", run.phase_started ? run.rows : -1);
    tri = shear(params, st, run, series, progress, hook);
    series.commit();
    write_packing(dir / "final.packing", st.particles, st.cell);
    if (params.output.vtk_every > 0 && run.rows % params.output.vtk_every == 0) write_snapshot(dir, params, st, run.rows);
    run.phase = RunProgress::Phase::done;
  }

  const double wall = wall_before + session_s();
  const long own_steps = st.step - run.first_step;  // steps this run took (not a prepared sample's)
  const double particle_steps = static_cast<double>(own_steps) * static_cast<double>(st.particles.size());
  const CompactionResult& comp = run.compaction;
  nlohmann::json s;
  s["version"] = QSDEM_VERSION;
  s["case"] = params.name;
  s["config"] = {{"resolved_si", to_json(params)}, {"as_written", params.as_written}};
  s["derived"] = {{"particles", st.particles.size()},
                  {"size_table", params.sample.from.empty() ? size_table_json(params) : nlohmann::json()},
                  {"sample_from", params.sample.from},
                  {"r_min_m", m0.r_min},
                  {"critical_time_s", m0.critical_time},
                  {"dt_s", m0.dt},
                  {"threads", omp_get_max_threads()},
                  {"triaxial_strain_rate_per_s", params.triaxial.strain_rate / m0.critical_time}};
  if (!note.empty()) s["note"] = note;
  s["compaction"] = {{"steps", comp.steps}, {"wall_s", comp.wall_s}, {"final", measures_json(comp.final)}};
  s["void_ratio_after_compaction"] = comp.final.void_ratio;
  if (!options.prepare_only) {
    s["triaxial"] = {{"steps", tri.steps},
                     {"rows", tri.rows},
                     {"wall_s", tri.wall_s},
                     {"final_e1", tri.final_e1},
                     {"max_lateral_stress_error", tri.max_lateral_stress_error},
                     {"mean_lateral_stress_error", tri.mean_lateral_stress_error}};
    s["mean_ufr"] = tri.mean_ufr;
    s["mean_iuf"] = tri.mean_iuf;
    s["mean_imom"] = tri.mean_imom;
    s["peak_phi_deg"] = tri.peak_phi_deg;
    s["peak_phi_e1"] = tri.peak_phi_e1;
    s["final_ev"] = tri.final_ev;
  }
  s["steps"] = own_steps;
  s["steps_cover"] = run.first_step == 0 ? (options.prepare_only ? "compaction" : "compaction + triaxial")
                                         : "triaxial of a prepared sample";
  s["wall_s"] = wall;
  s["particle_steps_per_s"] = particle_steps / std::max(wall, 1e-9);
  s["neighbor_builds"] = st.neighbor.builds;
  s["peak_rss_kib"] = peak_rss_kib();
  s["stages"] = stage_json(st.timers, own_steps);
  s["stage_table"] = format_stage_table(st.timers, own_steps);
  write_file_atomic(dir / "summary.json", s.dump(2) + "\n");
  // A finished run needs no checkpoint; a prepared sample keeps sample.qsck.
  fs::remove(dir / checkpoint_file);
  fs::remove(dir / "checkpoint.qsck.prev");
  return s;
}

// The sample named by sample.from: a prepared sample (directory of `qsdem prepare`, which skips
// compaction) or a packing file (which is compacted).
State load_sample(const Params& params, RunProgress& run) {
  namespace fs = std::filesystem;
  const fs::path from = params.sample.from;
  if (fs::is_directory(from)) {
    Checkpoint c = load_checkpoint(from / prepared_sample_file);
    const Params prepared = parse_case(c.case_text, c.case_source);
    const auto& a = prepared.material;
    const auto& b = params.material;
    if (a.density != b.density || a.young_modulus != b.young_modulus || a.poisson_ratio != b.poisson_ratio ||
        prepared.step_ratio != params.step_ratio)
      throw InputError(fmt::format(
          "sample.from = '{}': that sample was prepared with density {} kg/m^3, E {} Pa, nu {}, time.step_ratio {}; "
          "this case has {}, {}, {}, {}: they must be equal",
          from.string(), a.density, a.young_modulus, a.poisson_ratio, prepared.step_ratio, b.density, b.young_modulus,
          b.poisson_ratio, params.step_ratio));
    if (c.run.phase != RunProgress::Phase::triaxial || c.run.phase_started)
      throw InputError(fmt::format("sample.from = '{}': {} is not a sample at the end of compaction", from.string(),
                                   prepared_sample_file));
    run = c.run;
    run.wall_s = 0;
    run.first_step = c.state.step;  // its compaction steps and time are the sample's, not this run's
    c.state.timers = {};
    return std::move(c.state);
  }
  if (!fs::is_regular_file(from))
    throw InputError(fmt::format("sample.from = '{}': no such prepared sample directory or packing file",
                                 from.string()));
  return read_packing(from, params.material.density);
}

}  // namespace

nlohmann::json run_case(const Params& params, const RunOptions& options) {
  prepare_directory(options.out, options.force);
  write_file_atomic(options.out / "case.toml", params.case_text);
  RunProgress run;
  State st = params.sample.from.empty() ? generate_loose_sample(params) : load_sample(params, run);
  return execute(params, st, run, options, "");
}

nlohmann::json resume_run(const std::filesystem::path& dir, const RunOptions& options) {
  if (std::filesystem::exists(dir / "summary.json") && !std::filesystem::exists(dir / checkpoint_file))
    throw InputError(fmt::format("'{}' holds a finished run: nothing to resume", dir.string()));
  std::string note;
  Checkpoint c = load_latest_checkpoint(dir / checkpoint_file, &note);
  if (!note.empty()) std::fprintf(stderr, "qsdem: %s\n", note.c_str());
  const Params params = parse_case(c.case_text, c.case_source);
  RunOptions o = options;
  o.out = dir;
  return execute(params, c.state, c.run, o, note);
}

std::string format_run_table(const nlohmann::json& s) {
  std::string out;
  auto row = [&](const std::string& name, const std::string& value) {
    out += fmt::format("| {:<38} | {:>14} |\n", name, value);
  };
  row("quantity", "value");
  out += fmt::format("|{:-<40}|{:->16}|\n", "", "");
  row("particles", fmt::format("{}", s["derived"]["particles"].get<long>()));
  row("void ratio after compaction", fmt::format("{:.4f}", s["void_ratio_after_compaction"].get<double>()));
  if (s.contains("triaxial")) {
    row("peak friction angle (deg)", fmt::format("{:.2f}", s["peak_phi_deg"].get<double>()));
    row("mean UFR", fmt::format("{:.4g}", s["mean_ufr"].get<double>()));
    row("mean IMom", fmt::format("{:.4g}", s["mean_imom"].get<double>()));
    row("max lateral stress error", fmt::format("{:.3g} %", 100 * s["triaxial"]["max_lateral_stress_error"].get<double>()));
  }
  row("steps (" + s["steps_cover"].get<std::string>() + ")", fmt::format("{}", s["steps"].get<long>()));
  row("wall time (s)", fmt::format("{:.1f}", s["wall_s"].get<double>()));
  row("particle-steps per second", fmt::format("{:.4g}", s["particle_steps_per_s"].get<double>()));
  return out;
}

namespace {

template <class T>
double kib(const std::vector<T>& v) {
  return static_cast<double>(v.capacity() * sizeof(T)) / 1024;
}

// Heap held by the state's arrays (KiB), by structure: what `peak_rss_kib` is made of besides
// the binary, its libraries and transient build buffers.
nlohmann::json memory_kib(const State& st, const Schedule& schedule) {
  const Particles& p = st.particles;
  const PairList& q = st.pairs;
  double particles = 0;
  for_each_field(p, [&](const auto& array, ParticleField) { particles += kib(array); });
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

}  // namespace

nlohmann::json bench_packing(const Params& params, const std::filesystem::path& packing, long steps,
                             bool as_spheres) {
  State st = read_packing(packing, params.material.density);
  if (as_spheres) {
    State spheres;
    spheres.cell = st.cell;
    const Particles& p = st.particles;
    for (std::size_t i = 0; i < p.size(); ++i)
      spheres.particles.add(p.id[i], ShapeKind::sphere, Vec3::Constant(p.equiv_radius[i]), params.material.density,
                            p.s[i], Quat::Identity());
    st = std::move(spheres);
  }
  long ellipsoids = 0;
  for (ShapeKind k : st.particles.shape) ellipsoids += k == ShapeKind::ellipsoid;
  // The triaxial phase's friction and damping in a fixed cell: the same physics a peer code runs
  // on the same packing in a fixed periodic box.
  Model model = triaxial_model(params, st);
  for (auto& c : model.control) c = {};
  assign_damping(model, st.particles);
  evaluate_forces(model, st);
  st.timers = {};
  const auto t0 = std::chrono::steady_clock::now();
  long narrow_tests = 0, pw_iterations = 0;
  Schedule schedule;
  for (long n = 0; n < steps; ++n) {
    step(model, st, schedule);
    narrow_tests += st.narrow_tests;
    pw_iterations += st.pw_iterations;
  }
  const double wall = std::chrono::duration<double>(std::chrono::steady_clock::now() - t0).count();
  const Measures m = measure(st);
  const double np = static_cast<double>(st.particles.size());
  return {{"particles", st.particles.size()},
          {"ellipsoids", ellipsoids},
          {"contacts", m.contacts},
          {"pairs", st.pairs.size()},
          {"narrow_tests_per_step", static_cast<double>(narrow_tests) / static_cast<double>(std::max(1L, steps))},
          {"pw_iterations_per_step", static_cast<double>(pw_iterations) / static_cast<double>(std::max(1L, steps))},
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
          {"friction", model.friction},
          {"neighbor_builds", st.neighbor.builds},
          {"stages", stage_json(st.timers, steps)}};
}

}  // namespace qsdem
