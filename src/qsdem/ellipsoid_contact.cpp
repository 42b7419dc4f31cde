// Perram-Wertheim ellipsoid contact (SPEC 4). See ellipsoid_contact.hpp for the contract.
//
// Derivations (all lengths in metres, no scaling needed: F is dimensionless and the iteration
// runs on the unit direction e = l/|l|, so F(lambda; l) = |l|^2 F(lambda; e)).
//
// 1. Derivatives. With s = Q(lambda)^-1 e, D = Q_j - Q_i, u = D s, v = Q^-1 u and E = e.s:
//      dQ^-1/dlambda = -Q^-1 D Q^-1  =>  E' = -s.u,  E'' = 2 u.v,  ds/dlambda = -v
//      F   = w E,                  w = lambda (1 - lambda)
//      F'  = (1 - 2 lambda) E - w s.u
//      F'' = -2 E - 2 (1 - 2 lambda) s.u + 2 w u.v     (< 0: F is concave, see the header)
//    One adjugate of Q(lambda) per iteration serves both solves (s and v).
//
// 2. Iteration. Bracket [lo, hi] = [0, 1] (F'(0) = e^T M_i e > 0, F'(1) = -e^T M_j e < 0).
//    Each iterate moves lo or hi by the sign of F'; the Newton step lambda - F'/F'' is taken when it
//    stays strictly inside the bracket (and F'' < 0), otherwise the bracket is bisected. The
//    iteration stops after a Newton step h whose relative effect on s, |h| |v| / |s|, is below
//    kStepTol = 1e-7: the step is then taken to first order, s <- s - h v, F <- F + F' h / 2,
//    whose error is O((|h| |v|/|s|)^2) ~ 1e-14 relative; Newton's quadratic convergence puts the
//    new lambda at the same order. This saves the final re-factorisation: a warm start
//    (lambda of the previous time step) usually converges in one iteration.
//    Cold start: at the maximiser lambda = h_i(n) / (h_i(n) + h_j(n)) exactly (x0 - c_i =
//    (1 - lambda) Q_i s lies on the mu-scaled surface of i, whose support value along n is
//    mu h_i(n); same for j); with n ~ e this gives lambda0 = h_i(e) / (h_i(e) + h_j(e)), exact for
//    spheres (r_i / (r_i + r_j)).
//
// 3. Overlap. x0 = c_i + (1 - lambda) Q_i s. At the maximiser F_i(x0) = F_j(x0) = mu^2, so when
//    the ellipsoids overlap (mu^2 < 1) x0 lies strictly inside both, however deep the overlap.
//    Along x0 + t n: F_i = A_i t^2 + 2 B_i t + F_i(x0), A_i = n^T M_i n, B_i = n^T M_i (x0 - c_i)
//    ~ (1 - lambda) |s| > 0; with F_i(x0) < 1 the larger root t_i > 0 is where the line leaves i
//    along +n. For j, going along -n: B_j = -n^T M_j (x0 - c_j) ~ lambda |s| > 0, root t_j > 0.
//    p_i = x0 + t_i n, p_j = x0 - t_j n, delta = (p_i - p_j).n = t_i + t_j. The roots are taken
//    in the cancellation-free form -C / (B + sqrt(B^2 - A C)). Both quadratics use the same point
//    x0 and its actual levels F_i(x0), F_j(x0) (not mu^2): the result is the exact chord of the
//    line through x0 along n, unchanged when a residual error in lambda slides x0 along n. If
//    round-off puts x0 on the wrong side of a surface (mu^2 within ulps of 1), delta <= 0 and
//    the call reports no contact, so a returned overlap is always > 0.
// 4. Effective radius. With r_k = p_k - c_k: M_i r_i = M_i (x0 - c_i) + t_i M_i n and
//    M_j r_j = M_j (x0 - c_j) - t_j M_j n. The relative curvature K_i + K_j restricted to n-perp is
//    the restriction of A = M_i / |M_i r_i| + M_j / |M_j r_j|, whose determinant is n^T adj(A) n.
//
// 5. Quick rejections: bounding spheres (|l| >= max axis_i + max axis_j, lambda untouched) and,
//    on a cold start, the support planes normal to l (h_i(e) + h_j(e) <= |l|: the slab between
//    them separates the pair; lambda <- lambda0). A warm start instead relies on the early exit
//    F(lambda) >= 1 of its first iterate.
#include "qsdem/ellipsoid_contact.hpp"

#include <Eigen/Cholesky>
#include <algorithm>
#include <cmath>
#include <limits>

namespace qsdem {

namespace {

constexpr double kStepTol = 1e-7;  // see 2. above
constexpr int kMaxIterations = 100;

// Symmetric 3x3 matrix by its six entries (cheaper than Mat3 in the inner loop).
struct Sym {
  double xx, yy, zz, xy, xz, yz;

  Vec3 operator*(const Vec3& v) const {
    return {xx * v.x() + xy * v.y() + xz * v.z(), xy * v.x() + yy * v.y() + yz * v.z(),
            xz * v.x() + yz * v.y() + zz * v.z()};
  }
  Sym operator+(const Sym& o) const { return {xx + o.xx, yy + o.yy, zz + o.zz, xy + o.xy, xz + o.xz, yz + o.yz}; }
  Sym operator-(const Sym& o) const { return {xx - o.xx, yy - o.yy, zz - o.zz, xy - o.xy, xz - o.xz, yz - o.yz}; }
  Sym operator*(double k) const { return {k * xx, k * yy, k * zz, k * xy, k * xz, k * yz}; }
  // Adjugate (= det * inverse).
  Sym adjugate() const {
    return {yy * zz - yz * yz, xx * zz - xz * xz, xx * yy - xy * xy,
            xz * yz - xy * zz, xy * yz - xz * yy, xy * xz - xx * yz};
  }
  double det_with(const Sym& adj) const { return xx * adj.xx + xy * adj.xy + xz * adj.xz; }
};

// First two columns of the rotation matrix of a unit quaternion (body axes 1 and 2 in the world).
void body_axes(const Quat& q, Vec3& c0, Vec3& c1) {
  const double w = q.w(), x = q.x(), y = q.y(), z = q.z();
  c0 = {1 - 2 * (y * y + z * z), 2 * (x * y + w * z), 2 * (x * z - w * y)};
  c1 = {2 * (x * y - w * z), 1 - 2 * (x * x + z * z), 2 * (y * z + w * x)};
}

// R diag(d0, d1, d2) R^T = d2 I + (d0 - d2) c0 c0^T + (d1 - d2) c1 c1^T (columns orthonormal):
// two rank-one updates, exact d I for spheres.
Sym shape_from_axes(const Vec3& c0, const Vec3& c1, double d0, double d1, double d2) {
  const double k0 = d0 - d2, k1 = d1 - d2;
  const Vec3 u = k0 * c0, v = k1 * c1;
  return {d2 + u.x() * c0.x() + v.x() * c1.x(), d2 + u.y() * c0.y() + v.y() * c1.y(),
          d2 + u.z() * c0.z() + v.z() * c1.z(), u.x() * c0.y() + v.x() * c1.y(),
          u.x() * c0.z() + v.x() * c1.z(),      u.y() * c0.z() + v.y() * c1.z()};
}

// Larger root of A t^2 + 2 B t + C = 0 (A > 0), without cancellation; a negative discriminant
// (line missing the ellipsoid, impossible when it is needed) is clamped to the tangent point.
double far_root(double A, double B, double C) {
  const double root = std::sqrt(std::max(0.0, B * B - A * C));
  return B > 0 ? -C / (B + root) : (-B + root) / A;
}

}  // namespace

double pw_contact_function(const Vec3& l, const Mat3& Q_i, const Mat3& Q_j, double lambda) {
  const Mat3 Q = (1 - lambda) * Q_i + lambda * Q_j;
  return lambda * (1 - lambda) * l.dot(Q.ldlt().solve(l));
}

EllipsoidShape ellipsoid_shape(const Vec3& axes, const Quat& q) {
  Vec3 c0, c1;
  body_axes(q, c0, c1);
  const Vec3 a2 = axes.cwiseAbs2();
  const Sym Q = shape_from_axes(c0, c1, a2.x(), a2.y(), a2.z());
  // Through the adjugate of this very Q: the surfaces the overlap step cuts are those the PW
  // iteration saw (to ~cond(Q) eps <= 9 eps); once per particle instead of once per contact.
  const Sym adj = Q.adjugate();
  const Sym M = adj * (1 / Q.det_with(adj));
  return {Q.xx, Q.yy, Q.zz, Q.xy, Q.xz, Q.yz, M.xx, M.yy, M.zz, M.xy, M.xz, M.yz, axes.maxCoeff(), axes.minCoeff()};
}

bool ellipsoid_contact(const Vec3& l, const Vec3& axes_i, const Quat& q_i, const Vec3& axes_j, const Quat& q_j,
                       double& lambda, ContactGeometry& g, EllipsoidContactStats& stats) {
  // Bounding spheres first: most calls of a sparse pair list end here, before any matrix.
  const double reach = axes_i.maxCoeff() + axes_j.maxCoeff();
  if (!(l.squaredNorm() < reach * reach)) {
    stats = {};
    if (l.allFinite()) stats.gap_bound = l.norm() - reach;
    return false;
  }
  return ellipsoid_contact(l, ellipsoid_shape(axes_i, q_i), ellipsoid_shape(axes_j, q_j), lambda, g, stats);
}

bool ellipsoid_contact(const Vec3& l, const EllipsoidShape& si, const EllipsoidShape& sj, double& lambda,
                       ContactGeometry& g) {
  EllipsoidContactStats stats;
  return ellipsoid_contact(l, si, sj, lambda, g, stats);
}

bool ellipsoid_contact(const Vec3& l, const EllipsoidShape& si, const EllipsoidShape& sj, double& lambda,
                       ContactGeometry& g, EllipsoidContactStats& stats) {
  stats = {};
  // Bounding spheres: cannot overlap (also rejects a non-finite l).
  const double reach = si.reach + sj.reach;
  const double l2 = l.squaredNorm();
  if (!(l2 < reach * reach)) {
    if (std::isfinite(l2)) stats.gap_bound = std::sqrt(l2) - reach;
    return false;
  }

  const Sym Qi{si.xx, si.yy, si.zz, si.xy, si.xz, si.yz};
  const Sym Qj{sj.xx, sj.yy, sj.zz, sj.xy, sj.xz, sj.yz};
  // |l|^2 underflows below ~1e-154 m: take the norm the slow, safe way there (l = 0 only is coincident).
  const double ln = l2 > 1e-200 ? std::sqrt(l2) : l.stableNorm();

  Vec3 s = Vec3::Zero();  // Q(lambda)^-1 e, later Q^-1 l
  double lam = 0.5;       // irrelevant for coincident centres (s = 0)
  double F = 0;           // F(lambda; e)
  if (ln > 0) {
    const Vec3 e = l * (1 / ln);
    const Sym D = Qj - Qi;
    if (lambda > 0 && lambda < 1) {
      lam = lambda;
    } else {
      const double sup_i = std::sqrt(e.dot(Qi * e)), sup_j = std::sqrt(e.dot(Qj * e));  // h_i(e), h_j(e)
      lam = sup_i / (sup_i + sup_j);
      // Support planes normal to e already separate the pair: no PW needed.
      if (sup_i + sup_j <= ln) {
        lambda = lam;
        stats.early_exit = true;
        stats.gap_bound = ln - (sup_i + sup_j);
        return false;
      }
    }
    double lo = 0, hi = 1;
    for (;;) {
      ++stats.iterations;
      const Sym Q = Qi + D * lam;
      const Sym adj = Q.adjugate();
      const double inv_det = 1 / Q.det_with(adj);
      s = (adj * e) * inv_det;
      const double E = e.dot(s);
      const Vec3 u = D * s;
      const double su = s.dot(u);
      const double w = lam * (1 - lam);
      F = w * E;
      if (l2 * F >= 1) {  // F(lambda) <= mu^2: separation proved
        stats.early_exit = true;
        stats.mu2 = l2 * F;
        stats.gap_bound = (std::sqrt(stats.mu2) - 1) * (si.minor + sj.minor);
        lambda = lam;
        return false;
      }
      const Vec3 v = (adj * u) * inv_det;
      const double Fp = (1 - 2 * lam) * E - w * su;
      const double Fpp = -2 * E - 2 * (1 - 2 * lam) * su + 2 * w * u.dot(v);
      if (Fp > 0) lo = lam; else hi = lam;
      if (Fpp < 0) {
        // Converged: tested before the bracket, since a warm start sits on the maximiser and its
        // Newton step may round to lambda itself (or an ulp outside the new bracket), which would
        // otherwise send it bisecting from [lambda, 1] back to lambda (~50 iterations).
        const double h = -Fp / Fpp;
        if (h * h * v.squaredNorm() <= kStepTol * kStepTol * s.squaredNorm()) {
          lam += h;
          s -= h * v;
          F += 0.5 * Fp * h;
          break;
        }
      }
      double next = Fpp < 0 ? lam - Fp / Fpp : lo - 1;  // lo - 1: forces bisection
      if (!(next > lo && next < hi)) {
        next = 0.5 * (lo + hi);
        ++stats.bisections;
      }
      if (hi - lo <= 4 * std::numeric_limits<double>::epsilon() || stats.iterations >= kMaxIterations) break;
      lam = next;
    }
    lambda = lam;
  }
  const double mu2 = l2 * F;
  stats.mu2 = mu2;
  if (!(mu2 < 1)) {
    if (mu2 > 1) stats.gap_bound = (std::sqrt(mu2) - 1) * (si.minor + sj.minor);  // F may be refined by
    return false;                                                               // a first-order step
  }

  const double sn = s.norm();  // s is still Q^-1 e here: no underflow for tiny |l|
  const Vec3 n = sn > 0 ? Vec3(s * (1 / sn)) : Vec3::UnitZ();
  s *= ln;  // Q^-1 l

  // The line x0 + t n through the one point x0, cut by each surface (3. above), M = Q^-1 from
  // the shapes (ellipsoid_shape).
  const Sym Mi{si.mxx, si.myy, si.mzz, si.mxy, si.mxz, si.myz};
  const Sym Mj{sj.mxx, sj.myy, sj.mzz, sj.mxy, sj.mxz, sj.myz};
  const Vec3 di = (1 - lam) * (Qi * s);  // x0 - c_i
  const Vec3 dj = di - l;                // x0 - c_j
  const Vec3 Mdi = Mi * di, Mdj = Mj * dj;
  const Vec3 wi = Mi * n, wj = Mj * n;
  const double ti = far_root(n.dot(wi), n.dot(Mdi), di.dot(Mdi) - 1);   // along +n
  const double tj = far_root(n.dot(wj), -n.dot(Mdj), dj.dot(Mdj) - 1);  // along -n
  const double delta = ti + tj;
  if (!(delta > 0)) return false;  // mu^2 within round-off of 1

  g.normal = n;
  g.overlap = delta;
  g.arm_i = di + 0.5 * (ti - tj) * n;
  g.arm_j = g.arm_i - l;

  const double gi = (Mdi + ti * wi).norm();  // |M_i (p_i - c_i)|
  const double gj = (Mdj - tj * wj).norm();  // |M_j (p_j - c_j)|
  // adj(c A) = c^2 adj(A): scale M_i/g_i + M_j/g_j by g_i g_j to save two divisions.
  const Sym A = Mi * gj + Mj * gi;
  g.radius = gi * gj / std::sqrt(n.dot(A.adjugate() * n));
  return true;
}

bool ellipsoid_contact(const Vec3& l, const Vec3& axes_i, const Quat& q_i, const Vec3& axes_j, const Quat& q_j,
                       double& lambda, ContactGeometry& g) {
  EllipsoidContactStats stats;
  return ellipsoid_contact(l, axes_i, q_i, axes_j, q_j, lambda, g, stats);
}

}  // namespace qsdem
