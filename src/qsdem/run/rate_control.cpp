#include "qsdem/run/rate_control.hpp"

#include <fmt/format.h>

#include <algorithm>
#include <cmath>

namespace qsdem {
namespace {

// At each sample point (docs/physics.md, "Adaptive loading rate"): the filtered log index
// L <- L + (log I - L) / k, the step in log |eps'| -gain (L - log I_t) / b, clamped to
// +-log(max_factor), then |eps'| clamped to [min_rate, max_rate]. It also keeps the figures of
// summary.json over the rows: sum and extremes of eps' and the rows within the band.
class RateControl final : public Controller {
 public:
  explicit RateControl(const RateControlSettings& s) : s_(s) {}

  bool at_sample(const SamplePoint& point, PhaseControls& controls) override {
    ComponentControl& cc = controls.component[static_cast<std::size_t>(s_.component)];
    count_row(*point.measures, cc.value);
    // log of an index of 0 (no unbalanced force at all): the lowest the filter can see, so that
    // the rate rises by the largest step allowed.
    const double log_i = std::log(std::max(rate_control_index(*point.measures, s_.index), 1e-300));
    filtered_ = seen_ == 0 ? log_i : filtered_ + (log_i - filtered_) / static_cast<double>(s_.filter_points);
    ++seen_;
    const double limit = std::log(s_.max_factor);
    const double change = std::clamp(-s_.gain * (filtered_ - std::log(s_.target)) / s_.exponent, -limit, limit);
    const double magnitude = std::clamp(std::abs(cc.value) * std::exp(change), s_.min_rate, s_.max_rate);
    const double value = cc.value > 0 ? magnitude : -magnitude;
    if (value == cc.value) return false;
    cc.value = value;
    return true;
  }
  void at_end(const SamplePoint& point, const PhaseControls& controls) override {
    const double rate = controls.component[static_cast<std::size_t>(s_.component)].value;
    count_row(*point.measures, rate);
    final_rate_ = std::abs(rate);
    final_strain_ = std::abs(point.strain[static_cast<std::size_t>(s_.component)]);
  }

  std::vector<double> save() const override {
    return {filtered_, static_cast<double>(seen_), rows_,        rate_sum_,
            rate_min_, rate_max_,                 in_band_,     final_rate_, final_strain_};
  }
  void restore(const std::vector<double>& v) override {
    if (v.size() != 9) return;
    if (!(v[1] >= 0 && v[1] <= 1e15) || v[1] != std::floor(v[1]))
      throw InputError(fmt::format("a rate controller saved as having seen {} sample points", v[1]));
    filtered_ = v[0];
    seen_ = static_cast<long>(v[1]);
    rows_ = v[2], rate_sum_ = v[3], rate_min_ = v[4], rate_max_ = v[5], in_band_ = v[6];
    final_rate_ = v[7], final_strain_ = v[8];
  }

  nlohmann::json figures() const override {
    const double rows = std::max(rows_, 1.0);
    const double mean = rate_sum_ / rows;
    // The steps a run at a constant eps' would take over the same strain (SPEC 3.4: c_t eps' per step).
    const auto steps_at = [&](double rate) { return rate > 0 ? std::round(final_strain_ / (s_.step_ratio * rate)) : 0.0; };
    return {{"index", s_.index == RateControlSettings::Index::imom  ? "imom"
                      : s_.index == RateControlSettings::Index::ufr ? "ufr"
                                                                    : "iuf"},
            {"target", s_.target},
            {"band_factor", s_.band},
            {"mean_strain_rate", mean},
            {"mean_is", "over the rows, which are equal increments of the component's strain: strain-weighted"},
            {"final_strain_rate", final_rate_},
            {"constant_rate_steps_at_final", steps_at(final_rate_)},
            {"constant_rate_steps_at_mean", steps_at(mean)},
            {"min_strain_rate", rate_min_},
            {"max_strain_rate", rate_max_},
            {"share_within_band", in_band_ / rows},
            {"rows", rows_}};
  }

 private:
  // One row: the eps' it was loaded at (the rows are equal strain increments, so that the mean over
  // the rows is the strain-weighted mean) and whether its index is within the band.
  void count_row(const Measures& m, double rate) {
    const double r = std::abs(rate);
    rate_min_ = rows_ == 0 ? r : std::min(rate_min_, r);
    rate_max_ = rows_ == 0 ? r : std::max(rate_max_, r);
    rate_sum_ += r;
    rows_ += 1;
    const double i = rate_control_index(m, s_.index);
    if (i >= s_.target / s_.band && i <= s_.target * s_.band) in_band_ += 1;
  }

  RateControlSettings s_;
  double filtered_ = 0;  // the moving average of log I
  long seen_ = 0;        // sample points seen
  double rows_ = 0, rate_sum_ = 0, rate_min_ = 0, rate_max_ = 0, in_band_ = 0;
  double final_rate_ = 0, final_strain_ = 0;  // |eps'| and |strain| of the last row
};

}  // namespace

double rate_control_index(const Measures& m, RateControlSettings::Index index) {
  switch (index) {
    case RateControlSettings::Index::imom: return m.imom;
    case RateControlSettings::Index::ufr: return m.ufr;
    case RateControlSettings::Index::iuf: return m.iuf;
  }
  return m.imom;
}

namespace {

RateControlSettings read_rate_control_settings(ControllerKeys& keys, const Phase& phase, double step_ratio) {
  RateControlSettings s;
  s.step_ratio = step_ratio;
  const std::vector<std::string> names(component_names.begin(), component_names.end());
  const std::string name = keys.text("component", names);
  s.component = static_cast<int>(std::find(names.begin(), names.end(), name) - names.begin());
  const ComponentControl& control = phase.controls.component[static_cast<std::size_t>(s.component)];
  if (control.kind != ControlKind::strain_rate)
    keys.fail("component", "the component must be strain-rate controlled (give it a strain_rate: the start rate)");
  const std::string index = keys.text_or("index", "imom", {"imom", "ufr", "iuf"});
  s.index = index == "ufr" ? RateControlSettings::Index::ufr
            : index == "iuf" ? RateControlSettings::Index::iuf
                             : RateControlSettings::Index::imom;
  s.target = keys.quantity("target", std::nullopt, [](double v) { return v > 0 && v < 1; }, "must be in (0, 100 %)");
  const auto rate = [](double v) { return v > 0 && v < 0.01; };
  s.min_rate = keys.number("min_rate", std::nullopt, rate, "eps' must be in (0, 0.01)");
  s.max_rate = keys.number("max_rate", std::nullopt, rate, "eps' must be in (0, 0.01)");
  if (s.max_rate < s.min_rate) keys.fail("max_rate", fmt::format("must be >= min_rate ({})", s.min_rate));
  const double start = std::abs(control.value);
  if (start < s.min_rate || start > s.max_rate)
    keys.fail("max_rate", fmt::format("the start rate, the component's strain rate {}, must be within [min_rate, max_rate]",
                                      control.value));
  s.max_factor = keys.number("max_factor_per_point", 2.0, [](double v) { return v > 1 && v <= 100; },
                             "must be in (1, 100]");
  s.gain = keys.number("gain", 0.2, [](double v) { return v > 0 && v <= 1; }, "must be in (0, 1]");
  s.exponent = keys.number("exponent", 0.85, [](double v) { return v >= 0.1 && v <= 10; }, "must be in [0.1, 10]");
  s.filter_points = keys.integer("filter_points", 4, 1, 1000);
  s.band = keys.number("band_factor", 1.5, [](double v) { return v > 1; }, "must be > 1");
  return s;
}

}  // namespace

ControllerFactory read_rate_control(ControllerKeys& keys, const Phase& phase, double step_ratio) {
  const RateControlSettings s = read_rate_control_settings(keys, phase, step_ratio);
  // Rows at equal strain increments of the component, so that a mean over the rows (summary.json)
  // is strain-weighted and a row does not stand for more strain when the rate rises.
  const Cadence& c = phase.output.cadence;
  if (c.kind != Cadence::Kind::every_strain || c.strain_component != s.component)
    keys.fail("component", fmt::format("give the phase output.every_strain.{} (rows at equal increments of the "
                                       "strain of the component whose rate the controller changes)",
                                       component_names[static_cast<std::size_t>(s.component)]));
  return [s] { return std::make_unique<RateControl>(s); };
}

}  // namespace qsdem
