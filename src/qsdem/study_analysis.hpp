// Analysis of a study (SPEC 9): optimum damping ratio, power law of the moment index against the
// strain rate, quasi-static rate, tables, figures (gnuplot) and an HTML report.
// The choices (fits, averaging, flags) are documented in docs/analysis.md.
#pragma once
#include <filesystem>
#include <limits>
#include <span>
#include <string>

#include <nlohmann/json.hpp>

namespace qsdem {

// Minimum of an equilibrium index (mean IMom or mean UFR) over the damping ratio xi at one
// (sample, model, eps'), SPEC 9 / paper Figs. 3-8.
struct OptimumFit {
  static constexpr double nan = std::numeric_limits<double>::quiet_NaN();
  double xi_opt = nan;        // fitted (or sampled) optimum damping ratio, fraction
  double index_at_opt = nan;  // index there (parabola value when fitted)
  double xi_min = nan;        // sampled minimum
  double index_min = nan;
  int n_points = 0;           // points used (xi > 0, index > 0, finite)
  // "parabola": convex vertex of the log-log parabola through the minimum and its neighbours;
  // "edge": minimum at the end of the sampled range (no extrapolation);
  // "sampled-minimum": parabola not convex; "none": no usable point.
  std::string method = "none";
  std::string flag;           // "" when the parabola was used, else why not (human readable)
  bool at_edge = false;
  // v = c2 u^2 + c1 u + c0 with u = log10 xi, v = log10 index (only for "parabola"/"sampled-minimum")
  double c2 = nan, c1 = nan, c0 = nan;
};

// xi and index of equal length; points with xi <= 0 (xi = 0 cannot enter a log fit), index <= 0
// or non-finite values are ignored. The order of the input does not matter.
OptimumFit fit_optimum(std::span<const double> xi, std::span<const double> index);

// y = a x^b by least squares on (log10 x, log10 y), SPEC 9 / paper Fig. 9.
struct PowerLawFit {
  static constexpr double nan = std::numeric_limits<double>::quiet_NaN();
  double a = nan;
  double b = nan;
  double r2 = nan;
  int n = 0;          // points used (x > 0, y > 0, finite)
  bool ok = false;    // n >= 2 and x not all equal
  std::string note;   // e.g. "n=2: R^2 = 1 by construction"
};

PowerLawFit fit_power_law(std::span<const double> x, std::span<const double> y);

// The strain rate where the fitted power law gives IMom = imom_qs (0.1 % in the paper, Table 4):
// eps'_QS = (imom_qs / a)^(1/b). NaN when the fit is unusable or b <= 0.
double quasi_static_rate(const PowerLawFit& fit, double imom_qs = 1e-3);

// Throws std::runtime_error naming the Debian package (gnuplot-nox) when gnuplot cannot be run.
void require_gnuplot();

// Reads DIR/study.json (the manifest written by `qsdem study`) and every finished run's
// summary.json and series.csv; writes DIR/analysis/ (tables, figures) and DIR/report.html.
// Returns the analysis as JSON (also written to DIR/analysis/analysis.json).
// Unfinished runs (no summary.json) are listed as missing, never fatal.
nlohmann::json analyze_study(const std::filesystem::path& dir);

}  // namespace qsdem
