// `qsdem converge`: a case's quasi-static certificate (docs/analysis.md section 11). The case is
// prepared with several seeds and sheared at a ladder of falling strain rates, rung by rung, as a
// study (docs/study.md: it resumes, runs in parallel and over MPI); after each rung the analysis
// certifies the ladder so far, and the ladder stops at the first converged certificate, at its
// last rung or at the step budget.
#pragma once
#include <filesystem>
#include <limits>
#include <string>
#include <vector>

#include <nlohmann/json.hpp>

#include "qsdem/study/convergence.hpp"

namespace qsdem {

struct LadderOptions {
  std::filesystem::path case_file;  // empty: the built-in default case
  std::vector<std::string> sets;    // --set overrides of the case (preparation and runs)
  std::filesystem::path out;
  int seeds = 3;                    // samples prepared with sample.seed = 1 .. seeds
  double start_rate = std::numeric_limits<double>::quiet_NaN();  // NaN: the case's triaxial.strain_rate
  double factor = 3.16227766016838;  // eps' of a rung / eps' of the next (sqrt 10)
  int rungs = 4;                     // at most
  double max_steps = std::numeric_limits<double>::infinity();  // triaxial steps of every run together
  ConvergenceTolerances tolerances;
  int parallel = 0;                  // > 0: child processes at once
  bool quiet = false;
};

// The study file of the ladder (written to DIR/study.toml): one [[sample]] of the case with the
// seeds, its damping model and ratio, and a stage `rung-K` per rate. Throws InputError on a bad
// option or case.
std::string ladder_study_text(const LadderOptions& options);

// Runs the ladder in options.out and writes DIR/certificate.json (docs/analysis.md section 11).
// Returns 0 when converged, 4 when not, 2 (bad input), 3 (failed runs or analysis), 128 + signal.
int run_ladder(const LadderOptions& options);

}  // namespace qsdem
