"""Compatibility graphs in numpy/scipy: the Python reference the C++ core is checked against.

W is the first-order graph (spec 2.2), G = W * (W @ W) the second-order graph (spec 2.3). Both are
stored sparse (only where W passes its threshold), so memory grows with the edges, not N^2.
"""

from __future__ import annotations

from typing import TYPE_CHECKING

import numpy as np

if TYPE_CHECKING:  # imported where a graph is built: `import fastmac_exp` stays light
    import scipy.sparse as sp

from fastmac_exp.params import GAUSSIAN, GraphParams
from fastmac_exp.types import GraphSignals


def pair_inconsistency(src: np.ndarray, tgt: np.ndarray, rows: slice | np.ndarray) -> np.ndarray:
    """d_ij = | |p_i - p_j| - |q_i - q_j| | for i in `rows` and every j, in float64."""
    dp = np.linalg.norm(src[rows, None, :] - src[None, :, :], axis=2)
    dq = np.linalg.norm(tgt[rows, None, :] - tgt[None, :, :], axis=2)
    return np.abs(dp - dq)


def kernel(d: np.ndarray, gp: GraphParams) -> np.ndarray:
    """Compatibility score of an inconsistency d (spec 2.2)."""
    if gp.kernel == GAUSSIAN:
        return np.exp(-(d**2) / (2.0 * gp.alpha**2))
    return 1.0 - d**2 / gp.tau**2


def first_order(src: np.ndarray, tgt: np.ndarray, gp: GraphParams, block: int = 512) -> sp.csr_matrix:
    """Symmetric sparse W with zero diagonal: W_ij = kernel(d_ij) where it is >= gp.threshold."""
    n = len(src)
    rows, cols, vals = [], [], []
    for a in range(0, n, block):
        b = min(n, a + block)
        s = kernel(pair_inconsistency(src, tgt, slice(a, b)), gp)
        i, j = np.nonzero(s >= gp.threshold)
        i = i + a
        keep = j > i  # upper triangle; mirrored below
        rows.append(i[keep])
        cols.append(j[keep])
        vals.append(s[i[keep] - a, j[keep]])
    i = np.concatenate(rows) if rows else np.zeros(0, np.int64)
    j = np.concatenate(cols) if cols else np.zeros(0, np.int64)
    w = np.concatenate(vals) if vals else np.zeros(0)
    import scipy.sparse as sp

    upper = sp.coo_matrix((w, (i, j)), shape=(n, n))
    return (upper + upper.T).tocsr()


def second_order(w: sp.csr_matrix) -> sp.csr_matrix:
    """G = W * (W @ W), only on the support of W; entries without a common neighbour are dropped."""
    g = w.multiply(w @ w).tocsr()
    g.eliminate_zeros()
    return g


def signals_from_graph(w: sp.csr_matrix, self_loops: bool = True) -> GraphSignals:
    """Degree, high-pass and low-pass responses of the SOG built from W.

    self_loops=True is FastMAC's convention (W_ii = 1 before squaring): off the diagonal
    SOG_ij = W_ij (2 W_ij + sum_k W_ik W_kj), and SOG_ii = 1 + sum_k W_ik^2. self_loops=False uses
    MAC's G = W * (W @ W) with a zero diagonal.
    """
    g = w.multiply(w @ w).tocsr()
    if self_loops:
        off = (g + 2.0 * w.multiply(w)).tocsr()
        diag = 1.0 + np.asarray(w.multiply(w).sum(axis=1)).ravel()
    else:
        off = g
        diag = np.zeros(w.shape[0])
    s = diag + np.asarray(off.sum(axis=1)).ravel()
    neigh_s = off @ s  # sum_{j != i} SOG_ij s_j
    offsum = s - diag
    highpass = offsum * s - neigh_s  # sum_j SOG_ij (s_i - s_j); the diagonal term cancels
    with np.errstate(divide="ignore", invalid="ignore"):
        lowpass = np.where(s > 0, s + (diag * s + neigh_s) / np.where(s > 0, s, 1.0), 0.0)
    return GraphSignals(degree=s, highpass=highpass, lowpass=lowpass, n_edges=int(w.nnz // 2))


def graph_signals(src: np.ndarray, tgt: np.ndarray, gp: GraphParams, self_loops: bool = True) -> GraphSignals:
    """Build W from the correspondences and return the sampler's node signals."""
    return signals_from_graph(first_order(src, tgt, gp), self_loops=self_loops)
