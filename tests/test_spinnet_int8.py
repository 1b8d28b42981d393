"""SpinNet INT8 (descriptors/spinnet/quantize.py, MODEL_CARD.md): the C++ pooling equals grouping + the
point MLP's product + the max, the pooled float model computes what the shipped one does, the shipped int8
models are the recorded quantisation (the first and last four convolutions float32, the rest in uint8), the
per-channel equalisation is exact in float, their descriptors agree with float32's on a small synthetic
cloud and on the held-out synthetic pair, and `precision` is reachable from the config and checked."""

from __future__ import annotations

import hashlib
import json
from pathlib import Path

import numpy as np
import pytest

from fastmac_exp.descriptors.onnx_descriptor import resolve_model_path
from fastmac_exp.descriptors.patches import voxel_down
from fastmac_exp.descriptors.spinnet import (
    SHIPPED,
    SHIPPED_INT8,
    SpinNetDescriptor,
    SpinNetParams,
    group_cells,
    pool_cells,
    pool_cells_numpy,
)
from fastmac_exp.errors import InputError

from .test_onnx_descriptor import toy_room

REPO = Path(__file__).resolve().parents[1]
QUANT = json.loads((REPO / "descriptors" / "spinnet" / "quantize.json").read_text())
needs_core = pytest.mark.skipif(not __import__("fastmac_exp.core").core.available(), reason="no C++ core")


def sha256(path: Path) -> str:
    return hashlib.sha256(Path(path).read_bytes()).hexdigest()


def patches(p: SpinNetParams, m: int, seed: int) -> np.ndarray:
    """Aligned patches (m, P, 3) in metres with crowded cells (a cluster), sparse ones and empty ones, the
    keypoint (0) last as the runtime pads them."""
    rng = np.random.default_rng(seed)
    pts = rng.normal(size=(m, p.patch_points, 3)) * p.des_r / 3
    pts[:, : p.patch_points // 4] = rng.normal(size=(m, p.patch_points // 4, 3)) * p.voxel_r / 3 + [
        p.des_r / 2,
        0,
        0,
    ]
    pts = pts / np.maximum(1.0, np.linalg.norm(pts, axis=2, keepdims=True) / p.des_r)
    pts[:, -1] = 0
    return pts.astype(np.float32)


@needs_core
@pytest.mark.parametrize("samples", [1, 4])
def test_cpp_pooling_equals_grouping_then_the_max(samples):
    p = SpinNetParams(des_r=0.3, rad_n=3, ele_n=4, azi_n=8, voxel_r=0.06, samples=samples, patch_points=256)
    x = patches(p, 3, seed=samples)
    w = np.random.default_rng(7).normal(size=(3, 16)).astype(np.float32)
    got = pool_cells(x, p, w)
    want = (group_cells(x, p).reshape(3, p.cells, samples, 3) @ w).max(axis=2)
    assert got.shape == (3, p.cells, 16)
    np.testing.assert_allclose(got, want, rtol=0, atol=1e-6)
    np.testing.assert_allclose(got, pool_cells_numpy(x, p, w), rtol=0, atol=1e-6)


def test_pooled_float_model_computes_what_the_shipped_model_does():
    """descriptors/spinnet/quantize.py's first step alone (no quantisation): the same outputs."""
    onnx = pytest.importorskip("onnx")
    ort = pytest.importorskip("onnxruntime")
    from descriptors.spinnet.quantize import pooled_model

    src = resolve_model_path(SHIPPED["kitti"])
    pooled = pooled_model(src)
    meta = {p.key: p.value for p in pooled.metadata_props}
    w = np.asarray(json.loads(meta["spinnet.point_weights"]), np.float32)
    p = SpinNetDescriptor(model="kitti", progress=False).load("kitti").params
    cells = group_cells(patches(p, 2, seed=3), p)
    opts = ort.SessionOptions()
    opts.intra_op_num_threads = 1
    a = ort.InferenceSession(str(src), opts, providers=["CPUExecutionProvider"]).run(None, {"cells": cells})[
        0
    ]
    s = ort.InferenceSession(pooled.SerializeToString(), opts, providers=["CPUExecutionProvider"])
    b = s.run(None, {"pooled": (cells.reshape(2, p.cells, p.samples, 3) @ w).max(axis=2)})[0]
    assert meta["spinnet.input"] == "pooled" and "MatMul" not in {n.op_type for n in pooled.graph.node}
    np.testing.assert_allclose(b, a, rtol=0, atol=1e-5 * np.abs(a).max())
    assert onnx is not None


@needs_core
def test_per_channel_equalisation_is_exact_in_float():
    """quantize.py's `equalize` (a variant agreement.py scores): the equalised float model on its inputs
    divided per channel computes what the pooled model does, and the ranges it equalises did change."""
    pytest.importorskip("onnxruntime")
    from descriptors.spinnet.quantize import activation_ranges, equalize, point_weights, pooled_model, session

    pooled = pooled_model(resolve_model_path(SHIPPED["kitti"]))
    w, _ = point_weights(pooled)
    p = SpinNetDescriptor(model="kitti", progress=False).load("kitti").params
    x = pool_cells(patches(p, 6, seed=5), p, w)
    eq, div = equalize(pooled, x[:4], alpha=1.0)
    a = session(pooled).run(None, {"pooled": x[4:]})[0]
    b = session(eq).run(None, {"pooled": x[4:] / div})[0]
    np.testing.assert_allclose(b, a, rtol=0, atol=1e-5 * np.abs(a).max())
    np.testing.assert_allclose(point_weights(eq)[0] * div, w, rtol=1e-6)
    before, after = activation_ranges(pooled, x[:4]), activation_ranges(eq, x[:4] / div)
    for r0, r1 in zip(before, after, strict=True):  # each live channel of a convolution's input: one range
        live = r0 > 0
        assert r0[live].min() / r0.max() < 0.9 and r1[live].min() / r1.max() > 0.999
        assert not r1[~live].any()


def test_int8_models_are_the_recorded_quantisation_and_stay_in_uint8():
    onnx = pytest.importorskip("onnx")
    q = SpinNetDescriptor(threads=1, progress=False, precision="int8")
    for fam, rec in QUANT["families"].items():
        path = resolve_model_path(SHIPPED_INT8[fam])
        assert sha256(path) == rec["int8_sha256"] and path.stat().st_size < 1e6, fam
        assert sha256(resolve_model_path(SHIPPED[fam])) == rec["float_sha256"], fam
        model = q.load(fam)
        assert model.pooled and model.metadata["fastmac.precision"] == "int8"
        assert model.metadata["fastmac.quantized_from_sha256"] == rec["float_sha256"]
        assert model.params == SpinNetDescriptor(progress=False).load(fam).params
        graph = onnx.load(str(path)).graph
        ops = [n.op_type for n in graph.node]
        convs = [n.op_type for n in graph.node if n.op_type in ("Conv", "QLinearConv")]
        # the variant's float32 convolutions (0 and 7-10, 0-based) and uint8 ones (1-6): one QuantizeLinear
        # (before 1), one DequantizeLinear (after 6), the Relus between the uint8 ones gone into their
        # saturation
        assert model.metadata["fastmac.int8_variant"] == QUANT["variant"] == "first_last4_float"
        want = ["QLinearConv" if i not in QUANT["spec"]["float_convs"] else "Conv" for i in range(11)]
        assert convs == want == ["Conv"] + ["QLinearConv"] * 6 + ["Conv"] * 4, (fam, convs)
        assert ops.count("QuantizeLinear") == 1 and ops.count("DequantizeLinear") == 1, (fam, ops)
        assert ops.count("Relu") == 4, (fam, ops)  # the input's and those after convolutions 0, 6 and 7
        assert rec["fused_chains"] == 6 == int(model.metadata["fastmac.int8_fused_chains"])
    assert q.name == "spinnet_int8" and SpinNetDescriptor(progress=False).name == "spinnet"


@needs_core
def test_int8_descriptors_agree_with_float32_on_a_small_synthetic_cloud():
    """Measured on this room: mean cosine ~0.999; a broken quantisation (a wrong scale, a dropped bias, a
    fused chain that changed what a layer computes) falls well below."""
    room = toy_room(1) - np.array([1.0, 1.0, 1.2])
    kp = voxel_down(room, 0.2)[:24]
    fl = SpinNetDescriptor(threads=1, progress=False, cache_clouds=0)
    q = SpinNetDescriptor(threads=1, progress=False, precision="int8", cache_clouds=0)
    a = fl.describe(fl.load("3dmatch"), room, kp, 1.0)
    b = q.describe(q.load("3dmatch"), room, kp, 1.0)
    cos = np.sum(a * b, axis=1)
    assert cos.mean() > 0.995 and cos.min() > 0.97, (cos.mean(), cos.min())
    assert np.abs(a - b).max() > 1e-4  # another model, not the float one under a new name


def test_two_onnxruntime_threads_describe_what_one_does():
    """`threads: 0` (one a core) is the config's default: the descriptors must not depend on it (a cache or a
    study would otherwise depend on the machine). Both models, both precisions, bit for bit."""
    room = toy_room(1) - np.array([1.0, 1.0, 1.2])
    kp = voxel_down(room, 0.2)[:12]
    for precision in ("int8", "float32"):
        for family in ("3dmatch", "kitti"):
            out = []
            for threads in (1, 2):
                d = SpinNetDescriptor(threads=threads, progress=False, precision=precision, cache_clouds=0)
                out.append(d.describe(d.load(family), room, kp, 1.0))
            np.testing.assert_array_equal(out[0], out[1], err_msg=f"{precision} {family}")


HELD_OUT_KEYPOINTS = 48  # a cloud
# bounds on the held-out pair (test below). Measured (cosine mean / min / same nearest): 3DMatch
# 0.99991 / 0.99971 / 1.0, KITTI 0.99964 / 0.99836 / 0.9375; the models before (all in uint8) 0.99938 /
# 0.99852 / 1.0 and 0.99528 / 0.977 / 0.875 fail the cosine bounds (48 keypoints: same-nearest is coarse)
COS_MEAN = {"3dmatch": 0.9998, "kitti": 0.9993}
COS_MIN = {"3dmatch": 0.999, "kitti": 0.997}
SAME = {"3dmatch": 0.95, "kitti": 0.9}


def held_out_agreement(family: str, **int8) -> dict:
    """INT8 (the shipped model, or `int8`'s SpinNetDescriptor arguments) against float32 through the front
    end on the held-out synthetic pair of descriptors/spinnet/quantize.py (seed 1000, pair 2: never
    calibrated on), HELD_OUT_KEYPOINTS keypoints a cloud, one onnxruntime thread (deterministic)."""
    from descriptors.spinnet.quantize import agreement
    from fastmac_exp.datasets.synthetic import SyntheticDataset

    pair = SyntheticDataset(family, num_pairs=3, seed=1000, cache_dir=None).load(2)
    feats = []
    for extra in ({}, {"precision": "int8", **int8}):
        d = SpinNetDescriptor(
            threads=1, progress=False, keypoints=HELD_OUT_KEYPOINTS, cache_clouds=0, **extra
        )
        feats.append(
            [d.features(c, pair.voxel_size, family=family)[1] for c in (pair.src_cloud, pair.tgt_cloud)]
        )
    return agreement(*feats)


@needs_core
@pytest.mark.parametrize("family", ["3dmatch", "kitti"])
def test_int8_agrees_with_float32_on_the_held_out_synthetic_pair(family):
    """The shipped INT8 models keep the first and the last four convolutions in float32 (MODEL_CARD.md,
    INT8); measured values beside the bounds (COS_MEAN)."""
    got = held_out_agreement(family)
    assert got["keypoints"] == 2 * HELD_OUT_KEYPOINTS
    assert got["cosine_mean"] > COS_MEAN[family] and got["cosine_min"] > COS_MIN[family], got
    assert got["same_nearest_target"] >= SAME[family], got


def test_precision_reaches_the_config_and_is_checked():
    from hydra import compose, initialize_config_dir
    from hydra.utils import instantiate

    with initialize_config_dir(str(REPO / "conf"), version_base=None):
        cfg = compose("config", overrides=["descriptor=spinnet"])
    d = instantiate(cfg.descriptor)
    assert d.precision == "int8" and d.name == "spinnet_int8"  # the run's default
    assert d.model_for("3dlomatch").desc_path.name == "spinnet_3dmatch_int8.onnx"
    assert d.model_for("kitti").desc_path.name == "spinnet_kitti_int8.onnx"
    f = instantiate(cfg.descriptor, precision="float32")
    assert f.name == "spinnet" and f.model_for("kitti").desc_path.name == "spinnet_kitti.onnx"
    said = r"spinnet precision must be one of \('float32', 'int8'\), got 'fp16'"
    with pytest.raises(InputError, match=said):
        SpinNetDescriptor(precision="fp16")
    with pytest.raises(Exception, match=said):  # through the config: Hydra's error carries the message
        instantiate(cfg.descriptor, precision="fp16")
    wrong = SpinNetDescriptor(precision="int8", model_kitti_int8=SHIPPED["kitti"], progress=False)
    with pytest.raises(InputError, match="is float32 .* descriptor.precision is int8"):
        wrong.load("kitti")
    with pytest.raises(InputError, match="descriptors/spinnet/quantize.py"):
        SpinNetDescriptor(precision="int8", model_kitti_int8="nowhere_int8.onnx", progress=False).load(
            "kitti"
        )
