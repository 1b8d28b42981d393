"""Ctrl-C and SIGTERM for the main thread only.

Python runs signal handlers in its main thread, but the kernel hands a signal sent to the process to any
thread that does not block it. A helper thread that takes it (an OpenBLAS worker yielding after a product,
a timer thread waking) leaves the main thread asleep in whatever it waits on (a read, a lock) while the
signal is gone: the run does not stop. Threads created inside `interrupts_blocked()` inherit the blocked
mask (the libraries that start worker threads when they load: numpy's and scipy's OpenBLAS, onnxruntime's
sessions); `block_interrupts` is the initializer for a thread pool's own workers. The C++ core's pool
blocks them in its workers itself (parallel.cpp)."""

from __future__ import annotations

import signal
import threading
from collections.abc import Iterator
from contextlib import contextmanager

INTERRUPTS = (signal.SIGINT, signal.SIGTERM)


@contextmanager
def interrupts_blocked() -> Iterator[None]:
    """SIGINT and SIGTERM blocked in the calling (main) thread while the block runs, then restored: a signal
    that arrives meanwhile waits and is handled right after."""
    if not hasattr(signal, "pthread_sigmask") or threading.current_thread() is not threading.main_thread():
        yield
        return
    old = signal.pthread_sigmask(signal.SIG_BLOCK, INTERRUPTS)
    try:
        yield
    finally:
        signal.pthread_sigmask(signal.SIG_SETMASK, old)


def block_interrupts() -> None:
    """Blocks SIGINT and SIGTERM in the calling thread (a worker's initializer)."""
    if hasattr(signal, "pthread_sigmask"):
        signal.pthread_sigmask(signal.SIG_BLOCK, INTERRUPTS)
