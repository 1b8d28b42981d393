"""Paper-style tables and plots from a run or a sweep directory.

    python -m fastmac_exp.report outputs/multirun/2024-06-01_12-00-00 [--out DIR] [--no-plots]

Every results table below the directory (results.parquet, or results.jsonl for an interrupted run) is
read and concatenated, then aggregated per dataset x descriptor x sampler x ratio x backend x protocol:
pairs, failed, RR (%), mean RE (deg) and TE (cm) over the successful pairs, the median time per stage
and in total (ms), and, where a configuration ran with several seeds, the mean and standard deviation
of RR across seeds. Written to <out>/report.md (markdown tables), <out>/report.csv (every aggregate
column) and PNG plots (see fastmac_exp.report.plots); <out> defaults to <dir>/report.
"""

from __future__ import annotations

import argparse
import logging
import math
import sys
from collections.abc import Iterable
from pathlib import Path
from typing import Any

import numpy as np
import pandas as pd
from omegaconf import OmegaConf

from fastmac_exp.geometry.metrics import STAGES, cached_rows
from fastmac_exp.run.results import LOG_NAME, load_table, read_rows, to_table
from fastmac_exp.run.resume import CONFIG_NAME, RESUMED_NAME, differences

log = logging.getLogger(__name__)

GROUP_KEYS = ("dataset", "descriptor", "sampler", "ratio", "backend", "protocol")
# the tables' column order: MAC's stages, their total, then describe (which the total leaves out)
REPORT_STAGES = (*STAGES[1:], STAGES[0])
STAGE_LABELS = {  # the paper's names for the MAC stages
    "sampling": "Sampling",
    "graph": "GC",
    "cliques": "MCS",
    "selection": "NCS",
    "pose": "PE",
    "total": "total",
    "describe": "describe",
}


# -- loading ----------------------------------------------------------------------------------------------
def find_runs(root: str | Path, exclude: Iterable[Path] = ()) -> list[Path]:
    """Run directories below `root` (itself included) that hold results.parquet or results.jsonl."""
    root = Path(root)
    excluded = [Path(e).resolve() for e in exclude]
    dirs = {p.parent for name in ("results.parquet", LOG_NAME) for p in root.rglob(name)}
    if (root / "results.parquet").exists() or (root / LOG_NAME).exists():
        dirs.add(root)
    keep = [d for d in dirs if not any(d.resolve().is_relative_to(e) for e in excluded)]
    return sorted(keep)


def load_run(run_dir: Path) -> pd.DataFrame:
    """One run's table: the parquet file unless the JSON-lines log is newer (an interrupted resume)."""
    pq, jl = run_dir / "results.parquet", run_dir / LOG_NAME
    if pq.exists() and not (jl.exists() and jl.stat().st_mtime > pq.stat().st_mtime + 1e-3):
        return load_table(run_dir)
    return to_table(read_rows(jl))


def load_results(root: str | Path, exclude: Iterable[Path] = ()) -> pd.DataFrame:
    """Every run's rows below `root`, concatenated, with a `run` column (the run dir relative to root)."""
    root = Path(root)
    tables = []
    for run_dir in find_runs(root, exclude):
        try:
            t = load_run(run_dir)
        except Exception as exc:  # noqa: BLE001 - one unreadable run must not hide the others
            log.warning("skipping %s: %s", run_dir, exc)
            continue
        if len(t):
            t = t.copy()
            t.insert(0, "run", str(run_dir.relative_to(root)) if run_dir != root else ".")
            tables.append((run_dir, t))
    if not tables:
        return pd.DataFrame()
    return pd.concat(merge_same_experiments(tables), ignore_index=True)


def _saved_config(run_dir: Path):
    for name in (RESUMED_NAME, CONFIG_NAME):
        if (run_dir / name).is_file():
            try:
                cfg = OmegaConf.load(run_dir / name)
            except Exception:  # noqa: BLE001 - no config to compare: the run stands alone
                return None
            cfg.pop("limit", None)  # a resume may raise it: runs that differ only there are one experiment
            return cfg
    return None


def merge_same_experiments(tables: list[tuple[Path, pd.DataFrame]]) -> list[pd.DataFrame]:
    """Runs of one configuration (e.g. two sweep members, one started again with a higher limit) hold the
    same measurement of their common pairs: each pair is counted once (from the run holding the most
    rows), with a warning naming the runs, instead of twice."""
    classes: list[tuple[Any, list[tuple[Path, pd.DataFrame]]]] = []
    for run_dir, t in tables:
        cfg = _saved_config(run_dir)
        for saved, members in classes:
            if cfg is not None and saved is not None and not differences(saved, cfg):
                members.append((run_dir, t))
                break
        else:
            classes.append((cfg, [(run_dir, t)]))
    out = []
    for _, members in classes:
        if len(members) == 1:
            out.append(members[0][1])
            continue
        members.sort(key=lambda m: -len(m[1]))
        merged = pd.concat([t for _, t in members], ignore_index=True)
        keys = [k for k in ("pair", "seed") if k in merged]
        dup = merged.duplicated(keys, keep="first")
        log.warning(
            "%s hold one configuration (only limit differs): %d repeated pair(s) counted once",
            ", ".join(str(m[0]) for m in members),
            int(dup.sum()),
        )
        out.append(merged[~dup])
    return out


# -- aggregation ------------------------------------------------------------------------------------------
def _success(t: pd.DataFrame) -> pd.Series:
    if "success" not in t:
        return pd.Series(False, index=t.index)
    return t["success"].astype("boolean").fillna(False).astype(bool)


def _failed(t: pd.DataFrame) -> pd.Series:
    if "error" not in t:
        return pd.Series(False, index=t.index)
    return t["error"].fillna("").astype(str).ne("")


def group_keys(table: pd.DataFrame) -> list[str]:
    return [k for k in GROUP_KEYS if k in table.columns]


def aggregate(table: pd.DataFrame) -> pd.DataFrame:
    """One row per dataset x descriptor x sampler x ratio x backend x protocol (those columns present).

    Columns: pairs, failed, registered, RR (% of all pairs; failed pairs count as not registered), RE_deg
    and TE_cm (means over successful pairs), inlier_ratio_in/kept (means), t_<stage>_ms (medians over the
    pairs that have a time), seeds (distinct seeds), RR_seed_mean and RR_seed_std (% across the per-seed
    RRs, sample std; NaN unless >= 2 seeds), searches (how many pairs each clique search ran, e.g.
    "auto:bnb 7, auto:enumerate 1"; "" without a search column) and capped (pairs whose search hit a cap).
    Sorted by the keys with the ratio descending.
    """
    keys = group_keys(table)
    t = table.copy()
    t["_ok"] = _success(t)
    t["_failed"] = _failed(t)
    for k in keys:
        if k == "ratio":
            t[k] = pd.to_numeric(t[k], errors="coerce").astype(float)
        else:
            t[k] = t[k].astype(object).where(t[k].notna(), "").astype(str)
    for c in (
        "re_deg",
        "te_cm",
        "inlier_ratio_in",
        "inlier_ratio_kept",
        *(f"t_{s}_ms" for s in REPORT_STAGES),
    ):
        if c in t:
            t[c] = pd.to_numeric(t[c], errors="coerce").astype(float)
    rows = []
    groups = t.groupby(keys, sort=False, dropna=False) if keys else [((), t)]
    for key, g in groups:
        key = key if isinstance(key, tuple) else (key,)
        ok = g["_ok"]
        row = dict(zip(keys, key, strict=True))
        row.update(
            pairs=len(g),
            failed=int(g["_failed"].sum()),
            registered=int(ok.sum()),
            RR=100.0 * float(ok.mean()) if len(g) else math.nan,
            RE_deg=float(g.loc[ok, "re_deg"].mean()) if "re_deg" in g and ok.any() else math.nan,
            TE_cm=float(g.loc[ok, "te_cm"].mean()) if "te_cm" in g and ok.any() else math.nan,
        )
        for c in ("inlier_ratio_in", "inlier_ratio_kept"):
            row[c] = float(g[c].mean()) if c in g else math.nan
        for s in REPORT_STAGES:
            c = f"t_{s}_ms"
            row[c] = float(g[c].median()) if c in g and g[c].notna().any() else math.nan
        row["searches"] = _search_counts(g["search"]) if "search" in g else ""
        row["capped"] = int((g["cap_hit"].fillna("").astype(str) != "").sum()) if "cap_hit" in g else 0
        seeds = g["seed"].dropna().unique() if "seed" in g else []
        row["seeds"] = len(seeds)
        if len(seeds) >= 2:
            per_seed = 100.0 * g.groupby("seed")["_ok"].mean()
            row["RR_seed_mean"] = float(per_seed.mean())
            row["RR_seed_std"] = float(per_seed.std(ddof=1))
        else:
            row["RR_seed_mean"] = row["RR_seed_std"] = math.nan
        rows.append(row)
    out = pd.DataFrame(rows)
    if len(out) and keys:
        asc = [k != "ratio" for k in keys]
        out = out.sort_values(keys, ascending=asc, kind="stable").reset_index(drop=True)
    return out


def _search_counts(col: pd.Series) -> str:
    """'auto:bnb 7, auto:enumerate 1': pairs per search that ran (sorted by name; empty cells skipped)."""
    names = col.dropna().astype(str)
    counts = names[names != ""].value_counts()
    return ", ".join(f"{name} {counts[name]}" for name in sorted(counts.index))


def method_label(row: pd.Series | dict, keys: Iterable[str] = ("sampler", "backend", "protocol")) -> str:
    return " / ".join(str(row[k]) for k in keys if k in row and str(row[k]) != "")


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


def _to_mlflow(root: Path, out_dir: Path, all_runs: bool, uri: str | None) -> int | None:
    """--to-mlflow: every run; else, for a run or sweep that logged to MLflow, the report's files. An exit
    code on failure, else None."""
    from fastmac_exp.errors import InputError
    from fastmac_exp.trackers.mlflow_store import RECORD

    if not all_runs and not (root / RECORD).is_file():
        return None
    from fastmac_exp.report import mlflow_upload

    try:
        if all_runs:
            done = mlflow_upload.upload(root, uri, report_dir=out_dir)
            print(f"mlflow: {len(done['runs'])} run(s) in {done['uri']}"
                  + (f", parent run {done['parent']}" if done["parent"] else ""))  # fmt: skip
        else:
            run_id = mlflow_upload.upload_report(root, out_dir)
            print(f"mlflow: the report's files -> run {run_id}")
    except InputError as exc:
        print(f"error: {exc}", file=sys.stderr)
        return 2
    except Exception as exc:  # noqa: BLE001 - the report itself is written
        from fastmac_exp.trackers.mlflow_store import reason

        print(f"error: mlflow: {reason(exc)}", file=sys.stderr)
        return 1 if all_runs else None
    return None


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(
        prog="python -m fastmac_exp.report",
        description="Paper-style tables (markdown/CSV) and plots (PNG) from a run or multirun directory.",
    )
    parser.add_argument("dir", help="a run directory or a sweep (multirun) directory")
    parser.add_argument("--out", default=None, help="output directory (default: <dir>/report)")
    parser.add_argument("--no-plots", action="store_true", help="tables only")
    parser.add_argument(
        "--snapshots", type=int, default=4, metavar="N",
        help="PNG pictures of up to N pairs from the runs' rerun recordings (0: none; default 4)",
    )  # fmt: skip
    parser.add_argument(
        "--to-mlflow", action="store_true",
        help="also send the runs (and a sweep's report, to its parent run) to MLflow: what they did not log "
             "live, or all of them (docs/tracking.md)",
    )  # fmt: skip
    parser.add_argument(
        "--mlflow-uri", default=None, metavar="URI",
        help="with --to-mlflow: the tracking server (default: the one the runs logged to, else "
             "tracker.mlflow.uri, else MLFLOW_TRACKING_URI, else SQLite in <dir>)",
    )  # fmt: skip
    args = parser.parse_args(argv)
    logging.basicConfig(level=logging.INFO, format="%(levelname)s %(message)s")
    try:
        res = make_report(args.dir, args.out, plots=not args.no_plots, snapshots=args.snapshots)
    except FileNotFoundError as exc:
        print(f"error: {exc}", file=sys.stderr)
        return 2
    agg = res["aggregate"]
    cols = [c for c in (*GROUP_KEYS, "pairs", "failed", "RR", "RE_deg", "TE_cm", "t_total_ms") if c in agg]
    with pd.option_context("display.width", 160, "display.max_columns", 20, "display.max_rows", 200):
        print(agg[cols].to_string(index=False, float_format=lambda v: f"{v:.2f}"))
    out_dir = res["out_dir"]
    print(f"\nreport: {out_dir / 'report.md'}  table: {out_dir / 'report.csv'}")
    for p in res["plots"]:
        print(f"plot: {p}")
    for p in res["snapshots"]:
        print(f"pair: {p}")
    failed = _to_mlflow(Path(args.dir), out_dir, args.to_mlflow, args.mlflow_uri)
    return failed or 0


if __name__ == "__main__":
    sys.exit(main())
