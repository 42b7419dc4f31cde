// The convergence certificate of a study's ladders (docs/analysis.md section 11): the
// constant-rate runs of each (sample, model, ratio) at two or more rates, grouped by seed, handed
// to certify (convergence.hpp); its JSON, CSV and table.
#include <fmt/format.h>

#include <algorithm>
#include <cmath>

#include "qsdem/study/study_analysis_data.hpp"

namespace qsdem::analysis {
namespace {

ResponseCurve response_of(const Run& r) { return {r.s.e1, r.s.phi, r.s.ev, r.s.cn, r.s.q_over_p}; }

bool usable(const Run* r) { return r && r->finished && !r->s.e1.empty(); }

json change_json(const CurveChange& c) {
  return {{"rms", number_or_null(c.rms)}, {"error", number_or_null(c.error)}, {"excess", number_or_null(c.excess)}};
}

}  // namespace

std::vector<Ladder> make_ladders(const std::vector<Run>& runs, const ConvergenceTolerances& tol) {
  std::vector<Ladder> ladders;
  // (sample, model, xi) in the manifest's order, with every seed and rate it has.
  struct RateGroup {
    std::string sample, model;
    double xi;
    std::vector<long> seeds;
    std::vector<double> rates;
    std::vector<const Run*> runs;
  };
  std::vector<RateGroup> groups;
  for (const Run& r : runs) {
    if (r.controlled || !std::isfinite(r.rate) || !(r.rate > 0)) continue;
    auto g = std::find_if(groups.begin(), groups.end(), [&](const RateGroup& x) {
      return x.sample == r.sample && x.model == r.model && same_value(x.xi, r.xi);
    });
    if (g == groups.end()) g = groups.insert(groups.end(), RateGroup{r.sample, r.model, r.xi, {}, {}, {}});
    if (std::find(g->seeds.begin(), g->seeds.end(), r.seed) == g->seeds.end()) g->seeds.push_back(r.seed);
    if (!has_value(g->rates, r.rate)) g->rates.push_back(r.rate);
    g->runs.push_back(&r);
  }
  for (RateGroup& g : groups) {
    if (g.rates.size() < 2) continue;
    std::sort(g.rates.begin(), g.rates.end(), std::greater<>());
    std::sort(g.seeds.begin(), g.seeds.end());
    Ladder l;
    l.sample = g.sample, l.model = g.model, l.xi = g.xi, l.seeds = g.seeds;
    std::vector<Rung> rungs;
    for (double rate : g.rates) {
      std::vector<const Run*> at(g.seeds.size(), nullptr);
      for (const Run* r : g.runs)
        if (same_value(r->rate, rate)) {
          const auto s = std::find(g.seeds.begin(), g.seeds.end(), r->seed) - g.seeds.begin();
          if (!at[s]) at[s] = r;
        }
      if (!std::all_of(at.begin(), at.end(), usable)) {
        l.incomplete.push_back(rate);
        continue;
      }
      Rung rung{rate, {}};
      double steps = 0, wall = 0;
      for (const Run* r : at) {
        rung.seeds.push_back(response_of(*r));
        steps += std::isfinite(r->steps) ? r->steps : 0.0;
        wall += std::isfinite(r->wall_s) ? r->wall_s : 0.0;
      }
      rungs.push_back(std::move(rung));
      l.rates.push_back(rate);
      l.runs.push_back(at);
      l.rung_steps.push_back(steps), l.rung_wall_s.push_back(wall);
      l.steps += steps, l.wall_s += wall;
    }
    if (!rungs.empty()) l.certificate = certify(rungs, tol);
    if (rungs.empty()) l.certificate.reason = "no rate has every seed finished";
    ladders.push_back(std::move(l));
  }
  return ladders;
}

json ladders_json(const std::vector<Ladder>& ladders, const ConvergenceTolerances& tol) {
  json out = json::array();
  for (const Ladder& l : ladders) {
    const Certificate& c = l.certificate;
    json rungs = json::array();
    for (std::size_t k = 0; k < c.rungs.size(); ++k) {
      const RungVerdict& v = c.rungs[k];
      json ids = json::array();
      for (const Run* r : l.runs[k]) ids.push_back(r->id);
      rungs.push_back({{"rate", v.rate},
                       {"runs", ids},
                       {"phi_to_slowest", change_json(v.phi_to_slowest)},
                       {"ev_to_slowest", change_json(v.ev_to_slowest)},
                       {"phi_to_next", change_json(v.phi_to_next)},
                       {"ev_to_next", change_json(v.ev_to_next)},
                       {"ev_end_to_slowest", change_json(v.ev_end_to_slowest)},
                       {"ev_end_to_next", change_json(v.ev_end_to_next)},
                       {"within", v.within},
                       {"resolved", v.resolved},
                       {"steps", l.rung_steps[k]},
                       {"wall_s", l.rung_wall_s[k]}});
    }
    json scalars = json::array();
    for (const ScalarLimit& s : c.scalars) {
      json mean = json::array(), error = json::array();
      for (double m : s.mean) mean.push_back(number_or_null(m));
      for (double e : s.error) error.push_back(number_or_null(e));
      scalars.push_back({{"name", s.name},
                         {"mean", mean},
                         {"error", error},
                         {"limit", number_or_null(s.limit)},
                         {"band", number_or_null(s.band)},
                         {"extrapolated", s.extrapolated}});
    }
    out.push_back({{"sample", l.sample},
                   {"model", l.model},
                   {"xi", l.xi},
                   {"seeds", l.seeds},
                   {"rates", l.rates},
                   {"incomplete_rates", l.incomplete},
                   {"tolerances",
                    {{"phi_tolerance_deg", tol.phi_rms_deg},
                     {"ev_tolerance", tol.ev_rms},
                     {"within_seed_scatter", tol.within_seed_scatter},
                     {"ev_end_tolerance", number_or_null(tol.ev_end)}}},
                   {"status", c.status},
                   {"reason", c.reason},
                   {"certified_rate", c.certified ? json(l.rates[*c.certified]) : json(nullptr)},
                   {"phi_scatter_deg", number_or_null(c.phi_scatter_deg)},
                   {"ev_scatter", number_or_null(c.ev_scatter)},
                   {"limit_resolved", c.limit_resolved},
                   {"steps", l.steps},
                   {"wall_s", l.wall_s},
                   {"rungs", rungs},
                   {"scalars", scalars}});
  }
  return out;
}

std::string ladders_csv(const std::vector<Ladder>& ladders, const ConvergenceTolerances& tol) {
  // The change of ev at the end only where it is judged: a study without that tolerance keeps its columns.
  const bool end = std::isfinite(tol.ev_end);
  std::string out =
      "sample,model,xi,rate,seeds,phi_to_slowest_deg,phi_to_slowest_error_deg,phi_to_slowest_excess_deg,"
      "ev_to_slowest,ev_to_slowest_error,ev_to_slowest_excess,phi_to_next_deg,ev_to_next,within,resolved,certified,"
      "peak_phi_deg,peak_phi_error_deg,ev_end,ev_end_error,steps,wall_s";
  out += end ? ",ev_end_to_slowest,ev_end_to_slowest_error,ev_end_to_slowest_excess\n" : "\n";
  for (const Ladder& l : ladders) {
    const Certificate& c = l.certificate;
    const ScalarLimit *peak = c.scalar("peak_phi_deg"), *ev = c.scalar("ev");
    for (std::size_t k = 0; k < c.rungs.size(); ++k) {
      const RungVerdict& v = c.rungs[k];
      out += fmt::format("{},{},{},{},{},{},{},{},{},{},{},{},{},{},{},{},{},{},{},{},{},{}", l.sample, l.model,
                         csvnum(l.xi), csvnum(v.rate), l.seeds.size(), csvnum(v.phi_to_slowest.rms),
                         csvnum(v.phi_to_slowest.error), csvnum(v.phi_to_slowest.excess), csvnum(v.ev_to_slowest.rms),
                         csvnum(v.ev_to_slowest.error), csvnum(v.ev_to_slowest.excess), csvnum(v.phi_to_next.rms),
                         csvnum(v.ev_to_next.rms), v.within ? "true" : "false", v.resolved ? "true" : "false",
                         c.certified && *c.certified == k ? "true" : "false", csvnum(peak ? peak->mean[k] : nan),
                         csvnum(peak ? peak->error[k] : nan), csvnum(ev ? ev->mean[k] : nan),
                         csvnum(ev ? ev->error[k] : nan), csvnum(l.rung_steps[k]), csvnum(l.rung_wall_s[k]));
      out += end ? fmt::format(",{},{},{}\n", csvnum(v.ev_end_to_slowest.rms), csvnum(v.ev_end_to_slowest.error),
                               csvnum(v.ev_end_to_slowest.excess))
                 : "\n";
    }
  }
  return out;
}

Table table_ladders(const std::vector<Ladder>& ladders, const ConvergenceTolerances& tol) {
  Table t{"Convergence with the rate: the quasi-static certificate",
          fmt::format("Each (sample, model, ratio) run at two or more constant rates, every seed on each rate. Δ = the "
                      "seed mean of (curve at the rate − curve at the slowest rate) of the same seed, RMS over the "
                      "strain beyond the noise of the seed mean (± its standard error). Within: Δφ ≤ {}° and Δεv ≤ {} "
                      "%{}, each with a standard error as small{} (✗: not within; ?: within the tolerances but not "
                      "resolved). "
                      "Certified: the fastest rate within whose slower rates are all within, once the two slowest "
                      "agree (docs/analysis.md, section 11).",
                      sig(tol.phi_rms_deg), pct(tol.ev_rms),
                      std::isfinite(tol.ev_end)
                          ? fmt::format(", and εv at the end changed by at most {} % (shown after a second /)",
                                        pct(tol.ev_end))
                          : std::string(),
                      tol.within_seed_scatter ? ", and no larger than the seed scatter" : ""),
          {"sample", "model", "ξ (%)", "seeds", "ε' : Δφ (°) / Δεv (%)", "seed scatter φ (°) / εv (%)", "status",
           "certified ε'", "peak φ as ε' → 0 (°)", "εv at the end as ε' → 0 (%)", "steps", "reason"},
          {}};
  for (const Ladder& l : ladders) {
    const Certificate& c = l.certificate;
    std::string changes;
    for (const RungVerdict& v : c.rungs) {
      if (!changes.empty()) changes += "; ";
      const bool last = &v == &c.rungs.back();
      const auto shown = [&](const CurveChange& d, double scale) {
        return last ? std::string("0") : fmt::format("{} ± {}", sig(scale * d.excess, 2), sig(scale * d.error, 2));
      };
      const bool unresolved =
          !v.resolved && within_tolerances(v.phi_to_slowest, v.ev_to_slowest, v.ev_end_to_slowest, tol);
      changes += fmt::format("{}: {} / {}{}{}", sig(v.rate, 2), shown(v.phi_to_slowest, 1), shown(v.ev_to_slowest, 100),
                             std::isfinite(tol.ev_end) ? " / " + shown(v.ev_end_to_slowest, 100) : std::string(),
                             v.within ? "" : unresolved ? " ?" : " ✗");
    }
    const auto limit = [&](const char* name, double scale) {
      const ScalarLimit* s = c.scalar(name);
      return s ? fmt::format("{} ± {}{}", sig(scale * s->limit, 4), sig(scale * s->band, 2),
                             s->extrapolated ? " (extrapolated)" : "")
               : std::string("—");
    };
    t.rows.push_back({l.sample, l.model, pct(l.xi), std::to_string(l.seeds.size()), changes,
                      sig(c.phi_scatter_deg, 2) + " / " + pct(c.ev_scatter, 2), c.status,
                      c.certified ? sig(l.rates[*c.certified], 2) : "—", limit("peak_phi_deg", 1), limit("ev", 100),
                      sig(l.steps, 3), c.reason});
  }
  return t;
}

}  // namespace qsdem::analysis
