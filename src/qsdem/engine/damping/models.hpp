// The particle damping models a case can choose (`damping.model`, docs/config.md). A new model is
// its own header (damping/law.hpp says what it declares) and one entry here; the case parser, the
// compiled Model and the stages take everything else from its declaration.
#pragma once
#include <string>
#include <string_view>
#include <variant>
#include <vector>

#include "qsdem/engine/damping/contact.hpp"
#include "qsdem/engine/damping/global_mass.hpp"
#include "qsdem/engine/damping/local.hpp"
#include "qsdem/engine/damping/none.hpp"
#include "qsdem/engine/damping/size_dependent.hpp"
#include "qsdem/engine/damping/stiffness.hpp"

namespace qsdem {

// Registration: one entry per model.
using DampingLaw = std::variant<NoDamping, GlobalMassDamping, SizeDependentDamping, LocalDamping, StiffnessDamping,
                                ContactDamping>;

// The damping of a phase as the stages read it: the model, what it acts on, and what it asks of
// the force stage and the kick, resolved together by resolve_damping.
struct ResolvedDamping {
  DampingLaw law = NoDamping{};
  DampedMotion acts_on = DampedMotion::both;
  bool per_step = false;                 // the damping stage refills the factors before every kick
  bool needs_contact_stiffness = false;  // the force stage sums each particle's contact stiffnesses
  // Cundall's alpha of the kick on translation and on rotation (0 on the motion acts_on leaves
  // out, and for a viscous model).
  double cundall_translation = 0, cundall_rotation = 0;
};

// The names of the models, in registration order.
std::vector<std::string_view> damping_names();

// Whether `name` is a registered model.
bool is_damping_model(std::string_view name);

// What is wrong with model `name` at `ratio` on the case's contact law ("" if nothing); `on_ratio`
// tells whether the message is about the ratio (else about the model).
std::string check_damping(std::string_view name, double ratio, const ContactSettings& law, bool& on_ratio);

// The damping of a phase (InputError for an unknown name).
ResolvedDamping resolve_damping(std::string_view name, const DampingConstants& constants,
                                DampedMotion acts_on = DampedMotion::both);

// The contact law of a phase: the case's, or the one the damping model implies.
ContactSettings phase_contact_settings(std::string_view damping, double ratio, const ContactSettings& law);

}  // namespace qsdem
