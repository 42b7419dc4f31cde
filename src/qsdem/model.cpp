#include "qsdem/model.hpp"

#include <algorithm>
#include <cmath>
#include <limits>


namespace qsdem {

double Material::wave_speed() const { return std::sqrt(young_modulus / density); }

double critical_time(const Material& mat, double r_min) {
  return 2 * r_min * std::sqrt(mat.density / mat.young_modulus);
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
