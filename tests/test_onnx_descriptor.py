"""The learned-descriptor front end: the shipped ONNX model, its contract, errors, and correspondences."""

from __future__ import annotations

import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest
from scipy.spatial import cKDTree

from fastmac_exp.descriptors.onnx_descriptor import DEFAULT_MODEL, OnnxDescriptor, resolve_model_path
from fastmac_exp.descriptors.patches import PatchParams, extract_patches, support_clouds, voxel_down
from fastmac_exp.errors import InputError
from fastmac_exp.resources import MODELS_DIR
from fastmac_exp.types import Correspondences, Pair

REPO = Path(__file__).resolve().parents[1]
MODEL = resolve_model_path(DEFAULT_MODEL)


def box_surface(rng, lo, hi, spacing: float) -> np.ndarray:
    """Points on the surface of an axis-aligned box, about `spacing` apart."""
    lo, hi = np.asarray(lo, float), np.asarray(hi, float)
    out = []
    for axis in range(3):
        for side in (lo[axis], hi[axis]):
            a, b = [i for i in range(3) if i != axis]
            area = (hi[a] - lo[a]) * (hi[b] - lo[b])
            n = max(4, int(area / spacing**2))
            p = np.empty((n, 3))
            p[:, axis] = side
            p[:, a] = rng.uniform(lo[a], hi[a], n)
            p[:, b] = rng.uniform(lo[b], hi[b], n)
            out.append(p)
    return np.vstack(out)


def toy_room(seed: int = 0, spacing: float = 0.015, size: float = 2.0) -> np.ndarray:
    """A room corner (floor, two walls) with a few boxes: `size` metres across."""
    rng = np.random.default_rng(seed)
    parts = []
    for axis in range(3):  # floor z=0, walls x=0 and y=0
        n = int(size**2 / spacing**2)
        p = rng.uniform(0, size, (n, 3))
        p[:, axis] = 0.0
        parts.append(p)
    for _ in range(6):
        c = rng.uniform(0.15, 0.85, 2) * size
        s = rng.uniform(0.15, 0.5, 3)
        parts.append(box_surface(rng, [c[0], c[1], 0.0], [c[0] + s[0], c[1] + s[1], s[2]], spacing))
    pts = np.vstack(parts)
    return pts + rng.normal(scale=0.002, size=pts.shape)


def random_rotation(rng) -> np.ndarray:
    q, r = np.linalg.qr(rng.normal(size=(3, 3)))
    q = q * np.sign(np.diag(r))
    return q if np.linalg.det(q) > 0 else -q


@pytest.fixture(scope="module")
def desc() -> OnnxDescriptor:
    return OnnxDescriptor()


def test_shipped_model_meets_contract(desc):
    import onnxruntime as ort

    assert MODEL.is_file() and MODEL.stat().st_size < 5e6
    sess = ort.InferenceSession(str(MODEL), providers=["CPUExecutionProvider"])
    (inp,), (out,) = sess.get_inputs(), sess.get_outputs()
    assert inp.type == "tensor(float)" and len(inp.shape) == 3 and not isinstance(inp.shape[0], int)
    assert out.type == "tensor(float)" and len(out.shape) == 2
    k, c = desc.params.size, desc.params.channels
    for m in (1, 7, 300):  # dynamic batch axis
        x = np.random.default_rng(m).uniform(-1, 1, (m, k, c)).astype(np.float32)
        y = sess.run(None, {inp.name: x})[0]
        assert y.shape == (m, 32) and y.dtype == np.float32
        np.testing.assert_allclose(np.linalg.norm(y, axis=1), 1.0, atol=1e-4)
    kp, f = desc.features(toy_room(), 0.05)
    assert f.shape == (len(kp), 32) and f.dtype == np.float32
    np.testing.assert_allclose(np.linalg.norm(f, axis=1), 1.0, atol=1e-5)


def test_rotation_robustness(desc):
    """The same patch under a random rotation of the whole cloud: the LRF makes the descriptor invariant."""
    pts = toy_room(1)
    voxel = 0.05
    kp = voxel_down(pts, voxel)
    supports = support_clouds(pts, kp, voxel, desc.params)
    rng = np.random.default_rng(3)
    rot, t = random_rotation(rng), rng.uniform(-5, 5, 3)
    a = desc.embed(extract_patches(kp, supports, voxel, desc.params))
    moved = [s @ rot.T + t for s in supports]
    b = desc.embed(extract_patches(kp @ rot.T + t, moved, voxel, desc.params))
    cos = np.sum(a * b, axis=1)
    assert cos.mean() > 0.99, f"mean cosine under rotation {cos.mean():.3f}"


def test_rotation_robustness_end_to_end(desc):
    """Rotating the raw cloud also re-voxelises it (other keypoints, other patch samples): descriptors of
    keypoints that land within 2 cm of each other still agree (mean cosine ~0.83; a grid shift alone
    without rotation gives ~0.85, so the loss is resampling, not rotation), far above unrelated pairs."""
    pts = toy_room(1)
    rng = np.random.default_rng(4)
    rot, t = random_rotation(rng), rng.uniform(-5, 5, 3)
    k0, f0 = desc.features(pts, 0.05)
    k1, f1 = desc.features(pts @ rot.T + t, 0.05)
    dist, j = cKDTree((k1 - t) @ rot).query(k0)
    near = dist < 0.02
    assert near.mean() > 0.3
    cos = np.sum(f0[near] * f1[j[near]], axis=1)
    unrelated = np.sum(f0[near] * f1[rng.permutation(j[near])], axis=1)
    assert cos.mean() > 0.75 and cos.mean() > unrelated.mean() + 0.3, (cos.mean(), unrelated.mean())


def test_wrong_input_model_gives_clear_error(tmp_path):
    import onnx
    from onnx import TensorProto, helper

    x = helper.make_tensor_value_info("points", TensorProto.DOUBLE, ["N", 3])
    y = helper.make_tensor_value_info("feat", TensorProto.DOUBLE, ["N", 3])
    graph = helper.make_graph([helper.make_node("Identity", ["points"], ["feat"])], "wrong", [x], [y])
    model = helper.make_model(graph, opset_imports=[helper.make_opsetid("", 17)])
    model.ir_version = 8
    path = tmp_path / "wrong.onnx"
    onnx.save(model, str(path))
    with pytest.raises(InputError) as err:
        OnnxDescriptor(str(path))
    msg = str(err.value)
    assert "contract" in msg and "'points'" in msg and "rank 2" in msg and "tensor(double)" in msg
    want = PatchParams()
    assert f"rank 3, (M, {want.size}, {want.channels})" in msg  # what was expected


def test_wrong_patch_size_model(tmp_path):
    import onnx
    from onnx import TensorProto, helper

    x = helper.make_tensor_value_info("patches", TensorProto.FLOAT, ["M", 16, PatchParams().channels])
    y = helper.make_tensor_value_info("d", TensorProto.FLOAT, ["M", PatchParams().channels])
    node = helper.make_node("ReduceMax", ["patches", "axes"], ["d"], keepdims=0)
    axes = helper.make_tensor("axes", TensorProto.INT64, [1], [1])
    graph = helper.make_graph([node], "k16", [x], [y], initializer=[axes])
    model = helper.make_model(graph, opset_imports=[helper.make_opsetid("", 18)])
    model.ir_version = 8
    path = tmp_path / "k16.onnx"
    onnx.save(model, str(path))
    with pytest.raises(InputError, match=f"K = 16, the patch size is {PatchParams().size}"):
        OnnxDescriptor(str(path))


def test_missing_model_path(tmp_path):
    with pytest.raises(InputError, match=r"not found.*descriptors/fcgf_lite/train\.py"):
        OnnxDescriptor(str(tmp_path / "nope.onnx"))
    with pytest.raises(InputError, match="not found"):
        OnnxDescriptor("descriptors/does_not_exist.onnx")


def test_relative_model_path_from_other_cwd(tmp_path, monkeypatch):
    monkeypatch.chdir(tmp_path)
    d = OnnxDescriptor(DEFAULT_MODEL)
    assert d.model_path == MODEL


def test_correspondences_on_small_pair(desc):
    rng = np.random.default_rng(5)
    src = toy_room(2, spacing=0.02, size=1.5)
    gt = np.eye(4)
    gt[:3, :3], gt[:3, 3] = random_rotation(rng), rng.uniform(-1, 1, 3)
    tgt = src[rng.permutation(len(src))[: int(0.8 * len(src))]]  # resampled, 80 % of the points
    tgt = tgt @ gt[:3, :3].T + gt[:3, 3] + rng.normal(scale=0.003, size=tgt.shape)
    pair = Pair(name="toy", gt=gt, src_cloud=src, tgt_cloud=tgt, voxel_size=0.05)
    d = OnnxDescriptor(max_correspondences=300)
    corr = d(pair, np.random.default_rng(0))
    assert isinstance(corr, Correspondences) and corr.labels is not None
    assert len(corr) == 300 and corr.scores is not None
    assert corr.inlier_ratio > 0.2  # FPFH: about 0.08 on this pair
    mutual = OnnxDescriptor(mutual=True, max_correspondences=0)(pair, np.random.default_rng(0))
    assert 0 < len(mutual) and mutual.inlier_ratio >= corr.inlier_ratio
    assert d.name == "fcgf_lite" and d.graph_key == "fcgf"  # the model's name; FCGF's graph row


def test_pair_without_clouds(desc):
    with pytest.raises(InputError, match="needs both point clouds"):
        desc(Pair(name="x"), np.random.default_rng(0))


def test_runtime_path_does_not_import_torch():
    code = (
        "import sys; from fastmac_exp.descriptors.onnx_descriptor import OnnxDescriptor; "
        "OnnxDescriptor(); assert 'torch' not in sys.modules, 'torch imported'"
    )
    subprocess.run([sys.executable, "-c", code], check=True, cwd=REPO)


def test_config_instantiates():
    from hydra.utils import instantiate
    from omegaconf import OmegaConf

    cfg = OmegaConf.to_container(OmegaConf.load(REPO / "conf" / "descriptor" / "fcgf_lite.yaml"))
    assert cfg.pop("graph_key") == "fcgf"
    d = instantiate(cfg)
    assert isinstance(d, OnnxDescriptor) and d.graph_key == "fcgf" and d.max_correspondences == 5000
    assert d.name == "fcgf_lite"


def test_buffer_models_are_refused_here():
    with pytest.raises(InputError, match="descriptor=buffer"):
        OnnxDescriptor(MODELS_DIR / "buffer_3dmatch_desc.onnx")


def test_pickles_for_parallel_workers(desc):
    import pickle

    clone = pickle.loads(pickle.dumps(desc))
    shape = (5, desc.params.size, desc.params.channels)
    x = np.random.default_rng(0).uniform(-1, 1, shape).astype(np.float32)
    np.testing.assert_allclose(clone.embed(x), desc.embed(x), atol=1e-6)


def test_execution_providers_reach_the_session(monkeypatch, caplog):
    """`execution_providers` goes to onnxruntime; a provider this onnxruntime lacks, or one that fails to
    start, falls back to the CPU with a one-line notice; "auto" asks for CUDA first, silently."""
    import logging

    import onnxruntime as ort

    from fastmac_exp.descriptors.buffer import BufferDescriptor

    with caplog.at_level(logging.WARNING):
        d = OnnxDescriptor(execution_providers=["cuda", "cpu"])
    assert d._session.get_providers() == ["CPUExecutionProvider"]
    if "CUDAExecutionProvider" not in ort.get_available_providers():  # the CPU build (this project's pin)
        notes = [r.getMessage() for r in caplog.records if "CUDAExecutionProvider" in r.getMessage()]
        assert len(notes) == 1 and "\n" not in notes[0] and "running on CPUExecutionProvider" in notes[0]
        caplog.clear()
        with caplog.at_level(logging.WARNING):
            OnnxDescriptor()  # auto: no notice on a machine without a GPU
        assert not caplog.records

    seen = []
    real = ort.InferenceSession

    def fake(path, opts=None, providers=None):
        seen.append(list(providers))
        if "CUDAExecutionProvider" in providers and len(seen) % 2:  # every other GPU start fails
            raise RuntimeError("CUDA failure 100: no CUDA-capable device is detected\nmore lines")
        return real(path, opts, providers=["CPUExecutionProvider"])

    both = ["CUDAExecutionProvider", "CPUExecutionProvider"]
    monkeypatch.setattr(ort, "get_available_providers", lambda: both)
    monkeypatch.setattr(ort, "InferenceSession", fake)
    caplog.clear()
    with caplog.at_level(logging.WARNING):
        d = OnnxDescriptor(execution_providers="auto")
    assert seen == [both, ["CPUExecutionProvider"]]  # asked for CUDA, it failed, CPU
    assert d._session.get_providers() == ["CPUExecutionProvider"]
    assert any("did not start (CUDA failure 100" in r.getMessage() for r in caplog.records)
    seen.clear()
    BufferDescriptor(execution_providers=["tensorrt", "cuda"], progress=False).load("3dmatch")
    assert seen[0] == both  # TensorRT is not there: dropped; CUDA then the CPU fallback
    assert OnnxDescriptor(execution_providers=["cpu"])._session.get_providers() == ["CPUExecutionProvider"]
    assert seen[-1] == ["CPUExecutionProvider"]
