#include "qsdem/protocol.hpp"

#include <fmt/format.h>

#include <chrono>
#include <cmath>

#include "qsdem/step.hpp"

namespace qsdem {
namespace {

double seconds_since(std::chrono::steady_clock::time_point t0) {
  return std::chrono::duration<double>(std::chrono::steady_clock::now() - t0).count();
}

// Stops the run with a diagnostic when the state is no longer finite.
void check_finite(const Measures& m, const State& st, const char* phase) {
  if (std::isfinite(m.stress.sum()) && std::isfinite(m.ekin_trans + m.ekin_rot)) return;
  for (std::size_t i = 0; i < st.particles.size(); ++i)
    if (!st.particles.v[i].allFinite() || !st.particles.s[i].allFinite())
      throw RunError(fmt::format("{}: state is not finite at step {} (particle id {}): the time step is too "
                                 "large for the contact stiffness, lower time.step_ratio",
                                 phase, st.step, st.particles.id[i]));
  throw RunError(fmt::format("{}: stress is not finite at step {}", phase, st.step));
}

}  // namespace

void check_supported(const State& state) {
  for (ShapeKind k : state.particles.shape)
    if (k != ShapeKind::sphere)
      throw InputError("the sample holds ellipsoids (semi-axes not all equal), which this build cannot run yet: "
                       "their narrow phase is the ellipsoid issue; use spheres");
}

Model compaction_model(const Params& params, const State& state) {
  Model m = base_model(params, state.particles);
  m.friction = params.compaction.friction;
  m.damping = params.compaction.damping_model;
  m.damping_ratio = params.compaction.damping_ratio;
  for (auto& c : m.control) c = {AxisControl::Kind::stress, params.compaction.stress, 0.0};
  m.servo.max_strain_rate = params.compaction.max_strain_rate / m.critical_time;
  m.servo.zero_shear_stress = params.compaction.zero_shear_stress;
  return m;
}

Model triaxial_model(const Params& params, const State& state) {
  Model m = base_model(params, state.particles);
  m.friction = params.triaxial.friction;
  m.damping = params.damping.model;
  m.damping_ratio = params.damping.ratio;
  const double rate = params.triaxial.strain_rate / m.critical_time;  // eps' = rate t_c (SPEC 8)
  m.control[0] = {AxisControl::Kind::stress, params.triaxial.confining_stress, 0.0};
  m.control[1] = {AxisControl::Kind::stress, params.triaxial.confining_stress, 0.0};
  m.control[2] = {AxisControl::Kind::strain_rate, rate, state.cell.h(2, 2)};
  m.servo.max_strain_rate = params.triaxial.lateral_rate_factor * rate;
  return m;
}

long triaxial_steps(const Params& params) {
  return std::max(1L, std::lround(params.triaxial.final_axial_strain /
                                  (params.step_ratio * params.triaxial.strain_rate)));
}

CompactionResult compact(const Params& params, State& st, Progress& progress, SeriesWriter* log) {
  const auto t0 = std::chrono::steady_clock::now();
  const Model model = compaction_model(params, st);
  assign_damping(model, st.particles);
  st.servo_integral.setZero();
  const auto& c = params.compaction;
  const double v0 = st.cell.volume;
  const Mat3 h0 = st.cell.h;
  progress.begin("compaction", 0);
  CompactionResult r;
  for (long n = 1; n <= c.max_steps; ++n) {
    {
      step(model, st);
    }
    if (n % c.check_interval != 0) continue;
    Measures m;
    {
      ScopedStage t(st.timers, Stage::measures);
      m = measure(st);
    }
    check_finite(m, st, "compaction");
    // Stress error: each normal stress against the target and, when they are servo-controlled,
    // each shear stress against zero, relative to the target.
    double worst = 0;
    for (int a = 0; a < 3; ++a)
      for (int b = a; b < 3; ++b)
        if (a == b || c.zero_shear_stress)
          worst = std::max(worst, std::abs(m.stress(a, b) - (a == b ? c.stress : 0.0)) / c.stress);
    if (log) {
      ScopedStage t(st.timers, Stage::output);
      const double e1 = 1 - st.stress_h(2, 2) / h0(2, 2);
      log->write(series_row(st.step - 1, st.time - model.dt, e1, m.volume / v0 - 1, m));
    }
    progress.update(0, fmt::format("step {} | p {:.4g} kPa | stress error {:.2g}% | UFR {:.3g} | e {:.4f}",
                                   n, m.mean_stress / 1e3, 100 * worst, m.ufr, m.void_ratio));
    if (m.contacts > 0 && worst < c.stress_tolerance && m.ufr < c.ufr_tolerance) {
      r.steps = n;
      r.final = m;
      r.wall_s = seconds_since(t0);
      progress.end(fmt::format("compaction done: {} steps, p = {:.4g} kPa, void ratio {:.4f}, UFR {:.3g}, {}",
                               n, m.mean_stress / 1e3, m.void_ratio, m.ufr, format_duration(r.wall_s)));
      return r;
    }
  }
  const Measures m = measure(st);
  throw RunError(fmt::format(
      "compaction did not reach equilibrium in {} steps (compaction.max_steps): p = {:.4g} kPa (target {:.4g}), "
      "UFR {:.3g} (tolerance {:.3g}); raise compaction.max_steps or compaction.damping_ratio, or relax "
      "compaction.ufr_tolerance",
      c.max_steps, m.mean_stress / 1e3, c.stress / 1e3, m.ufr, c.ufr_tolerance));
}

TriaxialResult shear(const Params& params, State& st, SeriesWriter& series, Progress& progress) {
  const auto t0 = std::chrono::steady_clock::now();
  const Model model = triaxial_model(params, st);
  assign_damping(model, st.particles);
  st.servo_integral.setZero();
  const auto& t = params.triaxial;
  const long total = triaxial_steps(params);
  const double v0 = st.cell.volume;
  const double h0 = st.cell.h(2, 2);
  const long step0 = st.step;
  if (t.sample_points > total)
    throw InputError(fmt::format("triaxial.sample_points = {} is more than the {} steps of the test: lower it or "
                                 "lower triaxial.strain_rate",
                                 t.sample_points, total));
  TriaxialResult r;
  progress.begin("triaxial", static_cast<double>(total));
  int k = 1;
  long next = std::lround(static_cast<double>(k) * static_cast<double>(total) / t.sample_points);
  double sum_err = 0;
  // Force evaluation n (0..total) happens at axial strain n c_t eps'; sample k is taken at n_k.
  for (long n = 0; n <= total; ++n) {
    step(model, st);
    if (n != next) continue;
    Measures m;
    {
      ScopedStage ts(st.timers, Stage::measures);
      m = measure(st);
    }
    check_finite(m, st, "triaxial");
    const double e1 = 1 - st.stress_h(2, 2) / h0;
    const double ev = m.volume / v0 - 1;
    {
      ScopedStage ts(st.timers, Stage::output);
      series.write(series_row(n, static_cast<double>(n) * model.dt, e1, ev, m));
    }
    ++r.rows;
    r.mean_ufr += m.ufr;
    r.mean_iuf += m.iuf;
    r.mean_imom += m.imom;
    if (m.friction_angle_deg > r.peak_phi_deg) {
      r.peak_phi_deg = m.friction_angle_deg;
      r.peak_phi_e1 = e1;
    }
    for (int a = 0; a < 2; ++a) {
      const double err = std::abs(m.stress(a, a) / t.confining_stress - 1);
      r.max_lateral_stress_error = std::max(r.max_lateral_stress_error, err);
      sum_err += err;
    }
    r.final_ev = ev;
    r.final_e1 = e1;
    progress.update(static_cast<double>(n),
                    fmt::format("e1 {:.2f}% | phi {:.2f} deg | UFR {:.3g} | IMom {:.3g}", 100 * e1,
                                m.friction_angle_deg, m.ufr, m.imom));
    ++k;
    next = std::lround(static_cast<double>(k) * static_cast<double>(total) / t.sample_points);
  }
  r.steps = st.step - step0;
  r.mean_ufr /= r.rows;
  r.mean_iuf /= r.rows;
  r.mean_imom /= r.rows;
  r.mean_lateral_stress_error = sum_err / (2.0 * r.rows);
  r.wall_s = seconds_since(t0);
  progress.end(fmt::format("triaxial done: {} steps, peak phi {:.2f} deg at e1 {:.2f}%, mean UFR {:.3g}, mean "
                           "IMom {:.3g}, {}",
                           r.steps, r.peak_phi_deg, 100 * r.peak_phi_e1, r.mean_ufr, r.mean_imom,
                           format_duration(r.wall_s)));
  return r;
}

}  // namespace qsdem
