// The mutable state of a run (MuJoCo-style data): particles, cell, pairs and what the last force
// evaluation computed, plus the timers of every stage. How the threads share the work is not
// here (schedule.hpp).
#pragma once
#include <array>
#include <cstdint>
#include <vector>

#include "qsdem/engine/cell.hpp"
#include "qsdem/engine/ellipsoid_contact.hpp"
#include "qsdem/engine/neighbor.hpp"
#include "qsdem/engine/particles.hpp"
#include "qsdem/engine/timers.hpp"

namespace qsdem {

// Per-block results of the force stage: partial sums, summed in block order (thread-count
// independent), and where the block's contacts are.
struct ForceBlock {
  Mat3 stress_sum = Mat3::Zero();      // sum f (x) l over contacts (N m)
  Vec3 stiffness_sum = Vec3::Zero();   // sum (k_n n_k^2 + k_t (1 - n_k^2)) l_k^2 (N m)
  Vec3 shear_stiffness_sum = Vec3::Zero();  // the same for the shears 12, 13, 23 (servo.hpp)
  Vec3 viscosity_sum = Vec3::Zero();        // the two with the viscous coefficients c_n, c_t (N s m)
  Vec3 shear_viscosity_sum = Vec3::Zero();
  double max_overlap = 0;                   // largest delta / min(R_i, R_j) (blow-up watch)
  std::size_t max_overlap_pair = 0;
  // The energy sums (Model::track_energy, J): stored, and the step's slip, dashpot and stiffness work.
  double elastic_energy = 0, slip_work = 0, viscous_work = 0, stiffness_work = 0;
  long narrow_tests = 0;  // pairs whose narrow phase ran (not skipped as provably apart)
  long pw_iterations = 0;  // their Perram-Wertheim iterations (3x3 factorisations)
  // The block's contacts: PairList::contact_pairs[first_contact, + contacts), grouped by the
  // thread that owns their j end in the update region (Schedule::owner_first), each group in pair
  // order (Schedule::contact_owner_first).
  std::uint32_t first_contact = 0;
  std::uint32_t contacts = 0;
  // While the block runs: the contacts whose j end the block's first owner holds (j below
  // first_owner_end) go up from first_contact (`contacts` counts them), the others down from
  // slot_end, the end of its pairs' slots (later_contacts); close_block_contacts then moves the
  // others after the first ones.
  std::uint32_t first_owner_end = 0, slot_end = 0, later_contacts = 0;
};

// The energy of a run since its start (docs/physics.md 12), kept only when Model::track_energy.
// Between two instants, work of the cell + stiffness change = the dissipations + the change of the
// stored and kinetic energies, up to the time discretisation.
struct EnergyLedger {
  double boundary_work = 0;    // work done on the sample by the cell, sum -V sigma : L dt (J)
  double friction = 0;         // dissipated by Coulomb sliding (J)
  double contact_damping = 0;  // dissipated by the contacts' dashpots (J)
  double damping = 0;          // dissipated by the particle damping (J)
  double stiffness_change = 0; // stored energy the contact law made with no work: the tangential
                               // springs' as k_t follows the overlap (ContactOutput::stiffness_work, J)
  double elastic = 0;          // stored in the contacts at the last force evaluation (J)
  double kinetic = 0;          // of the fluctuations after the last kick, translation and rotation (J)
};
// Its terms in one order, with their names, for code that stores a ledger as numbers (a
// controller's saved state, a checkpoint's phase records).
struct EnergyTerm {
  const char* name;
  double EnergyLedger::* field;
};
inline constexpr std::array<EnergyTerm, 7> energy_ledger_terms{{{"boundary_work", &EnergyLedger::boundary_work},
                                                                 {"friction", &EnergyLedger::friction},
                                                                 {"contact_damping", &EnergyLedger::contact_damping},
                                                                 {"damping", &EnergyLedger::damping},
                                                                 {"stiffness_change", &EnergyLedger::stiffness_change},
                                                                 {"elastic", &EnergyLedger::elastic},
                                                                 {"kinetic", &EnergyLedger::kinetic}}};

struct State {
  Particles particles;
  Cell cell;
  PairList pairs;
  NeighborState neighbor;
  Vec3 servo_integral = Vec3::Zero();  // accumulated relative stress error per axis
  long step = 0;
  double time = 0;

  // From the last force evaluation (time t).
  Mat3 stress = Mat3::Zero();           // Love-Weber, compression positive (Pa), SPEC 7
  Vec3 affine_stiffness = Vec3::Zero(); // d sigma_kk / d eps_kk of an affine strain (Pa)
  Vec3 shear_stiffness = Vec3::Zero();  // -d sigma_ab / d D_ab dt for the shears 12, 13, 23 (Pa)
  Vec3 affine_viscosity = Vec3::Zero(); // d sigma_kk / d(-L_kk) of the contacts' dashpots (Pa s)
  Vec3 shear_viscosity = Vec3::Zero();  // -d sigma_ab / d D_ab of the dashpots, shears 12, 13, 23 (Pa s)
  double stress_volume = 1;             // V at which stress was evaluated (m^3)
  Mat3 stress_h = Mat3::Identity();     // cell matrix at which stress was evaluated (m)
  double max_overlap = 0;               // largest delta / min(R_i, R_j) over the contacts
  std::size_t max_overlap_pair = 0;     // the pair where it is
  long narrow_tests = 0;                // pairs tested by the narrow phase in the last step
  long pw_iterations = 0;               // their Perram-Wertheim iterations
  // Per particle, only when the phase's damping reads them (`stiffness`, damping/stiffness.hpp), else empty:
  // sum over its contacts of k_n and of k_t |x_c - x_i|^2 (N/m, N m).
  std::vector<double> contact_stiffness, contact_rotational_stiffness;
  EnergyLedger energy;
  // Per particle, only when Model::track_energy: what its last kick dissipated and its kinetic
  // energy after it (J), summed by the step in fixed blocks of particles (thread-count independent).
  std::vector<double> kick_dissipation, kick_kinetic;

  std::vector<ForceBlock> blocks;       // per force block (PairList::block_first)
  long contacts_build = -1;             // NeighborState::builds of the list the contacts are of

  StageTimers timers;
  std::vector<EllipsoidShape> shapes;   // scratch: per-particle shape matrices at time t
};

// Whether some particle is an ellipsoid: as the neighbour list recorded it when it holds these
// particles (NeighborState::ellipsoids), else by a pass over them.
inline bool has_ellipsoids(const State& s) {
  return s.neighbor.valid ? s.neighbor.ellipsoids : s.particles.has_ellipsoids();
}

}  // namespace qsdem
