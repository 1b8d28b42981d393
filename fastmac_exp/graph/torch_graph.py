"""The sampler's graph signals in PyTorch, for users with a GPU (sampler.device=cuda), as the paper ran.

Dense like the reference (blocks of rows keep memory at O(block * N)); float64 by default so that the
CPU result matches the C++ and numpy paths to 1e-6.
"""

from __future__ import annotations

import numpy as np
import torch

from fastmac_exp.errors import InputError
from fastmac_exp.params import GAUSSIAN, GraphParams
from fastmac_exp.types import GraphSignals


def _first_order(src: torch.Tensor, tgt: torch.Tensor, gp: GraphParams, block: int) -> torch.Tensor:
    n = src.shape[0]
    w = torch.zeros((n, n), dtype=src.dtype, device=src.device)
    for a in range(0, n, block):
        b = min(n, a + block)
        d = (
            torch.cdist(src[a:b], src, compute_mode="donot_use_mm_for_euclid_dist")
            - torch.cdist(tgt[a:b], tgt, compute_mode="donot_use_mm_for_euclid_dist")
        ).abs()
        s = torch.exp(-(d**2) / (2 * gp.alpha**2)) if gp.kernel == GAUSSIAN else 1 - d**2 / gp.tau**2
        w[a:b] = torch.where(s >= gp.threshold, s, torch.zeros_like(s))
    w.fill_diagonal_(0)
    return w


def graph_signals_torch(
    src: np.ndarray,
    tgt: np.ndarray,
    gp: GraphParams,
    self_loops: bool = True,
    device: str = "cpu",
    dtype: torch.dtype = torch.float64,
    block: int = 2048,
) -> GraphSignals:
    """Degree, high-pass and low-pass responses (same definitions as fastmac_exp.graph.numpy_graph)."""
    if device.startswith("cuda") and not torch.cuda.is_available():
        raise InputError("sampler.device=cuda but torch sees no CUDA device; use sampler.device=cpu")
    s_t = torch.as_tensor(src, dtype=dtype, device=device)
    t_t = torch.as_tensor(tgt, dtype=dtype, device=device)
    w = _first_order(s_t, t_t, gp, block)
    if self_loops:
        w = w + torch.eye(w.shape[0], dtype=dtype, device=device)
    sog = w * (w @ w)
    s = sog.sum(dim=1)
    diag = torch.diagonal(sog)
    neigh = sog @ s - diag * s
    highpass = (s - diag) * s - neigh
    safe = torch.where(s > 0, s, torch.ones_like(s))
    lowpass = torch.where(s > 0, s + (sog @ s) / safe, torch.zeros_like(s))
    n_edges = int(((w > 0).sum().item() - (w.shape[0] if self_loops else 0)) // 2)
    return GraphSignals(
        degree=s.cpu().numpy(),
        highpass=highpass.cpu().numpy(),
        lowpass=lowpass.cpu().numpy(),
        n_edges=n_edges,
    )
