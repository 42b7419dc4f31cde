// The critical state of a study's drained runs (docs/analysis.md section 12): each run's peak,
// dilatancy and window means, the critical state line e_c = Gamma - lambda ln p' and M of each
// (model, ratio, rate) over its samples; their JSON, CSV, tables and figures.
#include <fmt/format.h>

#include <algorithm>
#include <cmath>
#include <numeric>

#include "qsdem/engine/types.hpp"
#include "qsdem/study/study_analysis_data.hpp"

namespace qsdem {

namespace {

// Least-squares slope of y against x over [lo, hi) of both (finite pairs only); NaN with fewer than
// two points or no spread in x.
double slope(std::span<const double> x, std::span<const double> y, std::size_t lo, std::size_t hi) {
  double sx = 0, sy = 0, sxx = 0, sxy = 0;
  int n = 0;
  for (std::size_t i = lo; i < hi; ++i) {
    if (!std::isfinite(x[i]) || !std::isfinite(y[i])) continue;
    sx += x[i], sy += y[i], sxx += x[i] * x[i], sxy += x[i] * y[i], ++n;
  }
  if (n < 2) return RunCriticalState::nan;
  const double d = n * sxx - sx * sx;
  return d > 0 ? (n * sxy - sx * sy) / d : RunCriticalState::nan;
}

double mean_over(std::span<const double> v, std::size_t lo, std::size_t hi) {
  double sum = 0;
  int n = 0;
  for (std::size_t i = lo; i < hi && i < v.size(); ++i)
    if (std::isfinite(v[i])) sum += v[i], ++n;
  return n ? sum / n : RunCriticalState::nan;
}

}  // namespace

double triaxial_dilatancy_angle_deg(double dev_de1, double e1, double ev) {
  const double t = dev_de1 * (1 - e1) / (1 + ev);  // dv / d eps1, natural increments
  const double s = t / (2 + t);
  if (!std::isfinite(s) || std::abs(s) > 1) return RunCriticalState::nan;
  return std::asin(s) * 180 / pi;
}

RunCriticalState critical_state_of(const DrainedCurves& c, const CriticalStateSettings& settings) {
  RunCriticalState r;
  const std::size_t n = c.e1.size();
  if (n == 0 || c.ev.size() != n || c.phi_deg.size() != n || c.p.size() != n || c.stress_ratio.size() != n ||
      c.void_ratio.size() != n)
    return r;
  r.e0 = std::isfinite(c.e0) ? c.e0 : c.void_ratio[0];
  r.p0 = std::isfinite(c.p0) ? c.p0 : c.p[0];
  for (std::size_t i = 0; i < n; ++i)
    if (std::isfinite(c.phi_deg[i]) && !(c.phi_deg[i] <= r.peak_phi_deg)) r.peak_phi_deg = c.phi_deg[i], r.peak_e1 = c.e1[i];
  // psi from the local slope of ev(e1) over rows within a full window of +- dilatancy_half_window.
  const double last = c.e1[n - 1];
  std::size_t lo = 0, hi = 0;
  for (std::size_t i = 0; i < n; ++i) {
    if (c.e1[i] - dilatancy_half_window < c.e1[0] || c.e1[i] + dilatancy_half_window > last) continue;
    while (lo < n && c.e1[lo] < c.e1[i] - dilatancy_half_window) ++lo;
    while (hi < n && c.e1[hi] <= c.e1[i] + dilatancy_half_window) ++hi;
    const double psi = triaxial_dilatancy_angle_deg(slope(c.e1, c.ev, lo, hi), c.e1[i], c.ev[i]);
    if (std::isfinite(psi) && !(psi <= r.max_dilatancy_deg)) r.max_dilatancy_deg = psi, r.max_dilatancy_e1 = c.e1[i];
  }
  // The window: e1 >= from, to the end.
  const std::size_t w = static_cast<std::size_t>(
      std::find_if(c.e1.begin(), c.e1.end(), [&](double e) { return e >= settings.from; }) - c.e1.begin());
  r.rows = static_cast<int>(n - w);
  if (r.rows < 3) return r;
  r.phi_deg = mean_over(c.phi_deg, w, n);
  r.stress_ratio = mean_over(c.stress_ratio, w, n);
  r.void_ratio = mean_over(c.void_ratio, w, n);
  r.p = mean_over(c.p, w, n);
  r.fabric_dev = mean_over(c.fabric_dev, w, n);
  r.ev_slope = slope(c.e1, c.ev, w, n);
  r.stress_ratio_slope = slope(c.e1, c.stress_ratio, w, n) / r.stress_ratio;
  r.reached = std::abs(r.ev_slope) <= settings.ev_slope && std::abs(r.stress_ratio_slope) <= settings.stress_ratio_slope;
  return r;
}

CriticalStateLine fit_critical_state_line(std::span<const double> p, std::span<const double> void_ratio,
                                          std::span<const double> stress_ratio) {
  CriticalStateLine l;
  std::vector<double> x, y, m;
  for (std::size_t i = 0; i < p.size() && i < void_ratio.size(); ++i)
    if (std::isfinite(p[i]) && p[i] > 0 && std::isfinite(void_ratio[i])) {
      x.push_back(std::log(p[i] / 1e3)), y.push_back(void_ratio[i]);
      if (i < stress_ratio.size() && std::isfinite(stress_ratio[i])) m.push_back(stress_ratio[i]);
    }
  l.n = static_cast<int>(x.size());
  if (!m.empty()) {
    l.M = std::accumulate(m.begin(), m.end(), 0.0) / static_cast<double>(m.size());
    double ss = 0;
    for (double v : m) ss += (v - l.M) * (v - l.M);
    l.M_sd = m.size() > 1 ? std::sqrt(ss / static_cast<double>(m.size() - 1)) : RunCriticalState::nan;
    l.phi_cs_deg = std::asin(3 * l.M / (6 + l.M)) * 180 / pi;  // triaxial compression, sigma2 = sigma3
  }
  if (l.n == 0) {
    l.note = "no run reached the critical state";
    return l;
  }
  l.p_lo = std::exp(*std::min_element(x.begin(), x.end())) * 1e3;
  l.p_hi = std::exp(*std::max_element(x.begin(), x.end())) * 1e3;
  if (l.n < 2 || l.p_hi < 1.01 * l.p_lo) {
    l.note = "the runs' p'_c span less than 1 %: no line";
    return l;
  }
  const double xm = std::accumulate(x.begin(), x.end(), 0.0) / l.n, ym = std::accumulate(y.begin(), y.end(), 0.0) / l.n;
  double sxx = 0, sxy = 0, syy = 0;
  for (int i = 0; i < l.n; ++i) sxx += (x[i] - xm) * (x[i] - xm), sxy += (x[i] - xm) * (y[i] - ym), syy += (y[i] - ym) * (y[i] - ym);
  const double b = sxy / sxx;
  l.lambda = -b;
  l.gamma = ym - b * xm;
  double sse = 0;
  for (int i = 0; i < l.n; ++i) sse += std::pow(y[i] - (l.gamma + b * x[i]), 2);
  l.rms_residual = std::sqrt(sse / l.n);
  l.r2 = syy > 0 ? 1 - sse / syy : RunCriticalState::nan;
  if (l.n >= 3) {
    const double s2 = sse / (l.n - 2);
    l.lambda_se = std::sqrt(s2 / sxx);
    l.gamma_se = std::sqrt(s2 * (1.0 / l.n + xm * xm / sxx));
  } else {
    l.note = "2 runs: the line passes through both (no standard errors)";
  }
  l.ok = true;
  return l;
}

namespace analysis {
namespace {

json line_json(const CriticalStateLine& l) {
  return {{"ok", l.ok},
          {"n", l.n},
          {"gamma", number_or_null(l.gamma)},
          {"gamma_se", number_or_null(l.gamma_se)},
          {"lambda", number_or_null(l.lambda)},
          {"lambda_se", number_or_null(l.lambda_se)},
          {"r2", number_or_null(l.r2)},
          {"rms_residual", number_or_null(l.rms_residual)},
          {"p_lo_Pa", number_or_null(l.p_lo)},
          {"p_hi_Pa", number_or_null(l.p_hi)},
          {"M", number_or_null(l.M)},
          {"M_sd", number_or_null(l.M_sd)},
          {"phi_cs_deg", number_or_null(l.phi_cs_deg)},
          {"note", l.note}};
}

DrainedCurves curves_of(const Run& r) {
  return {r.s.e1, r.s.ev, r.s.phi, r.s.p, r.s.q_over_p, r.s.void_ratio, r.s.fabric_dev, r.e0, r.p0};
}

std::string group_title(const CriticalGroup& g) {
  return fmt::format("{} ξ = {} %, ε' = {}", g.model, pct(g.xi), sig(g.rate));
}

// The run's sample axes as a short label: "100 kPa, μc 0" (or the sample's name without them).
std::string axes_label(const Run& r) {
  std::string s;
  if (std::isfinite(r.confining_stress)) s += fmt::format("{:g} kPa", r.confining_stress / 1e3);
  if (std::isfinite(r.compaction_friction)) s += fmt::format("{}μc {:g}", s.empty() ? "" : ", ", r.compaction_friction);
  return s.empty() ? r.sample : s;
}

}  // namespace

std::vector<CriticalGroup> make_critical_groups(const std::vector<Run>& runs, const CriticalStateSettings& settings) {
  std::vector<CriticalGroup> groups;
  for (const Run& r : runs) {
    if (r.controlled || !r.finished || r.s.e1.empty()) continue;
    auto g = std::find_if(groups.begin(), groups.end(), [&](const CriticalGroup& x) {
      return x.model == r.model && same_value(x.xi, r.xi) && same_value(x.rate, r.rate);
    });
    if (g == groups.end()) g = groups.insert(groups.end(), CriticalGroup{r.model, r.xi, r.rate, {}, {}});
    g->runs.push_back({&r, critical_state_of(curves_of(r), settings)});
  }
  for (CriticalGroup& g : groups) {
    std::vector<double> p, e, m, p_all, e_all, m_all;
    for (const auto& mem : g.runs) {
      if (mem.cs.rows < 3) continue;
      p_all.push_back(mem.cs.p), e_all.push_back(mem.cs.void_ratio), m_all.push_back(mem.cs.stress_ratio);
      if (mem.cs.reached) p.push_back(mem.cs.p), e.push_back(mem.cs.void_ratio), m.push_back(mem.cs.stress_ratio);
    }
    g.line = fit_critical_state_line(p, e, m);
    g.line_all = fit_critical_state_line(p_all, e_all, m_all);
    if (!g.line.ok) continue;
    for (auto& mem : g.runs) {
      mem.state_parameter = mem.cs.e0 - g.line.void_ratio_at(mem.cs.p0);
      mem.off_line = mem.cs.void_ratio - g.line.void_ratio_at(mem.cs.p);
    }
  }
  return groups;
}

json critical_json(const std::vector<CriticalGroup>& groups, const CriticalStateSettings& settings) {
  json out = {{"settings", {{"from", settings.from}, {"ev_slope", settings.ev_slope},
                            {"stress_ratio_slope", settings.stress_ratio_slope},
                            {"dilatancy_half_window", dilatancy_half_window}}},
              {"groups", json::array()}};
  for (const CriticalGroup& g : groups) {
    json runs = json::array();
    for (const auto& m : g.runs) {
      const RunCriticalState& c = m.cs;
      runs.push_back({{"id", m.run->id},
                      {"sample", m.run->sample},
                      {"confining_stress_Pa", number_or_null(m.run->confining_stress)},
                      {"compaction_friction", number_or_null(m.run->compaction_friction)},
                      {"e0", number_or_null(c.e0)},
                      {"p0_Pa", number_or_null(c.p0)},
                      {"peak_phi_deg", number_or_null(c.peak_phi_deg)},
                      {"peak_e1", number_or_null(c.peak_e1)},
                      {"max_dilatancy_deg", number_or_null(c.max_dilatancy_deg)},
                      {"max_dilatancy_e1", number_or_null(c.max_dilatancy_e1)},
                      {"window_rows", c.rows},
                      {"phi_cs_deg", number_or_null(c.phi_deg)},
                      {"stress_ratio", number_or_null(c.stress_ratio)},
                      {"void_ratio", number_or_null(c.void_ratio)},
                      {"p_Pa", number_or_null(c.p)},
                      {"fabric_dev", number_or_null(c.fabric_dev)},
                      {"ev_slope", number_or_null(c.ev_slope)},
                      {"stress_ratio_slope", number_or_null(c.stress_ratio_slope)},
                      {"reached", c.reached},
                      {"state_parameter", number_or_null(m.state_parameter)},
                      {"off_line", number_or_null(m.off_line)}});
    }
    out["groups"].push_back({{"model", g.model},
                             {"xi", g.xi},
                             {"rate", g.rate},
                             {"runs", runs},
                             {"line", line_json(g.line)},
                             {"line_all_runs", line_json(g.line_all)}});
  }
  return out;
}

std::string critical_csv(const std::vector<CriticalGroup>& groups) {
  std::string out =
      "model,xi,rate,sample,confining_stress_Pa,compaction_friction,e0,p0_Pa,peak_phi_deg,peak_e1,max_dilatancy_deg,"
      "max_dilatancy_e1,window_rows,phi_cs_deg,stress_ratio,void_ratio,p_Pa,fabric_dev,ev_slope,stress_ratio_slope,"
      "reached,state_parameter,off_line\n";
  for (const CriticalGroup& g : groups)
    for (const auto& m : g.runs) {
      const RunCriticalState& c = m.cs;
      out += fmt::format("{},{},{},{},{},{},{},{},{},{},{},{},{},{},{},{},{},{},{},{},{},{},{}\n", g.model, csvnum(g.xi),
                         csvnum(g.rate), m.run->sample, csvnum(m.run->confining_stress),
                         csvnum(m.run->compaction_friction), csvnum(c.e0), csvnum(c.p0), csvnum(c.peak_phi_deg),
                         csvnum(c.peak_e1), csvnum(c.max_dilatancy_deg), csvnum(c.max_dilatancy_e1), c.rows,
                         csvnum(c.phi_deg), csvnum(c.stress_ratio), csvnum(c.void_ratio), csvnum(c.p),
                         csvnum(c.fabric_dev), csvnum(c.ev_slope), csvnum(c.stress_ratio_slope),
                         c.reached ? "true" : "false", csvnum(m.state_parameter), csvnum(m.off_line));
    }
  return out;
}

std::vector<Table> critical_tables(const std::vector<CriticalGroup>& groups, const CriticalStateSettings& st) {
  Table lines{"Critical state lines",
              fmt::format("Per (model, ξ, ε'): e_c = Γ − λ ln(p'_c / 1 kPa) by least squares over the runs at the "
                          "critical state (± standard errors), M = (q/p')_c the mean over those runs (± standard "
                          "deviation), φ_cs from M (sin φ = 3M/(6 + M)). A run is at the critical state when over "
                          "ε1 ≥ {} % |dεv/dε1| ≤ {} and |d(q/p')/dε1|/(q/p') ≤ {} (docs/analysis.md, section 12). "
                          "When some runs are not, a second row fits every run's window means: the line they end "
                          "on, not a critical state line.",
                          pct(st.from), sig(st.ev_slope), sig(st.stress_ratio_slope)),
              {"model", "ξ (%)", "ε'", "runs", "Γ", "λ", "R²", "RMS residual", "p'_c (kPa)", "M",
               "φ_cs (°)", "note"},
              {}};
  Table runs{"Critical state of each run",
             fmt::format("Start (e0, p'0), peak friction angle, largest dilatancy angle ψ_max (Schanz & Vermeer 1996, "
                         "from the slope of εv over ±{} % of ε1), the means over ε1 ≥ {} % (φ, q/p', e, p', the "
                         "contact-normal fabric deviator) and the slopes there; ψ0 = e0 − e_c(p'0) is the state "
                         "parameter (Been & Jefferies 1985) and Δe = e − e_c(p') the distance from the line.",
                         pct(dilatancy_half_window), pct(st.from)),
             {"model, ξ, ε'", "sample", "e0", "p'0 (kPa)", "ψ0", "peak φ (°)", "at ε1 (%)", "ψ_max (°)", "at ε1 (%)",
              "φ_cs (°)", "q/p'", "e_c", "p'_c (kPa)", "fabric dev", "dεv/dε1", "d(q/p')/dε1 /(q/p')", "critical",
              "Δe"},
             {}};
  for (const CriticalGroup& g : groups) {
    int reached = 0, windowed = 0;
    for (const auto& m : g.runs) reached += m.cs.reached, windowed += m.cs.rows >= 3;
    const auto row = [&](const CriticalStateLine& l, const std::string& which) {
      lines.rows.push_back(
          {g.model, pct(g.xi), sig(g.rate), which,
           l.ok ? fmt::format("{} ± {}", sig(l.gamma, 4), sig(l.gamma_se, 2)) : "—",
           l.ok ? fmt::format("{} ± {}", sig(l.lambda, 3), sig(l.lambda_se, 2)) : "—", sig(l.r2, 3),
           sig(l.rms_residual, 2),
           std::isfinite(l.p_lo) ? fmt::format("{}–{}", sig(l.p_lo / 1e3), sig(l.p_hi / 1e3)) : "—",
           fmt::format("{} ± {}", sig(l.M, 4), sig(l.M_sd, 2)), sig(l.phi_cs_deg, 4), l.note});
    };
    row(g.line, fmt::format("at the critical state: {} of {}", reached, g.runs.size()));
    if (reached < windowed) row(g.line_all, fmt::format("every run's window means: {} (not a critical state line)", windowed));
    for (const auto& m : g.runs) {
      const RunCriticalState& c = m.cs;
      runs.rows.push_back({group_title(g), m.run->sample, sig(c.e0, 4), sig(c.p0 / 1e3), sig(m.state_parameter, 3),
                           sig(c.peak_phi_deg, 4), pct(c.peak_e1, 3), sig(c.max_dilatancy_deg, 3),
                           pct(c.max_dilatancy_e1, 3), sig(c.phi_deg, 4), sig(c.stress_ratio, 4), sig(c.void_ratio, 4),
                           sig(c.p / 1e3, 4), sig(c.fabric_dev, 3), sig(c.ev_slope, 2), sig(c.stress_ratio_slope, 2),
                           c.reached ? "yes" : "no", sig(m.off_line, 2)});
    }
  }
  return {lines, runs};
}

void add_critical_figures(std::vector<Figure>& figs, const std::vector<CriticalGroup>& groups) {
  for (const CriticalGroup& g : groups) {
    Figure f{fmt::format("critical_state_{}_{}_{}", tag(g.model), tag(sig(100 * g.xi)), tag(sig(g.rate))),
             group_title(g) + ": to the critical state",
             "The stress ratio q/p', the volumetric strain and the contact-normal fabric deviator against the axial "
             "strain, and the void ratio against p' (log scale): each run's path from its start (a colour per run), "
             "its mean over the critical window (a point, filled when at the critical state), the fitted critical "
             "state line (black; grey and dashed: the line of every run's window means, when not all runs are at "
             "the critical state) and M (dashed).",
             {}};
    Panel ratio{"q/p'", "axial strain ε1 (%)", "stress ratio q/p'", false, false, {}};
    Panel ev{"εv", "axial strain ε1 (%)", "volumetric strain εv (%)", false, false, {}};
    Panel plane{"e–ln p'", "mean stress p' (kPa)", "void ratio e", true, false, {}};
    Panel fabric{"fabric", "axial strain ε1 (%)", "contact-normal fabric deviator", false, false, {}};
    double e1_max = 0;
    for (std::size_t i = 0; i < g.runs.size(); ++i) {
      const Run& r = *g.runs[i].run;
      const std::string label = axes_label(r), style = "lines lw 1.5 " + lc(i);
      Curve cr{label, {}, {}, style}, cv{label, {}, {}, style}, cp{"", {}, {}, style}, cf{"", {}, {}, style};
      const RunCriticalState& c = g.runs[i].cs;
      cp.x.push_back(c.p0 / 1e3), cp.y.push_back(c.e0);  // the path from where the shearing starts
      for (std::size_t j = 0; j < r.s.e1.size(); ++j) {
        const double x = 100 * r.s.e1[j];
        e1_max = std::max(e1_max, x);
        cr.x.push_back(x), cr.y.push_back(r.s.q_over_p[j]);
        cv.x.push_back(x), cv.y.push_back(100 * r.s.ev[j]);
        cp.x.push_back(r.s.p[j] / 1e3), cp.y.push_back(r.s.void_ratio[j]);
        cf.x.push_back(x), cf.y.push_back(r.s.fabric_dev[j]);
      }
      ratio.curves.push_back(std::move(cr));
      ev.curves.push_back(std::move(cv));
      plane.curves.push_back(std::move(cp));
      fabric.curves.push_back(std::move(cf));
      plane.curves.push_back({"", {c.p / 1e3}, {c.void_ratio}, fmt::format("points pt {} ps 1.5 {}", c.reached ? 7 : 6, lc(i))});
    }
    const bool at_cs = g.line.ok;
    const CriticalStateLine& l = at_cs ? g.line : g.line_all;
    if (l.ok) {
      Curve line{fmt::format("{} Γ = {}, λ = {}", at_cs ? "CSL" : "window means (not at the CS)", sig(l.gamma, 4),
                             sig(l.lambda, 3)),
                 {}, {}, at_cs ? "lines lw 2 lc rgb '#000000'" : "lines lw 2 dt 2 lc rgb '#808080'"};
      for (int k = 0; k <= 20; ++k) {
        const double p = l.p_lo / 1.5 * std::pow(1.5 * 1.5 * l.p_hi / l.p_lo, k / 20.0);
        line.x.push_back(p / 1e3), line.y.push_back(l.void_ratio_at(p));
      }
      plane.curves.push_back(std::move(line));
    }
    if (std::isfinite(l.M))
      ratio.curves.push_back({fmt::format("M = {}", sig(l.M, 3)), {0, e1_max}, {l.M, l.M}, "lines lw 2 dt 2 lc rgb '#000000'"});
    f.panels = {std::move(ratio), std::move(ev), std::move(plane), std::move(fabric)};
    figs.push_back(std::move(f));
  }
}

}  // namespace analysis
}  // namespace qsdem
