// Broad phase (SPEC 4): the Verlet pair list against brute force, its validity while particles move
// and the cell deforms, contact history across rebuilds, its size at Sample A polydispersity, and
// the cell-size guard of SPEC 3.
#include <gtest/gtest.h>
#include <omp.h>

#include <algorithm>
#include <array>
#include <cstdio>
#include <cmath>
#include <filesystem>
#include <limits>
#include <map>
#include <set>
#include <vector>

#include <fmt/format.h>

#include "qsdem/engine/cell.hpp"
#include "qsdem/engine/contact/hertz_mindlin.hpp"
#include "qsdem/engine/ellipsoid_contact.hpp"
#include "qsdem/engine/model.hpp"
#include "qsdem/engine/neighbor.hpp"
#include "qsdem/engine/particles.hpp"
#include "qsdem/engine/state.hpp"
#include "qsdem/engine/step.hpp"
#include "qsdem/run/generate.hpp"
#include "qsdem/run/packing_io.hpp"
#include "test_support.hpp"

using namespace qsdem;
namespace fs = std::filesystem;

namespace {

// The tangential force on j that pair k stores (the Hertz-Mindlin history).
Vec3 stored_shear(const State& st, std::size_t k) { return HertzMindlin::tangential_force(st.pairs.history.of(k)); }

constexpr double kE = 7.8e10, kNu = 0.3, kRho = 2650;  // SPEC 9 material
constexpr double kR0 = 1e-3;                           // smallest radius (m)
constexpr double kSkin = 0.2 * kR0;                    // the default skin ratio 0.2 R_min

Model test_model(double skin, double dt) {
  Model m;
  m.material = {kRho, kE, kNu};
  m.contact_law = make_contact_law(m.material, 0.5);
  m.dt = dt;
  m.skin = skin;
  return m;
}

// A general triclinic cell shape (every off-diagonal non-zero), unit scale.
Mat3 triclinic_shape() {
  Mat3 h;
  h << 1.0, 0.3, -0.2,  //
      0.1, 1.0, 0.25,   //
      -0.15, 0.05, 1.1;
  return h;
}

// Perpendicular widths computed independently of Cell::widths: 1 / |row k of h^-1|.
double min_width(const Mat3& h) {
  const Mat3 hi = h.inverse();
  return std::min({1 / hi.row(0).norm(), 1 / hi.row(1).norm(), 1 / hi.row(2).norm()});
}

// A pair key (i < j, image of j in unwrapped fractional coordinates).
struct Key {
  std::uint32_t i, j;
  std::array<int, 3> k;
  auto operator<=>(const Key&) const = default;
};

// Nearest integer (halves away from zero), without the libm call that dominates brute-force loops.
double nearest_int(double x) { return static_cast<double>(static_cast<long>(x + (x >= 0 ? 0.5 : -0.5))); }
Vec3 nearest_image(const Vec3& d) { return Vec3(-nearest_int(d.x()), -nearest_int(d.y()), -nearest_int(d.z())); }

Key make_key(std::size_t i, std::size_t j, const Vec3& k) {
  return {static_cast<std::uint32_t>(i), static_cast<std::uint32_t>(j),
          {static_cast<int>(k.x()), static_cast<int>(k.y()), static_cast<int>(k.z())}};
}

std::set<Key> engine_keys(const PairList& pl) {
  std::set<Key> out;
  for (std::size_t n = 0; n < pl.size(); ++n)
    out.insert({pl.i[n], pl.j[n], {pl.image[n].x(), pl.image[n].y(), pl.image[n].z()}});
  return out;
}

Vec3 key_image(const Key& key) { return Vec3(key.k[0], key.k[1], key.k[2]); }

double key_distance(const Particles& p, const Mat3& h, const Key& key) {
  return (h * (p.s[key.j] - p.s[key.i] + key_image(key))).norm();
}

// Brute force over all pairs i < j and the 27 images around the nearest one:
// every (i, j, k) with |x_j + h k - x_i| < R_i + R_j + extra.
std::set<Key> brute_pairs(const Particles& p, const Mat3& h, double extra) {
  std::set<Key> out;
  for (std::size_t i = 0; i < p.size(); ++i)
    for (std::size_t j = i + 1; j < p.size(); ++j) {
      const Vec3 d = p.s[j] - p.s[i];
      const Vec3 k0 = nearest_image(d);
      const double cut = p.bound_radius[i] + p.bound_radius[j] + extra;
      for (int a = -1; a <= 1; ++a)
        for (int b = -1; b <= 1; ++b)
          for (int c = -1; c <= 1; ++c) {
            const Vec3 k = k0 + Vec3(a, b, c);
            if ((h * (d + k)).norm() < cut) out.insert(make_key(i, j, k));
          }
    }
  return out;
}

// Keys in one set and not the other whose distance is not within rounding (1e-12 relative) of the
// cut-off: engine and test compute the same distance through different roundings.
int real_mismatches(const std::set<Key>& a, const std::set<Key>& b, const Particles& p, const Mat3& h,
                    double extra) {
  std::vector<Key> diff;
  std::set_symmetric_difference(a.begin(), a.end(), b.begin(), b.end(), std::back_inserter(diff));
  int n = 0;
  for (const Key& key : diff) {
    const double cut = p.bound_radius[key.i] + p.bound_radius[key.j] + extra;
    if (std::abs(key_distance(p, h, key) - cut) > 1e-12 * cut) ++n;
  }
  return n;
}

// Random spheres (overlaps allowed: the broad phase must not care). ratio 1: all R0; otherwise
// 85 % in [R0, 1.3 R0], 15 % log-uniform in [1.3 R0, ratio R0], and one of each extreme size.
// The cell has the given shape, scaled to the target solid fraction or to 1.1 times the SPEC 3
// minimum width 2 (2 R_max + skin), whichever is larger (room for a few % of compression). A third of the particles get their
// fractional coordinate unwrapped by a random lattice vector (SPEC 3: s is never wrapped).
State random_sample(std::size_t n, double ratio, const Mat3& shape, double solid_fraction, std::uint64_t seed) {
  Random rng(seed);
  std::vector<double> radii(n);
  for (std::size_t i = 0; i < n; ++i) {
    if (i == 0)
      radii[i] = ratio * kR0;
    else if (i == 1 || ratio == 1.0)
      radii[i] = kR0;
    else if (rng.uniform() < 0.85)
      radii[i] = kR0 * (1 + 0.3 * rng.uniform());
    else
      radii[i] = kR0 * 1.3 * std::pow(ratio / 1.3, rng.uniform());
  }
  double vsolid = 0;
  for (double r : radii) vsolid += 4.0 / 3.0 * pi * r * r * r;
  const double rmax = *std::max_element(radii.begin(), radii.end());
  const double scale_fill = std::cbrt(vsolid / solid_fraction / std::abs(shape.determinant()));
  const double scale_min = 1.1 * 2 * (2 * rmax + kSkin) / min_width(shape);
  State st;
  st.cell = make_cell(std::max(scale_fill, scale_min) * shape);
  for (std::size_t i = 0; i < n; ++i) {
    Vec3 s(rng.uniform(), rng.uniform(), rng.uniform());
    if (rng.uniform() < 1.0 / 3.0) s += Vec3(std::floor(5 * rng.uniform()) - 2, std::floor(5 * rng.uniform()) - 2,
                                             std::floor(5 * rng.uniform()) - 2);
    st.particles.add(static_cast<std::uint32_t>(i), ShapeKind::sphere, Vec3::Constant(radii[i]), kRho, s,
                     Quat::Identity());
  }
  return st;
}

// Runs a block on one OpenMP thread. The step-by-step tests call evaluate_forces hundreds of times
// on a few hundred particles: with threads, each of its parallel regions waits for a scheduler
// slice when the machine is busy (seconds per test). They check list validity, not threading;
// the threaded build_pairs is checked against brute force in EqualsBruteForce and at 8000 particles.
using qsdem_test::SingleThread;

}  // namespace

// SPEC 4: build_pairs lists exactly the pairs whose bounding spheres are closer than the skin, each
// once with i < j and its image, for monodisperse and size ratio 7.5 samples, orthorhombic and
// triclinic cells, three seeds each.
TEST(NeighborList, EqualsBruteForce) {
  for (double ratio : {1.0, 7.5})
    for (int tric = 0; tric <= 1; ++tric)
      for (std::uint64_t seed : {1u, 2u, 3u}) {
        SCOPED_TRACE(testing::Message() << "ratio " << ratio << (tric ? " triclinic" : " orthorhombic") << " seed "
                                        << seed);
        const Mat3 shape = tric ? triclinic_shape() : Mat3(Vec3(1.0, 1.1, 0.9).asDiagonal());
        State st = random_sample(600, ratio, shape, 0.55, seed);
        build_pairs(st.particles, st.cell, kSkin, st.pairs, st.neighbor);
        const PairList& pl = st.pairs;
        for (std::size_t n = 0; n < pl.size(); ++n) ASSERT_LT(pl.i[n], pl.j[n]);
        const std::set<Key> got = engine_keys(pl);
        EXPECT_EQ(got.size(), pl.size()) << "a pair is listed twice";
        const std::set<Key> want = brute_pairs(st.particles, st.cell.h, kSkin);
        // A real test needs several candidates per particle.
        ASSERT_GT(want.size(), st.particles.size());
        EXPECT_EQ(real_mismatches(got, want, st.particles, st.cell.h, kSkin), 0)
            << "engine " << got.size() << " pairs, brute force " << want.size();
      }
}

// Whether some particle is an ellipsoid, which the step asks twice per step: the list build
// records it (NeighborState::ellipsoids, with the surface paths it sizes), and without a valid
// list has_ellipsoids(State) passes over the particles; the same answer either way.
TEST(NeighborList, RecordsWhetherItsParticlesIncludeEllipsoids) {
  for (const bool ellipsoid : {false, true}) {
    SCOPED_TRACE(ellipsoid ? "one ellipsoid" : "spheres only");
    State st = random_sample(200, 1.0, Mat3(Vec3(1.0, 1.1, 0.9).asDiagonal()), 0.4, 7);
    if (ellipsoid)
      st.particles.add(200, ShapeKind::ellipsoid, Vec3(2 * kR0, kR0, kR0), kRho, Vec3(0.5, 0.5, 0.5),
                       Quat::Identity());
    ASSERT_FALSE(st.neighbor.valid);
    EXPECT_EQ(has_ellipsoids(st), ellipsoid) << "no list yet: from the particles";
    build_pairs(st.particles, st.cell, kSkin, st.pairs, st.neighbor);
    EXPECT_EQ(st.neighbor.ellipsoids, ellipsoid);
    EXPECT_EQ(has_ellipsoids(st), ellipsoid);
    EXPECT_EQ(st.neighbor.surface_path.size(), ellipsoid ? st.particles.size() : 0u);
  }
}

// A wide grading (size ratio 1000: 300 spheres of 1 mm and 5 of 1 um, the skin 0.2 R_min): the
// grids hold at most one bin per particle and class, where bins of 2 R_min + skin would number
// ~1e11 (an int overflow, then gigabytes), and the list is still exact.
TEST(NeighborList, WideGradingCostsBinsByParticlesAndStaysExact) {
  for (int tric = 0; tric <= 1; ++tric) {
    SCOPED_TRACE(tric ? "triclinic" : "orthorhombic");
    const Mat3 shape = tric ? triclinic_shape() : Mat3(Vec3(1.0, 1.1, 0.9).asDiagonal());
    State st = random_sample(300, 1.0, shape, 0.55, 7);
    Random rng(8);
    for (std::uint32_t f = 0; f < 5; ++f) {  // fines beside coarse particles, some within reach
      const Vec3 at = st.particles.s[f] + st.cell.h.inverse() * Vec3(kR0 + 2e-7 * f, 0, 0);
      st.particles.add(300 + f, ShapeKind::sphere, Vec3::Constant(1e-3 * kR0), kRho, at, Quat::Identity());
    }
    const double skin = 0.2 * 1e-3 * kR0;
    build_pairs(st.particles, st.cell, skin, st.pairs, st.neighbor);
    EXPECT_LE(st.neighbor.grid_bins, 305 + 2);
    EXPECT_LT(st.neighbor.distance_checks, 305L * 100);
    const std::set<Key> got = engine_keys(st.pairs);
    EXPECT_EQ(got.size(), st.pairs.size()) << "a pair is listed twice";
    const std::set<Key> want = brute_pairs(st.particles, st.cell.h, skin);
    std::size_t with_fines = 0;
    for (const Key& k : want) with_fines += k.j >= 300;
    ASSERT_GE(with_fines, 3u) << "the fines must have partners for the test to be one";
    EXPECT_EQ(real_mismatches(got, want, st.particles, st.cell.h, skin), 0)
        << "engine " << got.size() << " pairs, brute force " << want.size();
  }
}

// A blown-up state (a NaN position, or one beyond an int's count of cell images) is a RunError
// naming the particle, not a cast of NaN to int (undefined behaviour, found by the loaders' fuzzer).
// Above parallel_threshold the positions are wrapped on the threads: the error still names the
// first such particle.
TEST(NeighborList, BlownUpPositionIsARunError) {
  const int saved = omp_get_max_threads();
  omp_set_num_threads(2);
  for (const std::size_t n : {std::size_t{50}, parallel_threshold + 904})
    for (const double bad : {std::numeric_limits<double>::quiet_NaN(), 1e272}) {
      State st = random_sample(n, 1.0, Mat3::Identity(), 0.5, 1);
      st.particles.s[7].y() = bad;
      st.particles.s[n - 3].x() = bad;
      try {
        build_pairs(st.particles, st.cell, kSkin, st.pairs, st.neighbor);
        ADD_FAILURE() << "no error for " << bad;
      } catch (const RunError& e) {
        EXPECT_NE(std::string(e.what()).find(fmt::format("particle id {} ", st.particles.id[7])), std::string::npos)
            << e.what();
      }
    }
  omp_set_num_threads(saved);
}

// SPEC 4: the Verlet list stays valid while particles move and the cell deforms (compression,
// shear, both in a triclinic cell): at every step every pair that truly overlaps (brute force) is
// in the list under its image key and has the right overlap, and the engine reports no other
// contact. Particles drift at constant random fluctuation velocities; the list is maintained by
// evaluate_forces (needs_rebuild / build_pairs) exactly as in a run.
TEST(NeighborList, VerletValidWhileCellDeforms) {
  const SingleThread one_thread;
  const double dt = 1e-6;
  struct Scenario {
    const char* name;
    Mat3 shape;
    Mat3 L;        // velocity gradient (1/s)
    double drift;  // largest fluctuation displacement per step and component, in R0
  };
  Mat3 compress = Mat3::Identity() * -200.0;  // 2e-4 strain per axis per step
  Mat3 shear = Mat3::Zero();
  shear(0, 2) = 500.0;  // simple shear, 5e-4 per step
  Mat3 mixed;
  mixed << 100, 0, 0,  //
      200, 100, 0,     //
      0, -150, -300;
  const std::vector<Scenario> scenarios = {
      {"isotropic compression", Mat3::Identity(), compress, 0.004},
      {"simple shear", Mat3::Identity(), shear, 0.004},
      {"triaxial + shear, triclinic", triclinic_shape(), mixed, 0.004},
      // Affine only: every rebuild is due to the cell deformation (the strain term of the test).
      {"isotropic compression, no fluctuation", Mat3::Identity(), 1.5 * compress, 0.0},
  };
  const int steps = 150;
  for (const Scenario& sc : scenarios) {
    SCOPED_TRACE(sc.name);
    State st = random_sample(400, 7.5, sc.shape, 0.5, 42);
    const Model model = test_model(kSkin, dt);
    Particles& p = st.particles;
    Random rng(99);
    for (std::size_t i = 0; i < p.size(); ++i)  // |v dt| <= drift R0 per component per step
      p.v[i] = sc.drift * kR0 / dt * Vec3(2 * rng.uniform() - 1, 2 * rng.uniform() - 1, 2 * rng.uniform() - 1);
    evaluate_forces(model, st);
    const std::set<Key> initial = engine_keys(st.pairs);
    const long builds0 = st.neighbor.builds;
    std::set<Key> new_contacts;  // contacts that were not even candidates at the first build
    for (int n = 0; n < steps; ++n) {
      st.cell.L = sc.L;
      deform(st.cell, dt);  // h <- (I + dt L) h, then drift as advance_positions does
      for (std::size_t i = 0; i < p.size(); ++i) p.s[i] += dt * st.cell.h_inv * p.v[i];
      evaluate_forces(model, st);

      // Brute-force contacts. Every contact is shorter than half the smallest width (asserted), so
      // each fractional component of its branch is below 1/2 and -round(sj - si) is its only image.
      const Mat3& h = st.cell.h;
      const double wmin = min_width(h);
      ASSERT_LT(2 * 7.5 * kR0, 0.5 * wmin);
      std::map<Key, std::size_t> listed;
      for (std::size_t k = 0; k < st.pairs.size(); ++k)
        listed[{st.pairs.i[k], st.pairs.j[k], {st.pairs.image[k].x(), st.pairs.image[k].y(), st.pairs.image[k].z()}}] = k;
      int brute_contacts = 0, missing = 0;
      for (std::size_t i = 0; i < p.size(); ++i)
        for (std::size_t j = i + 1; j < p.size(); ++j) {
          const Vec3 d = p.s[j] - p.s[i];
          const Vec3 k = nearest_image(d);
          const double sum = p.bound_radius[i] + p.bound_radius[j];
          // Exact early reject: |b| >= |f_m| w_m >= |f_m| w_min for each fractional component f_m.
          if ((d + k).cwiseAbs().maxCoeff() * wmin >= sum) continue;
          const double delta = sum - (h * (d + k)).norm();
          if (delta <= 0) continue;
          ++brute_contacts;
          const Key key = make_key(i, j, k);
          if (!initial.count(key)) new_contacts.insert(key);
          const auto it = listed.find(key);
          if (it == listed.end()) {
            ++missing;
            ADD_FAILURE() << "step " << n << ": contact " << i << "-" << j << " (overlap " << delta << " m) not listed";
            continue;
          }
          // Same geometry through different roundings: 1e-12 of the radii sum.
          EXPECT_NEAR(st.pairs.overlap[it->second], delta, 1e-12 * sum);
        }
      int engine_contacts = 0;
      for (double o : st.pairs.overlap) engine_contacts += o > 0 ? 1 : 0;
      EXPECT_EQ(engine_contacts, brute_contacts) << "step " << n;
      ASSERT_EQ(missing, 0) << "step " << n;
    }
    // The check is only meaningful if the motion created contacts the first list did not hold
    // (so rebuilds were needed) and if the list was reused between rebuilds.
    const long builds = st.neighbor.builds - builds0;
    std::printf("[ info ] %s: %ld builds in %d steps, %zu new contacts\n", sc.name, builds, steps, new_contacts.size());
    EXPECT_GE(new_contacts.size(), 10u);
    EXPECT_GE(builds, 2);
    EXPECT_LT(builds, steps / 2);
  }
}

// SPEC 4: the rebuild test is safe right at its limit. Two equal spheres start just outside the
// list (gap skin + eps) and close it (a) with opposite fluctuation velocities across a periodic
// face, (b) by uniaxial compression of the cell along their branch, (c) by simple shear of a branch
// at 45 degrees. At every step from the first overlap on, the pair must be listed with the right
// overlap. (a) is tight for "twice the largest displacement", (b) for "strain times the longest
// branch": a rebuild test that drops either factor lets the contact go unlisted for many steps.
TEST(NeighborList, ContactNeverMissedAtTheSkinLimit) {
  const SingleThread one_thread;
  const double r = 2e-3, skin = 0.2e-3, eps = 0.005 * skin, dt = 1e-6, side = 20e-3;
  const Model model = test_model(skin, dt);
  struct Case {
    const char* name;
    Vec3 dir;     // branch direction from i to j
    Vec3 si;      // so that the pair straddles one or two faces
    Mat3 L;       // velocity gradient (1/s)
    double speed; // each sphere moves towards the other (m/s)
    int steps;
  };
  Mat3 uniaxial = Mat3::Zero(), shear = Mat3::Zero();
  uniaxial(0, 0) = -500.0;  // 5e-4 strain per step: rebuild at step 98, contact from step 101
  shear(0, 2) = 1000.0;     // 1e-3 shear per step: contact from gamma ~ 0.1 (step ~101)
  const std::vector<Case> cases = {
      // Closing 0.0493 skin per step: contact from step ~21; a factor 1 instead of 2 on the
      // displacement would rebuild only at step ~41.
      {"head-on fluctuation across the x face", Vec3(1, 0, 0), Vec3(0.97, 0.5, 0.5), Mat3::Zero(),
       0.0493 * skin / (2 * dt), 70},
      {"uniaxial compression along the branch", Vec3(1, 0, 0), Vec3(0.97, 0.5, 0.5), uniaxial, 0.0, 150},
      {"simple shear, branch at 45 degrees", Vec3(1, 0, -1), Vec3(0.97, 0.5, 0.04), shear, 0.0, 160},
  };
  for (const Case& c : cases) {
    SCOPED_TRACE(c.name);
    State st;
    st.cell = make_cell(Mat3::Identity() * side);
    const Vec3 n = c.dir.normalized();
    const Vec3 l0 = (2 * r + skin + eps) * n;
    const Vec3 sj = c.si + st.cell.h_inv * l0;
    const Vec3 sj_wrapped = sj - sj.array().floor().matrix();
    ASSERT_FALSE(sj_wrapped.isApprox(sj)) << "the pair straddles a face";
    st.particles.add(0, ShapeKind::sphere, Vec3::Constant(r), kRho, c.si, Quat::Identity());
    st.particles.add(1, ShapeKind::sphere, Vec3::Constant(r), kRho, sj_wrapped, Quat::Identity());
    Particles& p = st.particles;
    p.v[0] = c.speed * n;
    p.v[1] = -c.speed * n;
    evaluate_forces(model, st);
    ASSERT_EQ(st.pairs.size(), 0u) << "starts just outside the list";
    int contact_steps = 0;
    for (int step = 0; step < c.steps; ++step) {
      st.cell.L = c.L;
      deform(st.cell, dt);
      for (std::size_t i = 0; i < p.size(); ++i) p.s[i] += dt * st.cell.h_inv * p.v[i];
      evaluate_forces(model, st);
      const Vec3 d = p.s[1] - p.s[0];
      const Vec3 k = nearest_image(d);
      const double delta = 2 * r - (st.cell.h * (d + k)).norm();
      if (delta <= 0) continue;
      ++contact_steps;
      bool listed = false;
      for (std::size_t q = 0; q < st.pairs.size(); ++q)
        if (st.pairs.image[q].cast<double>() == k) {
          listed = true;
          EXPECT_NEAR(st.pairs.overlap[q], delta, 1e-12 * r);  // same geometry, other rounding
        }
      ASSERT_TRUE(listed) << "step " << step << ": contact with overlap " << delta << " m is not listed";
    }
    EXPECT_GE(contact_steps, 40) << "the spheres must come into contact";
  }
}

// SPEC 4: contact history is keyed by (i, j, image) and survives rebuilds, also after a particle's
// (unwrapped) fractional coordinate crossed a cell face. Two spheres: a tangential velocity loads
// the spring to F_t = -k_t dt v_t (checked by hand); at rest, a forced rebuild must keep it.
TEST(NeighborHistory, TwoSpheresKeepShearAcrossRebuildAndFace) {
  const SingleThread one_thread;
  const double ri = 1e-3, rj = 0.8e-3, dt = 1e-6;
  const Model model = test_model(kSkin, dt);
  const Mat3 h = Vec3(10e-3, 11e-3, 12e-3).asDiagonal();
  State st;
  st.cell = make_cell(h);
  const Vec3 l = 0.98 * (ri + rj) * Vec3(1, 0.2, -0.1).normalized();  // branch i -> j
  const Vec3 si(0.8, 0.5, 0.5);
  st.particles.add(0, ShapeKind::sphere, Vec3::Constant(ri), kRho, si, Quat::Identity());
  st.particles.add(1, ShapeKind::sphere, Vec3::Constant(rj), kRho, si + st.cell.h_inv * l, Quat::Identity());
  // j slides tangentially (perpendicular to l) for one evaluation.
  const Vec3 n = l.normalized();
  const Vec3 vt = Vec3(0, 0.3, 0.1) - Vec3(0, 0.3, 0.1).dot(n) * n;
  st.particles.v[1] = vt;
  evaluate_forces(model, st);
  ASSERT_EQ(st.pairs.size(), 1u);
  const Vec3 shear0 = stored_shear(st, 0);
  const Vec3i key0 = st.pairs.image[0];
  // Hand (SPEC 4): k_t = 8 G* sqrt(R_e delta), G* = G / (2 (2 - nu)), G = E / (2 (1 + nu)).
  const double gstar = kE / (2 * (1 + kNu)) / (2 * (2 - kNu));
  const double delta = ri + rj - l.norm();
  const double kt = 8 * gstar * std::sqrt(ri * rj / (ri + rj) * delta);
  EXPECT_LE((shear0 - (-kt * dt * vt)).norm(), 1e-12 * kt * dt * vt.norm());  // one rounding chain

  // At rest: nothing may change the spring, so after a forced rebuild it must be the same.
  st.particles.v[1].setZero();
  const long b0 = st.neighbor.builds;
  st.neighbor.valid = false;
  evaluate_forces(model, st);
  ASSERT_EQ(st.neighbor.builds, b0 + 1);
  ASSERT_EQ(st.pairs.size(), 1u);
  EXPECT_LE((stored_shear(st, 0) - shear0).norm(), 1e-12 * shear0.norm());

  // Translate both spheres so that j crosses the +x face (s_x > 1, unwrapped), then i as well;
  // each time force a rebuild at rest: same key, same spring.
  for (const double dx : {0.1, 0.2}) {
    for (Vec3& s : st.particles.s) s.x() += dx;
    st.neighbor.valid = false;
    evaluate_forces(model, st);
    ASSERT_EQ(st.pairs.size(), 1u);
    EXPECT_EQ(st.pairs.image[0], key0);
    // Rounding of the translated coordinates turns the normal by ~1e-15 rad: 1e-12 relative.
    EXPECT_LE((stored_shear(st, 0) - shear0).norm(), 1e-12 * shear0.norm());
  }
  EXPECT_GT(st.particles.s[1].x(), 1.0) << "j crossed the face";
  EXPECT_GT(st.particles.s[0].x(), 1.0) << "i crossed the face";
}

// SPEC 4, a whole sample: after loading the tangential springs of many contacts, translating the
// sample by an arbitrary vector (many particles cross faces) and forcing a rebuild at rest leaves
// every contact's spring unchanged under the same key.
TEST(NeighborHistory, SampleKeepsShearAfterFaceCrossingsAndRebuild) {
  const double dt = 1e-6;
  const Model model = test_model(kSkin, dt);
  State st = random_sample(300, 7.5, triclinic_shape(), 0.5, 5);
  Particles& p = st.particles;
  Random rng(17);
  for (std::size_t i = 0; i < p.size(); ++i) {
    p.v[i] = Vec3(2 * rng.uniform() - 1, 2 * rng.uniform() - 1, 2 * rng.uniform() - 1);
    p.omega[i] = 300 * Vec3(2 * rng.uniform() - 1, 2 * rng.uniform() - 1, 2 * rng.uniform() - 1);
    p.angmom.set(i, p.inertia[i].x() * p.omega[i]);
  }
  evaluate_forces(model, st);
  std::map<Key, Vec3> springs;
  double smax = 0;
  for (std::size_t k = 0; k < st.pairs.size(); ++k)
    if (st.pairs.overlap[k] > 0) {
      springs[{st.pairs.i[k], st.pairs.j[k], {st.pairs.image[k].x(), st.pairs.image[k].y(), st.pairs.image[k].z()}}] =
          stored_shear(st, k);
      smax = std::max(smax, stored_shear(st, k).norm());
    }
  ASSERT_GE(springs.size(), 100u);
  ASSERT_GT(smax, 0);

  for (std::size_t i = 0; i < p.size(); ++i) {
    p.v[i].setZero();
    p.omega[i].setZero();
    p.angmom.set(i, Vec3::Zero());
  }
  const Vec3 ds = st.cell.h_inv * Vec3(7.3e-3, -4.1e-3, 11.9e-3);
  int crossed = 0;
  for (Vec3& s : p.s) {
    const Vec3 before = s.array().floor().matrix();
    s += ds;
    crossed += (s.array().floor().matrix() != before) ? 1 : 0;
  }
  ASSERT_GE(crossed, 30) << "enough particles must cross a face";
  st.neighbor.valid = false;
  evaluate_forces(model, st);

  std::size_t kept = 0;
  for (std::size_t k = 0; k < st.pairs.size(); ++k) {
    const Key key{st.pairs.i[k], st.pairs.j[k], {st.pairs.image[k].x(), st.pairs.image[k].y(), st.pairs.image[k].z()}};
    const auto it = springs.find(key);
    if (it == springs.end()) continue;
    ++kept;
    // Rounding turns the normal by ~1e-14 rad at most; the spring is rotated by that much.
    EXPECT_LE((stored_shear(st, k) - it->second).norm(), 1e-12 * smax) << "pair " << key.i << "-" << key.j;
  }
  EXPECT_EQ(kept, springs.size()) << "every contact is still listed under its key";
}

// SPEC 4: Sample A polydispersity (equal-volume radii of the four classes of SPEC 9, ratio 7.5) at
// 8000 particles: the list equals brute force and holds a bounded number of pairs per particle.
// (Building it is fast; no timing is asserted.)
TEST(NeighborList, SampleASizesBoundedAndExact) {
  // SPEC 9 Sample A, (a, b = c) in mm and counts; spheres of the same volume.
  const std::array<std::pair<Vec3, int>, 4> table = {{{Vec3(1.2, 1.0, 1.0), 7284},
                                                      {Vec3(3.9, 3.0, 3.0), 498},
                                                      {Vec3(7.0, 5.0, 5.0), 150},
                                                      {Vec3(10.5, 7.0, 7.0), 68}}};
  std::vector<double> radii;
  double vsolid = 0;
  for (const auto& [ax, count] : table) {
    const double r = 1e-3 * std::cbrt(ax.prod());
    for (int c = 0; c < count; ++c) {
      radii.push_back(r);
      vsolid += 4.0 / 3.0 * pi * r * r * r;
    }
  }
  ASSERT_EQ(radii.size(), 8000u);
  const double side = std::cbrt(vsolid / 0.62);  // dense: solid fraction 0.62 (overlaps allowed)
  State st;
  st.cell = make_cell(Mat3::Identity() * side);
  Random rng(2024);
  for (std::size_t i = 0; i < radii.size(); ++i)
    st.particles.add(static_cast<std::uint32_t>(i), ShapeKind::sphere, Vec3::Constant(radii[i]), kRho,
                     Vec3(rng.uniform(), rng.uniform(), rng.uniform()), Quat::Identity());
  const double skin = 0.2 * radii.front();
  build_pairs(st.particles, st.cell, skin, st.pairs, st.neighbor);
  const double per_particle = 2.0 * static_cast<double>(st.pairs.size()) / 8000.0;
  std::printf("[ info ] Sample A sizes, 8000 spheres: %.2f pairs per particle\n", per_particle);
  EXPECT_LT(per_particle, 30.0);
  EXPECT_GT(per_particle, 1.0);

  // Brute force, one image per pair: the largest cut-off (2 R_max + skin) is below half the
  // smallest width (asserted), so -round(sj - si) is the only image that can be that close.
  const Mat3& h = st.cell.h;
  ASSERT_LT(2 * radii.back() + skin, 0.5 * min_width(h));
  const Particles& p = st.particles;
  std::set<Key> want;
  // Positions are in [0, 1) here, so each component of sj - si is in (-1, 1) and its nearest
  // image shift is -1, 0 or 1. A fractional component f of the branch bounds its length,
  // |b| >= |f| w (w = side here), which rejects most pairs exactly before the matrix product.
  auto nearest = [](double d) { return d > 0.5 ? -1.0 : (d < -0.5 ? 1.0 : 0.0); };
  for (std::size_t i = 0; i < p.size(); ++i) {
    ASSERT_TRUE((p.s[i].array() >= 0).all() && (p.s[i].array() < 1).all());
    for (std::size_t j = i + 1; j < p.size(); ++j) {
      const double cut = radii[i] + radii[j] + skin;
      const double reach = cut / side;
      const Vec3 d = p.s[j] - p.s[i];
      const Vec3 k(nearest(d.x()), nearest(d.y()), nearest(d.z()));
      const Vec3 f = d + k;
      if (std::abs(f.x()) >= reach || std::abs(f.y()) >= reach || std::abs(f.z()) >= reach) continue;
      if ((h * f).squaredNorm() < cut * cut) want.insert(make_key(i, j, k));
    }
  }
  const std::set<Key> got = engine_keys(st.pairs);
  EXPECT_EQ(got.size(), st.pairs.size());
  EXPECT_EQ(real_mismatches(got, want, p, h, skin), 0) << "engine " << got.size() << ", brute force " << want.size();
}

// SPEC 4, the skin test of a run of spheres: the motion bound that spares the pass over the
// particles restarts from each pass (twice the largest displacement it measured, plus the paths
// since), not from the build. Particles oscillate (their path grows faster than their
// displacement) and drift slowly, in a sheared triclinic cell, moved as step() moves them, until
// the pass calls for a rebuild: the bound never rules out a rebuild the pass would call for, the
// skin test answers as the pass does, and the bound still answers after the path since the build
// alone would have stopped it.
TEST(NeighborList, SkinTestBoundRestartsFromItsLastPass) {
  State st = random_sample(600, 7.5, triclinic_shape(), 0.55, 4);
  Particles& p = st.particles;
  NeighborState& ns = st.neighbor;
  build_pairs(p, st.cell, kSkin, st.pairs, ns);
  const double dt = 1e-6;
  Mat3 L;
  L << -1, 0.5, 0, 0, -1, 0, 0.3, 0, -1.5;
  st.cell.L = L * (1e-6 / dt);  // strain 1e-6 per step
  Random rng(7);
  const auto random_unit = [&] {
    return Vec3(2 * rng.uniform() - 1, 2 * rng.uniform() - 1, 2 * rng.uniform() - 1).normalized();
  };
  std::vector<Vec3> swing(p.size()), drift(p.size());
  for (std::size_t i = 0; i < p.size(); ++i) {
    swing[i] = (0.02 * kSkin / dt) * random_unit();  // 0.02 skin per step, turning back every 5 steps
    drift[i] = (0.002 * kSkin / dt) * random_unit();
  }
  int ruled_out = 0, ruled_out_past_build_bound = 0, step_of_rebuild = -1;
  for (int n = 0; n < 1000 && step_of_rebuild < 0; ++n) {
    const bool full = needs_rebuild(ns, p, st.cell, false);  // the pass alone, not recorded
    // The bound from the build: no pass recorded since (NeighborState::checked_displacement).
    NeighborState from_build = ns;
    from_build.checked_displacement = from_build.checked_fluctuation = from_build.checked_strain = 0;
    const bool build_bound = motion_bound_rules_out_rebuild(from_build, st.cell);
    if (motion_bound_rules_out_rebuild(ns, st.cell)) {
      ++ruled_out;
      ruled_out_past_build_bound += build_bound ? 0 : 1;
      ASSERT_FALSE(full) << "step " << n << ": the bound ruled out a rebuild the pass calls for";
    }
    ASSERT_EQ(needs_rebuild(ns, p, st.cell, true), full) << "step " << n;
    if (full) step_of_rebuild = n;
    // As step(): the cell moves, then the particles with the new cell.
    deform(st.cell, dt);
    ns.strain_path += dt * st.cell.L.norm();
    const double sign = (n / 5) % 2 == 0 ? 1.0 : -1.0;
    double vmax = 0;
    for (std::size_t i = 0; i < p.size(); ++i) {
      const Vec3 v = sign * swing[i] + drift[i];
      p.s[i] += dt * st.cell.h_inv * v;
      vmax = std::max(vmax, v.norm());
    }
    ns.fluctuation_path += 2 * dt * vmax;
  }
  std::printf("[ info ] rebuild called for at step %d; %d skin tests answered by the bound, %d of them past the "
              "bound from the build\n", step_of_rebuild, ruled_out, ruled_out_past_build_bound);
  EXPECT_GT(step_of_rebuild, 100) << "the drift reaches the skin";
  EXPECT_GT(ruled_out, step_of_rebuild / 2);
  EXPECT_GT(ruled_out_past_build_bound, step_of_rebuild / 4) << "the bound restarts from the passes";
}

// SPEC 3: a particle must stay smaller than half the smallest perpendicular cell width; with the
// Verlet skin the guard is 2 R_max + skin < w_min / 2. The width is the perpendicular one: a
// strongly skewed cell with 10 mm cell vectors but 2 mm between faces is refused.
TEST(NeighborCellSize, RefusesTooSmallCell) {
  const double r = 1e-3, skin = 0.1e-3;
  Particles p;
  p.add(0, ShapeKind::sphere, Vec3::Constant(r), kRho, Vec3(0.5, 0.5, 0.5), Quat::Identity());
  p.add(1, ShapeKind::sphere, Vec3::Constant(0.5 * r), kRho, Vec3(0.1, 0.2, 0.3), Quat::Identity());
  const double limit = 2 * (2 * r + skin);  // smallest allowed width (exclusive)
  auto cube = [](double w) { return make_cell(Mat3::Identity() * w); };
  EXPECT_THROW(check_cell_size(p, cube(0.99 * limit), skin), InputError);
  EXPECT_THROW(check_cell_size(p, cube(2 * (2 * r) + skin), skin), InputError);  // 2 d + skin: too small
  EXPECT_NO_THROW(check_cell_size(p, cube(1.01 * limit), skin));
  // Only the narrowest direction matters.
  EXPECT_THROW(check_cell_size(p, make_cell(Vec3(20e-3, 20e-3, 0.99 * limit).asDiagonal()), skin), InputError);

  // Skewed cell a = (10, 0, 0), b = (9.8, 2, 0), c = (0, 0, 10) mm: V = 200 mm^3,
  // |b x c| = |(20, -98, 0)| = 100.02, |c x a| = 100, |a x b| = 20, so widths are 2.0, 2.0, 10 mm.
  Mat3 skew;
  skew << 10e-3, 9.8e-3, 0,  //
      0, 2e-3, 0,            //
      0, 0, 10e-3;
  const double w_skew = 200.0 / std::sqrt(10004.0) * 1e-3;
  Particles small;  // 2 (2 r + skin) = 1.8 mm < 2 mm: fits
  small.add(0, ShapeKind::sphere, Vec3::Constant(0.4e-3), kRho, Vec3(0.5, 0.5, 0.5), Quat::Identity());
  ASSERT_LT(2 * (2 * 0.4e-3 + skin), w_skew);
  EXPECT_NO_THROW(check_cell_size(small, make_cell(skew), skin));
  Particles big;  // 2 (2 r + skin) = 2.2 mm > 2 mm although every cell vector is >= 10 mm
  big.add(0, ShapeKind::sphere, Vec3::Constant(0.5e-3), kRho, Vec3(0.5, 0.5, 0.5), Quat::Identity());
  ASSERT_GT(2 * (2 * 0.5e-3 + skin), w_skew);
  EXPECT_THROW(check_cell_size(big, make_cell(skew), skin), InputError);

  // The engine path refuses it too (build_pairs via evaluate_forces).
  State st;
  st.particles = big;
  st.cell = make_cell(skew);
  EXPECT_THROW(evaluate_forces(test_model(skin, 1e-6), st), InputError);
}

// SPEC 4: the broad phase is not quadratic at Sample A's size ratio 7.5. The distance checks of
// one build, per particle, stay the same when the sample grows 8-fold at the same size
// distribution and density (an O(N^2) search would do 8 times more per particle). The bound 1.5
// leaves room for boundary effects of the smaller cell.
TEST(NeighborList, DistanceChecksGrowLinearly) {
  const std::array<std::pair<double, int>, 4> table = {
      {{1.065e-3, 7284}, {3.275e-3, 498}, {5.595e-3, 150}, {8.015e-3, 68}}};  // SPEC 9 A, equal-volume radii
  auto checks_per_particle = [&](int scale_down) {
    std::vector<double> radii;
    double vsolid = 0;
    for (const auto& [r, count] : table)
      for (int c = 0; c < std::max(1, count / scale_down); ++c) {
        radii.push_back(r);
        vsolid += 4.0 / 3.0 * pi * r * r * r;
      }
    State st;
    st.cell = make_cell(Mat3::Identity() * std::cbrt(vsolid / 0.6));
    Random rng(11);
    for (std::size_t i = 0; i < radii.size(); ++i)
      st.particles.add(static_cast<std::uint32_t>(i), ShapeKind::sphere, Vec3::Constant(radii[i]), kRho,
                       Vec3(rng.uniform(), rng.uniform(), rng.uniform()), Quat::Identity());
    build_pairs(st.particles, st.cell, 0.2 * table[0].first, st.pairs, st.neighbor);
    return static_cast<double>(st.neighbor.distance_checks) / static_cast<double>(radii.size());
  };
  const double small = checks_per_particle(8), large = checks_per_particle(1);
  std::printf("[ info ] distance checks per particle: %.1f (1000 particles), %.1f (8000 particles)\n", small, large);
  EXPECT_GT(small, 0.0);
  EXPECT_LT(large / small, 1.5);
}

// Pairs proved apart are skipped by the force stage (NeighborState::moved, neighbor.hpp) only
// while they provably stay apart. A packing is shaken hard - random velocities and spins, the cell
// compressed and sheared - for 400 steps. Before every step, each pair the force stage is about to
// skip is apart by a fresh cold Perram-Wertheim test at the positions it will see; after every step the run has the same contacts and, within round-off, the same
// stress as a twin run that tests every pair.
static void check_skipping(State skipping, const char* what) {
  SCOPED_TRACE(what);
  Particles& p = skipping.particles;
  const double r_min = smallest_equiv_radius(p);
  const double dt = 0.2 * critical_time(Material{kRho, kE, kNu}, r_min);
  Model with_skip = test_model(0.2 * r_min, dt);
  with_skip.skip_apart_pairs = true;
  Model without_skip = with_skip;
  without_skip.skip_apart_pairs = false;

  Random rng(2026);
  const auto random_unit = [&] {
    return Vec3(2 * rng.uniform() - 1, 2 * rng.uniform() - 1, 2 * rng.uniform() - 1).normalized();
  };
  for (std::size_t i = 0; i < p.size(); ++i) {
    p.v[i] = 5e-5 * r_min / dt * random_unit();                        // 5e-5 R_min per step
    p.angmom.set(i, 1e-4 / dt * p.inertia[i].maxCoeff() * random_unit());  // ~1e-4 rad per step
    p.omega[i] = angular_velocity(p.q[i], p.inertia[i], p.angmom[i]);
  }
  Mat3 L;
  L << -1, 0.5, 0, 0, -1, 0, 0.3, 0, -1.5;
  skipping.cell.L = L * (2e-6 / dt);  // ~1e-3 strain over the run
  State testing_all = skipping;

  const int steps = 400;
  long skipped = 0, listed = 0, contacts_after_skip = 0, checked_steps = 0, ruled_out_by_bound = 0;
  std::set<std::size_t> ever_skipped;  // pair indices since the last build
  long builds = skipping.neighbor.builds;
  for (int n = 0; n < steps; ++n) {
    // A rebuild ruled out by the motion bound is ruled out by the full test too.
    if (motion_bound_rules_out_rebuild(skipping.neighbor, skipping.cell)) {
      ++ruled_out_by_bound;
      ASSERT_FALSE(needs_rebuild(skipping.neighbor, p, skipping.cell, false)) << "step " << n;
    }
    if (skipping.neighbor.valid && !needs_rebuild(skipping.neighbor, p, skipping.cell, false)) {
      ++checked_steps;
      const PairList& pairs = skipping.pairs;
      for (std::size_t k = 0; k < pairs.size(); ++k) {
        ++listed;
        if (!(skipping.neighbor.moved(pairs.i[k], pairs.j[k]) < pairs.apart_until[k])) continue;
        ++skipped;
        ever_skipped.insert(k);
        const std::uint32_t i = pairs.i[k], j = pairs.j[k];
        const Vec3 l = branch_vector(skipping.cell, p.s[i], p.s[j], pairs.image[k]);
        if (p.shape[i] == ShapeKind::sphere && p.shape[j] == ShapeKind::sphere) {
          // Skipped only in a run of spheres only (moved_any); exact test.
          ASSERT_FALSE(p.has_ellipsoids()) << "two spheres skipped in a run with ellipsoids";
          ASSERT_GE(l.norm(), p.bound_radius[i] + p.bound_radius[j])
              << "step " << n << ": pair " << i << "-" << j << " skipped while in contact";
          continue;
        }
        double cold = -1;
        ContactGeometry g;
        ASSERT_FALSE(ellipsoid_contact(l, p.semi_axes[i], p.q[i], p.semi_axes[j], p.q[j], cold, g))
            << "step " << n << ": pair " << i << "-" << j << " skipped while in contact (overlap " << g.overlap << ")";
      }
    }
    step(with_skip, skipping);
    step(without_skip, testing_all);
    if (skipping.neighbor.builds != builds) ever_skipped.clear(), builds = skipping.neighbor.builds;
    ASSERT_EQ(skipping.neighbor.builds, testing_all.neighbor.builds) << "step " << n;  // the same rebuilds
    ASSERT_EQ(skipping.pairs.size(), testing_all.pairs.size());
    for (std::size_t k = 0; k < skipping.pairs.size(); ++k) {
      ASSERT_EQ(skipping.pairs.overlap[k] > 0, testing_all.pairs.overlap[k] > 0) << "step " << n << ", pair " << k;
      if (skipping.pairs.overlap[k] > 0 && ever_skipped.count(k)) ++contacts_after_skip;
    }
    const double scale = testing_all.stress.norm();
    ASSERT_LT((skipping.stress - testing_all.stress).norm(), 1e-9 * scale) << "step " << n;
  }
  std::printf("[ info ] %s: %ld of %ld pair tests skipped over %ld steps without a rebuild; %ld contact-steps of "
              "pairs skipped earlier; %ld list builds; %ld skin tests answered by the motion bound\n",
              what, skipped, listed, checked_steps, contacts_after_skip, skipping.neighbor.builds, ruled_out_by_bound);
  EXPECT_GT(ruled_out_by_bound, steps / 10) << "the motion bound answers some skin tests";
  EXPECT_GT(checked_steps, steps / 2);
  EXPECT_GT(skipped, listed / 3) << "most apart pairs are skipped";
  EXPECT_GT(contacts_after_skip, 0) << "skipped pairs came back into contact: the skip expired in time";
}

TEST(NeighborSkip, ApartPairsSkippedOnlyWhileProvablyApart) {
  // The compacted paper-A-small packing: 2001 spheroids.
  const fs::path packing = fs::path(QSDEM_SOURCE_DIR) / "tests" / "golden" / "paper-A-small.packing";
  const State spheroids = read_packing(packing, kRho);
  check_skipping(spheroids, "spheroids");
  // Every other spheroid replaced by a sphere 3 % wider than its minor semi-axis: sphere-spheroid
  // pairs are skipped too (and sphere pairs always tested).
  State mixed;
  mixed.cell = spheroids.cell;
  const Particles& e = spheroids.particles;
  for (std::size_t i = 0; i < e.size(); ++i) {
    if (i % 2 == 0)
      mixed.particles.add(e.id[i], ShapeKind::ellipsoid, e.semi_axes[i], kRho, e.s[i], e.q[i]);
    else
      mixed.particles.add(e.id[i], ShapeKind::sphere, Vec3::Constant(1.03 * e.semi_axes[i].minCoeff()), kRho, e.s[i],
                          Quat::Identity());
  }
  check_skipping(mixed, "spheroids and spheres");
  // Spheres only (each 3 % wider than the spheroid's minor semi-axis): skipped by the largest
  // speed (NeighborState::moved_any) instead of per-particle paths.
  State spheres;
  spheres.cell = spheroids.cell;
  for (std::size_t i = 0; i < e.size(); ++i)
    spheres.particles.add(e.id[i], ShapeKind::sphere, Vec3::Constant(1.03 * e.semi_axes[i].minCoeff()), kRho, e.s[i],
                          Quat::Identity());
  check_skipping(spheres, "spheres");
}

// The history of the law about to run (adopt_history): a list that holds one of the same name and
// width keeps it (a law that shares it, e.g. Hertz-Mindlin with dashpots); any other is replaced
// by the law's released values, for every pair.
TEST(NeighborHistory, AdoptKeepsASharedHistoryAndReleasesAnother) {
  static constexpr HistoryLayout same{"tangential_force", 3, {5, 5, 5}, {}};
  static constexpr HistoryLayout other{"other", 2, {1, 2}, {}};
  PairList pairs;
  pairs.i = {0, 0, 1};
  pairs.j = {1, 2, 2};
  pairs.image.assign(3, Vec3i::Zero());
  adopt_history(pairs, HertzMindlin::history);  // a list no law has run on: released values
  EXPECT_EQ(pairs.history.values, std::vector<double>(9, 0.0));
  for (std::size_t k = 0; k < 9; ++k) pairs.history.values[k] = 0.5 + static_cast<double>(k);
  const std::vector<double> loaded = pairs.history.values;
  adopt_history(pairs, same);
  EXPECT_EQ(pairs.history.values, loaded);
  EXPECT_EQ(pairs.history.layout, &same);
  adopt_history(pairs, other);
  EXPECT_EQ(pairs.history.values, (std::vector<double>{1, 2, 1, 2, 1, 2}));
  EXPECT_EQ(pairs.history.layout, &other);
}
