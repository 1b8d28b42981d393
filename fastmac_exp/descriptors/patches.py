"""Learned-descriptor preprocessing (numpy / scipy): keypoints, normals, local reference frames and the
multi-scale LRF patches the ONNX models embed. Shared by the runtime front end (onnx_descriptor.py) and
the training recipe (descriptors/fcgf_lite/train.py), so that training and runtime cannot drift."""

from __future__ import annotations

from dataclasses import dataclass, fields

import numpy as np
from scipy.spatial import cKDTree

from fastmac_exp.descriptors.keypoints import MIN_POINTS, clean_points, keypoints, voxel_down  # noqa: F401
from fastmac_exp.errors import InputError


@dataclass(frozen=True)
class PatchParams:
    """How patches are cut (lengths are factors of the voxel size).

    Scale 1: the `k` nearest points of the cloud downsampled at `support_factor * voxel`, within
    R1 = `radius_factor * voxel`. Scale 2 (when `k2 > 0`): `k2` points of the cloud at
    `support_factor2 * voxel` within R2 = `radius_factor2 * voxel`, and a scale-flag channel.
    """

    k: int = 64
    radius_factor: float = 6.0
    support_factor: float = 1.0
    features: str = "lrf_n"
    k2: int = 48
    radius_factor2: float = 12.0
    support_factor2: float = 2.5

    def __post_init__(self) -> None:
        if self.features not in FEATURES:
            raise InputError(f"patch features must be one of {sorted(FEATURES)}, got {self.features!r}")
        if self.k < 4 or not (self.k2 == 0 or self.k2 >= 4):
            raise InputError(f"patch sizes must be at least 4 (k2 = 0: one scale), got {self.k}, {self.k2}")
        factors = (self.radius_factor, self.support_factor, self.radius_factor2, self.support_factor2)
        if not all(f > 0 for f in factors):
            raise InputError(f"radius and support factors must be positive, got {factors}")

    @property
    def size(self) -> int:
        """K of the model input: points per patch over all scales."""
        return self.k + self.k2

    @property
    def channels(self) -> int:
        """C of the model input."""
        return FEATURES[self.features] + (1 if self.k2 else 0)

    def scales(self) -> list[tuple[int, float, float]]:
        """(k, radius_factor, support_factor) per scale."""
        out = [(self.k, self.radius_factor, self.support_factor)]
        if self.k2:
            out.append((self.k2, self.radius_factor2, self.support_factor2))
        return out


def local_frames(local: np.ndarray, valid: np.ndarray, radius: float) -> np.ndarray:
    """LRFs of patches: `local (M, K, 3)` offsets, `valid (M, K)` -> `(M, 3, 3)`, rows x y z."""
    d = np.linalg.norm(local, axis=2)
    w = np.where(valid, np.clip(radius - d, 0.0, None), 0.0)  # (M, K)
    wsum = w.sum(axis=1)
    wsum = np.where(wsum > 0, wsum, 1.0)
    cov = np.matmul((local * w[:, :, None]).transpose(0, 2, 1), local) / wsum[:, None, None]
    _, vecs = np.linalg.eigh(cov)  # ascending eigenvalues; columns are eigenvectors
    z = vecs[:, :, 0]
    h = np.matmul(local, z[:, :, None])[:, :, 0]
    flip = (w * h).sum(axis=1) > 0  # patch should lie below the keypoint: sum w p.z <= 0
    z = np.where(flip[:, None], -z, z)
    h = np.where(flip[:, None], -h, h)
    tang = local - h[:, :, None] * z[:, None, :]
    wx = w * w * h * h
    x = np.matmul(wx[:, None, :], tang)[:, 0, :]
    nx = np.linalg.norm(x, axis=1)
    # fallback: largest eigenvector, signed by the majority of projections
    e = vecs[:, :, 2]
    s = (w * np.sign(np.matmul(local, e[:, :, None])[:, :, 0])).sum(axis=1)
    e = np.where((s < 0)[:, None], -e, e)
    scale = np.sqrt(np.einsum("mk,mk->m", wx, np.einsum("mki,mki->mk", tang, tang))) + 1e-12
    weak = nx < 1e-3 * scale + 1e-12
    x = np.where(weak[:, None], e, x / np.where(nx > 0, nx, 1.0)[:, None])
    # re-orthogonalise x against z, then y = z x x
    x = x - np.einsum("mi,mi->m", x, z)[:, None] * z
    x /= np.linalg.norm(x, axis=1, keepdims=True) + 1e-12
    y = np.cross(z, x)
    return np.stack([x, y, z], axis=1)


def point_normals(points: np.ndarray, k: int = 10, tree: cKDTree | None = None) -> np.ndarray:
    """Unoriented unit normals (smallest covariance eigenvector of the k nearest points), `(N, 3)`."""
    tree = tree if tree is not None else cKDTree(points)
    k = min(k, len(points))
    _, idx = tree.query(points, k=k)
    nb = points[idx.reshape(len(points), -1)]
    nb = nb - nb.mean(axis=1, keepdims=True)
    cov = np.matmul(nb.transpose(0, 2, 1), nb)
    return np.linalg.eigh(cov)[1][:, :, 0]


FEATURES = {"lrf": 3, "lrf_n": 5, "cyl": 4}


def scale_patches(
    keypoints: np.ndarray,
    support: np.ndarray,
    radius: float,
    k: int,
    features: str,
    tree: cKDTree | None = None,
    normals: np.ndarray | None = None,
) -> np.ndarray:
    """One scale's patches: `(M, k, FEATURES[features])` float32 (see the module docstring)."""
    kp = np.asarray(keypoints, dtype=np.float64)
    if len(kp) == 0:
        return np.zeros((0, k, FEATURES[features]), dtype=np.float32)
    tree = tree if tree is not None else cKDTree(support)
    kk = min(k, len(support))
    dist, idx = tree.query(kp, k=kk, distance_upper_bound=radius)
    if kk == 1:
        dist, idx = dist[:, None], idx[:, None]
    valid = np.isfinite(dist)
    valid[:, 0] = True  # the nearest support point (the keypoint's own voxel) always counts
    idx = np.where(valid, idx, idx[:, :1])  # pad with the nearest point: a max-pool ignores duplicates
    if kk < k:  # tiny clouds
        idx = np.concatenate([idx, np.repeat(idx[:, :1], k - kk, axis=1)], axis=1)
        valid = np.concatenate([valid, np.zeros((len(kp), k - kk), dtype=bool)], axis=1)
    local = support[idx] - kp[:, None, :]
    frames = local_frames(local, valid, radius)
    xyz = np.matmul(local, frames.transpose(0, 2, 1)) / radius
    if features == "lrf":
        return xyz.astype(np.float32)
    if normals is None:
        normals = point_normals(support, tree=tree)
    n = np.matmul(normals[idx], frames.transpose(0, 2, 1))  # neighbour normals in the LRF (unsigned)
    rho = np.sqrt(xyz[:, :, 0] ** 2 + xyz[:, :, 1] ** 2)
    nz = np.abs(n[:, :, 2])
    nr = np.abs(n[:, :, 0] * xyz[:, :, 0] + n[:, :, 1] * xyz[:, :, 1]) / np.maximum(rho, 1e-9)
    nr = np.where(rho > 1e-9, nr, 0.0)
    if features == "lrf_n":
        return np.concatenate([xyz, nz[..., None], nr[..., None]], axis=2).astype(np.float32)
    return np.stack([rho, xyz[:, :, 2], nz, nr], axis=2).astype(np.float32)


def extract_patches(
    keypoints: np.ndarray, supports: list[np.ndarray], voxel: float, params: PatchParams
) -> np.ndarray:
    """Model input `(M, params.size, params.channels)` float32 for `keypoints`; one support cloud a scale."""
    parts = []
    for s, ((k, rf, _), support) in enumerate(zip(params.scales(), supports, strict=True)):
        x = scale_patches(keypoints, support, rf * voxel, k, params.features)
        if params.k2:
            x = np.concatenate([x, np.full(x.shape[:2] + (1,), float(s), dtype=np.float32)], axis=2)
        parts.append(x)
    return np.concatenate(parts, axis=1)


def support_clouds(points: np.ndarray, keypoints: np.ndarray, voxel: float, params: PatchParams) -> list:
    """The support cloud of each scale (the keypoints themselves where the support factor is 1)."""
    return [keypoints if sf == 1.0 else voxel_down(points, sf * voxel) for _, _, sf in params.scales()]


def cloud_patches(
    points: np.ndarray, voxel: float, params: PatchParams, what: str = "cloud"
) -> tuple[np.ndarray, np.ndarray]:
    """Keypoints `(M, 3)` float64 and their model input `(M, K, C)` float32 for one cloud."""
    pts, kp = keypoints(points, voxel, what)
    return kp, extract_patches(kp, support_clouds(pts, kp, voxel, params), voxel, params)


class CylinderGrid:
    """For the dataclasses of the cylindrical-patch descriptors (BUFFER, SpinNet): their grid of
    rad_n x ele_n x azi_n cells with `samples` points a cell, and the fields read back from a model's
    metadata, stored as `<metadata_prefix>.<field>`."""

    metadata_prefix = ""

    @property
    def cells(self) -> int:
        return self.rad_n * self.ele_n * self.azi_n

    @property
    def size(self) -> int:
        """K of the network's input: cells x points a cell."""
        return self.cells * self.samples

    @classmethod
    def from_metadata(cls, meta: dict, where: str):
        values = {}
        for f in fields(cls):
            key = f"{cls.metadata_prefix}.{f.name}"
            raw = meta.get(key)
            if raw is None:
                continue
            try:
                values[f.name] = type(f.default)(raw)
            except ValueError as exc:
                raise InputError(f"model {where}: metadata {key}={raw!r} is not valid") from exc
        return cls(**values)
