"""A Hydra launcher that runs each sweep member as one task on a running Ray cluster, by address.

The closest working path to hydra-ray-launcher, which cannot be installed next to this project (every
release requires cloudpickle<3; joblib 1.6, under hydra-joblib-launcher, requires cloudpickle>=3.0).
Ray does the scheduling; the work is in fastmac_exp.run.ray_launch. Hydra finds this class because run.py's
directory (the checkout) is on sys.path and `hydra_plugins` is a namespace package. Ray is imported only
when a sweep launches, so Hydra's plugin scan works without the cluster extra.
"""

from __future__ import annotations

from collections.abc import Sequence
from typing import Any

from hydra.core.utils import JobReturn
from hydra.plugins.launcher import Launcher
from hydra.types import HydraContext, TaskFunction
from omegaconf import DictConfig


class FastmacRayLauncher(Launcher):
    def __init__(self, address: str | None = "auto", init: Any = None, remote: Any = None,
                 chdir: bool = True) -> None:  # fmt: skip
        self.address = address
        self.init = init or {}
        self.remote = remote or {}
        self.chdir = chdir
        self.config: DictConfig | None = None
        self.hydra_context: HydraContext | None = None
        self.task_function: TaskFunction | None = None

    def setup(self, *, hydra_context: HydraContext, task_function: TaskFunction, config: DictConfig) -> None:
        self.config, self.hydra_context, self.task_function = config, hydra_context, task_function

    def launch(self, job_overrides: Sequence[Sequence[str]], initial_job_idx: int) -> Sequence[JobReturn]:
        from fastmac_exp.run.ray_launch import launch

        return launch(self, job_overrides, initial_job_idx)
