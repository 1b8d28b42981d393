"""The tracker interface: the experiment loop tells every tracker about the run, each pair and the end."""

from __future__ import annotations

from pathlib import Path
from typing import Any

import pandas as pd

from fastmac_exp.pipeline import PairOutcome


class Tracker:
    """Base class with no-op hooks; subclasses override what they need.

    start: once, with the resolved config (a plain dict), the run directory and the pair names.
    log_pair: after each pair, in pair-index order of completion; `outcome.row` is the results row and
    `outcome.result` is None for a failed pair.
    finish: once, with the final table and summary (also after an interruption, when possible).
    """

    name = "tracker"

    def start(self, cfg: dict[str, Any], run_dir: Path, names: list[str]) -> None:
        pass

    def log_pair(self, outcome: PairOutcome) -> None:
        pass

    def finish(self, table: pd.DataFrame, summary: dict[str, Any]) -> None:
        pass
