"""Section 5 of docs/results.md: FastMAC's robustness to the descriptor (paper Fig. desc) on KITTI (the
KITTI-like family and the real outdoor pairs) and indoors (the 3DMatch-like family and the real indoor
pairs), every descriptor here (fpfh, fcgf_lite, buffer, spinnet), from
outputs/studies/descriptor_robustness_<data>; one figure a panel (RR / RE / TE against the ratio, a line a
descriptor), the inlier ratio of each descriptor's correspondences, the paper's claim checked; then the
hand-written BUFFER section (studies/text/descriptor_robustness_buffer.md).

`python -m studies.descriptor_robustness` rewrites section 5 of an existing docs/results.md (and its rows
in the wall-time table) without the other studies' runs."""

from __future__ import annotations

import argparse
import re
from pathlib import Path

import numpy as np

from fastmac_exp.report import markdown_table
from studies.common import (
    DATA,
    PAPER_RR,
    RATIOS,
    REPO,
    Page,
    data_heading,
    fnum,
    per_seed_pairs,
    ran_line,
    ran_records,
    render_claims,
    row_of,
    rr_cell,
    rr_mean,
    te_cell,
    text,
    verbatim,
    wall_times,
)

PANELS = {
    "kitti": ("Outdoor (paper's KITTI panel)", ("kitti", "real_outdoor"), "descriptor_robustness_kitti.png"),
    "indoor": ("Indoor (3DMatch)", ("3dmatch", "real_indoor"), "descriptor_robustness_indoor.png"),
    "object": ("Object scans (not in the paper)", ("real_object",), "descriptor_robustness_object.png"),
}
ORDER = ("fpfh", "fcgf_lite", "buffer", "buffer_int8", "spinnet", "spinnet_int8")
CLAIM = "Stronger descriptors keep RR at every ratio; FCGF and FPFH lose some at 1 %"
STRONG = ("spinnet", "spinnet_int8", "buffer", "buffer_int8")


def _descs(a) -> list[str]:
    found = set(a["sampler"])
    return [d for d in ORDER if d in found] + sorted(found - set(ORDER))


def _ir(t, d: str) -> float:
    return float(t.loc[t["descriptor"].astype(str).eq(d), "inlier_ratio_in"].mean())


def _claim(page: Page, data: str, t, a, descs: list[str]) -> str:
    """The paper's claim on one data set: RR at 1 % against 100 % per descriptor. "Strong" as the paper
    has it: SpinNet (the paper's list: GeoTransformer, CoFiNet, SpinNet, Predator), and BUFFER, SpinNet's
    successor; "weak": FPFH and fcgf_lite (standing in for FCGF)."""
    pairs = int(a["pairs"].max()) // max(int(a["seeds"].max()) if "seeds" in a else 1, 1)
    one = 100.0 / max(pairs, 1)
    drops = {d: rr_mean(row_of(a, d, 1.0)) - rr_mean(row_of(a, d, 0.01)) for d in descs}
    strong = [d for d in descs if d in STRONG]
    weak = [d for d in descs if d not in STRONG]
    keeps = all(drops[d] < one - 1e-9 for d in strong)
    weak_lose = [d for d in weak if drops[d] >= one - 1e-9]
    if any(not np.isfinite(v) for v in drops.values()):
        verdict = "incomplete (a descriptor lacks ratio 1 or 0.01)"
    elif not strong:
        verdict = "not tested (no strong descriptor ran)"
    elif keeps and weak_lose:
        verdict = "holds"
    elif keeps:
        verdict = "partly (the strong keep RR, but FPFH and fcgf_lite lose none either)"
    else:
        lost = ", ".join(d for d in strong if drops[d] >= one - 1e-9)
        verdict = f"does not hold ({lost} loses RR at 1 %)"
    ev = ", ".join(
        f"{d} {fnum(rr_mean(row_of(a, d, 1.0)))} → {fnum(rr_mean(row_of(a, d, 0.01)))}" for d in descs
    )
    page.claim(CLAIM, verdict, f"{data} ({per_seed_pairs(a)}): RR 100 % → 1 %: {ev}")  # its own pair count
    return (
        f"Paper's claim (*{CLAIM}*), here: **{verdict}**. RR at 100 % → 1 %: {ev} (one pair = "
        f"{one:.1f} points; strong: {', '.join(strong) or 'none'})."
    )


def trust_counts(t, d: str, ratio: float | None = None) -> tuple[int, int, int, int]:
    """(runs with a pose, right poses, false accepts: trusted and wrong, false rejects: right and not
    trusted) of descriptor d's rows, at one ratio or all; a row that failed has no pose to trust."""
    m = t["descriptor"].astype(str).eq(d) & t["error"].fillna("").eq("")
    if ratio is not None:
        m &= np.isclose(t["ratio"].astype(float), ratio)
    ok = t.loc[m, "success"].fillna(False).astype(bool)
    trusted = t.loc[m, "trusted"].fillna(False).astype(bool)
    return int(m.sum()), int(ok.sum()), int((trusted & ~ok).sum()), int((ok & ~trusted).sum())


def trust_table(t, descs: list[str]) -> str:
    """The `trusted` verdict against the GT per descriptor: every ratio, and FastMAC@20 alone."""
    rows = []
    for d in descs:
        every, at20 = trust_counts(t, d), trust_counts(t, d, 0.2)
        rows.append([d, *(f"{v:,}" for v in every), ", ".join(str(v) for v in at20)])
    header = ["descriptor", "runs", "right", "FA", "FR", "ratio 0.2: runs, right, FA, FR"]
    return markdown_table(header, rows, ["l", "r", "r", "r", "r", "r"])


def render(page: Page) -> None:
    page.add(*text("descriptor_robustness"))
    aggs = {}
    for data, t, a in page.per_data("descriptor_robustness", lambda t: t["descriptor"].astype(str)):
        aggs[data] = a
        ref = DATA[data][1]
        descs = _descs(a)
        page.add(data_heading(data, a), "")
        header = ["ratio"] + [f"{d} RR" for d in descs] + [f"{d} RE (°)" for d in descs]
        header += [f"{d} TE (cm)" for d in descs]
        paper_cols = [k for k in ("fpfh", "fcgf") if (ref, k) in PAPER_RR]
        header += [f"paper {ref} {k.upper()} RR" for k in paper_cols]
        rows = []
        for i, r in enumerate(RATIOS):
            cells = [f"{r:g}"] + [rr_cell(row_of(a, d, r)) for d in descs]
            cells += [
                fnum(row_of(a, d, r)["RE_deg"], 2) if row_of(a, d, r) is not None else "–" for d in descs
            ]
            cells += [te_cell(row_of(a, d, r)) for d in descs]
            cells += [fnum(PAPER_RR[(ref, k)][i], 2) for k in paper_cols]
            rows.append(cells)
        page.add(markdown_table(header, rows, ["l"] + ["r"] * (len(header) - 1)), "")
        inl = ", ".join(f"{d} {100 * _ir(t, d):.1f} %" for d in descs)
        page.add(f"Mean inlier ratio of the correspondences: {inl}.", "")
        n_in = t[np.isclose(t["ratio"].astype(float), 1.0)].groupby("descriptor")["n_in"].median()
        page.add(
            "Median correspondences a pair (what the ratios are fractions of; at 1 % FastMAC keeps a "
            "hundredth): " + ", ".join(f"{d} {n_in[d]:,.0f}" for d in descs if d in n_in) + ".",
            "",
        )
        if data.startswith("real_"):
            first = t[np.isclose(t["ratio"].astype(float), 1.0)]
            piv = first.pivot_table(
                index="pair", columns="descriptor", values="inlier_ratio_in", aggfunc="mean"
            )
            piv = piv[[d for d in descs if d in piv.columns]]
            prow = [[f"`{p}`"] + [fnum(100 * v, 1) for v in r] for p, r in piv.iterrows()]
            page.add(
                markdown_table(
                    ["pair (inlier ratio, %)"] + list(piv.columns), prow, ["l"] + ["r"] * len(piv.columns)
                ),
                "",
            )
        # the first seed's runs described the clouds; a later seed's learned descriptors reuse them (the
        # process-wide memory of described clouds) and report only the matching and the rows not yet described
        first_seed = t["seed"].min() if "seed" in t else None
        desc_s = (
            t.loc[
                ~t["describe_cached"].fillna(False).astype(bool)
                & (t["seed"].eq(first_seed) if first_seed is not None else True)
            ]
            .groupby("descriptor")["t_describe_ms"]
            .median()
            if "describe_cached" in t
            else None
        )
        if desc_s is not None and len(desc_s):
            page.add(
                "Median seconds describing a pair (the runs that described it: the first ratio's, seed "
                f"{first_seed if first_seed is not None else 0}; the other ratios read the correspondence "
                "cache): " + ", ".join(f"{d} {desc_s[d] / 1e3:.1f}" for d in descs if d in desc_s) + ".",
                "",
            )
        page.add(_claim(page, data, t, a, descs), "")
        if "trusted" in t:
            page.add(
                "The `trusted` verdict (docs/trust.md) against the GT, over the runs that gave a pose "
                "(pairs x seeds x ratios): FA = trusted and wrong, FR = right and not trusted; the last "
                "column is FastMAC@20 alone (register()'s default):",
                "",
                trust_table(t, descs),
                "",
            )
        for d in descs:
            err = t.loc[t["descriptor"].astype(str).eq(d) & t["error"].fillna("").ne(""), "error"]
            if len(err):
                page.notes.append(f"descriptor robustness, {data}, {d}: {len(err)} failed row(s), e.g. "
                                  f"`{err.iloc[0][:160]}`")  # fmt: skip
    for title, members, name in PANELS.values():
        part = {d: aggs[d] for d in members if d in aggs}
        if part:
            full = f"Descriptor robustness, {title}: FastMAC (high-pass) on every descriptor"
            page.figure(page.line_figure(part, name, full), f"descriptor robustness, {title}")
    page.add(*text("descriptor_robustness_findings"))  # by hand, from the tables of the last run
    page.add(*verbatim("descriptor_robustness_buffer"), "")  # descriptors/evaluate.py --real, by hand


def _replace(lines: list[str], old: list[str], new: list[str]) -> list[str]:
    """`lines` without the lines `old` (found by scanning `lines`, so old[0] comes first) and with `new` where
    old[0] was; unchanged where either is empty."""
    if not old or not new:
        return lines
    at, gone = lines.index(old[0]), set(old)
    return lines[:at] + new + [ln for ln in lines[at:] if ln not in gone]


def splice(studies: Path, docs: Path) -> None:
    """Rewrite section 5 of <docs>/results.md (up to "## 6.") from <studies>, its figures and CSVs, its claim
    in the recomputed list, its notes in the page's notes, and the descriptor_robustness rows of the
    wall-time table and the logged commands."""
    page = Page(studies=studies, docs=docs)
    page.fig.mkdir(parents=True, exist_ok=True)
    for old in [*page.fig.glob("descriptor_robustness*.png"), *page.csv.glob("descriptor_robustness_*.csv")]:
        old.unlink()
    render(page)
    records = ran_records(studies, ["descriptor_robustness_*"])  # the line under the heading, as make_results
    if records:
        page.md[1:1] = ["", ran_line(records)]
    md = (docs / "results.md").read_text()
    start, end = md.index("## 5. "), md.index("## 6. ")
    md = md[:start] + "\n".join(page.md).rstrip() + "\n\n" + md[end:]
    new = "\n".join(wall_times(studies)).splitlines()
    rows = [ln for ln in new if ln.startswith("| `descriptor_robustness_")]
    cmds = [ln for ln in new if ln.startswith("python run.py") and "descriptor_robustness_" in ln]
    lines = md.splitlines()
    # the claim (its title line and its evidence lines) and the notes, as make_results writes them
    head = next((i for i, ln in enumerate(lines) if ln.startswith(f"- **{CLAIM}**")), None)
    if head is not None and CLAIM in page.claims:
        stop = head + 1
        while stop < len(lines) and lines[stop].startswith("  - "):
            stop += 1
        lines[head:stop] = render_claims({CLAIM: page.claims[CLAIM]}, {})
    notes = [ln for ln in lines if ln.startswith("- descriptor robustness, ")]
    lines = _replace(lines, notes, [f"- {n}" for n in page.notes])
    old_rows = [ln for ln in lines if ln.startswith("| `descriptor_robustness_")]
    if old_rows and rows:
        secs = lambda rs: sum(int(r.split("|")[2].strip()) for r in rs)  # noqa: E731
        for i, ln in enumerate(lines):
            if m := re.match(r"\| \*\*total\*\* \| \*\*(\d+) s", ln):
                total = int(m.group(1)) - secs(old_rows) + secs(rows)
                lines[i] = f"| **total** | **{total} s ({total / 60:.0f} min)** |"
    lines = _replace(lines, old_rows, rows)
    old_cmds = [ln for ln in lines if ln.startswith("python run.py") and "descriptor_robustness_" in ln]
    lines = _replace(lines, old_cmds, cmds)
    (docs / "results.md").write_text("\n".join(lines).rstrip() + "\n")


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--studies", type=Path, default=REPO / "outputs" / "studies")
    ap.add_argument("--docs", type=Path, default=REPO / "docs")
    args = ap.parse_args(argv)
    splice(args.studies, args.docs)
    print(f"rewrote section 5 of {args.docs / 'results.md'}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
