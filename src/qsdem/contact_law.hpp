// Contact laws are small pure evaluators: geometry + relative motion + history in, force out.
// The pair loop (forces.cpp) calls them; a new law is a new struct with the same evaluate().
//
// HertzMindlin, documented in full as the example for the others (SPEC 4):
//   Inputs
//     g.normal      unit normal n, from particle i towards particle j
//     g.overlap     delta > 0 (m)
//     g.radius      effective radius R_e (m): R1 R2 / (R1 + R2) for spheres, the Gaussian
//                   curvature radius of the relative curvature for ellipsoids
//     rel_velocity  velocity of j's material point at the contact relative to i's (m/s),
//                   including the affine field's part L l (SPEC 3)
//     dt            time step (s)
//     shear         in/out: the stored tangential force on j (N), the contact's history
//   Law
//     contact radius a = sqrt(R_e delta)
//     normal force   F_n = 4/3 E* sqrt(R_e) delta^(3/2) = 4/3 E* a delta      (Hertz)
//     normal stiffness k_n = dF_n/ddelta = 2 E* a                              (for the servo)
//     tangential stiffness k_t = 8 G* a                                         (Mindlin, no slip)
//     the stored force is first turned into the new tangent plane keeping its magnitude (the
//     contact normal turns as particles move), then F_t <- F_t - k_t du_t with du_t = v_t dt,
//     then capped at |F_t| <= mu F_n (Coulomb sliding).
//   Output
//     force on j = F_n n + F_t (particle i receives the opposite), k_n and k_t.
//   No contact damping (the paper uses none).
#pragma once
#include <cmath>

#include "qsdem/types.hpp"

namespace qsdem {

// Where two bodies touch (from a narrow phase).
struct ContactGeometry {
  Vec3 normal;      // unit, from i towards j
  double overlap;   // delta (m), > 0 in contact
  Vec3 arm_i;       // contact point - centre of i (m)
  Vec3 arm_j;       // contact point - centre of j (m)
  double radius;    // effective Hertz radius R_e (m)
};

struct ContactForce {
  Vec3 force;                   // on j (N)
  double normal_stiffness;      // k_n (N/m)
  double tangential_stiffness;  // k_t (N/m)
};

struct HertzMindlin {
  double effective_modulus;        // E* = E / (2 (1 - nu^2))
  double effective_shear_modulus;  // G* = G / (2 (2 - nu))
  double friction;                 // mu

  ContactForce evaluate(const ContactGeometry& g, const Vec3& rel_velocity, double dt, Vec3& shear) const {
    ContactForce cf;
    evaluate(g.normal.x(), g.normal.y(), g.normal.z(), g.overlap, g.radius, rel_velocity.x(), rel_velocity.y(),
             rel_velocity.z(), dt, shear.x(), shear.y(), shear.z(), cf.force.x(), cf.force.y(), cf.force.z(),
             cf.normal_stiffness, cf.tangential_stiffness);
    return cf;
  }

  // The same law on components, its branches as selects: the pair loop (forces.cpp) runs it on a
  // chunk of contacts in vector lanes (one contact's law is a long chain of dependent operations).
  // Each sum is in the order of Eigen's for 3-vectors (left to right), so a lane gives the bits of
  // a contact alone.
  [[gnu::always_inline]] inline void evaluate(double nx, double ny, double nz, double overlap, double radius,
                                              double vx, double vy, double vz, double dt, double& sx, double& sy,
                                              double& sz, double& fx, double& fy, double& fz, double& kn,
                                              double& kt) const {
    const double a = std::sqrt(radius * overlap);
    const double fn = 4.0 / 3.0 * effective_modulus * a * overlap;
    kn = 2.0 * effective_modulus * a;
    kt = 8.0 * effective_shear_modulus * a;

    // Turn the stored tangential force into the current tangent plane, keeping its magnitude.
    const double old_mag2 = (sx * sx + sy * sy) + sz * sz;
    const double inv_old = 1 / old_mag2;  // off the chain below: shear is known before n
    const double sn = (sx * nx + sy * ny) + sz * nz;
    const double px = sx - sn * nx, py = sy - sn * ny, pz = sz - sn * nz;
    // |shear|^2 is now old (1 - x), x = (s.n)^2 / old (n unit), so the magnitude comes back by
    // (1 - x)^-1/2 = 1 + x/2 + 3x^2/8 + O(x^3): below x = 1e-6 (a quasi-static contact turns by
    // far less per step) the cut terms, 5x^3/16 + ..., are < 3.2e-19, under the rounding of the
    // direct form sqrt(old / new).
    const double x = sn * sn * inv_old;
    const double new_mag2 = (px * px + py * py) + pz * pz;
    const double root = std::sqrt(old_mag2 / new_mag2);  // in every lane, then a select
    const double direct = new_mag2 > 0 ? root : 1.0;
    const double back = x < 1e-6 ? 1 + x * (0.5 + 0.375 * x) : direct;
    const bool stored = old_mag2 > 0;  // no stored force: nothing to turn
    const double tx = stored ? px * back : sx, ty = stored ? py * back : sy, tz = stored ? pz * back : sz;

    const double vn = (vx * nx + vy * ny) + vz * nz;
    const double kdt = kt * dt;
    sx = tx - kdt * (vx - vn * nx), sy = ty - kdt * (vy - vn * ny), sz = tz - kdt * (vz - vn * nz);
    const double cap = friction * fn;
    const double mag2 = (sx * sx + sy * sy) + sz * sz;
    const double slide = cap / std::sqrt(mag2);  // Coulomb: |F_t| <= mu F_n
    const bool sliding = mag2 > cap * cap;
    sx = sliding ? sx * slide : sx, sy = sliding ? sy * slide : sy, sz = sliding ? sz * slide : sz;
    fx = fn * nx + sx, fy = fn * ny + sy, fz = fn * nz + sz;
  }
};

// Exact sphere-sphere geometry for the branch l from i to j; overlap <= 0 means apart. On
// components, with selects, so that the pair loop (forces.cpp) runs it in vector lanes; the
// ContactGeometry form below calls it. d = |l| (the caller's, when it has it).
[[gnu::always_inline]] inline void sphere_sphere(double lx, double ly, double lz, double d, double ri, double rj,
                                                 double& nx, double& ny, double& nz, double& overlap,
                                                 double& aix, double& aiy, double& aiz, double& ajx, double& ajy,
                                                 double& ajz, double& radius) {
  overlap = ri + rj - d;
  const double qx = lx / d, qy = ly / d, qz = lz / d;  // in every lane, then a select
  const bool apart_centres = d > 0;                     // coincident: normal +z
  nx = apart_centres ? qx : 0.0, ny = apart_centres ? qy : 0.0, nz = apart_centres ? qz : 1.0;
  const double arm_i = ri - 0.5 * overlap, arm_j = -(rj - 0.5 * overlap);  // midpoint of the overlap (SPEC 4)
  aix = arm_i * nx, aiy = arm_i * ny, aiz = arm_i * nz;
  ajx = arm_j * nx, ajy = arm_j * ny, ajz = arm_j * nz;
  radius = ri * rj / (ri + rj);
}
inline ContactGeometry sphere_sphere(const Vec3& branch, double d, double ri, double rj) {
  ContactGeometry g;
  sphere_sphere(branch.x(), branch.y(), branch.z(), d, ri, rj, g.normal.x(), g.normal.y(), g.normal.z(), g.overlap,
                g.arm_i.x(), g.arm_i.y(), g.arm_i.z(), g.arm_j.x(), g.arm_j.y(), g.arm_j.z(), g.radius);
  return g;
}
inline ContactGeometry sphere_sphere(const Vec3& branch, double ri, double rj) {
  return sphere_sphere(branch, branch.norm(), ri, rj);
}

}  // namespace qsdem
