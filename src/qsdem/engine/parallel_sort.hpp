// Sorts on the OpenMP threads: libstdc++'s parallel mode (a multiway merge sort) from
// parallel_threshold elements up, std:: below. The order does not depend on the thread count:
// parallel_sort requires that elements comparing equal are the same bits (unique keys, or plain
// values: the order is the one std::sort gives), parallel_stable_sort is stable (the order
// std::stable_sort gives).
#pragma once
#include <parallel/algorithm>

#include <algorithm>
#include <iterator>

#include "qsdem/engine/types.hpp"

namespace qsdem {

template <class It, class Less>
void parallel_sort(It first, It last, Less less) {
  if (static_cast<std::size_t>(std::distance(first, last)) < parallel_threshold)
    std::sort(first, last, less);
  else
    __gnu_parallel::sort(first, last, less, __gnu_parallel::multiway_mergesort_tag());
}

template <class It, class Less>
void parallel_stable_sort(It first, It last, Less less) {
  if (static_cast<std::size_t>(std::distance(first, last)) < parallel_threshold)
    std::stable_sort(first, last, less);
  else
    __gnu_parallel::stable_sort(first, last, less, __gnu_parallel::multiway_mergesort_tag());
}

}  // namespace qsdem
