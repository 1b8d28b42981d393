"""Peer methods as backends on the same correspondences, timed the same way (the state-of-the-art study).

Each returns a RegistrationResult whose whole time is under `pose` (they have no MAC stages).
"""

from __future__ import annotations

import time

import numpy as np

from fastmac_exp.errors import BackendUnavailable, RegistrationFailed
from fastmac_exp.params import MacParams
from fastmac_exp.types import Correspondences, RegistrationResult


def _result(pose: np.ndarray, n: int, ms: float) -> RegistrationResult:
    """A peer's answer: a pose and its time; peers report no clique."""
    return RegistrationResult(
        pose=pose,
        pose_unrefined=pose,
        kept=np.arange(n),
        clique=np.zeros(0, np.int64),
        timings={"graph": 0.0, "cliques": 0.0, "selection": 0.0, "pose": ms},
    )


def _o3d_inputs(corr: Correspondences):
    from fastmac_exp._open3d import o3d

    src = o3d.geometry.PointCloud(o3d.utility.Vector3dVector(corr.src))
    tgt = o3d.geometry.PointCloud(o3d.utility.Vector3dVector(corr.tgt))
    idx = np.tile(np.arange(len(corr), dtype=np.int32)[:, None], (1, 2))
    return o3d, src, tgt, o3d.utility.Vector2iVector(idx)


class RansacBackend:
    """Open3D's RANSAC on correspondences (3-point samples), a fixed iteration budget."""

    def __init__(self, max_iterations: int = 10000, confidence: float = 0.999, seed: int = 0) -> None:
        self.max_iterations = max_iterations
        self.confidence = confidence
        self.seed = seed
        self.name = (
            f"ransac{max_iterations // 1000}k" if max_iterations >= 1000 else f"ransac{max_iterations}"
        )

    def register(self, corr: Correspondences, params: MacParams) -> RegistrationResult:
        if len(corr) < 3:
            raise RegistrationFailed(f"need at least 3 correspondences, got {len(corr)}")
        o3d, src, tgt, idx = _o3d_inputs(corr)
        reg = o3d.pipelines.registration
        o3d.utility.random.seed(self.seed)
        t0 = time.perf_counter()
        out = reg.registration_ransac_based_on_correspondence(
            src, tgt, idx, params.inlier_threshold,
            reg.TransformationEstimationPointToPoint(False), 3, [],
            reg.RANSACConvergenceCriteria(self.max_iterations, self.confidence),
        )  # fmt: skip
        ms = (time.perf_counter() - t0) * 1e3
        return _result(np.asarray(out.transformation).copy(), len(corr), ms)


class FGRBackend:
    """Open3D's Fast Global Registration on the given correspondences."""

    name = "fgr"

    def __init__(self, iterations: int = 64) -> None:
        self.iterations = iterations

    def register(self, corr: Correspondences, params: MacParams) -> RegistrationResult:
        if len(corr) < 3:
            raise RegistrationFailed(f"need at least 3 correspondences, got {len(corr)}")
        o3d, src, tgt, idx = _o3d_inputs(corr)
        reg = o3d.pipelines.registration
        option = reg.FastGlobalRegistrationOption(
            maximum_correspondence_distance=params.inlier_threshold, iteration_number=self.iterations
        )
        t0 = time.perf_counter()
        out = reg.registration_fgr_based_on_correspondence(src, tgt, idx, option)
        ms = (time.perf_counter() - t0) * 1e3
        return _result(np.asarray(out.transformation).copy(), len(corr), ms)


class KissMatcherBackend:
    """KISS-Matcher (MIT-SPARK): ROBIN max-clique-style pruning + GNC-TLS solver on correspondences."""

    name = "kiss_matcher"

    def __init__(self, noise_bound_gain: float = 1.0) -> None:
        try:
            import kiss_matcher  # noqa: F401
        except ImportError as exc:
            raise BackendUnavailable(
                "backend=kiss_matcher needs the kiss-matcher package: pip install kiss-matcher"
            ) from exc
        self.noise_bound_gain = noise_bound_gain

    def register(self, corr: Correspondences, params: MacParams) -> RegistrationResult:
        import kiss_matcher

        if len(corr) < 3:
            raise RegistrationFailed(f"need at least 3 correspondences, got {len(corr)}")
        # the solver's noise bound is voxel_size * gain; we use the dataset's inlier threshold as the voxel
        cfg = kiss_matcher.KISSMatcherConfig(
            voxel_size=params.inlier_threshold, robin_noise_bound_gain=self.noise_bound_gain
        )
        matcher = kiss_matcher.KISSMatcher(cfg)
        src = [p.astype(np.float32).reshape(3, 1) for p in corr.src]
        tgt = [q.astype(np.float32).reshape(3, 1) for q in corr.tgt]
        t0 = time.perf_counter()
        sol = matcher.prune_and_solve(src, tgt)
        ms = (time.perf_counter() - t0) * 1e3
        pose = kiss_matcher_pose(sol)
        if pose is None:
            raise RegistrationFailed("kiss-matcher found no valid solution")
        return _result(pose, len(corr), ms)


def kiss_matcher_pose(sol) -> np.ndarray | None:
    """The 4x4 pose of a KISS-Matcher solution, None where the solver found no valid one."""
    if not sol.valid:
        return None
    pose = np.eye(4)
    pose[:3, :3] = np.asarray(sol.rotation)
    pose[:3, 3] = np.asarray(sol.translation).ravel()
    return pose
