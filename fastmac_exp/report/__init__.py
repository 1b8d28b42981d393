"""Paper-style reports of runs and sweeps (`python -m fastmac_exp.report`)."""

from fastmac_exp.report.tables import (
    GROUP_KEYS,
    aggregate,
    find_runs,
    group_keys,
    load_results,
    load_run,
    main,
    make_report,
    markdown_table,
    merge_same_experiments,
    method_label,
    pair_snapshots,
    render_markdown,
    worst_first,
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
