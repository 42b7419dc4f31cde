// The state of a Simulation as numpy copies, one row per particle in the order of the particle ids
// (the engine reorders particles in memory), and the contacts of the last force evaluation.
#include <pybind11/stl.h>

#include <algorithm>
#include <array>
#include <cmath>
#include <numeric>
#include <string_view>
#include <type_traits>

#include "qsdem/engine/contact/geometry.hpp"
#include "qsdem/engine/ellipsoid_contact.hpp"
#include "qsdem/engine/forces.hpp"
#include "qsdem/engine/measures.hpp"
#include "qsdem/run/controller.hpp"
#include "simulation.hpp"

namespace qsdem::python {

namespace {

// The particle indices in the order of their ids.
std::vector<std::size_t> by_id(const Particles& p) {
  std::vector<std::size_t> order(p.size());
  std::iota(order.begin(), order.end(), 0);
  std::sort(order.begin(), order.end(), [&](std::size_t a, std::size_t b) { return p.id[a] < p.id[b]; });
  return order;
}

// An (N, width) array of value(i) for the particles i in the order of their ids.
template <class F>
py::array_t<double> per_particle(const Particles& p, int width, F value) {
  const auto order = by_id(p);
  py::array_t<double> out({static_cast<py::ssize_t>(order.size()), static_cast<py::ssize_t>(width)});
  auto r = out.mutable_unchecked<2>();
  for (std::size_t k = 0; k < order.size(); ++k) {
    const auto row = value(order[k]);
    for (int c = 0; c < width; ++c) r(static_cast<py::ssize_t>(k), c) = row[c];
  }
  return out;
}

// Where pair k's bodies touch at the current positions (SPEC 4), as the force stage finds it:
// exact for two spheres, Perram-Wertheim otherwise (from the pair's warm start). False when apart.
bool contact_geometry(const State& st, std::size_t k, const Vec3& l, ContactGeometry& g) {
  const Particles& P = st.particles;
  const std::uint32_t i = st.pairs.i[k], j = st.pairs.j[k];
  if (P.shape[i] == ShapeKind::sphere && P.shape[j] == ShapeKind::sphere) {
    g = sphere_sphere(l, P.bound_radius[i], P.bound_radius[j]);
    return g.overlap > 0;
  }
  double lambda = k < st.pairs.pw_lambda.size() ? st.pairs.pw_lambda[k] : std::nan("");
  return ellipsoid_contact(l, P.semi_axes[i], P.q[i], P.semi_axes[j], P.q[j], lambda, g);
}

}  // namespace

py::array_t<double> matrix(const Mat3& a) {
  py::array_t<double> out({3, 3});
  auto r = out.mutable_unchecked<2>();
  for (int i = 0; i < 3; ++i)
    for (int j = 0; j < 3; ++j) r(i, j) = a(i, j);
  return out;
}

// Every member of Measures (for_each_measure): a tensor as a 3x3 array, a vector as a list of
// three, fabric values NaN where undefined (SPEC 7.1).
py::dict measures_dict(const Measures& m) {
  py::dict d;
  for_each_measure(m, [&](std::string_view name, const auto& v) {
    using V = std::remove_cvref_t<decltype(v)>;
    const py::str key(name.data(), name.size());
    if constexpr (std::is_same_v<V, Mat3>)
      d[key] = matrix(v);
    else if constexpr (std::is_same_v<V, Vec3>)
      d[key] = std::vector<double>{v[0], v[1], v[2]};
    else
      d[key] = v;
  });
  return d;
}

py::dict controls_dict(const PhaseControls& c, const Phase& phase) {
  py::dict d;
  for (std::size_t k = 0; k < component_count; ++k)
    d[component_names[k]] = py::make_tuple(control_kind_name(c.component[k].kind), c.component[k].value);
  d["max_strain_rate"] = c.max_strain_rate;
  d["rate_factor"] = c.rate_factor;
  d["friction"] = phase.friction;
  d["damping_ratio"] = phase.damping.ratio;
  return d;
}

py::dict record_dict(const PhaseRecord& r) {
  const double rows = static_cast<double>(std::max(1L, r.rows));
  py::dict d;
  d["steps"] = r.steps, d["rows"] = r.rows, d["wall_s"] = r.wall_s;
  d["peak_phi_deg"] = r.peak_phi_deg, d["peak_phi_e1"] = r.peak_phi_e1;
  d["final_e1"] = r.final_e1, d["final_ev"] = r.final_ev;
  d["mean_ufr"] = r.ufr / rows, d["mean_iuf"] = r.iuf / rows, d["mean_imom"] = r.imom / rows;
  return d;
}

// The pairs with overlap > 0 at the last force evaluation: ids, image, overlap and the force on j
// of that evaluation; the normal (from i to j) and the contact point of the geometry at the current
// positions, the ones the next force evaluation starts from; fn and ft the parts of the force
// along and across that normal.
py::dict contacts_dict(const State& st) {
  const PairList& pl = st.pairs;
  const Particles& P = st.particles;
  std::vector<std::size_t> k_of;
  if (pl.overlap.size() == pl.size())
    for (std::size_t k = 0; k < pl.size(); ++k)
      if (pl.overlap[k] > 0) k_of.push_back(k);
  const std::vector<Vec3> f = k_of.empty() ? std::vector<Vec3>{} : contact_forces_by_pair(st);
  const auto n = static_cast<py::ssize_t>(k_of.size());
  const py::ssize_t three = 3;
  py::array_t<std::int64_t> ids_i(n), ids_j(n), image({n, three});
  py::array_t<double> overlap(n), fn(n), ft(n), normal({n, three}), point({n, three}), force({n, three});
  auto ii = ids_i.mutable_unchecked<1>(), jj = ids_j.mutable_unchecked<1>();
  auto im = image.mutable_unchecked<2>();
  auto ov = overlap.mutable_unchecked<1>(), fnr = fn.mutable_unchecked<1>(), ftr = ft.mutable_unchecked<1>();
  auto nr = normal.mutable_unchecked<2>(), pr = point.mutable_unchecked<2>(), fr = force.mutable_unchecked<2>();
  for (py::ssize_t c = 0; c < n; ++c) {
    const std::size_t k = k_of[static_cast<std::size_t>(c)];
    const std::uint32_t i = pl.i[k], j = pl.j[k];
    const Vec3 xi = st.cell.h * P.s[i];
    const Vec3 l = st.cell.h * (P.s[j] + pl.image[k].cast<double>() - P.s[i]);
    ContactGeometry g{};
    // Apart now though in contact at the last evaluation: the direction of the branch, the point
    // on it midway between the surfaces' bounding spheres.
    if (!contact_geometry(st, k, l, g)) {
      g.normal = l.normalized();
      g.arm_i = 0.5 * (l.norm() + P.bound_radius[i] - P.bound_radius[j]) * g.normal;
    }
    const Vec3& fk = f[k];
    const double along = fk.dot(g.normal);
    ii(c) = P.id[i], jj(c) = P.id[j], ov(c) = pl.overlap[k];
    fnr(c) = along, ftr(c) = (fk - along * g.normal).norm();
    for (int a = 0; a < 3; ++a) {
      im(c, a) = pl.image[k][a], nr(c, a) = g.normal[a], fr(c, a) = fk[a];
      pr(c, a) = xi[a] + g.arm_i[a];
    }
  }
  py::dict d;
  d["i"] = ids_i, d["j"] = ids_j, d["image"] = image, d["overlap"] = overlap, d["point"] = point;
  d["normal"] = normal, d["force"] = force, d["fn"] = fn, d["ft"] = ft;
  return d;
}

void bind_state(py::class_<Simulation>& c) {
  c.def_property_readonly("ids", [](const Simulation& s) {
     const Particles& p = s.state().particles;
     const auto order = by_id(p);
     py::array_t<std::int64_t> out(static_cast<py::ssize_t>(order.size()));
     auto r = out.mutable_unchecked<1>();
     for (std::size_t k = 0; k < order.size(); ++k) r(static_cast<py::ssize_t>(k)) = p.id[order[k]];
     return out;
   })
      .def_property_readonly("positions",
                             [](const Simulation& s) {
                               const State& st = s.state();
                               return per_particle(st.particles, 3,
                                                   [&](std::size_t i) { return Vec3(st.cell.h * st.particles.s[i]); });
                             })
      .def_property_readonly("orientations",
                             [](const Simulation& s) {
                               const Particles& p = s.state().particles;
                               return per_particle(p, 4, [&](std::size_t i) {
                                 return std::array<double, 4>{p.q[i].w(), p.q[i].x(), p.q[i].y(), p.q[i].z()};
                               });
                             })
      .def_property_readonly("masses", [](const Simulation& s) {
        const Particles& p = s.state().particles;
        return per_particle(p, 1, [&](std::size_t i) { return std::array<double, 1>{p.mass[i]}; }).attr("ravel")();
      });
  // The per-particle vectors kept as they are reported.
  const std::array<std::pair<const char*, std::vector<Vec3> Particles::*>, 5> vectors{{
      {"semi_axes", &Particles::semi_axes},
      {"velocities", &Particles::v},
      {"spins", &Particles::omega},
      {"forces", &Particles::force},
      {"moments", &Particles::torque},
  }};
  for (const auto& [name, member] : vectors)
    c.def_property_readonly(name, [member = member](const Simulation& s) {
      const Particles& p = s.state().particles;
      return per_particle(p, 3, [&](std::size_t i) { return (p.*member)[i]; });
    });
  c.def_property_readonly("cell", [](const Simulation& s) { return matrix(s.state().cell.h); })
      .def_property_readonly("stress", [](const Simulation& s) { return matrix(s.state().stress); })
      .def("measures", [](const Simulation& s) { return measures_dict(measure(s.state())); })
      .def("contacts", [](const Simulation& s) { return contacts_dict(s.state()); });
}

}  // namespace qsdem::python
