#include "qsdem/engine/measures.hpp"

#include <Eigen/Eigenvalues>
#include <algorithm>
#include <cmath>
#include <stdexcept>
#include <tuple>
#include <utility>

#include "qsdem/engine/forces.hpp"

namespace qsdem {

namespace {

using Vec6 = Eigen::Matrix<double, 6, 1>;

// The entries xx, yy, zz, xy, xz, yz of w d d^T.
Vec6 dyad(const Vec3& d, double w) {
  Vec6 r;
  r << w * d.x() * d.x(), w * d.y() * d.y(), w * d.z() * d.z(), w * d.x() * d.y(), w * d.x() * d.z(), w * d.y() * d.z();
  return r;
}

// The symmetric tensor of the entries e (as dyad's) over `total`.
Mat3 tensor(const Vec6& e, double total) {
  Mat3 t;
  t << e[0], e[3], e[4], e[3], e[1], e[5], e[4], e[5], e[2];
  return t / total;
}

// Q = R diag(a^2, b^2, c^2) R^T (SPEC 4.3).
Mat3 shape_matrix(const Vec3& axes, const Quat& q) {
  const Mat3 r = q.toRotationMatrix();
  return r * axes.cwiseProduct(axes).asDiagonal() * r.transpose();
}

// The unit normal, from i to j, of listed pair k at the current positions: l/|l| for two spheres
// (SPEC 4.2), otherwise the Perram-Wertheim normal Q(lambda)^-1 l / |Q(lambda)^-1 l| (SPEC 4.5) at the
// pair's lambda, the maximiser the last force evaluation found (4.9), or without one the cold start of 4.4.
Vec3 contact_normal(const State& st, std::size_t k) {
  const Particles& p = st.particles;
  const std::uint32_t i = st.pairs.i[k], j = st.pairs.j[k];
  const Vec3 l = branch_vector(st.cell, p.s[i], p.s[j], st.pairs.image[k]);
  if (!(l.squaredNorm() > 0)) return Vec3::UnitZ();  // coincident centres, as sphere_sphere
  if (p.shape[i] == ShapeKind::sphere && p.shape[j] == ShapeKind::sphere) return l.normalized();
  const Mat3 qi = shape_matrix(p.semi_axes[i], p.q[i]), qj = shape_matrix(p.semi_axes[j], p.q[j]);
  double lambda = st.pairs.pw_lambda[k];
  if (!(lambda > 0 && lambda < 1)) {
    const Vec3 e = l.normalized();
    const double hi = std::sqrt(e.dot(qi * e)), hj = std::sqrt(e.dot(qj * e));
    lambda = hi / (hi + hj);
  }
  return ((1 - lambda) * qi + lambda * qj).ldlt().solve(l).normalized();
}

// fabric_deviator and the 33 entry of a network's tensor, NaN for an empty network.
std::pair<double, double> network(const Vec6& e, double total) {
  if (!(total > 0)) return {Measures::undefined, Measures::undefined};
  const Mat3 t = tensor(e, total);
  return {fabric_deviator(t), t(2, 2)};
}

// The contact fabrics of SPEC 7.1 from the contact forces by pair: phi over all contacts, over the
// strong and the weak network, and weighted by f_n. Per pair in parallel, summed in fixed blocks.
// The normals and f_n are kept per contact, numbered in pair order: most pairs of a list are not
// contacts, and these arrays set the peak memory of a large run.
void contact_fabric(const State& state, const ContactForceByPair& force, Measures& m) {
  const PairList& pairs = state.pairs;
  const std::size_t np = pairs.size();
  constexpr std::uint32_t none = ~0u;
  std::vector<std::uint32_t> ordinal(np, none);  // of the pairs with overlap > 0, in pair order
  std::uint32_t nc = 0;
  for (std::size_t k = 0; k < np; ++k)
    if (pairs.overlap[k] > 0) ordinal[k] = nc++;
  std::vector<Vec3> normal(nc);
  std::vector<double> fn(nc);
#pragma omp parallel for schedule(static) if (np > parallel_threshold)
  for (std::size_t k = 0; k < np; ++k) {
    if (ordinal[k] == none) continue;
    normal[ordinal[k]] = contact_normal(state, k);
    fn[ordinal[k]] = force[k].dot(normal[ordinal[k]]);  // F on j, n from i to j: compression positive
  }
  using Sums = Eigen::Matrix<double, 27, 1>;  // all, strong, weak, f_n-weighted (6 each); n_c, n_strong, sum f_n
  const Vec3 counts = blocked_sum<Vec3>(np, Vec3::Zero(), [&](std::size_t k) {
    return pairs.overlap[k] > 0 ? Vec3(1.0, fn[ordinal[k]], 0.0) : Vec3(Vec3::Zero());
  });
  if (!(counts[0] > 0)) return;
  const double mean_fn = counts[1] / counts[0];
  const Sums s = blocked_sum<Sums>(np, Sums::Zero(), [&](std::size_t k) {
    Sums r = Sums::Zero();
    if (pairs.overlap[k] <= 0) return r;
    const double f = fn[ordinal[k]];
    const Vec6 d = dyad(normal[ordinal[k]], 1.0);
    const bool strong = f > mean_fn;  // Radjai et al. (1998): strong above the mean, weak the rest
    r.segment<6>(0) = d;
    r.segment<6>(strong ? 6 : 12) = d;
    r.segment<6>(18) = f * d;
    r[24] = 1, r[25] = strong ? 1 : 0, r[26] = f;
    return r;
  });
  m.fabric = tensor(s.segment<6>(0), s[24]);
  m.fabric_dev = fabric_deviator(m.fabric);
  const Eigen::SelfAdjointEigenSolver<Mat3> eig(m.fabric);  // ascending
  m.fabric_major = eig.eigenvalues()[2];
  m.fabric_tilt_deg = std::acos(std::min(1.0, std::abs(eig.eigenvectors()(2, 2)))) * 180 / pi;
  std::tie(m.fabric_strong_dev, m.fabric_strong_33) = network(s.segment<6>(6), s[25]);
  std::tie(m.fabric_weak_dev, m.fabric_weak_33) = network(s.segment<6>(12), s[24] - s[25]);
  std::tie(m.fabric_force_dev, m.fabric_force_33) = network(s.segment<6>(18), s[26]);
  m.strong_fraction = s[25] / s[24];
}

// <a a^T> over the particles with a > b (their major axis is defined; SPEC 7.1), a = R e_x.
void orientation_fabric(const Particles& p, Measures& m) {
  using Sums = Eigen::Matrix<double, 7, 1>;
  const Sums s = blocked_sum<Sums>(p.size(), Sums::Zero(), [&](std::size_t i) {
    Sums r = Sums::Zero();
    if (!(p.semi_axes[i].x() > p.semi_axes[i].y() * (1 + 1e-9))) return r;  // a = b within rounding: no axis
    r.head<6>() = dyad(p.q[i] * Vec3::UnitX(), 1.0);
    r[6] = 1;
    return r;
  });
  std::tie(m.orient_dev, m.orient_33) = network(s.head<6>(), s[6]);
}

// Z_m = (2 n_c - N_1) / (n_p - N_0 - N_1), N_k the particles with k contacts (Thornton 2000):
// the rattlers with no or one contact left out. Serial, in pair order.
double mechanical_coordination(const State& state) {
  const PairList& pairs = state.pairs;
  std::vector<std::uint32_t> contacts(state.particles.size(), 0);
  long nc = 0;
  for (std::size_t k = 0; k < pairs.size(); ++k)
    if (pairs.overlap[k] > 0) ++contacts[pairs.i[k]], ++contacts[pairs.j[k]], ++nc;
  long n0 = 0, n1 = 0;
  for (const std::uint32_t c : contacts) n0 += c == 0, n1 += c == 1;
  const long rest = static_cast<long>(contacts.size()) - n0 - n1;
  return rest > 0 ? static_cast<double>(2 * nc - n1) / static_cast<double>(rest) : Measures::undefined;
}

}  // namespace

double fabric_deviator(const Mat3& phi) {
  const Mat3 dev = phi - phi.trace() / 3 * Mat3::Identity();
  return std::sqrt(1.5 * dev.squaredNorm());  // squaredNorm: phi'_ij phi'_ij
}

Measures measure(const State& state) {
  const Particles& p = state.particles;
  const PairList& pairs = state.pairs;
  Measures m;
  m.stress = state.stress;
  m.volume = state.stress_volume;

  Eigen::SelfAdjointEigenSolver<Mat3> eig(m.stress, Eigen::EigenvaluesOnly);
  const Vec3 ev = eig.eigenvalues();  // ascending
  m.principal = Vec3(ev[2], ev[1], ev[0]);
  const double s1 = m.principal[0], s2 = m.principal[1], s3 = m.principal[2];
  m.mean_stress = (s1 + s2 + s3) / 3;
  m.deviator = std::sqrt(0.5 * ((s1 - s2) * (s1 - s2) + (s2 - s3) * (s2 - s3) + (s3 - s1) * (s3 - s1)));
  m.octahedral = m.principal.norm() / std::sqrt(3.0);  // paper Eq. 5
  m.friction_angle_deg = (s1 + s3) > 0 ? std::asin((s1 - s3) / (s1 + s3)) * 180 / pi : 0;
  // The axial-lateral angle and the tilt of the principal frame (SPEC 7): they differ from phi and
  // 0 when the cell's shear stresses are not zero. (A second solve, so that the eigenvalues above
  // keep the bits of the values-only solver.)
  const double axial = m.stress(2, 2), lateral = 0.5 * (m.stress(0, 0) + m.stress(1, 1));
  m.friction_angle_al_deg = (axial + lateral) > 0 ? std::asin((axial - lateral) / (axial + lateral)) * 180 / pi : 0;
  const Eigen::SelfAdjointEigenSolver<Mat3> frame(m.stress);
  m.principal_tilt_deg = std::acos(std::min(1.0, std::abs(frame.eigenvectors()(2, 2)))) * 180 / pi;

  // Contact sums: n_c, sum |f_c|, sum |f_c|^2, in pair order (for any thread count).
  const ContactForceByPair force(state);
  const Vec3 c = blocked_sum<Vec3>(pairs.size(), Vec3::Zero(), [&](std::size_t k) {
    if (pairs.overlap[k] <= 0) return Vec3(Vec3::Zero());
    const double f2 = force[k].squaredNorm();
    return Vec3(1.0, std::sqrt(f2), f2);
  });
  // Particle sums: |f_p|, |f_p|^2, |M_p|, kinetic energies, solid volume.
  using Vec6 = Eigen::Matrix<double, 6, 1>;
  const Vec6 s = blocked_sum<Vec6>(p.size(), Vec6::Zero(), [&](std::size_t i) {
    Vec6 r;
    const double f2 = p.force[i].squaredNorm();
    r << std::sqrt(f2), f2, p.torque[i].norm(), 0.5 * p.mass[i] * p.v[i].squaredNorm(),
        0.5 * p.angmom[i].dot(p.omega[i]), ellipsoid_volume(p.semi_axes[i]);
    return r;
  });
  const double np = static_cast<double>(p.size());
  m.contacts = static_cast<long>(c[0]);
  m.coordination = np > 0 ? 2 * c[0] / np : 0;
  if (c[0] > 0) {
    m.ufr = (s[0] / np) / (c[1] / c[0]);                        // paper Eq. 3
    m.iuf = std::sqrt(s[1] / np) / std::sqrt(c[2] / c[0]);      // paper Eq. 2
  }
  if (m.octahedral > 0) m.imom = s[2] / (m.volume * m.octahedral);  // paper Eq. 4
  m.ekin_trans = s[3];
  m.ekin_rot = s[4];
  m.solid_volume = s[5];
  m.void_ratio = (m.volume - m.solid_volume) / m.solid_volume;
  contact_fabric(state, force, m);  // SPEC 7.1
  orientation_fabric(p, m);
  m.z_mech = mechanical_coordination(state);
  return m;
}

std::vector<double> size_classes(const Particles& particles) {
  std::vector<double> r(particles.equiv_radius);
  std::sort(r.begin(), r.end());
  std::vector<double> classes;
  for (double x : r)
    if (classes.empty() || x > classes.back() * (1 + 1e-9)) classes.push_back(x);
  return classes;
}

std::vector<ClassMeasures> class_measures(const State& state, const std::vector<double>& classes) {
  const Particles& p = state.particles;
  const PairList& pairs = state.pairs;
  const std::size_t n = p.size();
  std::vector<std::uint32_t> of(n);  // the class of each particle
  for (std::size_t i = 0; i < n; ++i) {
    // The last class whose first radius is <= R_i (size_classes: the class of R_i).
    const auto c = std::upper_bound(classes.begin(), classes.end(), p.equiv_radius[i]);
    if (c == classes.begin()) throw std::logic_error("class_measures: a particle outside the size classes");
    of[i] = static_cast<std::uint32_t>(c - classes.begin() - 1);
  }
  std::vector<ClassMeasures> out(classes.size());
  for (std::size_t c = 0; c < classes.size(); ++c) out[c].radius = classes[c];
  // Per contact: its ends' contact counts, and f_c . l_c (3 V its share of p, SPEC 7's
  // Love-Weber sum), half to each end's class.
  std::vector<std::uint32_t> contacts(n, 0);
  const ContactForceByPair force(state);
  double total = 0;
  for (std::size_t k = 0; k < pairs.size(); ++k) {
    if (pairs.overlap[k] <= 0) continue;
    const std::uint32_t i = pairs.i[k], j = pairs.j[k];
    ++contacts[i];
    ++contacts[j];
    const double w = force[k].dot(branch_vector(state.cell, p.s[i], p.s[j], pairs.image[k]));
    out[of[i]].stress_share += 0.5 * w;
    out[of[j]].stress_share += 0.5 * w;
    total += w;
  }
  for (std::size_t i = 0; i < n; ++i) {
    ClassMeasures& c = out[of[i]];
    ++c.count;
    c.contacts += contacts[i];
    c.in_contact += contacts[i] >= 1 ? 1 : 0;
    c.in_contact_2 += contacts[i] >= 2 ? 1 : 0;
    c.speed += p.v[i].norm();
    c.spin += p.omega[i].norm();
  }
  for (ClassMeasures& c : out) {
    const double count = static_cast<double>(std::max(1L, c.count));
    c.contacts /= count;
    c.in_contact /= count;
    c.in_contact_2 /= count;
    c.speed /= count;
    c.spin /= count;
    c.stress_share = total != 0 ? c.stress_share / total : 0;
  }
  return out;
}

}  // namespace qsdem
