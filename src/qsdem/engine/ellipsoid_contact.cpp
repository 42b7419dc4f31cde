// Perram-Wertheim ellipsoid contact (SPEC 4). See ellipsoid_contact.hpp for the contract.
//
// Derivations (all lengths in metres, no scaling needed: F is dimensionless and the iteration
// runs on the unit direction e = l/|l|, so F(lambda; l) = |l|^2 F(lambda; e)).
//
// 1. Derivatives. With s = Q(lambda)^-1 e, D = Q_j - Q_i, u = D s, v = Q^-1 u, z = Q^-1 D v, E = e.s:
//      d^n Q^-1/dlambda^n = (-1)^n n! (Q^-1 D)^n Q^-1  =>
//      E' = -s.u,  E'' = 2 u.v,  E''' = -6 v.D v,  s' = -v,  s'' = 2 z
//      F    = w E,                  w = lambda (1 - lambda)
//      F'   = (1 - 2 lambda) E - w s.u
//      F''  = -2 E - 2 (1 - 2 lambda) s.u + 2 w u.v     (< 0: F is concave, see the header)
//      F''' = 6 s.u + 6 (1 - 2 lambda) u.v - 6 w v.D v
//    One adjugate of Q(lambda) per iteration serves the three solves (s, v and z).
//
// 2. Iteration. Bracket [lo, hi] = [0, 1] (F'(0) = e^T M_i e > 0, F'(1) = -e^T M_j e < 0).
//    Each iterate moves lo or hi by the sign of F'; the Halley step h = -2 F' F'' / (2 F''^2 - F' F''')
//    (Newton's -F'/F'' where Halley's would be more than twice as long) is taken when it stays
//    strictly inside the bracket (and F'' < 0), otherwise the bracket is bisected. The iteration
//    stops after a step h whose relative effect on s, r = |h| |v| / |s|, is below kStepTol = 1e-5:
//    the step is then taken by Taylor series, s <- s - h v + h^2 z, F <- F + h (F' + h (F''/2 +
//    h F'''/6)), whose error is O(r^3) ~ 1e-15 relative; Halley's cubic convergence puts the new
//    lambda at the same order. This saves the final re-factorisation: a warm start (lambda of the
//    previous time step) usually converges in one iteration (a first-order Newton step would
//    need r < 1e-7).
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
#include "qsdem/engine/ellipsoid_contact.hpp"

#include <Eigen/Cholesky>
#include <algorithm>
#include <cmath>
#include <limits>

#include "qsdem/engine/clones.hpp"

namespace qsdem {

namespace {

constexpr double kStepTol = 1e-5;  // see 2. above
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

// Shape matrix of semi-axes (a0, a1, a2) turned by the unit quaternion (w, x, y, z), by components:
// R diag(d0, d1, d2) R^T = d2 I + (d0 - d2) c0 c0^T + (d1 - d2) c1 c1^T, d = a^2, with c0, c1 the
// first two columns of R (the body axes 1 and 2 in the world; orthonormal): two rank-one updates,
// exact d I for spheres. On components (not Vec3 and Quat) so that a loop of particles runs in
// vector lanes (ellipsoid_shapes).
[[gnu::always_inline]] inline void shape_of(double w, double x, double y, double z, double a0, double a1, double a2,
                                            EllipsoidShape& out) {
  const double c0x = 1 - 2 * (y * y + z * z), c0y = 2 * (x * y + w * z), c0z = 2 * (x * z - w * y);
  const double c1x = 2 * (x * y - w * z), c1y = 1 - 2 * (x * x + z * z), c1z = 2 * (y * z + w * x);
  const double d0 = a0 * a0, d1 = a1 * a1, d2 = a2 * a2;
  const double k0 = d0 - d2, k1 = d1 - d2;
  const double ux = k0 * c0x, uy = k0 * c0y, uz = k0 * c0z, vx = k1 * c1x, vy = k1 * c1y, vz = k1 * c1z;
  out.xx = d2 + ux * c0x + vx * c1x, out.yy = d2 + uy * c0y + vy * c1y, out.zz = d2 + uz * c0z + vz * c1z;
  out.xy = ux * c0y + vx * c1y, out.xz = ux * c0z + vx * c1z, out.yz = uy * c0z + vy * c1z;
  out.reach = std::max(std::max(a0, a1), a2);
  out.minor = std::min(std::min(a0, a1), a2);
}

// The gap proved by F(lambda) |l|^2 = mu^2 > 1 (EllipsoidContactStats::gap_bound): the mu-scaled
// pair only touches, and mu E_k contains E_k grown by (mu - 1) times its smallest semi-axis.
double contact_function_gap(double mu2, const EllipsoidShape& si, const EllipsoidShape& sj) {
  return (std::sqrt(mu2) - 1) * (si.minor + sj.minor);
}

// Larger root of A t^2 + 2 B t + C = 0 (A > 0), without cancellation; a negative discriminant
// (line missing the ellipsoid, impossible when it is needed) is clamped to the tangent point.
// Both forms are computed, so that a loop of calls has no branch (vector lanes).
double far_root(double A, double B, double C) {
  const double root = std::sqrt(std::max(0.0, B * B - A * C));
  const double stable_positive = -C / (B + root), stable_negative = (-B + root) / A;
  return B > 0 ? stable_positive : stable_negative;
}

}  // namespace

double pw_contact_function(const Vec3& l, const Mat3& Q_i, const Mat3& Q_j, double lambda) {
  const Mat3 Q = (1 - lambda) * Q_i + lambda * Q_j;
  return lambda * (1 - lambda) * l.dot(Q.ldlt().solve(l));
}

EllipsoidShape ellipsoid_shape(const Vec3& axes, const Quat& q) {
  EllipsoidShape out;
  shape_of(q.w(), q.x(), q.y(), q.z(), axes.x(), axes.y(), axes.z(), out);
  return out;
}

// In vector lanes where the CPU has AVX2 (chosen at load time; no FMA, so the same bits). The
// arrays as doubles: through Vec3 GCC 12 does not vectorise the loop ("no vectype").
QSDEM_CLONES void ellipsoid_shapes(const Vec3* axes, const ComponentArrays<Quat>& q, EllipsoidShape* out,
                                   std::size_t lo, std::size_t hi) {
  static_assert(sizeof(Vec3) == 3 * sizeof(double), "packed arrays");
  const double* const ad = reinterpret_cast<const double*>(axes);  // a0 a1 a2 per particle
  const double *const qx = q.component(0), *const qy = q.component(1), *const qz = q.component(2),
                      *const qw = q.component(3);
#pragma omp simd
  for (std::size_t a = lo; a < hi; ++a)
    shape_of(qw[a], qx[a], qy[a], qz[a], ad[3 * a], ad[3 * a + 1], ad[3 * a + 2], out[a]);
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
  EllipsoidContactBatch batch;
  batch.add(l, si, sj, lambda);
  ellipsoid_contacts(batch);
  lambda = batch.lambda[0];
  if (batch.touching[0]) g = batch.contact(0);
  stats = batch.stats[0];
  return batch.touching[0];
}

namespace {

// The batch's lanes between its three phases (ellipsoid_contacts below).
struct PwLanes {
  static constexpr int cap = EllipsoidContactBatch::capacity;
  // Lanes still iterating (slot a -> lane[a]): unit branch e, Q_i, D = Q_j - Q_i, bracket.
  alignas(64) double ex[cap], ey[cap], ez[cap], l2s[cap], lams[cap], los[cap], his[cap];
  alignas(64) double qxx[cap], qyy[cap], qzz[cap], qxy[cap], qxz[cap], qyz[cap];
  alignas(64) double dxx[cap], dyy[cap], dzz[cap], dxy[cap], dxz[cap], dyz[cap];
  int lane[cap];
  int na = 0;
  alignas(64) double lns[cap];  // |l|, by lane
  // 3.'s inputs (header comment, 3.): the lanes done iterating with mu^2 < 1, slot a -> lane ov[a].
  alignas(64) double c_l[3][cap], c_s[3][cap], c_lam[cap], c_ln[cap], c_Qi[6][cap], c_Qj[6][cap];
  int ov[cap];
  int no = 0;
};

// A lane done iterating at lambda with s = Q^-1 e and F: mu^2, then 3.'s slot or the gap bound.
[[gnu::always_inline]] inline void finish_lane(EllipsoidContactBatch& b, PwLanes& pw, int k, double lambda, double s_x,
                                               double s_y, double s_z, double F, double l2) {
  EllipsoidContactStats& st = b.stats[k];
  const double mu2 = l2 * F;
  st.mu2 = mu2;
  const EllipsoidShape& si = *b.shape_i[k];
  const EllipsoidShape& sj = *b.shape_j[k];
  if (!(mu2 < 1)) {
    if (mu2 > 1) st.gap_bound = contact_function_gap(mu2, si, sj);  // F may be refined by a Taylor step
    return;
  }
  const int no = pw.no++;
  pw.ov[no] = k;
  for (int c = 0; c < 3; ++c) pw.c_l[c][no] = b.l[k][c];
  pw.c_s[0][no] = s_x, pw.c_s[1][no] = s_y, pw.c_s[2][no] = s_z;
  pw.c_lam[no] = lambda, pw.c_ln[no] = pw.lns[k];
  const double qi[6] = {si.xx, si.yy, si.zz, si.xy, si.xz, si.yz};
  const double qj[6] = {sj.xx, sj.yy, sj.zz, sj.xy, sj.xz, sj.yz};
  for (int c = 0; c < 6; ++c) pw.c_Qi[c][no] = qi[c], pw.c_Qj[c][no] = qj[c];
}

// 1. Per lane, the quick rejections (bounding spheres, support planes) and the start of the
// iteration: the lanes left to iterate go into pw's slots.
[[gnu::always_inline]] inline void reject_or_start(EllipsoidContactBatch& b, PwLanes& pw) {
  for (int k = 0; k < b.size; ++k) {
    EllipsoidContactStats& st = b.stats[k];
    st = {};
    b.touching[k] = false;
    const Vec3& l = b.l[k];
    const EllipsoidShape& si = *b.shape_i[k];
    const EllipsoidShape& sj = *b.shape_j[k];
    // Bounding spheres: cannot overlap (also rejects a non-finite l).
    const double reach = si.reach + sj.reach;
    const double l2 = l.squaredNorm();
    if (!(l2 < reach * reach)) {
      if (std::isfinite(l2)) st.gap_bound = std::sqrt(l2) - reach;
      continue;
    }
    // |l|^2 underflows below ~1e-154 m: take the norm the slow, safe way there (l = 0 only is coincident).
    const double ln = l2 > 1e-200 ? std::sqrt(l2) : l.stableNorm();
    pw.lns[k] = ln;
    if (!(ln > 0)) {  // coincident centres: s = 0, F = 0 (lambda irrelevant and unchanged)
      finish_lane(b, pw, k, 0.5, 0, 0, 0, 0, l2);
      continue;
    }
    const Vec3 e = l * (1 / ln);
    const Sym Qi{si.xx, si.yy, si.zz, si.xy, si.xz, si.yz};
    const Sym Qj{sj.xx, sj.yy, sj.zz, sj.xy, sj.xz, sj.yz};
    const Sym D = Qj - Qi;
    double lam;
    if (b.lambda[k] > 0 && b.lambda[k] < 1) {
      lam = b.lambda[k];
    } else {
      const double sup_i = std::sqrt(e.dot(Qi * e)), sup_j = std::sqrt(e.dot(Qj * e));  // h_i(e), h_j(e)
      lam = sup_i / (sup_i + sup_j);
      // Support planes normal to e already separate the pair: no PW needed.
      if (sup_i + sup_j <= ln) {
        b.lambda[k] = lam;
        st.early_exit = true;
        st.gap_bound = ln - (sup_i + sup_j);
        continue;
      }
    }
    const int na = pw.na++;
    pw.lane[na] = k;
    pw.ex[na] = e.x(), pw.ey[na] = e.y(), pw.ez[na] = e.z(), pw.l2s[na] = l2;
    pw.lams[na] = lam, pw.los[na] = 0, pw.his[na] = 1;
    pw.qxx[na] = Qi.xx, pw.qyy[na] = Qi.yy, pw.qzz[na] = Qi.zz, pw.qxy[na] = Qi.xy, pw.qxz[na] = Qi.xz, pw.qyz[na] = Qi.yz;
    pw.dxx[na] = D.xx, pw.dyy[na] = D.yy, pw.dzz[na] = D.zz, pw.dxy[na] = D.xy, pw.dxz[na] = D.xz, pw.dyz[na] = D.yz;
  }
}

// 2. PW iterations (2. in the header comment), one per pass for all iterating lanes, in one loop
// without branches (selects); the lanes that are done leave the working set (compacted), those
// with mu^2 < 1 straight into 3.'s slots.
// One PW pass's outcome per lane (flags as doubles: the compiler keeps the pass in vector lanes
// only when every value it stores has the doubles' width).
struct PwOutcome {
  static constexpr int cap = PwLanes::cap;
  static constexpr double iterate = 0, separated = 1, converged = 2;  // status
  alignas(64) double Fo[cap], lam_out[cap], next[cap], isx[cap], isy[cap], isz[cap];
  alignas(64) double status[cap], bisected[cap], exhausted[cap];
};

// The lanes that are done after a pass leave (separated: the bound of their gap; converged or out
// of iterations: 3.'s slots); the others move down with their next lambda.
[[gnu::always_inline]] inline void retire_lanes(EllipsoidContactBatch& b, PwLanes& pw, const PwOutcome& o) {
  int m = 0;
  for (int a = 0; a < pw.na; ++a) {
    const int k = pw.lane[a];
    EllipsoidContactStats& st = b.stats[k];
    ++st.iterations;
    st.bisections += o.bisected[a] != 0 ? 1 : 0;
    if (o.status[a] == PwOutcome::separated) {
      st.early_exit = true;
      st.mu2 = pw.l2s[a] * o.Fo[a];
      st.gap_bound = contact_function_gap(st.mu2, *b.shape_i[k], *b.shape_j[k]);
      b.lambda[k] = pw.lams[a];
    } else if (o.status[a] == PwOutcome::converged || o.exhausted[a] != 0 || st.iterations >= kMaxIterations) {
      b.lambda[k] = o.lam_out[a];
      finish_lane(b, pw, k, o.lam_out[a], o.isx[a], o.isy[a], o.isz[a], o.Fo[a], pw.l2s[a]);
    } else {
      pw.lane[m] = k;
      pw.ex[m] = pw.ex[a], pw.ey[m] = pw.ey[a], pw.ez[m] = pw.ez[a], pw.l2s[m] = pw.l2s[a];
      pw.lams[m] = o.next[a], pw.los[m] = pw.los[a], pw.his[m] = pw.his[a];
      pw.qxx[m] = pw.qxx[a], pw.qyy[m] = pw.qyy[a], pw.qzz[m] = pw.qzz[a];
      pw.qxy[m] = pw.qxy[a], pw.qxz[m] = pw.qxz[a], pw.qyz[m] = pw.qyz[a];
      pw.dxx[m] = pw.dxx[a], pw.dyy[m] = pw.dyy[a], pw.dzz[m] = pw.dzz[a];
      pw.dxy[m] = pw.dxy[a], pw.dxz[m] = pw.dxz[a], pw.dyz[m] = pw.dyz[a];
      ++m;
    }
  }
  pw.na = m;
}

[[gnu::always_inline]] inline void iterate_lanes(EllipsoidContactBatch& b, PwLanes& pw) {
  constexpr double iterate = PwOutcome::iterate, separated = PwOutcome::separated, converged = PwOutcome::converged;
  PwOutcome o;
  while (pw.na > 0) {
#pragma omp simd
    for (int a = 0; a < pw.na; ++a) {
      // Written out by components, the twins of Sym's adjugate, det_with and product: the same
      // code through Sym and a struct of three doubles keeps GCC 12 from vectorising the
      // loop ("no vectype"); the order of every sum is Sym's, hence the same bits.
      const double lam = pw.lams[a], e_x = pw.ex[a], e_y = pw.ey[a], e_z = pw.ez[a];
      // Q = Q_i + D lambda, its adjugate and determinant.
      const double Qxx = pw.qxx[a] + pw.dxx[a] * lam, Qyy = pw.qyy[a] + pw.dyy[a] * lam, Qzz = pw.qzz[a] + pw.dzz[a] * lam;
      const double Qxy = pw.qxy[a] + pw.dxy[a] * lam, Qxz = pw.qxz[a] + pw.dxz[a] * lam, Qyz = pw.qyz[a] + pw.dyz[a] * lam;
      const double Axx = Qyy * Qzz - Qyz * Qyz, Ayy = Qxx * Qzz - Qxz * Qxz, Azz = Qxx * Qyy - Qxy * Qxy;
      const double Axy = Qxz * Qyz - Qxy * Qzz, Axz = Qxy * Qyz - Qxz * Qyy, Ayz = Qxy * Qxz - Qxx * Qyz;
      const double inv_det = 1 / (Qxx * Axx + Qxy * Axy + Qxz * Axz);
      // s = Q^-1 e, u = D s, v = Q^-1 u.
      const double s_x = (Axx * e_x + Axy * e_y + Axz * e_z) * inv_det;
      const double s_y = (Axy * e_x + Ayy * e_y + Ayz * e_z) * inv_det;
      const double s_z = (Axz * e_x + Ayz * e_y + Azz * e_z) * inv_det;
      const double E = e_x * s_x + e_y * s_y + e_z * s_z;
      const double u_x = pw.dxx[a] * s_x + pw.dxy[a] * s_y + pw.dxz[a] * s_z;
      const double u_y = pw.dxy[a] * s_x + pw.dyy[a] * s_y + pw.dyz[a] * s_z;
      const double u_z = pw.dxz[a] * s_x + pw.dyz[a] * s_y + pw.dzz[a] * s_z;
      const double su = s_x * u_x + s_y * u_y + s_z * u_z;
      const double w = lam * (1 - lam);
      const double F = w * E;
      const double apart = pw.l2s[a] * F >= 1 ? 1.0 : 0.0;  // F(lambda) <= mu^2: separation proved
      const double v_x = (Axx * u_x + Axy * u_y + Axz * u_z) * inv_det;
      const double v_y = (Axy * u_x + Ayy * u_y + Ayz * u_z) * inv_det;
      const double v_z = (Axz * u_x + Ayz * u_y + Azz * u_z) * inv_det;
      // D v, v.D v and z = Q^-1 D v: F''' and s'' for the Halley step and the Taylor series.
      const double Dv_x = pw.dxx[a] * v_x + pw.dxy[a] * v_y + pw.dxz[a] * v_z;
      const double Dv_y = pw.dxy[a] * v_x + pw.dyy[a] * v_y + pw.dyz[a] * v_z;
      const double Dv_z = pw.dxz[a] * v_x + pw.dyz[a] * v_y + pw.dzz[a] * v_z;
      const double z_x = (Axx * Dv_x + Axy * Dv_y + Axz * Dv_z) * inv_det;
      const double z_y = (Axy * Dv_x + Ayy * Dv_y + Ayz * Dv_z) * inv_det;
      const double z_z = (Axz * Dv_x + Ayz * Dv_y + Azz * Dv_z) * inv_det;
      const double uv = u_x * v_x + u_y * v_y + u_z * v_z;
      const double vDv = v_x * Dv_x + v_y * Dv_y + v_z * Dv_z;
      const double Fp = (1 - 2 * lam) * E - w * su;
      const double Fpp = -2 * E - 2 * (1 - 2 * lam) * su + 2 * w * uv;
      const double Fppp = 6 * su + 6 * (1 - 2 * lam) * uv - 6 * w * vDv;
      const double lo_old = pw.los[a], hi_old = pw.his[a];  // loaded in every lane (no conditional load)
      const double lo = Fp > 0 ? lam : lo_old, hi = Fp > 0 ? hi_old : lam;
      // Converged: tested before the bracket, since a warm start sits on the maximiser and its
      // step may round to lambda itself (or an ulp outside the new bracket), which would
      // otherwise send it bisecting from [lambda, 1] back to lambda (~50 iterations).
      // Halley's step, or Newton's (the denominator 2 F''^2) where Halley's would be more than
      // twice as long: 2 F''^2 - F' F''' < F''^2.
      const double Fpp2 = Fpp * Fpp, halley = 2 * Fpp2 - Fp * Fppp;
      const double h = -2 * Fp * Fpp / (halley >= Fpp2 ? halley : 2 * Fpp2);
      // (Flags are 0/1 doubles combined by selects and products: the loop must have no branch to
      // run in vector lanes.)
      const double small_step = h * h * (v_x * v_x + v_y * v_y + v_z * v_z) <=
                                        kStepTol * kStepTol * (s_x * s_x + s_y * s_y + s_z * s_z) ? 1.0 : 0.0;
      const double conv = Fpp < 0 ? small_step : 0.0;
      double step = Fpp < 0 ? lam + h : lo - 1;  // lo - 1 forces bisection
      const double inside = step > lo ? (step < hi ? 1.0 : 0.0) : 0.0;
      step = inside != 0 ? step : 0.5 * (lo + hi);
      // A converged step is taken by Taylor series (2. in the header comment).
      const bool take = conv * (1 - apart) != 0;
      const double hh = h * h;
      o.lam_out[a] = take ? lam + h : lam;
      o.isx[a] = take ? s_x - h * v_x + hh * z_x : s_x;
      o.isy[a] = take ? s_y - h * v_y + hh * z_y : s_y;
      o.isz[a] = take ? s_z - h * v_z + hh * z_z : s_z;
      o.Fo[a] = take ? F + h * (Fp + h * (0.5 * Fpp + h * (Fppp / 6))) : F;
      o.status[a] = apart != 0 ? separated : conv != 0 ? converged : iterate;
      o.bisected[a] = (1 - apart) * (1 - conv) * (1 - inside);
      o.exhausted[a] = hi - lo <= 4 * std::numeric_limits<double>::epsilon() ? 1.0 : 0.0;
      pw.los[a] = lo, pw.his[a] = hi, o.next[a] = step;
    }
    retire_lanes(b, pw, o);
  }
}

// 3. Overlap and 4. effective radius (header comment) of the lanes with mu^2 < 1, in one loop.
// The results go straight to the batch's geometry slots, where the law's lanes read them.
[[gnu::always_inline]] inline void overlap_and_curvature(EllipsoidContactBatch& b, PwLanes& pw) {
  auto& o = b.geometry;
  const int f = b.first;
#pragma omp simd
  for (int a = 0; a < pw.no; ++a) {
    const Sym Qi{pw.c_Qi[0][a], pw.c_Qi[1][a], pw.c_Qi[2][a], pw.c_Qi[3][a], pw.c_Qi[4][a], pw.c_Qi[5][a]};
    const Sym Qj{pw.c_Qj[0][a], pw.c_Qj[1][a], pw.c_Qj[2][a], pw.c_Qj[3][a], pw.c_Qj[4][a], pw.c_Qj[5][a]};
    // M = Q^-1 through the adjugate of this very Q: the surfaces cut here are those the PW
    // iteration saw (to ~cond(Q) eps <= 9 eps).
    const Sym adj_i = Qi.adjugate(), adj_j = Qj.adjugate();
    const Sym Mi = adj_i * (1 / Qi.det_with(adj_i));
    const Sym Mj = adj_j * (1 / Qj.det_with(adj_j));
    const double s_x = pw.c_s[0][a], s_y = pw.c_s[1][a], s_z = pw.c_s[2][a], ln = pw.c_ln[a], lam = pw.c_lam[a];
    const double l_x = pw.c_l[0][a], l_y = pw.c_l[1][a], l_z = pw.c_l[2][a];
    // Products by components, as in the iteration loop above (and for the same reason).
    const double sn = std::sqrt(s_x * s_x + s_y * s_y + s_z * s_z);  // s = Q^-1 e: no underflow for tiny |l|
    const double inv_sn = 1 / sn;
    const double n_x = sn > 0 ? s_x * inv_sn : 0, n_y = sn > 0 ? s_y * inv_sn : 0, n_z = sn > 0 ? s_z * inv_sn : 1;
    const double S_x = s_x * ln, S_y = s_y * ln, S_z = s_z * ln;  // Q^-1 l
    // The line x0 + t n through the one point x0, cut by each surface.
    const double k0 = 1 - lam;
    const double di_x = k0 * (Qi.xx * S_x + Qi.xy * S_y + Qi.xz * S_z);  // x0 - c_i
    const double di_y = k0 * (Qi.xy * S_x + Qi.yy * S_y + Qi.yz * S_z);
    const double di_z = k0 * (Qi.xz * S_x + Qi.yz * S_y + Qi.zz * S_z);
    const double dj_x = di_x - l_x, dj_y = di_y - l_y, dj_z = di_z - l_z;  // x0 - c_j
    const double Mdi_x = Mi.xx * di_x + Mi.xy * di_y + Mi.xz * di_z;
    const double Mdi_y = Mi.xy * di_x + Mi.yy * di_y + Mi.yz * di_z;
    const double Mdi_z = Mi.xz * di_x + Mi.yz * di_y + Mi.zz * di_z;
    const double Mdj_x = Mj.xx * dj_x + Mj.xy * dj_y + Mj.xz * dj_z;
    const double Mdj_y = Mj.xy * dj_x + Mj.yy * dj_y + Mj.yz * dj_z;
    const double Mdj_z = Mj.xz * dj_x + Mj.yz * dj_y + Mj.zz * dj_z;
    const double wi_x = Mi.xx * n_x + Mi.xy * n_y + Mi.xz * n_z;
    const double wi_y = Mi.xy * n_x + Mi.yy * n_y + Mi.yz * n_z;
    const double wi_z = Mi.xz * n_x + Mi.yz * n_y + Mi.zz * n_z;
    const double wj_x = Mj.xx * n_x + Mj.xy * n_y + Mj.xz * n_z;
    const double wj_y = Mj.xy * n_x + Mj.yy * n_y + Mj.yz * n_z;
    const double wj_z = Mj.xz * n_x + Mj.yz * n_y + Mj.zz * n_z;
    const double ti = far_root(n_x * wi_x + n_y * wi_y + n_z * wi_z, n_x * Mdi_x + n_y * Mdi_y + n_z * Mdi_z,
                               di_x * Mdi_x + di_y * Mdi_y + di_z * Mdi_z - 1);  // along +n
    const double tj = far_root(n_x * wj_x + n_y * wj_y + n_z * wj_z, -(n_x * Mdj_x + n_y * Mdj_y + n_z * Mdj_z),
                               dj_x * Mdj_x + dj_y * Mdj_y + dj_z * Mdj_z - 1);  // along -n
    const double half = 0.5 * (ti - tj);
    const double ai_x = di_x + half * n_x, ai_y = di_y + half * n_y, ai_z = di_z + half * n_z;
    o.nx[f + a] = n_x, o.ny[f + a] = n_y, o.nz[f + a] = n_z;
    o.overlap[f + a] = ti + tj;
    o.aix[f + a] = ai_x, o.aiy[f + a] = ai_y, o.aiz[f + a] = ai_z;
    o.ajx[f + a] = ai_x - l_x, o.ajy[f + a] = ai_y - l_y, o.ajz[f + a] = ai_z - l_z;
    // 4. in the header comment: |M_i (p_i - c_i)|, |M_j (p_j - c_j)|, and adj(c A) = c^2 adj(A):
    // M_i/g_i + M_j/g_j scaled by g_i g_j to save two divisions.
    const double pi_x = Mdi_x + ti * wi_x, pi_y = Mdi_y + ti * wi_y, pi_z = Mdi_z + ti * wi_z;
    const double pj_x = Mdj_x - tj * wj_x, pj_y = Mdj_y - tj * wj_y, pj_z = Mdj_z - tj * wj_z;
    const double gi = std::sqrt(pi_x * pi_x + pi_y * pi_y + pi_z * pi_z);
    const double gj = std::sqrt(pj_x * pj_x + pj_y * pj_y + pj_z * pj_z);
    const Sym A = (Mi * gj + Mj * gi).adjugate();
    const double nAn = n_x * (A.xx * n_x + A.xy * n_y + A.xz * n_z) + n_y * (A.xy * n_x + A.yy * n_y + A.yz * n_z) +
                       n_z * (A.xz * n_x + A.yz * n_y + A.zz * n_z);
    o.radius[f + a] = gi * gj / std::sqrt(nAn);
  }
  for (int a = 0; a < pw.no; ++a) {
    const int k = pw.ov[a];
    b.touching[k] = o.overlap[f + a] > 0;  // not when mu^2 is within round-off of 1
    b.slot[k] = f + a;
  }
}

}  // namespace

// The batch, in three phases (above). Each lane's arithmetic is the same sequence as for a lone
// pair. Three builds of the batch, chosen at load time by the CPU: eight lanes per instruction
// with AVX-512, four with AVX2, two with the x86-64 baseline (SSE2). None uses FMA, so all give
// the same bits.
QSDEM_CLONES_WIDE void ellipsoid_contacts(EllipsoidContactBatch& b) {
  PwLanes w;
  reject_or_start(b, w);
  iterate_lanes(b, w);
  overlap_and_curvature(b, w);
}

int EllipsoidContactBatch::add(const Vec3& branch, const EllipsoidShape& si, const EllipsoidShape& sj,
                               double warm_start) {
  l[size] = branch;
  shape_i[size] = &si;
  shape_j[size] = &sj;
  // The shapes are read when the batch runs: j's (one cache line) is often not in the cache.
  __builtin_prefetch(&sj);
  lambda[size] = warm_start;
  return size++;
}

bool ellipsoid_contact(const Vec3& l, const Vec3& axes_i, const Quat& q_i, const Vec3& axes_j, const Quat& q_j,
                       double& lambda, ContactGeometry& g) {
  EllipsoidContactStats stats;
  return ellipsoid_contact(l, axes_i, q_i, axes_j, q_j, lambda, g, stats);
}

}  // namespace qsdem
