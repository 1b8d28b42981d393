"""Hydra entry point: `python run.py sampler=highpass ratio=0.05 dataset=synthetic`, sweeps with -m."""

from __future__ import annotations

import logging
import sys

import hydra
from hydra.core.hydra_config import HydraConfig
from hydra.types import RunMode
from omegaconf import DictConfig

from fastmac_exp.errors import FastMacError

log = logging.getLogger("fastmac_exp")


@hydra.main(version_base="1.3", config_path="conf", config_name="config")
def main(cfg: DictConfig) -> float:
    from fastmac_exp.experiment import format_summary, run_experiment

    run_dir = HydraConfig.get().runtime.output_dir
    try:
        _, summary = run_experiment(cfg, run_dir)
    except Exception as exc:  # noqa: BLE001 - our own errors, even wrapped by Hydra's instantiate, exit cleanly
        ours = _own_error(exc)
        if ours is None:
            raise
        log.error("%s", ours)
        sys.exit(2)
    print(format_summary(summary))
    print(f"results: {summary['run_dir']}/results.parquet (and .csv, summary.json)")
    if summary.get("pairs", 0) and summary.get("failed", 0) == summary["pairs"]:
        log.error("every pair failed (reasons above)")
        # A single run fails; a sweep member is a measurement (e.g. random sampling at 1 % registers
        # nothing) and the sweep goes on.
        if HydraConfig.get().mode != RunMode.MULTIRUN:
            sys.exit(1)
    return float(summary.get("RR", 0.0))


def _own_error(exc: BaseException) -> FastMacError | None:
    """The project's error behind exc (Hydra wraps constructor errors in InstantiationException)."""
    seen = 0
    while exc is not None and seen < 10:
        if isinstance(exc, FastMacError):
            return exc
        exc = exc.__cause__ or exc.__context__
        seen += 1
    return None


if __name__ == "__main__":
    main()
