"""Hydra callbacks (conf/config.yaml: hydra.callbacks): what runs around the jobs, not inside them."""

from __future__ import annotations

import logging
import sys
from pathlib import Path
from typing import Any

from hydra.experimental.callback import Callback
from omegaconf import DictConfig

from fastmac_exp.runlock import held_by
from fastmac_exp.sweep_summary import sweep_table

log = logging.getLogger("fastmac_exp")


class RefuseLockedRunDir(Callback):
    """A single run into a directory another live run holds is refused before Hydra writes its .hydra/
    and log there (the experiment's own lock then keeps out a run that starts at the same instant)."""

    def on_run_start(self, config: DictConfig, **kwargs: Any) -> None:
        from hydra.core.hydra_config import HydraConfig

        # the default run.dir interpolates ${hydra:runtime.choices...}, which needs the HydraConfig that
        # Hydra sets only later in run_job: set it here (run_job sets the same config again)
        HydraConfig.instance().set_config(config)
        run_dir = Path(str(config.hydra.run.dir))
        owner = held_by(run_dir)
        if owner:
            log.addHandler(logging.StreamHandler())
            log.error("%s is in use by another run (%s); wait for it to end, or choose another run directory",
                      run_dir, owner)  # fmt: skip
            sys.exit(2)


class SweepSummary(Callback):
    """A sweep ends with one table of its members and the report command."""

    def on_multirun_end(self, config: DictConfig, **kwargs: Any) -> None:
        sweep_dir = Path(str(config.hydra.sweep.dir))
        if not sweep_dir.is_dir():
            return
        text = (f"\nsweep {sweep_dir}:\n{sweep_table(sweep_dir)}\n"
                f"next: python -m fastmac_exp.report {sweep_dir}\n")  # fmt: skip
        sys.stdout.flush()
        sys.stdout.write(text)
        sys.stdout.flush()
