"""The report page: report.md (markdown tables), report.csv (every aggregate column), the PNG plots
(fastmac_exp.report.plots) and pictures of the worst pairs from the runs' rerun recordings."""

from __future__ import annotations

import logging
import math
from pathlib import Path

import numpy as np
import pandas as pd

from fastmac_exp.geometry.metrics import cached_rows
from fastmac_exp.report.tables import REPORT_STAGES, STAGE_LABELS, aggregate, group_keys, load_results
from fastmac_exp.run.results import LOG_NAME

log = logging.getLogger(__name__)


# -- markdown ---------------------------------------------------------------------------------------------
def _fmt(v, digits: int = 2) -> str:
    if v is None or (isinstance(v, float) and not math.isfinite(v)):
        return "–"
    if isinstance(v, bool | np.bool_):
        return str(bool(v))
    if isinstance(v, int | np.integer):
        return str(int(v))
    if isinstance(v, float | np.floating):
        return f"{float(v):.{digits}f}"
    return str(v)


def _fmt_ms(v) -> str:
    if v is None or not math.isfinite(float(v)):
        return "–"
    v = float(v)
    return f"{v:.2f}" if v < 10 else f"{v:.1f}" if v < 1000 else f"{v:.0f}"


def markdown_table(header: list[str], rows: list[list[str]], align: list[str] | None = None) -> str:
    align = align or ["l"] * len(header)
    sep = ["---:" if a == "r" else ":---" for a in align]
    lines = ["| " + " | ".join(header) + " |", "| " + " | ".join(sep) + " |"]
    lines += ["| " + " | ".join(r) + " |" for r in rows]
    return "\n".join(lines)


def pair_snapshots(root: Path, table: pd.DataFrame, out_dir: Path, max_pairs: int) -> list[Path]:
    """PNGs of up to `max_pairs` recorded pairs (the runs' .rrd files), the pairs a researcher wants to see
    first across the whole sweep (not registered, then by RE; see worst_first), for a machine with no
    display to open the recordings on; `out_dir/pairs/<run>/<pair>.png`."""
    if max_pairs <= 0:
        return []
    try:
        from fastmac_exp.trackers.rerun_snapshot import read_pairs, render_pair
        from fastmac_exp.trackers.rerun_tracker import recording_parts, safe_name
    except ImportError as exc:  # rerun-sdk missing: tables and plots still come
        log.warning("no pair snapshots: %s", exc)
        return []
    recorded: dict[str, dict] = {}  # run -> {pair: geometry}, read when a run's pair is first wanted

    def geometry(run: str, pair: str):
        if run not in recorded:
            run_dir = root / run
            geos = {}
            rrds = [*recording_parts(run_dir / "recording.rrd"), *sorted((run_dir / "rerun").glob("*.rrd"))]
            for rrd in rrds:
                try:
                    geos.update({g.name: g for g in read_pairs(rrd)})
                except Exception as exc:  # noqa: BLE001 - one unreadable recording must not stop the report
                    log.warning("no snapshot of %s: %s", rrd, exc)
            recorded[run] = geos
        return recorded[run].get(pair)

    written: list[Path] = []
    rows = table.reset_index(drop=True)
    for k in worst_first(rows, positions=True):
        if len(written) >= max_pairs:
            break
        r = rows.iloc[k]
        run, pair = str(r["run"]), str(r["pair"])
        geo = geometry(run, pair)
        if geo is None:  # a pair that failed before it was recorded, or a run without recordings
            continue
        sub = out_dir / "pairs" if run == "." else out_dir / "pairs" / run
        written.append(render_pair(geo, sub / f"{safe_name(pair)}.png", _pair_title(r)))
    return written


def worst_first(rows: pd.DataFrame, positions: bool = False) -> list:
    """The pairs a researcher wants to see first: not registered, then by RE, largest first (their names,
    or with positions=True their row positions)."""
    ok = rows["success"].astype("boolean").fillna(False).astype(bool).to_numpy()
    re = pd.to_numeric(rows["re_deg"], errors="coerce").fillna(np.inf).to_numpy()
    order = sorted(range(len(rows)), key=lambda k: (ok[k], -re[k]))
    return order if positions else [str(rows["pair"].iloc[k]) for k in order]


def _pair_title(r: pd.Series) -> str:
    ok = "registered" if r.get("success") is True or r.get("success") == 1 else "not registered"
    what = f"{r.get('sampler')}@{r.get('ratio'):g}" if isinstance(r.get("ratio"), int | float) else ""
    return f"{r['pair']}  {what}  {ok}: RE {_fmt(r.get('re_deg'))} deg, TE {_fmt(r.get('te_cm'))} cm"


def render_markdown(agg: pd.DataFrame, source: str, n_runs: int, plots: list[Path], out_dir: Path,
                    snapshots: list[Path] = ()) -> str:  # fmt: skip
    keys = group_keys(agg)
    constant = [k for k in keys if agg[k].nunique(dropna=False) == 1]
    section_keys = [k for k in ("dataset", "descriptor") if k in keys]
    row_keys = [k for k in keys if k not in section_keys and not (k in constant and k != "ratio")]
    lines = [
        "# FastMAC experiment report",
        "",
        f"Source: `{source}` — {n_runs} run(s), {int(agg['pairs'].sum()) if len(agg) else 0} pairs.",
    ]
    const_txt = ", ".join(
        f"{k} = {agg[k].iloc[0]}" for k in constant if k not in section_keys and k != "ratio"
    )
    if const_txt:
        lines.append(f"All rows: {const_txt}.")
    lines += [
        "",
        "RR: registration recall in % of all pairs (failed pairs count as not registered); RE/TE: mean "
        "rotation (deg) and translation (cm) error over the successful pairs; times: median ms per pair "
        "(Sampling, GC = graph construction, MCS = maximal clique search, NCS = node-guided clique "
        "selection, PE = pose estimation; total = sampling + MAC; describe = features + matching).",
    ]
    multi_seed = bool((agg["seeds"] >= 2).any()) if "seeds" in agg else False
    sections = agg.groupby(section_keys, sort=False) if section_keys else [((), agg)]
    for sec, g in sections:
        sec = sec if isinstance(sec, tuple) else (sec,)
        title = " × ".join(f"{k} {v}" for k, v in zip(section_keys, sec, strict=True)) or "all"
        lines += ["", f"## {title}", "", "### Registration", ""]
        header = row_keys + ["pairs", "failed", "RR (%)", "RE (deg)", "TE (cm)"]
        if multi_seed:
            header += ["RR across seeds (%)", "seeds"]
        rows = []
        for _, r in g.iterrows():
            cells = [_fmt(r[k], 3) if k == "ratio" else _fmt(r[k]) for k in row_keys]
            if "ratio" in row_keys:
                cells[row_keys.index("ratio")] = f"{r['ratio']:g}"
            cells += [
                _fmt(r["pairs"]),
                _fmt(r["failed"]),
                _fmt(r["RR"], 1),
                _fmt(r["RE_deg"]),
                _fmt(r["TE_cm"]),
            ]
            if multi_seed:
                seed_txt = (
                    f"{r['RR_seed_mean']:.1f} ± {r['RR_seed_std']:.1f}"
                    if r["seeds"] >= 2
                    else _fmt(r["RR"], 1)
                )
                cells += [seed_txt, _fmt(r["seeds"])]
            rows.append(cells)
        lines.append(
            markdown_table(header, rows, ["l"] * len(row_keys) + ["r"] * (len(header) - len(row_keys)))
        )
        stages = [s for s in REPORT_STAGES if f"t_{s}_ms" in g and g[f"t_{s}_ms"].notna().any()]
        if stages:
            lines += ["", "### Time profile (median ms per pair)", ""]
            # Which clique search ran (auto picks per pair) and how many pairs hit a cap: the times
            # depend on both.
            with_search = "searches" in g and bool((g["searches"] != "").any())
            header = row_keys + [STAGE_LABELS[s] for s in stages]
            if with_search:
                header += ["search (pairs)", "capped"]
            rows = []
            for _, r in g.iterrows():
                cells = [f"{r[k]:g}" if k == "ratio" else _fmt(r[k]) for k in row_keys]
                cells += [_fmt_ms(r[f"t_{s}_ms"]) for s in stages]
                if with_search:
                    cells += [r["searches"] or "–", _fmt(r["capped"])]
                rows.append(cells)
            align = ["l"] * len(row_keys) + ["r"] * len(stages) + (["l", "r"] if with_search else [])
            lines.append(markdown_table(header, rows, align))
    for title, images in (("Plots", plots), ("Pairs (from the rerun recordings)", snapshots)):
        if images:
            lines += ["", f"## {title}", ""]
        for p in images:
            rel = p.relative_to(out_dir) if p.is_relative_to(out_dir) else p
            lines += [f"![{p.stem}]({rel})", ""]
    return "\n".join(lines).rstrip() + "\n"


# -- entry point ------------------------------------------------------------------------------------------
def make_report(
    root: str | Path, out: str | Path | None = None, plots: bool = True, snapshots: int = 4
) -> dict:
    """Write report.md, report.csv, the plots and PNG snapshots of up to `snapshots` recorded pairs for
    the runs below `root`; returns what was written."""
    root = Path(root)
    if not root.is_dir():
        raise FileNotFoundError(f"{root}: no such directory")
    out_dir = Path(out) if out else root / "report"
    table = load_results(root, exclude=[out_dir])
    if table.empty:
        raise FileNotFoundError(f"no results.parquet or {LOG_NAME} below {root}")
    out_dir.mkdir(parents=True, exist_ok=True)
    agg = aggregate(table)
    agg.to_csv(out_dir / "report.csv", index=False)
    written: list[Path] = []
    if plots:
        from fastmac_exp.report.plots import plot_all

        written = plot_all(agg, out_dir)
    pictures = pair_snapshots(root, table, out_dir, snapshots)
    n_runs = table["run"].nunique()
    text = render_markdown(agg, str(root), n_runs, written, out_dir, pictures)
    n_cached = cached_rows(table)
    if n_cached:
        text += (f"\nDescribe times: {n_cached} of {len(table)} rows read their correspondences from the "
                 "cache; their describe time is the one measured when the entry was computed.\n")  # fmt: skip
    (out_dir / "report.md").write_text(text)
    return {"table": table, "aggregate": agg, "out_dir": out_dir, "plots": written, "snapshots": pictures}
