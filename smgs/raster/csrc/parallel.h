// Thread-parallel loops of the compiled CPU renderer, on plain std::thread: no OpenMP runtime, so
// no thread spins while it waits (an OpenMP team spins at its barriers by default, which on a
// loaded machine takes the CPU from the thread it waits for), the build needs no -fopenmp (Apple
// clang has none), and the thread count is exactly the caller's (torch.get_num_threads()).
// A region costs one thread start per extra worker (~20-50 µs), small beside a render's tiles.
#pragma once

#include <algorithm>
#include <atomic>
#include <condition_variable>
#include <memory>
#include <mutex>
#include <cstdint>
#include <thread>
#include <vector>

namespace smgs {

// f(worker, i) for i in [0, n), items handed out one at a time (the tiles' costs differ widely);
// worker in [0, workers(nthreads, n)) indexes the caller's per-worker scratch.
inline int workers(int nthreads, int64_t n) { return int(std::max<int64_t>(1, std::min<int64_t>(nthreads, n))); }

// The caller works too and returns as soon as every item is done, without waiting for workers
// that have not yet started (on a loaded machine a new thread can wait a whole time slice for a
// core: joining it would cost that); such a late worker finds no item left and ends, touching only
// the shared counters it co-owns.
struct ParallelState {
  std::atomic<int64_t> next{0}, done{0};
  std::mutex mu;
  std::condition_variable cv;
};

template <class F>
void parallel_dynamic(int nthreads, int64_t n, F&& f) {
  const int nw = workers(nthreads, n);
  if (nw == 1) {
    for (int64_t i = 0; i < n; ++i) f(0, i);
    return;
  }
  auto st = std::make_shared<ParallelState>();
  auto* fp = &f;  // called only for claimed items, all of which finish before this function returns
  auto work = [st, fp, n](int w) {
    int64_t mine = 0;
    for (int64_t i; (i = st->next.fetch_add(1, std::memory_order_relaxed)) < n; ++mine) (*fp)(w, i);
    if (mine && st->done.fetch_add(mine, std::memory_order_acq_rel) + mine == n) {
      std::lock_guard<std::mutex> lock(st->mu);
      st->cv.notify_all();
    }
  };
  for (int w = 1; w < nw; ++w) std::thread(work, w).detach();
  work(0);
  std::unique_lock<std::mutex> lock(st->mu);
  st->cv.wait(lock, [&] { return st->done.load(std::memory_order_acquire) == n; });
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
