// The quasi-static certificate (docs/analysis.md, "Convergence with the rate"): a case run at a
// ladder of decreasing strain rates on the same prepared samples, one per seed; the response
// curves of each rung compared, seed by seed, with those of the slowest rung; the fastest rate
// whose response lies within the tolerances of the slowest, and the response's limit as the rate
// falls. The decision only: the runs are made by the caller.
#pragma once
#include <cstddef>
#include <limits>
#include <optional>
#include <string>
#include <vector>

namespace qsdem {

// One run's response as its series.csv writes it (SPEC 10.1: e1, ev, phi_deg, cn, q_Pa / p_Pa).
struct ResponseCurve {
  std::vector<double> e1, phi_deg, ev, cn, q_over_p;
};

// One rung of the ladder: a strain rate and one curve per seed, the seeds in the same order on
// every rung (seed s of every rung starts from the same prepared sample).
struct Rung {
  double rate = 0;  // eps' of the loading phase (1/s)
  std::vector<ResponseCurve> seeds;
};

// When a rung counts as the slowest one's response (docs/analysis.md section 11; the defaults
// fixed before any run): the change of phi and of ev beyond the noise of its seed mean
// (CurveChange::excess), each at most its tolerance, its standard error too (a change the seeds
// cannot resolve certifies nothing), and, with two or more seeds and within_seed_scatter, the
// excess at most the seed-to-seed scatter of the slowest rung's response (a rate effect smaller
// than the choice of sample).
// Optionally also the change of ev at the end (the last strain every curve reaches), seed-paired,
// beyond its noise: the RMS over the strain weighs the end, where ev accumulates a rate effect, no
// more than the start (NaN: not judged, the default).
struct ConvergenceTolerances {
  static constexpr double nan = std::numeric_limits<double>::quiet_NaN();
  double phi_rms_deg = 0.5;  // degrees
  double ev_rms = 1e-3;      // volumetric strain (0.1 %)
  bool within_seed_scatter = true;
  double ev_end = nan;       // |change of ev at the end| (volumetric strain); NaN: off
};

// The change of one measure between two rungs: the seed mean, at each strain of the grid, of
// (curve at the rung minus curve at the other rung) of the same seed, then its RMS over the
// grid; `error` is the RMS of the standard error of that mean (0 with one seed); `excess` is the
// change beyond that noise, sqrt(max(0, rms^2 - error^2)): the mean square of a seed mean is the
// square of the true change plus the squared standard error, and the sample variance estimates the
// latter without bias, so excess^2 estimates the true mean square change without bias.
struct CurveChange {
  static constexpr double nan = std::numeric_limits<double>::quiet_NaN();
  double rms = nan;
  double error = nan;
  double excess = nan;
};

// A scalar of the response (peak phi, its strain, and the values at the last common strain),
// per rung the seed mean and its standard error.
struct ScalarLimit {
  static constexpr double nan = std::numeric_limits<double>::quiet_NaN();
  std::string name;
  std::vector<double> mean, error;  // one per rung
  // The limit as the rate falls: the slowest rung's mean, or, where the last three rungs change
  // monotonically and by shrinking steps in log eps', their Aitken extrapolation; `band` is the
  // larger of the extrapolation's distance from the slowest rung (else the last change) and the
  // slowest rung's standard error.
  double limit = nan, band = nan;
  bool extrapolated = false;
};

struct RungVerdict {
  double rate = 0;
  CurveChange phi_to_slowest, ev_to_slowest;  // against the slowest rung
  CurveChange phi_to_next, ev_to_next;        // against the next slower rung
  // ev at the end against the slowest and the next slower rung: the change at one strain (its
  // `rms` is |seed mean|), computed whether or not ConvergenceTolerances::ev_end judges it
  CurveChange ev_end_to_slowest, ev_end_to_next;
  bool within = false;                        // phi_to_slowest, ev_to_slowest within the tolerances
  bool resolved = false;                      // their standard errors within the tolerances
};

struct Certificate {
  static constexpr double nan = std::numeric_limits<double>::quiet_NaN();
  // "converged": the last change (the two slowest rungs) is within the tolerances;
  // "not resolved": its excess is, but its standard error is not (more seeds would decide);
  // "not converged": its excess is not, or the ladder has one rung.
  std::string status = "not converged";
  std::string reason;                  // a sentence for the reader
  std::optional<std::size_t> certified;  // the fastest rung whose response and every slower rung's
                                         // are within the tolerances of the slowest (converged only)
  double phi_scatter_deg = nan, ev_scatter = nan;  // seed-to-seed scatter at the slowest rung (RMS of the
                                                   // standard deviation over the grid; NaN with one seed)
  bool limit_resolved = true;  // the slowest rung's standard error within the tolerances
  std::vector<RungVerdict> rungs;
  std::vector<ScalarLimit> scalars;  // peak_phi_deg, e1_at_peak, and phi_deg, ev, cn, q_over_p at the end

  const ScalarLimit* scalar(const std::string& name) const {  // nullptr when not computed
    for (const ScalarLimit& s : scalars)
      if (s.name == name) return &s;
    return nullptr;
  }
};

// Whether a change's part beyond the noise (CurveChange::excess) is within the tolerances of phi and
// ev, and of ev at the end when that tolerance is set; NaN (no common strain) is not.
bool within_tolerances(const CurveChange& phi, const CurveChange& ev, const CurveChange& ev_end,
                       const ConvergenceTolerances& tol);

// The certificate of a ladder ordered from the fastest rate to the slowest (rates strictly
// decreasing, every rung with the same number of seeds >= 1); std::invalid_argument otherwise.
// The strain grid is the slowest rung's first seed's e1; a curve is compared where both cover it.
Certificate certify(const std::vector<Rung>& ladder, const ConvergenceTolerances& tol = {});

}  // namespace qsdem
