"""MAC's work bound before the cubic step (issue 41; docs/keep_size.md, "MAC bounded on near-cliques").

`mac.max_work` bounds the clique search only. Before it, MAC builds the second-order graph G = W * (W W)
and the clustering coefficients' product, each ~ sum_i deg_i^2 multiply-adds (the wedges: a dense core of
m nodes costs ~m^3), which on the near-clique a high-pass keep is (80-98 % inliers) grows with the cube of
the keep: 5,000 kept of real KITTI took 4.4 s, 50,000 kept of 1,000,000 minutes.

So the work is counted first, in O(N * anchors) without building the graph: every node's first-order
degree is estimated from `ANCHORS` evenly spaced anchor correspondences (deterministic, so a bounded
result is the same on any machine), and the predicted product work is sum_i deg_i^2. Within
`mac.max_product_work` MAC runs as always (exact). Past it, MAC runs on the densest part of the keep that
fits: the K nodes of highest estimated degree, K the largest with sum over them of min(deg_i, K)^2 within
the budget. On a near-clique those are the consensus (the inliers are the dense core, and the reduction of
spec 2.5 then keeps its ~50 nodes of highest clustering anyway), so the selected clique, and the pose,
come from the same group; the pose is then refined (spec 5.3) on the whole keep, as MAC would, from the
hypothesis MAC chose. The row's `cap_hit` says so. Tested against the exact run on the inputs where both
run (tests/test_keep_size.py): the same pose within 0.5 deg / 5 cm.
"""

from __future__ import annotations

import numpy as np

from fastmac_exp import core
from fastmac_exp.core import graph_args, points
from fastmac_exp.params import MacParams

ANCHORS = 512  # anchor correspondences of the degree estimate (N * ANCHORS compatibility tests)


def estimated_degrees(
    src: np.ndarray, tgt: np.ndarray, params: MacParams, anchors: int = ANCHORS
) -> np.ndarray:
    """Every node's first-order degree (sum of weights) from evenly spaced anchors (exact: n <= anchors)."""
    n = len(src)
    m = min(n, anchors)
    idx = np.unique(np.linspace(0, n - 1, m).round().astype(np.int64))
    d = np.asarray(core.anchor_degree(src, tgt, params.graph, idx), dtype=np.float64)
    return d * ((n - 1) / len(idx)) if len(idx) < n else d


def product_work(degree: np.ndarray) -> float:
    """Predicted multiply-adds of one second-order product: sum_i deg_i^2."""
    return float(np.sum(np.square(degree)))


def densest_within(degree: np.ndarray, budget: float) -> np.ndarray:
    """The K nodes of highest degree (ascending indices), K the largest with sum over them of
    min(deg_i, K)^2 <= budget (their product work, with degrees capped by the sub-graph's size)."""
    order = np.argsort(-degree, kind="stable")
    d = degree[order]

    def work(k: int) -> float:
        return float(np.sum(np.square(np.minimum(d[:k], k))))

    lo, hi = 3, len(d)
    if work(hi) <= budget:
        return np.arange(len(d))
    while hi - lo > 1:  # work(lo) fits (or lo is the least MAC needs), work(hi) does not
        mid = (lo + hi) // 2
        if work(mid) <= budget:
            lo = mid
        else:
            hi = mid
    return np.sort(order[:lo])


def bounded_subset(src: np.ndarray, tgt: np.ndarray, params: MacParams) -> np.ndarray | None:
    """The nodes MAC runs on where the predicted product work passes the budget (None: all, exact)."""
    n = len(src)
    if params.max_product_work <= 0 or n <= ANCHORS:
        return None
    # a degree is at most n - 1 (weights <= 1; the estimate is scaled to n - 1 anchors), so the predicted
    # work is at most n (n - 1)^2: within the budget, the estimate cannot pass it (FastMAC's keeps of
    # <= 1,442 at the default budget: the estimate cost 0.5-0.7 ms a call there)
    if float(n) * float(n - 1) ** 2 <= params.max_product_work:
        return None
    degree = estimated_degrees(src, tgt, params)
    if product_work(degree) <= params.max_product_work:
        return None
    return densest_within(degree, params.max_product_work)


def mae(pose: np.ndarray, src: np.ndarray, tgt: np.ndarray, tau: float) -> float:
    e = np.linalg.norm(src @ pose[:3, :3].T + pose[:3, 3] - tgt, axis=1)
    return float(np.sum((tau - e[e < tau]) / tau))


def refine_on(
    pose: np.ndarray, src: np.ndarray, tgt: np.ndarray, params: MacParams
) -> tuple[np.ndarray, float]:
    """Spec 5.3 on the whole keep from MAC's hypothesis (the C++ core's fit: unweighted centroids)."""
    tau = params.inlier_threshold
    score = prev = mae(pose, src, tgt, tau)
    s_pts, t_pts = points(src), points(tgt)
    for _ in range(params.refine_iters):
        e = np.linalg.norm(src @ pose[:3, :3].T + pose[:3, 3] - tgt, axis=1)
        s = float(np.sum((tau - e[e < tau]) / tau))
        if s < prev:
            break
        prev = s
        inl = np.flatnonzero(e < tau)
        if len(inl) < 3:
            break
        w = 1.0 / (1.0 + (e[inl] / tau) ** 2)
        pose = np.asarray(
            core.core().kabsch(s_pts[inl], t_pts[inl], np.ascontiguousarray(w, dtype=np.float64))
        )
    return pose, score


__all__ = ["ANCHORS", "bounded_subset", "densest_within", "estimated_degrees", "graph_args", "product_work",
           "refine_on"]  # fmt: skip
