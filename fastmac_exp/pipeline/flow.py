"""One pair through the whole flow: describe -> sample -> MAC -> metrics.

`run_pair` is the flow as the experiment runs it, reading top-down: the correspondences (from the
descriptor or the cache), MAC's and the sampler's graph parameters, sampling and registration
(`register_correspondences`), then the verdict (`evaluate`). The library facade `fastmac_exp.register`
is in fastmac_exp/api.py.
"""

from __future__ import annotations

import time
from collections.abc import Callable
from dataclasses import dataclass, field
from typing import Any, NamedTuple

import numpy as np

from fastmac_exp.backends.base import Backend
from fastmac_exp.descriptors.base import Descriptor
from fastmac_exp.errors import InputError, RegistrationFailed
from fastmac_exp.families import family as family_record
from fastmac_exp.geometry.metrics import pose_errors
from fastmac_exp.geometry.offset import common_offset, moved_pair, pair_offset, result_to_original, translate
from fastmac_exp.geometry.trust import ChanceCounter, assess, explained, rival_support
from fastmac_exp.params import GraphParams, MacParams, mac_params_for
from fastmac_exp.pipeline.cache import CorrespondenceCache
from fastmac_exp.pipeline.row import PairRow
from fastmac_exp.pipeline.stopwatch import Stopwatch, registration_parts
from fastmac_exp.samplers import Sampler, SampleResult
from fastmac_exp.types import Correspondences, Pair, RegistrationResult

PROTOCOLS = ("honest", "reference")


@dataclass
class PairOutcome:
    """Everything known about one processed pair: the results row and, for trackers, the arrays."""

    row: dict[str, Any]
    pair: Pair | None = None
    corr: Correspondences | None = None
    result: RegistrationResult | None = None
    sample: SampleResult | None = None
    extra: dict[str, Any] = field(default_factory=dict)


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
    row: PairRow | None = None,
    cache: CorrespondenceCache | None = None,
    cache_key: str | None = None,
    samples: int | str | None = None,
    decoy: str = "auto",
    watch: Stopwatch | None = None,
) -> PairOutcome:
    """Describe, sample, register and evaluate one pair; exceptions propagate to the caller.

    `row` is filled in place, so a pair that fails later keeps what was measured. With a cache and a
    key, the descriptor's output is read from / written to the cache (its original describe time is
    reported, and the row says `describe_cached`). `watch`: the pair's stopwatch, already holding what came
    before (the experiment's `load`); the row's timings are its stages back to back (pipeline/stopwatch.py).
    """
    watch = watch if watch is not None else Stopwatch()
    row = row if row is not None else PairRow(index=0, pair=pair.name, dataset="", descriptor=descriptor.name,
                                              sampler=sampler.name, backend=getattr(backend, "name", ""),
                                              ratio=ratio, seed=0, protocol=protocol)  # fmt: skip
    # Georeferenced pairs are moved once, here, to a frame at the pair's centre (fastmac_exp.geometry.offset):
    # describe, sample, register and evaluate (TE at the scene, not at the frame's far origin) work in it,
    # and the pose and the correspondences go back to the original frame on the way out.
    offset = pair_offset(pair)
    moved = moved_pair(pair, offset)
    # The descriptor draws from a spawned child stream, which leaves `rng` itself untouched, so the
    # sampler's draws are the same whether the correspondences were computed or read from the cache.
    (desc_rng,) = rng.spawn(1)
    corr, describe_ms, cached = describe(moved, descriptor, desc_rng, cache, cache_key)
    if cached:
        row.describe_cached = True
        watch.lap("other")  # reading the cache
        watch.ms["describe"] = describe_ms  # the original computation's, as the row has always said
    else:
        watch.lap_in_parts({"describe": describe_ms})  # other: the frame's move, the cache's write
    if moved.gt is not None and corr.labels is None:
        moved.label(corr)
    watch.lap("evaluate")  # the labels are for scoring
    key = descriptor.graph_key
    params = mac_params_for(pair.family, key, pair.resolution, graph_overrides, mac_overrides)
    # FastMAC's sampling graph fixes the resolution (spec 7.2: FIXED_RESOLUTION, rescaled for object scans);
    # MAC's uses the pair's
    res = pair.sampler_resolution
    sample_graph = mac_params_for(pair.family, key, res, graph_overrides, mac_overrides).graph
    row.set(
        resolution=pair.resolution,
        n_in=len(corr),
        inliers_in=int(corr.labels.sum()) if corr.labels is not None else None,
        inlier_ratio_in=corr.inlier_ratio,
    )
    result, sample = register_correspondences(
        corr,
        params,
        sampler,
        backend,
        ratio,
        pair.family,
        rng,
        sample_graph=sample_graph,
        samples=samples,
        decoy=decoy,
        distinct=(pair.re_thresh_deg, pair.te_thresh_m),
    )
    watch.lap_in_parts(registration_parts(result.timings))
    kept_labels = corr.labels[result.kept] if corr.labels is not None else None
    if sample.scores_used:
        row.set(scores=sample.scores_used, anchors=sample.anchors)
    if sample.core:
        row.set(core=sample.core)
    row.set(engine=sampler_engine(sampler, sample))
    row.set(
        samples=samples,
        ratio=sample.ratio,
        n_kept=len(result.kept),
        inlier_ratio_kept=float(kept_labels.mean()) if kept_labels is not None else np.nan,
        clique_size=len(result.clique),
        clique_inliers=int(corr.labels[result.clique].sum()) if corr.labels is not None else None,
        pose_inliers=result.inliers,
        trusted=result.trusted,
        confidence=result.confidence,
        chance_inliers=result.chance_inliers,
        rival_inliers=result.rival_inliers,
        decoy_count=result.decoy_count,
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
    verdict = evaluate(moved, result, protocol)
    row.set(re_deg=verdict.re_deg, te_cm=verdict.te_cm, success=verdict.success)
    result_to_original(result, offset)
    if offset.any():
        corr = translate(corr, offset)
    watch.lap("evaluate")
    row.timings = watch.timings(result.timings["total"])
    row.pose = " ".join(f"{v:.17g}" for v in result.pose.ravel())  # exact: georeferenced poses are ~1e6
    return PairOutcome(row=row.to_dict(), pair=pair, corr=corr, result=result, sample=sample)


def sampler_engine(sampler: Sampler, sample: SampleResult) -> str:
    """Which engine computed the sampler's graph signals (fastmac_exp.graph.signals.compute_signals'
    choice): cpp, torch:<device> or python; "" for samplers without a graph."""
    impl = getattr(sampler, "impl", None)
    if impl is None or sample.scores is None and not sample.scores_used:
        return ""
    device = str(getattr(sampler, "device", "cpu"))
    if sample.scores_used == "estimate":
        return "cpp"
    if impl in ("auto", "cpp"):
        from fastmac_exp import core

        if impl == "cpp" or core.available():
            return "cpp"
    if impl == "torch" or device != "cpu":
        return f"torch:{device}"
    return "python"


def pose_inliers(corr: Correspondences, pose: np.ndarray, threshold: float) -> int:
    """How many correspondences the pose maps to within `threshold` of their target point."""
    return explained(corr.src, corr.tgt, pose, threshold)


def describe(
    pair: Pair,
    descriptor: Descriptor,
    rng: np.random.Generator,
    cache: CorrespondenceCache | None = None,
    cache_key: str | None = None,
) -> tuple[Correspondences, float, bool]:
    """(correspondences, describe ms, read from the cache) of a pair in run_pair's frame (moved to its
    centre where it is georeferenced): the pair's own correspondences when it carries them, else the cache's
    entry, else the descriptor's output (then stored in the cache, in that frame: its key says so)."""
    if pair.correspondences is not None:
        return pair.correspondences, 0.0, False
    cached = cache.load(cache_key) if cache is not None and cache_key else None
    if cached is not None:
        corr, describe_ms = cached
        return corr, describe_ms, True
    t0 = time.perf_counter()
    corr = descriptor(pair, rng)
    describe_ms = (time.perf_counter() - t0) * 1e3
    if cache is not None and cache_key:
        cache.save(cache_key, corr, describe_ms)
    return corr, describe_ms, False


DECOY_CHOICES = ("auto", "on", "off")


def register_correspondences(
    corr: Correspondences,
    params: MacParams,
    sampler: Sampler,
    backend: Backend,
    ratio: float = 1.0,
    family: str = "3dmatch",
    rng: np.random.Generator | None = None,
    sample_graph: GraphParams | None = None,
    samples: int | str | None = None,
    decoy: str = "auto",
    distinct: tuple[float, float] | None = None,
) -> tuple[RegistrationResult, SampleResult]:
    """Sample, then run MAC on the kept correspondences. Indices in the result refer to `corr`.

    sample_graph: the sampler's compatibility graph, when it differs from MAC's (FastMAC's graph fixes the
    resolution at 0.006 where MAC computes it from the clouds); None = MAC's. samples: keep min(samples, N)
    instead of floor(N * ratio); "auto" (or ratio="auto"): the keep sized from the scores.
    decoy: the trust check's decoy run (the same sampler and backend on the correspondences with their
    targets permuted; geometry.trust): "on", "off", or "auto" (only where the pose is not trusted with
    its own clique standing in for what the search finds by chance: a tight clique of most inliers).
    distinct: (degrees, metres) beyond which a hypothesis is a rival of the chosen pose (None: the
    family's success thresholds).
    """
    if decoy not in DECOY_CHOICES:
        raise InputError(f"decoy must be one of {DECOY_CHOICES}, got {decoy!r}")
    rng = rng if rng is not None else np.random.default_rng(0)
    corr.validate()
    offset = common_offset(corr.src, corr.tgt)  # georeferenced correspondences of a library caller
    work = translate(corr, -offset) if offset.any() else corr
    t0 = time.perf_counter()
    sample = sampler.sample(work, ratio, sample_graph or params.graph, family, rng, samples=samples)
    kept = sample.indices
    result = backend.register(work.subset(kept), params)
    total = (time.perf_counter() - t0) * 1e3
    check_not_degenerate(work.src[kept][result.clique], work.tgt[kept][result.clique])

    def run_decoy(chance: ChanceCounter) -> float:
        stream = rng.spawn(1)[0]  # spawned only now: the sampler's own spawns are as without the decoy
        args = (sampler, backend, ratio, family, stream, sample_graph, samples, chance)
        return decoy_count(work, params, *args)

    trust_ms, decoy_ms = judge(result, work, params, family, distinct, decoy, run_decoy)
    result_to_original(result, offset)
    result.kept = kept
    result.clique = kept[result.clique]
    result.scores = sample.scores
    result.timings = {"sampling": sample.timings.get("sampling", 0.0), **result.timings, "check": trust_ms,
                      **({"decoy": decoy_ms} if decoy_ms is not None else {}), "total": total}  # fmt: skip
    return result, sample


def judge(
    result: RegistrationResult,
    work: Correspondences,
    params: MacParams,
    family: str,
    distinct: tuple[float, float] | None,
    decoy: str,
    run_decoy: Callable[[ChanceCounter], float],
) -> tuple[float, float | None]:
    """Set the result's inliers and trust (geometry.trust) on the correspondences it was found on;
    (trust ms, decoy ms or None where the decoy did not run)."""
    t0 = time.perf_counter()
    tau = params.inlier_threshold
    result.inliers = pose_inliers(work, result.pose, tau)
    chance = ChanceCounter(work.src, work.tgt, tau)
    fam = family_record(family)
    re_deg, te_m = distinct if distinct is not None else (fam.re_thresh_deg, fam.te_thresh_m)
    rival = rival_support(result.hypothesis_poses, result.hypothesis_scores, result.pose, work.src, work.tgt,
                          tau, re_deg, te_m, chance)  # fmt: skip
    args = (work.src, work.tgt, result.pose, tau, result.inliers, len(result.clique))
    verdict = assess(*args, rival=rival, chance=chance) if decoy != "on" else None  # the clique first
    decoy_ms = count = None
    if verdict is None or (decoy == "auto" and not verdict.trusted):
        t1 = time.perf_counter()
        count = run_decoy(chance)  # rng spawned only now: the sampler's own spawns are as without it
        decoy_ms = (time.perf_counter() - t1) * 1e3
        verdict = assess(*args, rival=rival, decoy_count=count, chance=chance)
    result.trusted, result.confidence = verdict.trusted, verdict.confidence
    result.chance_inliers = verdict.chance_inliers
    result.rival_inliers, result.rival_chance = verdict.rival_inliers, verdict.rival_chance
    result.decoy_count = float("nan") if count is None else count
    return (time.perf_counter() - t0) * 1e3 - (decoy_ms or 0.0), decoy_ms


def decoy_count(
    corr: Correspondences,
    params: MacParams,
    sampler: Sampler,
    backend: Backend,
    ratio: float,
    family: str,
    rng: np.random.Generator,
    sample_graph: GraphParams | None,
    samples: int | str | None,
    chance: ChanceCounter,
) -> float:
    """What the same search explains beyond chance when the matches carry no information: sampler and
    backend on the correspondences with their targets permuted (the same two point sets, so chance under
    any pose is the same), its clique included. 0 where the decoy finds no pose at all."""
    perm = rng.permutation(len(corr))
    fake = Correspondences(src=corr.src, tgt=corr.tgt[perm])
    try:
        sample = sampler.sample(fake, ratio, sample_graph or params.graph, family, rng, samples=samples)
        res = backend.register(fake.subset(sample.indices), params)
    except RegistrationFailed:
        return 0.0
    if not np.isfinite(res.pose).all():
        return 0.0
    k = explained(fake.src, fake.tgt, res.pose, params.inlier_threshold)
    return float(k - chance(res.pose))


class Verdict(NamedTuple):
    re_deg: float
    te_cm: float
    success: bool | None  # None: the pair has no GT


def evaluate(pair: Pair, result: RegistrationResult, protocol: str) -> Verdict:
    """RE/TE/success of a result. honest: judge the final pose. reference: the original code's
    GT-assisted rule (spec 5.4): a pair counts as registered when either the unrefined or the refined pose
    passes; RE/TE are those of the refined pose."""
    if protocol not in PROTOCOLS:
        raise InputError(f"protocol must be one of {PROTOCOLS}, got {protocol!r}")
    if pair.gt is None:
        return Verdict(np.nan, np.nan, None)
    final = pose_errors(result.pose, pair.gt, pair.re_thresh_deg, pair.te_thresh_m)
    success = final.success
    if protocol == "reference":
        success = (
            success
            or pose_errors(result.pose_unrefined, pair.gt, pair.re_thresh_deg, pair.te_thresh_m).success
        )
    return Verdict(final.re_deg, final.te_cm, bool(success))


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
