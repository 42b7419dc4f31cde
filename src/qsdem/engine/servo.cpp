#include "qsdem/engine/servo.hpp"

#include <Eigen/LU>
#include <algorithm>
#include <array>
#include <cmath>

namespace qsdem {
namespace {

// The constant-volume components' shared rate (servo.hpp): det(I + dt L) = 1.
void hold_volume(const Model& model, Mat3& L) {
  std::array<bool, 3> held{};
  bool any = false;
  for (int k = 0; k < 3; ++k) {
    held[static_cast<std::size_t>(k)] = model.control[static_cast<std::size_t>(k)].kind == ControlKind::constant_volume;
    any = any || held[static_cast<std::size_t>(k)];
  }
  if (!any) return;
  Mat3 m = Mat3::Identity() + model.dt * L;
  // d det(m) / d m_kk is the cofactor of (k, k): the 2x2 minor of the two other axes.
  const auto cofactor = [&m](int k) {
    const int a = (k + 1) % 3, b = (k + 2) % 3;
    return m(a, a) * m(b, b) - m(a, b) * m(b, a);
  };
  double x = 1;
  for (int it = 0; it < 8; ++it) {
    double slope = 0;
    for (int k = 0; k < 3; ++k)
      if (held[static_cast<std::size_t>(k)]) m(k, k) = x;
    for (int k = 0; k < 3; ++k)
      if (held[static_cast<std::size_t>(k)]) slope += cofactor(k);
    const double dx = (m.determinant() - 1) / slope;
    x -= dx;
    if (std::abs(dx) <= 1e-17) break;
  }
  for (int k = 0; k < 3; ++k)
    if (held[static_cast<std::size_t>(k)]) L(k, k) = (x - 1) / model.dt;
}

}  // namespace

void servo_update(const Model& model, State& state) {
  const Mat3& last = state.cell.L;  // the rates of the last step
  Mat3 L = Mat3::Zero();
  for (int k = 0; k < 3; ++k) {
    const ResolvedControl& c = model.control[static_cast<std::size_t>(k)];
    switch (c.kind) {
      case ControlKind::fixed:
      case ControlKind::constant_volume:  // set last, by hold_volume
        break;
      case ControlKind::strain_rate:
        L(k, k) = -c.value * c.reference_length / state.cell.h(k, k);
        break;
      case ControlKind::stress: {
        const double target = c.value;
        const double err = (target - state.stress(k, k)) / target;
        const double cap = model.servo.max_strain_rate;
        const double stiff = state.affine_stiffness[k], viscosity = state.affine_viscosity[k];
        double rate;
        if (stiff <= 0) {
          rate = err > 0 ? -cap : cap;  // no contacts: close (or open) the cell at the cap
        } else {
          const double integral = state.servo_integral[k] + err;
          rate = (viscosity * last(k, k) -
                  (model.servo.proportional_gain * err + model.servo.integral_gain * integral) * target) /
                 (stiff * model.dt + viscosity);
          if (std::abs(rate) < cap) state.servo_integral[k] = integral;  // anti-windup
          rate = std::clamp(rate, -cap, cap);
        }
        L(k, k) = rate;
        break;
      }
    }
  }
  // Shear stresses are relaxed only once the packing carries the target stress (every normal
  // stress within 10 %): before that they are collisional noise, and chasing them only tilts the cell.
  bool jammed = true;
  for (int k = 0; k < 3; ++k) {
    const ResolvedControl& c = model.control[static_cast<std::size_t>(k)];
    if (c.kind == ControlKind::stress && std::abs(state.stress(k, k) / c.value - 1) > 0.1) jammed = false;
  }
  for (int s = 0; s < 3; ++s) {
    const ResolvedControl& c = model.control[static_cast<std::size_t>(3 + s)];
    const auto [a, b] = component_axes[static_cast<std::size_t>(3 + s)];
    switch (c.kind) {
      case ControlKind::fixed:
      case ControlKind::constant_volume:  // normal components only
        break;
      case ControlKind::strain_rate:
        L(a, b) = c.value;  // simple shear: x_a moves in proportion to x_b
        break;
      case ControlKind::stress: {
        const double g = state.shear_stiffness[s], viscosity = state.shear_viscosity[s];
        if (!jammed || g <= 0) break;
        const double cap = model.servo.max_strain_rate;
        const double rate = std::clamp((model.servo.proportional_gain * (state.stress(a, b) - c.value) +
                                        viscosity * last(a, b)) /
                                           (g * model.dt + viscosity),
                                       -cap, cap);
        L(a, b) = L(b, a) = rate;
        break;
      }
    }
  }
  hold_volume(model, L);
  state.cell.L = L;
}

}  // namespace qsdem
