#include "qsdem/particles.hpp"

#include <algorithm>
#include <cmath>

namespace qsdem {

// Every array of Particles is in the registry (a new array that is not would be left out of the
// reorder, the checkpoint and the memory accounting).
static_assert([] {
  std::size_t fields = 0;
  Particles p;
  for_each_field(p, [&](auto&, ParticleField) { ++fields; });
  return fields * sizeof(std::vector<double>) == sizeof(Particles);
}());

double ellipsoid_volume(const Vec3& ax) { return 4.0 / 3.0 * pi * ax.x() * ax.y() * ax.z(); }

Vec3 ellipsoid_inertia(double m, const Vec3& ax) {
  const Vec3 sq = ax.cwiseProduct(ax);
  return m / 5.0 * Vec3(sq.y() + sq.z(), sq.x() + sq.z(), sq.x() + sq.y());
}

bool Particles::has_ellipsoids() const {
  // An OR over all of them, which runs in vector lanes: the force stage asks every step.
  unsigned any = 0;
  for (const ShapeKind k : shape) any |= k != ShapeKind::sphere ? 1u : 0u;
  return any != 0;
}

void Particles::derive_inverses() {
  inv_mass.resize(mass.size());
  inv_inertia.resize(inertia.size());
  for (std::size_t i = 0; i < mass.size(); ++i) {
    inv_mass[i] = 1 / mass[i];
    inv_inertia[i] = inertia[i].cwiseInverse();
  }
}

void Particles::resize(std::size_t n) {
  for_each_field(*this, [n](auto& array, ParticleField) { array.resize(n); });
}

void Particles::add(std::uint32_t pid, ShapeKind kind, const Vec3& ax, double density,
                    const Vec3& frac_pos, const Quat& orientation) {
  const std::size_t k = size();
  resize(k + 1);
  const double m = density * ellipsoid_volume(ax);
  id[k] = pid;
  shape[k] = kind;
  semi_axes[k] = ax;
  bound_radius[k] = ax.maxCoeff();
  equiv_radius[k] = std::cbrt(ax.x() * ax.y() * ax.z());
  mass[k] = m;
  inertia[k] = ellipsoid_inertia(m, ax);
  inv_mass[k] = 1 / m;
  inv_inertia[k] = inertia[k].cwiseInverse();
  damping_translation[k] = damping_rotation[k] = 0.0;
  s[k] = frac_pos;
  q[k] = orientation.normalized();
  v[k] = Vec3::Zero();
  angmom[k] = Vec3::Zero();
  omega[k] = Vec3::Zero();
  force[k] = Vec3::Zero();
  torque[k] = Vec3::Zero();
}

}  // namespace qsdem
