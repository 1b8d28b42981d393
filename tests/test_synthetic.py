"""The synthetic dataset: seeded, rigid GT, real overlap, cache reuse and repair, clear errors."""

from __future__ import annotations

import logging

import numpy as np
import pytest
from scipy.spatial import cKDTree

from fastmac_exp.datasets import scenes as sc
from fastmac_exp.datasets.synthetic import SyntheticDataset, load_cached
from fastmac_exp.errors import InputError
from fastmac_exp.families import FAMILIES
from fastmac_exp.geometry.resolution import pair_resolution

TINY_INDOOR = {"points_per_scan": 6000}
TINY_OUTDOOR = {"points_per_scan": 12800}


def tiny(family: str = "3dmatch", **kw) -> SyntheticDataset:
    base = dict(TINY_OUTDOOR if family == "kitti" else TINY_INDOOR)
    base.update(kw)
    base.setdefault("cache_dir", None)
    base.setdefault("num_pairs", 2)
    return SyntheticDataset(family=family, **base)


def near_fraction(src: np.ndarray, tgt: np.ndarray, pose: np.ndarray, radius: float) -> float:
    d, _ = cKDTree(tgt).query(sc.transform(src, pose), k=1, distance_upper_bound=radius)
    return float(np.mean(np.isfinite(d)))


@pytest.fixture(scope="module")
def indoor_pair():
    return tiny("3dmatch").load(0)


@pytest.fixture(scope="module")
def outdoor_pair():
    return tiny("kitti", motion_range=[3.0, 4.0]).load(0)


def test_seeded_byte_identical():
    a, b = tiny("3dmatch").load(1), tiny("3dmatch").load(1)
    assert a.src_cloud.tobytes() == b.src_cloud.tobytes()
    assert a.tgt_cloud.tobytes() == b.tgt_cloud.tobytes()
    assert a.gt.tobytes() == b.gt.tobytes()
    c = tiny("3dmatch", seed=1).load(1)
    assert c.src_cloud.shape != a.src_cloud.shape or not np.array_equal(c.src_cloud, a.src_cloud)


def test_pair_index_independent_of_dataset_size_and_mixed():
    one = tiny("kitti", num_pairs=1).load(0)
    mixed = tiny("mixed", num_pairs=4, points_per_scan=None)
    assert mixed.names() == ["3dmatch_000", "kitti_000", "3dmatch_001", "kitti_001"]
    # mixed shares the single-family generation (with the same parameters)
    m1 = SyntheticDataset("mixed", num_pairs=2, cache_dir=None, points_per_scan=12800).load(1)
    assert m1.family == "kitti" and np.array_equal(m1.src_cloud, one.src_cloud)


@pytest.mark.parametrize("which", ["indoor_pair", "outdoor_pair"])
def test_gt_is_rigid_and_fields(which, request):
    pair = request.getfixturevalue(which)
    gt = pair.gt
    assert gt.shape == (4, 4) and gt.dtype == np.float64
    r = gt[:3, :3]
    assert np.allclose(r.T @ r, np.eye(3), atol=1e-9)
    assert np.isclose(np.linalg.det(r), 1.0, atol=1e-9)
    assert np.array_equal(gt[3], [0, 0, 0, 1])
    assert not np.allclose(gt, np.eye(4), atol=1e-3)  # a non-trivial pose
    for cloud in (pair.src_cloud, pair.tgt_cloud):
        assert cloud.dtype == np.float64 and cloud.ndim == 2 and cloud.shape[1] == 3 and len(cloud) > 1000
        assert np.isfinite(cloud).all()
    fam = "3dmatch" if which == "indoor_pair" else "kitti"
    assert pair.family == fam
    assert pair.inlier_threshold == FAMILIES[fam].inlier_threshold
    assert (pair.re_thresh_deg, pair.te_thresh_m) == (FAMILIES[fam].re_thresh_deg, FAMILIES[fam].te_thresh_m)
    assert pair.voxel_size == (0.05 if fam == "3dmatch" else 0.3)
    if fam == "3dmatch":  # computed from the clouds as MAC does (the default scans: ~0.0097 m)
        assert pair.resolution == pytest.approx(pair_resolution(pair.src_cloud, pair.tgt_cloud))
        assert pair.resolution > 0.006
    else:  # KITTI: the kernel does not use it
        assert pair.resolution == 0.006
    assert pair.scene and {"overlap", "seed", "rotation_deg"} <= set(pair.meta)


@pytest.mark.parametrize("which", ["indoor_pair", "outdoor_pair"])
def test_source_overlaps_target_under_gt_not_identity(which, request):
    pair = request.getfixturevalue(which)
    radius = 2 * pair.voxel_size
    under_gt = near_fraction(pair.src_cloud, pair.tgt_cloud, pair.gt, radius)
    under_id = near_fraction(pair.src_cloud, pair.tgt_cloud, np.eye(4), radius)
    if which == "indoor_pair":  # 15-40 % overlap by the generator's own (stricter) measure
        assert under_gt >= pair.meta["overlap"] > 0.15
        assert under_gt > under_id + 0.15
    else:
        assert under_gt > 0.4 and under_gt > under_id + 0.15


def test_indoor_overlap_in_requested_range():
    ds = tiny("3dmatch", overlap_range=[0.3, 1.0])
    assert ds.load(0).meta["overlap"] >= 0.3


def test_extra_rotation_is_folded_into_gt():
    a = tiny("3dmatch", extra_rotation_deg=0.0).load(0)
    b = tiny("3dmatch", extra_rotation_deg=180.0).load(0)
    # the same scene, the source moved rigidly: GT maps both sources onto the same target points
    assert np.array_equal(a.tgt_cloud, b.tgt_cloud)
    assert np.allclose(sc.transform(a.src_cloud, a.gt), sc.transform(b.src_cloud, b.gt), atol=1e-9)


def test_cache_reused(tmp_path):
    ds = tiny("3dmatch", cache_dir=str(tmp_path), num_pairs=1)
    first = ds.load(0)
    path = ds.cache_path(0)
    assert first.meta["cache"] == "built" and path.exists()
    mtime = path.stat().st_mtime_ns
    second = tiny("3dmatch", cache_dir=str(tmp_path), num_pairs=1).load(0)
    assert second.meta["cache"] == "hit" and path.stat().st_mtime_ns == mtime
    assert np.array_equal(first.src_cloud, second.src_cloud) and np.array_equal(first.gt, second.gt)
    # another generation parameter -> another cache file
    other = tiny("3dmatch", cache_dir=str(tmp_path), num_pairs=1, noise_scale=0.5)
    assert other.cache_path(0) != path


@pytest.mark.parametrize("damage", ["truncate", "garbage", "checksum"])
def test_corrupt_cache_rebuilt(tmp_path, caplog, damage):
    ds = tiny("kitti", cache_dir=str(tmp_path), num_pairs=1)
    ref = ds.load(0)
    path = ds.cache_path(0)
    if damage == "truncate":
        data = path.read_bytes()
        path.write_bytes(data[: len(data) // 2])
    elif damage == "garbage":
        path.write_bytes(b"not an npz file at all")
    else:  # valid npz, wrong content
        with np.load(path, allow_pickle=False) as z:
            arrays = {k: z[k] for k in z.files}
        arrays["src"] = arrays["src"] + 1.0
        np.savez(path, **arrays)
    assert load_cached(path) is None
    with caplog.at_level(logging.WARNING):
        again = ds.load(0)
    assert "corrupt" in caplog.text and "rebuilding" in caplog.text
    assert again.meta["cache"] == "built"
    assert np.array_equal(again.src_cloud, ref.src_cloud) and np.array_equal(again.gt, ref.gt)
    assert load_cached(path) is not None  # repaired on disk


def test_names_len_and_index_errors():
    ds = tiny("kitti", num_pairs=3)
    assert len(ds) == 3 and ds.names() == ["kitti_000", "kitti_001", "kitti_002"]
    with pytest.raises(IndexError):
        ds.load(3)


@pytest.mark.parametrize(
    "kwargs, match",
    [
        ({"family": "moon"}, "family"),
        ({"num_pairs": -1}, "num_pairs"),
        ({"overlap_range": [0.6, 0.2]}, "overlap_range"),
        ({"points_per_scan": 10}, "points_per_scan"),
        ({"voxel_size": 0.0}, "voxel_size"),
        ({"noise_scale": -1.0}, "noise_scale"),
    ],
)
def test_bad_arguments(kwargs, match):
    with pytest.raises(InputError, match=match):
        SyntheticDataset(**{"cache_dir": None, **kwargs})


def test_voxel_downsample_deterministic_centroids():
    pts = np.array([[0.001, 0.001, 0.001], [0.009, 0.009, 0.009], [0.015, 0.0, 0.0]])
    out = sc.voxel_downsample(pts, 0.01)
    assert out.shape == (2, 3)
    assert np.allclose(out[0], [0.005, 0.005, 0.005]) and np.allclose(out[1], [0.015, 0, 0])


@pytest.mark.slow
@pytest.mark.parametrize("family", ["3dmatch", "kitti", "3dlomatch"])
def test_default_pairs_are_dense_scans(family):
    """(How long they take to generate is benchmarks/bench_synthetic.py's, not a test's.)"""
    ds = SyntheticDataset(family=family, num_pairs=2, cache_dir=None)
    for i in range(2):
        pair = ds.load(i)
        assert len(pair.src_cloud) > 20000 and len(pair.tgt_cloud) > 20000
