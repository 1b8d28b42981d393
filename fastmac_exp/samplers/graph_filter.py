"""FastMAC's samplers: score = |filter response of the generalized degree| (spec 7.2-7.5), drawn
stochastically in proportion to it."""

from __future__ import annotations

import time

import numpy as np

from fastmac_exp.errors import InputError
from fastmac_exp.families import family as family_record
from fastmac_exp.graph import GraphSignals, compute_signals
from fastmac_exp.graph.estimate import EstimateParams, choose_scores, estimate_signals
from fastmac_exp.params import GraphParams
from fastmac_exp.samplers.base import Sampler, SampleResult, draw_proportional, minmax
from fastmac_exp.samplers.keep_size import KeepParams, auto_keep, keep_params
from fastmac_exp.types import Correspondences

FILTERS = ("highpass", "lowpass", "allpass")
SCORES = ("exact", "estimate", "auto")


def filter_response(sig: GraphSignals, filt: str) -> np.ndarray:
    """|response| of the degree signal to the high-, low- or all-pass filter (spec 7.3, 7.5)."""
    if filt == "highpass":
        return np.abs(sig.highpass)
    if filt == "lowpass":
        return np.abs(sig.lowpass)
    if filt == "allpass":
        return np.abs(sig.degree)
    raise InputError(f"unknown graph filter {filt!r}; expected one of {FILTERS}")


def filter_scores(
    sig: GraphSignals, filt: str, family: str, squared: bool = False, normalize: str = "auto"
) -> np.ndarray:
    """The sampling scores of a graph filter: |response| (squared if asked), min-max normalised where
    `normalize` (or, for "auto", the family) says so."""
    r = filter_response(sig, filt)
    if squared:
        r = r**2
    norm = family_record(family).sampler_normalize if normalize == "auto" else normalize
    return minmax(r) if norm == "minmax" else r


class GraphFilterSampler(Sampler):
    """FastMAC: score = |filter response of the generalized degree|, drawn stochastically.

    filter: highpass (FastMAC, Laplacian diag(s) - SOG), lowpass (I + D^-1 SOG), allpass (I).
    normalize: "auto" (min-max on 3DMatch-style families, none on KITTI, as the reference code),
    "minmax" or "none". squared: use |f|^2 as the paper writes instead of the code's |f|.
    self_loops: FastMAC's graph keeps W_ii = 1 (spec 7.2); False uses MAC's zero-diagonal SOG.
    impl: auto | cpp | torch | python; device: cpu or cuda (torch path).
    scores: exact (the whole graph, the reference), estimate (from anchors: docs/estimated_scores.md) or
    auto (exact where its predicted cost is small, else the estimate); estimate: the estimate's budget
    (EstimateParams' fields). The estimate's randomness is a child stream of the run's, so `auto` that
    picks the exact scores draws the same sample as `exact`. keep: samples=auto's rule (KeepParams'
    fields, docs/keep_size.md).
    """

    def __init__(
        self,
        filter: str = "highpass",
        normalize: str = "auto",
        squared: bool = False,
        self_loops: bool = True,
        impl: str = "auto",
        device: str = "cpu",
        scores: str = "auto",
        estimate: EstimateParams | dict | None = None,
        keep: KeepParams | dict | None = None,
    ) -> None:
        if filter not in FILTERS:
            raise InputError(f"unknown graph filter {filter!r}; expected one of {FILTERS}")
        if normalize not in ("auto", "minmax", "none"):
            raise InputError(f"sampler.normalize must be auto, minmax or none, got {normalize!r}")
        if scores not in SCORES:
            raise InputError(f"sampler.scores must be one of {', '.join(SCORES)}, got {scores!r}")
        if estimate is None or isinstance(estimate, EstimateParams):
            self.estimate = estimate or EstimateParams()
        else:
            try:
                self.estimate = EstimateParams(**dict(estimate))
            except TypeError as exc:
                raise InputError(f"sampler.estimate: {exc}") from None
        self.keep = keep_params(keep)
        self.score_mode = scores
        self.filter = filter
        self.name = filter + ("_squared" if squared else "")
        self.normalize = normalize
        self.squared = squared
        self.self_loops = self_loops
        self.impl = impl
        self.device = device

    def select_auto(
        self, corr: Correspondences, gp: GraphParams, family: str, rng: np.random.Generator
    ) -> SampleResult:
        """samples=auto: the scores, then the smallest keep expected to hold enough of the dense core."""
        t0 = time.perf_counter()
        sig, mode = self.signals(corr, gp, rng)
        scores = filter_scores(sig, self.filter, family, self.squared, self.normalize)
        k, core = auto_keep(scores, sig.degree, self.keep)
        t1 = time.perf_counter()
        if k >= len(corr):
            idx, zero_filled = np.arange(len(corr), dtype=np.int64), 0
        else:
            idx, zero_filled = draw_proportional(scores, k, rng)
        timings = {"sampling_prep": (t1 - t0) * 1e3, "sampling_draw": (time.perf_counter() - t1) * 1e3}
        return SampleResult(indices=idx, scores=scores, zero_filled=zero_filled, timings=timings,
                            scores_used=mode, anchors=sig.anchors, core=core)  # fmt: skip

    def scores(
        self, corr: Correspondences, gp: GraphParams, family: str, rng: np.random.Generator
    ) -> np.ndarray:
        return self.scored(corr, gp, family, rng)[0]

    def scored(
        self, corr: Correspondences, gp: GraphParams, family: str, rng: np.random.Generator
    ) -> tuple[np.ndarray, dict]:
        sig, mode = self.signals(corr, gp, rng)
        scores = filter_scores(sig, self.filter, family, self.squared, self.normalize)
        return scores, {"scores_used": mode, "anchors": sig.anchors}

    def signals(
        self, corr: Correspondences, gp: GraphParams, rng: np.random.Generator
    ) -> tuple[GraphSignals, str]:
        """Exact or estimated signals, as `scores` says, and which ("exact" or "estimate")."""
        mode = self.score_mode
        if mode == "estimate" and not (self.self_loops and self.impl in ("auto", "cpp")):
            raise InputError(
                "sampler.scores=estimate estimates FastMAC's graph in the C++ core: it needs "
                f"self_loops=true and impl=auto|cpp (got self_loops={self.self_loops}, impl={self.impl})"
            )
        if mode == "auto" and not (self.self_loops and self.impl in ("auto", "cpp")):
            mode = "exact"
        p = None
        if mode != "exact":
            # a child stream: the parent's draws (the sample itself) do not depend on the estimate's
            (est_rng,) = rng.spawn(1)
            if mode == "auto":
                mode, p = choose_scores(corr.src, corr.tgt, gp, self.estimate, est_rng)
        if mode == "exact":
            sig = compute_signals(corr.src, corr.tgt, gp, self.self_loops, self.impl, self.device)
        else:
            sig = estimate_signals(corr.src, corr.tgt, gp, est_rng, self.estimate, pilot_result=p)
        return sig, mode
