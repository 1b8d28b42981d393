"""The descriptor front-end interface: a pair in, correspondences out."""

from __future__ import annotations

import numpy as np

from fastmac_exp.errors import InputError
from fastmac_exp.types import Correspondences, Pair


class Descriptor:
    """Turns a Pair into putative correspondences (source point -> target point, metres).

    `graph_key` names the descriptor in the graph-parameter table (fastmac_exp.families), e.g. "fpfh" or
    "fcgf"; every descriptor takes it as a constructor argument (None: its own default), so a config node
    such as conf/descriptor/precomputed.yaml instantiates as it stands. Implementations attach GT labels
    with `pair.label(corr)` when the pair has a GT.
    """

    name = "descriptor"
    default_graph_key = "fpfh"

    def __init__(self, graph_key: str | None = None) -> None:
        key = self.default_graph_key if graph_key is None else graph_key
        if not isinstance(key, str) or not key:
            raise InputError(f"{self.name}: graph_key must be a descriptor name such as 'fpfh', got {key!r}")
        self.graph_key = key

    def __call__(self, pair: Pair, rng: np.random.Generator) -> Correspondences:
        raise NotImplementedError


class FeatureDescriptor(Descriptor):
    """A descriptor that describes keypoints of each cloud and matches them; what
    `matching.correspondences_from_features` reads: `features`, `voxel_size` (None: the pair's), `mutual`
    and `max_correspondences` (a random subset of this many, 0 = no cap)."""

    voxel_size: float | None = None
    mutual: bool = False
    max_correspondences: int = 5000

    def features(
        self, points: np.ndarray, voxel: float, what: str = "cloud"
    ) -> tuple[np.ndarray, np.ndarray]:
        """Keypoints (M, 3) and their features (M, D) of one cloud."""
        raise NotImplementedError
