"""A pair's stage timings taken back to back: each lap starts where the last one ended, so the stages add up
to the pair's end-to-end time by construction (nothing it spends time in falls between two stages)."""

from __future__ import annotations

import time
from dataclasses import dataclass, field


@dataclass
class Stopwatch:
    ms: dict[str, float] = field(default_factory=dict)  # stage -> milliseconds, in the order first timed
    last: float = field(default_factory=lambda: time.perf_counter())

    def lap(self, stage: str) -> float:
        """Adds the time since the last lap to `stage` (a stage timed twice sums); returns it in ms."""
        now = time.perf_counter()
        elapsed = (now - self.last) * 1e3
        self.last = now
        self.ms[stage] = self.ms.get(stage, 0.0) + elapsed
        return elapsed

    def lap_in_parts(self, parts: dict[str, float], rest: str = "other") -> None:
        """A lap that its callee timed inside: its parts (ms), and `rest` for what they leave of the lap
        (for register_correspondences: validation, subsetting, the backend's conversions)."""
        elapsed = self.lap(rest)
        self.ms[rest] -= elapsed
        for stage, ms in parts.items():
            self.ms[stage] = self.ms.get(stage, 0.0) + ms
        self.ms[rest] += elapsed - sum(parts.values())

    def timings(self, total: float) -> dict[str, float]:
        """A pair's `timings`: every stage, `total` (sampling + MAC, the papers' registration time) and
        `end_to_end` (the sum of the stages: the pair's whole time, nothing left out)."""
        return {**self.ms, "total": total, "end_to_end": sum(self.ms.values())}


def registration_parts(timings: dict[str, float]) -> dict[str, float]:
    """register_correspondences' stages without `total`, which overlaps them."""
    return {k: v for k, v in timings.items() if k != "total"}
