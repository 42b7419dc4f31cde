#include "qsdem/model.hpp"

#include <algorithm>
#include <cmath>
#include <limits>

#include <fmt/format.h>

namespace qsdem {

double Material::wave_speed() const { return std::sqrt(young_modulus / density); }

double critical_time(const Material& mat, double r_min) {
  return 2 * r_min * std::sqrt(mat.density / mat.young_modulus);
}

double damping_factor(DampingModel model, double xi0, double radius, double r_min, const Material& mat) {
  switch (model) {
    case DampingModel::none: return 0.0;
    case DampingModel::od: return 2 * xi0 * mat.wave_speed() / r_min;   // Eq. 15
    case DampingModel::nd: return 2 * xi0 * mat.wave_speed() / radius;  // Eq. 19
  }
  return 0.0;
}

void assign_damping(const Model& model, Particles& p) {
  for (std::size_t i = 0; i < p.size(); ++i) {
    p.damping[i] = damping_factor(model.damping, model.damping_ratio, p.equiv_radius[i], model.r_min,
                                  model.material);
    // Eq. 10 needs 1 - A dt/2 > 0, otherwise the update reverses the velocity every step.
    if (p.damping[i] * model.dt >= 2)
      throw InputError(fmt::format("damping ratio {:.4g} gives A_i dt / 2 = {:.3g} >= 1 for the time step (paper Eq. 10 "
                                   "reverses velocities): lower the damping ratio or time.step_ratio",
                                   model.damping_ratio, 0.5 * p.damping[i] * model.dt));
  }
}

double smallest_equiv_radius(const Particles& p) {
  double r = std::numeric_limits<double>::infinity();
  for (double x : p.equiv_radius) r = std::min(r, x);
  return r;
}

Model base_model(const Params& params, const Particles& particles) {
  Model m;
  m.material = {params.material.density, params.material.young_modulus, params.material.poisson_ratio};
  m.contact = params.contact;
  m.r_min = smallest_equiv_radius(particles);
  m.critical_time = critical_time(m.material, m.r_min);
  m.dt = params.step_ratio * m.critical_time;
  m.servo.proportional_gain = params.servo.proportional_gain;
  m.servo.integral_gain = params.servo.integral_gain;
  m.skin = params.neighbor.skin_ratio * m.r_min;
  m.sort_particles = true;
  m.skip_apart_pairs = true;
  return m;
}

}  // namespace qsdem
