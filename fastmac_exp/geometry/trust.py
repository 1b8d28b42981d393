"""Whether a pose can be trusted, without ground truth (docs/trust.md).

A pose T explains k correspondences (|T s_i - t_i| < tau). It is trusted when k is well beyond what a
wrong pose would explain on the same pair, each part measured on the pair itself:

- chance: a random matching of the same points puts lambda = (1/N) sum_i #{j : |T s_i - t_j| < tau}
  correspondences within tau under T (large for dense clouds and large thresholds: object scans);
- the search's pick: a search that keeps the best of many poses finds a consistent set even when the
  matches carry no information. The pose's own clique bounds it; where that bound leaves the pose
  untrusted (a tight clique of most of the inliers, a small set), the decoy measures it instead: the same
  sampler and MAC on the correspondences with their targets permuted;
- structure: FPFH matches planes to planes, so a wrong pose lines up walls and floors: STRUCTURE_RATE of N
  at any pose, and, where the search saw a distinct pose (rotation or translation at the source's centre
  beyond the family's success thresholds), what the best such rival explains that T does not, beyond
  chance (RIVAL_MARGIN times it): the ambiguity of a scene with two explanations.

The null count is Poisson with mean lambda + the largest of the three; confidence = 1 - P(X >= k), and
trusted = confidence >= TRUST_LEVEL.
"""

from __future__ import annotations

from typing import NamedTuple

import numpy as np

# confidence a pose needs to be trusted: a false-accept chance of 1 % under the null
TRUST_LEVEL = 0.99
# The two constants were chosen on the calibration half of benchmarks/calibrate_trust.py's pairs (no false
# accept there, then the fewest false rejects, then the larger) and are reported on the held-out half
# (docs/trust.md). What a wrong pose explains by structure at any pose, as a share of the correspondences:
STRUCTURE_RATE = 0.0125
# ... and how much of what its best distinct rival explains beyond it a wrong pose may explain too
RIVAL_MARGIN = 1.0
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
    """lambda for any pose over one set of correspondences (a stride of at most CHANCE_SAMPLE targets, its
    counts scaled back to all N): counted by the C++ core's grid (count_within) where it is built, else by a
    k-d tree built once; the two count the same (squared distance <= threshold^2)."""

    def __init__(self, src: np.ndarray, tgt: np.ndarray, threshold: float) -> None:
        from fastmac_exp import core

        n = self.n = len(src)
        self.threshold = float(threshold)
        self.sources = src[:: max(1, n // CHANCE_SAMPLE)] if n else src
        self.targets = np.ascontiguousarray(tgt[:: max(1, n // CHANCE_SAMPLE)], dtype=np.float64)
        self.scale = n / max(1, len(self.targets)) if n else 0.0
        self._count = core.core().count_within if core.available() and n else None
        self.tree = None
        if n and self._count is None:
            from scipy.spatial import cKDTree  # here, not at import: `import fastmac_exp` stays light

            self.tree = cKDTree(self.targets)

    def __call__(self, pose: np.ndarray, sources: np.ndarray | None = None) -> float:
        """lambda under `pose`; with `sources` (a subset of the set's), the part of it those contribute."""
        if not self.n:
            return 0.0
        if sources is None:
            picked, share = self.sources, 1.0
        else:
            if not len(sources):
                return 0.0
            picked, share = sources[:: max(1, len(sources) // CHANCE_SAMPLE)], len(sources) / self.n
        moved = np.ascontiguousarray(picked @ pose[:3, :3].T + pose[:3, 3], dtype=np.float64)
        if self._count is not None:
            near = self._count(moved, self.targets, self.threshold)
        else:
            near = self.tree.query_ball_point(moved, self.threshold, return_length=True)
        return float(np.mean(near)) * self.scale * share


def chance_inliers(src: np.ndarray, tgt: np.ndarray, pose: np.ndarray, threshold: float) -> float:
    """lambda: how many correspondences a random matching of the same points puts within `threshold`
    under `pose` (expected over the matching)."""
    return ChanceCounter(src, tgt, threshold)(pose)


def explained(src: np.ndarray, tgt: np.ndarray, pose: np.ndarray, threshold: float) -> int:
    """How many correspondences the pose maps to within `threshold` of their target point."""
    return int(explained_counts(src, tgt, pose[None], threshold)[0])


def explained_counts(src: np.ndarray, tgt: np.ndarray, poses: np.ndarray, threshold: float) -> np.ndarray:
    """`explained` for each of `poses` (H, 4, 4): by the C++ core where it is built (one call for all of
    them), else one numpy pass a pose."""
    from fastmac_exp import core

    poses = np.ascontiguousarray(poses, dtype=np.float64).reshape(-1, 4, 4)
    if core.available():
        src, tgt = (np.ascontiguousarray(a, dtype=np.float64) for a in (src, tgt))
        return core.core().explained_counts(src, tgt, poses, float(threshold))
    counts = [np.linalg.norm(src @ p[:3, :3].T + p[:3, 3] - tgt, axis=1) < threshold for p in poses]
    return np.array([int(c.sum()) for c in counts], dtype=np.int64)


def distinct(
    poses: np.ndarray, pose: np.ndarray, centre: np.ndarray, re_deg: float, te_m: float
) -> np.ndarray:
    """Which of `poses` (H, 4, 4) differ from `pose` by more than re_deg in rotation or te_m in where they
    put `centre` (the source's centre: a translation difference that does not depend on the origin)."""
    if len(poses) == 0:
        return np.zeros(0, bool)
    rot = poses[:, :3, :3]
    trace = np.einsum("hij,ij->h", rot, pose[:3, :3])  # trace(R_h R^T), without forming the products
    cos = np.clip((trace - 1.0) / 2.0, -1.0, 1.0)
    angle = np.degrees(np.arccos(cos))
    at = np.einsum("hij,j->hi", rot, centre) + poses[:, :3, 3]
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
    counts = explained_counts(others[0], others[1], poses[top], threshold)
    best = top[int(np.argmax(counts))]
    return float(counts.max()), chance(poses[best], sources=others[0])


def decide(
    inliers: int,
    clique: int,
    lam: float,
    n: int,
    rival_excess: float | None = None,
    decoy_count: float | None = None,
    margin: float | None = None,
    rate: float | None = None,
) -> tuple[float, float]:
    """(confidence, null mean) of a pose explaining `inliers` of n, fitted on `clique`, with chance count
    `lam`: the mean is lam + the largest of what a wrong pose explains beyond chance by the search's pick
    (decoy_count, what the decoy's pose explained beyond chance; None or NaN: not run, and the pose's own
    clique stands in), by structure at any pose (rate x n) and by the best rival's structure
    (margin x rival_excess, what it explains beyond the pose and chance; None or NaN: not measured)."""
    margin = RIVAL_MARGIN if margin is None else margin
    rate = STRUCTURE_RATE if rate is None else rate
    measured = decoy_count is not None and np.isfinite(decoy_count)
    parts = [max(float(decoy_count), 3.0) if measured else float(max(int(clique), 3)), rate * n]
    if rival_excess is not None and np.isfinite(rival_excess):
        parts.append(margin * max(float(rival_excess), 0.0))
    mean = lam + max(parts)
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
