"""Section 6 of docs/results.md: median stage times against the ratio (paper Table profile, Fig. 1), from
outputs/studies/time_profile_<data>/{fastmac,mac}."""

from __future__ import annotations

import math

import matplotlib.pyplot as plt
import numpy as np
import pandas as pd

from fastmac_exp.report import markdown_table, plots
from studies.common import PAPER_PROFILE, RATIOS, SHORT, Page, data_heading, ms, per_seed_pairs, row_of, text

STAGES = ("sampling", "graph", "cliques", "selection", "pose", "total")
HEADER = ["ratio", "Sampling", "GC", "MCS", "NCS", "PE", "total"]
LABEL = "MAC (ratio 1) / FastMAC"


def render(page: Page) -> None:
    page.add(*text("time_profile"))
    page.add("Paper (3DMatch, FCGF, GPU sampling):", "")
    rows = [[f"{r:g}"] + [ms(v) for v in PAPER_PROFILE[r]] for r in RATIOS]
    page.add(markdown_table(HEADER, rows, ["l"] + ["r"] * 6), "")
    paper_mac, paper_f20 = PAPER_PROFILE[1.0][-1], PAPER_PROFILE[0.2][-1]
    title = (
        "FastMAC@20 is much faster than MAC (time profile; paper 3DMatch: "
        f"{paper_mac:.0f} → {paper_f20:.0f} ms, {paper_mac / paper_f20:.0f}×)"
    )
    aggs = {}
    for data, t, a in page.per_data("time_profile", lambda t: pd.Series(LABEL, index=t.index)):
        aggs[data] = a
        page.add(data_heading(data, a, f", median N = {t['n_in'].median():.0f}"), "")
        rows = []
        for r in RATIOS:
            x = row_of(a, LABEL, r)
            rows.append([f"{r:g}"] + (["–"] * 6 if x is None else [ms(x[f"t_{s}_ms"]) for s in STAGES]))
        page.add(markdown_table(HEADER, rows, ["l"] + ["r"] * 6), "")
        mac, f20 = row_of(a, LABEL, 1.0), row_of(a, LABEL, 0.2)
        if mac is not None and f20 is not None:
            speed = mac["t_total_ms"] / f20["t_total_ms"]
            page.claim(
                title,
                "agrees" if speed >= 5 else "partly" if speed >= 2 else "disagrees",
                f"{data} ({per_seed_pairs(a)}, seed 0): {ms(mac['t_total_ms'])} → {ms(f20['t_total_ms'])} ms "
                f"({speed:.1f}×; MCS "
                f"{ms(mac['t_cliques_ms'])} → {ms(f20['t_cliques_ms'])} ms)",
            )
    if aggs:
        figure(page, aggs)
        page.figure("time_profile.png", "time profile")


def figure(page: Page, aggs: dict[str, pd.DataFrame]) -> None:
    """Stacked median stage times against the ratio, a panel per data set (the paper's Fig. 1, middle)."""
    n = len(aggs)
    ncols = min(n, 3)
    nrows = math.ceil(n / ncols)
    fig, axes = plt.subplots(nrows, ncols, figsize=(5.2 * ncols, 3.9 * nrows + 0.6), squeeze=False)
    for ax, (data, a) in zip(axes.flat, aggs.items(), strict=False):
        rows = [row_of(a, LABEL, r) for r in RATIOS]
        x = np.arange(len(RATIOS))
        bottom = np.zeros(len(RATIOS))
        for s in plots.PROFILE_STAGES:
            v = np.array([0.0 if r is None else np.nan_to_num(r[f"t_{s}_ms"]) for r in rows])
            ax.bar(x, v, bottom=bottom, color=plots.STAGE_COLORS[s], label=plots.STAGE_NAMES[s], width=0.7)
            bottom += v
        for xi, r in zip(x, rows, strict=True):
            if r is not None and np.isfinite(r["t_total_ms"]):
                ax.annotate(ms(r["t_total_ms"]), (xi, r["t_total_ms"]), xytext=(0, 3),
                            textcoords="offset points", ha="center", fontsize=8)  # fmt: skip
                ax.scatter([xi], [r["t_total_ms"]], marker="_", s=250, color="k", zorder=3)
        ax.set_xticks(x)
        ax.set_xticklabels(["MAC" if r == 1.0 else f"{r:g}" for r in RATIOS])
        ax.set_xlabel("sampling ratio")
        ax.set_ylabel("median ms per pair")
        ax.set_title(SHORT[data], fontsize=10)
        ax.margins(y=0.12)
        ax.grid(True, axis="y", alpha=0.3)
    for ax in list(axes.flat)[n:]:
        ax.set_visible(False)
    handles, labels = axes[0, 0].get_legend_handles_labels()
    handles.append(plt.Line2D([], [], color="k", marker="_", ls="", markersize=12))
    labels.append("median total (number)")
    fig.legend(handles, labels, loc="lower center", ncols=len(labels), fontsize=9, frameon=False)
    fig.suptitle("Time profile: median ms per stage (C++ core, one CPU thread for BLAS)", fontsize=12)
    fig.tight_layout(rect=(0, 0.5 / fig.get_figheight(), 1, 1 - 0.4 / fig.get_figheight()))
    fig.savefig(page.fig / "time_profile.png", dpi=110)
    plt.close(fig)
