"""Section 2 of docs/results.md: high-pass vs low-pass vs all-pass filter of the degree signal (paper Table
filter), from outputs/studies/filter_ablation_<data>."""

from __future__ import annotations

import pandas as pd

from fastmac_exp.report import markdown_table
from studies.common import (
    PAPER_FILTER,
    Page,
    compare,
    data_heading,
    one_pair,
    re_te,
    row_of,
    rr_cell,
    rr_mean,
    tally,
    text,
)

FILTER_NAMES = {
    "highpass": "high-pass",
    "allpass": "all-pass",
    "lowpass": "low-pass",
    "highpass_squared": "high-pass |f|²",  # the paper's main text; the code (and our default) uses |f|
}


def render(page: Page) -> None:
    page.add(*text("filter_ablation"))
    page.add("Paper (KITTI, FCGF):", "")
    paper_filters = [f for f in FILTER_NAMES if f in PAPER_FILTER]  # the paper tables the code's |f|
    header = ["ratio"] + [f"{FILTER_NAMES[f]} RR" for f in paper_filters]
    header += [f"{FILTER_NAMES[f]} RE (°) / TE (cm)" for f in paper_filters]
    rows = [[f"{r:g}"] + [f"{PAPER_FILTER[f][r][0]:.2f}" for f in paper_filters]
            + [f"{PAPER_FILTER[f][r][1]:.3f} / {PAPER_FILTER[f][r][2]:.2f}" for f in paper_filters]
            for r in (0.5, 0.2, 0.1, 0.05, 0.01)]  # fmt: skip
    page.add(markdown_table(header, rows, ["l"] + ["r"] * (2 * len(paper_filters))), "")
    aggs = {}
    for data, _, a in page.per_data("filter_ablation"):
        aggs[data] = a
        page.add(data_heading(data, a), "")
        ratios = sorted(a["ratio"].unique(), reverse=True)
        header = ["ratio"] + [f"{n} RR" for n in FILTER_NAMES.values()]
        header += [f"{n} RE (°) / TE (cm)" for n in FILTER_NAMES.values()]
        rows = [[f"{r:g}"] + [rr_cell(row_of(a, f, r)) for f in FILTER_NAMES]
                + [re_te(row_of(a, f, r)) for f in FILTER_NAMES] for r in ratios]  # fmt: skip
        page.add(markdown_table(header, rows, ["l"] + ["r"] * (2 * len(FILTER_NAMES))), "")
        claim(page, data, a, ratios)
    if aggs:
        title = "Filter ablation: high-pass vs low-pass vs all-pass of the degree signal"
        page.figure(page.line_figure(aggs, "filter_ablation.png", title, FILTER_NAMES), "filter ablation")


def claim(page: Page, data: str, a: pd.DataFrame, ratios: list[float]) -> None:
    """High-pass against the better of low-pass and all-pass at every ratio (within one pair: a tie)."""
    res = []
    for r in ratios:
        hp, lo, al = (row_of(a, f, r) for f in ("highpass", "lowpass", "allpass"))
        if hp is not None and lo is not None and al is not None:
            res.append((r, compare(rr_mean(hp), [rr_mean(lo), rr_mean(al)], one_pair(a)), hp, lo, al))
    wins = sum(c == "better" for _, c, *_ in res)
    losses = sum(c == "worse" for _, c, *_ in res)
    ties = len(res) - wins - losses  # equal, or apart by less than one pair
    low = "; ".join(f"{r:g}: {rr_cell(h)} / {rr_cell(lo)} / {rr_cell(al)}" for r, _, h, lo, al in res
                    if r <= 0.05)  # fmt: skip
    page.claim(
        "High-pass beats low-pass and all-pass",
        tally(wins, losses),
        f"{data}: high-pass best at {wins}, tied at {ties}, behind at {losses} of {len(res)} ratios "
        f"(RR high / low / all at {low})",
    )
