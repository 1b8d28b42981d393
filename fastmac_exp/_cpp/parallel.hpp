// Parallel loops for the core: a team of threads with dynamic scheduling.
//
// Default backend: std::thread, with the caller as thread 0 and blocking joins. Optional backend
// (CMake -DFASTMAC_OPENMP=ON): OpenMP. The default avoids libgomp's spin-waiting at barriers: the
// wait policy is read once per process when libgomp loads, torch ships and loads the same soname
// with the spinning default, and on a small shared machine a spinning barrier costs scheduler time
// slices (measured: a 2,000-correspondence MAC took 100-240 ms with 2 OpenMP threads after
// `import torch`, 5-15 ms with this backend).
#pragma once

#include <algorithm>
#include <atomic>
#include <cstdint>
#include <exception>
#include <mutex>
#include <thread>
#include <vector>

#ifdef FASTMAC_OPENMP
#include <omp.h>
#endif

namespace fastmac {

// Runs body(tid) for tid = 0 .. nthreads-1 concurrently and returns when all are done. The first
// exception thrown by any thread is rethrown here.
template <class F>
void parallel_region(int nthreads, F &&body) {
    if (nthreads <= 1) {
        body(0);
        return;
    }
    std::exception_ptr err;
    std::mutex mu;
    auto guarded = [&](int tid) {
        try {
            body(tid);
        } catch (...) {
            std::lock_guard<std::mutex> lock(mu);
            if (!err) err = std::current_exception();
        }
    };
#ifdef FASTMAC_OPENMP
#pragma omp parallel num_threads(nthreads)
    guarded(omp_get_thread_num());
#else
    std::vector<std::thread> pool;
    pool.reserve(nthreads - 1);
    for (int t = 1; t < nthreads; ++t) pool.emplace_back(guarded, t);
    guarded(0);
    for (auto &th : pool) th.join();
#endif
    if (err) std::rethrow_exception(err);
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

}  // namespace fastmac
