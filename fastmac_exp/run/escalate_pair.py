"""`escalate=auto` for run.py: a pair whose pose is not trusted runs the escalation's wider steps
(fastmac_exp.escalation.STEPS), as register() does, with the run's own parts changed step by step.

Off by default in run.py (a run measures its configuration, the paper's protocol); a run that wants a
dependable pose per pair (user pairs without GT) turns it on. The row is the chosen step's, with
`escalation_step`, `escalation` (each step tried: name, ms, trusted, confidence, error) and the time of
the whole escalation (`t_escalation_ms`).
"""

from __future__ import annotations

import dataclasses
import json
import time
from collections.abc import Callable
from typing import Any

from omegaconf import DictConfig, OmegaConf

from fastmac_exp.escalation import Step, available_steps, escalate
from fastmac_exp.families import FIXED_RESOLUTION
from fastmac_exp.pipeline import PairOutcome
from fastmac_exp.types import Pair, RegistrationResult


class StepParts:
    """The parts each step runs with, built once per process from the run's config."""

    def __init__(self, cfg: DictConfig, descriptor: Any, sampler: Any) -> None:
        self.cfg, self.descriptor, self.sampler = cfg, descriptor, sampler
        self._built: dict[str, Any] = {}

    def _part(self, key: str, make: Callable[[], Any]) -> Any:
        if key not in self._built:
            self._built[key] = make()
        return self._built[key]

    def fpfh(self) -> bool:
        return "mutual" in self.cfg.descriptor and "voxel_size" in self.cfg.descriptor

    def for_step(self, step: Step, pair: Pair) -> tuple[Pair, Any, Any, Any, bool]:
        """(pair, descriptor, sampler, samples, describes_alike) of one step; describes_alike: the run's
        correspondence cache holds this step's matches."""
        from hydra.utils import instantiate

        from fastmac_exp.options import compose_run
        from fastmac_exp.run.checks import run_samples

        ch = step.changes
        sampler = self.sampler
        if ch.get("sampler") == "none":
            sampler = self._part("none", lambda: instantiate(compose_run({"sampler": "none"}).sampler))
        samples = ch.get("samples", run_samples(self.cfg))
        descriptor, alike = self.descriptor, True
        if ch.get("resolution") == "fixed":
            pair = dataclasses.replace(pair, resolution=FIXED_RESOLUTION)
        if ch.get("mutual"):
            node = OmegaConf.merge(self.cfg.descriptor, {"mutual": True})
            descriptor, alike = self._part("mutual", lambda: instantiate(node)), False
        if "voxel_scale" in ch:
            pair = dataclasses.replace(pair, voxel_size=pair.voxel_size * ch["voxel_scale"])
            alike = False
        if ch.get("descriptor"):
            node = OmegaConf.merge(
                compose_run({"descriptor": ch["descriptor"]}).descriptor, {"progress": False}
            )
            descriptor, alike = self._part(ch["descriptor"], lambda: instantiate(node)), False
        return pair, descriptor, sampler, samples, alike


def escalate_pair(
    first: PairOutcome,
    pair: Pair,
    parts: StepParts,
    run_step: Callable[[Pair, Any, Any, Any, bool], PairOutcome],
    budget_s: float,
) -> PairOutcome:
    """The first outcome, or, where it is not trusted, the best of the escalation's steps."""
    outcomes: dict[str, PairOutcome] = {"first": first}
    clouds = pair.correspondences is None and pair.src_cloud is not None
    steps = available_steps(clouds, parts.fpfh())

    def attempt(step: Step) -> RegistrationResult:
        out = first if step.name == "first" else run_step(*parts.for_step(step, pair))
        outcomes[step.name] = out
        if out.result is not None:
            return out.result
        return RegistrationResult(pose=_nan(), pose_unrefined=_nan(), kept=_empty(), clique=_empty(),
                                  error=str(out.row.get("error") or "no result"))  # fmt: skip

    t0 = time.perf_counter()
    best = escalate(attempt, steps, budget_s)
    chosen = outcomes[best.step]
    row = dict(chosen.row)
    row["escalation_step"] = best.step
    row["escalation"] = json.dumps([{k: (round(v, 3) if isinstance(v, float) else v) for k, v in s.items()}
                                    for s in best.escalation])  # fmt: skip
    row["t_escalation_ms"] = (time.perf_counter() - t0) * 1e3
    chosen.row = row
    return chosen


def _nan():
    import numpy as np

    return np.full((4, 4), np.nan)


def _empty():
    import numpy as np

    return np.zeros(0, np.int64)
