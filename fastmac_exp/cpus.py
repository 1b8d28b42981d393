"""How many cores this process may run on: what a run's workers and the learned descriptors' lanes size
themselves by."""

from __future__ import annotations

import os


def available_cores() -> int:
    """The cores this process may run on (its affinity: a cgroup or taskset may allow fewer than exist)."""
    try:
        return max(len(os.sched_getaffinity(0)), 1)
    except AttributeError:  # no sched_getaffinity (macOS)
        return max(os.cpu_count() or 1, 1)
