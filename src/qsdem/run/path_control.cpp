#include "qsdem/run/path_control.hpp"

#include <fmt/format.h>

#include <Eigen/LU>
#include <cmath>
#include <numbers>

#include "qsdem/run/output.hpp"
#include "qsdem/run/units.hpp"

namespace qsdem {

double axial_deviator(const Mat3& stress) { return stress(2, 2) - 0.5 * (stress(0, 0) + stress(1, 1)); }

double CycleLoop::damping_ratio() const {
  const double stored = 0.125 * (q_max - q_min) * (e1_max - e1_min);
  return work / (4 * std::numbers::pi * stored);
}

namespace {

struct CyclicSettings {
  bool strain_bounds = false;  // the bounds are of e1 (else of q)
  double lower = 0, upper = 0;  // Pa (q) or e1
  long cycles = 1;
  double step_ratio = 0;  // c_t: e1 grows by c_t eps' per step (SPEC 3.4)
};

// "cyclic": axis 3 at its strain rate eps' (> 0, loading first) until the bound is reached, then at
// -eps' until the other one is, and so on. The bound is checked after every step: q of the step's
// force evaluation, or e1 of the next one (known exactly: c_t eps' per step), so that the rate turns
// at the first step that reaches it. A corner is the force evaluation after the turn (the last one
// the old rate moved the cell towards): e1 is extreme there. The first corner (a top) opens cycle 1;
// each second corner after it closes a cycle. Throughout, the work q de1 of the steps is summed
// (trapezoid rule over the force evaluations), so a loop's area is the difference of the sums at
// its corners, closed by the chord between its first and last corner (the cycle's accumulated
// strain does no loop work).
class Cyclic final : public Controller {
 public:
  explicit Cyclic(const CyclicSettings& s) : s_(s) {}

  bool at_sample(const SamplePoint& /*point*/, PhaseControls& /*controls*/) override { return false; }
  bool every_step() const override { return true; }
  bool at_step(const State& st, long /*step*/, const Mat3& h0, PhaseControls& controls) override {
    const double q = axial_deviator(st.stress);
    const double e1 = 1 - st.stress_h(2, 2) / h0(2, 2);
    if (seen_) work_ += 0.5 * (q + q_last_) * (e1 - e1_last_);
    seen_ = true;
    q_last_ = q;
    e1_last_ = e1;
    if (turning_) {
      corners_.push_back({q, e1, st.stress_h.determinant() / h0.determinant() - 1, work_, st.energy});
      turning_ = false;
    }
    if (done()) return false;
    double& rate = controls.component[2].value;
    const bool loading = rate > 0;
    const double x = s_.strain_bounds ? e1 + s_.step_ratio * rate : q;
    if (loading ? x >= s_.upper : x <= s_.lower) {
      rate = -rate;
      turning_ = true;
      return true;
    }
    return false;
  }
  bool done() const override { return static_cast<long>(corners_.size()) >= 2 * s_.cycles + 1; }

  // v[0] = seen + 2: each corner holds the energy ledger after its 4 values (a checkpoint of
  // format 8 holds the 4 alone).
  std::vector<double> save() const override {
    std::vector<double> v{seen_ ? 3.0 : 2.0, turning_ ? 1.0 : 0.0, q_last_, e1_last_, work_};
    for (const Corner& c : corners_) {
      v.insert(v.end(), {c.q, c.e1, c.ev, c.work});
      for (const EnergyTerm& term : energy_ledger_terms) v.push_back(c.energy.*term.field);
    }
    return v;
  }
  void restore(const std::vector<double>& v) override {
    const bool ledger = !v.empty() && v[0] >= 2;
    const std::size_t width = ledger ? 4 + energy_ledger_terms.size() : 4;
    if (v.size() < 5 || (v.size() - 5) % width != 0) return;
    seen_ = v[0] == 1 || v[0] == 3, turning_ = v[1] != 0, q_last_ = v[2], e1_last_ = v[3], work_ = v[4];
    corners_.clear();
    for (std::size_t k = 5; k < v.size(); k += width) {
      Corner c{v[k], v[k + 1], v[k + 2], v[k + 3], {}};
      if (ledger)
        for (std::size_t m = 0; m < energy_ledger_terms.size(); ++m) c.energy.*energy_ledger_terms[m].field = v[k + 4 + m];
      corners_.push_back(c);
    }
  }

  nlohmann::json figures() const override {
    nlohmann::json cycles = nlohmann::json::array();
    for (std::size_t k = 2; k < corners_.size(); k += 2) {
      const Corner &top = corners_[k - 2], &bottom = corners_[k - 1], &end = corners_[k];
      CycleLoop l;
      l.q_max = end.q, l.q_min = bottom.q, l.e1_max = end.e1, l.e1_min = bottom.e1;
      l.work = end.work - top.work - 0.5 * (top.q + end.q) * (end.e1 - top.e1);
      l.e1 = end.e1, l.ev = end.ev;
      nlohmann::json cycle{{"cycle", k / 2},
                           {"q_max_Pa", l.q_max},
                           {"q_min_Pa", l.q_min},
                           {"e1_max", l.e1_max},
                           {"e1_min", l.e1_min},
                           {"secant_modulus_Pa", l.secant_modulus()},
                           {"loop_work_J_m3", l.work},
                           {"damping_ratio", l.damping_ratio()},
                           {"e1", l.e1},
                           {"ev", l.ev}};
      // A loaded sample stores elastic energy: 0 at the corners means the run kept no ledger.
      if (top.energy.elastic > 0 && end.energy.elastic > 0) cycle["energy"] = energy_change(top.energy, end.energy);
      cycles.push_back(cycle);
    }
    return {{"bounds", s_.strain_bounds ? "strain" : "stress"},
            {"lower", s_.lower},
            {"upper", s_.upper},
            {"cycles", cycles}};
  }

 private:
  struct Corner {
    double q, e1, ev, work;
    EnergyLedger energy;  // the run's energy at the corner (all 0 unless output.energy)
  };
  CyclicSettings s_;
  bool seen_ = false, turning_ = false;
  double q_last_ = 0, e1_last_ = 0, work_ = 0;
  std::vector<Corner> corners_;
};

// "true_triaxial": s1 = s33 is loaded by axis 3's strain rate; after every step the stress targets
// of the two lateral axes become the s2 (intermediate) and s3 that keep p and b at the step's s1:
//   s1 + s2 + s3 = 3 p,  s2 - s3 = b (s1 - s3)  =>  s3 = (3 p - (1 + b) s1) / (2 - b),  s2 = s3 + b (s1 - s3).
class TrueTriaxial final : public Controller {
 public:
  TrueTriaxial(double p, double b, int intermediate) : p_(p), b_(b), intermediate_(intermediate) {}

  bool at_sample(const SamplePoint& /*point*/, PhaseControls& /*controls*/) override { return false; }
  bool every_step() const override { return true; }
  bool at_step(const State& st, long step, const Mat3& /*h0*/, PhaseControls& controls) override {
    const double s1 = st.stress(2, 2);
    const double s3 = (3 * p_ - (1 + b_) * s1) / (2 - b_);
    if (!(s3 > 0))
      throw RunError(fmt::format("true_triaxial: at step {} s1 = {:.4g} kPa exceeds 3 p / (1 + b) = {:.4g} kPa: no "
                                 "positive lateral stress keeps p = {:.4g} kPa and b = {:.3g}; end the phase earlier "
                                 "(stop.strain.33)",
                                 step, s1 / 1e3, 3 * p_ / (1 + b_) / 1e3, p_ / 1e3, b_));
    controls.component[static_cast<std::size_t>(intermediate_)].value = s3 + b_ * (s1 - s3);
    controls.component[static_cast<std::size_t>(1 - intermediate_)].value = s3;
    return true;
  }

 private:
  double p_, b_;
  int intermediate_;  // the lateral axis (0 or 1) that carries s2; the other carries s3
};

}  // namespace

ControllerFactory read_cyclic(ControllerKeys& keys, const Phase& phase, double step_ratio) {
  const ComponentControl& axial = phase.controls.component[2];
  if (axial.kind != ControlKind::strain_rate || !(axial.value > 0))
    keys.fail("kind", "a cyclic phase loads axis 3 first: give the phase strain_rate = { 33 = eps' > 0 }");
  if (phase.stop.strain[2])
    keys.fail("kind", "a cyclic phase ends after its cycles: remove stop.strain.33 (it would plan an end at one rate)");
  CyclicSettings s;
  s.step_ratio = step_ratio;
  s.cycles = keys.integer("cycles", 1, 1, 100'000);
  const bool by_stress = keys.has("q_amplitude"), by_strain = keys.has("strain_amplitude");
  if (by_stress == by_strain) keys.fail("q_amplitude", "give q_amplitude (with q_mean) or strain_amplitude, one of them");
  double mean = 0, amplitude = 0;
  const auto positive = [](double v) { return v > 0; };
  if (by_stress) {
    mean = keys.stress("q_mean", std::nullopt, [](double v) { return std::isfinite(v); }, "a stress");
    amplitude = keys.stress("q_amplitude", std::nullopt, positive, "must be > 0");
  } else {
    s.strain_bounds = true;
    mean = keys.quantity("strain_mean", 0.0, [](double v) { return std::abs(v) < 0.5; }, "must be in (-50 %, 50 %)");
    amplitude = keys.quantity("strain_amplitude", std::nullopt, [](double v) { return v > 0 && v < 0.5; },
                              "must be in (0, 50 %)");
    if (mean + amplitude <= 0) keys.fail("strain_mean", "the upper bound strain_mean + strain_amplitude must be > 0 (loading first)");
  }
  s.lower = mean - amplitude;
  s.upper = mean + amplitude;
  return [s] { return std::make_unique<Cyclic>(s); };
}

ControllerFactory read_true_triaxial(ControllerKeys& keys, const Phase& phase, double /*step_ratio*/) {
  const auto& c = phase.controls.component;
  if (c[2].kind != ControlKind::strain_rate)
    keys.fail("kind", "true_triaxial loads s1 along axis 3: give the phase strain_rate = { 33 = eps' }");
  if (c[0].kind != ControlKind::stress || c[1].kind != ControlKind::stress)
    keys.fail("kind", "true_triaxial sets the stress targets of axes 1 and 2: give the phase stress = { 11 = ..., 22 = ... }");
  const double p = keys.stress("p", std::nullopt, [](double v) { return v > 0; }, "must be > 0");
  const double b = keys.number("b", std::nullopt, [](double v) { return v >= 0 && v <= 1; }, "must be in [0, 1]");
  const std::string inter = keys.text_or("intermediate", "11", {"11", "22"});
  const int axis = inter == "11" ? 0 : 1;
  return [p, b, axis] { return std::make_unique<TrueTriaxial>(p, b, axis); };
}

}  // namespace qsdem
