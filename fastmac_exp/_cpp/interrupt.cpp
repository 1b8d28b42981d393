#include "interrupt.hpp"

namespace fastmac {

namespace {
std::atomic<PollFn> g_poll{nullptr};
}

void set_interrupt_poll(PollFn fn) { g_poll.store(fn); }

bool poll_interrupt() {
    const PollFn fn = g_poll.load();
    return fn != nullptr && fn();
}

}  // namespace fastmac
