#include "qsdem/protocol.hpp"

#include <fmt/format.h>

#include <algorithm>
#include <chrono>
#include <cmath>

#include "qsdem/step.hpp"

namespace qsdem {
namespace {

double seconds_since(std::chrono::steady_clock::time_point t0) {
  return std::chrono::duration<double>(std::chrono::steady_clock::now() - t0).count();
}

// Stops the run with a diagnostic when the state is no longer finite. `step`: the phase's step
// number, counted from 0 as in compaction.csv and series.csv.
void check_finite(const Measures& m, const State& st, const char* phase, long step) {
  if (std::isfinite(m.stress.sum()) && std::isfinite(m.ekin_trans + m.ekin_rot)) return;
  for (std::size_t i = 0; i < st.particles.size(); ++i)
    if (!st.particles.v[i].allFinite() || !st.particles.s[i].allFinite() || !st.particles.angmom[i].allFinite())
      throw RunError(fmt::format("{}: blow-up at {} step {}: the state of particle id {} is not finite (NaN or "
                                 "infinity). The time step may be too large for the contact stiffness: lower "
                                 "time.step_ratio",
                                 phase, phase, step, st.particles.id[i]));
  throw RunError(fmt::format("{}: blow-up at {} step {}: the stress is not finite (NaN or infinity)", phase, phase,
                             step));
}

// Kinetic energy beyond limits.max_kinetic_ratio * p V: the sample is flying apart, not sheared.
void check_kinetic(const Measures& m, const Params& params, long step) {
  const double ratio = (m.ekin_trans + m.ekin_rot) / (std::max(m.mean_stress, 0.0) * m.volume);
  if (ratio > params.limits.max_kinetic_ratio)
    throw RunError(fmt::format(
        "triaxial: blow-up at triaxial step {}: kinetic energy {:.3g} J is {:.3g} times p V (limit "
        "limits.max_kinetic_ratio = {:.3g}): the loading is far too fast for the damping; lower "
        "triaxial.strain_rate or time.step_ratio",
        step, m.ekin_trans + m.ekin_rot, ratio, params.limits.max_kinetic_ratio));
}

}  // namespace

void BlowUpWatch::check(const State& st, const Params& params, const char* phase, long step) {
  if (!std::isfinite(st.stress.trace())) {
    Measures m;
    m.stress = st.stress;
    check_finite(m, st, phase, step);
  }
  const double now = st.max_overlap;
  const auto pair = [&] {
    const std::size_t k = st.max_overlap_pair;
    return fmt::format("particles id {} and id {}", st.particles.id[st.pairs.i[k]], st.particles.id[st.pairs.j[k]]);
  };
  if (now > watch_level && seen_ > 0) {
    const auto end = recent_.begin() + std::min(seen_, window);
    const double low = *std::min_element(recent_.begin(), end);
    if (now >= 2 * low)
      throw RunError(fmt::format(
          "{}: blow-up at {} step {}: the largest overlap ({}, {:.3g} % of the smaller radius) doubled within {} "
          "steps (from {:.3g} %): a numerical instability, not a load. The time step is too large for the contact "
          "stiffness: lower time.step_ratio (now {})",
          phase, phase, step, pair(), 100 * now, std::min(seen_, window), 100 * low, params.step_ratio));
  }
  if (now > params.limits.max_overlap)
    throw RunError(fmt::format(
        "{}: blow-up at {} step {}: {} overlap by {:.3g} % of the smaller radius (limit limits.max_overlap = {:.3g} "
        "%: beyond it the contact geometry is meaningless). The time step may be too large (time.step_ratio) or "
        "the loading too fast (triaxial.strain_rate, compaction.max_strain_rate)",
        phase, phase, step, pair(), 100 * now, 100 * params.limits.max_overlap));
  recent_[static_cast<std::size_t>(seen_ % window)] = now;
  ++seen_;
}

TriaxialResult triaxial_result(const RunProgress& run) {
  const TriaxialSums& r = run.sums;
  const double rows = std::max(1, r.rows);
  TriaxialResult res;
  res.steps = run.phase_steps;
  res.rows = r.rows;
  res.mean_ufr = r.ufr / rows;
  res.mean_iuf = r.iuf / rows;
  res.mean_imom = r.imom / rows;
  res.peak_phi_deg = r.peak_phi_deg;
  res.peak_phi_e1 = r.peak_phi_e1;
  res.final_ev = r.final_ev;
  res.final_e1 = r.final_e1;
  res.max_lateral_stress_error = r.max_lateral_error;
  res.mean_lateral_stress_error = r.lateral_error / (2.0 * rows);
  res.wall_s = r.wall_s;
  return res;
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

Model triaxial_model(const Params& params, const State& state, double axial_reference_length) {
  Model m = base_model(params, state.particles);
  m.friction = params.triaxial.friction;
  m.damping = params.damping.model;
  m.damping_ratio = params.damping.ratio;
  m.damping_acts_on = params.damping.acts_on;
  const double rate = params.triaxial.strain_rate / m.critical_time;  // eps' = rate t_c (SPEC 8)
  m.control[0] = {AxisControl::Kind::stress, params.triaxial.confining_stress, 0.0};
  m.control[1] = {AxisControl::Kind::stress, params.triaxial.confining_stress, 0.0};
  m.control[2] = {AxisControl::Kind::strain_rate, rate, axial_reference_length};
  m.servo.max_strain_rate = params.triaxial.lateral_rate_factor * rate;
  return m;
}

Model triaxial_model(const Params& params, const State& state) {
  return triaxial_model(params, state, state.cell.h(2, 2));
}

long triaxial_steps(const Params& params) {
  return std::max(1L, std::lround(params.triaxial.final_axial_strain /
                                  (params.step_ratio * params.triaxial.strain_rate)));
}

// Starts a phase once (not again on resume): reference cell and servo memory.
static void start_phase(RunProgress& run, State& st) {
  if (run.phase_started) return;
  run.phase_started = true;
  run.phase_steps = 0;
  run.rows = 0;
  run.v0 = st.cell.volume;
  run.h0 = st.cell.h;
  st.servo_integral.setZero();
}

CompactionResult compact(const Params& params, State& st, RunProgress& run, Progress& progress, SeriesWriter* log,
                         const StepHook& hook) {
  const auto t0 = std::chrono::steady_clock::now();
  const Model model = compaction_model(params, st);
  start_phase(run, st);
  assign_damping(model, st.particles);
  const auto& c = params.compaction;
  progress.begin("compaction", 0);
  const double wall_before = run.compaction.wall_s;
  const long run_steps_at_start = run.phase_steps;
  BlowUpWatch watch;
  Schedule schedule;
  while (run.phase_steps < c.max_steps) {
    step(model, st, schedule);
    watch.check(st, params, "compaction", run.phase_steps);
    const long n = ++run.phase_steps;
    if (n % c.check_interval != 0) {
      if (hook) hook(false);
      continue;
    }
    Measures m;
    {
      ScopedStage t(st.timers, Stage::measures);
      m = measure(st);
    }
    check_finite(m, st, "compaction", n - 1);
    // Stress error: each normal stress against the target and, when they are servo-controlled,
    // each shear stress against zero, relative to the target.
    double worst = 0;
    for (int a = 0; a < 3; ++a)
      for (int b = a; b < 3; ++b)
        if (a == b || c.zero_shear_stress)
          worst = std::max(worst, std::abs(m.stress(a, b) - (a == b ? c.stress : 0.0)) / c.stress);
    if (log) {
      ScopedStage t(st.timers, Stage::output);
      const double e1 = 1 - st.stress_h(2, 2) / run.h0(2, 2);
      log->write(series_row(st.step - 1, st.time - model.dt, e1, m.volume / run.v0 - 1, m));
      ++run.rows;
    }
    progress.update(static_cast<double>(n - run_steps_at_start), fmt::format("step {} | p {:.4g} kPa | stress error {:.2g}% | UFR {:.3g} | e {:.4f}",
                                   n, m.mean_stress / 1e3, 100 * worst, m.ufr, m.void_ratio));
    const bool done = m.contacts > 0 && worst < c.stress_tolerance && m.ufr < c.ufr_tolerance;
    if (done) {
      run.compaction.steps = n;
      run.compaction.final = m;
      run.compaction.wall_s = wall_before + seconds_since(t0);
      progress.end(fmt::format("compaction done: {} steps, p = {:.4g} kPa, void ratio {:.4f}, UFR {:.3g}, {}",
                               n, m.mean_stress / 1e3, m.void_ratio, m.ufr, format_duration(run.compaction.wall_s)));
      return run.compaction;
    }
    run.compaction.wall_s = wall_before + seconds_since(t0);
    if (hook) hook(true);
  }
  const Measures m = measure(st);
  throw RunError(fmt::format(
      "compaction did not reach equilibrium in {} steps (compaction.max_steps): p = {:.4g} kPa (target {:.4g}), "
      "UFR {:.3g} (tolerance {:.3g}); raise compaction.max_steps or compaction.damping_ratio, or relax "
      "compaction.ufr_tolerance",
      c.max_steps, m.mean_stress / 1e3, c.stress / 1e3, m.ufr, c.ufr_tolerance));
}

TriaxialResult shear(const Params& params, State& st, RunProgress& run, SeriesWriter& series, Progress& progress,
                     const StepHook& hook) {
  const auto t0 = std::chrono::steady_clock::now();
  const auto& t = params.triaxial;
  const long total = triaxial_steps(params);
  if (t.sample_points > total)
    throw InputError(fmt::format("triaxial.sample_points = {} is more than the {} steps of the test: lower it or "
                                 "lower triaxial.strain_rate",
                                 t.sample_points, total));
  const double h_start = run.phase_started ? run.h0(2, 2) : st.cell.h(2, 2);
  const Model model = triaxial_model(params, st, h_start);
  start_phase(run, st);
  assign_damping(model, st.particles);
  const double v0 = run.v0, h0 = run.h0(2, 2);
  TriaxialSums& r = run.sums;
  const double wall_before = r.wall_s;
  const long steps_at_start = run.phase_steps;
  BlowUpWatch watch;
  progress.begin("triaxial", static_cast<double>(total - steps_at_start));
  auto sample_step = [&](long k) {
    return std::lround(static_cast<double>(k) * static_cast<double>(total) / t.sample_points);
  };
  // Force evaluation n (0..total) happens at axial strain n c_t eps'; sample k is taken at n_k.
  Schedule schedule;
  while (run.phase_steps <= total) {
    const long n = run.phase_steps;
    step(model, st, schedule);
    watch.check(st, params, "triaxial", n);
    ++run.phase_steps;
    r.wall_s = wall_before + seconds_since(t0);  // before the hook, which may save a checkpoint
    if (n != sample_step(run.rows + 1)) {
      if (hook) hook(false);
      continue;
    }
    Measures m;
    {
      ScopedStage ts(st.timers, Stage::measures);
      m = measure(st);
    }
    check_finite(m, st, "triaxial", n);
    check_kinetic(m, params, n);
    const double e1 = 1 - st.stress_h(2, 2) / h0;
    const double ev = m.volume / v0 - 1;
    {
      ScopedStage ts(st.timers, Stage::output);
      series.write(series_row(n, static_cast<double>(n) * model.dt, e1, ev, m));
      ++run.rows;
    }
    ++r.rows;
    r.ufr += m.ufr;
    r.iuf += m.iuf;
    r.imom += m.imom;
    if (m.friction_angle_deg > r.peak_phi_deg) {
      r.peak_phi_deg = m.friction_angle_deg;
      r.peak_phi_e1 = e1;
    }
    for (int a = 0; a < 2; ++a) {
      const double err = std::abs(m.stress(a, a) / t.confining_stress - 1);
      r.max_lateral_error = std::max(r.max_lateral_error, err);
      r.lateral_error += err;
    }
    r.final_ev = ev;
    r.final_e1 = e1;
    progress.update(static_cast<double>(n - steps_at_start),
                    fmt::format("e1 {:.2f}% | phi {:.2f} deg | UFR {:.3g} | IMom {:.3g}", 100 * e1,
                                m.friction_angle_deg, m.ufr, m.imom));
    if (run.rows == t.sample_points) break;
    if (hook) hook(true);
  }
  const TriaxialResult out = triaxial_result(run);
  progress.end(fmt::format("triaxial done: {} steps, peak phi {:.2f} deg at e1 {:.2f}%, mean UFR {:.3g}, mean "
                           "IMom {:.3g}, {}",
                           out.steps, out.peak_phi_deg, 100 * out.peak_phi_e1, out.mean_ufr, out.mean_imom,
                           format_duration(out.wall_s)));
  return out;
}

CompactionResult compact(const Params& params, State& st, Progress& progress, SeriesWriter* log) {
  RunProgress run;
  return compact(params, st, run, progress, log, {});
}

TriaxialResult shear(const Params& params, State& st, SeriesWriter& series, Progress& progress) {
  RunProgress run;
  run.phase = RunProgress::Phase::triaxial;
  return shear(params, st, run, series, progress, {});
}

}  // namespace qsdem
