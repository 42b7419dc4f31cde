#include "qsdem/run/protocol.hpp"

#include <fmt/format.h>

#include <Eigen/LU>
#include <algorithm>
#include <chrono>
#include <cmath>
#include <memory>

#include "qsdem/engine/damping/stage.hpp"
#include "qsdem/engine/fire.hpp"
#include "qsdem/engine/schedule.hpp"
#include "qsdem/engine/step.hpp"
#include "qsdem/run/controller.hpp"
#include "qsdem/run/row_schedule.hpp"

namespace qsdem {
namespace {

double seconds_since(std::chrono::steady_clock::time_point t0) {
  return std::chrono::duration<double>(std::chrono::steady_clock::now() - t0).count();
}

// Stops the run with a diagnostic when the state is no longer finite. `step`: the phase's step
// number, counted from 0 as in its rows.
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

// Kinetic energy beyond limits.max_kinetic_ratio * p V: the sample is flying apart, not loaded.
void check_kinetic(const Measures& m, const Params& params, const Phase& phase, long step) {
  const double ratio = (m.ekin_trans + m.ekin_rot) / (std::max(m.mean_stress, 0.0) * m.volume);
  if (ratio > params.limits.max_kinetic_ratio)
    throw RunError(fmt::format(
        "{}: blow-up at {} step {}: kinetic energy {:.3g} J is {:.3g} times p V (limit "
        "limits.max_kinetic_ratio = {:.3g}): the loading is far too fast for the damping; lower "
        "{} or time.step_ratio",
        phase.name, phase.name, step, m.ekin_trans + m.ekin_rot, ratio, params.limits.max_kinetic_ratio,
        phase.keys.strain_rate));
}

// The largest stress target of the stress-controlled normal components (0 without any).
double largest_normal_target(const PhaseControls& c) {
  double t = 0;
  for (int k = 0; k < 3; ++k)
    if (c.component[static_cast<std::size_t>(k)].kind == ControlKind::stress)
      t = std::max(t, c.component[static_cast<std::size_t>(k)].value);
  return t;
}

// The largest relative error of the stress-controlled components (StopCriteria::Equilibrium):
// a normal one against its target, a shear one relative to the largest normal target (or p).
double stress_error(const Measures& m, const PhaseControls& c) {
  const double largest = largest_normal_target(c);
  const double scale = largest > 0 ? largest : std::abs(m.mean_stress);
  double worst = 0;
  for (int k = 0; k < component_count; ++k) {
    const ComponentControl& cc = c.component[static_cast<std::size_t>(k)];
    if (cc.kind != ControlKind::stress) continue;
    const auto [a, b] = component_axes[static_cast<std::size_t>(k)];
    worst = std::max(worst, std::abs(m.stress(a, b) - cc.value) / (is_normal(k) ? cc.value : scale));
  }
  return worst;
}

// The phase's state at its start: its own control values, segments from force evaluation 0.
PhaseState fresh_state(const Phase& phase) {
  PhaseState s;
  s.live = true;
  s.controls = phase.controls;
  return s;
}

// Whether a measured end (phase.hpp: stop.stress, stop.strain of a component whose strain is not
// planned) holds at the state's last force evaluation.
bool measured_end(const Phase& phase, PhaseState& s, const State& st, const Mat3& h0) {
  bool reached = false;
  bool strain_needed = false;
  for (int c = 0; c < component_count; ++c) {
    const auto k = static_cast<std::size_t>(c);
    if (const auto& target = phase.stop.stress[k]) {
      const auto [a, b] = component_axes[k];
      const double sigma = st.stress(a, b);
      if (s.stress_side[k] == 0) s.stress_side[k] = sigma < *target ? 1 : -1;
      reached = reached || (s.stress_side[k] > 0 ? sigma >= *target : sigma <= *target);
    }
    strain_needed = strain_needed || (phase.stop.strain[k] && !planned_strain(phase, c));
  }
  if (!strain_needed) return reached;
  const auto strain = phase_strain(st.stress_h, h0);
  for (int c = 0; c < component_count; ++c) {
    const auto k = static_cast<std::size_t>(c);
    if (!phase.stop.strain[k] || planned_strain(phase, c)) continue;
    const double target = *phase.stop.strain[k];
    reached = reached || (target > 0 ? strain[k] >= target : strain[k] <= target);
  }
  return reached;
}

// The measures of the state's last force evaluation n, the run stopped when they show a blow-up
// (a phase that does not end in equilibrium: its kinetic energy too).
Measures measure_checked(const Params& params, const Phase& phase, State& st, long n) {
  Measures m;
  {
    ScopedStage ts(st.timers, Stage::measures);
    m = measure(st);
  }
  check_finite(m, st, phase.name.c_str(), n);
  if (!phase.stop.equilibrium) check_kinetic(m, params, phase, n);
  return m;
}

// The phase's stops, its strain and stress ones against the values now, for a message.
std::string stops_now(const Phase& phase, const State& st, const Mat3& h0) {
  const auto strain = phase_strain(st.stress_h, h0);
  std::string out = phase.stop.equilibrium ? "equilibrium" : "";
  if (phase.stop.steps > 0) out += fmt::format("{}{} steps", out.empty() ? "" : ", ", phase.stop.steps);
  for (int c = 0; c < component_count; ++c) {
    const auto k = static_cast<std::size_t>(c);
    const auto [a, b] = component_axes[k];
    if (const auto& e = phase.stop.strain[k])
      out += fmt::format("{}strain {} = {:.4g} % (now {:.4g} %)", out.empty() ? "" : ", ", component_names[k], 100 * *e,
                         100 * strain[k]);
    if (const auto& s = phase.stop.stress[k])
      out += fmt::format("{}stress {} = {:.4g} kPa (now {:.4g} kPa)", out.empty() ? "" : ", ", component_names[k],
                         *s / 1e3, st.stress(a, b) / 1e3);
  }
  return out;
}

// Step n of the phase, the run stopped when the loading went on until the cell no longer holds the
// sample.
void step_in_phase(const Model& model, State& st, Schedule& schedule, const Phase& phase, long n, const Mat3& h0) {
  try {
    step(model, st, schedule);
  } catch (const CellTooSmall& e) {
    throw RunError(fmt::format("{} stopped after {} step {}: the cell has deformed until {}, before the phase "
                               "reached its stops ({}): check that the loading moves towards them",
                               phase.name, phase.name, n, e.fact, stops_now(phase, st, h0)));
  }
}

bool in_equilibrium(const Measures& m, const StopCriteria::Equilibrium& e, double error) {
  return m.contacts > 0 && error < e.stress_tolerance && (!e.ufr || m.ufr < *e.ufr) && (!e.imom || m.imom < *e.imom);
}

// The phase's start, once (a resumed phase keeps what its checkpoint saved): its record's start,
// the servo's memory, its own control values and the particles' inertia scaling.
void begin_phase(const Params& params, State& st, RunProgress& run) {
  const Phase& phase = params.protocol.at(static_cast<std::size_t>(run.phase));
  PhaseRecord& rec = run.current();
  PhaseState& ps = run.state;
  if (!run.phase_started) {
    run.phase_started = true;
    rec = {};
    rec.h0 = st.cell.h;
    rec.v0 = st.cell.volume;
    rec.energy_start = st.energy;
    st.servo_integral.setZero();
    ps = fresh_state(phase);
    scale_inertia(st.particles, phase.inertia, params.material.density);  // SPEC 5.6; resumed: as saved
  } else if (!ps.live) {
    ps = fresh_state(phase);  // a checkpoint of an older format: no controller changed anything
  }
}

// The phase with solver = "fire" (docs/physics.md 5.7): increments of strain, each from rest, then
// FIRE to the solver's tolerances; one row per increment. Checkpoints are taken between increments
// (the hook), where FIRE's own state starts afresh: a resumed phase continues with the same bits.
void run_fire_phase(const Params& params, State& st, RunProgress& run, const RowSink& sink, Progress& progress,
                    const StepHook& hook) {
  const auto t0 = std::chrono::steady_clock::now();
  const Phase& phase = params.protocol.at(static_cast<std::size_t>(run.phase));
  const FireSolver& solver = *phase.fire;
  PhaseRecord& rec = run.current();
  PhaseState& ps = run.state;
  begin_phase(params, st, run);
  const Model model = phase_model(params, phase, ps.controls, st.particles, rec.h0);
  assign_damping(model, st.particles);  // none: FIRE is the dissipation
  const double step_ratio = params.step_ratio * model.step_gain;
  // The driving component, the fastest strain-rate one: its strain moves by the increment.
  int driver = -1;
  for (int c = 0; c < component_count; ++c) {
    const ComponentControl& cc = ps.controls.component[static_cast<std::size_t>(c)];
    if (cc.kind == ControlKind::strain_rate &&
        (driver < 0 || std::abs(cc.value) > std::abs(ps.controls.component[static_cast<std::size_t>(driver)].value)))
      driver = c;
  }
  const auto kd = static_cast<std::size_t>(driver);
  const double fastest = std::abs(ps.controls.component[kd].value);
  const std::optional<double>& target = phase.stop.strain[kd];
  const PhaseRecord& ref = run.phases.at(static_cast<std::size_t>(sink.reference_phase));
  const double p0 = run.phase > 0 ? run.phases.at(static_cast<std::size_t>(run.phase - 1)).final.mean_stress : 0.0;
  const char* name = phase.name.c_str();
  const double wall_before = rec.wall_s;
  BlowUpWatch watch;
  Schedule schedule;
  progress.begin(phase.name, target ? std::abs(*target) : 0.0);
  const auto limit_reached = [&] { return phase.stop.max_steps > 0 && rec.steps >= phase.stop.max_steps; };
  const auto evaluation = [&] {
    watch.check(st, params, name, rec.steps);
    ++rec.steps;
  };
  bool ended = false;
  while (!ended) {
    // The increment, the last one cut to the driver's strain stop; the others in proportion.
    const double strain = phase_strain(st.cell.h, rec.h0)[kd];
    double increment = solver.strain_increment;
    bool last = false;
    // (within a millionth of an increment: the strains' rounding leaves no sliver of an increment)
    if (target && std::abs(*target - strain) <= increment * (1 + 1e-6))
      increment = std::abs(*target - strain), last = true;
    PhaseControls loading = ps.controls;
    for (ComponentControl& cc : loading.component)
      if (cc.kind == ControlKind::strain_rate) cc.value *= increment / (fastest * step_ratio);  // one step's strain
    Model load = phase_model(params, phase, loading, st.particles, rec.h0);
    for (std::size_t i = 0; i < st.particles.size(); ++i)  // each increment from rest (athermal)
      st.particles.v[i].setZero(), st.particles.angmom.set(i, Vec3::Zero()), st.particles.omega[i].setZero();
    step(load, st, schedule);
    evaluation();
    // The relaxation: the strain-rate components held, the stress-controlled ones on their servo.
    Model relax = load;
    for (ResolvedControl& a : relax.control)
      if (a.kind == ControlKind::strain_rate) a = {};
    FireState fire = fire_start(relax);
    long iterations = 0;
    bool relaxed = false;
    Measures m;
    while (true) {
      fire_step(relax, st, schedule, fire);
      evaluation();
      ++iterations;
      if (iterations % solver.check_every == 0 || iterations >= solver.max_iterations || limit_reached()) {
        {
          ScopedStage ts(st.timers, Stage::measures);
          m = measure(st);
        }
        check_finite(m, st, name, rec.steps - 1);
        relaxed = m.contacts > 0 && m.ufr < solver.ufr && (!solver.imom || m.imom < *solver.imom) &&
                  stress_error(m, ps.controls) < solver.stress_tolerance;
        if (relaxed || iterations >= solver.max_iterations || limit_reached()) break;
      }
    }
    rec.wall_s = wall_before + seconds_since(t0);
    ended = last || measured_end(phase, ps, st, rec.h0) || (phase.stop.steps > 0 && rec.steps >= phase.stop.steps);
    const double e1 = 1 - st.stress_h(2, 2) / ref.h0(2, 2);
    record_row(phase, st, run, sink, m, {rec.steps - 1, model.dt, p0, e1}, std::nullopt, Relaxation{iterations, relaxed});
    progress.update(std::abs(phase_strain(st.stress_h, rec.h0)[kd]), increment_line(m, e1, iterations, relaxed));
    if (ended) break;
    if (hook) hook(true);
    if (limit_reached())
      throw RunError(fmt::format("{} did not reach its end in {} steps ({}): e1 = {:.4g} %; raise {} or the solver's "
                                 "tolerances",
                                 phase.name, phase.stop.max_steps, phase.keys.max_steps, 100 * e1, phase.keys.max_steps));
  }
  end_phase(run, phase, progress);
}

// Stops the run: the phase took stop.max_steps steps without reaching its end.
[[noreturn]] void out_of_steps(const Phase& phase, const State& st, const PhaseControls& controls,
                               const PhaseRecord& rec) {
  const Measures m = measure(st);
  if (const auto& equilibrium = phase.stop.equilibrium) {
    const double target = largest_normal_target(controls);
    throw RunError(fmt::format(
        "{} did not reach equilibrium in {} steps ({}): p = {:.4g} kPa (target {:.4g}), {} {:.3g} (tolerance {:.3g}); "
        "raise {} or {}, or relax {}",
        phase.name, phase.stop.max_steps, phase.keys.max_steps, m.mean_stress / 1e3, target / 1e3,
        equilibrium->ufr ? "UFR" : "IMom", equilibrium->ufr ? m.ufr : m.imom,
        equilibrium->ufr ? *equilibrium->ufr : *equilibrium->imom, phase.keys.max_steps, phase.keys.damping_ratio,
        phase.keys.ufr_tolerance));
  }
  throw RunError(fmt::format("{} did not reach its end in {} steps ({}): p = {:.4g} kPa, e1 = {:.4g} %; raise {} or "
                             "check its stop criteria",
                             phase.name, phase.stop.max_steps, phase.keys.max_steps, m.mean_stress / 1e3,
                             100 * (1 - st.stress_h(2, 2) / rec.h0(2, 2)), phase.keys.max_steps));
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
        "the loading too fast (a strain rate, the servo's max_strain_rate)",
        phase, phase, step, pair(), 100 * now, 100 * params.limits.max_overlap));
  recent_[static_cast<std::size_t>(seen_ % window)] = now;
  ++seen_;
}

void run_phase(const Params& params, State& st, RunProgress& run, const RowSink& sink, Progress& progress,
               const StepHook& hook) {
  const auto t0 = std::chrono::steady_clock::now();
  const Phase& phase = params.protocol.at(static_cast<std::size_t>(run.phase));
  if (phase.fire) return run_fire_phase(params, st, run, sink, progress, hook);
  PhaseRecord& rec = run.current();
  PhaseState& ps = run.state;
  begin_phase(params, st, run);
  std::unique_ptr<Controller> controller = phase.make_controller ? phase.make_controller() : nullptr;
  if (controller && !ps.controller.empty()) controller->restore(ps.controller);
  const auto keep_controller = [&] {
    if (controller) ps.controller = controller->save();
  };

  Model model = phase_model(params, phase, ps.controls, st.particles, rec.h0);
  assign_damping(model, st.particles);
  // A strain-rate component's strain grows by dt eps' / t_c = c_t s eps' per step (SPEC 3.4, 5.6).
  const double step_ratio = params.step_ratio * model.step_gain;
  const PhaseRecord& ref = run.phases.at(static_cast<std::size_t>(sink.reference_phase));
  const std::optional<StopCriteria::Equilibrium>& equilibrium = phase.stop.equilibrium;
  const char* name = phase.name.c_str();
  // p0: the mean stress at the phase's start, the last force evaluation of the phase before (its
  // last row); 0 before the first phase.
  const double p0 = run.phase > 0 ? run.phases.at(static_cast<std::size_t>(run.phase - 1)).final.mean_stress : 0.0;
  const double wall_before = rec.wall_s;
  const long steps_at_start = rec.steps;
  long end = planned_end(phase, ps, step_ratio);
  long sample = next_sample(phase, ps, rec.rows, end, step_ratio);
  BlowUpWatch watch;
  Schedule schedule;  // the threads' shares of the step, kept over the phase
  progress.begin(phase.name, end >= 0 ? static_cast<double>(end - steps_at_start) : 0.0);
  const auto limit_reached = [&] { return phase.stop.max_steps > 0 && rec.steps >= phase.stop.max_steps; };
  const auto replan = [&](const PhaseControls& before, long n) {
    controls_changed(before, ps, n, rec.rows, step_ratio);
    model = phase_model(params, phase, ps.controls, st.particles, rec.h0);
    end = planned_end(phase, ps, step_ratio);
  };
  bool ended = false;
  while (!ended) {
    const long n = rec.steps;  // the force evaluation of this step
    step_in_phase(model, st, schedule, phase, n, rec.h0);
    watch.check(st, params, name, n);
    ++rec.steps;
    rec.wall_s = wall_before + seconds_since(t0);  // before the hook, which may save a checkpoint
    ended = (end >= 0 && n >= end) || measured_end(phase, ps, st, rec.h0);
    if (controller && controller->every_step()) {
      const PhaseControls before = ps.controls;
      if (controller->at_step(st, n, rec.h0, ps.controls)) {
        replan(before, n);
        sample = next_sample(phase, ps, rec.rows, end, step_ratio);
      }
      keep_controller();
      ended = ended || controller->done();
    }
    const bool row = ended || (sample >= 0 && n >= sample) || measured_row(phase, ps, rec.rows, st, rec.h0);
    const bool check = equilibrium && rec.steps % equilibrium->every == 0;
    if (!row && !check) {
      if (hook) hook(false);
      if (limit_reached()) break;
      continue;
    }
    const Measures m = measure_checked(params, phase, st, n);
    const double error = stress_error(m, ps.controls);
    ended = ended || (check && in_equilibrium(m, *equilibrium, error));
    const double e1 = 1 - st.stress_h(2, 2) / ref.h0(2, 2);
    // The eps' of the rate-controlled component at which the steps up to this row were taken.
    const std::optional<double> strain_rate =
        phase.rate_component >= 0
            ? std::optional<double>(ps.controls.component[static_cast<std::size_t>(phase.rate_component)].value)
            : std::nullopt;
    if (row || ended) record_row(phase, st, run, sink, m, {n, model.dt, p0, e1}, strain_rate, std::nullopt);
    if (equilibrium)
      progress.update(static_cast<double>(rec.steps - steps_at_start), equilibrium_line(rec.steps, m, error));
    else
      progress.update(static_cast<double>(n - steps_at_start), loading_line(m, e1, strain_rate));
    if (ended) {
      if (controller) {
        controller->at_end({n, rec.rows, &m, phase_strain(st.stress_h, rec.h0), model.critical_time}, ps.controls);
        keep_controller();
      }
      break;
    }
    if (row && controller) {
      const SamplePoint point{n, rec.rows, &m, phase_strain(st.stress_h, rec.h0), model.critical_time};
      const PhaseControls before = ps.controls;
      if (controller->at_sample(point, ps.controls)) replan(before, n);
      keep_controller();
    }
    if (row) sample = next_sample(phase, ps, rec.rows, end, step_ratio);
    if (hook) hook(row);
    if (limit_reached()) break;
  }
  if (!ended) out_of_steps(phase, st, ps.controls, rec);
  end_phase(run, phase, progress);
}

const std::string& phase_name(const Params& params, std::int32_t p) {
  return params.protocol[std::min(static_cast<std::size_t>(p), params.protocol.size() - 1)].name;
}

PhaseRecord run_phase(const Params& params, std::size_t index, State& state, Progress& progress, SeriesWriter* rows) {
  RunProgress run;
  run.phase = static_cast<std::int32_t>(index);
  run.phases.resize(params.protocol.size());
  run_phase(params, state, run, {rows, run.phase, false}, progress, {});
  return run.current();
}

}  // namespace qsdem
