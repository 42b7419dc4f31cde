#include "qsdem/run/units.hpp"

#include <fmt/format.h>

#include <array>
#include <charconv>
#include <cmath>
#include <utility>

#include "qsdem/engine/types.hpp"

namespace qsdem {
namespace {

struct Unit {
  std::string_view name;
  double factor;
};

constexpr std::array length_units{Unit{"m", 1.0}, Unit{"cm", 1e-2}, Unit{"mm", 1e-3},
                                  Unit{"um", 1e-6}, Unit{"µm", 1e-6}};
constexpr std::array stress_units{Unit{"Pa", 1.0}, Unit{"kPa", 1e3}, Unit{"MPa", 1e6},
                                  Unit{"GPa", 1e9}};
constexpr std::array density_units{Unit{"kg/m^3", 1.0}, Unit{"kg/m3", 1.0},
                                   Unit{"g/cm^3", 1e3}, Unit{"g/cm3", 1e3}};
constexpr std::array ratio_units{Unit{"%", 1e-2}};
constexpr std::array time_units{Unit{"s", 1.0}, Unit{"ms", 1e-3}, Unit{"us", 1e-6}};

template <std::size_t N>
std::string join(const std::array<Unit, N>& units) {
  std::string out;
  for (const auto& u : units) {
    if (!out.empty()) out += ", ";
    out += u.name;
  }
  return out;
}

std::string_view trim(std::string_view s) {
  while (!s.empty() && (s.front() == ' ' || s.front() == '\t')) s.remove_prefix(1);
  while (!s.empty() && (s.back() == ' ' || s.back() == '\t')) s.remove_suffix(1);
  return s;
}

template <std::size_t N>
double convert(std::string_view text, double value, std::string_view unit,
               const std::array<Unit, N>& units, std::string_view what) {
  for (const auto& u : units)
    if (u.name == unit) return value * u.factor;
  throw InputError(fmt::format("'{}': unknown {} unit '{}' (allowed: {})", text, what, unit,
                               join(units)));
}

}  // namespace

std::string allowed_units(Dimension dim) {
  switch (dim) {
    case Dimension::length: return join(length_units);
    case Dimension::stress: return join(stress_units);
    case Dimension::density: return join(density_units);
    case Dimension::ratio: return "a plain number or %";
    case Dimension::time: return join(time_units);
  }
  return {};
}

double parse_quantity(std::string_view text, Dimension dim) {
  const std::string_view s = trim(text);
  double value = 0.0;
  const auto [end, ec] = std::from_chars(s.data(), s.data() + s.size(), value);
  if (ec == std::errc::result_out_of_range)
    throw InputError(fmt::format("'{}': the number is out of the range of a double (about 1e-308 to 1e308 in "
                                 "magnitude)",
                                 text));
  if (ec != std::errc{} || end == s.data())
    throw InputError(fmt::format("'{}' does not start with a number", text));
  if (!std::isfinite(value)) throw InputError(fmt::format("'{}' is not a finite number", text));
  const std::string_view unit = trim(std::string_view(end, static_cast<std::size_t>(s.data() + s.size() - end)));
  switch (dim) {
    case Dimension::length:
      if (unit.empty()) break;
      return convert(text, value, unit, length_units, "length");
    case Dimension::stress:
      if (unit.empty()) break;
      return convert(text, value, unit, stress_units, "stress");
    case Dimension::density:
      if (unit.empty()) break;
      return convert(text, value, unit, density_units, "density");
    case Dimension::time:
      if (unit.empty()) break;
      return convert(text, value, unit, time_units, "time");
    case Dimension::ratio:
      if (unit.empty()) return value;
      return convert(text, value, unit, ratio_units, "ratio");
  }
  throw InputError(fmt::format("'{}' has no unit; write it with one of: {}", text,
                               allowed_units(dim)));
}

}  // namespace qsdem
