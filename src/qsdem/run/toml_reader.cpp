#include "qsdem/run/toml_reader.hpp"

#include <fmt/format.h>

#include <cmath>
#include <sstream>

#include "qsdem/engine/types.hpp"

namespace qsdem {

std::string format_float(double v) {
  std::string t = fmt::format("{}", v);
  if (std::isfinite(v) && t.find_first_of(".eE") == std::string::npos) t += ".0";
  return t;
}

std::string describe(const toml::node& n) {
  if (n.is_string()) return '"' + *n.value<std::string>() + '"';
  if (n.is_table()) return "(a table)";
  if (n.is_array()) return "(an array)";
  if (n.is_floating_point()) return format_float(*n.value<double>());
  std::ostringstream os;
  n.visit([&](auto&& v) { os << v; });
  return os.str();
}

std::string TomlSource::where(const toml::node* n) const {
  if (!n) return file_;
  const auto& src = n->source();
  if (src.path && src.path->rfind("--set", 0) == 0) return *src.path;  // a command-line override
  if (src.begin.line > 0) return fmt::format("{}:{}", file_, src.begin.line);
  return file_;
}

void TomlSource::fail(const std::string& path, const toml::node* n, const std::string& why) const {
  if (n) throw InputError(fmt::format("{}: key '{}' = {}: {}", where(n), path, describe(*n), why));
  throw InputError(fmt::format("{}: key '{}': {}", file_, path, why));
}

}  // namespace qsdem
