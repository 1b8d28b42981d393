"""The library facade: register two clouds, or a set of correspondences, with FastMAC in one call."""

from __future__ import annotations

import time
from typing import Any

import numpy as np

from fastmac_exp.backends.base import Backend
from fastmac_exp.descriptors.base import Descriptor
from fastmac_exp.errors import InputError
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
        src = clean_cloud(np.asarray(source, dtype=np.float64), "source cloud")[0]
        tgt = clean_cloud(np.asarray(target, dtype=np.float64), "target cloud")[0]
        resolution = resolution_for(family, src, tgt)
        pair = Pair(
            name="register",
            family=family,
            src_cloud=src,
            tgt_cloud=tgt,
            resolution=resolution,
            voxel_size=voxel_size or fam.voxel_size,
            **fam.thresholds(),
        )
        if descriptor is None:
            from fastmac_exp.descriptors.fpfh import FPFHDescriptor

            descriptor = FPFHDescriptor()
        graph_key = descriptor.graph_key
        t0 = time.perf_counter()
        corr = describe_moved(descriptor, pair, rng)
        describe_ms = (time.perf_counter() - t0) * 1e3
    params = mac_params_for(family, graph_key, resolution, mac_overrides=mac_overrides)
    sample_graph = mac_params_for(family, graph_key, FIXED_RESOLUTION, mac_overrides=mac_overrides).graph
    result, _ = register_correspondences(
        corr, params, sampler_obj, backend_obj, ratio, family, rng, sample_graph=sample_graph
    )
    result.timings["describe"] = describe_ms
    return result
