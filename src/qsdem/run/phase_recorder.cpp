#include "qsdem/run/phase_recorder.hpp"

#include <fmt/format.h>

#include <algorithm>
#include <cmath>

#include "qsdem/engine/timers.hpp"

namespace qsdem {

void record_row(const Phase& phase, State& st, RunProgress& run, const RowSink& sink, const Measures& m,
                const RowPlace& at, std::optional<double> strain_rate, std::optional<Relaxation> relaxation) {
  PhaseRecord& rec = run.current();
  PhaseState& ps = run.state;
  const PhaseRecord& ref = run.phases.at(static_cast<std::size_t>(sink.reference_phase));
  const long n = at.n;
  const double e1 = at.e1;
  const double ev = m.volume / ref.v0 - 1;
  std::array<double, 3> gamma{};
  if (sink.columns.shear) {
    const auto e = phase_strain(st.stress_h, ref.h0);
    gamma = {e[3], e[4], e[5]};
  }
  const bool run_clock = phase.output.clock == PhaseOutput::Clock::run;
  const long row_step = run_clock ? st.step - 1 : n;
  const double row_time = run_clock ? st.time - at.dt : static_cast<double>(n) * at.dt;
  SeriesRow r{row_step, row_time, e1, ev, m, &phase.name, m.mean_stress - at.p0, gamma, strain_rate, st.energy};
  r.relaxation = relaxation;
  if (sink.writer) {
    ScopedStage ts(st.timers, Stage::output);
    sink.writer->write(series_row(r, sink.columns));
  }
  if (sink.classes) {
    ScopedStage ts(st.timers, Stage::output);
    sink.classes->write(classes_rows(r, class_measures(st, *sink.size_classes)));
  }
  ++rec.rows;
  ps.last_row_step = n;
  rec.ufr += m.ufr;
  rec.iuf += m.iuf;
  rec.imom += m.imom;
  if (m.friction_angle_deg > rec.peak_phi_deg) {
    rec.peak_phi_deg = m.friction_angle_deg;
    rec.peak_phi_e1 = e1;
  }
  for (int c = 0; c < component_count; ++c) {
    const ComponentControl& cc = ps.controls.component[static_cast<std::size_t>(c)];
    const auto [a, b] = component_axes[static_cast<std::size_t>(c)];
    if (is_normal(c) && cc.kind == ControlKind::stress) {
      const double err = std::abs(m.stress(a, a) / cc.value - 1);
      rec.max_stress_error = std::max(rec.max_stress_error, err);
      rec.stress_error += err;
    } else if (!is_normal(c) && m.mean_stress > 0) {
      const double target = cc.kind == ControlKind::stress ? cc.value : 0.0;
      rec.max_shear_stress = std::max(rec.max_shear_stress, std::abs(m.stress(a, b) - target) / m.mean_stress);
    }
  }
  rec.final_ev = ev;
  rec.final_e1 = e1;
  rec.final = m;
  rec.energy_end = st.energy;
}

void end_phase(RunProgress& run, const Phase& phase, Progress& progress) {
  const PhaseRecord& rec = run.current();
  run.controller_end.resize(run.phases.size());
  run.controller_end.at(static_cast<std::size_t>(run.phase)) = run.state.controller;
  const double rows = static_cast<double>(std::max(1L, rec.rows));
  if (phase.stop.equilibrium)
    progress.end(fmt::format("{} done: {} steps, p = {:.4g} kPa, void ratio {:.4f}, UFR {:.3g}, {}", phase.name,
                             rec.steps, rec.final.mean_stress / 1e3, rec.final.void_ratio, rec.final.ufr,
                             format_duration(rec.wall_s)));
  else
    progress.end(fmt::format("{} done: {} steps, peak phi {:.2f} deg at e1 {:.2f}%, mean UFR {:.3g}, mean IMom {:.3g}, {}",
                             phase.name, rec.steps, rec.peak_phi_deg, 100 * rec.peak_phi_e1, rec.ufr / rows,
                             rec.imom / rows, format_duration(rec.wall_s)));
}

std::string equilibrium_line(long steps, const Measures& m, double error) {
  return fmt::format("step {} | p {:.4g} kPa | stress error {:.2g}% | UFR {:.3g} | e {:.4f}", steps, m.mean_stress / 1e3,
                     100 * error, m.ufr, m.void_ratio);
}

std::string loading_line(const Measures& m, double e1, std::optional<double> strain_rate) {
  return fmt::format("e1 {:.2f}% | phi {:.2f} deg | UFR {:.3g} | IMom {:.3g}{}", 100 * e1, m.friction_angle_deg, m.ufr,
                     m.imom, strain_rate ? fmt::format(" | eps' {:.3g}", *strain_rate) : "");
}

std::string increment_line(const Measures& m, double e1, long iterations, bool relaxed) {
  return fmt::format("e1 {:.2f}% | phi {:.2f} deg | UFR {:.3g} | {} iterations{}", 100 * e1, m.friction_angle_deg, m.ufr,
                     iterations, relaxed ? "" : " (not relaxed)");
}

}  // namespace qsdem
