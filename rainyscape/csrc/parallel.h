// The worker pool shared by the compiled CPU kernels (the Gaussian rasteriser and the grid
// field's lookups): std::thread, no second OpenMP runtime next to torch's.
#pragma once

#include <algorithm>
#include <atomic>
#include <cstdint>
#include <exception>
#include <mutex>
#include <new>
#include <stdexcept>
#include <string>
#include <system_error>
#include <thread>
#include <vector>

namespace rs {
namespace detail {

// Runs fn(item, worker) for every item in [0, n) on up to `threads` workers (the calling
// thread is worker 0). Dynamic: items are handed out one at a time, so uneven tiles balance;
// returns the number of workers that ran. Fixed: worker w takes items w, w + threads, ...
// (a worker whose thread cannot be started runs on the calling thread), so what each worker
// accumulates, and the sum over workers, is the same on every run: the gradients of a resumed
// run match an uninterrupted one; returns `threads` (after the clamp to n).
template <class Fn>
int parallel_for(int64_t n, int threads, Fn&& fn, bool fixed = false) {
  threads = static_cast<int>(std::max<int64_t>(1, std::min<int64_t>(threads, n)));
  if (threads == 1) {
    for (int64_t i = 0; i < n; ++i) fn(i, 0);
    return 1;
  }
  std::atomic<int64_t> next{0};
  std::atomic<bool> failed{false};
  std::exception_ptr error;
  std::mutex error_lock;
  auto work = [&](int worker) {
    try {
      if (fixed) {
        for (int64_t i = worker; i < n && !failed.load(std::memory_order_relaxed); i += threads) fn(i, worker);
      } else {
        for (int64_t i = next.fetch_add(1); i < n; i = next.fetch_add(1)) fn(i, worker);
      }
    } catch (...) {
      std::lock_guard<std::mutex> lock(error_lock);
      if (!error) error = std::current_exception();
      failed.store(true);
      next.store(n);
    }
  };
  std::vector<std::thread> pool;
  pool.reserve(threads - 1);
  for (int t = 1; t < threads; ++t) {
    try {
      pool.emplace_back(work, t);
    } catch (const std::system_error&) {
      break;  // no more threads to be had: the ones started share the work
    }
  }
  work(0);
  if (fixed) {
    for (int t = static_cast<int>(pool.size()) + 1; t < threads; ++t) work(t);
  }
  for (auto& th : pool) th.join();
  if (error) std::rethrow_exception(error);
  return fixed ? threads : static_cast<int>(pool.size()) + 1;
}

}  // namespace detail

}  // namespace rs
