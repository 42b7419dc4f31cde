#include "qsdem/engine/damping/models.hpp"

#include <fmt/format.h>

#include <utility>

namespace qsdem {
namespace {

// Calls f.template operator()<Model>() for every registered model, in order.
template <class F>
void for_each_model(F&& f) {
  [&]<std::size_t... I>(std::index_sequence<I...>) {
    (f.template operator()<std::variant_alternative_t<I, DampingLaw>>(), ...);
  }(std::make_index_sequence<std::variant_size_v<DampingLaw>>());
}

}  // namespace

std::vector<std::string_view> damping_names() {
  std::vector<std::string_view> names;
  for_each_model([&]<class D>() { names.push_back(D::name); });
  return names;
}

bool is_damping_model(std::string_view name) {
  bool found = false;
  for_each_model([&]<class D>() { found = found || D::name == name; });
  return found;
}

std::string check_damping(std::string_view name, double ratio, const ContactSettings& law, bool& on_ratio) {
  std::string why;
  on_ratio = false;
  for_each_model([&]<class D>() {
    if (D::name != name || !why.empty()) return;
    if constexpr (requires { D::check(ratio, law); }) why = D::check(ratio, law);
    if (why.empty() && !D::ratio.contains(ratio)) {
      on_ratio = true;
      why = ratio < 0 ? std::string("must be >= 0")
                      : fmt::format("out of range: with model \"{}\" it is {}, in {}", D::name, D::ratio.meaning,
                                    D::ratio.shown);
    }
  });
  return why;
}

ResolvedDamping resolve_damping(std::string_view name, const DampingConstants& c, DampedMotion acts_on) {
  ResolvedDamping r;
  bool found = false;
  for_each_model([&]<class D>() {
    if (found || D::name != name) return;
    found = true;
    const D model = D::make(c);
    r.law = model;
    r.acts_on = acts_on;
    r.per_step = D::per_step;
    r.needs_contact_stiffness = D::needs_contact_stiffness;
    if constexpr (D::kick == Kick::cundall) {
      r.cundall_translation = acts_on != DampedMotion::rotation ? model.cundall_alpha() : 0.0;
      r.cundall_rotation = acts_on != DampedMotion::translation ? model.cundall_alpha() : 0.0;
    }
  });
  if (!found) throw InputError(fmt::format("unknown damping model '{}'", name));
  return r;
}

ContactSettings phase_contact_settings(std::string_view damping, double ratio, const ContactSettings& law) {
  ContactSettings s = law;
  for_each_model([&]<class D>() {
    if constexpr (requires { D::contact_law(ratio); })
      if (D::name == damping) s = D::contact_law(ratio);
  });
  return s;
}

}  // namespace qsdem
