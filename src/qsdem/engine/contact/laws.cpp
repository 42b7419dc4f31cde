#include "qsdem/engine/contact/laws.hpp"

#include <fmt/format.h>

#include <utility>

namespace qsdem {
namespace {

// Calls f.template operator()<Law>() for every registered law, in order.
template <class F>
void for_each_law(F&& f) {
  [&]<std::size_t... I>(std::index_sequence<I...>) {
    (f.template operator()<std::variant_alternative_t<I, ContactLaw>>(), ...);
  }(std::make_index_sequence<std::variant_size_v<ContactLaw>>());
}

}  // namespace

ContactLaw make_contact_law(const LawConstants& constants) {
  ContactLaw law;
  bool found = false;
  for_each_law([&]<class Law>() {
    if (!found && Law::name == constants.settings.law) {
      law = Law::make(constants);
      found = true;
    }
  });
  if (!found) throw InputError(fmt::format("unknown contact law '{}'", constants.settings.law));
  return law;
}

std::vector<std::string_view> contact_law_names() {
  std::vector<std::string_view> names;
  for_each_law([&]<class Law>() { names.push_back(Law::name); });
  return names;
}

std::vector<LawKey> contact_law_keys(std::string_view law) {
  std::vector<LawKey> keys;
  for_each_law([&]<class Law>() {
    if (Law::name == law) keys.assign(Law::keys.begin(), Law::keys.end());
  });
  return keys;
}

std::string check_contact_settings(const ContactSettings& settings, std::string& key) {
  std::string why;
  for_each_law([&]<class Law>() {
    if (Law::name == settings.law) why = Law::check(settings, key);
  });
  return why;
}

const HistoryLayout* find_history_layout(std::string_view name) {
  const HistoryLayout* found = nullptr;
  for_each_law([&]<class Law>() {
    if (!found && Law::history.name == name) found = &Law::history;
  });
  return found;
}

}  // namespace qsdem
