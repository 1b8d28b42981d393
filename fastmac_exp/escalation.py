"""What register() tries when a pose is not trusted: the steps, cheapest first, and the loop over them.

Each step is the user's call with a few options changed. The order is by cost and by evidence (docs/trust.md,
"Escalation"): the cheap sampling-side steps reuse the first step's correspondences; the steps that match
again (mutual matching, a finer keypoint voxel) describe the clouds again; a learned descriptor (BUFFER,
seconds a pair on a CPU) is last, where ONNX Runtime is installed. The loop stops at the first trusted
pose, or when the time budget is spent (a step that has started runs to its end), and otherwise returns
the most confident pose, untrusted.
"""

from __future__ import annotations

import time
from collections.abc import Callable, Sequence
from dataclasses import dataclass, field
from typing import Any

from fastmac_exp.types import RegistrationResult

ESCALATE_CHOICES = ("auto", "off")
# the default time budget of an escalation (s): the learned step alone costs 5-10 s a pair on 2 cores
DEFAULT_BUDGET_S = 30.0


@dataclass(frozen=True)
class Step:
    name: str
    changes: dict[str, Any] = field(default_factory=dict)  # register()'s keywords this step overrides
    clouds_only: bool = False  # it describes again: no step for a Correspondences input
    needs: str = ""  # a module that must import (the learned step: onnxruntime)


# FastMAC@20 (the call itself), then wider searches on the same matches, then other matches
STEPS: tuple[Step, ...] = (
    Step("first"),
    Step("samples_auto", {"samples": "auto"}),
    Step("mac_all", {"sampler": "none", "samples": None}),
    Step(
        "mac_fixed_resolution", {"sampler": "none", "samples": None, "resolution": "fixed"}, clouds_only=True
    ),
    Step("mutual", {"sampler": "none", "samples": None, "mutual": True}, clouds_only=True),
    Step("finer_voxel", {"sampler": "none", "samples": None, "voxel_scale": 0.75}, clouds_only=True),
    Step(
        "learned",
        {"descriptor": "buffer", "samples": "auto", "progress": False},
        clouds_only=True,
        needs="onnxruntime",
    ),
)


def available_steps(clouds: bool, fpfh: bool) -> list[Step]:
    """The steps that apply to a call: those that describe again need clouds, and the FPFH-option steps
    (mutual, finer voxel) a call that describes with FPFH; the learned step needs its runtime."""
    import importlib.util

    out = []
    for s in STEPS:
        if s.clouds_only and not clouds:
            continue
        if s.name in ("mutual", "finer_voxel") and not fpfh:
            continue
        if s.needs and importlib.util.find_spec(s.needs) is None:
            continue
        out.append(s)
    return out


def escalate(
    attempt: Callable[[Step], RegistrationResult], steps: Sequence[Step], budget_s: float = DEFAULT_BUDGET_S
) -> RegistrationResult:
    """Run `attempt` on each step until one returns a trusted pose or the budget is spent; the result
    carries `step` (which step gave the pose) and `escalation` (each step tried: name, ms, trusted,
    confidence, error)."""
    t0 = time.perf_counter()
    tried: list[dict[str, Any]] = []
    best: RegistrationResult | None = None
    for i, step in enumerate(steps):
        if i and time.perf_counter() - t0 >= budget_s:
            tried.append({"step": step.name, "ms": 0.0, "trusted": False, "confidence": 0.0,
                          "error": f"not tried: the budget of {budget_s:g} s was spent"})  # fmt: skip
            continue
        t1 = time.perf_counter()
        res = attempt(step)
        res.step = step.name
        tried.append({"step": step.name, "ms": (time.perf_counter() - t1) * 1e3, "trusted": bool(res.trusted),
                      "confidence": float(res.confidence), "error": res.error})  # fmt: skip
        if best is None or _better(res, best):
            best = res
        if res.trusted:
            break
    assert best is not None
    best.escalation = tried
    return best


def _better(a: RegistrationResult, b: RegistrationResult) -> bool:
    """A trusted pose beats an untrusted one, a pose beats none, then the more confident (then the
    earlier)."""
    return (a.trusted, a.ok, a.confidence) > (b.trusted, b.ok, b.confidence)
