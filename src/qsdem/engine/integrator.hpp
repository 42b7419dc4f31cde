// Time integration (SPEC 5) with the particle damping of SPEC 6.
#pragma once
#include <cstdint>
#include <span>

#include "qsdem/engine/cell.hpp"
#include "qsdem/engine/model.hpp"
#include "qsdem/engine/particles.hpp"

namespace qsdem {

// Central-difference velocity update with viscous damping factor A (paper Eq. 10):
//   v(t+dt/2) = [(1 - A dt/2) v(t-dt/2) + dt F/m] / (1 + A dt/2) = keep v + gain F/m,
// the two factors computed once (no division per particle). T: a double, or vector lanes of them
// (the kick's lanes, integrator.cpp): the same operations, so the same bits.
template <class T>
inline void damped_kick_factors(const T& a, double dt, T& keep, T& gain) {
  const T h = 0.5 * a * dt, c = 1 / (1 + h);
  keep = (1 - h) * c, gain = dt * c;
}
struct DampedKick {
  double keep, gain;
  DampedKick(double a, double dt) { damped_kick_factors(a, dt, keep, gain); }
  Vec3 operator()(const Vec3& v, const Vec3& rate) const { return keep * v + gain * rate; }
};

inline Vec3 damped_kick(const Vec3& v, const Vec3& force_over_mass, double a, double dt) {
  return DampedKick(a, dt)(v, force_over_mass);
}

// Where the kick writes, per particle, the energy the damping took in it and the kinetic energy
// after it (J): State::kick_dissipation, kick_kinetic (Model::track_energy), or none (null).
struct KickEnergy {
  double* dissipated = nullptr;
  double* kinetic = nullptr;
};

// Velocities and angular momenta to t + dt/2 (SPEC 5) with the damping stage's factors
// (Particles::damping_translation, damping_rotation); angular velocity from the body inertia.
// Particles [lo, hi), on the calling thread (the step runs it on each thread's range, step.cpp).
// Returns the largest |v|^2 after the kick (NeighborState::fluctuation_path).
// With `move` (dt h^-1 of the deformed cell) the particles are also translated, s += dt h^-1 v,
// and dt |v| is added to `path` (a surface path, or null), with the same bits as
// advance_positions: the step's translation, which the viscous kick makes in its own pass while it
// holds v (turn_orientations then does the rest of the drift).
double integrate_velocities(const Model& model, Particles& p, std::size_t lo = 0, std::size_t hi = SIZE_MAX,
                            KickEnergy energy = {}, const CellMap* move = nullptr, double* path = nullptr);

// Whether integrate_velocities with this model settles the momenta (SPEC 5.2: every viscous
// model; Cundall's local damping does not): after it, every angular momentum is zero or has a
// component of at least 2^-540 (what advance_positions' `settled` tells it).
bool kick_settles(const Model& model);

// Free rotation of a rigid body over dt at constant world angular momentum L (the drift half of
// the rotational leapfrog, SPEC 5): returns q(t+dt) from q(t). Second order, time-reversible and
// symplectic, gyroscopic motion included (omega follows the body as it turns). Exact for bodies
// with two equal principal moments (spheroids); NO_SQUISH splitting otherwise (integrator.cpp).
// Without `normalize` a spheroid's q(t+dt) is the product of the turns as it is (SPEC 5.4).
Quat free_rotation(const Quat& q, const Vec3& inertia, const Vec3& angmom, double dt, bool normalize = true);

// The steps (s.step a multiple of it) at which the drift restores the norm of the spheroids'
// orientations; between them it is 1 to round-off (SPEC 5.4).
constexpr long kNormalizeEvery = 16;
inline bool normalizes_orientations(long step) { return step % kNormalizeEvery == 0; }

// Positions and orientations to t + dt in the already deformed cell: s += dt h^-1 v (the affine
// part moves with h, SPEC 3); ellipsoids turn by free_rotation at the angular momentum
// L(t+dt/2) and leave omega = R I^-1 R^T L at the new orientation (what the next contact forces
// read). Spheres: orientation and omega = L / I untouched.
// surface_path (one per particle, or empty): adds how far each particle's surface can have moved
// in this step, dt |v| + 2 a |q_new - q_old| (NeighborState::surface_path).
// Particles [lo, hi), on the calling thread, as integrate_velocities. `settled`: the momenta are
// as a kick that settles them leaves them (kick_settles): no L of subnormal size to keep out of
// the vector lanes, and none looked for. `normalize`: the spheroids' orientations are normalised
// (normalizes_orientations), else left as the turns' product.
void advance_positions(const Model& model, const Cell& cell, Particles& p, std::span<double> surface_path = {},
                       std::size_t lo = 0, std::size_t hi = SIZE_MAX, bool settled = false, bool normalize = true);

// advance_positions without the translation (which integrate_velocities' `move` made): the
// ellipsoids' turn, omega and the turn's part of the surface path.
void turn_orientations(const Model& model, Particles& p, std::span<double> surface_path, std::size_t lo,
                       std::size_t hi, bool settled, bool normalize);

}  // namespace qsdem
