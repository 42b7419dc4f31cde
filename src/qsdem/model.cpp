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

}  // namespace qsdem
