"""SpinNet's learned descriptor (Ao, Hu et al., CVPR 2021) through onnxruntime: `descriptor=spinnet`.

The published 3DMatch and KITTI weights (QingyongHu/SpinNet@5581e7d1, ../shared/models/spinnet), converted
by `descriptors/spinnet/export.py` into `fastmac_exp/models/spinnet_<family>.onnx`; model card
`descriptors/spinnet/MODEL_CARD.md`. Runtime: numpy/scipy/Open3D + the C++ core's grouping + onnxruntime (CPU
unless a GPU provider is asked for); torch is never imported here.

Describing the keypoints of one cloud (lengths are SpinNet's, in metres, times `scale` = the pair's voxel /
the model's reference voxel, 1 on the real indoor and LiDAR pairs):

1. keypoints: the cloud voxel-downsampled at the pair's voxel (FPFH's keypoints), then at most `keypoints`
   of them (upstream describes 5,000 random points a fragment on a GPU; on a loaded 2-core CPU the INT8
   network costs ~0.015 s a keypoint indoors, ~0.011 outdoors, so the defaults are 1,000 farthest-point-
   sampled keypoints a fragment for the 3DMatch model and 2,500 random ones a scan for KITTI's;
   `MODEL_KEYPOINTS`). Source and target take the same rule, so a cloud described once serves as either;
2. the patch cloud: the cloud voxel-downsampled at `downsample` (3DMatch model: 0.01 m; KITTI: none, the raw
   scan as upstream), shuffled (seeded);
3. patch: the first `patch_points - 1` (2047) points of the shuffled cloud within `des_r` (0.3 / 2.0 m),
   padded with the keypoint, the keypoint last (BUFFER's `cut_patches`, C++), offsets from the keypoint;
4. alignment (3DMatch model): the patch's normal (least eigenvector of the uncentred scatter, signed so that
   axis . keypoint <= 0) rotated to +z (BUFFER's `pca_axes`, `align_rotations`; upstream cal_Z_axis and
   RodsRotatFormula); the KITTI model keeps the sensor frame, as upstream;
5. cells (C++ `spinnet_group_cells`): 9 radial x 40 elevation x 80 azimuth cells (KITTI: 9 x 30 x 60), each
   the first 30 patch points within `voxel_r` (0.04 / 0.3 m) of its centre, as offsets from the centre in
   the cell's azimuth frame (upstream sphere_query + var_to_invar, descriptors/spinnet/nets.py);
   -> the ONNX model -> 32 values, L2-normalised here.

Model contract (checked when a model is opened): one float32 input `(M, cells * samples, 3)` with M dynamic,
one float32 output `(M, D)`; metadata `fastmac.preprocess = spinnet` and the `spinnet.*` keys of
`SpinNetParams`.
"""

from __future__ import annotations

import json
import logging
import threading
import time
from dataclasses import dataclass
from pathlib import Path

import numpy as np
from scipy.spatial import cKDTree

from fastmac_exp.descriptors.base import FeatureDescriptor
from fastmac_exp.descriptors.buffer import (
    BufferDescriptor,
    CellTable,
    CloudState,
    _core,
    _session,
    align_rotations,
    check_desc_contract,
    cut_patches,
    pca_axes,
)
from fastmac_exp.descriptors.patches import CylinderGrid, voxel_down
from fastmac_exp.descriptors.patches import keypoints as voxel_keypoints
from fastmac_exp.errors import InputError
from fastmac_exp.families import FAMILIES

log = logging.getLogger(__name__)

SHIPPED = {"3dmatch": "models/spinnet_3dmatch.onnx", "kitti": "models/spinnet_kitti.onnx"}
SHIPPED_INT8 = {  # descriptors/spinnet/quantize.py
    "3dmatch": "models/spinnet_3dmatch_int8.onnx",
    "kitti": "models/spinnet_kitti_int8.onnx",
}
INPUTS = ("cells", "pooled")  # the model's input: the grouped cells, or their max-pooled point features
SAMPLINGS = ("fps", "random")
# per model: (keypoints a cloud, sampling). Indoors farthest-point sampling covers a fragment evenly (on the 4
# real indoor pairs 400 FPS keypoints give ~1.5x the inlier ratio of 400 random ones); on a LiDAR scan FPS
# spends its points on the sparse periphery, and a random subset (denser near the sensor) does better
# since INT8 (descriptors/spinnet/keypoints.json, chosen on some real pairs, checked on held-out ones): 1,000
# indoors (inlier ratio 0.081 -> 0.117 on the held-out pairs against 400), 2,500 on KITTI (0.173 -> 0.288
# against 1,000)
MODEL_KEYPOINTS = {"3dmatch": (1000, "fps"), "kitti": (2500, "random")}


@dataclass(frozen=True)
class SpinNetParams(CylinderGrid):
    """SpinNet's preprocessing (upstream ThreeDMatch/Test/preparation.py, KITTI/Test/test_kitti.py); lengths
    in metres at scale 1. Stored as `spinnet.<field>` metadata in the model."""

    metadata_prefix = "spinnet"

    family: str = "3dmatch"
    align: str = "pca"  # "pca": the patch normal -> +z (3DMatch) | "none": the sensor frame (KITTI)
    reference_voxel: float = 0.05  # the pair voxel size at which the published sizes apply
    downsample: float = 0.01  # the patch cloud's grid (0: the raw cloud)
    des_r: float = 0.3
    rad_n: int = 9
    ele_n: int = 40
    azi_n: int = 80
    voxel_r: float = 0.04
    samples: int = 30
    patch_points: int = 2048

    def __post_init__(self) -> None:
        if self.align not in ("pca", "none"):
            raise InputError(f"spinnet.align must be 'pca' or 'none', got {self.align!r}")
        if not all(v > 0 for v in (self.reference_voxel, self.des_r, self.voxel_r)) or self.downsample < 0:
            raise InputError("SpinNet lengths must be positive (downsample >= 0)")
        if min(self.rad_n, self.ele_n, self.azi_n, self.samples, self.patch_points) < 1:
            raise InputError("SpinNet counts must be positive")
        if self.cells > 32767:
            raise InputError(f"SpinNet grid of {self.cells} cells; at most 32,767")


# ----------------------------------------------------------------------------------------------------
# the cells


@dataclass(frozen=True)
class Grid:
    """Cell centres (float32, metres at scale 1), their azimuth rotations and the candidate table."""

    centres: np.ndarray
    rotations: np.ndarray
    r2: np.float32
    table: CellTable


_GRIDS: dict[tuple, Grid] = {}
_GRIDS_LOCK = threading.Lock()


def cell_centres(des_r: float, rad_n: int, azi_n: int, ele_n: int) -> np.ndarray:
    """(rad_n * ele_n * azi_n, 3) float32 centres, radial-major, then elevation, azimuth (upstream
    get_voxel_coordinate: shells (i + 1/2) / rad_n x des_r, elevation (j + 1/2) pi / ele_n, azimuth
    (k + 1/2) 2 pi / azi_n)."""
    beta = np.linspace(0, np.pi, ele_n, endpoint=False) + np.pi / ele_n / 2
    alpha = np.linspace(0, 2 * np.pi, azi_n, endpoint=False) + np.pi / azi_n
    b, a = np.meshgrid(beta, alpha, indexing="ij")
    unit = np.stack([np.sin(b) * np.cos(a), np.sin(b) * np.sin(a), np.cos(b)], -1) * des_r
    shells = np.arange(rad_n) / rad_n + 1 / (2 * rad_n)
    return (shells[:, None, None, None] * unit[None]).reshape(-1, 3).astype(np.float32)


def azimuth_rotations(azi_n: int) -> np.ndarray:
    """(azi_n, 3, 3) float32: the rotation by -k 2 pi / azi_n about z (upstream var_to_invar)."""
    t = -np.arange(azi_n) * 2 * np.pi / azi_n
    out = np.zeros((azi_n, 3, 3))
    out[:, 0, 0], out[:, 0, 1] = np.cos(t), -np.sin(t)
    out[:, 1, 0], out[:, 1, 1] = np.sin(t), np.cos(t)
    out[:, 2, 2] = 1.0
    return out.astype(np.float32)


def grid_for(p: SpinNetParams) -> Grid:
    key = (p.des_r, p.rad_n, p.ele_n, p.azi_n, p.voxel_r)
    with _GRIDS_LOCK:
        if key not in _GRIDS:
            centres = cell_centres(p.des_r, p.rad_n, p.azi_n, p.ele_n)
            table = CellTable(centres.astype(np.float64) / p.des_r, p.voxel_r / p.des_r, grid=24)
            r = np.float32(p.voxel_r)
            _GRIDS[key] = Grid(centres, azimuth_rotations(p.azi_n), np.float32(r * r), table)
        return _GRIDS[key]


def _kernel_args(aligned: np.ndarray, p: SpinNetParams) -> tuple:
    """The C++ kernels' arguments for aligned patches: the patches as float32, then the cell grid (centres,
    squared radius, cell table, inverse radius and cell size, samples a cell, rotations)."""
    g = grid_for(p)
    return (
        np.ascontiguousarray(aligned, dtype=np.float32),
        g.centres,
        float(g.r2),
        g.table.ptr,
        g.table.cells,
        g.table.g,
        float(np.float32(1.0 / p.des_r)),
        float(np.float32(1.0 / g.table.h)),
        p.samples,
        g.rotations,
    )


def group_cells(aligned: np.ndarray, p: SpinNetParams) -> np.ndarray:
    """Aligned patches `(M, P, 3)` (offsets from the keypoint, metres at scale 1) -> the model input
    `(M, cells * samples, 3)` float32 (module docstring, step 5). Needs the C++ core."""
    core = _core()
    if core is None or not hasattr(core, "spinnet_group_cells"):
        return group_cells_numpy(aligned, p)
    return core.spinnet_group_cells(*_kernel_args(aligned, p))


def pool_cells(aligned: np.ndarray, p: SpinNetParams, weights: np.ndarray) -> np.ndarray:
    """The input of a "pooled" model: per keypoint and cell the max over the cell's `samples` slots of
    slot @ `weights` (3, F), `(M, cells, F)` float32 (group_cells followed by the point MLP's product and the
    max over the samples, without the 10 MB a keypoint of grouped cells; the bias is added in the model, after
    the max, which it commutes with). Needs the C++ core for speed."""
    w = np.ascontiguousarray(weights, dtype=np.float32)
    core = _core()
    if core is None or not hasattr(core, "spinnet_pool_cells"):
        return pool_cells_numpy(aligned, p, w)
    return core.spinnet_pool_cells(*_kernel_args(aligned, p), w)


def pool_cells_numpy(aligned: np.ndarray, p: SpinNetParams, weights: np.ndarray) -> np.ndarray:
    """`pool_cells` from `group_cells_numpy` (the reference of the C++ kernel; slow)."""
    cells = group_cells_numpy(aligned, p).reshape(len(aligned), p.cells, p.samples, 3)
    return (cells @ np.asarray(weights, dtype=np.float32)).max(axis=2)


def group_cells_numpy(aligned: np.ndarray, p: SpinNetParams) -> np.ndarray:
    """`group_cells` in numpy, brute force over the cells (the reference of the C++ kernel; slow)."""
    g = grid_for(p)
    pts = np.ascontiguousarray(aligned, dtype=np.float32)
    m = len(pts)
    ns, ncell = p.samples, p.cells
    out = np.zeros((m, ncell, ns, 3), dtype=np.float32)
    rot = g.rotations[np.arange(ncell) % p.azi_n]  # (cells, 3, 3)
    for j in range(m):
        for lo in range(0, ncell, 1024):
            cc = slice(lo, min(lo + 1024, ncell))
            d = pts[j][None, :, :] - g.centres[cc, None, :]  # (cells, P, 3)
            d2 = (d[..., 0] * d[..., 0] + d[..., 1] * d[..., 1]) + d[..., 2] * d[..., 2]
            hit = d2 < g.r2
            rank = np.cumsum(hit, axis=1) - 1
            c, s = np.nonzero(hit & (rank < ns))
            out[j, lo + c, rank[c, s]] = np.einsum("cij,cj->ci", rot[lo + c], d[c, s])
            empty = np.flatnonzero(~hit.any(axis=1))
            out[j, lo + empty, 0] = np.einsum("cij,cj->ci", rot[lo + empty], d[empty, 0])
    return out.reshape(m, ncell * ns, 3)


def farthest_points(points: np.ndarray, n: int, seed: int = 0) -> np.ndarray:
    """Rows of `n` of `points` by farthest-point sampling from a seeded random start (in sampling order: a
    prefix of the result is the sampling of fewer points)."""
    pts = np.asarray(points, dtype=np.float64)
    n = min(int(n), len(pts))
    out = np.empty(n, dtype=np.int64)
    if n == 0:
        return out
    out[0] = np.random.default_rng(seed).integers(len(pts))
    dist = np.full(len(pts), np.inf)
    for i in range(1, n):
        delta = pts - pts[out[i - 1]]
        np.minimum(dist, np.einsum("ij,ij->i", delta, delta), out=dist)
        out[i] = int(np.argmax(dist))
    return out


# ----------------------------------------------------------------------------------------------------
# the model


class SpinNetModel:
    """One family's SpinNet session, its parameters and contract (the attributes BufferDescriptor.describe
    reads: desc_path, params, ref, output_dim). `pooled`: the model takes `pool_cells`'s input (metadata
    `spinnet.input = pooled`, the point MLP's product `spinnet.point_weights`; descriptors/spinnet/
    quantize.py), else the grouped cells."""

    ref = None
    ref_path = None

    def __init__(self, path: Path, threads: int, providers="auto") -> None:
        self.desc_path = path
        self.desc = _session(path, threads, providers)
        meta = self.desc.get_modelmeta().custom_metadata_map or {}
        if meta.get("fastmac.preprocess") != "spinnet":
            raise InputError(
                f"model {path} is not a SpinNet model (its metadata lacks fastmac.preprocess=spinnet)"
            )
        self.params = SpinNetParams.from_metadata(meta, str(path))
        self.metadata = dict(meta)
        kind = meta.get("spinnet.input", "cells")
        if kind not in INPUTS:
            raise InputError(f"model {path}: metadata spinnet.input={kind!r}, expected one of {INPUTS}")
        self.pooled = kind == "pooled"
        self.point_weights = None
        if self.pooled:
            try:
                w = np.asarray(json.loads(meta["spinnet.point_weights"]), dtype=np.float32)
            except (KeyError, ValueError, TypeError) as exc:
                raise InputError(
                    f"model {path}: a pooled SpinNet model needs spinnet.point_weights, a (3, F) list ({exc})"
                ) from exc
            if w.ndim != 2 or w.shape[0] != 3 or w.shape[1] < 1:
                raise InputError(f"model {path}: spinnet.point_weights has shape {w.shape}, expected (3, F)")
            self.point_weights = w
            shape = (self.params.cells, w.shape[1])
        else:
            shape = (self.params.size, 3)
        self.input_name, self.output_dim = check_desc_contract(self.desc, path, self.params, shape)


class SpinNetDescriptor(BufferDescriptor):
    """SpinNet's published descriptor through onnxruntime (module docstring).

    `model`: "auto" (the pair's family picks `model_3dmatch` for 3dmatch/3dlomatch, `model_kitti` for kitti,
    as for BUFFER), "3dmatch", "kitti" or the path of a model meeting the contract. `keypoints`: at most this
    many keypoints a cloud (None: the model's default, 1,000 indoors, 2,500 for KITTI; 0 = every voxel
    keypoint); each costs ~0.01-0.015 s of one CPU core in INT8, ~3x that in float32 (MODEL_CARD.md).
    `sampling`: how they are chosen among the voxel keypoints, "fps" (farthest points) or "random" (None:
    the model's, fps indoors, random for KITTI). `downsample`: the patch cloud's grid in metres at scale 1
    (None: the model's). The rest as BUFFER's: `voxel_size`, `scale`, `max_correspondences`, `mutual`,
    `threads`, `batch_size`, `execution_providers`, `seed`, `progress`, `cache_clouds` (a cloud shared by
    pairs is described once), `axis` (None: the model's; "pca" or "none" to override). `precision`:
    "float32" (the exported weights) or "int8" (`model_3dmatch_int8` / `model_kitti_int8`,
    descriptors/spinnet/quantize.py: the point MLP's max in the C++ core, the convolutions quantised; rows
    labelled `spinnet_int8`)."""

    name = "spinnet"
    default_graph_key = "spinnet"
    cost_note = (
        "SpinNet (INT8) describes 1,000 keypoints a 3DMatch fragment in ~15 s and 2,500 a KITTI scan in "
        "~20-30 s on a loaded 2-core CPU (float32: ~3x that); descriptor.keypoints=N trades speed for "
        "inliers; a pair in the correspondence cache is not described again"
    )

    def __init__(
        self,
        model: str = "auto",
        model_3dmatch: str = SHIPPED["3dmatch"],
        model_kitti: str = SHIPPED["kitti"],
        model_3dmatch_int8: str = SHIPPED_INT8["3dmatch"],
        model_kitti_int8: str = SHIPPED_INT8["kitti"],
        precision: str = "float32",
        keypoints: int | None = None,
        sampling: str | None = None,
        downsample: float | None = None,
        voxel_size: float | None = None,
        scale: float | None = None,
        max_correspondences: int = 5000,
        mutual: bool = False,
        threads: int = 1,
        batch_size: int = 8,
        seed: int = 0,
        progress: bool = True,
        axis: str | None = None,
        cache_clouds: int = 8,
        execution_providers="auto",
        graph_key: str | None = None,
        lanes: int | str = "auto",
    ) -> None:
        FeatureDescriptor.__init__(self, graph_key)
        if keypoints is not None and keypoints < 0:
            raise InputError(f"spinnet keypoints must be >= 0 (0 = every voxel keypoint), got {keypoints}")
        if sampling is not None and sampling not in SAMPLINGS:
            raise InputError(f"spinnet sampling must be one of {SAMPLINGS}, got {sampling!r}")
        if downsample is not None and downsample < 0:
            raise InputError(f"spinnet downsample must be >= 0 or None (the model's), got {downsample}")
        if axis not in (None, "pca", "none"):
            raise InputError(f"spinnet axis must be null, 'pca' or 'none', got {axis!r}")
        self._set_common(
            "spinnet", model, model_3dmatch, model_kitti, voxel_size, scale, max_correspondences, mutual,
            threads, batch_size, seed, progress, axis, cache_clouds, execution_providers, lanes,
        )  # fmt: skip
        self._set_precision(precision, model_3dmatch_int8, model_kitti_int8)
        self.max_keypoints = None if keypoints is None else int(keypoints)
        self.sampling = sampling
        self.downsample = downsample
        if self.model != "auto":
            self.load(self.model)

    title = "SpinNet"
    quantize_script = "descriptors/spinnet/quantize.py"

    def _open_model(self, path: Path) -> SpinNetModel:
        return SpinNetModel(path, self.session_threads(), self.execution_providers)

    def model_for(self, family: str) -> SpinNetModel:
        if self.model != "auto":
            return self.load(self.model)
        if family not in FAMILIES:
            raise InputError(
                f"descriptor=spinnet: no SpinNet model for family {family!r}; set descriptor.model"
            )
        return self.load(FAMILIES[family].buffer_model)  # the learned models' training set (3dmatch | kitti)

    # -- keypoints: a seeded subset of the voxel keypoints

    def keypoints(self, points, voxel, what="cloud", family="3dmatch"):
        """The voxel keypoints, then at most `keypoints` of them (None: the model's own default, 1,000 for the
        3DMatch model, 2,500 for KITTI's), by `sampling` (None: the model's, fps / random)."""
        pts, kp = voxel_keypoints(points, voxel, what)
        which = (
            self.model
            if self.model != "auto"
            else FAMILIES[family].buffer_model
            if family in FAMILIES
            else ""
        )
        n_default, how_default = MODEL_KEYPOINTS.get(which, MODEL_KEYPOINTS["3dmatch"])
        n = self.max_keypoints if self.max_keypoints is not None else n_default
        how = self.sampling or how_default
        if n and len(kp) > n:
            if how == "fps":
                kp = kp[farthest_points(kp, n, self.seed)]
            else:
                kp = kp[np.sort(np.random.default_rng(self.seed).choice(len(kp), size=n, replace=False))]
        return pts, kp

    # -- description (BufferDescriptor.describe keeps the per-cloud caches)

    def _describer_key(self, model) -> tuple:
        return (*super()._describer_key(model), self.downsample)

    def _state(self, model, how: str, pts: np.ndarray, key: tuple):
        state = self._states.get(key)
        if state is not None:
            self._states.move_to_end(key)
            return state, {"clouds_s": 0.0}
        t0 = time.perf_counter()
        down = model.params.downsample if self.downsample is None else self.downsample
        cloud = voxel_down(pts, down) if down > 0 else np.asarray(pts, dtype=np.float64)
        cloud = cloud[np.random.default_rng(self.seed).permutation(len(cloud))]
        state = CloudState(cloud, cKDTree(cloud), None, None)
        self._remember(self._states, key, state)
        return state, {"clouds_s": time.perf_counter() - t0}

    def _model_input(self, model, state: CloudState, k: np.ndarray, how: str, axes) -> np.ndarray:
        patch = self.patches(model, state, k, how)
        if model.pooled:
            return pool_cells(patch, model.params, model.point_weights)
        return group_cells(patch, model.params)

    def patches(self, model, state: CloudState, kp: np.ndarray, how: str) -> np.ndarray:
        """Aligned patches `(M, patch_points, 3)` float64 of the keypoints `kp` (steps 3-4)."""
        p = model.params
        index = state.index_for(p.des_r, p.patch_points)
        patch = (
            cut_patches(state.cloud, state.tree, kp, p.des_r, p.patch_points, index=index) - kp[:, None, :]
        )
        if how == "pca":
            patch = patch @ align_rotations(pca_axes(patch, kp))
        return patch


__all__ = [
    "SpinNetDescriptor",
    "SpinNetParams",
    "azimuth_rotations",
    "cell_centres",
    "group_cells",
    "pool_cells",
]
