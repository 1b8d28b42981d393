"""The library facade: register two clouds, or a set of correspondences, with FastMAC in one call."""

from __future__ import annotations

import time
from typing import Any

import numpy as np
from omegaconf import OmegaConf

from fastmac_exp.backends.base import Backend
from fastmac_exp.descriptors.base import Descriptor
from fastmac_exp.errors import FastMacError, InputError, RegistrationFailed
from fastmac_exp.escalation import DEFAULT_BUDGET_S, ESCALATE_CHOICES, Step, available_steps
from fastmac_exp.escalation import escalate as escalate_steps
from fastmac_exp.families import FIXED_RESOLUTION
from fastmac_exp.families import family as family_record
from fastmac_exp.geometry.offset import moved_pair, pair_offset, result_to_original
from fastmac_exp.geometry.resolution import resolution_for
from fastmac_exp.pipeline import register_correspondences
from fastmac_exp.pipeline.flow import DECOY_CHOICES
from fastmac_exp.pipeline.stopwatch import Stopwatch, registration_parts
from fastmac_exp.plans import plan_for
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
    escalate: str = "auto",
    budget_s: float = DEFAULT_BUDGET_S,
    decoy: str = "auto",
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
    descriptor: for clouds, a conf/descriptor option (fpfh, fcgf, ...) or a Descriptor (None: FPFH, whose
        options, e.g. mutual=True, are then reachable by name as for descriptor="fpfh").
    seed: the sampler's (and RANSAC's) draws.
    escalate: "auto" (default): when the pose is not trusted, try wider configurations in order of cost
        until one is (fastmac_exp.escalation.STEPS: samples="auto", MAC on every correspondence, MAC's
        graph at the fixed resolution, mutual matching, a finer keypoint voxel, BUFFER where ONNX Runtime
        is installed), within `budget_s` seconds; `result.step` names the step that gave the pose and
        `result.escalation` lists each step tried with its cost. "off": the call as given, once.
    decoy: the trust check's decoy run ("auto": only where the pose is not trusted without it; "on";
        "off"; docs/trust.md).
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
        fpfh (the default for clouds): mutual, max_correspondences, ratio_test, impl, ...;
        mac: inlier_threshold, min_clique_size, refine_iters, reduction, search (auto | bnb | enumerate),
            max_cliques, max_nodes, max_work, max_product_work, enumerate_budget, time_limit_s;
        graph: kernel, alpha, tau, threshold (None = the family's table, fastmac_exp/params.py).
    An unknown or ambiguous name raises InputError naming what to write.
    The configuration of a set of options is composed and built once and kept (fastmac_exp.plans): a
    call in a loop pays only its stages.

    MAC's graph: from clouds it uses the clouds' mesh resolution where the family computes one (3DMatch,
    3DLoMatch: the reference code's rule); from a Correspondences set there are no clouds, so it uses the
    fixed resolution (0.006 m). The same matches can therefore give two answers; the escalation tries
    the fixed-resolution graph on clouds too (step mac_fixed_resolution), so it covers both.

    Returns a RegistrationResult: `pose` maps source into target. Check `result.ok` (False, with
    `result.error` and a NaN pose, where no pose was found, e.g. no edge left after sampling) and
    `result.trusted`: False where the pose is not clearly better than chance, the search's own pick on
    permuted matches, or a distinct rival pose (`result.confidence`, in [0, 1], is what it is
    thresholded by; docs/trust.md). Bad input raises InputError.

    >>> result = register(src_xyz, tgt_xyz, family="3dmatch", voxel_size=0.05, ratio=0.2)
    >>> result.pose  # 4x4, maps source into target
    >>> register(corr, samples=5000, scores="exact", backend="turboreg", num_pivot=1000)
    """
    if escalate not in ESCALATE_CHOICES:
        raise InputError(f"register(): escalate must be one of {ESCALATE_CHOICES}, got {escalate!r}")
    if decoy not in DECOY_CHOICES:
        raise InputError(f"register(): decoy must be one of {DECOY_CHOICES}, got {decoy!r}")
    if not budget_s >= 0:
        raise InputError(f"register(): budget_s must be >= 0 seconds, got {budget_s}")
    clouds = not isinstance(source, Correspondences)
    if clouds and target is None:
        raise InputError("register(source, target): a target cloud is needed when source is a cloud")
    call = dict(family=family, voxel_size=voxel_size, sampler=sampler, ratio=ratio, samples=samples,
                backend=backend, descriptor=descriptor, seed=seed, decoy=decoy, options=options)  # fmt: skip
    t_call = time.perf_counter()
    prepared = _Prepared(source, target, family) if clouds else None
    described: dict[str, Correspondences] = {}  # steps that match alike share one description

    def attempt(step: Step) -> RegistrationResult:
        try:
            return _register_once(source, prepared, described, **_with_step(call, step))
        except FastMacError as exc:  # the call itself is the user's to fix; a wider step's is not
            if step.name == "first":
                raise
            return _failed(str(exc))

    if escalate == "off":
        result = attempt(Step("first"))
    else:
        fpfh = descriptor is None or descriptor == "fpfh"
        result = escalate_steps(attempt, available_steps(clouds, fpfh), budget_s)
    return _account(result, prepared, (time.perf_counter() - t_call) * 1e3)


def _account(result: RegistrationResult, prepared: _Prepared | None, call_ms: float) -> RegistrationResult:
    """The returned result's timings as one call's: the cleaning (done once for every step) after the set-up,
    and, where the escalation tried more than one step, `escalation`: the time of the steps whose pose was
    not kept; the stages still add up to `end_to_end`, the call's time."""
    t = result.timings
    stages = {k: v for k, v in t.items() if k not in ("total", "end_to_end")}
    if prepared is not None:
        stages = {k: v for k, v in stages.items() if k == "setup"} | {"clean": prepared.clean_ms} | {
            k: v for k, v in stages.items() if k != "setup"}  # fmt: skip
    if len(result.escalation) > 1:
        stages["escalation"] = max(call_ms - sum(stages.values()), 0.0)
    result.timings = {**stages, "total": t.get("total", 0.0), "end_to_end": sum(stages.values())}
    return result


class _Prepared:
    """The cleaned clouds and their mesh resolution, once for every step of an escalation."""

    def __init__(self, source: Any, target: Any, family: str) -> None:
        from fastmac_exp.io import clean_cloud

        t0 = time.perf_counter()
        self.src = clean_cloud(_points(source, "source"), "source cloud")[0]
        self.tgt = clean_cloud(_points(target, "target"), "target cloud")[0]
        self.clean_ms = (time.perf_counter() - t0) * 1e3
        self.family = family
        self._resolution: float | None = None

    @property
    def resolution(self) -> float:
        if self._resolution is None:
            self._resolution = resolution_for(self.family, self.src, self.tgt)
        return self._resolution


def _with_step(call: dict[str, Any], step: Step) -> dict[str, Any]:
    """The call's keywords with the step's changes: option keys (mutual) go into the options."""
    out = {**call, "options": dict(call["options"]), "resolution": "auto", "voxel_scale": 1.0}
    if step.name == "learned":  # the learned front end's own keypoint voxel (the family's)
        out["voxel_size"] = None
    for key, value in step.changes.items():
        if key in out:
            out[key] = value
        else:
            out["options"][key] = value
    return out


def _register_once(
    source: np.ndarray | Correspondences,
    prepared: _Prepared | None,
    described: dict[str, Correspondences],
    *,
    family: str,
    voxel_size: float | None,
    sampler: Sampler | str,
    ratio: float,
    samples: int | str | None,
    backend: Backend | str,
    descriptor: Descriptor | str | None,
    seed: int,
    decoy: str,
    options: dict[str, Any],
    resolution: str,
    voxel_scale: float,
) -> RegistrationResult:
    """One configuration, as register(escalate="off") runs it."""
    watch = Stopwatch()  # every stage, back to back: result.timings adds up to end_to_end
    picks: dict[str, str] = {}
    if isinstance(sampler, str):
        picks["sampler"] = sampler
    if isinstance(backend, str):
        picks["backend"] = _backend_choice(backend)
    if descriptor is None and prepared is not None:
        descriptor = "fpfh"  # the default front end, by name: its options are reachable
    if isinstance(descriptor, str):
        picks["descriptor"] = descriptor
    plan = plan_for(picks, options, seed)  # composed and built once per set of options
    cfg = plan.cfg
    rng = np.random.default_rng(seed)
    sampler_obj = plan.part("sampler") if isinstance(sampler, str) else sampler
    backend_obj = plan.part("backend") if isinstance(backend, str) else backend
    graph_key = "fpfh"
    offset = np.zeros(3)  # correspondences are moved by register_correspondences itself
    mac_resolution = FIXED_RESOLUTION  # correspondences alone: no clouds to compute it from
    watch.lap("setup")
    if isinstance(source, Correspondences):
        corr = source
    else:
        assert prepared is not None
        fam = family_record(family)
        if voxel_size is not None and not voxel_size > 0:
            raise InputError(
                f"register(): voxel_size must be positive or None (the family's), got {voxel_size}"
            )
        voxel = (fam.voxel_size if voxel_size is None else float(voxel_size)) * voxel_scale
        if resolution != "fixed":
            mac_resolution = prepared.resolution
        watch.lap("resolution")
        pair = Pair(name="register", family=family, src_cloud=prepared.src, tgt_cloud=prepared.tgt,
                    resolution=mac_resolution, voxel_size=voxel, **fam.thresholds())  # fmt: skip
        desc = plan.part("descriptor") if isinstance(descriptor, str) else descriptor
        graph_key = desc.graph_key
        # georeferenced clouds: moved once to a frame at the pair's centre, the pose mapped back on exit
        offset = pair_offset(pair)
        key = (
            f"{OmegaConf.to_yaml(cfg.descriptor) if isinstance(descriptor, str) else id(desc)}|{voxel}|{seed}"
        )
        if key not in described:
            described[key] = desc(moved_pair(pair, offset), rng)
        corr = described[key]
        watch.lap("describe")
    if len(corr) < 3:  # else the sampler's advice would be a ratio above 1
        error = f"{len(corr)} correspondence(s): a clique, and a pose, needs at least 3"
        if prepared is None:
            raise InputError(error)
        return _failed(error, watch)
    params = plan.params(family, graph_key, mac_resolution)
    sample_graph = plan.params(family, graph_key, FIXED_RESOLUTION).graph
    try:
        result, _ = register_correspondences(
            corr, params, sampler_obj, backend_obj, ratio, family, rng, sample_graph=sample_graph,
            samples=samples, decoy=decoy,
        )  # fmt: skip
    except RegistrationFailed as exc:  # a result flagged as failed, not an exception to catch
        return _failed(str(exc), watch)
    watch.lap_in_parts(registration_parts(result.timings))
    result.timings = watch.timings(result.timings["total"])
    return result_to_original(result, offset)


def _failed(error: str, watch: Stopwatch | None = None) -> RegistrationResult:
    """A result flagged as failed (NaN pose), with the stages timed before it failed."""
    timings: dict[str, float] = {}
    if watch is not None:
        watch.lap("other")
        timings = watch.timings(0.0)
    nan = np.full((4, 4), np.nan)
    empty = np.zeros(0, np.int64)
    return RegistrationResult(pose=nan, pose_unrefined=nan.copy(), kept=empty, clique=empty, error=error,
                              timings=timings)  # fmt: skip


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
