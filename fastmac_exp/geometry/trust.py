"""Whether a pose can be trusted, without ground truth (docs/trust.md).

A pose T explains k correspondences (|T s_i - t_i| < tau). The test asks whether k is more than the
pose would explain if it were wrong, with three wrong-pose explanations, each measured on the pair itself:

- chance: a random matching of the same points puts lambda = (1/N) sum_i #{j : |T s_i - t_j| < tau}
  correspondences within tau under T (large for dense clouds and large thresholds: object scans);
- the search's own pick: the pose was fitted on its clique (c), and a search that keeps the best of many
  poses finds more than lambda even when the matches carry no information: the decoy (the same sampler
  and MAC on the correspondences with their targets permuted) measures that excess on these clouds;
- structure: within one scene a wrong pose can line up walls and floors. The best *distinct* hypothesis
  the search itself scored (rotation or translation, at the source's centre, beyond the family's success
  thresholds from the chosen pose) is the rival; a pose that does not clearly beat its rival's excess over
  chance is ambiguous, whatever its count.

The null count is Poisson with mean max(c, 3) + lambda + max(decoy excess, RIVAL_MARGIN x the rival's
excess); confidence = 1 - P(X >= k) and trusted = confidence >= TRUST_LEVEL. Where neither the decoy nor
a rival was measured (a backend that keeps no hypotheses, the decoy off), the structure allowance
STRUCTURE_RATE x N of the previous test stands in for both.
"""

from __future__ import annotations

from typing import NamedTuple

import numpy as np

# confidence a pose needs to be trusted: a false-accept chance of 1 % under the null
TRUST_LEVEL = 0.99
# how much more than its best distinct rival's excess over chance a trusted pose must explain; chosen on
# the calibration half of benchmarks/calibrate_trust.py's pairs and reported on the other half
# (docs/trust.md)
RIVAL_MARGIN = 2.0
# the previous test's allowance for structure (1 % of N), used only where no rival and no decoy was
# measured: out of sample it both accepted wrong poses and rejected right ones (docs/trust.md)
STRUCTURE_RATE = 0.01
# the best-scored distinct hypotheses whose support beyond the chosen pose's is counted on every
# correspondence (bounded work: RIVALS x N)
RIVALS = 16
# sources and targets the chance rate is estimated on (strides over the set): bounded work at 10^6
CHANCE_SAMPLE = 20_000


class Trust(NamedTuple):
    trusted: bool
    confidence: float
    chance_inliers: float  # lambda: the correspondences chance explains under this pose
    rival_inliers: float = float("nan")  # what the best rival explains that the pose does not (NaN: none)
    rival_chance: float = float("nan")  # ... and chance's count under it
    null_mean: float = float("nan")  # the Poisson mean k was tested against


class ChanceCounter:
    """lambda for any pose over one set of correspondences: the target tree is built once (a stride of at
    most CHANCE_SAMPLE targets, its counts scaled back to all N)."""

    def __init__(self, src: np.ndarray, tgt: np.ndarray, threshold: float) -> None:
        n = len(src)
        self.threshold = float(threshold)
        self.sources = src[:: max(1, n // CHANCE_SAMPLE)] if n else src
        t_step = max(1, n // CHANCE_SAMPLE)
        self.scale = n / max(1, len(tgt[::t_step])) if n else 0.0
        from scipy.spatial import cKDTree  # here, not at import: `import fastmac_exp` stays light

        self.tree = cKDTree(tgt[::t_step]) if n else None

    def __call__(self, pose: np.ndarray) -> float:
        if self.tree is None:
            return 0.0
        moved = self.sources @ pose[:3, :3].T + pose[:3, 3]
        near = self.tree.query_ball_point(moved, self.threshold, return_length=True)
        return float(np.mean(near)) * self.scale


def chance_inliers(src: np.ndarray, tgt: np.ndarray, pose: np.ndarray, threshold: float) -> float:
    """lambda: how many correspondences a random matching of the same points puts within `threshold`
    under `pose` (expected over the matching)."""
    return ChanceCounter(src, tgt, threshold)(pose)


def explained(src: np.ndarray, tgt: np.ndarray, pose: np.ndarray, threshold: float) -> int:
    """How many correspondences the pose maps to within `threshold` of their target point."""
    residual = np.linalg.norm(src @ pose[:3, :3].T + pose[:3, 3] - tgt, axis=1)
    return int((residual < threshold).sum())


def distinct(poses: np.ndarray, pose: np.ndarray, centre: np.ndarray, re_deg: float, te_m: float) -> np.ndarray:
    """Which of `poses` (H, 4, 4) differ from `pose` by more than re_deg in rotation or te_m in where they
    put `centre` (the source's centre: a translation difference that does not depend on the origin)."""
    if len(poses) == 0:
        return np.zeros(0, bool)
    rel = np.einsum("hij,kj->hik", poses[:, :3, :3], pose[:3, :3])  # R_h R^T
    cos = np.clip((np.trace(rel, axis1=1, axis2=2) - 1.0) / 2.0, -1.0, 1.0)
    angle = np.degrees(np.arccos(cos))
    at = poses[:, :3, :3] @ centre + poses[:, :3, 3]
    shift = np.linalg.norm(at - (pose[:3, :3] @ centre + pose[:3, 3]), axis=1)
    return (angle > re_deg) | (shift > te_m)


def rival_support(
    poses: np.ndarray | None,
    scores: np.ndarray | None,
    pose: np.ndarray,
    src: np.ndarray,
    tgt: np.ndarray,
    threshold: float,
    re_deg: float,
    te_m: float,
    chance: ChanceCounter,
) -> tuple[float, float]:
    """(count, chance) of the best rival: among the RIVALS best-scored hypotheses distinct from `pose`,
    the one that explains the most correspondences `pose` does not explain. A near copy of the chosen
    pose explains the same matches (and is not a rival, whatever its distance); a wrong pose that
    structure supports explains others. (NaN, NaN): the backend kept no hypotheses; (0, 0): none is
    distinct (the search saw no other pose)."""
    if poses is None or scores is None:
        return float("nan"), float("nan")
    far = np.flatnonzero(distinct(poses, pose, src.mean(axis=0), re_deg, te_m)) if len(poses) else []
    if not len(far):
        return 0.0, 0.0
    top = far[np.argsort(-scores[far], kind="stable")[:RIVALS]]
    mine = np.linalg.norm(src @ pose[:3, :3].T + pose[:3, 3] - tgt, axis=1) < threshold
    others = src[~mine], tgt[~mine]
    counts = [explained(*others, poses[h], threshold) for h in top]
    best = top[int(np.argmax(counts))]
    return float(max(counts)), chance(poses[best])


def decide(
    inliers: int,
    clique: int,
    lam: float,
    n: int,
    rival_excess: float | None = None,
    decoy_count: float | None = None,
    margin: float | None = None,
) -> tuple[float, float]:
    """(confidence, null mean) of a pose explaining `inliers` of n, fitted on `clique`, with chance count
    `lam`. decoy_count: what the decoy's pose explained beyond chance (None or NaN: not run; the pose's own
    clique stands in, a bound that is high where the clique holds most of the inliers); rival_excess: what
    the best rival explains beyond the pose and chance (None or NaN: the backend kept no hypotheses; the
    previous 1 % allowance stands in)."""
    margin = RIVAL_MARGIN if margin is None else margin
    measured = decoy_count is not None and np.isfinite(decoy_count)
    search = max(float(decoy_count), 3.0) if measured else float(max(int(clique), 3))
    if rival_excess is not None and np.isfinite(rival_excess):
        structure = margin * max(float(rival_excess), 0.0)
    else:
        structure = STRUCTURE_RATE * n
    mean = lam + max(search, structure)
    if inliers <= 0:
        return 0.0, mean
    from scipy.special import gammainc  # not scipy.stats: 0.4 s less on a process's first call

    p = float(gammainc(int(inliers), mean))  # P(X >= inliers) for X ~ Poisson(mean)
    return 1.0 - min(max(p, 0.0), 1.0), mean


def assess(
    src: np.ndarray,
    tgt: np.ndarray,
    pose: np.ndarray,
    threshold: float,
    inliers: int,
    clique: int,
    *,
    rival: tuple[float, float] | None = None,
    decoy_count: float | None = None,
    chance: ChanceCounter | None = None,
) -> Trust:
    """Trust of a pose that maps `inliers` of the correspondences (src, tgt) within `threshold`, fitted on
    a clique of `clique`. rival: (count, chance) of the best rival the search scored (rival_support);
    decoy_count: what the same search explained beyond chance on permuted matches (None: not run)."""
    if not np.isfinite(pose).all():
        return Trust(False, 0.0, float("nan"))
    chance = chance if chance is not None else ChanceCounter(src, tgt, threshold)
    lam = chance(pose)
    rival_k, rival_lam = rival if rival is not None else (float("nan"), float("nan"))
    confidence, mean = decide(inliers, clique, lam, len(src), rival_k - rival_lam, decoy_count)
    return Trust(confidence >= TRUST_LEVEL, confidence, lam, rival_k, rival_lam, mean)
