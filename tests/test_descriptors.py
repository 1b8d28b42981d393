"""FPFH and oracle front ends: labels consistent with GT, exact oracle counts, clear errors."""

from __future__ import annotations

import numpy as np
import pytest

from fastmac_exp.datasets import scenes as sc
from fastmac_exp.datasets.synthetic import SyntheticDataset
from fastmac_exp.descriptors.fpfh import FPFHDescriptor, fpfh_features
from fastmac_exp.descriptors.oracle import OracleDescriptor
from fastmac_exp.errors import InputError
from fastmac_exp.types import Pair


def gt_error(pair: Pair, corr) -> np.ndarray:
    return np.linalg.norm(sc.transform(corr.src, pair.gt) - corr.tgt, axis=1)


@pytest.fixture(scope="module")
def pair() -> Pair:
    return SyntheticDataset("3dmatch", num_pairs=1, cache_dir=None, points_per_scan=6000).load(0)


def test_fpfh_features_shape_and_norm(pair):
    kp, f = fpfh_features(pair.src_cloud, 0.05)
    assert kp.ndim == 2 and kp.shape[1] == 3 and f.shape == (len(kp), 33)
    norms = np.linalg.norm(f, axis=1)
    assert np.allclose(norms[norms > 0], 1.0)


def test_fpfh_labels_match_gt(pair):
    corr = FPFHDescriptor()(pair, np.random.default_rng(0))
    assert corr.labels is not None and len(corr) > 100
    assert np.array_equal(corr.labels, gt_error(pair, corr) < pair.inlier_threshold)
    assert corr.labels.sum() > 0
    assert corr.src.dtype == np.float64 and corr.scores is not None


def _moved_copy(pair: Pair, pose: np.ndarray) -> Pair:
    return Pair(
        name="copy",
        gt=sc.inv_pose(pose),
        src_cloud=sc.transform(pair.tgt_cloud, pose),
        tgt_cloud=pair.tgt_cloud,
        voxel_size=0.05,
    )


def test_fpfh_on_a_shifted_copy_is_mostly_inliers(pair):
    """The same cloud shifted by whole voxels: the same keypoints and features, so nearly all right."""
    pose = sc.make_pose(np.eye(3), np.array([0.5, -1.0, 2.0]))
    corr = FPFHDescriptor(max_correspondences=0)(_moved_copy(pair, pose), np.random.default_rng(0))
    assert corr.inlier_ratio > 0.8
    assert np.array_equal(corr.labels, gt_error(_moved_copy(pair, pose), corr) < 0.1)


def test_fpfh_origin_normals_make_rotation_invariant(pair):
    """Open3D orients normals towards +z, which a rotation breaks; orienting them towards the sensor
    at the origin does not care about a rotation about it."""
    pose = sc.make_pose(sc.rot_axis_angle(np.array([1.0, 0.5, 0.2]), np.radians(150)), np.zeros(3))
    copy = _moved_copy(pair, pose)
    rng = np.random.default_rng(0)
    plus_z = FPFHDescriptor(max_correspondences=0, orient_normals="open3d")(copy, rng).inlier_ratio
    origin = FPFHDescriptor(max_correspondences=0)(copy, rng).inlier_ratio  # the default
    assert origin > plus_z and origin > 0.2
    with pytest.raises(InputError, match="orient_normals"):
        FPFHDescriptor(orient_normals="sideways")


def test_fpfh_cap_mutual_and_determinism(pair):
    full = FPFHDescriptor(max_correspondences=0)(pair, np.random.default_rng(0))
    capped = FPFHDescriptor(max_correspondences=200)(pair, np.random.default_rng(1))
    again = FPFHDescriptor(max_correspondences=200)(pair, np.random.default_rng(1))
    assert len(capped) == 200
    assert np.array_equal(capped.src, again.src) and np.array_equal(capped.tgt, again.tgt)
    mutual = FPFHDescriptor(max_correspondences=0, mutual=True)(pair, np.random.default_rng(0))
    assert 0 < len(mutual) < len(full)
    rows = {tuple(r) for r in np.hstack([full.src, full.tgt]).round(9)}
    assert all(tuple(r) in rows for r in np.hstack([mutual.src, mutual.tgt]).round(9))


def test_fpfh_voxel_override(pair):
    coarse = FPFHDescriptor(voxel_size=0.1, max_correspondences=0)(pair, np.random.default_rng(0))
    fine = FPFHDescriptor(max_correspondences=0)(pair, np.random.default_rng(0))
    assert len(coarse) < len(fine)


def test_fpfh_errors(pair):
    rng = np.random.default_rng(0)
    with pytest.raises(InputError, match="needs both point clouds"):
        FPFHDescriptor()(Pair(name="empty", gt=np.eye(4)), rng)
    few = Pair(name="few", src_cloud=np.random.default_rng(0).random((5, 3)), tgt_cloud=pair.tgt_cloud)
    with pytest.raises(InputError, match="after voxel downsampling"):
        FPFHDescriptor()(few, rng)
    with pytest.raises(InputError, match="voxel_size"):
        FPFHDescriptor(voxel_size=-1.0)
    with pytest.raises(InputError, match="max_correspondences"):
        FPFHDescriptor(max_correspondences=-3)


@pytest.mark.parametrize("ratio", [0.0, 0.1, 0.37, 1.0])
def test_oracle_exact_count_and_ratio(pair, ratio):
    n = 1000
    corr = OracleDescriptor(num_correspondences=n, inlier_ratio=ratio)(pair, np.random.default_rng(0))
    assert len(corr) == n
    assert int(corr.labels.sum()) == round(n * ratio)
    err = gt_error(pair, corr)
    assert np.array_equal(corr.labels, err < pair.inlier_threshold)
    thr = pair.inlier_threshold
    assert (err[corr.labels] < thr).all() and (err[~corr.labels] >= thr).all()


def test_oracle_noise_and_determinism(pair):
    exact = OracleDescriptor(200, 0.5, noise=0.0)(pair, np.random.default_rng(0))
    assert np.allclose(gt_error(pair, exact)[exact.labels], 0.0, atol=1e-9)
    loud = OracleDescriptor(500, 0.5, noise=1.0)(pair, np.random.default_rng(0))  # truncated below thr
    assert int(loud.labels.sum()) == 250
    a = OracleDescriptor(300, 0.2)(pair, np.random.default_rng(7))
    b = OracleDescriptor(300, 0.2)(pair, np.random.default_rng(7))
    assert np.array_equal(a.src, b.src) and np.array_equal(a.tgt, b.tgt)
    kp = OracleDescriptor(300, 0.2, keypoint_voxel=0.05)(pair, np.random.default_rng(7))
    assert int(kp.labels.sum()) == 60


def test_oracle_errors(pair):
    rng = np.random.default_rng(0)
    with pytest.raises(InputError, match="inlier_ratio"):
        OracleDescriptor(inlier_ratio=1.5)
    with pytest.raises(InputError, match="num_correspondences"):
        OracleDescriptor(num_correspondences=0)
    with pytest.raises(InputError, match="noise"):
        OracleDescriptor(noise=-0.1)
    no_gt = Pair(name="nogt", src_cloud=pair.src_cloud, tgt_cloud=pair.tgt_cloud)
    with pytest.raises(InputError, match="ground truth"):
        OracleDescriptor()(no_gt, rng)
    with pytest.raises(InputError, match="point clouds"):
        OracleDescriptor()(Pair(name="noclouds", gt=np.eye(4)), rng)
