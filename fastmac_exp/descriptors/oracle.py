"""Oracle front end: correspondences with an exact, chosen inlier ratio, made from the ground truth.

For controlled studies (how MAC/FastMAC behave as the inlier ratio falls) independent of any feature.
Inliers pair a source point with its GT image plus truncated Gaussian noise (error < the inlier
threshold); outliers pair a source point with a random target point whose error under GT is at least
the threshold. Labels therefore equal `pair.label`'s by construction.
"""

from __future__ import annotations

import numpy as np

from fastmac_exp.descriptors.base import Descriptor
from fastmac_exp.errors import InputError
from fastmac_exp.types import Correspondences, Pair

_MAX_ROUNDS = 50


def _gt_error(src: np.ndarray, tgt: np.ndarray, gt: np.ndarray) -> np.ndarray:
    # the same expression as Pair.label, so that labels agree to the last bit
    return np.linalg.norm(src @ gt[:3, :3].T + gt[:3, 3] - tgt, axis=1)


class OracleDescriptor(Descriptor):
    """`num_correspondences` matches of which exactly round(N * inlier_ratio) are GT inliers.

    `noise` is the per-axis sigma (m) of the inliers' Gaussian noise (None: a quarter of the pair's
    inlier threshold); the noise is truncated so every inlier stays below the threshold.
    `keypoint_voxel` (m) draws points from a voxel-downsampled cloud instead of the raw one.
    """

    name = "oracle"
    default_graph_key = "fpfh"

    def __init__(
        self,
        num_correspondences: int = 5000,
        inlier_ratio: float = 0.1,
        noise: float | None = None,
        keypoint_voxel: float | None = None,
        graph_key: str | None = None,
    ) -> None:
        super().__init__(graph_key)
        if int(num_correspondences) != num_correspondences or num_correspondences < 1:
            raise InputError(f"oracle num_correspondences must be an integer >= 1, got {num_correspondences}")
        if not 0.0 <= float(inlier_ratio) <= 1.0:
            raise InputError(f"oracle inlier_ratio must be in [0, 1], got {inlier_ratio}")
        if noise is not None and not float(noise) >= 0.0:
            raise InputError(f"oracle noise must be >= 0 or None, got {noise}")
        if keypoint_voxel is not None and not float(keypoint_voxel) > 0.0:
            raise InputError(f"oracle keypoint_voxel must be positive or None, got {keypoint_voxel}")
        self.num_correspondences = int(num_correspondences)
        self.inlier_ratio = float(inlier_ratio)
        self.noise = None if noise is None else float(noise)
        self.keypoint_voxel = None if keypoint_voxel is None else float(keypoint_voxel)

    def _points(self, cloud: np.ndarray, what: str, pair: Pair) -> np.ndarray:
        pts = np.asarray(cloud, dtype=np.float64)
        if pts.ndim != 2 or pts.shape[1] != 3:
            raise InputError(f"pair {pair.name!r}: {what} cloud must have shape (N, 3), got {pts.shape}")
        pts = pts[np.isfinite(pts).all(axis=1)]
        if self.keypoint_voxel is not None:
            from fastmac_exp.datasets.scenes import voxel_downsample

            pts = voxel_downsample(pts, self.keypoint_voxel)
        if len(pts) == 0:
            raise InputError(f"pair {pair.name!r}: the {what} cloud has no finite points")
        return pts

    def __call__(self, pair: Pair, rng: np.random.Generator) -> Correspondences:
        if pair.gt is None:
            raise InputError(f"pair {pair.name!r}: the oracle descriptor needs the ground truth (pair.gt)")
        if pair.src_cloud is None or pair.tgt_cloud is None:
            raise InputError(
                f"pair {pair.name!r}: the oracle descriptor needs both point clouds, but "
                f"{'the source' if pair.src_cloud is None else 'the target'} cloud is missing"
            )
        gt = np.asarray(pair.gt, dtype=np.float64)
        thr = float(pair.inlier_threshold)
        if thr <= 0:
            raise InputError(f"pair {pair.name!r}: inlier_threshold must be positive, got {thr}")
        src_pts = self._points(pair.src_cloud, "source", pair)
        tgt_pts = self._points(pair.tgt_cloud, "target", pair)
        n = self.num_correspondences
        n_in = int(round(n * self.inlier_ratio))
        n_out = n - n_in
        sigma = thr / 4.0 if self.noise is None else self.noise

        # inliers: GT image + truncated Gaussian noise (|error| < thr)
        s_in = src_pts[rng.choice(len(src_pts), size=n_in, replace=n_in > len(src_pts))]
        image = s_in @ gt[:3, :3].T + gt[:3, 3]
        t_in = image + rng.normal(0.0, sigma, size=image.shape)
        bad = _gt_error(s_in, t_in, gt) >= thr
        for _ in range(_MAX_ROUNDS):
            if not bad.any():
                break
            t_in[bad] = image[bad] + rng.normal(0.0, sigma, size=(int(bad.sum()), 3))
            bad = _gt_error(s_in, t_in, gt) >= thr
        if bad.any():  # very large noise: put the rest at a random radius below the threshold
            d = rng.normal(size=(int(bad.sum()), 3))
            d /= np.linalg.norm(d, axis=1, keepdims=True)
            t_in[bad] = image[bad] + d * (thr * 0.99 * rng.random((len(d), 1)))

        # outliers: a random target point at least thr away from the GT image
        s_out = src_pts[rng.choice(len(src_pts), size=n_out, replace=n_out > len(src_pts))]
        t_out = tgt_pts[rng.integers(0, len(tgt_pts), size=n_out)]
        bad = _gt_error(s_out, t_out, gt) < thr
        for _ in range(_MAX_ROUNDS):
            if not bad.any():
                break
            t_out[bad] = tgt_pts[rng.integers(0, len(tgt_pts), size=int(bad.sum()))]
            bad = _gt_error(s_out, t_out, gt) < thr
        if bad.any():  # a target cloud (nearly) inside the threshold everywhere: displace the match
            img = s_out[bad] @ gt[:3, :3].T + gt[:3, 3]
            d = rng.normal(size=img.shape)
            d /= np.linalg.norm(d, axis=1, keepdims=True)
            t_out[bad] = img + d * thr * rng.uniform(1.5, 10.0, size=(len(d), 1))

        order = rng.permutation(n)
        corr = Correspondences(src=np.vstack([s_in, s_out])[order], tgt=np.vstack([t_in, t_out])[order])
        corr = pair.label(corr)
        assert corr.labels is not None and int(corr.labels.sum()) == n_in, "oracle labels disagree with GT"
        return corr
