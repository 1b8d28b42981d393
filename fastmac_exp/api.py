"""The library facade: register two clouds, or a set of correspondences, with FastMAC in one call."""

from __future__ import annotations

import time
from typing import Any

import numpy as np

from fastmac_exp.backends.base import Backend
from fastmac_exp.descriptors.base import Descriptor
from fastmac_exp.errors import InputError, RegistrationFailed
from fastmac_exp.families import FIXED_RESOLUTION
from fastmac_exp.families import family as family_record
from fastmac_exp.offset import describe_moved
from fastmac_exp.params import mac_params_for
from fastmac_exp.pipeline import register_correspondences
from fastmac_exp.resolution import resolution_for
from fastmac_exp.samplers import Sampler
from fastmac_exp.types import Correspondences, Pair, RegistrationResult


def register(
    source: np.ndarray | Correspondences,
    target: np.ndarray | None = None,
    *,
    family: str = "3dmatch",
    voxel_size: float | None = None,
    sampler: Sampler | str = "highpass",
    ratio: float = 0.2,
    backend: Backend | str = "auto",
    descriptor: Descriptor | None = None,
    seed: int = 0,
    **mac_overrides: Any,
) -> RegistrationResult:
    """Register two point clouds (FPFH correspondences) or a Correspondences set with FastMAC.

    source, target: (N, 3) arrays (metres), or a Correspondences as `source` and no target.
    family: whose rules apply ("3dmatch", "3dlomatch", "kitti"): graph parameters, inlier threshold.
    voxel_size: the descriptor's keypoint voxel for clouds (> 0; None: the family's, 0.05 m / 0.3 m).
    sampler, ratio: FastMAC's sampler (a name or a Sampler) and the fraction it keeps, in (0, 1].
    backend: "auto" (the C++ core, which the install builds; the Python reference if it is missing),
    "cpp", "python", or a Backend. descriptor: for clouds (None: FPFH). seed: the sampler's draws.
    mac_overrides: MacParams fields (search, max_nodes, inlier_threshold, ...).

    Returns a RegistrationResult: `pose` maps source into target. Check `result.ok` (False, with
    `result.error` and a NaN pose, where MAC found no pose, e.g. no edge left after sampling) and
    `result.inliers` against the clique size: a pose of two unrelated clouds maps hardly more
    correspondences than its clique within the inlier threshold. Bad input raises InputError.

    >>> result = register(src_xyz, tgt_xyz, family="3dmatch", voxel_size=0.05, ratio=0.2)
    >>> result.pose  # 4x4, maps source into target
    """
    from fastmac_exp.backends import make_backend
    from fastmac_exp.samplers import make_sampler

    rng = np.random.default_rng(seed)
    sampler_obj = make_sampler(sampler) if isinstance(sampler, str) else sampler
    backend_obj = make_backend(backend) if isinstance(backend, str) else backend
    graph_key = "fpfh"
    describe_ms = 0.0
    resolution = FIXED_RESOLUTION  # correspondences alone: no clouds to compute it from
    if isinstance(source, Correspondences):
        corr = source
    else:
        if target is None:
            raise InputError("register(source, target): a target cloud is needed when source is a cloud")
        from fastmac_exp.io import clean_cloud

        fam = family_record(family)
        if voxel_size is not None and not voxel_size > 0:
            raise InputError(
                f"register(): voxel_size must be positive or None (the family's), got {voxel_size}"
            )
        src = clean_cloud(_points(source, "source"), "source cloud")[0]
        tgt = clean_cloud(_points(target, "target"), "target cloud")[0]
        resolution = resolution_for(family, src, tgt)
        pair = Pair(
            name="register",
            family=family,
            src_cloud=src,
            tgt_cloud=tgt,
            resolution=resolution,
            voxel_size=fam.voxel_size if voxel_size is None else float(voxel_size),
            **fam.thresholds(),
        )
        if descriptor is None:
            from fastmac_exp.descriptors.fpfh import FPFHDescriptor

            descriptor = FPFHDescriptor()
        graph_key = descriptor.graph_key
        t0 = time.perf_counter()
        corr = describe_moved(descriptor, pair, rng)
        describe_ms = (time.perf_counter() - t0) * 1e3
    if len(corr) < 3:  # else the sampler's advice would be a ratio above 1
        raise InputError(f"{len(corr)} correspondence(s): a clique, and a pose, needs at least 3")
    params = mac_params_for(family, graph_key, resolution, mac_overrides=mac_overrides)
    sample_graph = mac_params_for(family, graph_key, FIXED_RESOLUTION, mac_overrides=mac_overrides).graph
    try:
        result, _ = register_correspondences(
            corr, params, sampler_obj, backend_obj, ratio, family, rng, sample_graph=sample_graph
        )
    except RegistrationFailed as exc:  # a result flagged as failed, not an exception to catch
        nan = np.full((4, 4), np.nan)
        empty = np.zeros(0, np.int64)
        return RegistrationResult(
            pose=nan, pose_unrefined=nan.copy(), kept=empty, clique=empty, error=str(exc)
        )
    result.timings["describe"] = describe_ms
    return result


def _points(a: Any, what: str) -> np.ndarray:
    arr = np.asarray(a, dtype=np.float64)
    if arr.ndim != 2 or arr.shape[1] != 3:
        raise InputError(f"register(): {what} must be an (N, 3) array of points, got shape {arr.shape}")
    return arr
