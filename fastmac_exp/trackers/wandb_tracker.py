"""Weights & Biases tracker: one wandb run per experiment run, offline by default.

Offline runs are written into the run directory (`<run_dir>/wandb/offline-run-*`) and need no network;
upload them later with `wandb sync <run_dir>/wandb/offline-run-*`. Each resume of a run adds one more
offline run, named `<name> (part N)`, beside the earlier ones. Online:
`python run.py tracker.wandb.mode=online tracker.wandb.project=P tracker.wandb.entity=E`.

What is logged: the resolved config (plus the Hydra choices and overrides when run under Hydra); one
step per pair with its metrics (`pair/*`), stage timings (`time/*_ms`) and the running registration
recall (`running/*`); at the end the per-pair results as a `wandb.Table` and the run summary in
`run.summary`. Members of a Hydra multirun share a group (the sweep directory's name) and are named after
their override dirname (e.g. `ratio=0.1,sampler=random`).
"""

from __future__ import annotations

import logging
import math
import os
from pathlib import Path
from typing import Any

import numpy as np
import pandas as pd

from fastmac_exp.pipeline import PairOutcome
from fastmac_exp.trackers.base import Tracker

log = logging.getLogger(__name__)

MODES = ("offline", "online", "disabled")
_PAIR_KEYS = (
    "re_deg", "te_cm", "inlier_ratio_in", "inlier_ratio_kept", "n_in", "n_kept", "clique_size",
    "clique_inliers", "n_edges", "n_cliques", "score",
)  # fmt: skip


def _number(v: Any) -> float | int | None:
    """A finite int/float for wandb, or None for missing values (None, NaN, pd.NA, strings)."""
    if v is None or v is pd.NA:
        return None
    if isinstance(v, bool | np.bool_):
        return int(v)
    if isinstance(v, int | np.integer):
        return int(v)
    if isinstance(v, float | np.floating):
        return float(v) if math.isfinite(float(v)) else None
    return None


def hydra_context() -> dict[str, Any]:
    """Hydra's view of this job when it runs under Hydra: mode, sweep dir, override dirname, choices."""
    try:
        from hydra.core.hydra_config import HydraConfig
        from hydra.types import RunMode
    except ImportError:  # pragma: no cover - hydra is a dependency
        return {}
    if not HydraConfig.initialized():
        return {}
    hc = HydraConfig.get()
    ctx: dict[str, Any] = {
        "multirun": hc.mode == RunMode.MULTIRUN,
        "sweep_dir": str(hc.sweep.dir) if hc.mode == RunMode.MULTIRUN else None,
        "override_dirname": str(hc.job.override_dirname or ""),
        "job_num": hc.job.get("num"),
    }
    try:
        ctx["choices"] = {k: v for k, v in dict(hc.runtime.choices).items() if not k.startswith("hydra/")}
        ctx["overrides"] = list(hc.overrides.task)
    except Exception:  # noqa: BLE001 - informative only
        pass
    return ctx


class WandbTracker(Tracker):
    """Log a run to Weights & Biases (offline by default, never needing network in offline mode).

    mode: offline | online | disabled. project/entity: where online runs go. group: defaults to the
    Hydra sweep directory's name in a multirun. name: defaults to the override dirname (or the run
    directory's name). tags: a list of strings. log_table: log the per-pair table at the end.
    finish_timeout_s: how long `finish` may wait for uploads (online) before giving up; the data stays
    on disk for `wandb sync`.
    """

    name = "wandb"

    def __init__(
        self,
        mode: str = "offline",
        project: str = "fastmac-exp",
        entity: str | None = None,
        group: str | None = None,
        name: str | None = None,
        tags: list[str] | None = None,
        log_table: bool = True,
        job_type: str | None = None,
        finish_timeout_s: float = 60.0,
    ) -> None:
        if mode not in MODES:
            raise ValueError(f"tracker.wandb.mode must be one of {MODES}, got {mode!r}")
        self.mode = mode
        self.project = project
        self.entity = entity
        self.group = group
        self.run_name = name
        self.tags = [str(t) for t in tags] if tags else None
        self.log_table = bool(log_table)
        self.job_type = job_type
        self.finish_timeout_s = float(finish_timeout_s)
        self.run = None
        self.run_path: Path | None = None  # the offline run's directory, once started
        self._n = 0
        self._n_ok = 0
        self._t_sum = 0.0
        os.environ.setdefault("WANDB_SILENT", "true")
        os.environ.setdefault("WANDB_CONSOLE", "off")
        try:
            import wandb
        except Exception as exc:  # noqa: BLE001 - a broken install must not stop the experiment
            log.warning("wandb tracker disabled: `import wandb` failed (%s); pip install wandb", exc)
            self._wandb = None
        else:
            self._wandb = wandb

    # -- lifecycle -------------------------------------------------------------------------------------
    def start(self, cfg: dict[str, Any], run_dir: Path, names: list[str]) -> None:
        wandb = self._wandb
        if wandb is None or self.mode == "disabled":
            return
        run_dir = Path(run_dir)
        ctx = hydra_context()
        group = self.group
        if group is None and ctx.get("multirun") and ctx.get("sweep_dir"):
            group = Path(ctx["sweep_dir"]).name
        name = self.run_name or ctx.get("override_dirname") or run_dir.name
        earlier = find_offline_runs(run_dir)  # a resumed run: each part is its own run, the earlier kept
        if earlier:
            name = f"{name} (part {len(earlier) + 1})"
        mode = self.mode
        if mode == "online" and not self._logged_in():
            log.warning(
                "wandb: no API key (wandb login / WANDB_API_KEY); logging offline to %s/wandb instead, "
                "upload later with `wandb sync %s/wandb/offline-run-*`",
                run_dir,
                run_dir,
            )
            mode = "offline"
        config = dict(cfg)
        config["run_dir"] = str(run_dir)
        config["num_pairs"] = len(names)
        if ctx.get("choices"):
            config["hydra"] = {"choices": ctx["choices"], "overrides": ctx.get("overrides", [])}
        settings = {
            "mode": mode,
            "silent": True,
            "console": "off",
            "save_code": False,
            "disable_code": True,
            "disable_git": True,
            "disable_job_creation": True,
            "x_disable_stats": True,  # no system-metrics sampler
            "x_disable_meta": True,  # no git / host / program metadata capture
            "x_disable_machine_info": True,
            "x_save_requirements": False,
            "finish_timeout": self.finish_timeout_s,  # online: stop waiting for uploads after this long
        }
        known = getattr(wandb.Settings, "model_fields", None)  # settings differ across wandb versions
        if known:
            settings = {k: v for k, v in settings.items() if k in known}
        run_dir.mkdir(parents=True, exist_ok=True)
        try:
            self.run = wandb.init(
                dir=str(run_dir),
                project=self.project,
                entity=self.entity,
                group=group,
                name=name,
                job_type=self.job_type,
                tags=self.tags,
                config=config,
                settings=wandb.Settings(**settings),
                reinit="create_new",  # Hydra's basic launcher runs sweep members in one process
            )
        except Exception as exc:  # noqa: BLE001
            log.warning("wandb tracker disabled: wandb.init failed (%s)", exc)
            self.run = None
            return
        files_dir = getattr(self.run.settings, "files_dir", None)
        self.run_path = Path(files_dir).parent if files_dir else None

    @staticmethod
    def _logged_in() -> bool:
        import wandb

        try:
            return bool(wandb.login(prompt=False, verify=False))
        except Exception:  # noqa: BLE001
            return False

    def log_pair(self, outcome: PairOutcome) -> None:
        if self.run is None:
            return
        row = outcome.row
        self._n += 1
        ok = _number(row.get("success")) == 1
        self._n_ok += ok
        total = _number(row.get("t_total_ms"))
        self._t_sum += total or 0.0
        metrics: dict[str, Any] = {
            "pair/index": _number(row.get("index")),
            "pair/success": int(ok),
            "pair/failed": int(bool(row.get("error"))),
            "running/RR": self._n_ok / self._n,
            "running/mean_total_ms": self._t_sum / self._n,
        }
        for k in _PAIR_KEYS:
            metrics[f"pair/{k}"] = _number(row.get(k))
        for k, v in row.items():
            if k.startswith("t_") and k.endswith("_ms"):
                metrics[f"time/{k[2:]}"] = _number(v)
        self.run.log({k: v for k, v in metrics.items() if v is not None})

    def finish(self, table: pd.DataFrame, summary: dict[str, Any]) -> None:
        run = self.run
        if run is None:
            return
        self.run = None
        try:
            if self.log_table and len(table):
                run.log({"results": self._wandb.Table(dataframe=_plain(table))})
            run.summary.update({k: _summary_value(v) for k, v in summary.items()})
        finally:
            exit_code = 0 if summary.get("complete", True) else 1
            run.finish(exit_code=exit_code)


def _plain(table: pd.DataFrame) -> pd.DataFrame:
    """A copy wandb.Table accepts: nullable dtypes to object with None, NaN kept as floats."""
    out = table.copy()
    for c in out.columns:
        if isinstance(out[c].dtype, pd.BooleanDtype | pd.StringDtype) or out[c].dtype == object:
            out[c] = out[c].astype(object).where(out[c].notna(), None)
        elif str(out[c].dtype).startswith(("str", "string")):
            out[c] = out[c].astype(object)
    return out


def _summary_value(v: Any) -> Any:
    if isinstance(v, np.generic):
        v = v.item()
    if isinstance(v, float) and not math.isfinite(v):
        return None
    return v if isinstance(v, str | int | float | bool | type(None) | list | dict) else str(v)


def find_offline_runs(run_dir: str | Path) -> list[Path]:
    """The offline wandb runs written into a run directory (`<run_dir>/wandb/offline-run-*`)."""
    return sorted(Path(run_dir).glob("wandb/offline-run-*"))


def read_offline_run(path: str | Path, wait_s: float = 0.0) -> dict[str, Any]:
    """Decode an offline run's transaction log (`run-*.wandb`) with wandb's own record protobufs.

    `path` is the offline-run directory or the .wandb file. Returns {"run": {project, group, name,
    tags}, "config": {...}, "history": [step dicts], "summary": {...}, "exit_code": int | None}; values
    are JSON-decoded. This is the file `wandb sync` uploads, so it shows what the server will get.

    wandb's service writes the log asynchronously: `run.finish()` returns before the last records reach
    the disk (they do before the process exits). `wait_s` > 0 polls until the exit record is there.
    """
    import time

    deadline = time.monotonic() + wait_s
    while True:
        result = _read_offline_run(path)
        if result["exit_code"] is not None or time.monotonic() >= deadline:
            return result
        time.sleep(0.02)


def _read_offline_run(path: str | Path) -> dict[str, Any]:
    import json
    import struct

    from wandb.proto import wandb_internal_pb2 as pb

    path = Path(path)
    if path.is_dir():
        files = sorted(path.glob("run-*.wandb"))
        if not files:
            raise FileNotFoundError(f"no run-*.wandb in {path}")
        path = files[0]
    data = path.read_bytes()
    if len(data) < 7:  # created, nothing flushed yet
        return {"run": {}, "config": {}, "history": [], "summary": {}, "exit_code": None}
    ident, magic, version = struct.unpack("<4sHB", data[:7])
    if ident != b":W&B" or magic != 0xBEE1:
        raise ValueError(f"{path} is not a wandb transaction log")
    block = 32768  # LevelDB log format: 32 KiB blocks of (crc32, length, type) framed chunks
    pos, pending, records = 7, b"", []
    while pos + 7 <= len(data):
        if block - pos % block < 7:
            pos += block - pos % block
            continue
        _crc, length, kind = struct.unpack("<IHB", data[pos : pos + 7])
        pos += 7
        chunk = data[pos : pos + length]
        pos += length
        if kind == 1:  # full
            records.append(chunk)
        elif kind == 2:  # first
            pending = chunk
        elif kind == 3:  # middle
            pending += chunk
        elif kind == 4:  # last
            records.append(pending + chunk)
            pending = b""

    def items(seq) -> dict[str, Any]:
        out = {}
        for it in seq:
            key = it.key or "/".join(it.nested_key)
            out[key] = json.loads(it.value_json)
        return out

    result: dict[str, Any] = {"run": {}, "config": {}, "history": [], "summary": {}, "exit_code": None}
    for raw in records:
        rec = pb.Record()
        rec.ParseFromString(raw)
        kind = rec.WhichOneof("record_type")
        if kind == "run":
            r = rec.run
            result["run"] = {
                "project": r.project, "entity": r.entity, "group": r.run_group, "name": r.display_name,
                "tags": list(r.tags), "run_id": r.run_id, "job_type": r.job_type,
            }  # fmt: skip
            result["config"].update(items(r.config.update))
        elif kind == "config":
            result["config"].update(items(rec.config.update))
        elif kind == "history":
            result["history"].append(items(rec.history.item))
        elif kind == "summary":
            result["summary"].update(items(rec.summary.update))
        elif kind == "exit":
            result["exit_code"] = rec.exit.exit_code
    result["config"].pop("_wandb", None)
    return result
