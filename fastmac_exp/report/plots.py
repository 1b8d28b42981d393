"""Plots for the report (matplotlib, Agg backend, PNG), drawn from `report.aggregate`'s table.

- sampling.png: RR / RE / TE against the sampling ratio, one line per method (sampler, and backend or
  protocol where those vary), one row of three panels per dataset x descriptor (the paper's
  sampling-strategy figures); log-scaled ratio axis running from 1 down to 0.01.
- time_profile.png: median time per stage stacked against the ratio, one panel per method, one row per
  dataset x descriptor (the paper's time-profile figure).
- rr_vs_time.png: RR against median total time, one point per method and ratio (labelled sampler@ratio),
  one panel per dataset x descriptor.
"""

from __future__ import annotations

import math
import textwrap
from pathlib import Path

import matplotlib

matplotlib.use("Agg")

import matplotlib.pyplot as plt  # noqa: E402
import matplotlib.text  # noqa: E402
import matplotlib.transforms  # noqa: E402
import numpy as np  # noqa: E402
import pandas as pd  # noqa: E402
from matplotlib.ticker import FuncFormatter  # noqa: E402

from fastmac_exp.geometry.metrics import MAC_STAGES  # noqa: E402

PROFILE_STAGES = MAC_STAGES
STAGE_NAMES = {"sampling": "Sampling", "graph": "GC", "cliques": "MCS", "selection": "NCS", "pose": "PE"}
# the paper's stage names, spelt out in the figure's legend (not only in report.md)
STAGE_LONG = {
    "sampling": "Sampling", "graph": "GC: graph construction", "cliques": "MCS: maximal clique search",
    "selection": "NCS: node-guided clique selection", "pose": "PE: pose estimation",
}  # fmt: skip
STAGE_COLORS = {"sampling": "#4c72b0", "graph": "#dd8452", "cliques": "#55a868", "selection": "#c44e52",
                "pose": "#8172b3"}  # fmt: skip
MARKERS = ("o", "s", "^", "D", "v", "P", "X", "*")


def _panels(agg: pd.DataFrame) -> list[tuple[str, pd.DataFrame]]:
    """(title, rows) per dataset x descriptor."""
    keys = [k for k in ("dataset", "descriptor") if k in agg]
    if not keys:
        return [("", agg)]
    out = []
    for key, g in agg.groupby(keys, sort=False):
        key = key if isinstance(key, tuple) else (key,)
        out.append((" / ".join(str(k) for k in key), g))
    return out


def _method_keys(agg: pd.DataFrame) -> list[str]:
    """The columns that tell methods apart: the sampler, plus backend / protocol where they vary."""
    keys = [k for k in ("sampler",) if k in agg]
    keys += [k for k in ("backend", "protocol") if k in agg and agg[k].nunique(dropna=False) > 1]
    return keys


def _methods(g: pd.DataFrame, keys: list[str]) -> list[tuple[str, pd.DataFrame]]:
    if not keys:
        return [("all", g)]
    out = []
    for key, m in g.groupby(keys, sort=True):
        key = key if isinstance(key, tuple) else (key,)
        out.append((" / ".join(str(k) for k in key), m.sort_values("ratio", ascending=False)))
    return out


def _color_map(labels: list[str]) -> dict[str, tuple]:
    cmap = plt.get_cmap("tab10")
    return {lab: cmap(i % 10) for i, lab in enumerate(sorted(set(labels)))}


def _ratio_axis(ax, ratios: np.ndarray) -> None:
    ratios = np.asarray([r for r in ratios if np.isfinite(r) and r > 0], float)
    # ticks only where there are data (a tick without a point reads as a missing measurement)
    ticks = sorted(set(np.round(ratios, 6).tolist()) or {1.0}, reverse=True)
    lo = min(ticks)
    ax.set_xscale("log")
    ax.set_xticks(ticks)
    ax.set_xticklabels([f"{t:g}" for t in ticks])
    ax.minorticks_off()
    ax.set_xlim(max(ticks) * 1.25, lo / 1.25)  # inverted: from the most kept down to the sparsest sample
    ax.set_xlabel("sampling ratio")
    ax.grid(True, which="major", alpha=0.3)


def plot_sampling(
    agg: pd.DataFrame, path: Path, title: str = "Sampling strategy: accuracy against the sampling ratio"
) -> Path | None:
    """RR / RE / TE against ratio per method; one row of three panels per dataset x descriptor."""
    if agg.empty or "ratio" not in agg:
        return None
    panels = _panels(agg)
    mkeys = _method_keys(agg)
    colors = _color_map([lab for _, g in panels for lab, _ in _methods(g, mkeys)])
    fig, axes = plt.subplots(
        len(panels), 3, figsize=(14, 3.6 * len(panels) + 0.4), squeeze=False, layout="constrained"
    )
    metrics = (("RR", "RR (%)"), ("RE_deg", "RE (deg)"), ("TE_cm", "TE (cm)"))
    for row, (panel, g) in enumerate(panels):
        for col, (metric, label) in enumerate(metrics):
            ax = axes[row, col]
            for i, (lab, m) in enumerate(_methods(g, mkeys)):
                x, y = m["ratio"].to_numpy(float), m[metric].to_numpy(float)
                ax.plot(x, y, marker=MARKERS[i % len(MARKERS)], color=colors[lab], label=lab, lw=1.8, ms=6)
                if metric == "RR" and "RR_seed_std" in m and m["RR_seed_std"].notna().any():
                    mu, sd = m["RR_seed_mean"].to_numpy(float), m["RR_seed_std"].to_numpy(float)
                    lo, hi = np.clip(mu - sd, 0, 100), np.clip(mu + sd, 0, 100)
                    ax.fill_between(x, lo, hi, color=colors[lab], alpha=0.12, lw=0)
            _ratio_axis(ax, g["ratio"].to_numpy(float))
            ax.set_ylabel(label)
            if metric == "RR":
                ax.set_ylim(-3, 103)
            else:
                ax.set_ylim(bottom=0)
                if not g[metric].notna().any():  # RE/TE are means over successful pairs
                    ax.set_yticks([])  # no empty 0-0.05 scale
                    ax.text(0.5, 0.5, "no successful pair", transform=ax.transAxes, ha="center",
                            va="center", fontsize=11, color="0.4")  # fmt: skip
            ax.set_title(f"{panel}: {label}" if panel else label, fontsize=10)
        axes[row, 0].legend(fontsize=8, loc="best")
    _suptitle(fig, title)
    fig.savefig(path, dpi=110)
    plt.close(fig)
    return path


def _suptitle(fig, title: str) -> None:
    """The figure's title, wrapped to its width (a one-panel figure is narrower than a long title)."""
    width = max(30, int(fig.get_figwidth() * 11))  # ~11 characters an inch at 12 pt
    fig.suptitle("\n".join(textwrap.wrap(title, width)), fontsize=12)


def plot_time_profile(
    agg: pd.DataFrame,
    path: Path,
    title: str = "Time profile: median time per stage (bars: stage medians; line: median total)",
) -> Path | None:
    """Stacked median stage times against ratio; one panel per method, one row per dataset x descriptor."""
    stages = [s for s in PROFILE_STAGES if f"t_{s}_ms" in agg and agg[f"t_{s}_ms"].notna().any()]
    if agg.empty or not stages or "ratio" not in agg:
        return None
    panels = _panels(agg)
    mkeys = _method_keys(agg)
    ncols = max(len(_methods(g, mkeys)) for _, g in panels)
    # each panel its own y scale: one slow method (FPS) would flatten the others' bars to nothing
    fig, axes = plt.subplots(
        len(panels), ncols, figsize=(max(4.2 * ncols, 6), 3.6 * len(panels) + 0.4), squeeze=False,
        layout="constrained",
    )  # fmt: skip
    for row, (panel, g) in enumerate(panels):
        methods = _methods(g, mkeys)
        for col in range(ncols):
            ax = axes[row, col]
            if col >= len(methods):
                ax.set_visible(False)
                continue
            lab, m = methods[col]
            x = np.arange(len(m))
            bottom = np.zeros(len(m))
            for s in stages:
                v = np.nan_to_num(m[f"t_{s}_ms"].to_numpy(float))
                ax.bar(x, v, bottom=bottom, color=STAGE_COLORS[s], label=STAGE_LONG[s], width=0.7)
                bottom += v
            untimed = ~m[[f"t_{s}_ms" for s in stages]].notna().any(axis=1).to_numpy()
            for xi in x[untimed]:  # a member whose pairs all failed: say so, not an empty slot
                ax.text(xi, 0.5, "no times:\nevery pair\nfailed", transform=ax.get_xaxis_transform(),
                        ha="center", va="center", fontsize=7, color="0.35", rotation=90)  # fmt: skip
            if "t_total_ms" in m:
                tot = m["t_total_ms"].to_numpy(float)
                ax.scatter(
                    x, tot, marker="_", s=300, color="k", zorder=3, label="median total (sampling + MAC)"
                )
                for xi, ti, top in zip(x, tot, bottom, strict=True):
                    if math.isfinite(ti):  # above the bar too: the medians' sum can exceed the total's median
                        ax.annotate(f"{ti:.3g}", (xi, max(ti, top)), textcoords="offset points",
                                    xytext=(0, 4), ha="center", fontsize=7)  # fmt: skip
            ax.set_xticks(x)
            ax.set_xticklabels([f"{r:g}" for r in m["ratio"]])
            ax.set_xlabel("sampling ratio")
            ax.set_title(f"{panel}: {lab}" if panel else lab, fontsize=10)
            ax.grid(True, axis="y", alpha=0.3)
        for ax in axes[row]:
            if ax.get_visible():
                ax.set_ylabel("median time (ms)")
    legend: dict = {}
    for ax in axes.flat:
        for h, lab in zip(*ax.get_legend_handles_labels(), strict=True):
            legend.setdefault(lab, h)
    handles, labels = list(legend.values()), list(legend.keys())
    shown = sum(ax.get_visible() for ax in axes.flat)
    _suptitle(fig, title + ("; each panel its own y scale" if shown > 1 else ""))
    # below the panels: inside one it hid the bars and total labels it lay on
    columns = min(len(labels), 3 if ncols > 1 else 2)  # a one-panel figure is too narrow for three
    fig.legend(handles, labels, loc="outside lower center", ncols=columns, fontsize=8, frameon=False)
    for ax in axes.flat:  # room above the tallest bar for its total's label
        if ax.get_visible():
            ax.set_ylim(top=ax.get_ylim()[1] * 1.08)
    fig.savefig(path, dpi=110)
    plt.close(fig)
    return path


def plot_rr_vs_time(agg: pd.DataFrame, path: Path) -> Path | None:
    """RR against median total time; one point per method and ratio, one panel per dataset x descriptor."""
    if agg.empty or "t_total_ms" not in agg or not agg["t_total_ms"].notna().any():
        return None
    fig, _ = rr_vs_time_figure(agg)
    fig.savefig(path, dpi=110)
    plt.close(fig)
    return path


def rr_vs_time_figure(agg: pd.DataFrame):
    """(figure, the point labels placed on each panel) of plot_rr_vs_time."""
    panels = _panels(agg)
    mkeys = _method_keys(agg)
    colors = _color_map([lab for _, g in panels for lab, _ in _methods(g, mkeys)])
    backends = sorted(agg["backend"].astype(str).unique()) if "backend" in agg else []
    fig, axes = plt.subplots(1, len(panels), figsize=(6.5 * len(panels), 4.8), squeeze=False)
    labels: dict[int, list] = {}
    for col, (title, g) in enumerate(panels):
        ax = axes[0, col]
        labels[col] = []
        for lab, m in _methods(g, mkeys):
            m = m[m["t_total_ms"].notna()]
            if m.empty:
                continue
            ax.plot(m["t_total_ms"], m["RR"], color=colors[lab], lw=1, alpha=0.5)
            for _, r in m.iterrows():
                b = backends.index(str(r["backend"])) if backends else 0
                marker = MARKERS[b % len(MARKERS)]
                ax.scatter(r["t_total_ms"], r["RR"], color=colors[lab], marker=marker, s=45, zorder=3)
                name = f"{r.get('sampler', lab)}@{r['ratio']:g}" if "ratio" in r else lab
                labels[col].append(((r["t_total_ms"], r["RR"]), name, colors[lab]))
            ax.plot([], [], color=colors[lab], marker="o", ls="-", label=lab)
        for b, name in enumerate(backends):
            ax.scatter([], [], color="grey", marker=MARKERS[b % len(MARKERS)], label=f"backend {name}")
        ax.set_xscale("log")
        fmt = FuncFormatter(lambda v, _: f"{v:g}")
        ax.xaxis.set_major_formatter(fmt)
        ax.xaxis.set_minor_formatter(FuncFormatter(lambda v, _: f"{v:g}" if f"{v:.1g}"[0] in "25" else ""))
        ax.margins(x=0.18)
        ax.set_xlabel("median total time per pair (ms, sampling + MAC)")
        ax.set_ylabel("RR (%)")
        ax.set_ylim(-3, 105)
        ax.grid(True, which="both", alpha=0.3)
        ax.set_title(title or "RR against time", fontsize=10)
        ax.legend(fontsize=8, loc="best")
    _suptitle(fig, "Registration recall against time")
    fig.tight_layout()
    placed = [_place_labels(axes[0, col], items) for col, items in labels.items()]
    return fig, placed


# where a label may go around its point (points; dx, dy): near first, then further out with a leader line
LABEL_SPOTS = [(r * math.cos(a), r * math.sin(a)) for r in (7, 16, 28, 42, 58, 76)
               for a in np.radians((20, -20, 160, 200, 60, -60, 120, 240, 90, 270))]  # fmt: skip


def text_box(ann, renderer):
    """An annotation's text alone, without its leader line (Annotation's extent includes the line)."""
    ann.update_positions(renderer)  # the offset text's place on the canvas (else it is set at draw time)
    return matplotlib.text.Text.get_window_extent(ann, renderer)


def _place_labels(ax, items: list[tuple[tuple[float, float], str, tuple]]) -> list:
    """Annotate points (text in the point's colour) where the label overlaps no other label, no other
    point and stays inside the axes: the nearest free spot of LABEL_SPOTS, tied to its point by a thin line
    when it is not beside it; with none free, the spot that overlaps least. Returns the annotations."""
    ax.figure.canvas.draw()  # the axes' limits as drawn (autoscaling is lazy), then held
    ax.set_xlim(ax.get_xlim())
    ax.set_ylim(ax.get_ylim())
    renderer = ax.figure.canvas.get_renderer()
    frame = ax.get_window_extent(renderer)
    points = [ax.transData.transform(xy) for xy, _, _ in items]
    marks = [matplotlib.transforms.Bbox.from_extents(x - 4, y - 4, x + 4, y + 4) for x, y in points]
    legend = ax.get_legend()
    placed: list = [legend.get_window_extent(renderer)] if legend is not None else []  # and label boxes
    out = []

    def overlap(box, own: int) -> float:
        area = 0.0
        for k, other in enumerate(placed + marks):
            if k - len(placed) == own:
                continue
            w = min(box.x1, other.x1) - max(box.x0, other.x0)
            h = min(box.y1, other.y1) - max(box.y0, other.y0)
            area += max(w, 0) * max(h, 0)
        outside = box.width * box.height - max(min(box.x1, frame.x1) - max(box.x0, frame.x0), 0) * max(
            min(box.y1, frame.y1) - max(box.y0, frame.y0), 0)  # fmt: skip
        return area + 10 * outside

    order = sorted(range(len(items)), key=lambda k: (items[k][0][0], -items[k][0][1]))
    for k in order:
        xy, text, color = items[k]
        best = None
        for dx, dy in LABEL_SPOTS:
            far = math.hypot(dx, dy) > 10
            ann = ax.annotate(
                text, xy, xytext=(dx, dy), textcoords="offset points", fontsize=7, color=color,
                ha="left" if dx >= 0 else "right", va="bottom" if dy >= 0 else "top",
                arrowprops={"arrowstyle": "-", "color": color, "lw": 0.5, "alpha": 0.7} if far else None,
            )  # fmt: skip
            box = text_box(ann, renderer)
            cost = overlap(box, k)
            if best is None or cost < best[0]:
                if best is not None:
                    best[1].remove()
                best = (cost, ann, box)
            else:
                ann.remove()
            if cost == 0:
                break
        placed.append(best[2])
        out.append(best[1])
    return out


def plot_all(agg: pd.DataFrame, out_dir: str | Path) -> list[Path]:
    """Every plot that the aggregate has data for; returns the PNG paths written."""
    out_dir = Path(out_dir)
    out_dir.mkdir(parents=True, exist_ok=True)
    written = [
        plot_sampling(agg, out_dir / "sampling.png"),
        plot_time_profile(agg, out_dir / "time_profile.png"),
        plot_rr_vs_time(agg, out_dir / "rr_vs_time.png"),
    ]
    return [p for p in written if p is not None]
