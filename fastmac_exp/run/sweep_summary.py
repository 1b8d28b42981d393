"""The end of a sweep: one table of its members (RR, RE, TE, ms, failed pairs), which
fastmac_exp/run/callbacks.py prints once every member has finished."""

from __future__ import annotations

import json
import math
from pathlib import Path
from typing import Any


def _num(v: Any, fmt: str) -> str:
    return format(v, fmt) if isinstance(v, int | float) and math.isfinite(v) else "-"


def _job_order(d: Path) -> tuple[float, str]:
    num = d.name.split("_", 1)[0]  # hydra.sweep.subdir starts with the job number
    return (int(num) if num.isdigit() else math.inf, d.name)


def sweep_table(sweep_dir: Path) -> str:
    """The members' summaries as a text table, in job order; members without a summary say so."""
    members = sorted((d for d in sweep_dir.iterdir() if d.is_dir() and (d / "config.yaml").exists()),
                     key=_job_order)  # fmt: skip
    rows = [("member", "pairs", "RR %", "RE deg", "TE cm", "ms", "failed")]
    for d in members:
        try:
            s = json.loads((d / "summary.json").read_text())
        except (OSError, ValueError):
            rows.append((d.name, "-", "no summary (interrupted or refused)", "", "", "", ""))
            continue
        rr = s.get("RR")
        rows.append((d.name, str(s.get("pairs", 0)), _num(100 * rr if isinstance(rr, float) else rr, ".1f"),
                     _num(s.get("RE_deg"), ".2f"), _num(s.get("TE_cm"), ".2f"),
                     _num(s.get("median_total_ms"), ".1f"), str(s.get("failed", 0))))  # fmt: skip
    widths = [max(len(r[k]) for r in rows) for k in range(len(rows[0]))]
    lines = ["  ".join(c.ljust(w) if k == 0 else c.rjust(w) for k, (c, w) in enumerate(zip(r, widths)))
             for r in rows]  # fmt: skip
    return "\n".join(lines)
