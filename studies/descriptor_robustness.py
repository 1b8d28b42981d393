"""Section 5 of docs/results.md: FastMAC on FPFH and on learned descriptors (paper Fig. desc), from
outputs/studies/descriptor_robustness_<data>, then the hand-written BUFFER section
(studies/text/descriptor_robustness_buffer.md)."""

from __future__ import annotations

from fastmac_exp.report import markdown_table
from studies.common import (
    DATA,
    PAPER_RR,
    RATIOS,
    Page,
    data_heading,
    fnum,
    row_of,
    rr_cell,
    te_cell,
    text,
    verbatim,
)


def render(page: Page) -> None:
    page.add(*text("descriptor_robustness"))
    aggs = {}
    for data, t, a in page.per_data("descriptor_robustness", lambda t: t["descriptor"].astype(str)):
        aggs[data] = a
        ref = DATA[data][1]
        descs = sorted(set(a["sampler"]))
        page.add(data_heading(data, a), "")
        header = ["ratio"] + [f"{d} RR" for d in descs] + [f"{d} TE (cm)" for d in descs]
        paper_key = {d: "fpfh" if d == "fpfh" else "fcgf" for d in descs}
        paper_cols = list(dict.fromkeys(paper_key.values()))
        header += [f"paper {ref} {k.upper()} RR" for k in paper_cols]
        rows = []
        for i, r in enumerate(RATIOS):
            cells = [f"{r:g}"] + [rr_cell(row_of(a, d, r)) for d in descs]
            cells += [te_cell(row_of(a, d, r)) for d in descs]
            cells += [fnum(PAPER_RR[(ref, k)][i], 2) if (ref, k) in PAPER_RR else "–" for k in paper_cols]
            rows.append(cells)
        page.add(markdown_table(header, rows, ["l"] + ["r"] * (len(header) - 1)), "")
        inlier = {d: 100 * t.loc[t["descriptor"].astype(str).eq(d), "inlier_ratio_in"].mean() for d in descs}
        inl = ", ".join(f"{d} {v:.1f} %" for d, v in inlier.items())
        page.add(f"Mean inlier ratio of the correspondences: {inl}.", "")
        for d in descs:
            err = t.loc[t["descriptor"].astype(str).eq(d) & t["error"].fillna("").ne(""), "error"]
            if len(err):
                page.notes.append(f"descriptor robustness, {data}, {d}: {len(err)} failed row(s), e.g. "
                                  f"`{err.iloc[0][:160]}`")  # fmt: skip
    if aggs:
        title = "Descriptor robustness: FastMAC (high-pass) on FPFH and on the learned descriptors"
        page.figure(page.line_figure(aggs, "descriptor_robustness.png", title), "descriptor robustness")
    page.add(*verbatim("descriptor_robustness_buffer"), "")  # training/evaluate.py --real, by hand
