#include "qsdem/run/row_schedule.hpp"

#include <algorithm>
#include <cmath>

namespace qsdem {

long planned_end(const Phase& phase, const PhaseState& s, double step_ratio) {
  long end = phase.stop.steps > 0 ? phase.stop.steps - 1 : -1;
  for (int c = 0; c < 3; ++c)
    if (planned_strain(phase, c)) {
      const auto k = static_cast<std::size_t>(c);
      const long n = planned_step(s.segment_step[k], s.segment_strain[k], *phase.stop.strain[k], step_ratio,
                                  s.controls.component[k].value);
      end = end < 0 ? n : std::min(end, n);
    }
  return end;
}

long next_sample(const Phase& phase, const PhaseState& s, long rows, long end, double step_ratio) {
  const Cadence& c = phase.output.cadence;
  switch (c.kind) {
    case Cadence::Kind::points: {
      // row k of P at base + round((k - base_k) (end - base) / (P - base_k)); SPEC 8.4 from 0.
      const long k = rows + 1;
      if (k >= c.points) return end;
      return s.row_base_step + std::lround(static_cast<double>(k - s.row_base_rows) *
                                           static_cast<double>(end - s.row_base_step) /
                                           static_cast<double>(c.points - s.row_base_rows));
    }
    case Cadence::Kind::every_steps:
      return (rows + 1) * c.every_steps - 1;  // after every every_steps steps of the phase
    case Cadence::Kind::every_strain: {
      if (!is_normal(c.strain_component)) return -1;  // a shear strain is measured: measured_row
      const auto k = static_cast<std::size_t>(c.strain_component);
      const double eps = s.controls.component[k].value;
      const double target = static_cast<double>(rows + 1) * c.every_strain * (eps > 0 ? 1 : -1);
      return planned_step(s.segment_step[k], s.segment_strain[k], target, step_ratio, eps);
    }
  }
  return end;
}

bool measured_row(const Phase& phase, const PhaseState& s, long rows, const State& st, const Mat3& h0) {
  const Cadence& c = phase.output.cadence;
  if (c.kind != Cadence::Kind::every_strain || is_normal(c.strain_component)) return false;
  const auto k = static_cast<std::size_t>(c.strain_component);
  const double direction = s.controls.component[k].value > 0 ? 1.0 : -1.0;
  return direction * phase_strain(st.stress_h, h0)[k] >= static_cast<double>(rows + 1) * c.every_strain;
}

void controls_changed(const PhaseControls& before, PhaseState& s, long n, long rows, double step_ratio) {
  for (std::size_t k = 0; k < 3; ++k) {
    const ComponentControl& old = before.component[k];
    if (old.kind != ControlKind::strain_rate || old.value == s.controls.component[k].value) continue;
    s.segment_strain[k] += static_cast<double>(n + 1 - s.segment_step[k]) * (step_ratio * old.value);
    s.segment_step[k] = n + 1;
  }
  s.row_base_step = std::max(s.last_row_step, 0L);
  s.row_base_rows = rows;
}

}  // namespace qsdem
