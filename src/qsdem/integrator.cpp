#include "qsdem/integrator.hpp"

#include <cmath>

namespace qsdem {

void integrate_velocities(const Model& model, Particles& p) {
  const double dt = model.dt;
  const std::size_t n = p.size();
#pragma omp parallel for schedule(static) if (n > parallel_threshold)
  for (std::size_t i = 0; i < n; ++i) {
    const double a = p.damping[i];  // A_i = B_i (SPEC 6)
    p.v[i] = damped_kick(p.v[i], p.force[i] / p.mass[i], a, dt);
    // Rotation with D_i = B_i I_i: the same form on the angular momentum (SPEC 5).
    p.angmom[i] = damped_kick(p.angmom[i], p.torque[i], a, dt);
    // A sphere's inertia is isotropic: omega = L / I, no frame change needed.
    p.omega[i] = p.shape[i] == ShapeKind::sphere ? Vec3(p.angmom[i] / p.inertia[i].x())
                                                 : angular_velocity(p.q[i], p.inertia[i], p.angmom[i]);
  }
}

void advance_positions(const Model& model, const Cell& cell, Particles& p) {
  const double dt = model.dt;
  const Mat3 step_map = dt * cell.h_inv;
  const std::size_t n = p.size();
#pragma omp parallel for schedule(static) if (n > parallel_threshold)
  for (std::size_t i = 0; i < n; ++i) {
    p.s[i] += step_map * p.v[i];
    if (p.shape[i] == ShapeKind::sphere) continue;  // a sphere's orientation changes nothing
    const double angle = p.omega[i].norm() * dt;
    if (angle > 0) {
      p.q[i] = (Quat(Eigen::AngleAxisd(angle, p.omega[i] / p.omega[i].norm())) * p.q[i]).normalized();
    }
  }
}

}  // namespace qsdem
