// Invariance of the whole engine under rigid motions of the whole sample (issue: ellipsoids).
// A periodic sample of overlapping spheroids, ellipsoids and spheres (aspect up to 2, size ratio
// 5), moving and spinning so that tangential forces build up, is stepped as it is, translated by
// an arbitrary vector, and rotated by a random rotation R (cell h -> R h, orientations q -> R q,
// velocities, angular momenta, the velocity gradient L -> R L R^T). After every step the forces
// and torques of the moved copies equal R times those of the original, overlaps and tangential
// histories correspond, and the stress rotates as R sigma R^T.
#include <gtest/gtest.h>
#include <omp.h>

#include <vector>

#include "qsdem/engine/contact/hertz_mindlin.hpp"
#include "qsdem/engine/forces.hpp"
#include "qsdem/engine/measures.hpp"
#include "qsdem/engine/model.hpp"
#include "qsdem/engine/step.hpp"
#include "qsdem/run/generate.hpp"

using namespace qsdem;

namespace {

// The tangential force on j that pair k stores (the Hertz-Mindlin history).
Vec3 stored_shear(const State& st, std::size_t k) { return HertzMindlin::tangential_force(st.pairs.history.of(k)); }

Model invariance_model(const State& st) {
  Model m;
  m.material = {2650, 7.8e10, 0.3};
  m.contact_law = make_contact_law(m.material, 0.5);
  m.r_min = smallest_equiv_radius(st.particles);
  m.critical_time = critical_time(m.material, m.r_min);
  m.dt = 0.32 * m.critical_time;
  m.damping = resolve_damping("nd", {0.005, m.material.wave_speed(), m.r_min});
  m.skin = 0.2 * m.r_min;
  return m;
}

// Random overlapping particles in a triclinic cell, with random velocities and spins.
State random_sample(std::uint64_t seed) {
  Random rng(seed);
  State st;
  Mat3 h;
  h << 30e-3, 3e-3, -2e-3,  //
      1e-3, 28e-3, 2.5e-3,   //
      -1.5e-3, 0.5e-3, 32e-3;
  st.cell = make_cell(h);
  const std::vector<Vec3> shapes = {Vec3(1.5e-3, 1e-3, 1e-3), Vec3(2e-3, 1.5e-3, 1e-3), Vec3::Constant(1.2e-3),
                                    Vec3(5e-3, 3.5e-3, 3.5e-3), Vec3(1.3e-3, 1.3e-3, 0.8e-3)};
  for (std::uint32_t id = 0; id < 260; ++id) {
    const Vec3& ax = shapes[id % shapes.size()];
    const ShapeKind kind = ax.x() == ax.z() ? ShapeKind::sphere : ShapeKind::ellipsoid;
    st.particles.add(id, kind, ax, 2650, Vec3(rng.uniform(), rng.uniform(), rng.uniform()), rng.orientation());
    st.particles.v.back() = 0.05 * Vec3(rng.uniform() - 0.5, rng.uniform() - 0.5, rng.uniform() - 0.5);
    st.particles.angmom.set(
        id, st.particles.inertia.back().x() * 50 * Vec3(rng.uniform() - 0.5, rng.uniform() - 0.5, rng.uniform() - 0.5));
  }
  return st;
}

State rotated(const State& ref, const Mat3& R) {
  State st;
  st.cell = make_cell(R * ref.cell.h);
  st.cell.L = R * ref.cell.L * R.transpose();
  st.particles = ref.particles;
  const Quat qr(R);
  for (std::size_t i = 0; i < st.particles.size(); ++i) {
    st.particles.q.set(i, (qr * ref.particles.q[i]).normalized());
    st.particles.v[i] = R * ref.particles.v[i];
    st.particles.angmom.set(i, R * ref.particles.angmom[i]);
  }
  return st;
}

}  // namespace

TEST(Invariance, RigidRotationAndTranslationOfTheWholeSample) {
  const int saved = omp_get_max_threads();
  omp_set_num_threads(1);
  State ref = random_sample(5);
  Model model = invariance_model(ref);
  ref.cell.L << 0, 3.0, 0, 0, -2.0, 1.0, 0, 0, 1.5;  // a general velocity gradient (1/s)
  for (std::size_t i = 0; i < ref.particles.size(); ++i)
    ref.particles.omega[i] = angular_velocity(ref.particles.q[i], ref.particles.inertia[i], ref.particles.angmom[i]);
  assign_damping(model, ref.particles);

  const Mat3 R = Quat(0.3, -0.5, 0.7, 0.4).normalized().toRotationMatrix();
  State rot = rotated(ref, R);
  State moved = ref;
  for (Vec3& s : moved.particles.s) s += moved.cell.h_inv * Vec3(7.3e-3, -11.9e-3, 4.1e-3);
  for (State* st : {&rot, &moved})
    for (std::size_t i = 0; i < st->particles.size(); ++i)
      st->particles.omega[i] = angular_velocity(st->particles.q[i], st->particles.inertia[i], st->particles.angmom[i]);

  int ellipsoid_contacts = 0, with_shear = 0;
  for (int n = 0; n < 20; ++n) {
    step(model, ref);
    step(model, rot);
    step(model, moved);
    ASSERT_EQ(rot.pairs.size(), ref.pairs.size());
    ASSERT_EQ(moved.pairs.size(), ref.pairs.size());
    // Scale of the contact forces on each particle: resultants can cancel, so compare to it.
    std::vector<double> fscale(ref.particles.size(), 0.0), tscale(ref.particles.size(), 0.0);
    const std::vector<Vec3> ref_force = contact_forces_by_pair(ref);
    for (std::size_t k = 0; k < ref.pairs.size(); ++k) {
      if (ref.pairs.overlap[k] <= 0) continue;
      const double f = ref_force[k].norm();
      for (std::uint32_t a : {ref.pairs.i[k], ref.pairs.j[k]}) {
        fscale[a] += f;
        tscale[a] += f * ref.particles.bound_radius[a];
      }
      if (n == 19) {
        ellipsoid_contacts += (ref.particles.shape[ref.pairs.i[k]] == ShapeKind::ellipsoid ||
                               ref.particles.shape[ref.pairs.j[k]] == ShapeKind::ellipsoid);
        with_shear += stored_shear(ref, k).norm() > 1e-3 * f;
      }
    }
    for (std::size_t k = 0; k < ref.pairs.size(); ++k) {
      // Same pair keys (the sample's own images are unchanged by rigid motions of the sample).
      ASSERT_EQ(rot.pairs.i[k], ref.pairs.i[k]);
      ASSERT_EQ(rot.pairs.j[k], ref.pairs.j[k]);
      if (ref.pairs.overlap[k] <= 0) continue;
      // Overlaps: relative rounding of branch vectors (~1e-16 of 30 mm) over overlaps >= ~1e-7 m.
      EXPECT_NEAR(rot.pairs.overlap[k], ref.pairs.overlap[k], 1e-12) << "pair " << k;
      EXPECT_NEAR(moved.pairs.overlap[k], ref.pairs.overlap[k], 1e-12) << "pair " << k;
      EXPECT_LE((stored_shear(rot, k) - R * stored_shear(ref, k)).norm(), 1e-8 * ref_force[k].norm() + 1e-12);
    }
    // Resultants: tolerance 1e-8 of the contact forces acting on the particle (the narrow phase
    // of ellipsoids resolves the normal to ~1e-14, amplified by overlaps down to ~1e-6 of b).
    for (std::size_t i = 0; i < ref.particles.size(); ++i) {
      EXPECT_LE((rot.particles.force[i] - R * ref.particles.force[i]).norm(), 1e-8 * fscale[i] + 1e-15) << i;
      EXPECT_LE((rot.particles.torque[i] - R * ref.particles.torque[i]).norm(), 1e-8 * tscale[i] + 1e-18) << i;
      EXPECT_LE((moved.particles.force[i] - ref.particles.force[i]).norm(), 1e-8 * fscale[i] + 1e-15) << i;
      EXPECT_LE((moved.particles.torque[i] - ref.particles.torque[i]).norm(), 1e-8 * tscale[i] + 1e-18) << i;
    }
    const double smax = ref.stress.cwiseAbs().maxCoeff();
    EXPECT_LE((rot.stress - R * ref.stress * R.transpose()).cwiseAbs().maxCoeff(), 1e-8 * smax);
    EXPECT_LE((moved.stress - ref.stress).cwiseAbs().maxCoeff(), 1e-8 * smax);
  }
  const Measures a = measure(ref), b = measure(rot);
  EXPECT_NEAR(a.imom, b.imom, 1e-8 * a.imom);
  EXPECT_NEAR(a.ufr, b.ufr, 1e-8 * a.ufr);
  std::printf("[ info ] %d ellipsoid contacts, %d with tangential force, IMom %.3g\n", ellipsoid_contacts, with_shear,
              a.imom);
  EXPECT_GE(ellipsoid_contacts, 50) << "the test must exercise the ellipsoid narrow phase";
  EXPECT_GE(with_shear, 50) << "and the tangential history";
  omp_set_num_threads(saved);
}
