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

# hydra/launcher option -> (the Hydra plugin module it needs, the package that installs it)
LAUNCHER_PLUGINS = {
    "slurm": ("hydra_plugins.hydra_submitit_launcher", "hydra-submitit-launcher"),
    "ray_cluster": ("hydra_plugins.hydra_ray_launcher", "hydra-ray-launcher"),
}


def check_launcher(argv: list[str]) -> str | None:
    """The install hint for a `hydra/launcher=NAME` override whose plugin is missing, else None (Hydra's
    own message, "Could not load 'hydra/launcher/submitit_slurm'", names neither plugin nor package)."""
    import importlib.util

    for arg in argv:
        key, _, name = arg.lstrip("+~").partition("=")
        if key != "hydra/launcher" or name not in LAUNCHER_PLUGINS:
            continue
        module, package = LAUNCHER_PLUGINS[name]
        try:
            found = importlib.util.find_spec(module) is not None
        except ModuleNotFoundError:
            found = False
        if not found:
            return (f"hydra/launcher={name} needs the Hydra plugin {package!r}, which is not installed: "
                    f"pip install {package}")  # fmt: skip
    return None


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
    hint = check_launcher(sys.argv[1:])
    if hint:
        log.addHandler(logging.StreamHandler())
        log.error(hint)
        sys.exit(2)
    main()
