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
    const Vec3& n = g.normal;
    const double a = std::sqrt(g.radius * g.overlap);
    const double fn = 4.0 / 3.0 * effective_modulus * a * g.overlap;
    const double kn = 2.0 * effective_modulus * a;
    const double kt = 8.0 * effective_shear_modulus * a;

    // Turn the stored tangential force into the current tangent plane, keeping its magnitude.
    const double old_mag2 = shear.squaredNorm();
    if (old_mag2 > 0) {
      const double inv_old = 1 / old_mag2;  // off the chain below: shear is known before n
      const double sn = shear.dot(n);
      shear -= sn * n;
      // |shear|^2 is now old (1 - x), x = (s.n)^2 / old (n unit), so the magnitude comes back by
      // (1 - x)^-1/2 = 1 + x/2 + 3x^2/8 + O(x^3): below x = 1e-6 (a quasi-static contact turns by
      // far less per step) the cut terms, 5x^3/16 + ..., are < 3.2e-19, under the rounding of the
      // direct form, which takes a division and a square root in the chain of every contact.
      const double x = sn * sn * inv_old;
      if (x < 1e-6) {
        shear *= 1 + x * (0.5 + 0.375 * x);
      } else {
        const double new_mag2 = shear.squaredNorm();
        if (new_mag2 > 0) shear *= std::sqrt(old_mag2 / new_mag2);
      }
    }
    const Vec3 vt = rel_velocity - rel_velocity.dot(n) * n;
    shear -= kt * dt * vt;
    const double cap = friction * fn;
    const double mag2 = shear.squaredNorm();
    if (mag2 > cap * cap) shear *= cap / std::sqrt(mag2);
    return {fn * n + shear, kn, kt};
  }
};

// Exact sphere-sphere geometry for the branch l from i to j; overlap <= 0 means apart.
// d = |branch| (the caller's, when it has it: the same bits as branch.norm()).
inline ContactGeometry sphere_sphere(const Vec3& branch, double d, double ri, double rj) {
  ContactGeometry g;
  g.overlap = ri + rj - d;
  g.normal = d > 0 ? Vec3(branch / d) : Vec3::UnitZ();
  g.arm_i = (ri - 0.5 * g.overlap) * g.normal;   // midpoint of the overlap (SPEC 4)
  g.arm_j = -(rj - 0.5 * g.overlap) * g.normal;
  g.radius = ri * rj / (ri + rj);
  return g;
}
inline ContactGeometry sphere_sphere(const Vec3& branch, double ri, double rj) {
  return sphere_sphere(branch, branch.norm(), ri, rj);
}

}  // namespace qsdem
