// Hertz-Mindlin with rolling resistance (docs/physics.md 4.7.1): the elastic-plastic spring-dashpot
// rolling model, type C of Ai et al. (Powder Technol. 206, 2011, sec. 2.3), as LIGGGHTS'
// `rolling_friction epsd` and LAMMPS GRANULAR's `rolling sds` give it.
//
//   Inputs            Hertz-Mindlin's, plus the relative spin w = w_j - w_i and m*
//   History (6)       F_t, the stored tangential force on j (Hertz-Mindlin's), then M_r, the
//                     stored rolling moment on j (N m). An i/j swap negates both; a lost contact
//                     releases both (0).
//   Law               the forces of Hertz-Mindlin, and a rolling moment on j (i receives -M_r):
//     rolling stiffness   k_r = eta_k k_n R_e^2 (N m/rad), k_n = 2 E* a; eta_k = `rolling_stiffness`,
//                         by default Ai et al.'s 2.25 mu_r^2 (their Eq. 13, after Iwashita & Oda)
//     the spring          M_r turned into the tangent plane keeping its magnitude, then
//                         M_r <- M_r - k_r w_t dt, w_t = w - (w.n) n the rolling part of w (the
//                         twist about n is not resisted)
//     the slider          |M_r| <= mu_r R_e F_n (mu_r = `rolling_friction`); beyond, M_r is scaled
//                         to the cap (full mobilisation) and the slide dissipates
//                         mu_r R_e F_n (|M_r trial| - mu_r R_e F_n) / k_r
//     the dashpot         while not fully mobilised, M_d = -C_r w_t with C_r = 2 zeta_r sqrt(k_r I*),
//                         I* = m* R_e^2 (zeta_r = `rolling_damping_ratio`, default 0); off at full
//                         mobilisation (Ai et al.'s f = 0)
//   Output            torque on j M_r + M_d; Hertz-Mindlin's forces and stiffnesses; energy
//                     Hertz-Mindlin's + |M_r|^2 / (2 k_r); the slider's dissipation in slip_work
//                     with the Coulomb slip's, the dashpot's C_r |w_t|^2 dt in viscous_work, and the
//                     change of |M_r|^2 / (2 k_r) with k_r (k_r follows the overlap) in
//                     stiffness_work.
// I* = m* R_e^2 is the inertia the law knows (Ai et al.'s I_r, from each particle's inertia about
// the contact point, is 5.6 m* R_e^2 for two equal spheres): zeta_r is the damping ratio of the
// rolling spring on that inertia.
#pragma once
#include <array>
#include <cmath>
#include <string>
#include <string_view>

#include "qsdem/engine/contact/hertz_mindlin.hpp"

namespace qsdem {

struct HertzMindlinRolling {
  static constexpr std::string_view name = "hertz_mindlin_rolling";
  static constexpr HistoryLayout history{"tangential_force_rolling_moment",
                                         6,
                                         {0, 0, 0, 0, 0, 0},
                                         {OnSwap::negate, OnSwap::negate, OnSwap::negate, OnSwap::negate,
                                          OnSwap::negate, OnSwap::negate}};
  static constexpr bool needs_masses = true, needs_spins = true, has_torque = true, has_dashpots = false;
  static constexpr std::array<LawKey, 3> keys{
      {{"rolling_friction", "rolling friction coefficient mu_r in (0, 1]"},
       {"rolling_stiffness", "k_r / (k_n R_e^2) in (0, 100] (default 2.25 mu_r^2)"},
       {"rolling_damping_ratio", "damping ratio of the rolling dashpot in [0, 1) (default 0)"}}};

  static std::string check(const ContactSettings& s, std::string& key) {
    key = "rolling_friction";
    if (!s.has(key)) return "hertz_mindlin_rolling needs rolling_friction (mu_r in (0, 1])";
    if (const double v = s.value(key); !(v > 0 && v <= 1)) return "out of range: must be in (0, 1]";
    key = "rolling_stiffness";
    if (s.has(key))
      if (const double v = s.value(key); !(v > 0 && v <= 100)) return "out of range: must be in (0, 100]";
    key = "rolling_damping_ratio";
    if (s.has(key))
      if (const double v = s.value(key); !(v >= 0 && v < 1)) return "out of range: must be in [0, 1)";
    return {};
  }

  static HertzMindlinRolling make(const LawConstants& c) {
    std::string key;
    if (const std::string why = check(c.settings, key); !why.empty())
      throw InputError("[contact] " + key + ": " + why);
    const ContactSettings& s = c.settings;
    const double mu_r = s.value("rolling_friction");
    return {HertzMindlin::make(c), mu_r, s.has("rolling_stiffness") ? s.value("rolling_stiffness") : 2.25 * mu_r * mu_r,
            s.has("rolling_damping_ratio") ? s.value("rolling_damping_ratio") : 0.0};
  }

  HertzMindlin elastic;        // the forces and the tangential friction
  double rolling_friction;     // mu_r
  double rolling_stiffness;    // eta_k: k_r = eta_k k_n R_e^2
  double rolling_damping;      // zeta_r

  [[gnu::always_inline]] inline void evaluate(const ContactInput& c, double dt, HistoryView state,
                                              ContactOutput& out) const {
    elastic.evaluate(c, dt, state, out);
    const HistoryView moment{state.values + 3 * state.stride, state.stride};
    const double a = std::sqrt(c.radius * c.overlap);
    const double fn = elastic.normal_force(a, c.overlap);
    const double r2 = c.radius * c.radius;
    const double kr = rolling_stiffness * out.kn * r2;
    double mx = moment[0], my = moment[1], mz = moment[2];
    // |M_r|^2 / 2 (1/k_r - 1/k_r,before), k_r,before at the last evaluation's overlap (as F_t's).
    const double mag2 = (mx * mx + my * my) + mz * mz;
    const double kr_before = rolling_stiffness * 2.0 * elastic.effective_modulus * std::sqrt(c.radius * c.previous_overlap) * r2;
    out.stiffness_work += c.previous_overlap > 0 ? 0.5 * mag2 * (1 / kr - 1 / kr_before) : 0.0;
    HertzMindlin::turn_into_plane(c.nx, c.ny, c.nz, mx, my, mz);
    const double wn = (c.wx * c.nx + c.wy * c.ny) + c.wz * c.nz;
    const double wtx = c.wx - wn * c.nx, wty = c.wy - wn * c.ny, wtz = c.wz - wn * c.nz;
    const double krdt = kr * dt;
    mx = mx - krdt * wtx, my = my - krdt * wty, mz = mz - krdt * wtz;
    const double cap = rolling_friction * c.radius * fn;
    const bool mobilised = (mx * mx + my * my) + mz * mz > cap * cap;
    out.slip_work += HertzMindlin::cap_by_friction(cap, kr, mx, my, mz);
    moment[0] = mx, moment[1] = my, moment[2] = mz;
    const double damper = mobilised ? 0.0 : 2 * rolling_damping * std::sqrt(kr * c.mass * r2);
    out.tx = mx - damper * wtx, out.ty = my - damper * wty, out.tz = mz - damper * wtz;
    out.viscous_work += dt * damper * ((wtx * wtx + wty * wty) + wtz * wtz);
    out.energy += ((mx * mx + my * my) + mz * mz) / (2 * kr);
  }
};

}  // namespace qsdem
