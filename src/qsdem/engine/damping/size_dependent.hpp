// `nd`, size-dependent damping (SPEC 6.1, paper Eq. 17-19): each particle damped with its own
// frequency, A_i = 2 xi_0 omega#_i, omega#_i = sqrt(E/rho) / R_i (R_i its equal-volume radius);
// under inertia scaling the frequency of the scaled particle, sqrt(E/(mu_i rho)) / R_i (SPEC 5.6).
#pragma once
#include <cmath>
#include <string_view>

#include "qsdem/engine/damping/law.hpp"

namespace qsdem {

struct SizeDependentDamping {
  static constexpr std::string_view name = "nd";
  static constexpr RatioRange ratio{};
  static constexpr bool per_step = false, needs_contact_stiffness = false;
  static constexpr Kick kick = Kick::viscous;
  static SizeDependentDamping make(const DampingConstants& c) { return {2 * c.ratio * c.wave_speed}; }

  double two_xi0_c;  // 2 xi_0 sqrt(E/rho) (m/s)
  double factor(const Particles& p, std::size_t i, const DampingInputs&) const {
    return two_xi0_c / (p.equiv_radius[i] * std::sqrt(p.inertia_scale[i]));  // Eq. 19, SPEC 5.6
  }
};

}  // namespace qsdem
