// Splitting a loop over Gaussians by hand between the OpenMP threads, for loops that must
// live in a function of their own: a worker's __restrict pointers survive only there
// (OpenMP's outlined loop bodies drop the qualifier, and GCC then stops vectorising).
#pragma once
#include <cstdint>
#include <type_traits>

#include <omp.h>

namespace kgs {

// Runs work(begin, end) on each thread's contiguous share of [0, n).
template <typename Work>
inline void per_thread_share(int64_t n, Work&& work) {
#pragma omp parallel
  {
    const int64_t threads = omp_get_num_threads(), t = omp_get_thread_num();
    work(n * t / threads, n * (t + 1) / threads);
  }
}

// Calls f(flag) with the run-time flag as a compile-time constant (std::true_type or
// std::false_type): a select on a run-time flag inside a loop stops GCC vectorising it.
template <typename F>
inline void with_constant(bool flag, F&& f) {
  if (flag)
    f(std::true_type{});
  else
    f(std::false_type{});
}

}  // namespace kgs
