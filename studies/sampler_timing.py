"""Section 4 of docs/results.md, timing: sampling time against the number of samples, stochastic against
greedy deterministic (the paper's Fig. stochastic), from outputs/studies/sampler_timing/timing.csv (written
by studies/time_samplers.py)."""

from __future__ import annotations

import math

import matplotlib.pyplot as plt
import numpy as np
import pandas as pd

from fastmac_exp.report import markdown_table
from studies.common import Page, ms, rr_mean, text
from studies.stochastic import Rows


def render(page: Page, rr: Rows) -> None:
    """The timing table, figure and claims; `rr` is the registration half's rows (studies.stochastic)."""
    timing = page.studies / "sampler_timing" / "timing.csv"
    if not timing.exists():
        return
    tt = pd.read_csv(timing)
    page.add(*text("sampler_timing"))
    header = ["sampler", "N", "samples k", "preparation (ms)", "selection (ms)", "total (ms)"]
    stats = "kept_inlier_ratio" in tt
    if stats:
        header += ["inliers in the sample", "graph edges in the sample"]
    rows = []
    for _, r in tt.iterrows():
        skipped = isinstance(r.get("skipped"), str)
        cells = [r["sampler"], str(int(r["n"])), str(int(r["k"])), ms(r["prep_ms"]),
                 f"skipped ({r['skipped']})" if skipped else ms(r["select_ms"]),
                 "–" if skipped else ms(r["total_ms"])]  # fmt: skip
        if stats:
            cells += ["–" if skipped else f"{100 * r['kept_inlier_ratio']:.0f} %",
                      "–" if skipped else str(int(r["kept_edges"]))]  # fmt: skip
        rows.append(cells)
    page.add(markdown_table(header, rows, ["l"] + ["r"] * (len(header) - 1)), "")
    page.figure(figure(page, tt), "sampling time")
    claims(page, tt, rr)


def claims(page: Page, tt: pd.DataFrame, rr: Rows) -> None:
    """Deterministic sampling is much slower (the largest k timed of 1,000), and its quality."""
    det = tt[tt["sampler"].str.startswith("det") & tt["total_ms"].notna() & tt["n"].eq(1000)]
    sto = tt[tt["sampler"].str.startswith("sto") & tt["n"].eq(1000)].set_index("k")
    if not len(det):
        return
    big = det.sort_values("k").iloc[-1]
    k = int(big["k"])
    sk = float(sto.loc[k, "total_ms"]) if k in sto.index else math.nan
    slower = big["total_ms"] / sk
    kept_txt = ""
    if "kept_inlier_ratio" in tt:
        dk, sk50 = det[det["k"] == 50], sto.loc[[50]] if 50 in sto.index else sto.iloc[:0]
        if len(dk) and len(sk50):
            d0, s0 = dk.iloc[0], sk50.iloc[0]
            kept_txt = (
                f"; with 50 samples the greedy sample holds {100 * d0['kept_inlier_ratio']:.0f} % "
                f"inliers and {int(d0['kept_edges'])} graph edges, the stochastic one "
                f"{100 * s0['kept_inlier_ratio']:.0f} % and {int(s0['kept_edges'])}"
            )
    page.claim(
        "Deterministic sampling is much slower",
        "agrees" if slower >= 10 else "partly" if slower >= 2 else "disagrees",
        f"kitti, {k} of 1,000: deterministic {ms(big['total_ms'])} ms vs stochastic {ms(sk)} ms "
        f"({slower:.0f}× slower)",
    )
    if rr:
        s_rr = np.nanmean([rr_mean(x) for x, _ in rr.values()])
        d_rr = np.nanmean([rr_mean(y) for _, y in rr.values()])
        page.claim(
            "… for similar quality",
            "agrees" if d_rr >= s_rr - 10 else "disagrees: the deterministic sample is worse",
            f"kitti, 10–50 of 1,000: RR stochastic {s_rr:.1f} %, deterministic {d_rr:.1f} % "
            f"(mean over the sample counts){kept_txt}",
        )


def figure(page: Page, tt: pd.DataFrame) -> str:
    """Total time against k (left) and the preparation / selection split at k = 50 of 1,000 (right)."""
    fig, axes = plt.subplots(1, 2, figsize=(13, 5.2), gridspec_kw={"width_ratios": [1.5, 1]})
    ax = axes[0]
    colors = {"sto": "#dd8452", "det": "#4c72b0"}
    for (samp, n), g in tt[tt["total_ms"].notna()].groupby(["sampler", "n"]):
        ls = {500: ":", 1000: "-", 2000: "--"}.get(int(n), "-.")
        g = g.sort_values("k")
        name = "stochastic" if samp.startswith("sto") else "deterministic"
        ax.plot(g["k"], g["total_ms"], ls=ls, marker="o" if name == "stochastic" else "s",
                color=colors[samp[:3]], label=f"{name}, N = {int(n)}")  # fmt: skip
    ax.set_xscale("log")
    ax.set_yscale("log")
    ax.set_xlabel("number of samples k")
    ax.set_ylabel("sampling time per pair (ms, log)")
    ax.grid(True, which="both", alpha=0.3)
    ax.legend(fontsize=8, loc="upper center", bbox_to_anchor=(0.5, -0.14), ncols=3, frameon=False)
    ax.set_title("Time against the number of samples (preparation + selection)", fontsize=10)
    ax = axes[1]
    k0 = 50
    sel = tt[(tt["k"] == k0) & (tt["n"] == 1000) & tt["total_ms"].notna()]
    names = ["stochastic" if s.startswith("sto") else "deterministic" for s in sel["sampler"]]
    y = np.arange(len(sel))
    h = 0.38
    for off, col, color, lab in ((-h / 2, "prep_ms", "#8c8c8c", "preparation"),
                                 (h / 2, "select_ms", "#c44e52", "selection")):  # fmt: skip
        vals = sel[col].to_numpy(float)
        ax.barh(y + off, vals, height=h, color=color, label=lab)
        for yi, v in zip(y + off, vals, strict=True):
            ax.annotate(f"{ms(v)} ms", (v, yi), xytext=(4, 0), textcoords="offset points", va="center",
                        fontsize=8)  # fmt: skip
    ax.set_yticks(y)
    ax.set_yticklabels(names)
    ax.set_xscale("log")
    ax.set_xlim(left=0.01)
    ax.set_xlabel("time (ms, log)")
    ax.set_title(f"Profile: {k0} samples of 1,000 correspondences", fontsize=10)
    ax.legend(fontsize=8, loc="upper center", bbox_to_anchor=(0.5, -0.14), ncols=2, frameon=False)
    ax.margins(x=0.35)
    ax.grid(True, axis="x", which="both", alpha=0.3)
    fig.suptitle("Stochastic vs deterministic sampling: time (one synthetic KITTI-like pair)", fontsize=12)
    fig.tight_layout()
    fig.savefig(page.fig / "stochastic_time.png", dpi=110)
    plt.close(fig)
    return "stochastic_time.png"
