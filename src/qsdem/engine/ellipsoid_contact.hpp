// Exact ellipsoid-ellipsoid narrow phase (SPEC 4): Perram-Wertheim contact function, overlap
// along the PW normal, Greenwood effective radius. Pure functions, no state but `lambda`.
//
// Notation: centre c, rotation R (body to world, from the quaternion), semi-axes (a, b, c),
//   Q = R diag(a^2, b^2, c^2) R^T,  M = Q^-1,  F_k(x) = (x - c_k)^T M_k (x - c_k)  (inside: < 1),
//   l = c_j - c_i (branch vector through the periodic image),  Q(lambda) = (1 - lambda) Q_i + lambda Q_j.
//
// Method (derivations in ellipsoid_contact.cpp):
//   F(lambda) = lambda (1 - lambda) l^T Q(lambda)^-1 l = min_x [lambda F_i(x) + (1 - lambda) F_j(x)]
//   is a minimum of functions affine in lambda, hence concave on [0, 1], with F(0) = F(1) = 0,
//   F'(0) > 0 > F'(1): the maximiser is unique and bracketed. Safeguarded Halley (Newton with
//   F''') on F' keeps a bracket [lo, hi] and bisects whenever a step would leave it. mu^2 = max F; the
//   ellipsoids overlap iff mu^2 < 1 (touch at mu = 1). Any iterate with |l|^2 F(lambda) >= 1
//   already proves separation (F <= mu^2) and ends the call early.
//   At the maximiser x0 = c_i + (1 - lambda) Q_i s (s = Q(lambda)^-1 l) satisfies
//   F_i(x0) = F_j(x0) = mu^2, and grad F_i(x0) ~ +s, grad F_j(x0) ~ -s: n = s / |s| is the
//   common normal of the two level surfaces through x0, oriented from i to j (n . l = l^T Q^-1 l > 0).
//   Overlapping pairs have x0 strictly inside both ellipsoids, so the line x0 + t n leaves i at
//   a unique t_i > 0 and leaves j (going along -n) at a unique t_j > 0; delta = t_i + t_j > 0.
//   Accuracy vs the exact common-normal overlap: normal angle and R_e within O(delta/R),
//   delta within O(delta^2/R), contact point within O(delta) (measured constants < 0.6 in the tests).
//
// Lambda convention: lambda weights Q_j (lambda -> 0 when j is much smaller than i).
// Swapping i and j maps lambda -> 1 - lambda. At the maximiser lambda = h_i(n) / (h_i(n) + h_j(n)),
// h_k(n) = sqrt(n^T Q_k n) the support function (distance from centre to tangent plane).
#pragma once
#include "qsdem/engine/component_arrays.hpp"
#include "qsdem/engine/contact/geometry.hpp"
#include "qsdem/engine/types.hpp"

namespace qsdem {

// Diagnostics of one ellipsoid_contact call (tests, benchmarks).
struct EllipsoidContactStats {
  int iterations = 0;         // PW iterations (3x3 factorisations); 0 = bounding-sphere rejection
  int bisections = 0;         // of which bisection steps (safeguard)
  bool early_exit = false;    // stopped because F(lambda) >= 1 proved separation
  double mu2 = 0;             // F at the last iterate (= max F when converged)
  // When the call returns false: a proven lower bound of the distance between the two surfaces
  // (m), 0 when none is known. From the bounding spheres |l| - a_i - a_j, the support planes
  // |l| - h_i(e) - h_j(e), or the contact function: mu E_k (scaled about its centre) contains
  // E_k + ball((mu - 1) c_k), c_k its smallest semi-axis, and the mu-scaled pair only touches, so
  // the gap is >= (mu - 1)(c_i + c_j) with mu = sqrt(F(lambda)) <= sqrt(max F) at any iterate.
  double gap_bound = 0;
};

// Exact contact of two ellipsoids (SPEC 4): Perram-Wertheim contact function
//   F(lambda) = lambda (1 - lambda) l^T [(1 - lambda) Q_i + lambda Q_j]^-1 l,  Q = R diag(a^2, b^2, c^2) R^T,
// maximised over lambda in [0, 1] by a safeguarded Halley iteration (bracketed root of F'),
// warm-started from `lambda` (in/out; a value outside the open interval (0, 1), or NaN, means cold start).
// l = c_j - c_i is the branch vector from centre i to centre j (through the periodic image).
// q_i, q_j must be unit quaternions (body to world).
// Returns true when the ellipsoids overlap (mu^2 = max F < 1 and delta > 0), and then fills `g`:
//   g.normal  unit normal from i towards j, n = Q(lambda)^-1 l / |.| (common gradient direction at x0)
//   g.overlap delta > 0 between the surface points of i (x0 + t_i n) and of j (x0 - t_j n) on the
//             line through the PW point x0 along n
//   g.arm_i, g.arm_j  contact point - centre (contact point = midpoint of the two surface points)
//   g.radius  effective Hertz radius R_e = (k' k'')^(-1/2), k' k'' = det of the relative curvature
//             tensor K_i + K_j restricted to the plane normal to n, K = P M P / |M (p - c)|,
//             P = I - n n^T, p the surface point (Greenwood 1985); spheres give R1 R2 / (R1 + R2).
// When it returns false, `g` is unspecified. `lambda` is unchanged after a bounding-sphere
// rejection (|l| >= max semi-axis_i + max semi-axis_j); otherwise it holds the last iterate, which
// is the maximiser, or (early exit) a point where F >= 1 already proves separation, or the cold
// start guess when support planes normal to l separate the pair - in every case a warm start.
// Coincident centres (l = 0): F = 0, returns true with normal +z (as sphere_sphere does),
// x0 = c_i, delta = extent of i along +z + extent of j along -z; lambda is left unchanged.
bool ellipsoid_contact(const Vec3& l, const Vec3& axes_i, const Quat& q_i, const Vec3& axes_j, const Quat& q_j,
                       double& lambda, ContactGeometry& g);

// The same, reporting iteration counts and mu^2.
bool ellipsoid_contact(const Vec3& l, const Vec3& axes_i, const Quat& q_i, const Vec3& axes_j, const Quat& q_j,
                       double& lambda, ContactGeometry& g, EllipsoidContactStats& stats);

// Shape matrix Q = R diag(a^2, b^2, c^2) R^T of an ellipsoid (SPEC 4) by its six entries, and its
// bounding radius. Computed once per particle and step by the force stage (every particle has
// several pairs), instead of once per pair. One cache line: the batch reads j's at random, and
// M = Q^-1 (the surface x^T M x = 1) is computed in the batch for the contacts only.
struct alignas(64) EllipsoidShape {
  double xx, yy, zz, xy, xz, yz;
  double reach;  // largest semi-axis
  double minor;  // smallest semi-axis
};
EllipsoidShape ellipsoid_shape(const Vec3& axes, const Quat& q);
// The shapes of particles [lo, hi): out[a] = ellipsoid_shape(axes[a], q[a]), the same bits (one
// loop over the particles, in vector lanes).
void ellipsoid_shapes(const Vec3* axes, const ComponentArrays<Quat>& q, EllipsoidShape* out, std::size_t lo,
                      std::size_t hi);

// The same contact from precomputed shapes (bit-identical to the overloads above).
bool ellipsoid_contact(const Vec3& l, const EllipsoidShape& si, const EllipsoidShape& sj, double& lambda,
                       ContactGeometry& g, EllipsoidContactStats& stats);
bool ellipsoid_contact(const Vec3& l, const EllipsoidShape& si, const EllipsoidShape& sj, double& lambda,
                       ContactGeometry& g);

// A batch of contact tests, evaluated together by ellipsoid_contacts: the lanes' arithmetic is
// laid out as structure of arrays, so the compiler runs several pairs per vector instruction and
// the core overlaps their division and square-root chains (a lone pair is latency bound). Each
// lane gets exactly what ellipsoid_contact gives that pair alone (which is a batch of one).
struct EllipsoidContactBatch {
  static constexpr int capacity = 64;
  int size = 0;
  // In: the branch vector and the two shapes (not owned; alive until ellipsoid_contacts returns).
  Vec3 l[capacity];
  const EllipsoidShape* shape_i[capacity];
  const EllipsoidShape* shape_j[capacity];
  double lambda[capacity];  // in/out: the warm start, as for ellipsoid_contact
  // Out.
  bool touching[capacity];
  int slot[capacity];  // where touching: the slot of its geometry in `geometry`
  EllipsoidContactStats stats[capacity];
  // The geometry of the lanes tested for overlap, in slots first, first + 1, ... (at most `size`).
  // Room for two calls: a caller that alternates `first` between 0 and capacity still has the
  // last call's geometry (the force stage's law lanes hold contacts of both).
  int first = 0;
  ContactGeometrySlots<2 * capacity> geometry;

  // Appends a pair (size < capacity) and returns its lane.
  int add(const Vec3& branch, const EllipsoidShape& si, const EllipsoidShape& sj, double warm_start);
  // A touching lane's geometry.
  ContactGeometry contact(int k) const { return geometry.get(slot[k]); }
};
void ellipsoid_contacts(EllipsoidContactBatch& batch);

// ---- Helper (tests, diagnostics) ----

// F(lambda) = lambda (1 - lambda) l^T [(1 - lambda) Q_i + lambda Q_j]^-1 l by an LDLT solve
// (independent of the adjugate path used by ellipsoid_contact; slow, for checks).
double pw_contact_function(const Vec3& l, const Mat3& Q_i, const Mat3& Q_j, double lambda);

}  // namespace qsdem
