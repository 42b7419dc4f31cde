// The immutable parameters of a step (MuJoCo-style model): material, the resolved contact law and
// damping, time step and the control of the cell; numbers and made laws only, no names. A phase
// becomes one in phase_model (phase_model.hpp), again when a controller changes a control value.
#pragma once
#include <array>
#include <optional>

#include "qsdem/engine/cell_components.hpp"
#include "qsdem/engine/contact/laws.hpp"
#include "qsdem/engine/damping/models.hpp"
#include "qsdem/engine/particles.hpp"
#include "qsdem/engine/types.hpp"

namespace qsdem {

struct Material {
  double density = 2650;        // kg/m^3
  double young_modulus = 7.8e10;  // Pa
  double poisson_ratio = 0.3;

  // Same material on both sides of a contact (SPEC 4).
  double effective_modulus() const { return young_modulus / (2 * (1 - poisson_ratio * poisson_ratio)); }
  double shear_modulus() const { return young_modulus / (2 * (1 + poisson_ratio)); }
  double effective_shear_modulus() const { return shear_modulus() / (2 * (2 - poisson_ratio)); }
  double wave_speed() const;  // sqrt(E / rho)
};

// How one component of the cell's velocity gradient is driven, in SI units (SPEC 3, servo.hpp):
// a phase's ComponentControl resolved by phase_model.
struct ResolvedControl {
  ControlKind kind = ControlKind::fixed;
  // strain_rate: a normal component's engineering rate de/dt (1/s, compression positive), a shear
  // component's L_ab (1/s); stress: the target (Pa, compression positive).
  double value = 0;
  double reference_length = 0;  // a normal strain_rate: H0 = h_kk at e = 0 (m), see servo.hpp
};

struct Servo {
  double proportional_gain = 0.1;  // beta: fraction of the stress error removed per step
  double integral_gain = 0.002;    // gamma: per-step weight of the accumulated error
  double max_strain_rate = 0;      // |L_ab| cap on stress-controlled components (1/s)
};

struct Model {
  Material material;
  // The contact law made with its constants and the friction (contact/laws.hpp); the force stages
  // refuse a Model without one.
  std::optional<ContactLaw> contact_law;
  double r_min = 0;             // equal-volume radius of the smallest particle (m)
  double critical_time = 0;     // t_c = 2 R_min sqrt(rho/E), SPEC 5, unscaled: the unit of eps'
  double step_gain = 1;         // s, the particles' inertia scaling's gain of the step (SPEC 5.6)
  double dt = 0;                // c_t s t_c
  ResolvedDamping damping;      // the particle damping and what it asks of the stages (damping/)
  std::array<ResolvedControl, component_count> control{};  // 11, 22, 33, 12, 13, 23 (cell_components.hpp)
  Servo servo;
  double skin = 0;              // Verlet skin (m)
  bool sort_particles = false;  // re-sort particles in space at every list rebuild (reorder.hpp);
                                // the protocols turn it on, hand-built states keep their order
  bool track_energy = false;    // keep State::energy (the force stage and the kick sum their terms)
  bool skip_apart_pairs = false;  // skip ellipsoid pairs while provably apart (neighbor.hpp); needs
                                  // every move to go through step(); the protocols turn it on
  // The pair loops fetch the j ends' data ahead: unset, when the particles' arrays outgrow the
  // cache (forces.hpp, prefetches_j_ends). Speed only: the results are the same bits either way.
  std::optional<bool> prefetch_j_ends;
};

// The contact law `settings` names, made for `material` with Coulomb friction mu (InputError for an
// unknown law or bad keys).
ContactLaw make_contact_law(const Material& material, double friction, const ContactSettings& settings = {});

// The contact law of a Model, or std::logic_error when it has none: a Model is made by
// phase_model, or by hand with make_contact_law.
const ContactLaw& contact_law_of(const Model& model);

// t_c = 2 R_min sqrt(rho / E) (SPEC 5, paper section 4).
double critical_time(const Material& mat, double r_min);

double smallest_equiv_radius(const Particles& particles);

}  // namespace qsdem
