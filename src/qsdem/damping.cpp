#include "qsdem/damping.hpp"

#include <fmt/format.h>

namespace qsdem {

Damping make_damping(const Model& model, const State* state) {
  const double two_xi0_c = 2 * model.damping_ratio * model.material.wave_speed();
  switch (model.damping) {
    case DampingModel::none: return NoDamping{};
    case DampingModel::od: return GlobalMassDamping{two_xi0_c / model.r_min};        // Eq. 15
    case DampingModel::nd: return SizeDependentDamping{two_xi0_c};                    // Eq. 19
    case DampingModel::local: return LocalDamping{};
    case DampingModel::contact: return ContactDamping{};
    case DampingModel::stiffness: {  // SPEC 6.3
      const bool summed = state && !state->contact_stiffness.empty();
      return StiffnessDamping{2 * model.damping_ratio, summed ? state->contact_stiffness.data() : nullptr,
                              summed ? state->contact_rotational_stiffness.data() : nullptr};
    }
  }
  return NoDamping{};
}

ContactSettings contact_settings(const Model& model) {
  if (model.damping != DampingModel::contact) return model.contact;
  ContactSettings s;
  s.law = "hertz_mindlin_dashpot";
  s.values["damping_ratio"] = model.damping_ratio;
  return s;
}

LocalDampingCoefficients local_damping(const Model& model) {
  if (model.damping != DampingModel::local) return {};
  const double alpha = model.damping_ratio;
  return {model.damping_acts_on != DampedMotion::rotation ? alpha : 0.0,
          model.damping_acts_on != DampedMotion::translation ? alpha : 0.0};
}

double damping_factor(DampingModel model, double xi0, double radius, double r_min, const Material& mat) {
  switch (model) {
    case DampingModel::none:
    case DampingModel::local:
    case DampingModel::stiffness:
    case DampingModel::contact: return 0.0;
    case DampingModel::od: return 2 * xi0 * mat.wave_speed() / r_min;   // Eq. 15
    case DampingModel::nd: return 2 * xi0 * mat.wave_speed() / radius;  // Eq. 19
  }
  return 0.0;
}

namespace {

// Particles [lo, hi) get the model's factors, on what the phase damps.
template <class D>
void fill(const D& damping, const Model& model, Particles& p, std::size_t lo, std::size_t hi) {
  const bool translation = model.damping_acts_on != DampedMotion::rotation;
  const bool rotation = model.damping_acts_on != DampedMotion::translation;
  for (std::size_t i = lo; i < hi; ++i) {
    const double a = damping.factor(p, i);
    double b = a;
    if constexpr (requires { damping.rotation_factor(p, i); }) b = damping.rotation_factor(p, i);
    p.damping_translation[i] = translation ? a : 0.0;
    p.damping_rotation[i] = rotation ? b : 0.0;
  }
}

}  // namespace

void assign_damping(const Model& model, Particles& p) {
  std::visit([&](const auto& damping) { fill(damping, model, p, 0, p.size()); }, make_damping(model));
  for (std::size_t i = 0; i < p.size(); ++i) {
    // Eq. 10 needs 1 - A dt/2 > 0, otherwise the update reverses the velocity every step.
    const double a = std::max(p.damping_translation[i], p.damping_rotation[i]);
    if (a * model.dt >= 2)
      throw InputError(fmt::format("damping ratio {:.4g} gives A_i dt / 2 = {:.3g} >= 1 for the time step (paper Eq. 10 "
                                   "reverses velocities): lower the damping ratio or time.step_ratio",
                                   model.damping_ratio, 0.5 * a * model.dt));
  }
}

void update_damping(const Model& model, State& state, std::size_t lo, std::size_t hi) {
  std::visit(
      [&]<class D>(const D& damping) {
        if constexpr (D::per_step) fill(damping, model, state.particles, lo, hi);
      },
      make_damping(model, &state));
}

}  // namespace qsdem
