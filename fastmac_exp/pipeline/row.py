"""The results row of one pair, filled stage by stage as the pair goes through the flow.

A pair that fails half way keeps what was measured before the failure, so the row starts with the run's
labels and each stage sets its own fields; fields no stage reached stay UNSET and are left out of the
row's dict (and so of results.jsonl), exactly as a missing measurement should be.
"""

from __future__ import annotations

import dataclasses
from dataclasses import dataclass, field
from typing import Any


class _Unset:
    def __repr__(self) -> str:
        return "UNSET"

    def __bool__(self) -> bool:
        return False


UNSET: Any = _Unset()


@dataclass
class PairRow:
    """One pair's results; `to_dict()` is the row of the results table (fastmac_exp.run.results)."""

    # the run's labels, set before the pair is loaded
    index: int
    pair: str
    dataset: str
    descriptor: str
    sampler: str
    backend: str
    ratio: float
    seed: int
    protocol: str
    error: str = ""
    # the pair
    scene: Any = UNSET
    family: Any = UNSET
    describe_cached: Any = UNSET  # True when the correspondences were read from the cache
    resolution: Any = UNSET
    n_in: Any = UNSET
    inliers_in: Any = UNSET
    inlier_ratio_in: Any = UNSET
    # sampling and MAC
    samples: Any = UNSET  # the sample size asked for as a count (`samples=K` or auto; ratio is then k / N)
    scores: Any = UNSET  # graph-filter samplers: "exact" or "estimate" (what sampler.scores=auto chose)
    anchors: Any = UNSET  # the estimate's anchors (0 for exact scores)
    core: Any = UNSET  # samples=auto: the estimated dense core that sized the keep (docs/keep_size.md)
    engine: Any = UNSET  # what computed the sampler's graph signals: cpp, torch:<device> or python
    n_kept: Any = UNSET
    inlier_ratio_kept: Any = UNSET
    clique_size: Any = UNSET
    clique_inliers: Any = UNSET
    pose_inliers: Any = UNSET  # correspondences within the inlier threshold under the pose: a confidence
    trusted: Any = UNSET  # GT-free: the pose explains more correspondences than chance (geometry.trust)
    confidence: Any = UNSET  # ... 1 - its false-accept chance, what `trusted` thresholds
    chance_inliers: Any = UNSET  # ... the evidence: what chance explains under the pose (lambda)
    rival_inliers: Any = UNSET  # ... what the best distinct hypothesis explains (NaN: none)
    decoy_count: Any = UNSET  # ... what the search explains beyond chance on permuted matches (NaN: not run)
    score: Any = UNSET
    n_edges: Any = UNSET
    n_cliques: Any = UNSET
    n_selected: Any = UNSET
    reduced: Any = UNSET
    search: Any = UNSET
    search_nodes: Any = UNSET
    cap_hit: Any = UNSET
    zero_filled: Any = UNSET
    # the verdict
    re_deg: Any = UNSET
    te_cm: Any = UNSET
    success: Any = UNSET
    timings: dict[str, float] = field(default_factory=dict)  # ms per stage -> t_<stage>_ms columns
    pose: Any = UNSET  # the final pose, 16 numbers row-major

    def set(self, **values: Any) -> None:
        """Set several fields at once; an unknown name is a programming error, not a new column."""
        for k, v in values.items():
            if not hasattr(self, k) or k == "timings":
                raise AttributeError(f"PairRow has no field {k!r}")
            setattr(self, k, v)

    def to_dict(self) -> dict[str, Any]:
        out: dict[str, Any] = {}
        for f in dataclasses.fields(self):
            if f.name == "timings":
                continue
            if f.name == "pose":
                out.update({f"t_{stage}_ms": ms for stage, ms in self.timings.items()})
            v = getattr(self, f.name)
            if v is not UNSET:
                out[f.name] = v
        return out
