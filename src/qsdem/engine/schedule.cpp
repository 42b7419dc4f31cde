#include "qsdem/engine/schedule.hpp"

#include <algorithm>
#include <array>

#include "qsdem/engine/clones.hpp"

namespace qsdem {

bool Schedule::has_owners_of(const State& state) const {
  return owner_first.size() >= 2 && owner_first.back() == state.particles.size() &&
         contact_owner_first.size() == state.blocks.size() * (owners() + 1);
}

void share_blocks(Schedule& s, const PairList& pairs, long builds, int nthreads) {
  const std::size_t nblocks = pairs.block_first.size() - 1;
  s.timed = s.timed_build == builds && s.block_weight.size() == nblocks;
  s.block_seconds.resize(nblocks);
  s.block_weight.resize(nblocks);
  std::vector<std::size_t>& cut = s.block_cut;
  cut.assign(static_cast<std::size_t>(nthreads) + 1, nblocks);
  cut[0] = 0;
  if (nthreads == 1) return;
  const auto cost = [&](std::size_t b) {
    return s.timed ? s.block_weight[b]
                   : static_cast<double>(pairs.first_i[pairs.block_first[b + 1]] - pairs.first_i[pairs.block_first[b]]);
  };
  double total = 0;
  for (std::size_t b = 0; b < nblocks; ++b) total += cost(b);
  double before = 0;  // cost of blocks [0, b)
  int t = 1;
  for (std::size_t b = 0; b < nblocks && t < nthreads; ++b) {
    const double c = cost(b);
    while (t < nthreads && before + 0.5 * c >= total * t / nthreads) cut[t++] = b;  // b's middle is past the share
    before += c;
  }
}

void assign_owners(Schedule& s, const PairList& pairs, std::size_t n, std::size_t owners, int nthreads) {
  s.owner_first.resize(owners + 1);
  s.contact_owner_first.resize((pairs.block_first.size() - 1) * (owners + 1));
  if (s.owner_rate.size() != owners) s.owner_rate.clear();  // another thread count: not timed
  if (owners > 1 && !s.owner_rate.empty()) {
    // Shares proportional to each owner's particles per second, each at least a quarter of an
    // even share (so that every owner stays timed); the cuts on multiples of 8 particles (a Vec3
    // array's cache lines start together every 8).
    double speed = 0;
    for (const double rate : s.owner_rate) speed += 1 / rate;
    const std::size_t least = n / (4 * owners);
    double before = 0;
    s.owner_first[0] = 0;
    for (std::size_t t = 1; t < owners; ++t) {
      before += 1 / s.owner_rate[t - 1];
      const auto cut = static_cast<std::size_t>(static_cast<double>(n) * before / speed) / 8 * 8;
      s.owner_first[t] = std::clamp(cut, s.owner_first[t - 1] + least, n - (owners - t) * least);
    }
    s.owner_first[owners] = n;
    return;
  }
  for (std::size_t t = 0; t <= owners; ++t)
    s.owner_first[t] = t == 0        ? 0
                       : t == owners ? n
                       : owners == static_cast<std::size_t>(nthreads)
                           ? std::min<std::size_t>(n, pairs.block_first[s.block_cut[t]])
                           : n * t / owners;
}

void record_owner_times(Schedule& s) {
  const std::size_t owners = s.owners();
  if (owners < 2 || s.owner_seconds.size() != owners) return;
  // Rates only from a step that timed every owner on particles of its own.
  for (std::size_t t = 0; t < owners; ++t)
    if (s.owner_first[t + 1] == s.owner_first[t] || !(s.owner_seconds[t] > 0)) return;
  const bool timed = s.owner_rate.size() == owners;
  s.owner_rate.resize(owners);
  for (std::size_t t = 0; t < owners; ++t) {
    const double rate = s.owner_seconds[t] / static_cast<double>(s.owner_first[t + 1] - s.owner_first[t]);
    // Smoothed: one step's times carry the machine's noise.
    s.owner_rate[t] = timed ? 0.8 * s.owner_rate[t] + 0.2 * rate : rate;
  }
}

void assign_single_owner(Schedule& s, const State& state) {
  s.owner_first = {0, state.particles.size()};
  s.contact_owner_first.resize(2 * state.blocks.size());
  for (std::size_t b = 0; b < state.blocks.size(); ++b) {
    s.contact_owner_first[2 * b] = state.blocks[b].first_contact;
    s.contact_owner_first[2 * b + 1] = state.blocks[b].first_contact + state.blocks[b].contacts;
  }
}

namespace {

// The arrays of a block's contacts that move together when they are grouped (PairList::
// contact_pairs, contact_j, contact_force, contact_torque_j and, when summed,
// contact_stiffness_j): f(array, copy) with the calling thread's scratch copy of its type.
template <class F>
void for_each_contact_array(PairList& pairs, F&& f) {
  thread_local std::vector<std::uint32_t> copy_u32;
  thread_local std::vector<Vec3> copy_vec;
  thread_local std::vector<std::array<double, 2>> copy_stiffness;
  f(pairs.contact_pairs, copy_u32);
  f(pairs.contact_j, copy_u32);
  f(pairs.contact_force, copy_vec);
  f(pairs.contact_torque_j, copy_vec);
  if (!pairs.contact_stiffness_j.empty()) f(pairs.contact_stiffness_j, copy_stiffness);
}

}  // namespace

QSDEM_CLONES void group_contacts_by_owner(Schedule& s, PairList& pairs, std::size_t b, std::uint32_t first,
                                          std::uint32_t count) {
  const std::size_t owners = s.owners();
  std::uint32_t* const row = s.contact_owner_first.data() + b * (owners + 1);
  if (owners == 1) {  // one thread: one group, in place
    row[0] = first, row[1] = first + count;
    return;
  }
  // Each contact's owner: the number of the owners' first particles, after the first, at or below
  // its j (in vector lanes; the arrays are the thread's own, kept from block to block).
  thread_local std::vector<std::uint32_t> group, slot;
  group.resize(count);
  const std::uint32_t* const js = pairs.contact_j.data() + first;
  std::uint32_t* const g = group.data();
  std::fill(g, g + count, 0u);
  for (std::size_t t = 1; t < owners; ++t) {
    const auto from = static_cast<std::uint32_t>(s.owner_first[t]);  // particle indices fit 32 bits
#pragma omp simd
    for (std::uint32_t c = 0; c < count; ++c) g[c] += js[c] >= from ? 1 : 0;
  }
  // Group t's size, and where it starts (row[t]).
  std::uint32_t next = first;
  for (std::size_t t = 0; t < owners; ++t) {
    row[t] = next;
    std::uint32_t size = 0;
#pragma omp simd reduction(+ : size)
    for (std::uint32_t c = 0; c < count; ++c) size += g[c] == t ? 1 : 0;
    next += size;
    if (size == count) {  // one owner holds every j end: grouped as they are
      for (std::size_t u = t + 1; u <= owners; ++u) row[u] = first + count;
      return;
    }
  }
  row[owners] = next;
  // Each contact's new slot, group by group in pair order (a count in a register, not a counter
  // per group in memory: a contact's slot does not wait for the last one's store), then the four
  // arrays moved through a copy.
  // (Masks, not selects: GCC makes a branch of the select, and groups alternate at random.)
  slot.assign(count, 0u);
  std::uint32_t* const to = slot.data();
  for (std::size_t t = 0; t < owners; ++t) {
    if (row[t + 1] == row[t]) continue;
    std::uint32_t at = row[t];
    for (std::uint32_t c = 0; c < count; ++c) {
      const std::uint32_t mine = 0u - (g[c] == t ? 1u : 0u);  // all ones for group t's contacts
      to[c] += at & mine;
      at -= mine;
    }
  }
  for_each_contact_array(pairs, [&](auto& array, auto& copy) {
    copy.assign(array.begin() + first, array.begin() + first + count);
    for (std::uint32_t c = 0; c < count; ++c) array[to[c]] = copy[c];
  });
}

std::size_t owner_of(const Schedule& s, std::size_t i) {
  // The first owner whose range starts after i (owner_first ascends): i's owner is the one before.
  const auto after = std::upper_bound(s.owner_first.begin() + 1, s.owner_first.end() - 1, i);
  return static_cast<std::size_t>(after - s.owner_first.begin()) - 1;
}

std::uint32_t owner_end(const Schedule& s, std::size_t i) { return s.owner_first[owner_of(s, i) + 1]; }

void close_block_contacts(Schedule& s, PairList& pairs, std::size_t b, ForceBlock& block) {
  const std::size_t owners = s.owners();
  std::uint32_t* const row = s.contact_owner_first.data() + b * (owners + 1);
  const std::uint32_t first = block.first_contact, front = block.contacts, later = block.later_contacts;
  const std::size_t home = owner_of(s, block.first_owner_end - 1);  // the block's first owner
  block.contacts = front + later;
  block.later_contacts = 0;
  if (later == 0) {
    for (std::size_t t = 0; t <= owners; ++t) row[t] = t <= home ? first : first + front;
    return;
  }
  // The others, reversed into pair order right after the first owner's (through a copy: the two
  // ranges may overlap).
  const std::uint32_t from = block.slot_end - later, to = first + front;
  for_each_contact_array(pairs, [&](auto& array, auto& copy) {
    copy.assign(array.begin() + from, array.begin() + from + later);
    std::copy(copy.rbegin(), copy.rend(), array.begin() + to);
  });
  // Their owners all follow the first owner (j > i): with two owners they are one group.
  group_contacts_by_owner(s, pairs, b, to, later);
  for (std::size_t t = 0; t <= home; ++t) row[t] = first;
}

void record_thread_balance(const Schedule& s, StageTimers& timers) {
  double busiest = 0, sum = 0;
  for (const double busy : s.thread_busy) {
    busiest = std::max(busiest, busy);
    sum += busy;
  }
  timers.force_thread_mean += sum / static_cast<double>(s.thread_busy.size());
  timers.force_thread_max += busiest;
}

}  // namespace qsdem
