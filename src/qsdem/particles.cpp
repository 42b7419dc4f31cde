#include "qsdem/particles.hpp"

#include <algorithm>
#include <cmath>

namespace qsdem {

double ellipsoid_volume(const Vec3& ax) { return 4.0 / 3.0 * pi * ax.x() * ax.y() * ax.z(); }

Vec3 ellipsoid_inertia(double m, const Vec3& ax) {
  const Vec3 sq = ax.cwiseProduct(ax);
  return m / 5.0 * Vec3(sq.y() + sq.z(), sq.x() + sq.z(), sq.x() + sq.y());
}

bool Particles::has_ellipsoids() const {
  // An OR over all of them, which runs in vector lanes: the force stage asks every step, and
  // std::find took 0.45 % of a sphere run's step (it scans them all there).
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
  id.resize(n);
  shape.resize(n);
  semi_axes.resize(n);
  bound_radius.resize(n);
  equiv_radius.resize(n);
  mass.resize(n);
  inertia.resize(n);
  inv_mass.resize(n);
  inv_inertia.resize(n);
  damping.resize(n);
  s.resize(n);
  q.resize(n);
  v.resize(n);
  angmom.resize(n);
  omega.resize(n);
  force.resize(n);
  torque.resize(n);
}

void Particles::add(std::uint32_t pid, ShapeKind kind, const Vec3& ax, double density,
                    const Vec3& frac_pos, const Quat& orientation) {
  const double m = density * ellipsoid_volume(ax);
  id.push_back(pid);
  shape.push_back(kind);
  semi_axes.push_back(ax);
  bound_radius.push_back(ax.maxCoeff());
  equiv_radius.push_back(std::cbrt(ax.x() * ax.y() * ax.z()));
  mass.push_back(m);
  inertia.push_back(ellipsoid_inertia(m, ax));
  inv_mass.push_back(1 / m);
  inv_inertia.push_back(inertia.back().cwiseInverse());
  damping.push_back(0.0);
  s.push_back(frac_pos);
  q.push_back(orientation.normalized());
  v.push_back(Vec3::Zero());
  angmom.push_back(Vec3::Zero());
  omega.push_back(Vec3::Zero());
  force.push_back(Vec3::Zero());
  torque.push_back(Vec3::Zero());
}

}  // namespace qsdem
