"""A pose says when not to trust it (issue 42 item 2): the console, the rows and the real pairs."""

from __future__ import annotations

import dataclasses

import numpy as np
import pandas as pd
import pytest

from tests.test_cli import _blob_pair, run


def test_the_cli_warns_of_an_untrusted_pose_counts_it_and_the_row_carries_it(tmp_path):
    rng = np.random.default_rng(0)
    np.save(tmp_path / "a.npy", rng.uniform(0, 3, (20000, 3)))
    np.save(tmp_path / "b.npy", rng.uniform(0, 3, (20000, 3)))
    p = run("dataset=pairs", f"dataset.source={tmp_path / 'a.npy'}", f"dataset.target={tmp_path / 'b.npy'}",
            tmp=tmp_path)  # fmt: skip
    assert p.returncode == 0, p.stderr[-2000:]
    assert "UNTRUSTED POSE for a+b: it explains " in p.stdout + p.stderr
    assert "UNTRUSTED poses: 1" in p.stdout
    warning = "WARNING: 1 UNTRUSTED pose(s), not clearly more correspondences than a wrong pose would explain"
    assert warning in p.stdout
    assert "a+b: no ground truth: not scored; UNTRUSTED POSE (confidence 0." in p.stdout
    row = pd.read_csv(tmp_path / "run" / "results.csv").iloc[0]
    assert not bool(row["trusted"]) and 0.0 <= row["confidence"] < 0.99


def test_the_cli_trusts_a_right_pose_without_a_word(tmp_path):
    src, tgt, _ = _blob_pair(tmp_path)
    p = run("dataset=pairs", f"dataset.source={src}", f"dataset.target={tgt}", tmp=tmp_path)
    assert p.returncode == 0, p.stderr[-2000:]
    assert "UNTRUSTED" not in p.stdout + p.stderr
    row = pd.read_csv(tmp_path / "run" / "results.csv").iloc[0]
    assert bool(row["trusted"]) and row["confidence"] > 0.999


@pytest.fixture(scope="module")
def real_pairs():
    from fastmac_exp.datasets.user_pairs import SharedRealPairs, resolve_shared_root

    if not (resolve_shared_root("../shared/data") / "pairs.json").is_file():
        pytest.skip("../shared/data (the real pairs) is not here")
    ds = SharedRealPairs(ids=["kitti00_95_to_94", "apollo_sunnyvale_36822_to_38908", "3dm_homeat_38_to_2",
                              "3dm_redkitchen_6_to_0_geotransformer"])  # fmt: skip
    return [ds.load(i) for i in range(len(ds))]


def _trust(pair):
    from fastmac_exp.backends.cpp import CppBackend
    from fastmac_exp.descriptors.fpfh import FPFHDescriptor
    from fastmac_exp.pipeline import run_pair
    from fastmac_exp.samplers import GraphFilterSampler

    out = run_pair(pair, FPFHDescriptor(), GraphFilterSampler(), CppBackend(), 0.2, np.random.default_rng(0))
    return out.row


def test_real_pairs_registered_are_trusted_and_unrelated_ones_are_not(real_pairs):
    """docs/trust.md's calibration in small: KITTI 95->94 and home_at 38->2 register and are trusted; the
    Apollo pair (FPFH fails it: a wrong pose) and two swaps of sources between places are not."""
    kitchen, kitti, apollo, homeat = real_pairs  # pairs.json order
    for pair in (kitti, homeat):
        row = _trust(pair)
        assert row["success"] and row["trusted"], row
    row = _trust(apollo)
    assert not row["success"] and not row["trusted"], row
    for src, tgt in ((apollo, kitti), (kitchen, homeat)):
        swapped = dataclasses.replace(tgt, src_cloud=src.src_cloud, gt=None, name="swapped")
        assert not _trust(swapped)["trusted"]
