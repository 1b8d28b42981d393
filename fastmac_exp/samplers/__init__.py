"""Correspondence samplers (spec section 7) and the one name -> sampler table.

Graph-filter samplers (highpass, lowpass, allpass: FastMAC) score each correspondence by a filter
response of the generalized-degree signal of the second-order graph; xyz mixes in coordinate signals;
random, fps and deterministic are the paper's baselines; none keeps everything (plain MAC). The Hydra
configs in conf/sampler/ name the same classes through `_target_` (tests/test_config.py checks both).
"""

from __future__ import annotations

from collections.abc import Callable

from fastmac_exp.errors import InputError
from fastmac_exp.samplers.base import (
    Sampler,
    SampleResult,
    draw_proportional,
    gumbel_keys,
    minmax,
    sample_count,
)
from fastmac_exp.samplers.deterministic import DeterministicSampler
from fastmac_exp.samplers.graph_filter import FILTERS, GraphFilterSampler, filter_response
from fastmac_exp.samplers.simple import FPSSampler, NoSampler, RandomSampler, farthest_point_sampling
from fastmac_exp.samplers.xyz import XYZSampler, xyz_response

SAMPLERS: dict[str, Callable[[], Sampler]] = {
    "highpass": lambda: GraphFilterSampler("highpass"),
    "highpass_squared": lambda: GraphFilterSampler("highpass", squared=True),
    "lowpass": lambda: GraphFilterSampler("lowpass"),
    "allpass": lambda: GraphFilterSampler("allpass"),
    "xyz": lambda: XYZSampler("110"),
    "random": RandomSampler,
    "fps": FPSSampler,
    "deterministic": DeterministicSampler,
    "none": NoSampler,
}


def make_sampler(name: str) -> Sampler:
    """The sampler a config option names, with its defaults (the library API's `sampler="highpass"`)."""
    if name not in SAMPLERS:
        raise InputError(f"unknown sampler {name!r}; choose one of {sorted(SAMPLERS)}")
    return SAMPLERS[name]()


def ratio_used(name: str, ratio: float) -> float:
    """The ratio a sampler option really applies (`none` keeps everything whatever was asked)."""
    return 1.0 if name in SAMPLERS and SAMPLERS[name]().keeps_everything else ratio


__all__ = [
    "FILTERS",
    "SAMPLERS",
    "DeterministicSampler",
    "FPSSampler",
    "GraphFilterSampler",
    "NoSampler",
    "RandomSampler",
    "SampleResult",
    "Sampler",
    "XYZSampler",
    "draw_proportional",
    "farthest_point_sampling",
    "filter_response",
    "gumbel_keys",
    "make_sampler",
    "minmax",
    "ratio_used",
    "sample_count",
    "xyz_response",
]
