"""The library facade: register two clouds, or a set of correspondences, with FastMAC in one call."""

from __future__ import annotations

from typing import Any

import numpy as np
from omegaconf import OmegaConf

from fastmac_exp.backends.base import Backend
from fastmac_exp.descriptors.base import Descriptor
from fastmac_exp.errors import InputError, RegistrationFailed
from fastmac_exp.families import FIXED_RESOLUTION
from fastmac_exp.families import family as family_record
from fastmac_exp.geometry.offset import moved_pair, pair_offset, result_to_original
from fastmac_exp.geometry.resolution import resolution_for
from fastmac_exp.options import apply_options, compose_run, instantiate_part
from fastmac_exp.params import mac_params_for
from fastmac_exp.pipeline import register_correspondences
from fastmac_exp.pipeline.stopwatch import Stopwatch, registration_parts
from fastmac_exp.run.checks import check_devices
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
    samples: int | str | None = None,
    backend: Backend | str = "auto",
    descriptor: Descriptor | str | None = None,
    seed: int = 0,
    **options: Any,
) -> RegistrationResult:
    """Register two point clouds (FPFH correspondences) or a Correspondences set with FastMAC.

    source, target: (N, 3) arrays (metres), or a Correspondences as `source` and no target.
    family: whose rules apply ("3dmatch", "3dlomatch", "kitti"): graph parameters, inlier threshold.
    voxel_size: the descriptor's keypoint voxel for clouds (> 0; None: the family's, 0.05 m / 0.3 m).

    The run's options are the command line's, by the same names and from the same config files (conf/,
    fastmac_exp/options.py), so everything `python run.py GROUP=OPTION key=value` accepts is reachable here:

    sampler: a conf/sampler option (highpass, highpass_squared, lowpass, allpass, xyz, random, fps,
        deterministic, none) or a Sampler. ratio: the fraction it keeps, in (0, 1]; samples: a count K
        instead (keep min(K, N); ratio is then ignored), passed on as given; samples="auto" (or
        ratio="auto") sizes the keep from the scores (graph-filter samplers; docs/keep_size.md).
    backend: a conf/backend option (cpp, python, turboreg, ransac, fgr, kiss_matcher), "auto" (the C++ core,
        which the install builds; the Python reference if it is missing) or a Backend.
    descriptor: for clouds, a conf/descriptor option (fpfh, fcgf, ...) or a Descriptor (None: FPFH).
    seed: the sampler's (and RANSAC's) draws.
    **options: any option of the chosen sampler, backend and descriptor (by name), and MAC's `mac.*` and
        `graph.*` keys, by their bare name or, where a name is in two parts, by the full key as on the
        command line (`**{"backend.tau": 0.1}` with backend="turboreg", whose `tau` is also graph.tau):
        graph-filter samplers (highpass, lowpass, allpass): filter, normalize, squared, self_loops, impl
            (auto | cpp | torch | python), device (cpu | cuda), scores (auto | exact | estimate),
            estimate (a dict, or its keys anchors, min_anchors, pair_budget, pair_budget_per_node,
            pilot_anchors, power, uniform_mix, max_tests), keep (samples=auto's rule: a dict, or its keys
            core_inliers, min_keep, core_share, scarce_cover, scarce_ratio);
        xyz: code, sigma, knn, impl; deterministic: bandwidth, band, max_n, max_k;
        cpp: num_threads; ransac: max_iterations, confidence, seed; fgr: iterations;
        kiss_matcher: noise_bound_gain; turboreg: max_N, tau, num_pivot, radius_nms, tau_inlier, metric,
            hard, refine_iters, num_threads;
        mac: inlier_threshold, min_clique_size, refine_iters, reduction, search (auto | bnb | enumerate),
            max_cliques, max_nodes, max_work, max_product_work, enumerate_budget, time_limit_s;
        graph: kernel, alpha, tau, threshold (None = the family's table, fastmac_exp/params.py).
    An unknown or ambiguous name raises InputError naming what to write.

    Returns a RegistrationResult: `pose` maps source into target. Check `result.ok` (False, with
    `result.error` and a NaN pose, where no pose was found, e.g. no edge left after sampling) and
    `result.trusted`: False where the pose explains no more correspondences than chance would
    (`result.confidence`, in [0, 1], is what it is thresholded by; docs/trust.md). Bad input raises
    InputError.

    >>> result = register(src_xyz, tgt_xyz, family="3dmatch", voxel_size=0.05, ratio=0.2)
    >>> result.pose  # 4x4, maps source into target
    >>> register(corr, samples=5000, scores="exact", backend="turboreg", num_pivot=1000)
    """
    watch = Stopwatch()  # every stage, back to back: result.timings adds up to end_to_end
    picks: dict[str, str] = {}
    if isinstance(sampler, str):
        picks["sampler"] = sampler
    if isinstance(backend, str):
        picks["backend"] = _backend_choice(backend)
    if isinstance(descriptor, str):
        picks["descriptor"] = descriptor
    cfg = compose_run(picks)
    cfg.seed = int(seed)
    apply_options(cfg, options, tuple(picks))
    check_devices(cfg)
    rng = np.random.default_rng(seed)
    sampler_obj = instantiate_part(cfg.sampler) if isinstance(sampler, str) else sampler
    backend_obj = instantiate_part(cfg.backend) if isinstance(backend, str) else backend
    if isinstance(descriptor, str):
        descriptor = instantiate_part(cfg.descriptor)
    graph_overrides = OmegaConf.to_container(cfg.graph, resolve=True)
    mac_overrides = OmegaConf.to_container(cfg.mac, resolve=True)
    graph_key = "fpfh"
    offset = np.zeros(3)  # correspondences are moved by register_correspondences itself
    resolution = FIXED_RESOLUTION  # correspondences alone: no clouds to compute it from
    watch.lap("setup")
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
        watch.lap("clean")
        resolution = resolution_for(family, src, tgt)
        watch.lap("resolution")
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
        # georeferenced clouds: moved once to a frame at the pair's centre, the pose mapped back on exit
        offset = pair_offset(pair)
        corr = descriptor(moved_pair(pair, offset), rng)
        watch.lap("describe")
    if len(corr) < 3:  # else the sampler's advice would be a ratio above 1
        raise InputError(f"{len(corr)} correspondence(s): a clique, and a pose, needs at least 3")
    params = mac_params_for(family, graph_key, resolution, graph_overrides, mac_overrides)
    sample_graph = mac_params_for(family, graph_key, FIXED_RESOLUTION, graph_overrides, mac_overrides).graph
    try:
        result, _ = register_correspondences(
            corr,
            params,
            sampler_obj,
            backend_obj,
            ratio,
            family,
            rng,
            sample_graph=sample_graph,
            samples=samples,
        )
    except RegistrationFailed as exc:  # a result flagged as failed, not an exception to catch
        nan = np.full((4, 4), np.nan)
        empty = np.zeros(0, np.int64)
        return RegistrationResult(
            pose=nan, pose_unrefined=nan.copy(), kept=empty, clique=empty, error=str(exc)
        )
    watch.lap_in_parts(registration_parts(result.timings))
    result.timings = watch.timings(result.timings["total"])
    return result_to_original(result, offset)


def _backend_choice(name: str) -> str:
    """A backend name as the config group spells it; "auto" is the C++ core where it is built."""
    if name != "auto":
        return name
    from fastmac_exp import core

    return "cpp" if core.available() else "python"


def _points(a: Any, what: str) -> np.ndarray:
    arr = np.asarray(a, dtype=np.float64)
    if arr.ndim != 2 or arr.shape[1] != 3:
        raise InputError(f"register(): {what} must be an (N, 3) array of points, got shape {arr.shape}")
    return arr
