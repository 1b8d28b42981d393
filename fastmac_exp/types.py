"""Data model: plain dataclasses over numpy arrays, shared by every part of the pipeline."""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Any

import numpy as np

from fastmac_exp.errors import InputError
from fastmac_exp.families import FIXED_RESOLUTION

MAX_COORD = 1e6  # metres; anything beyond is taken as a unit or parsing error


def _as_points(name: str, a: Any) -> np.ndarray:
    arr = np.asarray(a, dtype=np.float64)
    if arr.ndim != 2 or arr.shape[1] != 3:
        raise InputError(f"{name} must have shape (N, 3), got {arr.shape}")
    return np.ascontiguousarray(arr)


@dataclass
class Correspondences:
    """Putative matches c_i = (src_i, tgt_i); a pose T is right when tgt ~ R src + t."""

    src: np.ndarray
    tgt: np.ndarray
    labels: np.ndarray | None = None
    scores: np.ndarray | None = None

    def __post_init__(self) -> None:
        self.src = _as_points("Correspondences.src", self.src)
        self.tgt = _as_points("Correspondences.tgt", self.tgt)
        if self.src.shape != self.tgt.shape:
            raise InputError(
                f"src and tgt must have the same number of rows, got {len(self.src)} and {len(self.tgt)}"
            )
        if self.labels is not None:
            self.labels = np.asarray(self.labels).astype(bool).reshape(-1)
            if len(self.labels) != len(self.src):
                raise InputError(f"labels has {len(self.labels)} rows, expected {len(self.src)}")
        if self.scores is not None:
            self.scores = np.asarray(self.scores, dtype=np.float64).reshape(-1)
            if len(self.scores) != len(self.src):
                raise InputError(f"scores has {len(self.scores)} rows, expected {len(self.src)}")

    def __len__(self) -> int:
        return len(self.src)

    def subset(self, idx: np.ndarray) -> Correspondences:
        """The correspondences at `idx`, in that order."""
        idx = np.asarray(idx, dtype=np.int64)
        return Correspondences(
            src=self.src[idx],
            tgt=self.tgt[idx],
            labels=None if self.labels is None else self.labels[idx],
            scores=None if self.scores is None else self.scores[idx],
        )

    def validate(self, where: str = "correspondences") -> None:
        """Raise InputError naming the first offending row if any coordinate is NaN, inf or absurd."""
        for name, arr in (("source", self.src), ("target", self.tgt)):
            bad = ~np.isfinite(arr).all(axis=1)
            if bad.any():
                row = int(np.flatnonzero(bad)[0])
                raise InputError(f"{where}: {name} point in row {row} is not finite: {arr[row].tolist()}")
            huge = (np.abs(arr) > MAX_COORD).any(axis=1)
            if huge.any():
                row = int(np.flatnonzero(huge)[0])
                raise InputError(
                    f"{where}: {name} point in row {row} has a coordinate beyond {MAX_COORD:g} m "
                    f"({arr[row].tolist()}); are the units right?"
                )

    @property
    def inlier_ratio(self) -> float:
        if self.labels is None or len(self.labels) == 0:
            return float("nan")
        return float(np.mean(self.labels))


@dataclass
class Pair:
    """One registration problem: two clouds and/or correspondences, the GT and the dataset's rules.

    `gt` maps source into target. Thresholds are the dataset family's (spec section 6).
    """

    name: str
    family: str = "3dmatch"  # whose rules apply: "3dmatch", "3dlomatch" or "kitti" (spec sections 2.2, 6)
    gt: np.ndarray | None = None
    src_cloud: np.ndarray | None = None
    tgt_cloud: np.ndarray | None = None
    correspondences: Correspondences | None = None
    voxel_size: float = 0.05
    inlier_threshold: float = 0.1
    re_thresh_deg: float = 15.0
    te_thresh_m: float = 0.3
    resolution: float = FIXED_RESOLUTION  # MAC's Gaussian kernel: alpha = 10 res (geometry.resolution)
    # FastMAC's sampling graph: the spec's fixed 3DMatch resolution (7.2), rescaled with the rules of pairs
    # that are not at room scale (object scans), where 0.006 m would link nearly every pair
    sampler_resolution: float = FIXED_RESOLUTION
    scene: str = ""
    meta: dict[str, Any] = field(default_factory=dict)

    def label(self, corr: Correspondences) -> Correspondences:
        """Attach GT inlier labels (error under GT below the inlier threshold) when a GT is known."""
        if self.gt is None:
            return corr
        err = np.linalg.norm(corr.src @ self.gt[:3, :3].T + self.gt[:3, 3] - corr.tgt, axis=1)
        corr.labels = err < self.inlier_threshold
        return corr


@dataclass
class RegistrationResult:
    """What MAC returns for one set of correspondences.

    `pose` is the final (refined) estimate; `pose_unrefined` the best hypothesis before refinement.
    `kept` indexes the correspondences given to `register` (after sampling); `clique` indexes `kept`'s
    subset that formed the winning hypothesis, expressed as indices into the input correspondences.
    """

    pose: np.ndarray
    pose_unrefined: np.ndarray
    kept: np.ndarray
    clique: np.ndarray
    score: float = 0.0
    n_cliques: int = 0
    n_selected: int = 0
    n_edges: int = 0
    reduced: bool = False
    cap_hit: str = ""
    # how the cliques were found: "bnb", "enumerate", "auto:enumerate" or "auto:bnb" (MacParams.search)
    search: str = "enumerate"
    search_nodes: int = 0  # branch-and-bound search-tree nodes (0 for the enumeration)
    timings: dict[str, float] = field(default_factory=dict)
    scores: np.ndarray | None = None  # per-node sampling scores over the input, if a sampler ran
    # what a user without GT can judge the pose by: the input correspondences the pose maps within the
    # inlier threshold (a right pose has many more than the clique; unrelated clouds about the clique's)
    inliers: int = 0
    # GT-free: whether the pose explains clearly more correspondences than a wrong pose would
    # (geometry.trust), and the confidence that is thresholded (1 - the false-accept chance; docs/trust.md)
    trusted: bool = False
    confidence: float = 0.0
    chance_inliers: float = float("nan")  # ... the evidence: what chance explains under this pose
    # MAC's hypotheses (one per selected clique, in order) and their MAE scores on the correspondences
    # it was given: the trust check's rivals (None from backends that keep no hypotheses)
    hypothesis_poses: np.ndarray | None = None
    hypothesis_scores: np.ndarray | None = None
    # the trust check's evidence beyond chance (geometry.trust.Trust): the decoy run's and the best
    # distinct rival's counts (NaN where not measured)
    decoy_count: float = float("nan")
    rival_inliers: float = float("nan")
    rival_chance: float = float("nan")
    error: str = ""  # register(): why no pose could be found ("" = a pose); then pose is all NaN
    # register()'s escalation (fastmac_exp.escalation): the step that gave this pose and every step tried
    # (name, ms, trusted, confidence, error); "" and [] where it did not escalate
    step: str = ""
    escalation: list[dict[str, Any]] = field(default_factory=list)

    @property
    def ok(self) -> bool:
        return not self.error


@dataclass
class GraphSignals:
    """Node signals of the graph the samplers score (spec 7.2-7.3), exact or estimated."""

    degree: np.ndarray  # generalized degree s_i = sum_j SOG_ij
    highpass: np.ndarray  # f = (diag(s) - SOG) s, signed
    lowpass: np.ndarray  # (I + D^-1 SOG) s
    n_edges: int  # first-order edges (unordered pairs); -1 where the graph was never built (estimate)
    dense_core: int = 0  # C++ engine: nodes whose products ran as a dense matrix product (0: all sparse)
    anchors: int = 0  # the estimate: anchors the signals were estimated from (0: exact)
