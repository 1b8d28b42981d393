"""Section 4 of docs/results.md, registration: greedy deterministic against stochastic high-pass sampling
(paper Fig. stochastic), from outputs/studies/stochastic_vs_deterministic_kitti. The timing half of the
section is studies/sampler_timing.py."""

from __future__ import annotations

import numpy as np
import pandas as pd

from fastmac_exp.report import markdown_table
from studies.common import DATA, Page, agg_by, fnum, row_of, rr_cell, text

Rows = dict[float, tuple[pd.Series | None, pd.Series | None]]


def render(page: Page) -> Rows:
    """The section's head and registration table; returns ratio -> (stochastic row, deterministic row) of
    the aggregate (empty when the study did not run) for the timing half's quality claim."""
    page.add(*text("stochastic"))
    t = page.load("stochastic_vs_deterministic", "kitti")
    rr: Rows = {}
    if t is None:
        return rr
    a = agg_by(t, t["sampler"].astype(str))
    page.save_csv(a, "stochastic_vs_deterministic_kitti")
    n_pairs = int(a["pairs"].max())
    page.add(f"### Registration (kitti: {DATA['kitti'][0]}; {n_pairs} pairs, 1,000 correspondences)", "")
    header = ["samples (ratio)", "stochastic RR", "deterministic RR", "deterministic: no graph edge",
              "stochastic: inlier ratio kept"]  # fmt: skip
    noedge = t["error"].fillna("").str.contains("edge")
    rows = []
    for r in sorted(a["ratio"].unique(), reverse=True):
        s, d = row_of(a, "highpass", r), row_of(a, "deterministic", r)
        ne = int((noedge & t["sampler"].eq("deterministic") & np.isclose(t["ratio"], r)).sum())
        rr[r] = (s, d)
        kept = fnum(100 * s["inlier_ratio_kept"], 1) + " %" if s is not None else "–"
        rows.append([f"{int(round(1000 * r))} ({r:g})", rr_cell(s), rr_cell(d), f"{ne} of {n_pairs}", kept])
    page.add(markdown_table(header, rows, ["l"] + ["r"] * 4), "")
    page.add(*text("stochastic_failed_runs"))
    return rr
