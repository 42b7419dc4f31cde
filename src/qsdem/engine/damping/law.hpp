// What a particle damping model is (SPEC 6), the twin of contact/law.hpp: a small struct that
// declares everything the case parser, the compiled Model and the stages need, registered once in
// damping/models.hpp. A model declares
//
//   static constexpr std::string_view name;      its value of the case key `damping.model`
//   static constexpr RatioRange ratio;           what its `damping.ratio` means and may be
//   static constexpr bool per_step;              its factors change during a phase: the damping
//                                                stage refills them before every kick (else once,
//                                                when the phase starts)
//   static constexpr bool needs_contact_stiffness;  the force stage sums each particle's contact
//                                                stiffnesses for it (DampingInputs)
//   static constexpr Kick kick;                  viscous (the factors A_i, B_i of paper Eq. 10) or
//                                                cundall (Cundall's non-viscous damping in the kick)
//   static Model make(const DampingConstants&);  the model of a phase
//   double factor(const Particles&, std::size_t i, const DampingInputs&) const;   A_i (1/s)
//   double rotation_factor(...) const;           optional: B_i when it differs from A_i
//   double cundall_alpha() const;                kick == cundall: Cundall's alpha
// and optionally
//   static std::string check(double ratio, const ContactSettings& law);  what is wrong with the
//                                                model on the case's contact law ("" if nothing)
//   static ContactSettings contact_law(double ratio);  the contact law the model implies for its
//                                                phase (the damping is in the contacts)
#pragma once
#include <cstddef>
#include <limits>
#include <string_view>

#include "qsdem/engine/particles.hpp"
#include "qsdem/engine/types.hpp"

namespace qsdem {

// How the kick applies a model: through the viscous factors A_i, B_i (paper Eq. 10), or as
// Cundall's non-viscous damping of the force and moment components (integrator.cpp).
enum class Kick : std::uint8_t { viscous, cundall };

// The allowed values of a model's damping.ratio: [0, max], or [0, max) when max_open.
struct RatioRange {
  double max = std::numeric_limits<double>::infinity();
  bool max_open = false;
  std::string_view meaning = "the nominal damping ratio xi_0";  // for messages
  std::string_view shown = ">= 0";                              // the range as messages write it
  bool contains(double r) const { return r >= 0 && (max_open ? r < max : r <= max); }
};

// What every model is made from: the phase's ratio and the material and sample constants.
struct DampingConstants {
  double ratio = 0;       // damping.ratio of the phase
  double wave_speed = 0;  // sqrt(E / rho) (m/s)
  double r_min = 0;       // equal-volume radius of the smallest particle (m), times the step gain s
                          // under inertia scaling (the radius of the scaled critical step, SPEC 5.6)
};

// What a per-step model reads of the last force evaluation: per particle, the sums over its
// contacts of k_n and of k_t |x_c - x_i|^2 (State::contact_stiffness, contact_rotational_stiffness;
// null before the phase's first force evaluation).
struct DampingInputs {
  const double* contact_stiffness = nullptr;
  const double* contact_rotational_stiffness = nullptr;
};

}  // namespace qsdem
