"""The trust test's rival and decoy (issue 48 item 1): hand cases for each piece, the two backends'
hypotheses, and the ambiguity the previous test could not see."""

from __future__ import annotations

import numpy as np
import pytest

from fastmac_exp.backends.cpp import CppBackend
from fastmac_exp.backends.python_mac import PythonBackend
from fastmac_exp.geometry.transforms import random_rotation
from fastmac_exp.geometry.trust import (
    RIVAL_MARGIN,
    STRUCTURE_RATE,
    ChanceCounter,
    decide,
    distinct,
    explained,
    rival_support,
)
from fastmac_exp.params import mac_params_for
from fastmac_exp.pipeline import register_correspondences
from fastmac_exp.samplers import NoSampler
from fastmac_exp.types import Correspondences


def _rot_z(deg: float) -> np.ndarray:
    c, s = np.cos(np.radians(deg)), np.sin(np.radians(deg))
    t = np.eye(4)
    t[:2, :2] = [[c, -s], [s, c]]
    return t


def test_distinct_is_rotation_beyond_the_angle_or_a_shift_of_the_centre_beyond_the_distance():
    centre = np.array([1.0, 2.0, 0.5])
    shifted = np.eye(4)
    shifted[:3, 3] = [0.2, 0, 0]
    poses = np.stack([_rot_z(10), _rot_z(20), shifted, np.eye(4)])
    # 10 deg about z moves the centre by 2 sin(5 deg) |(1, 2)| = 0.39 m: within 0.5 m
    assert distinct(poses, np.eye(4), centre, 15.0, 0.5).tolist() == [False, True, False, False]
    assert distinct(poses, np.eye(4), centre, 15.0, 0.1).tolist() == [True, True, True, False]


def test_decide_is_the_poisson_tail_of_chance_plus_the_largest_wrong_pose_part():
    from scipy.stats import poisson

    # nothing measured: the pose's own clique for the search's pick, or structure at any pose
    conf, mean = decide(40, 5, 2.0, 1000)
    assert mean == pytest.approx(2.0 + max(5, STRUCTURE_RATE * 1000))
    assert conf == pytest.approx(1 - poisson.sf(39, mean))
    assert decide(40, 30, 2.0, 1000)[1] == pytest.approx(2.0 + 30)
    # the decoy's count replaces the clique; the rival's excess, times the margin, is the third part
    conf, mean = decide(60, 30, 1.0, 400, rival_excess=20.0, decoy_count=4.0, margin=1.5, rate=0.01)
    assert mean == pytest.approx(1.0 + 30.0)
    assert conf == pytest.approx(1 - poisson.sf(59, mean))
    _, mean = decide(40, 30, 1.0, 100, rival_excess=-3.0, decoy_count=2.0, rate=0.01)
    assert mean == pytest.approx(1.0 + 3.0)  # a rival below chance allows nothing; a pose needs 3
    _, mean = decide(40, 30, 1.0, 100, rival_excess=float("nan"), decoy_count=float("nan"), rate=0.01)
    assert mean == pytest.approx(1.0 + 30)  # NaN: not measured
    assert decide(0, 3, 0.0, 10)[0] == 0.0


def _two_poses(n_a: int, n_b: int, noise: int, seed: int = 0):
    """Correspondences of which n_a agree on pose A, n_b on a distinct pose B, the rest random."""
    rng = np.random.default_rng(seed)
    a, b = np.eye(4), np.eye(4)
    a[:3, :3], a[:3, 3] = random_rotation(rng), [0.5, 0.1, 0.0]
    b[:3, :3], b[:3, 3] = random_rotation(rng), [-0.4, 0.3, 0.2]
    src = rng.uniform(0, 3, (n_a + n_b + noise, 3))
    tgt = rng.uniform(0, 3, (n_a + n_b + noise, 3))
    tgt[:n_a] = src[:n_a] @ a[:3, :3].T + a[:3, 3]
    tgt[n_a : n_a + n_b] = src[n_a : n_a + n_b] @ b[:3, :3].T + b[:3, 3]
    return src, tgt, a, b


def test_rival_support_counts_what_the_rival_explains_beyond_the_chosen_pose():
    src, tgt, a, b = _two_poses(60, 25, 400)
    chance = ChanceCounter(src, tgt, 0.1)
    near_a = a.copy()
    near_a[:3, 3] += [
        0.0,
        0.0,
        0.35,
    ]  # beyond 0.3 m from A: distinct, but it explains A's matches, not others
    poses = np.stack([a, near_a, b])
    k, lam = rival_support(poses, np.array([60.0, 50.0, 25.0]), a, src, tgt, 0.1, 15.0, 0.3, chance)
    assert k == explained(src[60:], tgt[60:], b, 0.1) and 25 <= k <= 27  # B's own, perhaps a chance one
    mine = np.linalg.norm(src @ a[:3, :3].T + a[:3, 3] - tgt, axis=1) < 0.1
    assert lam == pytest.approx(chance(b, sources=src[~mine]))  # chance among the matches A leaves
    assert chance(b, sources=src) == pytest.approx(chance(b))  # all sources: lambda itself
    # no distinct hypothesis: no rival (0); no hypotheses kept: not measured (NaN)
    assert rival_support(np.stack([a]), np.array([60.0]), a, src, tgt, 0.1, 15.0, 0.3, chance) == (0.0, 0.0)
    assert np.isnan(rival_support(None, None, a, src, tgt, 0.1, 15.0, 0.3, chance)[0])


@pytest.mark.parametrize("backend", [CppBackend, PythonBackend])
def test_an_ambiguous_pose_is_not_trusted_and_a_clear_one_is(backend):
    """Two distinct poses with comparable support: whichever MAC picks, its rival explains nearly as much,
    and the pose is not trusted; the previous test (1 % of N) trusted it. With the second pose's support
    small, the same first pose is trusted. (MAC's graph reduction would prune the weaker group's edges
    here, leaving no rival to see: it is off, as it is on the sparse graphs of real matches.)"""
    params = mac_params_for("3dmatch", "fpfh", mac_overrides={"reduction": False})
    src, tgt, _, _ = _two_poses(70, 60, 1000)
    res, _ = register_correspondences(Correspondences(src, tgt), params, NoSampler(), backend())
    assert res.inliers >= 60 and res.rival_inliers >= 55
    assert not res.trusted
    src, tgt, _, _ = _two_poses(70, 8, 1000)
    res, _ = register_correspondences(Correspondences(src, tgt), params, NoSampler(), backend())
    assert res.inliers >= 70 and res.trusted
    # its clique holds every inlier: with the clique standing in for the search's pick (decoy off) the
    # pose explains nothing beyond it; the decoy measures what the search finds by chance instead
    assert len(res.clique) >= 60 and np.isfinite(res.decoy_count) and res.decoy_count < 15
    off, _ = register_correspondences(Correspondences(src, tgt), params, NoSampler(), backend(), decoy="off")
    assert not off.trusted


def test_both_backends_keep_the_same_hypotheses():
    src, tgt, _, _ = _two_poses(50, 30, 300, seed=3)
    corr = Correspondences(src, tgt)
    params = mac_params_for("3dmatch", "fpfh", mac_overrides={"reduction": False})
    c, p = CppBackend().register(corr, params), PythonBackend().register(corr, params)
    assert c.hypothesis_poses.shape == p.hypothesis_poses.shape and len(c.hypothesis_poses) == c.n_selected
    np.testing.assert_allclose(c.hypothesis_poses, p.hypothesis_poses, atol=1e-8)
    np.testing.assert_allclose(c.hypothesis_scores, p.hypothesis_scores, rtol=1e-9, atol=1e-9)
    assert c.hypothesis_scores.max() == pytest.approx(c.score)


def test_the_decoy_runs_where_asked_and_measures_a_small_excess_on_random_matches():
    params = mac_params_for("3dmatch", "fpfh")
    src, tgt, _, _ = _two_poses(80, 0, 800)
    corr = Correspondences(src, tgt)
    res, _ = register_correspondences(corr, params, NoSampler(), CppBackend(), decoy="on")
    assert np.isfinite(res.decoy_count) and res.decoy_count < 20 and res.trusted
    assert "decoy" in res.timings
    off, _ = register_correspondences(corr, params, NoSampler(), CppBackend(), decoy="off")
    assert np.isnan(off.decoy_count) and "decoy" not in off.timings
    np.testing.assert_array_equal(off.pose, res.pose)  # the decoy draws from its own stream
    with pytest.raises(Exception, match="decoy must be one of"):
        register_correspondences(corr, params, NoSampler(), CppBackend(), decoy="maybe")


def test_rival_margin_is_the_documented_one():
    from pathlib import Path

    text = (Path(__file__).resolve().parents[1] / "docs" / "trust.md").read_text()
    assert f"RIVAL_MARGIN = {RIVAL_MARGIN:g}" in text


def test_chance_counter_counts_what_a_brute_force_counts(monkeypatch):
    """lambda from the core's grid (count_within) equals the mean of a brute-force count, and the k-d tree
    fallback (no core) gives the same."""
    from fastmac_exp import core
    from fastmac_exp.geometry import trust

    rng = np.random.default_rng(5)
    src, tgt = rng.uniform(0, 2, (700, 3)), rng.uniform(0, 2, (700, 3))
    pose = _rot_z(20.0)
    pose[:3, 3] = [0.1, -0.2, 0.05]
    moved = src @ pose[:3, :3].T + pose[:3, 3]
    brute = ((moved[:, None, :] - tgt[None]) ** 2).sum(-1) <= 0.15**2
    assert ChanceCounter(src, tgt, 0.15)(pose) == pytest.approx(brute.sum(1).mean(), rel=1e-12)
    assert ChanceCounter(src, tgt, 0.15)(pose, sources=src[:100]) == pytest.approx(
        brute[:100].sum(1).mean() * 100 / 700, rel=1e-12
    )
    monkeypatch.setattr(core, "available", lambda: False)
    fallback = trust.ChanceCounter(src, tgt, 0.15)
    assert fallback.tree is not None and fallback(pose) == pytest.approx(brute.sum(1).mean(), rel=1e-12)


def test_explained_counts_equal_numpy_per_pose_and_the_fallback_gives_the_same(monkeypatch):
    """The core's one call for all poses counts what one numpy pass a pose counts (a NaN pose counts 0, an
    empty set 0 for every pose); without the core, the numpy passes run."""
    from fastmac_exp import core
    from fastmac_exp.geometry import trust

    rng = np.random.default_rng(8)
    src = rng.uniform(-1, 1, (9000, 3))  # more than one chunk of rows (8,192)
    truth = _rot_z(30.0)
    truth[:3, 3] = [0.2, 0.1, -0.3]
    tgt = src @ truth[:3, :3].T + truth[:3, 3] + rng.normal(0, 0.05, src.shape)
    poses = np.stack([truth, np.eye(4), _rot_z(27.0), np.full((4, 4), np.nan)])
    poses[2, :3, 3] = truth[:3, 3]
    per_pose = [int((np.linalg.norm(src @ p[:3, :3].T + p[:3, 3] - tgt, axis=1) < 0.08).sum()) for p in poses]
    assert per_pose[0] > 4000 > per_pose[2] > per_pose[1] and per_pose[3] == 0  # the cases differ
    assert trust.explained_counts(src, tgt, poses, 0.08).tolist() == per_pose
    assert [explained(src, tgt, p, 0.08) for p in poses] == per_pose
    assert trust.explained_counts(src[:0], tgt[:0], poses, 0.08).tolist() == [0, 0, 0, 0]
    monkeypatch.setattr(core, "available", lambda: False)
    assert trust.explained_counts(src, tgt, poses, 0.08).tolist() == per_pose


def test_chance_counts_points_exactly_at_the_radius_far_from_the_origin():
    """count_within's cells are a hair wider than the radius: a lattice of the radius's spacing, a million
    radii from the origin, still counts each point's six neighbours at exactly the radius (<=), as a k-d
    tree does."""
    from scipy.spatial import cKDTree

    from fastmac_exp import core

    if not core.available():
        pytest.skip("the C++ core is not built")
    r = 0.125  # a power of two: the lattice's distances are exact
    lattice = np.stack(np.meshgrid(*[np.arange(5.0)] * 3), -1).reshape(-1, 3) * r + 1e6 * r
    ref = cKDTree(lattice).query_ball_point(lattice, r, return_length=True)
    assert ref.max() == 7  # itself and six at exactly r
    np.testing.assert_array_equal(core.core().count_within(lattice, lattice, r), ref)
