// Broad phase (SPEC 4): candidate pairs within a Verlet skin, found with one linked-cell grid per
// particle-size class so that a wide size distribution (Sample A: size ratio 7.5) costs O(N).
// Each pair is keyed by (i, j, image) with i < j; the image K is an integer cell shift of j in
// terms of the unwrapped fractional coordinates, so a physical contact keeps its key for ever
// and its tangential history survives every rebuild.
#pragma once
#include <array>
#include <concepts>
#include <cstdint>
#include <span>
#include <string>
#include <tuple>
#include <type_traits>
#include <vector>

#include "qsdem/engine/cell.hpp"
#include "qsdem/engine/contact/law.hpp"
#include "qsdem/engine/particles.hpp"

namespace qsdem {

inline constexpr std::size_t pairs_per_block = 1024;  // force stage work unit (PairList::block_first)

// The order of the pair keys: lexicographic in (i, j, image).
inline bool key_less(std::uint32_t ai, std::uint32_t aj, const Vec3i& ak, std::uint32_t bi, std::uint32_t bj,
                     const Vec3i& bk) {
  return std::tie(ai, aj, ak.x(), ak.y(), ak.z()) < std::tie(bi, bj, bk.x(), bk.y(), bk.z());
}

// The per-pair arrays that are not the contact law's (the pair registry, for_each_pair_field).
inline constexpr HistoryLayout no_history{"", 0, {}, {}};  // before a law has run on the list
inline constexpr HistoryLayout pw_lambda_layout{"pw_lambda", 1, {-1}, {OnSwap::mirror_unit}};
inline constexpr HistoryLayout apart_until_layout{"apart_until", 1, {-1}, {OnSwap::keep}};
inline constexpr HistoryLayout overlap_layout{"overlap", 1, {0}, {OnSwap::keep}};

// The contact law's history of every listed pair (contact/law.hpp): layout->width doubles per
// pair, pair k's at values[width k]. The law of the force stage adopts it (adopt_history).
struct PairHistory {
  const HistoryLayout* layout = &no_history;
  std::vector<double> values;

  std::span<double> of(std::size_t k) { return {values.data() + layout->width * k, std::size_t(layout->width)}; }
  std::span<const double> of(std::size_t k) const {
    return {values.data() + layout->width * k, std::size_t(layout->width)};
  }
};

struct PairList {
  // Key, sorted lexicographically by (i, j, image).
  std::vector<std::uint32_t> i, j;
  std::vector<Vec3i> image;
  // History carried across steps and rebuilds.
  PairHistory history;             // the contact law's (SPEC 4: the tangential force on j)
  std::vector<double> pw_lambda;   // Perram-Wertheim warm start (ellipsoids)
  // Pairs proved apart are not tested again while they provably stay apart (ellipsoid pairs): the
  // pair is skipped while NeighborState::moved(i, j) < apart_until (see there). -1: test it.
  std::vector<double> apart_until;
  // Result of the last force evaluation (at time t); the forces are kept by contact (below).
  std::vector<double> overlap;     // delta (m) > 0 when the pair is a contact, 0 when apart
  // overlap is that of the last force evaluation, so a pair with overlap 0 has no tangential
  // history. False until a force evaluation has run on this list (a checkpoint restores history,
  // not overlap): then every apart pair's history is checked.
  bool overlap_known = false;
  // The contacts of the last force evaluation, block by block (slots from the block's first pair
  // on; see ForceBlock): their pair indices, j ends, and the force results for the j end (the
  // force stage sums the i ends at once). Stored by contact, not by pair: the force stage writes
  // them in sequence and the gather reads them in sequence (by pair, they were sparse stores and
  // loads that missed the cache). contact_forces_by_pair (forces.hpp) gives them by pair.
  std::vector<std::uint32_t> contact_pairs;
  std::vector<std::uint32_t> contact_j;
  std::vector<Vec3> contact_force;     // contact force on j (N); i receives -force
  std::vector<Vec3> contact_torque_j;  // torque of the contact force about j's centre (N m)
  // k_n and k_t |x_c - x_j|^2 for the j end, only when State::contact_stiffness is summed (else empty).
  std::vector<std::array<double, 2>> contact_stiffness_j;
  // Layout for the deterministic per-particle sums (build_incidence).
  std::vector<std::uint32_t> first_i;     // size n + 1: pairs [first_i[a], first_i[a+1]) have i = a
  std::vector<std::uint32_t> block_first; // particle ranges of the force stage's blocks (~1024
                                          // pairs each, whole particles): nblocks + 1 entries

  std::size_t size() const { return i.size(); }
};

// What the pair registry tells about a per-pair array besides its layout.
struct PairField {
  bool kept;                   // build_pairs copies it for a pair listed before (else: released)
  std::uint32_t saved_since;  // checkpoint format from which the checkpoint saves it; 0: never
};

// The pair registry: f(layout, field, values...) for every per-pair array that lives as long as
// the pair is listed (the key i, j, image aside), with the array of each of the lists given (one
// or more; the history's layout is the first list's), layout.width doubles per pair, in the
// checkpoint's order. build_pairs, sort_particles (permutation and swap rules), the checkpoint and
// the memory accounting go through it. An array not sized for its list (size() * width) is left
// alone.
template <class F, class First, class... Lists>
  requires std::same_as<std::remove_const_t<First>, PairList>
void for_each_pair_field(F&& f, First& first, Lists&... lists) {
  f(*first.history.layout, PairField{true, 1}, first.history.values, lists.history.values...);
  f(pw_lambda_layout, PairField{true, 1}, first.pw_lambda, lists.pw_lambda...);
  f(apart_until_layout, PairField{false, 2}, first.apart_until, lists.apart_until...);  // motion bounds restart
  f(overlap_layout, PairField{true, 9}, first.overlap, lists.overlap...);  // the energy ledger's previous overlap
}

// The history of the law about to run: kept when the list holds one of the same name and width
// (a law that shares it), else every pair's set to the law's released values.
void adopt_history(PairList& pairs, const HistoryLayout& layout);

// `np` pairs' worth of the layout's released values.
std::vector<double> released_values(const HistoryLayout& layout, std::size_t np);

struct NeighborState {
  std::vector<Vec3> s_at_build;
  Mat3 h_at_build = Mat3::Identity();
  double skin = 0;
  double max_bound_radius = 0;
  long builds = 0;
  long distance_checks = 0;  // pair distances computed by the last build (linear in N, not N^2)
  long grid_bins = 0;        // bins of the last build's grids: at most one per particle and class
  bool valid = false;
  // Some particle of the list's particles is an ellipsoid (restart_motion): what the step asks
  // twice per step, without a pass over the particles (has_ellipsoids(State)).
  bool ellipsoids = false;

  // Motion since the last build, for skipping pairs that are provably apart. Per step the branch
  // vector of a pair changes by l <- (I + dt L) l + dt (v_j - v_i) (advance_positions), and a
  // turn of particle k by an angle theta moves its surface by at most 2 sin(theta/2) a_k. So
  // surface_path[k] = sum over steps of dt |v_k| + 2 a_k |q_new - q_old| (the quaternion chord is
  // 2 sin(theta/4) >= sin(theta/2)) and strain_path = sum of |dt L|_F bound how far the two
  // surfaces of a pair can have come closer: surface_path[i] + surface_path[j] + strain_path |l|,
  // with |l| <= branch_reach() for any listed pair that is still apart.
  // fluctuation_path = sum over steps of 2 dt max_k |v_k| bounds twice any centre's motion (the
  // skin test's motion_bound_rules_out_rebuild, any shapes). A run of spheres only (rotation moves
  // no sphere's surface) skips apart pairs by it instead of surface_path: it bounds
  // surface_path[i] + surface_path[j] for every pair, so skipping costs one sequential read per
  // pair and nothing per particle.
  std::vector<double> surface_path;
  double fluctuation_path = 0;
  double strain_path = 0;
  // The last pass of needs_rebuild over the particles: twice the largest
  // displacement it measured, and fluctuation_path and strain_path then. From there the motion
  // bound grows by the paths since (motion_bound_rules_out_rebuild), not since the build. Zero: as
  // at the build (also after a checkpoint, which does not keep them).
  double checked_displacement = 0, checked_fluctuation = 0, checked_strain = 0;

  // A listed pair has |l| < r_i + r_j + skin at the build; until the next build, (1 + strain)
  // times that plus twice the largest displacement (needs_rebuild: each <= skin). Apart pairs keep
  // |l| <= |l_0| + gap_0 <= 2 |l_0| while skipped (the gap of convex bodies is <= |l|).
  double branch_reach() const { return 2 * (2 * max_bound_radius + 3 * skin); }

  // Zero motion, as at a list build. Per-particle paths are tracked only when some particle is an
  // ellipsoid (and then two spheres are always tested directly); otherwise fluctuation_path.
  void restart_motion(const Particles& p);

  // Distance by which the surfaces of a listed pair can have approached since the build.
  double moved(std::uint32_t i, std::uint32_t j) const {
    return surface_path.empty() ? moved_any() : surface_path[i] + surface_path[j] + strain_path * branch_reach();
  }
  // The same for any pair, in a run of spheres only.
  double moved_any() const { return fluctuation_path + strain_path * branch_reach(); }
};

// True when some pair outside the list could now be closer than touching (SPEC 4): twice the
// largest fluctuation displacement plus the stretch of the longest listed branch exceeds the skin.
// use_motion_bound: first try motion_bound_rules_out_rebuild, valid only when the particles moved
// through step() since the build (which keeps the paths); the same answer, without the pass.
// The pass over the particles is recorded in ns (checked_displacement) when use_motion_bound.
bool needs_rebuild(NeighborState& ns, const Particles& p, const Cell& cell, bool use_motion_bound);

// True when the paths (fluctuation_path, strain_path) since the last pass of
// needs_rebuild (or the build) prove that no particle has moved far enough for it to be true.
bool motion_bound_rules_out_rebuild(const NeighborState& ns, const Cell& cell);

// Rebuilds `pairs` (keeping the history of pairs present before) and the incidence lists.
void build_pairs(const Particles& p, const Cell& cell, double skin, PairList& pairs, NeighborState& ns);

// Rebuilds first_i and block_first from the (sorted) pair keys.
void build_incidence(PairList& pairs, std::size_t n_particles);

// The cell-size guard's error: an input error before a run, a deformation gone too far in one.
struct CellTooSmall : InputError {
  CellTooSmall(const std::string& sizes, const std::string& advice) : InputError(sizes + ": " + advice), fact(sizes) {}
  std::string fact;  // the sizes, without the advice for a sample before its run
};

// Refuses a cell in which a particle could touch its own image (SPEC 3): throws CellTooSmall.
void check_cell_size(const Particles& p, const Cell& cell, double skin);

}  // namespace qsdem
