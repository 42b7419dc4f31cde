#include "qsdem/forces.hpp"

#include <fmt/format.h>

#include <algorithm>
#include <cmath>

#include "qsdem/contact_law.hpp"
#include "qsdem/ellipsoid_contact.hpp"

namespace qsdem {
void compute_contact_forces(const Model& model, State& state) {
  Particles& p = state.particles;
  PairList& pairs = state.pairs;
  const Cell& cell = state.cell;
  const HertzMindlin law{model.material.effective_modulus(), model.material.effective_shear_modulus(),
                         model.friction};
  const double dt = model.dt;
  const std::size_t np = pairs.size();
  const std::size_t n = p.size();
  const std::size_t nblocks = pairs.block_first.size() - 1;
  state.blocks.resize(nblocks);
  // Shape matrices once per particle (each takes part in several pairs); only when some particle
  // is an ellipsoid, so a sphere run pays nothing.
  if (p.has_ellipsoids()) {
    state.shapes.resize(n);
#pragma omp parallel for schedule(static) if (n > parallel_threshold)
    for (std::size_t a = 0; a < n; ++a) state.shapes[a] = ellipsoid_shape(p.semi_axes[a], p.q[a]);
  }
  const EllipsoidShape* shapes = state.shapes.data();
  // Skipping provably apart pairs needs the motion bounds of the current list (neighbor.hpp).
  const NeighborState& ns = state.neighbor;
  const bool skip_apart = model.skip_apart_pairs && ns.surface_path.size() == n && pairs.apart_until.size() == np;

  // Each block owns whole particles as the i end of their pairs (sorted by i): it writes their
  // i-side resultants itself; gather_resultants adds the j ends. Static: each thread keeps the
  // same particles (and their data in its cache) from step to step; dynamic was measured slower
  // on spheres (2 threads, contact stage 484 vs 413 us/step).
#pragma omp parallel for schedule(static) if (np > parallel_threshold)
  for (std::size_t b = 0; b < nblocks; ++b) {
    ForceBlock acc;
    const std::uint32_t a0 = pairs.block_first[b], a1 = pairs.block_first[b + 1];
    for (std::uint32_t a = a0; a < a1; ++a) {
      p.force[a] = Vec3::Zero();
      p.torque[a] = Vec3::Zero();
    }
    // One flat loop over the block's pairs, summing into p.force[i] directly (a loop per particle,
    // ~2-4 pairs each, mispredicts its exit: the sphere contact stage measured 7 % slower).
    for (std::uint32_t k = pairs.first_i[a0]; k < pairs.first_i[a1]; ++k) {
      const std::uint32_t i = pairs.i[k], j = pairs.j[k];
      const bool spheres = p.shape[i] == ShapeKind::sphere && p.shape[j] == ShapeKind::sphere;
      // Still provably apart (its overlap is 0 and its spring released since the test that proved
      // it). Not for two spheres: their direct test is as cheap as the skip test.
      if (!spheres && skip_apart && ns.moved(i, j) < pairs.apart_until[k]) continue;
      ++acc.narrow_tests;
      const Vec3 l = branch_vector(cell, p.s[i], p.s[j], pairs.image[k]);
      // Narrow phase (SPEC 4): exact for spheres; Perram-Wertheim for any pair with an ellipsoid.
      ContactGeometry g;
      bool touching;
      if (spheres) {
        const double ri = p.bound_radius[i], rj = p.bound_radius[j];
        const double d2 = l.squaredNorm();
        touching = d2 < (ri + rj) * (ri + rj);  // most listed pairs are apart: keep that path short
        if (touching)
          g = sphere_sphere(l, ri, rj);
        else
          pairs.overlap[k] = ri + rj - std::sqrt(d2);
      } else {
        EllipsoidContactStats stats;
        touching = ellipsoid_contact(l, shapes[i], shapes[j], pairs.pw_lambda[k], g, stats);
        if (!touching) {
          pairs.overlap[k] = 0;  // apart (the contact function gives no gap)
          // Not tested again until the surfaces may have closed the proven gap; the margin covers
          // the round-off of mu (1e-9 of the minor axes, far above it).
          const double gap = stats.gap_bound - 1e-9 * (shapes[i].minor + shapes[j].minor);
          if (skip_apart && gap > 0) pairs.apart_until[k] = ns.moved(i, j) + gap;
        }
      }
      if (!touching) {
        if (!pairs.shear[k].isZero()) pairs.shear[k].setZero();  // contact lost: spring released
        continue;  // force and torque are read only where overlap > 0
      }
      pairs.overlap[k] = g.overlap;
      const double ratio = g.overlap / std::min(p.equiv_radius[i], p.equiv_radius[j]);
      if (ratio > acc.max_overlap) {
        acc.max_overlap = ratio;
        acc.max_overlap_pair = k;
      }
      // Velocity of j's contact point relative to i's, with the affine part L l (SPEC 3).
      const Vec3 vrel = p.v[j] + p.omega[j].cross(g.arm_j) - p.v[i] - p.omega[i].cross(g.arm_i) + cell.L * l;
      const ContactForce cf = law.evaluate(g, vrel, dt, pairs.shear[k]);
      pairs.force[k] = cf.force;
      pairs.torque_j[k] = g.arm_j.cross(cf.force);  // SPEC 4: (x_c - x_j) x F
      p.force[i] -= cf.force;
      p.torque[i] += g.arm_i.cross(-cf.force);
      acc.stress_sum.noalias() += cf.force * l.transpose();  // Love-Weber (SPEC 7)
      const Vec3 n2 = g.normal.cwiseProduct(g.normal);
      acc.stiffness_sum += (cf.normal_stiffness * n2 + cf.tangential_stiffness * (Vec3::Ones() - n2))
                             .cwiseProduct(l.cwiseProduct(l));
      // Affine pure shear D_ab = D_ba (servo.hpp): 2 k_n n_a^2 n_b^2 + k_t ((n_a^2 + n_b^2)/2 - 2 n_a^2 n_b^2).
      const Vec3 nn(n2.x() * n2.y(), n2.x() * n2.z(), n2.y() * n2.z());
      const Vec3 half(0.5 * (n2.x() + n2.y()), 0.5 * (n2.x() + n2.z()), 0.5 * (n2.y() + n2.z()));
      acc.shear_stiffness_sum +=
          l.squaredNorm() * (2 * cf.normal_stiffness * nn + cf.tangential_stiffness * (half - 2 * nn));
    }
    state.blocks[b] = acc;
  }

  Mat3 sum = Mat3::Zero();
  Vec3 stiff = Vec3::Zero(), shear_stiff = Vec3::Zero();
  state.max_overlap = 0;
  state.narrow_tests = 0;
  for (const ForceBlock& b : state.blocks) {
    sum += b.stress_sum;
    stiff += b.stiffness_sum;
    shear_stiff += b.shear_stiffness_sum;
    state.narrow_tests += b.narrow_tests;
    if (b.max_overlap > state.max_overlap) {
      state.max_overlap = b.max_overlap;
      state.max_overlap_pair = b.max_overlap_pair;
    }
  }
  const double v = cell.volume;
  state.stress = 0.5 * (sum + sum.transpose()) / v;  // f on j and l from i to j: compression positive
  state.affine_stiffness = stiff / v;
  state.shear_stiffness = shear_stiff / v;
  state.stress_volume = v;
  state.stress_h = cell.h;
}

void gather_resultants(State& state) {
  Particles& p = state.particles;
  const PairList& pairs = state.pairs;
  const std::size_t n = p.size();
  // Adds the j ends to the i-side sums the force stage wrote, in pair order.
#pragma omp parallel for schedule(static) if (n > parallel_threshold)
  for (std::size_t a = 0; a < n; ++a) {
    Vec3 f = p.force[a], t = p.torque[a];
    for (std::uint32_t e = pairs.first_j[a]; e < pairs.first_j[a + 1]; ++e) {
      const std::uint32_t k = pairs.incident_j[e];
      if (pairs.overlap[k] <= 0) continue;  // not a contact: its force slots are stale
      f += pairs.force[k];
      t += pairs.torque_j[k];
    }
    p.force[a] = f;
    p.torque[a] = t;
  }
}

}  // namespace qsdem
