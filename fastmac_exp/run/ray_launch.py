"""Sweep members as Ray tasks (hydra/launcher=ray_cluster, hydra_plugins/fastmac_ray_launcher).

The driver (`python run.py -m ...`) connects to a running Ray cluster by address, submits one task per
sweep member and waits for all of them; Ray places the tasks on the cluster's CPUs. Each task runs the
member exactly as Hydra's basic launcher would (hydra.core.utils.run_job), in the driver's working
directory, which must be on a filesystem every node sees at the same path (as on a Slurm cluster): the
config directory, the data, the caches and the sweep directory are all found there.
"""

from __future__ import annotations

import logging
import os
import socket
import sys
from collections.abc import Sequence
from pathlib import Path
from typing import Any

from hydra.core.hydra_config import HydraConfig
from hydra.core.singleton import Singleton
from hydra.core.utils import JobReturn, configure_log, filter_overrides, run_job, setup_globals
from omegaconf import DictConfig, OmegaConf, open_dict

log = logging.getLogger(__name__)

# One fresh worker process per member (no logging handlers or modules left over from the previous
# member), one CPU each (a member runs its pairs one after the other unless workers=N), and no silent
# retry: a member that crashed is rerun with resume=auto, which keeps its finished pairs.
REMOTE_DEFAULTS = {"num_cpus": 1, "max_calls": 1, "max_retries": 0}


def _plain(node: Any) -> dict[str, Any]:
    if node is None:
        return {}
    return dict(OmegaConf.to_container(node, resolve=True)) if isinstance(node, DictConfig) else dict(node)


def run_member(hydra_context, sweep_config: DictConfig, task_function, singleton_state: dict[Any, Any],
               cwd: str | None) -> JobReturn:  # fmt: skip
    """One sweep member, on a Ray worker."""
    if cwd is not None:
        if not Path(cwd).is_dir():
            raise RuntimeError(
                f"Ray worker on {socket.gethostname()}: the driver's working directory {cwd} does not exist "
                "here; run the sweep from a directory that every node mounts at the same path"
            )
        os.chdir(cwd)
        if cwd not in sys.path:  # as `python run.py` has the checkout on sys.path
            sys.path.insert(0, cwd)
    setup_globals()
    Singleton.set_state(singleton_state)
    HydraConfig.instance().set_config(sweep_config)
    return run_job(
        hydra_context=hydra_context,
        task_function=task_function,
        config=sweep_config,
        job_dir_key="hydra.sweep.dir",
        job_subdir_key="hydra.sweep.subdir",
    )


def connect(address: str | None, init: dict[str, Any]) -> bool:
    """ray.init by address unless already connected; True if this call connected."""
    import ray

    if ray.is_initialized():
        return False
    kwargs = {"log_to_driver": True, **init}
    if address:
        kwargs["address"] = address
    log.info("connecting to Ray at %s", kwargs.get("address", "a new local instance"))
    try:
        _check_reachable(address)
        ray.init(**kwargs)
    except ConnectionError as exc:
        why = f"{exc}" + (f" ({type(exc.__cause__).__name__})" if exc.__cause__ is not None else "")
        raise ConnectionError(
            f"hydra/launcher=ray_cluster: cannot connect to a Ray cluster at {address!r}: {why}. Start one "
            "with `ray start --head` or pass hydra.launcher.address=HOST:PORT; a cluster started by "
            "`ray start` uses token authentication, so export RAY_AUTH_MODE=token with its token in "
            "~/.ray/auth_token or RAY_AUTH_TOKEN (docs/cluster.md)"
        ) from exc
    return True


def _check_reachable(address: str | None, timeout_s: float = 10.0) -> None:
    """Fail at once when nothing listens at a HOST:PORT address (ray.init would retry for minutes)."""
    if not address or address == "auto" or "://" in address or ":" not in address:
        return
    host, _, port = address.rpartition(":")
    try:
        socket.create_connection((host, int(port)), timeout=timeout_s).close()
    except (OSError, ValueError) as exc:
        raise ConnectionError(f"nothing answers at {address} ({exc})") from exc


def launch(launcher, job_overrides: Sequence[Sequence[str]], initial_job_idx: int) -> list[JobReturn]:
    try:
        import ray
    except ModuleNotFoundError as exc:
        raise ModuleNotFoundError(
            "hydra/launcher=ray_cluster needs Ray: pip install -e '.[cluster]' -c constraints.txt"
        ) from exc
    setup_globals()
    config = launcher.config
    configure_log(config.hydra.hydra_logging, config.hydra.verbose)
    sweep_dir = Path(str(config.hydra.sweep.dir))
    sweep_dir.mkdir(parents=True, exist_ok=True)
    connected = connect(launcher.address, _plain(launcher.init))
    try:
        remote = ray.remote(**{**REMOTE_DEFAULTS, **_plain(launcher.remote)})(run_member)
        cwd = os.getcwd() if launcher.chdir else None
        log.info("Ray: launching %d sweep members, sweep output dir %s", len(job_overrides), sweep_dir)
        state = Singleton.get_state()
        refs = []
        for idx, overrides in enumerate(job_overrides, start=initial_job_idx):
            log.info("\t#%d : %s", idx, " ".join(filter_overrides(overrides)))
            sweep_config = launcher.hydra_context.config_loader.load_sweep_config(config, list(overrides))
            with open_dict(sweep_config):
                sweep_config.hydra.job.id = f"{sweep_config.hydra.job.name}_{idx}"
                sweep_config.hydra.job.num = idx
            task = launcher.task_function
            refs.append(remote.remote(launcher.hydra_context, sweep_config, task, state, cwd))
        return _gather(ray, refs, job_overrides, initial_job_idx, sweep_dir)
    finally:
        if connected:
            ray.shutdown()


def _gather(ray, refs, job_overrides, initial_job_idx: int, sweep_dir: Path) -> list[JobReturn]:
    """Every member's JobReturn; members whose task died (node lost, OOM kill) are named together."""
    results, lost = [], []
    for idx, (ref, overrides) in enumerate(zip(refs, job_overrides), start=initial_job_idx):
        try:
            results.append(ray.get(ref))
        except ray.exceptions.RayError as exc:
            lost.append(f"#{idx} ({' '.join(filter_overrides(overrides))}): {type(exc).__name__}: "
                        f"{str(exc).splitlines()[0] if str(exc) else ''}")  # fmt: skip
    if lost:
        raise RuntimeError(
            f"{len(lost)} of {len(refs)} sweep members did not finish on Ray:\n  "
            + "\n  ".join(lost)
            + f"\nThe finished pairs are saved; rerun the same command with hydra.sweep.dir={sweep_dir} "
            "resume=auto to complete the sweep."
        )
    return results
