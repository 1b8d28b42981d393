"""descriptor=fcgf: checkpoints in FCGF's own format (a random, checkpoint-shaped state dict saved with
torch.save, its config an easydict.EasyDict), identification by hash, the ONNX model against the torch path,
the cached conversion, and the front end. With FCGF_CHECKPOINT pointing at a published 3DMatch checkpoint,
the inlier ratio on the real indoor pairs against FPFH's (skipped otherwise)."""

from __future__ import annotations

import os
import sys
import types
from collections import OrderedDict
from pathlib import Path

import numpy as np
import pytest
import torch

from fastmac_exp.descriptors import fcgf_checkpoint
from fastmac_exp.descriptors.fcgf import NO_CHECKPOINT, FcgfDescriptor, cached_model_path
from fastmac_exp.descriptors.fcgf_checkpoint import PublishedCheckpoint, file_ids, load_checkpoint
from fastmac_exp.descriptors.fcgf_maps import unet_maps, voxelize
from fastmac_exp.descriptors.fcgf_onnx import build_model, onnx_feeds
from fastmac_exp.descriptors.fcgf_plan import NetConfig
from fastmac_exp.descriptors.fcgf_torch import ResUNetBN2C
from fastmac_exp.descriptors.matching import match_descriptors
from fastmac_exp.errors import InputError, own_error
from tests.test_fcgf_sparse import random_state

REPO = Path(__file__).resolve().parents[1]
F32 = dict(rtol=1e-4, atol=2e-5)  # float32 sums in another order (ONNX folds BN into a scale and shift)


def fake_easydict_module():
    """A stand-in for the easydict package, so that the pickle names easydict.EasyDict as FCGF's does."""
    mod = types.ModuleType("easydict")

    class EasyDict(dict):
        def __init__(self, d=None):
            super().__init__()
            for k, v in (d or {}).items():
                setattr(self, k, v)

        def __setattr__(self, name, value):
            super().__setattr__(name, value)
            self[name] = value

    EasyDict.__module__, EasyDict.__qualname__ = "easydict", "EasyDict"
    mod.EasyDict = EasyDict
    return mod


def save_checkpoint(
    path, cfg: NetConfig, seed=0, voxel=0.025, model="ResUNetBN2C", legacy=False, old_me=False, edit=None
):
    """A checkpoint as FCGF's trainer saves one: state_dict, config (EasyDict), optimizer, scheduler, ..."""
    state = OrderedDict((k, v.float()) for k, v in random_state(cfg, seed).items())
    if old_me:  # ME < 0.5: 1x1x1 kernels (1, in, out), as the 2019 checkpoints were saved
        for key in ("conv1_tr.kernel", "final.kernel"):
            state[key] = state[key][None]
    if edit:
        edit(state)
    mod = fake_easydict_module()
    sys.modules["easydict"] = mod
    try:
        config = mod.EasyDict(
            {"model": model, "voxel_size": voxel, "conv1_kernel_size": cfg.conv1_kernel_size,
             "model_n_out": cfg.out_channels, "normalize_feature": cfg.normalize_feature, "bn_momentum": 0.05,
             "out_dir": "outputs/x", "trainer": "HardestContrastiveLossTrainer"}
        )  # fmt: skip
        ck = {"epoch": 100, "state_dict": state, "config": config, "best_val": np.float64(0.9578),
              "best_val_epoch": 97, "best_val_metric": "feat_match_ratio",
              "optimizer": {"state": {}, "param_groups": [{"lr": 0.05, "params": [0, 1]}]},
              "scheduler": {"gamma": 0.99, "base_lrs": [0.1], "last_epoch": 100}}  # fmt: skip
        torch.save(ck, path, _use_new_zipfile_serialization=not legacy)
    finally:
        del sys.modules["easydict"]
    return Path(path)


CFG = NetConfig(1, 5, 16, True)


@pytest.fixture
def ckpt(tmp_path):
    return save_checkpoint(tmp_path / "model.pth", CFG)


def cloud(seed=0, n=6000):
    """A wavy sheet and a wall: surface-like, as a scan is."""
    rng = np.random.default_rng(seed)
    u = rng.uniform(0, 1.2, (n, 2))
    sheet = np.c_[u, 0.15 * np.sin(4 * u[:, 0]) * np.cos(3 * u[:, 1])]
    wall = np.c_[rng.uniform(0, 1.2, n // 3), np.full(n // 3, 1.2), rng.uniform(0, 0.6, n // 3)]
    return np.concatenate([sheet, wall])


# -- checkpoints


@pytest.mark.parametrize("legacy", [False, True], ids=["zip", "legacy"])
def test_an_unknown_checkpoint_is_refused_with_what_was_found(tmp_path, legacy):
    p = save_checkpoint(tmp_path / "x.pth", CFG, legacy=legacy)
    ids = file_ids(p)
    with pytest.raises(InputError) as e:
        load_checkpoint(p)
    msg = str(e.value)
    for part in (
        ids.sha256,
        ids.git_blob,
        "conv1 5, 16 channels",
        "voxel 0.025",
        f"descriptor.sha256={ids.sha256}",
    ):
        assert part in msg, (part, msg)
    ck = load_checkpoint(p, trusted_sha256=ids.sha256.upper())
    assert ck.known is None and ck.cfg == CFG and ck.voxel_size == 0.025 and ck.bn_momentum == 0.05
    assert ck.state["final.kernel"].shape == (64, 16) and ck.state["final.kernel"].dtype == np.float32


def test_file_ids_are_sha256_and_the_git_blob_id(tmp_path):
    p = tmp_path / "f"
    p.write_bytes(b"hello\n")  # `git hash-object` of this content: ce0136250...
    ids = file_ids(p)
    assert ids.git_blob == "ce013625030ba8dba906f756967f9e9ca394464a"
    assert ids.sha256 == "5891b5b522d5df086d0ff0b110fbd9d21bb4fc7163af34d08286a2e846f6be03"


def test_a_published_checkpoint_is_known_by_its_git_blob(ckpt, monkeypatch):
    ids = file_ids(ckpt)
    entry = PublishedCheckpoint(
        "x.pth", "3dmatch", 0.025, 16, True, "https://example.invalid/x.pth", git_blob=ids.git_blob
    )
    monkeypatch.setattr(fcgf_checkpoint, "PUBLISHED", (entry,))
    assert load_checkpoint(ckpt).known == entry
    wrong = PublishedCheckpoint(
        "y.pth", "kitti", 0.3, 16, True, "https://example.invalid/y.pth", sha256=ids.sha256
    )
    monkeypatch.setattr(fcgf_checkpoint, "PUBLISHED", (wrong,))
    with pytest.raises(InputError, match="has the hash of y.pth but not its config"):
        load_checkpoint(ckpt)


def test_the_kitti_checkpoint_of_the_dgr_fork_is_listed_by_its_blob():
    (kitti,) = [c for c in fcgf_checkpoint.PUBLISHED if c.file == "2019-07-31_19-37-00.pth"]
    assert kitti.git_blob == "5fdeef3cce537bab12cd1d2b5962b06c9462ba38" and kitti.voxel_size == 0.3


def _drop(key):
    return lambda s: s.pop(key)


def _reshape(key, shape):
    return lambda s: s.__setitem__(key, torch.zeros(shape))


@pytest.mark.parametrize(
    ("edit", "model", "match"),
    [
        (_drop("block3.norm2.bn.running_var"), "ResUNetBN2C", "missing block3.norm2.bn.running_var"),
        (_reshape("conv3_tr.kernel", (27, 128, 64)), "ResUNetBN2C",
         r"conv3_tr.kernel \(27, 128, 64\) \(expected \(27, 256, 64\)\)"),
        (lambda s: s.__setitem__("block9.conv1.kernel", torch.zeros(1)), "ResUNetBN2C",
         "unexpected block9.conv1.kernel"),
        (None, "ResUNetBN2B", "is a 'ResUNetBN2B'"),
        (_reshape("conv1.kernel", (125, 3, 32)), "ResUNetBN2C", "takes 3 input channels"),
        (_reshape("conv1.kernel", (343, 1, 32)), "ResUNetBN2C", "does not fit conv1_kernel_size 5"),
    ],
    ids=["missing", "shape", "unexpected", "model", "channels", "conv1"],
)  # fmt: skip
def test_a_checkpoint_that_does_not_fit_is_refused_naming_what(tmp_path, edit, model, match):
    p = save_checkpoint(tmp_path / "bad.pth", CFG, model=model, edit=edit)
    with pytest.raises(InputError, match=match):
        load_checkpoint(p, trusted_sha256=file_ids(p).sha256)


def test_not_a_checkpoint_and_code_in_a_pickle_are_refused(tmp_path):
    p = tmp_path / "x.pth"
    p.write_bytes(b"not a checkpoint")
    with pytest.raises(InputError, match="could not be read"):
        load_checkpoint(p, trusted_sha256=file_ids(p).sha256)
    torch.save(
        {"state_dict": {}, "config": types.SimpleNamespace(model="x")}, p
    )  # a global outside the allowlist
    with pytest.raises(InputError, match="could not be read"):
        load_checkpoint(p, trusted_sha256=file_ids(p).sha256)


# -- ONNX against torch


@pytest.mark.parametrize(
    "cfg", [NetConfig(1, 5, 16, True), NetConfig(1, 7, 32, False)], ids=["k5-16", "k7-32-raw"]
)
def test_onnx_equals_the_torch_path(tmp_path, cfg):
    import onnxruntime as ort

    p = save_checkpoint(tmp_path / "c.pth", cfg, old_me=cfg.conv1_kernel_size == 7)
    ck = load_checkpoint(p, trusted_sha256=file_ids(p).sha256)
    coords, _ = voxelize(cloud(), 0.025)
    maps = unet_maps(coords, cfg.conv1_kernel_size)
    assert maps.sizes[0] > 1000 and maps.sizes[3] > 10
    x = np.ones((len(coords), 1), np.float32)
    model = ResUNetBN2C(cfg)
    model.load_fcgf({k: torch.from_numpy(v) for k, v in ck.state.items()})
    want = model(torch.from_numpy(x), maps).numpy()
    onnx_model = build_model(ck.state, cfg, {"fastmac.preprocess": "fcgf"})
    outs = []
    for threads in (1, 2):
        opts = ort.SessionOptions()
        opts.intra_op_num_threads = threads
        sess = ort.InferenceSession(onnx_model.SerializeToString(), opts, providers=["CPUExecutionProvider"])
        outs.append(sess.run(None, onnx_feeds(x, maps, [i.name for i in sess.get_inputs()]))[0])
    np.testing.assert_allclose(outs[0], want, **F32)
    np.testing.assert_array_equal(outs[0], outs[1])  # no thread-dependent sums
    assert np.abs(want).max() > 0.1 and want.std() > 0.01


# -- the front end


def test_descriptor_converts_once_into_the_data_home_and_describes(ckpt, tmp_path, monkeypatch):
    monkeypatch.setenv("FASTMAC_DATA", str(tmp_path / "home"))
    monkeypatch.delenv("FCGF_CHECKPOINT", raising=False)
    sha = file_ids(ckpt).sha256
    d = FcgfDescriptor(checkpoint=str(ckpt), sha256=sha)
    assert d.model_path == cached_model_path(sha) and d.model_path.is_relative_to(tmp_path / "home" / "fcgf")
    assert d.voxel_size == 0.025 and d.graph_key == "fcgf" and d.name == "fcgf"
    pts = cloud(1)
    kp, f = d.features(pts, d.voxel_size)
    coords, first = voxelize(pts, 0.025)
    assert np.array_equal(kp, pts[first]) and f.shape == (len(coords), 16)
    np.testing.assert_allclose(np.linalg.norm(f, axis=1), 1.0, rtol=1e-5)
    model = ResUNetBN2C(CFG)
    model.load_fcgf({k: torch.from_numpy(v) for k, v in load_checkpoint(ckpt, sha).state.items()})
    want = model(torch.ones((len(coords), 1)), unet_maps(coords, 5)).numpy()
    np.testing.assert_allclose(f, want, **F32)
    # a second front end takes the cached model: no conversion
    monkeypatch.setattr("fastmac_exp.descriptors.fcgf.convert", lambda *a: pytest.fail("converted again"))
    monkeypatch.setenv("FCGF_CHECKPOINT", str(ckpt))
    again = FcgfDescriptor(sha256=sha)
    assert np.array_equal(again.features(pts, again.voxel_size)[1], f)


def test_matching_only_the_capped_sources_gives_the_plain_path_s_correspondences(ckpt, tmp_path, monkeypatch):
    from fastmac_exp.descriptors.matching import correspondences_from_features
    from fastmac_exp.types import Pair

    monkeypatch.setenv("FASTMAC_DATA", str(tmp_path / "home"))
    d = FcgfDescriptor(checkpoint=str(ckpt), sha256=file_ids(ckpt).sha256, max_correspondences=300)
    src = cloud(2)
    pair = Pair(name="p", src_cloud=src, tgt_cloud=src + 0.01, voxel_size=0.05, family="3dmatch")
    fast = d(pair, np.random.default_rng(5))
    plain = correspondences_from_features(d, pair, np.random.default_rng(5), match_descriptors)
    assert (
        len(fast.src) == 300 and np.array_equal(fast.src, plain.src) and np.array_equal(fast.tgt, plain.tgt)
    )


def test_descriptor_refuses_an_unknown_checkpoint_and_a_missing_one(ckpt, tmp_path, monkeypatch):
    monkeypatch.setenv("FASTMAC_DATA", str(tmp_path / "home"))
    with pytest.raises(InputError, match="not a published checkpoint"):
        FcgfDescriptor(checkpoint=str(ckpt))
    assert not (tmp_path / "home").exists()
    with pytest.raises(InputError, match="does not exist"):
        FcgfDescriptor(checkpoint=str(tmp_path / "nosuch.pth"))


def test_descriptor_fcgf_without_a_checkpoint_says_both_ways(monkeypatch):
    from hydra import compose, initialize_config_dir

    from fastmac_exp.run.experiment import Components

    monkeypatch.delenv("FCGF_CHECKPOINT", raising=False)
    with initialize_config_dir(config_dir=str(REPO / "conf"), version_base="1.3"):
        cfg = compose(config_name="config", overrides=["descriptor=fcgf"])
    with pytest.raises(Exception) as e:  # noqa: B017 - Hydra wraps the constructor's error
        Components(cfg)
    assert str(own_error(e.value)) == NO_CHECKPOINT
    assert "descriptor.checkpoint=PATH" in NO_CHECKPOINT and "FCGF_CHECKPOINT=PATH" in NO_CHECKPOINT


def test_descriptor_fcgf_config_builds_the_front_end(ckpt, tmp_path, monkeypatch):
    from hydra import compose, initialize_config_dir

    from fastmac_exp.run.experiment import Components

    monkeypatch.setenv("FASTMAC_DATA", str(tmp_path / "home"))
    overrides = [
        "descriptor=fcgf",
        f"descriptor.checkpoint={ckpt}",
        f"descriptor.sha256={file_ids(ckpt).sha256}",
    ]
    with initialize_config_dir(config_dir=str(REPO / "conf"), version_base="1.3"):
        cfg = compose(config_name="config", overrides=overrides)
    parts = Components(cfg)
    assert isinstance(parts.descriptor, FcgfDescriptor) and parts.labels["descriptor"] == "fcgf"


# -- a published checkpoint, where one is given


@pytest.mark.real
@pytest.mark.skipif(
    not os.environ.get("FCGF_CHECKPOINT"), reason="FCGF_CHECKPOINT does not point at a checkpoint"
)
def test_published_checkpoint_inlier_ratio_on_real_indoor_pairs(tmp_path, monkeypatch):
    """FCGF's paper: several times FPFH's inlier ratio on 3DMatch; here at least 3x on the real pairs."""
    from fastmac_exp.datasets.user_pairs import SharedRealPairs
    from fastmac_exp.descriptors.fpfh import FPFHDescriptor

    root = REPO.parent / "shared" / "data"
    if not (root / "pairs.json").is_file():
        pytest.skip("../shared/data is absent")
    d = FcgfDescriptor()  # FCGF_CHECKPOINT; a published file is known by its hash
    if d.checkpoint_voxel > 0.1:
        pytest.skip(f"{d.checkpoint} is a KITTI checkpoint (voxel {d.checkpoint_voxel} m)")
    ds = SharedRealPairs(root=root, category="indoor")
    fpfh = FPFHDescriptor()
    ir = {"fcgf": [], "fpfh": []}
    for i in range(len(ds)):
        pair = ds.load(i)
        ir["fcgf"].append(d(pair, np.random.default_rng(0)).inlier_ratio)
        ir["fpfh"].append(fpfh(pair, np.random.default_rng(0)).inlier_ratio)
    mean = {k: float(np.mean(v)) for k, v in ir.items()}
    assert mean["fcgf"] >= 3 * mean["fpfh"], (mean, ir)
