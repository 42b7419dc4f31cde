// Controllers: objects a phase calls at each of its sample points (and, when they ask, after every
// step) that see the measures and may change the phase's control values: strain rates, stress
// targets, the servo's cap. The phase loop builds a new Model from the changed values before the
// next step (the step itself only ever sees an immutable Model), and keeps the controller's
// saved state in the checkpoint, so that a resumed run gives the same bits.
//
// A new kind: a class derived from Controller, a function that reads its keys from the case
// (ControllerKeys) and returns a factory, and an entry in controller_kinds() (controller.cpp).
#pragma once
#include <array>
#include <functional>
#include <memory>
#include <nlohmann/json.hpp>
#include <optional>
#include <string>
#include <string_view>
#include <vector>

#include "qsdem/engine/measures.hpp"
#include "qsdem/engine/state.hpp"
#include "qsdem/run/phase.hpp"
#include "qsdem/run/units.hpp"

namespace qsdem {

// What a controller sees at a sample point of its phase.
struct SamplePoint {
  long step = 0;  // the phase's force evaluation of the row (0, 1, ...)
  long row = 0;   // the row's number in the phase (1, 2, ...)
  const Measures* measures = nullptr;
  std::array<double, component_count> strain{};  // the phase's strain components (StopCriteria)
  double critical_time = 0;                       // t_c (s): eps' = rate t_c
};

class Controller {
 public:
  virtual ~Controller() = default;
  // At each sample point: may change the values of `controls` (not their kinds); they apply from
  // the next step. Returns whether it changed any.
  virtual bool at_sample(const SamplePoint& point, PhaseControls& controls) = 0;
  // A controller that acts between sample points too returns true here; at_step is then called
  // after every step with the state of the last force evaluation (State::stress, stress_h) and
  // the cell at the phase's start.
  virtual bool every_step() const { return false; }
  virtual bool at_step(const State& /*state*/, long /*step*/, const Mat3& /*h0*/, PhaseControls& /*controls*/) {
    return false;
  }
  // Whether the phase ends after this step (a controller that counts cycles, ControllerKind::ends_phase).
  virtual bool done() const { return false; }
  // What it needs to continue exactly after a resume (saved in the checkpoint), and its restoration,
  // which throws InputError, saying why, on a saved state it could not continue from (a damaged one).
  virtual std::vector<double> save() const { return {}; }
  virtual void restore(const std::vector<double>& /*saved*/) {}
  // At the phase's last row (no change can apply any more): a controller that keeps figures of
  // the rows counts it.
  virtual void at_end(const SamplePoint& /*point*/, const PhaseControls& /*controls*/) {}
  // Its figures for the phase's entry of summary.json (after restore() of the phase's last state).
  virtual nlohmann::json figures() const { return nlohmann::json::object(); }
};

// The case parser's reader of one [phase.controller] table: each accessor reads the key (relative to
// the table) and, on a bad value, throws InputError naming the file, line, key, value and what is allowed.
class ControllerKeys {
 public:
  virtual ~ControllerKeys() = default;
  virtual std::string text(const std::string& key, const std::vector<std::string>& choices) = 0;
  virtual std::vector<long> integers(const std::string& key, long lo, long hi) = 0;
  virtual std::vector<double> numbers(const std::string& key) = 0;
  virtual std::vector<double> quantities(const std::string& key, Dimension dim) = 0;
  // One value; `def`: its value when absent (nullopt: the key is required).
  virtual std::string text_or(const std::string& key, const std::string& def, const std::vector<std::string>& choices) = 0;
  virtual double number(const std::string& key, std::optional<double> def, const std::function<bool(double)>& ok,
                        const std::string& allowed) = 0;
  virtual double quantity(const std::string& key, std::optional<double> def, const std::function<bool(double)>& ok,
                          const std::string& allowed) = 0;  // a ratio ("0.1 %" or a number)
  virtual long integer(const std::string& key, long def, long lo, long hi) = 0;
  virtual double stress(const std::string& key, std::optional<double> def, const std::function<bool(double)>& ok,
                        const std::string& allowed) = 0;  // a stress ("50 kPa")
  virtual bool has(const std::string& key) = 0;  // whether the table gives the key
  [[noreturn]] virtual void fail(const std::string& key, const std::string& why) = 0;
};

struct ControllerKind {
  std::string_view name;
  std::string_view meaning;
  // Reads the kind's own keys for `phase` (whose controls are read) and returns its factory.
  ControllerFactory (*read)(ControllerKeys& keys, const Phase& phase, double step_ratio);
  bool ends_phase = false;  // its done() ends the phase: the phase needs no stop criterion of its own
  // It plans its steps with time.step_ratio alone: the phase refuses inertia scaling.
  bool plans_with_step_ratio = false;
  // It moves the strain rate of its `component` key: that eps' is the phase's strain_rate column.
  bool writes_rate_column = false;
};

// Every controller kind a case may name (phase.controller.kind).
const std::vector<ControllerKind>& controller_kinds();

}  // namespace qsdem
