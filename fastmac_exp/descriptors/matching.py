"""The part every feature front end shares: describe both clouds, match (`match_descriptors` for learned
unit-length features), cap, label."""

from __future__ import annotations

from collections.abc import Callable

import numpy as np

from fastmac_exp.errors import InputError
from fastmac_exp.types import Correspondences, Pair

Matcher = Callable[[np.ndarray, np.ndarray, bool], tuple[np.ndarray, np.ndarray, np.ndarray]]
Chooser = Callable[[np.ndarray, np.random.Generator], np.ndarray]  # (keypoints, rng) -> the rows described


def correspondences_from_features(
    descriptor, pair: Pair, rng: np.random.Generator, match: Matcher
) -> Correspondences:
    """Keypoints + features of both clouds via `descriptor.features(points, voxel, what=...)`, matched by
    `match(src_f, tgt_f, mutual) -> (src_idx, tgt_idx, distance)`, capped at `descriptor.max_correspondences`
    by a random subset drawn with `rng`, scored 1 - distance and labelled by the pair's GT."""
    _need_clouds(descriptor, pair)
    voxel = descriptor.voxel_size if descriptor.voxel_size is not None else pair.voxel_size
    src_kp, src_f = descriptor.features(pair.src_cloud, voxel, what=f"pair {pair.name!r}: source cloud")
    tgt_kp, tgt_f = descriptor.features(pair.tgt_cloud, voxel, what=f"pair {pair.name!r}: target cloud")
    return _matched(descriptor, pair, rng, match, src_kp, src_f, tgt_kp, tgt_f)


def correspondences_from_chosen_keypoints(
    descriptor, pair: Pair, rng: np.random.Generator, match: Matcher, choose: Chooser
) -> Correspondences:
    """`correspondences_from_features` on chosen keypoints of both clouds, for a descriptor that can describe
    chosen keypoints only (`keypoints(points, voxel, what) -> (cloud, keypoints)`, `features_of(cloud,
    keypoints, rows, what)`): each cloud's keypoints cut to the rows `choose(keypoints, rng)` (source first),
    only those described, then matched, capped and labelled as there. With `choose` keeping every row and
    drawing nothing from `rng`, the output is `correspondences_from_features`'."""
    _need_clouds(descriptor, pair)
    voxel = descriptor.voxel_size if descriptor.voxel_size is not None else pair.voxel_size
    sides = []
    for side, points in (("source", pair.src_cloud), ("target", pair.tgt_cloud)):
        what = f"pair {pair.name!r}: {side} cloud"
        cloud, kp = descriptor.keypoints(points, voxel, what)
        rows = np.asarray(choose(kp, rng), dtype=np.int64)
        sides += [kp[rows], descriptor.features_of(cloud, kp, rows, what)]
    return _matched(descriptor, pair, rng, match, *sides)


def _matched(descriptor, pair: Pair, rng, match: Matcher, src_kp, src_f, tgt_kp, tgt_f) -> Correspondences:
    """Matched (`descriptor.mutual`), capped at `descriptor.max_correspondences` by a random subset drawn
    with `rng`, scored 1 - distance and labelled by the pair's GT."""
    si, ti, dist = match(src_f, tgt_f, descriptor.mutual)
    keep = capped_rows(len(si), descriptor.max_correspondences, rng)
    if keep is not None:
        si, ti, dist = si[keep], ti[keep], dist[keep]
    corr = Correspondences(src=src_kp[si], tgt=tgt_kp[ti], scores=1.0 - dist)
    return pair.label(corr)


def correspondences_from_kept_sources(
    descriptor, pair: Pair, rng: np.random.Generator, match: Matcher
) -> Correspondences:
    """`correspondences_from_features` for a descriptor that can describe chosen keypoints only
    (`keypoints(points, voxel, what) -> (cloud, keypoints)`, `features_of(cloud, keypoints, rows, what)`):
    with one-way matching every source keypoint gives one correspondence, so the cap's subset (the same
    draw from `rng`) is known before anything is described and only those source keypoints are; the
    output is the same. Mutual matching needs every descriptor and takes the plain path."""
    if descriptor.mutual:
        return correspondences_from_features(descriptor, pair, rng, match)
    _need_clouds(descriptor, pair)
    voxel = descriptor.voxel_size if descriptor.voxel_size is not None else pair.voxel_size
    what = f"pair {pair.name!r}: source cloud"
    cloud, src_kp = descriptor.keypoints(pair.src_cloud, voxel, what)
    si = capped_rows(len(src_kp), descriptor.max_correspondences, rng)
    si = np.arange(len(src_kp)) if si is None else si
    src_f = descriptor.features_of(cloud, src_kp, si, what)
    tgt_kp, tgt_f = descriptor.features(pair.tgt_cloud, voxel, what=f"pair {pair.name!r}: target cloud")
    rows, ti, dist = match(src_f, tgt_f, False)
    corr = Correspondences(src=src_kp[si[rows]], tgt=tgt_kp[ti], scores=1.0 - dist)
    return pair.label(corr)


def capped_rows(n: int, cap: int, rng: np.random.Generator) -> np.ndarray | None:
    """The rows a cap keeps of `n` correspondences: a sorted random subset of `cap` drawn with `rng`, or None
    (all) when `cap` is 0 or not below `n`."""
    if cap and n > cap:
        return np.sort(rng.choice(n, size=cap, replace=False))
    return None


def _need_clouds(descriptor, pair: Pair) -> None:
    if pair.src_cloud is None or pair.tgt_cloud is None:
        raise InputError(
            f"pair {pair.name!r}: the {descriptor.name} descriptor needs both point clouds, but "
            f"{'the source' if pair.src_cloud is None else 'the target'} cloud is missing"
        )


def match_descriptors(
    src_feat: np.ndarray, tgt_feat: np.ndarray, mutual: bool = False, chunk: int = 2048
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Exact nearest target descriptor for every source descriptor (unit vectors: max cosine).

    Returns `(src_idx, tgt_idx, euclidean feature distance)`; `mutual` keeps only pairs that are each
    other's nearest neighbour. Brute force in chunks (faster than a k-d tree in 32 dimensions).
    """
    s = np.ascontiguousarray(src_feat, dtype=np.float32)
    t = np.ascontiguousarray(tgt_feat, dtype=np.float32)

    def nearest(a: np.ndarray, b: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        idx = np.empty(len(a), dtype=np.int64)
        sim = np.empty(len(a), dtype=np.float32)
        for i in range(0, len(a), chunk):
            block = a[i : i + chunk] @ b.T
            j = np.argmax(block, axis=1)
            idx[i : i + chunk] = j
            sim[i : i + chunk] = block[np.arange(len(j)), j]
        return idx, sim

    nn_idx, sim = nearest(s, t)
    dist = np.sqrt(np.clip(2.0 - 2.0 * sim.astype(np.float64), 0.0, None))
    src_idx = np.arange(len(s))
    if mutual:
        back, _ = nearest(t, s)
        keep = back[nn_idx] == src_idx
        src_idx, nn_idx, dist = src_idx[keep], nn_idx[keep], dist[keep]
    return src_idx, nn_idx, dist
