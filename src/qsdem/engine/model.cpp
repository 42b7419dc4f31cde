#include "qsdem/engine/model.hpp"

#include <algorithm>
#include <cmath>
#include <limits>
#include <stdexcept>

namespace qsdem {

double Material::wave_speed() const { return std::sqrt(young_modulus / density); }

ContactLaw make_contact_law(const Material& m, double friction, const ContactSettings& settings) {
  return make_contact_law({m.effective_modulus(), m.effective_shear_modulus(), friction, settings});
}

const ContactLaw& contact_law_of(const Model& model) {
  if (!model.contact_law)
    throw std::logic_error("a Model without a contact law: make it with phase_model, or set contact_law by "
                           "make_contact_law");
  return *model.contact_law;
}

double critical_time(const Material& mat, double r_min) {
  return 2 * r_min * std::sqrt(mat.density / mat.young_modulus);
}

double smallest_equiv_radius(const Particles& p) {
  double r = std::numeric_limits<double>::infinity();
  for (double x : p.equiv_radius) r = std::min(r, x);
  return r;
}

}  // namespace qsdem
