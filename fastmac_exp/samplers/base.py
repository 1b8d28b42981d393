"""The sampler interface and the draw they share: score the nodes, then keep k = floor(N * ratio) of them.

Draws use Gumbel-top-k keys (log score + Gumbel noise), which is distributed exactly like successive
draws in proportion to the remaining scores (torch.multinomial without replacement) and lets the numpy,
C++ and torch paths give identical samples for the same uniform numbers.
"""

from __future__ import annotations

import time
from dataclasses import dataclass, field

import numpy as np

from fastmac_exp.errors import InputError
from fastmac_exp.params import GraphParams
from fastmac_exp.samplers.keep_size import is_auto
from fastmac_exp.types import Correspondences


@dataclass
class SampleResult:
    """Kept indices in draw order, the per-node scores (if any) and what happened."""

    indices: np.ndarray
    scores: np.ndarray | None = None
    zero_filled: int = 0  # samples drawn uniformly because fewer than k nodes had a positive score
    # ms: "sampling" (all of it) and, where the sampler has them, its two stages: "sampling_prep" (scores:
    # graph and signal, or the eigendecomposition) and "sampling_draw" (the draw or the greedy selection)
    timings: dict[str, float] = field(default_factory=dict)
    ratio: float = 1.0  # the ratio the sampler used: k / N (1.0 for `none`, whatever was asked)
    scores_used: str = ""  # graph filters: "exact" or "estimate" (what `scores=auto` chose)
    anchors: int = 0  # the estimate's anchors (0: exact scores)
    core: int = 0  # samples=auto: the estimated dense core's size that set the keep (0: not auto)


def sample_count(n: int, ratio: float, min_count: int = 3) -> int:
    """k = floor(n * ratio); ratio must lie in (0, 1] and k must allow a clique of `min_count`."""
    if isinstance(ratio, bool) or not (isinstance(ratio, int | float) and 0.0 < float(ratio) <= 1.0):
        raise InputError(f"ratio must be in (0, 1], got {ratio!r}")
    k = n if ratio >= 1.0 else int(np.floor(n * ratio + 1e-9))
    if k < min_count:
        raise InputError(
            f"ratio={ratio} keeps {k} of {n} correspondences, fewer than the {min_count} a clique needs; "
            f"use ratio >= {min_count / max(n, 1):.4g}"
        )
    return k


def count_from_samples(n: int, samples: int, min_count: int = 3) -> int:
    """k = min(samples, n): a sample size given as a count (FastMAC's KITTI code draws a fixed count)."""
    if isinstance(samples, bool) or not isinstance(samples, int | np.integer) or samples < min_count:
        raise InputError(f"samples must be an integer >= {min_count} (a clique's size), got {samples!r}")
    return min(int(samples), n)


def gumbel_keys(scores: np.ndarray, uniforms: np.ndarray) -> np.ndarray:
    """log(score) + Gumbel noise; -inf where the score is 0 (such nodes are drawn last, uniformly)."""
    with np.errstate(divide="ignore"):
        return np.log(scores) - np.log(-np.log(uniforms))


def draw_proportional(scores: np.ndarray, k: int, rng: np.random.Generator) -> tuple[np.ndarray, int]:
    """k indices without replacement, in draw order, with probability proportional to `scores`.

    If fewer than k scores are positive, the rest are drawn uniformly from the zero-score nodes and
    their count is returned (the reference code raises instead, spec 7.4).
    """
    scores = np.asarray(scores, dtype=np.float64)
    if not np.isfinite(scores).all() or (scores < 0).any():
        raise InputError("sampling scores must be finite and non-negative")
    u = rng.random(len(scores))
    u = np.clip(u, np.finfo(np.float64).tiny, 1.0 - np.finfo(np.float64).epsneg)
    pos = np.flatnonzero(scores > 0)
    zero_filled = max(0, k - len(pos))
    # positive scores by their Gumbel keys; then, if needed, the zero-score nodes in the order of their
    # own uniforms (a uniformly random order: ranking them by a key such as -1e300 - u would not be,
    # since -1e300 - u == -1e300 in float64 and a stable sort then keeps index order)
    order = pos[np.argsort(-gumbel_keys(scores[pos], u[pos]), kind="stable")][:k]
    if zero_filled:
        zero = np.flatnonzero(~(scores > 0))
        order = np.concatenate([order, zero[np.argsort(u[zero], kind="stable")][:zero_filled]])
    return order.astype(np.int64), zero_filled


def minmax(r: np.ndarray) -> np.ndarray:
    span = r.max() - r.min() if len(r) else 0.0
    return (r - r.min()) / span if span > 0 else np.zeros_like(r)


class Sampler:
    """Base class: subclasses implement `scores` or override `select`."""

    name = "base"
    keeps_everything = False  # True: the ratio is ignored (plain MAC)

    def sample(
        self,
        corr: Correspondences,
        ratio: float | str,
        gp: GraphParams,
        family: str,
        rng: np.random.Generator,
        samples: int | str | None = None,
    ) -> SampleResult:
        """Keep k = floor(N * ratio), or k = min(samples, N) when `samples` is given (it wins over ratio);
        samples="auto" (or ratio="auto") sizes the keep from the scores (samplers that have them)."""
        n = len(corr)
        if is_auto(samples) or (samples is None and is_auto(ratio)):
            t0 = time.perf_counter()
            res = self.select_auto(corr, gp, family, rng)
            res.timings["sampling"] = (time.perf_counter() - t0) * 1e3
            res.ratio = len(res.indices) / max(n, 1)
            return res
        k = sample_count(n, ratio) if samples is None else count_from_samples(n, samples)
        t0 = time.perf_counter()
        if k >= n:
            res = SampleResult(indices=np.arange(n, dtype=np.int64))
        else:
            res = self.select(corr, k, gp, family, rng)
        res.timings["sampling"] = (time.perf_counter() - t0) * 1e3
        res.ratio = float(ratio) if samples is None else len(res.indices) / max(n, 1)
        return res

    def select_auto(
        self, corr: Correspondences, gp: GraphParams, family: str, rng: np.random.Generator
    ) -> SampleResult:
        """The keep sized from the scores (samples=auto): graph-filter samplers only."""
        raise InputError(
            f"samples=auto sizes the keep from the graph's scores: sampler {self.name!r} has none "
            "(use highpass, lowpass or allpass, or give samples as a count)"
        )

    def select(
        self, corr: Correspondences, k: int, gp: GraphParams, family: str, rng: np.random.Generator
    ) -> SampleResult:
        t0 = time.perf_counter()
        scores, info = self.scored(corr, gp, family, rng)
        t1 = time.perf_counter()
        idx, zero_filled = draw_proportional(scores, k, rng)
        timings = {"sampling_prep": (t1 - t0) * 1e3, "sampling_draw": (time.perf_counter() - t1) * 1e3}
        return SampleResult(indices=idx, scores=scores, zero_filled=zero_filled, timings=timings, **info)

    def scored(
        self, corr: Correspondences, gp: GraphParams, family: str, rng: np.random.Generator
    ) -> tuple[np.ndarray, dict]:
        """The scores and what made them (SampleResult fields: graph filters say exact or estimated)."""
        return self.scores(corr, gp, family, rng), {}

    def scores(
        self, corr: Correspondences, gp: GraphParams, family: str, rng: np.random.Generator
    ) -> np.ndarray:
        raise NotImplementedError
