"""Section 3 of docs/results.md: the degree signal against the xyz signal (paper Fig. ablation), from
outputs/studies/signal_ablation_<data>."""

from __future__ import annotations

from fastmac_exp.report import markdown_table
from studies.common import (
    Page,
    compare,
    data_heading,
    ms,
    one_pair,
    row_of,
    rr_cell,
    rr_mean,
    tally,
    te_cell,
    text,
)

SIGNAL_NAMES = {
    "xyz001": "001 degree",
    "xyz110": "110 xyz",
    "xyz111": "111 degree+xyz",
    "xyz000": "000 random",
}
CLAIMS = (
    ("xyz110", "The degree signal beats the xyz signal (001 > 110)"),
    ("xyz111", "Adding xyz to the degree hurts (001 > 111)"),
)


def render(page: Page) -> None:
    page.add(*text("signal_ablation"))
    aggs = {}
    for data, _, a in page.per_data("signal_ablation"):
        aggs[data] = a
        page.add(data_heading(data, a), "")
        codes = [c for c in SIGNAL_NAMES if c in set(a["sampler"])]
        ratios = sorted(a["ratio"].unique(), reverse=True)
        header = ["ratio"] + [f"{SIGNAL_NAMES[c]} RR" for c in codes]
        header += [f"{SIGNAL_NAMES[c]} TE (cm)" for c in codes]
        rows = [
            [f"{r:g}"] + [rr_cell(row_of(a, c, r)) for c in codes] + [te_cell(row_of(a, c, r)) for c in codes]
            for r in ratios
        ]
        page.add(markdown_table(header, rows, ["l"] + ["r"] * 2 * len(codes)), "")
        t_s = ", ".join(f"{SIGNAL_NAMES[c]} {ms(a.loc[a['sampler'] == c, 't_sampling_ms'].median())}"
                        for c in codes)  # fmt: skip
        page.add(f"Median sampling time per pair (ms): {t_s}.", "")
        for other, title in CLAIMS:
            both = [(row_of(a, "xyz001", r), row_of(a, other, r)) for r in ratios]
            res = [
                compare(rr_mean(d), [rr_mean(o)], one_pair(a))
                for d, o in both
                if d is not None and o is not None
            ]
            wins, losses = res.count("better"), res.count("worse")
            ties = len(res) - wins - losses  # equal, or apart by less than one pair
            page.claim(
                title,
                tally(wins, losses),
                f"{data}: 001 above at {wins}, tied at {ties}, below at {losses} of {len(res)} ratios",
            )
    if aggs:
        title = "Signal ablation: which graph signal guides the sampling (seed 0)"
        page.figure(page.line_figure(aggs, "signal_ablation.png", title, SIGNAL_NAMES), "signal ablation")
