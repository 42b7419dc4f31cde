// `od`, global mass damping (SPEC 6.1, paper Eq. 13, 15): every particle damped with the
// highest frequency of the sample, A_i = 2 xi_0 omega_max, omega_max = sqrt(E/rho) / R_min.
#pragma once
#include <string_view>

#include "qsdem/engine/damping/law.hpp"

namespace qsdem {

struct GlobalMassDamping {
  static constexpr std::string_view name = "od";
  static constexpr RatioRange ratio{};
  static constexpr bool per_step = false, needs_contact_stiffness = false;
  static constexpr Kick kick = Kick::viscous;
  static GlobalMassDamping make(const DampingConstants& c) { return {2 * c.ratio * c.wave_speed / c.r_min}; }  // Eq. 15

  double alpha;  // 2 xi_0 omega_max (1/s)
  double factor(const Particles&, std::size_t, const DampingInputs&) const { return alpha; }
};

}  // namespace qsdem
