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

// The geometry of N contacts by components, one contact per slot (structure of arrays): the
// narrow phases write it and the law's lanes read it in place (forces.cpp), with no record between.
template <int N>
struct alignas(64) ContactGeometrySlots {
  static constexpr int capacity = N;
  double nx[N], ny[N], nz[N], overlap[N], radius[N];
  double aix[N], aiy[N], aiz[N], ajx[N], ajy[N], ajz[N];

  void set(int s, const ContactGeometry& g) {
    nx[s] = g.normal.x(), ny[s] = g.normal.y(), nz[s] = g.normal.z(), overlap[s] = g.overlap, radius[s] = g.radius;
    aix[s] = g.arm_i.x(), aiy[s] = g.arm_i.y(), aiz[s] = g.arm_i.z();
    ajx[s] = g.arm_j.x(), ajy[s] = g.arm_j.y(), ajz[s] = g.arm_j.z();
  }
  ContactGeometry get(int s) const {
    return {{nx[s], ny[s], nz[s]}, overlap[s], {aix[s], aiy[s], aiz[s]}, {ajx[s], ajy[s], ajz[s]}, radius[s]};
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
