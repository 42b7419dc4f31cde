// The data of a study's analysis, shared by its computation (study_analysis.cpp) and its
// rendering as tables, figures and the report (study_report.cpp, and the certificate's page,
// converge_page.cpp). Internal to the study layer.
#pragma once
#include <algorithm>
#include <cctype>
#include <cmath>
#include <filesystem>
#include <limits>
#include <map>
#include <optional>
#include <string>
#include <utility>
#include <vector>

#include <nlohmann/json.hpp>

#include "qsdem/run/figures.hpp"
#include "qsdem/study/convergence.hpp"
#include "qsdem/study/study_analysis.hpp"

namespace qsdem::analysis {

namespace fs = std::filesystem;
using nlohmann::json;

constexpr double nan = std::numeric_limits<double>::quiet_NaN();

inline bool same_value(double a, double b) { return a == b || std::abs(a - b) <= 1e-12 * std::max(std::abs(a), std::abs(b)); }

inline bool has_value(const std::vector<double>& v, double x) {
  return std::any_of(v.begin(), v.end(), [&](double y) { return same_value(x, y); });
}

inline bool has_name(const std::vector<std::string>& v, const std::string& x) { return std::find(v.begin(), v.end(), x) != v.end(); }

// The curves of a run (series.csv by header name, SPEC 10).
struct Series {
  std::vector<double> e1, ev, phi, cn, ufr, imom, ekin;
  std::vector<double> q_over_p;  // q_Pa / p_Pa
  std::vector<double> p, void_ratio, fabric_dev;  // p_Pa, void_ratio, fabric_dev (NaN: no column)
};

// A controlled run's controller: study.json "rate_control", summary.json triaxial.controller
// (docs/physics.md 8.5).
struct Control {
  std::string index;   // "imom", "ufr" or "iuf"
  double target = nan;
  double mean_rate = nan, final_rate = nan, min_rate = nan, max_rate = nan;  // |eps'|, mean strain-weighted
  double share_in_band = nan, band_factor = nan, rows = nan;
  double steps_at_final = nan, steps_at_mean = nan;  // a constant-rate run over the same strain
  double mean_index = nan;                           // the mean over the rows of the controlled index
};

// A run of the manifest: its entry, the means of its summary.json, its curves.
struct Run {
  std::string id, sample, model, dir;
  std::string damping_model;  // the case's damping.model (the label's own name for a bare model)
  std::string stage;          // the first stage that lists it ("" without stages)
  long seed = 0;
  double confining_stress = nan, compaction_friction = nan;  // the sample axes (study.json "samples")
  double xi = nan, rate = nan;  // a controlled run: the start rate
  bool controlled = false;      // its rate followed an index: kept out of the groups and fits
  Control control;
  bool finished = false;
  std::string problem;  // why a run counts as missing
  double mean_imom = nan, mean_ufr = nan, mean_iuf = nan, peak_phi = nan, final_ev = nan;
  double mean_ekin = nan, ekin_norm = nan;  // mean ekin_J, and divided by eps'^2 (paper Table 6)
  double steps = nan, wall_s = nan, particles = nan, psps = nan;
  double e0 = nan, p0 = nan;  // void ratio and p (Pa) where the shearing starts (summary.json compaction.final)
  Series s;
};

// One row of the paper's Table 4 with its Fig. 9 fit (SPEC 9).
struct PaperRef {
  double xi_opt, eps_qs, improvement, a, b, r2;
};

// One sampled damping ratio at one (sample, model, eps'): the mean over its finished seeds.
struct Point {
  double xi = nan;
  int n_runs = 0, n_finished = 0;
  double imom = nan, ufr = nan, iuf = nan, phi = nan, ekin_norm = nan;
};

// One (sample, model, eps'): its points and optima.
struct Group {
  std::string sample, model;
  double rate = nan;
  std::vector<Point> points;  // sorted by xi
  OptimumFit opt_imom, opt_ufr;
  const Run* chosen = nullptr;  // the finished run closest to xi_opt (IMom), for Figs. 10-11, 19
};

// One (sample, model): the power law of IMom at the optimum against eps'.
struct Law {
  std::string sample, model;
  PowerLawFit fit;
  double eps_qs = nan;
  std::vector<double> rates, imom_at_opt, xi_opt;  // the points of the fit (Fig. 9) and Fig. 7
  int n_flagged = 0;
  int n_single = 0;  // rates run at one ratio: in the fit, not in xi_opt_geomean/lo/hi
  double xi_opt_geomean = nan, xi_opt_lo = nan, xi_opt_hi = nan;
};

// eps'_QS(model) / eps'_QS(baseline) of one sample (SPEC 9: the paper's ND/OD with baseline od).
struct Improvement {
  std::string sample, model, baseline;
  double eps_qs = nan, eps_qs_baseline = nan, ratio = nan;
};

// Paper Table 6: runs of one (sample, model) with equal xi*eps' (3 significant digits) at
// different rates.
struct EqualSet {
  std::string sample, model, product;
  std::vector<const Run*> runs;
};

// The ratios a stage picked for one (sample, model), as recorded in study.json.
struct Pick {
  std::string sample, model;
  double xi_opt = nan;  // the optimum when the ratios were picked
  std::string method;
  int runs_used = 0;
  std::vector<double> ratios;  // what the stage runs
};

// A stage of study.json ("stages"): which runs it lists (docs/study.md).
struct DesignStage {
  std::string name;
  std::vector<std::string> samples, models;
  std::vector<double> rates, ratios;  // a grid; `ratios` empty when they are picked
  struct Listed {
    std::string model;
    double xi, rate;
  };
  std::vector<Listed> listed;  // a list of runs instead of a grid
  std::string from, pick;      // ratios picked from stage `from`
  double at_rate = nan;
  int digits = 2;
  std::vector<Pick> picks;

  const Pick* pick_of(const std::string& sample, const std::string& model) const {
    for (const Pick& p : picks)
      if (p.sample == sample && p.model == model) return &p;
    return nullptr;
  }
  bool controlled = false;     // rate_control: its runs are controlled ones
  bool lists(const Run& r) const { return r.controlled == controlled && lists(r.sample, r.model, r.xi, r.rate); }
  bool lists(const std::string& sample, const std::string& model, double xi, double rate) const {
    if (!has_name(samples, sample)) return false;
    if (!listed.empty())
      return std::any_of(listed.begin(), listed.end(), [&](const Listed& l) {
        return l.model == model && same_value(l.xi, xi) && same_value(l.rate, rate);
      });
    if (!has_name(models, model) || !has_value(rates, rate)) return false;
    if (from.empty()) return has_value(ratios, xi);
    const Pick* p = pick_of(sample, model);
    return p && has_value(p->ratios, xi);
  }
};

// A stage's pick as it would be made now, against the one recorded when its runs were made.
struct PickCheck {
  const DesignStage* stage;
  const Pick* recorded;         // null: not picked yet
  StageOptimum now;
  std::vector<double> now_ratios;
  bool changed = false;         // the source's optimum now gives other ratios than the runs use
};

constexpr double deviation_strains[] = {0.02, 0.05, 0.10};  // the tables' 2, 5 and 10 % axial strain

// A run against the reference run of its (sample, seed), and its verdict.
struct Deviation {
  const Run* run = nullptr;
  const Run* ref = nullptr;
  CurveDeviation phi, ev, cn;
  int quasi_static = -1;  // 1 yes, 0 no, -1 not decided
  std::string verdict;
};

// A controlled run against the power law of the constant-rate runs of its sample, seed, model and
// damping ratio (the same index against eps'): the rate that law gives at the controller's target.
struct ControlComparison {
  const Run* run = nullptr;
  std::vector<const Run*> fit_runs;  // the finished constant-rate runs of the fit
  PowerLawFit fit;
  double eps_qs = nan;               // (target / a)^(1/b)
  double mean_over_qs = nan, final_over_qs = nan;
};

// A run of a stage of listed runs against the stage's first finished run of the same sample and
// seed (the paper's Table 5 pair, Figs. 10-11: two models, each at its own quasi-static rate).
struct ListedPair {
  const DesignStage* stage = nullptr;
  const Run* run = nullptr;
  const Run* first = nullptr;
  CurveDeviation phi, ev, cn;  // run - first
};

// The scatter between seeds: for each sample with two or more finished reference runs, the
// largest RMS deviation between two of them.
struct SeedScatter {
  std::string sample;
  int seeds = 0;
  double phi = nan, ev = nan, cn = nan;
};

// One ladder of the convergence certificate (docs/analysis.md section 11): the constant-rate runs
// of one (sample, model, ratio) at two or more rates, every seed of the group on each rung.
struct Ladder {
  std::string sample, model;
  double xi = nan;
  std::vector<long> seeds;
  std::vector<double> rates;                    // the complete rungs, fastest first
  std::vector<std::vector<const Run*>> runs;    // per rung, per seed
  std::vector<double> incomplete;               // rates at which a seed has not finished
  Certificate certificate;
  std::vector<double> rung_steps, rung_wall_s;  // per rung, summed over its seeds
  double steps = 0, wall_s = 0;                 // of every run of the complete rungs
};

// The critical state of the constant-rate runs of one (model, ratio, rate) over the samples, and
// their critical state line (docs/analysis.md section 12).
struct CriticalGroup {
  std::string model;
  double xi = nan, rate = nan;
  struct Member {
    const Run* run = nullptr;
    RunCriticalState cs;
    double state_parameter = nan;  // e0 - e_c(p0) on the group's line (Been & Jefferies 1985)
    double off_line = nan;         // e_c - e_c(p'_c) on the line
  };
  std::vector<Member> runs;
  CriticalStateLine line;      // over the members that reached the critical state
  CriticalStateLine line_all;  // over every member's window means, at the critical state or not
};

// Everything the tables, figures and files are made from; groups, laws and deviations point
// into `runs`, so an Analysis is filled in place and never copied.
struct Analysis {
  Analysis() = default;
  Analysis(const Analysis&) = delete;
  Analysis& operator=(const Analysis&) = delete;

  AnalysisSettings settings;  // baseline resolved
  std::vector<Run> runs;
  std::vector<Group> groups;
  std::vector<Law> laws;
  std::vector<Improvement> imps;
  std::vector<EqualSet> equal;
  std::vector<DesignStage> stages;
  std::vector<PickCheck> picks;
  std::map<std::pair<std::string, long>, const Run*> refs;
  std::vector<Deviation> devs;
  std::vector<SeedScatter> scatter;
  std::vector<ControlComparison> controls;
  std::vector<ListedPair> pairs;
  std::vector<Ladder> ladders;
  std::vector<CriticalGroup> critical;  // with [analysis] critical_state

  const Run* reference_of(const std::string& sample) const {  // the first seed's (for figures)
    for (const auto& [key, r] : refs)
      if (key.first == sample) return r;
    return nullptr;
  }
};

// A table, rendered as Markdown and as HTML from the same cells.
struct Table {
  std::string title, note;
  std::vector<std::string> head;
  std::vector<std::vector<std::string>> rows;
  bool detail = false;  // folded (<details>) in the report
};

// A table as HTML: its title as a heading (or a <details> summary), its note, its cells escaped.
std::string to_html(const Table& t);

// A finite number as JSON, NaN and infinities as null.
inline json number_or_null(double v) { return std::isfinite(v) ? json(v) : json(nullptr); }

// A name for a file: letters, digits, '-' and '_' kept, anything else '_' ("0.5" -> "0_5").
inline std::string tag(const std::string& s) {
  std::string r;
  for (char c : s) r += (std::isalnum(static_cast<unsigned char>(c)) || c == '-' || c == '_') ? c : '_';
  return r.empty() ? "_" : r;
}

// Numbers in tables: NaN shown as a dash.
std::string sig(double v, int digits = 3);
std::string pct(double v, int digits = 3);  // a fraction in percent
std::string csvnum(double v);               // 9 significant digits; NaN: empty
std::string read_text(const fs::path& p);
double mean_finite(const std::vector<double>& v);
std::optional<PaperRef> paper_ref(const std::string& sample, const std::string& model);
json paper_reference_json();
const Improvement* find_improvement(const std::vector<Improvement>& imps, const std::string& sample,
                                    const std::string& model);
const OptimumFit* find_opt(const std::vector<Group>& groups, const Run& r);

// The convergence certificate of each ladder of the runs (study_convergence.cpp), its JSON, CSV and table.
std::vector<Ladder> make_ladders(const std::vector<Run>& runs, const ConvergenceTolerances& tol);
json ladders_json(const std::vector<Ladder>& ladders, const ConvergenceTolerances& tol);
std::string ladders_csv(const std::vector<Ladder>& ladders, const ConvergenceTolerances& tol);
Table table_ladders(const std::vector<Ladder>& ladders, const ConvergenceTolerances& tol);

// The critical state of each (model, ratio, rate) (study_critical_state.cpp), its JSON, CSV,
// tables and figures.
std::vector<CriticalGroup> make_critical_groups(const std::vector<Run>& runs, const CriticalStateSettings& settings);
json critical_json(const std::vector<CriticalGroup>& groups, const CriticalStateSettings& settings);
std::string critical_csv(const std::vector<CriticalGroup>& groups);
std::vector<Table> critical_tables(const std::vector<CriticalGroup>& groups, const CriticalStateSettings& settings);
void add_critical_figures(std::vector<Figure>& figs, const std::vector<CriticalGroup>& groups);

// Rendering (study_report.cpp).
std::vector<Table> make_tables(const Analysis& a);
std::string to_markdown(const Table& t);
std::vector<Figure> make_figures(const Analysis& a);
std::string report_html(const json& a, const AnalysisSettings& settings, const std::vector<Table>& tables,
                        const std::vector<Figure>& figs, const std::vector<bool>& drawn, const std::vector<Run>& runs,
                        const std::string& toml);

}  // namespace qsdem::analysis
