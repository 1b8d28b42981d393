"""One pair through the whole flow: describe -> sample -> MAC -> metrics."""

from __future__ import annotations

import time
from dataclasses import dataclass, field
from typing import Any

import numpy as np

from fastmac_exp.backends.base import Backend
from fastmac_exp.cache import CorrespondenceCache
from fastmac_exp.descriptors.base import Descriptor
from fastmac_exp.errors import InputError, RegistrationFailed
from fastmac_exp.families import FIXED_RESOLUTION
from fastmac_exp.families import family as family_record
from fastmac_exp.metrics import pose_errors
from fastmac_exp.params import GraphParams, MacParams, mac_params_for
from fastmac_exp.resolution import resolution_for
from fastmac_exp.samplers import Sampler, SampleResult
from fastmac_exp.types import Correspondences, Pair, RegistrationResult

PROTOCOLS = ("honest", "reference")


def check_not_degenerate(src: np.ndarray, tgt: np.ndarray) -> None:
    """A pose from duplicated or collinear points is not determined: refuse it instead of guessing.
    An empty set passes: the peer backends (RANSAC, FGR, ...) report no clique to check."""
    if len(src) == 0 and len(tgt) == 0:
        return
    for name, pts in (("source", src), ("target", tgt)):
        centred = pts - pts.mean(axis=0)
        sv = np.linalg.svd(centred, compute_uv=False) if len(pts) >= 2 else np.zeros(1)
        scale = max(float(np.abs(pts).max()), 1.0)
        if len(sv) < 2 or sv[1] <= 1e-9 * scale * np.sqrt(len(pts)):
            raise RegistrationFailed(
                f"the winning clique's {name} points are duplicated or collinear ({len(pts)} points); "
                "the rotation about their line is undetermined"
            )


def register_correspondences(
    corr: Correspondences,
    params: MacParams,
    sampler: Sampler,
    backend: Backend,
    ratio: float = 1.0,
    family: str = "3dmatch",
    rng: np.random.Generator | None = None,
    sample_graph: GraphParams | None = None,
) -> tuple[RegistrationResult, SampleResult]:
    """Sample, then run MAC on the kept correspondences. Indices in the result refer to `corr`.

    sample_graph: the sampler's compatibility graph, when it differs from MAC's (FastMAC's graph fixes the
    resolution at 0.006 where MAC computes it from the clouds); None = MAC's.
    """
    rng = rng if rng is not None else np.random.default_rng(0)
    corr.validate()
    t0 = time.perf_counter()
    sample = sampler.sample(corr, ratio, sample_graph or params.graph, family, rng)
    kept = sample.indices
    result = backend.register(corr.subset(kept), params)
    total = (time.perf_counter() - t0) * 1e3
    check_not_degenerate(corr.src[kept][result.clique], corr.tgt[kept][result.clique])
    result.kept = kept
    result.clique = kept[result.clique]
    result.scores = sample.scores
    result.timings = {"sampling": sample.timings.get("sampling", 0.0), **result.timings, "total": total}
    return result, sample


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
        corr = descriptor(pair, rng)
        describe_ms = (time.perf_counter() - t0) * 1e3
    params = mac_params_for(family, graph_key, resolution, mac_overrides=mac_overrides)
    sample_graph = mac_params_for(family, graph_key, FIXED_RESOLUTION, mac_overrides=mac_overrides).graph
    result, _ = register_correspondences(
        corr, params, sampler_obj, backend_obj, ratio, family, rng, sample_graph=sample_graph
    )
    result.timings["describe"] = describe_ms
    return result


@dataclass
class PairOutcome:
    """Everything known about one processed pair: the results row and, for trackers, the arrays."""

    row: dict[str, Any]
    pair: Pair | None = None
    corr: Correspondences | None = None
    result: RegistrationResult | None = None
    sample: SampleResult | None = None
    extra: dict[str, Any] = field(default_factory=dict)


def evaluate(row: dict[str, Any], pair: Pair, result: RegistrationResult, protocol: str) -> None:
    """Fill RE/TE/success into `row`. honest: judge the final pose. reference: the original code's
    GT-assisted rule (spec 5.4): a pair counts as registered when either the unrefined or the refined pose
    passes; RE/TE are those of the refined pose."""
    if protocol not in PROTOCOLS:
        raise InputError(f"protocol must be one of {PROTOCOLS}, got {protocol!r}")
    if pair.gt is None:
        row.update(re_deg=np.nan, te_cm=np.nan, success=None)
        return
    final = pose_errors(result.pose, pair.gt, pair.re_thresh_deg, pair.te_thresh_m)
    success = final.success
    if protocol == "reference":
        success = (
            success
            or pose_errors(result.pose_unrefined, pair.gt, pair.re_thresh_deg, pair.te_thresh_m).success
        )
    row.update(re_deg=final.re_deg, te_cm=final.te_cm, success=bool(success))


def run_pair(
    pair: Pair,
    descriptor: Descriptor,
    sampler: Sampler,
    backend: Backend,
    ratio: float,
    rng: np.random.Generator,
    protocol: str = "honest",
    graph_overrides: dict[str, Any] | None = None,
    mac_overrides: dict[str, Any] | None = None,
    row: dict[str, Any] | None = None,
    cache: CorrespondenceCache | None = None,
    cache_key: str | None = None,
) -> PairOutcome:
    """Describe, sample, register and evaluate one pair; exceptions propagate to the caller.

    With a cache and a key, the descriptor's output is read from / written to the cache (its original
    describe time is reported, and the row says `describe_cached`).
    """
    row = row if row is not None else {}  # filled in place: a pair that fails later keeps what was measured
    # The descriptor draws from a spawned child stream, which leaves `rng` itself untouched, so the
    # sampler's draws are the same whether the correspondences were computed or read from the cache.
    (desc_rng,) = rng.spawn(1)
    describe_ms = 0.0
    if pair.correspondences is not None:
        corr = pair.correspondences
    else:
        cached = cache.load(cache_key) if cache is not None and cache_key else None
        if cached is not None:
            corr, describe_ms = cached
            row["describe_cached"] = True
        else:
            t0 = time.perf_counter()
            corr = descriptor(pair, desc_rng)
            describe_ms = (time.perf_counter() - t0) * 1e3
            if cache is not None and cache_key:
                cache.save(cache_key, corr, describe_ms)
    if pair.gt is not None and corr.labels is None:
        pair.label(corr)
    params = mac_params_for(
        pair.family, descriptor.graph_key, pair.resolution, graph_overrides, mac_overrides
    )
    # FastMAC's sampling graph fixes the resolution at 0.006 (spec 7.2); MAC's uses the pair's
    sample_graph = mac_params_for(
        pair.family, descriptor.graph_key, FIXED_RESOLUTION, graph_overrides, mac_overrides
    ).graph
    row.update(
        resolution=pair.resolution,
        n_in=len(corr),
        inliers_in=int(corr.labels.sum()) if corr.labels is not None else None,
        inlier_ratio_in=corr.inlier_ratio,
    )
    result, sample = register_correspondences(
        corr, params, sampler, backend, ratio, pair.family, rng, sample_graph=sample_graph
    )
    kept_labels = corr.labels[result.kept] if corr.labels is not None else None
    row.update(
        ratio=sample.ratio,
        n_kept=len(result.kept),
        inlier_ratio_kept=float(kept_labels.mean()) if kept_labels is not None else np.nan,
        clique_size=len(result.clique),
        clique_inliers=int(corr.labels[result.clique].sum()) if corr.labels is not None else None,
        score=result.score,
        n_edges=result.n_edges,
        n_cliques=result.n_cliques,
        n_selected=result.n_selected,
        reduced=result.reduced,
        search=result.search,
        search_nodes=result.search_nodes,
        cap_hit=result.cap_hit,
        zero_filled=sample.zero_filled,
    )
    evaluate(row, pair, result, protocol)
    timings = {"describe": describe_ms, **result.timings}
    for stage, ms in timings.items():
        row[f"t_{stage}_ms"] = ms
    row["pose"] = " ".join(f"{v:.9g}" for v in result.pose.ravel())
    return PairOutcome(row=row, pair=pair, corr=corr, result=result, sample=sample)
