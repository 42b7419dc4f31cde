#include "qsdem/integrator.hpp"

#include <algorithm>
#include <cmath>

namespace qsdem {

double integrate_velocities(const Model& model, Particles& p, std::size_t lo, std::size_t hi) {
  const double dt = model.dt;
  hi = std::min(hi, p.size());
  double v2max = 0;
  double damping = 0;  // the factors of the last damping seen (one value in most runs)
  DampedKick kick(damping, dt);
  for (std::size_t i = lo; i < hi; ++i) {
    if (p.damping[i] != damping) kick = DampedKick(damping = p.damping[i], dt);  // A_i = B_i (SPEC 6)
    const Vec3 v = kick(p.v[i], p.force[i] * p.inv_mass[i]);
    p.v[i] = v;
    v2max = std::max(v2max, v.squaredNorm());
    // Rotation with D_i = B_i I_i: the same form on the angular momentum (SPEC 5).
    p.angmom[i] = kick(p.angmom[i], p.torque[i]);
    // A sphere's inertia is isotropic: omega = L / I, no frame change needed. An ellipsoid's
    // omega is set by advance_positions at its new orientation (nothing reads it before).
    if (p.shape[i] == ShapeKind::sphere) p.omega[i] = p.angmom[i] * p.inv_inertia[i].x();
  }
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
// linearly to 2.5e-4 / 4.4e-6, and its orientation error is 64x / 630x smaller, at ~1.25x the
// cost (micro-benchmark); the spheroid flow costs about half of NO_SQUISH.
namespace {

// sin and cos of a half angle. The per-step rotations of a quasi-static run are ~1e-6-1e-3 rad:
// below 0.05 the Taylor polynomials (to x^7 and x^8) are within 3e-16 relative of libm and
// ~4x cheaper than its sin + cos (micro-benchmark).
inline void sin_cos(double x, double& s, double& c) {
  if (std::abs(x) <= 0.05) {
    const double x2 = x * x;
    s = x * (1 - x2 * (1.0 / 6) * (1 - x2 * (1.0 / 20) * (1 - x2 * (1.0 / 42))));
    c = 1 - x2 * 0.5 * (1 - x2 * (1.0 / 12) * (1 - x2 * (1.0 / 30) * (1 - x2 * (1.0 / 56))));
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

// Unit vector of body axis k in the world frame: column k of R(q).
inline Vec3 body_axis(const Quat& q, int k) {
  const double w = q.w(), x = q.x(), y = q.y(), z = q.z();
  if (k == 0) return {1 - 2 * (y * y + z * z), 2 * (x * y + w * z), 2 * (x * z - w * y)};
  if (k == 1) return {2 * (x * y - w * z), 1 - 2 * (x * x + z * z), 2 * (y * z + w * x)};
  return {2 * (x * z + w * y), 2 * (y * z - w * x), 1 - 2 * (x * x + y * y)};
}

// Free symmetric top, symmetry axis k, inverse moments inv_s (about k) and inv_perp. Divisions
// are few on purpose: they dominated this function's profile.
inline Quat spheroid_rotation(const Quat& q, int k, double inv_s, double inv_perp, const Vec3& angmom,
                              double dt) {
  const double l2 = angmom.squaredNorm();
  if (l2 == 0) return q;
  const double inv_l = 1 / std::sqrt(l2);
  const double pi_s = body_axis(q, k).dot(angmom);   // body component on the symmetry axis
  const double precession = 0.5 * dt * l2 * inv_l * inv_perp;  // half angles
  const double spin = 0.5 * dt * pi_s * (inv_s - inv_perp);
  double sp, cp, ss, cs;
  sin_cos(precession, sp, cp);
  sin_cos(spin, ss, cs);
  sp *= inv_l;
  const Quat about_l(cp, sp * angmom.x(), sp * angmom.y(), sp * angmom.z());
  Quat about_axis(cs, 0, 0, 0);
  about_axis.vec()[k] = ss;
  Quat r = about_l * q * about_axis;
  // |r|^2 = 1 + O(ulps) (unit factors): one Newton step for |r|^-1, 1.5 - |r|^2/2, is exact to
  // round-off there and needs no square root or division (they led this function's profile).
  const double n2 = r.coeffs().squaredNorm();
  r.coeffs() *= std::abs(n2 - 1) < 1e-8 ? 1.5 - 0.5 * n2 : 1 / std::sqrt(n2);
  return r;
}

// The symmetry axis of a body with two equal moments (-1: three distinct moments). Equal moments
// are computed by the same expression (ellipsoid_inertia), so b == c gives bit-equal I_b, I_c.
inline int symmetry_axis(const Vec3& inertia) {
  if (inertia.y() == inertia.z()) return 0;
  if (inertia.x() == inertia.y()) return 2;
  return -1;
}

}  // namespace

Quat free_rotation(const Quat& q, const Vec3& inertia, const Vec3& angmom, double dt) {
  if (const int k = symmetry_axis(inertia); k >= 0)
    return spheroid_rotation(q, k, 1 / inertia[k], 1 / inertia[(k + 1) % 3], angmom, dt);
  Vec3 body = q.conjugate() * angmom;  // pi = R^T L
  Quat r = q;
  rotate_about_body_axis(2, 0.5 * dt, inertia, body, r);
  rotate_about_body_axis(1, 0.5 * dt, inertia, body, r);
  rotate_about_body_axis(0, dt, inertia, body, r);
  rotate_about_body_axis(1, 0.5 * dt, inertia, body, r);
  rotate_about_body_axis(2, 0.5 * dt, inertia, body, r);
  return r.normalized();
}

void advance_positions(const Model& model, const Cell& cell, Particles& p, std::span<double> surface_path,
                       std::size_t lo, std::size_t hi) {
  const double dt = model.dt;
  const Mat3 step_map = dt * cell.h_inv;
  const std::size_t n = p.size();
  const bool track = surface_path.size() == n;
  hi = std::min(hi, n);
  for (std::size_t i = lo; i < hi; ++i) {
    p.s[i] += step_map * p.v[i];  // moves x = h s by exactly dt v in the deformed cell
    if (track) surface_path[i] += dt * p.v[i].norm();
    if (p.shape[i] == ShapeKind::sphere) continue;  // a sphere's orientation changes nothing
    const Quat old = p.q[i];
    const Vec3& inertia = p.inertia[i];
    // The body turns at constant L; omega = R I^-1 R^T L then follows the new orientation
    // (gyroscopic). Spheroid: I^-1 = inv_perp 1 + (inv_s - inv_perp) e e^T, e the symmetry axis.
    if (const int k = symmetry_axis(inertia); k >= 0) {
      const double inv_s = p.inv_inertia[i][k], inv_perp = p.inv_inertia[i][(k + 1) % 3];
      const Vec3& angmom = p.angmom[i];
      p.q[i] = spheroid_rotation(old, k, inv_s, inv_perp, angmom, dt);
      const Vec3 e = body_axis(p.q[i], k);
      p.omega[i] = inv_perp * angmom + ((inv_s - inv_perp) * e.dot(angmom)) * e;
    } else {
      p.q[i] = free_rotation(old, inertia, p.angmom[i], dt);
      p.omega[i] = angular_velocity(p.q[i], inertia, p.angmom[i]);
    }
    if (track) {  // chord |q - q_old| = 2 sin(theta/4) of the shorter arc (q and -q are one turn)
      const double chord2 = std::min((p.q[i].coeffs() - old.coeffs()).squaredNorm(),
                                     (p.q[i].coeffs() + old.coeffs()).squaredNorm());
      surface_path[i] += 2 * p.bound_radius[i] * std::sqrt(chord2);
    }
  }
}

}  // namespace qsdem
