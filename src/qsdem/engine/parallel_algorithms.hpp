// Sorts and prefix sums on the OpenMP threads: libstdc++'s parallel mode (a multiway merge sort,
// a two-pass prefix sum) from parallel_threshold elements up, std:: below. The results do not
// depend on the thread count: parallel_sort requires that elements comparing equal are the same
// bits (unique keys, or plain values: the order is the one std::sort gives), parallel_stable_sort
// is stable (the order std::stable_sort gives), and parallel_partial_sum is for integers (their
// sums in any grouping are exact).
#pragma once
#include <parallel/algorithm>
#include <parallel/numeric>

#include <algorithm>
#include <concepts>
#include <iterator>
#include <numeric>

#include "qsdem/engine/types.hpp"

namespace qsdem {

// A range run on the threads: from parallel_threshold elements up.
template <class It>
bool on_threads(It first, It last) {
  return static_cast<std::size_t>(std::distance(first, last)) >= parallel_threshold;
}

template <class It, class Less>
void parallel_sort(It first, It last, Less less) {
  if (!on_threads(first, last))
    std::sort(first, last, less);
  else
    __gnu_parallel::sort(first, last, less, __gnu_parallel::multiway_mergesort_tag());
}

template <class It, class Less>
void parallel_stable_sort(It first, It last, Less less) {
  if (!on_threads(first, last))
    std::stable_sort(first, last, less);
  else
    __gnu_parallel::stable_sort(first, last, less, __gnu_parallel::multiway_mergesort_tag());
}

// out[k] = in[0] + ... + in[k] (inclusive), out not overlapping in.
template <class In, class Out>
  requires std::integral<typename std::iterator_traits<In>::value_type>
void parallel_partial_sum(In first, In last, Out out) {
  if (!on_threads(first, last))
    std::partial_sum(first, last, out);
  else
    __gnu_parallel::partial_sum(first, last, out, std::plus<>());
}

}  // namespace qsdem
