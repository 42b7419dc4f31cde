#include "qsdem/measures.hpp"

#include <Eigen/Eigenvalues>
#include <algorithm>
#include <cmath>
#include <stdexcept>

#include "qsdem/forces.hpp"

namespace qsdem {

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
  const std::vector<Vec3> force = contact_forces_by_pair(state);
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
  const std::vector<Vec3> force = contact_forces_by_pair(state);
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
