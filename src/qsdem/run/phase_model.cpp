#include "qsdem/run/phase_model.hpp"

#include <algorithm>
#include <cmath>

#include "qsdem/engine/state.hpp"

namespace qsdem {

namespace {

// What every phase of a case shares: material, time step, servo gains, skin.
Model case_model(const Params& params, const Particles& particles) {
  Model m;
  m.material = {params.material.density, params.material.young_modulus, params.material.poisson_ratio};
  m.r_min = smallest_equiv_radius(particles);
  m.critical_time = critical_time(m.material, m.r_min);
  m.dt = params.step_ratio * m.critical_time;
  m.servo.proportional_gain = params.servo.proportional_gain;
  m.servo.integral_gain = params.servo.integral_gain;
  m.skin = params.neighbor.skin_ratio * m.r_min;
  m.sort_particles = true;
  m.skip_apart_pairs = true;
  m.track_energy = params.output.energy;
  return m;
}

}  // namespace

Model phase_model(const Params& params, const Phase& phase, const PhaseControls& controls, const Particles& particles,
                  const Mat3& h0) {
  Model m = case_model(params, particles);
  // The step of the scaled particles, dt = c_t s t_c (SPEC 5.6). A phase without scaling has every
  // mu_i = 1 (its start set them), so s = 1: its model skips the pass over the particles.
  if (phase.inertia.on()) {
    m.step_gain = step_gain(particles);
    m.dt = params.step_ratio * m.step_gain * m.critical_time;
  }
  const PhaseDamping& d = phase.damping;
  m.contact_law = make_contact_law(m.material, phase.friction, phase_contact_settings(d.model, d.ratio, phase.contact));
  // od's highest frequency is that of the scaled sample, sqrt(E/rho) / (s R_min) (SPEC 5.6).
  m.damping = resolve_damping(d.model, {d.ratio, m.material.wave_speed(), m.r_min * m.step_gain}, d.acts_on);
  double fastest = 0;  // the fastest strain-rate component (1/s)
  for (int c = 0; c < component_count; ++c) {
    const ComponentControl& cc = controls.component[static_cast<std::size_t>(c)];
    ResolvedControl& axis = m.control[static_cast<std::size_t>(c)];
    switch (cc.kind) {
      case ControlKind::fixed: axis = {}; break;
      case ControlKind::strain_rate: {
        const double rate = cc.value / m.critical_time;  // eps' = rate t_c (SPEC 8)
        axis = {ControlKind::strain_rate, rate, is_normal(c) ? h0(c, c) : 0.0};
        fastest = std::max(fastest, std::abs(rate));
        break;
      }
      case ControlKind::stress: axis = {ControlKind::stress, cc.value, 0.0}; break;
      case ControlKind::constant_volume: axis = {ControlKind::constant_volume, 0.0, 0.0}; break;
    }
  }
  m.servo.max_strain_rate =
      controls.rate_factor > 0 ? controls.rate_factor * fastest : controls.max_strain_rate / m.critical_time;
  return m;
}

Model compaction_model(const Params& params, const State& state) {
  const Phase& p = params.protocol.front();
  return phase_model(params, p, p.controls, state.particles, state.cell.h);
}

Model triaxial_model(const Params& params, const State& state) {
  const Phase& p = params.protocol.back();
  return phase_model(params, p, p.controls, state.particles, state.cell.h);
}

}  // namespace qsdem
