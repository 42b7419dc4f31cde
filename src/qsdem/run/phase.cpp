#include "qsdem/run/phase.hpp"

#include <Eigen/LU>

#include <algorithm>
#include <cmath>

namespace qsdem {

bool planned_strain(const Phase& phase, int c) {
  // A FIRE phase's strain grows by its increments, measured (fire_phase.hpp).
  return !phase.fire && is_normal(c) && phase.stop.strain[static_cast<std::size_t>(c)].has_value() &&
         phase.controls.component[static_cast<std::size_t>(c)].kind == ControlKind::strain_rate;
}

double fastest_strain_rate(const Phase& phase) {
  double fastest = 0;
  for (const ComponentControl& c : phase.controls.component)
    if (c.kind == ControlKind::strain_rate) fastest = std::max(fastest, std::abs(c.value));
  return fastest;
}

bool holds_volume(const Phase& phase) {
  return std::any_of(phase.controls.component.begin(), phase.controls.component.end(),
                     [](const ComponentControl& c) { return c.kind == ControlKind::constant_volume; });
}

bool shears(const Phase& phase) {
  return std::any_of(phase.controls.component.begin() + 3, phase.controls.component.end(),
                     [](const ComponentControl& c) { return c.kind == ControlKind::strain_rate; });
}

long planned_step(long from, double strain, double target, double step_ratio, double eps) {
  return std::max(std::max(from, 1L), from + std::lround((target - strain) / (step_ratio * eps)));
}

long planned_end(const Phase& phase, double step_ratio) {
  long end = phase.stop.steps > 0 ? phase.stop.steps - 1 : -1;
  for (int c = 0; c < component_count; ++c)
    if (planned_strain(phase, c)) {
      const auto k = static_cast<std::size_t>(c);
      const long n = planned_step(0, 0.0, *phase.stop.strain[k], step_ratio, phase.controls.component[k].value);
      end = end < 0 ? n : std::min(end, n);
    }
  return end;
}

std::array<double, component_count> phase_strain(const Mat3& h, const Mat3& h0) {
  std::array<double, component_count> e{};
  for (int k = 0; k < 3; ++k) e[static_cast<std::size_t>(k)] = 1 - h(k, k) / h0(k, k);
  const Mat3 f = h * h0.inverse();
  for (int c = 3; c < component_count; ++c) {
    const auto [a, b] = component_axes[static_cast<std::size_t>(c)];
    e[static_cast<std::size_t>(c)] = f(a, b) + f(b, a);
  }
  return e;
}

}  // namespace qsdem
