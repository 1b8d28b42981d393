"""python -m fastmac_exp.report: the report of a run or a sweep directory, and its upload to MLflow.

    python -m fastmac_exp.report outputs/multirun/2024-06-01_12-00-00 [--out DIR] [--no-plots]

Writes <out>/report.md, <out>/report.csv and the plots (fastmac_exp.report.page); <out> defaults to
<dir>/report.
"""

from __future__ import annotations

import argparse
import logging
import sys
from pathlib import Path

import pandas as pd

from fastmac_exp.report.page import make_report
from fastmac_exp.report.tables import GROUP_KEYS


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
