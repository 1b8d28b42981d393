"""The learned front ends' per-keypoint progress bar."""

from __future__ import annotations

from typing import Any


def keypoint_bar(total: int, label: str, enabled: bool, batch_size: int) -> Any:
    """A tqdm bar over a cloud's `total` keypoints, or a disabled one: when `enabled` is False (the run's
    progress=false, the descriptor's progress=false), for a short cloud (under four batches), and where
    stderr is not a terminal (tqdm's disable=None), so that a log or CI gets no carriage-return line per
    batch."""
    from tqdm import tqdm

    tqdm.monitor_interval = 0  # no monitor thread: a timer thread could take the run's Ctrl-C (interrupts.py)

    show = enabled and total >= 4 * batch_size
    return tqdm(total=total, desc=label, unit="kp", leave=False, disable=None if show else True)
