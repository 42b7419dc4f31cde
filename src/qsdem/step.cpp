#include "qsdem/step.hpp"

#include <fmt/format.h>

#include <cmath>

#include "qsdem/forces.hpp"
#include "qsdem/integrator.hpp"
#include "qsdem/reorder.hpp"
#include "qsdem/servo.hpp"

namespace qsdem {

void evaluate_forces(const Model& model, State& s) {
  {
    ScopedStage t(s.timers, Stage::neighbor);
    // The motion bounds are those of the skipping of apart pairs (kept by step()).
    if (needs_rebuild(s.neighbor, s.particles, s.cell, model.skip_apart_pairs)) {
      if (model.sort_particles) sort_particles(s);  // neighbours in space, neighbours in memory
      build_pairs(s.particles, s.cell, model.skin, s.pairs, s.neighbor);
    }
  }
  {
    ScopedStage t(s.timers, Stage::contact_forces);
    compute_contact_forces(model, s);
  }
  {
    ScopedStage t(s.timers, Stage::gather);
    gather_resultants(s);
  }
}

void step(const Model& model, State& s) {
  evaluate_forces(model, s);
  {
    ScopedStage t(s.timers, Stage::integrate);
    const double v2max = integrate_velocities(model, s.particles);
    // A run of spheres only skips apart pairs by the largest speed (NeighborState::moved_any).
    if (s.neighbor.surface_path.empty()) s.neighbor.fluctuation_path += 2 * model.dt * std::sqrt(v2max);
  }
  {
    ScopedStage t(s.timers, Stage::servo);
    servo_update(model, s);
  }
  {
    ScopedStage t(s.timers, Stage::advance);
    deform(s.cell, model.dt);
    s.neighbor.strain_path += model.dt * s.cell.L.norm();  // Frobenius >= 2-norm (neighbor.hpp)
    advance_positions(model, s.cell, s.particles, s.neighbor.surface_path);
    s.time += model.dt;
    ++s.step;
  }
}

std::string format_stage_table(const StageTimers& t, long steps) {
  std::string out = fmt::format("{:<24} {:>10} {:>7} {:>12}\n", "stage", "seconds", "share", "us/step");
  const double total = t.total();
  for (std::size_t k = 0; k < t.seconds.size(); ++k)
    out += fmt::format("{:<24} {:>10.3f} {:>6.1f}% {:>12.2f}\n", stage_names[k], t.seconds[k],
                       total > 0 ? 100 * t.seconds[k] / total : 0.0,
                       steps > 0 ? 1e6 * t.seconds[k] / static_cast<double>(steps) : 0.0);
  out += fmt::format("{:<24} {:>10.3f} {:>6.1f}% {:>12.2f}\n", "total", total, 100.0,
                     steps > 0 ? 1e6 * total / static_cast<double>(steps) : 0.0);
  return out;
}

}  // namespace qsdem
