// The Python module qsdem._qsdem (docs/python.md): whole runs through the functions the CLI calls
// (run_case, resume_run, run_study, analyze_study), and the Simulation class (simulation.cpp,
// state.cpp). The Python part (python/qsdem/__init__.py) turns case arguments and overrides into
// the CLI's strings and reads run directories.
#include <pybind11/pybind11.h>
#include <pybind11/stl.h>

#include <omp.h>

#include <string>
#include <vector>

#include "qsdem/default_case.hpp"
#include "qsdem/run/config.hpp"
#include "qsdem/run/files.hpp"
#include "qsdem/run/plot.hpp"
#include "qsdem/run/run.hpp"
#include "qsdem/study/study.hpp"
#include "qsdem/study/study_analysis.hpp"
#include "qsdem/version.hpp"
#include "simulation.hpp"

namespace qsdem::python {

Params read_case(const std::string& kind, const std::string& value, const std::vector<std::string>& sets) {
  if (kind == "path") return load_case(value, sets);
  if (kind == "text") return parse_case(value, "<string>", sets);
  return parse_case(default_case_toml, default_case_name, sets);
}

namespace {

// --threads: the OpenMP threads of the whole process (0: all cores).
void set_threads(int threads) {
  if (threads < 0 || threads > 256)
    throw InputError(
        fmt::format("threads = {} is not allowed: give a whole number from 0 (all cores) to 256", threads));
  if (threads > 0) omp_set_num_threads(threads);
}

std::string run_py(const std::string& kind, const std::string& value, const std::vector<std::string>& sets,
                   const std::string& out, bool progress, bool prepare, bool force) {
  const Params params = read_case(kind, value, sets);
  py::gil_scoped_release release;
  return json_text(run_case(params, {out, !progress, prepare, force}), -1);
}

std::string resume_py(const std::string& dir, const std::vector<std::string>& sets, bool progress) {
  RunOptions options;
  options.out = dir, options.quiet = !progress, options.sets = sets;
  py::gil_scoped_release release;
  return json_text(resume_run(dir, options), -1);
}

int study_py(const std::string& file, const std::string& out, bool progress, int parallel, const std::string& order,
             const std::string& executable) {
  if (parallel < 0) throw InputError(fmt::format("parallel = {} is not allowed: give a whole number >= 1", parallel));
  if (!order.empty() && order != "longest_first" && order != "shortest_first")
    throw InputError(fmt::format("order = '{}' is not allowed (allowed: longest_first, shortest_first)", order));
  StudyOptions options;
  options.out = out, options.quiet = !progress, options.parallel = parallel, options.order = order;
  options.executable = executable.empty() ? QSDEM_CLI : executable;
  options.again = fmt::format("qsdem.study('{}', out='{}')", file, out);
  py::gil_scoped_release release;
  return run_study(file, options);
}

// `qsdem plot`: the page and the figures drawn, and the ones left out with why.
py::dict plot_py(const std::string& dir, const std::string& out) {
  PlotResult r;
  {
    py::gil_scoped_release release;
    r = plot_run(dir, out);
  }
  py::dict d;
  d["page"] = r.page.string();
  d["figures"] = r.figures;
  d["notes"] = r.notes;
  return d;
}

std::string analyze_py(const std::string& dir) {
  py::gil_scoped_release release;
  return json_text(analyze_study(dir), -1);
}

// The run layer's exceptions as Python's: CaseError (a ValueError) for what the CLI reports as an
// input error, RunError for a run that cannot go on, Interrupted (a KeyboardInterrupt) for a run
// stopped by SIGINT or SIGTERM.
void bind_errors(py::module_& m) {
  static py::exception<InputError> case_error(m, "CaseError", PyExc_ValueError);
  static py::exception<RunError> run_error(m, "RunError", PyExc_RuntimeError);
  static py::exception<Interrupted> interrupted(m, "Interrupted", PyExc_KeyboardInterrupt);
  py::register_exception_translator([](std::exception_ptr p) {
    try {
      if (p) std::rethrow_exception(p);
    } catch (const Interrupted& e) {
      interrupted(e.what());
    } catch (const InputError& e) {
      case_error(e.what());
    } catch (const RunError& e) {
      run_error(e.what());
    }
  });
}

}  // namespace
}  // namespace qsdem::python

PYBIND11_MODULE(_qsdem, m) {
  using namespace qsdem;
  using namespace qsdem::python;
  m.doc() = "qsdem: quasi-static DEM of spheres and ellipsoids in a deformable periodic cell (docs/python.md)";
  m.attr("__version__") = QSDEM_VERSION;
  m.attr("cli") = QSDEM_CLI;
  m.attr("default_case_toml") = default_case_toml;
  bind_errors(m);
  m.def("check_case", [](const std::string& kind, const std::string& value, const std::vector<std::string>& sets) {
    return json_text(to_json(read_case(kind, value, sets)), -1);
  });
  m.def("set_threads", &set_threads);
  m.def("max_threads", [] { return omp_get_max_threads(); });
  m.def("run", &run_py);
  m.def("resume", &resume_py);
  m.def("study", &study_py);
  m.def("analyze", &analyze_py);
  m.def("plot", &plot_py);
  bind_simulation(m);
}
