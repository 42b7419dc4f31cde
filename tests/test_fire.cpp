// The FIRE relaxation (docs/physics.md 5.7) against closed forms and its own invariants: a
// perturbed, frictionless compressed chain lattice of spheres or of spheroids touching pole to pole
// relaxes to the Hertz solution (equal overlaps, the stress of the closed form, the least stored
// energy), the power check stops every particle and
// restarts the step and the mixing, and the energy of the conservative system falls to its minimum.
#include <gtest/gtest.h>

#include <cmath>
#include <random>

#include "qsdem/engine/damping/stage.hpp"
#include "qsdem/engine/fire.hpp"
#include "qsdem/engine/measures.hpp"
#include "qsdem/engine/step.hpp"
#include "qsdem/run/config.hpp"
#include "qsdem/run/phase.hpp"
#include "qsdem/run/phase_model.hpp"

using namespace qsdem;

namespace {

constexpr double kRho = 2650, kE = 7.8e10, kNu = 0.3;
constexpr double kR = 1e-3, kDelta = 4e-6;  // sphere radius, the chains' overlap (m)
constexpr int kLateral = 3, kChain = 6;     // chains of kChain spheres on a kLateral^2 grid
constexpr double kGap = 2.4 * kR;           // lateral spacing: no contact between chains

// Chains of equal particles along 33 in a periodic cell, each contact with overlap kDelta; the 33
// fractional positions of the free ones moved by up to `shake` of the overlap (the chains stay in
// contact). Frictionless: a perturbed chain relaxes along its axis only. Spheres of radius kR, or
// prolate spheroids of semi-axes (kR, kR, a) with their axis of revolution along 33, touching pole
// to pole.
State chains(double shake, unsigned seed, double a = kR) {
  State st;
  const double pitch = 2 * a - kDelta;
  const ShapeKind shape = a == kR ? ShapeKind::sphere : ShapeKind::ellipsoid;
  Mat3 h = Mat3::Zero();
  h(0, 0) = h(1, 1) = kLateral * kGap;
  h(2, 2) = kChain * pitch;
  st.cell = make_cell(h);
  std::mt19937 rng(seed);
  std::uniform_real_distribution<double> u(-1, 1);
  std::uint32_t id = 0;
  for (int x = 0; x < kLateral; ++x)
    for (int y = 0; y < kLateral; ++y)
      for (int z = 0; z < kChain; ++z) {
        const double dz = z == 0 ? 0.0 : shake * kDelta * u(rng) / h(2, 2);
        const Vec3 s((x + 0.5) / kLateral, (y + 0.5) / kLateral, (z + 0.5) / kChain + dz);
        st.particles.add(id++, shape, Vec3(kR, kR, a), kRho, s, Quat::Identity());
      }
  return st;
}

Model fire_model(const State& st) {
  Params params;
  params.material = {kRho, kE, kNu};
  Phase phase;
  phase.friction = 0;
  phase.damping = {"none", 0.0, DampedMotion::both};
  Model m = phase_model(params, phase, phase.controls, st.particles, st.cell.h);  // every component fixed
  m.sort_particles = false;
  m.track_energy = true;
  return m;
}

// Hertz between equal surfaces of radius of curvature r: F = 4/3 E* sqrt(r/2) delta^(3/2), stored
// 2/5 F delta (SPEC 4); a sphere's r is kR.
double hertz_force(const Model& m, double delta, double r = kR) {
  return 4.0 / 3.0 * m.material.effective_modulus() * std::sqrt(r / 2) * std::pow(delta, 1.5);
}

// FIRE steps until UFR < 1e-11 (checked every 10 steps) or 20000 steps; the UFR reached.
double relax(const Model& model, State& st, long& steps, long& resets) {
  FireState fire = fire_start(model);
  Schedule schedule;
  double ufr = 1;
  steps = 0;
  while (steps < 20000) {
    fire_step(model, st, schedule, fire);
    ++steps;
    if (steps % 10 == 0 && (ufr = measure(st).ufr) < 1e-11) break;
  }
  resets = fire.resets;
  return ufr;
}

double kinetic(const Particles& p) {
  double k = 0;
  for (std::size_t i = 0; i < p.size(); ++i)
    k += 0.5 * p.mass[i] * p.v[i].squaredNorm() + 0.5 * p.angmom[i].dot(p.omega[i]);
  return k;
}

}  // namespace

// The relaxed lattice is the closed-form one: every overlap kDelta (the chain's length is held by
// the cell), sigma_33 = F / gap^2, no lateral stress, the stored energy N 2/5 F delta.
TEST(Fire, PerturbedChainsRelaxToTheHertzSolution) {
  State st = chains(0.4, 7);
  const Model model = fire_model(st);
  assign_damping(model, st.particles);
  evaluate_forces(model, st);
  const double start = st.energy.elastic;
  long steps = 0, resets = 0;
  const double ufr = relax(model, st, steps, resets);
  std::printf("[ info ] %ld FIRE steps, %ld stops, UFR %.3g\n", steps, resets, ufr);
  ASSERT_LT(ufr, 1e-11);
  const Measures m = measure(st);
  const double f = hertz_force(model, kDelta);
  EXPECT_NEAR(m.stress(2, 2), f / (kGap * kGap), 1e-9 * f / (kGap * kGap));
  EXPECT_NEAR(m.stress(0, 0), 0.0, 1e-12 * f / (kGap * kGap));
  const double n = static_cast<double>(st.particles.size());
  EXPECT_NEAR(st.energy.elastic, n * 0.4 * f * kDelta, 1e-8 * n * 0.4 * f * kDelta);
  EXPECT_GT(start, st.energy.elastic) << "the perturbation stored more";
  // Each chain equally spaced: neighbours' 33 separation = 2R - delta.
  const double pitch = 2 * kR - kDelta;
  for (std::size_t i = 0; i + 1 < st.particles.size(); ++i) {
    if ((i + 1) % kChain == 0) continue;
    const double dz = st.cell.h(2, 2) * (st.particles.s[i + 1].z() - st.particles.s[i].z());
    EXPECT_NEAR(dz, pitch, 1e-9 * kDelta) << "particle " << i;
  }
}

// The same lattice of prolate spheroids (semi-axes 1, 1, 1.5 mm) touching pole to pole, an exact
// ellipsoid contact (Perram-Wertheim, docs/physics.md 4.4-4.6): at a pole both principal radii of
// curvature are b^2/a, so the relaxed lattice carries the Hertz force of two spheres of that radius
// at overlap kDelta, sigma_33 = F / gap^2, and stores N 2/5 F delta; the poles stay on the axis.
TEST(Fire, PerturbedSpheroidChainsRelaxToTheHertzSolutionAtThePoles) {
  constexpr double a = 1.5 * kR;
  State st = chains(0.4, 5, a);
  ASSERT_EQ(st.particles.shape.front(), ShapeKind::ellipsoid);  // the Perram-Wertheim path, not the spheres'
  const Model model = fire_model(st);
  assign_damping(model, st.particles);
  evaluate_forces(model, st);
  const double start = st.energy.elastic;
  long steps = 0, resets = 0;
  const double ufr = relax(model, st, steps, resets);
  std::printf("[ info ] spheroids: %ld FIRE steps, %ld stops, UFR %.3g\n", steps, resets, ufr);
  ASSERT_LT(ufr, 1e-11);
  const Measures m = measure(st);
  const double f = hertz_force(model, kDelta, kR * kR / a);
  EXPECT_NEAR(m.stress(2, 2), f / (kGap * kGap), 1e-9 * f / (kGap * kGap));
  EXPECT_NEAR(m.stress(0, 0), 0.0, 1e-12 * f / (kGap * kGap));
  const double n = static_cast<double>(st.particles.size());
  EXPECT_NEAR(st.energy.elastic, n * 0.4 * f * kDelta, 1e-8 * n * 0.4 * f * kDelta);
  EXPECT_GT(start, st.energy.elastic) << "the perturbation stored more";
  const double pitch = 2 * a - kDelta;
  for (std::size_t i = 0; i + 1 < st.particles.size(); ++i) {
    EXPECT_NEAR(st.particles.q[i].angularDistance(Quat::Identity()), 0.0, 1e-12) << "particle " << i << " turned";
    if ((i + 1) % kChain == 0) continue;
    const double dz = st.cell.h(2, 2) * (st.particles.s[i + 1].z() - st.particles.s[i].z());
    EXPECT_NEAR(dz, pitch, 1e-9 * kDelta) << "particle " << i;
  }
}

// Bitzek et al.'s F4: a step whose power F.v is not positive stops every particle before its kick,
// halves the step (to no less than dt_min) and restarts alpha; the kicked velocities are then
// dt F / m, mixed with the force's direction.
TEST(Fire, PowerCheckStopsTheParticlesAndRestarts) {
  State st = chains(0.4, 3);
  const Model model = fire_model(st);
  assign_damping(model, st.particles);
  evaluate_forces(model, st);
  // Moving against the force: P < 0.
  for (std::size_t i = 0; i < st.particles.size(); ++i) st.particles.v[i] = -1e-3 * st.particles.force[i];
  ASSERT_LT(fire_power(st.particles), 0);
  FireState fire = fire_start(model);
  fire.alpha = 0.05, fire.positive = 9;
  const double dt_before = fire.dt;
  Schedule schedule;
  State before = st;
  fire_step(model, st, schedule, fire);
  const FireConstants c;
  EXPECT_EQ(fire.resets, 1);
  EXPECT_EQ(fire.positive, 0);
  EXPECT_DOUBLE_EQ(fire.dt, c.f_dec * dt_before);
  EXPECT_DOUBLE_EQ(fire.alpha, c.alpha_start);
  // From rest: u_i = dt F_i / m_i, then v_i = (1 - alpha) u_i + alpha |u| F_i / |F|.
  const Particles& p = st.particles;
  double u2 = 0, f2 = 0;
  for (std::size_t i = 0; i < p.size(); ++i)
    u2 += (fire.dt * p.force[i] / p.mass[i]).squaredNorm(), f2 += p.force[i].squaredNorm();
  for (std::size_t i = 0; i < p.size(); ++i) {
    const Vec3 expected = (1 - c.alpha_start) * fire.dt * p.force[i] / p.mass[i] +
                          c.alpha_start * std::sqrt(u2 / f2) * p.force[i];
    EXPECT_LT((p.v[i] - expected).norm(), 1e-12 * expected.norm() + 1e-300) << "particle " << i;
  }
  // The forces of this step are those of the state it started from.
  for (std::size_t i = 0; i < p.size(); ++i) EXPECT_EQ(p.force[i], [&] {
      State again = before;
      evaluate_forces(model, again);
      return again.particles.force[i];
    }());
}

// A conservative system (frictionless, no damping): between two stops the leapfrog keeps the
// energy (to its shadow error) and the mixing never adds kinetic energy (equal masses:
// |(1 - alpha) v + alpha |v| F^| <= |v|); at a stop every particle is at rest, so the energy is the
// stored one alone. So the stored energy at the successive stops never rises, and it ends at the minimum.
TEST(Fire, EnergyOfAConservativeSystemFalls) {
  State st = chains(0.45, 11);
  const Model model = fire_model(st);
  assign_damping(model, st.particles);
  evaluate_forces(model, st);
  std::vector<double> at_stops{st.energy.elastic};  // at rest at the start
  FireState fire = fire_start(model);
  Schedule schedule;
  for (int k = 0; k < 3000; ++k) {
    const long resets = fire.resets;
    fire_step(model, st, schedule, fire);
    if (fire.resets > resets) at_stops.push_back(st.energy.elastic);  // the forces of this step: at rest there
  }
  const double f = hertz_force(model, kDelta);
  const double minimum = static_cast<double>(st.particles.size()) * 0.4 * f * kDelta;
  std::printf("[ info ] %zu stops, stored energy %.6g J at the start, %.6g J at the end, minimum %.6g J\n",
              at_stops.size() - 1, at_stops.front(), st.energy.elastic, minimum);
  ASSERT_GE(at_stops.size(), 3u);
  // (A step from rest has P = 0 and counts as a stop; at the minimum P is round-off: equal energies.)
  for (std::size_t k = 1; k < at_stops.size(); ++k)
    EXPECT_LE(at_stops[k], at_stops[k - 1] + 1e-13 * at_stops.front()) << "stop " << k;
  EXPECT_NEAR(st.energy.elastic + kinetic(st.particles), minimum, 1e-8 * minimum);
}
