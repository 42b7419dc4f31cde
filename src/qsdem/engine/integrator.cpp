#include "qsdem/engine/integrator.hpp"

#include <algorithm>
#include <array>
#include <cmath>
#include <cstdint>
#include <cstring>

#include "qsdem/engine/clones.hpp"

namespace qsdem {

namespace {

// Cundall's local damping of one vector (SPEC 6 `local`): each component f_k of a force (or moment)
// becomes f_k - alpha |f_k| sign(v_k) = f_k (1 - alpha sign(f_k) sign(v_k)), as YADE's NewtonIntegrator.
// The factor is 1 - alpha for equal signs, 1 + alpha for opposite ones and 1 where f or v is zero,
// chosen by selects (vector lanes, the bits of the product of signs): (1 - alpha (-1)) = 1 + alpha
// and 1 - alpha 0 = 1 exactly. Where f or v is NaN the velocity is NaN either way.
[[gnu::always_inline]] inline double cundall_damped(double f, double v, double alpha) {
  const bool moving = (f != 0) & (v != 0), opposite = (f < 0) != (v < 0);
  return f * (moving ? (opposite ? 1 + alpha : 1 - alpha) : 1.0);
}
[[gnu::always_inline]] inline Vec3 cundall_damped(const Vec3& f, const Vec3& v, double alpha) {
  return {cundall_damped(f.x(), v.x(), alpha), cundall_damped(f.y(), v.y(), alpha), cundall_damped(f.z(), v.z(), alpha)};
}

// After the viscous kick a velocity or angular momentum whose every component is below 2^-540 (SI)
// is set to zero (SPEC 5.2): a rattler's decays geometrically under viscous damping, and would pass
// through the subnormal numbers, each operation on which costs ~50 ns here (a microcode assist).
// 2^-540 = 2.8e-163 m/s or kg m^2/s moves or turns a particle by far less than the round-off of
// its position and orientation (advance_positions: |L|^2 rounds to 0, no turn).
constexpr double kSettled = 0x1p-540;
[[gnu::always_inline]] inline bool settled(double x, double y, double z) {
  return (std::abs(x) < kSettled) & (std::abs(y) < kSettled) & (std::abs(z) < kSettled);
}
[[gnu::always_inline]] inline Vec3 settle(const Vec3& x) {
  return settled(x.x(), x.y(), x.z()) ? Vec3::Zero() : x;
}

// Column K of R(q), q = (w, x, y, z): the body axis K in the world frame (T: a double or vector lanes).
template <int K, class T>
[[gnu::always_inline]] inline void body_axis(const T& w, const T& x, const T& y, const T& z, T& ax, T& ay, T& az) {
  if constexpr (K == 0) {
    ax = 1 - 2 * (y * y + z * z), ay = 2 * (x * y + w * z), az = 2 * (x * z - w * y);
  } else if constexpr (K == 1) {
    ax = 2 * (x * y - w * z), ay = 1 - 2 * (x * x + z * z), az = 2 * (y * z + w * x);
  } else {
    ax = 2 * (x * z + w * y), ay = 2 * (y * z - w * x), az = 1 - 2 * (x * x + y * y);
  }
}

// omega = R I^-1 R^T L of a body with two equal moments, symmetry axis K: I^-1 = inv_perp 1 +
// (inv_s - inv_perp) e e^T with e = R e_K (SPEC 5), one column of R instead of two rotations.
template <int K, class T>
[[gnu::always_inline]] inline void axisymmetric_omega(const T& w, const T& x, const T& y, const T& z, const T& lx,
                                                      const T& ly, const T& lz, const T& inv_s, const T& inv_perp,
                                                      T& ox, T& oy, T& oz) {
  T ex, ey, ez;
  body_axis<K>(w, x, y, z, ex, ey, ez);
  const T f = (inv_s - inv_perp) * (ex * lx + ey * ly + ez * lz);
  ox = inv_perp * lx + f * ex, oy = inv_perp * ly + f * ey, oz = inv_perp * lz + f * ez;
}
inline Vec3 axisymmetric_omega(int k, const Quat& q, const Vec3& l, double inv_s, double inv_perp) {
  Vec3 o;
  const auto at = [&]<int K>() {
    axisymmetric_omega<K>(q.w(), q.x(), q.y(), q.z(), l.x(), l.y(), l.z(), inv_s, inv_perp, o.x(), o.y(), o.z());
  };
  if (k == 0) at.template operator()<0>();
  else if (k == 1) at.template operator()<1>();
  else at.template operator()<2>();
  return o;
}

// A particle's omega from its angular momentum L (angular_velocity), by the cheapest exact form
// its moments allow (Particles::symmetry_axis).
inline Vec3 particle_omega(const Particles& p, std::size_t i, const Vec3& l) {
  const int k = p.symmetry_axis[i];
  if (k == kSphereBody) return l * p.inv_transverse_moment[i];
  if (k >= 0) return axisymmetric_omega(k, p.q[i], l, p.inv_axial_moment[i], p.inv_transverse_moment[i]);
  return angular_velocity(p.q[i], p.inertia[i], l);
}

// The kick with Cundall's local damping of particles [lo, hi), on components, in vector lanes,
// translation and rotation in two loops (one loop of both ran out of registers). One particle at a
// time it cost 4-5 times the viscous kick (1001 spheres, random signs of the rattlers' velocities:
// 25-55 us against 4-13 us per step). `local` has no viscous factors (A_i = B_i = 0: a Cundall
// model, damping/models.hpp): the kick is v + dt a, the bits of DampedKick(0, dt) (1 v + dt a).
// Sums in the order of Eigen's for 3-vectors (left to right). Built for AVX-512 too (no FMA: the
// same bits), as the spheres' rotation: the kick of 1001 spheres 5.5 -> 3.7 us.
QSDEM_CLONES_WIDE double local_kick_translation(const double* inv_mass, const Vec3* force, Vec3* vel, std::size_t lo,
                                           std::size_t hi, double dt, double alpha) {
  double v2max = 0;
  const double half = 0.5 * dt;
#pragma omp simd reduction(max : v2max)
  for (std::size_t i = lo; i < hi; ++i) {
    const double m = inv_mass[i];
    const double ax = force[i].x() * m, ay = force[i].y() * m, az = force[i].z() * m;
    double vx = vel[i].x(), vy = vel[i].y(), vz = vel[i].z();
    // The sign of the fluctuating velocity at t predicted from t - dt/2 (YADE's cundallDamp2nd).
    vx = vx + dt * cundall_damped(ax, vx + half * ax, alpha);
    vy = vy + dt * cundall_damped(ay, vy + half * ay, alpha);
    vz = vz + dt * cundall_damped(az, vz + half * az, alpha);
    vel[i].x() = vx, vel[i].y() = vy, vel[i].z() = vz;
    const double v2 = (vx * vx + vy * vy) + vz * vz;
    v2max = v2max < v2 ? v2 : v2max;  // std::max(v2max, v2)
  }
  return v2max;
}

// Rotation, spheres only: omega = L / I has the signs of L(t - dt/2) + dt/2 M.
// The angular momentum's component arrays, through local pointers (as the kick's other arrays).
struct AngmomArrays {
  double *x, *y, *z;
  explicit AngmomArrays(ComponentArrays<Vec3>& l) : x(l.component(0)), y(l.component(1)), z(l.component(2)) {}
  Vec3 operator[](std::size_t i) const { return {x[i], y[i], z[i]}; }
  void set(std::size_t i, const Vec3& l) const { x[i] = l.x(), y[i] = l.y(), z[i] = l.z(); }
};

// inv_moment: each sphere's 1 / I (Particles::inv_transverse_moment).
QSDEM_CLONES_WIDE void local_kick_spheres(const double* inv_moment, const Vec3* torque, AngmomArrays angmom,
                                          Vec3* omega, std::size_t lo, std::size_t hi, double dt, double alpha) {
  const double half = 0.5 * dt;
#pragma omp simd
  for (std::size_t i = lo; i < hi; ++i) {
    const double mx = torque[i].x(), my = torque[i].y(), mz = torque[i].z();
    double lx = angmom.x[i], ly = angmom.y[i], lz = angmom.z[i];
    lx = lx + dt * cundall_damped(mx, lx + half * mx, alpha);
    ly = ly + dt * cundall_damped(my, ly + half * my, alpha);
    lz = lz + dt * cundall_damped(mz, lz + half * mz, alpha);
    angmom.x[i] = lx, angmom.y[i] = ly, angmom.z[i] = lz;
    const double inv = inv_moment[i];
    omega[i].x() = lx * inv, omega[i].y() = ly * inv, omega[i].z() = lz * inv;
  }
}

// Rotation with ellipsoids among the particles: an ellipsoid's moment is damped by omega at q(t)
// from L(t - dt/2) (YADE's cundallDamp1st for aspherical bodies), and its omega is set by
// advance_positions at its new orientation; a sphere's omega is set by local_kick_sphere_spins
// (storing every omega here made the kick of 8000 spheroids 12 % slower).
QSDEM_CLONES void local_kick_bodies(const Vec3* torque, const ShapeKind* shape, AngmomArrays angmom,
                                    const Vec3* omega, std::size_t lo, std::size_t hi, double dt, double alpha) {
  const double half = 0.5 * dt;
#pragma omp simd
  for (std::size_t i = lo; i < hi; ++i) {
    const bool sphere = shape[i] == ShapeKind::sphere;
    const double mx = torque[i].x(), my = torque[i].y(), mz = torque[i].z();
    double lx = angmom.x[i], ly = angmom.y[i], lz = angmom.z[i];
    const double ox = omega[i].x(), oy = omega[i].y(), oz = omega[i].z();
    const double sx = sphere ? lx + half * mx : ox, sy = sphere ? ly + half * my : oy, sz = sphere ? lz + half * mz : oz;
    lx = lx + dt * cundall_damped(mx, sx, alpha);
    ly = ly + dt * cundall_damped(my, sy, alpha);
    lz = lz + dt * cundall_damped(mz, sz, alpha);
    angmom.x[i] = lx, angmom.y[i] = ly, angmom.z[i] = lz;
  }
}

// The spheres' omega = L / I among ellipsoids.
void local_kick_sphere_spins(const double* inv_moment, const ShapeKind* shape, AngmomArrays angmom, Vec3* omega,
                             std::size_t lo, std::size_t hi) {
  for (std::size_t i = lo; i < hi; ++i)
    if (shape[i] == ShapeKind::sphere) omega[i] = angmom[i] * inv_moment[i];
}

double local_kick(Particles& p, std::size_t lo, std::size_t hi, double dt, double alpha, double alpha_rot) {
  hi = std::min(hi, p.size());
  if (lo >= hi) return 0;
  const double v2max = local_kick_translation(p.inv_mass.data(), p.force.data(), p.v.data(), lo, hi, dt, alpha);
  unsigned ellipsoids = 0, spheres = 0;  // ORs over the range, in vector lanes
  for (std::size_t i = lo; i < hi; ++i) {
    ellipsoids |= p.shape[i] != ShapeKind::sphere ? 1u : 0u;
    spheres |= p.shape[i] == ShapeKind::sphere ? 1u : 0u;
  }
  if (ellipsoids == 0) {
    local_kick_spheres(p.inv_transverse_moment.data(), p.torque.data(), AngmomArrays(p.angmom), p.omega.data(), lo,
                       hi, dt, alpha_rot);
  } else {
    local_kick_bodies(p.torque.data(), p.shape.data(), AngmomArrays(p.angmom), p.omega.data(), lo, hi, dt, alpha_rot);
    if (spheres != 0)
      local_kick_sphere_spins(p.inv_transverse_moment.data(), p.shape.data(), AngmomArrays(p.angmom), p.omega.data(),
                              lo, hi);
  }
  return v2max;
}

// The kick's arrays through local pointers: through p, each store made GCC load the next array's
// address again (it cannot tell that a Vec3 store leaves p's vectors alone).
struct KickArrays {
  const double *damping_of, *damping_rot_of, *inv_mass;  // A_i, B_i (SPEC 6), 1 / m
  const double* inv_moment;                              // a sphere's 1 / I (inv_transverse_moment)
  const Vec3 *force, *torque;
  const ShapeKind* shape;
  Vec3* vel;
  AngmomArrays angmom;
  Vec3* omega;
  Vec3* pos;  // (a kick that also translates)
  explicit KickArrays(Particles& p)
      : damping_of(p.damping_translation.data()), damping_rot_of(p.damping_rotation.data()),
        inv_mass(p.inv_mass.data()), inv_moment(p.inv_transverse_moment.data()), force(p.force.data()),
        torque(p.torque.data()), shape(p.shape.data()), vel(p.v.data()), angmom(p.angmom), omega(p.omega.data()),
        pos(p.s.data()) {}
};

// The kick's energy identity of particle i (physics.md 12, D_p): m (v' - v).(v' + v)/2 =
// dt F.v_mid - dissipated, so the damping took (dt F - m dv).v_mid; the same with M, L and
// omega = I^-1 L at this orientation (the drift keeps the rotational energy: a free rotation).
// Also the kinetic energy after the kick.
inline void kick_energy(const Particles& p, std::size_t i, double dt, const Vec3& v_old, const Vec3& v,
                        const Vec3& l_old, const Vec3& l, KickEnergy energy) {
  const Vec3 v_mid = 0.5 * (v_old + v), l_mid = 0.5 * (l_old + l);
  const double mass = 1 / p.inv_mass[i];
  energy.dissipated[i] = (dt * p.force[i] - mass * (v - v_old)).dot(v_mid) +
                         (dt * p.torque[i] - (l - l_old)).dot(particle_omega(p, i, l_mid));
  energy.kinetic[i] = 0.5 * mass * v.squaredNorm() + 0.5 * l.dot(particle_omega(p, i, l));
}

// The viscous kick of particles [lo, hi), one particle at a time (the lanes' last particles).
// Track: also each particle's dissipation and kinetic energy (KickEnergy).
template <bool Track>
double kick_particles(const Model& model, Particles& p, std::size_t lo, std::size_t hi, KickEnergy energy) {
  const double dt = model.dt;
  hi = std::min(hi, p.size());
  double v2max = 0;
  // The factors of the last damping seen, for translation and rotation (one value each in most runs).
  double damping = 0, damping_rot = 0;
  DampedKick kick(damping, dt), kick_rot(damping_rot, dt);
  const KickArrays arrays(p);
  for (std::size_t i = lo; i < hi; ++i) {
    if (arrays.damping_of[i] != damping) kick = DampedKick(damping = arrays.damping_of[i], dt);  // A_i (SPEC 6)
    if (arrays.damping_rot_of[i] != damping_rot)
      kick_rot = DampedKick(damping_rot = arrays.damping_rot_of[i], dt);  // B_i
    const Vec3 v_old = arrays.vel[i], l_old = arrays.angmom[i];
    const Vec3 v = settle(kick(v_old, arrays.force[i] * arrays.inv_mass[i]));
    arrays.vel[i] = v;
    v2max = std::max(v2max, v.squaredNorm());
    // Rotation with D_i = B_i I_i: the same form on the angular momentum (SPEC 5).
    const Vec3 l = settle(kick_rot(l_old, arrays.torque[i]));
    arrays.angmom.set(i, l);
    if constexpr (Track) kick_energy(p, i, dt, v_old, v, l_old, l, energy);
    // A sphere's inertia is isotropic: omega = L / I, no frame change needed. An ellipsoid's
    // omega is set by advance_positions at its new orientation (nothing reads it before).
    if (arrays.shape[i] == ShapeKind::sphere) arrays.omega[i] = l * arrays.inv_moment[i];
  }
  return v2max;
}

// The viscous kick (kick_particles<false>) four particles at a time. The 3-vector arrays
// are read as the components' lanes of four particles (load_xyz4: three loads and six shuffles),
// so the arithmetic runs in vector lanes without the stride-3 loads GCC makes of them. Each lane
// has its own factors of DampedKick, computed by the same operations (the same bits as the
// factors kept from particle to particle), and the same sums in the same order: bit for bit the
// kick of one particle at a time, which takes the range's last particles (fewer than four).
// (GCC warns that such vectors change the ABI of a call where AVX is off: these helpers are
// always inlined: no call passes them. GCC gives the warning at the end of the file: off from here on.)
#pragma GCC diagnostic ignored "-Wpsabi"
using Lanes4 = double __attribute__((vector_size(32)));
using Mask4 = std::int64_t __attribute__((vector_size(32)));

[[gnu::always_inline]] inline Lanes4 load4(const double* p) {
  Lanes4 x;
  std::memcpy(&x, p, sizeof x);
  return x;
}
[[gnu::always_inline]] inline void store4(double* p, const Lanes4& x) { std::memcpy(p, &x, sizeof x); }

// Four consecutive 3-vectors (x0 y0 z0 x1 | y1 z1 x2 y2 | z2 x3 y3 z3) as lanes of x, y and z.
struct Xyz4 {
  Lanes4 x, y, z;
};
[[gnu::always_inline]] inline Xyz4 load_xyz4(const Vec3* v) {
  const double* d = v->data();
  const Lanes4 a = load4(d), b = load4(d + 4), c = load4(d + 8);
  const Lanes4 x = __builtin_shufflevector(a, b, 0, 3, 6, 6), y = __builtin_shufflevector(a, b, 1, 4, 7, 7),
               z = __builtin_shufflevector(a, b, 2, 5, 5, 5);
  return {__builtin_shufflevector(x, c, 0, 1, 2, 5), __builtin_shufflevector(y, c, 0, 1, 2, 6),
          __builtin_shufflevector(z, c, 0, 1, 4, 7)};
}
[[gnu::always_inline]] inline void store_xyz4(Vec3* v, const Xyz4& r) {
  double* d = v->data();
  store4(d, __builtin_shufflevector(__builtin_shufflevector(r.x, r.y, 0, 4, 0, 1), r.z, 0, 1, 4, 3));
  store4(d + 4, __builtin_shufflevector(__builtin_shufflevector(r.y, r.z, 1, 5, 1, 2), r.x, 0, 1, 6, 3));
  store4(d + 8, __builtin_shufflevector(__builtin_shufflevector(r.x, r.y, 3, 3, 7, 7), r.z, 6, 1, 2, 7));
}

// DampedKick(a, dt)'s factors in lanes, computed again only when a group's damping differs from
// the last group's (a division per lane; equal damping gives equal factors, +0 and -0 alike).
struct KickFactors {
  Lanes4 a{}, keep, gain;  // a = 0: keep 1, gain dt
  explicit KickFactors(double dt) : keep{1, 1, 1, 1}, gain{dt, dt, dt, dt} {}
  [[gnu::always_inline]] void update(const Lanes4& next, double dt) {
    const Mask4 same = next == a;
    if ((same[0] & same[1] & same[2] & same[3]) != 0) return;
    a = next;
    damped_kick_factors(a, dt, keep, gain);
  }
};

// The kick and its settle, in lanes: keep v + gain rate, zero where every |component| < 2^-540.
[[gnu::always_inline]] inline Xyz4 damped_kick_lanes(const KickFactors& f, const Xyz4& v, const Xyz4& rate) {
  const Lanes4 keep = f.keep, gain = f.gain;
  Xyz4 out{keep * v.x + gain * rate.x, keep * v.y + gain * rate.y, keep * v.z + gain * rate.z};
  const auto small = [](const Lanes4& x) { return (x < kSettled) & (x > -kSettled); };
  const Mask4 keep_bits = ~(small(out.x) & small(out.y) & small(out.z));
  out.x = reinterpret_cast<Lanes4>(reinterpret_cast<Mask4>(out.x) & keep_bits);
  out.y = reinterpret_cast<Lanes4>(reinterpret_cast<Mask4>(out.y) & keep_bits);
  out.z = reinterpret_cast<Lanes4>(reinterpret_cast<Mask4>(out.z) & keep_bits);
  return out;
}

// The drift's translation of particles [lo, hi) (advance_positions): s += dt h^-1 v (m: dt h^-1,
// in the order of Eigen's product, CellMap) and, with a path, path += dt |v|; four particles at a
// time in lanes. A particle is still where every |v_k| < slow and every |s_k| >= 2^-500: the step
// is below half an ulp of s and |v|^2 rounds to 0, so s and the path keep their bits and are left
// alone (no arithmetic on subnormal numbers); a group of four with such a v goes one at a time,
// unless that v is zeros (a settled rattler's): the lanes add zeros, which keeps the same bits.
[[gnu::always_inline]] inline void translate_one(const CellMap& m, double dt, double slow, Vec3& s, const Vec3& v,
                                                 double* path) {
  constexpr double far = 0x1p-500;
  const auto small = [slow](double x) { return std::abs(x) < slow; };
  const auto apart = [](double x) { return std::abs(x) >= far; };
  if (small(v.x()) && small(v.y()) && small(v.z()) && apart(s.x()) && apart(s.y()) && apart(s.z())) return;
  double x, y, z;
  m.apply(v.x(), v.y(), v.z(), x, y, z);
  s.x() += x, s.y() += y, s.z() += z;
  if (path) *path += dt * std::sqrt((v.x() * v.x() + v.y() * v.y()) + v.z() * v.z());
}

// |v|^2 in lanes, summed as Eigen's squaredNorm.
[[gnu::always_inline]] inline Lanes4 squared(const Xyz4& v) { return (v.x * v.x + v.y * v.y) + v.z * v.z; }

// The surface path's part of a translation, path += dt |v| (NeighborState::surface_path), in lanes.
[[gnu::always_inline]] inline void add_speed(double* path, const Lanes4& v2, double dt) {
  const Lanes4 speed{std::sqrt(v2[0]), std::sqrt(v2[1]), std::sqrt(v2[2]), std::sqrt(v2[3])};
  store4(path, load4(path) + dt * speed);
}

// s + m v in lanes (the order of CellMap::apply).
[[gnu::always_inline]] inline Xyz4 moved(const CellMap& m, const Xyz4& s, const Xyz4& v) {
  return {s.x + ((m.h00 * v.x + m.h01 * v.y) + m.h02 * v.z), s.y + ((m.h10 * v.x + m.h11 * v.y) + m.h12 * v.z),
          s.z + (m.h20 * v.x + (m.h21 * v.y + m.h22 * v.z))};
}

// The speed below which a particle is still (translate): every |v_k| below 2^-556 / (3 max|m|)
// and 2^-540 moves s by less than 2^-555, under half an ulp of any |s_k| >= 2^-500.
inline double still_speed(const CellMap& m) {
  const double largest = std::max({std::abs(m.h00), std::abs(m.h01), std::abs(m.h02), std::abs(m.h10),
                                   std::abs(m.h11), std::abs(m.h12), std::abs(m.h20), std::abs(m.h21),
                                   std::abs(m.h22)});
  return largest > 0 ? std::min(0x1p-556 / (3 * largest), kSettled) : 0.0;
}

QSDEM_CLONES void translate(const CellMap m, double dt, double slow, Vec3* pos, const Vec3* vel, double* path,
                            std::size_t lo, std::size_t hi) {
  std::size_t i = lo;
  for (; i + 4 <= hi; i += 4) {
    const Xyz4 v = load_xyz4(vel + i);
    const auto below = [slow](const Lanes4& x) { return (x < slow) & (x > -slow); };
    const Mask4 zero = (v.x == 0) & (v.y == 0) & (v.z == 0);
    const Mask4 small = below(v.x) & below(v.y) & below(v.z) & ~zero;
    if ((small[0] | small[1] | small[2] | small[3]) != 0) {
      for (std::size_t k = i; k < i + 4; ++k) translate_one(m, dt, slow, pos[k], vel[k], path ? path + k : nullptr);
      continue;
    }
    store_xyz4(pos + i, moved(m, load_xyz4(pos + i), v));
    if (path) add_speed(path + i, squared(v), dt);
  }
  for (; i < hi; ++i) translate_one(m, dt, slow, pos[i], vel[i], path ? path + i : nullptr);
}

// a . b and a x b in lanes, in the order of Eigen's dot and cross.
[[gnu::always_inline]] inline Lanes4 dot(const Xyz4& a, const Xyz4& b) { return (a.x * b.x + a.y * b.y) + a.z * b.z; }
[[gnu::always_inline]] inline Xyz4 cross(const Xyz4& a, const Xyz4& b) {
  return {a.y * b.z - a.z * b.y, a.z * b.x - a.x * b.z, a.x * b.y - a.y * b.x};
}

// Eigen's q * v in lanes (Quaternion::_transformVector): uv = q.vec x v, uv += uv,
// v + w uv + q.vec x uv.
[[gnu::always_inline]] inline Xyz4 rotated(const Lanes4& w, const Xyz4& u, const Xyz4& v) {
  Xyz4 uv = cross(u, v);
  uv = {uv.x + uv.x, uv.y + uv.y, uv.z + uv.z};
  const Xyz4 c = cross(u, uv);
  return {v.x + w * uv.x + c.x, v.y + w * uv.y + c.y, v.z + w * uv.z + c.z};
}

// What omega = I^-1 L (particle_omega) needs of four particles: each lane's kind (a sphere, symmetry
// axis 0, 1 or 2, three distinct moments) and the moments and orientation that kind reads.
struct LanesBodies {
  bool spheres;                  // four spheres: nothing else is loaded
  Lanes4 inv_transverse, inv_axial, w;
  Xyz4 axis, inertia;            // q's vector part; the moments, for three distinct ones
  std::array<Mask4, 3> about;  // the lanes of symmetry axis 0, 1, 2
  Mask4 three;                 // the lanes of three distinct moments
};
[[gnu::always_inline]] inline bool any(const Mask4& m) { return (m[0] | m[1] | m[2] | m[3]) != 0; }
[[gnu::always_inline]] inline LanesBodies lanes_bodies(const Particles& p, std::size_t i, bool spheres) {
  LanesBodies b;  // (no zeros written: the fields a lane's kind does not read stay unset)
  b.spheres = spheres;
  b.inv_transverse = load4(p.inv_transverse_moment.data() + i);
  if (spheres) return b;
  const std::int8_t* const k = p.symmetry_axis.data() + i;
  const Mask4 kind{k[0], k[1], k[2], k[3]};
  for (int K = 0; K < 3; ++K) b.about[K] = kind == K;
  b.three = kind == kThreeMoments;
  b.w = load4(p.q.component(3) + i);
  b.axis = {load4(p.q.component(0) + i), load4(p.q.component(1) + i), load4(p.q.component(2) + i)};
  b.inv_axial = load4(p.inv_axial_moment.data() + i);
  if (any(b.three)) b.inertia = load_xyz4(p.inertia.data() + i);
  return b;
}
[[gnu::always_inline]] inline void pick(const Mask4& m, const Xyz4& c, Xyz4& out) {
  out = {m ? c.x : out.x, m ? c.y : out.y, m ? c.z : out.z};
}
template <int K>
[[gnu::always_inline]] inline void pick_axisymmetric(const LanesBodies& b, const Xyz4& l, Xyz4& out) {
  if (!any(b.about[K])) return;
  Xyz4 c;
  axisymmetric_omega<K>(b.w, b.axis.x, b.axis.y, b.axis.z, l.x, l.y, l.z, b.inv_axial, b.inv_transverse, c.x, c.y, c.z);
  pick(b.about[K], c, out);
}
// particle_omega of four particles, lane by lane.
[[gnu::always_inline]] inline Xyz4 lanes_omega(const LanesBodies& b, const Xyz4& l) {
  Xyz4 out{l.x * b.inv_transverse, l.y * b.inv_transverse, l.z * b.inv_transverse};  // a sphere's
  if (b.spheres) return out;
  pick_axisymmetric<0>(b, l, out);
  pick_axisymmetric<1>(b, l, out);
  pick_axisymmetric<2>(b, l, out);
  if (any(b.three)) {
    const Xyz4 body = rotated(b.w, {-b.axis.x, -b.axis.y, -b.axis.z}, l);  // q.conjugate() * l
    pick(b.three, rotated(b.w, b.axis, {body.x / b.inertia.x, body.y / b.inertia.y, body.z / b.inertia.z}), out);
  }
  return out;
}

// The kick's energy terms of four particles (kick_energy, the same operations in the same order):
// the dissipation (dt F - m dv).v_mid + (dt M - dL).omega(L_mid) and the kinetic energy
// m |v|^2 / 2 + L.omega(L) / 2, with each lane's omega as particle_omega gives it.
[[gnu::always_inline]] inline void kick_energy_lanes(const Particles& p, std::size_t i, bool spheres, double dt,
                                                     const Lanes4& inv_mass, const Xyz4& f, const Xyz4& v_old,
                                                     const Xyz4& v, const Xyz4& torque, const Xyz4& l_old,
                                                     const Xyz4& l, KickEnergy energy) {
  const LanesBodies bodies = lanes_bodies(p, i, spheres);
  const Lanes4 half{0.5, 0.5, 0.5, 0.5};
  const Xyz4 v_mid{half * (v_old.x + v.x), half * (v_old.y + v.y), half * (v_old.z + v.z)};
  const Xyz4 l_mid{half * (l_old.x + l.x), half * (l_old.y + l.y), half * (l_old.z + l.z)};
  const Lanes4 mass = 1 / inv_mass;
  const Xyz4 lost{dt * f.x - mass * (v.x - v_old.x), dt * f.y - mass * (v.y - v_old.y),
                  dt * f.z - mass * (v.z - v_old.z)};
  const Xyz4 lost_rot{dt * torque.x - (l.x - l_old.x), dt * torque.y - (l.y - l_old.y),
                      dt * torque.z - (l.z - l_old.z)};
  store4(energy.dissipated + i, dot(lost, v_mid) + dot(lost_rot, lanes_omega(bodies, l_mid)));
  store4(energy.kinetic + i, half * mass * squared(v) + half * dot(l, lanes_omega(bodies, l)));
}

// With `move` (dt h^-1) it also translates the particles, s += dt h^-1 v with the new v, and adds
// dt |v| to a surface `path`, as translate does (the same bits: a settled v is zeros or not
// small, so no particle is still). Track: also the energy terms (kick_energy).
template <bool Track>
QSDEM_CLONES double viscous_kick(const Model& model, Particles& p, std::size_t lo, std::size_t hi,
                                 const CellMap* move, double* path, KickEnergy energy) {
  hi = std::min(hi, p.size());
  const double dt = model.dt;
  const KickArrays arrays(p);
  double *const lx = arrays.angmom.x, *const ly = arrays.angmom.y, *const lz = arrays.angmom.z;
  Lanes4 v2max{};
  KickFactors kick(dt), kick_rot(dt);  // translation, rotation
  std::size_t i = lo;
  for (; i + 4 <= hi; i += 4) {
    const Lanes4 m = load4(arrays.inv_mass + i);
    const Xyz4 f = load_xyz4(arrays.force + i);
    kick.update(load4(arrays.damping_of + i), dt);
    const Xyz4 v_old = load_xyz4(arrays.vel + i);
    const Xyz4 v = damped_kick_lanes(kick, v_old, {f.x * m, f.y * m, f.z * m});
    store_xyz4(arrays.vel + i, v);
    if (move) store_xyz4(arrays.pos + i, moved(*move, load_xyz4(arrays.pos + i), v));
    const Lanes4 v2 = squared(v);
    if (path) add_speed(path + i, v2, dt);
    v2max = v2max < v2 ? v2 : v2max;  // std::max(v2max, v2) lane by lane
    kick_rot.update(load4(arrays.damping_rot_of + i), dt);
    const Xyz4 l_old{load4(lx + i), load4(ly + i), load4(lz + i)}, torque = load_xyz4(arrays.torque + i);
    const Xyz4 l = damped_kick_lanes(kick_rot, l_old, torque);
    store4(lx + i, l.x), store4(ly + i, l.y), store4(lz + i, l.z);
    // A sphere's omega = L / I (kick_particles); an ellipsoid's is the drift's.
    std::uint32_t kinds;
    std::memcpy(&kinds, arrays.shape + i, sizeof kinds);
    if constexpr (Track) kick_energy_lanes(p, i, kinds == 0, dt, m, f, v_old, v, torque, l_old, l, energy);
    if (kinds == 0) {  // four spheres (ShapeKind::sphere = 0)
      const Lanes4 inv = load4(arrays.inv_moment + i);
      store_xyz4(arrays.omega + i, {l.x * inv, l.y * inv, l.z * inv});
    } else {
      for (std::size_t k = 0; k < 4; ++k)
        if (arrays.shape[i + k] == ShapeKind::sphere)
          arrays.omega[i + k] = Vec3(l.x[k], l.y[k], l.z[k]) * arrays.inv_moment[i + k];
    }
  }
  double out = 0;
  for (std::size_t k = 0; k < 4; ++k) out = std::max(out, v2max[k]);
  out = std::max(out, kick_particles<Track>(model, p, i, hi, energy));
  if (move) translate(*move, dt, still_speed(*move), arrays.pos, arrays.vel, path, i, hi);
  return out;
}

// Cundall's local kick with the energy terms: chunk by chunk, the momenta before the kick kept,
// the chunk kicked by local_kick, then kick_energy of each particle from both (in lanes, four at a
// time; the chunk's last particles one at a time).
QSDEM_CLONES double local_kick_tracked(const Model& model, Particles& p, std::size_t lo, std::size_t hi,
                                       KickEnergy energy) {
  hi = std::min(hi, p.size());
  const double dt = model.dt;
  constexpr std::size_t chunk = 256;
  Vec3 v_old[chunk];
  alignas(64) double lx[chunk], ly[chunk], lz[chunk];
  const KickArrays arrays(p);
  double v2max = 0;
  for (std::size_t c0 = lo; c0 < hi; c0 += chunk) {
    const std::size_t c1 = std::min(hi, c0 + chunk), n = c1 - c0;
    std::copy(arrays.vel + c0, arrays.vel + c1, v_old);
    std::copy(arrays.angmom.x + c0, arrays.angmom.x + c1, lx);
    std::copy(arrays.angmom.y + c0, arrays.angmom.y + c1, ly);
    std::copy(arrays.angmom.z + c0, arrays.angmom.z + c1, lz);
    const double alpha = model.damping.cundall_translation, alpha_rot = model.damping.cundall_rotation;
    v2max = std::max(v2max, local_kick(p, c0, c1, dt, alpha, alpha_rot));
    std::size_t a = 0;
    for (; a + 4 <= n; a += 4) {
      const std::size_t i = c0 + a;
      std::uint32_t kinds;
      std::memcpy(&kinds, arrays.shape + i, sizeof kinds);
      kick_energy_lanes(p, i, kinds == 0, dt, load4(arrays.inv_mass + i), load_xyz4(arrays.force + i),
                        load_xyz4(v_old + a), load_xyz4(arrays.vel + i), load_xyz4(arrays.torque + i),
                        {load4(lx + a), load4(ly + a), load4(lz + a)},
                        {load4(arrays.angmom.x + i), load4(arrays.angmom.y + i), load4(arrays.angmom.z + i)}, energy);
    }
    for (; a < n; ++a)
      kick_energy(p, c0 + a, dt, v_old[a], arrays.vel[c0 + a], {lx[a], ly[a], lz[a]}, arrays.angmom[c0 + a], energy);
  }
  return v2max;
}

}  // namespace

bool kick_settles(const Model& model) {
  // Cundall's damping only where it acts: alpha = 0 would change no bit, but costs the signs.
  return !(model.damping.cundall_translation > 0 || model.damping.cundall_rotation > 0);
}

double integrate_velocities(const Model& model, Particles& p, std::size_t lo, std::size_t hi, KickEnergy energy,
                            const CellMap* move, double* path) {
  const bool local = !kick_settles(model);
  if (!local)  // (moves in its pass)
    return energy.dissipated ? viscous_kick<true>(model, p, lo, hi, move, path, energy)
                             : viscous_kick<false>(model, p, lo, hi, move, path, {});
  const double v2max = energy.dissipated ? local_kick_tracked(model, p, lo, hi, energy)
                                         : local_kick(p, lo, hi, model.dt, model.damping.cundall_translation,
                                                      model.damping.cundall_rotation);
  if (move) translate(*move, model.dt, still_speed(*move), p.s.data(), p.v.data(), path, lo, std::min(hi, p.size()));
  return v2max;
}

// Orientation scheme (SPEC 5; notes-ellipsoid-algorithms 3). The kick above moves L with the
// torque at fixed q; this drift moves q at fixed world L along the free rigid-body flow
// H = sum_k pi_k^2 / (2 I_k), pi = R^T L the body-frame angular momentum. With a symplectic drift
// the whole step is a symplectic kick-drift leapfrog (undamped).
//  - Two equal moments (spheroid, the paper's particles): the free flow is known in closed form,
//    H = |L|^2 / (2 I_perp) + pi_s^2 (1/I_s - 1/I_perp) / 2 with commuting terms, so
//    R(t) = exp(t L/I_perp) R(0) exp(t pi_s (1/I_s - 1/I_perp) e_s): precession about L times
//    spin about the symmetry axis e_s. Exact; two sin/cos.
//  - Three distinct moments: NO_SQUISH (Miller, Eleftheriou, Pattnaik, Ndirango, Newns & Martyna,
//    J. Chem. Phys. 116, 8649 (2002); LAMMPS MathExtra::no_squish_rotate, same axis order
//    3,2,1,2,3): the exact flows of pi_k^2 / (2 I_k) composed as
//    R3(dt/2) R2(dt/2) R1(dt) R2(dt/2) R3(dt/2). Second order, symplectic, time-reversible.
// Measured against Richardson (LAMMPS fix nve/asphere) on a free 3:2:1 ellipsoid
// (tests/test_rotation.cpp, omega dt = 0.02, 1e5 steps): NO_SQUISH keeps |dE/E| bounded at
// 2.8e-5 (near the intermediate axis) / 3.7e-7 (near the major axis) where Richardson drifts
// linearly to 2.5e-4 / 4.4e-6, and its orientation error is 64x / 630x smaller.
namespace {

// sin and cos of a half angle. The per-step rotations of a quasi-static run are ~1e-6-1e-3 rad:
// below kTaylorHalfAngle the Taylor polynomials to x^5 and x^4 leave out less than
// x^7/7! (8e-19 of the sine) and x^6/6! (6e-18): libm's to round-off, and cheaper than its sin
// and cos (SPEC 5.4). They are polynomials in x^2 (sin x = x sinc x): sinc_cos_taylor.
constexpr double kTaylorHalfAngle = 0.004;
[[gnu::always_inline]] inline void sinc_cos_taylor(double x2, double& sinc, double& c) {
  sinc = 1 - x2 * (1.0 / 6) * (1 - x2 * (1.0 / 20));
  c = 1 - x2 * 0.5 * (1 - x2 * (1.0 / 12));
}
[[gnu::always_inline]] inline void sin_cos_taylor(double x, double& s, double& c) {
  double sinc;
  sinc_cos_taylor(x * x, sinc, c);
  s = x * sinc;
}
inline void sin_cos(double x, double& s, double& c) {
  if (std::abs(x) <= kTaylorHalfAngle) {
    sin_cos_taylor(x, s, c);
  } else {
    s = std::sin(x);
    c = std::cos(x);
  }
}

// Exact flow of pi_k^2 / (2 I_k) for time tau (lb = pi, body-frame L): the body turns about its
// axis k by phi = tau pi_k / I_k (q <- q (cos phi/2, sin phi/2 e_k)); pi_k is constant and, L
// being fixed in the world, the other two body components turn by -phi.
inline void rotate_about_body_axis(int k, double tau, const Vec3& inertia, Vec3& lb, Quat& q) {
  const double half = 0.5 * tau * lb[k] / inertia[k];
  double sh, ch;
  sin_cos(half, sh, ch);
  const double c = 1 - 2 * sh * sh, s = 2 * sh * ch;  // cos phi, sin phi
  const int i = (k + 1) % 3, j = (k + 2) % 3;
  const double li = lb[i], lj = lb[j];
  lb[i] = c * li + s * lj;
  lb[j] = c * lj - s * li;
  Quat r(ch, 0, 0, 0);
  r.vec()[k] = sh;
  q = q * r;
}

// Quaternion product a b by components (w, x, y, z), in the order of Eigen's SSE product (what
// Quat * Quat runs): the lanes give the same bits as the Eigen code did before them.
struct QuatParts {
  double w, x, y, z;
};
[[gnu::always_inline]] inline QuatParts multiply(const QuatParts& a, const QuatParts& b) {
  return {(a.w * b.w - a.y * b.y) - (a.z * b.z + a.x * b.x), (a.w * b.x + a.y * b.z) - (a.z * b.y - a.x * b.w),
          (a.w * b.y + a.y * b.w) + (a.z * b.x - a.x * b.z), (a.w * b.z - a.y * b.x) + (a.z * b.w + a.x * b.y)};
}

// q e with e = (c, s u_K), a turn about the body axis K: multiply(q, e) without the products with
// e's zero components (each only adds or subtracts a signed zero: the same bits for a nonzero sum).
template <int K>
[[gnu::always_inline]] inline QuatParts multiply_axis(const QuatParts& a, double c, double s) {
  if constexpr (K == 0) return {a.w * c - a.x * s, a.w * s + a.x * c, a.y * c + a.z * s, a.z * c - a.y * s};
  else if constexpr (K == 1) return {a.w * c - a.y * s, a.x * c - a.z * s, a.w * s + a.y * c, a.z * c + a.x * s};
  else return {a.w * c - a.z * s, a.y * s + a.x * c, a.y * c - a.x * s, a.w * s + a.z * c};
}

// Column K of R(q): the body axis K in the world frame.
template <int K>
[[gnu::always_inline]] inline void body_axis(const QuatParts& q, double& ax, double& ay, double& az) {
  body_axis<K>(q.w, q.x, q.y, q.z, ax, ay, az);
}

// Free symmetric top, symmetry axis K, inverse moments inv_s (about K) and inv_perp, angular
// momentum L: the orientation after dt. Few divisions: they are the slowest operations here. With
// `taylor_only` both half angles take the Taylor polynomials and the norm its Newton step (no
// branch, for vector lanes), and `outside` tells when one of them is beyond its range (the caller
// then runs the lane again without it). Without `normalize` the product of the turns is returned
// as it is: its norm is 1 to round-off, and is restored every kNormalizeEvery steps (SPEC 5.4).
template <int K, bool taylor_only, bool normalize>
[[gnu::always_inline]] inline QuatParts spheroid_rotation(const QuatParts& q, double inv_s, double inv_perp,
                                                          double lx, double ly, double lz, double dt, bool& outside,
                                                          double& pi_s) {
  const double l2 = lx * lx + ly * ly + lz * lz;
  double ax, ay, az;
  body_axis<K>(q, ax, ay, az);
  pi_s = ax * lx + ay * ly + az * lz;                        // body component on the symmetry axis
  const double spin = 0.5 * dt * pi_s * (inv_s - inv_perp);  // half angle of the spin
  // The half angle of the precession is x = rate |L|. Within the Taylor range its sine and cosine are
  // polynomials in x^2 = rate^2 |L|^2, and sp = sin x / |L| (the factor of the precession axis's
  // components) is rate sinc x: no square root or division (they took a sixth of the lanes' time).
  // |L| = 0 gives x = 0 and no NaN (`still` below).
  const double rate = 0.5 * dt * inv_perp;
  const double x2 = rate * rate * l2;
  double sp, cp, ss, cs;
  constexpr double range2 = kTaylorHalfAngle * kTaylorHalfAngle;
  if (taylor_only || x2 <= range2) {  // (no branch in the lanes: taylor_only is a constant)
    sinc_cos_taylor(x2, sp, cp);
    sp *= rate;
  } else {
    const double inv_l = 1 / std::sqrt(l2);
    const double x = 0.5 * dt * l2 * inv_l * inv_perp;
    sp = std::sin(x) * inv_l;
    cp = std::cos(x);
  }
  if constexpr (taylor_only) {
    outside = !(x2 <= range2) | !(std::abs(spin) <= kTaylorHalfAngle);
    sin_cos_taylor(spin, ss, cs);
  } else {
    outside = false;
    sin_cos(spin, ss, cs);
  }
  const QuatParts about_l{cp, sp * lx, sp * ly, sp * lz};
  const QuatParts r = multiply_axis<K>(multiply(about_l, q), cs, ss);
  const bool still = l2 == 0;  // no angular momentum: no turn
  if constexpr (!normalize)  // (component by component: a select of the struct is a branch)
    return {still ? q.w : r.w, still ? q.x : r.x, still ? q.y : r.y, still ? q.z : r.z};
  // |r|^2 = 1 + O(ulps) (unit factors): one Newton step for |r|^-1, 1.5 - |r|^2/2, is exact to
  // round-off there and needs no square root or division.
  // (Summed as Eigen sums a 4-vector: (x^2 + z^2) + (y^2 + w^2).)
  const double n2 = (r.x * r.x + r.z * r.z) + (r.y * r.y + r.w * r.w);
  double scale;
  if constexpr (taylor_only) {
    // A select would compute the square root and division in every lane (a quarter of the lanes'
    // time); a lane beyond the Newton step's range runs again instead.
    outside = outside | !(std::abs(n2 - 1) < 1e-8);
    scale = 1.5 - 0.5 * n2;
  } else {
    scale = std::abs(n2 - 1) < 1e-8 ? 1.5 - 0.5 * n2 : 1 / std::sqrt(n2);
  }
  return {still ? q.w : r.w * scale, still ? q.x : r.x * scale, still ? q.y : r.y * scale, still ? q.z : r.z * scale};
}

inline QuatParts parts(const Quat& q) { return {q.w(), q.x(), q.y(), q.z()}; }

template <bool normalize>
inline QuatParts spheroid_rotation(int k, const QuatParts& q, double inv_s, double inv_perp, const Vec3& l, double dt) {
  bool outside;
  double pi_s;
  if (k == 0) return spheroid_rotation<0, false, normalize>(q, inv_s, inv_perp, l.x(), l.y(), l.z(), dt, outside, pi_s);
  if (k == 1) return spheroid_rotation<1, false, normalize>(q, inv_s, inv_perp, l.x(), l.y(), l.z(), dt, outside, pi_s);
  return spheroid_rotation<2, false, normalize>(q, inv_s, inv_perp, l.x(), l.y(), l.z(), dt, outside, pi_s);
}

// Spheroids to turn, with the same symmetry axis, in lanes (structure of arrays). In: the
// orientation and angular momentum (TurnInput) and the inverse moments; out: the new orientation,
// omega, and the squared quaternion chord of the turn.
struct TurnLanes {
  static constexpr int capacity = 64;
  int size = 0;
  std::uint32_t particle[capacity];
  double qw[capacity], qx[capacity], qy[capacity], qz[capacity];  // in, when copied (load_lane)
  double lx[capacity], ly[capacity], lz[capacity];
  double inv_s[capacity], inv_perp[capacity];
  double nw[capacity], nx[capacity], ny[capacity], nz[capacity];  // out
  double ox[capacity], oy[capacity], oz[capacity], chord2[capacity];
  double outside[capacity];  // 1: a half angle beyond the Taylor range, or the norm beyond the
                             // Newton step's (lane to run again)
};

// Where the lanes read q, L and the inverse moments about the symmetry axis and across it: lane a
// at [a] of these. The particle arrays themselves for a run of consecutive spheroids
// (turn_in_place: no copies), else the lanes' copies.
struct TurnInput {
  const double *qw, *qx, *qy, *qz, *lx, *ly, *lz, *inv_s, *inv_perp;
};
inline TurnInput copies(const TurnLanes& t) { return {t.qw, t.qx, t.qy, t.qz, t.lx, t.ly, t.lz, t.inv_s, t.inv_perp}; }

// Where the lanes put the new q: lane a at [a] of these, the lanes' own (TurnLanes::nw...) or, for
// a run turned in place, the particle arrays it was read from; then with a surface path (else
// null) also path[a] += 2 bound_radius[a] |q - q_old| there (the chord, TurnLanes::chord2).
struct TurnOutput {
  double *qw, *qx, *qy, *qz;
  double* path = nullptr;
  const double* bound_radius = nullptr;
};
inline TurnOutput into_lanes(TurnLanes& t) { return {t.nw, t.nx, t.ny, t.nz}; }

// One lane: the turn, then omega = R I^-1 R^T L at the new orientation (gyroscopic; spheroid:
// I^-1 = inv_perp 1 + (inv_s - inv_perp) e e^T, e the symmetry axis), then the chord. A lane of
// the Taylor polynomials beyond their range (taylor_only, `outside`) puts back q_old and adds no
// path: it runs again, from the same input (`turn`).
template <int K, bool taylor_only, bool path, bool normalize>
[[gnu::always_inline]] inline void turn_lane(const TurnInput& in, const TurnOutput& out, TurnLanes& t, int a,
                                             double dt) {
  const QuatParts old{in.qw[a], in.qx[a], in.qy[a], in.qz[a]};
  const double lx = in.lx[a], ly = in.ly[a], lz = in.lz[a], inv_s = in.inv_s[a], inv_perp = in.inv_perp[a];
  bool outside;
  double pi_s;
  const QuatParts q = spheroid_rotation<K, taylor_only, normalize>(old, inv_s, inv_perp, lx, ly, lz, dt, outside, pi_s);
  double ex, ey, ez;
  body_axis<K>(q, ex, ey, ez);
  // e.L at the new orientation is pi_s: the free flow keeps it (precession about L, spin about e).
  const double f = (inv_s - inv_perp) * pi_s;
  t.ox[a] = inv_perp * lx + f * ex, t.oy[a] = inv_perp * ly + f * ey, t.oz[a] = inv_perp * lz + f * ez;
  out.qw[a] = outside ? old.w : q.w, out.qx[a] = outside ? old.x : q.x;
  out.qy[a] = outside ? old.y : q.y, out.qz[a] = outside ? old.z : q.z;
  // Chord |q - q_old| of the shorter arc (q and -q are one turn), summed as Eigen sums a 4-vector.
  // Within the Taylor range (half angles below kTaylorHalfAngle) q_old . q > 0: the arc from q_old is the shorter.
  const double dx = q.x - old.x, dy = q.y - old.y, dz = q.z - old.z, dw = q.w - old.w;
  const double minus = (dx * dx + dz * dz) + (dy * dy + dw * dw);
  double chord2;
  if constexpr (taylor_only) {
    chord2 = minus;
  } else {
    const double sx = q.x + old.x, sy = q.y + old.y, sz = q.z + old.z, sw = q.w + old.w;
    const double plus = (sx * sx + sz * sz) + (sy * sy + sw * sw);
    chord2 = plus < minus ? plus : minus;
  }
  t.chord2[a] = chord2;
  if constexpr (path) {
    const double moved = out.path[a] + 2 * out.bound_radius[a] * std::sqrt(chord2);
    out.path[a] = outside ? out.path[a] : moved;
  }
  t.outside[a] = outside ? 1.0 : 0.0;
}

// All lanes at once, by the Taylor polynomials (several lanes per vector instruction: a lone
// spheroid's turn is one long chain of dependent operations). Built for AVX-512, AVX2 and the
// x86-64 baseline, chosen at load time; no FMA, so the same bits as one lane at a time. Returns
// whether a lane is outside the polynomials' range.
// (The pointers as copies: through the references GCC reloads them after every store, and
// vectorises only with scatters.)
template <int K, bool path, bool normalize>
[[gnu::always_inline]] inline bool turn_all(const TurnInput in, const TurnOutput out, TurnLanes& t, double dt) {
  double outside = 0;
#pragma omp simd reduction(max : outside)
  for (int a = 0; a < t.size; ++a) {
    turn_lane<K, true, path, normalize>(in, out, t, a, dt);
    outside = outside < t.outside[a] ? t.outside[a] : outside;
  }
  return outside != 0;
}
template <bool path, bool normalize>
[[gnu::always_inline]] inline bool turn_all(int k, const TurnInput in, const TurnOutput out, TurnLanes& t, double dt) {
  if (k == 0) return turn_all<0, path, normalize>(in, out, t, dt);
  if (k == 1) return turn_all<1, path, normalize>(in, out, t, dt);
  return turn_all<2, path, normalize>(in, out, t, dt);
}
QSDEM_CLONES_WIDE bool turn_lanes(int k, const TurnInput& in, const TurnOutput& out, TurnLanes& t, double dt,
                                  bool normalize) {
  if (out.path) return normalize ? turn_all<true, true>(k, in, out, t, dt) : turn_all<true, false>(k, in, out, t, dt);
  return normalize ? turn_all<false, true>(k, in, out, t, dt) : turn_all<false, false>(k, in, out, t, dt);
}

// One lane again, with libm (its input is unchanged).
template <bool path, bool normalize>
void turn_lane_again(int k, const TurnInput& in, const TurnOutput& out, TurnLanes& t, int a, double dt) {
  if (k == 0) turn_lane<0, false, path, normalize>(in, out, t, a, dt);
  else if (k == 1) turn_lane<1, false, path, normalize>(in, out, t, a, dt);
  else turn_lane<2, false, path, normalize>(in, out, t, a, dt);
}

// The lanes' turn; a lane beyond the Taylor range runs again, with libm.
void turn(int k, const TurnInput& in, const TurnOutput& out, TurnLanes& t, double dt, bool normalize) {
  if (!turn_lanes(k, in, out, t, dt, normalize)) return;
  const bool path = out.path != nullptr;
  for (int a = 0; a < t.size; ++a) {
    if (t.outside[a] == 0) continue;
    if (path) normalize ? turn_lane_again<true, true>(k, in, out, t, a, dt) : turn_lane_again<true, false>(k, in, out, t, a, dt);
    else normalize ? turn_lane_again<false, true>(k, in, out, t, a, dt) : turn_lane_again<false, false>(k, in, out, t, a, dt);
  }
}

// The particle arrays a turn reads and writes, through local pointers: through Particles, each
// store made GCC load the next array's address again (as in integrate_velocities).
struct SpinArrays {
  double *qw, *qx, *qy, *qz;
  AngmomArrays l;
  const std::int8_t* symmetry_axis;  // Particles::symmetry_axis, and the inverse moments about it and across
  const double *inv_axial, *inv_transverse;
  Vec3* omega;
  const double* bound_radius;
  double* path;  // the surface path, or nullptr when it is not tracked

  SpinArrays(Particles& p, double* surface_path)
      : qw(p.q.component(3)), qx(p.q.component(0)), qy(p.q.component(1)), qz(p.q.component(2)),
        l(p.angmom), symmetry_axis(p.symmetry_axis.data()), inv_axial(p.inv_axial_moment.data()),
        inv_transverse(p.inv_transverse_moment.data()), omega(p.omega.data()), bound_radius(p.bound_radius.data()),
        path(surface_path) {}
  Quat q(std::size_t i) const { return {qw[i], qx[i], qy[i], qz[i]}; }
  // Lanes a = 0, 1, ... at particles i, i + 1, ...
  TurnInput from(std::size_t i) const {
    return {qw + i, qx + i, qy + i, qz + i, l.x + i, l.y + i, l.z + i, inv_axial + i, inv_transverse + i};
  }
  TurnOutput into(std::size_t i) const {
    return {qw + i, qx + i, qy + i, qz + i, path ? path + i : nullptr, bound_radius + i};
  }
};

// Lane a <- particle i, with its inverse moments about the symmetry axis and across it.
inline void load_lane(TurnLanes& t, int a, const SpinArrays& s, std::uint32_t i) {
  t.particle[a] = i;
  t.qw[a] = s.qw[i], t.qx[a] = s.qx[i], t.qy[a] = s.qy[i], t.qz[a] = s.qz[i];
  t.lx[a] = s.l.x[i], t.ly[a] = s.l.y[i], t.lz[a] = s.l.z[i];
  t.inv_s[a] = s.inv_axial[i], t.inv_perp[a] = s.inv_transverse[i];
}

// The surface path of a turn: 2 bound_radius |q - q_old| (the chord).
inline void add_turn_path(const SpinArrays& s, std::size_t i, double chord2) {
  s.path[i] += 2 * s.bound_radius[i] * std::sqrt(chord2);
}

// Turns the spheroids of the lanes (symmetry axis k, loaded by load_lane) and stores their
// orientation, omega and surface path.
void turn_spheroids(int k, TurnLanes& t, const SpinArrays& s, double dt, bool normalize) {
  turn(k, copies(t), into_lanes(t), t, dt, normalize);
  for (int a = 0; a < t.size; ++a) {
    const std::uint32_t i = t.particle[a];
    s.qw[i] = t.nw[a], s.qx[i] = t.nx[a], s.qy[i] = t.ny[a], s.qz[i] = t.nz[a];
    s.omega[i] = Vec3(t.ox[a], t.oy[a], t.oz[a]);
    if (s.path) add_turn_path(s, i, t.chord2[a]);
  }
  t.size = 0;
}

// Turns the t.size consecutive spheroids from particle i0 (symmetry axis k) in place: the lanes
// read q, L and the inverse moments and write q and the path where they are.
void turn_in_place(int k, TurnLanes& t, const SpinArrays& s, std::size_t i0, double dt, bool normalize) {
  turn(k, s.from(i0), s.into(i0), t, dt, normalize);
  for (int a = 0; a < t.size; ++a) s.omega[i0 + a] = Vec3(t.ox[a], t.oy[a], t.oz[a]);
  t.size = 0;
}

// Every |L_k| below 2^-540 (kSettled; a rattler's L decayed by damping): each L_k^2 < 2^-1080 rounds to 0,
// so |L|^2 = 0, spheroid_rotation returns q itself (`still`) and the chord is 0. Such an L is
// often subnormal, and an operation on a subnormal costs ~50 ns here (a microcode assist, for the
// whole vector it is in): these spheroids stay out of the lanes and get only their omega, by the
// lanes' arithmetic (turn_lane). An L of zeros (as the viscous kick settles it) is no subnormal:
// those spheroids stay in the lanes, which give them the same bits (q kept, a zero chord).
inline bool resting(double x, double y, double z) {
  return settled(x, y, z) & !((x == 0) & (y == 0) & (z == 0));
}
inline bool resting(const Vec3& l) { return resting(l.x(), l.y(), l.z()); }

// What a run of particles [i0, i0 + n) is, in vector lanes: kAllSpheres, or the symmetry axis k
// (0 or 2) that every one of them turns about, none resting, or kMixed (advance_positions sorts
// it one at a time). From Particles::symmetry_axis (a byte each: a run of spheres reads nothing
// more), then for a run of spheroids their L, unless `settled` (none is resting).
constexpr int kAllSpheres = kSphereBody, kMixed = -1;
QSDEM_CLONES int sort_run(const std::int8_t* symmetry_axis, AngmomArrays l, std::size_t i0, int n, bool settled) {
  const std::int8_t* const axis = symmetry_axis + i0;
  const int k = axis[0];
  int others = 0;  // a count (the same reduction for any build)
#pragma omp simd reduction(+ : others)
  for (int a = 0; a < n; ++a) others += axis[a] != k ? 1 : 0;
  if (others != 0 || k == kThreeMoments) return kMixed;
  if (k == kSphereBody) return kAllSpheres;
  if (settled) return k;
  int resting_any = 0;
#pragma omp simd reduction(+ : resting_any)
  for (int a = 0; a < n; ++a) {
    const std::size_t i = i0 + static_cast<std::size_t>(a);
    resting_any += resting(l.x[i], l.y[i], l.z[i]) ? 1 : 0;
  }
  return resting_any != 0 ? kMixed : k;
}

}  // namespace

Quat free_rotation(const Quat& q, const Vec3& inertia, const Vec3& angmom, double dt, bool normalize) {
  if (const int k = equal_moments_axis(inertia); k >= 0) {
    const double inv_s = 1 / inertia[k], inv_perp = 1 / inertia[transverse_axis(k)];
    const QuatParts r = normalize ? spheroid_rotation<true>(k, parts(q), inv_s, inv_perp, angmom, dt)
                                  : spheroid_rotation<false>(k, parts(q), inv_s, inv_perp, angmom, dt);
    return Quat(r.w, r.x, r.y, r.z);
  }
  Vec3 body = q.conjugate() * angmom;  // pi = R^T L
  Quat r = q;
  rotate_about_body_axis(2, 0.5 * dt, inertia, body, r);
  rotate_about_body_axis(1, 0.5 * dt, inertia, body, r);
  rotate_about_body_axis(0, dt, inertia, body, r);
  rotate_about_body_axis(1, 0.5 * dt, inertia, body, r);
  rotate_about_body_axis(2, 0.5 * dt, inertia, body, r);
  return r.normalized();
}

void turn_orientations(const Model& model, Particles& p, std::span<double> surface_path, std::size_t lo,
                       std::size_t hi, bool settled, bool normalize) {
  const double dt = model.dt;
  const std::size_t n = p.size();
  const bool track = surface_path.size() == n;
  hi = std::min(hi, n);
  const SpinArrays spin(p, track ? surface_path.data() : nullptr);
  // The particles go in runs of a lane set's size. A run whose every particle is a turning
  // spheroid of one symmetry axis turns in place; otherwise its spheroids wait in lanes, one set
  // per symmetry axis, and turn a full set at a time.
  constexpr int run_size = TurnLanes::capacity;
  TurnLanes run, lanes[3];  // the lanes of a run in place, and of each axis's spheroids of mixed runs
  int axis[run_size];  // the symmetry axis of each particle of the run that turns in lanes, else -1
  for (std::size_t r0 = lo, r1; r0 < hi; r0 = r1) {
    r1 = std::min(hi, (r0 / run_size + 1) * run_size);  // runs from multiples of run_size: aligned lanes
    const int size = static_cast<int>(r1 - r0);
    if (const int kind = sort_run(spin.symmetry_axis, spin.l, r0, size, settled); kind != kMixed) {
      if (kind == kAllSpheres) continue;  // a sphere's orientation changes nothing
      run.size = size;
      turn_in_place(kind, run, spin, r0, dt, normalize);
      continue;
    }
    // A mixed run: each particle in turn; its turning spheroids wait in the lanes of their axis.
    int turning = 0;
    for (int a = 0; a < size; ++a) {
      const std::size_t i = r0 + a;
      axis[a] = -1;
      const int k = spin.symmetry_axis[i];
      if (k == kSphereBody) continue;  // a sphere's orientation changes nothing
      if (k >= 0) {
        if (resting(spin.l[i])) {
          spin.omega[i] = axisymmetric_omega(k, spin.q(i), spin.l[i], spin.inv_axial[i], spin.inv_transverse[i]);
          continue;
        }
        axis[a] = k, ++turning;
        continue;
      }
      // Three distinct moments: NO_SQUISH, one at a time. omega = R I^-1 R^T L then follows the
      // new orientation (gyroscopic).
      const Quat old = spin.q(i);
      const Quat q = free_rotation(old, p.inertia[i], spin.l[i], dt);
      p.q.set(i, q);
      p.omega[i] = angular_velocity(q, p.inertia[i], spin.l[i]);
      if (track)  // chord |q - q_old| = 2 sin(theta/4) of the shorter arc (q and -q are one turn)
        add_turn_path(spin, i, std::min((q.coeffs() - old.coeffs()).squaredNorm(),
                                        (q.coeffs() + old.coeffs()).squaredNorm()));
    }
    for (int a = 0; a < size && turning > 0; ++a) {
      if (axis[a] < 0) continue;
      TurnLanes& t = lanes[axis[a]];
      load_lane(t, t.size++, spin, static_cast<std::uint32_t>(r0 + a));
      if (t.size == TurnLanes::capacity) turn_spheroids(axis[a], t, spin, dt, normalize);
    }
  }
  for (int k = 0; k < 3; ++k)
    if (lanes[k].size > 0) turn_spheroids(k, lanes[k], spin, dt, normalize);
}

void advance_positions(const Model& model, const Cell& cell, Particles& p, std::span<double> surface_path,
                       std::size_t lo, std::size_t hi, bool settled, bool normalize) {
  // x = h s moves by dt v; a rattler's v decays to subnormal numbers too: below still_speed s and
  // the path would keep their bits (|v|^2 rounds to 0), and are left alone (translate_one).
  const CellMap step_map(model.dt * cell.h_inv);
  const bool track = surface_path.size() == p.size();
  translate(step_map, model.dt, still_speed(step_map), p.s.data(), p.v.data(), track ? surface_path.data() : nullptr,
            lo, std::min(hi, p.size()));
  turn_orientations(model, p, surface_path, lo, hi, settled, normalize);
}

}  // namespace qsdem
