// The Python module's Simulation (docs/python.md "Stepping"): a case stepped from Python through the
// phase loop of a run (run_phase), without files, and its state read as numpy copies.
#pragma once

#include <pybind11/numpy.h>
#include <pybind11/pybind11.h>

#include <optional>
#include <string>
#include <vector>

#include "qsdem/engine/state.hpp"
#include "qsdem/run/config.hpp"
#include "qsdem/run/progress.hpp"
#include "qsdem/run/protocol.hpp"

namespace qsdem::python {

namespace py = pybind11;

// The case as the Python part gives it: a file (kind "path"), TOML text ("text") or the built-in
// default case ("default"), with --set strings. Throws InputError as the CLI's reading does.
Params read_case(const std::string& kind, const std::string& value, const std::vector<std::string>& sets);

class Simulation {
 public:
  // Makes the sample as a run does (new_sample); every phase's controller is wrapped so that the
  // Python callback is called at its sample points.
  Simulation(Params params, bool progress);
  // Continues the run a checkpoint holds (written by save, in the format of a run's checkpoint): its case
  // (with `sets`, as `qsdem resume --set`), state and place in its phases.
  Simulation(const std::string& checkpoint, const std::vector<std::string>& sets, bool progress);
  Simulation(const Simulation&) = delete;  // its controllers point to it
  Simulation& operator=(const Simulation&) = delete;

  bool finished() const { return run_.phase >= static_cast<int>(params_.protocol.size()); }
  // Up to n steps of the current phase (fewer when it ends); returns the steps taken. The GIL is
  // released while stepping; Ctrl-C (a Python signal) stops it between two steps.
  long step(long n);

  // The phase's friction and damping ratio, changed by a callback: the model is rebuilt with them
  // from the next step (the loop pauses and continues, as after step(n)).
  void change_phase(int phase, std::optional<double> friction, std::optional<double> damping_ratio);

  // The state and the place in the phases as a checkpoint file (written atomically), which the
  // checkpoint constructor continues with the same bits. Refused (RunError) after a callback
  // changed a phase's friction or damping ratio: the checkpoint holds the case as written.
  void save(const std::string& path);

  py::object callback;  // on_sample's function, or None
  const Params& params() const { return params_; }
  const State& state() const { return st_; }
  const RunProgress& run() const { return run_; }

 private:
  Params params_;
  State st_;
  RunProgress run_;
  Progress progress_;
  bool rebuild_ = false;  // a callback changed the phase: pause after this step and continue
  std::string changed_phase_;  // the name of a phase whose friction or damping a callback changed
  void wrap_controllers();
};

// state.cpp: the state and the measures as Python objects (copies).
py::array_t<double> matrix(const Mat3& a);
py::dict measures_dict(const Measures& m);
// The control values and the phase's friction and damping ratio, as a callback reads and changes them.
py::dict controls_dict(const PhaseControls& c, const Phase& phase);
py::dict record_dict(const PhaseRecord& r);
// The contacts of the last force evaluation, by particle id (docs/python.md).
py::dict contacts_dict(const State& st);
// The state's members of the Simulation class (ids, positions, ..., cell, stress, contacts).
void bind_state(py::class_<Simulation>& c);

// simulation.cpp: the Simulation class, with its stepping and callback members.
void bind_simulation(py::module_& m);

}  // namespace qsdem::python
