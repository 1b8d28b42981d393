"""What every feature front end starts from: the cloud without non-finite rows, and its voxel keypoints.

Two implementations of the voxel grid (`impl`): Open3D's `voxel_down_sample` (the reference) and the C++
core's (fastmac_exp/_cpp/fpfh.cpp), which gives the same centroids to the last bit, ordered by voxel
instead of Open3D's hash-map order. "auto" takes the core where it is built. FPFH uses "auto"; the learned
front ends keep Open3D's order, which their recorded results were made with.
"""

from __future__ import annotations

import numpy as np

from fastmac_exp.errors import InputError

MIN_POINTS = 10
IMPLS = ("auto", "core", "open3d")


def resolve_impl(impl: str) -> str:
    """ "core" or "open3d" for a configured `impl` ("auto": the core where the extension is built)."""
    from fastmac_exp import core

    if impl not in IMPLS:
        raise InputError(f"impl must be one of {IMPLS}, got {impl!r}")
    if impl == "auto":
        return "core" if core.available() else "open3d"
    if impl == "core":
        core.core()  # BackendUnavailable with the build instructions when it is missing
    return impl


def clean_points(points: np.ndarray, what: str = "cloud") -> np.ndarray:
    """The cloud as (N, 3) float64 with non-finite rows dropped."""
    pts = np.asarray(points, dtype=np.float64)
    if pts.ndim != 2 or pts.shape[1] != 3:
        raise InputError(f"{what} must have shape (N, 3), got {pts.shape}")
    return np.ascontiguousarray(pts[np.isfinite(pts).all(axis=1)])


def voxel_down(points: np.ndarray, voxel: float, impl: str = "open3d") -> np.ndarray:
    """Voxel centroids of a finite cloud (`impl` as above)."""
    pts = np.ascontiguousarray(points, dtype=np.float64)
    if resolve_impl(impl) == "core":
        from fastmac_exp import core

        try:
            return core.core().voxel_downsample(pts, float(voxel))
        except ValueError as exc:
            raise InputError(f"{exc} (descriptor.impl=open3d has no such limit)") from None
    from fastmac_exp._open3d import o3d

    pcd = o3d.geometry.PointCloud(o3d.utility.Vector3dVector(pts))
    return np.asarray(pcd.voxel_down_sample(float(voxel)).points, dtype=np.float64)


def keypoints(
    points: np.ndarray, voxel: float, what: str = "cloud", impl: str = "open3d"
) -> tuple[np.ndarray, np.ndarray]:
    """(the cleaned cloud, its voxel keypoints at `voxel`); InputError below MIN_POINTS keypoints."""
    pts = clean_points(points, what)
    return pts, _keypoints_of(pts, voxel, what, impl, "the descriptor")


def voxel_keypoints(
    points: np.ndarray, voxel: float, what: str = "cloud", impl: str = "open3d", who: str = "the descriptor"
) -> np.ndarray:
    """The voxel keypoints of the cloud's finite points alone: the core drops non-finite rows itself, so it
    gets the cloud as given, without a cleaned copy."""
    if resolve_impl(impl) != "core":
        return keypoints(points, voxel, what, impl)[1]
    pts = np.asarray(points, dtype=np.float64)
    if pts.ndim != 2 or pts.shape[1] != 3:
        raise InputError(f"{what} must have shape (N, 3), got {pts.shape}")
    return _keypoints_of(np.ascontiguousarray(pts), voxel, what, impl, who)


def _keypoints_of(pts: np.ndarray, voxel: float, what: str, impl: str, who: str) -> np.ndarray:
    if voxel is None or not voxel > 0:
        raise InputError(f"{who}: voxel size must be positive, got {voxel}")
    try:
        kp = voxel_down(pts, voxel, impl)
    except InputError as exc:
        raise InputError(f"{what}: {exc}") from None
    require_keypoints(kp, len(pts), voxel, what, who)
    return kp


def require_keypoints(
    kp: np.ndarray, n_points: int, voxel: float, what: str, who: str = "the descriptor"
) -> None:
    """InputError when fewer than MIN_POINTS keypoints survived the voxel grid."""
    if len(kp) < MIN_POINTS:
        raise InputError(
            f"{what} has {len(kp)} point(s) after voxel downsampling at {voxel} m (from {n_points}); "
            f"{who} needs at least {MIN_POINTS}. Is the voxel size right for the cloud's units?"
        )


def spread_rows(kp: np.ndarray, cap: int, steps: int = 10) -> np.ndarray:
    """Sorted rows of at most `cap` keypoints spread evenly over the cloud: one a cell of the finest cubic
    grid (anchored at the keypoints' lower corner) with at most `cap` occupied cells, the keypoint nearest its
    cell's centre (ties: the lower row). The grid size is bisected in `steps` geometric steps, so the count
    lands a few per cent below `cap`. Every row when `cap` is not below len(kp). Deterministic: a cloud's
    subset is the same in every pair and run, so its described rows are reused."""
    pts = np.asarray(kp, dtype=np.float64)
    if cap < 1:
        raise InputError(f"a keypoint cap must be >= 1, got {cap}")
    if len(pts) <= cap:
        return np.arange(len(pts))
    lower = pts.min(axis=0)

    def cells(h: float) -> tuple[np.ndarray, np.ndarray]:
        ijk = np.floor((pts - lower) / h).astype(np.int64)
        dims = ijk.max(axis=0) + 1
        return ijk, (ijk[:, 0] * dims[1] + ijk[:, 1]) * dims[2] + ijk[:, 2]

    def count(h: float) -> int:
        return len(np.unique(cells(h)[1]))

    hi = float(np.ptp(pts, axis=0).max()) * 1.001 + 1e-12  # one cell holds them all
    lo = hi / 1024
    while count(lo) <= cap and lo > 1e-12:  # duplicates: even a fine grid holds few cells
        hi, lo = lo, lo / 1024
    for _ in range(steps):
        mid = (lo * hi) ** 0.5
        lo, hi = (mid, hi) if count(mid) > cap else (lo, mid)
    ijk, key = cells(hi)
    d2 = (((pts - lower) - (ijk + 0.5) * hi) ** 2).sum(axis=1)
    order = np.lexsort((np.arange(len(pts)), d2, key))
    ks = key[order]
    first = np.ones(len(ks), dtype=bool)
    first[1:] = ks[1:] != ks[:-1]
    return np.sort(order[first])
