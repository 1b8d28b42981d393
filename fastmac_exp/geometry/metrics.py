"""Registration metrics (spec section 6): RE in degrees, TE in centimetres, success, recall."""

from __future__ import annotations

from dataclasses import dataclass
from typing import TYPE_CHECKING

import numpy as np

if TYPE_CHECKING:  # pandas is imported where a table is summarised: `import fastmac_exp` stays light
    import pandas as pd

from fastmac_exp.geometry.transforms import nearest_rigid, rotation_error_deg, translation_error_m


@dataclass
class PoseErrors:
    re_deg: float
    te_cm: float
    success: bool


def pose_errors(pose: np.ndarray, gt: np.ndarray, re_max_deg: float, te_max_m: float) -> PoseErrors:
    """RE, TE and success by the dataset's thresholds (0 <= RE <= RE_max and 0 <= TE <= TE_max).

    RE is measured against the nearest rotation of the GT's 3x3 block: benchmark GTs (3DMatch gt.log) are
    off orthonormal by up to 5e-4, which would otherwise put a floor of up to ~1.5 deg under RE.
    """
    re = rotation_error_deg(pose[:3, :3], nearest_rigid(gt)[:3, :3])
    te = translation_error_m(pose[:3, 3], gt[:3, 3])
    return PoseErrors(re_deg=re, te_cm=te * 100.0, success=bool(re <= re_max_deg and te <= te_max_m))


STAGES = ("describe", "sampling", "graph", "cliques", "selection", "pose", "total")
MAC_STAGES = STAGES[1:-1]  # what `total` sums: sampling and MAC's four stages
TURBOREG_STAGES = ("pivots", "hypotheses")  # backend=turboreg's stages besides graph and pose
# Everything a pair spends time in, in its order (a row has those it went through; pipeline/stopwatch.py
# times them back to back): `setup` and `clean` are register()'s, `load` the experiment's (the files,
# the cleaning), `other` the glue inside sampling + MAC, `check` the pose's inliers and trust, `evaluate`
# the GT labels and the verdict. `end_to_end` is their sum; `total` stays sampling + MAC, the papers' figure.
PAIR_STAGES = ("setup", "load", "clean", "resolution", "describe", "sampling", "graph", "cliques",
               "selection", "pivots", "hypotheses", "pose", "other", "check", "decoy", "escalation",
               "evaluate")  # fmt: skip


def summarize(table: pd.DataFrame) -> dict:
    """RR over the pairs with GT (failed pairs count as not registered; a pair without GT is not scored),
    RE/TE means over successful pairs, median time per stage (ms)."""
    import pandas as pd

    n = len(table)
    if n == 0:
        return {"pairs": 0, "failed": 0, "RR": float("nan")}
    ok = table["success"].fillna(False).astype(bool)
    errors = (
        table["error"].fillna("").astype(str).ne("") if "error" in table else pd.Series(False, table.index)
    )
    unscored = int((table["success"].isna() & ~errors).sum())
    scored = n - unscored
    out = {
        "pairs": n,
        "failed": int(errors.sum()),
        "registered": int(ok.sum()),
        "scored": scored,
        "unscored": unscored,
        "RR": float(ok.sum() / scored) if scored else float("nan"),
        "RE_deg": float(table.loc[ok, "re_deg"].mean()) if ok.any() else float("nan"),
        "TE_cm": float(table.loc[ok, "te_cm"].mean()) if ok.any() else float("nan"),
        "inlier_ratio_in": float(table["inlier_ratio_in"].mean())
        if "inlier_ratio_in" in table
        else float("nan"),
        "inlier_ratio_kept": float(table["inlier_ratio_kept"].mean())
        if "inlier_ratio_kept" in table
        else float("nan"),
    }
    for stage in (*PAIR_STAGES, "total", "end_to_end"):
        col = f"t_{stage}_ms"
        if col in table:
            out[f"median_{stage}_ms"] = float(table[col].median())
    out["describe_cached"] = cached_rows(table)
    return out


def cached_rows(table: pd.DataFrame) -> int:
    """Rows whose correspondences came from the cache (their describe time is the original computation's)."""
    if "describe_cached" not in table:
        return 0
    return int(table["describe_cached"].fillna(False).astype(bool).sum())
