// Thread-parallel loops of the compiled CPU renderer, on plain std::thread: no OpenMP runtime, so
// no thread spins while it waits (an OpenMP team spins at its barriers by default, which on a
// loaded machine takes the CPU from the thread it waits for), the build needs no -fopenmp (Apple
// clang has none), and the thread count is exactly the caller's (torch.get_num_threads()).
// A region costs one thread start per extra worker (~20-50 µs), small beside a render's tiles.
#pragma once

#include <algorithm>
#include <atomic>
#include <cstdint>
#include <thread>
#include <vector>

namespace smgs {

// f(worker, i) for i in [0, n), items handed out one at a time (the tiles' costs differ widely);
// worker in [0, workers(nthreads, n)) indexes the caller's per-worker scratch.
inline int workers(int nthreads, int64_t n) { return int(std::max<int64_t>(1, std::min<int64_t>(nthreads, n))); }

template <class F>
void parallel_dynamic(int nthreads, int64_t n, F&& f) {
  const int nw = workers(nthreads, n);
  std::atomic<int64_t> next{0};
  auto work = [&](int w) {
    for (int64_t i; (i = next.fetch_add(1, std::memory_order_relaxed)) < n;) f(w, i);
  };
  if (nw == 1) return work(0);
  std::vector<std::thread> pool;
  pool.reserve(nw - 1);
  for (int w = 1; w < nw; ++w) pool.emplace_back(work, w);
  work(0);
  for (auto& t : pool) t.join();
}

// f(i) for i in [0, n) in contiguous chunks (cheap, uniform items).
template <class F>
void parallel_static(int nthreads, int64_t n, F&& f) {
  const int64_t chunk = std::max<int64_t>(4096, (n + 4 * int64_t(nthreads) - 1) / (4 * int64_t(nthreads)));
  const int64_t nchunks = (n + chunk - 1) / chunk;
  parallel_dynamic(nthreads, nchunks, [&](int, int64_t c) {
    const int64_t e = std::min(n, (c + 1) * chunk);
    for (int64_t i = c * chunk; i < e; ++i) f(i);
  });
}

}  // namespace smgs
