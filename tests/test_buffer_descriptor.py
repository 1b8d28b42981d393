"""BUFFER through ONNX (descriptors/buffer/MODEL_CARD.md): the published weights load with no missing or
unexpected key, the shipped models compute what a torch forward pass of those weights computes, the numpy
preprocessing equals brute force, the descriptor is rotation invariant, and the front end plugs in.

Without ../shared the shipped models are still checked against the torch reference's outputs frozen at
export time (descriptors/buffer/export.json); only the checks that read the .pth files or a real fragment
skip.
"""

from __future__ import annotations

import hashlib
import json
import os
import pickle
import subprocess
import sys
import time
from pathlib import Path

import numpy as np
import pytest
from hydra import compose, initialize_config_dir

from fastmac_exp.descriptors.buffer import (
    SHIPPED,
    BufferDescriptor,
    BufferModel,
    BufferParams,
    align_rotations,
    check_desc_contract,
    forget_described_clouds,
    group_cells,
    ref_inputs,
)
from fastmac_exp.descriptors.onnx_descriptor import resolve_model_path
from fastmac_exp.descriptors.patches import voxel_down
from fastmac_exp.errors import InputError
from fastmac_exp.resources import MODELS_DIR
from fastmac_exp.types import Correspondences, Pair

from .test_onnx_descriptor import random_rotation, toy_room

REPO = Path(__file__).resolve().parents[1]
WEIGHTS = REPO.parent / "shared" / "models" / "buffer"
FRAGMENT = REPO.parent / "shared" / "data" / "teaser_3dmatch_redkitchen" / "cloud_bin_0.ply"
EXPORT = json.loads((REPO / "descriptors" / "buffer" / "export.json").read_text())
needs_weights = pytest.mark.skipif(
    not (WEIGHTS / "3dmatch" / "Desc_best.pth").is_file(), reason=f"BUFFER weights not at {WEIGHTS}"
)
needs_fragment = pytest.mark.skipif(not FRAGMENT.is_file(), reason=f"no 3DMatch fragment at {FRAGMENT}")
TOL_DESC = 1e-5  # unit descriptors, onnxruntime vs torch, float32 (measured <= 7e-7)
TOL_AXIS = 1e-4  # unit Ref axes (measured 6e-5: float32 rounding; float64 agrees to 6e-14)


def sha256(path) -> str:
    return hashlib.sha256(path.read_bytes()).hexdigest()


def session(path):
    import onnxruntime as ort

    opts = ort.SessionOptions()
    opts.intra_op_num_threads = 1
    return ort.InferenceSession(str(path), opts, providers=["CPUExecutionProvider"])


@pytest.fixture(scope="module")
def desc() -> BufferDescriptor:
    return BufferDescriptor(threads=1, progress=False)


@pytest.fixture(scope="module")
def room() -> np.ndarray:
    """A toy room (floor, two walls, boxes) with the sensor (the origin) inside it, 1.2 m above the floor."""
    return toy_room(1) - np.array([1.0, 1.0, 1.2])


def test_shipped_models_are_the_recorded_export(desc):
    for fam, rec in EXPORT["families"].items():
        path = resolve_model_path(SHIPPED[fam])
        assert path.stat().st_size < 5e6 and sha256(path) == rec["desc_onnx"]["sha256"], fam
        model = desc.load(fam)
        assert model.params == BufferParams(**rec["params"])
        assert (model.ref is not None) == (fam == "3dmatch")
    ref = EXPORT["families"]["3dmatch"]["ref_onnx"]
    assert sha256(MODELS_DIR / ref["file"]) == ref["sha256"]
    assert desc.load("3dmatch").limits == tuple(EXPORT["families"]["3dmatch"]["neighbor_limits"])


def test_shipped_models_reproduce_the_torch_reference_outputs(desc):
    """onnxruntime on fixed inputs == the torch reference's outputs recorded when the .pth was converted."""
    from descriptors.buffer.export import golden_cloud, golden_grouped

    x = golden_grouped()
    for fam, rec in EXPORT["families"].items():
        got = session(resolve_model_path(SHIPPED[fam])).run(None, {"grouped": x})[0]
        want = np.asarray(rec["golden_desc"]["outputs"], dtype=np.float32)
        assert np.abs(got - want).max() < TOL_DESC, fam
        np.testing.assert_allclose(np.linalg.norm(got, axis=1), 1.0, atol=1e-5)
    pts, normals = golden_cloud()
    model = desc.load("3dmatch")
    axis = model.ref.run(None, ref_inputs(pts, normals, model.voxel0, model.conv_radius, model.limits))[0]
    want = np.asarray(EXPORT["families"]["3dmatch"]["golden_ref"]["first_axes"])
    scale = np.linalg.norm(want, axis=1, keepdims=True)
    assert np.abs((axis[: len(want)] - want) / scale).max() < TOL_AXIS


@needs_weights
def test_published_weights_load_with_no_missing_or_unexpected_key():
    import torch

    from descriptors.buffer.nets import DescReference, RefReference, load_published

    for fam in ("3dmatch", "kitti"):
        for prefix, cls, n in (("Ref", RefReference, 141), ("Desc", DescReference, 58)):
            path = WEIGHTS / fam / f"{prefix}_best.pth"
            module = cls()
            got = load_published(module, path, prefix)
            assert got == {"missing": [], "unexpected": [], "loaded": n}, (fam, prefix)
            raw = torch.load(str(path), map_location="cpu", weights_only=True)
            key = "conv_net.ops.0.weight" if prefix == "Desc" else "encoder_blocks.0.conv.map_to_feat.weight"
            assert torch.equal(module.state_dict()[key], raw[f"{prefix}.{key}"])


@needs_weights
def test_onnx_equals_a_torch_forward_pass_of_the_published_weights(desc):
    import torch

    from descriptors.buffer.export import golden_cloud, golden_grouped, random_grouped, ref_batch_reference
    from descriptors.buffer.nets import DescReference, RefReference, load_published

    for fam in ("3dmatch", "kitti"):
        ref = DescReference()
        load_published(ref, WEIGHTS / fam / "Desc_best.pth", "Desc")
        ref.eval()
        sess = session(resolve_model_path(SHIPPED[fam]))
        for x in (golden_grouped(), random_grouped(16, BufferParams(), seed=5)):
            with torch.no_grad():
                want = ref(torch.from_numpy(x)).numpy()
            assert np.abs(sess.run(None, {"grouped": x})[0] - want).max() < TOL_DESC, fam
    net = RefReference()
    load_published(net, WEIGHTS / "3dmatch" / "Ref_best.pth", "Ref")
    net.eval()
    model = desc.load("3dmatch")
    pts, normals = golden_cloud(seed=12)  # not the cloud the recorded outputs came from
    feed = ref_inputs(pts, normals, model.voxel0, model.conv_radius, model.limits)
    with torch.no_grad():
        want = net(ref_batch_reference(feed, pts, model.voxel0, model.limits)).numpy()
    got = model.ref.run(None, feed)[0]
    unit = [a / np.linalg.norm(a, axis=1, keepdims=True) for a in (got, want)]
    assert np.abs(unit[0] - unit[1]).max() < TOL_AXIS


def brute_force_cells(aligned: np.ndarray, params: BufferParams) -> np.ndarray:
    """Upstream's sphere_query + grouping, one cell at a time (pointnet2 ball_query semantics)."""
    from descriptors.buffer.nets import cell_centres

    centres = cell_centres().astype(np.float32)
    r = np.float32(params.delta / params.rad_n)
    r2 = np.float32(r * r)
    out = np.zeros((len(aligned), params.cells, params.samples, 3), dtype=np.float32)
    for m, patch in enumerate(aligned.astype(np.float32)):
        for v, c in enumerate(centres):
            d = patch - c
            inside = np.flatnonzero(d[:, 0] * d[:, 0] + d[:, 1] * d[:, 1] + d[:, 2] * d[:, 2] < r2)[
                : params.samples
            ]
            out[m, v, : len(inside)] = np.where(inside[:, None] == 0, 0.0, patch[inside])
    return out.reshape(len(aligned), -1, 3)


def test_cell_grouping_equals_brute_force():
    rng = np.random.default_rng(0)
    params = BufferParams()
    pts = rng.normal(size=(6, 512, 3))
    pts[:3, :, 2] *= 0.1  # three flat patches, three blobs
    pts *= (rng.uniform(size=(6, 512, 1)) ** (1 / 3)) / np.linalg.norm(pts, axis=2, keepdims=True)
    pts[:, 400:] = 0.0  # padding slots hold the keypoint (the origin)
    want = brute_force_cells(pts, params)
    for fast in (False, True):  # numpy, then the C++ core's kernel (numpy again when it is not built)
        got = group_cells(pts, params, fast=fast)
        assert got.shape == (6, params.size, 3) and got.dtype == np.float32
        assert np.array_equal(got, want), fast
    assert np.array_equal(group_cells(pts, params, chunk=1, fast=False), want)


needs_core = pytest.mark.skipif(not __import__("fastmac_exp.core").core.available(), reason="no C++ core")


@needs_core
def test_cpp_patch_kernels_equal_numpy(room):
    """The C++ core's cut_patches (with and without its per-cloud index) and group_cells give numpy's patches
    and cells, bit for bit, on a room and a sparse street-like cloud (balls of a few points to many hundreds,
    keypoints off the cloud, so patches padded with the keypoint, which group_cells skips after `samples`
    copies); the index's prefix levels are exercised by small patches (k = 8, 40: several levels, balls
    that fill in the smallest prefix and balls that do not)."""
    from scipy.spatial import cKDTree

    from fastmac_exp.descriptors.buffer import _core, cut_patches, patch_index

    rng = np.random.default_rng(3)
    street = np.vstack([room * 8.0, rng.uniform(-30, 30, (3000, 3)) * [1, 1, 0.1]])
    params = BufferParams()
    for cloud, radius in ((room, 0.3), (street, 3.0)):
        cloud = cloud[rng.permutation(len(cloud))]
        kp = np.vstack([cloud[rng.choice(len(cloud), 200, replace=False)], rng.uniform(-40, 40, (10, 3))])
        tree = cKDTree(cloud)
        for k in (512, 40, 8):
            a = cut_patches(cloud, tree, kp, radius, k, fast=False)
            b = cut_patches(cloud, tree, kp, radius, k)
            index = patch_index(cloud, radius, k)
            assert index is not None and index.n == len(cloud) and (k == 512 or index.levels > 1)
            c = cut_patches(cloud, tree, kp, radius, k, index=index)
            assert np.array_equal(a, b) and np.array_equal(a, c), (radius, k)
        assert (a[:, :-1] == kp[:, None, :]).all(axis=2).any()  # some patches are padded
        aligned = (cut_patches(cloud, tree, kp, radius, 512) - kp[:, None, :]) / radius
        assert np.array_equal(group_cells(aligned, params), group_cells(aligned, params, fast=False))
    with pytest.raises(ValueError, match="another cloud"):
        _core().buffer_cut_patches(cloud[:-1], kp, radius, 512, patch_index(cloud, radius, 512))


def test_alignment_takes_the_axis_to_z():
    from scipy.spatial.transform import Rotation

    rng = np.random.default_rng(1)
    a = rng.normal(size=(50, 3))
    a /= np.linalg.norm(a, axis=1, keepdims=True)
    r = align_rotations(a)
    np.testing.assert_allclose(np.einsum("mi,mij->mj", a, r), np.tile([0.0, 0.0, 1.0], (50, 1)), atol=1e-12)
    np.testing.assert_allclose(r @ r.transpose(0, 2, 1), np.tile(np.eye(3), (50, 1, 1)), atol=1e-12)
    # Rodrigues about a x z by the angle between them (upstream RodsRotatFormula), used as offsets @ R
    c = np.cross(a, [0.0, 0.0, 1.0])
    rotvec = c / np.linalg.norm(c, axis=1, keepdims=True) * np.arccos(a[:, 2])[:, None]
    np.testing.assert_allclose(r, Rotation.from_rotvec(rotvec).as_matrix().transpose(0, 2, 1), atol=1e-12)


def cosine_stats(a: np.ndarray, b: np.ndarray) -> tuple[float, float]:
    """Mean cosine of corresponding descriptors, and how often the counterpart is the nearest one."""
    cos = np.sum(a * b, axis=1)
    return float(cos.mean()), float(np.mean(np.argmax(a @ b.T, axis=1) == np.arange(len(a))))


def test_rotation_invariance(desc, room):
    """The cloud rotated about the sensor (all grids resampled): the Ref axis keeps the descriptors
    (mean cosine ~0.97); without it (axis=none) they fall apart (~0.7)."""
    rng = np.random.default_rng(5)
    kp = voxel_down(room, 0.05)
    kp = kp[rng.choice(len(kp), 120, replace=False)]
    rot = random_rotation(np.random.default_rng(10))
    model = desc.load("3dmatch")
    a = desc.describe(model, room, kp, 1.0)
    b = desc.describe(model, room @ rot.T, kp @ rot.T, 1.0)
    cos, _ = cosine_stats(a, b)
    assert cos > 0.95, cos
    plain = BufferDescriptor(model="3dmatch", axis="none", threads=1, progress=False)
    pm = plain.load("3dmatch")
    cos_plain, _ = cosine_stats(
        plain.describe(pm, room, kp, 1.0), plain.describe(pm, room @ rot.T, kp @ rot.T, 1.0)
    )
    assert cos_plain < 0.85 and cos > cos_plain + 0.1, (cos, cos_plain)


@needs_fragment
def test_rotation_invariance_on_a_real_fragment(desc):
    """3DMatch redkitchen cloud_bin_0 rotated about its sensor: the rotated keypoint's descriptor is the
    nearest for ~94 % of 150 keypoints (a different shuffle seed, no motion: ~97 %)."""
    from fastmac_exp.io import read_points

    pts = np.asarray(read_points(FRAGMENT), dtype=np.float64)
    kp = voxel_down(pts, 0.05)
    kp = kp[np.random.default_rng(5).choice(len(kp), 150, replace=False)]
    rot = random_rotation(np.random.default_rng(21))
    model = desc.load("3dmatch")
    cos, top1 = cosine_stats(
        desc.describe(model, pts, kp, 1.0), desc.describe(model, pts @ rot.T, kp @ rot.T, 1.0)
    )
    assert cos > 0.92 and top1 > 0.85, (cos, top1)


def test_kitti_model_is_yaw_invariant(room):
    """The KITTI model keeps the LiDAR's z (as upstream): invariant to a rotation about z only."""
    desc = BufferDescriptor(model="kitti", threads=1, progress=False)
    model = desc.load("kitti")
    street = room * 6.0  # a room 6x larger: KITTI's sizes (voxel 0.3 m, patch radius 3 m)
    kp = voxel_down(street, 0.3)
    kp = kp[np.random.default_rng(6).choice(len(kp), 100, replace=False)]
    t = 0.7
    yaw = np.array([[np.cos(t), -np.sin(t), 0], [np.sin(t), np.cos(t), 0], [0, 0, 1]])
    a = desc.describe(model, street, kp, 1.0)
    cos_yaw, _ = cosine_stats(a, desc.describe(model, street @ yaw.T, kp @ yaw.T, 1.0))
    tilt = random_rotation(np.random.default_rng(3))
    cos_tilt, _ = cosine_stats(a, desc.describe(model, street @ tilt.T, kp @ tilt.T, 1.0))
    assert cos_yaw > 0.95 and cos_tilt < cos_yaw - 0.1, (cos_yaw, cos_tilt)


def test_front_end_on_a_pair(desc):
    """Correspondences for a rotated, resampled copy of a small room: labelled, capped, and far more
    inliers than chance (~1/300 here; measured ~0.5 on this scene of planes and boxes)."""
    room = toy_room(2, spacing=0.02, size=1.5) - np.array([0.75, 0.75, 1.0])
    rng = np.random.default_rng(2)
    gt = np.eye(4)
    gt[:3, :3] = random_rotation(rng)  # about the sensor, as a second scan from the same place
    tgt = room[rng.permutation(len(room))[: int(0.8 * len(room))]] @ gt[:3, :3].T
    pair = Pair(name="room", gt=gt, src_cloud=room, tgt_cloud=tgt, voxel_size=0.05, family="3dmatch")
    small = BufferDescriptor(voxel_size=0.2, max_correspondences=150, threads=1, progress=False)
    corr = small(pair, np.random.default_rng(0))
    assert isinstance(corr, Correspondences) and corr.labels is not None and len(corr) == 150
    assert corr.inlier_ratio > 0.25, corr.inlier_ratio
    assert small.name == "buffer" and small.graph_key == "spinnet"
    assert small.model_for("3dlomatch").desc_path.name == "buffer_3dmatch_desc.onnx"
    assert small.model_for("kitti").desc_path.name == "buffer_kitti_desc.onnx"
    clone = pickle.loads(pickle.dumps(small))  # joblib workers: sessions reopen after unpickling
    kp = corr.src[:8]
    np.testing.assert_array_equal(
        clone.describe(clone.load("3dmatch"), room, kp, 1.0),
        small.describe(small.load("3dmatch"), room, kp, 1.0),
    )


def test_contracts_refuse_other_models(tmp_path):
    import onnx
    from onnx import TensorProto, helper

    with pytest.raises(InputError, match="not a BUFFER descriptor model"):
        BufferModel(MODELS_DIR / "fcgf_lite.onnx", None, 1)
    x = helper.make_tensor_value_info("grouped", TensorProto.FLOAT, ["M", 100, 3])
    y = helper.make_tensor_value_info("d", TensorProto.FLOAT, ["M", 300])
    graph = helper.make_graph([helper.make_node("Flatten", ["grouped"], ["d"])], "g", [x], [y])
    model = helper.make_model(graph, opset_imports=[helper.make_opsetid("", 17)])
    helper.set_model_props(model, {"fastmac.preprocess": "buffer", "buffer.align": "none"})
    path = tmp_path / "wrong.onnx"
    onnx.save(model, str(path))
    with pytest.raises(InputError, match=r"K = 100, expected 4200"):
        BufferModel(path, None, 1)
    with pytest.raises(InputError, match="Expected one float32 input"):
        check_desc_contract(session(path), path, BufferParams())


def test_runtime_path_does_not_import_torch():
    code = (
        "import sys; import numpy as np; from fastmac_exp.descriptors.buffer import BufferDescriptor; "
        "d = BufferDescriptor(model='3dmatch', threads=1, progress=False); m = d.load('3dmatch'); "
        "rng = np.random.default_rng(0); p = rng.uniform(-1, 1, (3000, 3)) * [2, 2, 0.02] + [0, 0, -1]; "
        "d.describe(m, p, p[:20], 1.0); assert 'torch' not in sys.modules, 'torch imported'"
    )
    subprocess.run([sys.executable, "-c", code], check=True, cwd=REPO)


def test_config_and_graph_thresholds():
    from hydra import compose, initialize_config_dir
    from hydra.utils import instantiate

    from fastmac_exp.params import mac_params_for

    with initialize_config_dir(config_dir=str(REPO / "conf"), version_base="1.3"):
        cfg = compose(config_name="config", overrides=["descriptor=buffer", "descriptor.progress=false"])
    assert cfg.descriptor.graph_key == "spinnet" and cfg.descriptor.model == "auto"
    d = instantiate(cfg.descriptor)  # the node as it stands
    assert isinstance(d, BufferDescriptor) and d.max_correspondences == 5000 and d.graph_key == "spinnet"
    assert d.precision == "int8" and d.cache_clouds == 32 and d.name == "buffer_int8"  # the run's default
    assert d.model_for("kitti").desc_path.name == "buffer_kitti_desc_int8.onnx"
    f = instantiate(cfg.descriptor, precision="float32")
    assert f.model_for("kitti").desc_path.name == "buffer_kitti_desc.onnx" and f.name == "buffer"
    # spec 2.2: BUFFER's descriptor is a (mini) SpinNet: Gaussian 0.85 indoors, KITTI "any other" 0.999
    assert mac_params_for("3dmatch", "spinnet").graph.threshold == 0.85
    assert mac_params_for("3dlomatch", "spinnet").graph.threshold == 0.85
    assert mac_params_for("kitti", "spinnet").graph.threshold == 0.999


def test_sessions_do_not_spin_and_threads_give_the_same_descriptors(room):
    """The config's default is one onnxruntime thread a core; its workers must not spin (the patch thread
    beside them needs the core, docs in descriptors/buffer/MODEL_CARD.md), and the thread count must not
    change what is described (a cache or a study would otherwise depend on the machine)."""
    with initialize_config_dir(config_dir=str(REPO / "conf"), version_base="1.3"):
        for name in ("buffer", "spinnet"):
            cfg = compose(config_name="config", overrides=[f"descriptor={name}"])
            assert cfg.descriptor.threads == 0, name
    kp = room[np.random.default_rng(4).choice(len(room), 40, replace=False)]
    out = {}
    for threads in (1, 2):
        d = BufferDescriptor(threads=threads, progress=False, cache_clouds=0, precision="int8")
        model = d.load("3dmatch")
        for sess in (model.desc, model.ref):
            opts = sess.get_session_options()
            assert opts.get_session_config_entry("session.intra_op.allow_spinning") == "0"
            assert opts.intra_op_num_threads == threads
        out[threads] = d.describe(model, room, kp, 1.0)
    np.testing.assert_array_equal(out[1], out[2])


@pytest.mark.parametrize("kind", ["buffer", "spinnet"])
def test_lanes_give_the_same_descriptors_and_share_the_cores(room, kind):
    """Batches run in lanes (each thread prepares and runs its own batches) describe what one lane does, bit
    for bit; lanes auto (the config's) opens one-thread sessions on the CPU and runs one lane a core."""
    from fastmac_exp.descriptors.spinnet import SpinNetDescriptor

    make = BufferDescriptor if kind == "buffer" else SpinNetDescriptor
    with initialize_config_dir(config_dir=str(REPO / "conf"), version_base="1.3"):
        assert compose(config_name="config", overrides=[f"descriptor={kind}"]).descriptor.lanes == "auto"
    kp = room[np.random.default_rng(5).choice(len(room), 37, replace=False)]
    out = {}
    for lanes in (1, 2, 3, "auto"):
        d = make(threads=0, lanes=lanes, batch_size=4, progress=False, cache_clouds=0, precision="int8")
        model = d.load("3dmatch")
        want_threads = 0 if lanes == 1 else 1
        assert model.desc.get_session_options().intra_op_num_threads == want_threads, lanes
        if model.ref is not None:  # run once a cloud, outside the lanes: one thread a core
            assert model.ref.get_session_options().intra_op_num_threads == 0
        out[lanes] = d.describe(model, room, kp, 1.0)
        assert d.last_timings.get("lanes", 1) == d.lanes_for(model)
    assert make(threads=0, progress=False).lanes_for(model) == len(os.sched_getaffinity(0))
    assert make(threads=1, progress=False).lanes_for(model) == 1  # a set thread count is kept to
    for lanes in (2, 3, "auto"):
        np.testing.assert_array_equal(out[lanes], out[1])


def test_a_failing_lane_stops_the_others(room, monkeypatch):
    """An error in one batch ends the describe with that error; the other lanes stop after their batch
    instead of describing the rest of the cloud."""
    d = BufferDescriptor(threads=1, lanes=2, batch_size=2, progress=False, cache_clouds=0, precision="int8")
    model = d.load("3dmatch")
    calls = []
    real = BufferDescriptor._model_input

    def failing(self, model, state, k, how, axes):
        calls.append(len(calls))
        if len(calls) == 3:
            raise InputError("batch 3 is bad")
        if len(calls) > 3:  # the other lane, after the failure: slow, so that stopping it shows
            time.sleep(0.2)
        return real(self, model, state, k, how, axes)

    monkeypatch.setattr(BufferDescriptor, "_model_input", failing)
    kp = room[np.random.default_rng(6).choice(len(room), 40, replace=False)]
    with pytest.raises(InputError, match="batch 3 is bad"):
        d.describe(model, room, kp, 1.0)
    assert len(calls) <= 6  # of 20 batches (the rest would take the other lane 3 s)


def test_lanes_must_be_auto_or_a_positive_count():
    for bad in (0, -1, 1.5, "two", True):
        with pytest.raises(InputError, match="lanes"):
            BufferDescriptor(lanes=bad, progress=False)


GOLDEN = REPO / "tests" / "data" / "buffer_golden.npz"


def golden_pair(family: str) -> Pair:
    """The generated pair whose BUFFER output before the speed work (commit 6333dc0) is frozen in GOLDEN."""
    room = toy_room(2, spacing=0.02, size=1.5) - np.array([0.75, 0.75, 1.0])
    rng = np.random.default_rng(2)
    gt = np.eye(4)
    gt[:3, :3] = random_rotation(rng)
    tgt = room[rng.permutation(len(room))[: int(0.8 * len(room))]] @ gt[:3, :3].T
    return Pair(name="room", gt=gt, src_cloud=room, tgt_cloud=tgt, voxel_size=0.05, family=family)


@pytest.mark.parametrize("family,scale", [("3dmatch", None), ("kitti", 0.1)])
def test_same_output_as_before_the_speed_work(family, scale):
    """Describing only the kept source keypoints, and the cloud cache, change nothing: the correspondences
    and descriptors equal those the code computed before (describing every keypoint of both clouds)."""
    gold = np.load(GOLDEN)
    pair = golden_pair(family)
    d = BufferDescriptor(voxel_size=0.08, max_correspondences=300, threads=1, progress=False, scale=scale)
    corr = d(pair, np.random.default_rng(0))
    src_log, tgt_log = d.timings_log
    assert (src_log["keypoints"], tgt_log["keypoints"]) == (300, 1837)  # 300 of the 1,538 source keypoints
    # the same rows: the generated target cloud itself differs in its last bits under another BLAS kernel
    # (CI's second pass, OPENBLAS_CORETYPE=Prescott), hence a tolerance far below any point spacing
    np.testing.assert_allclose(corr.src, gold[f"{family}_src"], rtol=0, atol=1e-12)
    np.testing.assert_allclose(corr.tgt, gold[f"{family}_tgt"], rtol=0, atol=1e-12)
    np.testing.assert_allclose(corr.scores, gold[f"{family}_scores"], atol=1e-4)
    s = 1.0 if scale is None else scale
    for side, cloud in (("src", pair.src_cloud), ("tgt", pair.tgt_cloud)):
        _, f = d.features(cloud, 0.08, family=family, scale=s)
        got, want = f[gold[f"{family}_{side}_rows"]], gold[f"{family}_{side}_desc"]
        # to 1e-4 row by row; under another BLAS kernel (CI's OPENBLAS_CORETYPE=Prescott pass) the frozen
        # cloud moves in its last bits and a keypoint near a cell border may move by ~2e-4, never more than
        # 1e-3 (a wrong descriptor is off by ~0.1)
        off = np.abs(got - want).max(axis=1)
        assert np.mean(off > 1e-4) <= 0.01 and off.max() < 1e-3, (np.mean(off > 1e-4), off.max())
    assert d.timings_log[-1]["keypoints"] == 0  # the target was described whole by the pair: all reused


def test_cache_describes_a_shared_cloud_once(room):
    """A cloud described once is not described again; a smaller cache forgets, and cache_clouds=0 keeps
    nothing; the descriptors are the same either way."""
    d = BufferDescriptor(threads=1, progress=False, cache_clouds=1)
    model = d.load("3dmatch")
    kp = voxel_down(room, 0.2)
    a = d.describe(model, room, kp, 1.0, rows=np.arange(10))
    assert d.last_timings["keypoints"] == 10
    b = d.describe(model, room, kp, 1.0)
    assert (d.last_timings["keypoints"], d.last_timings["reused"]) == (len(kp) - 10, 10)
    np.testing.assert_array_equal(a, b[:10])
    d.describe(model, room + 0.01, kp + 0.01, 1.0)  # another cloud evicts the first (cache of 1)
    c = d.describe(model, room, kp, 1.0)
    assert d.last_timings["keypoints"] == len(kp)
    np.testing.assert_allclose(b, c, atol=1e-6)
    none = BufferDescriptor(threads=1, progress=False, cache_clouds=0)
    none.describe(none.load("3dmatch"), room, kp, 1.0)
    none.describe(none.load("3dmatch"), room, kp, 1.0)
    assert none.last_timings["keypoints"] == len(kp) and not none._described
    with pytest.raises(InputError):
        BufferDescriptor(cache_clouds=-1)


class CountingSession:
    """An onnxruntime session that counts its runs (how many times the network ran)."""

    def __init__(self, session) -> None:
        self.session, self.runs = session, 0

    def run(self, *args, **kwargs):
        self.runs += 1
        return self.session.run(*args, **kwargs)

    def __getattr__(self, name):
        return getattr(self.session, name)


def counted(d, which: str = "3dmatch") -> CountingSession:
    model = d.load(which)
    model.desc = CountingSession(model.desc)
    return model.desc


def test_instances_share_described_clouds():
    """A sweep's members are new instances in one process: a second instance describing the same pair runs
    no network and gives the same correspondences; the run's seed still draws the cap (some other source
    rows described, as a cold describer gives them); another descriptor seed or other points describe
    again."""
    pair = golden_pair("3dmatch")

    def make(**kw):
        return BufferDescriptor(voxel_size=0.2, max_correspondences=60, threads=1, progress=False, **kw)

    first = make()
    a = first(pair, np.random.default_rng(0))
    second = make()
    runs = counted(second)
    b = second(pair, np.random.default_rng(0))
    assert runs.runs == 0 and [t["keypoints"] for t in second.timings_log] == [0, 0]
    for x, y in ((a.src, b.src), (a.tgt, b.tgt), (a.scores, b.scores)):
        np.testing.assert_array_equal(x, y)
    c = second(pair, np.random.default_rng(1))  # another cap: the target reused, new source rows described
    assert runs.runs > 0 and second.timings_log[-1]["keypoints"] == 0
    forget_described_clouds()
    cold = make()(pair, np.random.default_rng(1))
    np.testing.assert_array_equal(c.src, cold.src)
    np.testing.assert_array_equal(c.tgt, cold.tgt)
    np.testing.assert_allclose(c.scores, cold.scores, atol=1e-6)
    other_seed = make(seed=1)  # its own shuffles: described again
    runs = counted(other_seed)
    other_seed(pair, np.random.default_rng(1))
    assert runs.runs > 0 and other_seed.timings_log[-1]["keypoints"] > 0
    moved = Pair(name="moved", gt=pair.gt, src_cloud=pair.src_cloud + 0.01, tgt_cloud=pair.tgt_cloud + 0.01,
                 voxel_size=pair.voxel_size, family=pair.family)  # fmt: skip
    again = make()
    runs = counted(again)
    again(moved, np.random.default_rng(1))
    assert runs.runs > 0 and again.timings_log[-1]["keypoints"] > 0
    none = make(cache_clouds=0)  # keeps nothing, and reads nothing the others keep
    runs = counted(none)
    none(pair, np.random.default_rng(1))
    assert runs.runs > 0 and not none._described


def test_mutual_matching_describes_every_keypoint():
    pair = golden_pair("3dmatch")
    d = BufferDescriptor(voxel_size=0.2, max_correspondences=20, mutual=True, threads=1, progress=False)
    corr = d(pair, np.random.default_rng(0))
    n_src = len(voxel_down(pair.src_cloud, 0.2))
    assert d.timings_log[0]["keypoints"] == n_src and len(corr) <= 20


QUANT = json.loads((REPO / "descriptors" / "buffer" / "quantize.json").read_text())


def test_int8_models_are_the_recorded_quantisation_of_the_shipped_models():
    from fastmac_exp.descriptors.buffer import SHIPPED_INT8

    q = BufferDescriptor(threads=1, progress=False, precision="int8")
    for fam, rec in QUANT["families"].items():
        path = resolve_model_path(SHIPPED_INT8[fam])
        assert sha256(path) == rec["int8_sha256"] and path.stat().st_size < 1e6, fam
        assert sha256(resolve_model_path(SHIPPED[fam])) == rec["float_sha256"], fam
        model = q.load(fam)
        assert model.desc_path == path and model.metadata["fastmac.precision"] == "int8"
        assert model.metadata["fastmac.quantized_from_sha256"] == rec["float_sha256"]
        assert model.params == BufferDescriptor(progress=False).load(fam).params
        assert "QLinearConv" in {n.op_type for n in __import__("onnx").load(str(path)).graph.node}
    assert q.name == "buffer_int8" and BufferDescriptor(progress=False).name == "buffer"


def test_int8_models_keep_the_convolutions_in_uint8():
    """The shipped int8 models went through fuse_requantize: between the convolutions no float32 chain
    (DequantizeLinear -> Relu -> padding -> QuantizeLinear) is left, only the uint8 padding."""
    from fastmac_exp.descriptors.buffer import SHIPPED_INT8

    onnx = pytest.importorskip("onnx")
    for fam, rec in QUANT["families"].items():
        graph = onnx.load(str(resolve_model_path(SHIPPED_INT8[fam]))).graph
        ops = [n.op_type for n in graph.node]
        assert ops.count("QLinearConv") == 10 and ops.count("QuantizeLinear") == 1, (fam, ops)
        assert ops.count("DequantizeLinear") == 2 and ops.count("Relu") == 2, (fam, ops)  # the tail only
        assert rec["fused_chains"] == 9 and rec["int8_unfused_sha256"] != rec["int8_sha256"]


def test_fuse_requantize_keeps_what_the_network_computes(tmp_path):
    """fuse_requantize on a small quantised network of the same shape (conv -> relu -> circular padding ->
    conv -> relu -> 1x1 conv): the chains go, the outputs stay those of the unfused int8 model within a
    quantisation step and as close to float32, and a chain whose QuantizeLinear has a zero point is kept."""
    onnx = pytest.importorskip("onnx")
    ort = pytest.importorskip("onnxruntime")
    from onnx import TensorProto, helper, numpy_helper
    from onnxruntime.quantization import CalibrationDataReader, QuantFormat, QuantType, quantize_static

    from descriptors.buffer.quantize import fuse_requantize

    rng = np.random.default_rng(0)
    init = [
        numpy_helper.from_array(rng.normal(0, 0.3, (8, 4, 3, 3)).astype(np.float32), "w0"),
        numpy_helper.from_array(rng.normal(0, 0.3, (8, 8, 3, 3)).astype(np.float32), "w1"),
        numpy_helper.from_array(rng.normal(0, 0.3, (2, 8, 1, 1)).astype(np.float32), "w2"),
        numpy_helper.from_array(np.array([-1], np.int64), "m1"),
        numpy_helper.from_array(np.array([1], np.int64), "p1"),
        numpy_helper.from_array(np.array([0], np.int64), "z"),
        numpy_helper.from_array(np.array([3], np.int64), "ax"),
        numpy_helper.from_array(np.array([2**62], np.int64), "big"),
    ]
    nodes = []

    def pad(x, name):  # upstream's circular padding of the azimuth (the last axis)
        nodes.extend(
            [
                helper.make_node("Slice", [x, "m1", "big", "ax"], [name + "_l"]),
                helper.make_node("Slice", [x, "z", "p1", "ax"], [name + "_r"]),
                helper.make_node("Concat", [name + "_l", x, name + "_r"], [name], axis=3),
            ]
        )
        return name

    conv = dict(kernel_shape=[3, 3], pads=[1, 0, 1, 0])
    nodes.append(helper.make_node("Conv", [pad("x", "x_p"), "w0"], ["c0"], **conv))
    nodes.append(helper.make_node("Relu", ["c0"], ["r0"]))
    nodes.append(helper.make_node("Conv", [pad("r0", "r0_p"), "w1"], ["c1"], **conv))
    nodes.append(helper.make_node("Relu", ["c1"], ["r1"]))
    nodes.append(helper.make_node("Conv", ["r1", "w2"], ["y"]))
    graph = helper.make_graph(
        nodes,
        "toy",
        [helper.make_tensor_value_info("x", TensorProto.FLOAT, ["M", 4, 5, 12])],
        [helper.make_tensor_value_info("y", TensorProto.FLOAT, ["M", 2, 5, 12])],
        init,
    )
    model = helper.make_model(graph, opset_imports=[helper.make_opsetid("", 17)])
    model.ir_version = 8
    src, q = tmp_path / "f.onnx", tmp_path / "q.onnx"
    onnx.save(model, str(src))
    data = np.abs(rng.normal(0, 1, (64, 4, 5, 12))).astype(np.float32)

    class Reader(CalibrationDataReader):
        def __init__(self) -> None:
            self.done = False

        def get_next(self):
            if self.done:
                return None
            self.done = True
            return {"x": data}

    quantize_static(
        str(src), str(q), Reader(), quant_format=QuantFormat.QOperator, op_types_to_quantize=["Conv"],
        per_channel=True, activation_type=QuantType.QUInt8, weight_type=QuantType.QInt8,
    )  # fmt: skip
    unfused = onnx.load(str(q))
    fused = onnx.load(str(q))
    assert fuse_requantize(fused) == 3  # two conv -> relu -> pad -> conv chains and the input's padding
    onnx.checker.check_model(fused)
    ops = [n.op_type for n in fused.graph.node]
    assert "Relu" not in ops and ops.count("QuantizeLinear") == 1 and ops.count("DequantizeLinear") == 1, ops

    def run(m):
        return ort.InferenceSession(m.SerializeToString(), providers=["CPUExecutionProvider"]).run(
            None, {"x": data}
        )[0]

    want, a, b = run(model), run(unfused), run(fused)
    scale = np.abs(want).max()
    assert np.abs(b - a).max() < 0.1 * scale and not np.array_equal(a, b)  # requantised once, not twice
    assert np.abs(b - want).mean() <= 1.05 * np.abs(a - want).mean(), (
        np.abs(b - want).mean(),
        np.abs(a - want).mean(),
    )
    # a QuantizeLinear with a non-zero zero point (not after a Relu's output) is not fused
    zp = next(t for t in unfused.graph.initializer if t.name.endswith("zero_point") and "r0" in t.name)
    zp.CopyFrom(numpy_helper.from_array(np.array(3, np.uint8), zp.name))
    assert fuse_requantize(unfused) == 2


def test_int8_descriptors_stay_close_to_float32(room):
    """Quantised descriptors point the same way as the float32 ones (measured mean cosine 0.998 on real
    indoor keypoints, descriptors/buffer/quantize.json) and keep the rotation invariance."""
    kp = voxel_down(room, 0.15)
    fl = BufferDescriptor(threads=1, progress=False)
    q = BufferDescriptor(threads=1, progress=False, precision="int8")
    a = fl.describe(fl.load("3dmatch"), room, kp, 1.0)
    b = q.describe(q.load("3dmatch"), room, kp, 1.0)
    mean, nearest = cosine_stats(a, b)  # measured 0.997 and 0.71 (the room's plane patches look alike)
    assert mean > 0.99 and nearest > 0.6, (mean, nearest)
    assert np.abs(a - b).max() > 1e-4  # it is another model, not the float one under a new name
    rot = random_rotation(np.random.default_rng(5))
    mean_rot, _ = cosine_stats(b, q.describe(q.load("3dmatch"), room @ rot.T, kp @ rot.T, 1.0))
    assert mean_rot > 0.95, mean_rot


def test_precision_is_checked():
    with pytest.raises(InputError, match="precision"):
        BufferDescriptor(precision="fp16")
    wrong = BufferDescriptor(precision="int8", model_3dmatch_int8=SHIPPED["3dmatch"], progress=False)
    with pytest.raises(InputError, match="float32"):
        wrong.load("3dmatch")
    with pytest.raises(InputError, match="descriptors/buffer/quantize.py"):
        BufferDescriptor(precision="int8", model_kitti_int8="nowhere_int8.onnx").load("kitti")
