"""PNG snapshots of the pairs in a Rerun recording, for machines without a display.

Reads the `.rrd` the rerun tracker wrote (with rerun's own reader, so a snapshot shows what the recording
holds) and draws each recorded pair as two matplotlib panels in the recording's up axis: the
correspondence view (source, target, the sampled lines by GT label, the clique) and the registration
view (target, the source as given, under the estimated and the GT pose). Used by the report:
`python -m fastmac_exp.report <run_dir>` writes `report/pairs/<pair>.png`.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from pathlib import Path

import matplotlib

matplotlib.use("Agg")

import matplotlib.pyplot as plt  # noqa: E402
import numpy as np  # noqa: E402
from mpl_toolkits.mplot3d.art3d import Line3DCollection  # noqa: E402

from fastmac_exp.trackers.rerun_tracker import (  # noqa: E402
    BEFORE,
    CLIQUE,
    ESTIMATE,
    GT_POSE,
    INLIER,
    OUTLIER,
    SOURCE,
    TARGET,
    safe_name,
)

MAX_DRAWN_POINTS = 6000  # per cloud: matplotlib's 3D scatter is slow and a PNG shows no more
_UP_CODES = {1: 1.0, 2: -1.0}  # rerun's ViewDir: 1 = Up, 2 = Down


@dataclass
class PairGeometry:
    """One recorded pair as read back from the file: clouds (n, 3), lines (m, 2, 3) with class ids."""

    name: str
    clouds: dict[str, np.ndarray] = field(default_factory=dict)  # entity below the pair root -> points
    lines: dict[str, tuple[np.ndarray, np.ndarray]] = field(default_factory=dict)  # -> (strips, classes)
    poses: dict[str, np.ndarray] = field(default_factory=dict)  # "estimate" / "gt" -> 4x4
    up: tuple[int, float] | None = None  # (axis, sign) of the up direction


def split_entity_path(path: str) -> list[str]:
    """An entity path's parts with rerun's escaping undone (`scene\\/a` is the one part `scene/a`)."""
    parts, cur, escaped = [], [], False
    for ch in path.strip("/"):
        if escaped:
            cur.append(ch)
            escaped = False
        elif ch == "\\":
            escaped = True
        elif ch == "/":
            parts.append("".join(cur))
            cur = []
        else:
            cur.append(ch)
    parts.append("".join(cur))
    return parts


def _first(batch, column: str):
    return batch.column(column).to_pylist()[0] if column in batch.schema.names else None


def read_pairs(rrd: str | Path) -> list[PairGeometry]:
    """Every pair with geometry in `rrd`, in the order the recording holds them."""
    from rerun.chunk import RrdReader

    pairs: dict[str, PairGeometry] = {}
    for chunk in RrdReader(Path(rrd)).stream().to_chunks():
        parts = split_entity_path(chunk.entity_path)
        if len(parts) < 3 or parts[0] != "pairs":
            continue
        name, sub = parts[1], "/".join(parts[2:])
        geo = pairs.setdefault(name, PairGeometry(name=name))
        batch = chunk.to_record_batch()
        points = _first(batch, "Points3D:positions")
        if points is not None:
            geo.clouds[sub] = np.asarray(points, np.float64).reshape(-1, 3)
        strips = _first(batch, "LineStrips3D:strips")
        if strips is not None:
            classes = _first(batch, "LineStrips3D:class_ids") or [0] * len(strips)
            geo.lines[sub] = (np.asarray(strips, np.float64).reshape(-1, 2, 3), np.asarray(classes, int))
        translation = _first(batch, "Transform3D:translation")
        mat = _first(batch, "Transform3D:mat3x3")
        if translation is not None and mat is not None:
            pose = np.eye(4)
            pose[:3, :3] = np.asarray(mat, np.float64).reshape(-1)[:9].reshape(3, 3).T  # column-major
            pose[:3, 3] = np.asarray(translation, np.float64).reshape(-1)[:3]
            geo.poses[sub.rsplit("/", 1)[-1]] = pose
        coords = _first(batch, "ViewCoordinates:xyz")
        if coords is not None and sub == "registration":
            coords = np.asarray(coords).reshape(-1)[:3].tolist()
            axis = next((i for i, c in enumerate(coords) if c in _UP_CODES), None)
            geo.up = None if axis is None else (axis, _UP_CODES[coords[axis]])
    return sorted((g for g in pairs.values() if g.clouds or g.lines), key=lambda g: g.name)


def _to_z_up(points: np.ndarray, up: tuple[int, float] | None) -> np.ndarray:
    """Permute axes so that the recording's up direction is matplotlib's +z."""
    if up is None or len(points) == 0:
        return points
    axis, sign = up
    others = [i for i in range(3) if i != axis]
    return np.stack([points[:, others[0]], points[:, others[1]], sign * points[:, axis]], axis=1)


def _thin(points: np.ndarray, n: int = MAX_DRAWN_POINTS) -> np.ndarray:
    if len(points) <= n:
        return points
    return points[np.random.default_rng(0).choice(len(points), n, replace=False)]


def _rgb(style) -> tuple[float, float, float]:
    return tuple(c / 255 for c in style.color)


def _box(points: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """The axes' box for these points: the central 99 % on each axis, no side under a fifth of the longest."""
    lo, hi = np.percentile(points, 0.5, axis=0), np.percentile(points, 99.5, axis=0)
    span = np.maximum(hi - lo, 0.2 * float((hi - lo).max()) + 1e-9)
    centre = (lo + hi) / 2
    return centre - span / 2, centre + span / 2


def _fit_axes(ax, points: np.ndarray) -> tuple[np.ndarray, np.ndarray] | None:
    """Equal scale on all axes, the box shaped like the data (flat LiDAR scans stay wide), no panes; returns
    the box (matplotlib's 3-D axes draw points outside their limits too: _inside drops them)."""
    ax.set_axis_off()
    if not len(points):
        return None
    lo, hi = _box(points)
    for setter, a, b in zip((ax.set_xlim, ax.set_ylim, ax.set_zlim), lo, hi, strict=True):
        setter(a, b)
    ax.set_box_aspect(tuple(hi - lo), zoom=1.0)
    return lo, hi


def _inside(points: np.ndarray, box: tuple[np.ndarray, np.ndarray] | None) -> np.ndarray:
    if box is None:
        return points
    return points[((points >= box[0]) & (points <= box[1])).all(axis=1)]


def render_pair(geo: PairGeometry, out: str | Path, title: str = "") -> Path:
    """Two panels for one pair; returns the PNG's path."""
    up = geo.up
    fig = plt.figure(figsize=(12, 6), layout="constrained")
    ax = fig.add_subplot(1, 2, 1, projection="3d", computed_zorder=False)  # draw order = layer order
    drawn = []
    for sub, style in (("matches/source", SOURCE), ("matches/target", TARGET)):
        if sub in geo.clouds:
            drawn.append((_to_z_up(_thin(geo.clouds[sub]), up), style))
    box = _fit_axes(ax, np.vstack([p for p, _ in drawn]) if drawn else np.zeros((0, 3)))
    for p, style in drawn:
        p = _inside(p, box)
        ax.scatter(*p.T, s=0.3, color=_rgb(style), alpha=0.5, depthshade=False, label=style.label)
    for sub in ("matches/sampled", "matches/clique"):
        if sub not in geo.lines:
            continue
        strips, classes = geo.lines[sub]
        for style, width, alpha in ((OUTLIER, 0.4, 0.7), (INLIER, 0.6, 0.9), (CLIQUE, 2.0, 1.0)):
            sel = strips[classes == style.id]
            if len(sel):
                segs = np.stack([_to_z_up(sel[:, 0], up), _to_z_up(sel[:, 1], up)], axis=1)
                ax.add_collection3d(
                    Line3DCollection(segs, colors=[_rgb(style)], linewidths=width, alpha=alpha)
                )
    ax.set_title("correspondences: sampled lines by GT label, the clique")
    ax2 = fig.add_subplot(1, 2, 2, projection="3d", computed_zorder=False)
    drawn = []
    clouds = (("registration/source_before/source", BEFORE), ("registration/target", TARGET),
              ("registration/gt/source", GT_POSE), ("registration/estimate/source", ESTIMATE))  # fmt: skip
    for sub, style in clouds:
        if sub not in geo.clouds:
            continue
        p = geo.clouds[sub]
        pose_name = sub.split("/")[1]
        if pose_name in geo.poses:
            pose = geo.poses[pose_name]
            p = p @ pose[:3, :3].T + pose[:3, 3]
        drawn.append((_to_z_up(_thin(p), up), style))
    # the box holds the registered clouds, and the source before registration where that does not shrink
    # them to under half the panel (a far-away source is shown as far as the box reaches)
    after = [p for p, style in drawn if style is not BEFORE]
    fit = np.vstack(after) if after else np.zeros((0, 3))
    if after and len(drawn) > len(after):
        everything = np.vstack([p for p, _ in drawn])
        lo, hi = _box(fit)
        lo_all, hi_all = _box(everything)
        if np.linalg.norm(hi_all - lo_all) <= 2.0 * np.linalg.norm(hi - lo):
            fit = everything
    box = _fit_axes(ax2, fit)
    for p, style in drawn:
        p = _inside(p, box)
        ax2.scatter(*p.T, s=0.3, color=_rgb(style), alpha=0.6, depthshade=False)
    ax2.set_title("registration: target, source before / estimated / GT")
    shown = (INLIER, OUTLIER, CLIQUE, SOURCE, TARGET, BEFORE, ESTIMATE, GT_POSE)
    handles = [plt.Line2D([], [], color=_rgb(s), lw=3, label=s.label) for s in shown]
    fig.legend(handles=handles, loc="lower center", ncols=4, fontsize=8, frameon=False)
    fig.suptitle(title or geo.name)
    out = Path(out)
    out.parent.mkdir(parents=True, exist_ok=True)
    fig.savefig(out, dpi=110)
    plt.close(fig)
    return out


def snapshot_recording(
    rrd: str | Path, out_dir: str | Path, max_pairs: int = 4, titles: dict[str, str] | None = None
) -> list[Path]:
    """PNGs of the first `max_pairs` pairs in `rrd`, named after the pairs, under `out_dir`."""
    written = []
    for geo in read_pairs(rrd)[: max(0, max_pairs)]:
        name = safe_name(geo.name)
        written.append(render_pair(geo, Path(out_dir) / f"{name}.png", (titles or {}).get(geo.name, "")))
    return written
