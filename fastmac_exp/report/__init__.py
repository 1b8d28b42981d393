"""Paper-style reports of runs and sweeps: the results as one table and its aggregate (tables), the
markdown page with its plots and pair pictures (page, plots), and `python -m fastmac_exp.report` (cli)."""

from fastmac_exp.report.cli import main
from fastmac_exp.report.page import make_report, markdown_table, pair_snapshots, render_markdown, worst_first
from fastmac_exp.report.tables import (
    GROUP_KEYS,
    aggregate,
    find_runs,
    group_keys,
    load_results,
    load_run,
    merge_same_experiments,
    method_label,
)

__all__ = [
    "GROUP_KEYS",
    "aggregate",
    "find_runs",
    "group_keys",
    "load_results",
    "load_run",
    "main",
    "make_report",
    "markdown_table",
    "merge_same_experiments",
    "method_label",
    "pair_snapshots",
    "render_markdown",
    "worst_first",
]
