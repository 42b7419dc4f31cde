#include "qsdem/study/convergence.hpp"

#include <fmt/format.h>

#include <algorithm>
#include <cmath>
#include <span>
#include <stdexcept>

#include "qsdem/study/study_analysis.hpp"

namespace qsdem {
namespace {

using Measure = std::vector<double> ResponseCurve::*;

// The seed mean of (a's curve - b's curve) at each grid strain and the standard error of that mean:
// paired by seed, so the scatter the seeds share (the same prepared sample) cancels.
CurveChange change(const Rung& a, const Rung& b, Measure m, std::span<const double> grid) {
  const std::size_t n = a.seeds.size();
  std::vector<std::vector<double>> d(n);
  for (std::size_t s = 0; s < n; ++s)
    d[s] = curve_deviation(b.seeds[s].e1, b.seeds[s].*m, a.seeds[s].e1, a.seeds[s].*m, grid).at;
  double sum = 0, sum_error = 0;
  int points = 0;
  for (std::size_t k = 0; k < grid.size(); ++k) {
    double mean = 0;
    bool finite = true;
    for (std::size_t s = 0; s < n; ++s) finite = finite && std::isfinite(d[s][k]), mean += d[s][k];
    if (!finite) continue;
    mean /= static_cast<double>(n);
    double var = 0;
    for (std::size_t s = 0; s < n; ++s) var += (d[s][k] - mean) * (d[s][k] - mean);
    const double se2 = n > 1 ? var / static_cast<double>(n - 1) / static_cast<double>(n) : 0.0;
    sum += mean * mean, sum_error += se2, ++points;
  }
  CurveChange c;
  if (points > 0)
    c.rms = std::sqrt(sum / points), c.error = std::sqrt(sum_error / points),
    c.excess = std::sqrt(std::max(0.0, (sum - sum_error) / points));
  return c;
}

// The RMS over the grid of the standard deviation over the seeds of one rung's curves.
double scatter(const Rung& r, Measure m, std::span<const double> grid) {
  const std::size_t n = r.seeds.size();
  if (n < 2) return std::numeric_limits<double>::quiet_NaN();
  const ResponseCurve& first = r.seeds.front();
  std::vector<std::vector<double>> d(n);
  for (std::size_t s = 0; s < n; ++s) d[s] = curve_deviation(first.e1, first.*m, r.seeds[s].e1, r.seeds[s].*m, grid).at;
  double sum = 0;
  int points = 0;
  for (std::size_t k = 0; k < grid.size(); ++k) {
    double mean = 0;
    bool finite = true;
    for (std::size_t s = 0; s < n; ++s) finite = finite && std::isfinite(d[s][k]), mean += d[s][k];
    if (!finite) continue;
    mean /= static_cast<double>(n);
    double var = 0;
    for (std::size_t s = 0; s < n; ++s) var += (d[s][k] - mean) * (d[s][k] - mean);
    sum += var / static_cast<double>(n - 1), ++points;
  }
  return points > 0 ? std::sqrt(sum / points) : std::numeric_limits<double>::quiet_NaN();
}

// Whether a value of ev's change at the end is within its tolerance; without one, it is not judged.
bool end_within(double value, const ConvergenceTolerances& tol) {
  return !std::isfinite(tol.ev_end) || value <= tol.ev_end;
}

// Whether a change's excess is within the tolerances (and the seed scatter, when it counts).
bool small(const CurveChange& phi, const CurveChange& ev, const CurveChange& ev_end, const ConvergenceTolerances& tol,
           double phi_scatter, double ev_scatter) {
  if (!within_tolerances(phi, ev, ev_end, tol)) return false;
  if (!tol.within_seed_scatter || !std::isfinite(phi_scatter)) return true;
  return phi.excess <= phi_scatter && ev.excess <= ev_scatter;
}

// Whether the seeds resolve a change to the tolerances.
bool resolved(const CurveChange& phi, const CurveChange& ev, const CurveChange& ev_end,
              const ConvergenceTolerances& tol) {
  return phi.error <= tol.phi_rms_deg && ev.error <= tol.ev_rms && end_within(ev_end.error, tol);
}

// A curve's value at strain x (linear between its points; NaN outside it).
double value_at(const ResponseCurve& c, Measure m, double x) {
  const std::vector<double> zero(c.e1.size(), 0.0);
  const double at[] = {x};
  return curve_deviation(c.e1, zero, c.e1, c.*m, at).at[0];
}

void set_mean(ScalarLimit& s, const std::vector<double>& per_seed) {
  const double n = static_cast<double>(per_seed.size());
  double mean = 0, var = 0;
  for (double v : per_seed) mean += v;
  mean /= n;
  for (double v : per_seed) var += (v - mean) * (v - mean);
  s.mean.push_back(mean);
  s.error.push_back(per_seed.size() > 1 ? std::sqrt(var / (n - 1) / n) : 0.0);
}

// Aitken's extrapolation of the last three rungs where they change monotonically by shrinking steps.
void set_limit(ScalarLimit& s) {
  const std::size_t k = s.mean.size() - 1;
  const double y = s.mean[k], se = s.error[k];
  s.limit = y, s.band = se, s.extrapolated = false;
  if (k == 0) return;
  const double d2 = y - s.mean[k - 1];
  s.band = std::max(se, std::abs(d2));
  if (k < 2) return;
  const double d1 = s.mean[k - 1] - s.mean[k - 2];
  if (d1 == 0 || d1 * d2 <= 0 || std::abs(d2) >= std::abs(d1)) return;
  const double rho = d2 / d1;
  s.limit = y + d2 * rho / (1 - rho);
  s.band = std::max(se, std::abs(s.limit - y));
  s.extrapolated = true;
}

}  // namespace

bool within_tolerances(const CurveChange& phi, const CurveChange& ev, const CurveChange& ev_end,
                       const ConvergenceTolerances& tol) {
  return phi.excess <= tol.phi_rms_deg && ev.excess <= tol.ev_rms && end_within(ev_end.excess, tol);
}

Certificate certify(const std::vector<Rung>& ladder, const ConvergenceTolerances& tol) {
  if (ladder.empty()) throw std::invalid_argument("certify: the ladder has no rung");
  const std::size_t seeds = ladder.front().seeds.size();
  for (std::size_t k = 0; k < ladder.size(); ++k) {
    if (ladder[k].seeds.size() != seeds || seeds == 0)
      throw std::invalid_argument(fmt::format("certify: rung {} has {} seeds, the first {}", k, ladder[k].seeds.size(), seeds));
    if (k > 0 && !(ladder[k].rate < ladder[k - 1].rate))
      throw std::invalid_argument("certify: the rates must decrease from rung to rung");
  }
  const Rung& slowest = ladder.back();
  const std::vector<double>& grid = slowest.seeds.front().e1;
  // The end: the last strain every curve of the ladder reaches.
  double end_strain = grid.empty() ? 0.0 : *std::max_element(grid.begin(), grid.end());
  for (const Rung& r : ladder)
    for (const ResponseCurve& s : r.seeds)
      if (!s.e1.empty()) end_strain = std::min(end_strain, *std::max_element(s.e1.begin(), s.e1.end()));
  const double end[] = {end_strain};
  Certificate c;
  c.phi_scatter_deg = scatter(slowest, &ResponseCurve::phi_deg, grid);
  c.ev_scatter = scatter(slowest, &ResponseCurve::ev, grid);
  for (std::size_t k = 0; k < ladder.size(); ++k) {
    RungVerdict v;
    v.rate = ladder[k].rate;
    if (k + 1 < ladder.size()) {
      v.phi_to_slowest = change(ladder[k], slowest, &ResponseCurve::phi_deg, grid);
      v.ev_to_slowest = change(ladder[k], slowest, &ResponseCurve::ev, grid);
      v.phi_to_next = change(ladder[k], ladder[k + 1], &ResponseCurve::phi_deg, grid);
      v.ev_to_next = change(ladder[k], ladder[k + 1], &ResponseCurve::ev, grid);
      v.ev_end_to_slowest = change(ladder[k], slowest, &ResponseCurve::ev, end);
      v.ev_end_to_next = change(ladder[k], ladder[k + 1], &ResponseCurve::ev, end);
      v.resolved = resolved(v.phi_to_slowest, v.ev_to_slowest, v.ev_end_to_slowest, tol);
      v.within = v.resolved && small(v.phi_to_slowest, v.ev_to_slowest, v.ev_end_to_slowest, tol, c.phi_scatter_deg,
                                     c.ev_scatter);
    } else {
      v.phi_to_slowest = v.ev_to_slowest = v.ev_end_to_slowest = {0.0, 0.0, 0.0};
      v.within = v.resolved = true;
    }
    c.rungs.push_back(v);
  }
  const double phi_se = std::isfinite(c.phi_scatter_deg) ? c.phi_scatter_deg / std::sqrt(double(seeds)) : 0.0;
  const double ev_se = std::isfinite(c.ev_scatter) ? c.ev_scatter / std::sqrt(double(seeds)) : 0.0;
  c.limit_resolved = phi_se <= tol.phi_rms_deg && ev_se <= tol.ev_rms;

  if (ladder.size() < 2) {
    c.reason = "one rung: nothing to compare it with";
  } else {
    const RungVerdict& last = c.rungs[ladder.size() - 2];
    const CurveChange &phi = last.phi_to_next, &ev = last.ev_to_next, &ev_end = last.ev_end_to_next;
    const bool judge_end = std::isfinite(tol.ev_end);
    const std::string change = fmt::format(
        "change of phi {:.3g} deg (beyond the noise {:.3g}, standard error {:.3g}), of ev {:.3g} ({:.3g}, {:.3g}){}; "
        "tolerances {:.3g} deg, {:.3g}{}{}",
        phi.rms, phi.excess, phi.error, ev.rms, ev.excess, ev.error,
        judge_end ? fmt::format(", of ev at the end {:.3g} ({:.3g}, {:.3g})", ev_end.rms, ev_end.excess, ev_end.error)
                  : std::string(),
        tol.phi_rms_deg, tol.ev_rms, judge_end ? fmt::format(", {:.3g} at the end", tol.ev_end) : std::string(),
        tol.within_seed_scatter && std::isfinite(c.phi_scatter_deg)
            ? fmt::format("; seed scatter {:.3g} deg, {:.3g}", c.phi_scatter_deg, c.ev_scatter)
            : std::string());
    if (!small(phi, ev, ev_end, tol, c.phi_scatter_deg, c.ev_scatter)) {
      c.reason = "the two slowest rates still differ: " + change;
    } else if (!resolved(phi, ev, ev_end, tol)) {
      c.status = "not resolved";
      c.reason = "the two slowest rates differ by less than their noise, but the noise exceeds a tolerance (more "
                 "seeds would decide): " + change;
    } else {
      c.status = "converged";
      std::size_t k = ladder.size() - 1;
      while (k > 0 && c.rungs[k - 1].within) --k;
      c.certified = k;
      c.reason = fmt::format("the response at eps' = {:.3g} and every slower rate is within the tolerances "
                             "of the slowest rate, {:.3g}",
                             ladder[k].rate, slowest.rate);
    }
  }
  if (!c.limit_resolved)
    c.reason += fmt::format("; the seeds scatter more than the tolerances (standard error {:.3g} deg, {:.3g}): the "
                            "limit is not resolved, more seeds would resolve it",
                            phi_se, ev_se);

  // The scalars of the response: per seed, then their mean over the seeds.
  const char* names[] = {"peak_phi_deg", "e1_at_peak", "phi_deg", "ev", "cn", "q_over_p"};
  const Measure ends[] = {&ResponseCurve::phi_deg, &ResponseCurve::ev, &ResponseCurve::cn, &ResponseCurve::q_over_p};
  for (const char* name : names) c.scalars.push_back({name, {}, {}});
  for (const Rung& r : ladder) {
    std::vector<std::vector<double>> v(6);
    for (const ResponseCurve& s : r.seeds) {
      std::size_t peak = 0;
      for (std::size_t i = 0; i < s.phi_deg.size(); ++i)
        if (s.phi_deg[i] > s.phi_deg[peak]) peak = i;
      v[0].push_back(s.phi_deg.empty() ? Certificate::nan : s.phi_deg[peak]);
      v[1].push_back(s.e1.empty() ? Certificate::nan : s.e1[peak]);
      for (int m = 0; m < 4; ++m) v[2 + m].push_back(value_at(s, ends[m], end_strain));
    }
    for (int m = 0; m < 6; ++m) set_mean(c.scalars[m], v[m]);
  }
  for (ScalarLimit& s : c.scalars) set_limit(s);
  return c;
}

}  // namespace qsdem
