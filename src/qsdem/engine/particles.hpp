// Particle storage, structure of arrays (SPEC 2). Static properties (shape, mass, inertia,
// damping factor) and dynamic state live side by side so that a re-sort permutes one object.
// Every array is listed once more, in for_each_field below: resize, the reorder permutation,
// the checkpoint and the memory accounting go through that list.
#pragma once
#include <algorithm>
#include <concepts>
#include <cstdint>
#include <type_traits>
#include <vector>

#include "qsdem/engine/component_arrays.hpp"
#include "qsdem/engine/types.hpp"

namespace qsdem {

// Particles::symmetry_axis of a sphere, and of a body of three distinct moments.
constexpr std::int8_t kSphereBody = -2, kThreeMoments = -1;

struct Particles {
  // Static per run.
  std::vector<std::uint32_t> id;       // stable id, as generated or read
  std::vector<ShapeKind> shape;
  std::vector<Vec3> semi_axes;         // a >= b >= c, body frame (m)
  std::vector<double> bound_radius;    // radius of the bounding sphere = a (m)
  std::vector<double> equiv_radius;    // R_i = (abc)^(1/3) (m), SPEC 2
  std::vector<double> mass;            // kg: mu_i times the solid's (the dynamics' mass, SPEC 5.6)
  std::vector<Vec3> inertia;           // principal moments, body frame (kg m^2), mu_i times the solid's
  std::vector<double> inertia_scale;   // mu_i, the phase's inertia scaling (1: none), SPEC 5.6
  // Kept with mass and inertia (the integrator multiplies instead of dividing): 1 / mass; how the
  // drift turns the body: kSphereBody (no turn), the symmetry axis 0-2 of a body with two equal
  // moments (a spheroid's free flow, SPEC 5), or kThreeMoments; and 1 / I about that axis and
  // across it (a sphere's 1 / I both; 0 for three distinct moments, which the drift reads from
  // the moments).
  std::vector<double> inv_mass;
  std::vector<std::int8_t> symmetry_axis;
  std::vector<double> inv_axial_moment, inv_transverse_moment;
  std::vector<double> damping_translation;  // A_i (1/s), the damping stage's (damping/stage.hpp), SPEC 6
  std::vector<double> damping_rotation;     // B_i (1/s)

  // Dynamic state.
  std::vector<Vec3> s;                 // fractional position h^-1 x, never wrapped (SPEC 3)
  ComponentArrays<Quat> q;             // orientation, body -> world (component arrays: the drift's lanes)
  std::vector<Vec3> v;                 // fluctuation velocity at t - dt/2 (m/s)
  ComponentArrays<Vec3> angmom;        // angular momentum, world frame, at t - dt/2 (component arrays)
  std::vector<Vec3> omega;             // angular velocity, world frame, derived from angmom

  // Contact resultants at t (contact forces only, no damping), SPEC 7.
  std::vector<Vec3> force;
  std::vector<Vec3> torque;

  std::size_t size() const { return id.size(); }
  bool has_ellipsoids() const;
  std::size_t heap_bytes() const;  // held by the arrays
  // Sets inv_mass, symmetry_axis and the inverse moments from mass and inertia (a restored
  // checkpoint stores only these).
  void derive_inverses();
  void derive_inverses(std::size_t i);
  void resize(std::size_t n);
  // Appends one particle at rest with mass properties from the shape (SPEC 2).
  void add(std::uint32_t pid, ShapeKind kind, const Vec3& semi_axes, double density,
           const Vec3& frac_pos, const Quat& orientation);
};

// What the field registry tells about an array of Particles.
struct ParticleField {
  const char* name;
  // Checkpoint format from which the checkpoint saves the array; 0: never (derived from others).
  std::uint32_t saved_since;
};

// The field registry: f(array, ParticleField) for every array of Particles, in declaration order
// (the checkpoint's order). A static_assert in particles.cpp checks that it lists them all.
template <class P, class F>
  requires std::same_as<std::remove_const_t<P>, Particles>
constexpr void for_each_field(P& p, F&& f) {
  f(p.id, ParticleField{"id", 1});
  f(p.shape, ParticleField{"shape", 1});
  f(p.semi_axes, ParticleField{"semi_axes", 1});
  f(p.bound_radius, ParticleField{"bound_radius", 1});
  f(p.equiv_radius, ParticleField{"equiv_radius", 1});
  f(p.mass, ParticleField{"mass", 1});
  f(p.inertia, ParticleField{"inertia", 1});
  f(p.inertia_scale, ParticleField{"inertia_scale", 11});  // 1 in older formats (no scaling)
  f(p.inv_mass, ParticleField{"inv_mass", 0});
  f(p.symmetry_axis, ParticleField{"symmetry_axis", 0});
  f(p.inv_axial_moment, ParticleField{"inv_axial_moment", 0});
  f(p.inv_transverse_moment, ParticleField{"inv_transverse_moment", 0});
  f(p.damping_translation, ParticleField{"damping_translation", 1});
  f(p.damping_rotation, ParticleField{"damping_rotation", 0});  // set with the translation's on load
  f(p.s, ParticleField{"s", 1});
  f(p.q, ParticleField{"q", 1});
  f(p.v, ParticleField{"v", 1});
  f(p.angmom, ParticleField{"angmom", 1});
  f(p.omega, ParticleField{"omega", 1});
  f(p.force, ParticleField{"force", 1});
  f(p.torque, ParticleField{"torque", 1});
}

// Sets every particle's mu_i, mass and moments for `scaling` (SPEC 5.6): mu_i times those of the
// solid of density rho (SPEC 2). Leaves the particles untouched when the scaling is off and every
// mu_i is 1 already.
void scale_inertia(Particles& p, const InertiaScaling& scaling, double density);

// s = min_i R_i sqrt(mu_i) / R_min: the scaled critical step over the unscaled t_c (SPEC 5.6).
double step_gain(const Particles& p);

// Mass and principal moments of a solid ellipsoid (SPEC 2).
double ellipsoid_volume(const Vec3& semi_axes);
Vec3 ellipsoid_inertia(double mass, const Vec3& semi_axes);

// The symmetry axis of a body with two equal moments (kThreeMoments: three distinct ones). Equal
// moments come from the same expression (ellipsoid_inertia): b == c gives bit-equal I_b, I_c.
inline int equal_moments_axis(const Vec3& inertia) {
  if (inertia.y() == inertia.z()) return 0;
  if (inertia.x() == inertia.y()) return 2;
  return kThreeMoments;
}

// A body axis across the symmetry axis k (its moment is I_perp).
constexpr int transverse_axis(int k) { return (k + 1) % 3; }

// 1 / I_min, the largest inverse moment of particle i (the bits of max_k 1 / I_k: division rounds
// monotonically).
inline double inv_smallest_moment(const Particles& p, std::size_t i) {
  return p.symmetry_axis[i] == kThreeMoments ? 1 / p.inertia[i].minCoeff()
                                             : std::max(p.inv_axial_moment[i], p.inv_transverse_moment[i]);
}

// World-frame angular velocity from angular momentum: omega = R I^-1 R^T L.
inline Vec3 angular_velocity(const Quat& q, const Vec3& inertia, const Vec3& angmom) {
  const Vec3 body = q.conjugate() * angmom;
  return q * Vec3(body.x() / inertia.x(), body.y() / inertia.y(), body.z() / inertia.z());
}

}  // namespace qsdem
