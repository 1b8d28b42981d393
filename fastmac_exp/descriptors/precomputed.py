"""The `precomputed` front end: the pair already carries its correspondences (MAC's released layout)."""

from __future__ import annotations

import numpy as np

from fastmac_exp.descriptors.base import Descriptor
from fastmac_exp.errors import InputError
from fastmac_exp.types import Correspondences, Pair


class PrecomputedDescriptor(Descriptor):
    """Returns `pair.correspondences` as loaded (with the file's GT labels).

    `graph_key` names the descriptor that produced the correspondences ("fpfh", "fcgf", "spinnet", ...):
    it selects the graph parameters (fastmac_exp.params) and, through the dataset configs, which files
    the MAC-layout datasets read (e.g. `@corr_fcgf.txt` for fcgf).
    """

    name = "precomputed"

    def __init__(self, graph_key: str = "fpfh") -> None:
        super().__init__(graph_key)

    def __call__(self, pair: Pair, rng: np.random.Generator) -> Correspondences:
        if pair.correspondences is None:
            raise InputError(
                f"pair {pair.name!r}: the precomputed descriptor needs correspondences stored with the pair "
                "(datasets 3dmatch, 3dlomatch, kitti); this dataset gives point clouds, so choose a "
                "front end that computes them, e.g. descriptor=fpfh"
            )
        corr = pair.correspondences
        if corr.labels is None and pair.gt is not None:
            corr = pair.label(corr)
        return corr
