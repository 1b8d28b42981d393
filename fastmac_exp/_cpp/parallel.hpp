// Parallel loops for the core: a team of threads with dynamic scheduling.
//
// Default backend: a persistent pool of std::threads that sleep on a condition variable. The caller is
// thread 0 and always runs; pool workers join a region only if they wake up while it is still open, and
// the caller waits only for workers that did join. On a busy machine a worker that is not scheduled in
// time therefore costs nothing (no spinning, no waiting for a thread to start), and the results never
// depend on which workers took part: every loop hands out its work through a shared DynamicRange, so
// body(tid) must not assume that any tid other than 0 runs.
//
// Optional backend (CMake -DFASTMAC_OPENMP=ON): OpenMP. Not the default because libgomp spins at
// barriers with the wait policy of whoever loaded it first (torch ships the same soname), which on a
// small shared machine made 2-thread runs 10-40x slower (measured: a 2,000-correspondence MAC took
// 100-240 ms after `import torch`, against 5-15 ms).
#pragma once

#include <algorithm>
#include <atomic>
#include <chrono>
#include <condition_variable>
#include <cstdint>
#include <exception>
#include <mutex>
#include <type_traits>
#include <utility>

#ifdef FASTMAC_OPENMP
#include <omp.h>
#endif

namespace fastmac {

namespace detail {
// Runs fn(ctx, tid) on the caller (tid 0) and on up to nthreads - 1 pool workers (tid 1, 2, ...) that
// join in time; returns when every participant is done. Rethrows the first exception.
void pool_run(int nthreads, void (*fn)(void *, int), void *ctx);
}  // namespace detail

// Runs body(tid) concurrently: always for tid 0 (the caller), for other tids if workers are free.
template <class F>
void parallel_region(int nthreads, F &&body) {
    if (nthreads <= 1) {
        body(0);
        return;
    }
#ifdef FASTMAC_OPENMP
    std::exception_ptr err;
    std::mutex mu;
#pragma omp parallel num_threads(nthreads)
    {
        try {
            body(omp_get_thread_num());
        } catch (...) {
            std::lock_guard<std::mutex> lock(mu);
            if (!err) err = std::current_exception();
        }
    }
    if (err) std::rethrow_exception(err);
#else
    using Body = std::remove_reference_t<F>;
    detail::pool_run(
        nthreads, [](void *ctx, int tid) { (*static_cast<Body *>(ctx))(tid); }, (void *)&body);
#endif
}

// Hands out [begin, end) in chunks, in increasing order, to whichever thread asks next.
class DynamicRange {
   public:
    DynamicRange(int64_t begin, int64_t end, int64_t chunk)
        : next_(begin), end_(end), chunk_(std::max<int64_t>(chunk, 1)) {}
    bool next(int64_t &lo, int64_t &hi) {
        lo = next_.fetch_add(chunk_, std::memory_order_relaxed);
        if (lo >= end_) return false;
        hi = std::min(lo + chunk_, end_);
        return true;
    }

   private:
    std::atomic<int64_t> next_;
    const int64_t end_, chunk_;
};

// body(i, tid) for every i in [begin, end), dynamically scheduled in chunks.
template <class F>
void parallel_for(int64_t begin, int64_t end, int nthreads, int64_t chunk, F &&body) {
    if (nthreads <= 1 || end - begin <= chunk) {
        for (int64_t i = begin; i < end; ++i) body(i, 0);
        return;
    }
    DynamicRange range(begin, end, chunk);
    parallel_region(nthreads, [&](int tid) {
        int64_t lo, hi;
        while (range.next(lo, hi))
            for (int64_t i = lo; i < hi; ++i) body(i, tid);
    });
}

// The threads inside a region's long loop, for the caller to wait on where Ctrl-C can still be seen: each
// thread enter()s and leave()s; wait(poll) returns as soon as the last one has left (woken by it, not by a
// sleep's end: a 200 us sleep made a 0.35 ms clique search take 0.57 on two threads) and calls poll()
// every `every` meanwhile.
class Inside {
   public:
    void enter() {
        std::lock_guard<std::mutex> lock(mu_);
        ++count_;
    }
    void leave() {
        bool last;
        {
            std::lock_guard<std::mutex> lock(mu_);
            last = --count_ == 0;
        }
        if (last) cv_.notify_all();
    }
    template <class Poll>
    void wait(Poll &&poll, std::chrono::microseconds every = std::chrono::microseconds(200)) {
        std::unique_lock<std::mutex> lock(mu_);
        while (count_ > 0) {
            if (cv_.wait_for(lock, every, [this] { return count_ == 0; })) return;
            lock.unlock();
            poll();
            lock.lock();
        }
    }

   private:
    std::mutex mu_;
    std::condition_variable cv_;
    int count_ = 0;
};

}  // namespace fastmac
