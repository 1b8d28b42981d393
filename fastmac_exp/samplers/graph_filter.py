"""FastMAC's samplers: score = |filter response of the generalized degree| (spec 7.2-7.5), drawn
stochastically in proportion to it."""

from __future__ import annotations

import numpy as np

from fastmac_exp.errors import InputError
from fastmac_exp.families import family as family_record
from fastmac_exp.graph import GraphSignals, compute_signals
from fastmac_exp.params import GraphParams
from fastmac_exp.samplers.base import Sampler, minmax
from fastmac_exp.types import Correspondences

FILTERS = ("highpass", "lowpass", "allpass")


def filter_response(sig: GraphSignals, filt: str) -> np.ndarray:
    """|response| of the degree signal to the high-, low- or all-pass filter (spec 7.3, 7.5)."""
    if filt == "highpass":
        return np.abs(sig.highpass)
    if filt == "lowpass":
        return np.abs(sig.lowpass)
    if filt == "allpass":
        return np.abs(sig.degree)
    raise InputError(f"unknown graph filter {filt!r}; expected one of {FILTERS}")


class GraphFilterSampler(Sampler):
    """FastMAC: score = |filter response of the generalized degree|, drawn stochastically.

    filter: highpass (FastMAC, Laplacian diag(s) - SOG), lowpass (I + D^-1 SOG), allpass (I).
    normalize: "auto" (min-max on 3DMatch-style families, none on KITTI, as the reference code),
    "minmax" or "none". squared: use |f|^2 as the paper writes instead of the code's |f|.
    self_loops: FastMAC's graph keeps W_ii = 1 (spec 7.2); False uses MAC's zero-diagonal SOG.
    impl: auto | cpp | torch | python; device: cpu or cuda (torch path).
    """

    def __init__(
        self,
        filter: str = "highpass",
        normalize: str = "auto",
        squared: bool = False,
        self_loops: bool = True,
        impl: str = "auto",
        device: str = "cpu",
    ) -> None:
        if filter not in FILTERS:
            raise InputError(f"unknown graph filter {filter!r}; expected one of {FILTERS}")
        if normalize not in ("auto", "minmax", "none"):
            raise InputError(f"sampler.normalize must be auto, minmax or none, got {normalize!r}")
        self.filter = filter
        self.name = filter + ("_squared" if squared else "")
        self.normalize = normalize
        self.squared = squared
        self.self_loops = self_loops
        self.impl = impl
        self.device = device

    def scores(
        self, corr: Correspondences, gp: GraphParams, family: str, rng: np.random.Generator
    ) -> np.ndarray:
        sig = compute_signals(corr.src, corr.tgt, gp, self.self_loops, self.impl, self.device)
        r = filter_response(sig, self.filter)
        if self.squared:
            r = r**2
        norm = self.normalize
        if norm == "auto":
            norm = family_record(family).sampler_normalize
        return minmax(r) if norm == "minmax" else r
