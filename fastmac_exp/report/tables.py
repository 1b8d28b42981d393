"""The results of a run or a sweep as one table, and its aggregate per configuration.

Every results table below a directory (results.parquet, or results.jsonl for an interrupted run) is read and
concatenated (runs that are one experiment resumed are merged), then aggregated per dataset x descriptor x
sampler x ratio x backend x protocol: pairs, failed, RR (%), mean RE (deg) and TE (cm) over the successful
pairs, the median time per stage and in total (ms), and, where a configuration ran with several seeds, the
mean and standard deviation of RR across seeds.
"""

from __future__ import annotations

import logging
import math
from collections.abc import Iterable
from pathlib import Path
from typing import Any

import pandas as pd
from omegaconf import OmegaConf

from fastmac_exp.geometry.metrics import STAGES
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
