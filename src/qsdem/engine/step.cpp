#include "qsdem/engine/step.hpp"

#include <fmt/format.h>

#include <omp.h>

#include <algorithm>
#include <array>
#include <cmath>

#include "qsdem/engine/damping/stage.hpp"
#include "qsdem/engine/forces.hpp"
#include "qsdem/engine/integrator.hpp"
#include "qsdem/engine/measures.hpp"
#include "qsdem/engine/reorder.hpp"
#include "qsdem/engine/servo.hpp"

namespace qsdem {

// Stages 1 and 2: the pair forces at the current positions, with each particle's i-side sums.
void pair_forces(const Model& model, State& s, Schedule& schedule) {
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
    compute_contact_forces(model, s, schedule);
  }
}

// Stages 4-6 in one parallel region with no barrier: each thread owns a contiguous range of
// particles, adds their j-end contact forces, kicks them and drifts them (a particle's update
// reads only itself and the pair results). The kick's pass also translates them (timed as
// "integrate velocities"); "advance positions" is the ellipsoids' turn. One fork-join per step
// instead of three, one pass over the particle arrays. The region's wall time is shared among the
// three stages in proportion to the threads' summed time in each.
double update_particles(const Model& model, State& s, Schedule& schedule) {
  Particles& p = s.particles;
  // The force stage fixed the threads' particle ranges for this step (Schedule::owner_first).
  if (!schedule.has_owners_of(s)) assign_single_owner(schedule, s);
  const std::size_t owners = schedule.owners();
  const int nthreads = static_cast<int>(owners);
  KickEnergy kick_energy;
  if (model.track_energy) {
    s.kick_dissipation.resize(p.size());
    s.kick_kinetic.resize(p.size());
    kick_energy = {s.kick_dissipation.data(), s.kick_kinetic.data()};
  }
  double v2max = 0;
  std::array<double, 3> busy{};  // gather, kick, drift, summed over the threads
  schedule.owner_seconds.assign(owners, 0.0);
  const bool normalize = normalizes_orientations(s.step);
  // The drift's translation is made by the kick's pass (integrate_velocities' `move`, while it
  // holds v); the turn of the ellipsoids' orientations follows (spheres have none).
  const CellMap move(model.dt * s.cell.h_inv);
  double* const path = s.neighbor.surface_path.size() == p.size() ? s.neighbor.surface_path.data() : nullptr;
  const bool turns = has_ellipsoids(s);
  const double start = omp_get_wtime();
  // Thread r takes the particles the force stage assigned it (Schedule::owner_first, cut by the
  // owners' measured times) and reads only their contacts, which the force stage grouped by owner.
#pragma omp parallel num_threads(nthreads) if (nthreads > 1)
  {
    const int team = omp_get_num_threads();
    std::array<double, 3> mine{};
    double m = 0;
    for (int r = omp_get_thread_num(); r < nthreads; r += team) {
      const std::size_t lo = schedule.owner_first[r], hi = schedule.owner_first[r + 1];
      const double t0 = omp_get_wtime();
      gather_resultants(s.pairs, schedule, p, static_cast<std::size_t>(r));
      if (!s.contact_stiffness.empty()) gather_contact_stiffness(s.pairs, schedule, s, static_cast<std::size_t>(r));
      const double t1 = omp_get_wtime();
      update_damping(model, s, lo, hi);  // the damping stage, before the kick (damping/stage.hpp)
      m = std::max(m, integrate_velocities(model, p, lo, hi, kick_energy, &move, path));
      const double t2 = omp_get_wtime();
      if (turns) turn_orientations(model, p, s.neighbor.surface_path, lo, hi, kick_settles(model), normalize);
      const double t3 = omp_get_wtime();
      mine[0] += t1 - t0, mine[1] += t2 - t1, mine[2] += t3 - t2;
      schedule.owner_seconds[r] = t3 - t0;
    }
#pragma omp critical(qsdem_update_particles)
    {
      v2max = std::max(v2max, m);
      for (std::size_t k = 0; k < 3; ++k) busy[k] += mine[k];
    }
  }
  record_owner_times(schedule);  // the next steps' ranges (assign_owners)
  const double wall = omp_get_wtime() - start, sum = busy[0] + busy[1] + busy[2];
  constexpr std::array stages{Stage::gather, Stage::integrate, Stage::advance};
  for (std::size_t k = 0; k < 3; ++k)
    s.timers.seconds[static_cast<std::size_t>(stages[k])] += sum > 0 ? wall * busy[k] / sum : wall / 3;
  if (model.track_energy) {
    // Summed in fixed blocks on the threads (blocked_sum): the same bits for any thread count.
    const Eigen::Vector2d sums = blocked_sum<Eigen::Vector2d>(p.size(), Eigen::Vector2d::Zero(), [&](std::size_t i) {
      return Eigen::Vector2d(s.kick_dissipation[i], s.kick_kinetic[i]);
    });
    s.energy.damping += sums[0];
    s.energy.kinetic = sums[1];
  }
  return v2max;
}

void evaluate_forces(const Model& model, State& s) {
  Schedule schedule;
  pair_forces(model, s, schedule);
  ScopedStage t(s.timers, Stage::gather);
  gather_resultants(s, schedule);
}

void step(const Model& model, State& s) {
  Schedule schedule;
  step(model, s, schedule);
}

void step(const Model& model, State& s, Schedule& schedule) {
  // The cell's work from the last force evaluation to this one: the cell moved by L dt under the
  // stresses at both ends (trapezoid), -V sigma : L dt (compression positive).
  // (The force stage leaves L alone: the servo runs after it.)
  const auto power = [&] { return s.stress_volume * s.stress.cwiseProduct(s.cell.L).sum(); };  // V sigma : L
  const double power_before = model.track_energy ? power() : 0.0;
  pair_forces(model, s, schedule);
  if (model.track_energy) s.energy.boundary_work -= 0.5 * model.dt * (power_before + power());
  {
    // The cell's motion for the step needs only the stress and stiffness of the pair forces.
    ScopedStage t(s.timers, Stage::servo);
    servo_update(model, s);
    deform(s.cell, model.dt);
    s.neighbor.strain_path += model.dt * s.cell.L.norm();  // Frobenius >= 2-norm (neighbor.hpp)
  }
  const double v2max = update_particles(model, s, schedule);
  // The skin test's bound of the motion (any shapes), by which a run of spheres only also skips
  // apart pairs (NeighborState::moved_any).
  s.neighbor.fluctuation_path += 2 * model.dt * std::sqrt(v2max);
  s.time += model.dt;
  ++s.step;
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
