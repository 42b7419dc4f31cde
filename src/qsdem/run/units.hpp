// Quantities with units in the configuration (SPEC 1): "390 kPa", "2.13 mm", "0.5 %".
#pragma once
#include <string>
#include <string_view>

namespace qsdem {

enum class Dimension { length, stress, density, ratio, time };

// Parses "<number> <unit>" into SI. Throws InputError naming what was expected.
// A ratio accepts a bare number (0.005) or a percentage ("0.5 %").
double parse_quantity(std::string_view text, Dimension dim);

// The units accepted for a dimension, for error messages and docs.
std::string allowed_units(Dimension dim);

}  // namespace qsdem
