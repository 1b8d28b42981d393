"""Estimated sampler signals: anchors instead of the whole graph (docs/estimated_scores.md).

The exact signals need every first-order pair (N^2 / 2 tests) and every triangle of the graph; the
estimate tests every node against m anchor correspondences only. Anchors are drawn in two stages:
a pilot of `pilot_anchors` nodes, uniform without replacement, gives every node a first-order degree
estimate d~; then `anchors` draws, i.i.d. and with replacement, from the defensive mixture
q = (1 - mix) d~^power / sum d~^power + mix / N (Hesterberg 1995), which puts the anchors where the
triangles are (the consistent group) while every node keeps a positive probability. The C++ core then
forms importance-weighted (Horvitz-Thompson) estimates of the degree and of the filter terms; the
estimate of the generalized degree is unbiased given the pilot. All randomness comes from `rng`.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from fastmac_exp.errors import InputError
from fastmac_exp.params import GraphParams
from fastmac_exp.types import GraphSignals


@dataclass(frozen=True)
class EstimateParams:
    """The estimate's budget: anchors of the signal stage and of the pilot, and the pilot's weighting."""

    anchors: int = 2048  # most i.i.d. draws from q; cost N * anchors tests + sum_i (compatible anchors)^2 / 2
    min_anchors: int = 32  # fewest draws, whatever the pair budget
    pair_budget: float = 4e6  # pair work allowed: the longest prefix of 32 * 2^k draws within
    pair_budget_per_node: float = 200.0  # max(pair_budget, this * N)
    pilot_anchors: int = 1024  # uniform pilot nodes (without replacement)
    power: float = 1.0  # q ~ pilot degree ** power
    uniform_mix: float = 0.1  # share of q that stays uniform (defensive mixture)
    max_tests: float = 1.5e9  # node-anchor tests of the three passes: caps pilot and anchors at large N

    def pilot_size(self, n: int) -> int:
        return int(min(self.pilot_anchors, n, max(128, self.max_tests / (4 * n))))

    def anchor_cap(self, n: int) -> int:
        return int(min(self.anchors, max(self.min_anchors, self.max_tests / (2 * n))))

    def __post_init__(self) -> None:
        if not (isinstance(self.anchors, int) and self.anchors >= 2):
            raise InputError(f"sampler.estimate.anchors must be an integer >= 2, got {self.anchors!r}")
        if not (isinstance(self.min_anchors, int) and 2 <= self.min_anchors <= self.anchors):
            raise InputError(
                f"sampler.estimate.min_anchors must be an integer in [2, anchors={self.anchors}], "
                f"got {self.min_anchors!r}"
            )
        if not (self.pair_budget >= 0 and self.pair_budget_per_node >= 0):
            raise InputError("sampler.estimate.pair_budget and pair_budget_per_node must be >= 0")
        if not (isinstance(self.pilot_anchors, int) and self.pilot_anchors >= 1):
            raise InputError(
                f"sampler.estimate.pilot_anchors must be an integer >= 1, got {self.pilot_anchors!r}"
            )
        if not (np.isfinite(self.power) and self.power >= 0):
            raise InputError(f"sampler.estimate.power must be finite and >= 0, got {self.power!r}")
        if not (self.max_tests > 0):
            raise InputError(f"sampler.estimate.max_tests must be positive, got {self.max_tests!r}")
        if not (0.0 < self.uniform_mix <= 1.0):
            raise InputError(f"sampler.estimate.uniform_mix must be in (0, 1], got {self.uniform_mix!r}")


@dataclass
class Pilot:
    """The pilot stage: uniform anchors and every node's first-order degree estimate (scaled to N)."""

    anchors: np.ndarray  # the pilot's nodes in draw order; the first `used` were tested
    degree: np.ndarray  # ~ sum_{j != i} W_ij
    used: int = 0

    def proposal(self, ep: EstimateParams) -> np.ndarray:
        """q: the anchors' sampling law (sums to 1, positive everywhere)."""
        n = len(self.degree)
        base = np.power(np.maximum(self.degree, 0.0), ep.power) if ep.power > 0 else np.ones(n)
        total = base.sum()
        if not (total > 0 and np.isfinite(total)):
            return np.full(n, 1.0 / n)
        return (1.0 - ep.uniform_mix) * base / total + ep.uniform_mix / n


# the pilot stops after its first block where the graph is dense (mean degree above this share of N): there
# 256 nodes already place the anchors well, and the pilot is the estimate's largest cost
PILOT_BLOCK = 256
DENSE_PILOT = 0.02


def pilot(
    src: np.ndarray,
    tgt: np.ndarray,
    gp: GraphParams,
    m0: int,
    rng: np.random.Generator,
    first_block: bool = False,
) -> Pilot:
    """The pilot's degrees from a uniform sample of up to m0 nodes. It stops after its first block of
    PILOT_BLOCK where the graph is dense, or always with first_block (auto's choice needs no more; the
    estimate then extends it with `extend`)."""
    from fastmac_exp import core

    n = len(src)
    m0 = min(m0, n)
    order = rng.choice(n, size=m0, replace=False)  # a uniformly random order: any prefix is a uniform sample
    used = min(PILOT_BLOCK, m0)
    p = Pilot(
        anchors=order, degree=core.anchor_degree(src, tgt, gp, np.sort(order[:used])) * ((n - 1) / used)
    )
    p.used = used
    return p if first_block else extend(src, tgt, gp, p)


def extend(src: np.ndarray, tgt: np.ndarray, gp: GraphParams, p: Pilot) -> Pilot:
    """The pilot's remaining nodes, unless its first block found the graph dense."""
    from fastmac_exp import core

    n, used, m0 = len(src), p.used, len(p.anchors)
    if used >= m0 or p.degree.mean() / (n - 1) >= DENSE_PILOT:
        return p
    rest = core.anchor_degree(src, tgt, gp, np.sort(p.anchors[used:]))
    degree = (p.degree * (used / (n - 1)) + rest) * ((n - 1) / m0)
    out = Pilot(anchors=p.anchors, degree=degree)
    out.used = m0
    return out


def estimate_signals(
    src: np.ndarray,
    tgt: np.ndarray,
    gp: GraphParams,
    rng: np.random.Generator,
    ep: EstimateParams = EstimateParams(),
    pilot_result: Pilot | None = None,
) -> GraphSignals:
    """FastMAC's degree, high-pass and low-pass signals estimated from anchors (module docstring)."""
    from fastmac_exp import core

    n = len(src)
    if n < 3:
        raise InputError(f"the estimate needs at least 3 correspondences, got {n}")
    p = (
        extend(src, tgt, gp, pilot_result)
        if pilot_result is not None
        else pilot(src, tgt, gp, ep.pilot_size(n), rng)
    )
    q = p.proposal(ep)
    a = rng.choice(n, size=ep.anchor_cap(n), replace=True, p=q)
    budget = max(ep.pair_budget, ep.pair_budget_per_node * n)
    m = core.anchors_within(src, tgt, gp, a, ep.min_anchors, budget)
    return core.anchor_signals(src, tgt, gp, a[:m], 1.0 / q[a[:m]])


# auto's cost model, in units of ~1 ns of one core, fixed (not timed) so that the choice is the same on
# every machine: the exact path screens N^2 / 2 pairs and walks the wedges of the dense core (~ sum of the
# squared degrees); the estimate tests N * anchors pairs and walks ~ pair_budget pairs.
EXACT_PAIR_COST = 0.5
EXACT_WEDGE_COST = 1.0
ESTIMATE_TEST_COST = 2.0
ESTIMATE_PAIR_COST = 2.0
EXACT_BELOW = 2000  # auto: exact without a pilot below this many correspondences


def predicted_costs(n: int, p: Pilot, ep: EstimateParams) -> tuple[float, float]:
    """(exact, estimate) work predicted from the pilot's degrees (units above)."""
    exact = EXACT_PAIR_COST * n * (n - 1) / 2 + EXACT_WEDGE_COST * float(np.sum(p.degree**2))
    budget = max(ep.pair_budget, ep.pair_budget_per_node * n)
    tests = n * (ep.pilot_size(n) + 2 * ep.anchor_cap(n))
    estimate = ESTIMATE_TEST_COST * tests + ESTIMATE_PAIR_COST * budget
    return exact, estimate


def choose_scores(
    src: np.ndarray, tgt: np.ndarray, gp: GraphParams, ep: EstimateParams, rng: np.random.Generator
) -> tuple[str, Pilot | None]:
    """auto: "exact" where its predicted cost is at most the estimate's, else "estimate" (with the pilot
    it ran, which the estimate reuses)."""
    n = len(src)
    if n < EXACT_BELOW:
        return "exact", None
    p = pilot(src, tgt, gp, ep.pilot_size(n), rng, first_block=True)
    exact, estimate = predicted_costs(n, p, ep)
    return ("exact" if exact <= estimate else "estimate"), p
