"""Point-cloud resolution ("mesh resolution", spec 1.5), which sets MAC's Gaussian kernel (alpha = 10 res).

MAC computes it from the two clouds for 3DMatch, 3DLoMatch and ETH (non-Predator descriptors): the mean,
over all points, of the distance to the nearest other point, averaged over source and target. It is not
used by KITTI (quadratic kernel) and FastMAC's sampling graph fixes it at 0.006 (spec 7.2), so those keep
`FIXED_RESOLUTION`. Where the project keeps a fixed value on purpose:
- the sampler's graph (FastMAC's code: resolution 0.006 on 3DMatch/3DLoMatch);
- the KITTI family (the kernel does not use it);
- correspondences without clouds (the MAC layout when its .ply files are absent, user correspondences);
- object scans (the bunny, the dragon): the 3DMatch rules rescaled by 1/25 (datasets/user_pairs.py).
"""

from __future__ import annotations

import time

import numpy as np

from fastmac_exp.errors import InputError
from fastmac_exp.families import FAMILIES, FIXED_RESOLUTION

COMPUTED_FAMILIES = tuple(f.name for f in FAMILIES.values() if f.resolution_from_clouds)


def mesh_resolution(points: np.ndarray) -> float:
    """Mean distance of each point to its nearest other point (a duplicate point contributes 0).

    The C++ core's grid search where it is built (exact; 300,000 points in tens of ms on two threads),
    else scipy's k-d tree."""
    from fastmac_exp import core

    pts = np.asarray(points, dtype=np.float64)
    if pts.ndim != 2 or pts.shape[1] != 3 or len(pts) < 2:
        raise InputError(f"mesh resolution needs an (N >= 2, 3) cloud, got shape {pts.shape}")
    if not np.isfinite(pts).all():
        raise InputError("mesh resolution: the cloud has non-finite coordinates")
    if core.available():
        return float(core.core().nearest_other_distances(np.ascontiguousarray(pts)).mean())
    # one thread: scipy's threaded query (workers=-1) joins its threads in Python, where a Ctrl-C raises
    # KeyboardInterrupt while they still write into the result: a segfault (5 of 6 Ctrl-C's during a run);
    # 43 ms instead of 34 on a 38k-point scan
    from scipy.spatial import cKDTree

    d, _ = cKDTree(pts).query(pts, k=2, workers=1)
    return float(d[:, 1].mean())


def pair_resolution(src: np.ndarray, tgt: np.ndarray) -> float:
    """(mr(source) + mr(target)) / 2, as MAC computes it."""
    return 0.5 * (mesh_resolution(src) + mesh_resolution(tgt))


def timed_resolution_for(family: str, src: np.ndarray, tgt: np.ndarray) -> tuple[float, dict[str, float]]:
    """resolution_for and a pair's meta entry saying how long it took ({"resolution_ms": ms}): the
    experiment names it as a stage of its own instead of leaving it inside the dataset's load."""
    t0 = time.perf_counter()
    res = resolution_for(family, src, tgt)
    return res, {"resolution_ms": (time.perf_counter() - t0) * 1e3}


def resolution_for(family: str, src: np.ndarray | None, tgt: np.ndarray | None) -> float:
    """The resolution MAC would use for a pair of this family: computed from the clouds where it is."""
    if family in COMPUTED_FAMILIES and src is not None and tgt is not None:
        return pair_resolution(src, tgt)
    return FIXED_RESOLUTION
