#include "qsdem/run/grading.hpp"

#include <fmt/format.h>

#include <algorithm>
#include <cmath>
#include <limits>
#include <numeric>

#include "qsdem/run/generate.hpp"

namespace qsdem {

namespace {

GradingSizes with_coefficients(double d10, double d30, double d50, double d60) {
  return {d10, d30, d50, d60, d60 / d10, d30 * d30 / (d10 * d60)};  // ASTM D2487, 3.1.2 and 3.1.3
}

// The number-weighted mean of d^3 over [a, b] with n(d) ~ d^-4 (physics.md 8.6):
// int d^-1 / int d^-4 = 3 ln(b/a) / (a^-3 - b^-3).
double mean_cube(double a, double b) { return 3 * std::log(b / a) / (std::pow(a, -3) - std::pow(b, -3)); }

// The size table's shape of an equal-volume diameter d and aspect ratio alpha = a/b >= 1:
// b = (d/2) alpha^(-1/3), a = alpha b, so that a b^2 = (d/2)^3.
SizeClass shaped(double d, double alpha) {
  SizeClass c;
  c.count = 1;
  if (alpha == 1) {
    c.semi_axes = Vec3::Constant(d / 2);
    return c;
  }
  const double b = d / 2 / std::cbrt(alpha);
  c.shape = ShapeKind::ellipsoid;
  c.semi_axes = Vec3(alpha * b, b, b);
  return c;
}

// Its own stream, apart from the placement's (generate.cpp), from the same seed (splitmix64's step).
std::uint64_t size_seed(std::uint64_t seed) {
  std::uint64_t z = seed + 0x9e3779b97f4a7c15ULL;
  z = (z ^ (z >> 30)) * 0xbf58476d1ce4e5b9ULL;
  z = (z ^ (z >> 27)) * 0x94d049bb133111ebULL;
  return z ^ (z >> 31);
}

}  // namespace

double curve_size(const Grading& g, double x) {
  const std::size_t m = g.size.size();
  // The first point passing at least x; a flat stretch at x gives its smallest size.
  std::size_t k = 0;
  while (k + 1 < m && g.passing[k] < x) ++k;
  if (k == 0) return g.size[0];
  const double p0 = g.passing[k - 1], p1 = g.passing[k];
  const double t = p1 > p0 ? (x - p0) / (p1 - p0) : 1;
  return g.size[k - 1] * std::pow(g.size[k] / g.size[k - 1], t);
}

GradingSizes curve_sizes(const Grading& g) {
  return with_coefficients(curve_size(g, 0.1), curve_size(g, 0.3), curve_size(g, 0.5), curve_size(g, 0.6));
}

GradingSizes sample_sizes(std::vector<double> d) {
  std::sort(d.begin(), d.end());
  double total = 0;
  for (double x : d) total += x * x * x;
  const auto at = [&](double x) {
    double below = 0;
    for (double s : d)
      if ((below += s * s * s) >= x * total) return s;
    return d.back();
  };
  return with_coefficients(at(0.1), at(0.3), at(0.5), at(0.6));
}

std::vector<double> number_fractions(const Grading& g) {
  std::vector<double> w(g.size.size() - 1);
  for (std::size_t k = 0; k < w.size(); ++k)
    w[k] = (g.passing[k + 1] - g.passing[k]) / mean_cube(g.size[k], g.size[k + 1]);
  const double sum = std::accumulate(w.begin(), w.end(), 0.0);
  for (double& x : w) x /= sum;
  return w;
}

std::vector<long> interval_counts(const Grading& g, long n) {
  const std::vector<double> f = number_fractions(g);
  std::vector<long> count(f.size());
  std::vector<std::size_t> order(f.size());
  long given = 0;
  for (std::size_t k = 0; k < f.size(); ++k) {
    count[k] = static_cast<long>(std::floor(f[k] * static_cast<double>(n)));
    given += count[k];
    order[k] = k;
  }
  const auto rest = [&](std::size_t k) { return f[k] * static_cast<double>(n) - static_cast<double>(count[k]); };
  std::stable_sort(order.begin(), order.end(), [&](std::size_t a, std::size_t b) { return rest(a) > rest(b); });
  for (std::size_t k = 0; given < n; ++k, ++given) ++count[order[k % order.size()]];
  return count;
}

std::vector<double> draw_diameters(const Grading& g, long n, std::uint64_t seed) {
  const std::vector<long> count = interval_counts(g, n);
  Random rng(size_seed(seed));
  std::vector<double> d;
  d.reserve(static_cast<std::size_t>(n));
  for (std::size_t k = 0; k < count.size(); ++k) {
    const double a = g.size[k], b = g.size[k + 1], ia = std::pow(a, -3), ib = std::pow(b, -3);
    for (long j = 0; j < count[k]; ++j) {
      // The inverse of the interval's number CDF F(d) = (a^-3 - d^-3)/(a^-3 - b^-3).
      const double u = (static_cast<double>(j) + rng.uniform()) / static_cast<double>(count[k]);
      d.push_back(std::clamp(std::pow(ia - u * (ia - ib), -1.0 / 3), a, b));
    }
  }
  return d;
}

std::vector<SizeClass> grading_table(const Grading& g, long n, std::uint64_t seed) {
  const std::vector<long> count = interval_counts(g, n);
  const std::vector<double> d = draw_diameters(g, n, seed);
  std::vector<SizeClass> table;
  table.reserve(d.size());
  std::size_t i = 0;
  for (std::size_t k = 0; k < count.size(); ++k)
    for (long j = 0; j < count[k]; ++j) table.push_back(shaped(d[i++], g.aspect_ratio[k]));
  return table;
}

std::vector<double> grading_classes(const Grading& g, const Particles& particles) {
  // Interval k from d_k/2, less the 1e-9 by which an equal-volume radius (a b c)^(1/3) may round
  // below its drawn d/2 (as size_classes, measures.cpp).
  const std::size_t m = g.size.size() - 1;
  std::vector<double> lower(m), smallest(m, std::numeric_limits<double>::infinity());
  for (std::size_t k = 0; k < m; ++k) lower[k] = g.size[k] / 2 * (1 - 1e-9);
  for (double r : particles.equiv_radius) {
    const auto at = std::upper_bound(lower.begin(), lower.end(), r);
    const std::size_t k = at == lower.begin() ? 0 : static_cast<std::size_t>(at - lower.begin() - 1);
    smallest[k] = std::min(smallest[k], r);
  }
  std::vector<double> classes;
  for (double r : smallest)
    if (std::isfinite(r)) classes.push_back(r);
  return classes;
}

namespace {
nlohmann::json sizes_json(const GradingSizes& s) {
  return {{"D10_m", s.d10}, {"D30_m", s.d30}, {"D50_m", s.d50}, {"D60_m", s.d60}, {"Cu", s.cu}, {"Cc", s.cc}};
}
}  // namespace

nlohmann::json grading_json(const Grading& g, long n, std::uint64_t seed) {
  const std::vector<long> count = interval_counts(g, n);
  const std::vector<double> d = draw_diameters(g, n, seed);
  double total = 0;
  for (double x : d) total += x * x * x;
  nlohmann::json intervals = nlohmann::json::array();
  std::size_t i = 0;
  for (std::size_t k = 0; k < count.size(); ++k) {
    double mass = 0;
    for (long j = 0; j < count[k]; ++j, ++i) mass += d[i] * d[i] * d[i];
    intervals.push_back({{"from_m", g.size[k]},
                         {"to_m", g.size[k + 1]},
                         {"aspect_ratio", g.aspect_ratio[k]},
                         {"mass_fraction", g.passing[k + 1] - g.passing[k]},
                         {"sampled_mass_fraction", mass / total},
                         {"count", count[k]}});
  }
  return {{"particles", n}, {"intervals", intervals}, {"curve", sizes_json(curve_sizes(g))},
          {"sample", sizes_json(sample_sizes(d))}};
}

std::string describe_grading(const Grading& g, long n, std::uint64_t seed) {
  const GradingSizes c = curve_sizes(g), s = sample_sizes(draw_diameters(g, n, seed));
  const auto line = [](const char* what, const GradingSizes& x) {
    return fmt::format("{}: D10 {:.4g} mm, D30 {:.4g} mm, D50 {:.4g} mm, D60 {:.4g} mm, Cu {:.3f}, Cc {:.3f}", what,
                       1e3 * x.d10, 1e3 * x.d30, 1e3 * x.d50, 1e3 * x.d60, x.cu, x.cc);
  };
  return fmt::format("grading of {} particles from a sieve curve of {} points; {}; {}", n, g.size.size(),
                     line("curve", c), line("sample", s));
}

}  // namespace qsdem
