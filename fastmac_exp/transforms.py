"""Rigid-transform helpers: Kabsch fits, errors against ground truth, rigidity checks."""

from __future__ import annotations

import numpy as np

from fastmac_exp.errors import InputError


def kabsch(src: np.ndarray, tgt: np.ndarray, weights: np.ndarray | None = None) -> np.ndarray:
    """Least-squares rigid T (4x4) with tgt ~ R src + t, as MAC's C++ fits it (spec 5.1).

    Centroids are the unweighted means; the weights enter only the cross-covariance
    H = sum w (p - p_bar)(q - q_bar)^T. A reflection is fixed by flipping the last singular vector.
    """
    p_bar = src.mean(axis=0)
    q_bar = tgt.mean(axis=0)
    p = src - p_bar
    q = tgt - q_bar
    h = (p * (weights[:, None] if weights is not None else 1.0)).T @ q
    u, _, vt = np.linalg.svd(h)
    v = vt.T
    if np.linalg.det(u) * np.linalg.det(v) < 0:
        v[:, 2] = -v[:, 2]
    r = v @ u.T
    t = q_bar - r @ p_bar
    pose = np.eye(4)
    pose[:3, :3] = r
    pose[:3, 3] = t
    return pose


def rotation_error_deg(r_est: np.ndarray, r_gt: np.ndarray) -> float:
    """RE = arccos((tr(R_est^T R_gt) - 1) / 2) in degrees (spec 6)."""
    c = (np.trace(r_est.T @ r_gt) - 1.0) / 2.0
    return float(np.degrees(np.arccos(np.clip(c, -1.0, 1.0))))


def translation_error_m(t_est: np.ndarray, t_gt: np.ndarray) -> float:
    return float(np.linalg.norm(t_est - t_gt))


def check_rigid(t: np.ndarray, where: str = "transform", tol: float = 1e-4) -> np.ndarray:
    """Return t as a float64 4x4 array, or raise InputError if it is not a rigid transform."""
    t = np.asarray(t, dtype=np.float64)
    if t.shape != (4, 4):
        raise InputError(f"{where}: expected a 4x4 matrix, got shape {t.shape}")
    if not np.isfinite(t).all():
        raise InputError(f"{where}: matrix has NaN or inf entries")
    r = t[:3, :3]
    if not np.allclose(t[3], [0, 0, 0, 1], atol=tol):
        raise InputError(f"{where}: last row must be 0 0 0 1, got {t[3].tolist()}")
    if not np.allclose(r.T @ r, np.eye(3), atol=tol) or np.linalg.det(r) < 0:
        raise InputError(f"{where}: the 3x3 block is not a rotation (orthonormal with det +1)")
    return t


def random_rotation(rng: np.random.Generator, max_angle_deg: float = 180.0) -> np.ndarray:
    """A rotation about a uniformly random axis by an angle uniform in [0, max_angle_deg]."""
    axis = rng.normal(size=3)
    axis /= np.linalg.norm(axis)
    angle = np.radians(rng.uniform(0, max_angle_deg))
    k = np.array([[0, -axis[2], axis[1]], [axis[2], 0, -axis[0]], [-axis[1], axis[0], 0]])
    return np.eye(3) + np.sin(angle) * k + (1 - np.cos(angle)) * (k @ k)
