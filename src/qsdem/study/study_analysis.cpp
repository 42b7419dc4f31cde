// Analysis of a study (SPEC 9, paper sections 4-5). Choices and formulas: docs/analysis.md.
#include "qsdem/study/study_analysis.hpp"
#include "qsdem/study/study_analysis_data.hpp"

#include <algorithm>
#include <chrono>
#include <cctype>
#include <cmath>
#include <cstdlib>
#include <cstring>
#include <ctime>
#include <fstream>
#include <map>
#include <numeric>
#include <optional>
#include <sstream>
#include <stdexcept>
#include <tuple>
#include <string>
#include <vector>

#include <fmt/format.h>

#include "qsdem/run/files.hpp"
#include "qsdem/run/output.hpp"
#include "qsdem/version.hpp"

namespace qsdem {

namespace fs = std::filesystem;
using nlohmann::json;

// ---------------------------------------------------------------------------------------------
// Pure fits
// ---------------------------------------------------------------------------------------------

OptimumFit fit_optimum(std::span<const double> xi, std::span<const double> index) {
  if (xi.size() != index.size()) throw std::invalid_argument("fit_optimum: xi and index differ in length");
  // Only points that can enter a log-log fit (xi = 0 is tabulated elsewhere, SPEC 9).
  std::vector<std::pair<double, double>> p;
  for (std::size_t i = 0; i < xi.size(); ++i)
    if (std::isfinite(xi[i]) && std::isfinite(index[i]) && xi[i] > 0 && index[i] > 0)
      p.emplace_back(xi[i], index[i]);
  std::sort(p.begin(), p.end());
  OptimumFit f;
  f.n_points = static_cast<int>(p.size());
  if (p.empty()) {
    f.flag = "no data";
    return f;
  }
  const auto imin = static_cast<std::size_t>(
      std::min_element(p.begin(), p.end(), [](auto& l, auto& r) { return l.second < r.second; }) - p.begin());
  f.xi_min = p[imin].first;
  f.index_min = p[imin].second;
  if (p.size() == 1) {
    // One ratio (e.g. a stage that ran only the optimum picked from another): no minimum to find.
    f.xi_opt = f.xi_min;
    f.index_at_opt = f.index_min;
    f.method = "single";
    f.flag = "one damping ratio at this rate: its value, not a minimum";
    return f;
  }
  if (imin == 0 || imin + 1 == p.size()) {
    // The minimum may lie outside the sampled range: report the end value, never extrapolate.
    f.xi_opt = f.xi_min;
    f.index_at_opt = f.index_min;
    f.method = "edge";
    f.at_edge = true;
    f.flag = imin == 0 ? "at edge of range (smallest xi > 0)" : "at edge of range (largest xi)";
    return f;
  }
  // Parabola v = c2 u^2 + c1 u + c0 through the minimum and its two neighbours (u = log10 xi,
  // v = log10 index): the paper's curves are smooth in log-log around the minimum (Figs. 3-6).
  const double u0 = std::log10(p[imin - 1].first), u1 = std::log10(p[imin].first),
               u2 = std::log10(p[imin + 1].first);
  const double v0 = std::log10(p[imin - 1].second), v1 = std::log10(p[imin].second),
               v2 = std::log10(p[imin + 1].second);
  const double d01 = (v1 - v0) / (u1 - u0), d12 = (v2 - v1) / (u2 - u1);
  f.c2 = (d12 - d01) / (u2 - u0);
  f.c1 = d01 - f.c2 * (u0 + u1);
  f.c0 = v0 - f.c2 * u0 * u0 - f.c1 * u0;
  if (!(f.c2 > 0)) {
    // Flat or concave (only possible with ties): no vertex to trust.
    f.xi_opt = f.xi_min;
    f.index_at_opt = f.index_min;
    f.method = "sampled-minimum";
    f.flag = "parabola not convex: sampled minimum";
    return f;
  }
  const double u = std::clamp(-f.c1 / (2 * f.c2), u0, u2);
  f.xi_opt = std::pow(10.0, u);
  f.index_at_opt = std::pow(10.0, (f.c2 * u + f.c1) * u + f.c0);
  f.method = "parabola";
  return f;
}

PowerLawFit fit_power_law(std::span<const double> x, std::span<const double> y) {
  if (x.size() != y.size()) throw std::invalid_argument("fit_power_law: x and y differ in length");
  std::vector<double> lx, ly;
  for (std::size_t i = 0; i < x.size(); ++i)
    if (std::isfinite(x[i]) && std::isfinite(y[i]) && x[i] > 0 && y[i] > 0) {
      lx.push_back(std::log10(x[i]));
      ly.push_back(std::log10(y[i]));
    }
  PowerLawFit f;
  f.n = static_cast<int>(lx.size());
  if (f.n < 2) {
    f.note = fmt::format("n={}: at least 2 rates needed", f.n);
    return f;
  }
  const double n = static_cast<double>(f.n);
  const double mx = std::accumulate(lx.begin(), lx.end(), 0.0) / n;
  const double my = std::accumulate(ly.begin(), ly.end(), 0.0) / n;
  double sxx = 0, sxy = 0, syy = 0;
  for (std::size_t i = 0; i < lx.size(); ++i) {
    sxx += (lx[i] - mx) * (lx[i] - mx);
    sxy += (lx[i] - mx) * (ly[i] - my);
    syy += (ly[i] - my) * (ly[i] - my);
  }
  if (!(sxx > 0)) {
    f.note = "all x equal: no fit";
    return f;
  }
  f.b = sxy / sxx;
  f.a = std::pow(10.0, my - f.b * mx);
  double ssr = 0;
  for (std::size_t i = 0; i < lx.size(); ++i) {
    const double r = ly[i] - (my + f.b * (lx[i] - mx));
    ssr += r * r;
  }
  f.r2 = syy > 0 ? 1.0 - ssr / syy : 1.0;
  f.ok = true;
  if (f.n == 2) f.note = "n=2: R^2 = 1 by construction";
  return f;
}

double quasi_static_rate(const PowerLawFit& fit, double imom_qs) {
  if (!fit.ok || !(fit.b > 0) || !(fit.a > 0)) return std::numeric_limits<double>::quiet_NaN();
  return std::pow(imom_qs / fit.a, 1.0 / fit.b);
}

namespace {

// A curve y(e1), finite points only, sorted by e1.
std::vector<std::pair<double, double>> sorted_curve(std::span<const double> e1, std::span<const double> y) {
  if (e1.size() != y.size()) throw std::invalid_argument("curve_deviation: e1 and y differ in length");
  std::vector<std::pair<double, double>> c;
  for (std::size_t i = 0; i < e1.size(); ++i)
    if (std::isfinite(e1[i]) && std::isfinite(y[i])) c.emplace_back(e1[i], y[i]);
  std::stable_sort(c.begin(), c.end(), [](const auto& a, const auto& b) { return a.first < b.first; });
  return c;
}

// A strain within this of a curve's end counts as on the curve: the last sample point of a run to
// 10 % is at 10 % up to rounding.
constexpr double strain_slack = 1e-9;

double interpolate(const std::vector<std::pair<double, double>>& c, double x) {
  if (c.empty() || x < c.front().first - strain_slack || x > c.back().first + strain_slack)
    return std::numeric_limits<double>::quiet_NaN();
  x = std::clamp(x, c.front().first, c.back().first);
  const auto hi = std::lower_bound(c.begin(), c.end(), x, [](const auto& p, double v) { return p.first < v; });
  if (hi == c.begin()) return hi->second;
  const auto lo = hi - 1;
  if (hi->first == x || hi->first == lo->first) return hi->second;
  return lo->second + (hi->second - lo->second) * (x - lo->first) / (hi->first - lo->first);
}

}  // namespace

CurveDeviation curve_deviation(std::span<const double> e1_ref, std::span<const double> y_ref,
                               std::span<const double> e1, std::span<const double> y,
                               std::span<const double> at_strains) {
  const auto ref = sorted_curve(e1_ref, y_ref), run = sorted_curve(e1, y);
  CurveDeviation d;
  for (double s : at_strains) d.at.push_back(interpolate(run, s) - interpolate(ref, s));
  if (ref.empty() || run.empty()) return d;
  const double lo = std::max(ref.front().first, run.front().first);
  const double hi = std::min(ref.back().first, run.back().first);
  if (lo > hi + strain_slack) return d;
  d.e1_lo = lo, d.e1_hi = hi;
  double sum = 0;
  for (const auto& [x, yr] : ref) {
    if (x < lo - strain_slack || x > hi + strain_slack) continue;
    const double diff = interpolate(run, x) - yr;
    sum += diff * diff;
    ++d.n;
  }
  if (d.n > 0) d.rms = std::sqrt(sum / d.n);
  return d;
}

nlohmann::ordered_json to_json(const AnalysisSettings& s) {
  const auto opt = [](double v) { return std::isfinite(v) ? nlohmann::ordered_json(v) : nlohmann::ordered_json(nullptr); };
  nlohmann::ordered_json j;
  j["baseline"] = s.baseline;
  j["imom_target"] = s.imom_target;
  if (s.has_reference) {
    nlohmann::ordered_json r = nlohmann::ordered_json::object();
    if (!s.reference_model.empty()) r["model"] = s.reference_model;
    if (std::isfinite(s.reference_ratio)) r["ratio"] = s.reference_ratio;
    if (std::isfinite(s.reference_rate)) r["rate"] = s.reference_rate;
    j["reference"] = r;
  } else {
    j["reference"] = nullptr;
  }
  j["phi_tolerance_deg"] = s.phi_tolerance_deg;
  j["ev_tolerance"] = s.ev_tolerance;
  j["cn_tolerance"] = opt(s.cn_tolerance);
  j["convergence"] = {{"phi_tolerance_deg", s.convergence.phi_rms_deg},
                      {"ev_tolerance", s.convergence.ev_rms},
                      {"within_seed_scatter", s.convergence.within_seed_scatter}};
  if (std::isfinite(s.convergence.ev_end)) j["convergence"]["ev_end_tolerance"] = s.convergence.ev_end;
  if (s.critical_state.on)
    j["critical_state"] = {{"from", s.critical_state.from},
                           {"ev_slope", s.critical_state.ev_slope},
                           {"stress_ratio_slope", s.critical_state.stress_ratio_slope}};
  return j;
}

AnalysisSettings analysis_settings_from_json(const nlohmann::json& j) {
  AnalysisSettings s;
  if (!j.is_object()) return s;
  const auto number = [&](const nlohmann::json& o, const char* key, double def) {
    const auto it = o.find(key);
    return it != o.end() && it->is_number() ? it->get<double>() : def;
  };
  if (j.contains("baseline") && j["baseline"].is_string()) s.baseline = j["baseline"];
  s.imom_target = number(j, "imom_target", s.imom_target);
  if (j.contains("reference") && j["reference"].is_object()) {
    const auto& r = j["reference"];
    s.has_reference = true;
    if (r.contains("model") && r["model"].is_string()) s.reference_model = r["model"];
    s.reference_ratio = number(r, "ratio", s.reference_ratio);
    s.reference_rate = number(r, "rate", s.reference_rate);
  }
  s.phi_tolerance_deg = number(j, "phi_tolerance_deg", s.phi_tolerance_deg);
  s.ev_tolerance = number(j, "ev_tolerance", s.ev_tolerance);
  s.cn_tolerance = number(j, "cn_tolerance", s.cn_tolerance);
  if (j.contains("convergence") && j["convergence"].is_object()) {
    const auto& c = j["convergence"];
    s.convergence.phi_rms_deg = number(c, "phi_tolerance_deg", s.convergence.phi_rms_deg);
    s.convergence.ev_rms = number(c, "ev_tolerance", s.convergence.ev_rms);
    if (c.contains("within_seed_scatter") && c["within_seed_scatter"].is_boolean())
      s.convergence.within_seed_scatter = c["within_seed_scatter"];
    s.convergence.ev_end = number(c, "ev_end_tolerance", s.convergence.ev_end);
  }
  if (j.contains("critical_state") && j["critical_state"].is_object()) {
    const auto& c = j["critical_state"];
    s.critical_state.on = true;
    s.critical_state.from = number(c, "from", s.critical_state.from);
    s.critical_state.ev_slope = number(c, "ev_slope", s.critical_state.ev_slope);
    s.critical_state.stress_ratio_slope = number(c, "stress_ratio_slope", s.critical_state.stress_ratio_slope);
  }
  return s;
}

void require_gnuplot() {
  if (!gnuplot_available())
    throw std::runtime_error(
        "qsdem study analysis: gnuplot is needed for the figures but could not be run; install the "
        "Debian package gnuplot-nox (apt-get install gnuplot-nox)");
}

namespace analysis {

// ---------------------------------------------------------------------------------------------
// Small helpers
// ---------------------------------------------------------------------------------------------

double num(const json& j, const char* key) {
  if (!j.is_object()) return nan;
  auto it = j.find(key);
  return it != j.end() && it->is_number() ? it->get<double>() : nan;
}

std::string read_text(const fs::path& p) {
  int err = 0;
  std::optional<std::string> text = read_regular_file(p, &err);
  if (!text) throw std::runtime_error(fmt::format("cannot read {}: {}", p.string(), file_error(err)));
  return std::move(*text);
}

// Numbers in tables: NaN shown as a dash (md/html) or empty (CSV).
std::string sig(double v, int digits) {
  if (!std::isfinite(v)) return "—";
  return fmt::format("{:.{}g}", v, digits);
}
std::string pct(double v, int digits) { return std::isfinite(v) ? sig(100 * v, digits) : "—"; }
std::string csvnum(double v) { return std::isfinite(v) ? fmt::format("{:.9g}", v) : ""; }
std::string csvstr(const std::string& s) {
  if (s.find_first_of(",\"\n") == std::string::npos) return s;
  std::string r = "\"";
  for (char c : s) r += c == '"' ? std::string("\"\"") : std::string(1, c);
  return r + "\"";
}

std::string utc_string(std::time_t t) {
  std::tm tm{};
  gmtime_r(&t, &tm);
  char buf[64];
  std::strftime(buf, sizeof buf, "%Y-%m-%d %H:%M UTC", &tm);
  return buf;
}

double log_distance(double a, double b) { return std::abs(std::log10(a) - std::log10(b)); }

// ---------------------------------------------------------------------------------------------
// Inputs
// ---------------------------------------------------------------------------------------------

// series.csv by header name (SPEC 10; more columns may follow, order is not assumed).
Series read_series(const fs::path& p) {
  std::istringstream in(read_text(p));
  std::string line;
  if (!std::getline(in, line)) throw std::runtime_error(p.string() + ": empty");
  std::map<std::string, std::size_t> col;
  {
    std::stringstream ss(line);
    std::string name;
    for (std::size_t i = 0; std::getline(ss, name, ','); ++i) {
      if (!name.empty() && name.back() == '\r') name.pop_back();
      col[name] = i;
    }
  }
  for (const char* need : {"e1", "ev", "phi_deg", "cn", "ufr", "imom", "ekin_J"})
    if (!col.count(need)) throw std::runtime_error(fmt::format("{}: no column {}", p.string(), need));
  Series s;
  std::vector<double> v;
  while (std::getline(in, line)) {
    if (line.empty()) continue;
    v.clear();
    const char* c = line.c_str();
    while (true) {
      char* end = nullptr;
      v.push_back(std::strtod(c, &end));
      if (end == c) v.back() = nan;
      const char* comma = std::strchr(c, ',');
      if (!comma) break;
      c = comma + 1;
    }
    if (v.size() < col.size()) continue;  // a truncated row is skipped
    s.e1.push_back(v[col["e1"]]);
    s.ev.push_back(v[col["ev"]]);
    s.phi.push_back(v[col["phi_deg"]]);
    s.cn.push_back(v[col["cn"]]);
    s.ufr.push_back(v[col["ufr"]]);
    s.imom.push_back(v[col["imom"]]);
    s.ekin.push_back(v[col["ekin_J"]]);
    s.q_over_p.push_back(col.count("q_Pa") && col.count("p_Pa") ? v[col["q_Pa"]] / v[col["p_Pa"]] : nan);
    const auto optional = [&](const char* name) { return col.count(name) ? v[col[name]] : nan; };
    s.p.push_back(optional("p_Pa"));
    s.void_ratio.push_back(optional("void_ratio"));
    s.fabric_dev.push_back(optional("fabric_dev"));
  }
  return s;
}

double mean_finite(const std::vector<double>& v) {
  double sum = 0;
  int n = 0;
  for (double x : v)
    if (std::isfinite(x)) sum += x, ++n;
  return n ? sum / n : nan;
}

Run load_run(const fs::path& dir, const json& m) {
  Run r;
  r.id = m.value("id", std::string());
  r.sample = m.value("sample", std::string());
  r.model = m.value("model", std::string());
  r.damping_model = m.value("damping_model", r.model);
  r.stage = m.value("stage", std::string());
  r.dir = m.value("dir", std::string());
  r.seed = m.value("seed", 0L);
  r.xi = num(m, "xi");
  r.rate = num(m, "rate");
  if (m.contains("rate_control") && m["rate_control"].is_object()) {
    r.controlled = true;
    r.control.index = m["rate_control"].value("index", std::string("imom"));
    r.control.target = num(m["rate_control"], "target");
  }
  const fs::path rd = dir / r.dir;
  if (!std::isfinite(r.xi) || !std::isfinite(r.rate) || r.xi < 0 || r.rate <= 0) {
    r.problem = "manifest entry without a valid xi and rate";
    return r;
  }
  if (!fs::exists(rd / "summary.json")) {
    r.problem = "not finished (no summary.json)";
    return r;
  }
  try {
    const json s = json::parse(read_text(rd / "summary.json"));
    r.mean_imom = num(s, "mean_imom");
    r.mean_ufr = num(s, "mean_ufr");
    r.mean_iuf = num(s, "mean_iuf");
    r.peak_phi = num(s, "peak_phi_deg");
    r.final_ev = num(s, "final_ev");
    r.steps = num(s, "steps");
    r.wall_s = num(s, "wall_s");
    r.psps = num(s, "particle_steps_per_s");
    if (s.contains("derived")) r.particles = num(s["derived"], "particles");
    if (s.contains("compaction") && s["compaction"].contains("final")) {
      r.e0 = num(s["compaction"]["final"], "void_ratio");
      r.p0 = num(s["compaction"]["final"], "p_Pa");
    }
    if (r.controlled && s.contains("triaxial") && s["triaxial"].contains("controller")) {
      const json& c = s["triaxial"]["controller"];
      Control& k = r.control;
      k.mean_rate = num(c, "mean_strain_rate"), k.final_rate = num(c, "final_strain_rate");
      k.min_rate = num(c, "min_strain_rate"), k.max_rate = num(c, "max_strain_rate");
      k.share_in_band = num(c, "share_within_band"), k.band_factor = num(c, "band_factor"), k.rows = num(c, "rows");
      k.steps_at_final = num(c, "constant_rate_steps_at_final");
      k.steps_at_mean = num(c, "constant_rate_steps_at_mean");
      k.mean_index = num(s, ("mean_" + k.index).c_str());
    }
    if (fs::exists(rd / "series.csv")) {
      r.s = read_series(rd / "series.csv");
      r.mean_ekin = mean_finite(r.s.ekin);
      r.ekin_norm = r.mean_ekin / (r.rate * r.rate);
      // Summary averages are authoritative; the series is the fallback (same definition, SPEC 8).
      if (!std::isfinite(r.mean_imom)) r.mean_imom = mean_finite(r.s.imom);
      if (!std::isfinite(r.mean_ufr)) r.mean_ufr = mean_finite(r.s.ufr);
    }
    r.finished = true;
  } catch (const std::exception& e) {
    r.problem = std::string("unreadable: ") + e.what();
  }
  return r;
}

// ---------------------------------------------------------------------------------------------
// Paper reference values (SPEC 9: Table 4, Fig. 9, Table 6)
// ---------------------------------------------------------------------------------------------

std::optional<PaperRef> paper_ref(const std::string& sample, const std::string& model) {
  if (sample.empty()) return std::nullopt;
  const char s = sample[0];
  if (s == 'A' && model == "od") return PaperRef{0.0023, 4.38e-8, 1.0, 336.46, 0.7511, 0.9970};
  if (s == 'A' && model == "nd") return PaperRef{0.0051, 1.03e-7, 2.35, 629.92, 0.8300, 0.9995};
  if (s == 'B' && model == "od") return PaperRef{0.0034, 5.46e-7, 1.0, 1124.07, 0.9661, 0.9997};
  if (s == 'B' && model == "nd") return PaperRef{0.0040, 5.42e-7, 0.99, 1047.28, 0.9607, 0.9990};
  return std::nullopt;
}

json paper_reference_json() {
  json j;
  for (const char* s : {"A", "B"})
    for (const char* m : {"od", "nd"}) {
      const auto r = *paper_ref(s, m);
      j["table4_fig9"][std::string(s) + "-" + m] = {{"xi_opt", r.xi_opt},   {"eps_qs", r.eps_qs},
                                                   {"improvement", r.improvement}, {"a", r.a},
                                                   {"b", r.b},             {"r2", r.r2}};
    }
  j["table6_B_od"] = json::array({
      {{"model", "B5"}, {"xi", 0.0005}, {"rate", 1e-5}, {"xi_opt", 0.0044}, {"peak_phi_deg", 23.20},
       {"mean_imom", 0.0503}, {"mean_ufr", 0.1279}, {"ekin_J", 1.29}, {"ekin_over_rate2_J", 1.29e10}},
      {{"model", "B6"}, {"xi", 0.005}, {"rate", 1e-6}, {"xi_opt", 0.0034}, {"peak_phi_deg", 23.60},
       {"mean_imom", 0.0022}, {"mean_ufr", 0.0053}, {"ekin_J", 1.32e-2}, {"ekin_over_rate2_J", 1.32e10}},
      {{"model", "B7"}, {"xi", 0.05}, {"rate", 1e-7}, {"xi_opt", 0.0033}, {"peak_phi_deg", 23.90},
       {"mean_imom", 0.0021}, {"mean_ufr", 0.0050}, {"ekin_J", 1.28e-4}, {"ekin_over_rate2_J", 1.28e10}},
  });
  j["source"] = "Yousefi (2018), Table 4, Fig. 9, Table 6 (SPEC 9)";
  return j;
}

// ---------------------------------------------------------------------------------------------
// Grouping and fits
// ---------------------------------------------------------------------------------------------

double avg(const std::vector<double>& v) { return mean_finite(v); }

std::vector<Group> make_groups(const std::vector<Run>& runs) {
  // Keys keep the manifest's order of samples and models; rates and xi are sorted numerically.
  std::vector<std::pair<std::string, std::string>> sm;
  std::map<std::tuple<std::string, std::string, double>, std::map<double, std::vector<const Run*>>> g;
  for (const Run& r : runs) {
    if (!std::isfinite(r.xi) || !std::isfinite(r.rate)) continue;  // listed as missing (load_run)
    if (r.controlled) continue;  // its rate is not constant: no point of an index against eps'
    if (std::find(sm.begin(), sm.end(), std::make_pair(r.sample, r.model)) == sm.end())
      sm.emplace_back(r.sample, r.model);
    g[{r.sample, r.model, r.rate}][r.xi].push_back(&r);
  }
  std::vector<Group> out;
  for (const auto& [s, m] : sm)
    for (auto& [key, byxi] : g) {
      if (std::get<0>(key) != s || std::get<1>(key) != m) continue;
      Group gr{s, m, std::get<2>(key), {}, {}, {}, nullptr};
      for (auto& [xi, rs] : byxi) {
        Point p;
        p.xi = xi;
        p.n_runs = static_cast<int>(rs.size());
        std::vector<double> im, uf, iu, ph, ek;
        for (const Run* r : rs) {
          if (!r->finished) continue;
          ++p.n_finished;
          im.push_back(r->mean_imom);
          uf.push_back(r->mean_ufr);
          iu.push_back(r->mean_iuf);
          ph.push_back(r->peak_phi);
          ek.push_back(r->ekin_norm);
        }
        p.imom = avg(im), p.ufr = avg(uf), p.iuf = avg(iu), p.phi = avg(ph), p.ekin_norm = avg(ek);
        gr.points.push_back(p);
      }
      std::vector<double> xs, im, uf;
      for (const Point& p : gr.points) xs.push_back(p.xi), im.push_back(p.imom), uf.push_back(p.ufr);
      gr.opt_imom = fit_optimum(xs, im);
      gr.opt_ufr = fit_optimum(xs, uf);
      // Representative run: finished, xi > 0, nearest to xi_opt in log10 xi (first seed wins).
      if (std::isfinite(gr.opt_imom.xi_opt))
        for (auto& [xi, rs] : byxi)
          for (const Run* r : rs)
            if (r->finished && xi > 0 && !r->s.e1.empty() &&
                (!gr.chosen || log_distance(xi, gr.opt_imom.xi_opt) <
                                   log_distance(gr.chosen->xi, gr.opt_imom.xi_opt) - 1e-12))
              gr.chosen = r;
      out.push_back(std::move(gr));
    }
  return out;
}

// Table 4's one value from the per-rate optima (analysis.md section 3).
double geometric_mean(const std::vector<double>& xs) {
  double s = 0;
  for (double x : xs) s += std::log10(x);
  return std::pow(10.0, s / static_cast<double>(xs.size()));
}

std::vector<Law> make_laws(const std::vector<Group>& groups, double imom_target) {
  std::vector<Law> laws;
  for (const Group& g : groups) {
    auto it = std::find_if(laws.begin(), laws.end(),
                           [&](const Law& l) { return l.sample == g.sample && l.model == g.model; });
    if (it == laws.end()) {
      laws.push_back(Law{g.sample, g.model, {}, nan, {}, {}, {}, 0, 0, nan, nan, nan});
      it = laws.end() - 1;
    }
    if (!std::isfinite(g.opt_imom.index_at_opt)) continue;
    it->rates.push_back(g.rate);
    it->imom_at_opt.push_back(g.opt_imom.index_at_opt);
    it->xi_opt.push_back(g.opt_imom.xi_opt);
    if (g.opt_imom.method != "parabola") ++it->n_flagged;
    if (g.opt_imom.method == "single") ++it->n_single;
  }
  for (Law& l : laws) {
    l.fit = fit_power_law(l.rates, l.imom_at_opt);
    l.eps_qs = quasi_static_rate(l.fit, imom_target);
    // A rate run at one ratio has that ratio's index, not a minimum: in the fit, not in xi_opt.
    std::vector<double> optima;
    for (const Group& g : groups)
      if (g.sample == l.sample && g.model == l.model && std::isfinite(g.opt_imom.index_at_opt) &&
          g.opt_imom.method != "single")
        optima.push_back(g.opt_imom.xi_opt);
    if (!optima.empty()) {
      l.xi_opt_geomean = geometric_mean(optima);
      l.xi_opt_lo = *std::min_element(optima.begin(), optima.end());
      l.xi_opt_hi = *std::max_element(optima.begin(), optima.end());
    }
  }
  return laws;
}

// One per (sample, model) with a law, the baseline's own row included (ratio 1 when its eps'_QS
// is finite).
std::vector<Improvement> make_improvements(const std::vector<Law>& laws, const std::string& baseline) {
  std::vector<Improvement> out;
  for (const Law& l : laws) {
    Improvement im{l.sample, l.model, baseline, l.eps_qs};
    for (const Law& k : laws)
      if (k.sample == l.sample && k.model == baseline) im.eps_qs_baseline = k.eps_qs;
    im.ratio = im.eps_qs / im.eps_qs_baseline;
    out.push_back(im);
  }
  return out;
}

const Improvement* find_improvement(const std::vector<Improvement>& imps, const std::string& sample,
                                    const std::string& model) {
  for (const Improvement& im : imps)
    if (im.sample == sample && im.model == model) return &im;
  return nullptr;
}

const OptimumFit* find_opt(const std::vector<Group>& groups, const Run& r) {
  for (const Group& g : groups)
    if (g.sample == r.sample && g.model == r.model && g.rate == r.rate) return &g.opt_imom;
  return nullptr;
}

std::vector<EqualSet> make_equal_sets(const std::vector<Run>& runs) {
  std::vector<EqualSet> out;
  for (const Run& r : runs) {
    if (!r.finished || !(r.xi > 0) || r.controlled) continue;
    const std::string key = fmt::format("{:.3g}", r.xi * r.rate);
    auto it = std::find_if(out.begin(), out.end(), [&](const EqualSet& e) {
      return e.sample == r.sample && e.model == r.model && e.product == key;
    });
    if (it == out.end()) out.push_back({r.sample, r.model, key, {&r}});
    else it->runs.push_back(&r);
  }
  std::erase_if(out, [](const EqualSet& e) {
    for (const Run* r : e.runs)
      if (r->rate != e.runs.front()->rate) return false;
    return true;  // a single rate: nothing to compare
  });
  for (EqualSet& e : out)
    std::sort(e.runs.begin(), e.runs.end(), [](const Run* a, const Run* b) { return a->rate > b->rate; });
  return out;
}

// Each controlled run against the power law of the same index over the constant-rate runs of its
// sample, seed, model and damping ratio (docs/analysis.md, controlled runs).
std::vector<ControlComparison> make_controls(const std::vector<Run>& runs) {
  std::vector<ControlComparison> out;
  for (const Run& c : runs) {
    if (!c.controlled) continue;
    ControlComparison k;
    k.run = &c;
    std::vector<double> x, y;
    for (const Run& r : runs) {
      if (r.controlled || !r.finished || r.sample != c.sample || r.seed != c.seed || r.model != c.model ||
          !same_value(r.xi, c.xi))
        continue;
      const double index = c.control.index == "ufr" ? r.mean_ufr : c.control.index == "iuf" ? r.mean_iuf : r.mean_imom;
      if (!(index > 0) || !std::isfinite(index)) continue;
      k.fit_runs.push_back(&r);
      x.push_back(r.rate), y.push_back(index);
    }
    k.fit = fit_power_law(x, y);
    k.eps_qs = quasi_static_rate(k.fit, c.control.target);
    k.mean_over_qs = c.control.mean_rate / k.eps_qs;
    k.final_over_qs = c.control.final_rate / k.eps_qs;
    out.push_back(std::move(k));
  }
  return out;
}

// ---------------------------------------------------------------------------------------------
// Stages of a staged design (docs/study.md): which runs each lists, the ratios picked
// ---------------------------------------------------------------------------------------------

std::vector<double> numbers(const json& j, const char* key) {
  std::vector<double> v;
  if (j.contains(key) && j[key].is_array())
    for (const json& x : j[key])
      if (x.is_number()) v.push_back(x.get<double>());
  return v;
}

std::vector<std::string> names(const json& j, const char* key) {
  std::vector<std::string> v;
  if (j.contains(key) && j[key].is_array())
    for (const json& x : j[key])
      if (x.is_string()) v.push_back(x.get<std::string>());
  return v;
}

// The stages of study.json ("stages"); none for a design without [[stage]] tables.
std::vector<DesignStage> read_stages(const json& manifest) {
  std::vector<DesignStage> out;
  if (!manifest.contains("stages") || !manifest["stages"].is_array()) return out;
  for (const json& j : manifest["stages"]) {
    DesignStage s;
    s.name = j.value("name", std::string());
    s.samples = names(j, "samples");
    s.models = names(j, "models");
    s.rates = numbers(j, "strain_rates");
    s.ratios = numbers(j, "damping_ratios");
    if (j.contains("runs") && j["runs"].is_array())
      for (const json& r : j["runs"]) s.listed.push_back({r.value("model", std::string()), num(r, "xi"), num(r, "rate")});
    s.from = j.value("from", std::string());
    s.pick = j.value("pick", std::string());
    s.at_rate = num(j, "at_rate");
    s.digits = j.value("digits", 2);
    s.controlled = j.contains("rate_control");
    if (j.contains("picks") && j["picks"].is_array())
      for (const json& p : j["picks"])
        s.picks.push_back({p.value("sample", std::string()), p.value("model", std::string()), num(p, "xi_opt"),
                           p.value("method", std::string()), p.value("runs_used", 0), numbers(p, "ratios")});
    out.push_back(std::move(s));
  }
  return out;
}

// The optimum of each (sample, model) over `runs` (one stage's), in their order.
std::vector<StageOptimum> optima_of(const std::vector<Run>& runs, double at_rate) {
  const std::vector<Group> groups = make_groups(runs);
  std::vector<StageOptimum> out;
  for (const Run& r : runs) {
    auto it = std::find_if(out.begin(), out.end(), [&](const StageOptimum& o) { return o.sample == r.sample && o.model == r.model; });
    if (it == out.end()) {
      out.push_back(StageOptimum{r.sample, r.model, nan, {}, {}, 0});
      it = out.end() - 1;
    }
    if (r.xi > 0 && !has_value(it->sampled, r.xi)) it->sampled.push_back(r.xi);
    it->runs_used += r.finished;
  }
  for (StageOptimum& o : out) {
    std::sort(o.sampled.begin(), o.sampled.end());
    std::vector<double> xs;
    for (const Group& g : groups) {
      if (g.sample != o.sample || g.model != o.model || !std::isfinite(g.opt_imom.index_at_opt)) continue;
      if (std::isfinite(at_rate)) {
        if (!same_value(g.rate, at_rate)) continue;
        o.xi_opt = g.opt_imom.xi_opt;
        o.method = fmt::format("at eps' {}: {}", sig(g.rate), g.opt_imom.method);
      }
      xs.push_back(g.opt_imom.xi_opt);
    }
    if (!std::isfinite(at_rate) && !xs.empty()) {
      o.xi_opt = geometric_mean(xs);
      o.method = fmt::format("geometric mean over {} rate{}", xs.size(), xs.size() == 1 ? "" : "s");
    }
  }
  return out;
}

std::vector<PickCheck> check_picks(const std::vector<DesignStage>& stages, const std::vector<Run>& runs) {
  std::vector<PickCheck> out;
  for (const DesignStage& st : stages) {
    if (st.from.empty()) continue;
    const auto src = std::find_if(stages.begin(), stages.end(), [&](const DesignStage& s) { return s.name == st.from; });
    if (src == stages.end()) continue;
    std::vector<Run> members;
    for (const Run& r : runs)
      if (src->lists(r)) members.push_back(r);
    for (const StageOptimum& o : optima_of(members, st.at_rate)) {
      if (!has_name(st.samples, o.sample) || !has_name(st.models, o.model)) continue;
      PickCheck c{&st, st.pick_of(o.sample, o.model), o, pick_ratios(o, st.pick, st.digits)};
      if (c.recorded) {
        c.changed = c.now_ratios.size() != c.recorded->ratios.size();
        for (std::size_t k = 0; !c.changed && k < c.now_ratios.size(); ++k)
          c.changed = !same_value(c.now_ratios[k], c.recorded->ratios[k]);
      }
      out.push_back(std::move(c));
    }
  }
  return out;
}

// ---------------------------------------------------------------------------------------------
// Damping dependence: each run against the reference run of its (sample, seed) (docs/analysis.md)
// ---------------------------------------------------------------------------------------------

// The reference run of each (sample, seed), from every run of the manifest (finished or not: the
// choice must not depend on which runs have finished).
std::map<std::pair<std::string, long>, const Run*> find_references(const std::vector<Run>& runs,
                                                                   const AnalysisSettings& st) {
  std::map<std::pair<std::string, long>, const Run*> out;
  if (!st.has_reference) return out;
  std::map<std::pair<std::string, long>, std::vector<const Run*>> candidates;
  for (const Run& r : runs) {
    if (!std::isfinite(r.xi) || !std::isfinite(r.rate) || r.controlled) continue;
    if (!st.reference_model.empty() && r.model != st.reference_model) continue;
    if (std::isfinite(st.reference_ratio) && !same_value(r.xi, st.reference_ratio)) continue;
    if (std::isfinite(st.reference_rate) && !same_value(r.rate, st.reference_rate)) continue;
    candidates[{r.sample, r.seed}].push_back(&r);
  }
  // The slowest rate, then the least damped (no damping counts as xi = 0), then manifest order.
  const auto damping = [](const Run* r) { return r->damping_model == "none" ? 0.0 : r->xi; };
  for (const auto& [key, c] : candidates)
    out[key] = *std::min_element(c.begin(), c.end(), [&](const Run* a, const Run* b) {
      if (a->rate != b->rate) return a->rate < b->rate;
      return damping(a) < damping(b);
    });
  return out;
}

CurveDeviation deviation_of(const std::vector<double>& e1_ref, const std::vector<double>& y_ref,
                            const std::vector<double>& e1, const std::vector<double>& y) {
  return curve_deviation(e1_ref, y_ref, e1, y, deviation_strains);
}

// phi, ev and Cn of `run` against those of `ref` (finished, with rows); no verdict.
Deviation curves_against(const Run& run, const Run& ref) {
  Deviation d;
  d.run = &run;
  d.ref = &ref;
  const Series& a = ref.s;
  d.phi = deviation_of(a.e1, a.phi, run.s.e1, run.s.phi);
  d.ev = deviation_of(a.e1, a.ev, run.s.e1, run.s.ev);
  d.cn = deviation_of(a.e1, a.cn, run.s.e1, run.s.cn);
  return d;
}

// Every finished run of a (sample, seed) that has a reference, with its verdict: quasi-static
// only if its mean IMom is under the target AND its RMS deviations are within the tolerances.
std::vector<Deviation> make_deviations(const std::vector<Run>& runs,
                                       const std::map<std::pair<std::string, long>, const Run*>& refs,
                                       const AnalysisSettings& st) {
  std::vector<Deviation> out;
  for (const Run& r : runs) {
    const auto it = refs.find({r.sample, r.seed});
    if (!r.finished || it == refs.end()) continue;
    const Run& ref = *it->second;
    if (!ref.finished || ref.s.e1.empty()) {
      Deviation d;
      d.run = &r;
      d.ref = &ref;
      d.verdict = "not decided: the reference run has not finished";
      out.push_back(d);
      continue;
    }
    Deviation d = curves_against(r, ref);
    std::vector<std::string> why;
    if (!(r.mean_imom < st.imom_target))
      why.push_back(fmt::format("mean IMom {} % ≥ {} %", pct(r.mean_imom), pct(st.imom_target)));
    const auto check = [&](const CurveDeviation& c, double tol, const std::string& what, const std::string& unit,
                           double scale) {
      if (!std::isfinite(tol)) return;
      if (!(c.rms <= tol))
        why.push_back(fmt::format("RMS Δ{} {}{} > {}{}", what, sig(scale * c.rms), unit, sig(scale * tol), unit));
    };
    check(d.phi, st.phi_tolerance_deg, "φ", "°", 1);
    check(d.ev, st.ev_tolerance, "εv", " %", 100);
    check(d.cn, st.cn_tolerance, "Cn", "", 1);
    d.quasi_static = why.empty() ? 1 : 0;
    for (const std::string& w : why) d.verdict += (d.verdict.empty() ? "" : "; ") + w;
    if (why.empty()) d.verdict = "quasi-static";
    out.push_back(d);
  }
  return out;
}

std::vector<SeedScatter> make_seed_scatter(const std::map<std::pair<std::string, long>, const Run*>& refs) {
  std::map<std::string, std::vector<const Run*>> by_sample;
  for (const auto& [key, r] : refs)
    if (r->finished && !r->s.e1.empty()) by_sample[key.first].push_back(r);
  std::vector<SeedScatter> out;
  for (const auto& [sample, rs] : by_sample) {
    if (rs.size() < 2) continue;
    SeedScatter s{sample, static_cast<int>(rs.size()), 0, 0, 0};
    for (std::size_t i = 0; i < rs.size(); ++i)
      for (std::size_t j = i + 1; j < rs.size(); ++j) {
        const Series &a = rs[i]->s, &b = rs[j]->s;
        s.phi = std::max(s.phi, deviation_of(a.e1, a.phi, b.e1, b.phi).rms);
        s.ev = std::max(s.ev, deviation_of(a.e1, a.ev, b.e1, b.ev).rms);
        s.cn = std::max(s.cn, deviation_of(a.e1, a.cn, b.e1, b.cn).rms);
      }
    out.push_back(s);
  }
  return out;
}

// Each stage of listed runs: every finished run against the stage's first finished run of the same
// sample and seed, in manifest order.
std::vector<ListedPair> make_listed_pairs(const std::vector<DesignStage>& stages, const std::vector<Run>& runs) {
  std::vector<ListedPair> out;
  for (const DesignStage& st : stages) {
    if (st.listed.size() < 2) continue;
    std::map<std::pair<std::string, long>, const Run*> first;
    for (const Run& r : runs) {
      if (!r.finished || r.s.e1.empty() || !st.lists(r)) continue;
      const auto [it, fresh] = first.try_emplace({r.sample, r.seed}, &r);
      if (fresh) continue;
      const Deviation c = curves_against(r, *it->second);
      out.push_back({&st, &r, it->second, c.phi, c.ev, c.cn});
    }
  }
  return out;
}

// ---------------------------------------------------------------------------------------------
// JSON and CSV
// ---------------------------------------------------------------------------------------------

json opt_json(const OptimumFit& o) {
  return {{"xi_opt", o.xi_opt},   {"index_at_opt", o.index_at_opt},
          {"xi_min", o.xi_min},   {"index_min", o.index_min},
          {"n_points", o.n_points}, {"method", o.method},
          {"flag", o.flag},       {"at_edge", o.at_edge},
          {"parabola", {{"c2", o.c2}, {"c1", o.c1}, {"c0", o.c0}}}};
}

json run_json(const Run& r) {
  return {{"id", r.id},
          {"sample", r.sample},
          {"seed", r.seed},
          {"model", r.model},
          {"damping_model", r.damping_model},
          {"stage", r.stage.empty() ? json(nullptr) : json(r.stage)},
          {"xi", r.xi},
          {"rate", r.rate},
          {"xi_times_rate", r.xi * r.rate},
          {"dir", r.dir},
          {"finished", r.finished},
          {"problem", r.problem},
          {"mean_imom", r.mean_imom},
          {"mean_ufr", r.mean_ufr},
          {"mean_iuf", r.mean_iuf},
          {"peak_phi_deg", r.peak_phi},
          {"final_ev", r.final_ev},
          {"mean_ekin_J", r.mean_ekin},
          {"ekin_over_rate2_J", r.ekin_norm},
          {"steps", r.steps},
          {"wall_s", r.wall_s},
          {"particle_steps_per_s", r.psps},
          {"particles", r.particles},
          {"series_rows", r.s.e1.size()},
          {"rate_control", r.controlled ? json{{"index", r.control.index}, {"target", r.control.target}} : json(nullptr)}};
}

json controls_json(const std::vector<ControlComparison>& controls) {
  json out = json::array();
  for (const ControlComparison& k : controls) {
    const Run& r = *k.run;
    const Control& c = r.control;
    json ids = json::array();
    for (const Run* f : k.fit_runs) ids.push_back(f->id);
    out.push_back({{"id", r.id},
                   {"sample", r.sample},
                   {"seed", r.seed},
                   {"model", r.model},
                   {"xi", r.xi},
                   {"start_rate", r.rate},
                   {"finished", r.finished},
                   {"index", c.index},
                   {"target", c.target},
                   {"band_factor", c.band_factor},
                   {"mean_strain_rate", c.mean_rate},
                   {"final_strain_rate", c.final_rate},
                   {"min_strain_rate", c.min_rate},
                   {"max_strain_rate", c.max_rate},
                   {"share_within_band", c.share_in_band},
                   {"mean_index", c.mean_index},
                   {"rows", c.rows},
                   {"wall_s", r.wall_s},
                   {"steps", r.steps},
                   {"constant_rate_steps_at_final", c.steps_at_final},
                   {"constant_rate_steps_at_mean", c.steps_at_mean},
                   {"constant_rate_fit",
                    {{"runs", ids},
                     {"n", k.fit.n},
                     {"ok", k.fit.ok},
                     {"a", k.fit.a},
                     {"b", k.fit.b},
                     {"r2", k.fit.r2},
                     {"note", k.fit.note},
                     {"eps_qs_at_target", k.eps_qs}}},
                   {"mean_over_eps_qs", k.mean_over_qs},
                   {"final_over_eps_qs", k.final_over_qs}});
  }
  return out;
}

std::string controls_csv(const std::vector<ControlComparison>& controls) {
  std::string s = "id,sample,seed,model,xi,start_rate,index,target,mean_strain_rate,final_strain_rate,"
                  "min_strain_rate,max_strain_rate,share_within_band,band_factor,mean_index,wall_s,steps,"
                  "constant_rate_steps_at_final,fit_runs,fit_a,fit_b,fit_r2,fit_eps_qs_at_target,mean_over_eps_qs,"
                  "final_over_eps_qs\n";
  for (const ControlComparison& k : controls) {
    const Run& r = *k.run;
    const Control& c = r.control;
    s += fmt::format("{},{},{},{},{},{},{},{},{},{},{},{},{},{},{},{},{},{},{},{},{},{},{},{},{}\n", csvstr(r.id),
                     csvstr(r.sample), r.seed, csvstr(r.model), csvnum(r.xi), csvnum(r.rate), csvstr(c.index),
                     csvnum(c.target), csvnum(c.mean_rate), csvnum(c.final_rate), csvnum(c.min_rate),
                     csvnum(c.max_rate), csvnum(c.share_in_band), csvnum(c.band_factor), csvnum(c.mean_index),
                     csvnum(r.wall_s), csvnum(r.steps), csvnum(c.steps_at_final), k.fit.n, csvnum(k.fit.a),
                     csvnum(k.fit.b), csvnum(k.fit.r2), csvnum(k.eps_qs), csvnum(k.mean_over_qs),
                     csvnum(k.final_over_qs));
  }
  return s;
}

std::string per_run_csv(const std::vector<Run>& runs) {
  std::string s =
      "id,sample,seed,model,xi,rate,xi_times_rate,status,mean_imom,mean_ufr,mean_iuf,peak_phi_deg,final_ev,"
      "mean_ekin_J,ekin_over_rate2_J,steps,wall_s,particles,dir,stage\n";
  for (const Run& r : runs)
    s += fmt::format("{},{},{},{},{},{},{},{},{},{},{},{},{},{},{},{},{},{},{},{}\n", csvstr(r.id), csvstr(r.sample),
                     r.seed, csvstr(r.model), csvnum(r.xi), csvnum(r.rate), csvnum(r.xi * r.rate),
                     r.finished ? "finished" : "missing", csvnum(r.mean_imom), csvnum(r.mean_ufr),
                     csvnum(r.mean_iuf), csvnum(r.peak_phi), csvnum(r.final_ev), csvnum(r.mean_ekin),
                     csvnum(r.ekin_norm), csvnum(r.steps), csvnum(r.wall_s), csvnum(r.particles), csvstr(r.dir),
                     csvstr(r.stage));
  return s;
}

std::string optimum_csv(const std::vector<Group>& groups) {
  std::string s = "sample,model,rate,index,n_points,xi_opt,index_at_opt,method,flag,xi_sampled_min,"
                  "index_sampled_min,chosen_run\n";
  for (const Group& g : groups)
    for (const auto& [name, o] : {std::pair{"imom", &g.opt_imom}, std::pair{"ufr", &g.opt_ufr}})
      s += fmt::format("{},{},{},{},{},{},{},{},{},{},{},{}\n", csvstr(g.sample), csvstr(g.model), csvnum(g.rate),
                       name, o->n_points, csvnum(o->xi_opt), csvnum(o->index_at_opt), o->method, csvstr(o->flag),
                       csvnum(o->xi_min), csvnum(o->index_min), g.chosen ? csvstr(g.chosen->id) : "");
  return s;
}

std::string power_law_csv(const std::vector<Law>& laws, const std::vector<Improvement>& imps) {
  std::string s = "sample,model,n_rates,a,b,r2,note,n_flagged_optima,eps_qs,improvement,xi_opt_geomean,"
                  "xi_opt_min,xi_opt_max,paper_xi_opt,paper_a,paper_b,paper_r2,paper_eps_qs,paper_improvement\n";
  for (const Law& l : laws) {
    const Improvement* im = find_improvement(imps, l.sample, l.model);
    const double imp = im ? im->ratio : nan;
    const auto ref = paper_ref(l.sample, l.model);
    auto r = [&](double PaperRef::*m) { return ref ? csvnum((*ref).*m) : std::string(); };
    s += fmt::format("{},{},{},{},{},{},{},{},{},{},{},{},{},{},{},{},{},{},{}\n", csvstr(l.sample), csvstr(l.model),
                     l.fit.n, csvnum(l.fit.a), csvnum(l.fit.b), csvnum(l.fit.r2), csvstr(l.fit.note), l.n_flagged,
                     csvnum(l.eps_qs), csvnum(imp), csvnum(l.xi_opt_geomean), csvnum(l.xi_opt_lo),
                     csvnum(l.xi_opt_hi), r(&PaperRef::xi_opt), r(&PaperRef::a), r(&PaperRef::b), r(&PaperRef::r2),
                     r(&PaperRef::eps_qs), r(&PaperRef::improvement));
  }
  return s;
}

std::string deviation_csv(const std::vector<Deviation>& devs) {
  std::string s = "id,sample,seed,model,xi,rate,reference,mean_imom";
  for (const char* q : {"phi_deg", "ev", "cn"})
    s += fmt::format(",{0}_rms,{0}_at_2pct,{0}_at_5pct,{0}_at_10pct", q);
  s += ",e1_lo,e1_hi,quasi_static,verdict\n";
  for (const Deviation& d : devs) {
    const Run& r = *d.run;
    s += fmt::format("{},{},{},{},{},{},{},{}", csvstr(r.id), csvstr(r.sample), r.seed, csvstr(r.model), csvnum(r.xi),
                     csvnum(r.rate), csvstr(d.ref->id), csvnum(r.mean_imom));
    for (const CurveDeviation* c : {&d.phi, &d.ev, &d.cn}) {
      s += fmt::format(",{}", csvnum(c->rms));
      for (std::size_t k = 0; k < std::size(deviation_strains); ++k)
        s += fmt::format(",{}", csvnum(k < c->at.size() ? c->at[k] : nan));
    }
    s += fmt::format(",{},{},{},{}\n", csvnum(d.phi.e1_lo), csvnum(d.phi.e1_hi),
                     d.quasi_static < 0 ? "" : d.quasi_static ? "true" : "false", csvstr(d.verdict));
  }
  return s;
}

json deviation_json(const CurveDeviation& c) {
  return {{"rms", c.rms}, {"at", c.at}, {"n", c.n}, {"e1_lo", c.e1_lo}, {"e1_hi", c.e1_hi}};
}

// The deviations of phi, ev and Cn, keyed as in analysis.json.
json curves_json(const CurveDeviation& phi, const CurveDeviation& ev, const CurveDeviation& cn) {
  return {{"phi_deg", deviation_json(phi)}, {"ev", deviation_json(ev)}, {"cn", deviation_json(cn)}};
}

json groups_json(const std::vector<Group>& groups) {
  json out = json::array();
  for (const Group& g : groups) {
    json pts = json::array();
    for (const Point& p : g.points)
      pts.push_back({{"xi", p.xi}, {"n_runs", p.n_runs}, {"n_finished", p.n_finished}, {"mean_imom", p.imom},
                     {"mean_ufr", p.ufr}, {"mean_iuf", p.iuf}, {"peak_phi_deg", p.phi},
                     {"ekin_over_rate2_J", p.ekin_norm}});
    out.push_back({{"sample", g.sample},
                   {"model", g.model},
                   {"rate", g.rate},
                   {"points", pts},
                   {"optimum_imom", opt_json(g.opt_imom)},
                   {"optimum_ufr", opt_json(g.opt_ufr)},
                   {"chosen_run", g.chosen ? json(g.chosen->id) : json(nullptr)}});
  }
  return out;
}

json power_laws_json(const Analysis& a) {
  json out = json::array();
  for (const Law& l : a.laws) {
    const auto ref = paper_ref(l.sample, l.model);
    json paper = nullptr;
    if (ref)
      paper = {{"xi_opt", ref->xi_opt}, {"eps_qs", ref->eps_qs}, {"a", ref->a},
               {"b", ref->b},           {"r2", ref->r2},         {"improvement", ref->improvement}};
    out.push_back({{"sample", l.sample},
                   {"model", l.model},
                   {"n_rates", l.fit.n},
                   {"ok", l.fit.ok},
                   {"a", l.fit.a},
                   {"b", l.fit.b},
                   {"r2", l.fit.r2},
                   {"note", l.fit.note},
                   {"eps_qs", l.eps_qs},
                   {"imom_qs", a.settings.imom_target},
                   {"rates", l.rates},
                   {"imom_at_opt", l.imom_at_opt},
                   {"xi_opt", l.xi_opt},
                   {"n_flagged_optima", l.n_flagged},
                   {"n_single_ratio", l.n_single},
                   {"xi_opt_geomean", l.xi_opt_geomean},
                   {"xi_opt_min", l.xi_opt_lo},
                   {"xi_opt_max", l.xi_opt_hi},
                   {"paper", paper}});
  }
  return out;
}

json stages_json(const Analysis& a) {
  json out = json::array();
  for (const DesignStage& st : a.stages) {
    json ids = json::array(), picks = json::array();
    for (const Run& r : a.runs)
      if (st.lists(r)) ids.push_back(r.id);
    for (const PickCheck& c : a.picks)
      if (c.stage == &st)
        picks.push_back({{"sample", c.now.sample},
                         {"model", c.now.model},
                         {"picked", c.recorded != nullptr},
                         {"xi_opt_when_picked", c.recorded ? json(c.recorded->xi_opt) : json(nullptr)},
                         {"ratios_run", c.recorded ? json(c.recorded->ratios) : json(nullptr)},
                         {"xi_opt_now", c.now.xi_opt},
                         {"method_now", c.now.method},
                         {"ratios_now", c.now_ratios},
                         {"runs_used_now", c.now.runs_used},
                         {"changed", c.changed}});
    out.push_back({{"name", st.name}, {"from", st.from.empty() ? json(nullptr) : json(st.from)}, {"runs", ids},
                   {"picks", picks}});
  }
  return out;
}

json damping_json(const Analysis& a) {
  if (!a.settings.has_reference) return nullptr;
  json refs = json::array(), devs = json::array(), scatter = json::array();
  for (const auto& [key, r] : a.refs)
    refs.push_back({{"sample", key.first}, {"seed", key.second}, {"run", r->id}, {"finished", r->finished}});
  for (const Deviation& d : a.devs) {
    json j = {{"id", d.run->id},
              {"reference", d.ref->id},
              {"mean_imom", d.run->mean_imom},
              {"quasi_static", d.quasi_static < 0 ? json(nullptr) : json(d.quasi_static == 1)},
              {"verdict", d.verdict}};
    j.update(curves_json(d.phi, d.ev, d.cn));
    devs.push_back(std::move(j));
  }
  for (const SeedScatter& s : a.scatter)
    scatter.push_back({{"sample", s.sample}, {"seeds", s.seeds}, {"phi_deg", s.phi}, {"ev", s.ev}, {"cn", s.cn}});
  return {{"strains", deviation_strains}, {"references", refs}, {"runs", devs}, {"seed_scatter", scatter}};
}

json listed_pairs_json(const Analysis& a) {
  json out = json::array();
  for (const ListedPair& p : a.pairs) {
    json j = {{"stage", p.stage->name}, {"id", p.run->id}, {"against", p.first->id}};
    j.update(curves_json(p.phi, p.ev, p.cn));
    out.push_back(std::move(j));
  }
  return out;
}

// The study's date for the report: the manifest's, else when study.json was written.
std::string study_date(const fs::path& dir, const json& manifest) {
  for (const char* k : {"date", "created", "started"})
    if (manifest.contains(k) && manifest[k].is_string()) return manifest[k];
  std::error_code ec;
  const auto ft = fs::last_write_time(dir / "study.json", ec);
  if (ec) return "unknown";
  const auto sys = std::chrono::file_clock::to_sys(ft);
  return utc_string(std::chrono::system_clock::to_time_t(
                        std::chrono::time_point_cast<std::chrono::system_clock::duration>(sys))) +
         " (study.json written)";
}

}  // namespace analysis

using namespace analysis;

namespace {

json read_manifest(const fs::path& dir) {
  const fs::path manifest_path = dir / "study.json";
  if (!fs::exists(manifest_path)) throw std::runtime_error("analyze_study: no " + manifest_path.string());
  try {
    return json::parse(read_text(manifest_path));
  } catch (const json::exception& e) {
    throw std::runtime_error("analyze_study: " + manifest_path.string() + ": " + e.what());
  }
}

// Fills `a` in place (its groups and deviations point into its runs).
void build_analysis(Analysis& a, const fs::path& dir, const json& manifest) {
  a.settings = analysis_settings_from_json(manifest.contains("analysis") ? manifest["analysis"] : json());
  if (manifest.contains("runs") && manifest["runs"].is_array())
    for (const json& m : manifest["runs"]) a.runs.push_back(load_run(dir, m));
  if (manifest.contains("samples") && manifest["samples"].is_array())
    for (const json& smp : manifest["samples"])
      for (Run& r : a.runs)
        if (r.sample == smp.value("name", std::string()) && r.seed == smp.value("seed", -1L)) {
          r.confining_stress = num(smp, "confining_stress_Pa");
          r.compaction_friction = num(smp, "compaction_friction");
        }
  if (a.settings.baseline.empty() && !a.runs.empty()) a.settings.baseline = a.runs.front().model;  // the design's first
  a.groups = make_groups(a.runs);
  a.laws = make_laws(a.groups, a.settings.imom_target);
  a.imps = make_improvements(a.laws, a.settings.baseline);
  a.equal = make_equal_sets(a.runs);
  a.stages = read_stages(manifest);
  a.picks = check_picks(a.stages, a.runs);
  a.refs = find_references(a.runs, a.settings);
  a.devs = make_deviations(a.runs, a.refs, a.settings);
  a.scatter = make_seed_scatter(a.refs);
  a.controls = make_controls(a.runs);
  a.pairs = make_listed_pairs(a.stages, a.runs);
  a.ladders = make_ladders(a.runs, a.settings.convergence);
  if (a.settings.critical_state.on) a.critical = make_critical_groups(a.runs, a.settings.critical_state);
}

}  // namespace

std::vector<StageOptimum> stage_optima(const fs::path& dir, const json& manifest, const std::string& stage,
                                       double at_rate) {
  const std::vector<DesignStage> stages = read_stages(manifest);
  const auto st = std::find_if(stages.begin(), stages.end(), [&](const DesignStage& s) { return s.name == stage; });
  if (st == stages.end()) throw std::runtime_error("stage_optima: no stage '" + stage + "' in the manifest");
  std::vector<Run> runs;
  if (manifest.contains("runs") && manifest["runs"].is_array())
    for (const json& m : manifest["runs"]) {
      Run r = load_run(dir, m);
      if (st->lists(r)) runs.push_back(std::move(r));
    }
  return optima_of(runs, at_rate);
}

std::vector<double> pick_ratios(const StageOptimum& o, const std::string& pick, int digits) {
  if (!std::isfinite(o.xi_opt) || !(o.xi_opt > 0)) return {};
  const double xi = std::stod(fmt::format("{:.{}g}", o.xi_opt, std::clamp(digits, 1, 17)));
  std::vector<double> out{xi};
  if (pick == "optimum+neighbours") {
    double below = nan, above = nan;
    for (double s : o.sampled) {
      if (s < xi && !same_value(s, xi)) below = s;
      if (s > xi && !same_value(s, xi) && !std::isfinite(above)) above = s;
    }
    if (std::isfinite(below)) out.insert(out.begin(), below);
    if (std::isfinite(above)) out.push_back(above);
  }
  return out;
}

namespace {

// analysis.json's content, figures aside (docs/analysis.md).
json analysis_json(const Analysis& an, const fs::path& dir, const json& manifest, const std::string& study_file,
                   const std::string& toml) {
  const std::vector<Run>& runs = an.runs;
  json a;
  a["study"] = {{"name", manifest.value("name", std::string("(unnamed)"))},
                {"dir", fs::absolute(dir).string()},
                {"study_file", study_file},
                {"date", study_date(dir, manifest)},
                {"analysed_at", utc_string(std::time(nullptr))},
                {"qsdem_version", QSDEM_VERSION}};
  a["resolved_configuration"] = toml;
  a["settings"] = to_json(an.settings);
  int finished = 0;
  for (const Run& r : runs) finished += r.finished;
  a["counts"] = {{"runs", static_cast<int>(runs.size())},
                 {"finished", finished},
                 {"missing", static_cast<int>(runs.size()) - finished}};
  a["runs"] = json::array();
  a["missing_runs"] = json::array();
  for (const Run& r : runs) {
    a["runs"].push_back(run_json(r));
    if (!r.finished) a["missing_runs"].push_back({{"id", r.id}, {"dir", r.dir}, {"reason", r.problem}});
  }
  a["groups"] = groups_json(an.groups);
  a["power_laws"] = power_laws_json(an);
  a["improvements"] = json::array();
  for (const Improvement& im : an.imps) {
    if (im.model == im.baseline) continue;
    const auto ref = paper_ref(im.sample, im.model), base = paper_ref(im.sample, im.baseline);
    a["improvements"].push_back({{"sample", im.sample},
                                 {"model", im.model},
                                 {"baseline", im.baseline},
                                 {"eps_qs", im.eps_qs},
                                 {"eps_qs_baseline", im.eps_qs_baseline},
                                 {"improvement", im.ratio},
                                 {"paper_improvement", ref && base ? json(ref->improvement / base->improvement)
                                                                   : json(nullptr)}});
  }
  a["equal_xi_rate"] = json::array();
  for (const EqualSet& e : an.equal) {
    json ids = json::array();
    for (const Run* r : e.runs) ids.push_back(r->id);
    a["equal_xi_rate"].push_back({{"sample", e.sample}, {"model", e.model}, {"xi_times_rate", e.product}, {"runs", ids}});
  }
  a["stages"] = stages_json(an);
  a["controlled_runs"] = controls_json(an.controls);
  a["damping_dependence"] = damping_json(an);
  a["listed_pairs"] = listed_pairs_json(an);
  a["convergence"] = ladders_json(an.ladders, an.settings.convergence);
  if (an.settings.critical_state.on) a["critical_state"] = critical_json(an.critical, an.settings.critical_state);
  a["paper_reference"] = paper_reference_json();

  return a;
}

// The tables (tables.md) and the CSVs of the analysis, named in a["files"]; a CSV an earlier
// analysis wrote and this one has no rows for is removed.
void write_tables(const Analysis& an, const std::vector<Table>& tables, const fs::path& adir, json& a) {
  std::string md = "# Study " + a["study"]["name"].get<std::string>() + "\n\nGenerated by qsdem analyze_study " +
                   a["study"]["analysed_at"].get<std::string>() +
                   ". Indices in percent. Choices: docs/analysis.md.\n\n";
  for (const Table& t : tables) md += to_markdown(t);
  write_file_atomic(adir / "tables.md", md);
  write_file_atomic(adir / "per_run.csv", per_run_csv(an.runs));
  write_file_atomic(adir / "optimum.csv", optimum_csv(an.groups));
  write_file_atomic(adir / "power_law.csv", power_law_csv(an.laws, an.imps));
  a["files"] = {{"tables_md", "analysis/tables.md"},
                {"per_run_csv", "analysis/per_run.csv"},
                {"optimum_csv", "analysis/optimum.csv"},
                {"power_law_csv", "analysis/power_law.csv"},
                {"analysis_json", "analysis/analysis.json"},
                {"report_html", "report.html"}};
  if (!an.controls.empty()) {
    write_file_atomic(adir / "controlled_runs.csv", controls_csv(an.controls));
    a["files"]["controlled_runs_csv"] = "analysis/controlled_runs.csv";
  } else {
    fs::remove(adir / "controlled_runs.csv");
  }
  if (!an.ladders.empty()) {
    write_file_atomic(adir / "convergence.csv", ladders_csv(an.ladders, an.settings.convergence));
    a["files"]["convergence_csv"] = "analysis/convergence.csv";
  } else {
    fs::remove(adir / "convergence.csv");
  }
  if (an.settings.critical_state.on) {
    write_file_atomic(adir / "critical_state.csv", critical_csv(an.critical));
    a["files"]["critical_state_csv"] = "analysis/critical_state.csv";
  } else {
    fs::remove(adir / "critical_state.csv");
  }
  if (an.settings.has_reference) {
    write_file_atomic(adir / "deviation.csv", deviation_csv(an.devs));
    a["files"]["deviation_csv"] = "analysis/deviation.csv";
  } else {
    fs::remove(adir / "deviation.csv");  // of an earlier analysis with a reference
  }
}

}  // namespace

nlohmann::json analyze_study(const std::filesystem::path& dir) {
  require_utf8(fs::absolute(dir).string(), "the study directory");  // analysis.json names it
  const json manifest = read_manifest(dir);
  const std::string study_file = manifest.value("study_file", std::string("study.toml"));
  std::string toml;
  if (fs::exists(dir / study_file)) toml = read_text(dir / study_file);

  Analysis an;
  build_analysis(an, dir, manifest);
  const std::vector<Run>& runs = an.runs;
  const std::vector<Table> tables = make_tables(an);

  const fs::path adir = dir / "analysis", figdir = adir / "figures";
  make_directories(dir, "analysis/figures");

  json a = analysis_json(an, dir, manifest, study_file, toml);
  // Tables and CSVs first: they are useful even when gnuplot is missing.
  write_tables(an, tables, adir, a);
  a["figures"] = json::array();
  write_file_atomic(adir / "analysis.json", json_text(a) + "\n");

  require_gnuplot();
  std::vector<Figure> figs = make_figures(an);
  std::vector<bool> drawn;
  for (Figure& f : figs) {
    drawn.push_back(render_figure(figdir, f, "SPEC 9"));
    a["figures"].push_back({{"name", f.name},
                            {"title", f.title},
                            {"drawn", drawn.back()},
                            {"png", drawn.back() ? json("analysis/figures/" + f.name + ".png") : json(nullptr)},
                            {"svg", drawn.back() ? json("analysis/figures/" + f.name + ".svg") : json(nullptr)},
                            {"script", drawn.back() ? json("analysis/figures/" + f.name + ".gp") : json(nullptr)}});
  }
  write_file_atomic(adir / "analysis.json", json_text(a) + "\n");
  write_file_atomic(dir / "report.html", report_html(a, an.settings, tables, figs, drawn, runs, toml));
  return a;
}

}  // namespace qsdem
