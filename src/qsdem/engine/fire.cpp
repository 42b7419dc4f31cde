#include "qsdem/engine/fire.hpp"

#include <algorithm>
#include <cmath>

#include "qsdem/engine/forces.hpp"
#include "qsdem/engine/integrator.hpp"
#include "qsdem/engine/servo.hpp"
#include "qsdem/engine/step.hpp"

namespace qsdem {

namespace {

// Particles [lo, hi) of the kick and drift run in blocks of this many, each on one thread: a
// particle's update reads only itself, so no result depends on the thread count.
constexpr std::size_t block = 1024;

// Every particle at rest: the velocities and angular momenta (and so omega) set to zero.
void stop_particles(Particles& p) {
  std::fill(p.v.begin(), p.v.end(), Vec3::Zero());
  p.angmom.fill(Vec3::Zero());
  std::fill(p.omega.begin(), p.omega.end(), Vec3::Zero());
}

// v <- (1 - alpha) v + alpha |v| F / |F|, and L with M (Bitzek et al. Eq. 2), the norms over all
// particles, summed in particle order. Spheres' omega follows L; an ellipsoid's is set by the drift.
void mix_velocities(Particles& p, double alpha) {
  double v2 = 0, f2 = 0, l2 = 0, m2 = 0;
  for (std::size_t i = 0; i < p.size(); ++i)
    v2 += p.v[i].squaredNorm(), f2 += p.force[i].squaredNorm(), l2 += p.angmom[i].squaredNorm(),
        m2 += p.torque[i].squaredNorm();
  const double vf = f2 > 0 ? alpha * std::sqrt(v2 / f2) : 0.0, lm = m2 > 0 ? alpha * std::sqrt(l2 / m2) : 0.0;
  const double keep_v = f2 > 0 ? 1 - alpha : 1.0, keep_l = m2 > 0 ? 1 - alpha : 1.0;
  for (std::size_t i = 0; i < p.size(); ++i) {
    p.v[i] = keep_v * p.v[i] + vf * p.force[i];
    p.angmom.set(i, keep_l * p.angmom[i] + lm * p.torque[i]);
    if (p.shape[i] == ShapeKind::sphere) p.omega[i] = p.angmom[i] * p.inv_transverse_moment[i];
  }
}

}  // namespace

FireState fire_start(const Model& model, const FireConstants& c) {
  FireState f;
  f.dt = 0.5 * model.dt;
  f.alpha = c.alpha_start;
  return f;
}

double fire_power(const Particles& p) {
  double power = 0;
  for (std::size_t i = 0; i < p.size(); ++i) power += p.force[i].dot(p.v[i]) + p.torque[i].dot(p.omega[i]);
  return power;
}

void fire_step(const Model& model, State& s, Schedule& schedule, FireState& fire, const FireConstants& c) {
  Particles& p = s.particles;
  Model m = model;
  m.dt = fire.dt;  // the forces integrate the motion of the last drift
  pair_forces(m, s, schedule);
  {
    ScopedStage t(s.timers, Stage::gather);
    gather_resultants(s, schedule);
  }
  {
    ScopedStage t(s.timers, Stage::integrate);
    if (fire_power(p) > 0) {
      if (++fire.positive > c.n_min) {
        fire.dt = std::min(fire.dt * c.f_inc, model.dt);
        fire.alpha *= c.f_alpha;
      }
    } else {
      fire.positive = 0;
      ++fire.resets;
      fire.dt = std::max(fire.dt * c.f_dec, c.dt_min_ratio * model.dt);
      fire.alpha = c.alpha_start;
      stop_particles(p);
    }
  }
  m.dt = fire.dt;
  {
    ScopedStage t(s.timers, Stage::servo);
    servo_update(m, s);
    deform(s.cell, m.dt);
    s.neighbor.strain_path += m.dt * s.cell.L.norm();  // Frobenius >= 2-norm (neighbor.hpp)
  }
  double v2max = 0;
  {
    ScopedStage t(s.timers, Stage::integrate);
    const std::size_t n = p.size();
    // The undamped kick (Model::damping none: A_i = B_i = 0), then the mixing over all particles.
#pragma omp parallel for schedule(static)
    for (std::size_t lo = 0; lo < n; lo += block) integrate_velocities(m, p, lo, std::min(n, lo + block));
    mix_velocities(p, fire.alpha);
    for (std::size_t i = 0; i < n; ++i) v2max = std::max(v2max, p.v[i].squaredNorm());
  }
  {
    ScopedStage t(s.timers, Stage::advance);
    const std::size_t n = p.size();
#pragma omp parallel for schedule(static)
    for (std::size_t lo = 0; lo < n; lo += block)
      advance_positions(m, s.cell, p, s.neighbor.surface_path, lo, std::min(n, lo + block));
  }
  s.neighbor.fluctuation_path += 2 * m.dt * std::sqrt(v2max);
  s.time += m.dt;
  ++s.step;
}

}  // namespace qsdem
