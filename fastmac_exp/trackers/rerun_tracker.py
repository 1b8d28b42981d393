"""Rerun tracker: the pairs of a run as a Rerun recording (.rrd), for `rerun <file>.rrd`.

per="run": one file, `<run_dir>/recording.rrd` (or `path`); per="pair": one file per recorded pair,
`<run_dir>/rerun/<pair>.rrd` (or under the directory `path`). Nothing is spawned or served; data goes
straight to the file through a private `rr.RecordingStream`.

Entity layout (pair names are escaped with `rr.escape_entity_path_part`):

    pairs/<pair>/matches/source            Points3D   source cloud (yellow), in its own frame
    pairs/<pair>/matches/target            Points3D   target cloud (blue), shifted along +x by the
                                                      `offset` stored in pairs/<pair>/info so lines show
    pairs/<pair>/matches/correspondences   LineStrips3D  every correspondence (thin): green = GT inlier,
                                                      red = outlier, grey = unlabelled
    pairs/<pair>/matches/sampled           LineStrips3D  the sampler's kept subset (thicker)
    pairs/<pair>/matches/clique            LineStrips3D  the selected clique (thickest)
    pairs/<pair>/registration/target       Points3D   target cloud
    pairs/<pair>/registration/estimate     Transform3D  estimated pose, with .../estimate/source the
                                                      source cloud under it (orange)
    pairs/<pair>/registration/gt           Transform3D  GT pose, with .../gt/source (green)
    pairs/<pair>/info                      TextDocument  the results row
    metrics/time_ms/<stage>                Scalars    stage timings, every pair
    metrics/{re_deg,te_cm,success,running_rr,inlier_ratio_in,inlier_ratio_kept}   Scalars
    log                                    TextLog    failed pairs

Everything is on the sequence timeline `pair` (the pair's index). Clouds are downsampled to
`max_points`; when a dataset has no clouds (precomputed correspondences) the correspondence end points
stand in for them. Geometry is recorded for the first `max_pairs` successful pairs; scalars for all.
"""

from __future__ import annotations

import logging
import math
import uuid
from pathlib import Path
from typing import Any

import numpy as np
import pandas as pd

from fastmac_exp.pipeline import PairOutcome
from fastmac_exp.trackers.base import Tracker

log = logging.getLogger(__name__)

PER = ("run", "pair")
APP_ID = "fastmac-exp"
GREEN = (40, 200, 60)
RED = (230, 40, 40)
GREY = (150, 150, 150)
SRC_COLOR = (250, 190, 20)
TGT_COLOR = (40, 140, 255)
EST_COLOR = (255, 120, 0)
GT_COLOR = (60, 220, 120)


def _finite(v: Any) -> float | None:
    if v is None or v is pd.NA or isinstance(v, str):
        return None
    try:
        f = float(v)
    except (TypeError, ValueError):
        return None
    return f if math.isfinite(f) else None


def downsample(points: np.ndarray, max_points: int, seed: int = 0) -> np.ndarray:
    """At most `max_points` rows, a fixed random subset in the original order."""
    idx = subset_index(len(points), max_points, seed)
    return points if idx is None else points[idx]


def subset_index(n: int, max_points: int, seed: int = 0) -> np.ndarray | None:
    if max_points <= 0 or n <= max_points:
        return None
    return np.sort(np.random.default_rng(seed).choice(n, size=max_points, replace=False))


def label_colors(labels: np.ndarray | None, n: int) -> np.ndarray:
    """Green for GT inliers, red for outliers, grey when labels are unknown; (n, 3) uint8."""
    if labels is None:
        return np.tile(np.array(GREY, dtype=np.uint8), (n, 1))
    return np.where(np.asarray(labels, bool)[:, None], np.array(GREEN, np.uint8), np.array(RED, np.uint8))


def safe_name(name: str) -> str:
    """A file name for a pair name (slashes and odd characters replaced)."""
    keep = "".join(c if c.isalnum() or c in "-_.=" else "_" for c in str(name))
    return keep.strip(".") or "pair"


class RerunTracker(Tracker):
    """Record pairs to .rrd files: clouds, correspondences, sample, clique, poses and timings.

    per: "run" (one file) or "pair" (one file per pair). max_pairs: how many pairs get geometry (<= 0:
    none, scalars only). path: the .rrd file (per="run") or directory (per="pair"); relative paths are
    relative to the run directory. max_points: the cap on points per cloud and lines per line set.
    radius: the point radius in scene units (lines scale from it); null = 0.2 x the pair's voxel size.
    """

    name = "rerun"

    def __init__(
        self,
        per: str = "run",
        max_pairs: int = 8,
        path: str | None = None,
        max_points: int = 50000,
        radius: float | None = None,
        blueprint: bool = True,
    ) -> None:
        if per not in PER:
            raise ValueError(f"tracker.rerun.per must be one of {PER}, got {per!r}")
        self.per = per
        self.max_pairs = int(max_pairs)
        self.path = path
        self.max_points = int(max_points)
        self.radius = radius
        self.blueprint = bool(blueprint)
        self.rec = None
        self.files: list[Path] = []
        self.recorded: list[str] = []  # entity roots of the pairs with geometry
        self._n = 0
        self._n_ok = 0
        self._run_dir: Path | None = None
        try:
            import rerun as rr
        except Exception as exc:  # noqa: BLE001 - a broken install must not stop the experiment
            log.warning("rerun tracker disabled: `import rerun` failed (%s); pip install rerun-sdk", exc)
            self._rr = None
        else:
            self._rr = rr

    # -- lifecycle -------------------------------------------------------------------------------------
    def start(self, cfg: dict[str, Any], run_dir: Path, names: list[str]) -> None:
        if self._rr is None:
            return
        self._run_dir = Path(run_dir)
        if self.per == "run":
            target = Path(self.path) if self.path else Path("recording.rrd")
            target = target if target.is_absolute() else self._run_dir / target
            self.rec = self._open(target, recording_name=self._run_dir.name)
            log.info("rerun: recording to %s (view with `rerun %s`)", target, target)

    def _open(self, path: Path, recording_name: str):
        rr = self._rr
        path.parent.mkdir(parents=True, exist_ok=True)
        rec = rr.RecordingStream(APP_ID, recording_id=uuid.uuid4())
        rec.save(path)
        rec.send_recording_name(recording_name)
        self.files.append(path)
        return rec

    def _close(self, rec, blueprint_roots: list[str]) -> None:
        if self.blueprint and blueprint_roots:
            try:
                rec.send_blueprint(self._make_blueprint(blueprint_roots), make_active=True)
            except Exception as exc:  # noqa: BLE001 - the layout is a convenience
                log.debug("rerun: no blueprint: %s", exc)
        rec.flush(timeout_sec=30.0)
        rec.disconnect()

    def _make_blueprint(self, roots: list[str]):
        rrb = self._rr.blueprint
        tabs = [
            rrb.Horizontal(
                rrb.Spatial3DView(origin=f"{root}/matches", name="correspondences"),
                rrb.Spatial3DView(origin=f"{root}/registration", name="registration"),
                rrb.Vertical(
                    rrb.TextDocumentView(origin=f"{root}/info", name="row"),
                    rrb.TimeSeriesView(origin="metrics/time_ms", name="stage times (ms)"),
                    row_shares=[1, 1],
                ),
                column_shares=[2, 2, 1],
                name=root.rsplit("/", 1)[-1],
            )
            for root in roots
        ]
        tabs.append(rrb.TimeSeriesView(origin="metrics", name="metrics"))
        return rrb.Blueprint(rrb.Tabs(*tabs), collapse_panels=True)

    def log_pair(self, outcome: PairOutcome) -> None:
        if self._rr is None or self._run_dir is None:
            return
        row = outcome.row
        self._n += 1
        ok = _finite(row.get("success")) == 1.0
        self._n_ok += ok
        want_geometry = outcome.corr is not None and len(self.recorded) < self.max_pairs
        if self.per == "run":
            rec = self.rec
        elif want_geometry:
            base = Path(self.path) if self.path else Path("rerun")
            base = base if base.is_absolute() else self._run_dir / base
            rec = self._open(base / f"{safe_name(row.get('pair', self._n))}.rrd", str(row.get("pair")))
        else:
            return
        index = int(_finite(row.get("index")) if _finite(row.get("index")) is not None else self._n - 1)
        rec.set_time("pair", sequence=index)
        self._log_scalars(rec, row, ok)
        if row.get("error"):
            rr = self._rr
            rec.log("log", rr.TextLog(f"pair {row.get('pair')} failed: {row['error']}", level="ERROR"))
        if want_geometry:
            root = "pairs/" + self._rr.escape_entity_path_part(str(row.get("pair", index)))
            self._log_geometry(rec, root, outcome)
            self.recorded.append(root)
            if self.per == "pair":
                self._close(rec, [root])

    def _log_scalars(self, rec, row: dict[str, Any], ok: bool) -> None:
        rr = self._rr
        for k, v in row.items():
            if k.startswith("t_") and k.endswith("_ms") and _finite(v) is not None:
                rec.log(f"metrics/time_ms/{k[2:-3]}", rr.Scalars(_finite(v)))
        for k in ("re_deg", "te_cm", "inlier_ratio_in", "inlier_ratio_kept"):
            if _finite(row.get(k)) is not None:
                rec.log(f"metrics/{k}", rr.Scalars(_finite(row[k])))
        rec.log("metrics/success", rr.Scalars(float(ok)))
        rec.log("metrics/running_rr", rr.Scalars(self._n_ok / self._n))

    def _log_geometry(self, rec, root: str, outcome: PairOutcome) -> None:
        rr = self._rr
        corr, pair, result, sample = outcome.corr, outcome.pair, outcome.result, outcome.sample
        src_pts = pair.src_cloud if pair is not None and pair.src_cloud is not None else corr.src
        tgt_pts = pair.tgt_cloud if pair is not None and pair.tgt_cloud is not None else corr.tgt
        src_pts = downsample(np.asarray(src_pts, np.float32), self.max_points, seed=1)
        tgt_pts = downsample(np.asarray(tgt_pts, np.float32), self.max_points, seed=2)
        r = self.radius if self.radius is not None else 0.2 * (pair.voxel_size if pair is not None else 0.05)

        # correspondence view: target shifted along +x so that the lines are readable
        extent = float(np.ptp(src_pts[:, 0])) if len(src_pts) else 1.0
        dx = (
            (float(src_pts[:, 0].max()) - float(tgt_pts[:, 0].min()) + 0.25 * extent) if len(tgt_pts) else 0.0
        )
        offset = np.array([dx, 0.0, 0.0], np.float32)
        rec.log(f"{root}/matches/source", rr.Points3D(src_pts, colors=SRC_COLOR, radii=r))
        rec.log(f"{root}/matches/target", rr.Points3D(tgt_pts + offset, colors=TGT_COLOR, radii=r))

        def lines(idx: np.ndarray | None, radius: float, entity: str) -> None:
            idx = np.arange(len(corr)) if idx is None else np.asarray(idx, np.int64)
            sub = subset_index(len(idx), self.max_points, seed=3)
            if sub is not None:
                idx = idx[sub]
            strips = np.stack([corr.src[idx], corr.tgt[idx] + offset], axis=1).astype(np.float32)
            labels = corr.labels[idx] if corr.labels is not None else None
            rec.log(
                f"{root}/matches/{entity}",
                rr.LineStrips3D(strips, colors=label_colors(labels, len(idx)), radii=radius),
            )

        lines(None, 0.1 * r, "correspondences")
        if result is not None or sample is not None:
            kept = result.kept if result is not None else sample.indices
            lines(kept, 0.3 * r, "sampled")
        if result is not None and len(result.clique):
            lines(result.clique, 0.8 * r, "clique")

        # registration view: the source under the estimated and the GT pose, next to the target
        rec.log(f"{root}/registration/target", rr.Points3D(tgt_pts, colors=TGT_COLOR, radii=r))
        poses = []
        if result is not None:
            poses.append(("estimate", result.pose, EST_COLOR))
        if pair is not None and pair.gt is not None:
            poses.append(("gt", pair.gt, GT_COLOR))
        for entity, pose, color in poses:
            pose = np.asarray(pose, np.float64)
            rec.log(
                f"{root}/registration/{entity}",
                rr.Transform3D(translation=pose[:3, 3], mat3x3=pose[:3, :3]),
            )
            rec.log(f"{root}/registration/{entity}/source", rr.Points3D(src_pts, colors=color, radii=r))

        rec.log(
            f"{root}/info", rr.TextDocument(_row_markdown(outcome.row, offset), media_type="text/markdown")
        )

    def finish(self, table: pd.DataFrame, summary: dict[str, Any]) -> None:
        if self.rec is not None:
            rec, self.rec = self.rec, None
            self._close(rec, self.recorded)


def _row_markdown(row: dict[str, Any], offset: np.ndarray) -> str:
    keys = [k for k in row if k != "pose"]
    lines = [f"### {row.get('pair')}", "", "| key | value |", "| --- | --- |"]
    for k in keys:
        v = row[k]
        if isinstance(v, float):
            v = f"{v:.4g}"
        lines.append(f"| {k} | {v} |")
    lines += ["", f"matches view: target shifted by {offset.tolist()} along x"]
    return "\n".join(lines)
