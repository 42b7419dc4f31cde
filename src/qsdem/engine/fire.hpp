// FIRE, the fast inertial relaxation engine (Bitzek, Koskinen, Gumbsch, Moseler & Gumbsch,
// PRL 97, 170201, 2006), as the relaxation of a quasi-static increment (docs/physics.md 5.7):
// undamped leapfrog steps whose velocities are turned towards the force, with a step that grows
// while the power F.v stays positive and a stop of every particle when it turns negative.
#pragma once
#include "qsdem/engine/model.hpp"
#include "qsdem/engine/schedule.hpp"
#include "qsdem/engine/state.hpp"

namespace qsdem {

// Bitzek et al.'s recommended constants (their Table, and FIRE 2.0, Guenole et al., Comput.
// Mater. Sci. 175, 109584, 2020): N_min, f_inc, f_dec, alpha_start, f_alpha; the step between
// dt_min and the stable step of the Model (dt_max = Model::dt: a DEM step is set by stability,
// not accuracy, so FIRE may not exceed it).
struct FireConstants {
  long n_min = 5;
  double f_inc = 1.1, f_dec = 0.5, alpha_start = 0.1, f_alpha = 0.99;
  double dt_min_ratio = 0.02;  // dt_min = dt_min_ratio dt_max
};

// FIRE's own state over one relaxation: the step, the mixing weight and the steps since the power
// last turned negative. A relaxation starts from rest at dt_max / 2.
struct FireState {
  double dt = 0;         // the step of the last drift (s)
  double alpha = 0.1;
  long positive = 0;
  long resets = 0;       // steps whose power was not positive (velocities stopped)
};

FireState fire_start(const Model& model, const FireConstants& c = {});

// The generalised power of the particles' motion, sum F.v + M.omega (W), with the forces and
// torques of the state's last evaluation and the velocities of its last kick; in particle order.
double fire_power(const Particles& p);

// One FIRE step (one force evaluation) from t to t + dt:
//   1. the pair forces and resultants at t (with the step of the last drift, whose motion the
//      tangential springs integrate);
//   2. the power P = F.v + M.omega: P > 0 for more than N_min steps grows dt (to dt_max) and
//      lowers alpha; P <= 0 stops every particle (v = L = 0), halves dt and restarts alpha;
//   3. the servo and the cell over the new dt (Model's controls: strain-rate components move,
//      stress-controlled ones follow their servo);
//   4. the undamped kick v += dt F / m, L += dt M, then the mixing v <- (1 - alpha) v + alpha |v| F/|F|
//      (and L with M), with the norms over all particles (Bitzek et al. Eq. 2; FIRE 2.0's
//      semi-implicit Euler order: kick, mix, drift);
//   5. the drift of positions and orientations over dt.
// `model`: the phase's Model with its damping off (Model::damping none) and dt = dt_max.
void fire_step(const Model& model, State& state, Schedule& schedule, FireState& fire, const FireConstants& c = {});

}  // namespace qsdem
