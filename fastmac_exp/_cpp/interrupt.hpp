// Ctrl-C inside the core: the Python binding installs a poll function (it takes the GIL and runs the
// interpreter's pending signal handlers); long loops call Interrupt::check() from the calling thread,
// which polls at most every few milliseconds, and stop when it reports an interrupt.
#pragma once

#include <atomic>
#include <chrono>
#include <stdexcept>

namespace fastmac {

// Thrown by a search that stopped because the user interrupted it (Python sees KeyboardInterrupt).
struct Interrupted : std::runtime_error {
    Interrupted() : std::runtime_error("interrupted") {}
};

using PollFn = bool (*)();  // true = an interrupt is pending
void set_interrupt_poll(PollFn fn);
bool poll_interrupt();  // calls the installed function (false when none)

// Rate-limited polling for one search, to be called from the thread that entered the core.
class Interrupt {
   public:
    bool check() {
        if (hit_) return true;
        const auto now = std::chrono::steady_clock::now();
        if (now - last_ < std::chrono::milliseconds(20)) return false;
        last_ = now;
        hit_ = poll_interrupt();
        return hit_;
    }
    bool hit() const { return hit_; }

   private:
    std::chrono::steady_clock::time_point last_ = std::chrono::steady_clock::now();
    bool hit_ = false;
};

// Ctrl-C for the loops of one parallel region: thread 0 (the caller) polls at its checks, and every
// thread leaves its loop at its next check once one is seen; after the region, throw_if_hit() throws
// Interrupted. Loops check once per chunk of work (a few milliseconds at most).
class InterruptibleRegion {
   public:
    bool stopped(int tid) {
        if (tid == 0 && !hit_.load(std::memory_order_relaxed) && interrupt_.check())
            hit_.store(true, std::memory_order_relaxed);
        return hit_.load(std::memory_order_relaxed);
    }
    void throw_if_hit() const {
        if (hit_.load()) throw Interrupted();
    }

   private:
    Interrupt interrupt_;
    std::atomic<bool> hit_{false};
};

}  // namespace fastmac
