#include "qsdem/run.hpp"

#include <fmt/format.h>
#include <omp.h>
#include <sys/resource.h>

#include <chrono>

#include "qsdem/generate.hpp"
#include "qsdem/measures.hpp"
#include "qsdem/packing_io.hpp"
#include "qsdem/protocol.hpp"
#include "qsdem/step.hpp"

namespace qsdem {
namespace {

nlohmann::json stage_json(const StageTimers& t, long steps) {
  nlohmann::json j = nlohmann::json::object();
  for (std::size_t k = 0; k < t.seconds.size(); ++k)
    j[stage_names[k]] = {{"seconds", t.seconds[k]},
                         {"us_per_step", steps > 0 ? 1e6 * t.seconds[k] / static_cast<double>(steps) : 0.0}};
  return j;
}

long peak_rss_kib() {
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

}  // namespace

nlohmann::json run_case(const Params& params, const RunOptions& options) {
  const auto t0 = std::chrono::steady_clock::now();
  std::filesystem::create_directories(options.out);
  Progress progress(Progress::detect(options.quiet));

  State st = generate_loose_sample(params);
  check_supported(st);
  const Model m0 = compaction_model(params, st);

  SeriesWriter compaction_log(options.out / "compaction.csv");
  const CompactionResult comp = compact(params, st, progress, &compaction_log);
  compaction_log.commit();
  write_packing(options.out / "compacted.packing", st.particles, st.cell);

  TriaxialResult tri;
  if (!options.prepare_only) {
    SeriesWriter series(options.out / "series.csv");
    tri = shear(params, st, series, progress);
    series.commit();
    write_packing(options.out / "final.packing", st.particles, st.cell);
  }

  const double wall = std::chrono::duration<double>(std::chrono::steady_clock::now() - t0).count();
  const double particle_steps = static_cast<double>(st.step) * static_cast<double>(st.particles.size());

  nlohmann::json counts = nlohmann::json::array();
  double solid = 0;
  for (const auto& c : resolve_table(params.sample)) solid += static_cast<double>(c.count) * ellipsoid_volume(c.semi_axes);
  for (const auto& c : resolve_table(params.sample))
    counts.push_back({{"shape", to_string(c.shape)},
                      {"semi_axes_m", {c.semi_axes.x(), c.semi_axes.y(), c.semi_axes.z()}},
                      {"count", c.count},
                      {"mass_fraction", static_cast<double>(c.count) * ellipsoid_volume(c.semi_axes) / solid}});

  nlohmann::json s;
  s["version"] = QSDEM_VERSION;
  s["case"] = params.name;
  s["config"] = {{"resolved_si", to_json(params)}, {"as_written", params.as_written}};
  s["derived"] = {{"particles", st.particles.size()},
                  {"size_table", counts},
                  {"r_min_m", m0.r_min},
                  {"critical_time_s", m0.critical_time},
                  {"dt_s", m0.dt},
                  {"threads", omp_get_max_threads()},
                  {"triaxial_strain_rate_per_s", params.triaxial.strain_rate / m0.critical_time}};
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
  s["steps"] = st.step;
  s["wall_s"] = wall;
  s["particle_steps_per_s"] = particle_steps / wall;
  s["neighbor_builds"] = st.neighbor.builds;
  s["peak_rss_kib"] = peak_rss_kib();
  s["stages"] = stage_json(st.timers, st.step);
  s["stage_table"] = format_stage_table(st.timers, st.step);
  write_file_atomic(options.out / "summary.json", s.dump(2) + "\n");
  return s;
}

std::string format_run_table(const nlohmann::json& s) {
  std::string out;
  auto row = [&](const char* name, const std::string& value) { out += fmt::format("| {:<38} | {:>14} |\n", name, value); };
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
  row("steps (compaction + triaxial)", fmt::format("{}", s["steps"].get<long>()));
  row("wall time (s)", fmt::format("{:.1f}", s["wall_s"].get<double>()));
  row("particle-steps per second", fmt::format("{:.4g}", s["particle_steps_per_s"].get<double>()));
  return out;
}

nlohmann::json bench_packing(const Params& params, const std::filesystem::path& packing, long steps) {
  State st = read_packing(packing, params.material.density);
  check_supported(st);
  // The triaxial phase's friction and damping in a fixed cell: the same physics a peer code runs
  // on the same packing in a fixed periodic box.
  Model model = triaxial_model(params, st);
  for (auto& c : model.control) c = {};
  assign_damping(model, st.particles);
  evaluate_forces(model, st);
  st.timers = {};
  const auto t0 = std::chrono::steady_clock::now();
  for (long n = 0; n < steps; ++n) step(model, st);
  const double wall = std::chrono::duration<double>(std::chrono::steady_clock::now() - t0).count();
  const Measures m = measure(st);
  const double np = static_cast<double>(st.particles.size());
  return {{"particles", st.particles.size()},
          {"contacts", m.contacts},
          {"pairs", st.pairs.size()},
          {"ekin_J", m.ekin_trans + m.ekin_rot},
          {"ekin_trans_J", m.ekin_trans},
          {"steps", steps},
          {"threads", omp_get_max_threads()},
          {"wall_s", wall},
          {"particle_steps_per_s", np * static_cast<double>(steps) / wall},
          {"peak_rss_kib", peak_rss_kib()},
          {"dt_s", model.dt},
          {"density_kg_m3", model.material.density},
          {"young_modulus_Pa", model.material.young_modulus},
          {"poisson_ratio", model.material.poisson_ratio},
          {"friction", model.friction},
          {"neighbor_builds", st.neighbor.builds},
          {"stages", stage_json(st.timers, steps)}};
}

}  // namespace qsdem
