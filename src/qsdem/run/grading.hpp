// Gradings from a sieve curve (docs/physics.md 8.6): the sizes of N particles drawn by mass from
// the curve's points (d_k, P_k), the characteristic sizes D_x and the coefficients Cu and Cc
// (ASTM D2487) of the curve and of the sample drawn.
#pragma once
#include <cstdint>
#include <string>
#include <vector>

#include <nlohmann/json.hpp>

#include "qsdem/engine/particles.hpp"
#include "qsdem/run/config.hpp"

namespace qsdem {

// D10, D30, D50, D60 (m), Cu = D60/D10 and Cc = D30^2/(D10 D60).
struct GradingSizes {
  double d10 = 0, d30 = 0, d50 = 0, d60 = 0, cu = 0, cc = 0;
};

// D_x of the curve: the size passing the mass fraction x (in [0, 1]), linear in log d between points.
double curve_size(const Grading& g, double x);
GradingSizes curve_sizes(const Grading& g);

// The same of particles of equal-volume diameters d: D_x is the smallest d_i of which the
// particles no larger than d_i hold at least the mass fraction x (mass proportional to d^3).
GradingSizes sample_sizes(std::vector<double> d);

// Interval k's share of the particles, by number, when its mass fraction P_k+1 - P_k is spread
// with the number density n(d) ~ d^-4 (a cumulative mass linear in log d), normalised to 1.
std::vector<double> number_fractions(const Grading& g);

// The whole particle counts of the intervals: N times number_fractions, rounded by largest
// remainder (ties to the smaller interval) so that they sum to N.
std::vector<long> interval_counts(const Grading& g, long n);

// The equal-volume diameters of the n particles, interval by interval (ascending within each):
// stratified draws u_j = (j + U_j)/N_k of the interval's number distribution, U_j from the seed.
std::vector<double> draw_diameters(const Grading& g, long n, std::uint64_t seed);

// The size table of the drawn particles, one row of count 1 per particle (a sphere, or a prolate
// spheroid of its interval's aspect ratio with the drawn equal-volume diameter).
std::vector<SizeClass> grading_table(const Grading& g, long n, std::uint64_t seed);

// The size classes of classes.csv for a graded sample (docs/physics.md 10.3): the particles of
// each sieve interval that holds any, named by its smallest equal-volume radius, ascending.
std::vector<double> grading_classes(const Grading& g, const Particles& particles);

// For summary.json: the curve, each interval's mass fractions (curve and drawn) and counts, and
// the sizes of the curve and of the sample.
nlohmann::json grading_json(const Grading& g, long n, std::uint64_t seed);

// One line for the run's opening: D10, D50, Cu and Cc of the curve and of the sample.
std::string describe_grading(const Grading& g, long n, std::uint64_t seed);

}  // namespace qsdem
