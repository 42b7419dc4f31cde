// A loading phase as data (SPEC 8): what drives each of the six components of the cell, the
// phase's contact law, friction and particle damping, when it ends, when it takes a sample point
// and which file the rows go to, and an optional controller that may change the control values
// during the phase. A run is a list of phases, a Protocol; the case parser writes the default one
// ([compaction] then [triaxial]) in the same terms as a [[phase]] list (docs/config.md).
#pragma once
#include <array>
#include <cstdint>
#include <functional>
#include <memory>
#include <optional>
#include <string>
#include <vector>

#include "qsdem/engine/cell_components.hpp"
#include "qsdem/engine/types.hpp"

namespace qsdem {

class Controller;

struct ComponentControl {
  ControlKind kind = ControlKind::fixed;
  // strain_rate: eps' = rate t_c (dimensionless, SPEC 8), de/dt of a normal component
  // (compression positive) or L_ab of a shear one; stress: the target (Pa, compression positive);
  // constant_volume (normal components only): the rate that keeps the cell's volume, shared by
  // every such component of the phase (servo.hpp); no value.
  double value = 0;
};

// What drives the cell in a phase. A controller changes the values, never the kinds.
struct PhaseControls {
  std::array<ComponentControl, component_count> component{};
  // The cap of the servo's rate on stress-controlled components, one of: an eps' (> 0), or a
  // factor (> 0) times the fastest strain-rate component.
  double max_strain_rate = 0;
  double rate_factor = 0;
};

struct PhaseDamping {
  std::string model = "nd";  // a damping model's name (damping/models.hpp)
  double ratio = 0.005;  // xi_0
  DampedMotion acts_on = DampedMotion::both;
};

// When a phase ends: after the step where the first of the given criteria holds.
struct StopCriteria {
  long steps = 0;  // > 0: after this many steps
  // A component reaching a value: its strain from the phase's start (a normal one compression
  // positive, a shear one gamma_ab = F_ab + F_ba), its stress (Pa).
  std::array<std::optional<double>, component_count> strain{}, stress{};
  // Equilibrium, checked every `every` steps: contacts, every stress-controlled component within
  // stress_tolerance of its target (relative to it; a shear one relative to the largest normal
  // target), and the given indices below their tolerances.
  struct Equilibrium {
    double stress_tolerance = 0.01;
    std::optional<double> ufr, imom;
    long every = 200;
  };
  std::optional<Equilibrium> equilibrium;
  long max_steps = 0;  // > 0: not ending within this many steps stops the run (RunError)
};

// The sample points of a phase (rows of its file); its last step is always one.
struct Cadence {
  enum class Kind : std::int32_t { points, every_steps, every_strain };
  Kind kind = Kind::every_steps;
  long points = 0;           // points: this many, evenly spread over the phase's planned steps
  long every_steps = 200;    // every_steps: after every this many steps
  int strain_component = 2;  // every_strain: whenever this strain-rate controlled normal component's
  double every_strain = 0;   // strain grows by this much
};

struct PhaseOutput {
  std::string file = "series.csv";  // in the run directory
  // The row's step and time_s: the phase's force evaluation n and n dt, or the run's step count
  // and time since the sample was generated.
  enum class Clock : std::int32_t { phase, run } clock = Clock::phase;
  Cadence cadence;
};

// The case keys of a phase's settings, as the case writes them, that messages and studies name
// (e.g. "compaction.max_steps" or "phase.0.stop.max_steps"); strain_rate: its first strain-rate
// component's, or its servo's cap without one.
struct PhaseKeys {
  std::string max_steps, damping_model, damping_ratio, ufr_tolerance, strain_rate;
  std::array<std::string, component_count> strain_rates;  // each strain-rate component's, "" for the others
};

// A quasi-static phase solved by increments (docs/physics.md 5.7): each increment moves the
// strain-rate components by one step of strain (the fastest by strain_increment, the others in
// proportion to their rates), then FIRE relaxes the particles and the stress-controlled components
// from rest until the indices and the stress errors are below their tolerances, checked every
// check_every force evaluations, or until max_iterations (the increment's row says which).
struct FireSolver {
  double strain_increment = 1e-4;
  double ufr = 1e-3;
  std::optional<double> imom;
  double stress_tolerance = 1e-3;
  long max_iterations = 100'000;
  long check_every = 10;
};

using ControllerFactory = std::function<std::unique_ptr<Controller>()>;

struct Phase {
  std::string name;  // in messages, the progress line, summary.json and a file's phase column
  ContactSettings contact;  // the contact law and its keys (contact/laws.hpp): the case's [contact]
  double friction = 0.5;
  PhaseDamping damping;
  InertiaScaling inertia;  // the particles' inertia scaling during the phase (SPEC 5.6)
  PhaseControls controls;
  StopCriteria stop;
  PhaseOutput output;
  std::string controller;             // its kind (controller.hpp), "" for none
  ControllerFactory make_controller;  // a new controller of that kind for the phase
  int rate_component = -1;  // a "rate" controller's component: its eps' is the strain_rate column
  PhaseKeys keys;
  std::optional<FireSolver> fire;  // solver = "fire"; none: the dynamics at the phase's rates
};

using Protocol = std::vector<Phase>;

// Whether a normal component of the phase keeps the cell's volume (ComponentControl::constant_volume).
bool holds_volume(const Phase& phase);

// Whether a shear component of the phase has a strain rate (simple shear).
bool shears(const Phase& phase);

// The largest |eps'| of the phase's strain-rate components (0 without one): "the phase's rate",
// which a study varies with the components' proportions kept.
double fastest_strain_rate(const Phase& phase);

// Whether the phase ends when the strain of component c reaches a value at a step known in
// advance: a normal strain-rate component, whose strain grows by exactly c_t eps' per step (SPEC 3.4).
bool planned_strain(const Phase& phase, int c);

// The force evaluation (0, 1, ...) at which a normal strain-rate component, at nominal strain
// `strain` at force evaluation `from` and at rate eps' from there on, reaches `target`:
// from + round((target - strain) / (c_t eps')), and at least one step on.
long planned_step(long from, double strain, double target, double step_ratio, double eps);

// The last force evaluation of a phase whose end is known in advance (by steps or a planned
// strain), with its initial control values; -1 when it ends on a measured criterion only.
long planned_end(const Phase& phase, double step_ratio);

// The strain components of the cell h against the cell h0 (StopCriteria): e_kk = 1 - h_kk/h0_kk,
// gamma_ab = F_ab + F_ba with F = h h0^-1.
std::array<double, component_count> phase_strain(const Mat3& h, const Mat3& h0);

}  // namespace qsdem
