"""Georeferenced clouds (UTM-like coordinates, 1e5-1e6 m): the descriptors and MAC work on the pair moved
by a common offset, so that float32 screens, covariances and Kabsch see small numbers, and the offset is
composed into the returned pose. A result then does not depend on where the scan sits.

Pairs whose common centre is within CENTRE_BEYOND of the origin (scans in their sensor's frame) are left
as they are: float32 resolves 6e-5 m there, a thousandth of the smallest voxel, and FPFH's normals keep
facing the frame's origin, which is the sensor (descriptors/fpfh.py). For a moved pair they face the
pair's centre, the best stand-in for a sensor that a georeferenced frame no longer says where it was.
"""

from __future__ import annotations

import dataclasses

import numpy as np

from fastmac_exp.types import Correspondences, Pair, RegistrationResult

CENTRE_BEYOND = 1e3  # metres


def common_offset(*clouds: np.ndarray | None) -> np.ndarray:
    """The pair's common offset: the mean of the clouds' centroids in whole metres (subtracting it is exact
    for coordinates on a fine binary grid), or zero near the origin."""
    arrays = [np.asarray(c, dtype=np.float64) for c in clouds if c is not None and len(c)]
    if not arrays:
        return np.zeros(3)
    # |mean| <= max |x|: a pair within half CENTRE_BEYOND of the origin everywhere is not moved, decided by
    # min / max (a KITTI scan: 0.1 ms against 1-2 ms for the column means); NaN fails the test, as before
    if max(max(-float(a.min()), float(a.max())) for a in arrays) <= CENTRE_BEYOND / 2:
        return np.zeros(3)
    centres = [a.mean(axis=0) for a in arrays]
    mid = np.mean(centres, axis=0)
    return np.round(mid) if np.abs(mid).max() > CENTRE_BEYOND else np.zeros(3)


def translate(corr: Correspondences, d: np.ndarray) -> Correspondences:
    return dataclasses.replace(corr, src=corr.src + d, tgt=corr.tgt + d)


def to_original(pose: np.ndarray, offset: np.ndarray) -> np.ndarray:
    """A pose between the moved clouds (x - offset) as a pose between the original ones."""
    out = np.array(pose, dtype=np.float64, copy=True)
    out[:3, 3] = pose[:3, 3] + offset - pose[:3, :3] @ offset
    return out


def to_moved(pose: np.ndarray, offset: np.ndarray) -> np.ndarray:
    """The inverse of to_original: a pose between the original clouds as one between the moved ones."""
    return to_original(pose, -offset)


def pair_offset(pair: Pair) -> np.ndarray:
    """The pair's common offset: from its clouds, else from its correspondences."""
    if pair.src_cloud is not None and pair.tgt_cloud is not None:
        return common_offset(pair.src_cloud, pair.tgt_cloud)
    if pair.correspondences is not None:
        return common_offset(pair.correspondences.src, pair.correspondences.tgt)
    return np.zeros(3)


def result_to_original(result: RegistrationResult, offset: np.ndarray) -> RegistrationResult:
    """A result registered in the moved frame with its poses mapped back to the original one (in place)."""
    if offset.any():
        result.pose = to_original(result.pose, offset)
        result.pose_unrefined = to_original(result.pose_unrefined, offset)
    return result


def moved_pair(pair: Pair, offset: np.ndarray) -> Pair:
    """The pair in the moved frame: clouds, correspondences and GT."""
    if not offset.any():
        return pair
    return dataclasses.replace(
        pair,
        src_cloud=None if pair.src_cloud is None else pair.src_cloud - offset,
        tgt_cloud=None if pair.tgt_cloud is None else pair.tgt_cloud - offset,
        correspondences=None if pair.correspondences is None else translate(pair.correspondences, -offset),
        gt=None if pair.gt is None else to_moved(pair.gt, offset),
    )


def describe_moved(descriptor, pair: Pair, rng: np.random.Generator) -> Correspondences:
    """The descriptor's correspondences, computed on the moved clouds, in the original frame (for callers that
    work in the original frame; run_pair and register move the pair once and stay in the moved frame)."""
    offset = common_offset(pair.src_cloud, pair.tgt_cloud)
    corr = descriptor(moved_pair(pair, offset), rng)
    return translate(corr, offset) if offset.any() else corr
