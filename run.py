"""Hydra entry point: `python run.py sampler=highpass ratio=0.05 dataset=synthetic`, sweeps with -m."""

from __future__ import annotations

import logging
import sys

import hydra
from hydra.core.hydra_config import HydraConfig
from omegaconf import DictConfig

from fastmac_exp.errors import FastMacError

log = logging.getLogger("fastmac_exp")


@hydra.main(version_base="1.3", config_path="conf", config_name="config")
def main(cfg: DictConfig) -> float:
    from fastmac_exp.experiment import format_summary, run_experiment

    run_dir = HydraConfig.get().runtime.output_dir
    try:
        _, summary = run_experiment(cfg, run_dir)
    except FastMacError as exc:
        log.error("%s", exc)
        sys.exit(2)
    print(format_summary(summary))
    print(f"results: {summary['run_dir']}/results.parquet (and .csv, summary.json)")
    return float(summary.get("RR", 0.0))


if __name__ == "__main__":
    main()
