// The force stage written plainly (SPEC 4, 7), to read and to test the fast one (forces.cpp)
// against: one loop over the listed pairs, in pair order, with no lanes, blocks or threads. Each
// pair: the narrow phase (sphere_sphere, or ellipsoid_contact for a pair with an ellipsoid), the
// velocity of j's contact point relative to i's with the affine part (SPEC 3), the contact law
// (contact/laws.hpp), the torques, and the stress, stiffness and viscosity sums. It reads the state
// and returns what the fast stage would write into it.
#pragma once
#include <vector>

#include "qsdem/engine/contact/law.hpp"
#include "qsdem/engine/model.hpp"
#include "qsdem/engine/state.hpp"

namespace qsdem {

struct ReferenceContact {
  std::size_t pair;
  double overlap;
  Vec3 force;              // on j (N); i receives -force
  Vec3 torque_i, torque_j;  // about each centre (N m)
  ContactOutput law;       // the law's outputs (k_n, k_t, c_n, c_t, elastic energy)
};

struct ReferenceForces {
  std::vector<ReferenceContact> contacts;  // the contacts, in pair order
  std::vector<Vec3> force, torque;         // per particle: the contact resultants (SPEC 7)
  std::vector<double> history;             // the law's history after the stage, as PairList's
  std::vector<double> pw_lambda;           // the Perram-Wertheim warm starts after the stage
  Mat3 stress = Mat3::Zero();              // as State::stress and the rest
  Vec3 affine_stiffness = Vec3::Zero(), shear_stiffness = Vec3::Zero();
  Vec3 affine_viscosity = Vec3::Zero(), shear_viscosity = Vec3::Zero();
  double elastic_energy = 0;               // sum of the contacts' elastic energies (J)
  // Per particle: sum of k_n and of k_t |x_c - x_i|^2 over its contacts (State::contact_stiffness).
  std::vector<double> contact_stiffness, contact_rotational_stiffness;
};

// The contact forces of every listed pair of `state` at its current positions, with the law of
// `model`.
ReferenceForces reference_contact_forces(const Model& model, const State& state);

}  // namespace qsdem
