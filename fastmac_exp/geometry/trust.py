"""Whether a pose can be trusted, without ground truth (docs/trust.md).

The evidence is how many correspondences the pose explains beyond the clique it was fitted on, against
how many chance explains under the same pose: a correspondence whose target is any target point of the
set (a random matching of the same clouds) lands within the inlier threshold of its transformed source
at rate lambda / N, where lambda = (1/N) sum_i #{j : |T s_i - t_j| < tau}. A pose of unrelated clouds
explains its clique and about lambda more; a right pose explains the other true matches too. The
p-value of the excess under Poisson(lambda), times the number of hypotheses the pose was picked from,
is the false-accept chance; `confidence` = 1 - that, and `trusted` = confidence >= TRUST_LEVEL.
"""

from __future__ import annotations

import math
from typing import NamedTuple

import numpy as np

# confidence a pose needs to be trusted: a false-accept chance of 1 % under the null (docs/trust.md
# calibrates it on the real pairs of ../shared/data and on unrelated pairs made of them)
TRUST_LEVEL = 0.99
# What a search finds beyond lambda on unrelated clouds of real scenes, as a share of the correspondences:
# FPFH matches planes to planes and edges to edges, so the best of the searched poses explains more than a
# random matching would: up to 0.65 % of N on the 30 unrelated pairs of docs/trust.md, 1.9 % the least a
# right pose explained there (KITTI 15->0)
STRUCTURE_RATE = 0.01
# sources the chance rate is estimated on (a stride over the set): bounded work on 10^6 correspondences
CHANCE_SAMPLE = 20_000


class Trust(NamedTuple):
    trusted: bool
    confidence: float
    chance_inliers: float  # lambda: the correspondences chance explains under this pose


def chance_inliers(src: np.ndarray, tgt: np.ndarray, pose: np.ndarray, threshold: float) -> float:
    """lambda: how many correspondences a random matching of the same points puts within `threshold`
    under `pose` (expected over the matching)."""
    n = len(src)
    if n == 0:
        return 0.0
    step = max(1, n // CHANCE_SAMPLE)
    moved = src[::step] @ pose[:3, :3].T + pose[:3, 3]
    from scipy.spatial import cKDTree  # here, not at import: `import fastmac_exp` stays light

    near = cKDTree(tgt).query_ball_point(moved, threshold, return_length=True)
    return float(np.mean(near))


def assess(
    src: np.ndarray, tgt: np.ndarray, pose: np.ndarray, threshold: float, inliers: int, clique: int
) -> Trust:
    """Trust of a pose that maps `inliers` of the correspondences (src, tgt) within `threshold`, fitted on
    a clique of `clique`."""
    if not np.isfinite(pose).all():
        return Trust(False, 0.0, float("nan"))
    lam = chance_inliers(src, tgt, pose, threshold)
    mean = max(int(clique), 3) + lam + STRUCTURE_RATE * len(src)
    from scipy.stats import poisson

    log_p = float(poisson.logsf(int(inliers) - 1, mean))  # log P(X >= inliers): exact far in the tail
    confidence = 1.0 - math.exp(min(log_p, 0.0))
    return Trust(confidence >= TRUST_LEVEL, confidence, lam)
