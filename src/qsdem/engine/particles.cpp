#include "qsdem/engine/particles.hpp"

#include <algorithm>
#include <cmath>
#include <limits>

namespace qsdem {

// Every array of Particles is in the registry (a new array that is not would be left out of the
// reorder, the checkpoint and the memory accounting).
static_assert([] {
  std::size_t fields = 0;  // bytes
  Particles p;
  for_each_field(p, [&](auto& array, ParticleField) { fields += sizeof(array); });
  return fields == sizeof(Particles);
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

std::size_t Particles::heap_bytes() const {
  std::size_t bytes = 0;
  const auto add = [&]<class T, class A>(const std::vector<T, A>& a) { bytes += a.capacity() * sizeof(T); };
  for_each_field(*this, [&]<class Array>(const Array& array, ParticleField) {
    if constexpr (requires { array.components(); })
      for (const auto& c : array.components()) add(c);
    else
      add(array);
  });
  return bytes;
}

void Particles::derive_inverses() {
  resize(mass.size());  // sizes the derived arrays
  for (std::size_t i = 0; i < mass.size(); ++i) derive_inverses(i);
}

void Particles::derive_inverses(std::size_t i) {
  inv_mass[i] = 1 / mass[i];
  const Vec3 inv = inertia[i].cwiseInverse();
  const int k = shape[i] == ShapeKind::sphere ? kSphereBody : equal_moments_axis(inertia[i]);
  symmetry_axis[i] = static_cast<std::int8_t>(k);
  const int axial = k == kSphereBody ? 0 : k;
  inv_axial_moment[i] = k == kThreeMoments ? 0.0 : inv[axial];
  inv_transverse_moment[i] = k == kThreeMoments ? 0.0 : inv[transverse_axis(axial)];
}

void scale_inertia(Particles& p, const InertiaScaling& scaling, double density) {
  const std::size_t n = p.size();
  if (!scaling.on() && std::all_of(p.inertia_scale.begin(), p.inertia_scale.end(), [](double mu) { return mu == 1; }))
    return;
  double r_min = std::numeric_limits<double>::infinity(), r_max = 0;
  for (const double r : p.equiv_radius) r_min = std::min(r_min, r), r_max = std::max(r_max, r);
  // R*: the radius whose t_c = 2 R sqrt(rho/E) (SPEC 5.1) every particle's scaled step reaches.
  const double target = scaling.target == InertiaScaling::Target::coarsest ? r_max : scaling.factor * r_min;
  for (std::size_t i = 0; i < n; ++i) {
    const double ratio = target / p.equiv_radius[i];
    const double mu = scaling.on() ? std::clamp(ratio * ratio, 1.0, scaling.cap) : 1.0;
    const double m = mu * (density * ellipsoid_volume(p.semi_axes[i]));  // as Particles::add at mu = 1
    p.inertia_scale[i] = mu;
    p.mass[i] = m;
    p.inertia[i] = ellipsoid_inertia(m, p.semi_axes[i]);
    p.derive_inverses(i);
  }
}

double step_gain(const Particles& p) {
  double r_min = std::numeric_limits<double>::infinity(), scaled = r_min;
  for (std::size_t i = 0; i < p.size(); ++i) {
    r_min = std::min(r_min, p.equiv_radius[i]);
    scaled = std::min(scaled, p.equiv_radius[i] * std::sqrt(p.inertia_scale[i]));
  }
  return scaled / r_min;  // exactly 1 when every mu_i is 1
}

void Particles::resize(std::size_t n) {
  inertia_scale.resize(n, 1.0);  // new particles are unscaled, whoever sets their masses
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
  inertia_scale[k] = 1.0;
  derive_inverses(k);
  damping_translation[k] = damping_rotation[k] = 0.0;
  s[k] = frac_pos;
  q.set(k, orientation.normalized());
  v[k] = Vec3::Zero();
  angmom.set(k, Vec3::Zero());
  omega[k] = Vec3::Zero();
  force[k] = Vec3::Zero();
  torque[k] = Vec3::Zero();
}

}  // namespace qsdem
