// Rendering of a study's analysis (SPEC 9): tables as Markdown and HTML from the same cells,
// figures drawn by gnuplot (paper Figs. 3-19), and the one-page HTML report. docs/analysis.md.
#include <algorithm>
#include <cctype>
#include <cmath>
#include <optional>
#include <string>
#include <tuple>
#include <vector>

#include <fmt/format.h>

#include "qsdem/run/figures.hpp"
#include "qsdem/run/output.hpp"
#include "qsdem/study/study_analysis_data.hpp"
#include "qsdem/version.hpp"

namespace qsdem::analysis {

namespace {

std::string md_escape(const std::string& s) {
  std::string r;
  for (char c : s) r += c == '|' ? std::string("\\|") : std::string(1, c);
  return r;
}

// File-name-safe tag for sample/model names.

// ---------------------------------------------------------------------------------------------
// Tables
// ---------------------------------------------------------------------------------------------

std::string fit_text(double a, double b) {
  return std::isfinite(a) ? fmt::format("{} ε'^{}", sig(a, 5), sig(b, 4)) : "—";
}

std::string list_text(const std::vector<double>& v, bool percent) {
  std::string s;
  for (double x : v) s += (s.empty() ? "" : ", ") + (percent ? pct(x) : sig(x));
  return s;
}

std::string trio(const CurveDeviation& c, double scale, int digits = 3) {
  std::string s;
  for (double x : c.at) s += (s.empty() ? "" : " / ") + sig(scale * x, digits);
  return s;
}

// Table 4 of the paper, one row per (sample, model).
Table table_power_law(const Analysis& a) {
  Table t{"Optimum damping ratio, power law and quasi-static rate (paper Table 4, Fig. 9)",
          fmt::format("ξopt: geometric mean over the rates of the IMom optimum [range], rates run at one ratio "
                      "left out; IMom at ξopt: at the "
                      "lowest and highest rate; fit IMom = a ε'^b over the rates (log-log least squares); "
                      "ε'QS where the fit gives IMom = {} %; improvement = ε'QS(model)/ε'QS({}). Paper columns "
                      "only for samples named A*/B* and models od/nd.",
                      pct(a.settings.imom_target), a.settings.baseline),
          {"sample", "model", "ξopt (%)", "paper ξopt (%)", "IMom at ξopt (%)", "a", "b", "R²",
           "paper fit (Fig. 9)", "ε'QS", "paper ε'QS", "improvement", "paper improvement"},
          {}};
  for (const Law& l : a.laws) {
    const auto ref = paper_ref(l.sample, l.model);
    const auto base_ref = paper_ref(l.sample, a.settings.baseline);
    std::string imr = "—";
    if (!l.imom_at_opt.empty())
      imr = fmt::format("{} (ε' {}) … {} (ε' {})", pct(l.imom_at_opt.front()), sig(l.rates.front()),
                        pct(l.imom_at_opt.back()), sig(l.rates.back()));
    std::string r2 = sig(l.fit.r2, 4);
    if (!l.fit.note.empty()) r2 += " (" + l.fit.note + ")";
    if (l.n_flagged) r2 += fmt::format(" [{} of {} optima not from the parabola]", l.n_flagged, l.rates.size());
    const Improvement* im = find_improvement(a.imps, l.sample, l.model);
    t.rows.push_back({l.sample, l.model,
                      (std::isfinite(l.xi_opt_geomean)
                           ? fmt::format("{} [{}–{}]", pct(l.xi_opt_geomean), pct(l.xi_opt_lo), pct(l.xi_opt_hi))
                           : "—") +
                          (l.n_single ? fmt::format(" (over {} of {} rates: {} run at one ratio)",
                                                    l.rates.size() - l.n_single, l.rates.size(), l.n_single)
                                      : ""),
                      ref ? pct(ref->xi_opt) : "", imr, sig(l.fit.a, 5), sig(l.fit.b, 4), r2,
                      ref ? fmt::format("{}, R² = {}", fit_text(ref->a, ref->b), sig(ref->r2, 4)) : "",
                      sig(l.eps_qs), ref ? sig(ref->eps_qs) : "", im ? sig(im->ratio) : "—",
                      ref && base_ref ? sig(ref->improvement / base_ref->improvement) : ""});
  }
  return t;
}

// The optimum at each rate (paper Figs. 7-8).
Table table_optima(const Analysis& a) {
  Table t{"Optimum damping ratio at each rate (paper Figs. 7 and 8)",
          "Parabola in (log10 ξ, log10 index) through the sampled minimum and its neighbours; "
          "flags say when the sampled minimum is reported instead.",
          {"sample", "model", "ε'", "ξopt IMom (%)", "IMom at ξopt (%)", "IMom fit", "ξopt UFR (%)",
           "UFR at ξopt (%)", "UFR fit", "run shown in curves"},
          {}};
  auto how = [](const OptimumFit& f) { return f.flag.empty() ? f.method : f.method + ": " + f.flag; };
  for (const Group& g : a.groups)
    t.rows.push_back({g.sample, g.model, sig(g.rate), pct(g.opt_imom.xi_opt), pct(g.opt_imom.index_at_opt),
                      how(g.opt_imom), pct(g.opt_ufr.xi_opt), pct(g.opt_ufr.index_at_opt), how(g.opt_ufr),
                      g.chosen ? g.chosen->id : "—"});
  return t;
}

// Per (sample, model, rate): every xi (paper Figs. 3-6, 13-14).
Table table_points(const Group& g) {
  Table t{fmt::format("{} {} ε' = {}: indices against the damping ratio", g.sample, g.model, sig(g.rate)),
          "",
          {"ξ (%)", "runs finished", "mean IMom (%)", "mean UFR (%)", "mean Iuf (%)", "peak φ (°)", "Ekin/ε'² (J)"},
          {}};
  for (const Point& p : g.points) {
    const std::string fin = fmt::format("{}/{}", p.n_finished, p.n_runs) + (p.n_finished ? "" : " missing");
    t.rows.push_back({pct(p.xi), fin, pct(p.imom), pct(p.ufr), pct(p.iuf), sig(p.phi, 4), sig(p.ekin_norm)});
  }
  t.detail = true;
  return t;
}

// Table 6 of the paper: runs with equal xi*eps'.
Table table_equal(const Analysis& a) {
  Table t{"Runs with equal ξ·ε' (paper Table 6)",
          "Ekin/ε'²: mean kinetic energy over the series rows divided by ε'². ξopt: the IMom optimum "
          "at the run's rate.",
          {"run", "ξ (%)", "ε'", "ξ·ε'", "ξopt (%)", "peak φ (°)", "Ekin/ε'² (J)", "mean IMom (%)", "mean UFR (%)"},
          {}};
  for (const EqualSet& e : a.equal)
    for (const Run* r : e.runs) {
      const OptimumFit* o = find_opt(a.groups, *r);
      t.rows.push_back({r->id, pct(r->xi), sig(r->rate), sig(r->xi * r->rate), o ? pct(o->xi_opt) : "—",
                        sig(r->peak_phi, 4), sig(r->ekin_norm), pct(r->mean_imom), pct(r->mean_ufr)});
    }
  return t;
}

Table table_paper6() {
  Table t{"Paper Table 6 (Sample B, OD), for comparison", "",
          {"model", "ξ (%)", "ε'", "ξ·ε'", "ξopt (%)", "peak φ (°)", "Ekin/ε'² (J)", "mean IMom (%)", "mean UFR (%)"},
          {}};
  const json paper = paper_reference_json();  // named: a temporary's member would dangle in the loop
  for (const json& p : paper["table6_B_od"]) {
    const double xi = p["xi"], rate = p["rate"];
    t.rows.push_back({p["model"].get<std::string>(), pct(xi), sig(rate), sig(xi * rate),
                      pct(p["xi_opt"].get<double>()), sig(p["peak_phi_deg"].get<double>(), 4),
                      sig(p["ekin_over_rate2_J"].get<double>()), pct(p["mean_imom"].get<double>()),
                      pct(p["mean_ufr"].get<double>())});
  }
  return t;
}

// The stages of a staged design, in the order they ran.
Table table_stages(const Analysis& a) {
  Table t{"Stages of the design",
          "Each stage starts when the stage it picks its damping ratios from has finished and been analysed "
          "(docs/study.md).",
          {"stage", "samples", "models", "damping ratios (%)", "ε'", "runs finished"},
          {}};
  for (const DesignStage& st : a.stages) {
    int n = 0, fin = 0;
    for (const Run& r : a.runs)
      if (st.lists(r)) ++n, fin += r.finished;
    std::string ratios, rates, models;
    if (!st.listed.empty()) {
      for (const DesignStage::Listed& l : st.listed) {
        ratios += (ratios.empty() ? "" : "; ") + l.model + " " + pct(l.xi);
        rates += (rates.empty() ? "" : "; ") + l.model + " " + sig(l.rate);
      }
      models = "listed runs";
    } else {
      ratios = st.from.empty() ? list_text(st.ratios, true)
                               : fmt::format("{} of stage {}{} ({} significant digits)", st.pick, st.from,
                                             std::isfinite(st.at_rate) ? " at ε' " + sig(st.at_rate) : "",
                                             st.digits);
      rates = list_text(st.rates, false);
      for (const std::string& m : st.models) models += (models.empty() ? "" : ", ") + m;
    }
    std::string samples;
    for (const std::string& s : st.samples) samples += (samples.empty() ? "" : ", ") + s;
    t.rows.push_back({st.name, samples, models, ratios, rates, fmt::format("{}/{}", fin, n)});
  }
  return t;
}

// The ratios each later stage picked, and whether the source's optimum still gives them.
Table table_picks(const Analysis& a) {
  Table t{"Damping ratios picked by later stages",
          "ξopt when picked: the optimum recorded in study.json when the stage's runs were made; ξopt now: "
          "the same optimum from the runs of the source stage as they are now. A change is flagged: the "
          "stage's runs keep the ratios they were made with.",
          {"stage", "from", "sample", "model", "ξopt when picked (%)", "ratios run (%)", "ξopt now (%)", "from runs",
           "flag"},
          {}};
  for (const PickCheck& c : a.picks) {
    std::string flag;
    if (!c.recorded) flag = "not picked yet";
    else if (c.changed) flag = "CHANGED: the optimum now gives " + list_text(c.now_ratios, true) + " %";
    t.rows.push_back({c.stage->name, c.stage->from, c.now.sample, c.now.model,
                      c.recorded ? pct(c.recorded->xi_opt) : "—", c.recorded ? list_text(c.recorded->ratios, true) : "—",
                      pct(c.now.xi_opt) + (c.now.method.empty() ? "" : " (" + c.now.method + ")"),
                      std::to_string(c.now.runs_used), flag});
  }
  return t;
}

std::string reference_rule(const AnalysisSettings& st) {
  std::string s;
  if (!st.reference_model.empty()) s += "model " + st.reference_model;
  if (std::isfinite(st.reference_ratio)) s += std::string(s.empty() ? "" : ", ") + "ξ = " + pct(st.reference_ratio) + " %";
  if (std::isfinite(st.reference_rate)) s += std::string(s.empty() ? "" : ", ") + "ε' = " + sig(st.reference_rate);
  return (s.empty() ? "any run" : s) + "; of those, the slowest rate, then the least damped";
}

// Each run against the reference run of its (sample, seed) (issue: does the damping change the answer?).
Table table_deviation(const Analysis& a) {
  const AnalysisSettings& st = a.settings;
  Table t{"Damping dependence: deviation from the reference run",
          fmt::format("Reference of each sample and seed: {}. Δ = run − reference; RMS over the common strain range "
                      "on the reference's strains, and at 2 / 5 / 10 % axial strain. Quasi-static: mean IMom < {} % "
                      "and RMS Δφ ≤ {}° and RMS Δεv ≤ {} %{}.",
                      reference_rule(st), pct(st.imom_target), sig(st.phi_tolerance_deg), pct(st.ev_tolerance),
                      std::isfinite(st.cn_tolerance) ? " and RMS ΔCn ≤ " + sig(st.cn_tolerance) : ""),
          {"run", "reference", "mean IMom (%)", "RMS Δφ (°)", "Δφ at 2 / 5 / 10 % (°)", "RMS Δεv (%)",
           "Δεv at 2 / 5 / 10 % (%)", "RMS ΔCn", "ΔCn at 2 / 5 / 10 %", "verdict"},
          {}};
  for (const Deviation& d : a.devs)
    t.rows.push_back({d.run->id, d.ref == d.run ? "(itself)" : d.ref->id, pct(d.run->mean_imom), sig(d.phi.rms),
                      trio(d.phi, 1), pct(d.ev.rms), trio(d.ev, 100), sig(d.cn.rms), trio(d.cn, 1), d.verdict});
  return t;
}

Table table_references(const Analysis& a) {
  Table t{"Reference runs and the scatter between seeds",
          "The scatter is the largest RMS deviation between the reference runs of two seeds of one sample: a "
          "tolerance below it cannot tell the damping from the sample.",
          {"sample", "seed", "reference run", "status", "seed scatter: RMS Δφ (°)", "RMS Δεv (%)", "RMS ΔCn"},
          {}};
  for (const auto& [key, r] : a.refs) {
    const auto s = std::find_if(a.scatter.begin(), a.scatter.end(), [&](const SeedScatter& x) { return x.sample == key.first; });
    const bool first = a.reference_of(key.first) == r;
    t.rows.push_back({key.first, std::to_string(key.second), r->id, r->finished ? "finished" : r->problem,
                      first && s != a.scatter.end() ? sig(s->phi) : "", first && s != a.scatter.end() ? pct(s->ev) : "",
                      first && s != a.scatter.end() ? sig(s->cn) : ""});
  }
  return t;
}

// The runs of a stage of listed runs against each other (the paper's Table 5 pair, Figs. 10-11).
Table table_listed_pairs(const Analysis& a) {
  Table t{"Runs of a stage of listed runs against each other",
          "Each finished run of a stage that lists its runs (e.g. the paper's Table 5 pair, Figs. 10-11) against the "
          "stage's first finished run of the same sample and seed. Δ = run − first; RMS over the common strain range "
          "on the first run's strains, and at 2 / 5 / 10 % axial strain.",
          {"stage", "run", "against", "mean IMom (%)", "peak φ (°)", "RMS Δφ (°)", "Δφ at 2 / 5 / 10 % (°)",
           "RMS Δεv (%)", "Δεv at 2 / 5 / 10 % (%)", "RMS ΔCn", "ΔCn at 2 / 5 / 10 %"},
          {}};
  for (const ListedPair& p : a.pairs)
    t.rows.push_back({p.stage->name, p.run->id, p.first->id,
                      pct(p.run->mean_imom) + " / " + pct(p.first->mean_imom),
                      sig(p.run->peak_phi, 4) + " / " + sig(p.first->peak_phi, 4), sig(p.phi.rms), trio(p.phi, 1),
                      pct(p.ev.rms), trio(p.ev, 100), sig(p.cn.rms), trio(p.cn, 1)});
  return t;
}

// Controlled runs against the constant-rate power law of the same sample, seed, model and ratio.
Table table_controls(const Analysis& a) {
  Table t{"Controlled runs: the rate that holds the index at its target",
          "ε' of a controlled run: its mean over the rows (equal strain increments: strain-weighted) and its last "
          "value. Fit: the index's power law over the constant-rate runs of the same sample, seed, model and ratio "
          "(controlled runs are in no fit); ε'QS is where it meets the target. Share: rows with the index within a "
          "factor f of the target. Steps at ε' final: a constant-rate run at the final ε' over the same strain.",
          {"run", "index", "target (%)", "mean ε'", "final ε'", "share in band", "f", "mean index (%)", "wall (s)",
           "steps", "steps at ε' final", "fit runs", "fit ε'QS", "mean / ε'QS", "final / ε'QS"},
          {}};
  for (const ControlComparison& k : a.controls) {
    const Run& r = *k.run;
    const Control& c = r.control;
    if (!r.finished) {
      t.rows.push_back({r.id, c.index, pct(c.target), r.problem, "", "", "", "", "", "", "", "", "", "", ""});
      continue;
    }
    t.rows.push_back({r.id, c.index, pct(c.target), sig(c.mean_rate), sig(c.final_rate), sig(c.share_in_band),
                      sig(c.band_factor), pct(c.mean_index), sig(r.wall_s), sig(r.steps, 4), sig(c.steps_at_final, 4),
                      std::to_string(k.fit.n), sig(k.eps_qs), sig(k.mean_over_qs), sig(k.final_over_qs)});
  }
  return t;
}

Table table_missing(const Analysis& a) {
  Table t{"Missing runs", "Runs of the manifest without a usable summary.json; left out of every fit.",
          {"run", "directory", "reason"}, {}};
  for (const Run& r : a.runs)
    if (!r.finished) t.rows.push_back({r.id, r.dir, r.problem});
  return t;
}

// ---------------------------------------------------------------------------------------------
// Figures (gnuplot; paper Figs. 3-19)
// ---------------------------------------------------------------------------------------------

std::vector<std::string> samples_of(const std::vector<Law>& laws) {
  std::vector<std::string> samples;
  for (const Law& l : laws)
    if (!has_name(samples, l.sample)) samples.push_back(l.sample);
  return samples;
}

// (a) Mean index against xi at each rate, one figure per (sample, model) and index, paper Figs. 3-6.
Figure index_vs_xi_figure(const Analysis& a, const Law& l, bool is_imom) {
  const std::string idx = is_imom ? "IMom" : "UFR";
  Figure f{fmt::format("{}_vs_xi_{}_{}", is_imom ? "imom" : "ufr", tag(l.sample), tag(l.model)),
           fmt::format("{} {}: mean {} against the damping ratio", l.sample, l.model, idx),
           fmt::format("Mean {} over the run against ξ at each ε' (log-log; ξ = 0 not shown); open "
                       "circles: ξopt from the parabola fit (paper Figs. 3-6 for IMom).",
                       idx),
           {}};
  Panel p{f.title, "damping ratio ξ (%)", "mean " + idx + " (%)", true, true, {}};
  std::size_t k = 0;
  for (const Group& g : a.groups) {
    if (g.sample != l.sample || g.model != l.model) continue;
    Curve c{"ε' = " + sig(g.rate), {}, {}, "linespoints pt 7 ps 0.8 " + lc(k)};
    for (const Point& q : g.points) c.x.push_back(100 * q.xi), c.y.push_back(100 * (is_imom ? q.imom : q.ufr));
    const OptimumFit& o = is_imom ? g.opt_imom : g.opt_ufr;
    p.curves.push_back(std::move(c));
    p.curves.push_back(Curve{k == 0 ? "ξopt" : "", {100 * o.xi_opt}, {100 * o.index_at_opt},
                             "points pt 6 ps 2.2 lw 2 " + lc(k)});
    ++k;
  }
  f.panels.push_back(std::move(p));
  return f;
}

// (b) xi_opt against the rate, every model and both indices, paper Figs. 7-8.
Figure xiopt_vs_rate_figure(const Analysis& a, const std::string& s) {
  Figure f{"xiopt_vs_rate_" + tag(s), s + ": optimum damping ratio against the strain rate",
           "ξopt from IMom (solid) and from UFR (dashed) against ε' for each damping model "
           "(paper Figs. 7 and 8); semi-log like the paper.",
           {}};
  Panel p{f.title, "dimensionless strain rate ε'", "ξopt (%)", true, false, {}, "set yrange [0:*]\n"};
  std::size_t k = 0;
  for (const Law& l : a.laws) {
    if (l.sample != s) continue;
    Curve ci{l.model + " (IMom)", {}, {}, "linespoints pt 7 dt 1 " + lc(k)};
    Curve cu{l.model + " (UFR)", {}, {}, "linespoints pt 4 dt 2 " + lc(k)};
    for (const Group& g : a.groups) {
      // A rate run at one ratio has no optimum of its own.
      if (g.sample != s || g.model != l.model || g.opt_imom.method == "single") continue;
      ci.x.push_back(g.rate), ci.y.push_back(100 * g.opt_imom.xi_opt);
      cu.x.push_back(g.rate), cu.y.push_back(100 * g.opt_ufr.xi_opt);
    }
    p.curves.push_back(std::move(ci));
    p.curves.push_back(std::move(cu));
    ++k;
  }
  f.panels.push_back(std::move(p));
  return f;
}

// (c) IMom at xi_opt against the rate with the fitted power law, paper Fig. 9.
Figure power_law_figure(const Analysis& a, const std::string& s) {
  const double target = a.settings.imom_target;
  Figure f{"imom_opt_vs_rate_" + tag(s), s + ": moment index at the optimum damping ratio",
           fmt::format("IMom at ξopt against ε' with the fitted power law IMom = a ε'^b (lines; dashed below the "
                       "slowest rate, down to ε'QS); dotted: the paper's fit; dashed grey: the quasi-static target "
                       "IMom = {} % (paper Fig. 9, Table 4).",
                       pct(target)),
           {}};
  Panel p{f.title, "dimensionless strain rate ε'", "IMom at ξopt (%)", true, true, {}};
  std::size_t k = 0;
  double lo = INFINITY, hi = 0;
  for (const Law& l : a.laws) {
    if (l.sample != s) continue;
    Curve pts{l.model, {}, {}, "points pt 7 ps 1.3 " + lc(k)};
    for (std::size_t i = 0; i < l.rates.size(); ++i) {
      pts.x.push_back(l.rates[i]), pts.y.push_back(100 * l.imom_at_opt[i]);
      lo = std::min(lo, l.rates[i]), hi = std::max(hi, l.rates[i]);
    }
    p.curves.push_back(std::move(pts));
    if (l.fit.ok && l.rates.size() >= 2) {
      const double x0 = *std::min_element(l.rates.begin(), l.rates.end());
      const double x1 = *std::max_element(l.rates.begin(), l.rates.end());
      const auto line = [](double from, double to, double pa, double pb, Curve c) {
        for (int i = 0; i <= 40; ++i) {
          const double x = from * std::pow(to / from, i / 40.0);
          c.x.push_back(x), c.y.push_back(100 * pa * std::pow(x, pb));
        }
        return c;
      };
      p.curves.push_back(line(x0, x1, l.fit.a, l.fit.b,
                              Curve{fmt::format("{} fit: {} ε'^{}, R² = {}", l.model, sig(l.fit.a, 4), sig(l.fit.b, 3),
                                                sig(l.fit.r2, 4)),
                                    {}, {}, "lines lw 1.5 " + lc(k)}));
      // Below the slowest rate the fit is an extrapolation, drawn dashed down to eps'_QS (Table 4).
      const double x_lo = std::isfinite(l.eps_qs) && l.eps_qs < x0 ? l.eps_qs : x0;
      if (x_lo < x0) {
        p.curves.push_back(line(x_lo, x0, l.fit.a, l.fit.b, Curve{"", {}, {}, "lines dt 2 lw 1.5 " + lc(k)}));
        lo = std::min(lo, x_lo);
      }
      // The paper's fit (Fig. 9) over the same rates, for the trend (SPEC 9: never tuned to it).
      if (const auto ref = paper_ref(l.sample, l.model))
        p.curves.push_back(line(x_lo, x1, ref->a, ref->b,
                                Curve{fmt::format("paper {}: {} ε'^{}", l.model, sig(ref->a, 5), sig(ref->b, 4)),
                                      {}, {}, "lines dt 3 lw 1.5 " + lc(k)}));
    }
    ++k;
  }
  if (hi > 0)
    p.curves.push_back(Curve{fmt::format("IMom = {} %", pct(target)), {lo, hi}, {100 * target, 100 * target},
                             "lines dt 2 lc rgb '#888888'"});
  f.panels.push_back(std::move(p));
  return f;
}

// (e) Peak friction angle against xi*eps', paper Figs. 12-14 (the product governs, section 5.7).
Figure peak_phi_figure(const Analysis& a, const std::string& s) {
  Figure f{"peakphi_vs_xirate_" + tag(s), s + ": peak friction angle against ξ·ε'",
           "Peak mobilised friction angle of every finished run (ξ > 0) against ξ·ε' (semi-log).", {}};
  Panel p{f.title, "ξ·ε'", "peak friction angle φ (°)", true, false, {}};
  std::size_t k = 0;
  for (const Law& l : a.laws) {
    if (l.sample != s) continue;
    Curve c{l.model, {}, {}, "points pt 7 ps 0.9 " + lc(k++)};
    for (const Run& r : a.runs)
      if (r.finished && r.sample == s && r.model == l.model && r.xi > 0)
        c.x.push_back(r.xi * r.rate), c.y.push_back(r.peak_phi);
    p.curves.push_back(std::move(c));
  }
  f.panels.push_back(std::move(p));
  return f;
}

// A quantity of a run's series against e1, as a panel shows it.
enum class Quantity { phi, ev, cn, imom, ufr, ekin_over_rate2 };

struct QuantityAxis {
  const char* title;  // the panel's
  const char* ylabel;
  bool logy;
};

QuantityAxis axis_of(Quantity q) {
  switch (q) {
    case Quantity::phi: return {"φ", "friction angle φ (°)", false};
    case Quantity::ev: return {"εv", "volumetric strain εv (%)", false};
    case Quantity::cn: return {"Cn", "coordination number Cn", false};
    case Quantity::imom: return {"IMom", "moment index IMom (%)", false};
    case Quantity::ufr: return {"UFR", "unbalanced force ratio UFR (%)", false};
    case Quantity::ekin_over_rate2: return {"Ekin/ε'²", "Ekin/ε'² (J)", true};
  }
  return {"", "", false};
}

Curve series_curve(const Run& r, Quantity q, const std::string& label, const std::string& style) {
  Curve c{label, {}, {}, style};
  for (std::size_t j = 0; j < r.s.e1.size(); ++j) {
    double y = 0;
    switch (q) {
      case Quantity::phi: y = r.s.phi[j]; break;
      case Quantity::ev: y = 100 * r.s.ev[j]; break;
      case Quantity::cn: y = r.s.cn[j]; break;
      case Quantity::imom: y = 100 * r.s.imom[j]; break;
      case Quantity::ufr: y = 100 * r.s.ufr[j]; break;
      case Quantity::ekin_over_rate2: y = r.s.ekin[j] / (r.rate * r.rate); break;
    }
    c.x.push_back(100 * r.s.e1[j]), c.y.push_back(y);
  }
  return c;
}

std::string run_label(const Run& r) { return fmt::format("{} ε' = {}, ξ = {} %", r.model, sig(r.rate), pct(r.xi)); }

// phi, ev, Cn and IMom against e1 of some runs, with the sample's reference run (black, dashed) in
// the first three panels when the study names one.
Figure response_figure(const std::string& name, const std::string& title, const std::string& caption,
                       const std::vector<const Run*>& shown, const Run* reference) {
  Figure f{name, title, caption, {}};
  for (const Quantity q : {Quantity::phi, Quantity::ev, Quantity::cn, Quantity::imom}) {
    const QuantityAxis ax = axis_of(q);
    Panel p{ax.title, "axial strain ε1 (%)", ax.ylabel, false, ax.logy, {}};
    for (std::size_t i = 0; i < shown.size(); ++i)
      p.curves.push_back(series_curve(*shown[i], q, run_label(*shown[i]), "lines lw 1.5 " + lc(i)));
    if (reference && reference->finished && q != Quantity::imom)
      p.curves.push_back(series_curve(*reference, q, "reference: " + reference->model + " ε' = " + sig(reference->rate),
                                      "lines lw 1.5 dt 2 lc rgb '#000000'"));
    f.panels.push_back(std::move(p));
  }
  return f;
}

// (g) The runs of equal xi*eps' of one (sample, model), paper Figs. 15-19: a colour per product,
// solid for the slowest run of a set, dashed for the faster ones.
void add_equal_figure(std::vector<Figure>& figs, const Analysis& a, const Law& l) {
  Figure f{fmt::format("equal_{}_{}", tag(l.sample), tag(l.model)),
           fmt::format("{} {}: runs with equal ξ·ε'", l.sample, l.model),
           "Friction angle, volumetric strain, coordination number, moment index, UFR and kinetic energy / ε'² "
           "against the axial strain for the runs with equal ξ·ε' (paper Figs. 15-19, Table 6): a colour per "
           "ξ·ε', solid for the slowest run of each, dashed for the faster.",
           {}};
  std::size_t k = 0;
  std::vector<std::pair<const Run*, std::string>> shown;
  for (const EqualSet& e : a.equal) {
    if (e.sample != l.sample || e.model != l.model) continue;
    double slowest = INFINITY;
    for (const Run* r : e.runs) slowest = std::min(slowest, r->rate);
    for (const Run* r : e.runs)
      if (!r->s.e1.empty())
        shown.emplace_back(r, (r->rate == slowest ? "lines lw 1.5 " : "lines lw 1.5 dt 2 ") + lc(k));
    ++k;
  }
  if (shown.empty()) return;
  for (const Quantity q : {Quantity::phi, Quantity::ev, Quantity::cn, Quantity::imom, Quantity::ufr,
                           Quantity::ekin_over_rate2}) {
    const QuantityAxis ax = axis_of(q);
    Panel p{ax.title, "axial strain ε1 (%)", ax.ylabel, false, ax.logy, {}};
    for (const auto& [r, style] : shown)
      p.curves.push_back(series_curve(*r, q, q == Quantity::phi ? run_label(*r) : "", style));
    f.panels.push_back(std::move(p));
  }
  figs.push_back(std::move(f));
}

// (d) and (f): the run closest to xi_opt at each rate, paper Figs. 10-11 and 19.
void add_curve_figures(std::vector<Figure>& figs, const Analysis& a, const Law& l) {
  std::vector<const Run*> shown;
  for (const Group& g : a.groups)
    if (g.sample == l.sample && g.model == l.model && g.chosen) shown.push_back(g.chosen);
  figs.push_back(response_figure(
      fmt::format("curves_{}_{}", tag(l.sample), tag(l.model)), fmt::format("{} {}: runs nearest ξopt", l.sample, l.model),
      "Friction angle, volumetric strain, coordination number and moment index against the axial "
      "strain for the run nearest ξopt at each rate (paper Figs. 10-11).",
      shown, a.reference_of(l.sample)));

  Figure e{fmt::format("ekin_{}_{}", tag(l.sample), tag(l.model)),
           fmt::format("{} {}: kinetic energy / ε'² (runs nearest ξopt)", l.sample, l.model),
           "Kinetic energy of the fluctuations divided by ε'² against the axial strain (paper Fig. 19; "
           "log y, zeros skipped).",
           {}};
  Panel p{e.title, "axial strain ε1 (%)", "Ekin/ε'² (J)", false, true, {}};
  for (std::size_t i = 0; i < shown.size(); ++i)
    p.curves.push_back(series_curve(*shown[i], Quantity::ekin_over_rate2,
                                    fmt::format("ε' = {}, ξ = {} %", sig(shown[i]->rate), pct(shown[i]->xi)),
                                    "lines lw 1.5 " + lc(i)));
  e.panels.push_back(std::move(p));
  figs.push_back(std::move(e));
}

// The runs of a small stage (e.g. the paper's Table 5 pair, Figs. 10-11), per sample.
constexpr std::size_t max_stage_curves = 8;

void add_stage_figures(std::vector<Figure>& figs, const Analysis& a, const std::string& s) {
  for (const DesignStage& st : a.stages) {
    std::vector<const Run*> shown;
    for (const Run& r : a.runs)
      if (r.sample == s && r.finished && !r.s.e1.empty() && st.lists(r)) shown.push_back(&r);
    if (shown.empty() || shown.size() > max_stage_curves) continue;
    figs.push_back(response_figure(fmt::format("stage_{}_{}", tag(st.name), tag(s)),
                                   fmt::format("{}: the runs of stage {}", s, st.name),
                                   "Friction angle, volumetric strain, coordination number and moment index against "
                                   "the axial strain for every finished run of the stage (paper Figs. 10-11 for the "
                                   "Table 5 pair).",
                                   shown, a.reference_of(s)));
  }
}

// The convergence certificate of a ladder of two or more seeds (section 11): phi and ev against e1
// at every rung (a colour per rate, a dash per seed), and the seed mean of peak phi and of ev at the
// end against the rate with the mean -/+ its standard error (dashed). Ladders of one seed (a sweep's
// rates) are in the table only.
void add_ladder_figures(std::vector<Figure>& figs, const Analysis& a) {
  for (const Ladder& l : a.ladders) {
    if (l.seeds.size() < 2 || l.rates.empty()) continue;
    Figure f{fmt::format("ladder_{}_{}_{}", tag(l.sample), tag(l.model), tag(sig(100 * l.xi))),
             fmt::format("{} {} ξ = {} %: the response as the rate falls", l.sample, l.model, pct(l.xi)),
             fmt::format("Friction angle and volumetric strain against the axial strain at each rate of the ladder "
                         "(a colour per rate, solid for seed {}, dashed for the others), and the seed mean of the "
                         "peak friction angle and of εv at the last strain against the rate, between the mean ∓ its "
                         "standard error (dashed). Certificate: {}.",
                         l.seeds.front(), l.certificate.status),
             {}};
    for (const Quantity q : {Quantity::phi, Quantity::ev}) {
      const QuantityAxis ax = axis_of(q);
      Panel p{ax.title, "axial strain ε1 (%)", ax.ylabel, false, false, {}};
      for (std::size_t k = 0; k < l.rates.size(); ++k)
        for (std::size_t s = 0; s < l.runs[k].size(); ++s)
          p.curves.push_back(series_curve(*l.runs[k][s], q, s == 0 ? fmt::format("ε' = {}", sig(l.rates[k])) : "",
                                          (s == 0 ? "lines lw 1.5 " : "lines lw 1 dt 2 ") + lc(k)));
      f.panels.push_back(std::move(p));
    }
    for (const auto& [name, ylabel, scale] : {std::tuple{"peak_phi_deg", "peak φ (°)", 1.0},
                                              std::tuple{"ev", "εv at the last strain (%)", 100.0}}) {
      const ScalarLimit* sc = l.certificate.scalar(name);
      if (!sc) continue;
      Panel p{ylabel, "strain rate ε'", ylabel, true, false, {}};
      Curve mean{"seed mean", {}, {}, "linespoints pt 7 lw 1.5 lc 1"}, lo{"", {}, {}, "lines dt 2 lc 1"},
          hi{"", {}, {}, "lines dt 2 lc 1"};
      for (std::size_t k = 0; k < l.rates.size(); ++k) {
        const double m = scale * sc->mean[k], e = std::isfinite(sc->error[k]) ? scale * sc->error[k] : 0.0;
        mean.x.push_back(l.rates[k]), mean.y.push_back(m);
        lo.x.push_back(l.rates[k]), lo.y.push_back(m - e);
        hi.x.push_back(l.rates[k]), hi.y.push_back(m + e);
      }
      p.curves = {mean, lo, hi};
      // Fastest rate on the left, a margin of a factor 1.5 each side; log x labels each rate.
      std::string tics;
      for (double r : l.rates) tics += fmt::format("{}'{}' {:.9g}", tics.empty() ? "" : ", ", sig(r, 3), r);
      p.extra = fmt::format("set xrange [{:.9g}:{:.9g}]\nset xtics ({})\n", 1.5 * l.rates.front(),
                            l.rates.back() / 1.5, tics);
      f.panels.push_back(std::move(p));
    }
    figs.push_back(std::move(f));
  }
}

// The damping dependence of one sample: RMS deviations from the reference against the mean IMom
// (quasi-static: left of the target and under the tolerance) and RMS dphi against xi.
Figure deviation_figure(const Analysis& a, const std::string& s) {
  const AnalysisSettings& st = a.settings;
  Figure f{"deviation_" + tag(s), s + ": deviation from the reference run",
           fmt::format("RMS deviation of φ, εv and Cn from the reference run of the same seed against the mean "
                       "IMom of each run (dashed: the target {} % and the tolerances; a quasi-static run lies left "
                       "of and below them), and RMS Δφ against ξ for each model and ε'.",
                       pct(st.imom_target)),
           {}};
  std::vector<std::string> models;
  for (const Law& l : a.laws)
    if (l.sample == s) models.push_back(l.model);
  const struct {
    const char* title;
    const char* ylabel;
    double scale, tol;
    CurveDeviation Deviation::*m;
  } kinds[3] = {{"Δφ", "RMS Δφ (°)", 1, st.phi_tolerance_deg, &Deviation::phi},
                {"Δεv", "RMS Δεv (%)", 100, st.ev_tolerance, &Deviation::ev},
                {"ΔCn", "RMS ΔCn", 1, st.cn_tolerance, &Deviation::cn}};
  for (const auto& kind : kinds) {
    Panel p{kind.title, "mean IMom (%)", kind.ylabel, true, false, {}, "set yrange [0:*]\n"};
    double ymax = 0, xlo = INFINITY, xhi = 0;
    for (std::size_t k = 0; k < models.size(); ++k) {
      Curve c{models[k], {}, {}, "points pt 7 ps 0.9 " + lc(k)};
      for (const Deviation& d : a.devs)
        if (d.run->sample == s && d.run->model == models[k] && std::isfinite((d.*kind.m).rms)) {
          c.x.push_back(100 * d.run->mean_imom), c.y.push_back(kind.scale * (d.*kind.m).rms);
          ymax = std::max(ymax, c.y.back());
          if (d.run->mean_imom > 0) xlo = std::min(xlo, c.x.back()), xhi = std::max(xhi, c.x.back());
        }
      p.curves.push_back(std::move(c));
    }
    if (xhi > 0) {
      const double x0 = std::min(xlo, 100 * st.imom_target), x1 = std::max(xhi, 100 * st.imom_target);
      const double y1 = std::max(ymax, std::isfinite(kind.tol) ? kind.scale * kind.tol : 0.0);
      p.curves.push_back(Curve{"target", {100 * st.imom_target, 100 * st.imom_target}, {0, y1},
                               "lines dt 2 lc rgb '#888888'"});
      if (std::isfinite(kind.tol))
        p.curves.push_back(Curve{"tolerance", {x0, x1}, {kind.scale * kind.tol, kind.scale * kind.tol},
                                 "lines dt 3 lc rgb '#888888'"});
    }
    f.panels.push_back(std::move(p));
  }
  Panel p{"RMS Δφ against ξ", "damping ratio ξ (%)", "RMS Δφ (°)", true, false, {}, "set yrange [0:*]\n"};
  std::size_t k = 0;
  for (const Group& g : a.groups) {
    if (g.sample != s) continue;
    Curve c{fmt::format("{} ε' = {}", g.model, sig(g.rate)), {}, {}, "linespoints pt 7 ps 0.8 " + lc(k++)};
    for (const Point& q : g.points) {
      std::vector<double> v;
      for (const Deviation& d : a.devs)
        if (d.run->sample == s && d.run->model == g.model && d.run->rate == g.rate && d.run->xi == q.xi)
          v.push_back(d.phi.rms);
      c.x.push_back(100 * q.xi), c.y.push_back(mean_finite(v));
    }
    p.curves.push_back(std::move(c));
  }
  f.panels.push_back(std::move(p));
  return f;
}

}  // namespace

std::string to_html(const Table& t) {
  std::string s = t.detail ? "<details><summary>" + html_escape(t.title) + "</summary>\n"
                           : "<h3>" + html_escape(t.title) + "</h3>\n";
  if (!t.note.empty()) s += "<p class=\"note\">" + html_escape(t.note) + "</p>\n";
  s += "<table>\n<thead><tr>";
  for (const auto& c : t.head) s += "<th>" + html_escape(c) + "</th>";
  s += "</tr></thead>\n<tbody>\n";
  for (const auto& r : t.rows) {
    s += "<tr>";
    for (const auto& c : r) s += "<td>" + html_escape(c) + "</td>";
    s += "</tr>\n";
  }
  if (t.rows.empty()) s += "<tr><td colspan=\"" + std::to_string(t.head.size()) + "\">(no rows)</td></tr>\n";
  return s + "</tbody></table>\n" + (t.detail ? "</details>\n" : "");
}

std::string to_markdown(const Table& t) {
  std::string s = "### " + t.title + "\n\n";
  if (!t.note.empty()) s += t.note + "\n\n";
  auto line = [&](const std::vector<std::string>& cells) {
    s += "|";
    for (const auto& c : cells) {
      s += ' ';  // appended piecewise: GCC 12 warns (-Wrestrict, false positive) on " " + x + " |"
      s += md_escape(c);
      s += " |";
    }
    s += "\n";
  };
  line(t.head);
  s += "|";
  for (std::size_t i = 0; i < t.head.size(); ++i) s += " --- |";
  s += "\n";
  for (const auto& r : t.rows) line(r);
  if (t.rows.empty()) s += "\n(no rows)\n";
  return s + "\n";
}

std::vector<Table> make_tables(const Analysis& a) {
  std::vector<Table> tables;
  if (!a.stages.empty()) tables.push_back(table_stages(a));
  if (!a.picks.empty()) tables.push_back(table_picks(a));
  tables.push_back(table_power_law(a));
  if (!a.controls.empty()) tables.push_back(table_controls(a));
  tables.push_back(table_optima(a));
  for (const Group& g : a.groups) tables.push_back(table_points(g));
  tables.push_back(table_equal(a));
  if (std::any_of(a.runs.begin(), a.runs.end(), [](const Run& r) { return !r.sample.empty() && r.sample[0] == 'B'; }))
    tables.push_back(table_paper6());
  if (a.settings.has_reference) {
    tables.push_back(table_references(a));
    tables.push_back(table_deviation(a));
  }
  if (!a.pairs.empty()) tables.push_back(table_listed_pairs(a));
  if (!a.ladders.empty()) tables.push_back(table_ladders(a.ladders, a.settings.convergence));
  if (a.settings.critical_state.on)
    for (Table& t : critical_tables(a.critical, a.settings.critical_state)) tables.push_back(std::move(t));
  tables.push_back(table_missing(a));
  return tables;
}

std::vector<Figure> make_figures(const Analysis& a) {
  std::vector<Figure> figs;
  for (const Law& l : a.laws)
    for (const bool is_imom : {true, false}) figs.push_back(index_vs_xi_figure(a, l, is_imom));
  for (const std::string& s : samples_of(a.laws)) {
    figs.push_back(xiopt_vs_rate_figure(a, s));
    figs.push_back(power_law_figure(a, s));
    figs.push_back(peak_phi_figure(a, s));
  }
  for (const Law& l : a.laws) add_curve_figures(figs, a, l);
  for (const Law& l : a.laws) add_equal_figure(figs, a, l);
  for (const std::string& s : samples_of(a.laws)) {
    add_stage_figures(figs, a, s);
    if (a.settings.has_reference) figs.push_back(deviation_figure(a, s));
  }
  add_ladder_figures(figs, a);
  add_critical_figures(figs, a.critical);
  return figs;
}

std::string report_html(const json& a, const AnalysisSettings& settings, const std::vector<Table>& tables,
                        const std::vector<Figure>& figs, const std::vector<bool>& drawn, const std::vector<Run>& runs,
                        const std::string& toml) {
  const std::string name = a["study"]["name"];
  std::string h = html_head("qsdem study " + name);
  h += "<h1>qsdem study: " + html_escape(name) + "</h1>\n";
  h += "<p>Study date: " + html_escape(a["study"]["date"].get<std::string>()) +
       ". Analysed: " + html_escape(a["study"]["analysed_at"].get<std::string>()) + ". Runs: " +
       std::to_string(a["counts"]["finished"].get<int>()) + " finished of " +
       std::to_string(a["counts"]["runs"].get<int>()) + ".</p>\n";
  h += "<h2>How to read this report</h2>\n<p>Each run is one drained triaxial test (SPEC 8) of a sample "
       "with a damping model (nd: size-dependent, od: global mass damping, none; or a labelled entry of the "
       "design's model axis) at a damping ratio ξ and a dimensionless strain rate ε'. For every (sample, model, ε') "
       "the optimum damping ratio ξopt is the minimum of the mean moment index IMom (and separately of UFR) over "
       "ξ, refined by a parabola in log-log through the smallest sampled value and its neighbours; a flag says "
       "when the minimum lies at the edge of the sampled ξ range. IMom at ξopt is fitted as a ε'^b over the "
       "rates; ε'QS is the rate where that fit reaches the target IMom = " + html_escape(pct(settings.imom_target)) +
       " %, and the improvement of a model is ε'QS(model)/ε'QS(" + html_escape(settings.baseline) +
       "): above 1 the model allows faster quasi-static loading than the baseline. Columns headed 'paper' repeat "
       "Yousefi (2018), Table 4, Fig. 9 and Table 6, for samples named A* or B* and models od/nd; our numbers are "
       "not expected to match them digit for digit (other code, packing and contact geometry), only in trend. ";
  h += settings.has_reference
           ? "The damping dependence compares each run's φ, εv and Cn against the axial strain with the reference "
             "run of its sample and seed: a run is called quasi-static only if its mean IMom is under the target "
             "and these deviations are within the tolerances. "
           : "No reference run is named ([analysis] reference of the study file), so the damping dependence of the "
             "response is not assessed: a low index alone does not show that the damping left the response "
             "unchanged. ";
  h += "All indices are shown in percent. Details: docs/analysis.md.</p>\n";
  h += "<p>Data: <a href=\"analysis/per_run.csv\">per_run.csv</a>, <a href=\"analysis/optimum.csv\">optimum.csv</a>, "
       "<a href=\"analysis/power_law.csv\">power_law.csv</a>, " +
       std::string(settings.has_reference ? "<a href=\"analysis/deviation.csv\">deviation.csv</a>, " : "") +
       "<a href=\"analysis/analysis.json\">analysis.json</a>, <a href=\"analysis/tables.md\">tables.md</a>.</p>\n";
  h += "<h2>Tables</h2>\n<p class=\"note\">The tables per (sample, model, ε') are folded: click a title "
       "to open it.</p>\n";
  for (const Table& t : tables) h += to_html(t);
  h += "<h2>Figures</h2>\n";
  for (std::size_t i = 0; i < figs.size(); ++i) {
    const Figure& f = figs[i];
    if (!drawn[i]) {
      h += "<p class=\"note\">" + html_escape(f.title) + ": no data to plot.</p>\n";
      continue;
    }
    h += figure_html(f, "analysis/figures/");
  }
  h += "<h2 id=\"missing\">Missing runs</h2>\n";
  int missing = 0;
  std::string ul;
  for (const Run& r : runs)
    if (!r.finished) ++missing, ul += "<li>" + html_escape(r.id) + " (" + html_escape(r.problem) + ")</li>\n";
  h += missing ? "<ul class=\"missing\">\n" + ul + "</ul>\n" : "<p>None: every run of the manifest finished.</p>\n";
  h += "<h2>Resolved configuration (" + html_escape(a["study"]["study_file"].get<std::string>()) + ")</h2>\n<pre>" +
       html_escape(toml) + "</pre>\n";
  h += "<p class=\"note\">Generated by qsdem " QSDEM_VERSION " (qsdem::analyze_study).</p>\n</body>\n</html>\n";
  return h;
}

}  // namespace qsdem::analysis
