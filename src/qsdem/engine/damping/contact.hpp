// `contact`: no particle damping; the damping is in the contacts (SPEC 6.4): the phase's contact
// law becomes hertz_mindlin_dashpot with the dashpots' damping ratio zeta = the phase's ratio.
// It adds the dashpots to the elastic law hertz_mindlin only.
#pragma once
#include <string>
#include <string_view>

#include <fmt/format.h>

#include "qsdem/engine/damping/law.hpp"

namespace qsdem {

struct ContactDamping {
  static constexpr std::string_view name = "contact";
  static constexpr RatioRange ratio{1, true, "the dashpots' damping ratio", "[0, 1)"};
  static constexpr bool per_step = false, needs_contact_stiffness = false;
  static constexpr Kick kick = Kick::viscous;
  static ContactDamping make(const DampingConstants&) { return {}; }

  static std::string check(double, const ContactSettings& law) {
    if (law.law == "hertz_mindlin") return {};
    return fmt::format("\"contact\" adds the dashpots to contact.law = \"hertz_mindlin\", not to \"{}\": give the "
                       "dashpots either by this model and its ratio or by the law's keys, not both",
                       law.law);
  }
  static ContactSettings contact_law(double ratio) {
    ContactSettings s;
    s.law = "hertz_mindlin_dashpot";
    s.values["damping_ratio"] = ratio;
    return s;
  }

  double factor(const Particles&, std::size_t, const DampingInputs&) const { return 0.0; }
};

}  // namespace qsdem
