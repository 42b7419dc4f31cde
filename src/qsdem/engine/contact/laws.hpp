// The contact laws a case can choose ([contact] law = NAME, docs/config.md). A new law is its own
// header (contact/law.hpp says what it declares) and one entry here; the force stages, the pair
// list, the checkpoint and the case file take everything else from its declaration.
#pragma once
#include <string>
#include <string_view>
#include <variant>
#include <vector>

#include "qsdem/engine/contact/hertz_mindlin.hpp"
#include "qsdem/engine/contact/hertz_mindlin_dashpot.hpp"
#include "qsdem/engine/contact/hertz_mindlin_rolling.hpp"

namespace qsdem {

// Registration: one entry per law, the first is the default.
using ContactLaw = std::variant<HertzMindlin, HertzMindlinDashpot, HertzMindlinRolling>;

// The law that settings.law names, made from the constants (InputError for an unknown name).
ContactLaw make_contact_law(const LawConstants& constants);

// The names of the laws, in registration order.
std::vector<std::string_view> contact_law_names();

// The own keys of the law `law` (empty for an unknown name).
std::vector<LawKey> contact_law_keys(std::string_view law);

// What is wrong with the law's keys ("" if nothing); `key` is then the key to name.
std::string check_contact_settings(const ContactSettings& settings, std::string& key);

// The history that some law declares under `name` (nullptr when none does).
const HistoryLayout* find_history_layout(std::string_view name);

}  // namespace qsdem
