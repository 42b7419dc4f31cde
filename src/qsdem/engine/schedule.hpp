// How the threads share the step's work: the force stage's blocks and the particle update's
// ranges. Scheduling only: every thread count and every cut gives the same bits (the sums run in
// block order and, per particle, in pair order). The force stage fills a Schedule, the update
// stage reads its owners; the caller keeps it from step to step (the blocks' times of the last
// steps set the next cut).
#pragma once
#include <omp.h>

#include <atomic>
#include <cstdint>
#include <span>
#include <vector>

#include "qsdem/engine/state.hpp"

namespace qsdem {

struct Schedule {
  // Per force block (PairList::block_first): its time in the last step, and its recent times
  // smoothed (what the threads share in the next step).
  std::vector<double> block_seconds, block_weight;
  long timed_build = -1;  // NeighborState::builds of the list whose blocks were timed
  bool timed = false;     // this step's blocks are those timed (share_blocks)
  std::vector<std::size_t> block_cut;       // thread t starts with blocks [cut[t], cut[t + 1])
  std::vector<std::uint8_t> block_claimed;  // 1 once a thread has taken the block this step
  std::vector<double> thread_busy;          // each thread's seconds in its blocks this step
  // The update region's particles: thread t owns [owner_first[t], owner_first[t + 1]).
  // contact_owner_first, (owners + 1) per block: block b's contacts whose j end thread t owns are
  // the slots [row[t], row[t + 1]) of PairList::contact_pairs / contact_j, row =
  // contact_owner_first + b (owners + 1).
  std::vector<std::size_t> owner_first;
  std::vector<std::uint32_t> contact_owner_first;
  // Per owner: its seconds in the update region this step (gather, kick, drift), and its recent
  // seconds per particle smoothed (what sets the next steps' ranges).
  std::vector<double> owner_seconds, owner_rate;

  std::size_t owners() const { return owner_first.size() - 1; }
  // True when the owners describe the contacts of `state`'s last force evaluation.
  bool has_owners_of(const State& state) const;
};

// Cuts the blocks into contiguous ranges of equal cost for the threads (block_cut): the blocks'
// smoothed times of the last steps when they are the same blocks (timed_build == builds, then
// `timed` is set), else (right after a list build) their pair counts.
void share_blocks(Schedule& s, const PairList& pairs, long builds, int nthreads);

// The update region's ranges of n particles for `owners` threads, sized contact_owner_first
// for the blocks. Once the update region has timed its owners (owner_rate), ranges of equal
// expected time: a range's particles cost more than others' when they have more contacts to
// gather or more spheroids turning, and the same particles cost more on one core than the other
// (their force-stage sums were written by the other core). Before that: with as many owners as
// the force stage's threads, thread t owns the particles of its blocks; else an even split.
void assign_owners(Schedule& s, const PairList& pairs, std::size_t n, std::size_t owners, int nthreads);

// The update region's owners took owner_seconds for their ranges this step: their smoothed
// seconds per particle.
void record_owner_times(Schedule& s);

// One owner for all: every particle and, per block, all its contacts (ForceBlock::first_contact,
// contacts) of `state`'s last force evaluation. The update stage's split when the force stage
// has not set the owners.
void assign_single_owner(Schedule& s, const State& state);

// Groups block b's contacts, slots [first, first + count), by the thread that owns their j end,
// keeping the pair order within each group (the four contact arrays moved together), and
// writes the block's row of contact_owner_first.
void group_contacts_by_owner(Schedule& s, PairList& pairs, std::size_t b, std::uint32_t first, std::uint32_t count);

// The owner of particle i: the last whose range (Schedule::owner_first) starts at or below it.
std::size_t owner_of(const Schedule& s, std::size_t i);

// The end of the particles of the owner of particle i: the force stage's block that starts at i
// writes the contacts whose j end is below it up from its first slot, the others down from its
// last (ForceBlock::first_owner_end). With one owner, every particle's.
std::uint32_t owner_end(const Schedule& s, std::size_t i);

// Block b's contacts as the force stage wrote them (ForceBlock: those of the block's first owner
// up from first_contact, in pair order; the others down from slot_end, in reverse pair order):
// the others moved after the first ones in pair order and grouped by owner
// (group_contacts_by_owner), the block's row of contact_owner_first written, and `contacts` the
// block's count. Only the others move: a block whose j ends its first owner holds moves nothing.
void close_block_contacts(Schedule& s, PairList& pairs, std::size_t b, ForceBlock& block);

// Block b took `seconds` this step: its time and smoothed weight.
inline void record_block_time(Schedule& s, std::size_t b, double seconds) {
  s.block_seconds[b] = seconds;
  // Smoothed: one step's times carry the machine's noise.
  s.block_weight[b] = s.timed ? 0.8 * s.block_weight[b] + 0.2 * seconds : seconds;
}

// Runs every block once on nthreads threads: run(b) returns its seconds. Each thread starts with
// its range (block_cut), from the back: a block's pairs reach forward (j > i), to particles the
// blocks run before it have just loaded. A thread done with its range takes the blocks left at
// the front of the others', one at a time, from the front: the owner and the thief meet where the
// range's work is shared as it happens (the smoothed cut misses by the noise of the last steps).
// A block is claimed once, by an atomic exchange of its flag; the owner stops at the first block a
// thief has claimed, and a thief at the first one claimed by anyone, so each range is a suffix of
// its owner's and a prefix of one thief's.
template <class Run>
void run_blocks(Schedule& s, std::size_t nblocks, int nthreads, Run&& run) {
  s.block_claimed.assign(nblocks, 0);
  s.thread_busy.assign(static_cast<std::size_t>(nthreads), 0.0);
  const std::vector<std::size_t>& cut = s.block_cut;
  const auto claim = [&](std::size_t b) {
    return std::atomic_ref<std::uint8_t>(s.block_claimed[b]).exchange(1, std::memory_order_relaxed) == 0;
  };
#pragma omp parallel num_threads(nthreads) if (nthreads > 1)
  {
    const int team = omp_get_num_threads(), me = omp_get_thread_num();
    double busy = 0;
    for (int r = me; r < nthreads; r += team)
      for (std::size_t b = cut[r + 1]; b-- > cut[r] && claim(b);) busy += run(b);
    for (int d = 1; d < nthreads; ++d) {
      const int r = (me + d) % nthreads;
      for (std::size_t b = cut[r]; b < cut[r + 1] && claim(b); ++b) busy += run(b);
    }
    s.thread_busy[static_cast<std::size_t>(me)] = busy;
  }
}

// Adds this step's mean and largest thread time in the force stage to the timers (balance).
void record_thread_balance(const Schedule& s, StageTimers& timers);

}  // namespace qsdem
