"""BUFFER describing what is matched (`match_keypoints`): the chosen-keypoint path gives what matching
every keypoint gives where it must (no cap, or the chosen rows' descriptors matched directly), the spread
choice on a hand case, the options reachable from the config and bad values refused."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

from fastmac_exp.descriptors.buffer import MATCH_KEYPOINTS, BufferDescriptor, forget_described_clouds
from fastmac_exp.descriptors.keypoints import spread_rows, voxel_down
from fastmac_exp.descriptors.matching import correspondences_from_chosen_keypoints, match_descriptors
from fastmac_exp.errors import InputError
from fastmac_exp.types import Pair

from .test_buffer_descriptor import golden_pair

REPO = Path(__file__).resolve().parents[1]


def make(**kw) -> BufferDescriptor:
    return BufferDescriptor(voxel_size=0.2, threads=1, progress=False, **kw)


# ----------------------------------------------------------------------------------------------------
# the spread choice


def test_spread_rows_hand_case():
    """A 4 x 4 lattice (spacing 1) capped at 4: the finest grid with at most 4 cells is 2 x 2 (size just above
    1.5), and each cell keeps the lattice point nearest its centre: the 4 central points."""
    xy = np.array([(x, y) for x in range(4) for y in range(4)], dtype=float)
    kp = np.c_[xy, np.zeros(16)]
    rows = spread_rows(kp, 4)
    assert sorted(map(tuple, kp[rows, :2].astype(int))) == [(1, 1), (1, 2), (2, 1), (2, 2)]
    np.testing.assert_array_equal(spread_rows(kp, 16), np.arange(16))  # not below the count: every row
    assert len(spread_rows(kp, 1)) == 1


def test_spread_rows_counts_and_determinism():
    rng = np.random.default_rng(4)
    kp = rng.uniform(-5, 5, (6000, 3)) * [1, 1, 0.1]
    for cap in (10, 300, 2500):
        rows = spread_rows(kp, cap)
        assert len(rows) <= cap and len(rows) >= 0.8 * cap, cap
        assert np.all(np.diff(rows) > 0)  # sorted, distinct
        np.testing.assert_array_equal(rows, spread_rows(kp.copy(), cap))
    with pytest.raises(InputError, match="cap must be >= 1"):
        spread_rows(kp, 0)


# ----------------------------------------------------------------------------------------------------
# the chosen-keypoint path


class HandDescriptor:
    """Keypoints given by hand, a one-hot-like feature per keypoint, and a log of the rows described."""

    name = "hand"
    voxel_size = None
    max_correspondences = 0

    def __init__(self, feats: dict, mutual: bool) -> None:
        self.feats, self.mutual, self.described = feats, mutual, []

    def keypoints(self, points, voxel, what):
        return points, points

    def features_of(self, cloud, kp, rows, what):
        side = "src" if "source" in what else "tgt"
        self.described.append((side, list(rows)))
        f = self.feats[side][rows]
        return f / np.linalg.norm(f, axis=1, keepdims=True)


def test_chosen_keypoints_hand_case():
    """Source keypoints 0..3, target 0..3; features e0, e1, e2, e0+e1 (source) and e1, e0, e2+e3, e3
    (target). Choosing source rows {0, 1, 3} and target rows {0, 1, 2}: one-way gives 0->1 (e0), 1->0 (e1),
    3 -> the first of its two equal nearest (0); mutual keeps 0->1 and 1->0 only (target 0's nearest source
    is 1). Only the chosen rows are described."""
    e = np.eye(4)
    feats = {
        "src": np.array([e[0], e[1], e[2], e[0] + e[1]]),
        "tgt": np.array([e[1], e[0], e[2] + e[3], e[3]]),
    }
    src = np.arange(12.0).reshape(4, 3)
    tgt = src + 100
    pair = Pair(name="hand", src_cloud=src, tgt_cloud=tgt, voxel_size=1.0)
    rows = {0: [0, 1, 3], 100: [0, 1, 2]}  # by the cloud: the source starts at 0, the target at 100

    def choose(kp, rng):
        return np.array(rows[int(kp[0, 0])])

    for mutual, expect in ((False, [(0, 1), (1, 0), (3, 0)]), (True, [(0, 1), (1, 0)])):
        d = HandDescriptor(feats, mutual)
        corr = correspondences_from_chosen_keypoints(
            d, pair, np.random.default_rng(0), match_descriptors, choose
        )
        got = [(int(s[0]) // 3, int(t[0] - 100) // 3) for s, t in zip(corr.src, corr.tgt, strict=True)]
        assert got == expect, mutual
        assert d.described == [("src", [0, 1, 3]), ("tgt", [0, 1, 2])]


@pytest.mark.parametrize("mutual", [False, True])
def test_no_cap_is_matching_every_keypoint(mutual):
    """match_keypoints at or above both clouds' counts describes and matches every keypoint: the same
    correspondences as the path that matches everything (max_correspondences 0: no draw either way)."""
    pair = golden_pair("3dmatch")
    every = make(mutual=mutual, max_correspondences=0)(pair, np.random.default_rng(0))
    forget_described_clouds()
    chosen = make(mutual=mutual, max_correspondences=0, match_keypoints=10**6)
    corr = chosen(pair, np.random.default_rng(0))
    n = [len(voxel_down(c, 0.2)) for c in (pair.src_cloud, pair.tgt_cloud)]
    assert [t["keypoints"] for t in chosen.timings_log] == n
    for a, b in ((every.src, corr.src), (every.tgt, corr.tgt), (every.scores, corr.scores)):
        np.testing.assert_array_equal(a, b)


@pytest.mark.parametrize("choice", ["spread", "random"])
def test_capped_path_matches_the_chosen_rows_of_every_keypoint(choice):
    """Capped at 40 keypoints a cloud: only the chosen rows are described, and the correspondences are the
    mutual matches of those rows' descriptors taken from describing every keypoint (a row's descriptor does
    not depend on which others are described)."""
    pair = golden_pair("3dmatch")
    d = make(mutual=True, max_correspondences=0, match_keypoints=40, keypoint_choice=choice)
    corr = d(pair, np.random.default_rng(3))
    full = make(cache_clouds=0)
    scale = full.scale_for(full.model_for("3dmatch"), pair.voxel_size)  # the pair's: keypoints at 0.2 only
    skp, sf = full.features(pair.src_cloud, 0.2, family="3dmatch", scale=scale)
    tkp, tf = full.features(pair.tgt_cloud, 0.2, family="3dmatch", scale=scale)
    if choice == "spread":
        a, b = spread_rows(skp, 40), spread_rows(tkp, 40)
    else:  # the run's rng, source first
        rng = np.random.default_rng(3)
        a = np.sort(rng.choice(len(skp), 40, replace=False))
        b = np.sort(rng.choice(len(tkp), 40, replace=False))
    assert [t["keypoints"] for t in d.timings_log] == [len(a), len(b)] and len(skp) > 40 < len(tkp)
    r, t, dist = match_descriptors(sf[a], tf[b], True)
    np.testing.assert_array_equal(corr.src, skp[a[r]])
    np.testing.assert_array_equal(corr.tgt, tkp[b[t]])
    np.testing.assert_allclose(corr.scores, 1 - dist, atol=1e-6)
    assert len(corr) > 0 and corr.labels is not None


def test_random_choice_follows_the_run_seed_and_spread_does_not():
    pair = golden_pair("3dmatch")
    src = {}
    for choice in ("random", "spread"):
        d = make(mutual=True, match_keypoints=30, keypoint_choice=choice)
        src[choice] = [d(pair, np.random.default_rng(s)).src for s in (0, 0, 1)]
        np.testing.assert_array_equal(src[choice][0], src[choice][1])
    assert not np.array_equal(src["random"][0], src["random"][2])
    np.testing.assert_array_equal(src["spread"][0], src["spread"][2])


# ----------------------------------------------------------------------------------------------------
# options


def test_match_keypoints_by_model():
    d = make(match_keypoints="auto")
    assert d.match_keypoints_for("3dmatch") == MATCH_KEYPOINTS["3dmatch"] == (1000, "spread")
    assert d.match_keypoints_for("3dlomatch") == MATCH_KEYPOINTS["3dmatch"]
    assert d.match_keypoints_for("kitti") == MATCH_KEYPOINTS["kitti"] == (5000, "random")
    assert make(match_keypoints="auto", model="kitti").match_keypoints_for("3dmatch") == (5000, "random")
    assert make(match_keypoints=700, keypoint_choice="spread").match_keypoints_for("kitti") == (700, "spread")
    assert make().match_keypoints_for("kitti")[0] == 0  # the class default: every target keypoint


def test_config_reaches_the_options():
    from hydra import compose, initialize_config_dir
    from hydra.utils import instantiate

    with initialize_config_dir(config_dir=str(REPO / "conf"), version_base="1.3"):
        cfg = compose(config_name="config", overrides=["descriptor=buffer"])
        set_ = compose(
            config_name="config",
            overrides=[
                "descriptor=buffer",
                "descriptor.match_keypoints=1200",
                "descriptor.keypoint_choice=random",
            ],
        )
    default = instantiate(cfg.descriptor)
    assert (default.match_keypoints, default.keypoint_choice, default.mutual) == ("auto", "auto", True)
    d = instantiate(set_.descriptor)
    assert d.match_keypoints_for("3dmatch") == (1200, "random")


@pytest.mark.parametrize("value", [-1, 1.5, "many", True, None])
def test_bad_match_keypoints_refused(value):
    with pytest.raises(InputError, match=r"match_keypoints must be 'auto', 0 .* got"):
        make(match_keypoints=value)


def test_bad_keypoint_choice_refused():
    with pytest.raises(InputError, match="keypoint_choice must be one of .*'fps'"):
        make(keypoint_choice="fps")
