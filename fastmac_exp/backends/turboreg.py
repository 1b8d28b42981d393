"""TurboReg (Yan et al., ICCV 2025) on the C++ core's CPU implementation (fastmac_exp/_cpp/turboreg.cpp).

Same correspondences, same harness as MAC: a sampler may run in front of it (FastMAC + TurboReg), and the
row carries its stages in ms: graph (C and SC^2), pivots (top-K1 edges and the TurboCliques grown from
them), hypotheses (Kabsch per clique and the IN / MAE / MSE metric) and pose (the post-refinement).
docs/turboreg.md: what is reproduced, parity with upstream and speed.
"""

from __future__ import annotations

import numpy as np

from fastmac_exp import core
from fastmac_exp.core import points
from fastmac_exp.errors import InputError, RegistrationFailed
from fastmac_exp.families import family as family_record
from fastmac_exp.params import MacParams
from fastmac_exp.types import Correspondences, RegistrationResult

METRICS = ("IN", "MAE", "MSE")
FAMILY = "family"  # max_N: the family's upstream value


class TurboRegBackend:
    """TurboReg's estimator. None = the dataset family's upstream default (families.Family.turboreg).

    max_N: "family" (default) keeps the first max_N correspondences as upstream does (3DMatch 7,000,
    KITTI 6,000); an int keeps that many; None or 0 keeps every one. tau: tau_length_consis (m); num_pivot:
    K1; radius_nms: upstream's radiu_nms length cut (m); tau_inlier: the metric's and the refinement's
    inlier threshold (m); metric: "IN" (inlier count), "MAE" or "MSE"; hard: upstream's hard graph
    C = [d < tau] (its default) or the soft relu(1 - (d / tau)^2). num_threads: 0 = automatic.
    """

    name = "turboreg"

    def __init__(
        self,
        max_N: int | str | None = FAMILY,  # noqa: N803 (upstream's name)
        tau: float | None = None,
        num_pivot: int | None = None,
        radius_nms: float | None = None,
        tau_inlier: float | None = None,
        metric: str = "IN",
        hard: bool = True,
        refine_iters: int = 20,
        num_threads: int = 0,
    ) -> None:
        if isinstance(max_N, str) and max_N != FAMILY:
            raise InputError(f"turboreg max_N must be an int, null (all) or {FAMILY!r}, got {max_N!r}")
        if isinstance(max_N, int) and max_N < 0:
            raise InputError(f"turboreg max_N must be >= 0 (0 or null: all), got {max_N}")
        if metric not in METRICS:
            raise InputError(f"turboreg metric must be one of {', '.join(METRICS)}, got {metric!r}")
        for key, v in (("tau", tau), ("radius_nms", radius_nms), ("tau_inlier", tau_inlier)):
            if v is not None and not (v >= 0 if key == "radius_nms" else v > 0):
                want = ">= 0" if key == "radius_nms" else "positive"
                raise InputError(f"turboreg {key} must be {want}, got {v}")
        if num_pivot is not None and num_pivot < 1:
            raise InputError(f"turboreg num_pivot must be >= 1, got {num_pivot}")
        self._core = core.core()
        self.max_N, self.tau, self.num_pivot = max_N, tau, num_pivot
        self.radius_nms, self.tau_inlier, self.metric = radius_nms, tau_inlier, metric
        self.hard, self.refine_iters, self.num_threads = bool(hard), int(refine_iters), int(num_threads)

    def settings(self, family: str) -> dict:
        """The parameters used for a pair of this family (None resolved to the family's defaults)."""
        max_n, tau, k1, nms, tau_in = family_record(family or "3dmatch").turboreg
        m = max_n if self.max_N == FAMILY else (self.max_N or 0)
        return {
            "max_n": int(m),
            "tau": float(tau if self.tau is None else self.tau),
            "num_pivot": int(k1 if self.num_pivot is None else self.num_pivot),
            "radius_nms": float(nms if self.radius_nms is None else self.radius_nms),
            "tau_inlier": float(tau_in if self.tau_inlier is None else self.tau_inlier),
        }

    def register(self, corr: Correspondences, params: MacParams) -> RegistrationResult:
        n = len(corr)
        if n < 3:
            raise RegistrationFailed(f"need at least 3 correspondences, got {n}")
        src, tgt = points(corr.src), points(corr.tgt)
        if not (np.isfinite(src).all() and np.isfinite(tgt).all()):
            raise InputError("correspondences must be finite (NaN or inf found)")
        s = self.settings(params.family)
        r = self._core.turboreg(
            src, tgt, **s, metric=self.metric, hard=self.hard, refine_iters=self.refine_iters,
            num_threads=self.num_threads,
        )  # fmt: skip
        return RegistrationResult(
            pose=r["pose"],
            pose_unrefined=r["pose_unrefined"],
            kept=np.arange(n),
            clique=np.asarray(r["clique"], np.int64),
            score=float(r["score"]),
            n_cliques=int(r["n_hypotheses"]),
            n_selected=int(r["n_unique"]),
            n_edges=int(r["n_edges"]),
            search="turboclique",
            timings=dict(r["timings"]),
        )
