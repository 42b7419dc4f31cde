// Hertz-Mindlin with Coulomb friction (SPEC 4), the paper's contact law and the documented example
// of a contact law (contact/law.hpp).
//
//   Inputs (ContactInput)
//     n             unit normal, from particle i towards particle j
//     delta         overlap > 0 (m)
//     R_e           effective radius (m)
//     v             velocity of j's material point at the contact relative to i's (m/s)
//     dt            time step (s)
//   History (3 doubles, "tangential_force")
//     F_t           the stored tangential force on j (N). An i/j swap negates it (it becomes the
//                   force on the other end); a lost contact releases it (0).
//   Law
//     contact radius a = sqrt(R_e delta)
//     normal force   F_n = 4/3 E* sqrt(R_e) delta^(3/2) = 4/3 E* a delta      (Hertz)
//     normal stiffness k_n = dF_n/ddelta = 2 E* a                              (for the servo)
//     tangential stiffness k_t = 8 G* a                                         (Mindlin, no slip)
//     the stored force is first turned into the new tangent plane keeping its magnitude (the
//     contact normal turns as particles move), then F_t <- F_t - k_t du_t with du_t = v_t dt,
//     then capped at |F_t| <= mu F_n (Coulomb sliding).
//   Output (ContactOutput)
//     force on j = F_n n + F_t (particle i receives the opposite), k_n and k_t, and the elastic
//     energy 2/5 F_n delta (= 8/15 E* sqrt(R_e) delta^(5/2), the integral of F_n) + |F_t|^2 / (2 k_t),
//     and the sliding's dissipation mu F_n (|F_t trial| - mu F_n) / k_t (the cap times the slip).
//     k_t follows the overlap while the turned F_t keeps its magnitude, so |F_t|^2 / (2 k_t)
//     changes by |F_t|^2 / 2 (1/k_t - 1/k_t,before) with no work done (stiffness_work; the
//     incremental Mindlin law is not conservative, Elata & Berryman, Mech. Mater. 24 (1996)).
//   No contact damping (the paper uses none), no masses, no spins, no torque of its own.
#pragma once
#include <array>
#include <cmath>
#include <span>
#include <string>
#include <string_view>

#include "qsdem/engine/contact/law.hpp"

namespace qsdem {

struct HertzMindlin {
  static constexpr std::string_view name = "hertz_mindlin";
  static constexpr HistoryLayout history{
      "tangential_force", 3, {0, 0, 0}, {OnSwap::negate, OnSwap::negate, OnSwap::negate}};
  static constexpr bool needs_masses = false, needs_spins = false, has_torque = false, has_dashpots = false;
  static constexpr std::array<LawKey, 0> keys{};
  static std::string check(const ContactSettings&, std::string&) { return {}; }
  static HertzMindlin make(const LawConstants& c) {
    return {c.effective_modulus, c.effective_shear_modulus, c.friction};
  }

  double effective_modulus;        // E* = E / (2 (1 - nu^2))
  double effective_shear_modulus;  // G* = G / (2 (2 - nu))
  double friction;                 // mu

  // The stored tangential force on j of a contact's history (N).
  static Vec3 tangential_force(std::span<const double> history) { return {history[0], history[1], history[2]}; }

  // The law on components, its branches as selects: the pair driver (forces.cpp) runs it on a
  // chunk of contacts in vector lanes (one contact's law is a long chain of dependent operations).
  // Each sum is in the order of Eigen's for 3-vectors (left to right), so a lane gives the bits of
  // a contact alone.
  [[gnu::always_inline]] inline void evaluate(const ContactInput& c, double dt, HistoryView shear,
                                              ContactOutput& out) const {
    const double a = std::sqrt(c.radius * c.overlap);
    const double fn = normal_force(a, c.overlap);
    out.kn = 2.0 * effective_modulus * a;
    out.kt = 8.0 * effective_shear_modulus * a;
    double sx = shear[0], sy = shear[1], sz = shear[2];
    out.stiffness_work = stiffness_work(c, out.kt, sx, sy, sz);
    turn_into_plane(c.nx, c.ny, c.nz, sx, sy, sz);
    add_tangential_spring(c, out.kt * dt, sx, sy, sz);
    out.slip_work = cap_by_friction(friction * fn, out.kt, sx, sy, sz);
    shear[0] = sx, shear[1] = sy, shear[2] = sz;
    out.fx = fn * c.nx + sx, out.fy = fn * c.ny + sy, out.fz = fn * c.nz + sz;
    out.tx = out.ty = out.tz = 0;
    out.cn = out.ct = 0;
    out.viscous_work = 0;
    out.energy = 0.4 * fn * c.overlap + ((sx * sx + sy * sy) + sz * sz) / (2 * out.kt);
  }

  // |F_t|^2 / 2 (1/k_t - 1/k_t,before) of the stored force F_t = s, k_t,before = 8 G* sqrt(R_e
  // delta_before) (the current R_e: exact for spheres); 0 for a new contact.
  [[gnu::always_inline]] inline double stiffness_work(const ContactInput& c, double kt, double sx, double sy,
                                                      double sz) const {
    const double before = 8.0 * effective_shear_modulus * std::sqrt(c.radius * c.previous_overlap);
    const double mag2 = (sx * sx + sy * sy) + sz * sz;
    return c.previous_overlap > 0 ? 0.5 * mag2 * (1 / kt - 1 / before) : 0.0;
  }

  // Hertz: F_n = 4/3 E* a delta, a = sqrt(R_e delta).
  [[gnu::always_inline]] inline double normal_force(double a, double overlap) const {
    return 4.0 / 3.0 * effective_modulus * a * overlap;
  }

  // Turns the stored tangential force into the current tangent plane (normal n), keeping its
  // magnitude.
  [[gnu::always_inline]] static inline void turn_into_plane(double nx, double ny, double nz, double& sx, double& sy,
                                                            double& sz) {
    const double old_mag2 = (sx * sx + sy * sy) + sz * sz;
    const double inv_old = 1 / old_mag2;  // off the chain below: shear is known before n
    const double sn = (sx * nx + sy * ny) + sz * nz;
    const double px = sx - sn * nx, py = sy - sn * ny, pz = sz - sn * nz;
    // |shear|^2 is now old (1 - x), x = (s.n)^2 / old (n unit), so the magnitude comes back by
    // (1 - x)^-1/2 = 1 + x/2 + 3x^2/8 + O(x^3): below x = 1e-6 (a quasi-static contact turns by
    // far less per step) the cut terms, 5x^3/16 + ..., are < 3.2e-19, under the rounding of the
    // direct form sqrt(old / new).
    const double x = sn * sn * inv_old;
    const double new_mag2 = (px * px + py * py) + pz * pz;
    const double root = std::sqrt(old_mag2 / new_mag2);  // in every lane, then a select
    const double direct = new_mag2 > 0 ? root : 1.0;
    const double back = x < 1e-6 ? 1 + x * (0.5 + 0.375 * x) : direct;
    const bool stored = old_mag2 > 0;  // no stored force: nothing to turn
    sx = stored ? px * back : sx, sy = stored ? py * back : sy, sz = stored ? pz * back : sz;
  }

  // F_t <- F_t - k_t du_t, du_t = v_t dt the tangential part of the relative displacement
  // (kdt = k_t dt).
  [[gnu::always_inline]] static inline void add_tangential_spring(const ContactInput& c, double kdt, double& sx,
                                                                  double& sy, double& sz) {
    const double vn = (c.vx * c.nx + c.vy * c.ny) + c.vz * c.nz;
    sx = sx - kdt * (c.vx - vn * c.nx), sy = sy - kdt * (c.vy - vn * c.ny), sz = sz - kdt * (c.vz - vn * c.nz);
  }

  // Coulomb: |F_t| <= cap (= mu F_n), by scaling F_t down to the cap when it is beyond. Returns
  // the energy the slip dissipates, cap (|F_t| - cap) / k_t (the slip is the spring's excess
  // stretch; 0 without sliding). A driver that does not read it pays nothing (inlined, unused).
  [[gnu::always_inline]] static inline double cap_by_friction(double cap, double kt, double& sx, double& sy,
                                                              double& sz) {
    const double mag2 = (sx * sx + sy * sy) + sz * sz;
    const double mag = std::sqrt(mag2);
    const double slide = cap / mag;
    const bool sliding = mag2 > cap * cap;
    sx = sliding ? sx * slide : sx, sy = sliding ? sy * slide : sy, sz = sliding ? sz * slide : sz;
    return sliding ? cap * (mag - cap) / kt : 0.0;
  }
};

}  // namespace qsdem
