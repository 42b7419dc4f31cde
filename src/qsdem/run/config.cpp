#include "qsdem/run/config.hpp"

#include <fmt/format.h>

#include <algorithm>
#include <cctype>
#include <cerrno>
#include <charconv>
#include <cmath>
#include <cstring>
#include <filesystem>
#include <fstream>
#include <functional>
#include <limits>
#include <optional>
#include <set>
#include <sstream>
#include <tuple>
#include <utility>

#define TOML_EXCEPTIONS 1
#include <toml++/toml.h>

#include "qsdem/engine/contact/laws.hpp"
#include "qsdem/engine/damping/models.hpp"
#include "qsdem/run/controller.hpp"
#include "qsdem/run/files.hpp"
#include "qsdem/run/toml_reader.hpp"
#include "qsdem/run/units.hpp"

namespace qsdem {

namespace {

std::vector<std::string> split_path(const std::string& path) {
  std::vector<std::string> parts;
  std::stringstream ss(path);
  for (std::string p; std::getline(ss, p, '.');) parts.push_back(p);
  return parts;
}

bool is_index(const std::string& s) {
  return !s.empty() && s.find_first_not_of("0123456789") == std::string::npos;
}

// An index's value (is_index), SIZE_MAX when it is too large to be one: out of range of any array.
std::size_t index_value(const std::string& s) {
  std::size_t v = 0;
  const auto [end, err] = std::from_chars(s.data(), s.data() + s.size(), v);
  return err == std::errc() && end == s.data() + s.size() ? v : SIZE_MAX;
}

// Applies "a.b.c=value" to the table; the value is parsed as TOML, or kept as a string.
void apply_override(toml::table& root, const std::string& assignment) {
  require_utf8(assignment, "--set");  // a value that is not TOML is kept as a string, unchecked by the parser
  const auto eq = assignment.find('=');
  if (eq == std::string::npos || eq == 0)
    throw InputError(fmt::format("--set '{}': expected key=value, e.g. damping.ratio=\"0.3 %\"",
                                 assignment));
  const std::string key = assignment.substr(0, eq);
  const std::string text = assignment.substr(eq + 1);
  toml::table parsed;  // holds the value as "v"
  try {
    parsed = toml::parse("v = " + text, "--set " + key);
  } catch (const toml::parse_error&) {
    parsed = toml::table{};
    parsed.insert("v", text);  // not TOML: a bare string such as nd or 0.3 %
  }
  toml::node& value = *parsed.get("v");
  const auto parts = split_path(key);
  toml::node* node = &root;
  for (std::size_t k = 0; k + 1 < parts.size(); ++k) {
    const std::string& p = parts[k];
    if (auto* arr = node->as_array(); arr && is_index(p)) {
      const auto idx = index_value(p);
      if (idx >= arr->size())
        throw InputError(fmt::format("--set '{}': index {} is out of range ({} entries)", key,
                                     p, arr->size()));
      node = arr->get(idx);
    } else if (auto* tbl = node->as_table()) {
      if (!tbl->contains(p)) tbl->insert(p, toml::table{});
      node = tbl->get(p);
    } else {
      throw InputError(fmt::format("--set '{}': '{}' is not a table", key, p));
    }
  }
  const std::string& last = parts.back();
  if (auto* arr = node->as_array(); arr && is_index(last)) {
    const auto idx = index_value(last);
    if (idx >= arr->size())
      throw InputError(fmt::format("--set '{}': index {} is out of range ({} entries)", key, last, arr->size()));
    arr->replace(arr->begin() + static_cast<std::ptrdiff_t>(idx), std::move(value));
  } else if (auto* tbl = node->as_table()) {
    tbl->insert_or_assign(last, std::move(value));
  } else {
    throw InputError(fmt::format("--set '{}': parent of '{}' is not a table", key, last));
  }
}

// Reads keys from the TOML tree, remembering which were read so that leftovers are reported
// as unknown keys.
class Reader : public TomlSource {
 public:
  Reader(const toml::table& root, std::string source) : TomlSource(std::move(source)), root_(root) {}

  const toml::node* find(const std::string& path) const {
    const toml::node* node = &root_;
    for (const auto& p : split_path(path)) {
      if (const auto* tbl = node->as_table()) {
        node = tbl->get(p);
      } else if (const auto* arr = node->as_array(); arr && is_index(p)) {
        node = arr->get(index_value(p));
      } else {
        return nullptr;
      }
      if (!node) return nullptr;
    }
    return node;
  }

  const toml::node* get(const std::string& path, bool required) {
    const toml::node* n = find(path);
    if (!n && required) {
      // Name what the table does hold: a missing key is most often a misspelt one.
      std::string why = "is required but missing";
      const auto dot = path.rfind('.');
      const toml::node* parent = dot == std::string::npos ? &root_ : find(path.substr(0, dot));
      if (const auto* tbl = parent ? parent->as_table() : nullptr; tbl && !tbl->empty()) {
        std::string keys;
        for (const auto& [k, v] : *tbl) keys += (keys.empty() ? "" : ", ") + std::string(k.str());
        why += fmt::format(" ({} has: {})", where(parent), keys);
      }
      fail(path, nullptr, why);
    }
    asked_.insert(path);
    if (n) used_.insert(path);
    if (const std::string w = written(path); w != path) {  // the key the case wrote, asked and read
      asked_.insert(w);
      if (find(w)) used_.insert(w);
    }
    return n;
  }

  // Every key some reader asked for, found or not (case_keys).
  const std::set<std::string>& asked() const { return asked_; }

  // Keys under `path` stand for those under `written` in messages (the [[phase]] tables written
  // from [compaction] and [triaxial]: a message names the key the case wrote, at its line).
  void alias(const std::string& path, const std::string& written) { aliases_[path] = written; }

  // The key the case wrote for `path`: its alias, or that of its longest aliased prefix.
  std::string written(const std::string& path) const {
    for (std::string p = path;;) {
      if (const auto it = aliases_.find(p); it != aliases_.end()) return it->second + path.substr(p.size());
      const auto dot = p.rfind('.');
      if (dot == std::string::npos) return path;
      p.resize(dot);
    }
  }

  // Throws InputError naming the key the case wrote (with its node, for its line).
  [[noreturn]] void fail(const std::string& path, const toml::node* n, const std::string& why) const {
    const std::string w = written(path);
    TomlSource::fail(w, written_node(path, w, n), why);
  }

  using Check = std::function<bool(double)>;

  double quantity(const std::string& path, Dimension dim, std::optional<double> def,
                  const Check& ok, const std::string& allowed) {
    const toml::node* n = get(path, !def.has_value());
    if (!n) return *def;
    double v = 0;
    if (n->is_string()) {
      try {
        v = parse_quantity(*n->value<std::string>(), dim);
      } catch (const InputError& e) {
        fail(path, n, e.what());
      }
    } else if (dim == Dimension::ratio && (n->is_floating_point() || n->is_integer())) {
      v = *n->value<double>();
    } else {
      fail(path, n, fmt::format("expected a string with a unit ({}), e.g. \"{}\"",
                                allowed_units(dim), example(dim)));
    }
    if (!std::isfinite(v) || !ok(v)) fail(path, n, "out of range: " + allowed);
    return v;
  }

  double number(const std::string& path, std::optional<double> def, const Check& ok,
                const std::string& allowed) {
    const toml::node* n = get(path, !def.has_value());
    if (!n) return *def;
    if (!(n->is_floating_point() || n->is_integer())) fail(path, n, "expected a number");
    const double v = *n->value<double>();
    if (!std::isfinite(v) || !ok(v)) fail(path, n, "out of range: " + allowed);
    return v;
  }

  long integer(const std::string& path, std::optional<long> def, long lo, long hi) {
    const toml::node* n = get(path, !def.has_value());
    if (!n) return *def;
    if (!n->is_integer()) {
      const double d = n->is_floating_point() ? *n->value<double>() : 0.5;
      fail(path, n, d == std::floor(d) && std::abs(d) < 1e15
                        ? fmt::format("expected a whole number written without a decimal point: {}", long(d))
                        : std::string("expected a whole number (an integer), e.g. 100"));
    }
    const long v = static_cast<long>(*n->value<std::int64_t>());
    if (v < lo || v > hi) fail(path, n, fmt::format("out of range: must be in [{}, {}]", lo, hi));
    return v;
  }

  bool boolean(const std::string& path, bool def) {
    const toml::node* n = get(path, false);
    if (!n) return def;
    if (!n->is_boolean()) fail(path, n, "expected true or false");
    return *n->value<bool>();
  }

  std::string text(const std::string& path, std::optional<std::string> def,
                   const std::vector<std::string>& choices) {
    const toml::node* n = get(path, !def.has_value());
    if (!n) return *def;
    if (!n->is_string()) fail(path, n, "expected a string");
    std::string v = *n->value<std::string>();
    if (!choices.empty() && std::find(choices.begin(), choices.end(), v) == choices.end()) {
      std::string list;
      for (const auto& c : choices) list += (list.empty() ? "" : ", ") + ("\"" + c + "\"");
      fail(path, n, "allowed values: " + list);
    }
    return v;
  }

  const toml::array* array_of_tables(const std::string& path) {
    const toml::node* n = get(path, true);
    const auto* arr = n->as_array();
    if (!arr || arr->empty() || !arr->is_array_of_tables())
      fail(path, n, fmt::format("expected a non-empty array of tables ([[{}]] entries)", path));
    return arr;
  }

  // An optional key: nullopt when absent (asked all the same, for case_keys).
  std::optional<double> optional_number(const std::string& path, const Check& ok, const std::string& allowed) {
    if (!get(path, false)) return std::nullopt;
    return number(path, std::nullopt, ok, allowed);
  }
  std::optional<double> optional_quantity(const std::string& path, Dimension dim, const Check& ok,
                                          const std::string& allowed) {
    if (!get(path, false)) return std::nullopt;
    return quantity(path, dim, std::nullopt, ok, allowed);
  }
  std::optional<long> optional_integer(const std::string& path, long lo, long hi) {
    if (!get(path, false)) return std::nullopt;
    return integer(path, std::nullopt, lo, hi);
  }

  // An array of plain values, each checked by `element` (which returns the value or a reason).
  template <class T, class Element>
  std::vector<T> list(const std::string& path, const char* expected, Element element) {
    const toml::node* n = get(path, true);
    const auto* arr = n->as_array();
    if (!arr) fail(path, n, fmt::format("expected an array of {}", expected));
    std::vector<T> out;
    for (std::size_t k = 0; k < arr->size(); ++k) {
      std::string why;
      const std::optional<T> v = element(*arr->get(k), why);
      if (!v) fail(path, n, fmt::format("entry {} ({}): {}", k, describe(*arr->get(k)), why));
      out.push_back(*v);
    }
    return out;
  }

  // Reports the first key that no reader asked for.
  void reject_unknown() const { visit_unknown(root_, ""); }

 private:
  static const char* example(Dimension d) {
    switch (d) {
      case Dimension::length: return "2.13 mm";
      case Dimension::stress: return "390 kPa";
      case Dimension::density: return "2650 kg/m^3";
      case Dimension::ratio: return "0.5 %";
      case Dimension::time: return "1 s";
    }
    return "";
  }

  // A table the case may hold, named without its array indices ("phase.0.stop" -> "phase.stop").
  static bool known_section(const std::string& path) {
    static const std::set<std::string> sections{
        "material",       "sample",           "sample.particles",      "sample.grading",
        "time",           "contact",          "damping",
        "compaction",     "triaxial",         "triaxial.rate_control", "servo",
        "neighbor",       "checkpoint",       "limits",
        "output",         "phase",            "phase.damping",
        "phase.strain_rate", "phase.stress",  "phase.servo",
        "phase.stop",     "phase.stop.strain", "phase.stop.stress",
        "phase.stop.equilibrium", "phase.output", "phase.output.every_strain",
        "phase.controller", "compaction.inertia_scaling", "triaxial.inertia_scaling",
        "phase.inertia_scaling", "phase.solver"};
    std::string name;
    for (const auto& part : split_path(path))
      if (!is_index(part)) name += (name.empty() ? "" : ".") + part;
    return sections.count(name) > 0;
  }

  void visit_unknown(const toml::node& node, const std::string& prefix) const {
    if (const auto* tbl = node.as_table()) {
      for (const auto& [k, v] : *tbl) {
        const std::string path = prefix.empty() ? std::string(k.str()) : prefix + "." + std::string(k.str());
        if (v.is_table() || v.is_array_of_tables()) {
          if (!known_section(path))
            throw InputError(fmt::format("{}: unknown section '{}' (see docs/config.md for the sections)",
                                         where(&v), path));
          visit_unknown(v, path);
        } else if (!used_.count(path)) {
          const std::string w = written(path);  // a key of a written phase: the case's own
          throw InputError(fmt::format("{}: unknown key '{}' (see docs/config.md for the keys)",
                                       where(written_node(path, w, &v)), w));
        }
      }
    } else if (const auto* arr = node.as_array()) {
      for (std::size_t i = 0; i < arr->size(); ++i) visit_unknown(*arr->get(i), prefix + "." + std::to_string(i));
    }
  }

  // The node of `w` = written(path), for its line: n itself, or the written key's when there is one.
  const toml::node* written_node(const std::string& path, const std::string& w, const toml::node* n) const {
    const toml::node* at = w == path ? n : find(w);
    return at ? at : n;
  }

  const toml::table& root_;
  std::set<std::string> used_;
  std::set<std::string> asked_;
  std::map<std::string, std::string> aliases_;
};

const auto positive = [](double v) { return v > 0; };
const auto non_negative = [](double v) { return v >= 0; };

// A phase's damping model and ratio: the model's name, its ratio's range and its check on the case's
// contact law from its declaration (damping/models.hpp).
std::pair<std::string, double> damping_model(Reader& r, const std::string& model_key, const std::string& ratio_key,
                                             const ContactSettings& contact) {
  const std::vector<std::string_view> names = damping_names();
  const std::string model = r.text(model_key, std::string("nd"), std::vector<std::string>(names.begin(), names.end()));
  const double ratio = r.quantity(ratio_key, Dimension::ratio, 0.005, non_negative, "must be >= 0");
  bool on_ratio = false;
  if (const std::string why = check_damping(model, ratio, contact, on_ratio); !why.empty()) {
    const std::string& key = on_ratio ? ratio_key : model_key;
    r.fail(key, r.find(key), why);
  }
  return {model, ratio};
}

DampedMotion damped_motion(Reader& r, const std::string& path) {
  const std::string m = r.text(path, std::string("both"), {"both", "translation", "rotation"});
  return m == "translation" ? DampedMotion::translation : m == "rotation" ? DampedMotion::rotation : DampedMotion::both;
}

// `<k>.inertia_scaling` (SPEC 5.6): off when absent; on with target = "coarsest" or factor = F, and
// the cap of mu_i. Its keys are asked whether or not the table is there (case_keys).
InertiaScaling inertia_scaling(Reader& r, const std::string& k) {
  const std::string key = k + ".inertia_scaling";
  if (const toml::node* n = r.find(key); n && !n->is_table())
    r.fail(key, n, "expected a table: { target = \"coarsest\" } or { factor = F }, optionally with cap = C");
  InertiaScaling s;
  const std::string target = r.text(key + ".target", std::string(), {"coarsest"});
  const auto factor = r.optional_number(key + ".factor", [](double v) { return v > 1 && v <= 1e3; },
                                        "must be in (1, 1000]: the target step over the unscaled one");
  s.cap = r.number(key + ".cap", s.cap, [](double v) { return v >= 1 && v <= 1e6; },
                   "must be in [1, 10^6]: the largest factor on a particle's mass");
  if (!target.empty() && factor)
    r.fail(key + ".factor", r.find(key + ".factor"), "give one of target and factor, not both");
  if (!target.empty()) s.target = InertiaScaling::Target::coarsest;
  if (factor) s.target = InertiaScaling::Target::factor, s.factor = *factor;
  if (const toml::node* n = r.find(key); n && !s.on())
    r.fail(key, n, "needs target = \"coarsest\" or factor = F (> 1)");
  return s;
}

// [contact]: the law (contact/laws.hpp) and the keys it declares, checked by the law.
ContactSettings read_contact(Reader& r) {
  ContactSettings c;
  const std::vector<std::string_view> laws = contact_law_names();
  c.law = r.text("contact.law", std::string(laws.front()), std::vector<std::string>(laws.begin(), laws.end()));
  const std::vector<LawKey> keys = contact_law_keys(c.law);
  const toml::node* table = r.find("contact");
  if (table && table->is_table()) {
    for (const auto& [k, v] : *table->as_table()) {
      const std::string name(k.str()), path = "contact." + name;
      if (name == "law") continue;
      bool own = false;
      std::string list;
      for (const LawKey& key : keys) {
        own = own || key.name == name;
        list += fmt::format("{}{} ({})", list.empty() ? "" : ", ", key.name, key.meaning);
      }
      if (!own)
        r.fail(path, &v, fmt::format("not a key of contact law \"{}\" ({})", c.law,
                                     list.empty() ? "it has no keys of its own" : "its keys: " + list));
      c.values[name] = r.quantity(path, Dimension::ratio, 0.0, [](double) { return true; }, "");
    }
  }
  std::string key;
  if (const std::string why = check_contact_settings(c, key); !why.empty())
    r.fail("contact." + key, r.find("contact." + key), why);
  return c;
}

// Particle sizes qsdem accepts: from 1 nm to 1 km. Outside, masses and inertias of a double run
// out of range (a 1e-320 m sphere has a mass of 0) long before the physics has a meaning.
constexpr double min_particle_size = 1e-9, max_particle_size = 1e3;
bool particle_size(double v) { return v >= min_particle_size && v <= max_particle_size; }

// [[sample.grading]]: the points of a sieve curve (docs/physics.md 8.6), each a size and its
// percent passing by mass; the shape of interval k = [d_k, d_k+1] from point k+1's `shape`, else
// from sample.grading_shape.
Grading read_grading(Reader& r, const toml::array& points) {
  const std::string key = "sample.grading";
  if (points.size() < 2)
    r.fail(key, r.find(key), fmt::format("a sieve curve needs at least 2 points (it has {}): the smallest size "
                                         "at 0 % passing and the largest at 100 %", points.size()));
  // a/b of a shape: 1 for a sphere; a spheroid's own aspect_ratio, or the one it inherits.
  const auto read_shape = [&](const std::string& shape_key, const std::string& ratio_key, double inherited) {
    const std::string shape = r.text(shape_key, std::string(inherited > 1 ? "spheroid" : "sphere"), {"sphere", "spheroid"});
    if (shape == "sphere") return 1.0;
    return r.number(ratio_key, inherited > 1 ? std::optional(inherited) : std::nullopt,
                    [](double v) { return v >= 1 && v <= 100; }, "must be in [1, 100] (a/b of a prolate spheroid, SPEC 2)");
  };
  const double whole = read_shape("sample.grading_shape", "sample.grading_aspect_ratio", 1);
  Grading g;
  for (std::size_t k = 0; k < points.size(); ++k) {
    const std::string p = fmt::format("{}.{}.", key, k);
    const double d = r.quantity(p + "size", Dimension::length, std::nullopt, particle_size, "must be from 1 nm to 1 km");
    const double pass = r.quantity(p + "passing", Dimension::ratio, std::nullopt,
                                   [](double v) { return v >= 0 && v <= 1; }, "must be from 0 % to 100 % (0 to 1 as a plain number)");
    if (k > 0 && !(d > g.size.back()))
      r.fail(p + "size", r.find(p + "size"),
             fmt::format("the sizes must increase from point to point: point {}'s is {:g} mm", k - 1, 1e3 * g.size.back()));
    if (k > 0 && pass < g.passing.back())
      r.fail(p + "passing", r.find(p + "passing"),
             fmt::format("the percent passing must not decrease from point to point: point {}'s is {:g} %", k - 1,
                         100 * g.passing.back()));
    if (k == 0 && pass != 0)
      r.fail(p + "passing", r.find(p + "passing"),
             "the first point is the sample's smallest size and must pass 0 %: add a point below the finest sieve");
    if (k + 1 == points.size() && pass != 1)
      r.fail(p + "passing", r.find(p + "passing"), "the last point is the sample's largest size and must pass 100 %");
    for (const char* shape_key : {"shape", "aspect_ratio"})
      if (k == 0 && r.find(p + shape_key))
        r.fail(p + shape_key, r.find(p + shape_key),
               "the first point opens the curve: a shape belongs to a later point, for the interval that ends there");
    if (k > 0) g.aspect_ratio.push_back(read_shape(p + "shape", p + "aspect_ratio", whole));
    g.size.push_back(d);
    g.passing.push_back(pass);
  }
  return g;
}

SizeClass read_size_class(Reader& r, const std::string& p) {
  SizeClass c;
  const std::string shape = r.text(p + ".shape", std::string("sphere"), {"sphere", "spheroid", "ellipsoid"});
  const std::string allowed = "must be from 1 nm to 1 km";
  if (shape == "sphere") {
    const double d = r.quantity(p + ".diameter", Dimension::length, std::nullopt, particle_size, allowed);
    c.shape = ShapeKind::sphere;
    c.semi_axes = Vec3::Constant(d / 2);
  } else if (shape == "spheroid") {
    const double a = r.quantity(p + ".major_semi_axis", Dimension::length, std::nullopt, particle_size, allowed);
    const double b = r.quantity(p + ".minor_semi_axis", Dimension::length, std::nullopt, particle_size, allowed);
    if (a < b) r.fail(p + ".major_semi_axis", r.find(p + ".major_semi_axis"),
                      "the major semi-axis must be >= the minor one (prolate spheroid, SPEC 2)");
    c.shape = a == b ? ShapeKind::sphere : ShapeKind::ellipsoid;
    c.semi_axes = Vec3(a, b, b);
  } else {
    const toml::node* n = r.get(p + ".semi_axes", true);
    const auto* arr = n->as_array();
    if (!arr || arr->size() != 3) r.fail(p + ".semi_axes", n, "expected 3 lengths [a, b, c]");
    for (int k = 0; k < 3; ++k) {
      const auto* e = arr->get(static_cast<std::size_t>(k));
      if (!e->is_string()) r.fail(p + ".semi_axes", n, "each semi-axis is a string with a unit");
      try {
        c.semi_axes[k] = parse_quantity(*e->value<std::string>(), Dimension::length);
      } catch (const InputError& err) {
        r.fail(p + ".semi_axes", n, err.what());
      }
      if (!particle_size(c.semi_axes[k])) r.fail(p + ".semi_axes", n, "each semi-axis must be from 1 nm to 1 km");
    }
    if (!(c.semi_axes[0] >= c.semi_axes[1] && c.semi_axes[1] >= c.semi_axes[2]))
      r.fail(p + ".semi_axes", n, "order them a >= b >= c (SPEC 2)");
    c.shape = c.semi_axes[0] == c.semi_axes[2] ? ShapeKind::sphere : ShapeKind::ellipsoid;
  }
  c.count = r.integer(p + ".count", std::nullopt, 1, 100'000'000);
  return c;
}

// The [phase.controller] table for a controller kind: the Reader under the table's path.
class ControllerTable final : public ControllerKeys {
 public:
  ControllerTable(Reader& r, std::string prefix) : r_(r), prefix_(std::move(prefix)) {}
  std::string text(const std::string& key, const std::vector<std::string>& choices) override {
    return r_.text(path(key), std::nullopt, choices);
  }
  std::vector<long> integers(const std::string& key, long lo, long hi) override {
    return r_.list<long>(path(key), "whole numbers", [&](const toml::node& e, std::string& why) -> std::optional<long> {
      if (!e.is_integer()) return why = "expected a whole number", std::nullopt;
      const long v = static_cast<long>(*e.value<std::int64_t>());
      if (v < lo || v > hi) return why = fmt::format("out of range: must be in [{}, {}]", lo, hi), std::nullopt;
      return v;
    });
  }
  std::vector<double> numbers(const std::string& key) override {
    return r_.list<double>(path(key), "numbers", [](const toml::node& e, std::string& why) -> std::optional<double> {
      if (!(e.is_floating_point() || e.is_integer()) || !std::isfinite(*e.value<double>()))
        return why = "expected a finite number", std::nullopt;
      return *e.value<double>();
    });
  }
  std::vector<double> quantities(const std::string& key, Dimension dim) override {
    return r_.list<double>(path(key), "strings with a unit",
                           [dim](const toml::node& e, std::string& why) -> std::optional<double> {
                             if (!e.is_string()) return why = "expected a string with a unit", std::nullopt;
                             try {
                               return parse_quantity(*e.value<std::string>(), dim);
                             } catch (const InputError& err) {
                               return why = err.what(), std::nullopt;
                             }
                           });
  }
  std::string text_or(const std::string& key, const std::string& def, const std::vector<std::string>& choices) override {
    return r_.text(path(key), def, choices);
  }
  double number(const std::string& key, std::optional<double> def, const std::function<bool(double)>& ok,
                const std::string& allowed) override {
    return r_.number(path(key), def, ok, allowed);
  }
  double quantity(const std::string& key, std::optional<double> def, const std::function<bool(double)>& ok,
                  const std::string& allowed) override {
    return r_.quantity(path(key), Dimension::ratio, def, ok, allowed);
  }
  long integer(const std::string& key, long def, long lo, long hi) override { return r_.integer(path(key), def, lo, hi); }
  double stress(const std::string& key, std::optional<double> def, const std::function<bool(double)>& ok,
                const std::string& allowed) override {
    return r_.quantity(path(key), Dimension::stress, def, ok, allowed);
  }
  bool has(const std::string& key) override { return r_.find(path(key)) != nullptr; }
  [[noreturn]] void fail(const std::string& key, const std::string& why) override {
    r_.fail(path(key), r_.find(path(key)), why);
  }

 private:
  std::string path(const std::string& key) const { return prefix_ + "." + key; }
  Reader& r_;
  std::string prefix_;
};

// `<k>.solver` (docs/physics.md 5.7): absent or kind = "dynamic" for the dynamics at the phase's
// rates; kind = "fire" for increments relaxed by FIRE, with their tolerances.
std::optional<FireSolver> fire_solver(Reader& r, const std::string& k) {
  const std::string key = k + ".solver";
  if (const toml::node* n = r.find(key); n && !n->is_table())
    r.fail(key, n, "expected a table: { kind = \"fire\", strain_increment = \"0.01 %\", ufr = \"0.1 %\" }");
  const std::string kind = r.text(key + ".kind", std::string("dynamic"), {"dynamic", "fire"});
  const std::vector<std::string> keys{"strain_increment", "ufr", "imom", "stress_tolerance", "max_iterations",
                                      "check_every"};
  if (kind == "dynamic")
    for (const std::string& name : keys)
      if (r.find(key + "." + name)) r.fail(key + "." + name, r.find(key + "." + name), "only with kind = \"fire\"");
  // Its keys are asked whether or not the table is there (case_keys).
  FireSolver f;
  f.strain_increment = r.quantity(key + ".strain_increment", Dimension::ratio, f.strain_increment,
                                  [](double v) { return v > 0 && v <= 0.01; }, "must be in (0, 1 %]");
  f.ufr = r.quantity(key + ".ufr", Dimension::ratio, f.ufr, positive, "must be > 0");
  f.imom = r.optional_quantity(key + ".imom", Dimension::ratio, positive, "must be > 0");
  f.stress_tolerance = r.quantity(key + ".stress_tolerance", Dimension::ratio, f.stress_tolerance, positive, "must be > 0");
  f.max_iterations = r.integer(key + ".max_iterations", f.max_iterations, 1, 1'000'000'000);
  f.check_every = r.integer(key + ".check_every", f.check_every, 1, 1'000'000);
  if (kind == "dynamic") return std::nullopt;
  return f;
}

// What a FIRE phase refuses: its own dissipation is FIRE's, its rows are its increments, and it
// ends on strain, stress or steps.
void check_fire_phase(Reader& r, const std::string& k, const Phase& ph) {
  const std::string why = "not in a phase with solver.kind = \"fire\"";
  for (const std::string name : {".damping.model", ".damping.ratio", ".damping.acts_on", ".controller",
                                 ".stop.equilibrium", ".output.points", ".output.every_steps", ".output.every_strain"})
    if (const toml::node* n = r.find(k + name))
      r.fail(k + name, n,
             why + (name.starts_with(".damping") ? ": FIRE is the phase's dissipation (the particle damping is off)"
                    : name.starts_with(".output")  ? ": each increment writes one row"
                    : name == ".controller"        ? ": the increments set the pace"
                                                   : ": each increment is relaxed to the solver's tolerances"));
  if (const toml::node* e = r.find("output.energy"); e && e->value<bool>().value_or(false))
    r.fail(k + ".solver", r.find(k + ".solver"),
           "not with output.energy = true: the energy ledger holds no term for FIRE's stops and mixing");
  bool driven = false;
  for (const auto& c : ph.controls.component) driven = driven || c.kind == ControlKind::strain_rate;
  if (!driven)
    r.fail(k + ".solver", r.find(k + ".solver"),
           "a FIRE phase needs a strain_rate component: its increments are steps of strain (their direction and "
           "proportions from the rates)");
}

// Default sample points: 250 over a phase whose end is known in advance, else every 200 steps.
constexpr long default_points = 250, default_every_steps = 200, default_max_steps = 2'000'000;
// The most steps a phase may plan: a year of the fastest stepping on the smallest sample, and far
// below the step counter's range (a rate near 1e-20 plans past it).
constexpr double max_planned_steps = 1e12;

// A phase's controls: a strain rate or a stress per component, the components that hold the
// volume, and the cap of the servo's rate.
void read_phase_controls(Reader& r, const std::string& k, Phase& ph) {
  bool any_rate = false;
  for (int c = 0; c < component_count; ++c) {
    const std::string name = component_names[static_cast<std::size_t>(c)];
    const std::string rate_key = k + ".strain_rate." + name, stress_key = k + ".stress." + name;
    const auto rate = r.optional_number(rate_key, [](double v) { return v != 0 && std::abs(v) < 0.01; },
                                        "eps' must be nonzero and in (-0.01, 0.01); leave the component out to fix it");
    const auto stress = r.optional_quantity(
        stress_key, Dimension::stress, [c](double v) { return !is_normal(c) || v > 0; },
        is_normal(c) ? "a normal stress target must be > 0 (compression positive)" : "any stress");
    if (rate && stress)
      r.fail(stress_key, r.find(stress_key),
             fmt::format("component {} has a strain_rate too: give one control per component", name));
    auto& control = ph.controls.component[static_cast<std::size_t>(c)];
    if (rate) control = {ControlKind::strain_rate, *rate};
    if (stress) control = {ControlKind::stress, *stress};
    any_rate = any_rate || rate.has_value();
  }
  // The normal components whose shared rate keeps the cell's volume (an undrained test, SPEC 3.7).
  const std::string cv_key = k + ".constant_volume";
  if (r.get(cv_key, false)) {
    const std::vector<std::string> normal{"11", "22", "33"};
    const auto held = r.list<std::string>(cv_key, "normal components (\"11\", \"22\", \"33\")",
                                          [&](const toml::node& e, std::string& why) -> std::optional<std::string> {
                                            if (!e.is_string()) return why = "expected a string", std::nullopt;
                                            const std::string v = *e.value<std::string>();
                                            if (std::find(normal.begin(), normal.end(), v) == normal.end())
                                              return why = "must be \"11\", \"22\" or \"33\"", std::nullopt;
                                            return v;
                                          });
    if (held.empty()) r.fail(cv_key, r.find(cv_key), "give at least one normal component");
    for (const std::string& name : held) {
      auto& control = ph.controls.component[static_cast<std::size_t>(std::stoi(name) / 11 - 1)];
      if (control.kind == ControlKind::constant_volume)
        r.fail(cv_key, r.find(cv_key), fmt::format("component {} is listed twice", name));
      if (control.kind != ControlKind::fixed)
        r.fail(cv_key, r.find(cv_key),
               fmt::format("component {} has a strain_rate or a stress too: give one control per component", name));
      control.kind = ControlKind::constant_volume;
    }
    bool driven = false;
    for (const auto& c : ph.controls.component)
      driven = driven || c.kind == ControlKind::strain_rate || c.kind == ControlKind::stress;
    if (held.size() == 3 || !driven)
      r.fail(cv_key, r.find(cv_key),
             "another component must be driven (a strain_rate or a stress) for the volume to be held against");
  }
  const auto cap = r.optional_number(k + ".servo.max_strain_rate", [](double v) { return v > 0 && v < 0.1; },
                                     "must be in (0, 0.1)");
  const auto factor = r.optional_number(k + ".servo.rate_factor", [](double v) { return v >= 1; }, "must be >= 1");
  if (cap && factor)
    r.fail(k + ".servo.rate_factor", r.find(k + ".servo.rate_factor"), "give max_strain_rate or rate_factor, not both");
  if (factor && !any_rate)
    r.fail(k + ".servo.rate_factor", r.find(k + ".servo.rate_factor"),
           "the phase has no strain-rate component to scale; give servo.max_strain_rate");
  ph.controls.max_strain_rate = cap ? *cap : (factor || any_rate ? 0.0 : 2e-5);
  ph.controls.rate_factor = factor ? *factor : (cap || !any_rate ? 0.0 : 10.0);
}

// When a phase ends: steps, strain or stress of a component, equilibrium, or a controller that
// ends it; and its step budget. Returns the planned end (planned_end: -1 when not known in advance).
long read_phase_stop(Reader& r, const std::string& k, Phase& ph, double step_ratio) {
  auto& stop = ph.stop;
  stop.steps = r.optional_integer(k + ".stop.steps", 1, std::numeric_limits<long>::max()).value_or(0);
  for (int c = 0; c < component_count; ++c) {
    const auto kc = static_cast<std::size_t>(c);
    const std::string name = component_names[kc];
    stop.strain[kc] = r.optional_quantity(k + ".stop.strain." + name, Dimension::ratio,
                                          [](double v) { return v != 0 && std::abs(v) < 1; },
                                          "must be nonzero and in (-100 %, 100 %)");
    stop.stress[kc] = r.optional_quantity(k + ".stop.stress." + name, Dimension::stress, [](double) { return true; }, "");
    const auto& control = ph.controls.component[kc];
    if (stop.strain[kc] && control.kind == ControlKind::fixed)
      r.fail(k + ".stop.strain." + name, r.find(k + ".stop.strain." + name),
             fmt::format("component {} is fixed (no strain_rate, stress or constant_volume): its strain stays 0", name));
    if (planned_strain(ph, c) && (*stop.strain[kc] > 0) != (control.value > 0))
      r.fail(k + ".stop.strain." + name, r.find(k + ".stop.strain." + name),
             fmt::format("the strain rate of component {} ({}) never reaches it", name, control.value));
    if (planned_strain(ph, c)) {
      const double steps = std::abs(*stop.strain[kc] / (step_ratio * control.value));
      if (steps > max_planned_steps)
        r.fail(k + ".strain_rate." + name, r.find(k + ".strain_rate." + name),
               fmt::format("the phase would take {:.3g} steps to its strain stop (stop.strain / (time.step_ratio "
                           "strain_rate)), more than the {:.0e} allowed: raise the rate",
                           steps, max_planned_steps));
    }
  }
  if (r.find(k + ".stop.equilibrium")) {
    const std::string e = k + ".stop.equilibrium";
    StopCriteria::Equilibrium eq;
    eq.stress_tolerance = r.quantity(e + ".stress_tolerance", Dimension::ratio, 0.01, positive, "must be > 0");
    eq.ufr = r.optional_quantity(e + ".ufr", Dimension::ratio, positive, "must be > 0");
    eq.imom = r.optional_quantity(e + ".imom", Dimension::ratio, positive, "must be > 0");
    eq.every = r.integer(e + ".every", default_every_steps, 1, 1'000'000);
    if (!eq.ufr && !eq.imom) r.fail(e, r.find(e), "give ufr or imom (or both): the index that says the sample is in equilibrium");
    stop.equilibrium = eq;
  }
  bool any_stop = stop.steps > 0 || stop.equilibrium.has_value();
  for (int c = 0; c < component_count; ++c)
    any_stop = any_stop || stop.strain[static_cast<std::size_t>(c)] || stop.stress[static_cast<std::size_t>(c)];
  // A controller that ends the phase itself (ControllerKind::ends_phase) is a stop criterion.
  const toml::node* controller_kind = r.find(k + ".controller.kind");
  for (const ControllerKind& kind : controller_kinds())
    any_stop = any_stop || (kind.ends_phase && controller_kind && controller_kind->value<std::string>() == std::string(kind.name));
  if (!any_stop)
    r.fail(k + ".stop", r.find(k + ".stop"), "give at least one end: steps, strain, stress or equilibrium");
  const long end = planned_end(ph, step_ratio);
  stop.max_steps = r.optional_integer(k + ".stop.max_steps", 1, std::numeric_limits<long>::max())
                       .value_or(end < 0 ? default_max_steps : 0);
  return end;
}

// Where a phase's rows go and when it takes one: points over a planned end, every steps, or
// every strain of a strain-rate component; `end`: the phase's planned end (read_phase_stop).
void read_phase_output(Reader& r, const std::string& k, Phase& ph, long end) {
  auto& out = ph.output;
  out.file = r.text(k + ".output.file", std::string("series.csv"), {});
  if (out.file.size() < 5 || out.file.substr(out.file.size() - 4) != ".csv" || out.file.find('/') != std::string::npos ||
      out.file.front() == '.')
    r.fail(k + ".output.file", r.find(k + ".output.file"), "must be a file name ending in .csv, in the run directory");
  if (out.file == classes_file)
    r.fail(k + ".output.file", r.find(k + ".output.file"),
           fmt::format("{} is the run's per-class file (output.classes): name another file", classes_file));
  out.clock = r.text(k + ".output.clock", std::string("phase"), {"phase", "run"}) == "run" ? PhaseOutput::Clock::run
                                                                                      : PhaseOutput::Clock::phase;
  const auto points = r.optional_integer(k + ".output.points", 1, 1'000'000);
  const auto every = r.optional_integer(k + ".output.every_steps", 1, std::numeric_limits<long>::max());
  std::optional<double> strain_step;
  for (int c = 0; c < component_count; ++c) {
    const std::string key = k + ".output.every_strain." + component_names[static_cast<std::size_t>(c)];
    const auto d = r.optional_quantity(key, Dimension::ratio, positive, "must be > 0");
    if (!d) continue;
    if (strain_step) r.fail(key, r.find(key), "give the strain interval of one component only");
    if (ph.controls.component[static_cast<std::size_t>(c)].kind != ControlKind::strain_rate)
      r.fail(key, r.find(key), "the component must be strain-rate controlled (give it a strain_rate)");
    strain_step = d;
    out.cadence.strain_component = c;
  }
  if ((points ? 1 : 0) + (every ? 1 : 0) + (strain_step ? 1 : 0) > 1)
    r.fail(k + ".output", r.find(k + ".output"), "give one of points, every_steps, every_strain");
  if (points && end < 0)
    r.fail(k + ".output.points", r.find(k + ".output.points"),
           "points spreads the rows over a phase whose end is known in advance (stop.steps, or stop.strain of a "
           "strain-rate component): give every_steps or every_strain");
  if (points && *points > end)
    r.fail(k + ".output.points", r.find(k + ".output.points"),
           fmt::format("more sample points than the {} steps of the phase: lower it", end));
  if (strain_step) {
    out.cadence.kind = Cadence::Kind::every_strain;
    out.cadence.every_strain = *strain_step;
  } else if (every || end < 0) {
    out.cadence.kind = Cadence::Kind::every_steps;
    out.cadence.every_steps = every.value_or(default_every_steps);
  } else {
    out.cadence.kind = Cadence::Kind::points;
    out.cadence.points = points.value_or(std::min(default_points, end));
  }
}

// A phase's controller (controller_kinds()), with what its entry declares.
void read_phase_controller(Reader& r, const std::string& k, Phase& ph, double step_ratio) {
  if (!r.find(k + ".controller")) return;
  std::vector<std::string> names;
  for (const ControllerKind& kind : controller_kinds()) names.emplace_back(kind.name);
  ph.controller = r.text(k + ".controller.kind", std::nullopt, names);
  ControllerTable table(r, k + ".controller");
  const ControllerKind& kind = *std::find_if(controller_kinds().begin(), controller_kinds().end(),
                                             [&](const ControllerKind& c) { return c.name == ph.controller; });
  ph.make_controller = kind.read(table, ph, step_ratio);
  if (kind.writes_rate_column) {
    const std::vector<std::string> components(component_names.begin(), component_names.end());
    const std::string name = r.text(k + ".controller.component", std::nullopt, components);
    ph.rate_component = static_cast<int>(std::find(components.begin(), components.end(), name) - components.begin());
  }
  if (ph.inertia.on() && kind.plans_with_step_ratio)
    r.fail(k + ".inertia_scaling", r.find(k + ".inertia_scaling"),
           fmt::format("not with controller \"{}\", which plans its steps with time.step_ratio alone", ph.controller));
}

// One [[phase]] entry, `k` = "phase.N" (docs/config.md).
Phase read_phase(Reader& r, const std::string& k, std::size_t index, double step_ratio, const ContactSettings& contact) {
  Phase ph;
  ph.name = r.text(k + ".name", fmt::format("phase-{}", index), {});
  if (ph.name.empty() || ph.name.find_first_of(",\"\n\r") != std::string::npos)
    r.fail(k + ".name", r.find(k + ".name"), "must be a non-empty name without commas, quotes or line breaks (a CSV column)");
  ph.friction = r.number(k + ".friction", std::nullopt, non_negative, "must be >= 0");
  std::tie(ph.damping.model, ph.damping.ratio) =
      damping_model(r, k + ".damping.model", k + ".damping.ratio", contact);
  ph.damping.acts_on = damped_motion(r, k + ".damping.acts_on");
  ph.inertia = inertia_scaling(r, k);
  ph.fire = fire_solver(r, k);
  if (ph.fire) ph.damping = {"none", 0.0, DampedMotion::both};

  read_phase_controls(r, k, ph);
  if (ph.fire) check_fire_phase(r, k, ph);
  const long end = read_phase_stop(r, k, ph, step_ratio);
  read_phase_output(r, k, ph, end);
  read_phase_controller(r, k, ph, step_ratio);
  // The keys messages and studies name: those the case wrote (Reader::written).
  PhaseKeys& keys = ph.keys;
  keys = {r.written(k + ".stop.max_steps"), r.written(k + ".damping.model"), r.written(k + ".damping.ratio"),
          r.written(k + ".stop.equilibrium.ufr"), {}, {}};
  for (std::size_t c = component_count; c-- > 0;)
    if (ph.controls.component[c].kind == ControlKind::strain_rate)
      keys.strain_rate = keys.strain_rates[c] = r.written(k + ".strain_rate." + component_names[c]);
  if (keys.strain_rate.empty()) keys.strain_rate = r.written(k + ".servo.max_strain_rate");
  return ph;
}

nlohmann::json to_json(const toml::table& tbl) {
  std::ostringstream os;
  os << toml::json_formatter{tbl};
  return nlohmann::json::parse(os.str());
}

}  // namespace

namespace {

// parse_case; `asked`, when given, receives every key the parser asked for.
// [sample]: the seed, the loose packing's solid fraction and the particles: a size table, a sieve
// curve, or a given sample (sample.from, kept absolute in the case text).
void read_sample(Reader& r, toml::table& root, const std::string& source, const std::filesystem::path& base_dir,
                 Params::Sample& sample) {
  sample.seed = static_cast<std::uint64_t>(r.integer("sample.seed", 1, 0, std::numeric_limits<long>::max()));
  sample.initial_solid_fraction = r.number("sample.initial_solid_fraction", 0.15,
                                             [](double v) { return v > 0 && v <= 0.2; }, "must be in (0, 0.2] (SPEC 8: a loose sample)");
  sample.total_particles = r.integer("sample.total_particles", 0, 0, 100'000'000);
  sample.from = r.text("sample.from", std::string(), {});
  if (!sample.from.empty()) {
    // In the case file: relative to the case file's directory (as study paths are to the study
    // file); on the command line (--set): relative to the working directory. Kept absolute, in
    // the case text too, so that a resume elsewhere names the same sample.
    namespace fs = std::filesystem;
    const auto& src = r.find("sample.from")->source();
    const bool in_file = src.path && *src.path == source;
    fs::path from = sample.from;
    if (from.is_relative() && in_file) from = base_dir / from;
    sample.from = fs::absolute(from).lexically_normal().string();
    require_utf8(sample.from, "sample.from");  // with the working directory that made it absolute
    root["sample"].as_table()->insert_or_assign("from", sample.from);
  }
  // A sieve curve instead of the size table: sample.total_particles particles drawn from it.
  if (const toml::node* grading = r.get("sample.grading", false)) {
    if (r.find("sample.particles"))
      r.fail("sample.particles", r.find("sample.particles"),
             "a case gives either the size table [[sample.particles]] or the sieve curve [[sample.grading]], not both");
    if (!grading->is_array_of_tables())
      r.fail("sample.grading", grading, "expected an array of tables ([[sample.grading]] entries, one per point)");
    sample.grading = read_grading(r, *grading->as_array());
    if (sample.total_particles == 0)
      r.fail("sample.total_particles", r.find("sample.total_particles"),
             "a sieve curve [[sample.grading]] needs the number of particles to draw from it: set it >= 1");
  }
  // A given sample replaces the generated one: then the size table is not needed (nor read).
  if (sample.grading.empty() && (sample.from.empty() || r.find("sample.particles"))) {
    const auto* table = r.array_of_tables("sample.particles");
    for (std::size_t k = 0; k < table->size(); ++k)
      sample.table.push_back(read_size_class(r, "sample.particles." + std::to_string(k)));
  }

}

// The [[phase]] table the default protocol's tables are written into: each value is the written
// key's node (its text, so that the phase reads the same number) or, when the case leaves the key
// out, its default; the phase's key then names the written one in messages.
class PhaseTable {
 public:
  PhaseTable(Reader& r, std::string path, std::string name) : r_(r), path_(std::move(path)) { t_.insert("name", name); }

  // `key` of the phase from the written key `from` (checked by the caller), or `value` when absent.
  template <class V>
  void put(const std::string& key, const std::string& from, V value) {
    if (const toml::node* n = r_.find(from))
      n->visit([&](const auto& node) { insert(key, node); });
    else
      insert(key, std::move(value));
    r_.alias(path_ + "." + key, from);
  }
  // `key` of the phase with a value that no written key holds (named as the phase's own).
  template <class V>
  void set(const std::string& key, V value) {
    insert(key, std::move(value));
    r_.alias(path_ + "." + key, path_ + "." + key);
  }
  const toml::table& table() const { return t_; }

 private:
  template <class V>
  void insert(const std::string& key, V value) {
    toml::table* t = &t_;
    std::size_t from = 0;
    for (std::size_t dot; (dot = key.find('.', from)) != std::string::npos; from = dot + 1) {
      const std::string part = key.substr(from, dot - from);
      if (!t->contains(part)) t->insert(part, toml::table{});
      t = t->get(part)->as_table();
    }
    t->insert_or_assign(key.substr(from), std::move(value));
  }

  Reader& r_;
  std::string path_;
  toml::table t_;
};

std::string pascals(double v) { return fmt::format("{:.17g} Pa", v); }

// [compaction] (SPEC 8.2): the loose sample compressed to an isotropic stress, as phase.0.
toml::table compaction_phase(Reader& r, const ContactSettings& contact) {
  PhaseTable ph(r, "phase.0", "compaction");
  ph.put("friction", "compaction.friction", r.number("compaction.friction", 0.2, non_negative, "must be >= 0"));
  const auto [model, ratio] = damping_model(r, "compaction.damping_model", "compaction.damping_ratio", contact);
  ph.put("damping.model", "compaction.damping_model", model);
  ph.put("damping.ratio", "compaction.damping_ratio", ratio);
  const double stress = r.quantity("compaction.stress", Dimension::stress, 390e3, positive, "must be > 0");
  for (const char* c : {"11", "22", "33"}) ph.put(std::string("stress.") + c, "compaction.stress", pascals(stress));
  if (r.boolean("compaction.zero_shear_stress", true))
    for (const char* c : {"12", "13", "23"}) ph.set(std::string("stress.") + c, pascals(0.0));
  ph.put("servo.max_strain_rate", "compaction.max_strain_rate",
         r.number("compaction.max_strain_rate", 2e-5, [](double v) { return v > 0 && v < 0.1; }, "must be in (0, 0.1)"));
  ph.put("stop.equilibrium.stress_tolerance", "compaction.stress_tolerance",
         r.quantity("compaction.stress_tolerance", Dimension::ratio, 0.01, positive, "must be > 0"));
  ph.put("stop.equilibrium.ufr", "compaction.ufr_tolerance",
         r.quantity("compaction.ufr_tolerance", Dimension::ratio, 0.01, positive, "must be > 0"));
  const long every = r.integer("compaction.check_interval", 200, 1, 1'000'000);
  ph.put("stop.equilibrium.every", "compaction.check_interval", std::int64_t{every});
  ph.put("stop.max_steps", "compaction.max_steps",
         std::int64_t{r.integer("compaction.max_steps", 2'000'000, 1, std::numeric_limits<long>::max())});
  ph.set("output.file", "compaction.csv");
  ph.set("output.clock", "run");
  ph.put("output.every_steps", "compaction.check_interval", std::int64_t{every});
  if (inertia_scaling(r, "compaction").on()) ph.put("inertia_scaling", "compaction.inertia_scaling", toml::table{});
  return ph.table();
}

// [triaxial] with [damping] (SPEC 8.3): the drained triaxial test at a constant axial strain rate,
// or one that follows an index ([triaxial.rate_control]), as phase.1.
toml::table triaxial_phase(Reader& r, const ContactSettings& contact, double step_ratio) {
  PhaseTable ph(r, "phase.1", "triaxial");
  ph.put("friction", "triaxial.friction", r.number("triaxial.friction", 0.5, non_negative, "must be >= 0"));
  const auto [model, ratio] = damping_model(r, "damping.model", "damping.ratio", contact);
  ph.put("damping.model", "damping.model", model);
  ph.put("damping.ratio", "damping.ratio", ratio);
  ph.put("damping.acts_on", "damping.acts_on", to_string(damped_motion(r, "damping.acts_on")));
  const double confining =
      r.quantity("triaxial.confining_stress", Dimension::stress, 390e3, positive, "must be > 0");
  for (const char* c : {"11", "22"}) ph.put(std::string("stress.") + c, "triaxial.confining_stress", pascals(confining));
  if (r.boolean("triaxial.zero_shear_stress", false))
    for (const char* c : {"12", "13", "23"}) ph.set(std::string("stress.") + c, pascals(0.0));
  const double rate =
      r.number("triaxial.strain_rate", 1e-5, [](double v) { return v > 0 && v < 0.01; }, "eps' must be in (0, 0.01)");
  ph.put("strain_rate.33", "triaxial.strain_rate", rate);
  ph.put("servo.rate_factor", "triaxial.lateral_rate_factor",
         r.number("triaxial.lateral_rate_factor", 10.0, [](double v) { return v >= 1; }, "must be >= 1"));
  const double final_strain = r.quantity("triaxial.final_axial_strain", Dimension::ratio, 0.10,
                                         [](double v) { return v > 0 && v < 0.5; }, "must be in (0, 50 %)");
  ph.put("stop.strain.33", "triaxial.final_axial_strain", final_strain);
  const long points = r.integer("triaxial.sample_points", 250, 1, 1'000'000);
  const double steps = final_strain / (step_ratio * rate);
  if (steps > max_planned_steps)
    r.fail("triaxial.strain_rate", r.find("triaxial.strain_rate"),
           fmt::format("the test would take {:.3g} steps (final_axial_strain / (time.step_ratio strain_rate)), more "
                       "than the {:.0e} allowed: raise the rate",
                       steps, max_planned_steps));
  if (static_cast<double>(points) > steps)
    r.fail("triaxial.sample_points", r.find("triaxial.sample_points"),
           fmt::format("more sample points than the {:.0f} steps of the test (final_axial_strain / (step_ratio "
                       "strain_rate)): lower it or lower triaxial.strain_rate",
                       steps));
  ph.set("output.file", "series.csv");
  const bool inertia = inertia_scaling(r, "triaxial").on();
  if (inertia) ph.put("inertia_scaling", "triaxial.inertia_scaling", toml::table{});
  if (const toml::node* control = r.find("triaxial.rate_control")) {
    // The axial strain rate follows an index; the rows are spread by axial strain, so that each
    // stands for an equal strain increment whatever the rate (docs/config.md).
    if (inertia)
      r.fail("triaxial.inertia_scaling", r.find("triaxial.inertia_scaling"),
             "not with triaxial.rate_control, which plans its steps with time.step_ratio alone");
    if (!control->is_table()) r.fail("triaxial.rate_control", control, "expected a table of the rate controller's keys");
    for (const char* own : {"kind", "component"})
      if (const toml::node* n = r.find(std::string("triaxial.rate_control.") + own))
        r.fail(std::string("triaxial.rate_control.") + own, n,
               "unknown key: [triaxial.rate_control] drives the axial component (33) with the rate controller");
    ph.put("controller", "triaxial.rate_control", toml::table{});
    ph.set("controller.kind", "rate");
    ph.set("controller.component", "33");
    ph.set("output.every_strain.33", final_strain / static_cast<double>(points));
  } else {
    ph.put("output.points", "triaxial.sample_points", std::int64_t{points});
  }
  return ph.table();
}

// [servo]: the stress servo's gains (SPEC 3).
void read_servo(Reader& r, Params& p) {
  p.servo.proportional_gain = r.number("servo.proportional_gain", 0.1, [](double v) { return v > 0 && v < 1; }, "must be in (0, 1)");
  p.servo.integral_gain = r.number("servo.integral_gain", 0.002, [](double v) { return v >= 0 && v <= 0.1; }, "must be in [0, 0.1]");
}

// The protocol: the [[phase]] list, or [compaction] then [triaxial] (with [triaxial.rate_control]
// and [damping]) written into the case as the two phases they stand for, read as a list.
void read_protocol(Reader& r, toml::table& root, Params& p) {
  p.phase_list = r.find("phase") != nullptr;
  if (p.phase_list) {
    // The phase list is the whole protocol: the tables of the default one would be ignored.
    for (const char* section : {"compaction", "triaxial", "damping"})
      if (const toml::node* n = r.find(section))
        throw InputError(fmt::format("{}: [{}] with [[phase]]: the protocol is the phase list, which does not read "
                                     "[{}]; write its settings in the phases (docs/config.md)",
                                     r.where(n), section, section));
  } else {
    root.insert("phase", toml::array{compaction_phase(r, p.contact), triaxial_phase(r, p.contact, p.step_ratio)});
  }
  const auto* phases = r.array_of_tables("phase");
  for (std::size_t k = 0; k < phases->size(); ++k) {
    p.protocol.push_back(read_phase(r, "phase." + std::to_string(k), k, p.step_ratio, p.contact));
    p.protocol.back().contact = p.contact;
    for (std::size_t j = 0; j < k; ++j)
      if (p.protocol[j].name == p.protocol[k].name)
        r.fail("phase." + std::to_string(k) + ".name", r.find("phase." + std::to_string(k) + ".name"),
               fmt::format("phase.{} has the same name: each phase needs its own", j));
  }
}

// What every run of the case shares beyond the physics: the neighbour list's skin, checkpoints,
// extra output and the safety limits.
void read_run_settings(Reader& r, Params& p) {
  p.neighbor.skin_ratio = r.number("neighbor.skin_ratio", 0.2, [](double v) { return v > 0 && v <= 2; }, "must be in (0, 2]");

  p.checkpoint.every_sample_points =
      static_cast<int>(r.integer("checkpoint.every_sample_points", 25, 0, 1'000'000));
  p.checkpoint.every_minutes = r.number("checkpoint.every_minutes", 10.0, [](double v) { return v >= 0; }, "must be >= 0");
  p.output.vtk_every = static_cast<int>(r.integer("output.vtk_every", 0, 0, 1'000'000));
  p.output.classes = r.boolean("output.classes", true);
  p.output.energy = r.boolean("output.energy", false);
  p.limits.max_overlap = r.quantity("limits.max_overlap", Dimension::ratio, 1.0, [](double v) { return v > 0 && v <= 1; },
                                    "must be in (0, 100 %]");
  p.limits.max_kinetic_ratio = r.number("limits.max_kinetic_ratio", 1.0, positive, "must be > 0");
}

Params parse(const std::string& toml_text, const std::string& source, const std::vector<std::string>& overrides,
             const std::filesystem::path& base_dir, std::set<std::string>* asked) {
  toml::table root;
  try {
    root = toml::parse(toml_text, source);
  } catch (const toml::parse_error& e) {
    throw InputError(fmt::format("{}:{}: TOML syntax error: {}", source, e.source().begin.line,
                                 e.description()));
  }
  for (const auto& o : overrides) apply_override(root, o);

  Reader r(root, source);
  Params p;
  p.source = source;
  p.name = r.text("name", std::string("case"), {});

  p.material.density = r.quantity("material.density", Dimension::density, std::nullopt, positive, "must be > 0");
  p.material.young_modulus = r.quantity("material.young_modulus", Dimension::stress, std::nullopt, positive, "must be > 0");
  p.material.poisson_ratio = r.number("material.poisson_ratio", std::nullopt,
                                      [](double v) { return v > -1 && v < 0.5; }, "must be in (-1, 0.5)");

  read_sample(r, root, source, base_dir, p.sample);

  // Stability: dt must stay below about 20 % of the Rayleigh time 2.73 t_c (LIGGGHTS' rule), c_t <= 0.5.
  p.step_ratio = r.number("time.step_ratio", 0.32, [](double v) { return v > 0 && v <= 0.5; },
                          "must be in (0, 0.5]: above 0.5 the time step exceeds the stability bound (20 % of the "
                          "Rayleigh time)");

  p.contact = read_contact(r);

  read_servo(r, p);
  read_protocol(r, root, p);
  read_run_settings(r, p);
  r.reject_unknown();
  if (asked) *asked = r.asked();
  if (!p.phase_list) root.erase("phase");  // the case as written: its own tables
  p.as_written = to_json(root);
  std::ostringstream text;
  text << root;
  p.case_text = text.str();
  return p;
}

// Cases that between them make the parser ask for every key it knows (case_keys): each is the
// material and either a sample of its own or the one-sphere sample and a protocol.
constexpr const char* key_probe_material = R"(
    material = { density = "1 kg/m^3", young_modulus = "1 Pa", poisson_ratio = 0 }
  )";
constexpr const char* key_probe_one_sphere = R"(
    [[sample.particles]]
    diameter = "1 m"
    count = 1
  )";
constexpr const char* key_probe_samples[] = {
    // One size-table row of each shape.
    R"(
    [[sample.particles]]
    shape = "sphere"
    diameter = "1 m"
    count = 1
    [[sample.particles]]
    shape = "spheroid"
    major_semi_axis = "1 m"
    minor_semi_axis = "1 m"
    count = 1
    [[sample.particles]]
    shape = "ellipsoid"
    semi_axes = ["1 m", "1 m", "1 m"]
    count = 1
  )",
    // A sieve curve with a shape for the whole curve and one for an interval.
    R"(
    [sample]
    total_particles = 10
    grading_shape = "spheroid"
    grading_aspect_ratio = 1.2
    [[sample.grading]]
    size = "1 m"
    passing = 0
    [[sample.grading]]
    size = "2 m"
    passing = 1
    shape = "spheroid"
    aspect_ratio = 1.5
  )",
};
constexpr const char* key_probe_protocols[] = {
    // A phase list that names each optional table.
    R"(
    [[phase]]
    friction = 0.2
    stress = { 11 = "1 Pa", 22 = "1 Pa", 33 = "1 Pa" }
    stop = { equilibrium = { ufr = 0.01 } }
    controller = { kind = "schedule", component = "11", at_sample = [1], values = ["2 Pa"] }
  )",
    // The rate controller's keys, of a phase and of the default triaxial test.
    R"(
    [[phase]]
    friction = 0.2
    stress = { 11 = "1 Pa", 22 = "1 Pa" }
    strain_rate = { 33 = 1e-5 }
    stop = { strain = { 33 = 0.01 } }
    output = { every_strain = { 33 = 0.001 } }
    controller = { kind = "rate", component = "33", target = 0.01, min_rate = 1e-6, max_rate = 1e-4 }
  )",
    R"(
    [triaxial.rate_control]
    target = 0.01
    min_rate = 1e-6
    max_rate = 1e-4
  )",
    // The path controllers' keys (path_control.hpp): cyclic by q, cyclic by strain, true triaxial.
    R"(
    [[phase]]
    friction = 0.2
    stress = { 11 = "1 Pa", 22 = "1 Pa" }
    strain_rate = { 33 = 1e-5 }
    controller = { kind = "cyclic", q_mean = "1 Pa", q_amplitude = "1 Pa", cycles = 2 }
  )",
    R"(
    [[phase]]
    friction = 0.2
    stress = { 11 = "1 Pa", 22 = "1 Pa" }
    strain_rate = { 33 = 1e-5 }
    controller = { kind = "cyclic", strain_mean = 0.001, strain_amplitude = 0.001 }
  )",
    R"(
    [[phase]]
    friction = 0.2
    stress = { 11 = "1 Pa", 22 = "1 Pa" }
    strain_rate = { 33 = 1e-5 }
    stop = { strain = { 33 = 0.01 } }
    controller = { kind = "true_triaxial", p = "1 Pa", b = 0.5, intermediate = "11" }
  )",
};

}  // namespace

Params parse_case(const std::string& toml_text, const std::string& source,
                  const std::vector<std::string>& overrides, const std::filesystem::path& base_dir) {
  return parse(toml_text, source, overrides, base_dir, nullptr);
}

std::vector<std::string> case_keys() {
  std::vector<std::string> cases;
  for (const char* sample : key_probe_samples) cases.push_back(std::string(key_probe_material) + sample);
  for (const char* protocol : key_probe_protocols)
    cases.push_back(std::string(key_probe_material) + key_probe_one_sphere + protocol);
  std::set<std::string> asked;
  for (const std::string& text : cases) {
    std::set<std::string> more;
    parse(text, "<case_keys>", {}, {}, &more);
    asked.insert(more.begin(), more.end());
  }
  // The keys of an array's entries without the index: sample.particles.2.count -> sample.particles.count.
  const auto unindexed = [](const std::string& key, const std::string& array) {
    const std::string head = array + ".";
    if (key.rfind(head, 0) != 0 || key.size() <= head.size() || !std::isdigit(static_cast<unsigned char>(key[head.size()])))
      return std::optional<std::string>();
    const auto dot = key.find('.', head.size());
    return std::optional<std::string>(dot == std::string::npos ? array : head + key.substr(dot + 1));
  };
  std::set<std::string> keys;
  for (const std::string& k : asked) {
    if (const auto row = unindexed(k, "sample.particles")) keys.insert(*row);
    else if (const auto point = unindexed(k, "sample.grading")) keys.insert(*point);
    else if (const auto phase = unindexed(k, "phase")) keys.insert(*phase);
    else keys.insert(k);
  }
  keys.erase("phase");  // the array itself
  for (std::string_view law : contact_law_names())  // each law's own keys, read only for that law
    for (const LawKey& key : contact_law_keys(law)) keys.insert("contact." + std::string(key.name));
  return {keys.begin(), keys.end()};
}

nlohmann::json to_json(const Phase& ph) {
  nlohmann::json controls = nlohmann::json::object();
  for (int c = 0; c < component_count; ++c) {
    const ComponentControl& cc = ph.controls.component[static_cast<std::size_t>(c)];
    const char* name = component_names[static_cast<std::size_t>(c)];
    if (cc.kind == ControlKind::strain_rate) controls[name] = {{"strain_rate", cc.value}};
    if (cc.kind == ControlKind::stress) controls[name] = {{"stress_Pa", cc.value}};
    if (cc.kind == ControlKind::constant_volume) controls[name] = {{"constant_volume", true}};
  }
  nlohmann::json stop = nlohmann::json::object();
  if (ph.stop.steps > 0) stop["steps"] = ph.stop.steps;
  for (int c = 0; c < component_count; ++c) {
    const auto k = static_cast<std::size_t>(c);
    if (ph.stop.strain[k]) stop["strain"][component_names[k]] = *ph.stop.strain[k];
    if (ph.stop.stress[k]) stop["stress_Pa"][component_names[k]] = *ph.stop.stress[k];
  }
  if (const auto& e = ph.stop.equilibrium) {
    stop["equilibrium"] = {{"stress_tolerance", e->stress_tolerance}, {"every", e->every}};
    if (e->ufr) stop["equilibrium"]["ufr"] = *e->ufr;
    if (e->imom) stop["equilibrium"]["imom"] = *e->imom;
  }
  if (ph.stop.max_steps > 0) stop["max_steps"] = ph.stop.max_steps;
  const Cadence& cd = ph.output.cadence;
  nlohmann::json output = {{"file", ph.output.file}, {"clock", ph.output.clock == PhaseOutput::Clock::run ? "run" : "phase"}};
  if (cd.kind == Cadence::Kind::points) output["points"] = cd.points;
  if (cd.kind == Cadence::Kind::every_steps) output["every_steps"] = cd.every_steps;
  if (cd.kind == Cadence::Kind::every_strain)
    output["every_strain"] = {{component_names[static_cast<std::size_t>(cd.strain_component)], cd.every_strain}};
  nlohmann::json servo = nlohmann::json::object();
  if (ph.controls.max_strain_rate > 0) servo["max_strain_rate"] = ph.controls.max_strain_rate;
  if (ph.controls.rate_factor > 0) servo["rate_factor"] = ph.controls.rate_factor;
  nlohmann::json j = {{"name", ph.name},
                      {"friction", ph.friction},
                      {"damping", {{"model", ph.damping.model}, {"ratio", ph.damping.ratio},
                                   {"acts_on", to_string(ph.damping.acts_on)}}},
                      {"control", controls},
                      {"servo", servo},
                      {"stop", stop},
                      {"output", output}};
  if (!ph.controller.empty()) j["controller"] = ph.controller;
  if (const auto& f = ph.fire) {
    j["solver"] = {{"kind", "fire"},           {"strain_increment", f->strain_increment}, {"ufr", f->ufr},
                   {"stress_tolerance", f->stress_tolerance}, {"max_iterations", f->max_iterations},
                   {"check_every", f->check_every}};
    if (f->imom) j["solver"]["imom"] = *f->imom;
  }
  if (ph.inertia.on()) {
    const bool coarsest = ph.inertia.target == InertiaScaling::Target::coarsest;
    j["inertia_scaling"] = {{"target", coarsest ? "coarsest" : "factor"}, {"cap", ph.inertia.cap}};
    if (!coarsest) j["inertia_scaling"]["factor"] = ph.inertia.factor;
  }
  return j;
}

nlohmann::json to_json(const Params& p) {
  nlohmann::json table = nlohmann::json::array();
  for (const auto& c : p.sample.table)
    table.push_back({{"shape", to_string(c.shape)},
                     {"semi_axes_m", {c.semi_axes.x(), c.semi_axes.y(), c.semi_axes.z()}},
                     {"count", c.count}});
  nlohmann::json protocol = nlohmann::json::array();
  for (const Phase& ph : p.protocol) protocol.push_back(to_json(ph));
  nlohmann::json contact = {{"law", p.contact.law}};
  for (const auto& [key, value] : p.contact.values) contact[key] = value;
  nlohmann::json out = {
      {"name", p.name},
      {"source", p.source},
      {"material", {{"density_kg_m3", p.material.density}, {"young_modulus_Pa", p.material.young_modulus},
                    {"poisson_ratio", p.material.poisson_ratio}}},
      {"sample", {{"seed", p.sample.seed}, {"initial_solid_fraction", p.sample.initial_solid_fraction},
                  {"total_particles", p.sample.total_particles}, {"particles", table}, {"from", p.sample.from}}},
      {"time", {{"step_ratio", p.step_ratio}}},
      {"contact", contact},
      {"servo", {{"proportional_gain", p.servo.proportional_gain}, {"integral_gain", p.servo.integral_gain}}},
      {"neighbor", {{"skin_ratio", p.neighbor.skin_ratio}}},
      {"checkpoint", {{"every_sample_points", p.checkpoint.every_sample_points},
                      {"every_minutes", p.checkpoint.every_minutes}}},
      {"limits", {{"max_overlap", p.limits.max_overlap}, {"max_kinetic_ratio", p.limits.max_kinetic_ratio}}},
      {"output", {{"vtk_every", p.output.vtk_every}, {"classes", p.output.classes}, {"energy", p.output.energy}}},
      {"protocol", protocol},
  };
  if (const Grading& g = p.sample.grading; !g.empty())
    out["sample"]["grading"] = {{"size_m", g.size}, {"passing", g.passing}, {"aspect_ratio", g.aspect_ratio}};
  return out;
}

Params load_case(const std::string& path, const std::vector<std::string>& overrides) {
  namespace fs = std::filesystem;
  require_utf8(path, "the case file's path");
  std::error_code ec;
  if (fs::is_directory(path, ec))
    throw InputError(fmt::format("case file '{}' is a directory: give a case file (TOML, docs/config.md)", path));
  std::ifstream in(path);
  if (!in) throw InputError(fmt::format("cannot open case file '{}': {}", path, std::strerror(errno)));
  std::stringstream ss;
  ss << in.rdbuf();
  return parse_case(ss.str(), path, overrides, fs::path(path).parent_path());
}

}  // namespace qsdem
