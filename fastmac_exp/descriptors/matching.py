"""The part every feature front end shares: describe both clouds, match, cap, label."""

from __future__ import annotations

from collections.abc import Callable

import numpy as np

from fastmac_exp.errors import InputError
from fastmac_exp.types import Correspondences, Pair

Matcher = Callable[[np.ndarray, np.ndarray, bool], tuple[np.ndarray, np.ndarray, np.ndarray]]


def correspondences_from_features(
    descriptor, pair: Pair, rng: np.random.Generator, match: Matcher
) -> Correspondences:
    """Keypoints + features of both clouds via `descriptor.features(points, voxel, what=...)`, matched by
    `match(src_f, tgt_f, mutual) -> (src_idx, tgt_idx, distance)`, capped at `descriptor.max_correspondences`
    by a random subset drawn with `rng`, scored 1 - distance and labelled by the pair's GT."""
    if pair.src_cloud is None or pair.tgt_cloud is None:
        raise InputError(
            f"pair {pair.name!r}: the {descriptor.name} descriptor needs both point clouds, but "
            f"{'the source' if pair.src_cloud is None else 'the target'} cloud is missing"
        )
    voxel = descriptor.voxel_size if descriptor.voxel_size is not None else pair.voxel_size
    src_kp, src_f = descriptor.features(pair.src_cloud, voxel, what=f"pair {pair.name!r}: source cloud")
    tgt_kp, tgt_f = descriptor.features(pair.tgt_cloud, voxel, what=f"pair {pair.name!r}: target cloud")
    si, ti, dist = match(src_f, tgt_f, descriptor.mutual)
    cap = descriptor.max_correspondences
    if cap and len(si) > cap:
        keep = np.sort(rng.choice(len(si), size=cap, replace=False))
        si, ti, dist = si[keep], ti[keep], dist[keep]
    corr = Correspondences(src=src_kp[si], tgt=tgt_kp[ti], scores=1.0 - dist)
    return pair.label(corr)
