// Particle damping (SPEC 6) as a stage of the step, chosen per phase (Model::damping): it gives
// every particle its viscous factors before the kick, A_i for translation (Particles::
// damping_translation) and B_i for rotation (damping_rotation), which the kick applies (paper
// Eq. 10, integrator.hpp). What is damped, translation, rotation or both, is data of the phase
// (Model::damping_acts_on): the other factor is 0.
//
// A damping model is a struct with
//   static constexpr DampingModel kind;   its name in the case ([damping] model)
//   static constexpr bool per_step;       its factors change during a phase (else they are set
//                                         once, when the phase starts)
//   double factor(const Particles&, std::size_t i) const;   A_i (1/s), before acts_on
//   double rotation_factor(const Particles&, std::size_t i) const;   B_i, when it differs from A_i
// and an entry in the Damping variant (damping.cpp makes it from the Model).
#pragma once
#include <cmath>
#include <cstddef>
#include <variant>

#include "qsdem/model.hpp"
#include "qsdem/particles.hpp"
#include "qsdem/state.hpp"

namespace qsdem {

// `none`: A_i = B_i = 0.
struct NoDamping {
  static constexpr DampingModel kind = DampingModel::none;
  static constexpr bool per_step = false;
  double factor(const Particles&, std::size_t) const { return 0.0; }
};

// `od`, global mass damping (paper Eq. 13, 15): A_i = 2 xi_0 omega_max, omega_max = sqrt(E/rho) / R_min.
struct GlobalMassDamping {
  static constexpr DampingModel kind = DampingModel::od;
  static constexpr bool per_step = false;
  double alpha;  // 2 xi_0 omega_max (1/s)
  double factor(const Particles&, std::size_t) const { return alpha; }
};

// `nd`, size-dependent damping (paper Eq. 17-19): A_i = 2 xi_0 omega#_i, omega#_i = sqrt(E/rho) / R_i.
struct SizeDependentDamping {
  static constexpr DampingModel kind = DampingModel::nd;
  static constexpr bool per_step = false;
  double two_xi0_c;  // 2 xi_0 sqrt(E/rho) (m/s)
  double factor(const Particles& p, std::size_t i) const { return two_xi0_c / p.equiv_radius[i]; }
};

// `local`, Cundall's non-viscous damping (SPEC 6; PFC's local damping, YADE's NewtonIntegrator
// `damping`): no viscous factor; the kick damps each component k of the force and of the moment,
// F_k <- F_k - alpha |F_k| sign(v_k) (integrator.cpp, LocalDampingKick), alpha = the phase's ratio.
struct LocalDamping {
  static constexpr DampingModel kind = DampingModel::local;
  static constexpr bool per_step = false;
  double factor(const Particles&, std::size_t) const { return 0.0; }
};

// `stiffness`, contact-stiffness damping (SPEC 6.3): like `nd`, but each particle's frequencies
// from its current contacts (State::contact_stiffness, contact_rotational_stiffness, summed by the
// force stage every step): A_i = 2 xi_0 sqrt(sum_c k_n,c / m_i), B_i = 2 xi_0 sqrt(sum_c k_t,c
// |x_c - x_i|^2 / I_min,i), I_min the smallest principal moment. A particle without contacts gets 0.
struct StiffnessDamping {
  static constexpr DampingModel kind = DampingModel::stiffness;
  static constexpr bool per_step = true;
  double two_xi0;
  const double* stiffness = nullptr;   // per particle; null before the phase's first force evaluation
  const double* rotational_stiffness = nullptr;
  double factor(const Particles& p, std::size_t i) const {
    return stiffness ? two_xi0 * std::sqrt(stiffness[i] * p.inv_mass[i]) : 0.0;
  }
  double rotation_factor(const Particles& p, std::size_t i) const {
    return rotational_stiffness ? two_xi0 * std::sqrt(rotational_stiffness[i] * p.inv_inertia[i].maxCoeff()) : 0.0;
  }
};

// `contact`: no particle damping; the phase's contact law is hertz_mindlin_dashpot with the damping
// ratio zeta = the phase's ratio (contact_settings below, SPEC 6.4).
struct ContactDamping {
  static constexpr DampingModel kind = DampingModel::contact;
  static constexpr bool per_step = false;
  double factor(const Particles&, std::size_t) const { return 0.0; }
};

using Damping = std::variant<NoDamping, GlobalMassDamping, SizeDependentDamping, LocalDamping, StiffnessDamping,
                             ContactDamping>;

// The contact law of a phase: Model::contact, or for the damping `contact` the law with dashpots,
// hertz_mindlin_dashpot, whose damping_ratio is the phase's ratio (contact/hertz_mindlin_dashpot.hpp).
ContactSettings contact_settings(const Model& model);

// Whether the force stage must sum each particle's contact stiffnesses for the phase's damping.
inline bool needs_contact_stiffness(const Model& model) { return model.damping == DampingModel::stiffness; }

// Cundall's alpha of a phase on translation and on rotation (0 unless the model is `local`, and
// on the motion Model::damping_acts_on leaves out).
struct LocalDampingCoefficients {
  double translation = 0, rotation = 0;
};
LocalDampingCoefficients local_damping(const Model& model);

// The damping model of a phase (`state`: the contact stiffnesses a per-step model reads).
Damping make_damping(const Model& model, const State* state = nullptr);

// A_i = B_i of SPEC 6 for one particle of equivalent radius `radius`: 0 (none, local, contact), 2 xi0
// omega_max (od), 2 xi0 omega#_i (nd); `stiffness` depends on the contacts (0 here).
double damping_factor(DampingModel model, double xi0, double radius, double r_min, const Material& mat);

// The damping stage at the start of a phase: every particle's factors, translation and rotation
// as Model::damping_acts_on says. InputError when a factor would reverse velocities (A dt/2 >= 1).
void assign_damping(const Model& model, Particles& particles);

// The damping stage before the kick, particles [lo, hi): the factors of a model whose factors
// change during the phase (per_step: stiffness, from the state's contact stiffnesses). The models
// constant in a phase (none, od, nd, local) were set by assign_damping, and this does nothing for them.
void update_damping(const Model& model, State& state, std::size_t lo, std::size_t hi);

}  // namespace qsdem
