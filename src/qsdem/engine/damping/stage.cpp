#include "qsdem/engine/damping/stage.hpp"

#include <fmt/format.h>

#include <algorithm>

namespace qsdem {
namespace {

// Particles [lo, hi) get the model's factors, on what the phase damps.
template <class D>
void fill(const D& damping, DampedMotion acts_on, const DampingInputs& in, Particles& p, std::size_t lo,
          std::size_t hi) {
  const bool translation = acts_on != DampedMotion::rotation;
  const bool rotation = acts_on != DampedMotion::translation;
  for (std::size_t i = lo; i < hi; ++i) {
    const double a = damping.factor(p, i, in);
    double b = a;
    if constexpr (requires { damping.rotation_factor(p, i, in); }) b = damping.rotation_factor(p, i, in);
    p.damping_translation[i] = translation ? a : 0.0;
    p.damping_rotation[i] = rotation ? b : 0.0;
  }
}

}  // namespace

void assign_damping(const Model& model, Particles& p) {
  std::visit([&](const auto& damping) { fill(damping, model.damping.acts_on, {}, p, 0, p.size()); },
             model.damping.law);
  for (std::size_t i = 0; i < p.size(); ++i) {
    // Eq. 10 needs 1 - A dt/2 > 0, otherwise the update reverses the velocity every step.
    const double a = std::max(p.damping_translation[i], p.damping_rotation[i]);
    if (a * model.dt >= 2)
      throw InputError(fmt::format("the damping gives A_i dt / 2 = {:.3g} >= 1 for the time step (paper Eq. 10 "
                                   "reverses velocities): lower damping.ratio or time.step_ratio",
                                   0.5 * a * model.dt));
  }
}

void update_damping(const Model& model, State& state, std::size_t lo, std::size_t hi) {
  if (!model.damping.per_step) return;
  const bool summed = !state.contact_stiffness.empty();
  const DampingInputs in{summed ? state.contact_stiffness.data() : nullptr,
                         summed ? state.contact_rotational_stiffness.data() : nullptr};
  std::visit([&](const auto& damping) { fill(damping, model.damping.acts_on, in, state.particles, lo, hi); },
             model.damping.law);
}

}  // namespace qsdem
