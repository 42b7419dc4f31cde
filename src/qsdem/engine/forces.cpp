#include "qsdem/engine/forces.hpp"

#include <omp.h>

#include <algorithm>
#include <array>
#include <cmath>
#include <fstream>
#include <string>
#include <stdexcept>

#include "qsdem/engine/clones.hpp"
#include "qsdem/engine/contact/laws.hpp"
#include "qsdem/engine/ellipsoid_contact.hpp"

namespace qsdem {
namespace {

struct EnergySums {
  double elastic = 0, slip = 0, viscous = 0, stiffness = 0;
};

// The law as the driver runs it, with what it sums besides forces and stress: each particle's
// contact stiffnesses (State::contact_stiffness) and the energy terms (State::energy). Each choice is
// its own instantiation, so that a phase that does not read the sums does not pay for them.
template <class Law, bool Stiffness, bool Energy>
struct DrivenLaw : Law {
  static constexpr bool sums_stiffness = Stiffness, sums_energy = Energy;
};
template <class Law>
constexpr bool sums_contact_stiffness = Law::sums_stiffness;
template <class Law>
constexpr bool sums_energy = Law::sums_energy;

// Inputs of the force stage's blocks, read-only except the pair history and results.
template <class Law>
struct ForceInputs {
  const Law& law;
  double dt;
  const Cell& cell;
  const EllipsoidShape* shapes;  // per particle, when some particle is an ellipsoid
  const NeighborState& ns;
  bool skip_apart;               // skip pairs provably apart (neighbor.hpp)
  bool prefetch_j_ends;          // fetch the j ends' data ahead (Model::prefetch_j_ends)
  Schedule& schedule;            // owners of the update region (close_block_contacts)
  double* contact_stiffness = nullptr;             // State's, for a law that sums stiffnesses
  double* contact_rotational_stiffness = nullptr;
};

// The size of the largest cache of CPU 0 from sysfs (in a virtual machine, sysconf gives the
// host's total of every L3), else 32 MiB.
long last_level_cache_bytes() {
  long largest = 0;
  for (int index = 0;; ++index) {
    std::ifstream in("/sys/devices/system/cpu/cpu0/cache/index" + std::to_string(index) + "/size");
    long size = 0;
    char unit = 0;
    if (!(in >> size)) break;
    in >> unit;
    largest = std::max(largest, size * (unit == 'K' ? 1l << 10 : unit == 'M' ? 1l << 20 : 1l));
  }
  return largest > 0 ? largest : 32l << 20;
}

// The pair driver: written once, instantiated per contact law (contact/law.hpp).
//
// The contacts of a chunk of pairs (SPEC 4), in lanes (structure of arrays): `add` takes a
// contact's pair, velocities and history; its geometry is either the lanes' own (`sphere_geometry`
// computes the spheres') or, in force_block, in the slot `slot[a]` of the Perram-Wertheim batch's
// geometry; `evaluate_contacts` runs the relative velocity, the law and the contact's torques and
// sum terms on all lanes at once (vector lanes: one contact is a long chain of dependent
// operations); `commit_contacts` writes the results in pair order (the order of every sum, as one
// contact at a time: the same bits).
template <class Law>
struct ContactLanes {
  static constexpr int width = Law::history.width;  // the law's history per contact
  // 16 contacts at a time: the lanes' ~60 arrays stay within a third of the L1 cache.
  static constexpr int capacity = 16;
  // Each array's length: 3 cache lines (an odd number), so that lane a of the arrays falls in
  // different sets of the L1 cache (arrays a power of two apart share a few sets).
  static constexpr int stride = capacity + 8;
  int size = 0;
  std::uint32_t pair[stride], first[stride], second[stride];  // k, i, j
  // In: branch l, geometry (the lanes' own, or its slot in another's), the spheres' |l| and radii
  // (for sphere_geometry), velocities and spins of i and j, the affine velocity L l, the history.
  double lx[stride], ly[stride], lz[stride];
  ContactGeometrySlots<stride> geometry;
  std::int64_t slot[stride];  // 64 bits: GCC runs the loads by slot in vector lanes only with 64-bit indices
  double distance[stride], ri[stride], rj[stride];
  double r_min[stride];  // min(R_i, R_j), for the largest overlap ratio
  double vix[stride], viy[stride], viz[stride], vjx[stride], vjy[stride], vjz[stride];
  double wix[stride], wiy[stride], wiz[stride], wjx[stride], wjy[stride], wjz[stride];
  double ux[stride], uy[stride], uz[stride], history[width][stride];
  // Out: the force on j, the torques about j's and i's centres (and the new history), and the
  // contact's terms of the block's sums: f l^T by row, the stiffnesses of the servo (servo.hpp).
  double fx[stride], fy[stride], fz[stride], tjx[stride], tjy[stride], tjz[stride];
  double tix[stride], tiy[stride], tiz[stride];
  double stress[9][stride], stiffness[3][stride], shear_stiffness[3][stride];
  double mass[Law::needs_masses ? stride : 1];  // m* (laws with needs_masses)
  // The contact's terms of the viscosity sums (laws with has_dashpots).
  static constexpr int viscous_stride = Law::has_dashpots ? stride : 1;
  double viscosity[3][viscous_stride], shear_viscosity[3][viscous_stride];
  // k_n, k_t |arm_i|^2 and k_t |arm_j|^2 (a law that sums stiffnesses).
  static constexpr int stiffness_stride = sums_contact_stiffness<Law> ? stride : 1;
  double kn[stiffness_stride], kt_arm_i[stiffness_stride], kt_arm_j[stiffness_stride];
  // The contact's stored energy and the step's slip and dashpot dissipation (a law that sums energy).
  static constexpr int energy_stride = sums_energy<Law> ? stride : 1;
  double elastic[energy_stride], slip_work[energy_stride], viscous_work[energy_stride];
  double stiffness_work[energy_stride], previous_overlap[energy_stride];

  // Appends the contact of pair k (i, j) with branch l; returns its lane.
  [[gnu::always_inline]] int add(const ForceInputs<Law>& in, const Particles& p, const PairList& pairs,
                                 std::uint32_t k, std::uint32_t i, std::uint32_t j, const Vec3& l) {
    const int a = size++;
    pair[a] = k, first[a] = i, second[a] = j;
    lx[a] = l.x(), ly[a] = l.y(), lz[a] = l.z();
    const Vec3 &vi = p.v[i], &vj = p.v[j], &wi = p.omega[i], &wj = p.omega[j];
    vix[a] = vi.x(), viy[a] = vi.y(), viz[a] = vi.z(), vjx[a] = vj.x(), vjy[a] = vj.y(), vjz[a] = vj.z();
    wix[a] = wi.x(), wiy[a] = wi.y(), wiz[a] = wi.z(), wjx[a] = wj.x(), wjy[a] = wj.y(), wjz[a] = wj.z();
    const Vec3 u = in.cell.L * l;  // the affine field's part (SPEC 3), in Eigen's order of sums
    ux[a] = u.x(), uy[a] = u.y(), uz[a] = u.z();
    const double* const h = pairs.history.values.data() + width * k;
    for (int c = 0; c < width; ++c) history[c][a] = h[c];
    if constexpr (Law::needs_masses) mass[a] = p.mass[i] * p.mass[j] / (p.mass[i] + p.mass[j]);
    if constexpr (sums_energy<Law>) previous_overlap[a] = pairs.overlap.size() == pairs.size() ? pairs.overlap[k] : 0.0;
    r_min[a] = std::min(p.equiv_radius[i], p.equiv_radius[j]);
    return a;
  }
  void set_spheres(int a, double d, double radius_i, double radius_j) {
    distance[a] = d, ri[a] = radius_i, rj[a] = radius_j;
  }
};

// sphere_sphere (contact/geometry.hpp) on every lane.
template <class Law>
QSDEM_CLONES_WIDE void sphere_geometry(ContactLanes<Law>& c) {
  auto& g = c.geometry;
#pragma omp simd
  for (int a = 0; a < c.size; ++a)
    sphere_sphere(c.lx[a], c.ly[a], c.lz[a], c.distance[a], c.ri[a], c.rj[a], g.nx[a], g.ny[a], g.nz[a], g.overlap[a],
                  g.aix[a], g.aiy[a], g.aiz[a], g.ajx[a], g.ajy[a], g.ajz[a], g.radius[a]);
}

// Where the lanes' geometry is: their own, lane by lane, or `slots`, at the slots they name (BySlot).
// The own geometry as c's member: through a reference of its own the lanes' loops are longer.
template <bool BySlot, class Law, class Slots>
[[gnu::always_inline]] inline const auto& lanes_geometry(const ContactLanes<Law>& c, const Slots& slots) {
  if constexpr (BySlot) return slots;
  else return c.geometry;
}

// On every lane: the velocity of j's contact point relative to i's (SPEC 3), the law, the torques
// (x_c - x_j) x F on j and (x_c - x_i) x (-F) on i (SPEC 4) with the law's own, and the contact's
// terms of the sums. Built for AVX-512, AVX2 and the x86-64 baseline, chosen at load time; no FMA,
// so the same bits.
template <bool BySlot, class Law, class Slots>
QSDEM_CLONES_WIDE void evaluate_contacts(const Law& law, double dt, ContactLanes<Law>& c, const Slots& slots) {
  const auto& g = lanes_geometry<BySlot>(c, slots);
#pragma omp simd
  for (int a = 0; a < c.size; ++a) {
    const std::int64_t s = BySlot ? c.slot[a] : a;
    const double nx = g.nx[s], ny = g.ny[s], nz = g.nz[s];
    const double aix = g.aix[s], aiy = g.aiy[s], aiz = g.aiz[s], ajx = g.ajx[s], ajy = g.ajy[s], ajz = g.ajz[s];
    // v_j + w_j x arm_j - v_i - w_i x arm_i + L l, summed left to right as Eigen does.
    const double wjx = c.wjx[a], wjy = c.wjy[a], wjz = c.wjz[a], wix = c.wix[a], wiy = c.wiy[a], wiz = c.wiz[a];
    ContactInput in;
    in.nx = nx, in.ny = ny, in.nz = nz, in.overlap = g.overlap[s], in.radius = g.radius[s];
    in.vx = c.vjx[a] + (wjy * ajz - wjz * ajy) - c.vix[a] - (wiy * aiz - wiz * aiy) + c.ux[a];
    in.vy = c.vjy[a] + (wjz * ajx - wjx * ajz) - c.viy[a] - (wiz * aix - wix * aiz) + c.uy[a];
    in.vz = c.vjz[a] + (wjx * ajy - wjy * ajx) - c.viz[a] - (wix * aiy - wiy * aix) + c.uz[a];
    in.wx = Law::needs_spins ? wjx - wix : 0.0, in.wy = Law::needs_spins ? wjy - wiy : 0.0;
    in.wz = Law::needs_spins ? wjz - wiz : 0.0;
    if constexpr (Law::needs_masses) in.mass = c.mass[a];
    else in.mass = 0;
    if constexpr (sums_energy<Law>) in.previous_overlap = c.previous_overlap[a];
    else in.previous_overlap = 0;
    ContactOutput out;
    law.evaluate(in, dt, HistoryView{&c.history[0][a], ContactLanes<Law>::stride}, out);
    const double fx = out.fx, fy = out.fy, fz = out.fz, kn = out.kn, kt = out.kt;
    c.fx[a] = fx, c.fy[a] = fy, c.fz[a] = fz;
    if constexpr (sums_energy<Law>) {
      c.elastic[a] = out.energy, c.slip_work[a] = out.slip_work, c.viscous_work[a] = out.viscous_work;
      c.stiffness_work[a] = out.stiffness_work;
    }
    if constexpr (sums_contact_stiffness<Law>) {
      c.kn[a] = kn;
      c.kt_arm_i[a] = kt * ((aix * aix + aiy * aiy) + aiz * aiz);
      c.kt_arm_j[a] = kt * ((ajx * ajx + ajy * ajy) + ajz * ajz);
    }
    // Love-Weber f l^T (SPEC 7).
    const double l[3] = {c.lx[a], c.ly[a], c.lz[a]}, f[3] = {fx, fy, fz};
    for (int r = 0; r < 3; ++r)
      for (int q = 0; q < 3; ++q) c.stress[3 * r + q][a] = f[r] * l[q];
    // Affine stiffness: (k_n n_k^2 + k_t (1 - n_k^2)) l_k^2. Pure shear D_ab = D_ba (servo.hpp):
    // |l|^2 (2 k_n n_a^2 n_b^2 + k_t ((n_a^2 + n_b^2)/2 - 2 n_a^2 n_b^2)), ab = 12, 13, 23.
    const double n2[3] = {nx * nx, ny * ny, nz * nz};
    const double l2 = (l[0] * l[0] + l[1] * l[1]) + l[2] * l[2];
    for (int q = 0; q < 3; ++q) {
      c.stiffness[q][a] = (kn * n2[q] + kt * (1 - n2[q])) * (l[q] * l[q]);
      // The pair (a, b) of shear q: component_axes[3 + q] written out, as the table's lookup here
      // made the contact stage 10 % slower.
      const int u = q < 2 ? 0 : 1, w = q == 0 ? 1 : 2;
      const double nn = n2[u] * n2[w], half = 0.5 * (n2[u] + n2[w]);
      c.shear_stiffness[q][a] = l2 * (2 * kn * nn + kt * (half - 2 * nn));
      if constexpr (Law::has_dashpots) {  // the same sums of the viscous coefficients
        const double cn = out.cn, ct = out.ct;
        c.viscosity[q][a] = (cn * n2[q] + ct * (1 - n2[q])) * (l[q] * l[q]);
        c.shear_viscosity[q][a] = l2 * (2 * cn * nn + ct * (half - 2 * nn));
      }
    }
    double tjx = ajy * fz - ajz * fy;  // as Eigen's cross
    double tjy = ajz * fx - ajx * fz;
    double tjz = ajx * fy - ajy * fx;
    const double mx = -fx, my = -fy, mz = -fz;
    double tix = aiy * mz - aiz * my;
    double tiy = aiz * mx - aix * mz;
    double tiz = aix * my - aiy * mx;
    if constexpr (Law::has_torque) {
      tjx += out.tx, tjy += out.ty, tjz += out.tz;
      tix -= out.tx, tiy -= out.ty, tiz -= out.tz;
    }
    c.tjx[a] = tjx, c.tjy[a] = tjy, c.tjz[a] = tjz;
    c.tix[a] = tix, c.tiy[a] = tiy, c.tiz[a] = tiz;
  }
}

// The lanes' contacts, in order: the contact's results for its j end, the pair's history, i's
// resultant, the block's contact list, stress and stiffness sums.
template <bool BySlot, class Law, class Slots>
void commit_contacts(const ForceInputs<Law>& in, const ContactLanes<Law>& c, const Slots& slots, Particles& p,
                     PairList& pairs, ForceBlock& acc) {
  constexpr int width = ContactLanes<Law>::width;
  const auto& g = lanes_geometry<BySlot>(c, slots);
  // The sums in locals and the arrays through local pointers: through acc and the vectors GCC
  // loaded and stored every sum at every contact (a store through a double* may alias them).
  double stress[9], stiffness[3], shear_stiffness[3];
  for (int r = 0; r < 3; ++r)
    for (int q = 0; q < 3; ++q) stress[3 * r + q] = acc.stress_sum(r, q);
  for (int q = 0; q < 3; ++q) stiffness[q] = acc.stiffness_sum[q], shear_stiffness[q] = acc.shear_stiffness_sum[q];
  double max_overlap = acc.max_overlap;
  std::size_t max_overlap_pair = acc.max_overlap_pair;
  // Each contact's slot: up from the block's first for a j end of the block's first owner, else
  // down from its last (ForceBlock; close_block_contacts groups them).
  std::uint32_t up = acc.first_contact + acc.contacts, down = acc.slot_end - acc.later_contacts;
  std::uint32_t at[ContactLanes<Law>::stride];
  std::uint32_t* const contact_j = pairs.contact_j.data();
  std::uint32_t* const contact_pairs = pairs.contact_pairs.data();
  Vec3* const contact_force = pairs.contact_force.data();
  Vec3* const contact_torque = pairs.contact_torque_j.data();
  double* const overlap = pairs.overlap.data();
  double* const history = pairs.history.values.data();
  Vec3* const force = p.force.data();
  Vec3* const torque = p.torque.data();
  for (int a = 0; a < c.size; ++a) {
    const std::uint32_t k = c.pair[a], i = c.first[a], j = c.second[a];
    const std::uint32_t first_owner = j < acc.first_owner_end ? 1 : 0;
    at[a] = first_owner != 0 ? up : down - 1;
    up += first_owner, down -= 1 - first_owner;
    const double delta = g.overlap[BySlot ? c.slot[a] : a];
    overlap[k] = delta;
    contact_j[at[a]] = j;
    contact_pairs[at[a]] = k;
    if (delta > max_overlap * c.r_min[a]) {  // delta / R_min > max, without a division per contact
      max_overlap = delta / c.r_min[a];
      max_overlap_pair = k;
    }
    for (int m = 0; m < width; ++m) history[width * k + m] = c.history[m][a];
    const Vec3 f(c.fx[a], c.fy[a], c.fz[a]);
    contact_force[at[a]] = f;
    contact_torque[at[a]] = Vec3(c.tjx[a], c.tjy[a], c.tjz[a]);
    force[i] -= f;
    torque[i] += Vec3(c.tix[a], c.tiy[a], c.tiz[a]);
    for (int m = 0; m < 9; ++m) stress[m] += c.stress[m][a];
    for (int q = 0; q < 3; ++q) stiffness[q] += c.stiffness[q][a], shear_stiffness[q] += c.shear_stiffness[q][a];
  }
  if constexpr (sums_contact_stiffness<Law>)
    for (int a = 0; a < c.size; ++a) {
      const std::uint32_t i = c.first[a];
      in.contact_stiffness[i] += c.kn[a];
      in.contact_rotational_stiffness[i] += c.kt_arm_i[a];
      pairs.contact_stiffness_j[at[a]] = {c.kn[a], c.kt_arm_j[a]};
    }
  if constexpr (Law::has_dashpots)
    for (int a = 0; a < c.size; ++a)
      for (int q = 0; q < 3; ++q)
        acc.viscosity_sum[q] += c.viscosity[q][a], acc.shear_viscosity_sum[q] += c.shear_viscosity[q][a];
  if constexpr (sums_energy<Law>)
    for (int a = 0; a < c.size; ++a) {
      acc.elastic_energy += c.elastic[a];
      acc.slip_work += c.slip_work[a];
      acc.viscous_work += c.viscous_work[a];
      acc.stiffness_work += c.stiffness_work[a];
    }
  acc.contacts = up - acc.first_contact;
  acc.later_contacts = acc.slot_end - down;
  for (int r = 0; r < 3; ++r)
    for (int q = 0; q < 3; ++q) acc.stress_sum(r, q) = stress[3 * r + q];
  for (int q = 0; q < 3; ++q) acc.stiffness_sum[q] = stiffness[q], acc.shear_stiffness_sum[q] = shear_stiffness[q];
  acc.max_overlap = max_overlap;
  acc.max_overlap_pair = max_overlap_pair;
}

// Evaluates and commits the lanes' contacts, whose geometry is at their slots (ContactLanes::slot)
// of `slots`, or with BySlot false the lanes' own, and empties them.
template <bool BySlot = true, class Law, class Slots>
inline void flush_contacts(const ForceInputs<Law>& in, ContactLanes<Law>& c, const Slots& slots, Particles& p,
                           PairList& pairs, ForceBlock& acc) {
  evaluate_contacts<BySlot>(in.law, in.dt, c, slots);
  commit_contacts<BySlot>(in, c, slots, p, pairs, acc);
  c.size = 0;
}

// The same for sphere contacts, whose geometry is computed here in the lanes (ContactLanes::set_spheres).
template <class Law>
inline void flush_sphere_contacts(const ForceInputs<Law>& in, ContactLanes<Law>& c, Particles& p, PairList& pairs,
                                  ForceBlock& acc) {
  sphere_geometry(c);
  flush_contacts<false>(in, c, c.geometry, p, pairs, acc);
}

// A pair that is apart: no force; a contact just lost releases its history (the law's released
// values; written only when it differs from them).
template <class Law>
inline void mark_apart(PairList& pairs, std::uint32_t k) {
  constexpr int width = Law::history.width;
  pairs.overlap[k] = 0;
  double* const h = pairs.history.values.data() + width * k;
  bool released = true;
  for (int m = 0; m < width; ++m) released &= h[m] == Law::history.released[m];
  if (!released)
    for (int m = 0; m < width; ++m) h[m] = Law::history.released[m];
}

// What the pair loops read of a pair's j end (its position, radius and shape) and of a contact's
// (its velocities and R_j), fetched ahead (Model::prefetch_j_ends) into L2 (prefetcht1): the
// lines wait there while the lanes in between, which fill the L1, run.
inline void prefetch_pair_end(const Particles& p, const EllipsoidShape* shapes, std::uint32_t j) {
  __builtin_prefetch(p.s.data() + j, 0, 2);
  __builtin_prefetch(p.bound_radius.data() + j, 0, 2);
  if (shapes != nullptr) {
    __builtin_prefetch(p.shape.data() + j, 0, 2);
    __builtin_prefetch(shapes + j, 0, 2);
  }
}
inline void prefetch_contact_end(const Particles& p, std::uint32_t j) {
  __builtin_prefetch(p.v.data() + j, 0, 2);
  __builtin_prefetch(p.omega.data() + j, 0, 2);
  __builtin_prefetch(p.equiv_radius.data() + j, 0, 2);
}

// Block b's results before its pairs: where its contacts go (ForceBlock::first_contact,
// first_owner_end, slot_end).
inline ForceBlock open_block(const Schedule& schedule, const PairList& pairs, std::size_t b) {
  ForceBlock acc;
  acc.first_contact = pairs.first_i[pairs.block_first[b]];
  acc.slot_end = pairs.first_i[pairs.block_first[b + 1]];
  acc.first_owner_end = owner_end(schedule, pairs.block_first[b]);
  return acc;
}

// Zeroes the i-side resultants of block b's particles (the pair loop sums into them), and their
// stiffness sums for a law that sums stiffnesses.
template <class Law>
inline void clear_block_resultants(const ForceInputs<Law>& in, Particles& p, const PairList& pairs, std::size_t b) {
  for (std::uint32_t a = pairs.block_first[b]; a < pairs.block_first[b + 1]; ++a) {
    p.force[a] = Vec3::Zero();
    p.torque[a] = Vec3::Zero();
  }
  if constexpr (sums_contact_stiffness<Law>)
    for (std::uint32_t a = pairs.block_first[b]; a < pairs.block_first[b + 1]; ++a)
      in.contact_stiffness[a] = in.contact_rotational_stiffness[a] = 0;
}

// Which of n listed pairs to test: keep[m] = 0 while pair m is still provably apart
// (NeighborState::moved(i, j), the same sum, below its apart_until), else 1. In vector lanes (AVX2
// gathers the paths).
QSDEM_CLONES void to_test(const double* path, const std::uint32_t* pair_i,
                                                       const std::uint32_t* pair_j, const double* apart_until,
                                                       double strain, std::uint32_t n, double* keep) {
#pragma omp simd
  for (std::uint32_t m = 0; m < n; ++m) keep[m] = path[pair_i[m]] + path[pair_j[m]] + strain < apart_until[m] ? 0.0 : 1.0;
}

// The pairs of block b (whole particles as i ends), any shapes: spheres exactly, pairs with an
// ellipsoid by Perram-Wertheim, skipped while provably apart. The pairs to test are taken a batch
// at a time: the ellipsoid pairs' narrow phase runs on the whole batch at once (EllipsoidContactBatch),
// then the law runs on the contacts in pair order (the order of the sums, as one pair at a time).
// Built as the lanes it calls are (their inlined parts in vector lanes of the same width).
template <class Law>
QSDEM_CLONES_WIDE ForceBlock force_block(const ForceInputs<Law>& in, Particles& p, PairList& pairs, std::size_t b) {
  ForceBlock acc = open_block(in.schedule, pairs, b);
  clear_block_resultants(in, p, pairs, b);
  constexpr int capacity = EllipsoidContactBatch::capacity;
  EllipsoidContactBatch batch;
  int lane[capacity];  // the pair's lane in the batch, -1 for two spheres
  Vec3 branch[capacity];
  ContactLanes<Law> contacts;
  constexpr int width = ContactLanes<Law>::width;
  // One flat loop over the block's pairs, summing into p.force[i] directly (a loop per particle,
  // ~2-4 pairs each, mispredicts its exit).
  const std::uint32_t k1 = pairs.first_i[pairs.block_first[b + 1]];
  // The skip scan's data in locals: through the references GCC reloaded every pointer and
  // recomputed the bound's strain term for every pair. Without skip_apart the motion bounds and
  // apart_until may not be sized: nothing is read.
  const std::uint32_t* const pair_i = pairs.i.data();
  const std::uint32_t* const pair_j = pairs.j.data();
  const double* const apart_until = in.skip_apart ? pairs.apart_until.data() : nullptr;
  const double* const path = in.skip_apart ? in.ns.surface_path.data() : nullptr;
  const double strain = in.skip_apart ? in.ns.strain_path * in.ns.branch_reach() : 0;
  constexpr std::uint32_t window = 256;
  std::uint32_t listed[window];
  alignas(64) double keep[window];
  for (std::uint32_t w0 = pairs.first_i[pairs.block_first[b]]; w0 < k1; w0 += window) {
    // The pairs to test: not still provably apart (its overlap is 0 and its spring released since
    // the test that proved it). First each pair's outcome, in vector lanes, then the list, without
    // a branch on the outcome (it mispredicts). Two spheres are always tested (their direct test is
    // as cheap as the skip test): only ellipsoid lanes set apart_until, so theirs stays -1 from the
    // list build, below any motion.
    const std::uint32_t w1 = std::min(k1, w0 + window);
    std::uint32_t nl = 0;
    if (in.skip_apart) {
      to_test(path, pair_i + w0, pair_j + w0, apart_until + w0, strain, w1 - w0, keep);
      for (std::uint32_t k = w0; k < w1; ++k) {
        listed[nl] = k;
        nl += keep[k - w0] != 0 ? 1 : 0;
      }
    } else {
      for (std::uint32_t k = w0; k < w1; ++k) listed[nl++] = k;
    }
    for (std::uint32_t m0 = 0; m0 < nl; m0 += capacity) {
      const int nt = static_cast<int>(std::min<std::uint32_t>(capacity, nl - m0));
      const std::uint32_t* const tested = listed + m0;
      if (in.prefetch_j_ends)  // the next batch's j ends (and the window's first batch's own)
        for (std::uint32_t m = m0 == 0 ? 0 : m0 + capacity; m < std::min(nl, m0 + 2 * capacity); ++m) {
          const std::uint32_t j = pair_j[listed[m]];
          prefetch_pair_end(p, in.shapes, j);
          prefetch_contact_end(p, j);
        }
      // The batch writes its geometry in the other half of its slots: the lanes may still hold the
      // last batch's contacts. Any left from the batch before, whose half is reused (after batches
      // of few contacts), are evaluated first.
      batch.first = capacity - batch.first;
      if (contacts.size > 0 && (contacts.slot[0] < capacity) == (batch.first == 0))
        flush_contacts(in, contacts, batch.geometry, p, pairs, acc);
      batch.size = 0;
      for (int m = 0; m < nt; ++m) {
        const std::uint32_t kt = tested[m], i = pairs.i[kt], j = pairs.j[kt];
        const bool spheres = p.shape[i] == ShapeKind::sphere && p.shape[j] == ShapeKind::sphere;
        branch[m] = branch_vector(in.cell, p.s[i], p.s[j], pairs.image[kt]);
        lane[m] = spheres ? -1 : batch.add(branch[m], in.shapes[i], in.shapes[j], pairs.pw_lambda[kt]);
        // The law's history: the listed pairs' overflow L2.
        __builtin_prefetch(pairs.history.values.data() + width * kt, 1);
      }
      acc.narrow_tests += nt;
      // Narrow phase (SPEC 4): Perram-Wertheim for any pair with an ellipsoid; exact for spheres.
      ellipsoid_contacts(batch);
      for (int a = 0; a < batch.size; ++a) acc.pw_iterations += batch.stats[a].iterations;
      int sphere_slot = batch.first + batch.size;  // two spheres' geometry: the slots after the batch's
      for (int m = 0; m < nt; ++m) {
        const std::uint32_t kt = tested[m], i = pairs.i[kt], j = pairs.j[kt];
        const Vec3& l = branch[m];
        int slot = -1;
        bool touching;
        if (lane[m] < 0) {
          const double ri = p.bound_radius[i], rj = p.bound_radius[j];
          touching = l.squaredNorm() < (ri + rj) * (ri + rj);
          if (touching) {
            const ContactGeometry g = sphere_sphere(l, ri, rj);
            touching = g.overlap > 0;  // a contact always has overlap > 0 (PairList::overlap)
            slot = sphere_slot++;
            batch.geometry.set(slot, g);
          }
        } else {
          const int a = lane[m];
          pairs.pw_lambda[kt] = batch.lambda[a];
          touching = batch.touching[a];
          if (touching) {
            slot = batch.slot[a];
          } else {
            // Not tested again until the surfaces may have closed the proven gap; the margin covers
            // the round-off of mu (1e-9 of the minor axes, far above it).
            const double gap = batch.stats[a].gap_bound - 1e-9 * (in.shapes[i].minor + in.shapes[j].minor);
            if (in.skip_apart && gap > 0) pairs.apart_until[kt] = in.ns.moved(i, j) + gap;
          }
        }
        if (!touching) {
          mark_apart<Law>(pairs, kt);
          continue;
        }
        contacts.slot[contacts.add(in, p, pairs, kt, i, j, l)] = slot;
        if (contacts.size == ContactLanes<Law>::capacity) flush_contacts(in, contacts, batch.geometry, p, pairs, acc);
      }
    }
  }
  flush_contacts(in, contacts, batch.geometry, p, pairs, acc);
  close_block_contacts(in.schedule, pairs, b, acc);
  return acc;
}

// The test of n sphere pairs by their fractional branches (in: s_j - s_i + image; out: the branch l,
// as branch_vector gives it) and reach r = r_i + r_j: |l|, touching (1: |l|^2 < r^2, else 0), and
// for an apart pair the motion `moved` + gap (|l| - r, less a margin for its round-off) below which
// it is not tested again (-1: tested at the next step).
QSDEM_CLONES_WIDE void sphere_tests(const CellMap& h, double* lx, double* ly, double* lz, const double* reach,
                                    std::uint32_t n, double moved, double* distance, double* touch, double* until) {
#pragma omp simd
  for (std::uint32_t m = 0; m < n; ++m) {
    double x, y, z;
    h.apply(lx[m], ly[m], lz[m], x, y, z);
    lx[m] = x, ly[m] = y, lz[m] = z;
    const double r = reach[m];
    const double d2 = (x * x + y * y) + z * z;
    const double d = std::sqrt(d2);
    const bool t = d2 < r * r;
    const double gap = d - r * (1 + 1e-9);
    distance[m] = d;
    touch[m] = t ? 1.0 : 0.0;
    until[m] = !t && gap > 0 ? moved + gap : -1.0;
  }
}

// The same for a run of spheres only, where most listed pairs are apart (~88 % in spheres-A).
// A pair proved apart is skipped, on one sequential read, while the motion of any two particles
// since then (NeighborState::moved_any) is below its gap. The others go through a first pass over
// a chunk that tests them without a branch on the outcome; a second runs the law on the touching.
template <class Law>
QSDEM_CLONES_WIDE ForceBlock sphere_force_block(const ForceInputs<Law>& in, Particles& p, PairList& pairs,
                                                std::size_t b) {
  ForceBlock acc = open_block(in.schedule, pairs, b);
  clear_block_resultants(in, p, pairs, b);
  constexpr std::uint32_t chunk = 128;
  std::uint32_t tested[chunk], touching[chunk], lost[chunk];
  alignas(64) double lx[chunk], ly[chunk], lz[chunk], reach[chunk], distance[chunk], touch[chunk], until[chunk];
  ContactLanes<Law> contacts;
  constexpr int width = ContactLanes<Law>::width;
  const std::uint32_t k0 = pairs.first_i[pairs.block_first[b]], k1 = pairs.first_i[pairs.block_first[b + 1]];
  const bool overlap_known = pairs.overlap_known;
  const double moved = in.skip_apart ? in.ns.moved_any() : 0;
  const bool prefetch = in.prefetch_j_ends;
  const CellMap cell_map(in.cell.h);
  for (std::uint32_t c0 = k0; c0 < k1; c0 += chunk) {
    const std::uint32_t c1 = std::min(k1, c0 + chunk);
    // The pairs to test: not (still) provably apart, i.e. overlap 0 and no history since the test
    // that proved it. Listed without a branch on the outcome (it is ~50/50 and mispredicts).
    std::uint32_t nk = 0;
    if (prefetch)  // the next chunk's
      for (std::uint32_t k = c1; k < std::min(k1, c1 + chunk); ++k) prefetch_pair_end(p, nullptr, pairs.j[k]);
    for (std::uint32_t k = c0; k < c1; ++k) {
      tested[nk] = k;
      nk += in.skip_apart && moved < pairs.apart_until[k] ? 0 : 1;
    }
    acc.narrow_tests += nk;
    // Their branch vectors and radii; then |l| and the outcome in vector lanes (a square root per
    // pair, in a loop without loads that miss); then the touching are listed.
    for (std::uint32_t m = 0; m < nk; ++m) {
      const std::uint32_t k = tested[m], i = pairs.i[k], j = pairs.j[k];
      const Vec3 d = p.s[j] - p.s[i] + pairs.image[k].cast<double>();  // as in branch_vector
      lx[m] = d.x(), ly[m] = d.y(), lz[m] = d.z();
      reach[m] = p.bound_radius[i] + p.bound_radius[j];
    }
    sphere_tests(cell_map, lx, ly, lz, reach, nk, moved, distance, touch, until);
    // The touching and the contacts just lost are listed without a branch (t and the last step's
    // overlap are ~50/50 at random: GCC made branches of selects on them, which mispredicted).
    std::uint32_t nt = 0, nl = 0;
    for (std::uint32_t m = 0; m < nk; ++m) {
      const std::uint32_t k = tested[m];
      const std::uint32_t t = touch[m] != 0 ? 1 : 0;
      touching[nt] = m;
      nt += t;
      // The law's history, for a contact (the address by arithmetic, for the same reason); the
      // contacts are every ~9th listed pair, too sparse for the hardware prefetcher.
      __builtin_prefetch(pairs.history.values.data() + width * (c0 + (k - c0) * t), 1);
      if (prefetch) {  // and its j end's velocities (else i's, already loaded)
        const std::uint32_t i = pairs.i[k];
        prefetch_contact_end(p, i + (pairs.j[k] - i) * t);
      }
      lost[nl] = k;
      nl += (1 - t) & ((pairs.overlap[k] != 0 ? 1u : 0u) | (overlap_known ? 0u : 1u));
      if (in.skip_apart) pairs.apart_until[k] = until[m];
    }
    for (std::uint32_t n = 0; n < nl; ++n) mark_apart<Law>(pairs, lost[n]);
    for (std::uint32_t n = 0; n < nt; ++n) {
      const std::uint32_t m = touching[n], k = tested[m], i = pairs.i[k], j = pairs.j[k];
      const double ri = p.bound_radius[i], rj = p.bound_radius[j];
      if (!(ri + rj - distance[m] > 0)) {  // sphere_sphere's overlap
        mark_apart<Law>(pairs, k);  // |l| rounded to r_i + r_j: not a contact
        continue;
      }
      contacts.set_spheres(contacts.add(in, p, pairs, k, i, j, Vec3(lx[m], ly[m], lz[m])), distance[m], ri, rj);
      if (contacts.size == ContactLanes<Law>::capacity) flush_sphere_contacts(in, contacts, p, pairs, acc);
    }
  }
  flush_sphere_contacts(in, contacts, p, pairs, acc);
  close_block_contacts(in.schedule, pairs, b, acc);
  return acc;
}

// The blocks of the force stage with the law: the pair driver instantiated on it.
template <class Law>
void run_force_blocks(const ForceInputs<Law>& in, State& state, std::size_t nblocks, int nthreads, bool all_spheres) {
  adopt_history(state.pairs, Law::history);
  Particles& p = state.particles;
  PairList& pairs = state.pairs;
  Schedule& schedule = in.schedule;
  run_blocks(schedule, nblocks, nthreads, [&](std::size_t b) {
    const double t0 = omp_get_wtime();
    state.blocks[b] = all_spheres ? sphere_force_block(in, p, pairs, b) : force_block(in, p, pairs, b);
    const double seconds = omp_get_wtime() - t0;
    record_block_time(schedule, b, seconds);
    return seconds;
  });
}

// The step's stress, affine stiffnesses and viscosities (SPEC 7) and energy sums from the force
// blocks' partial sums, added in block order (no result depends on the thread count).
void sum_force_blocks(const Model& model, State& state) {
  EnergySums energy;
  Mat3 sum = Mat3::Zero();
  Vec3 stiff = Vec3::Zero(), shear_stiff = Vec3::Zero(), viscosity = Vec3::Zero(), shear_viscosity = Vec3::Zero();
  state.max_overlap = 0;
  state.narrow_tests = 0;
  state.pw_iterations = 0;
  for (const ForceBlock& b : state.blocks) {
    sum += b.stress_sum;
    stiff += b.stiffness_sum;
    shear_stiff += b.shear_stiffness_sum;
    viscosity += b.viscosity_sum;
    shear_viscosity += b.shear_viscosity_sum;
    energy.elastic += b.elastic_energy, energy.slip += b.slip_work, energy.viscous += b.viscous_work;
    energy.stiffness += b.stiffness_work;
    state.narrow_tests += b.narrow_tests;
    state.pw_iterations += b.pw_iterations;
    if (b.max_overlap > state.max_overlap) {
      state.max_overlap = b.max_overlap;
      state.max_overlap_pair = b.max_overlap_pair;
    }
  }
  const Cell& cell = state.cell;
  const double v = cell.volume;
  state.stress = 0.5 * (sum + sum.transpose()) / v;  // f on j and l from i to j: compression positive
  state.affine_stiffness = stiff / v;
  state.shear_stiffness = shear_stiff / v;
  state.affine_viscosity = viscosity / v;
  state.shear_viscosity = shear_viscosity / v;
  state.stress_volume = v;
  state.stress_h = cell.h;
  if (model.track_energy) {
    state.energy.elastic = energy.elastic;
    state.energy.friction += energy.slip;
    state.energy.contact_damping += energy.viscous;
    state.energy.stiffness_change += energy.stiffness;
  }
}

}  // namespace

bool beyond_cache(const Particles& p) {
  static const long cache = last_level_cache_bytes();
  return p.heap_bytes() > static_cast<std::size_t>(cache / 2);
}

void compute_contact_forces(const Model& model, State& state, Schedule& schedule) {
  Particles& p = state.particles;
  PairList& pairs = state.pairs;
  const std::size_t np = pairs.size();
  const std::size_t n = p.size();
  const std::size_t nblocks = pairs.block_first.size() - 1;
  state.blocks.resize(nblocks);
  pairs.contact_pairs.resize(np);
  pairs.contact_j.resize(np);
  pairs.contact_force.resize(np);
  pairs.contact_torque_j.resize(np);
  // The per-particle contact stiffnesses, only for a damping that reads them.
  const bool stiffness_sums = model.damping.needs_contact_stiffness;
  if (stiffness_sums) {
    pairs.contact_stiffness_j.resize(np);
    state.contact_stiffness.resize(n);
    state.contact_rotational_stiffness.resize(n);
  } else {
    pairs.contact_stiffness_j.clear();
    state.contact_stiffness.clear();
    state.contact_rotational_stiffness.clear();
  }
  // Shape matrices once per particle (each takes part in several pairs); only when some particle
  // is an ellipsoid, so a sphere run pays nothing.
  const bool all_spheres = !has_ellipsoids(state);
  if (!all_spheres) {
    state.shapes.resize(n);
#pragma omp parallel if (n > parallel_threshold)
    {
      const std::size_t nt = static_cast<std::size_t>(omp_get_num_threads());
      const std::size_t t = static_cast<std::size_t>(omp_get_thread_num());
      ellipsoid_shapes(p.semi_axes.data(), p.q, state.shapes.data(), n * t / nt, n * (t + 1) / nt);
    }
  }
  // Skipping provably apart pairs needs the motion bounds of the current list (neighbor.hpp).
  const NeighborState& ns = state.neighbor;
  const bool motion_known = all_spheres ? ns.surface_path.empty() : ns.surface_path.size() == n;

  // Each block owns whole particles as the i end of their pairs (sorted by i): it writes their
  // i-side resultants itself; gather_resultants adds the j ends. Which thread runs a block changes
  // no result. Each thread starts with a contiguous range of blocks, so it keeps the same particles
  // (a thread keeps its particles' data in its cache) from step to step, cut where the blocks'
  // smoothed times of the last steps are equal (blocks differ in contacts and narrow tests). Right after a list build pair counts stand
  // in. What the cut misses, the threads share at the ranges' ends (run_blocks).
  const int nthreads = np > parallel_threshold ? omp_get_max_threads() : 1;
  share_blocks(schedule, pairs, ns.builds, nthreads);
  // The update region's particle ranges (step.cpp), fixed here so that each block can group its
  // contacts by the thread that owns their j end.
  const std::size_t owners = n > parallel_threshold ? static_cast<std::size_t>(omp_get_max_threads()) : 1;
  assign_owners(schedule, pairs, n, owners, nthreads);
  const bool skip_apart = model.skip_apart_pairs && motion_known && pairs.apart_until.size() == np;
  const bool prefetch_j_ends = prefetches_j_ends(model, p);
  std::visit(
      [&]<class Law>(const Law& law) {
        const auto run = [&]<bool Stiffness, bool Energy>() {
          const DrivenLaw<Law, Stiffness, Energy> driven{law};
          const ForceInputs<DrivenLaw<Law, Stiffness, Energy>> in{
              driven,     model.dt, state.cell, state.shapes.data(), ns, skip_apart, prefetch_j_ends, schedule,
              Stiffness ? state.contact_stiffness.data() : nullptr,
              Stiffness ? state.contact_rotational_stiffness.data() : nullptr};
          run_force_blocks(in, state, nblocks, nthreads, all_spheres);
        };
        if (stiffness_sums && model.track_energy) run.template operator()<true, true>();
        else if (stiffness_sums) run.template operator()<true, false>();
        else if (model.track_energy) run.template operator()<false, true>();
        else run.template operator()<false, false>();
      },
      contact_law_of(model));
  schedule.timed_build = ns.builds;
  state.contacts_build = ns.builds;
  pairs.overlap_known = true;
  if (nthreads > 1) record_thread_balance(schedule, state.timers);

  sum_force_blocks(model, state);
}

void gather_resultants(const PairList& pairs, const Schedule& schedule, Particles& p, std::size_t t) {
  const std::size_t owners = schedule.owners();
  const std::vector<std::uint32_t>& contact_owner_first = schedule.contact_owner_first;
  constexpr std::uint32_t ahead = 16;  // contacts: the loads below miss the cache
  // Through local pointers (integrate_velocities says why).
  const std::uint32_t* const contact_j = pairs.contact_j.data();
  const Vec3* const contact_force = pairs.contact_force.data();
  const Vec3* const contact_torque = pairs.contact_torque_j.data();
  Vec3* const force = p.force.data();
  Vec3* const torque = p.torque.data();
  for (std::size_t row = 0; row < contact_owner_first.size(); row += owners + 1) {
    const std::uint32_t m0 = contact_owner_first[row + t], m1 = contact_owner_first[row + t + 1];
    for (std::uint32_t m = m0; m < m1; ++m) {
      if (m + ahead < m1) {
        __builtin_prefetch(&force[contact_j[m + ahead]], 1);
        __builtin_prefetch(&torque[contact_j[m + ahead]], 1);
      }
      const std::uint32_t j = contact_j[m];
      force[j] += contact_force[m];
      torque[j] += contact_torque[m];
    }
  }
}

void gather_contact_stiffness(const PairList& pairs, const Schedule& schedule, State& state, std::size_t t) {
  const std::size_t owners = schedule.owners();
  const std::vector<std::uint32_t>& contact_owner_first = schedule.contact_owner_first;
  const std::uint32_t* const contact_j = pairs.contact_j.data();
  const std::array<double, 2>* const terms = pairs.contact_stiffness_j.data();
  double* const kn = state.contact_stiffness.data();
  double* const krot = state.contact_rotational_stiffness.data();
  for (std::size_t row = 0; row < contact_owner_first.size(); row += owners + 1)
    for (std::uint32_t m = contact_owner_first[row + t]; m < contact_owner_first[row + t + 1]; ++m) {
      kn[contact_j[m]] += terms[m][0];
      krot[contact_j[m]] += terms[m][1];
    }
}

ContactForceByPair::ContactForceByPair(const State& state)
    : slot_(state.pairs.size(), none), force_(state.pairs.contact_force.data()) {
  // The contact slots are those of the last force evaluation: on a list built since, they are stale.
  if (!state.blocks.empty() && state.contacts_build != state.neighbor.builds)
    throw std::logic_error("contact forces by pair: the pair list changed since the last force evaluation");
  for (const ForceBlock& b : state.blocks)
    for (std::uint32_t m = b.first_contact; m < b.first_contact + b.contacts; ++m) slot_[state.pairs.contact_pairs[m]] = m;
}

std::vector<Vec3> contact_forces_by_pair(const State& state) {
  const ContactForceByPair force(state);
  std::vector<Vec3> by_pair(state.pairs.size());
  for (std::size_t k = 0; k < by_pair.size(); ++k) by_pair[k] = force[k];
  return by_pair;
}

void gather_resultants(State& state, const Schedule& schedule) {
  // Adds the j ends of the contacts to the i-side sums the force stage wrote, in pair order (so
  // for any thread count): each owner of a range of particles (Schedule::owner_first) reads the
  // contacts the force stage grouped for it, which costs less than reading every pair's overlap
  // through the j incidence.
  const int owners = static_cast<int>(schedule.owners());
#pragma omp parallel num_threads(owners) if (owners > 1)
  {
    const int team = omp_get_num_threads();
    for (int t = omp_get_thread_num(); t < owners; t += team) {
      gather_resultants(state.pairs, schedule, state.particles, static_cast<std::size_t>(t));
      if (!state.contact_stiffness.empty())
        gather_contact_stiffness(state.pairs, schedule, state, static_cast<std::size_t>(t));
    }
  }
}

}  // namespace qsdem
