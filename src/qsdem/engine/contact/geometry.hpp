// Where two bodies touch: the narrow phase's result (SPEC 4), the input of every contact law
// (contact/law.hpp). The exact sphere-sphere geometry is here; the ellipsoids' is
// ellipsoid_contact.hpp.
#pragma once
#include <cmath>

#include "qsdem/engine/types.hpp"

namespace qsdem {

// Where two bodies touch (from a narrow phase).
struct ContactGeometry {
  Vec3 normal;      // unit, from i towards j
  double overlap;   // delta (m), > 0 in contact
  Vec3 arm_i;       // contact point - centre of i (m)
  Vec3 arm_j;       // contact point - centre of j (m)
  double radius;    // effective Hertz radius R_e (m)
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
