#include "qsdem/run/summary.hpp"

#include <fmt/format.h>
#include <omp.h>
#include <sys/resource.h>

#include <algorithm>
#include <cmath>
#include <cstdio>
#include <memory>
#include <optional>
#include <sstream>

#include "qsdem/engine/model.hpp"
#include "qsdem/run/controller.hpp"
#include "qsdem/run/generate.hpp"
#include "qsdem/run/grading.hpp"
#include "qsdem/run/output.hpp"
#include "qsdem/version.hpp"

namespace qsdem {
namespace {

nlohmann::json measures_json(const Measures& m) {
  return {{"p_Pa", m.mean_stress},  {"q_Pa", m.deviator},       {"s11_Pa", m.stress(0, 0)},
          {"s22_Pa", m.stress(1, 1)}, {"s33_Pa", m.stress(2, 2)}, {"void_ratio", m.void_ratio},
          {"ufr", m.ufr},           {"iuf", m.iuf},             {"imom", m.imom},
          {"cn", m.coordination},   {"contacts", m.contacts},  {"ekin_J", m.ekin_trans + m.ekin_rot}};
}

// The common target (Pa) of the three normal components of a phase that holds them all at one
// stress, else none. "Equal" allows for unit conversion's rounding ("400 kPa" and "0.4 MPa").
std::optional<double> isotropic_target(const Phase& phase) {
  const auto& c = phase.controls.component;
  for (std::size_t k = 0; k < 3; ++k)
    if (c[k].kind != ControlKind::stress || std::abs(c[k].value - c[0].value) > 1e-9 * std::abs(c[0].value))
      return std::nullopt;
  return c[0].value;
}

// Phase p as an isotropic branch (docs/loading-paths.md): a phase after the first with an isotropic
// target, from the end of the phase before to its own end; null for any other phase. Compression
// positive: volume_strain = -(V_end - V_start)/V_start, the secant bulk modulus dp/volume_strain;
// a branch back to the start stress (within 1 %) of the isotropic branch before it also gives the
// volume strain the pair of branches leaves (the hysteresis of a load-unload cycle).
nlohmann::json isotropic_branch(const Protocol& protocol, const std::vector<PhaseRecord>& records, std::size_t p) {
  const std::optional<double> target = isotropic_target(protocol[p]);
  if (p == 0 || !target) return nullptr;
  const Measures &start = records[p - 1].final, &end = records[p].final;
  const double volume_strain = -(end.volume - start.volume) / start.volume;
  nlohmann::json j = {{"p_start_Pa", start.mean_stress}, {"p_end_Pa", end.mean_stress}, {"volume_strain", volume_strain}};
  if (volume_strain != 0) j["bulk_modulus_Pa"] = (end.mean_stress - start.mean_stress) / volume_strain;
  if (p >= 2 && isotropic_target(protocol[p - 1])) {
    const Measures& before = records[p - 2].final;  // the start of the branch before
    if (std::abs(*target - before.mean_stress) <= 0.01 * before.mean_stress)
      j["residual_volume_strain"] = -(end.volume / before.volume - 1);
  }
  return j;
}

// The figures of phase p, which has ended; `records`: those of the protocol's phases; with
// `energy`, the change of the energy ledger over the phase (docs/physics.md 12).
nlohmann::json phase_figures(const Protocol& protocol, const std::vector<PhaseRecord>& records, std::size_t p,
                             bool energy) {
  const Phase& phase = protocol[p];
  const PhaseRecord& r = records[p];
  const double rows = static_cast<double>(std::max(1L, r.rows));
  int normal_targets = 0;
  for (int c = 0; c < 3; ++c)
    normal_targets += phase.controls.component[static_cast<std::size_t>(c)].kind == ControlKind::stress;
  nlohmann::json j = {{"name", phase.name},
                      {"file", phase.output.file},
                      {"steps", r.steps},
                      {"rows", r.rows},
                      {"wall_s", r.wall_s},
                      {"mean_ufr", r.ufr / rows},
                      {"mean_iuf", r.iuf / rows},
                      {"mean_imom", r.imom / rows},
                      {"peak_phi_deg", r.peak_phi_deg},
                      {"peak_phi_e1", r.peak_phi_e1},
                      {"final_e1", r.final_e1},
                      {"final_ev", r.final_ev},
                      {"max_stress_error", r.max_stress_error},
                      {"mean_stress_error", normal_targets > 0 ? r.stress_error / (normal_targets * rows) : 0.0},
                      {"max_shear_stress", r.max_shear_stress},
                      {"final", measures_json(r.final)}};
  if (nlohmann::json iso = isotropic_branch(protocol, records, p); !iso.is_null()) j["isotropic"] = iso;
  if (energy) j["energy"] = energy_change(r.energy_start, r.energy_end);
  return j;
}

// The size table of a generated sample: each class's shape, semi-axes, count and mass fraction.
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

// Phase p, which has ended, as summary.json's `phases` entry. `records`: those of the protocol's
// phases; `controller`: the phase's controller's state at its end (RunProgress::controller_end),
// or none; `energy`: the run keeps the energy ledger (output.energy).
nlohmann::json phase_json(const Protocol& protocol, const std::vector<PhaseRecord>& records, std::size_t p,
                          const std::vector<double>* controller, bool energy) {
  const Phase& phase = protocol[p];
  nlohmann::json j = phase_figures(protocol, records, p, energy);
  if (phase.make_controller && controller && !controller->empty()) {
    const std::unique_ptr<Controller> c = phase.make_controller();
    c->restore(*controller);
    if (nlohmann::json f = c->figures(); !f.empty()) j["controller"] = f;
  }
  return j;
}

// The state of phase p's controller at its end (RunProgress::controller_end), or none.
const std::vector<double>* controller_end(const RunProgress& run, std::size_t p) {
  return p < run.controller_end.size() ? &run.controller_end[p] : nullptr;
}

// What a run's steps cover, by the phases' names: "compaction + triaxial", "compaction" (a
// prepared sample) or "triaxial of a prepared sample".
std::string steps_cover(const Protocol& protocol, const RunProgress& run) {
  const std::size_t first = run.first_step == 0 ? 0 : 1, last = run.prepare_only ? 1 : protocol.size();
  std::string names;
  for (std::size_t p = first; p < last; ++p) names += (names.empty() ? "" : " + ") + protocol[p].name;
  return first == 0 ? names : names + " of a prepared sample";
}

}  // namespace

nlohmann::json run_summary(const Params& params, const State& st, const RunProgress& run, double wall,
                           const std::string& note) {
  const double r_min = smallest_equiv_radius(st.particles);
  const double t_c =
      critical_time({params.material.density, params.material.young_modulus, params.material.poisson_ratio}, r_min);
  const long own_steps = st.step - run.first_step;  // steps this run took (not a prepared sample's)
  const double particle_steps = static_cast<double>(own_steps) * static_cast<double>(st.particles.size());
  nlohmann::json s;
  s["version"] = QSDEM_VERSION;
  s["build"] = build_record();
  s["builds"] = nlohmann::json::array();
  for (const std::string& b : run.builds) s["builds"].push_back(nlohmann::json::parse(b));
  s["case"] = params.name;
  s["config"] = {{"resolved_si", to_json(params)}, {"as_written", params.as_written}};
  s["derived"] = {{"particles", st.particles.size()},
                  {"size_table", params.sample.from.empty() && params.sample.grading.empty() ? size_table_json(params)
                                                                                             : nlohmann::json()},
                  {"sample_from", params.sample.from},
                  {"r_min_m", r_min},
                  {"critical_time_s", t_c},
                  {"dt_s", params.step_ratio * t_c},
                  {"threads", omp_get_max_threads()}};
  if (params.sample.from.empty() && !params.sample.grading.empty())
    s["derived"]["grading"] = grading_json(params.sample.grading, params.sample.total_particles, params.sample.seed);
  if (const double rate = fastest_strain_rate(params.protocol.back()); rate > 0)
    s["derived"]["triaxial_strain_rate_per_s"] = rate / t_c;
  if (!note.empty()) s["note"] = note;
  if (!run.changes.empty()) {
    nlohmann::json changes = nlohmann::json::array();
    std::istringstream lines(run.changes);
    for (std::string line; std::getline(lines, line);) changes.push_back(line);
    s["resume_changes"] = changes;
  }
  nlohmann::json phases = nlohmann::json::array();
  for (std::size_t p = 0; p < params.protocol.size() && p < static_cast<std::size_t>(run.phase); ++p)
    phases.push_back(phase_json(params.protocol, run.phases, p, controller_end(run, p), params.output.energy));
  s["phases"] = phases;
  // The first phase as the sample's compaction; the last, when it is another, as the test.
  const PhaseRecord& first = run.phases.front();
  s["compaction"] = {{"steps", first.steps}, {"wall_s", first.wall_s}, {"final", measures_json(first.final)}};
  s["void_ratio_after_compaction"] = first.final.void_ratio;
  if (!run.prepare_only && run.phases.size() > 1) {
    const nlohmann::json last =
        phase_json(params.protocol, run.phases, run.phases.size() - 1, controller_end(run, run.phases.size() - 1),
                   params.output.energy);
    s["triaxial"] = {{"steps", last["steps"]},
                     {"rows", last["rows"]},
                     {"wall_s", last["wall_s"]},
                     {"final_e1", last["final_e1"]},
                     {"max_lateral_stress_error", last["max_stress_error"]},
                     {"mean_lateral_stress_error", last["mean_stress_error"]},
                     {"max_shear_stress", last["max_shear_stress"]}};
    if (last.contains("controller")) s["triaxial"]["controller"] = last["controller"];
    for (const char* key : {"mean_ufr", "mean_iuf", "mean_imom", "peak_phi_deg", "peak_phi_e1", "final_ev"})
      s[key] = last[key];
  }
  s["steps"] = own_steps;
  s["steps_cover"] = steps_cover(params.protocol, run);
  s["wall_s"] = wall;
  s["particle_steps_per_s"] = particle_steps / std::max(wall, 1e-9);
  s["neighbor_builds"] = st.neighbor.builds;
  s["peak_rss_kib"] = peak_rss_kib();
  s["stages"] = stage_json(st.timers, own_steps);
  s["stage_table"] = format_stage_table(st.timers, own_steps);
  return s;
}

nlohmann::json stage_json(const StageTimers& t, long steps) {
  nlohmann::json j = nlohmann::json::object();
  for (std::size_t k = 0; k < t.seconds.size(); ++k)
    j[stage_names[k]] = {{"seconds", t.seconds[k]},
                         {"us_per_step", steps > 0 ? 1e6 * t.seconds[k] / static_cast<double>(steps) : 0.0}};
  return j;
}

// VmHWM of /proc/self/status, which starts afresh at exec. getrusage's ru_maxrss does not: Linux
// carries the larger peak of the process image before exec over, so when launched by a bigger
// parent it reported the parent's. getrusage only where /proc is not readable.
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

nlohmann::json build_record() {
  const std::string commit = QSDEM_COMMIT;
  const int clean = QSDEM_TREE_CLEAN;
  return {{"version", QSDEM_VERSION},
          {"commit", commit.empty() ? nlohmann::json() : nlohmann::json(commit)},
          {"tree_clean", clean < 0 ? nlohmann::json() : nlohmann::json(clean == 1)}};
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

}  // namespace qsdem
