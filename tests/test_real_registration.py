"""MAC (no sampling) and FastMAC with FPFH recover the GT on the real 3DMatch and KITTI pairs of
../shared/data, through the same pipeline a run uses. Skipped cleanly when the data is absent."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

from fastmac_exp.backends import make_backend
from fastmac_exp.descriptors.fpfh import FPFHDescriptor
from fastmac_exp.pipeline import run_pair
from fastmac_exp.samplers import make_sampler

SHARED = Path(__file__).resolve().parents[1].parent / "shared" / "data"
pytestmark = [
    pytest.mark.real,
    pytest.mark.skipif(not (SHARED / "pairs.json").is_file(), reason=f"shared real data absent ({SHARED})"),
]

INDOOR = ["3dm_redkitchen_6_to_0_geotransformer", "3dm_redkitchen_4_to_0_teaser_fullres",
          "3dlm_redkitchen_7_to_0_mac_fullres"]  # fmt: skip
KITTI = ["kitti00_95_to_94", "kitti00_199_to_198"]


def _pair(pair_id: str):
    from fastmac_exp.datasets.user_pairs import SharedRealPairs

    ds = SharedRealPairs(root=SHARED, ids=[pair_id])
    return ds.load(0)


@pytest.fixture(scope="module")
def backend():
    return make_backend("auto")


@pytest.mark.parametrize("pair_id", INDOOR + KITTI)
def test_mac_with_fpfh_recovers_gt(pair_id, backend):
    pair = _pair(pair_id)
    out = run_pair(pair, FPFHDescriptor(), make_sampler("none"), backend, 1.0, np.random.default_rng(0))
    row = out.row
    assert row["success"], (pair_id, row["re_deg"], row["te_cm"], row["inlier_ratio_in"])
    assert row["re_deg"] < (5.0 if pair.family != "kitti" else 1.0)


@pytest.mark.parametrize("pair_id", INDOOR[:2] + KITTI[:1])
def test_fastmac_highpass_20_percent_recovers_gt(pair_id, backend):
    pair = _pair(pair_id)
    out = run_pair(pair, FPFHDescriptor(), make_sampler("highpass"), backend, 0.2, np.random.default_rng(0))
    assert out.row["success"], (pair_id, out.row["re_deg"], out.row["te_cm"])
    assert out.row["n_kept"] == int(out.row["n_in"] * 0.2)


def test_library_register_on_two_clouds():
    import fastmac_exp
    from fastmac_exp.geometry.metrics import pose_errors

    pair = _pair(INDOOR[1])
    res = fastmac_exp.register(pair.src_cloud, pair.tgt_cloud, family="3dmatch", voxel_size=0.05, ratio=0.2)
    assert pose_errors(res.pose, pair.gt, 15, 0.3).success
    assert {"describe", "sampling", "graph", "cliques", "selection", "pose", "total"} <= set(res.timings)
