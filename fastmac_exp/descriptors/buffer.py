"""BUFFER's learned descriptor (Ao et al., CVPR 2023) through onnxruntime: `descriptor=buffer`.

The published 3DMatch and KITTI weights, converted by `descriptors/buffer/export.py` into
`fastmac_exp/models/buffer_<family>_desc.onnx` (+ `buffer_3dmatch_ref.onnx`); model card
`descriptors/buffer/MODEL_CARD.md`. Runtime: numpy/scipy/Open3D preprocessing + onnxruntime (CPU);
torch is never imported here.

Describing the keypoints of one cloud (lengths are BUFFER's, in metres, times `scale`; `scale` = the pair's
voxel size / the model's reference voxel (0.05 m for the 3DMatch model, 0.3 m for KITTI), i.e. 1 on the
real indoor and LiDAR pairs):

1. keypoints: the cloud voxel-downsampled at the pair's voxel (Open3D, exactly FPFH's keypoints);
2. the patch cloud: the cloud voxel-downsampled at `downsample` (0.02 / 0.05 m), shuffled (seeded);
3. reference axis (3DMatch model, `align = ref`): the patch cloud downsampled again at `voxel_size_0`
   (0.035 m), shuffled, at most `max_points`; Open3D normals (30 nearest points) oriented towards the
   origin; KPConv-style grids (barycentres on absolute grids of 0.07 and 0.14 m) and radius
   neighbourhoods (0.07, 0.14, 0.28 m, nearest first, truncated to the calibrated limits K_l, shadow
   index = the support count) -> the `Ref` ONNX model -> one axis a point, normalised and flipped so
   that axis . p <= 0 (towards the sensor at the origin, as upstream); each keypoint takes the axis of
   its nearest Ref point, re-oriented at the keypoint. The KITTI model (`align = none`) keeps the
   sensor's z axis, as upstream does for KITTI;
4. patch: the first `patch_points - 1` (511) points of the shuffled patch cloud within `des_r` (0.3 /
   3.0 m) of the keypoint, padded with the keypoint, the keypoint in the last slot (pointnet2
   ball_query semantics on a shuffled cloud = a uniform random subset of the ball);
5. alignment: offsets from the keypoint rotated by the Rodrigues rotation taking the axis to +z
   (upstream's RodsRotatFormula), divided by `des_r`;
6. cells (`group_cells`): 3 radial x 7 elevation x 20 azimuth cell centres; each cell takes the first 10
   patch points (in slot order) within 0.8 / 3 of its centre; empty slots are 0 and so is patch slot 0
   (upstream's sphere_query masks the index 0); -> the `Desc` ONNX model -> 32-D unit vectors.

Model contracts (checked when a model is opened; a mismatch raises InputError naming what was
expected and what was found):

- Desc: one float32 input of rank 3, `(M, 4200, 3)` with M dynamic (cells x 10 points x xyz), one
  float32 output of rank 2, `(M, D)`; metadata `fastmac.preprocess = buffer` and the `buffer.*` keys of
  `BufferParams`. Any model with this contract plugs in (`descriptor.model=path/to/desc.onnx`).
- Ref: inputs `normals (N0, 3)`, `points0..2 (N_l, 3)` float32 and `neighbors0..2`, `pools0..1` (rank 2),
  `upsamples0..1` (rank 1) int64; one float32 output `(N0, 3)`; metadata `buffer.neighbor_limits`,
  `buffer.conv_radius`, `buffer.voxel_size_0`.
"""

from __future__ import annotations

import hashlib
import logging
import threading
import time
from collections import OrderedDict
from concurrent.futures import ThreadPoolExecutor
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np
from scipy.spatial import cKDTree

from fastmac_exp.cpus import available_cores
from fastmac_exp.descriptors.base import FeatureDescriptor
from fastmac_exp.descriptors.keypoints import spread_rows
from fastmac_exp.descriptors.matching import (
    capped_rows,
    correspondences_from_chosen_keypoints,
    correspondences_from_kept_sources,
    match_descriptors,
)
from fastmac_exp.descriptors.onnx_descriptor import open_session, resolve_model_path
from fastmac_exp.descriptors.patches import MIN_POINTS, CylinderGrid, keypoints, voxel_down
from fastmac_exp.descriptors.progress import keypoint_bar
from fastmac_exp.errors import InputError
from fastmac_exp.families import FAMILIES
from fastmac_exp.interrupts import block_interrupts, interrupts_blocked
from fastmac_exp.types import Correspondences, Pair

log = logging.getLogger(__name__)

SHIPPED = {
    "3dmatch": "models/buffer_3dmatch_desc.onnx",  # relative to the package (fastmac_exp/models/)
    "kitti": "models/buffer_kitti_desc.onnx",
}
SHIPPED_INT8 = {  # descriptors/buffer/quantize.py
    "3dmatch": "models/buffer_3dmatch_desc_int8.onnx",
    "kitti": "models/buffer_kitti_desc_int8.onnx",
}
PRECISIONS = ("float32", "int8")
KEYPOINT_CHOICES = ("auto", "spread", "random")
# match_keypoints=auto / keypoint_choice=auto, per model: the smallest count (of 1,000-5,000) from which on
# the mutual matches kept the mean inlier ratio and the RR of every-target matching on pairs never reported
# (descriptors/buffer/matched.py --tune, record descriptors/buffer/matched_tune.json): indoors synthetic
# 3dmatch and 3dlomatch pairs (seed 3000), where a spread subset held at every count and a random one did
# not; outdoors the real scans kitti00_5_to_0 and kitti00_15_to_0 (the synthetic scans, 11k keypoints where
# a real one has 17k, kept their IR at far fewer): only 5,000 held there, a random subset ahead of a spread
# one, which spends a LiDAR scan's keypoints on its sparse periphery (SpinNet found the same)
MATCH_KEYPOINTS = {"3dmatch": (1000, "spread"), "kitti": (5000, "random")}
REF_INPUTS = (
    ("normals", "tensor(float)", 2),
    ("points0", "tensor(float)", 2),
    ("points1", "tensor(float)", 2),
    ("points2", "tensor(float)", 2),
    ("neighbors0", "tensor(int64)", 2),
    ("neighbors1", "tensor(int64)", 2),
    ("neighbors2", "tensor(int64)", 2),
    ("pools0", "tensor(int64)", 2),
    ("pools1", "tensor(int64)", 2),
    ("upsamples0", "tensor(int64)", 1),
    ("upsamples1", "tensor(int64)", 1),
)


@dataclass(frozen=True)
class BufferParams(CylinderGrid):
    """BUFFER's preprocessing (upstream ThreeDMatch/config.py, KITTI/config.py); lengths in metres at
    scale 1. Stored as `buffer.<field>` metadata in the Desc model."""

    metadata_prefix = "buffer"

    family: str = "3dmatch"
    align: str = "ref"  # "ref": Ref-network axis -> +z | "none": keep the sensor frame (KITTI)
    reference_voxel: float = 0.05  # the pair voxel size at which the published sizes apply
    downsample: float = 0.02
    voxel_size_0: float = 0.035
    max_points: int = 30000
    des_r: float = 0.3
    patch_points: int = 512
    rad_n: int = 3
    ele_n: int = 7
    azi_n: int = 20
    delta: float = 0.8
    samples: int = 10
    ref_model: str = ""  # the Ref model file, relative to the Desc model's folder (align = ref)

    def __post_init__(self) -> None:
        if self.align not in ("ref", "none"):
            raise InputError(f"buffer.align must be 'ref' or 'none', got {self.align!r}")
        lengths = (self.reference_voxel, self.downsample, self.voxel_size_0, self.des_r, self.delta)
        if not all(v > 0 for v in lengths):
            raise InputError(f"BUFFER lengths must be positive, got {lengths}")
        if min(self.patch_points, self.rad_n, self.ele_n, self.azi_n, self.samples, self.max_points) < 1:
            raise InputError("BUFFER counts must be positive")


# ----------------------------------------------------------------------------------------------------
# geometry (numpy / scipy / Open3D)


def grid_subsample(points: np.ndarray, dl: float) -> np.ndarray:
    """KPConv's grid subsampling: the barycentre of the points in each cell of an absolute grid of
    size `dl` (cells [k dl, (k+1) dl)); order of the cells is not significant."""
    pts = np.asarray(points, dtype=np.float64)
    origin = np.floor(pts.min(axis=0) / dl) * dl
    ijk = np.floor((pts - origin) / dl).astype(np.int64)
    dims = ijk.max(axis=0) + 1
    key = (ijk[:, 0] * dims[1] + ijk[:, 1]) * dims[2] + ijk[:, 2]
    _, inv, counts = np.unique(key, return_inverse=True, return_counts=True)
    out = np.stack([np.bincount(inv, weights=pts[:, k], minlength=len(counts)) for k in range(3)], axis=1)
    return out / counts[:, None]


def radius_neighbors(queries: np.ndarray, supports: np.ndarray, radius: float, limit: int) -> np.ndarray:
    """KPConv's neighbour matrix: per query the supports within `radius`, nearest first, at most `limit`;
    width = min(limit, the largest count); missing slots hold len(supports) (the shadow index)."""
    tree = cKDTree(supports)
    k = max(1, min(int(limit), len(supports)))
    _, idx = tree.query(queries, k=k, distance_upper_bound=radius)
    idx = idx.reshape(len(queries), k).astype(np.int64)
    width = int((idx < len(supports)).sum(axis=1).max()) if len(idx) else 1
    return np.ascontiguousarray(idx[:, : max(1, min(width, k))])


def oriented_normals(points: np.ndarray) -> np.ndarray:
    """Open3D normals (30 nearest points, Open3D's default) oriented towards the origin (the sensor)."""
    from fastmac_exp._open3d import o3d

    pcd = o3d.geometry.PointCloud(o3d.utility.Vector3dVector(np.ascontiguousarray(points, dtype=np.float64)))
    pcd.estimate_normals()
    pcd.orient_normals_towards_camera_location(np.zeros(3))
    return np.asarray(pcd.normals, dtype=np.float64)


def ref_inputs(points: np.ndarray, normals: np.ndarray, voxel0: float, conv_radius: float, limits) -> dict:
    """The Ref model's inputs for one cloud (its finest layer = `points`)."""
    r0 = voxel0 * conv_radius
    p = [np.asarray(points, dtype=np.float64)]
    p.append(grid_subsample(p[0], 2 * r0 / conv_radius))
    p.append(grid_subsample(p[1], 4 * r0 / conv_radius))
    r = [r0, 2 * r0, 4 * r0]
    feed = {"normals": np.ascontiguousarray(normals, dtype=np.float32)}
    for layer in range(3):
        feed[f"points{layer}"] = p[layer].astype(np.float32)
        feed[f"neighbors{layer}"] = radius_neighbors(p[layer], p[layer], r[layer], limits[layer])
    for layer in range(2):
        feed[f"pools{layer}"] = radius_neighbors(p[layer + 1], p[layer], r[layer], limits[layer])
        feed[f"upsamples{layer}"] = np.ascontiguousarray(
            radius_neighbors(p[layer], p[layer + 1], 2 * r[layer], limits[layer])[:, 0]
        )
    return feed


def align_rotations(axes: np.ndarray) -> np.ndarray:
    """(M, 3, 3) matrices R with `offsets @ R` = offsets rotated so that each unit axis becomes +z
    (upstream RodsRotatFormula(axis, z) and `delta_x @ R`). An axis exactly on -z stays unrotated, as
    upstream; the arccos argument is clipped to [-1, 1] (upstream would give NaN for |a_z| > 1 by
    rounding)."""
    a = np.asarray(axes, dtype=np.float64)
    c = np.stack([a[:, 1], -a[:, 0], np.zeros(len(a))], axis=1)  # a x z
    theta = np.arccos(np.clip(a[:, 2] / np.maximum(np.linalg.norm(a, axis=1), 1e-12), -1.0, 1.0))
    c /= np.maximum(np.linalg.norm(c, axis=1, keepdims=True), 1e-12)
    k = np.zeros((len(a), 3, 3))
    k[:, 0, 1], k[:, 0, 2] = -c[:, 2], c[:, 1]
    k[:, 1, 0], k[:, 1, 2] = c[:, 2], -c[:, 0]
    k[:, 2, 0], k[:, 2, 1] = -c[:, 1], c[:, 0]
    eye = np.eye(3)[None]
    r = eye + np.sin(theta)[:, None, None] * k + (1 - np.cos(theta))[:, None, None] * (k @ k)
    return r.transpose(0, 2, 1)


def pca_axes(offsets: np.ndarray, centres: np.ndarray) -> np.ndarray:
    """Upstream's axis when no Ref axis is given (cal_Z_axis): the least singular vector of the patch's
    uncentred scatter about the keypoint, flipped so that axis . keypoint <= 0. (M, 3)."""
    cov = np.einsum("mki,mkj->mij", offsets, offsets)
    _, vecs = np.linalg.eigh(cov)
    z = vecs[:, :, 0]
    flip = np.einsum("ij,ij->i", z, centres) > 0
    z[flip] *= -1
    return z


def _core():
    """The C++ core when it is built (its patch kernels), else None (the numpy versions run)."""
    from fastmac_exp import core

    return core.core() if core.available() else None


def cut_patches(
    cloud: np.ndarray,
    tree: cKDTree,
    keypoints: np.ndarray,
    radius: float,
    k: int,
    workers: int = 1,
    fast=True,
    index=None,
):
    """`(M, k, 3)` patches: the first k-1 points (in `cloud` order) within `radius` of each keypoint,
    padded with the keypoint, the keypoint itself in the last slot. `fast`: the C++ core's kernel when it is
    built (the same patches, ~10x faster on LiDAR scans, whose balls hold thousands of points); `index`:
    its grid over `cloud` from `patch_index` (built once per cloud instead of once per call)."""
    core = _core() if fast else None
    if core is not None:
        try:
            return core.buffer_cut_patches(
                np.ascontiguousarray(cloud, dtype=np.float64),
                np.ascontiguousarray(keypoints, dtype=np.float64),
                float(radius),
                int(k),
                index,
            )
        except ValueError:  # a cloud spanning more than 2^20 radii: the k-d tree below handles it
            pass
    lists = tree.query_ball_point(keypoints, radius, return_sorted=True, workers=workers)
    out = np.repeat(np.asarray(keypoints, dtype=np.float64)[:, None, :], k, axis=1)
    for i, nb in enumerate(lists):
        n = min(len(nb), k - 1)
        if n:
            out[i, :n] = cloud[nb[:n]]
    return out


def patch_index(cloud: np.ndarray, radius: float, k: int):
    """The C++ core's grid for `cut_patches(cloud, ..., radius, k, index=...)`, or None (no core, or a cloud
    it cannot grid: cut_patches then takes its other paths). Prefixes of the cloud sorted by cell, so that a
    dense ball reads a few thousand points of a small prefix (the first k-1 hits in index order all lie in
    it) instead of every point of its 27 cells; the patches are the same."""
    core = _core()
    if core is None:
        return None
    try:
        return core.buffer_patch_index(np.ascontiguousarray(cloud, dtype=np.float64), float(radius), int(k))
    except ValueError:
        return None


class CellTable:
    """Candidate cells for `group_cells`: for each voxel of a G^3 grid over [-1, 1]^3, the cells whose
    ball (radius r around its centre) meets the voxel, as CSR arrays (exact test afterwards)."""

    def __init__(self, centres: np.ndarray, radius: float, grid: int = 48) -> None:
        self.g, self.h = grid, 2.0 / grid
        margin = radius + 1e-5
        keys, cells = [], []
        for v, c in enumerate(centres):
            lo = np.clip(np.floor((c - margin + 1) / self.h).astype(int), 0, grid - 1)
            hi = np.clip(np.floor((c + margin + 1) / self.h).astype(int), 0, grid - 1)
            ax = [np.arange(lo[d], hi[d] + 1) for d in range(3)]
            ijk = np.stack(np.meshgrid(*ax, indexing="ij"), -1).reshape(-1, 3)
            box_lo = ijk * self.h - 1
            near = np.clip(c, box_lo, box_lo + self.h)
            ok = ((near - c) ** 2).sum(axis=1) < margin * margin
            ijk = ijk[ok]
            keys.append((ijk[:, 0] * grid + ijk[:, 1]) * grid + ijk[:, 2])
            cells.append(np.full(len(ijk), v, dtype=np.int16))
        key = np.concatenate(keys)
        cell = np.concatenate(cells)
        order = np.argsort(key, kind="stable")  # cells ascending within a voxel
        self.cells = cell[order]
        self.ptr = np.zeros(grid**3 + 1, dtype=np.int64)
        np.cumsum(np.bincount(key, minlength=grid**3), out=self.ptr[1:])


_TABLES: dict[tuple, tuple[np.ndarray, CellTable]] = {}
_TABLES_LOCK = threading.Lock()


def cell_geometry(params: BufferParams) -> tuple[np.ndarray, np.float32, CellTable]:
    """Cell centres (float32, unit radius), the squared cell radius (float32) and the candidate table."""
    key = (params.rad_n, params.ele_n, params.azi_n, params.delta)
    with _TABLES_LOCK:
        if key not in _TABLES:
            beta = np.linspace(0, np.pi, params.ele_n, endpoint=False) + np.pi / params.ele_n / 2
            alpha = np.linspace(0, 2 * np.pi, params.azi_n, endpoint=False) + np.pi / params.azi_n
            b, a = np.meshgrid(beta, alpha, indexing="ij")
            unit = np.stack([np.sin(b) * np.cos(a), np.sin(b) * np.sin(a), np.cos(b)], -1).reshape(-1, 3)
            shells = np.arange(params.rad_n) / params.rad_n + 1 / (2 * params.rad_n)
            centres = (shells[:, None, None] * unit[None]).reshape(-1, 3).astype(np.float32)
            radius = float(np.float32(params.delta / params.rad_n))
            _TABLES[key] = (centres, CellTable(centres.astype(np.float64), radius))
        centres, table = _TABLES[key]
    r = np.float32(params.delta / params.rad_n)
    return centres, np.float32(r * r), table


def group_cells(aligned: np.ndarray, params: BufferParams, chunk: int = 96, fast=True) -> np.ndarray:
    """Upstream's sphere_query on aligned patches `(M, P, 3)` (units of des_r) -> `(M, cells * samples, 3)`
    float32: per cell (radial-major, then elevation, azimuth) the first `samples` patch points in slot
    order whose squared distance to the cell centre is below (delta / rad_n)^2 (float32, as the CUDA
    kernel), empty slots 0, patch slot 0 contributing 0 (upstream masks index 0). `fast`: the C++ core's
    kernel when it is built (the same cells, one pass per keypoint instead of numpy's sort)."""
    centres, r2, table = cell_geometry(params)
    m_all, p_n = aligned.shape[:2]
    ncell, ns = params.cells, params.samples
    if m_all == 0:
        return np.zeros((0, ncell * ns, 3), dtype=np.float32)
    core = _core() if fast else None
    if core is not None:
        return core.buffer_group_cells(
            np.ascontiguousarray(aligned, dtype=np.float32),
            centres,
            float(r2),
            table.ptr,
            table.cells,
            table.g,
            float(np.float32(1.0 / table.h)),
            ns,
        )
    if chunk * ncell >= 65536:
        chunk = max(1, 65535 // ncell)
    pts = np.ascontiguousarray(aligned, dtype=np.float32)
    values = pts.copy()
    values[:, 0] = 0.0
    out = np.zeros((m_all, ncell, ns, 3), dtype=np.float32)
    cx, cy, cz = (np.ascontiguousarray(centres[:, d]) for d in range(3))
    g, inv_h = table.g, np.float32(1.0 / table.h)
    for s in range(0, m_all, chunk):
        p = pts[s : s + chunk].reshape(-1, 3)
        n = len(p)
        ijk = ((p + np.float32(1.0)) * inv_h).astype(np.int32)
        np.clip(ijk, 0, g - 1, out=ijk)
        cid = (ijk[:, 0] * g + ijk[:, 1]) * g + ijk[:, 2]
        start = table.ptr[cid]
        cnt = table.ptr[cid + 1] - start
        rep = np.repeat(np.arange(n, dtype=np.int32), cnt)
        idx = np.arange(len(rep), dtype=np.int64) + np.repeat(start - (np.cumsum(cnt) - cnt), cnt)
        cell = table.cells[idx]
        dx = p[:, 0][rep] - cx[cell]
        dy = p[:, 1][rep] - cy[cell]
        dz = p[:, 2][rep] - cz[cell]
        ok = (dx * dx + dy * dy + dz * dz) < r2
        rep, cell = rep[ok], cell[ok]
        if not len(rep):
            continue
        m = rep // p_n
        key = (m * ncell + cell).astype(np.uint16)
        order = np.argsort(key, kind="stable")  # radix sort; slot order kept within a cell
        ks = key[order]
        first = np.empty(len(ks), dtype=bool)
        first[0] = True
        np.not_equal(ks[1:], ks[:-1], out=first[1:])
        starts = np.flatnonzero(first)
        rank = np.arange(len(ks)) - starts[np.cumsum(first) - 1]
        keep = rank < ns
        o = order[keep]
        mm, jj = m[o], rep[o] - m[o] * p_n
        out[s + mm, cell[o], rank[keep]] = values[s + mm, jj]
    return out.reshape(m_all, ncell * ns, 3)


# ----------------------------------------------------------------------------------------------------
# ONNX models


def _session(path: Path, threads: int, providers="auto"):
    import onnxruntime as ort

    opts = ort.SessionOptions()
    if threads:
        opts.intra_op_num_threads = threads
    # The patches of the next batch are prepared in another thread while a batch runs (`_embed`): workers
    # that spin between onnxruntime's parallel sections take that thread's core. Without spinning, two
    # threads describe a KITTI pair in 1.7 s against 2.0 s spinning and 2.2 s on one thread (issue 50).
    opts.add_session_config_entry("session.intra_op.allow_spinning", "0")
    opts.graph_optimization_level = ort.GraphOptimizationLevel.ORT_ENABLE_ALL
    try:
        with interrupts_blocked():  # onnxruntime's threads start with the session
            return open_session(path, opts, providers, f"BUFFER model {path.name}")
    except Exception as exc:  # noqa: BLE001 - onnxruntime raises several types for a bad file
        raise InputError(f"BUFFER model {path} could not be loaded: {exc}") from exc


def _io_str(items) -> str:
    return ", ".join(f"{i.name!r}: {i.type} ({', '.join(str(d) for d in i.shape)})" for i in items) or "none"


def check_desc_contract(sess, path: Path, params: BufferParams, shape=None) -> tuple[str, int | None]:
    """(input name, output dim or None); InputError when the Desc model does not fit its contract: one
    float32 input (M, K, C) with (K, C) = `shape` (None: the cells, (params.size, 3)), one output (M, D)."""
    k, c = (params.size, 3) if shape is None else shape
    ins, outs = sess.get_inputs(), sess.get_outputs()
    problems = []
    if len(ins) != 1:
        problems.append(f"{len(ins)} inputs")
    else:
        i = ins[0]
        if i.type != "tensor(float)":
            problems.append(f"input {i.name!r} has type {i.type}")
        if len(i.shape) != 3:
            problems.append(f"input {i.name!r} has rank {len(i.shape)}")
        else:
            if isinstance(i.shape[0], int):
                problems.append(f"input {i.name!r} has a fixed batch dimension {i.shape[0]}")
            if isinstance(i.shape[1], int) and i.shape[1] != k:
                problems.append(f"input {i.name!r} has K = {i.shape[1]}, expected {k}")
            if isinstance(i.shape[2], int) and i.shape[2] != c:
                problems.append(f"input {i.name!r} has {i.shape[2]} channels, expected {c}")
    if len(outs) != 1:
        problems.append(f"{len(outs)} outputs")
    elif outs[0].type != "tensor(float)" or len(outs[0].shape) != 2:
        problems.append(f"output {outs[0].name!r} is {outs[0].type} of rank {len(outs[0].shape)}")
    if problems:
        raise InputError(
            f"BUFFER descriptor model {path} does not fit the contract ({'; '.join(problems)}). Expected one "
            f"float32 input (M, {k}, {c}) with M dynamic and one float32 output (M, D); found "
            f"inputs [{_io_str(ins)}] and outputs [{_io_str(outs)}]"
        )
    d = outs[0].shape[1]
    return ins[0].name, d if isinstance(d, int) else None


def check_ref_contract(sess, path: Path) -> None:
    ins = {i.name: i for i in sess.get_inputs()}
    outs = sess.get_outputs()
    problems = []
    for name, typ, rank in REF_INPUTS:
        i = ins.pop(name, None)
        if i is None:
            problems.append(f"no input {name!r}")
        elif i.type != typ or len(i.shape) != rank:
            problems.append(f"input {name!r} is {i.type} of rank {len(i.shape)}")
    if ins:
        problems.append(f"unexpected inputs {sorted(ins)}")
    if len(outs) != 1 or outs[0].type != "tensor(float)" or len(outs[0].shape) != 2:
        problems.append("not one float32 output of rank 2")
    if problems:
        want = ", ".join(f"{n} ({t}, rank {r})" for n, t, r in REF_INPUTS)
        raise InputError(
            f"BUFFER reference-axis model {path} does not fit the contract ({'; '.join(problems)}). "
            f"Expected inputs {want} and one float32 output (N0, 3); found inputs "
            f"[{_io_str(sess.get_inputs())}] and outputs [{_io_str(outs)}]"
        )


class BufferModel:
    """One family's Desc (+ Ref) sessions, their parameters and contracts."""

    def __init__(
        self,
        desc_path: Path,
        ref_path: str | None,
        threads: int,
        providers="auto",
        ref_threads: int | None = None,
    ) -> None:
        self.desc_path = desc_path
        self.threads = threads
        self.desc = _session(desc_path, threads, providers)
        meta = self.desc.get_modelmeta().custom_metadata_map or {}
        if meta.get("fastmac.preprocess") != "buffer":
            raise InputError(
                f"model {desc_path} is not a BUFFER descriptor model (its metadata lacks "
                f"fastmac.preprocess=buffer); use descriptor=fcgf_lite for LRF patch models"
            )
        self.params = BufferParams.from_metadata(meta, str(desc_path))
        self.metadata = dict(meta)
        self.input_name, self.output_dim = check_desc_contract(self.desc, desc_path, self.params)
        self.ref = None
        self.ref_path = None
        if self.params.align == "ref":
            name = ref_path or self.params.ref_model
            if not name:
                raise InputError(f"model {desc_path} aligns by a Ref model but names none (buffer.ref_model)")
            p = Path(name)
            self.ref_path = p if p.is_absolute() or ref_path else desc_path.parent / p
            self.ref_path = resolve_model_path(self.ref_path)
            # the Ref network runs once a cloud, outside the lanes: its own threads (None: the Desc's)
            self.ref = _session(self.ref_path, threads if ref_threads is None else ref_threads, providers)
            check_ref_contract(self.ref, self.ref_path)
            rmeta = self.ref.get_modelmeta().custom_metadata_map or {}
            try:
                self.limits = tuple(int(v) for v in rmeta["buffer.neighbor_limits"].split(","))
                self.conv_radius = float(rmeta["buffer.conv_radius"])
                self.voxel0 = float(rmeta["buffer.voxel_size_0"])
            except (KeyError, ValueError) as exc:
                raise InputError(
                    f"Ref model {self.ref_path}: metadata buffer.neighbor_limits / conv_radius / "
                    f"voxel_size_0 missing or invalid ({exc})"
                ) from exc
            if len(self.limits) != 3:
                raise InputError(f"Ref model {self.ref_path}: 3 neighbour limits expected, got {self.limits}")


# ----------------------------------------------------------------------------------------------------
# the front end


@dataclass
class CloudState:
    """One cloud prepared for description (in BUFFER's units): the shuffled patch cloud and its k-d tree,
    the Ref network's points and unit axes (None when the axis is not the Ref's)."""

    cloud: np.ndarray
    tree: cKDTree
    ref_points: np.ndarray | None
    ref_axes: np.ndarray | None
    patch_index: object = None  # cut_patches' C++ grid over `cloud` (patch_index), built on first use
    patch_index_of: tuple | None = None  # the (radius, k) it was built for
    _lock: threading.Lock = field(default_factory=threading.Lock, repr=False)

    def index_for(self, radius: float, k: int):
        """The C++ grid of `cloud` for patches of `radius` and `k` points (built once; None: no core)."""
        with self._lock:
            if self.patch_index_of != (radius, k):
                self.patch_index = patch_index(self.cloud, radius, k)
                self.patch_index_of = (radius, k)
            return self.patch_index


@dataclass
class Described:
    """The descriptors of one cloud's keypoints computed so far (`done` marks the rows filled)."""

    desc: np.ndarray
    done: np.ndarray


class _CloudMemory:
    """The clouds described in this process, shared by every BUFFER and SpinNet instance that keeps clouds
    (cache_clouds > 0): Hydra's basic launcher runs a sweep's members in one process, one new descriptor
    each, so a seed sweep would otherwise describe every cloud again for each seed. The keys hold all that
    determines a described row (the describer's class, model files, axis, scale, its own seed and
    settings, the points' digest) and not the run's seed, which draws only the matches' cap."""

    def __init__(self) -> None:
        self.states: OrderedDict[tuple, CloudState] = OrderedDict()
        self.described: OrderedDict[tuple, Described] = OrderedDict()


_MEMORY = _CloudMemory()


def forget_described_clouds() -> None:
    """Empties the process-wide memory of described clouds (tests that count descriptions)."""
    _MEMORY.states.clear()
    _MEMORY.described.clear()


def _digest(a: np.ndarray) -> str:
    a = np.ascontiguousarray(a)
    return hashlib.blake2b(a.tobytes(), digest_size=16).hexdigest() + str(a.shape)


class BufferDescriptor(FeatureDescriptor):
    """BUFFER's published descriptor (Ref axis + cylindrical patch network) through onnxruntime.

    `model`: "auto" (the pair's family picks `model_3dmatch` for 3dmatch/3dlomatch, `model_kitti` for kitti),
    "3dmatch", "kitti", or the path of a Desc model meeting the contract; `model_3dmatch` / `model_kitti`:
    the Desc files (default: the shipped ones); `ref_model`: the Ref file for Desc models that align by it
    (None: the one named in the Desc model's metadata, next to it). Keypoints: the cloud voxel-downsampled at
    `voxel_size` (None: the pair's), as FPFH. `scale`: BUFFER's lengths are multiplied by it (None: the
    pair's voxel size / the model's reference voxel). Matching, cap and labels as the other front ends
    (`max_correspondences` random subset, one-way nearest neighbour unless `mutual`).
    `threads`: onnxruntime intra-op threads (0: all cores); `batch_size`: keypoints per run;
    `execution_providers`: "auto" (onnxruntime-gpu's CUDA provider when there is one, else the CPU) or a
    list such as ["cuda", "cpu"] (onnx_descriptor.session_providers: CPU fallback with a notice); `seed`:
    the shuffles (upstream shuffles at random; fixed here so a cloud is always described the same way);
    `progress`: a progress bar over each cloud's keypoints. `axis`: None = the model's (`ref` for the
    3DMatch model, `none` for KITTI); `pca` = upstream's own fallback (cal_Z_axis, the patch's normal),
    kept for comparison (descriptors/buffer/MODEL_CARD.md: the Ref axis is better). `precision`:
    "float32" (the exported weights) or "int8" (`model_3dmatch_int8` / `model_kitti_int8`: the Desc
    convolutions quantised by descriptors/buffer/quantize.py, about 3x faster; rows labelled
    `buffer_int8`). `cache_clouds`: how many clouds' preparation and described keypoints are kept in
    memory (0: none), so a cloud shared by pairs is described once; the memory is the process's, shared
    by the instances (a sweep's members: its seeds describe each cloud once, the run's seed drawing only
    the matches' cap). `match_keypoints` 0: a pair describes only the source keypoints its correspondences
    keep (one-way matching: the cap's random subset of the source keypoints, drawn as before) and every
    target keypoint; N: at most N keypoints of each cloud are described and matched (`mutual`), chosen by
    `keypoint_choice` ("spread": one a cell of the finest grid with at most N cells, the same in every run;
    "random": a random subset drawn with the run's rng; "auto": the model's); `match_keypoints` "auto":
    N by model (MATCH_KEYPOINTS).
    """

    match_keypoints: int | str = 0  # class defaults: SpinNet (a subclass) chooses its own keypoints
    keypoint_choice: str = "auto"

    name = "buffer"
    default_graph_key = "spinnet"
    # said when a run starts (run/experiment.py), until the descriptor is fast
    cost_note = (
        "BUFFER describes a pair in about 1-1.5 s indoors and 2-3 s on a KITTI pair on a CPU core with INT8, "
        "AVX512-VNNI and the config's match_keypoints=auto (about 2-3x that without VNNI or in float32, "
        "3x with match_keypoints=0); a pair in the correspondence cache is not described again; limit=N "
        "runs fewer"
    )

    def __init__(
        self,
        model: str = "auto",
        model_3dmatch: str = SHIPPED["3dmatch"],
        model_kitti: str = SHIPPED["kitti"],
        model_3dmatch_int8: str = SHIPPED_INT8["3dmatch"],
        model_kitti_int8: str = SHIPPED_INT8["kitti"],
        precision: str = "float32",
        ref_model: str | None = None,
        voxel_size: float | None = None,
        scale: float | None = None,
        max_correspondences: int = 5000,
        mutual: bool = False,
        threads: int = 0,
        batch_size: int = 64,
        seed: int = 0,
        progress: bool = True,
        axis: str | None = None,
        cache_clouds: int = 8,
        execution_providers="auto",
        graph_key: str | None = None,
        match_keypoints: int | str = 0,
        keypoint_choice: str = "auto",
        lanes: int | str = "auto",
    ) -> None:
        super().__init__(graph_key)
        self.match_keypoints = check_match_keypoints(match_keypoints)
        if keypoint_choice not in KEYPOINT_CHOICES:
            raise InputError(
                f"buffer keypoint_choice must be one of {KEYPOINT_CHOICES}, got {keypoint_choice!r}"
            )
        self.keypoint_choice = keypoint_choice
        if axis not in (None, "ref", "pca", "none"):
            raise InputError(f"buffer axis must be null, 'ref', 'pca' or 'none', got {axis!r}")
        self._set_common(
            "buffer", model, model_3dmatch, model_kitti, voxel_size, scale, max_correspondences, mutual,
            threads, batch_size, seed, progress, axis, cache_clouds, execution_providers, lanes,
        )  # fmt: skip
        self._set_precision(precision, model_3dmatch_int8, model_kitti_int8)
        self.ref_model = ref_model
        if self.model != "auto":
            self.load(self.model)

    def _set_common(
        self, label, model, model_3dmatch, model_kitti, voxel_size, scale, max_correspondences, mutual,
        threads, batch_size, seed, progress, axis, cache_clouds, execution_providers, lanes="auto",
    ) -> None:  # fmt: skip
        """The options and state BUFFER and SpinNet (a subclass) share, checked (`label` names the
        descriptor in the messages)."""
        if cache_clouds < 0:
            raise InputError(f"{label} cache_clouds must be >= 0 (0 = no cache), got {cache_clouds}")
        if voxel_size is not None and not voxel_size > 0:
            raise InputError(f"{label} voxel_size must be positive or None (the pair's), got {voxel_size}")
        if scale is not None and not scale > 0:
            raise InputError(f"{label} scale must be positive or None (from the voxel size), got {scale}")
        if max_correspondences < 0:
            raise InputError(f"max_correspondences must be >= 0 (0 = no cap), got {max_correspondences}")
        if threads < 0 or batch_size < 1:
            raise InputError(f"threads must be >= 0 and batch_size >= 1, got {threads}, {batch_size}")
        counted = not isinstance(lanes, bool) and isinstance(lanes, int | np.integer) and lanes >= 1
        if lanes != "auto" and not counted:
            raise InputError(f"{label} lanes must be 'auto' or an integer >= 1, got {lanes!r}")
        self.lanes = lanes if lanes == "auto" else int(lanes)
        self.model = str(model)
        self.model_3dmatch = str(model_3dmatch)
        self.model_kitti = str(model_kitti)
        self.voxel_size = voxel_size
        self.scale = scale
        self.max_correspondences = int(max_correspondences)
        self.mutual = bool(mutual)
        self.threads = int(threads)
        self.batch_size = int(batch_size)
        self.seed = int(seed)
        self.progress = bool(progress)
        self.axis = axis
        self.cache_clouds = int(cache_clouds)
        self.execution_providers = execution_providers
        self._models: dict = {}
        self._attach_memory()
        self.last_timings: dict[str, float] = {}
        self.timings_log: list[dict] = []  # one entry a described cloud (the last 1000)

    def _set_precision(self, precision: str, model_3dmatch_int8: str, model_kitti_int8: str) -> None:
        """`precision` checked; int8 labels the rows `<name>_int8`."""
        if precision not in PRECISIONS:
            raise InputError(f"{self.name} precision must be one of {PRECISIONS}, got {precision!r}")
        self.model_3dmatch_int8 = str(model_3dmatch_int8)
        self.model_kitti_int8 = str(model_kitti_int8)
        self.precision = precision
        if precision == "int8":
            self.name = f"{type(self).name}_int8"

    def __getstate__(self) -> dict:  # onnxruntime sessions do not pickle (joblib launchers)
        state = self.__dict__.copy()
        state["_models"] = {}
        state["_states"], state["_described"] = None, None  # the receiving process's own memory instead
        return state

    def __setstate__(self, state: dict) -> None:
        self.__dict__.update(state)
        self._attach_memory()

    def _attach_memory(self) -> None:
        """The process-wide described clouds, or (cache_clouds=0) private dicts that stay empty."""
        if self.cache_clouds:
            self._states, self._described = _MEMORY.states, _MEMORY.described
        else:
            self._states, self._described = OrderedDict(), OrderedDict()

    def _describer_key(self, model) -> tuple:
        """What besides the cloud, axis, scale and seed decides a described row: shared between instances,
        the memory must tell apart describers that one instance alone never mixes."""
        return (type(self).__name__, str(model.desc_path), str(model.ref_path), str(self.execution_providers))

    def model_path(self, which: str) -> Path:
        """The Desc model file for "3dmatch", "kitti" or a path, at `precision` (int8: the shipped int8 file,
        or for a path `<stem>_int8.onnx` beside it)."""
        if self.precision == "float32":
            return resolve_model_path(
                {"3dmatch": self.model_3dmatch, "kitti": self.model_kitti}.get(which, which)
            )
        named = {"3dmatch": self.model_3dmatch_int8, "kitti": self.model_kitti_int8}.get(which)
        if named is None:
            path = resolve_model_path(which)
            named = str(path.with_name(path.stem + "_int8.onnx"))
        try:
            return resolve_model_path(named)
        except InputError as exc:
            raise InputError(
                f"{exc}; the int8 {self.title} models are made by `python {self.quantize_script}`"
            ) from exc

    title = "BUFFER"
    quantize_script = "descriptors/buffer/quantize.py"

    def _open_model(self, path: Path) -> BufferModel:
        return BufferModel(
            path, self.ref_model, self.session_threads(), self.execution_providers, ref_threads=self.threads
        )

    def session_threads(self) -> int:
        """onnxruntime's intra-op threads a session run: `threads`, else (0) one where several lanes share
        the cores (lanes auto or > 1), else one a core (onnxruntime's 0)."""
        return self.threads if self.threads or self.lanes == 1 else 1

    def lanes_for(self, model) -> int:
        """How many batches run at once (`lanes`; auto: one a CPU core the process may use where the
        session runs on the CPU and `threads` is 0, else one: a set thread count is kept to)."""
        if self.lanes != "auto":
            return self.lanes
        if self.threads or model.desc.get_providers()[0] != "CPUExecutionProvider":
            return 1
        return available_cores()

    def load(self, which: str) -> BufferModel:
        if which not in self._models:
            model = self._open_model(self.model_path(which))
            found = model.metadata.get("fastmac.precision", "float32")
            if found != self.precision:
                raise InputError(
                    f"{self.title} model {model.desc_path} is {found} (metadata fastmac.precision), "
                    f"descriptor.precision is {self.precision}"
                )
            self._models[which] = model
        return self._models[which]

    def model_for(self, family: str) -> BufferModel:
        if self.model != "auto":
            return self.load(self.model)
        if family not in FAMILIES:
            raise InputError(
                f"descriptor=buffer: no BUFFER model for family {family!r}; set descriptor.model"
            )
        return self.load(FAMILIES[family].buffer_model)

    # -- description

    def _state(self, model: BufferModel, how: str, pts: np.ndarray, key: tuple) -> tuple[CloudState, dict]:
        """The cloud prepared for description (cached by content) and the seconds it took (0 if cached)."""
        state = self._states.get(key)
        if state is not None:
            self._states.move_to_end(key)
            return state, {"clouds_s": 0.0, "ref_s": 0.0}
        t0 = time.perf_counter()
        p = model.params
        rng = np.random.default_rng(self.seed)
        cloud = voxel_down(pts, p.downsample)
        cloud = cloud[rng.permutation(len(cloud))]
        ref_pts = ref_axes = None
        t1 = time.perf_counter()
        if how == "ref":
            ref_pts = voxel_down(cloud, p.voxel_size_0)
            ref_pts = ref_pts[rng.permutation(len(ref_pts))][: p.max_points]
            if len(ref_pts) < MIN_POINTS:
                raise InputError(
                    f"only {len(ref_pts)} points at BUFFER's Ref grid ({p.voxel_size_0} m, scaled)"
                )
            feed = ref_inputs(
                ref_pts, oriented_normals(ref_pts), model.voxel0, model.conv_radius, model.limits
            )
            ref_axes = np.asarray(model.ref.run(None, feed)[0], dtype=np.float64)
            ref_axes /= np.maximum(np.linalg.norm(ref_axes, axis=1, keepdims=True), 1e-12)
        state = CloudState(cloud, cKDTree(cloud), ref_pts, ref_axes)
        self._remember(self._states, key, state)
        return state, {"clouds_s": t1 - t0, "ref_s": time.perf_counter() - t1}

    def _remember(self, cache: OrderedDict, key, value) -> None:
        if self.cache_clouds:
            cache[key] = value
            while len(cache) > self.cache_clouds:
                cache.popitem(last=False)

    def describe(
        self,
        model: BufferModel,
        points: np.ndarray,
        keypoints: np.ndarray,
        scale: float,
        what: str = "cloud",
        rows: np.ndarray | None = None,
    ) -> np.ndarray:
        """Descriptors float32 of `keypoints` (in the cloud's units) of the cloud `points`: `(M, D)`, or
        `(len(rows), D)` for the keypoints `rows` only. A keypoint's descriptor depends on it and the cloud
        alone, so the described rows of the last `cache_clouds` clouds are kept and never computed twice
        (a cloud that is the target of several pairs, or the source here and the target there)."""
        p = model.params
        t0 = time.perf_counter()
        how = self.axis or p.align
        if how == "ref" and model.ref is None:
            raise InputError(f"BUFFER model {model.desc_path} has no Ref model; use axis=pca or none")
        pts = np.asarray(points, dtype=np.float64) / scale
        kp = np.asarray(keypoints, dtype=np.float64) / scale
        cloud_key = (*self._describer_key(model), how, float(scale), self.seed, _digest(pts))
        state, prep = self._state(model, how, pts, cloud_key)
        key = (cloud_key, _digest(kp))
        entry = self._described.get(key)
        if entry is None:
            entry = Described(
                np.zeros((len(kp), model.output_dim or 32), np.float32), np.zeros(len(kp), bool)
            )
            self._remember(self._described, key, entry)
        else:
            self._described.move_to_end(key)
        want = np.arange(len(kp)) if rows is None else np.asarray(rows, dtype=np.int64)
        todo = np.unique(want[~entry.done[want]])
        timings = self._embed(model, state, kp, todo, how, entry, what)
        self.last_timings = {
            **prep,
            **timings,
            "total_s": time.perf_counter() - t0,
            "keypoints": len(todo),
            "reused": len(want) - len(todo),
            "what": what,
        }
        self.timings_log = [*self.timings_log[-999:], self.last_timings]
        return entry.desc[want].copy()

    def _embed(self, model, state: CloudState, kp, todo, how: str, entry: Described, what: str) -> dict:
        """Describes the keypoints `kp[todo]` into `entry` (unit rows); the stage seconds."""
        sel = kp[todo]
        axes = None
        if how == "ref" and len(sel):
            _, nearest = cKDTree(state.ref_points).query(sel)
            axes = state.ref_axes[nearest]
            flip = np.einsum("ij,ij->i", axes, sel) > 0
            axes[flip] *= -1
        m, bs = len(sel), self.batch_size
        starts = list(range(0, m, bs))
        t_patches = 0.0

        lock = threading.Lock()

        def prepare(s: int) -> np.ndarray:
            nonlocal t_patches
            t = time.perf_counter()
            k_axes = None if axes is None else axes[s : s + bs]
            x = self._model_input(model, state, sel[s : s + bs], how, k_axes)
            with lock:  # lanes prepare in several threads
                t_patches += time.perf_counter() - t
            return x

        bar = keypoint_bar(m, f"{self.title} {what}", self.progress, bs)

        def store(s: int, x: np.ndarray, y: np.ndarray) -> None:
            if y.ndim != 2 or y.shape[0] != len(x) or y.shape[1] != entry.desc.shape[1]:
                raise InputError(
                    f"{self.title} model {model.desc_path} returned {y.shape} for {len(x)} patches, "
                    f"expected ({len(x)}, {entry.desc.shape[1]})"
                )
            norm = np.linalg.norm(y, axis=1, keepdims=True)
            entry.desc[todo[s : s + len(y)]] = y / np.where(norm > 0, norm, 1.0)
            entry.done[todo[s : s + len(y)]] = True
            bar.update(len(y))

        lanes = min(self.lanes_for(model), len(starts))
        if lanes > 1:
            out = self._run_lanes(model, starts, prepare, store, lanes)
            bar.close()
            return {**out, "patches_s": t_patches}
        t_prep = t_run = 0.0
        # numpy prepares the next batch while onnxruntime runs this one (both release the GIL)
        with ThreadPoolExecutor(max_workers=1, initializer=block_interrupts) as pool:
            pending = pool.submit(prepare, starts[0]) if starts else None
            for n_i, s in enumerate(starts):
                ta = time.perf_counter()
                x = pending.result()
                tb = time.perf_counter()
                if n_i + 1 < len(starts):
                    pending = pool.submit(prepare, starts[n_i + 1])
                y = model.desc.run(None, {model.input_name: x})[0]
                t_prep += tb - ta
                t_run += time.perf_counter() - tb
                store(s, x, y)
        bar.close()
        return {"wait_for_patches_s": t_prep, "network_s": t_run, "patches_s": t_patches}

    @staticmethod
    def _run_lanes(model, starts: list[int], prepare, store, lanes: int) -> dict:
        """The batches `starts` in `lanes` threads, each preparing and running its own batches in turn (a
        batch's patches and its network run on one core, the lanes on the others), so that no core waits on
        another's stage; the same descriptors as one lane (a batch's result does not depend on the thread
        or on onnxruntime's thread count). Where a lane fails or the run is interrupted the others stop
        after their batch. Seconds: the lanes' network runs, summed."""
        lock, stop = threading.Lock(), threading.Event()
        t_run = [0.0] * lanes
        queue = iter(starts)

        def lane(i: int) -> None:
            try:
                while not stop.is_set():
                    with lock:
                        s = next(queue, None)
                    if s is None:
                        return
                    x = prepare(s)
                    t = time.perf_counter()
                    y = model.desc.run(None, {model.input_name: x})[0]
                    t_run[i] += time.perf_counter() - t
                    with lock:
                        store(s, x, y)
            except BaseException:
                stop.set()  # the other lanes end after their batch
                raise

        with ThreadPoolExecutor(max_workers=lanes, initializer=block_interrupts) as pool:
            futures = [pool.submit(lane, i) for i in range(lanes)]
            try:
                for f in futures:
                    f.result()
            except BaseException:
                stop.set()
                raise
        return {"wait_for_patches_s": 0.0, "network_s": sum(t_run), "lanes": lanes}

    def _model_input(self, model, state: CloudState, k: np.ndarray, how: str, axes) -> np.ndarray:
        """The network's input for the keypoints `k`: their patches, aligned (`axes`: the keypoints' Ref
        axes when `how` is "ref"), grouped into the cells."""
        p = model.params
        index = state.index_for(p.des_r, p.patch_points)
        patch = cut_patches(state.cloud, state.tree, k, p.des_r, p.patch_points, index=index) - k[:, None, :]
        if how == "pca":
            patch = patch @ align_rotations(pca_axes(patch, k))
        elif axes is not None:
            patch = patch @ align_rotations(axes)
        return group_cells(patch / p.des_r, p)

    def keypoints(
        self, points: np.ndarray, voxel: float, what: str = "cloud", family: str = "3dmatch"
    ) -> tuple[np.ndarray, np.ndarray]:
        """(the cleaned cloud, its keypoints): the voxel keypoints (FPFH's); SpinNet takes a subset."""
        return keypoints(points, voxel, what)

    def scale_for(self, model: BufferModel, voxel: float | None) -> float:
        if self.scale is not None:
            return self.scale
        if voxel and voxel > 0:
            return voxel / model.params.reference_voxel
        raise InputError("no voxel size to scale BUFFER's lengths by; set descriptor.scale")

    def features(
        self, points: np.ndarray, voxel: float, what: str = "cloud", family: str = "3dmatch", scale=None
    ) -> tuple[np.ndarray, np.ndarray]:
        """Keypoints `(M, 3)` (voxel downsampling at `voxel`) and their descriptors `(M, D)` float32."""
        pts, kp = self.keypoints(points, voxel, what, family=family)
        model = self.model_for(family)
        scale = self.scale_for(model, voxel) if scale is None else scale
        return kp, self.describe(model, pts, kp, scale, what)

    def __call__(self, pair: Pair, rng: np.random.Generator) -> Correspondences:
        model = self.model_for(pair.family)
        if self.scale is None and not (pair.voxel_size and pair.voxel_size > 0):
            raise InputError(f"pair {pair.name!r} has no voxel size; set descriptor.scale for {self.name}")
        scale = self.scale_for(model, pair.voxel_size)
        bound = _Bound(self, pair.family, scale)
        cap, how = self.match_keypoints_for(pair.family)
        if not cap:
            return correspondences_from_kept_sources(bound, pair, rng, match_descriptors)
        if how == "spread":
            choose = lambda kp, _rng: spread_rows(kp, cap)  # noqa: E731
        else:
            choose = lambda kp, rng: _all_if_none(capped_rows(len(kp), cap, rng), len(kp))  # noqa: E731
        return correspondences_from_chosen_keypoints(bound, pair, rng, match_descriptors, choose)

    def match_keypoints_for(self, family: str) -> tuple[int, str]:
        """(keypoints a cloud the pair describes and matches, 0: the kept sources and every target; how they
        are chosen, "spread" or "random")."""
        which = self.model if self.model in MATCH_KEYPOINTS else None
        if which is None:  # auto, or a model file of the user's: the family's model's
            fam = FAMILIES.get(family)
            which = fam.buffer_model if fam is not None else "3dmatch"
        count, how = MATCH_KEYPOINTS[which]
        cap = count if self.match_keypoints == "auto" else self.match_keypoints
        return cap, how if self.keypoint_choice == "auto" else self.keypoint_choice


def check_match_keypoints(value) -> int | str:
    """`match_keypoints` as given ("auto" or a count >= 0); InputError naming the value otherwise."""
    if value == "auto":
        return "auto"
    if isinstance(value, bool) or not isinstance(value, int | np.integer) or value < 0:
        raise InputError(
            "buffer match_keypoints must be 'auto', 0 (every target keypoint) or a keypoint count >= 1 a "
            f"cloud, got {value!r}"
        )
    return int(value)


def _all_if_none(rows: np.ndarray | None, n: int) -> np.ndarray:
    return np.arange(n) if rows is None else rows


class _Bound(FeatureDescriptor):
    """The descriptor as `matching` sees it, with the pair's family and scale."""

    def __init__(self, desc: BufferDescriptor, family: str, scale: float) -> None:
        super().__init__(desc.graph_key)
        self.desc, self.family, self.scale = desc, family, scale
        self.name = desc.name
        self.voxel_size = desc.voxel_size
        self.mutual = desc.mutual
        self.max_correspondences = desc.max_correspondences

    def features(self, points, voxel, what="cloud"):
        return self.desc.features(points, voxel, what=what, family=self.family, scale=self.scale)

    def keypoints(self, points, voxel, what="cloud"):
        return self.desc.keypoints(points, voxel, what, family=self.family)

    def features_of(self, cloud, kp, rows, what="cloud"):
        return self.desc.describe(self.desc.model_for(self.family), cloud, kp, self.scale, what, rows)


__all__ = [
    "BufferDescriptor",
    "forget_described_clouds",
    "BufferParams",
    "align_rotations",
    "cut_patches",
    "grid_subsample",
    "group_cells",
    "patch_index",
    "radius_neighbors",
    "ref_inputs",
]
