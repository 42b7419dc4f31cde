// Analysis of a study (SPEC 9, paper sections 4-5). Choices and formulas: docs/analysis.md.
#include "qsdem/study_analysis.hpp"

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

#include "qsdem/output.hpp"
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

void require_gnuplot() {
  if (std::system("gnuplot --version > /dev/null 2>&1") != 0)
    throw std::runtime_error(
        "qsdem study analysis: gnuplot is needed for the figures but could not be run; install the "
        "Debian package gnuplot-nox (apt-get install gnuplot-nox)");
}

namespace {

constexpr double nan = std::numeric_limits<double>::quiet_NaN();
constexpr double imom_qs = 1e-3;  // 0.1 %, the paper's quasi-static threshold (section 5.5)

// ---------------------------------------------------------------------------------------------
// Small helpers
// ---------------------------------------------------------------------------------------------

double num(const json& j, const char* key) {
  if (!j.is_object()) return nan;
  auto it = j.find(key);
  return it != j.end() && it->is_number() ? it->get<double>() : nan;
}

std::string read_text(const fs::path& p) {
  std::ifstream in(p, std::ios::binary);
  if (!in) throw std::runtime_error("cannot read " + p.string());
  std::ostringstream s;
  s << in.rdbuf();
  return s.str();
}

void write_plain(const fs::path& p, const std::string& text) {
  std::ofstream out(p, std::ios::binary);
  out << text;
  if (!out) throw std::runtime_error("cannot write " + p.string());
}

// Numbers in tables: NaN shown as a dash (md/html) or empty (CSV).
std::string sig(double v, int digits = 3) {
  if (!std::isfinite(v)) return "—";
  return fmt::format("{:.{}g}", v, digits);
}
std::string pct(double v, int digits = 3) { return std::isfinite(v) ? sig(100 * v, digits) : "—"; }
std::string csvnum(double v) { return std::isfinite(v) ? fmt::format("{:.9g}", v) : ""; }
std::string csvstr(const std::string& s) {
  if (s.find_first_of(",\"\n") == std::string::npos) return s;
  std::string r = "\"";
  for (char c : s) r += c == '"' ? std::string("\"\"") : std::string(1, c);
  return r + "\"";
}

std::string html_escape(const std::string& s) {
  std::string r;
  for (char c : s) {
    switch (c) {
      case '&': r += "&amp;"; break;
      case '<': r += "&lt;"; break;
      case '>': r += "&gt;"; break;
      case '"': r += "&quot;"; break;
      case '\'': r += "&#39;"; break;
      default: r += c;
    }
  }
  return r;
}

std::string md_escape(const std::string& s) {
  std::string r;
  for (char c : s) r += c == '|' ? std::string("\\|") : std::string(1, c);
  return r;
}

// A double-quoted gnuplot string (terminals run with `noenhanced`, so only \ and " matter).
std::string gp_str(const std::string& s) {
  std::string r = "\"";
  for (char c : s) {
    if (c == '\\' || c == '"') r += '\\';
    r += c;
  }
  return r + "\"";
}

std::string shell_quote(const std::string& s) {
  std::string r = "'";
  for (char c : s) r += c == '\'' ? std::string("'\\''") : std::string(1, c);
  return r + "'";
}

// File-name-safe tag for sample/model names.
std::string tag(const std::string& s) {
  std::string r;
  for (char c : s) r += (std::isalnum(static_cast<unsigned char>(c)) || c == '-' || c == '_') ? c : '_';
  return r.empty() ? "_" : r;
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

struct Series {
  std::vector<double> e1, ev, phi, cn, ufr, imom, ekin;
};

struct Run {
  std::string id, sample, model, dir;
  long seed = 0;
  double xi = nan, rate = nan;
  bool finished = false;
  std::string problem;  // why a run counts as missing
  double mean_imom = nan, mean_ufr = nan, mean_iuf = nan, peak_phi = nan, final_ev = nan;
  double mean_ekin = nan, ekin_norm = nan;  // mean ekin_J, and divided by eps'^2 (paper Table 6)
  double steps = nan, wall_s = nan, particles = nan, psps = nan;
  Series s;
};

// series.csv by header name (SPEC 10; more columns may follow, order is not assumed).
Series read_series(const fs::path& p) {
  std::ifstream in(p);
  if (!in) throw std::runtime_error("cannot read " + p.string());
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
  r.dir = m.value("dir", std::string());
  r.seed = m.value("seed", 0L);
  r.xi = num(m, "xi");
  r.rate = num(m, "rate");
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

struct PaperRef {
  double xi_opt, eps_qs, improvement, a, b, r2;
};

std::optional<PaperRef> paper_ref(const std::string& sample, const std::string& model) {
  if (sample.empty()) return std::nullopt;
  const char s = sample[0];
  if (s == 'A' && model == "od") return PaperRef{0.0023, 4.38e-8, 1.0, 336.46, 0.7511, 0.9970};
  if (s == 'A' && model == "nd") return PaperRef{0.0051, 1.03e-7, 2.35, 629.92, 0.8300, 0.9995};
  if (s == 'B' && model == "od") return PaperRef{0.0034, 5.46e-7, 1.0, 1124.07, 0.9661, 0.9997};
  if (s == 'B' && model == "nd") return PaperRef{0.0040, 5.42e-7, 0.99, 1047.28, 0.9607, 0.9990};
  return std::nullopt;
}

std::optional<double> paper_improvement(const std::string& sample) {
  if (sample.empty()) return std::nullopt;
  if (sample[0] == 'A') return 2.35;
  if (sample[0] == 'B') return 0.99;
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

// One sampled damping ratio at one (sample, model, eps'): the mean over its finished seeds.
struct Point {
  double xi = nan;
  int n_runs = 0, n_finished = 0;
  double imom = nan, ufr = nan, iuf = nan, phi = nan, ekin_norm = nan;
};

struct Group {
  std::string sample, model;
  double rate = nan;
  std::vector<Point> points;  // sorted by xi
  OptimumFit opt_imom, opt_ufr;
  const Run* chosen = nullptr;  // the finished run closest to xi_opt (IMom), for Figs. 10-11, 15-19
};

struct Law {
  std::string sample, model;
  PowerLawFit fit;
  double eps_qs = nan;
  std::vector<double> rates, imom_at_opt, xi_opt;  // the points of the fit (Fig. 9) and Fig. 7
  int n_flagged = 0;
  double xi_opt_geomean = nan, xi_opt_lo = nan, xi_opt_hi = nan;
};

double avg(const std::vector<double>& v) { return mean_finite(v); }

std::vector<Group> make_groups(const std::vector<Run>& runs) {
  // Keys keep the manifest's order of samples and models; rates and xi are sorted numerically.
  std::vector<std::pair<std::string, std::string>> sm;
  std::map<std::tuple<std::string, std::string, double>, std::map<double, std::vector<const Run*>>> g;
  for (const Run& r : runs) {
    if (!std::isfinite(r.xi) || !std::isfinite(r.rate)) continue;  // listed as missing (load_run)
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

std::vector<Law> make_laws(const std::vector<Group>& groups) {
  std::vector<Law> laws;
  for (const Group& g : groups) {
    auto it = std::find_if(laws.begin(), laws.end(),
                           [&](const Law& l) { return l.sample == g.sample && l.model == g.model; });
    if (it == laws.end()) {
      laws.push_back(Law{g.sample, g.model, {}, nan, {}, {}, {}, 0, nan, nan, nan});
      it = laws.end() - 1;
    }
    if (!std::isfinite(g.opt_imom.index_at_opt)) continue;
    it->rates.push_back(g.rate);
    it->imom_at_opt.push_back(g.opt_imom.index_at_opt);
    it->xi_opt.push_back(g.opt_imom.xi_opt);
    if (g.opt_imom.method != "parabola") ++it->n_flagged;
  }
  for (Law& l : laws) {
    l.fit = fit_power_law(l.rates, l.imom_at_opt);
    l.eps_qs = quasi_static_rate(l.fit, imom_qs);
    if (!l.xi_opt.empty()) {
      double s = 0;
      for (double x : l.xi_opt) s += std::log10(x);
      l.xi_opt_geomean = std::pow(10.0, s / static_cast<double>(l.xi_opt.size()));
      l.xi_opt_lo = *std::min_element(l.xi_opt.begin(), l.xi_opt.end());
      l.xi_opt_hi = *std::max_element(l.xi_opt.begin(), l.xi_opt.end());
    }
  }
  return laws;
}

struct Improvement {
  std::string sample;
  double eps_qs_nd = nan, eps_qs_od = nan, ratio = nan;
};

std::vector<Improvement> make_improvements(const std::vector<Law>& laws) {
  std::vector<Improvement> out;
  for (const Law& l : laws) {
    if (std::any_of(out.begin(), out.end(), [&](auto& i) { return i.sample == l.sample; })) continue;
    Improvement im{l.sample};
    for (const Law& k : laws) {
      if (k.sample != l.sample) continue;
      if (k.model == "nd") im.eps_qs_nd = k.eps_qs;
      if (k.model == "od") im.eps_qs_od = k.eps_qs;
    }
    im.ratio = im.eps_qs_nd / im.eps_qs_od;
    out.push_back(im);
  }
  return out;
}

const OptimumFit* find_opt(const std::vector<Group>& groups, const Run& r) {
  for (const Group& g : groups)
    if (g.sample == r.sample && g.model == r.model && g.rate == r.rate) return &g.opt_imom;
  return nullptr;
}

// Paper Table 6: runs of one (sample, model) with equal xi*eps' (3 significant digits) at
// different rates.
struct EqualSet {
  std::string sample, model, product;
  std::vector<const Run*> runs;
};

std::vector<EqualSet> make_equal_sets(const std::vector<Run>& runs) {
  std::vector<EqualSet> out;
  for (const Run& r : runs) {
    if (!r.finished || !(r.xi > 0)) continue;
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

// ---------------------------------------------------------------------------------------------
// Tables (rendered both as Markdown and as HTML from the same cells)
// ---------------------------------------------------------------------------------------------

struct Table {
  std::string title, note;
  std::vector<std::string> head;
  std::vector<std::vector<std::string>> rows;
  bool detail = false;  // folded (<details>) in the report
};

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

std::string fit_text(double a, double b) {
  return std::isfinite(a) ? fmt::format("{} ε'^{}", sig(a, 5), sig(b, 4)) : "—";
}

std::vector<Table> make_tables(const std::vector<Run>& runs, const std::vector<Group>& groups,
                               const std::vector<Law>& laws, const std::vector<Improvement>& imps,
                               const std::vector<EqualSet>& equal) {
  std::vector<Table> tables;
  // Table 4 of the paper, one row per (sample, model).
  {
    Table t{"Optimum damping ratio, power law and quasi-static rate (paper Table 4, Fig. 9)",
            "ξopt: geometric mean over the rates of the IMom optimum [range]; IMom at ξopt: at the "
            "lowest and highest rate; fit IMom = a ε'^b over the rates (log-log least squares); "
            "ε'QS where the fit gives IMom = 0.1 %; improvement = ε'QS(nd)/ε'QS(od). Paper columns "
            "only for samples named A*/B*.",
            {"sample", "model", "ξopt (%)", "paper ξopt (%)", "IMom at ξopt (%)", "a", "b", "R²",
             "paper fit (Fig. 9)", "ε'QS", "paper ε'QS", "improvement", "paper improvement"},
            {}};
    for (const Law& l : laws) {
      const auto ref = paper_ref(l.sample, l.model);
      std::string imr = "—";
      if (!l.imom_at_opt.empty())
        imr = fmt::format("{} (ε' {}) … {} (ε' {})", pct(l.imom_at_opt.front()), sig(l.rates.front()),
                          pct(l.imom_at_opt.back()), sig(l.rates.back()));
      std::string r2 = sig(l.fit.r2, 4);
      if (!l.fit.note.empty()) r2 += " (" + l.fit.note + ")";
      if (l.n_flagged) r2 += fmt::format(" [{} of {} optima not from the parabola]", l.n_flagged, l.rates.size());
      std::string improvement = "—", paper_imp;
      for (const Improvement& im : imps)
        if (im.sample == l.sample && l.model == "nd") improvement = sig(im.ratio);
      if (l.model == "od" && std::isfinite(l.eps_qs)) improvement = "1";
      if (ref && l.model == "nd") paper_imp = sig(ref->improvement);
      if (ref && l.model == "od") paper_imp = "1";
      t.rows.push_back({l.sample, l.model,
                        std::isfinite(l.xi_opt_geomean)
                            ? fmt::format("{} [{}–{}]", pct(l.xi_opt_geomean), pct(l.xi_opt_lo), pct(l.xi_opt_hi))
                            : "—",
                        ref ? pct(ref->xi_opt) : "", imr, sig(l.fit.a, 5), sig(l.fit.b, 4), r2,
                        ref ? fmt::format("{}, R² = {}", fit_text(ref->a, ref->b), sig(ref->r2, 4)) : "",
                        sig(l.eps_qs), ref ? sig(ref->eps_qs) : "", improvement, paper_imp});
    }
    tables.push_back(std::move(t));
  }
  // The optimum at each rate (paper Figs. 7-8).
  {
    Table t{"Optimum damping ratio at each rate (paper Figs. 7 and 8)",
            "Parabola in (log10 ξ, log10 index) through the sampled minimum and its neighbours; "
            "flags say when the sampled minimum is reported instead.",
            {"sample", "model", "ε'", "ξopt IMom (%)", "IMom at ξopt (%)", "IMom fit", "ξopt UFR (%)",
             "UFR at ξopt (%)", "UFR fit", "run shown in curves"},
            {}};
    auto how = [](const OptimumFit& f) { return f.flag.empty() ? f.method : f.method + ": " + f.flag; };
    for (const Group& g : groups)
      t.rows.push_back({g.sample, g.model, sig(g.rate), pct(g.opt_imom.xi_opt), pct(g.opt_imom.index_at_opt),
                        how(g.opt_imom), pct(g.opt_ufr.xi_opt), pct(g.opt_ufr.index_at_opt), how(g.opt_ufr),
                        g.chosen ? g.chosen->id : "—"});
    tables.push_back(std::move(t));
  }
  // Per (sample, model, rate): every xi (paper Figs. 3-6, 13-14).
  for (const Group& g : groups) {
    Table t{fmt::format("{} {} ε' = {}: indices against the damping ratio", g.sample, g.model, sig(g.rate)),
            "",
            {"ξ (%)", "runs finished", "mean IMom (%)", "mean UFR (%)", "mean Iuf (%)", "peak φ (°)",
             "Ekin/ε'² (J)"},
            {}};
    for (const Point& p : g.points) {
      const std::string fin = fmt::format("{}/{}", p.n_finished, p.n_runs) + (p.n_finished ? "" : " missing");
      t.rows.push_back({pct(p.xi), fin, pct(p.imom), pct(p.ufr), pct(p.iuf), sig(p.phi, 4), sig(p.ekin_norm)});
    }
    t.detail = true;
    tables.push_back(std::move(t));
  }
  // Table 6 of the paper: runs with equal xi*eps'.
  {
    Table t{"Runs with equal ξ·ε' (paper Table 6)",
            "Ekin/ε'²: mean kinetic energy over the series rows divided by ε'². ξopt: the IMom optimum "
            "at the run's rate.",
            {"run", "ξ (%)", "ε'", "ξ·ε'", "ξopt (%)", "peak φ (°)", "Ekin/ε'² (J)", "mean IMom (%)",
             "mean UFR (%)"},
            {}};
    for (const EqualSet& e : equal)
      for (const Run* r : e.runs) {
        const OptimumFit* o = find_opt(groups, *r);
        t.rows.push_back({r->id, pct(r->xi), sig(r->rate), sig(r->xi * r->rate), o ? pct(o->xi_opt) : "—",
                          sig(r->peak_phi, 4), sig(r->ekin_norm), pct(r->mean_imom), pct(r->mean_ufr)});
      }
    tables.push_back(std::move(t));
  }
  if (std::any_of(runs.begin(), runs.end(), [](const Run& r) { return !r.sample.empty() && r.sample[0] == 'B'; })) {
    Table t{"Paper Table 6 (Sample B, OD), for comparison", "",
            {"model", "ξ (%)", "ε'", "ξ·ε'", "ξopt (%)", "peak φ (°)", "Ekin/ε'² (J)", "mean IMom (%)",
             "mean UFR (%)"},
            {}};
    const json paper = paper_reference_json();  // named: a temporary's member would dangle in the loop
    for (const json& p : paper["table6_B_od"]) {
      const double xi = p["xi"], rate = p["rate"];
      t.rows.push_back({p["model"].get<std::string>(), pct(xi), sig(rate), sig(xi * rate),
                        pct(p["xi_opt"].get<double>()), sig(p["peak_phi_deg"].get<double>(), 4),
                        sig(p["ekin_over_rate2_J"].get<double>()), pct(p["mean_imom"].get<double>()),
                        pct(p["mean_ufr"].get<double>())});
    }
    tables.push_back(std::move(t));
  }
  // Missing runs.
  {
    Table t{"Missing runs", "Runs of the manifest without a usable summary.json; left out of every fit.",
            {"run", "directory", "reason"}, {}};
    for (const Run& r : runs)
      if (!r.finished) t.rows.push_back({r.id, r.dir, r.problem});
    tables.push_back(std::move(t));
  }
  return tables;
}

// ---------------------------------------------------------------------------------------------
// Figures (gnuplot; paper Figs. 2-19)
// ---------------------------------------------------------------------------------------------

struct Curve {
  std::string title;  // empty: no key entry
  std::vector<double> x, y;
  std::string style;  // gnuplot `with ...` clause
};

struct Panel {
  std::string title, xlabel, ylabel;
  bool logx = false, logy = false;
  std::vector<Curve> curves;
  std::string extra = "";  // more gnuplot commands before `plot` (ranges)
};

struct Figure {
  std::string name, title, caption;
  std::vector<Panel> panels;  // 1 or 4 (2x2)
};

bool usable(double v, bool log) { return std::isfinite(v) && (!log || v > 0); }

// Drops points a log axis cannot show (SPEC 9: NaN and zero are skipped, never plotted as 0).
void clean(Panel& p) {
  for (Curve& c : p.curves) {
    Curve k{c.title, {}, {}, c.style};
    for (std::size_t i = 0; i < c.x.size() && i < c.y.size(); ++i)
      if (usable(c.x[i], p.logx) && usable(c.y[i], p.logy)) k.x.push_back(c.x[i]), k.y.push_back(c.y[i]);
    c = std::move(k);
  }
  std::erase_if(p.curves, [](const Curve& c) { return c.x.empty(); });
}

std::string panel_commands(const Panel& p, const std::string& datafile, std::size_t& block) {
  std::string s;
  s += "set title " + gp_str(p.title) + "\n";
  s += "set xlabel " + gp_str(p.xlabel) + "\nset ylabel " + gp_str(p.ylabel) + "\n";
  s += p.logx ? "set logscale x\nset format x '%g'\n" : "unset logscale x\nset format x '%g'\n";
  s += p.logy ? "set logscale y\nset format y '%g'\n" : "unset logscale y\nset format y '%g'\n";
  // Margins so that points do not sit on the frame (graph units work on log axes too).
  s += "set autoscale\nset offsets graph 0.04, graph 0.04, graph 0.06, graph 0.06\n" + p.extra;
  if (p.curves.empty()) {
    // An empty panel of a multiplot: say so instead of failing on "all points undefined".
    s += "set xrange [1:10]\nset yrange [1:10]\nset label 99 'no data' at graph 0.5,0.5 center\n"
         "plot 1/0 notitle\nunset label 99\nset autoscale\n";
    return s;
  }
  s += "plot ";
  for (std::size_t i = 0; i < p.curves.size(); ++i) {
    const Curve& c = p.curves[i];
    s += fmt::format("{}'{}' index {} using 1:2 with {} {}", i ? ", \\\n     " : "", datafile, block++, c.style,
                     c.title.empty() ? std::string("notitle") : "title " + gp_str(c.title));
  }
  return s + "\n";
}

// Writes NAME.dat and NAME.gp into figdir and runs gnuplot there (.svg and .png).
// Returns false (and nothing is drawn) when the figure has no usable point.
bool render(const fs::path& figdir, Figure& f) {
  for (Panel& p : f.panels) clean(p);
  if (std::all_of(f.panels.begin(), f.panels.end(), [](const Panel& p) { return p.curves.empty(); })) return false;
  std::string dat;
  for (const Panel& p : f.panels)
    for (const Curve& c : p.curves) {
      dat += "# " + c.title + "\n";
      for (std::size_t i = 0; i < c.x.size(); ++i) dat += fmt::format("{:.9g} {:.9g}\n", c.x[i], c.y[i]);
      dat += "\n\n";  // two blank lines: a new gnuplot `index`
    }
  write_plain(figdir / (f.name + ".dat"), dat);
  const bool multi = f.panels.size() > 1;
  std::string body = "reset\nset grid\nset key top left Left reverse samplen 2 font ',9'\n";
  if (multi) body += "set multiplot layout 2,2 title " + gp_str(f.title) + "\n";
  std::size_t block = 0;
  for (const Panel& p : f.panels) body += panel_commands(p, f.name + ".dat", block);
  if (multi) body += "unset multiplot\n";
  const std::string size = multi ? "1100,820" : "820,560";
  std::string gp = "# " + f.title + " (generated by qsdem, SPEC 9)\nset encoding utf8\n";
  gp += "set terminal svg size " + size + " noenhanced font 'DejaVu Sans,12' background '#ffffff'\n";
  gp += "set output '" + f.name + ".svg'\n" + body + "unset output\n";
  gp += "set terminal pngcairo size " + size + " noenhanced font 'DejaVu Sans,10' background '#ffffff'\n";
  gp += "set output '" + f.name + ".png'\n" + body + "unset output\n";
  write_plain(figdir / (f.name + ".gp"), gp);
  const std::string cmd = fmt::format("cd {} && gnuplot {} > {} 2>&1", shell_quote(figdir.string()),
                                      shell_quote(f.name + ".gp"), shell_quote(f.name + ".log"));
  if (std::system(cmd.c_str()) != 0) {
    std::string log;
    try {
      log = read_text(figdir / (f.name + ".log"));
    } catch (...) {
    }
    throw std::runtime_error(fmt::format("gnuplot failed on {}: {}", (figdir / (f.name + ".gp")).string(), log));
  }
  for (const char* ext : {".svg", ".png"})
    if (!fs::exists(figdir / (f.name + ext)) || fs::file_size(figdir / (f.name + ext)) == 0)
      throw std::runtime_error("gnuplot wrote no " + (figdir / (f.name + ext)).string());
  fs::remove(figdir / (f.name + ".log"));
  return true;
}

std::string lc(std::size_t i) { return fmt::format("lc {}", i + 1); }

std::vector<Figure> make_figures(const std::vector<Run>& runs, const std::vector<Group>& groups,
                                 const std::vector<Law>& laws) {
  std::vector<Figure> figs;
  std::vector<std::string> samples;
  for (const Law& l : laws)
    if (std::find(samples.begin(), samples.end(), l.sample) == samples.end()) samples.push_back(l.sample);

  // (a) mean index against xi at each rate, one figure per (sample, model), paper Figs. 3-6.
  for (const Law& l : laws)
    for (const bool is_imom : {true, false}) {
      const std::string idx = is_imom ? "IMom" : "UFR";
      Figure f{fmt::format("{}_vs_xi_{}_{}", is_imom ? "imom" : "ufr", tag(l.sample), tag(l.model)),
               fmt::format("{} {}: mean {} against the damping ratio", l.sample, l.model, idx),
               fmt::format("Mean {} over the run against ξ at each ε' (log-log; ξ = 0 not shown); open "
                           "circles: ξopt from the parabola fit (paper Figs. 3-6 for IMom).",
                           idx),
               {}};
      Panel p{f.title, "damping ratio ξ (%)", "mean " + idx + " (%)", true, true, {}};
      std::size_t k = 0;
      for (const Group& g : groups) {
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
      figs.push_back(std::move(f));
    }

  for (const std::string& s : samples) {
    // (b) xi_opt against the rate, both models and both indices, paper Figs. 7-8.
    {
      Figure f{"xiopt_vs_rate_" + tag(s), s + ": optimum damping ratio against the strain rate",
               "ξopt from IMom (solid) and from UFR (dashed) against ε' for each damping model "
               "(paper Figs. 7 and 8); semi-log like the paper.",
               {}};
      Panel p{f.title, "dimensionless strain rate ε'", "ξopt (%)", true, false, {}, "set yrange [0:*]\n"};
      std::size_t k = 0;
      for (const Law& l : laws) {
        if (l.sample != s) continue;
        Curve ci{l.model + " (IMom)", {}, {}, "linespoints pt 7 dt 1 " + lc(k)};
        Curve cu{l.model + " (UFR)", {}, {}, "linespoints pt 4 dt 2 " + lc(k)};
        for (const Group& g : groups) {
          if (g.sample != s || g.model != l.model) continue;
          ci.x.push_back(g.rate), ci.y.push_back(100 * g.opt_imom.xi_opt);
          cu.x.push_back(g.rate), cu.y.push_back(100 * g.opt_ufr.xi_opt);
        }
        p.curves.push_back(std::move(ci));
        p.curves.push_back(std::move(cu));
        ++k;
      }
      f.panels.push_back(std::move(p));
      figs.push_back(std::move(f));
    }
    // (c) IMom at xi_opt against the rate with the fitted power law, paper Fig. 9.
    {
      Figure f{"imom_opt_vs_rate_" + tag(s), s + ": moment index at the optimum damping ratio",
               "IMom at ξopt against ε' with the fitted power law IMom = a ε'^b (lines); dashed grey: the "
               "quasi-static threshold IMom = 0.1 % (paper Fig. 9, Table 4).",
               {}};
      Panel p{f.title, "dimensionless strain rate ε'", "IMom at ξopt (%)", true, true, {}};
      std::size_t k = 0;
      double lo = INFINITY, hi = 0;
      for (const Law& l : laws) {
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
          Curve fit{fmt::format("{} fit: {} ε'^{}, R² = {}", l.model, sig(l.fit.a, 4), sig(l.fit.b, 3),
                                sig(l.fit.r2, 4)),
                    {}, {}, "lines lw 1.5 " + lc(k)};
          for (int i = 0; i <= 40; ++i) {
            const double x = x0 * std::pow(x1 / x0, i / 40.0);
            fit.x.push_back(x), fit.y.push_back(100 * l.fit.a * std::pow(x, l.fit.b));
          }
          // The paper's fit (Fig. 9) over the same rates, for the trend (SPEC 9: never tuned to it).
          std::optional<Curve> pf;
          if (const auto ref = paper_ref(l.sample, l.model)) {
            pf = Curve{fmt::format("paper {}: {} ε'^{}", l.model, sig(ref->a, 5), sig(ref->b, 4)), {}, {},
                       "lines dt 3 lw 1.5 " + lc(k)};
            for (double x : fit.x) pf->x.push_back(x), pf->y.push_back(100 * ref->a * std::pow(x, ref->b));
          }
          p.curves.push_back(std::move(fit));
          if (pf) p.curves.push_back(std::move(*pf));
        }
        ++k;
      }
      if (hi > 0) p.curves.push_back(Curve{"IMom = 0.1 %", {lo, hi}, {0.1, 0.1}, "lines dt 2 lc rgb '#888888'"});
      f.panels.push_back(std::move(p));
      figs.push_back(std::move(f));
    }
    // (e) peak friction angle against xi*eps', paper Figs. 12-14 (the product governs, section 5.7).
    {
      Figure f{"peakphi_vs_xirate_" + tag(s), s + ": peak friction angle against ξ·ε'",
               "Peak mobilised friction angle of every finished run (ξ > 0) against ξ·ε' (semi-log).", {}};
      Panel p{f.title, "ξ·ε'", "peak friction angle φ (°)", true, false, {}};
      std::vector<std::string> models;
      for (const Law& l : laws)
        if (l.sample == s) models.push_back(l.model);
      for (std::size_t k = 0; k < models.size(); ++k) {
        Curve c{models[k], {}, {}, "points pt 7 ps 0.9 " + lc(k)};
        for (const Run& r : runs)
          if (r.finished && r.sample == s && r.model == models[k] && r.xi > 0)
            c.x.push_back(r.xi * r.rate), c.y.push_back(r.peak_phi);
        p.curves.push_back(std::move(c));
      }
      f.panels.push_back(std::move(p));
      figs.push_back(std::move(f));
    }
  }

  // (d) and (f): the run closest to xi_opt at each rate, paper Figs. 10-11 and 15-19.
  for (const Law& l : laws) {
    std::vector<const Group*> gs;
    for (const Group& g : groups)
      if (g.sample == l.sample && g.model == l.model && g.chosen) gs.push_back(&g);
    Figure f{fmt::format("curves_{}_{}", tag(l.sample), tag(l.model)),
             fmt::format("{} {}: runs nearest ξopt", l.sample, l.model),
             "Friction angle, volumetric strain, coordination number and moment index against the axial "
             "strain for the run nearest ξopt at each rate (paper Figs. 10, 11, 15-18).",
             {}};
    const char* names[4][2] = {{"friction angle φ (°)", "φ"},
                               {"volumetric strain εv (%)", "εv"},
                               {"coordination number Cn", "Cn"},
                               {"moment index IMom (%)", "IMom"}};
    for (int k = 0; k < 4; ++k) {
      Panel p{names[k][1], "axial strain ε1 (%)", names[k][0], false, false, {}};
      for (std::size_t i = 0; i < gs.size(); ++i) {
        const Run& r = *gs[i]->chosen;
        Curve c{fmt::format("ε' = {}, ξ = {} %", sig(r.rate), pct(r.xi)), {}, {}, "lines lw 1.5 " + lc(i)};
        const std::vector<double>& y = k == 0 ? r.s.phi : k == 1 ? r.s.ev : k == 2 ? r.s.cn : r.s.imom;
        const double scale = (k == 1 || k == 3) ? 100.0 : 1.0;
        for (std::size_t j = 0; j < r.s.e1.size(); ++j) c.x.push_back(100 * r.s.e1[j]), c.y.push_back(scale * y[j]);
        p.curves.push_back(std::move(c));
      }
      f.panels.push_back(std::move(p));
    }
    figs.push_back(std::move(f));

    Figure e{fmt::format("ekin_{}_{}", tag(l.sample), tag(l.model)),
             fmt::format("{} {}: kinetic energy / ε'² (runs nearest ξopt)", l.sample, l.model),
             "Kinetic energy of the fluctuations divided by ε'² against the axial strain (paper Fig. 19; "
             "log y, zeros skipped).",
             {}};
    Panel p{e.title, "axial strain ε1 (%)", "Ekin/ε'² (J)", false, true, {}};
    for (std::size_t i = 0; i < gs.size(); ++i) {
      const Run& r = *gs[i]->chosen;
      Curve c{fmt::format("ε' = {}, ξ = {} %", sig(r.rate), pct(r.xi)), {}, {}, "lines lw 1.5 " + lc(i)};
      for (std::size_t j = 0; j < r.s.e1.size(); ++j)
        c.x.push_back(100 * r.s.e1[j]), c.y.push_back(r.s.ekin[j] / (r.rate * r.rate));
      p.curves.push_back(std::move(c));
    }
    e.panels.push_back(std::move(p));
    figs.push_back(std::move(e));
  }
  return figs;
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
          {"series_rows", r.s.e1.size()}};
}

std::string per_run_csv(const std::vector<Run>& runs) {
  std::string s =
      "id,sample,seed,model,xi,rate,xi_times_rate,status,mean_imom,mean_ufr,mean_iuf,peak_phi_deg,final_ev,"
      "mean_ekin_J,ekin_over_rate2_J,steps,wall_s,particles,dir\n";
  for (const Run& r : runs)
    s += fmt::format("{},{},{},{},{},{},{},{},{},{},{},{},{},{},{},{},{},{},{}\n", csvstr(r.id), csvstr(r.sample),
                     r.seed, csvstr(r.model), csvnum(r.xi), csvnum(r.rate), csvnum(r.xi * r.rate),
                     r.finished ? "finished" : "missing", csvnum(r.mean_imom), csvnum(r.mean_ufr),
                     csvnum(r.mean_iuf), csvnum(r.peak_phi), csvnum(r.final_ev), csvnum(r.mean_ekin),
                     csvnum(r.ekin_norm), csvnum(r.steps), csvnum(r.wall_s), csvnum(r.particles), csvstr(r.dir));
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
    double imp = nan;
    for (const Improvement& im : imps)
      if (im.sample == l.sample && l.model == "nd") imp = im.ratio;
    if (l.model == "od" && std::isfinite(l.eps_qs)) imp = 1.0;
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

// ---------------------------------------------------------------------------------------------
// Report
// ---------------------------------------------------------------------------------------------

std::string report_html(const json& a, const std::vector<Table>& tables, const std::vector<Figure>& figs,
                        const std::vector<bool>& drawn, const std::vector<Run>& runs, const std::string& toml) {
  const std::string name = a["study"]["name"];
  std::string h = "<!DOCTYPE html>\n<html lang=\"en\">\n<head>\n<meta charset=\"utf-8\">\n<title>qsdem study " +
                  html_escape(name) + "</title>\n<style>\n"
                  "body{font-family:'DejaVu Sans',Arial,sans-serif;margin:2em auto;max-width:1200px;color:#222}\n"
                  "table{border-collapse:collapse;margin:0.5em 0 1.5em;font-size:0.9em}\n"
                  "th,td{border:1px solid #bbb;padding:0.25em 0.5em;text-align:right}\n"
                  "th{background:#eee}td:first-child{text-align:left}\n"
                  "figure{margin:1em 0 2em}img{max-width:100%;border:1px solid #ddd}\n"
                  ".note{color:#555;font-size:0.9em}pre{background:#f6f6f6;padding:1em;overflow:auto}\n"
                  "summary{font-weight:bold;margin:0.4em 0;cursor:pointer}\n"
                  "</style>\n</head>\n";
  // Counts the images that really decoded, for the headless-browser test (tests/test_study_analysis).
  h += "<body data-images-loaded=\"pending\" data-images-total=\"pending\">\n"
       "<script>\nwindow.addEventListener('load', function () {\n"
       "  var imgs = Array.prototype.slice.call(document.images);\n"
       "  var ok = imgs.filter(function (im) { return im.complete && im.naturalWidth > 0; }).length;\n"
       "  document.body.setAttribute('data-images-loaded', String(ok));\n"
       "  document.body.setAttribute('data-images-total', String(imgs.length));\n"
       "});\n</script>\n";
  h += "<h1>qsdem study: " + html_escape(name) + "</h1>\n";
  h += "<p>Study date: " + html_escape(a["study"]["date"].get<std::string>()) +
       ". Analysed: " + html_escape(a["study"]["analysed_at"].get<std::string>()) + ". Runs: " +
       std::to_string(a["counts"]["finished"].get<int>()) + " finished of " +
       std::to_string(a["counts"]["runs"].get<int>()) + ".</p>\n";
  h += "<h2>How to read this report</h2>\n<p>Each run is one drained triaxial test (SPEC 8) of a sample "
       "with a damping model (nd: size-dependent, od: global mass damping) at a damping ratio ξ and a "
       "dimensionless strain rate ε'. For every (sample, model, ε') the optimum damping ratio ξopt is the "
       "minimum of the mean moment index IMom (and separately of UFR) over ξ, refined by a parabola in "
       "log-log through the smallest sampled value and its neighbours; a flag says when the minimum lies "
       "at the edge of the sampled ξ range. IMom at ξopt is fitted as a ε'^b over the rates; ε'QS is the "
       "rate where that fit reaches IMom = 0.1 %, and the improvement is ε'QS(nd)/ε'QS(od): above 1 the "
       "size-dependent damping allows faster quasi-static loading. Columns headed 'paper' repeat "
       "Yousefi (2018), Table 4, Fig. 9 and Table 6, for samples named A* or B*; our numbers are not "
       "expected to match them digit for digit (other code, packing and contact geometry), only in trend. "
       "All indices are shown in percent. Details: docs/analysis.md.</p>\n";
  h += "<p>Data: <a href=\"analysis/per_run.csv\">per_run.csv</a>, <a href=\"analysis/optimum.csv\">optimum.csv</a>, "
       "<a href=\"analysis/power_law.csv\">power_law.csv</a>, <a href=\"analysis/analysis.json\">analysis.json</a>, "
       "<a href=\"analysis/tables.md\">tables.md</a>.</p>\n";
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
    h += "<figure id=\"" + f.name + "\"><img src=\"analysis/figures/" + f.name + ".png\" alt=\"" +
         html_escape(f.title) + "\"><figcaption>" + html_escape(f.caption) + " <a href=\"analysis/figures/" +
         f.name + ".svg\">SVG</a> · <a href=\"analysis/figures/" + f.name +
         ".dat\">data</a> · <a href=\"analysis/figures/" + f.name + ".gp\">gnuplot script</a></figcaption></figure>\n";
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

}  // namespace

// ---------------------------------------------------------------------------------------------

nlohmann::json analyze_study(const std::filesystem::path& dir) {
  const fs::path manifest_path = dir / "study.json";
  if (!fs::exists(manifest_path)) throw std::runtime_error("analyze_study: no " + manifest_path.string());
  json manifest;
  try {
    manifest = json::parse(read_text(manifest_path));
  } catch (const json::exception& e) {
    throw std::runtime_error("analyze_study: " + manifest_path.string() + ": " + e.what());
  }
  const std::string study_file = manifest.value("study_file", std::string("study.toml"));
  std::string toml;
  if (fs::exists(dir / study_file)) toml = read_text(dir / study_file);

  std::vector<Run> runs;
  if (manifest.contains("runs") && manifest["runs"].is_array())
    for (const json& m : manifest["runs"]) runs.push_back(load_run(dir, m));

  const std::vector<Group> groups = make_groups(runs);
  const std::vector<Law> laws = make_laws(groups);
  const std::vector<Improvement> imps = make_improvements(laws);
  const std::vector<EqualSet> equal = make_equal_sets(runs);
  const std::vector<Table> tables = make_tables(runs, groups, laws, imps, equal);

  const fs::path adir = dir / "analysis", figdir = adir / "figures";
  fs::create_directories(figdir);

  json a;
  a["study"] = {{"name", manifest.value("name", std::string("(unnamed)"))},
                {"dir", fs::absolute(dir).string()},
                {"study_file", study_file},
                {"date", study_date(dir, manifest)},
                {"analysed_at", utc_string(std::time(nullptr))},
                {"qsdem_version", QSDEM_VERSION}};
  a["resolved_configuration"] = toml;
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
  a["groups"] = json::array();
  for (const Group& g : groups) {
    json pts = json::array();
    for (const Point& p : g.points)
      pts.push_back({{"xi", p.xi}, {"n_runs", p.n_runs}, {"n_finished", p.n_finished}, {"mean_imom", p.imom},
                     {"mean_ufr", p.ufr}, {"mean_iuf", p.iuf}, {"peak_phi_deg", p.phi},
                     {"ekin_over_rate2_J", p.ekin_norm}});
    a["groups"].push_back({{"sample", g.sample},
                           {"model", g.model},
                           {"rate", g.rate},
                           {"points", pts},
                           {"optimum_imom", opt_json(g.opt_imom)},
                           {"optimum_ufr", opt_json(g.opt_ufr)},
                           {"chosen_run", g.chosen ? json(g.chosen->id) : json(nullptr)}});
  }
  a["power_laws"] = json::array();
  for (const Law& l : laws) {
    const auto ref = paper_ref(l.sample, l.model);
    json paper = nullptr;
    if (ref)
      paper = {{"xi_opt", ref->xi_opt}, {"eps_qs", ref->eps_qs}, {"a", ref->a},
               {"b", ref->b},           {"r2", ref->r2},         {"improvement", ref->improvement}};
    a["power_laws"].push_back({{"sample", l.sample},
                               {"model", l.model},
                               {"n_rates", l.fit.n},
                               {"ok", l.fit.ok},
                               {"a", l.fit.a},
                               {"b", l.fit.b},
                               {"r2", l.fit.r2},
                               {"note", l.fit.note},
                               {"eps_qs", l.eps_qs},
                               {"imom_qs", imom_qs},
                               {"rates", l.rates},
                               {"imom_at_opt", l.imom_at_opt},
                               {"xi_opt", l.xi_opt},
                               {"n_flagged_optima", l.n_flagged},
                               {"xi_opt_geomean", l.xi_opt_geomean},
                               {"xi_opt_min", l.xi_opt_lo},
                               {"xi_opt_max", l.xi_opt_hi},
                               {"paper", paper}});
  }
  a["improvements"] = json::array();
  for (const Improvement& im : imps) {
    const auto p = paper_improvement(im.sample);
    a["improvements"].push_back({{"sample", im.sample},
                                 {"eps_qs_nd", im.eps_qs_nd},
                                 {"eps_qs_od", im.eps_qs_od},
                                 {"improvement", im.ratio},
                                 {"paper_improvement", p ? json(*p) : json(nullptr)}});
  }
  a["equal_xi_rate"] = json::array();
  for (const EqualSet& e : equal) {
    json ids = json::array();
    for (const Run* r : e.runs) ids.push_back(r->id);
    a["equal_xi_rate"].push_back({{"sample", e.sample}, {"model", e.model}, {"xi_times_rate", e.product}, {"runs", ids}});
  }
  a["paper_reference"] = paper_reference_json();

  // Tables and CSVs first: they are useful even when gnuplot is missing.
  std::string md = "# Study " + a["study"]["name"].get<std::string>() + "\n\nGenerated by qsdem analyze_study " +
                   a["study"]["analysed_at"].get<std::string>() +
                   ". Indices in percent. Choices: docs/analysis.md.\n\n";
  for (const Table& t : tables) md += to_markdown(t);
  write_file_atomic(adir / "tables.md", md);
  write_file_atomic(adir / "per_run.csv", per_run_csv(runs));
  write_file_atomic(adir / "optimum.csv", optimum_csv(groups));
  write_file_atomic(adir / "power_law.csv", power_law_csv(laws, imps));
  a["files"] = {{"tables_md", "analysis/tables.md"},
                {"per_run_csv", "analysis/per_run.csv"},
                {"optimum_csv", "analysis/optimum.csv"},
                {"power_law_csv", "analysis/power_law.csv"},
                {"analysis_json", "analysis/analysis.json"},
                {"report_html", "report.html"}};
  a["figures"] = json::array();
  write_file_atomic(adir / "analysis.json", a.dump(2) + "\n");

  require_gnuplot();
  std::vector<Figure> figs = make_figures(runs, groups, laws);
  std::vector<bool> drawn;
  for (Figure& f : figs) {
    drawn.push_back(render(figdir, f));
    a["figures"].push_back({{"name", f.name},
                            {"title", f.title},
                            {"drawn", drawn.back()},
                            {"png", drawn.back() ? json("analysis/figures/" + f.name + ".png") : json(nullptr)},
                            {"svg", drawn.back() ? json("analysis/figures/" + f.name + ".svg") : json(nullptr)},
                            {"script", drawn.back() ? json("analysis/figures/" + f.name + ".gp") : json(nullptr)}});
  }
  write_file_atomic(adir / "analysis.json", a.dump(2) + "\n");
  write_file_atomic(dir / "report.html", report_html(a, tables, figs, drawn, runs, toml));
  return a;
}

}  // namespace qsdem
