// `stiffness`, contact-stiffness damping (SPEC 6.3): like `nd`, but each particle's frequencies
// from its current contacts, summed by the force stage every step:
//   A_i = 2 xi_0 sqrt(sum_c k_n,c / m_i),  B_i = 2 xi_0 sqrt(sum_c k_t,c |x_c - x_i|^2 / I_min,i),
// I_min the smallest principal moment. A particle without contacts gets 0. The ratio is at most
// 0.5, so that A_i dt / 2 = xi_0 omega_i dt < 1 wherever the undamped leapfrog is stable
// (omega_i dt < 2).
#pragma once
#include <cmath>
#include <string_view>

#include "qsdem/engine/damping/law.hpp"

namespace qsdem {

struct StiffnessDamping {
  static constexpr std::string_view name = "stiffness";
  static constexpr RatioRange ratio{0.5, false, "the nominal damping ratio xi_0", "[0, 50 %]"};
  static constexpr bool per_step = true, needs_contact_stiffness = true;
  static constexpr Kick kick = Kick::viscous;
  static StiffnessDamping make(const DampingConstants& c) { return {2 * c.ratio}; }

  double two_xi0;
  double factor(const Particles& p, std::size_t i, const DampingInputs& in) const {
    return in.contact_stiffness ? two_xi0 * std::sqrt(in.contact_stiffness[i] * p.inv_mass[i]) : 0.0;
  }
  double rotation_factor(const Particles& p, std::size_t i, const DampingInputs& in) const {
    return in.contact_rotational_stiffness
               ? two_xi0 * std::sqrt(in.contact_rotational_stiffness[i] * inv_smallest_moment(p, i))
               : 0.0;
  }
};

}  // namespace qsdem
