// The immutable parameters of one phase of a run (MuJoCo-style model): material, contact law
// constants, time step, damping model and loading. Protocols build one Model per phase.
#pragma once
#include <array>

#include "qsdem/config.hpp"
#include "qsdem/particles.hpp"
#include "qsdem/types.hpp"

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

// How one axis of the cell is driven (SPEC 3). Compression positive.
struct AxisControl {
  enum class Kind { fixed, strain_rate, stress } kind = Kind::fixed;
  double value = 0;  // strain_rate: engineering rate de/dt (1/s); stress: target (Pa)
  double reference_length = 0;  // strain_rate: H0 = h_kk at e = 0 (m), see servo.hpp
};

struct Servo {
  double proportional_gain = 0.1;  // beta: fraction of the stress error removed per step
  double integral_gain = 0.002;    // gamma: per-step weight of the accumulated error
  double max_strain_rate = 0;      // |L_kk| cap on stress-controlled axes (1/s)
  bool zero_shear_stress = false;  // also drive the shear stresses to zero (servo.hpp)
};

struct Model {
  Material material;
  ContactSettings contact;      // the contact law and its keys (contact/laws.hpp)
  double friction = 0.5;        // Coulomb mu
  double r_min = 0;             // equal-volume radius of the smallest particle (m)
  double critical_time = 0;     // t_c = 2 R_min sqrt(rho/E), SPEC 5
  double dt = 0;                // c_t t_c
  DampingModel damping = DampingModel::none;  // the damping stage's model (damping.hpp)
  double damping_ratio = 0;     // xi_0
  DampedMotion damping_acts_on = DampedMotion::both;
  std::array<AxisControl, 3> control{};
  Servo servo;
  double skin = 0;              // Verlet skin (m)
  bool sort_particles = false;  // re-sort particles in space at every list rebuild (reorder.hpp);
                                // the protocols turn it on, hand-built states keep their order
  bool skip_apart_pairs = false;  // skip ellipsoid pairs while provably apart (neighbor.hpp); needs
                                  // every move to go through step(); the protocols turn it on
};

// t_c = 2 R_min sqrt(rho / E) (SPEC 5, paper section 4).
double critical_time(const Material& mat, double r_min);

double smallest_equiv_radius(const Particles& particles);

// The model of a phase from the case parameters; the caller sets friction, damping, control.
Model base_model(const Params& params, const Particles& particles);

}  // namespace qsdem
