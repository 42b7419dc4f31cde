#include "reference_forces.hpp"

#include <cmath>
#include <variant>

#include "qsdem/engine/contact/laws.hpp"
#include "qsdem/engine/ellipsoid_contact.hpp"

namespace qsdem {
namespace {

// Where pair k's bodies touch (SPEC 4): exact for two spheres, Perram-Wertheim otherwise
// (warm-started from and updating `lambda`). False when they do not overlap.
bool narrow_phase(const Particles& p, std::uint32_t i, std::uint32_t j, const Vec3& l, double& lambda,
                  ContactGeometry& g) {
  if (p.shape[i] == ShapeKind::sphere && p.shape[j] == ShapeKind::sphere) {
    const double reach = p.bound_radius[i] + p.bound_radius[j];
    if (!(l.squaredNorm() < reach * reach)) return false;
    g = sphere_sphere(l, p.bound_radius[i], p.bound_radius[j]);
    return g.overlap > 0;
  }
  return ellipsoid_contact(l, p.semi_axes[i], p.q[i], p.semi_axes[j], p.q[j], lambda, g);
}

template <class Law>
ReferenceForces run(const Law& law, const Model& model, const State& state) {
  const Particles& p = state.particles;
  const PairList& pairs = state.pairs;
  const Cell& cell = state.cell;
  constexpr int width = Law::history.width;
  ReferenceForces out;
  out.force.assign(p.size(), Vec3::Zero());
  out.torque.assign(p.size(), Vec3::Zero());
  out.contact_stiffness.assign(p.size(), 0.0);
  out.contact_rotational_stiffness.assign(p.size(), 0.0);
  PairList adopted;  // the law's history, as the fast stage adopts it (adopt_history)
  adopted.i = pairs.i;
  adopted.history = pairs.history;
  adopt_history(adopted, Law::history);
  out.history = adopted.history.values;
  out.pw_lambda = pairs.pw_lambda;
  Mat3 sum = Mat3::Zero();
  for (std::size_t k = 0; k < pairs.size(); ++k) {
    const std::uint32_t i = pairs.i[k], j = pairs.j[k];
    double* const history = out.history.data() + width * k;
    const Vec3 l = branch_vector(cell, p.s[i], p.s[j], pairs.image[k]);
    ContactGeometry g;
    if (!narrow_phase(p, i, j, l, out.pw_lambda[k], g)) {
      for (int m = 0; m < width; ++m) history[m] = Law::history.released[m];  // released
      continue;
    }
    const Vec3 v = p.v[j] + p.omega[j].cross(g.arm_j) - p.v[i] - p.omega[i].cross(g.arm_i) + cell.L * l;
    const double mass = Law::needs_masses ? p.mass[i] * p.mass[j] / (p.mass[i] + p.mass[j]) : 0.0;
    const Vec3 spin = Law::needs_spins ? Vec3(p.omega[j] - p.omega[i]) : Vec3::Zero();
    const ContactOutput o = evaluate_contact(law, g, v, spin, mass, model.dt, history);
    const Vec3 f(o.fx, o.fy, o.fz), extra = Law::has_torque ? Vec3(o.tx, o.ty, o.tz) : Vec3::Zero();
    const Vec3 torque_j = g.arm_j.cross(f) + extra, torque_i = g.arm_i.cross(Vec3(-f)) - extra;
    out.force[j] += f;
    out.force[i] -= f;
    out.torque[j] += torque_j;
    out.torque[i] += torque_i;
    sum += f * l.transpose();  // Love-Weber (SPEC 7)
    // The affine stiffness and viscosity of the servo (servo.hpp): diagonal, and the shears 12,
    // 13, 23 of a pure shear D_ab = D_ba.
    const Vec3 n2 = g.normal.cwiseProduct(g.normal);
    constexpr int shear_axes[3][2] = {{0, 1}, {0, 2}, {1, 2}};
    for (int q = 0; q < 3; ++q) {
      const int a = shear_axes[q][0], b = shear_axes[q][1];
      const double nn = n2[a] * n2[b], half = 0.5 * (n2[a] + n2[b]);
      out.affine_stiffness[q] += (o.kn * n2[q] + o.kt * (1 - n2[q])) * (l[q] * l[q]);
      out.shear_stiffness[q] += l.squaredNorm() * (2 * o.kn * nn + o.kt * (half - 2 * nn));
      if constexpr (Law::has_dashpots) {
        out.affine_viscosity[q] += (o.cn * n2[q] + o.ct * (1 - n2[q])) * (l[q] * l[q]);
        out.shear_viscosity[q] += l.squaredNorm() * (2 * o.cn * nn + o.ct * (half - 2 * nn));
      }
    }
    out.elastic_energy += o.energy;
    out.contact_stiffness[i] += o.kn;
    out.contact_stiffness[j] += o.kn;
    out.contact_rotational_stiffness[i] += o.kt * g.arm_i.squaredNorm();
    out.contact_rotational_stiffness[j] += o.kt * g.arm_j.squaredNorm();
    out.contacts.push_back({k, g.overlap, f, torque_i, torque_j, o});
  }
  const double volume = cell.volume;
  out.stress = 0.5 * (sum + sum.transpose()) / volume;  // f on j and l from i to j: compression positive
  out.affine_stiffness /= volume;
  out.shear_stiffness /= volume;
  out.affine_viscosity /= volume;
  out.shear_viscosity /= volume;
  return out;
}

}  // namespace

ReferenceForces reference_contact_forces(const Model& model, const State& state) {
  return std::visit([&](const auto& l) { return run(l, model, state); }, contact_law_of(model));
}

}  // namespace qsdem
