"""Rerun tracker: the pairs of a run as a Rerun recording (.rrd), for `rerun <file>.rrd`.

per="run": one file, `<run_dir>/recording.rrd` (or `path`), and one more for each resume of the run
(`recording.part2.rrd`, ...: the earlier parts are never rewritten; `rerun <run_dir>/recording*.rrd`
opens them all); per="pair": one file per recorded pair, `<run_dir>/rerun/<pair>.rrd` (or under the
directory `path`). Nothing is spawned or served; data goes
straight to the file through a private `rr.RecordingStream`.

Entity layout (pair names are escaped with `rr.escape_entity_path_part`). A pair's geometry is static (it
lives under the pair's own path, so every pair's tab shows whatever the timeline cursor is at); the
per-pair scalars sit on the sequence timeline `pair` (the pair's index).

    legend                                TextDocument  what each colour means (also the class labels)
    pairs/<pair>/matches/source           Points3D   source cloud, in its own frame
    pairs/<pair>/matches/target           Points3D   target cloud, shifted by the `offset` stored in
                                                     pairs/<pair>/info (beside the source, or above it
                                                     for z-up scans) so lines show
    pairs/<pair>/matches/all              LineStrips3D  every correspondence, outliers subsampled to
                                                     `max_outlier_lines` (hidden in the default layout)
    pairs/<pair>/matches/sampled          LineStrips3D  the sampler's kept subset: GT inliers, GT outliers
                                                     (thin, light) or unlabelled
    pairs/<pair>/matches/clique           LineStrips3D  the winning clique, in its own colour
    pairs/<pair>/registration/source_before/source   Points3D   the source as given (no pose)
    pairs/<pair>/registration/target      Points3D   target cloud
    pairs/<pair>/registration/estimate    Transform3D + TransformAxes3D  estimated pose, with
                                                     .../estimate/source the source under it
    pairs/<pair>/registration/gt          Transform3D + TransformAxes3D  GT pose, with .../gt/source
    pairs/<pair>/stage_ms                 TextDocument  the pair's own stage times without describe, in
                                                     STAGE_BARS order, each named, with a bar (rerun's
                                                     BarChart has no category labels)
    pairs/<pair>/info                     TextDocument  the results row
    metrics/time_ms/<stage>               Scalars    sampling .. pose and total (MAC + sampling), ms
    metrics/describe_ms                   Scalars    features + matching, ms (own plot: it dwarfs the rest)
    metrics/re_deg, metrics/te_cm         Scalars    rotation (deg) and translation (cm) error
    metrics/ratio/{inlier_ratio_in,inlier_ratio_kept,success,running_rr}   Scalars (0..1)
    log                                   TextLog    failed pairs

Every line carries a hover label `#<correspondence id> <class> score <sampler score>`, and the views are
set to the dataset's up axis (`up`, or the family's: +z for KITTI-like scans, -y for 3DMatch-like camera
fragments). Clouds are downsampled to `max_points`; when a dataset has no clouds (precomputed
correspondences) the correspondence end points stand in for them. Geometry is recorded for the first
`max_pairs` registered pairs and the first `max_pairs` that did not register; scalars for all.
"""

from __future__ import annotations

import logging
import math
import uuid
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np
import pandas as pd

from fastmac_exp.families import FAMILIES
from fastmac_exp.geometry.metrics import MAC_STAGES
from fastmac_exp.pipeline import PairOutcome
from fastmac_exp.trackers.base import Tracker

log = logging.getLogger(__name__)

PER = ("run", "pair")
APP_ID = "fastmac-exp"


@dataclass(frozen=True)
class Style:
    """One annotation class: what the viewer's hover shows and the legend lists, and its colour."""

    id: int
    label: str
    color: tuple[int, int, int]
    colour_name: str  # for the legend: the viewer's markdown has no coloured text


UNLABELLED = Style(0, "correspondence (no GT label)", (150, 150, 150), "grey")
INLIER = Style(1, "GT inlier", (40, 210, 60), "green")
OUTLIER = Style(2, "GT outlier", (235, 70, 70), "red, thin")  # bright enough on dark and white
CLIQUE = Style(3, "winning clique", (255, 0, 230), "magenta, thick")
SOURCE = Style(4, "source cloud", (250, 190, 20), "yellow")
TARGET = Style(5, "target cloud", (40, 140, 255), "blue")
BEFORE = Style(6, "source before registration", (150, 150, 150), "grey")
ESTIMATE = Style(7, "source under the estimated pose", (255, 120, 0), "orange")
GT_POSE = Style(8, "source under the GT pose", (170, 90, 255), "violet")
STYLES = (UNLABELLED, INLIER, OUTLIER, CLIQUE, SOURCE, TARGET, BEFORE, ESTIMATE, GT_POSE)
LABELS = {s.id: s.label for s in STYLES}

STAGE_BARS = MAC_STAGES
UP_AXES = {"+x": "RIGHT_HAND_X_UP", "-x": "RIGHT_HAND_X_DOWN", "+y": "RIGHT_HAND_Y_UP",
           "-y": "RIGHT_HAND_Y_DOWN", "+z": "RIGHT_HAND_Z_UP", "-z": "RIGHT_HAND_Z_DOWN"}  # fmt: skip
UI_POINT_RADIUS = 1.5
RATIO_KEYS = ("inlier_ratio_in", "inlier_ratio_kept")


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


def label_classes(labels: np.ndarray | None, n: int) -> np.ndarray:
    """The annotation class of each correspondence: GT inlier, GT outlier, or unlabelled; (n,) uint16."""
    if labels is None:
        return np.full(n, UNLABELLED.id, np.uint16)
    return np.where(np.asarray(labels, bool), INLIER.id, OUTLIER.id).astype(np.uint16)


def thin_outliers(idx: np.ndarray, labels: np.ndarray | None, max_outliers: int, seed: int = 0) -> np.ndarray:
    """`idx` with its GT outliers subsampled to `max_outliers` (<0: all kept); inliers all kept."""
    if labels is None or max_outliers < 0:
        return idx
    out = ~np.asarray(labels, bool)[idx]
    keep = subset_index(int(out.sum()), max_outliers, seed)
    if keep is None:
        return idx
    mask = ~out
    mask[np.flatnonzero(out)[keep]] = True
    return idx[mask]


def up_axis(pair_family: str | None, up: str | None) -> str | None:
    """The view's up axis: the tracker's `up` when given, else the family's; None: rerun's default."""
    fam = FAMILIES.get(str(pair_family))
    chosen = up if up is not None else (fam.up_axis if fam is not None else None)
    if chosen is not None and chosen not in UP_AXES:
        raise ValueError(f"tracker.rerun.up must be one of {sorted(UP_AXES)} or null, got {up!r}")
    return chosen


def safe_name(name: str) -> str:
    """A file name for a pair name (slashes and odd characters replaced)."""
    keep = "".join(c if c.isalnum() or c in "-_.=" else "_" for c in str(name))
    return keep.strip(".") or "pair"


def legend_markdown() -> str:
    matches = (INLIER, OUTLIER, CLIQUE, UNLABELLED, SOURCE, TARGET)
    registration = (TARGET, BEFORE, ESTIMATE, GT_POSE)
    return "\n".join(
        ["### Correspondences", "", "| colour | meaning |", "| --- | --- |",
         *(f"| {s.colour_name} | {s.label} |" for s in matches), "",
         "Lines: the sampled set without the clique (GT outliers thinned to `max_outlier_lines`) and "
         "the clique; every "
         "correspondence is in `matches/all` (hidden: toggle its eye in the blueprint panel). Hover a line "
         "for its correspondence id, class and sampler score.", "",
         "### Registration", "", "| colour | meaning |", "| --- | --- |",
         *(f"| {s.colour_name} | {s.label} |" for s in registration), "",
         "Axes (x red, y green, z blue): the target frame, the estimated and the GT pose."]
    )  # fmt: skip


class RerunTracker(Tracker):
    """Record pairs to .rrd files: clouds, correspondences, sample, clique, poses and timings.

    per: "run" (one file) or "pair" (one file per pair). max_pairs: how many pairs get geometry (<= 0:
    none, scalars only). path: the .rrd file (per="run") or directory (per="pair"); relative paths are
    relative to the run directory. max_points: the cap on points per cloud and lines per line set.
    max_outlier_lines: the cap on GT-outlier lines among all correspondences (-1: no cap).
    radius: the point radius in scene units (lines scale from it); null = a fixed size on screen.
    up: the views' up axis ("+z", "-y", ...); null = the dataset family's.
    sweep_max_pairs: max_pairs in a sweep member (the report shows a few pairs of a sweep; twenty members
    recording as a single run does made 126 MB); None: max_pairs.
    """

    name = "rerun"

    def __init__(
        self,
        per: str = "run",
        max_pairs: int = 8,
        path: str | None = None,
        max_points: int = 50000,
        max_outlier_lines: int = 300,
        radius: float | None = None,
        up: str | None = None,
        blueprint: bool = True,
        sweep_max_pairs: int | None = 1,
    ) -> None:
        if per not in PER:
            raise ValueError(f"tracker.rerun.per must be one of {PER}, got {per!r}")
        up_axis(None, up)  # a bad value fails here, not at the first pair
        self.per = per
        self.max_pairs = int(max_pairs)
        self.sweep_max_pairs = sweep_max_pairs
        self.path = path
        self.max_points = int(max_points)
        self.max_outlier_lines = int(max_outlier_lines)
        self.radius = radius
        self.up = up
        self.blueprint = bool(blueprint)
        self.rec = None
        self.files: list[Path] = []
        self.recorded: list[str] = []  # entity roots of the pairs with geometry
        self._eyes: dict[str, dict[str, dict[str, Any]]] = {}  # root -> view -> EyeControls3D arguments
        self._n = 0
        self._n_ok = 0
        self._n_geo_ok = self._n_geo_failed = 0  # pairs recorded with geometry
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
        if self.sweep_max_pairs is not None and in_multirun() and self.sweep_max_pairs < self.max_pairs:
            log.info("rerun: a sweep member records the geometry of %d pair(s) "
                     "(tracker.rerun.sweep_max_pairs=null: as a run)", self.sweep_max_pairs)  # fmt: skip
            self.max_pairs = int(self.sweep_max_pairs)
        if self.per == "run":
            target = Path(self.path) if self.path else Path("recording.rrd")
            target = target if target.is_absolute() else self._run_dir / target
            parts = recording_parts(target)
            name = self._run_dir.name + (f" (part {len(parts) + 1})" if parts else "")
            target = part_path(target, len(parts) + 1)
            self.rec = self._open(target, recording_name=name)
            log.info("rerun: recording to %s (view with `rerun %s`)", target, target)

    def _open(self, path: Path, recording_name: str):
        rr = self._rr
        path.parent.mkdir(parents=True, exist_ok=True)
        rec = rr.RecordingStream(APP_ID, recording_id=uuid.uuid4())
        rec.save(path)
        rec.send_recording_name(recording_name)
        classes = [rr.AnnotationInfo(id=s.id, label=s.label, color=s.color) for s in STYLES]
        rec.log("/", rr.AnnotationContext(classes), static=True)
        rec.log("legend", rr.TextDocument(legend_markdown(), media_type="text/markdown"), static=True)
        self._log_series_styles(rec)
        self.files.append(path)
        return rec

    def _log_series_styles(self, rec) -> None:
        rr = self._rr
        for stage in (*STAGE_BARS, "total"):
            rec.log(f"metrics/time_ms/{stage}", rr.SeriesPoints(names=stage), static=True)
        names = {"describe_ms": "describe (ms)", "re_deg": "RE (deg)", "te_cm": "TE (cm)",
                 "ratio/inlier_ratio_in": "inlier ratio in", "ratio/inlier_ratio_kept": "inlier ratio kept",
                 "ratio/running_rr": "running RR"}  # fmt: skip
        for path, name in names.items():  # one value per pair: points, not lines between pairs
            style = rr.SeriesLines(names=name) if path.endswith("running_rr") else rr.SeriesPoints(names=name)
            rec.log(f"metrics/{path}", style, static=True)
        rec.log(
            "metrics/ratio/success", rr.SeriesPoints(names="success (0/1)", marker_sizes=3.0), static=True
        )

    def _close(self, rec, blueprint_roots: list[str]) -> None:
        if self.blueprint and blueprint_roots:
            try:
                rec.send_blueprint(self._make_blueprint(blueprint_roots), make_active=True)
            except Exception as exc:  # noqa: BLE001 - the layout is a convenience
                log.debug("rerun: no blueprint: %s", exc)
        rec.flush(timeout_sec=30.0)
        rec.disconnect()

    def _make_blueprint(self, roots: list[str], active_tab: int | None = None):
        rrb = self._rr.blueprint
        hidden = rrb.EntityBehavior(visible=False)
        tabs = [
            rrb.Horizontal(
                rrb.Spatial3DView(
                    origin=f"{root}/matches",
                    name="correspondences: sampled, clique",
                    overrides={f"{root}/matches/all": hidden},
                    **self._eye_controls(root, "matches"),
                ),
                rrb.Spatial3DView(
                    origin=f"{root}/registration",
                    name="registration: before, estimate, GT",
                    **self._eye_controls(root, "registration"),
                ),
                rrb.Vertical(
                    rrb.TextDocumentView(origin="legend", name="legend"),
                    rrb.TextDocumentView(origin=f"{root}/stage_ms", name="stage ms"),
                    rrb.TextDocumentView(origin=f"{root}/info", name="row"),
                    row_shares=[3, 1, 2],
                ),
                column_shares=[2, 2, 1],
                name=root.rsplit("/", 1)[-1],
            )
            for root in roots
        ]
        tabs.append(
            rrb.Grid(
                rrb.TimeSeriesView(origin="metrics/time_ms", name="stage times (ms)"),
                rrb.TimeSeriesView(origin="metrics/describe_ms", name="describe (ms)"),
                rrb.TimeSeriesView(origin="metrics/re_deg", name="rotation error (deg)"),
                rrb.TimeSeriesView(origin="metrics/te_cm", name="translation error (cm)"),
                rrb.TimeSeriesView(
                    origin="metrics/ratio", name="ratios (0..1)", axis_y=rrb.ScalarAxis(range=(0.0, 1.05))
                ),
                rrb.TextLogView(origin="log", name="failed pairs"),
                grid_columns=2,
                name="metrics",
            )
        )
        return rrb.Blueprint(rrb.Tabs(*tabs, active_tab=active_tab), collapse_panels=True)

    def _eye_controls(self, root: str, view: str) -> dict[str, Any]:
        eye = self._eyes.get(root, {}).get(view)
        return {"eye_controls": self._rr.blueprint.EyeControls3D(**eye)} if eye else {}

    def log_pair(self, outcome: PairOutcome) -> None:
        if self._rr is None or self._run_dir is None:
            return
        row = outcome.row
        self._n += 1
        ok = _finite(row.get("success")) == 1.0
        self._n_ok += ok
        # the first max_pairs registered pairs and, beside them, up to max_pairs that did not register:
        # the ones a researcher most wants to see
        shown = self._n_geo_ok if ok else self._n_geo_failed
        want_geometry = outcome.corr is not None and shown < self.max_pairs
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
            if ok:
                self._n_geo_ok += 1
            else:
                self._n_geo_failed += 1
            if self.per == "pair":
                self._close(rec, [root])

    def _log_scalars(self, rec, row: dict[str, Any], ok: bool) -> None:
        rr = self._rr
        for k, v in row.items():
            if k.startswith("t_") and k.endswith("_ms") and _finite(v) is not None:
                stage = k[2:-3]
                path = "metrics/describe_ms" if stage == "describe" else f"metrics/time_ms/{stage}"
                rec.log(path, rr.Scalars(_finite(v)))
        for k in ("re_deg", "te_cm"):
            if _finite(row.get(k)) is not None:
                rec.log(f"metrics/{k}", rr.Scalars(_finite(row[k])))
        for k in RATIO_KEYS:
            if _finite(row.get(k)) is not None:
                rec.log(f"metrics/ratio/{k}", rr.Scalars(_finite(row[k])))
        rec.log("metrics/ratio/success", rr.Scalars(float(ok)))
        rec.log("metrics/ratio/running_rr", rr.Scalars(self._n_ok / self._n))

    def _log_geometry(self, rec, root: str, outcome: PairOutcome) -> None:
        rr = self._rr
        corr, pair, result, sample = outcome.corr, outcome.pair, outcome.result, outcome.sample
        src_pts = pair.src_cloud if pair is not None and pair.src_cloud is not None else corr.src
        tgt_pts = pair.tgt_cloud if pair is not None and pair.tgt_cloud is not None else corr.tgt
        src_pts = downsample(np.asarray(src_pts, np.float32), self.max_points, seed=1)
        tgt_pts = downsample(np.asarray(tgt_pts, np.float32), self.max_points, seed=2)
        # rerun reads a negative radius as UI points: the same size on screen at any scene scale
        r = float(self.radius) if self.radius is not None else -UI_POINT_RADIUS
        up = up_axis(pair.family if pair is not None else None, self.up)

        def static(entity: str, *archetypes) -> None:
            rec.log(f"{root}/{entity}", *archetypes, static=True)

        if up is not None:
            coords = getattr(rr.ViewCoordinates, UP_AXES[up])
            static("matches", coords)
            static("registration", coords)

        offset = match_offset(src_pts, tgt_pts, up)
        static("matches/source", rr.Points3D(src_pts, class_ids=SOURCE.id, radii=0.5 * r))
        static("matches/target", rr.Points3D(tgt_pts + offset, class_ids=TARGET.id, radii=0.5 * r))

        scores = sample.scores if sample is not None and sample.scores is not None else corr.scores
        classes = label_classes(corr.labels, len(corr))

        def lines(entity: str, idx: np.ndarray, radius: float, clique: bool = False) -> None:
            idx = np.asarray(idx, np.int64)
            sub = subset_index(len(idx), self.max_points, seed=3)
            if sub is not None:
                idx = idx[sub]
            strips = np.stack([corr.src[idx], corr.tgt[idx] + offset], axis=1).astype(np.float32)
            cls = np.full(len(idx), CLIQUE.id, np.uint16) if clique else classes[idx]
            radii = np.full(len(idx), radius, np.float32)
            if not clique:
                radii[cls == OUTLIER.id] *= 0.4  # outliers thinner than inliers
            tags = [
                f"#{i} {LABELS[c]}" + ("" if scores is None else f" score {float(scores[i]):.3g}")
                for i, c in zip(idx.tolist(), classes[idx].tolist(), strict=True)
            ]
            static(
                f"matches/{entity}",
                rr.LineStrips3D(strips, class_ids=cls, radii=radii, labels=tags, show_labels=False),
                rr.AnyValues(correspondence_id=idx),
            )

        everything = thin_outliers(np.arange(len(corr)), corr.labels, self.max_outlier_lines, seed=4)
        lines("all", everything, 0.15 * r)
        shown = {"all": (len(everything), len(corr))}
        if result is not None or sample is not None:
            kept = np.sort(np.asarray(result.kept if result is not None else sample.indices, np.int64))
            if result is not None:  # the clique is drawn on its own, over everything else
                kept = np.setdiff1d(kept, np.asarray(result.clique, np.int64))
            thinned = thin_outliers(kept, corr.labels, self.max_outlier_lines, seed=5)
            lines("sampled", thinned, 0.4 * r)
            shown["sampled"] = (len(thinned), len(kept))
        if result is not None and len(result.clique):
            lines("clique", result.clique, 1.2 * r, clique=True)
            shown["clique"] = (len(result.clique), len(result.clique))
        both = np.vstack([src_pts, tgt_pts + offset]) if len(src_pts) else tgt_pts
        self._eyes[root] = {
            "matches": _eye(both.mean(0) if len(both) else np.zeros(3), scale_of(both), up, side=True),
            "registration": _eye(tgt_pts.mean(0) if len(tgt_pts) else np.zeros(3), scale_of(tgt_pts), up),
        }

        # registration view: the target frame; the source as given, under the estimated and the GT pose
        axes = rr.TransformAxes3D(axis_length=0.15 * scale_of(tgt_pts))
        static("registration", axes)
        static("registration/target", rr.Points3D(tgt_pts, class_ids=TARGET.id, radii=r))
        static("registration/source_before/source", rr.Points3D(src_pts, class_ids=BEFORE.id, radii=0.5 * r))
        poses = []
        if result is not None:
            poses.append(("estimate", result.pose, ESTIMATE))
        if pair is not None and pair.gt is not None:
            poses.append(("gt", pair.gt, GT_POSE))
        for entity, pose, style in poses:
            pose = np.asarray(pose, np.float64)
            static(
                f"registration/{entity}", rr.Transform3D(translation=pose[:3, 3], mat3x3=pose[:3, :3]), axes
            )
            static(f"registration/{entity}/source", rr.Points3D(src_pts, class_ids=style.id, radii=r))

        bars = {s: _finite(outcome.row.get(f"t_{s}_ms")) for s in STAGE_BARS}
        if any(b is not None for b in bars.values()):
            static("stage_ms", rr.TextDocument(_stage_markdown(bars), media_type="text/markdown"))
        static("info", rr.TextDocument(_row_markdown(outcome.row, offset, shown), media_type="text/markdown"))

    def finish(self, table: pd.DataFrame, summary: dict[str, Any]) -> None:
        if self.rec is not None:
            rec, self.rec = self.rec, None
            self._close(rec, self.recorded)


def in_multirun() -> bool:
    """Whether this process runs a member of a Hydra sweep."""
    from hydra.core.hydra_config import HydraConfig
    from hydra.types import RunMode

    return HydraConfig.initialized() and HydraConfig.get().mode == RunMode.MULTIRUN


def part_path(path: Path, part: int) -> Path:
    """The file of a recording's `part` (1: `path` itself; a resumed run records into `<stem>.partN.rrd`
    beside the earlier parts, which stay as they are)."""
    return path if part == 1 else path.with_name(f"{path.stem}.part{part}{path.suffix}")


def recording_parts(path: str | Path) -> list[Path]:
    """The existing files of a recording and of its resumed parts, in the order they were written."""
    path, out = Path(path), []
    while (p := part_path(path, len(out) + 1)).is_file():
        out.append(p)
    return out


def scale_of(points: np.ndarray) -> float:
    return float(np.ptp(points, axis=0).max()) if len(points) else 1.0


def match_offset(src: np.ndarray, tgt: np.ndarray, up: str | None) -> np.ndarray:
    """Where the correspondence view puts the target: flat LiDAR scans (z up) stacked above the source,
    anything else beside it along +x, a quarter of the source's width apart, so that lines are readable."""
    if not len(src) or not len(tgt):
        return np.zeros(3, np.float32)
    if up == "+z":
        gap = 0.3 * float(np.ptp(src[:, :2], axis=0).max())
        return np.array([0.0, 0.0, float(src[:, 2].max() - tgt[:, 2].min()) + gap], np.float32)
    dx = float(src[:, 0].max()) - float(tgt[:, 0].min()) + 0.25 * float(np.ptp(src[:, 0]))
    return np.array([dx, 0.0, 0.0], np.float32)


def _eye(centre: np.ndarray, extent: float, up: str | None, side: bool = False) -> dict[str, Any]:
    """A 3D view's eye on the dataset's up axis: camera fragments from behind the sensor, a little above;
    flat LiDAR scans from behind and high above, or from the side (`side`, for the stacked match view)."""
    if up is None:
        return {}
    axis = "xyz".index(up[1])
    up_vec = np.zeros(3)
    up_vec[axis] = 1.0 if up[0] == "+" else -1.0
    if axis == 2:
        back = np.array([0.0, -1.0, 0.0])
        position = centre + extent * ((0.8 * back + 0.35 * up_vec) if side else (0.25 * back + 0.5 * up_vec))
    else:
        position = centre + extent * (1.5 * np.array([0.0, 0.0, -1.0]) + 0.8 * up_vec)
    return {"position": position.tolist(), "look_target": centre.tolist(), "eye_up": up_vec.tolist()}


HEADLINE = ("success", "re_deg", "te_cm", "n_in", "n_kept", "inlier_ratio_in", "inlier_ratio_kept",
            "clique_size", "clique_inliers", "error")  # fmt: skip


def _stage_markdown(ms: dict[str, float | None], width: int = 24) -> str:
    """The stage times as a labelled bar list: `stage  ms  bar`, the longest stage `width` blocks."""
    top = max((v for v in ms.values() if v is not None), default=0.0)
    lines = ["| stage | ms | |", "| --- | ---: | --- |"]
    for stage, v in ms.items():
        if v is None:
            lines.append(f"| {stage} | - | |")
            continue
        n = int(round(width * v / top)) if top > 0 else 0
        lines.append(f"| {stage} | {v:.1f} | {'█' * n} |")
    return "\n".join(lines)


def _row_markdown(
    row: dict[str, Any], offset: np.ndarray, shown: dict[str, tuple[int, int]] | None = None
) -> str:
    """The results row, headline keys first, then the stage times, then everything else."""
    times = [k for k in row if k.startswith("t_") and k.endswith("_ms")]
    order = [k for k in HEADLINE if k in row] + times
    order += [k for k in row if k not in order and k != "pose"]
    lines = [f"### {row.get('pair')}", "", "| key | value |", "| --- | --- |"]
    for k in order:
        v = row[k]
        if isinstance(v, float):
            v = f"{v:.4g}"
        lines.append(f"| {k} | {v} |")
    lines += ["", f"matches view: target shifted by {offset.tolist()}"]
    for entity, (n_shown, n) in (shown or {}).items():
        lines.append(f"- `matches/{entity}`: {n_shown} of {n} lines shown")
    return "\n".join(lines)
