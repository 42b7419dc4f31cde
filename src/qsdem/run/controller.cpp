#include "qsdem/run/controller.hpp"

#include "qsdem/run/path_control.hpp"
#include "qsdem/run/rate_control.hpp"

#include <fmt/format.h>

#include <algorithm>
#include <cmath>

namespace qsdem {
namespace {

// "schedule": at given sample points of the phase, a component's control value (its strain rate
// eps' or its stress target) becomes the next of a list: a rate jump, a staged loading.
class ValueSchedule final : public Controller {
 public:
  ValueSchedule(int component, std::vector<long> at, std::vector<double> values)
      : component_(component), at_(std::move(at)), values_(std::move(values)) {}

  bool at_sample(const SamplePoint& point, PhaseControls& controls) override {
    bool changed = false;
    for (; next_ < at_.size() && point.row >= at_[next_]; ++next_) {
      controls.component[static_cast<std::size_t>(component_)].value = values_[next_];
      changed = true;
    }
    return changed;
  }
  std::vector<double> save() const override { return {static_cast<double>(next_)}; }
  void restore(const std::vector<double>& saved) override {
    const double next = saved.empty() ? 0 : saved[0];
    if (saved.size() > 1 || !(next >= 0 && next <= static_cast<double>(at_.size())) || next != std::floor(next))
      throw InputError(fmt::format("a schedule of {} entries saved as {} values, the first {}", at_.size(),
                                   saved.size(), next));
    next_ = static_cast<std::size_t>(next);
  }

 private:
  int component_;
  std::vector<long> at_;
  std::vector<double> values_;
  std::size_t next_ = 0;  // the first entry not applied yet
};

ControllerFactory read_schedule(ControllerKeys& keys, const Phase& phase, double /*step_ratio*/) {
  const std::vector<std::string> names(component_names.begin(), component_names.end());
  const std::string name = keys.text("component", names);
  const int c = static_cast<int>(std::find(names.begin(), names.end(), name) - names.begin());
  const ComponentControl& control = phase.controls.component[static_cast<std::size_t>(c)];
  if (control.kind == ControlKind::fixed || control.kind == ControlKind::constant_volume)
    keys.fail("component", "the phase does not drive this component by a value (give it a strain_rate or a stress)");
  std::vector<long> at = keys.integers("at_sample", 1, 100'000'000);
  if (at.empty()) keys.fail("at_sample", "give at least one sample point number");
  for (std::size_t k = 1; k < at.size(); ++k)
    if (at[k] <= at[k - 1]) keys.fail("at_sample", "the sample point numbers must increase");
  std::vector<double> values;
  if (control.kind == ControlKind::strain_rate) {
    values = keys.numbers("values");
    for (double v : values) {
      if (!(std::abs(v) > 0 && std::abs(v) < 0.01)) keys.fail("values", "each strain rate eps' must be in (0, 0.01) in magnitude");
      if (planned_strain(phase, c) && (v > 0) != (control.value > 0))
        keys.fail("values", "a rate of the other sign would never reach the phase's stop.strain of this component");
    }
  } else {
    values = keys.quantities("values", Dimension::stress);
    for (double v : values)
      if (is_normal(c) && !(v > 0)) keys.fail("values", "each normal stress target must be > 0 (compression positive)");
  }
  if (values.size() != at.size())
    keys.fail("values", fmt::format("give one value per entry of at_sample ({})", at.size()));
  return [c, at, values] { return std::make_unique<ValueSchedule>(c, at, values); };
}

}  // namespace

const std::vector<ControllerKind>& controller_kinds() {
  static const std::vector<ControllerKind> kinds{
      {"schedule", "at the sample points at_sample, the component's strain rate or stress target becomes the next of values",
       &read_schedule},
      {"rate", "the component's strain rate follows an equilibrium index to its target (docs/physics.md, adaptive loading rate)",
       &read_rate_control, false, true, true},
      {"cyclic", "axis 3's strain rate turns whenever q (or e1) reaches a bound, for the given number of cycles "
                 "(docs/loading-paths.md, cyclic triaxial)",
       &read_cyclic, true, true},
      {"true_triaxial", "the stress targets of axes 1 and 2 hold p and b = (s2 - s3)/(s1 - s3) while axis 3 is strained "
                        "(docs/loading-paths.md, true triaxial)",
       &read_true_triaxial},
  };
  return kinds;
}

}  // namespace qsdem
