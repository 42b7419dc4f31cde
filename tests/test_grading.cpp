// Gradings from a sieve curve (docs/physics.md 8.6, src/qsdem/run/grading.cpp): D_x, Cu and Cc of a
// known curve exactly, the drawn mass fractions per interval within a bound derived from N, the
// number distribution, determinism under the seed, and each bad curve refused with its message.
#include <gtest/gtest.h>

#include <cmath>
#include <initializer_list>
#include <string>
#include <vector>

#include "case_errors.hpp"
#include "qsdem/engine/particles.hpp"
#include "qsdem/run/config.hpp"
#include "qsdem/run/generate.hpp"
#include "qsdem/run/grading.hpp"

using namespace qsdem;
using qsdem_test::error_of;
using qsdem_test::expect_mentions;

namespace {

// 1, 2, 4, 8 mm passing 0, 20, 70, 100 %: mass fractions 0.2, 0.5, 0.3, size ratio 8.
Grading known_curve() {
  Grading g;
  g.size = {1e-3, 2e-3, 4e-3, 8e-3};
  g.passing = {0, 0.2, 0.7, 1};
  g.aspect_ratio = {1, 1, 1};
  return g;
}

const std::string material = R"(
name = "graded"
[material]
density = "2650 kg/m^3"
young_modulus = "78 GPa"
poisson_ratio = 0.3
)";

// A case with the known curve, its point k's `passing` or `size` line replaced when asked.
std::string graded_case(const std::string& sample = "total_particles = 300", const std::string& extra = "",
                        std::vector<std::string> points = {"size = \"1 mm\"\npassing = \"0 %\"",
                                                           "size = \"2 mm\"\npassing = \"20 %\"",
                                                           "size = \"4 mm\"\npassing = \"70 %\"",
                                                           "size = \"8 mm\"\npassing = \"100 %\""}) {
  std::string out = material + "[sample]\n" + sample + "\n";
  for (const std::string& p : points) out += "[[sample.grading]]\n" + p + "\n";
  return out + extra;
}

}  // namespace

// D_x linear in log d between the points: D10 = 1 mm * 2^(0.1/0.2), D30 = 2 mm * 2^(0.1/0.5),
// D50 = 2 mm * 2^0.6, D60 = 2 mm * 2^0.8; Cu = 2^1.3, Cc = 2^(2 + 0.4 - 0.5 - 1 - 0.8) = 2^0.1.
TEST(Grading, SizesAndCoefficientsOfAKnownCurve) {
  const GradingSizes s = curve_sizes(known_curve());
  EXPECT_NEAR(s.d10, 1e-3 * std::sqrt(2.0), 1e-15);
  EXPECT_NEAR(s.d30, 2e-3 * std::pow(2.0, 0.2), 1e-15);
  EXPECT_NEAR(s.d50, 2e-3 * std::pow(2.0, 0.6), 1e-15);
  EXPECT_NEAR(s.d60, 2e-3 * std::pow(2.0, 0.8), 1e-15);
  EXPECT_NEAR(s.cu, std::pow(2.0, 1.3), 1e-12);
  EXPECT_NEAR(s.cc, std::pow(2.0, 0.1), 1e-12);
  // A flat stretch (no mass between 2 and 4 mm): D_x at its height is its smallest size.
  Grading flat = known_curve();
  flat.passing = {0, 0.3, 0.3, 1};
  EXPECT_DOUBLE_EQ(curve_size(flat, 0.3), 2e-3);
  EXPECT_DOUBLE_EQ(curve_size(flat, 0.65), 4e-3 * std::pow(2.0, 0.5));
}

// The sample's D_x: the smallest d_i whose finer-or-equal particles hold the mass fraction x.
// Two of 1 mm (mass 1 each) and one of 2 mm (mass 8): cumulative 0.1, 0.2, 1.
TEST(Grading, SampleSizesAreTheMassCurveOfTheParticles) {
  const GradingSizes s = sample_sizes({2e-3, 1e-3, 1e-3});
  EXPECT_EQ(s.d10, 1e-3);
  EXPECT_EQ(s.d30, 2e-3);
  EXPECT_EQ(s.d60, 2e-3);
  EXPECT_DOUBLE_EQ(s.cu, 2);
  EXPECT_DOUBLE_EQ(s.cc, 2);
}

// With n(d) ~ d^-4 in an interval, its mean d^3 is 3 ln(b/a)/(a^-3 - b^-3); the number fractions
// are f_k / <d^3>_k normalised; the counts are those rounded to sum to N, each within 1 of N n_k.
TEST(Grading, CountsRealiseTheNumberFractions) {
  const Grading g = known_curve();
  const std::vector<double> n = number_fractions(g);
  std::vector<double> w;
  for (std::size_t k = 0; k < 3; ++k) {
    const double a = g.size[k], b = g.size[k + 1];
    w.push_back((g.passing[k + 1] - g.passing[k]) * (std::pow(a, -3) - std::pow(b, -3)) / (3 * std::log(b / a)));
  }
  const double sum = w[0] + w[1] + w[2];
  for (std::size_t k = 0; k < 3; ++k) EXPECT_NEAR(n[k], w[k] / sum, 1e-14);
  for (long total : {1L, 7L, 300L, 20000L}) {
    const std::vector<long> c = interval_counts(g, total);
    EXPECT_EQ(c[0] + c[1] + c[2], total);
    for (std::size_t k = 0; k < 3; ++k) EXPECT_LT(std::abs(c[k] - n[k] * total), 1.0) << total << " " << k;
  }
  // An interval without mass holds no particle.
  Grading flat = g;
  flat.passing = {0, 0.3, 0.3, 1};
  EXPECT_EQ(interval_counts(flat, 1000)[1], 0);
}

// The drawn mass fraction of each interval against the curve's. Bound from N: the count of interval
// k is within 1 of N n_k (relative alpha_k = 1/(N n_k)); its stratified draws of the increasing
// d(u)^3 have a mean within (b^3 - a^3)/N_k of <d^3>_k (the strata's errors telescope), relative
// beta_k. With eps_k = (1 + alpha_k)(1 + beta_k) - 1 and eps = sum f_j eps_j, the fraction is
// within f_k (eps_k + eps)/(1 - eps). Every draw lies in its interval, and the sizes are its own.
TEST(Grading, DrawnMassFractionsFollowTheCurve) {
  const Grading g = known_curve();
  for (long total : {300L, 20000L}) {
    const std::vector<long> c = interval_counts(g, total);
    const std::vector<double> n = number_fractions(g), d = draw_diameters(g, total, 5);
    ASSERT_EQ(d.size(), static_cast<std::size_t>(total));
    std::vector<double> mass(3, 0.0), eps_k(3);
    double all = 0, eps = 0;
    std::size_t i = 0;
    for (std::size_t k = 0; k < 3; ++k) {
      const double a = g.size[k], b = g.size[k + 1];
      for (long j = 0; j < c[k]; ++j, ++i) {
        EXPECT_GE(d[i], a);
        EXPECT_LE(d[i], b);
        mass[k] += d[i] * d[i] * d[i];
      }
      all += mass[k];
      const double mean_cube = 3 * std::log(b / a) / (std::pow(a, -3) - std::pow(b, -3));
      const double alpha = 1 / (n[k] * total), beta = (b * b * b - a * a * a) / (c[k] * mean_cube);
      eps_k[k] = (1 + alpha) * (1 + beta) - 1;
      eps += (g.passing[k + 1] - g.passing[k]) * eps_k[k];
    }
    for (std::size_t k = 0; k < 3; ++k) {
      const double f = g.passing[k + 1] - g.passing[k];
      EXPECT_NEAR(mass[k] / all, f, f * (eps_k[k] + eps) / (1 - eps)) << total << " interval " << k;
    }
    if (total == 20000) {  // the bound is then tight enough to mean something: below 2 % of f_k
      EXPECT_LT(eps_k[2] + eps, 0.02);
    }
  }
}

// The same seed draws the same sizes; another seed others. Spheroids of aspect ratio alpha have
// a = alpha b and the drawn equal-volume diameter 2 (a b^2)^(1/3).
TEST(Grading, DeterministicUnderTheSeedAndShaped) {
  Grading g = known_curve();
  EXPECT_EQ(draw_diameters(g, 500, 3), draw_diameters(g, 500, 3));
  EXPECT_NE(draw_diameters(g, 500, 3), draw_diameters(g, 500, 4));
  g.aspect_ratio = {1, 1.5, 1};
  const std::vector<long> c = interval_counts(g, 500);
  const std::vector<double> d = draw_diameters(g, 500, 3);
  const std::vector<SizeClass> table = grading_table(g, 500, 3);
  ASSERT_EQ(table.size(), 500u);
  for (std::size_t i = 0; i < table.size(); ++i) {
    const Vec3& ax = table[i].semi_axes;
    const bool middle = i >= static_cast<std::size_t>(c[0]) && i < static_cast<std::size_t>(c[0] + c[1]);
    EXPECT_EQ(table[i].shape, middle ? ShapeKind::ellipsoid : ShapeKind::sphere) << i;
    EXPECT_NEAR(ax.x() / ax.y(), middle ? 1.5 : 1.0, 1e-12);
    EXPECT_NEAR(2 * std::cbrt(ax.x() * ax.y() * ax.z()), d[i], 1e-12 * d[i]);
    EXPECT_EQ(table[i].count, 1);
  }
}

// The case file: [[sample.grading]] with sample.total_particles; the shape of the whole curve or
// of the interval that ends at a point; resolve_table draws the particles.
TEST(Grading, ReadFromTheCaseFile) {
  const Params p = parse_case(graded_case("total_particles = 300\ngrading_shape = \"spheroid\"\ngrading_aspect_ratio = 1.2",
                                          "", {"size = \"1 mm\"\npassing = 0", "size = \"2 mm\"\npassing = 0.2",
                                               "size = \"4 mm\"\npassing = \"70 %\"\nshape = \"sphere\"",
                                               "size = \"8 mm\"\npassing = \"100 %\"\naspect_ratio = 2"}),
                              "case.toml");
  ASSERT_EQ(p.sample.grading.size.size(), 4u);
  EXPECT_DOUBLE_EQ(p.sample.grading.size[2], 4e-3);
  EXPECT_DOUBLE_EQ(p.sample.grading.passing[2], 0.7);
  EXPECT_EQ(p.sample.grading.aspect_ratio, (std::vector<double>{1.2, 1, 2}));
  EXPECT_TRUE(p.sample.table.empty());
  EXPECT_EQ(resolve_table(p.sample).size(), 300u);
  EXPECT_EQ(to_json(p)["sample"]["grading"]["size_m"].size(), 4u);
}

// Each bad curve is refused naming the key, the value and what is allowed.
TEST(Grading, BadCurvesAreRefused) {
  const auto pts = [](const std::string& p0, const std::string& p1, const std::string& p2) {
    return std::vector<std::string>{p0, p1, p2};
  };
  expect_mentions(error_of(graded_case("total_particles = 10", "",
                                       pts("size = \"1 mm\"\npassing = 0", "size = \"3 mm\"\npassing = 0.5",
                                           "size = \"2 mm\"\npassing = 1"))),
                  {"sample.grading.2.size", "\"2 mm\"", "must increase", "point 1's is 3 mm"});
  expect_mentions(error_of(graded_case("total_particles = 10", "",
                                       pts("size = \"1 mm\"\npassing = 0", "size = \"2 mm\"\npassing = \"60 %\"",
                                           "size = \"3 mm\"\npassing = \"50 %\""))),
                  {"sample.grading.2.passing", "\"50 %\"", "must not decrease", "point 1's is 60 %"});
  expect_mentions(error_of(graded_case("total_particles = 10", "",
                                       pts("size = \"1 mm\"\npassing = 0", "size = \"2 mm\"\npassing = \"60 %\"",
                                           "size = \"3 mm\"\npassing = \"90 %\""))),
                  {"sample.grading.2.passing", "\"90 %\"", "must pass 100 %"});
  expect_mentions(error_of(graded_case("total_particles = 10", "",
                                       pts("size = \"1 mm\"\npassing = \"-5 %\"", "size = \"2 mm\"\npassing = 0.5",
                                           "size = \"3 mm\"\npassing = 1"))),
                  {"sample.grading.0.passing", "\"-5 %\"", "from 0 % to 100 %"});
  expect_mentions(error_of(graded_case("total_particles = 10", "",
                                       pts("size = \"-1 mm\"\npassing = 0", "size = \"2 mm\"\npassing = 0.5",
                                           "size = \"3 mm\"\npassing = 1"))),
                  {"sample.grading.0.size", "\"-1 mm\"", "from 1 nm to 1 km"});
  expect_mentions(error_of(graded_case("total_particles = 10", "",
                                       pts("size = \"1 mm\"\npassing = 0.1", "size = \"2 mm\"\npassing = 0.5",
                                           "size = \"3 mm\"\npassing = 1"))),
                  {"sample.grading.0.passing", "0.1", "must pass 0 %"});
  expect_mentions(error_of(graded_case("total_particles = 10", "", {"size = \"1 mm\"\npassing = 1"})),
                  {"sample.grading", "at least 2 points (it has 1)"});
  expect_mentions(error_of(graded_case("total_particles = 10", "[[sample.particles]]\ndiameter = \"2 mm\"\ncount = 5\n")),
                  {"sample.particles", "either the size table", "not both"});
  expect_mentions(error_of(graded_case("seed = 2")), {"sample.total_particles", "number of particles", ">= 1"});
  expect_mentions(error_of(graded_case("total_particles = 10", "",
                                       pts("size = \"1 mm\"\npassing = 0\nshape = \"spheroid\"",
                                           "size = \"2 mm\"\npassing = 0.5", "size = \"3 mm\"\npassing = 1"))),
                  {"sample.grading.0.shape", "opens the curve"});
  expect_mentions(error_of(graded_case("total_particles = 10\ngrading_shape = \"spheroid\"")),
                  {"sample.grading_aspect_ratio", "required"});
  expect_mentions(error_of(graded_case("total_particles = 10\ngrading_shape = \"spheroid\"\ngrading_aspect_ratio = 0.5")),
                  {"sample.grading_aspect_ratio", "0.5", "[1, 100]"});
  expect_mentions(error_of(graded_case("total_particles = 10\ngrading_shape = \"cube\"")),
                  {"sample.grading_shape", "\"cube\"", "\"sphere\", \"spheroid\""});
}
