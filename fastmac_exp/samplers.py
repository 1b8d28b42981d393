"""Correspondence samplers: score the nodes, then keep k = floor(N * ratio) of them (spec section 7).

Graph-filter samplers (highpass, lowpass, allpass) score each correspondence by a filter response of the
generalized-degree signal of the second-order graph and draw without replacement in proportion to the
score. Draws use Gumbel-top-k keys (log score + Gumbel noise), which is distributed exactly like
successive draws in proportion to the remaining scores (torch.multinomial without replacement) and lets
the numpy, C++ and torch paths give identical samples for the same uniform numbers.
"""

from __future__ import annotations

import time
from dataclasses import dataclass, field

import numpy as np

from fastmac_exp.errors import InputError
from fastmac_exp.graph import GraphSignals, graph_signals
from fastmac_exp.params import GraphParams
from fastmac_exp.types import Correspondences

FILTERS = ("highpass", "lowpass", "allpass")


@dataclass
class SampleResult:
    """Kept indices in draw order, the per-node scores (if any) and what happened."""

    indices: np.ndarray
    scores: np.ndarray | None = None
    zero_filled: int = 0  # samples drawn uniformly because fewer than k nodes had a positive score
    timings: dict[str, float] = field(default_factory=dict)


def sample_count(n: int, ratio: float, min_count: int = 3) -> int:
    """k = floor(n * ratio); ratio must lie in (0, 1] and k must allow a clique of `min_count`."""
    if not (isinstance(ratio, int | float) and 0.0 < float(ratio) <= 1.0):
        raise InputError(f"ratio must be in (0, 1], got {ratio!r}")
    k = n if ratio >= 1.0 else int(np.floor(n * ratio + 1e-9))
    if k < min_count:
        raise InputError(
            f"ratio={ratio} keeps {k} of {n} correspondences, fewer than the {min_count} a clique needs; "
            f"use ratio >= {min_count / max(n, 1):.4g}"
        )
    return k


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


def compute_signals(
    corr: Correspondences, gp: GraphParams, self_loops: bool = True, impl: str = "auto", device: str = "cpu"
) -> GraphSignals:
    """Node signals from the fastest available implementation: cpp (built core), torch or python."""
    if impl in ("auto", "cpp"):
        from fastmac_exp.backends import cpp

        if cpp.available():
            out = cpp.graph_signals(corr.src, corr.tgt, gp, self_loops=self_loops)
            if isinstance(out, dict):
                out = GraphSignals(
                    degree=np.asarray(out["degree"]),
                    highpass=np.asarray(out["highpass"]),
                    lowpass=np.asarray(out["lowpass"]),
                    n_edges=int(out["n_edges"]),
                )
            return out
        if impl == "cpp":
            cpp.CppBackend()  # raises BackendUnavailable with build instructions
    if impl == "torch" or device != "cpu":
        from fastmac_exp.torch_graph import graph_signals_torch

        return graph_signals_torch(corr.src, corr.tgt, gp, self_loops=self_loops, device=device)
    if impl not in ("auto", "python"):
        raise InputError(f"sampler.impl must be auto, cpp, torch or python, got {impl!r}")
    return graph_signals(corr.src, corr.tgt, gp, self_loops=self_loops)


def filter_response(sig: GraphSignals, filt: str) -> np.ndarray:
    """|response| of the degree signal to the high-, low- or all-pass filter (spec 7.3, 7.5)."""
    if filt == "highpass":
        return np.abs(sig.highpass)
    if filt == "lowpass":
        return np.abs(sig.lowpass)
    if filt == "allpass":
        return np.abs(sig.degree)
    raise InputError(f"unknown graph filter {filt!r}; expected one of {FILTERS}")


class Sampler:
    """Base class: subclasses implement `scores` or override `select`."""

    name = "base"

    def sample(
        self, corr: Correspondences, ratio: float, gp: GraphParams, family: str, rng: np.random.Generator
    ) -> SampleResult:
        n = len(corr)
        k = sample_count(n, ratio)
        t0 = time.perf_counter()
        if k >= n:
            res = SampleResult(indices=np.arange(n, dtype=np.int64))
        else:
            res = self.select(corr, k, gp, family, rng)
        res.timings["sampling"] = (time.perf_counter() - t0) * 1e3
        return res

    def select(
        self, corr: Correspondences, k: int, gp: GraphParams, family: str, rng: np.random.Generator
    ) -> SampleResult:
        scores = self.scores(corr, gp, family, rng)
        idx, zero_filled = draw_proportional(scores, k, rng)
        return SampleResult(indices=idx, scores=scores, zero_filled=zero_filled)

    def scores(
        self, corr: Correspondences, gp: GraphParams, family: str, rng: np.random.Generator
    ) -> np.ndarray:
        raise NotImplementedError


class GraphFilterSampler(Sampler):
    """FastMAC: score = |filter response of the generalized degree|, drawn stochastically.

    filter: highpass (FastMAC, Laplacian diag(s) - SOG), lowpass (I + D^-1 SOG), allpass (I).
    normalize: "auto" (min-max on 3DMatch-style families, none on KITTI, as the reference code),
    "minmax" or "none". squared: use |f|^2 as the paper writes instead of the code's |f|.
    self_loops: FastMAC's graph keeps W_ii = 1 (spec 7.2); False uses MAC's zero-diagonal SOG.
    impl: auto | cpp | torch | python; device: cpu or cuda (torch path).
    """

    def __init__(
        self,
        filter: str = "highpass",
        normalize: str = "auto",
        squared: bool = False,
        self_loops: bool = True,
        impl: str = "auto",
        device: str = "cpu",
    ) -> None:
        if filter not in FILTERS:
            raise InputError(f"unknown graph filter {filter!r}; expected one of {FILTERS}")
        if normalize not in ("auto", "minmax", "none"):
            raise InputError(f"sampler.normalize must be auto, minmax or none, got {normalize!r}")
        self.filter = filter
        self.name = filter + ("_squared" if squared else "")
        self.normalize = normalize
        self.squared = squared
        self.self_loops = self_loops
        self.impl = impl
        self.device = device

    def scores(
        self, corr: Correspondences, gp: GraphParams, family: str, rng: np.random.Generator
    ) -> np.ndarray:
        sig = compute_signals(corr, gp, self_loops=self.self_loops, impl=self.impl, device=self.device)
        r = filter_response(sig, self.filter)
        if self.squared:
            r = r**2
        norm = self.normalize
        if norm == "auto":
            norm = "none" if family == "kitti" else "minmax"
        return minmax(r) if norm == "minmax" else r


def xyz_response(points: np.ndarray, sigma: float = 0.6, knn: int = 0, block: int = 1024) -> np.ndarray:
    """|L_x X| on a Gaussian graph over the points (spec 7.5): dense Wx = exp(-|x_i - x_j|^2 / sigma^2),
    or, with knn > 0, the paper's k-nearest-neighbour graph with the same weights."""
    n = len(points)
    out = np.empty(n)
    if knn > 0:
        from scipy.spatial import cKDTree

        d, j = cKDTree(points).query(points, k=min(knn + 1, n))
        w = np.exp(-(d[:, 1:] ** 2) / sigma**2)
        nb = points[j[:, 1:]]
        lx = w.sum(axis=1)[:, None] * points - np.einsum("ij,ijk->ik", w, nb)
        return np.linalg.norm(lx, axis=1)
    for a in range(0, n, block):
        b = min(n, a + block)
        d2 = ((points[a:b, None, :] - points[None, :, :]) ** 2).sum(axis=2)
        w = np.exp(-d2 / sigma**2)
        lx = w.sum(axis=1)[:, None] * points[a:b] - w @ points
        out[a:b] = np.linalg.norm(lx, axis=1)
    return out


class XYZSampler(Sampler):
    """The paper's signal ablation: pi = w_src r_src + w_tgt r_tgt + w_deg r_deg, each min-max normalised.

    code "111" = weights (1, 1, 1), "110" = xyz only, "001" = degree only (highpass), "000" = random.
    """

    def __init__(self, code: str = "110", sigma: float = 0.6, knn: int = 0, impl: str = "auto") -> None:
        if len(code) != 3 or set(code) - {"0", "1"}:
            raise InputError(f"sampler.code must be three 0/1 digits such as '110', got {code!r}")
        self.code = code
        self.weights = tuple(float(c) for c in code)
        self.sigma = sigma
        self.knn = knn
        self.impl = impl
        self.name = f"xyz{code}"

    def scores(
        self, corr: Correspondences, gp: GraphParams, family: str, rng: np.random.Generator
    ) -> np.ndarray:
        w_src, w_tgt, w_deg = self.weights
        total = np.zeros(len(corr))
        if w_src:
            total += w_src * minmax(xyz_response(corr.src, self.sigma, self.knn))
        if w_tgt:
            total += w_tgt * minmax(xyz_response(corr.tgt, self.sigma, self.knn))
        if w_deg:
            sig = compute_signals(corr, gp, self_loops=True, impl=self.impl)
            total += w_deg * minmax(np.abs(sig.highpass))
        if not (w_src or w_tgt or w_deg):
            total = np.ones(len(corr))  # "000": uniform
        return total


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

    def sample(self, corr, ratio, gp, family, rng) -> SampleResult:
        return SampleResult(indices=np.arange(len(corr), dtype=np.int64), timings={"sampling": 0.0})
