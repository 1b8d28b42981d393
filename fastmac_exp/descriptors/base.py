"""The descriptor front-end interface: a pair in, correspondences out."""

from __future__ import annotations

from typing import Protocol

import numpy as np

from fastmac_exp.types import Correspondences, Pair


class Descriptor(Protocol):
    """Turns a Pair into putative correspondences (source point -> target point, metres).

    `graph_key` names the descriptor in the graph-parameter table (fastmac_exp.params), e.g. "fpfh"
    or "fcgf". Implementations attach GT labels with `pair.label(corr)` when the pair has a GT.
    """

    name: str
    graph_key: str

    def __call__(self, pair: Pair, rng: np.random.Generator) -> Correspondences: ...
