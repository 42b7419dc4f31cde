// The periodic cell (SPEC 3) and what the contact stage sees through it (SPEC 4): contacts across
// faces, edges and corners, translation invariance, images of a sheared (triclinic) cell, cell
// deformation with the affine field, volume and perpendicular widths.
#include <gtest/gtest.h>
#include <omp.h>

#include <array>
#include <cmath>
#include <vector>

#include "qsdem/engine/cell.hpp"
#include "qsdem/engine/forces.hpp"
#include "qsdem/engine/model.hpp"
#include "qsdem/engine/particles.hpp"
#include "qsdem/engine/state.hpp"
#include "qsdem/engine/step.hpp"
#include "qsdem/run/generate.hpp"
#include "test_support.hpp"

using namespace qsdem;

namespace {

// SPEC 9 material, written out here so that the hand-computed Hertz forces do not reuse the code.
constexpr double kE = 7.8e10, kNu = 0.3, kRho = 2650;
constexpr double kEstar = kE / (2 * (1 - kNu * kNu));  // SPEC 4: E* = E / (2 (1 - nu^2))

Model test_model(double skin, double dt) {
  Model m;
  m.material = {kRho, kE, kNu};
  m.contact_law = make_contact_law(m.material, 0.5);
  m.dt = dt;
  m.skin = skin;
  return m;
}

Vec3 wrap01(const Vec3& s) { return s - Vec3(s.array().floor()); }

// Hertz normal force magnitude, SPEC 4: F_n = 4/3 E* sqrt(R_e) delta^(3/2), R_e = R1 R2/(R1+R2).
double hertz(double ri, double rj, double delta) {
  return 4.0 / 3.0 * kEstar * std::sqrt(ri * rj / (ri + rj)) * std::pow(delta, 1.5);
}

Mat3 orthorhombic() { return Vec3(10e-3, 12e-3, 14e-3).asDiagonal(); }

// A general triclinic cell: every off-diagonal term non-zero.
Mat3 triclinic(double scale) {
  Mat3 h;
  h << 1.0, 0.25, -0.2,  //
      0.1, 1.05, 0.3,    //
      -0.15, 0.05, 0.95;
  return scale * h;
}

// Simple shear of amount gamma: the top face (3rd cell vector) slides along x.
Mat3 simple_shear(double side, double gamma) {
  Mat3 h;
  h << 1, 0, gamma,  //
      0, 1, 0,       //
      0, 0, 1;
  return side * h;
}

struct Motion {
  Vec3 vi = Vec3::Zero(), vj = Vec3::Zero(), wi = Vec3::Zero(), wj = Vec3::Zero();
  Mat3 L = Mat3::Zero();
};

// Two spheres at fractional positions si, sj, with the given motion, after one force evaluation.
State evaluate_pair(const Mat3& h, double ri, double rj, const Vec3& si, const Vec3& sj, const Motion& mo,
                    const Model& model) {
  State st;
  st.cell = make_cell(h);
  st.cell.L = mo.L;
  Particles& p = st.particles;
  p.add(0, ShapeKind::sphere, Vec3::Constant(ri), kRho, si, Quat::Identity());
  p.add(1, ShapeKind::sphere, Vec3::Constant(rj), kRho, sj, Quat::Identity());
  p.v[0] = mo.vi;
  p.v[1] = mo.vj;
  p.omega[0] = mo.wi;
  p.omega[1] = mo.wj;
  p.angmom.set(0, p.inertia[0].x() * mo.wi);
  p.angmom.set(1, p.inertia[1].x() * mo.wj);
  evaluate_forces(model, st);
  return st;
}

// Random overlapping spheres of the given (radius, count) classes, largest first, uniform in the
// cell; a candidate is rejected if it overlaps any placed sphere by more than a quarter of the
// radii sum (keeps every contact normal well defined). Brute force over the 27 nearest images.
State random_overlapping(const Mat3& h, const std::vector<std::pair<double, int>>& classes,
                         std::uint64_t seed) {
  State st;
  st.cell = make_cell(h);
  Random rng(seed);
  std::uint32_t id = 0;
  for (const auto& [r, count] : classes) {
    for (int c = 0; c < count; ++c) {
      bool placed = false;
      for (int attempt = 0; attempt < 10000 && !placed; ++attempt) {
        const Vec3 s(rng.uniform(), rng.uniform(), rng.uniform());
        bool ok = true;
        for (std::size_t q = 0; q < st.particles.size() && ok; ++q) {
          const Vec3 d = st.particles.s[q] - s;
          const Vec3 k0 = (-d.array().round()).matrix();
          for (int a = -1; a <= 1 && ok; ++a)
            for (int b = -1; b <= 1 && ok; ++b)
              for (int e = -1; e <= 1 && ok; ++e)
                if ((h * (d + k0 + Vec3(a, b, e))).norm() < 0.75 * (r + st.particles.bound_radius[q])) ok = false;
        }
        if (ok) {
          st.particles.add(id++, ShapeKind::sphere, Vec3::Constant(r), kRho, s, Quat::Identity());
          placed = true;
        }
      }
      if (!placed) throw std::runtime_error("random_overlapping: could not place a sphere");
    }
  }
  return st;
}

// Random velocities, spins and a velocity gradient so that tangential forces and torques are
// non-zero (one evaluation from zero history gives F_t = -k_t dt v_t).
void add_random_motion(State& st, std::uint64_t seed) {
  Random rng(seed);
  auto u = [&rng] { return 2 * rng.uniform() - 1; };
  Particles& p = st.particles;
  for (std::size_t i = 0; i < p.size(); ++i) {
    p.v[i] = Vec3(u(), u(), u());
    p.omega[i] = 500 * Vec3(u(), u(), u());
    p.angmom.set(i, p.inertia[i].x() * p.omega[i]);
  }
  st.cell.L << 30, -20, 10,  //
      15, -40, 25,           //
      -10, 5, 20;
}

// Number of contacts (overlap > 0) whose two spheres, wrapped into the unit cell, touch only
// through a non-zero image. Because every contact is shorter than half the smallest width, each
// fractional component of its branch is below 1/2, so the image is -round(sj - si) exactly.
int crossing_contacts(const State& st) {
  const Particles& p = st.particles;
  int n = 0;
  for (std::size_t i = 0; i < p.size(); ++i)
    for (std::size_t j = i + 1; j < p.size(); ++j) {
      const Vec3 d = wrap01(p.s[j]) - wrap01(p.s[i]);
      const Vec3 k = (-d.array().round()).matrix();
      if ((st.cell.h * (d + k)).norm() < p.bound_radius[i] + p.bound_radius[j] && !k.isZero()) ++n;
    }
  return n;
}

int contacts(const State& st) {
  int n = 0;
  for (double d : st.pairs.overlap) n += d > 0 ? 1 : 0;
  return n;
}

// Per-particle scales for comparing resultants: the sum of the magnitudes of the contact forces
// on the particle (rounding in a resultant is relative to these, not to the possibly cancelling
// sum) and the same times the radius for torques.
void resultant_scales(const State& st, std::vector<double>& fscale, std::vector<double>& tscale) {
  const Particles& p = st.particles;
  fscale.assign(p.size(), 0.0);
  const std::vector<Vec3> force = contact_forces_by_pair(st);
  for (std::size_t k = 0; k < st.pairs.size(); ++k) {
    const double f = force[k].norm();
    fscale[st.pairs.i[k]] += f;
    fscale[st.pairs.j[k]] += f;
  }
  tscale.resize(p.size());
  for (std::size_t i = 0; i < p.size(); ++i) tscale[i] = fscale[i] * p.bound_radius[i];
}

// Runs a test on one OpenMP thread: these tests evaluate a few spheres many times, and on a busy
// machine each parallel region of the force stages then waits for a scheduler slice. Threading is
// not what they check.
using qsdem_test::SingleThread;

}  // namespace

// SPEC 3/4: a contact across any face, edge or corner of the periodic cell is the same contact as
// in the bulk: same force on both spheres, same torques. Checked in an orthorhombic and a
// triclinic cell, with translation, spin and an affine velocity gradient so that the tangential
// force (which depends on the branch through L l) is non-zero.
TEST(CellPeriodic, ContactAcrossFacesEdgesCornersEqualsBulk) {
  const SingleThread one_thread;
  const double ri = 1.0e-3, rj = 0.7e-3;
  const Model model = test_model(0.2e-3, 1e-6);
  Motion mo;
  mo.vi = Vec3(0.3, -0.8, 0.5);
  mo.vj = Vec3(-0.6, 0.2, 0.9);
  mo.wi = Vec3(300, -500, 200);
  mo.wj = Vec3(-100, 400, 600);
  mo.L << 50, 20, -30,  //
      -40, 60, 10,      //
      25, -15, -70;

  // Fractional directions of the branch and where sphere i sits: 6 faces, 2 edges, 2 corners.
  struct Case {
    const char* name;
    Vec3 dir;  // fractional direction of the branch from i to j
    Vec3 si;   // i next to the face(s) the branch crosses
  };
  const std::vector<Case> cases = {
      {"+x face", Vec3(1, 0.3, -0.2), Vec3(0.995, 0.5, 0.5)},
      {"-x face", Vec3(-1, -0.2, 0.3), Vec3(0.005, 0.5, 0.5)},
      {"+y face", Vec3(0.2, 1, 0.3), Vec3(0.5, 0.995, 0.5)},
      {"-y face", Vec3(-0.3, -1, 0.2), Vec3(0.5, 0.005, 0.5)},
      {"+z face", Vec3(0.3, -0.2, 1), Vec3(0.5, 0.5, 0.995)},
      {"-z face", Vec3(-0.2, 0.3, -1), Vec3(0.5, 0.5, 0.005)},
      {"+x+y edge", Vec3(1, 1, 0.2), Vec3(0.995, 0.995, 0.5)},
      {"-y+z edge", Vec3(0.1, -1, 1), Vec3(0.5, 0.005, 0.995)},
      {"+x+y+z corner", Vec3(1, 1, 1), Vec3(0.995, 0.995, 0.995)},
      {"+x-y-z corner", Vec3(1, -0.8, -1.2), Vec3(0.995, 0.005, 0.005)},
  };
  for (const Mat3& h : {orthorhombic(), triclinic(10e-3)}) {
    const Mat3 hinv = h.inverse();
    for (const Case& c : cases) {
      SCOPED_TRACE(c.name);
      // |l| = 0.97 (ri + rj): a real overlap of 3 % of the radii sum.
      const Vec3 l = 0.97 * (ri + rj) * (h * c.dir).normalized();
      const Vec3 sb(0.5, 0.5, 0.5);
      const State bulk = evaluate_pair(h, ri, rj, sb, sb + hinv * l, mo, model);
      const Vec3 sj_unwrapped = c.si + hinv * l;
      const Vec3 sj = wrap01(sj_unwrapped);
      // The configuration really crosses the face(s): j sits on the other side of the cell.
      ASSERT_GE((sj_unwrapped - sj).cwiseAbs().sum(), 1.0);
      const State edge = evaluate_pair(h, ri, rj, c.si, sj, mo, model);

      // The bulk force is Hertz along the branch (SPEC 4): its normal part is 4/3 E* sqrt(Re) d^1.5.
      const Vec3 fb = bulk.particles.force[1];
      const double delta = ri + rj - l.norm();
      EXPECT_NEAR(fb.dot(l.normalized()), hertz(ri, rj, delta), 1e-12 * hertz(ri, rj, delta));
      // The tangential part must be present, or the test would not check L l and the spins.
      ASSERT_GT((fb - fb.dot(l.normalized()) * l.normalized()).norm(), 1e-3 * fb.norm());

      // Rounding: the branch differs by ~1e-16 of the cell size (~1e-15 of |l|), amplified by
      // |l|/delta ~ 30 in the overlap: 1e-12 relative leaves two orders of margin.
      const double tol_f = 1e-12 * fb.norm();
      const double tol_t = 1e-12 * fb.norm() * (ri + rj);
      EXPECT_LE((edge.particles.force[1] - fb).norm(), tol_f);
      EXPECT_LE((edge.particles.force[0] - bulk.particles.force[0]).norm(), tol_f);
      EXPECT_LE((edge.particles.force[0] + edge.particles.force[1]).norm(), tol_f);  // action = reaction
      EXPECT_LE((edge.particles.torque[0] - bulk.particles.torque[0]).norm(), tol_t);
      EXPECT_LE((edge.particles.torque[1] - bulk.particles.torque[1]).norm(), tol_t);
    }
  }
}

// SPEC 3: the periodic system has no origin. Translating the whole sample by a cell vector or by
// any vector changes no force or torque. Random overlapping spheres of size ratio 7.5, many
// contacts across the boundary, tangential forces from random motion; orthorhombic and triclinic.
TEST(CellPeriodic, TranslationInvariance) {
  // (radius, count): 150 spheres, radii 1 to 7.5 mm.
  const std::vector<std::pair<double, int>> classes = {{7.5e-3, 4}, {5e-3, 8}, {3e-3, 18}, {1e-3, 120}};
  const Model model = test_model(0.2e-3, 1e-6);
  const std::array<Mat3, 2> cells = {Mat3(Vec3::Constant(34e-3).asDiagonal()), triclinic(36e-3)};
  for (std::size_t c = 0; c < cells.size(); ++c) {
    SCOPED_TRACE(c == 0 ? "cubic" : "triclinic");
    const Mat3& h = cells[c];
    State ref = random_overlapping(h, classes, 7 + c);
    add_random_motion(ref, 11 + c);
    evaluate_forces(model, ref);
    const int nc = contacts(ref);
    const int crossing = crossing_contacts(ref);
    ASSERT_GE(nc, 60);
    ASSERT_GE(crossing, 15) << "too few contacts across the boundary to test anything";
    std::vector<double> fscale, tscale;
    resultant_scales(ref, fscale, tscale);

    const Vec3 t_cart(13.7e-3, -21.1e-3, 7.9e-3);
    const std::vector<std::pair<const char*, Vec3>> shifts = {
        {"cell vector a", Vec3(1, 0, 0)},
        {"cell vector b", Vec3(0, 1, 0)},
        {"cell vector c", Vec3(0, 0, 1)},
        {"a - 2b + 3c", Vec3(1, -2, 3)},
        {"arbitrary", Vec3(h.inverse() * t_cart)},
        {"arbitrary, small", Vec3(h.inverse() * Vec3(0.3e-3, 0.9e-3, -0.4e-3))},
    };
    int moved_across = 0;  // contacts whose crossing status changed under some translation
    for (const auto& [name, ds] : shifts) {
      SCOPED_TRACE(name);
      State moved;
      moved.cell = ref.cell;
      moved.particles = ref.particles;
      for (Vec3& s : moved.particles.s) s += ds;
      evaluate_forces(model, moved);
      EXPECT_EQ(contacts(moved), nc);
      moved_across += std::abs(crossing_contacts(moved) - crossing);
      // Rounding: fractional positions of order 1-3 carry ~1e-16 absolute error, i.e. ~1e-14 of
      // the branch; overlaps are >= ~1e-3 of the branch here, so ~1e-11 at worst in one contact
      // force relative to the contact forces on the particle: 1e-10 is the tolerance the brief
      // asks for and still catches any wrong image (an O(1) change).
      for (std::size_t i = 0; i < ref.particles.size(); ++i) {
        EXPECT_LE((moved.particles.force[i] - ref.particles.force[i]).norm(), 1e-10 * fscale[i]) << "particle " << i;
        EXPECT_LE((moved.particles.torque[i] - ref.particles.torque[i]).norm(), 1e-10 * tscale[i])
            << "particle " << i;
      }
    }
    EXPECT_GT(moved_across, 0) << "the arbitrary translations must move contacts across the boundary";
  }
}

// SPEC 3: in a sheared cell the periodic image of j is x_j + h k, with h's off-diagonal terms.
// Two spheres touch only through one image; the test enumerates the images by hand, finds the
// single k that overlaps and checks the engine's branch, overlap and Hertz force against it.
TEST(CellPeriodic, TriclinicImagesByHand) {
  const SingleThread one_thread;
  const double ri = 1.2e-3, rj = 0.8e-3;
  const Model model = test_model(0.2e-3, 1e-6);
  struct Case {
    const char* name;
    Mat3 h;
    Vec3 si;
    Vec3 dir;  // Cartesian direction of the intended branch
  };
  const std::vector<Case> cases = {
      // Through the sheared top face (k_z != 0): the image is offset by gamma L along x.
      {"simple shear 0.3, top face", simple_shear(10e-3, 0.3), Vec3(0.3, 0.5, 0.985), Vec3(0.3, 0.2, 1.0)},
      {"simple shear 0.3, top-left edge", simple_shear(10e-3, 0.3), Vec3(0.01, 0.5, 0.985), Vec3(-0.8, 0.1, 0.9)},
      {"triclinic, corner", triclinic(12e-3), Vec3(0.985, 0.015, 0.985), Vec3(1.0, -1.0, 1.0)},
      {"triclinic, face", triclinic(12e-3), Vec3(0.5, 0.99, 0.4), Vec3(0.1, 1.0, -0.3)},
  };
  for (const Case& c : cases) {
    SCOPED_TRACE(c.name);
    const Mat3& h = c.h;
    const Vec3 b_design = 0.95 * (ri + rj) * c.dir.normalized();
    const Vec3 sj = wrap01(c.si + h.inverse() * b_design);

    // Hand: Cartesian centres, then every image x_j + h k - x_i for k in {-2..2}^3.
    const Vec3 xi = h * c.si, xj = h * sj;
    int found = 0;
    Vec3i k_hand = Vec3i::Zero();
    Vec3 b_hand = Vec3::Zero();
    for (int a = -2; a <= 2; ++a)
      for (int bb = -2; bb <= 2; ++bb)
        for (int e = -2; e <= 2; ++e) {
          const Vec3 b = xj + h * Vec3(a, bb, e) - xi;
          if (b.norm() < ri + rj) {
            ++found;
            k_hand = Vec3i(a, bb, e);
            b_hand = b;
          }
        }
    ASSERT_EQ(found, 1) << "exactly one image touches";
    ASSERT_FALSE(k_hand.isZero()) << "the contact exists only through an image";
    ASSERT_LE((b_hand - b_design).norm(), 1e-12 * b_design.norm());
    // |b| is below half the smallest width, so every fractional component of b is below 1/2 and
    // the fractional minimum image (cell.hpp) must be the same k.
    ASSERT_LT(b_hand.norm(), 0.5 * make_cell(h).widths().minCoeff());
    EXPECT_EQ(minimum_image(sj - c.si), k_hand);
    const double delta = ri + rj - b_hand.norm();
    const Vec3 f_hand = hertz(ri, rj, delta) * b_hand.normalized();  // at rest: no tangential force

    // Also with j's fractional coordinate unwrapped by a lattice vector (SPEC 3: s never wrapped).
    for (const Vec3& shift : {Vec3(0, 0, 0), Vec3(2, -1, 3)}) {
      const State st = evaluate_pair(h, ri, rj, c.si, sj + shift, Motion{}, model);
      int in_contact = 0;
      const std::vector<Vec3> force = contact_forces_by_pair(st);
      for (std::size_t k = 0; k < st.pairs.size(); ++k) {
        if (st.pairs.overlap[k] <= 0) continue;
        ++in_contact;
        ASSERT_EQ(st.pairs.i[k], 0u);
        ASSERT_EQ(st.pairs.j[k], 1u);
        // The image key is in unwrapped coordinates: k_hand minus the shift of j.
        EXPECT_EQ(st.pairs.image[k], Vec3i(k_hand - shift.cast<int>()));
        const Vec3 l = branch_vector(st.cell, st.particles.s[0], st.particles.s[1], st.pairs.image[k]);
        // Rounding of fractional coordinates of order 1-4: ~1e-15 of |b|.
        EXPECT_LE((l - b_hand).norm(), 1e-12 * b_hand.norm());
        // Overlap is 5 % of the radii sum: the branch's 1e-15 becomes ~2e-14 of delta.
        EXPECT_NEAR(st.pairs.overlap[k], delta, 1e-12 * delta);
        EXPECT_LE((force[k] - f_hand).norm(), 1e-12 * f_hand.norm());
      }
      EXPECT_EQ(in_contact, 1);
      EXPECT_LE((st.particles.force[1] - f_hand).norm(), 1e-12 * f_hand.norm());
      EXPECT_LE((st.particles.force[0] + f_hand).norm(), 1e-12 * f_hand.norm());
    }
  }
}

// SPEC 3: dh/dt = L h, one step h(t+dt) = (I + dt L) h; the cell's inverse and volume follow.
TEST(CellDeform, MatrixFollowsVelocityGradient) {
  const Mat3 h0 = triclinic(20e-3);
  Mat3 L;
  L << -0.4, 0.3, 0.1,  //
      0.05, 0.2, -0.25,  //
      0.15, -0.1, 0.35;
  const double dt = 1e-2;
  Cell cell = make_cell(h0);
  cell.L = L;
  deform(cell, dt);

  // Hand: h1_rc = h0_rc + dt sum_m L_rm h0_mc.
  Mat3 h1;
  for (int r = 0; r < 3; ++r)
    for (int c = 0; c < 3; ++c) {
      double sum = 0;
      for (int m = 0; m < 3; ++m) sum += L(r, m) * h0(m, c);
      h1(r, c) = h0(r, c) + dt * sum;
    }
  // A product of O(1e-2) numbers rounded once or twice: 1e-15 of the cell size.
  EXPECT_LE((cell.h - h1).cwiseAbs().maxCoeff(), 1e-15 * 20e-3);
  EXPECT_LE((cell.h * cell.h_inv - Mat3::Identity()).cwiseAbs().maxCoeff(), 1e-13);

  // Volume by the triple product a . (b x c), written out.
  auto det = [](const Mat3& m) {
    return m(0, 0) * (m(1, 1) * m(2, 2) - m(1, 2) * m(2, 1)) - m(0, 1) * (m(1, 0) * m(2, 2) - m(1, 2) * m(2, 0)) +
           m(0, 2) * (m(1, 0) * m(2, 1) - m(1, 1) * m(2, 0));
  };
  const Mat3 F = Mat3::Identity() + dt * L;
  EXPECT_NEAR(cell.volume, det(F) * det(h0), 1e-13 * det(h1));

  // A particle at rest keeps s, so its Cartesian position is moved by the affine field:
  // x(t+dt) = x + dt L x.
  const Vec3 s(0.3, -0.7, 1.4);  // unwrapped on purpose
  const Vec3 x0 = h0 * s;
  const Vec3 x1 = cell.to_cartesian(s);
  EXPECT_LE((x1 - (x0 + dt * L * x0)).norm(), 1e-14 * x0.norm());
}

// SPEC 3 homogeneous formulation through a whole step(): with no contacts and no damping a particle
// moves as x(t+dt) = (I + dt L) x(t) + dt v, where v is its fluctuation velocity; at v = 0 its
// fractional coordinate does not change at all. L comes from strain-rate controlled axes.
TEST(CellDeform, StepMovesParticlesWithAffineField) {
  const SingleThread one_thread;
  const double side = 20e-3;
  const Mat3 h0 = simple_shear(side, 0.3);
  Model model = test_model(0.2e-3, 1e-4);
  const Vec3 rates(0.5, -0.3, 1.0);  // engineering strain rates, compression positive (1/s)
  for (int k = 0; k < 3; ++k) {
    ResolvedControl& ac = model.control[static_cast<std::size_t>(k)];
    ac.kind = ControlKind::strain_rate;
    ac.value = rates[k];
    ac.reference_length = h0(k, k);  // H0 = h_kk at e = 0 now, so L_kk = -rate (SPEC 3, servo.hpp)
  }
  State st;
  st.cell = make_cell(h0);
  const double r = 1e-3;
  // Far apart (no contact): centres 0.5 cell apart in every fractional direction.
  st.particles.add(0, ShapeKind::sphere, Vec3::Constant(r), kRho, Vec3(0.2, 0.3, 0.1), Quat::Identity());
  st.particles.add(1, ShapeKind::sphere, Vec3::Constant(r), kRho, Vec3(0.7, 0.8, 1.6), Quat::Identity());
  const Vec3 v1(0.02, -0.01, 0.03);
  st.particles.v[1] = v1;
  const Vec3 s0 = st.particles.s[0];
  const Vec3 x0 = h0 * st.particles.s[0], x1 = h0 * st.particles.s[1];

  step(model, st);

  const Mat3 L = Vec3(-rates).asDiagonal();
  ASSERT_EQ(st.pairs.size(), 0u);
  EXPECT_TRUE(st.particles.force[0].isZero() && st.particles.force[1].isZero());
  EXPECT_LE((st.cell.L - L).cwiseAbs().maxCoeff(), 1e-12);
  const double dt = model.dt;
  // Hand: the deformed cell and the affine field.
  const Mat3 h1 = (Mat3::Identity() + dt * L) * h0;
  EXPECT_LE((st.cell.h - h1).cwiseAbs().maxCoeff(), 1e-15 * side);
  EXPECT_EQ(st.particles.s[0], s0) << "a particle at rest keeps its fractional coordinate exactly";
  // Rounding of a few operations on positions of order 1e-2 m: 1e-15 of the cell size.
  EXPECT_LE((st.cell.to_cartesian(st.particles.s[0]) - (x0 + dt * L * x0)).norm(), 1e-15 * side);
  EXPECT_LE((st.cell.to_cartesian(st.particles.s[1]) - (x1 + dt * L * x1 + dt * v1)).norm(), 1e-15 * side);
}

// SPEC 3: V = det h and the perpendicular widths V / |a_j x a_k|, checked against closed forms.
TEST(CellGeometry, VolumeAndWidths) {
  // Upper-triangular (LAMMPS-style) cell a = (lx,0,0), b = (xy,ly,0), c = (xz,yz,lz):
  //   V = lx ly lz; b x c = (ly lz, -xy lz, xy yz - ly xz); c x a = (0, lz lx, -yz lx); a x b = (0,0,lx ly).
  const double lx = 10e-3, ly = 12e-3, lz = 14e-3, xy = 3e-3, xz = -2e-3, yz = 4e-3;
  Mat3 h;
  h << lx, xy, xz,  //
      0, ly, yz,    //
      0, 0, lz;
  const Cell c = make_cell(h);
  const double v = lx * ly * lz;
  const double wa = v / std::sqrt(ly * lz * ly * lz + xy * lz * xy * lz + (xy * yz - ly * xz) * (xy * yz - ly * xz));
  const double wb = ly * lz / std::sqrt(lz * lz + yz * yz);
  const double wc = lz;
  // Exact formulas evaluated in double: a few ulps.
  EXPECT_NEAR(c.volume, v, 1e-14 * v);
  const Vec3 w = c.widths();
  EXPECT_NEAR(w.x(), wa, 1e-14 * wa);
  EXPECT_NEAR(w.y(), wb, 1e-14 * wb);
  EXPECT_NEAR(w.z(), wc, 1e-14 * wc);

  // Simple shear gamma: the faces normal to x get closer, L / sqrt(1 + gamma^2); volume unchanged.
  const double side = 10e-3, gamma = 0.3;
  const Cell s = make_cell(simple_shear(side, gamma));
  EXPECT_NEAR(s.volume, side * side * side, 1e-14 * side * side * side);
  EXPECT_NEAR(s.widths().x(), side / std::sqrt(1 + gamma * gamma), 1e-14 * side);
  EXPECT_NEAR(s.widths().y(), side, 1e-14 * side);
  EXPECT_NEAR(s.widths().z(), side, 1e-14 * side);

  // A rigid rotation of the cell changes neither the volume nor the widths.
  const Mat3 rot = Eigen::AngleAxisd(0.7, Vec3(1, -2, 0.5).normalized()).toRotationMatrix();
  const Cell rc = make_cell(rot * h);
  EXPECT_NEAR(rc.volume, v, 1e-13 * v);
  EXPECT_NEAR(rc.widths().x(), wa, 1e-13 * wa);
  EXPECT_NEAR(rc.widths().y(), wb, 1e-13 * wb);
  EXPECT_NEAR(rc.widths().z(), wc, 1e-13 * wc);
}
