"""MAC in Python (numpy, scipy.sparse, python-igraph): the readable reference of the C++ core.

Follows the spec (sections 2-5) with one deliberate choice shared with the C++ core: maximal cliques
are put in a canonical order (members ascending, cliques lexicographic) before node-guided selection,
so tie-breaking does not depend on the enumeration order of a particular library version.
"""

from __future__ import annotations

import time

import igraph
import numpy as np
import scipy.sparse as sp

from fastmac_exp.errors import RegistrationFailed
from fastmac_exp.geometry.transforms import kabsch
from fastmac_exp.graph import first_order, second_order
from fastmac_exp.params import MacParams
from fastmac_exp.types import Correspondences, RegistrationResult


def _ms(t0: float) -> float:
    return (time.perf_counter() - t0) * 1e3


def clustering(g: sp.csr_matrix) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """Degrees, clustering coefficients, weighted triangle sums and neighbour-pair counts on G (spec 2.4).

    w_i = sum over neighbour pairs {a, b} of i with G_ab != 0 of (G_ia G_ib G_ab)^(1/3)
        = diag(C C C)_i / 2 with C = G^(1/3) elementwise.
    """
    deg = np.diff(g.indptr).astype(np.float64)
    c = g.copy()
    c.data = np.cbrt(c.data)
    tri = np.asarray((c @ c).multiply(c).sum(axis=1)).ravel() / 2.0
    pairs = deg * (deg - 1.0) / 2.0
    cc = np.where(deg > 1, tri / np.where(pairs > 0, pairs, 1.0), 0.0)
    return deg, cc, tri, pairs


def otsu(cc: np.ndarray) -> float:
    """The reference code's Otsu threshold on clustering coefficients, quirks included (spec 2.4, 9.7)."""
    lo, hi = float(cc.min()), float(cc.max())
    default = (hi - lo) / 2.0
    if hi == 0.0 or hi == lo:
        return default
    h = (hi - lo) / 100.0
    bins = np.minimum(np.floor(cc / h).astype(np.int64), 99)
    hist = np.bincount(np.clip(bins, 0, 99), minlength=100).astype(np.float64)
    sums = np.bincount(np.clip(bins, 0, 99), weights=cc, minlength=100)
    total_n, total_s = hist.sum(), sums.sum()
    n1 = s1 = 0.0
    best, best_i = -1000.0, None
    for i in range(100):
        n1 += hist[i]
        s1 += sums[i]
        if n1 == 0:
            continue
        n2 = total_n - n1
        if n2 == 0:
            break
        m1, m2 = s1 / n1, (total_s - s1) / n2
        score = n1 * n2 * (m1 - m2) ** 2
        if score > best:
            best, best_i = score, i
    return default if best_i is None else best_i * (hi - lo) / 100.0


def reduce_graph(g: sp.csr_matrix) -> tuple[sp.csr_matrix, bool]:
    """Spec 2.5: on very dense graphs keep only edges between ~50 nodes of highest clustering."""
    n = g.shape[0]
    deg, cc, tri, pairs = clustering(g)
    if n <= 50 or cc.max() == 0:
        return g, False
    avg = float(cc.mean())
    many = deg > 1
    total = float(tri[many].sum() / pairs[many].sum()) if many.any() else 0.0
    ot = otsu(cc)
    if min(ot, avg, total) <= 3:
        return g, False
    m = max(ot, total)
    c50 = float(np.sort(cc)[::-1][min(49, n - 1)])
    f = 10.0
    while f * m > c50:
        f -= 0.05
    good = cc > f * m
    coo = g.tocoo()
    keep = good[coo.row] & good[coo.col]
    reduced = sp.csr_matrix((coo.data[keep], (coo.row[keep], coo.col[keep])), shape=g.shape)
    return reduced, True


def canonical_cliques(cliques: list[tuple[int, ...]] | list[list[int]]) -> list[tuple[int, ...]]:
    """Members ascending, cliques in lexicographic order."""
    return sorted(tuple(sorted(c)) for c in cliques)


def clique_weights(cliques: list[tuple[int, ...]], g: sp.csr_matrix) -> np.ndarray:
    """w_C = sum over member pairs a < b of G_ab (float64), for every clique."""
    n = g.shape[0]
    upper = sp.triu(g, k=1).tocsr()
    upper.sort_indices()
    coo = upper.tocoo()
    keys = coo.row.astype(np.int64) * n + coo.col
    vals = coo.data
    weights = np.zeros(len(cliques))
    by_size: dict[int, list[int]] = {}
    for ci, c in enumerate(cliques):
        by_size.setdefault(len(c), []).append(ci)
    for k, ids in by_size.items():
        members = np.asarray([cliques[ci] for ci in ids], dtype=np.int64)
        ia, ib = np.triu_indices(k, 1)
        q = members[:, ia] * n + members[:, ib]
        pos = np.clip(np.searchsorted(keys, q), 0, max(len(keys) - 1, 0))
        found = keys[pos] == q if len(keys) else np.zeros_like(q, dtype=bool)
        weights[ids] = np.where(found, vals[pos], 0.0).sum(axis=1)
    return weights


def select_cliques(cliques: list[tuple[int, ...]], g: sp.csr_matrix, n: int) -> list[tuple[int, ...]]:
    """Node-guided clique selection (spec 4): each node keeps its heaviest clique; deduplicate by owner.

    Equivalent to the reference loop (cliques in order, a node switches only on a strictly heavier
    clique, weights start at 0): per node, the heaviest clique, the earliest among equals.
    """
    weights = clique_weights(cliques, g)
    sizes = np.fromiter((len(c) for c in cliques), dtype=np.int64, count=len(cliques))
    nodes = np.fromiter((v for c in cliques for v in c), dtype=np.int64, count=int(sizes.sum()))
    cid = np.repeat(np.arange(len(cliques)), sizes)
    w = weights[cid]
    keep = w > 0
    nodes, cid, w = nodes[keep], cid[keep], w[keep]
    order = np.lexsort((cid, -w, nodes))
    nodes, cid = nodes[order], cid[order]
    first = np.ones(len(nodes), dtype=bool)
    first[1:] = nodes[1:] != nodes[:-1]
    owner = np.full(n, -1, dtype=np.int64)
    owner[nodes[first]] = cid[first]
    seen: set[int] = set()
    out = []
    for ci in owner[owner >= 0]:
        if int(ci) not in seen:
            seen.add(int(ci))
            out.append(cliques[int(ci)])
    return out


def mae_score(pose: np.ndarray, src: np.ndarray, tgt: np.ndarray, tau: float) -> tuple[float, np.ndarray]:
    """Spec 5.2: sum over e_i < tau of (tau - e_i) / tau, and the residuals e."""
    e = np.linalg.norm(src @ pose[:3, :3].T + pose[:3, 3] - tgt, axis=1)
    inl = e < tau
    return float(np.sum((tau - e[inl]) / tau)), e


def refine(pose: np.ndarray, score: float, src: np.ndarray, tgt: np.ndarray, params: MacParams) -> np.ndarray:
    """Spec 5.3: re-fit on the inliers with weights 1/(1+(e/tau)^2); stop when the score drops."""
    tau = params.inlier_threshold
    prev = score
    for _ in range(params.refine_iters):
        s, e = mae_score(pose, src, tgt, tau)
        if s < prev:
            break
        prev = s
        inl = e < tau
        if inl.sum() < 3:
            break
        w = 1.0 / (1.0 + (e[inl] / tau) ** 2)
        pose = kabsch(src[inl], tgt[inl], w)
    return pose


class PythonBackend:
    """MAC with numpy, scipy.sparse and python-igraph."""

    name = "python"

    def register(self, corr: Correspondences, params: MacParams) -> RegistrationResult:
        n = len(corr)
        if n < 3:
            raise RegistrationFailed(f"need at least 3 correspondences, got {n}")
        src, tgt = corr.src, corr.tgt
        timings: dict[str, float] = {}

        t0 = time.perf_counter()
        w = first_order(src, tgt, params.graph)
        g = second_order(w)
        timings["graph"] = _ms(t0)
        if g.nnz == 0:
            raise RegistrationFailed(
                f"graph has no second-order edge ({w.nnz // 2} first-order edges among {n} correspondences)"
            )

        t0 = time.perf_counter()
        gc, reduced = reduce_graph(g) if params.reduction else (g, False)
        upper = sp.triu(gc, k=1).tocoo()
        graph = igraph.Graph(n=n, edges=np.column_stack([upper.row, upper.col]).tolist())
        raw = graph.maximal_cliques(min=params.min_clique_size)
        cap_hit = ""
        if params.max_cliques and len(raw) > params.max_cliques:
            raw, cap_hit = raw[: params.max_cliques], f"max_cliques={params.max_cliques}"
        cliques = canonical_cliques(raw)
        timings["cliques"] = _ms(t0)
        if not cliques:
            raise RegistrationFailed(f"no maximal clique of size >= {params.min_clique_size}")

        t0 = time.perf_counter()
        selected = select_cliques(cliques, g, n)
        timings["selection"] = _ms(t0)

        t0 = time.perf_counter()
        best_score, best_pose, best_i = 0.0, None, -1
        hyp_poses = np.empty((len(selected), 4, 4))
        hyp_scores = np.empty(len(selected))
        for i, c in enumerate(selected):
            idx = np.asarray(c)
            pose = kabsch(src[idx], tgt[idx])
            s, _ = mae_score(pose, src, tgt, params.inlier_threshold)
            hyp_poses[i], hyp_scores[i] = pose, s
            if s > best_score:
                best_score, best_pose, best_i = s, pose, i
        if best_pose is None:
            raise RegistrationFailed("no hypothesis has a positive score")
        refined = refine(best_pose, best_score, src, tgt, params)
        timings["pose"] = _ms(t0)

        return RegistrationResult(
            pose=refined,
            pose_unrefined=best_pose,
            kept=np.arange(n),
            clique=np.asarray(selected[best_i], dtype=np.int64),
            score=best_score,
            n_cliques=len(cliques),
            n_selected=len(selected),
            n_edges=int(w.nnz // 2),
            reduced=reduced,
            cap_hit=cap_hit,
            timings=timings,
            hypothesis_poses=hyp_poses,
            hypothesis_scores=hyp_scores,
        )
