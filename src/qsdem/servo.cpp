#include "qsdem/servo.hpp"

#include <algorithm>
#include <cmath>

namespace qsdem {

void servo_update(const Model& model, State& state) {
  Mat3 L = Mat3::Zero();
  for (int k = 0; k < 3; ++k) {
    const AxisControl& c = model.control[static_cast<std::size_t>(k)];
    switch (c.kind) {
      case AxisControl::Kind::fixed:
        break;
      case AxisControl::Kind::strain_rate:
        L(k, k) = -c.value * c.reference_length / state.cell.h.col(k).norm();
        break;
      case AxisControl::Kind::stress: {
        const double target = c.value;
        const double err = (target - state.stress(k, k)) / target;
        const double cap = model.servo.max_strain_rate;
        const double stiff = state.affine_stiffness[k];
        double rate;
        if (stiff <= 0) {
          rate = err > 0 ? -cap : cap;  // no contacts: close (or open) the cell at the cap
        } else {
          const double integral = state.servo_integral[k] + err;
          rate = -(model.servo.proportional_gain * err + model.servo.integral_gain * integral) * target /
                 (stiff * model.dt);
          if (std::abs(rate) < cap) state.servo_integral[k] = integral;  // anti-windup
          rate = std::clamp(rate, -cap, cap);
        }
        L(k, k) = rate;
        break;
      }
    }
  }
  state.cell.L = L;
}

}  // namespace qsdem
