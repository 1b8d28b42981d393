"""The per-pair results table: an append-only JSON-lines log flushed after every pair, turned into
parquet and CSV when the run ends (or is resumed), so an interrupted run loses no finished pair."""

from __future__ import annotations

import json
import logging
import math
import os
import re
from pathlib import Path
from typing import Any

import numpy as np
import pandas as pd

log = logging.getLogger(__name__)

LOG_NAME = "results.jsonl"

# The results row's columns in display order (the design's data model); rows may carry more.
COLUMNS = [
    "index", "dataset", "pair", "scene", "family", "descriptor", "sampler", "ratio", "backend", "seed",
    "protocol", "resolution", "n_in", "n_kept", "inliers_in", "inlier_ratio_in", "inlier_ratio_kept",
    "clique_size", "clique_inliers", "pose_inliers", "trusted", "confidence", "re_deg", "te_cm", "success",
    "score", "n_edges",
    "n_cliques", "n_selected", "reduced", "search", "search_nodes", "cap_hit", "zero_filled", "t_load_ms",
    "t_resolution_ms", "t_describe_ms", "t_sampling_ms", "t_graph_ms", "t_cliques_ms", "t_selection_ms",
    "t_pose_ms", "t_other_ms", "t_check_ms", "t_evaluate_ms", "t_total_ms", "t_end_to_end_ms", "error",
    "pose",
]  # fmt: skip
TIMING_COLUMNS = [c for c in COLUMNS if c.startswith("t_")]


def _jsonable(v: Any) -> Any:
    if isinstance(v, np.generic):
        v = v.item()
    if isinstance(v, float) and not math.isfinite(v):
        return None
    return v


class ResultsLog:
    """Append rows to <run_dir>/results.jsonl, one fsync'ed line per pair."""

    def __init__(self, run_dir: Path) -> None:
        self.run_dir = Path(run_dir)
        self.run_dir.mkdir(parents=True, exist_ok=True)
        self.path = self.run_dir / LOG_NAME
        self.rows = read_rows(self.path)
        if self.path.exists():
            # rewrite without a torn last line so that appends start on a clean line
            self._rewrite(self.rows)

    def _rewrite(self, rows: list[dict[str, Any]]) -> None:
        tmp = self.path.with_suffix(".jsonl.tmp")
        with open(tmp, "w") as f:
            for r in rows:
                f.write(json.dumps({k: _jsonable(v) for k, v in r.items()}) + "\n")
            f.flush()
            os.fsync(f.fileno())
        os.replace(tmp, self.path)

    def check_writable(self) -> None:
        """OSError now, not at the first finished pair, when rows cannot be appended to an existing log."""
        if self.path.exists():
            with open(self.path, "a"):
                pass

    def done(self) -> set[str]:
        return {str(r["pair"]) for r in self.rows}

    def append(self, row: dict[str, Any]) -> None:
        line = json.dumps({k: _jsonable(v) for k, v in row.items()})
        with open(self.path, "a") as f:
            f.write(line + "\n")
            f.flush()
            os.fsync(f.fileno())
        self.rows.append(row)

    def reload(self) -> None:
        """The rows as the log on disk holds them: after an interrupt, which can land between a row's
        fsync and its entry here, the log is what was saved."""
        self.rows = read_rows(self.path)

    def table(self) -> pd.DataFrame:
        return to_table(self.rows)

    def write_tables(self) -> pd.DataFrame:
        """results.parquet and results.csv, one row per pair, ordered by pair index."""
        table = self.table()
        table.to_csv(self.run_dir / "results.csv", index=False)
        try:
            table.to_parquet(self.run_dir / "results.parquet", index=False)
        except (ImportError, ValueError) as exc:  # pragma: no cover - pyarrow is a dependency
            log.warning("could not write parquet: %s", exc)
        return table


POSES_DIR = "poses"


def pose_file(run_dir: Path, pair: str) -> Path:
    """Where a pair without GT keeps its estimated pose: a 4x4 text file, the format dataset.gt reads."""
    return Path(run_dir) / POSES_DIR / (re.sub(r"[^A-Za-z0-9._+-]", "_", pair) + ".txt")


def write_pose(run_dir: Path, row: dict[str, Any]) -> Path:
    path = pose_file(run_dir, str(row["pair"]))
    path.parent.mkdir(exist_ok=True)
    np.savetxt(path, pose_matrix(row["pose"]), fmt="%.17g")
    return path


def pose_matrix(pose: str) -> np.ndarray:
    """The results row's `pose` (16 numbers, row-major) as a 4x4 array."""
    return np.array([float(v) for v in str(pose).split()]).reshape(4, 4)


def read_rows(path: Path) -> list[dict[str, Any]]:
    """Rows of a results log; a torn (partially written) last line is dropped, duplicates keep the last."""
    if not Path(path).exists():
        return []
    by_pair: dict[str, dict[str, Any]] = {}
    with open(path) as f:
        for n, line in enumerate(f, 1):
            line = line.strip()
            if not line:
                continue
            try:
                row = json.loads(line)
            except json.JSONDecodeError:
                log.warning("%s:%d: dropping a torn line (the run was interrupted while writing it)", path, n)
                continue
            by_pair[str(row.get("pair"))] = row
    return list(by_pair.values())


def to_table(rows: list[dict[str, Any]]) -> pd.DataFrame:
    table = pd.DataFrame(rows)
    for c in COLUMNS:
        if c not in table:
            table[c] = None
    extra = [c for c in table.columns if c not in COLUMNS]
    table = table[COLUMNS + extra]
    if len(table):
        table = table.sort_values("index", kind="stable").reset_index(drop=True)
    table["error"] = table["error"].fillna("").astype(str)
    for c in ("re_deg", "te_cm", "inlier_ratio_in", "inlier_ratio_kept", "score", *TIMING_COLUMNS):
        table[c] = pd.to_numeric(table[c], errors="coerce")
    table["success"] = table["success"].astype("boolean")
    return table


def load_table(path: str | Path) -> pd.DataFrame:
    """A run's table from its directory: results.parquet if complete, else the JSON-lines log."""
    path = Path(path)
    if path.is_dir():
        if (path / "results.parquet").exists():
            return pd.read_parquet(path / "results.parquet")
        return to_table(read_rows(path / LOG_NAME))
    if path.suffix == ".parquet":
        return pd.read_parquet(path)
    if path.suffix == ".csv":
        return pd.read_csv(path)
    return to_table(read_rows(path))
