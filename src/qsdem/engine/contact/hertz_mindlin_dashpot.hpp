// Hertz-Mindlin with viscous dashpots in the normal and the tangential direction (SPEC 6 `contact`):
// the viscoelastic Hertz law of LIGGGHTS (`gran model hertz`, src/normal_model_hertz.h, with
// `tangential history`) and of LAMMPS (`pair_style granular`, `hertz/material` with `damping
// coeff_restitution`, src/GRANULAR/gran_sub_mod_damping.cpp, whose normal coefficient is the same).
//
//   gamma_n = -2 sqrt(5/6) beta sqrt(S_n m*),  gamma_t = -2 sqrt(5/6) beta sqrt(S_t m*)   (>= 0)
//   S_n = 2 E* sqrt(R_e delta) = k_n,  S_t = 8 G* sqrt(R_e delta) = k_t,  m* = m_i m_j / (m_i + m_j)
//   beta = ln e / sqrt(ln^2 e + pi^2) from a restitution coefficient e in (0, 1] (key
//   `restitution`), or beta = -zeta from a damping ratio zeta in [0, 1) (key `damping_ratio`; the
//   two are the same model: zeta = -ln e / sqrt(ln^2 e + pi^2)).
//
//   normal force     F_n = 4/3 E* sqrt(R_e) delta^(3/2) - gamma_n v_n, v_n = v.n (< 0 closing).
//                    Not capped at 0 (LIGGGHTS' limitForce off): it turns slightly attractive at
//                    the end of an impact, and with it a head-on impact rebounds with exactly e
//                    at every speed (the damping scales as delta^(1/4): the impact's equation,
//                    x'' + sqrt(5) |beta| x^(1/4) x' + x^(3/2) = 0 in its own units, integrated
//                    numerically, gives e to 5e-7).
//   tangential force the spring F_s of Hertz-Mindlin (turned into the tangent plane, then
//                    F_s <- F_s - k_t v_t dt); when |F_s| > mu |F_n| it is scaled to mu |F_n| and
//                    the contact slides without dashpot, else F_t = F_s - gamma_t v_t (LIGGGHTS'
//                    tangential history model).
//   History          the spring F_s: Hertz-Mindlin's ("tangential_force"), so either law can
//                    follow the other.
//   Output           force on j = F_n n + F_t; k_n, k_t as Hertz-Mindlin; gamma_n, and gamma_t
//                    (0 when sliding) for the servo; elastic energy
//                    2/5 (4/3 E* sqrt(R_e) delta^(3/2)) delta + |F_s|^2 / (2 k_t).
// The dashpot forces are contact forces: they count in the stress, the resultants and the indices.
// e = 1 (or zeta = 0) gives Hertz-Mindlin's bits.
#pragma once
#include <array>
#include <cmath>
#include <string>
#include <string_view>

#include "qsdem/engine/contact/hertz_mindlin.hpp"

namespace qsdem {

struct HertzMindlinDashpot {
  static constexpr std::string_view name = "hertz_mindlin_dashpot";
  static constexpr const HistoryLayout& history = HertzMindlin::history;
  static constexpr bool needs_masses = true, needs_spins = false, has_torque = false, has_dashpots = true;
  static constexpr std::array<LawKey, 2> keys{{{"restitution", "restitution coefficient e in (0, 1]"},
                                               {"damping_ratio", "damping ratio in [0, 1)"}}};

  static std::string check(const ContactSettings& s, std::string& key) {
    const bool e = s.has("restitution"), zeta = s.has("damping_ratio");
    key = e ? "restitution" : "damping_ratio";
    if (e && zeta) return "give restitution or damping_ratio, not both";
    if (!e && !zeta) return "hertz_mindlin_dashpot needs restitution (in (0, 1]) or damping_ratio (in [0, 1))";
    const double v = s.value(key);
    if (e && !(v > 0 && v <= 1)) return "out of range: must be in (0, 1]";
    if (zeta && !(v >= 0 && v < 1)) return "out of range: must be in [0, 1)";
    return {};
  }

  static HertzMindlinDashpot make(const LawConstants& c) {
    std::string key;
    if (const std::string why = check(c.settings, key); !why.empty())
      throw InputError("[contact] " + key + ": " + why);
    double beta;
    if (c.settings.has("restitution")) {
      const double log_e = std::log(c.settings.value("restitution"));
      beta = log_e / std::sqrt(log_e * log_e + pi * pi);
    } else {
      beta = -c.settings.value("damping_ratio");
    }
    return {HertzMindlin::make(c), -2 * std::sqrt(5.0 / 6.0) * beta};
  }

  HertzMindlin elastic;  // the springs and the friction
  double dashpot;        // -2 sqrt(5/6) beta >= 0: gamma = dashpot sqrt(S m*)

  [[gnu::always_inline]] inline void evaluate(const ContactInput& c, double dt, HistoryView spring,
                                              ContactOutput& out) const {
    const double a = std::sqrt(c.radius * c.overlap);
    const double fn_elastic = elastic.normal_force(a, c.overlap);
    out.kn = 2.0 * elastic.effective_modulus * a;
    out.kt = 8.0 * elastic.effective_shear_modulus * a;
    const double vn = (c.vx * c.nx + c.vy * c.ny) + c.vz * c.nz;
    const double gamma_n = dashpot * std::sqrt(out.kn * c.mass), gamma_t = dashpot * std::sqrt(out.kt * c.mass);
    const double fn = fn_elastic - gamma_n * vn;
    double sx = spring[0], sy = spring[1], sz = spring[2];
    out.stiffness_work = elastic.stiffness_work(c, out.kt, sx, sy, sz);
    HertzMindlin::turn_into_plane(c.nx, c.ny, c.nz, sx, sy, sz);
    HertzMindlin::add_tangential_spring(c, out.kt * dt, sx, sy, sz);
    const double cap = elastic.friction * std::abs(fn);
    const bool sliding = (sx * sx + sy * sy) + sz * sz > cap * cap;
    out.slip_work = HertzMindlin::cap_by_friction(cap, out.kt, sx, sy, sz);
    spring[0] = sx, spring[1] = sy, spring[2] = sz;
    const double vtx = c.vx - vn * c.nx, vty = c.vy - vn * c.ny, vtz = c.vz - vn * c.nz;
    const double tx = sliding ? sx : sx - gamma_t * vtx, ty = sliding ? sy : sy - gamma_t * vty;
    const double tz = sliding ? sz : sz - gamma_t * vtz;
    out.fx = fn * c.nx + tx, out.fy = fn * c.ny + ty, out.fz = fn * c.nz + tz;
    out.tx = out.ty = out.tz = 0;
    out.cn = gamma_n, out.ct = sliding ? 0.0 : gamma_t;
    // The dashpots' power on the relative velocity, over the step: gamma_n vn^2 + gamma_t |v_t|^2.
    const double vt2 = (vtx * vtx + vty * vty) + vtz * vtz;
    out.viscous_work = dt * (gamma_n * vn * vn + out.ct * vt2);
    out.energy = 0.4 * fn_elastic * c.overlap + ((sx * sx + sy * sy) + sz * sz) / (2 * out.kt);
  }
};

}  // namespace qsdem
