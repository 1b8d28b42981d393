"""The baselines: uniform random sampling, farthest point sampling, and no sampling (plain MAC)."""

from __future__ import annotations

import numpy as np

from fastmac_exp.samplers.base import Sampler, SampleResult


class RandomSampler(Sampler):
    """Uniform sampling without replacement."""

    name = "random"

    def select(self, corr, k, gp, family, rng) -> SampleResult:
        return SampleResult(indices=rng.permutation(len(corr))[:k].astype(np.int64))


def farthest_point_sampling(x: np.ndarray, k: int, start: int) -> np.ndarray:
    """Greedy FPS with squared Euclidean distance (FastMAC's fps.py works in 6-D on (p, q))."""
    n = len(x)
    idx = np.empty(k, dtype=np.int64)
    dist = np.full(n, np.inf)
    cur = start
    for i in range(k):
        idx[i] = cur
        dist = np.minimum(dist, ((x - x[cur]) ** 2).sum(axis=1))
        cur = int(np.argmax(dist))
    return idx


class FPSSampler(Sampler):
    """Farthest point sampling in the 6-D correspondence space (p, q), random start."""

    name = "fps"

    def select(self, corr, k, gp, family, rng) -> SampleResult:
        x = np.hstack([corr.src, corr.tgt])
        return SampleResult(indices=farthest_point_sampling(x, k, int(rng.integers(len(corr)))))


class NoSampler(Sampler):
    """Keep every correspondence: plain MAC. Any ratio is ignored."""

    name = "none"
    keeps_everything = True

    def sample(self, corr, ratio, gp, family, rng, samples=None) -> SampleResult:
        return SampleResult(
            indices=np.arange(len(corr), dtype=np.int64), timings={"sampling": 0.0}, ratio=1.0
        )
