"""Planted correspondences: a known share of inliers (the GT pose plus Gaussian noise) among uniform outliers
in a box, for benchmarks, studies and tests at any N (50,000 to 1,000,000 in bench_core) without a point
cloud or a descriptor."""

from __future__ import annotations

import numpy as np

from fastmac_exp.geometry.transforms import random_rotation
from fastmac_exp.types import Correspondences

OUTDOOR_ROOM = (60.0, 60.0, 4.0)  # bench_core's outdoor-like scene (with noise 0.1 m)


def planted(
    n: int, inlier_ratio: float = 0.08, noise: float = 0.02, seed: int = 0, room: tuple = (3.0, 3.0, 2.5)
) -> tuple[Correspondences, np.ndarray]:
    """n correspondences in a `room` (3 x 3 x 2.5 m) around a random pose (rotation up to 60 degrees).

    round(n * inlier_ratio) inliers with Gaussian noise (std `noise` per axis); the outliers' targets are
    uniform in the moved room; the order is shuffled. Returns (Correspondences with labels, 4x4 GT).
    """
    rng = np.random.default_rng(seed)
    room = np.asarray(room, float)
    gt = np.eye(4)
    gt[:3, :3] = random_rotation(rng, 60.0)
    gt[:3, 3] = rng.uniform(-0.5, 0.5, 3)
    src = rng.uniform(0, 1, (n, 3)) * room
    tgt = src @ gt[:3, :3].T + gt[:3, 3]
    k = int(round(n * inlier_ratio))
    tgt[:k] += rng.normal(0, noise, (k, 3))
    tgt[k:] = (rng.uniform(0, 1, (n - k, 3)) * room) @ gt[:3, :3].T + gt[:3, 3]
    labels = np.zeros(n, bool)
    labels[:k] = True
    perm = rng.permutation(n)
    return Correspondences(src[perm], tgt[perm], labels=labels[perm]), gt
