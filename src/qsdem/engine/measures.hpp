// The measures of SPEC 7, evaluated at sample points from the last force evaluation.
#pragma once
#include <concepts>
#include <limits>

#include "qsdem/engine/model.hpp"
#include "qsdem/engine/state.hpp"

namespace qsdem {

struct Measures {
  Mat3 stress = Mat3::Zero();  // compression positive (Pa)
  Vec3 principal = Vec3::Zero();  // s1 >= s2 >= s3 (Pa)
  double mean_stress = 0;      // p = tr(sigma)/3 (Pa)
  double deviator = 0;         // q = sqrt(3 J2) (Pa); = s1 - s3 under axisymmetry
  double octahedral = 0;       // sigma_oct = sqrt(s1^2+s2^2+s3^2)/sqrt(3) (paper Eq. 5)
  double friction_angle_deg = 0;  // asin((s1 - s3)/(s1 + s3))
  double friction_angle_al_deg = 0;  // axial-lateral: asin((s33 - sl)/(s33 + sl)), sl = (s11 + s22)/2
  double principal_tilt_deg = 0;  // angle between the direction of s1 and the x3 axis
  double ufr = 0;              // paper Eq. 3
  double iuf = 0;              // paper Eq. 2
  double imom = 0;             // paper Eq. 4
  long contacts = 0;           // n_c: pairs with delta > 0
  double coordination = 0;     // 2 n_c / n_p
  double ekin_trans = 0, ekin_rot = 0;  // fluctuation kinetic energy (J)
  double volume = 0;           // V (m^3)
  double solid_volume = 0;     // sum of particle volumes (m^3)
  double void_ratio = 0;       // (V - V_s)/V_s
  // Fabric (SPEC 7.1), NaN where undefined (no contact, no particle of the kind). n the unit normal
  // of a contact, f_n = F . n its normal force, <.> the mean over the n_c contacts.
  static constexpr double undefined = std::numeric_limits<double>::quiet_NaN();
  Mat3 fabric = Mat3::Constant(undefined);  // phi = <n n^T> (Satake 1982, Oda 1982)
  double fabric_major = undefined;          // its largest eigenvalue
  double fabric_tilt_deg = undefined;       // angle between its major direction and x3
  double fabric_dev = undefined;            // sqrt(3/2 phi'_ij phi'_ij)
  double fabric_strong_33 = undefined, fabric_strong_dev = undefined;  // contacts with f_n > <f_n>
  double fabric_weak_33 = undefined, fabric_weak_dev = undefined;      // f_n <= <f_n> (Radjai et al. 1998)
  double strong_fraction = undefined;       // share of the contacts in the strong network
  double fabric_force_33 = undefined, fabric_force_dev = undefined;  // sum f_n n n^T / sum f_n
  double orient_33 = undefined, orient_dev = undefined;  // <a a^T>, a the major axis of a particle with a > b
  double z_mech = undefined;                // (2 n_c - N_1) / (n_p - N_0 - N_1) (Thornton 2000)
};

Measures measure(const State& state);

// Every member of Measures by name, in declaration order: f(name, value), value a Mat3&, Vec3&,
// double& or the long& of `contacts`. The one list of them: a checkpoint saves a phase's last
// measures by name through it (run_progress.hpp), and the Python module's measures dict is made
// from it, so a new member costs one line here; a test checks that it covers Measures.
template <class M, class F>
  requires std::same_as<std::remove_const_t<M>, Measures>
void for_each_measure(M& m, F&& f) {
  f("stress", m.stress);
  f("principal", m.principal);
  f("mean_stress", m.mean_stress);
  f("deviator", m.deviator);
  f("octahedral", m.octahedral);
  f("friction_angle_deg", m.friction_angle_deg);
  f("friction_angle_al_deg", m.friction_angle_al_deg);
  f("principal_tilt_deg", m.principal_tilt_deg);
  f("ufr", m.ufr);
  f("iuf", m.iuf);
  f("imom", m.imom);
  f("contacts", m.contacts);
  f("coordination", m.coordination);
  f("ekin_trans", m.ekin_trans);
  f("ekin_rot", m.ekin_rot);
  f("volume", m.volume);
  f("solid_volume", m.solid_volume);
  f("void_ratio", m.void_ratio);
  f("fabric", m.fabric);
  f("fabric_major", m.fabric_major);
  f("fabric_tilt_deg", m.fabric_tilt_deg);
  f("fabric_dev", m.fabric_dev);
  f("fabric_strong_33", m.fabric_strong_33);
  f("fabric_strong_dev", m.fabric_strong_dev);
  f("fabric_weak_33", m.fabric_weak_33);
  f("fabric_weak_dev", m.fabric_weak_dev);
  f("strong_fraction", m.strong_fraction);
  f("fabric_force_33", m.fabric_force_33);
  f("fabric_force_dev", m.fabric_force_dev);
  f("orient_33", m.orient_33);
  f("orient_dev", m.orient_dev);
  f("z_mech", m.z_mech);
}

// The deviatoric invariant sqrt(3/2 phi'_ij phi'_ij), phi' = phi - tr(phi)/3 I, of a fabric tensor
// (SPEC 7.1): phi_1 - phi_3 when two principal values are equal, as q of the stress.
double fabric_deviator(const Mat3& phi);

// The size classes of a sample: its distinct equal-volume radii R_i (SPEC 2), ascending; radii
// within a relative 1e-9 of a class's smallest are in that class (the rows of a size table give equal radii
// bit for bit; a packing read from a file may round them).
std::vector<double> size_classes(const Particles& particles);

// The measures of one size class at a sample point (docs/physics.md 10.3), from the last force evaluation.
struct ClassMeasures {
  double radius = 0;             // the class's equal-volume radius (m)
  long count = 0;                // its particles
  double contacts = 0;           // mean contacts per particle (pairs with delta > 0 it is in)
  double in_contact = 0;         // fraction of its particles with >= 1 contact
  double in_contact_2 = 0;       // with >= 2
  double stress_share = 0;       // share of p carried by its contacts (a mixed contact: half each)
  double speed = 0;              // mean |v_i|, the fluctuation velocity (m/s)
  double spin = 0;               // mean |omega_i| (1/s)
};

// One entry per class of `classes` (size_classes): O(N + pairs), serial, in particle and pair order.
std::vector<ClassMeasures> class_measures(const State& state, const std::vector<double>& classes);

// Sum of a per-index term in fixed blocks, so the result does not depend on the thread count.
template <class T, class Term>
T blocked_sum(std::size_t n, const T& zero, Term term) {
  constexpr std::size_t block = 2048;
  const std::size_t nb = (n + block - 1) / block;
  std::vector<T> partial(nb, zero);
#pragma omp parallel for schedule(static) if (nb > 1)
  for (std::size_t b = 0; b < nb; ++b) {
    T acc = zero;
    const std::size_t end = std::min(n, (b + 1) * block);
    for (std::size_t k = b * block; k < end; ++k) acc += term(k);
    partial[b] = acc;
  }
  T total = zero;
  for (const T& x : partial) total += x;
  return total;
}

}  // namespace qsdem
