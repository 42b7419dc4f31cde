// Simulation: a case stepped from Python. The phases run through run_phase, the CLI's phase loop,
// paused between two steps by its step hook (as a checkpoint pauses a run: the loop's own state
// lives in RunProgress, so a phase continued gives the bits of one run without pause). Rows are
// counted, not written. A Python callback is called at every sample point, after the phase's own
// controller, and may change the phase's control values.
#include "simulation.hpp"

#include <pybind11/functional.h>
#include <pybind11/stl.h>

#include <algorithm>
#include <climits>
#include <cmath>
#include <memory>
#include <utility>

#include "qsdem/engine/damping/models.hpp"

#include "qsdem/run/checkpoint.hpp"
#include "qsdem/run/controller.hpp"
#include "qsdem/run/run.hpp"

namespace qsdem::python {

namespace {

struct Pause {};  // thrown by the step hook when step(n) has taken its n steps

bool is_number(const py::handle& v) {
  return (py::isinstance<py::float_>(v) || py::isinstance<py::int_>(v)) && !py::isinstance<py::bool_>(v);
}

// What a callback changes besides the control values: the phase's friction and damping ratio.
struct PhaseChange {
  std::optional<double> friction, damping_ratio;
};

// One change `key: value` a sample-point callback returns, checked and applied to `next`.
void apply_change(const std::string& key, const py::handle& value_obj, const Phase& phase, PhaseControls& next,
                  PhaseChange& change) {
  if (!is_number(value_obj))
    throw py::type_error(fmt::format("on_sample: the value of '{}' must be a number, not {}", key,
                                     std::string(py::str(value_obj.get_type().attr("__name__")))));
  const double value = value_obj.cast<double>();
  if (!std::isfinite(value)) throw py::value_error(fmt::format("on_sample: '{}' = {} is not finite", key, value));
  if (key == "max_strain_rate" || key == "rate_factor") {
    if (value <= 0)
      throw py::value_error(fmt::format("on_sample: '{}' = {} is not allowed: give a number > 0", key, value));
    (key == "max_strain_rate" ? next.max_strain_rate : next.rate_factor) = value;
    return;
  }
  if (key == "friction") {
    if (value < 0) throw py::value_error(fmt::format("on_sample: friction = {} is not allowed: give a number >= 0", value));
    change.friction = value;
    return;
  }
  if (key == "damping_ratio") {
    bool on_ratio = false;
    const std::string why = value < 0 ? "must be >= 0" : check_damping(phase.damping.model, value, phase.contact, on_ratio);
    if (!why.empty())
      throw py::value_error(fmt::format("on_sample: damping_ratio = {} is not allowed for damping model '{}': {}", value,
                                        phase.damping.model, why));
    change.damping_ratio = value;
    return;
  }
  const auto it = std::find(component_names.begin(), component_names.end(), key);
  if (it == component_names.end())
    throw py::value_error(fmt::format(
        "on_sample: unknown control '{}' (allowed: 11, 22, 33, 12, 13, 23, max_strain_rate, rate_factor, friction, "
        "damping_ratio)",
        key));
  const auto c = static_cast<int>(it - component_names.begin());
  ComponentControl& cc = next.component[static_cast<std::size_t>(c)];
  if (cc.kind == ControlKind::fixed || cc.kind == ControlKind::constant_volume)
    throw py::value_error(fmt::format("on_sample: component {} is {} in this phase: it has no value to change "
                                      "(a callback changes values, not kinds)",
                                      key, control_kind_name(cc.kind)));
  if (cc.kind == ControlKind::stress && is_normal(c) && value <= 0)
    throw py::value_error(
        fmt::format("on_sample: stress target {} = {} Pa is not allowed: give a value > 0", key, value));
  cc.value = value;
}

// The changes a callback returns, {"33": value, "friction": value, ...}: every entry is checked
// before any applies (a bad one raises, naming it). True when a control value changed.
bool apply_changes(const py::dict& changes, const Phase& phase, PhaseControls& controls, PhaseChange& change) {
  PhaseControls next = controls;
  for (const auto& [key, value] : changes) apply_change(py::str(key), value, phase, next, change);
  bool changed = next.max_strain_rate != controls.max_strain_rate || next.rate_factor != controls.rate_factor;
  for (std::size_t k = 0; k < component_count; ++k)
    changed = changed || next.component[k].value != controls.component[k].value;
  controls = next;
  return changed;
}

// The phase's controller (if its case gives one), then the Python callback, at each sample point.
class CallbackController : public Controller {
 public:
  CallbackController(std::unique_ptr<Controller> inner, Simulation& sim, int phase)
      : inner_(std::move(inner)), sim_(sim), phase_(phase) {}
  bool at_sample(const SamplePoint& point, PhaseControls& controls) override;
  bool every_step() const override { return inner_ && inner_->every_step(); }
  bool at_step(const State& st, long step, const Mat3& h0, PhaseControls& controls) override {
    return inner_ && inner_->at_step(st, step, h0, controls);
  }
  bool done() const override { return inner_ && inner_->done(); }
  std::vector<double> save() const override { return inner_ ? inner_->save() : std::vector<double>{}; }
  void restore(const std::vector<double>& saved) override {
    if (inner_) inner_->restore(saved);
  }
  void at_end(const SamplePoint& point, const PhaseControls& controls) override {
    if (inner_) inner_->at_end(point, controls);
  }
  nlohmann::json figures() const override { return inner_ ? inner_->figures() : nlohmann::json::object(); }

 private:
  std::unique_ptr<Controller> inner_;
  Simulation& sim_;
  int phase_;
};

bool CallbackController::at_sample(const SamplePoint& point, PhaseControls& controls) {
  const bool changed = inner_ && inner_->at_sample(point, controls);
  py::gil_scoped_acquire gil;
  if (!sim_.callback || sim_.callback.is_none()) return changed;
  py::dict d;
  d["phase"] = phase_, d["phase_name"] = sim_.params().protocol[static_cast<std::size_t>(phase_)].name;
  d["step"] = point.step, d["row"] = point.row;
  d["measures"] = measures_dict(*point.measures);
  d["strain"] = std::vector<double>(point.strain.begin(), point.strain.end());
  d["critical_time"] = point.critical_time;
  d["controls"] = controls_dict(controls, sim_.params().protocol[static_cast<std::size_t>(phase_)]);
  const py::object r = sim_.callback(d);
  if (r.is_none()) return changed;
  if (!py::isinstance<py::dict>(r))
    throw py::type_error("on_sample: the callback returns None or a dict of new control values, e.g. {\"33\": 2e-5}");
  const Phase& phase = sim_.params().protocol[static_cast<std::size_t>(phase_)];
  PhaseChange change;
  const bool controls_changed = apply_changes(r.cast<py::dict>(), phase, controls, change);
  if (change.friction || change.damping_ratio) sim_.change_phase(phase_, change.friction, change.damping_ratio);
  return controls_changed || changed;
}

// The first phase that writes `p`'s file: a run measures the strains of its rows from its start.
int reference_phase(const Params& params, std::size_t p) {
  const std::string& file = params.protocol[p].output.file;
  const auto first = std::find_if(params.protocol.begin(), params.protocol.end(),
                                  [&](const Phase& q) { return q.output.file == file; });
  return static_cast<int>(first - params.protocol.begin());
}

}  // namespace

void Simulation::wrap_controllers() {
  for (std::size_t p = 0; p < params_.protocol.size(); ++p) {
    ControllerFactory inner = params_.protocol[p].make_controller;
    params_.protocol[p].make_controller = [this, inner, p] {
      return std::make_unique<CallbackController>(inner ? inner() : nullptr, *this, static_cast<int>(p));
    };
  }
}

Simulation::Simulation(Params params, bool progress)
    : params_(std::move(params)), progress_(progress ? Progress::detect(false) : Progress::Mode::quiet) {
  wrap_controllers();
  py::gil_scoped_release release;
  st_ = new_sample(params_, run_);
  run_.phases.resize(params_.protocol.size());
}

Simulation::Simulation(const std::string& checkpoint, const std::vector<std::string>& sets, bool progress)
    : progress_(progress ? Progress::detect(false) : Progress::Mode::quiet) {
  Checkpoint c = load_checkpoint(checkpoint);
  params_ = parse_case(c.case_text, c.case_source, sets);
  wrap_controllers();  // first: a callback may have changed the control values the checkpoint holds
  check_checkpoint_case(c, params_, checkpoint);
  st_ = std::move(c.state);
  run_ = std::move(c.run);
  run_.phases.resize(params_.protocol.size());
}

void Simulation::change_phase(int phase, std::optional<double> friction, std::optional<double> damping_ratio) {
  Phase& ph = params_.protocol[static_cast<std::size_t>(phase)];
  if (friction) ph.friction = *friction;
  if (damping_ratio) ph.damping.ratio = *damping_ratio;
  changed_phase_ = ph.name;
  rebuild_ = true;
}

void Simulation::save(const std::string& path) {
  if (!changed_phase_.empty())
    throw RunError(fmt::format("save('{}'): a callback changed the friction or the damping ratio of phase '{}', which "
                               "a checkpoint cannot hold (it holds the case as written, and the control values)",
                               path, changed_phase_));
  py::gil_scoped_release release;
  save_checkpoint(path, params_.case_text, params_.source, st_, run_);
}

long Simulation::step(long n) {
  if (n < 1) throw py::value_error(fmt::format("step(n): n = {} is not allowed: give a whole number >= 1", n));
  if (finished()) throw py::value_error("step(): every phase of the case has ended");
  const auto p = static_cast<std::size_t>(run_.phase);
  const long before = run_.phase_started ? run_.current().steps : 0;
  const long target = n > LONG_MAX - before ? LONG_MAX : before + n;  // the phase's steps when step(n) returns
  const long max_steps = params_.protocol[p].stop.max_steps;
  py::gil_scoped_release release;
  long hooks = 0;  // the hook follows every step but the phase's last
  const StepHook hook = [&](bool) {
    if (++hooks % 256 == 0) {  // Ctrl-C in Python stops the stepping between two steps
      py::gil_scoped_acquire gil;
      if (PyErr_CheckSignals() != 0) throw py::error_already_set();
    }
    const long steps = run_.current().steps;
    // At the step limit the loop itself stops (RunError), as in a run.
    if ((steps >= target || rebuild_) && !(max_steps > 0 && steps >= max_steps)) throw Pause{};
  };
  for (;;) {
    try {
      run_phase(params_, st_, run_, {nullptr, reference_phase(params_, p), {}, nullptr, nullptr}, progress_, hook);
      ++run_.phase;
      run_.phase_started = false;
      run_.state = {};
      rebuild_ = false;
      break;
    } catch (const Pause&) {
      // Continued after a change of the phase: run_phase builds its model again from params_.
      if (std::exchange(rebuild_, false) && run_.current().steps < target) continue;
      break;
    } catch (const InputError& e) {  // what only the run could find, as run_case reports it
      rebuild_ = false;
      throw RunError(fmt::format("{} stopped after {} step {}: {}", params_.protocol[p].name, params_.protocol[p].name,
                                 run_.phases[p].steps - 1, e.what()));
    }
  }
  return run_.phases[p].steps - before;
}

void bind_simulation(py::module_& m) {
  py::class_<Simulation> c(m, "Simulation");
  c.def(py::init([](const std::string& kind, const std::string& value, const std::vector<std::string>& sets,
                    bool progress) {
          if (kind == "checkpoint") return std::make_unique<Simulation>(value, sets, progress);
          return std::make_unique<Simulation>(read_case(kind, value, sets), progress);
        }),
        py::arg("kind"), py::arg("value"), py::arg("sets"), py::arg("progress"))
      .def("step", &Simulation::step, py::arg("n") = 1)
      .def("save", &Simulation::save, py::arg("path"))
      .def("run_phase", [](Simulation& s) { return s.step(LONG_MAX); })
      .def_property_readonly("finished", &Simulation::finished)
      .def_property_readonly("phase", [](const Simulation& s) { return s.run().phase; })
      .def_property_readonly("phases",
                             [](const Simulation& s) {
                               std::vector<std::string> names;
                               for (const Phase& p : s.params().protocol) names.push_back(p.name);
                               return names;
                             })
      .def_property_readonly("phase_steps",
                             [](const Simulation& s) {
                               return s.finished() || !s.run().phase_started ? 0L : s.run().current().steps;
                             })
      .def_property_readonly("steps", [](const Simulation& s) { return s.state().step; })
      .def_property_readonly("time", [](const Simulation& s) { return s.state().time; })
      .def_property_readonly("record",
                             [](const Simulation& s) {
                               return s.finished() || !s.run().phase_started ? py::dict()
                                                                             : record_dict(s.run().current());
                             })
      .def_property_readonly("records",
                             [](const Simulation& s) {
                               py::list l;
                               const int begun = s.run().phase + (s.run().phase_started ? 1 : 0);
                               for (int p = 0; p < std::min<int>(begun, static_cast<int>(s.run().phases.size())); ++p)
                                 l.append(record_dict(s.run().phases[static_cast<std::size_t>(p)]));
                               return l;
                             })
      .def_property_readonly("controls",
                             [](const Simulation& s) {
                               if (s.finished()) return py::dict();
                               const RunProgress& r = s.run();
                               const bool live = r.phase_started && r.state.live;
                               const Phase& phase = s.params().protocol[static_cast<std::size_t>(r.phase)];
                               return controls_dict(live ? r.state.controls : phase.controls, phase);
                             })
      .def("_set_callback", [](Simulation& s, py::object fn) { s.callback = std::move(fn); });
  bind_state(c);
}

}  // namespace qsdem::python
