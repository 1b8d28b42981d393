"""Hydra callbacks (conf/config.yaml: hydra.callbacks): what runs around the jobs, not inside them."""

from __future__ import annotations

import logging
import sys
from pathlib import Path
from typing import Any

from hydra.experimental.callback import Callback
from omegaconf import DictConfig, OmegaConf

from fastmac_exp.run.runlock import held_by
from fastmac_exp.run.sweep_summary import sweep_table
from fastmac_exp.trackers.redact import redact_logs, redact_text

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


class RedactCredentials(Callback):
    """A tracker URI's user:password (tracker.mlflow.uri=https://user:pw@host) stays off the console, the
    logs and Hydra's copies of the config and the overrides (.hydra/*.yaml, a sweep's multirun.yaml)."""

    def on_run_start(self, config: DictConfig, **kwargs: Any) -> None:
        redact_logs()

    def on_multirun_start(self, config: DictConfig, **kwargs: Any) -> None:
        redact_logs()

    def on_job_start(self, config: DictConfig, **kwargs: Any) -> None:
        # Hydra has written them just before (hydra.core.utils.run_job)
        out = Path(str(config.hydra.runtime.output_dir))
        files = list((out / str(config.hydra.output_subdir or ".hydra")).glob("*.yaml"))
        files.append(Path(str(config.hydra.sweep.dir)) / "multirun.yaml")
        for path in files:
            try:
                text = path.read_text()
            except OSError:
                continue
            clean = redact_text(text)
            if clean != text:
                path.write_text(clean)


class CloseMlflowParent(Callback):
    """A sweep logged to MLflow ends with its parent run finished, the members' table attached."""

    def on_multirun_end(self, config: DictConfig, **kwargs: Any) -> None:
        sweep_dir = Path(str(config.hydra.sweep.dir))
        if not (sweep_dir / "mlflow_run.json").is_file():
            return
        from fastmac_exp.trackers.mlflow_tracker import close_parent

        uri = OmegaConf.select(config, "tracker.mlflow.uri", default=None)
        close_parent(sweep_dir, uri, sweep_table(sweep_dir))
