"""Section 7 of docs/results.md: MAC, FastMAC@50/20 and the peers on the same correspondences (paper Tables
kitti/3dmatch/3dlomatch), from outputs/studies/state_of_the_art_<data>."""

from __future__ import annotations

import math

import matplotlib.pyplot as plt
import numpy as np
import pandas as pd

from fastmac_exp.report import markdown_table
from studies.common import DATA, PAPER_SOTA, SHORT, Page, data_heading, fnum, ms, text

METHOD_ORDER = (
    "mac",
    "fastmac50",
    "fastmac20",
    "ransac1k",
    "ransac10k",
    "fgr",
    "kiss_matcher",
    "turboreg",
    "fastmac20_turboreg",
)
METHOD_NAMES = {"mac": "MAC", "fastmac50": "FastMAC@50", "fastmac20": "FastMAC@20", "ransac1k": "RANSAC 1k",
                "ransac10k": "RANSAC 10k", "fgr": "FGR", "kiss_matcher": "KISS-Matcher",
                "turboreg": "TurboReg", "fastmac20_turboreg": "FastMAC@20 + TurboReg"}  # fmt: skip


def method_of(t: pd.DataFrame) -> pd.Series:
    """State-of-the-art member of a row: fastmac<percent> for high-pass (fastmac<percent>_<backend> in front
    of a backend other than MAC's), else the backend (cpp = mac)."""
    backend = t["backend"].astype(str)
    out = backend.replace({"cpp": "mac"})
    fast = t["sampler"].astype(str).eq("highpass")
    out[fast] = "fastmac" + (t.loc[fast, "ratio"].astype(float) * 100).round().astype(int).astype(str)
    other = fast & ~backend.isin(["cpp", "python"])
    out[other] = out[other] + "_" + backend[other]
    return out


def loss_title() -> str:
    """The claim on FastMAC@20's RR loss, with the paper's MAC -> FastMAC@20 RR per benchmark."""
    paper = ", ".join(
        f"{b} {m['mac'][0]:.2f} → {m['fastmac20'][0]:.2f} %"
        for b, m in PAPER_SOTA.items()
        if "fastmac20" in m
    )
    return (
        f"FastMAC@20 loses little RR against MAC (paper: {paper}; agrees: at most the paper's loss plus one "
        "pair)"
    )


def render(page: Page) -> None:
    page.add(*text("state_of_the_art"))
    aggs = {}
    for data, t, a in page.per_data("state_of_the_art", method_of):
        meth = method_of(t)
        aggs[data] = a
        ref = DATA[data][1]
        paper = PAPER_SOTA.get(ref, {})
        page.add(data_heading(data, a), "")
        header = ["method", "RR (%)", "RE (°)", "TE (cm)", "time (ms)", "failed",
                  f"paper {ref} RR", "paper RE", "paper TE", "paper time (ms)"]  # fmt: skip
        rows = []
        for m in METHOD_ORDER:
            x = a[a["sampler"] == m]
            if not len(x):
                continue
            x, p = x.iloc[0], paper.get(m, (np.nan,) * 4)
            rows.append([METHOD_NAMES[m], fnum(x["RR"]), fnum(x["RE_deg"], 2), fnum(x["TE_cm"], 2),
                         ms(x["t_total_ms"]), str(int(x["failed"])), fnum(p[0], 2), fnum(p[1], 2),
                         fnum(p[2], 2), ms(p[3])])  # fmt: skip
            err = t.loc[meth.eq(m) & t["error"].fillna("").ne(""), "error"]
            if len(err):
                page.notes.append(f"state of the art, {data}, {METHOD_NAMES[m]}: {len(err)} failed "
                                  f"pair(s), e.g. `{err.iloc[0][:160]}`")  # fmt: skip
        page.add(markdown_table(header, rows, ["l"] + ["r"] * 9), "")
        claim(page, data, a, paper)
    if aggs:
        figure(page, aggs)
        page.figure("state_of_the_art.png", "state of the art")


def claim(page: Page, data: str, a: pd.DataFrame, paper: dict) -> None:
    """FastMAC@20 loses at most the paper's own RR loss (on the benchmark the data stand in for) plus one
    pair of ours."""
    mac, f20 = (a[a["sampler"] == m] for m in ("mac", "fastmac20"))
    if not (len(mac) and len(f20)):
        return
    mac, f20 = mac.iloc[0], f20.iloc[0]
    drop, speed = mac["RR"] - f20["RR"], mac["t_total_ms"] / f20["t_total_ms"]
    n_pairs = int(mac["pairs"])
    paper_drop = (
        max(paper["mac"][0] - paper["fastmac20"][0], 0.0) if "mac" in paper and "fastmac20" in paper else 0.0
    )
    page.claim(
        loss_title(),
        "agrees" if drop <= paper_drop + 100 / n_pairs + 1e-9 else "disagrees",
        f"{data} ({n_pairs} pairs, seed 0): RR {fnum(mac['RR'])} → {fnum(f20['RR'])} %, at "
        f"{ms(mac['t_total_ms'])} → {ms(f20['t_total_ms'])} ms ({speed:.1f}×)",
    )


def figure(page: Page, aggs: dict[str, pd.DataFrame]) -> None:
    """RR against the median time per method, a panel per data set."""
    n = len(aggs)
    ncols = min(n, 3)
    nrows = math.ceil(n / ncols)
    fig, axes = plt.subplots(nrows, ncols, figsize=(5.6 * ncols, 4.4 * nrows), squeeze=False)
    cmap = plt.get_cmap("tab10")
    colors = {m: cmap(i) for i, m in enumerate(METHOD_ORDER)}
    for ax, (data, a) in zip(axes.flat, aggs.items(), strict=False):
        for m in METHOD_ORDER:
            x = a[a["sampler"] == m]
            if not len(x) or not np.isfinite(x["t_total_ms"].iloc[0]):
                continue
            ax.scatter(x["t_total_ms"], x["RR"], color=colors[m], s=70, label=METHOD_NAMES[m], zorder=3,
                       marker="*" if m.startswith("fastmac") else "o", alpha=0.85)  # fmt: skip
        ax.set_xscale("log")
        ax.set_ylim(-3, 105)
        ax.set_xlabel("median time per pair (ms, log)")
        ax.set_ylabel("RR (%)")
        ax.set_title(SHORT[data], fontsize=10)
        ax.grid(True, which="both", alpha=0.3)
        ax.margins(x=0.15)
    for ax in list(axes.flat)[n:]:
        ax.set_visible(False)
    handles: dict = {}
    for ax in axes.flat:
        for h, lab in zip(*ax.get_legend_handles_labels(), strict=True):
            handles.setdefault(lab, h)
    fig.legend(list(handles.values()), list(handles.keys()), loc="lower center", ncols=len(handles),
               fontsize=9, frameon=False)  # fmt: skip
    fig.suptitle("State of the art: RR against time on the same correspondences", fontsize=12)
    fig.tight_layout(rect=(0, 0.07 / nrows, 1, 1))
    fig.savefig(page.fig / "state_of_the_art.png", dpi=110)
    plt.close(fig)
