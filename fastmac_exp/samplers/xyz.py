"""The paper's signal ablation (spec 7.5): coordinate signals |L_x X| next to the degree signal."""

from __future__ import annotations

import numpy as np

from fastmac_exp.errors import InputError
from fastmac_exp.graph import compute_signals
from fastmac_exp.params import GraphParams
from fastmac_exp.samplers.base import Sampler, minmax
from fastmac_exp.types import Correspondences


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
            sig = compute_signals(corr.src, corr.tgt, gp, self_loops=True, impl=self.impl)
            total += w_deg * minmax(np.abs(sig.highpass))
        if not (w_src or w_tgt or w_deg):
            total = np.ones(len(corr))  # "000": uniform
        return total
