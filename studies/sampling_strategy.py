"""Section 1 of docs/results.md: high-pass vs random vs FPS sampling (paper Figs. down1-3), from
outputs/studies/sampling_strategy_<data>/{sweep,mac}."""

from __future__ import annotations

import numpy as np
import pandas as pd

from fastmac_exp.report import markdown_table
from studies.common import (
    DATA,
    PAPER_RR,
    RATIOS,
    Page,
    compare,
    data_heading,
    fnum,
    per_seed_pairs,
    re_te,
    row_of,
    rr_cell,
    rr_mean,
    text,
)

SAMPLER_NAMES = {"highpass": "high-pass", "random": "random", "fps": "FPS"}


def render(page: Page) -> None:
    page.add(*text("sampling_strategy"))
    aggs = {}
    for data, t, a in page.per_data("sampling_strategy"):
        zero = t.groupby("pair")["inliers_in"].max()
        if (zero == 0).any():
            names = ", ".join(f"`{p}`" for p in zero[zero == 0].index)
            page.notes.append(f"{data}: {names} has no correct correspondence at all (0 GT inliers among "
                              "the FPFH matches), so no correspondence-based method can register it; "
                              "it caps the RR of every method in this data set.")  # fmt: skip
        mac = a[a["sampler"] == "none"]  # the ratio-1 point of every line
        a = pd.concat([a[a["sampler"] != "none"]] + [mac.assign(sampler=s) for s in SAMPLER_NAMES],
                      ignore_index=True)  # fmt: skip
        aggs[data] = a
        page.pair_counts[data] = per_seed_pairs(a)
        page.mac_rr[data] = f"{rr_cell(row_of(a, 'highpass', 1.0))} %"
        ref = DATA[data][1]
        paper = PAPER_RR[(ref, "fpfh")]
        page.add(data_heading(data, a), "")
        header = ["ratio"] + [f"{n} RR" for n in SAMPLER_NAMES.values()] + [f"paper RR ({ref} FPFH)"]
        rows = [
            [f"{r:g}"] + [rr_cell(row_of(a, s, r)) for s in SAMPLER_NAMES] + [fnum(paper[i], 2)]
            for i, r in enumerate(RATIOS)
        ]
        page.add(markdown_table(header, rows, ["l", "r", "r", "r", "r"]), "")
        header = ["ratio"] + [f"{n} RE (°) / TE (cm)" for n in SAMPLER_NAMES.values()]
        rows = [[f"{r:g}"] + [re_te(row_of(a, s, r)) for s in SAMPLER_NAMES] for r in RATIOS]
        page.add(markdown_table(header, rows, ["l", "r", "r", "r"]), "")
        claims(page, data, a)
    if aggs:
        title = "Sampling strategy: high-pass vs random vs FPS (MAC after each); band = ± std over seeds"
        page.figure(page.line_figure(aggs, "sampling_strategy.png", title), "sampling strategy")


def claims(page: Page, data: str, a: pd.DataFrame) -> None:
    """High-pass against the others at 5 % and 1 %; FPS against random at 20-5 %."""
    for r in (0.05, 0.01):
        hp, rnd, fps = (row_of(a, s, r) for s in SAMPLER_NAMES)
        if hp is None or rnd is None or fps is None:
            continue
        spread = float(np.nanmax([hp["RR_seed_std"], rnd["RR_seed_std"], fps["RR_seed_std"], 0.0]))
        c = compare(rr_mean(hp), [rr_mean(rnd), rr_mean(fps)], spread)
        te = ""
        if c == "tie":
            te = f"; TE {fnum(hp['TE_cm'], 1)} vs {fnum(rnd['TE_cm'], 1)} / {fnum(fps['TE_cm'], 1)} cm"
        v = {"better": "agrees", "tie": "no difference"}.get(c, "partly" if "within" in c else "disagrees")
        page.claim(
            f"High-pass beats random and FPS at {r:g}",
            v,
            f"{data}: high-pass {rr_cell(hp)} vs random {rr_cell(rnd)}, FPS {rr_cell(fps)}{te}",
        )
    pairs = [(row_of(a, "fps", r), row_of(a, "random", r)) for r in (0.2, 0.1, 0.05)]
    pairs = [(f, q) for f, q in pairs if f is not None and q is not None]
    below = sum(rr_mean(f) < rr_mean(q) for f, q in pairs)
    same = sum(rr_mean(f) == rr_mean(q) for f, q in pairs)
    if pairs:
        above = len(pairs) - below - same
        v = (
            "agrees"
            if below > len(pairs) / 2
            else "no difference"
            if same == len(pairs)
            else "partly (otherwise tied)"
            if above == 0
            else "disagrees"
        )
        page.claim(
            "FPS is worse than random (paper: KITTI)",
            v,
            f"{data}: FPS below random at {below}, equal at {same} of {len(pairs)} ratios (0.2, 0.1, 0.05)",
        )
