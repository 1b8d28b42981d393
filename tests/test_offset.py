"""Georeferenced clouds: the same pair 1e5 m and 1e6 m from the origin registers as it does near it."""

from __future__ import annotations

import dataclasses

import numpy as np
import pytest

from fastmac_exp.backends import make_backend
from fastmac_exp.datasets.synthetic import SyntheticDataset
from fastmac_exp.descriptors.fpfh import FPFHDescriptor
from fastmac_exp.geometry.offset import common_offset, to_moved, to_original
from fastmac_exp.pipeline import run_pair
from fastmac_exp.samplers import make_sampler


def _placed(pair, d: np.ndarray):
    """The pair moved by d (GT included). Coordinates on a 2^-20 m grid, so adding whole metres is exact:
    the moved pair is the same pair, not a rounded copy of it."""
    gt = pair.gt.copy()
    gt[:3, 3] = pair.gt[:3, 3] + d - pair.gt[:3, :3] @ d
    return dataclasses.replace(pair, src_cloud=pair.src_cloud + d, tgt_cloud=pair.tgt_cloud + d, gt=gt)


@pytest.mark.parametrize("family", ["3dmatch", "kitti"])
def test_a_pair_far_from_the_origin_registers_as_near_it(tmp_path, family):
    pair = SyntheticDataset(family=family, num_pairs=1, seed=0, cache_dir=str(tmp_path)).load(0)
    grid = 2.0**-20
    pair = dataclasses.replace(pair, src_cloud=np.round(pair.src_cloud / grid) * grid,
                               tgt_cloud=np.round(pair.tgt_cloud / grid) * grid)  # fmt: skip
    centre = np.round((pair.src_cloud.mean(0) + pair.tgt_cloud.mean(0)) / 2)
    near = _placed(pair, -centre)  # the pair about the origin: no offset applies

    def register(p):
        return run_pair(p, FPFHDescriptor(), make_sampler("highpass"), make_backend("cpp"), 0.2,
                        np.random.default_rng([0, 0])).row  # fmt: skip

    ref = register(near)
    assert ref["success"], ref
    for d in ([1e5, -5e4, 1e3], [999_900.0, -5e5, 1e4]):  # UTM-like eastings, northings and heights
        far = register(_placed(near, np.array(d)))
        assert far["success"], far
        assert abs(far["re_deg"] - ref["re_deg"]) < 1e-3 and abs(far["te_cm"] - ref["te_cm"]) < 1e-3
        assert far["clique_size"] == ref["clique_size"] and far["n_in"] == ref["n_in"]
        pose = np.array([float(v) for v in far["pose"].split()]).reshape(4, 4)
        np.testing.assert_allclose(to_moved(pose, np.array(d)), np.array(
            [float(v) for v in ref["pose"].split()]).reshape(4, 4), atol=1e-6)  # fmt: skip


def test_the_offset_composes_into_the_pose():
    rng = np.random.default_rng(0)
    pts = rng.uniform(-5, 5, (100, 3)) + [4e5, 5e6 / 10, 30.0]
    offset = common_offset(pts, pts + 1.0)
    assert np.all(offset == np.round(offset)) and np.abs(offset - pts.mean(0)).max() < 2
    assert not common_offset(pts - pts.mean(0)).any()  # near the origin: left alone
    pose = np.eye(4)
    pose[:3, :3] = np.linalg.qr(rng.normal(size=(3, 3)))[0] * [1, 1, 1]
    if np.linalg.det(pose[:3, :3]) < 0:
        pose[:3, 0] *= -1
    pose[:3, 3] = [1.0, -2.0, 0.5]
    moved = to_moved(pose, offset)
    np.testing.assert_allclose((pts - offset) @ moved[:3, :3].T + moved[:3, 3] + offset,
                               pts @ pose[:3, :3].T + pose[:3, 3], atol=1e-6)  # fmt: skip
    np.testing.assert_allclose(to_original(moved, offset), pose, atol=1e-9)


def test_a_cached_far_pair_registers_exactly_as_described(tmp_path):
    """run_pair moves the pair once and describes it in the moved frame; the correspondence cache keeps that
    frame, so a run that reads it registers exactly as the run that described (no round trip through the
    original frame's large coordinates), and the outcome's correspondences are the original frame's."""
    from fastmac_exp.pipeline.cache import CorrespondenceCache

    pair = SyntheticDataset(family="3dmatch", num_pairs=1, seed=0, cache_dir=str(tmp_path)).load(0)
    grid = 2.0**-20
    pair = dataclasses.replace(pair, src_cloud=np.round(pair.src_cloud / grid) * grid,
                               tgt_cloud=np.round(pair.tgt_cloud / grid) * grid)  # fmt: skip
    far = _placed(pair, np.array([2e5, -3e5, 50.0]))
    cache = CorrespondenceCache(tmp_path / "corr")

    def register():
        return run_pair(far, FPFHDescriptor(), make_sampler("highpass"), make_backend("cpp"), 0.2,
                        np.random.default_rng([0, 0]), cache=cache, cache_key="far")  # fmt: skip

    described, cached = register(), register()
    assert not described.row.get("describe_cached") and cached.row["describe_cached"]
    assert described.row["success"] and cached.row["pose"] == described.row["pose"]
    stored, _ = cache.load("far")
    assert np.abs(stored.src.mean(axis=0)).max() < 50.0  # the pair-centred frame
    assert np.abs(described.corr.src.mean(axis=0) - far.src_cloud.mean(axis=0)).max() < 50.0  # the original
    np.testing.assert_array_equal(cached.corr.src, described.corr.src)


def test_the_offset_is_the_rounded_mean_of_the_centroids_wherever_the_points_lie():
    """The min / max shortcut decides only clouds wholly within CENTRE_BEYOND / 2 of the origin; the rest
    take the centroids' mean as before (a cloud reaching past it with its centre near the origin, one centred
    just inside CENTRE_BEYOND, one beyond it, one with a NaN)."""
    from fastmac_exp.geometry.offset import CENTRE_BEYOND

    rng = np.random.default_rng(3)
    unit = rng.uniform(-1, 1, (500, 3))
    wide = unit * [0.9 * CENTRE_BEYOND, 1.0, 1.0]  # points beyond CENTRE_BEYOND / 2, centre near 0
    assert np.abs(wide).max() > CENTRE_BEYOND / 2 and not common_offset(wide, wide).any()
    inside = unit + [0.99 * CENTRE_BEYOND, 0, 0]
    assert not common_offset(inside, inside + 1).any()
    beyond = unit + [1.2 * CENTRE_BEYOND, -3.3 * CENTRE_BEYOND, 7.0]
    mid = np.mean([beyond.mean(0), (beyond + 2).mean(0)], axis=0)
    np.testing.assert_array_equal(common_offset(beyond, beyond + 2), np.round(mid))
    assert np.abs(common_offset(beyond, beyond + 2) - [1201, -3299, 8]).max() <= 1
    nan = unit.copy()
    nan[7, 1] = np.nan
    assert not common_offset(nan, unit).any()  # as before: a NaN centre is not beyond anything
    assert not common_offset(None, np.zeros((0, 3))).any()
