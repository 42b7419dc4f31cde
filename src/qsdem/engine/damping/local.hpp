// `local`, Cundall's non-viscous damping (SPEC 6.2; PFC's local damping, YADE's NewtonIntegrator
// `damping`): no viscous factor; the kick damps each component k of the force and of the moment,
// F_k <- F_k - alpha |F_k| sign(v_k) (integrator.cpp), alpha = the phase's ratio.
#pragma once
#include <string_view>

#include "qsdem/engine/damping/law.hpp"

namespace qsdem {

struct LocalDamping {
  static constexpr std::string_view name = "local";
  static constexpr RatioRange ratio{1, true, "Cundall's alpha", "[0, 1)"};
  static constexpr bool per_step = false, needs_contact_stiffness = false;
  static constexpr Kick kick = Kick::cundall;
  static LocalDamping make(const DampingConstants& c) { return {c.ratio}; }

  double alpha;
  double cundall_alpha() const { return alpha; }
  double factor(const Particles&, std::size_t, const DampingInputs&) const { return 0.0; }
};

}  // namespace qsdem
