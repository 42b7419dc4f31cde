// `none`: no particle damping, A_i = B_i = 0 (SPEC 6.1).
#pragma once
#include <string_view>

#include "qsdem/engine/damping/law.hpp"

namespace qsdem {

struct NoDamping {
  static constexpr std::string_view name = "none";
  static constexpr RatioRange ratio{std::numeric_limits<double>::infinity(), false, "not used", ">= 0"};
  static constexpr bool per_step = false, needs_contact_stiffness = false;
  static constexpr Kick kick = Kick::viscous;
  static NoDamping make(const DampingConstants&) { return {}; }
  double factor(const Particles&, std::size_t, const DampingInputs&) const { return 0.0; }
};

}  // namespace qsdem
