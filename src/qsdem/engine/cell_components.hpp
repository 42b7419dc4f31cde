// The six components of the periodic cell's velocity gradient that a loading phase drives
// (SPEC 3, 8), and how each is driven: one vocabulary for the case's controls (phase.hpp) and the
// model's resolved ones (model.hpp).
#pragma once
#include <array>
#include <cstdint>

namespace qsdem {

// The components in the order of the case keys 11, 22, 33, 12, 13, 23: the normal ones are the
// axes 0-2, the shear ones (3 + s) the axis pairs (a, b) with a < b.
inline constexpr int component_count = 6;
inline constexpr std::array<const char*, component_count> component_names{"11", "22", "33", "12", "13", "23"};
inline constexpr std::array<std::array<int, 2>, component_count> component_axes{
    {{0, 0}, {1, 1}, {2, 2}, {0, 1}, {0, 2}, {1, 2}}};
inline constexpr bool is_normal(int component) { return component < 3; }

// How a component is driven: held (fixed), at a strain rate, to a stress, or (normal components
// only) at the rate shared by every such component that keeps the cell's volume (servo.hpp).
// Stored as int32 in checkpoints.
enum class ControlKind : std::int32_t { fixed, strain_rate, stress, constant_volume };

// A kind's name as the case keys spell it.
inline constexpr const char* control_kind_name(ControlKind k) {
  switch (k) {
    case ControlKind::fixed: return "fixed";
    case ControlKind::strain_rate: return "strain_rate";
    case ControlKind::stress: return "stress";
    case ControlKind::constant_volume: return "constant_volume";
  }
  return "?";
}

}  // namespace qsdem
