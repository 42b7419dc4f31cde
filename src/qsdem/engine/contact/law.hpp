// What a contact law is (the pattern of HOOMD-blue's pair evaluators and of LAMMPS GRANULAR's
// sub-models): a small struct on which the force stage's one pair driver (forces.cpp) and the
// reference force stage (tests/support/reference_forces.cpp) are instantiated. contact/hertz_mindlin.hpp is the
// documented example; contact/laws.hpp registers the laws. A law declares
//
//   static constexpr std::string_view name;        its value of the case key [contact] law
//   static constexpr HistoryLayout history;        its per-contact history (below), or a reference
//                                                  to another law's, to share it
//   static constexpr bool needs_masses;            it reads ContactInput::mass
//   static constexpr bool needs_spins;             it reads ContactInput::wx, wy, wz
//   static constexpr bool has_torque;              it returns a torque besides arm x force
//   static constexpr bool has_dashpots;            it returns viscous coefficients (cn, ct)
//   static constexpr std::array<LawKey, N> keys;   its own keys in [contact] (below)
//   static std::string check(const ContactSettings&, std::string& key);  what is wrong, "" if
//                                                  nothing (key: the key to name)
//   static Law make(const LawConstants&);          the law of a phase
//   void evaluate(const ContactInput&, double dt, HistoryView history, ContactOutput&) const;
//
// evaluate runs in vector lanes, one contact per lane: it must be inline, branch-free (selects),
// and sum in a fixed order (the same bits on every build). `history` holds the contact's
// history.width values, read and updated in place. The pair list keeps the history, transfers it
// across list rebuilds, applies the swap rules when a reorder exchanges a pair's ends and the
// released values when the contact is lost, and the checkpoint saves it under its name
// (neighbor.hpp, the pair registry).
#pragma once
#include <array>
#include <cstdint>
#include <string>
#include <string_view>

#include "qsdem/engine/contact/geometry.hpp"
#include "qsdem/engine/types.hpp"

namespace qsdem {

inline constexpr int max_history_width = 8;

// What exchanging the two ends of a pair (i <-> j, when a reorder renumbers them) does to a value.
enum class OnSwap : std::uint8_t {
  keep,         // a scalar of the pair
  negate,       // a component of a vector on j (it becomes the vector on the other end)
  mirror_unit,  // a weight of j's side in (0, 1): x -> 1 - x (other values are kept)
};

// A per-pair array of `width` doubles per pair, as the pair list keeps it (neighbor.hpp): a law's
// contact history, and the narrow phase's and the skip's state.
struct HistoryLayout {
  std::string_view name;  // what the values are; two laws with one name share their history
  int width = 0;          // doubles per pair
  std::array<double, max_history_width> released{};  // the values of a pair new to the list, or
                                                     // of a contact that is lost
  std::array<OnSwap, max_history_width> on_swap{};
};

// A contact's history values, read and written in place: value m is at values[m * stride] (the
// driver's lanes keep each value in its own array, one contact per lane).
struct HistoryView {
  double* values;
  int stride = 1;
  [[gnu::always_inline]] double& operator[](int m) const { return values[m * stride]; }
};

// One contact, by components (vector lanes): what the driver gives the law.
struct ContactInput {
  double nx, ny, nz;   // unit normal, from i towards j
  double overlap;      // delta > 0 (m)
  double radius;       // effective radius R_e (m): R1 R2 / (R1 + R2) for spheres, the Gaussian
                       // curvature radius of the relative curvature for ellipsoids (SPEC 4)
  double vx, vy, vz;   // velocity of j's material point at the contact relative to i's (m/s),
                       // including the affine field's part L l (SPEC 3)
  double wx, wy, wz;   // w_j - w_i (rad/s), for laws with needs_spins (else 0)
  double mass;         // m* = m_i m_j / (m_i + m_j) (kg), for laws with needs_masses (else 0)
  double previous_overlap;  // delta at the pair's last force evaluation, 0 for a new contact (m): for
                            // stiffness_work, given only when the run keeps its energy (else 0)
};

// What the law returns for one contact.
struct ContactOutput {
  double fx, fy, fz;  // force on j (N); i receives the opposite
  double tx, ty, tz;  // torque on j besides arm_j x f (N m), laws with has_torque; i receives the
                      // opposite
  double kn, kt;      // normal and tangential stiffness (N/m): the servo's affine stiffness
  double cn, ct;      // normal and tangential viscous coefficient (N s/m) of the contact's force,
                      // laws with has_dashpots: the servo's affine viscosity
  double energy;      // elastic energy stored in the contact (J)
  double slip_work;   // energy the Coulomb sliding of this step dissipated (J): the capped force
                      // times the slip, mu F_n (|F_t trial| - mu F_n) / k_t
  double viscous_work;  // energy the contact's dashpots dissipated in this step (J), laws with
                        // has_dashpots (else 0)
  double stiffness_work;  // change of the stored energy in this step that no force's work made (J):
                          // an incremental law whose stiffness follows the overlap (0 if none)
};

// What every law is made from: the material's contact constants (SPEC 4), the phase's friction
// and the law's own keys.
struct LawConstants {
  double effective_modulus;        // E* = E / (2 (1 - nu^2))
  double effective_shear_modulus;  // G* = G / (2 (2 - nu))
  double friction;                 // mu
  const ContactSettings& settings;
};

// One of a law's own keys in [contact]: a ratio (a number, or "x %"), checked by the law's check.
struct LawKey {
  std::string_view name;
  std::string_view meaning;
};

// One contact of `law` outside the driver (the reference force stage, tests): the geometry, the
// relative velocity v at the contact (SPEC 3), the relative spin w_j - w_i, the effective mass,
// and the law's history (in/out).
template <class Law>
ContactOutput evaluate_contact(const Law& law, const ContactGeometry& g, const Vec3& v, const Vec3& spin, double mass,
                               double dt, double* history) {
  const ContactInput in{g.normal.x(), g.normal.y(), g.normal.z(), g.overlap, g.radius, v.x(),  v.y(),
                        v.z(),        spin.x(),     spin.y(),     spin.z(),  mass,     0.0};
  ContactOutput out;
  law.evaluate(in, dt, HistoryView{history}, out);
  return out;
}

}  // namespace qsdem
