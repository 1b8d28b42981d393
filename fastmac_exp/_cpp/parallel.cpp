// The persistent worker pool behind parallel_region (see parallel.hpp).
#include "parallel.hpp"

#include <condition_variable>
#include <thread>
#include <vector>

#include <pthread.h>
#include <signal.h>
#include <unistd.h>

namespace fastmac {
namespace detail {

namespace {

class Pool {
   public:
    Pool() : pid_(getpid()) {}
    // Never destroyed (it is leaked on purpose): workers may be blocked in wait() at process exit.

    pid_t pid() const { return pid_; }

    void run(int nthreads, void (*fn)(void *, int), void *ctx) {
        // One region at a time; a concurrent caller (another Python thread) runs its region alone.
        std::unique_lock<std::mutex> region(region_mu_, std::try_to_lock);
        if (!region.owns_lock()) {
            fn(ctx, 0);
            return;
        }
        {
            std::lock_guard<std::mutex> lock(mu_);
            const size_t want = (size_t)std::min(nthreads - 1, 255);
            const uint64_t before = generation_;  // new workers start out looking for the next region
            if (threads_.size() < want) {
                // Created with the interrupts blocked, so that a new worker never holds them open, not even
                // until it first runs (on a loaded machine that can be long): a signal meanwhile waits here.
                sigset_t old;
                pthread_sigmask(SIG_BLOCK, &interrupt_signals(), &old);
                while (threads_.size() < want) threads_.emplace_back([this, before] { worker(before); });
                pthread_sigmask(SIG_SETMASK, &old, nullptr);
            }
            fn_ = fn;
            ctx_ = ctx;
            slots_ = (int)want;
            next_tid_ = 1;
            active_ = 0;
            open_ = true;
            err_ = nullptr;
            ++generation_;
        }
        work_cv_.notify_all();
        std::exception_ptr mine;
        try {
            fn(ctx, 0);
        } catch (...) {
            mine = std::current_exception();
        }
        std::exception_ptr theirs;
        {
            // The caller's share is done only when the work is exhausted, so workers that have not
            // joined yet would find nothing: close the region and wait for those that did join.
            std::unique_lock<std::mutex> lock(mu_);
            open_ = false;
            done_cv_.wait(lock, [this] { return active_ == 0; });
            theirs = err_;
            err_ = nullptr;
        }
        if (mine) std::rethrow_exception(mine);
        if (theirs) std::rethrow_exception(theirs);
    }

   private:
    // A process-directed Ctrl-C or SIGTERM is for Python's main thread: a worker that took it would leave
    // the main thread asleep in whatever it waits on (a read, a lock) with the signal gone.
    static const sigset_t &interrupt_signals() {
        static const sigset_t set = [] {
            sigset_t s;
            sigemptyset(&s);
            for (int sig : {SIGINT, SIGTERM, SIGHUP, SIGQUIT, SIGALRM, SIGUSR1, SIGUSR2, SIGCHLD, SIGWINCH})
                sigaddset(&s, sig);
            return s;
        }();
        return set;
    }

    void worker(uint64_t seen) {
        pthread_sigmask(SIG_BLOCK, &interrupt_signals(), nullptr);  // (inherited blocked already: run())
        std::unique_lock<std::mutex> lock(mu_);
        for (;;) {
            work_cv_.wait(lock, [&] { return generation_ != seen; });
            seen = generation_;
            if (!open_ || next_tid_ > slots_) continue;
            const int tid = next_tid_++;
            ++active_;
            void (*fn)(void *, int) = fn_;
            void *ctx = ctx_;
            lock.unlock();
            std::exception_ptr err;
            try {
                fn(ctx, tid);
            } catch (...) {
                err = std::current_exception();
            }
            lock.lock();
            if (err && !err_) err_ = err;
            if (--active_ == 0) done_cv_.notify_all();
        }
    }

    const pid_t pid_;
    std::mutex region_mu_;
    std::mutex mu_;
    std::condition_variable work_cv_, done_cv_;
    std::vector<std::thread> threads_;
    uint64_t generation_ = 0;
    bool open_ = false;
    int slots_ = 0, next_tid_ = 1, active_ = 0;
    void (*fn_)(void *, int) = nullptr;
    void *ctx_ = nullptr;
    std::exception_ptr err_;
};

std::mutex g_pool_mu;
std::atomic<Pool *> g_pool{nullptr};

Pool &pool() {
    Pool *p = g_pool.load(std::memory_order_acquire);
    // After fork() the child has none of the parent's threads: start a fresh pool there (the old
    // one, whose mutexes may have been held at the fork, is abandoned).
    if (p && p->pid() == getpid()) return *p;
    std::lock_guard<std::mutex> lock(g_pool_mu);
    p = g_pool.load(std::memory_order_acquire);
    if (!p || p->pid() != getpid()) {
        p = new Pool();
        g_pool.store(p, std::memory_order_release);
    }
    return *p;
}

}  // namespace

void pool_run(int nthreads, void (*fn)(void *, int), void *ctx) { pool().run(nthreads, fn, ctx); }

}  // namespace detail
}  // namespace fastmac
