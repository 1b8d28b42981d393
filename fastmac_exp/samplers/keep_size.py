"""`samples=auto`: the keep's size from the scores (docs/keep_size.md).

A keep needs enough inliers for MAC to find the consensus, and every inlier beyond that costs MAC cubic
time, so the size is set by the inliers the keep is expected to hold, not by N or a fraction:

1. the estimated dense core: with FastMAC's self-loops a node in a consistent group of m mutually
   compatible nodes has generalized degree s_i = (W^3)_ii ~ m^2, so r_i = sqrt(s_i - 1) ~ m. The core's
   size m^ is the largest m with at least m nodes of r_i >= share * m (an h-index of r / share); its
   members are those nodes. Inliers are the group; outliers' r is small.
2. the draw's expected inclusion: successive sampling in proportion to the scores pi (the Gumbel-top-k
   draw) includes node i with probability ~ 1 - exp(-lambda pi_i), lambda set by the keep's size
   (Rosen's approximation of successive sampling, "Asymptotic theory for successive sampling", Ann. Math.
   Stat. 1972). Where the core holds at least `core_inliers` nodes (inliers plentiful and consistent), the
   keep is the smallest whose expected core members reach `core_inliers`, at least `min_keep`.
3. where the core is smaller (inliers scarce, or a sparse graph whose scores separate them poorly), the
   keep must not lose the few there are: the smallest keep expected to hold `scarce_cover` of the core,
   and at least N * min(1, scarce_ratio * core_inliers / core) of the nodes: ratio 0.2's keep, or a
   superset of it (the Gumbel-top-k draw of k + j nodes extends the draw of k), from a core of 200 down,
   all N (plain MAC) from a core of scarce_ratio * core_inliers (40) down.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from fastmac_exp.errors import InputError

AUTO = "auto"


@dataclass(frozen=True)
class KeepParams:
    """samples=auto's rule: the expected core members a keep should hold, its floor and the core's share."""

    core_inliers: float = 200.0  # expected members of the estimated dense core in the keep
    min_keep: int = 500  # fewest kept (or N where smaller)
    core_share: float = 0.5  # a core member's sqrt(s - 1) is at least this share of the core's size
    scarce_cover: float = 0.9  # a core smaller than core_inliers: the share of it the keep should hold
    scarce_ratio: float = 0.2  # ... and the keep at least N * min(1, scarce_ratio * core_inliers / core)

    def __post_init__(self) -> None:
        if not (np.isfinite(self.core_inliers) and self.core_inliers >= 3):
            raise InputError(f"sampler.keep.core_inliers must be a number >= 3, got {self.core_inliers!r}")
        if isinstance(self.min_keep, bool) or not isinstance(self.min_keep, int) or self.min_keep < 3:
            raise InputError(f"sampler.keep.min_keep must be an integer >= 3, got {self.min_keep!r}")
        for key in ("core_share", "scarce_cover", "scarce_ratio"):
            v = getattr(self, key)
            if not (isinstance(v, int | float) and 0.0 < v <= 1.0):
                raise InputError(f"sampler.keep.{key} must be in (0, 1], got {v!r}")


def keep_params(value: KeepParams | dict | None) -> KeepParams:
    if value is None or isinstance(value, KeepParams):
        return value or KeepParams()
    try:
        return KeepParams(**dict(value))
    except TypeError as exc:
        raise InputError(f"sampler.keep: {exc}") from None


def is_auto(value: object) -> bool:
    return isinstance(value, str) and value == AUTO


def dense_core(degree: np.ndarray, share: float = 0.5) -> np.ndarray:
    """The estimated dense core's members (a boolean mask) from the generalized degrees (module doc, 1)."""
    r = np.sqrt(np.maximum(np.asarray(degree, dtype=np.float64) - 1.0, 0.0)) / share
    desc = -np.sort(-r)
    # the largest m (1-based) with desc[m - 1] >= m
    hits = np.flatnonzero(desc >= np.arange(1, len(desc) + 1))
    m = int(hits[-1]) + 1 if len(hits) else 0
    if m == 0:
        return np.zeros(len(r), dtype=bool)
    return r >= m


def expected_inclusion(scores: np.ndarray, lam: float) -> np.ndarray:
    return -np.expm1(-lam * scores)


def keep_covering(scores: np.ndarray, members: np.ndarray, target: float) -> int | None:
    """The smallest keep whose draw holds `target` of `members` in expectation (None: no keep does)."""
    pos = scores > 0
    top = scores[pos].max() if pos.any() else 0.0
    cs = scores[members & pos] / top if top > 0 else np.zeros(0)
    if len(cs) == 0 or len(cs) * (1.0 - 1e-9) < target:
        return None
    s = scores[pos] / top
    # lambda with sum over the members of 1 - exp(-lambda pi_i) = target: bisection in log lambda
    lo, hi = 1e-12, 1.0
    while expected_inclusion(cs, hi).sum() < target:
        hi *= 4.0
        if hi > 1e30:
            return None
    for _ in range(80):
        mid = np.sqrt(lo * hi)
        if expected_inclusion(cs, mid).sum() < target:
            lo = mid
        else:
            hi = mid
        if hi / lo < 1.0 + 1e-6:
            break
    return int(np.ceil(expected_inclusion(s, hi).sum()))


def auto_keep(scores: np.ndarray, degree: np.ndarray, kp: KeepParams = KeepParams()) -> tuple[int, int]:
    """(k, the estimated core's size) by the module's rule (2 where the core is large, 3 where scarce)."""
    scores = np.asarray(scores, dtype=np.float64)
    n = len(scores)
    core = dense_core(degree, kp.core_share)
    m = int(core.sum())
    if m >= kp.core_inliers:
        k = keep_covering(scores, core, kp.core_inliers)
        floor = kp.min_keep
    else:
        k = keep_covering(scores, core, kp.scarce_cover * m) if m > 0 else None
        floor = max(kp.min_keep, int(np.ceil(n * min(1.0, kp.scarce_ratio * kp.core_inliers / max(m, 1)))))
    return (n if k is None else int(min(n, max(floor, k)))), m
