// Analysis of a study (SPEC 9): optimum damping ratio, power law of the moment index against the
// strain rate, quasi-static rate, improvement over a baseline model, the damping dependence of the
// response (deviation from a reference run), tables, figures (gnuplot) and an HTML report.
// The choices (fits, averaging, flags, tolerances) are documented in docs/analysis.md.
#pragma once
#include <cmath>
#include <filesystem>
#include <limits>
#include <span>
#include <string>
#include <vector>

#include <nlohmann/json.hpp>

#include "qsdem/study/convergence.hpp"

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
  // "single": one usable point, its value (no minimum to find);
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

// Deviation of a curve y(e1) from a reference curve y_ref(e1_ref) (docs/analysis.md, damping
// dependence): the run's curve is interpolated linearly at the reference's strains that lie in
// the common strain range; rms is the root mean square of the differences there (run minus
// reference). at[k] is the difference at strain at_strains[k], both curves interpolated; NaN
// outside either curve's range. Strains need not be sorted; non-finite points are skipped.
struct CurveDeviation {
  static constexpr double nan = std::numeric_limits<double>::quiet_NaN();
  double rms = nan;
  std::vector<double> at;  // one per at_strains entry
  int n = 0;               // reference points in the common range
  double e1_lo = nan, e1_hi = nan;  // the common range
};

CurveDeviation curve_deviation(std::span<const double> e1_ref, std::span<const double> y_ref,
                               std::span<const double> e1, std::span<const double> y,
                               std::span<const double> at_strains);

// The critical state of each run and the critical state line ([analysis] critical_state,
// docs/analysis.md section 12): the window of axial strain the critical values are the means of,
// and the slopes under which the run counts as at the critical state there.
struct CriticalStateSettings {
  bool on = false;
  double from = 0.30;               // the window: e1 >= from, to the end of the run
  double ev_slope = 0.05;           // |d ev / d e1| over the window (least squares), at most
  double stress_ratio_slope = 0.5;  // |d(q/p') / d e1| / mean(q/p') over the window, at most
};

// The curves of one drained run that its critical state is read from (series.csv columns).
struct DrainedCurves {
  std::span<const double> e1, ev, phi_deg, p, stress_ratio, void_ratio;  // stress_ratio: q/p
  std::span<const double> fabric_dev;  // empty or NaN: not written
  double e0 = std::numeric_limits<double>::quiet_NaN();  // the state the shearing starts from (the
  double p0 = std::numeric_limits<double>::quiet_NaN();  // first row's when NaN)
};

// The critical state of one run (docs/analysis.md section 12): its start, peak and dilatancy, and
// the means over the window e1 >= from.
struct RunCriticalState {
  static constexpr double nan = std::numeric_limits<double>::quiet_NaN();
  double e0 = nan, p0 = nan;                             // void ratio and p' (Pa) at the start
  double peak_phi_deg = nan, peak_e1 = nan;              // the largest phi and its axial strain
  double max_dilatancy_deg = nan, max_dilatancy_e1 = nan;  // psi_max (triaxial_dilatancy_angle_deg)
  int rows = 0;                                          // rows in the window
  double phi_deg = nan, stress_ratio = nan, void_ratio = nan, p = nan, fabric_dev = nan;  // window means
  double ev_slope = nan, stress_ratio_slope = nan;  // d ev/d e1 and d(q/p')/d e1 / mean(q/p') (least squares)
  bool reached = false;  // rows >= 3 and both slopes within the settings' bounds
};

// The half width (axial strain) of the window of the local dilatancy slope.
constexpr double dilatancy_half_window = 0.01;

// The dilatancy angle of a drained triaxial compression (Schanz & Vermeer 1996), from the slope
// d ev/d e1 of the engineering strains (ev dilation positive, e1 compression positive) at (e1, ev):
// with the natural increments dv = d ev/(1 + ev) and d eps1 = d e1/(1 - e1),
// sin psi = dv / (2 d eps1 + dv). Degrees; NaN when the slope gives |sin psi| > 1.
double triaxial_dilatancy_angle_deg(double dev_de1, double e1, double ev);

RunCriticalState critical_state_of(const DrainedCurves& c, const CriticalStateSettings& settings);

// The critical state line e_c = Gamma - lambda ln(p'_c / 1 kPa) by least squares over the runs' window
// means, and M = q/p' at the critical state (the mean of the runs' stress ratios).
struct CriticalStateLine {
  static constexpr double nan = std::numeric_limits<double>::quiet_NaN();
  int n = 0;                                   // runs used
  double gamma = nan, lambda = nan;            // e at p' = 1 kPa; slope against ln p'
  double gamma_se = nan, lambda_se = nan;      // standard errors (n >= 3)
  double r2 = nan, rms_residual = nan;         // of e_c about the line
  double p_lo = nan, p_hi = nan;               // the range of p'_c (Pa)
  double M = nan, M_sd = nan;                  // mean and standard deviation of (q/p')_c
  double phi_cs_deg = nan;                     // from M: sin phi = 3 M / (6 + M)
  bool ok = false;                             // n >= 2 and the p'_c differ by more than 1 %
  std::string note;
  double void_ratio_at(double p) const { return gamma - lambda * std::log(p / 1e3); }
};

CriticalStateLine fit_critical_state_line(std::span<const double> p, std::span<const double> void_ratio,
                                          std::span<const double> stress_ratio);

// The study's analysis settings ([analysis] of the study file, study.json "analysis").
struct AnalysisSettings {
  static constexpr double nan = std::numeric_limits<double>::quiet_NaN();
  std::string baseline;        // model label; "": the first model of the design
  double imom_target = 1e-3;   // mean IMom below it counts as quasi-static (SPEC 9: 0.1 %)
  bool has_reference = false;  // the damping dependence is assessed only with a reference
  // The reference run of each (sample, seed): the runs matching the given fields (empty / NaN:
  // any), then those at the slowest rate, then the least damped (none counts as xi = 0).
  std::string reference_model;
  double reference_ratio = nan, reference_rate = nan;
  double phi_tolerance_deg = 1.0;  // RMS deviation of phi(e1) from the reference, degrees
  double ev_tolerance = 0.005;     // RMS deviation of ev(e1), volumetric strain as a fraction
  double cn_tolerance = nan;       // RMS deviation of the coordination number; NaN: not checked
  ConvergenceTolerances convergence;  // the certificate of the ladders (section 11)
  CriticalStateSettings critical_state;
};

nlohmann::ordered_json to_json(const AnalysisSettings& s);
// Missing keys keep their defaults (a manifest written before the settings existed).
AnalysisSettings analysis_settings_from_json(const nlohmann::json& j);

// The IMom optimum of one (sample, model) over the finished runs of one stage of a study, as
// the analysis computes it (docs/analysis.md section 2); the ratios a later stage picks from it
// (docs/study.md, staged designs).
struct StageOptimum {
  static constexpr double nan = std::numeric_limits<double>::quiet_NaN();
  std::string sample, model;
  double xi_opt = nan;          // at `at_rate`, or the geometric mean over the stage's rates
  std::string method;           // "geometric mean of k rates" or the fit's method at one rate
  std::vector<double> sampled;  // the stage's ratios xi > 0 of this (sample, model), ascending
  int runs_used = 0;            // finished runs the optimum comes from
};

// `manifest` is study.json's content; `stage` the name of one of its stages. at_rate NaN: every
// rate of the stage.
std::vector<StageOptimum> stage_optima(const std::filesystem::path& dir, const nlohmann::json& manifest,
                                       const std::string& stage, double at_rate);

// The ratios picked from an optimum: "optimum" gives xi_opt rounded to `digits` significant
// digits; "optimum+neighbours" adds the nearest sampled ratios below and above it. Empty when
// xi_opt is not finite.
std::vector<double> pick_ratios(const StageOptimum& o, const std::string& pick, int digits);

// Throws std::runtime_error naming the Debian package (gnuplot-nox) when gnuplot cannot be run.
void require_gnuplot();

// Reads DIR/study.json (the manifest written by `qsdem study`) and every finished run's
// summary.json and series.csv; writes DIR/analysis/ (tables, figures) and DIR/report.html.
// Returns the analysis as JSON (also written to DIR/analysis/analysis.json).
// Unfinished runs (no summary.json) are listed as missing, never fatal.
nlohmann::json analyze_study(const std::filesystem::path& dir);

}  // namespace qsdem
