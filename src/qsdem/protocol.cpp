#include "qsdem/protocol.hpp"

#include <fmt/format.h>

#include <Eigen/LU>
#include <algorithm>
#include <chrono>
#include <cmath>
#include <memory>

#include "qsdem/controller.hpp"
#include "qsdem/damping/stage.hpp"
#include "qsdem/fire.hpp"
#include "qsdem/schedule.hpp"
#include "qsdem/step.hpp"

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

using Kind = ComponentControl::Kind;

// The largest stress target of the stress-controlled normal components (0 without any).
double largest_normal_target(const PhaseControls& c) {
  double t = 0;
  for (int k = 0; k < 3; ++k)
    if (c.component[static_cast<std::size_t>(k)].kind == Kind::stress)
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
    if (cc.kind != Kind::stress) continue;
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

// The last force evaluation of the phase as planned now (-1: it ends on measured criteria only).
long planned_end(const Phase& phase, const PhaseState& s, double step_ratio) {
  long end = phase.stop.steps > 0 ? phase.stop.steps - 1 : -1;
  for (int c = 0; c < 3; ++c)
    if (planned_strain(phase, c)) {
      const auto k = static_cast<std::size_t>(c);
      const long n = planned_step(s.segment_step[k], s.segment_strain[k], *phase.stop.strain[k], step_ratio,
                                  s.controls.component[k].value);
      end = end < 0 ? n : std::min(end, n);
    }
  return end;
}

// The force evaluation of the phase's next sample point by its cadence (the end is one too).
long next_sample(const Phase& phase, const PhaseState& s, long rows, long end, double step_ratio) {
  const Cadence& c = phase.output.cadence;
  switch (c.kind) {
    case Cadence::Kind::points: {
      // row k of P at base + round((k - base_k) (end - base) / (P - base_k)); SPEC 8.4 from 0.
      const long k = rows + 1;
      if (k >= c.points) return end;
      return s.row_base_step + std::lround(static_cast<double>(k - s.row_base_rows) *
                                           static_cast<double>(end - s.row_base_step) /
                                           static_cast<double>(c.points - s.row_base_rows));
    }
    case Cadence::Kind::every_steps:
      return (rows + 1) * c.every_steps - 1;  // after every every_steps steps of the phase
    case Cadence::Kind::every_strain: {
      if (!is_normal(c.strain_component)) return -1;  // a shear strain is measured: measured_row
      const auto k = static_cast<std::size_t>(c.strain_component);
      const double eps = s.controls.component[k].value;
      const double target = static_cast<double>(rows + 1) * c.every_strain * (eps > 0 ? 1 : -1);
      return planned_step(s.segment_step[k], s.segment_strain[k], target, step_ratio, eps);
    }
  }
  return end;
}

// Whether the next row of a cadence by the strain of a shear component (not planned: the cell's
// normal components may move under it) is due at the state's last force evaluation: its strain
// gamma_ab (phase_strain) has passed the next multiple of the interval, in the rate's direction.
bool measured_row(const Phase& phase, const PhaseState& s, long rows, const State& st, const Mat3& h0) {
  const Cadence& c = phase.output.cadence;
  if (c.kind != Cadence::Kind::every_strain || is_normal(c.strain_component)) return false;
  const auto k = static_cast<std::size_t>(c.strain_component);
  const double direction = s.controls.component[k].value > 0 ? 1.0 : -1.0;
  return direction * phase_strain(st.stress_h, h0)[k] >= static_cast<double>(rows + 1) * c.every_strain;
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

bool in_equilibrium(const Measures& m, const StopCriteria::Equilibrium& e, double error) {
  return m.contacts > 0 && error < e.stress_tolerance && (!e.ufr || m.ufr < *e.ufr) && (!e.imom || m.imom < *e.imom);
}

// After a controller changed the control values at force evaluation n (they apply from n + 1):
// a planned strain's segment restarts at n + 1 with its nominal strain there, and the rows still
// to come are spread from the last one.
void controls_changed(const PhaseControls& before, PhaseState& s, long n, long rows, double step_ratio) {
  for (std::size_t k = 0; k < 3; ++k) {
    const ComponentControl& old = before.component[k];
    if (old.kind != Kind::strain_rate || old.value == s.controls.component[k].value) continue;
    s.segment_strain[k] += static_cast<double>(n + 1 - s.segment_step[k]) * (step_ratio * old.value);
    s.segment_step[k] = n + 1;
  }
  s.row_base_step = std::max(s.last_row_step, 0L);
  s.row_base_rows = rows;
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

// Where a row is in its phase: its force evaluation n, the phase's step, the mean stress p0 at the
// phase's start and the axial strain e1 of the file's reference.
struct RowPlace {
  long n;
  double dt, p0, e1;
};

// Writes the row of the state's last force evaluation to the phase's file (and classes.csv) and
// adds it to the phase's record (SPEC 8.4).
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
    if (is_normal(c) && cc.kind == Kind::stress) {
      const double err = std::abs(m.stress(a, a) / cc.value - 1);
      rec.max_stress_error = std::max(rec.max_stress_error, err);
      rec.stress_error += err;
    } else if (!is_normal(c) && m.mean_stress > 0) {
      const double target = cc.kind == Kind::stress ? cc.value : 0.0;
      rec.max_shear_stress = std::max(rec.max_shear_stress, std::abs(m.stress(a, b) - target) / m.mean_stress);
    }
  }
  rec.final_ev = ev;
  rec.final_e1 = e1;
  rec.final = m;
  rec.energy_end = st.energy;
}

// The phase's end in the run's records (its controller's last saved state) and its closing line.
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
    if (cc.kind == Kind::strain_rate &&
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
      if (cc.kind == Kind::strain_rate) cc.value *= increment / (fastest * step_ratio);  // one step's strain
    Model load = phase_model(params, phase, loading, st.particles, rec.h0);
    for (std::size_t i = 0; i < st.particles.size(); ++i)  // each increment from rest (athermal)
      st.particles.v[i].setZero(), st.particles.angmom[i].setZero(), st.particles.omega[i].setZero();
    step(load, st, schedule);
    evaluation();
    // The relaxation: the strain-rate components held, the stress-controlled ones on their servo.
    Model relax = load;
    for (AxisControl& a : relax.control)
      if (a.kind == AxisControl::Kind::strain_rate) a = {};
    for (AxisControl& a : relax.shear_control)
      if (a.kind == AxisControl::Kind::strain_rate) a = {};
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
    progress.update(std::abs(phase_strain(st.stress_h, rec.h0)[kd]),
                    fmt::format("e1 {:.2f}% | phi {:.2f} deg | UFR {:.3g} | {} iterations{}", 100 * e1,
                                m.friction_angle_deg, m.ufr, iterations, relaxed ? "" : " (not relaxed)"));
    if (ended) break;
    if (hook) hook(true);
    if (limit_reached())
      throw RunError(fmt::format("{} did not reach its end in {} steps ({}): e1 = {:.4g} %; raise {} or the solver's "
                                 "tolerances",
                                 phase.name, phase.stop.max_steps, phase.keys.max_steps, 100 * e1, phase.keys.max_steps));
  }
  end_phase(run, phase, progress);
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

std::array<double, component_count> phase_strain(const Mat3& h, const Mat3& h0) {
  std::array<double, component_count> e{};
  for (int k = 0; k < 3; ++k) e[static_cast<std::size_t>(k)] = 1 - h(k, k) / h0(k, k);
  const Mat3 f = h * h0.inverse();
  for (int c = 3; c < component_count; ++c) {
    const auto [a, b] = component_axes[static_cast<std::size_t>(c)];
    e[static_cast<std::size_t>(c)] = f(a, b) + f(b, a);
  }
  return e;
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
    try {
      step(model, st, schedule);
    } catch (const CellTooSmall& e) {  // the loading went on until the cell no longer holds the sample
      throw RunError(fmt::format("{} stopped after {} step {}: the cell has deformed until {}, before the phase "
                                 "reached its stops ({}): check that the loading moves towards them",
                                 phase.name, phase.name, n, e.fact, stops_now(phase, st, rec.h0)));
    }
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
    Measures m;
    {
      ScopedStage ts(st.timers, Stage::measures);
      m = measure(st);
    }
    check_finite(m, st, name, n);
    if (!equilibrium) check_kinetic(m, params, phase, n);
    const double error = stress_error(m, ps.controls);
    ended = ended || (check && in_equilibrium(m, *equilibrium, error));
    const double e1 = 1 - st.stress_h(2, 2) / ref.h0(2, 2);
    // The eps' of the rate-controlled component at which the steps up to this row were taken.
    const double strain_rate_now =
        phase.rate_component >= 0 ? ps.controls.component[static_cast<std::size_t>(phase.rate_component)].value : 0.0;
    if (row || ended)
      record_row(phase, st, run, sink, m, {n, model.dt, p0, e1},
                 phase.rate_component >= 0 ? std::optional<double>(strain_rate_now) : std::nullopt, std::nullopt);
    if (equilibrium)
      progress.update(static_cast<double>(rec.steps - steps_at_start),
                      fmt::format("step {} | p {:.4g} kPa | stress error {:.2g}% | UFR {:.3g} | e {:.4f}", rec.steps,
                                  m.mean_stress / 1e3, 100 * error, m.ufr, m.void_ratio));
    else
      progress.update(static_cast<double>(n - steps_at_start),
                      fmt::format("e1 {:.2f}% | phi {:.2f} deg | UFR {:.3g} | IMom {:.3g}{}", 100 * e1,
                                  m.friction_angle_deg, m.ufr, m.imom,
                                  phase.rate_component >= 0 ? fmt::format(" | eps' {:.3g}", strain_rate_now) : ""));
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
  if (!ended) {
    const Measures m = measure(st);
    if (equilibrium) {
      const double target = largest_normal_target(ps.controls);
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
