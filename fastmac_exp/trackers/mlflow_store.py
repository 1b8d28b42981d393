"""What the MLflow tracker and `report --to-mlflow` share: the store's address and credentials, the run
records kept in run and sweep directories, and the conversion of configs, rows and summaries to MLflow's
params and metrics.

A run directory's `mlflow_run.json` names the MLflow run it logs to (and the store), so that a resumed
run continues that run; a sweep directory's names the sweep's parent run. Credentials never go into
either: the URI is kept without user:password, which come from MLFLOW_TRACKING_USERNAME /
MLFLOW_TRACKING_PASSWORD (or MLFLOW_TRACKING_TOKEN) at run time.
"""

from __future__ import annotations

import contextlib
import fcntl
import json
import math
import os
import re
import time
from collections.abc import Iterator
from pathlib import Path
from typing import Any

import numpy as np
import pandas as pd

from fastmac_exp.errors import InputError
from fastmac_exp.trackers.redact import redact_text, split_credentials

RECORD = "mlflow_run.json"
INSTALL = 'pip install -e ".[mlflow]" -c constraints.txt'
PARENT_TAG = "mlflow.parentRunId"
# per pair (one step per pair index) and per run
PAIR_KEYS = ("re_deg", "te_cm", "inlier_ratio_in", "inlier_ratio_kept", "n_in", "n_kept", "clique_size",
             "score")  # fmt: skip
SUMMARY_KEYS = {"RR": "rr", "RE_deg": "re_deg", "TE_cm": "te_cm", "failed": "failed_pairs", "pairs": "pairs",
                "registered": "registered", "scored": "scored", "inlier_ratio_in": "inlier_ratio_in",
                "inlier_ratio_kept": "inlier_ratio_kept"}  # fmt: skip
# what a pair's or a run's logging may wait for: a few quick retries, not mlflow's ~4 minutes of backoff
HTTP_DEFAULTS = {"MLFLOW_HTTP_REQUEST_MAX_RETRIES": "2", "MLFLOW_HTTP_REQUEST_BACKOFF_FACTOR": "1",
                 "MLFLOW_HTTP_REQUEST_TIMEOUT": "30"}  # fmt: skip


def client_class():
    """mlflow's MlflowClient, or a one-line InputError with the install command."""
    try:
        from mlflow.tracking import MlflowClient
    except ImportError:
        raise InputError(f"tracker=mlflow needs the mlflow extra, not installed here: {INSTALL}") from None
    return MlflowClient


def local_store(directory: Path) -> str:
    """A SQLite store in `directory` (no server needed; browse with `mlflow ui --backend-store-uri ...`)."""
    return f"sqlite:///{(Path(directory) / 'mlflow.db').resolve()}"


def artifact_root(uri: str) -> str | None:
    """Where a new experiment's artifacts go: beside a local SQLite store; a server decides for itself."""
    if uri.startswith("sqlite:///"):
        return (Path(uri[len("sqlite:///") :]).parent / "mlartifacts").resolve().as_uri()
    return None


def use_uri(uri: str) -> str:
    """The URI without credentials; a user:password in it goes to the environment mlflow reads."""
    clean, user, password = split_credentials(uri)
    if user is not None:
        os.environ["MLFLOW_TRACKING_USERNAME"] = user
    if password is not None:
        os.environ["MLFLOW_TRACKING_PASSWORD"] = password
    for key, value in HTTP_DEFAULTS.items():
        os.environ.setdefault(key, value)
    return clean


def reason(exc: BaseException) -> str:
    """A short reason for a failed request (mlflow's messages hold whole tracebacks of urllib3)."""
    text = redact_text(str(exc))
    m = re.search(r"\[Errno -?\d+\] ([^'\")\]]+)", text)
    if m:
        return m.group(1).strip()
    m = re.search(r"\b(40[13])\b", text)
    if m:
        return (f"HTTP {m.group(1)}: the server wants credentials (MLFLOW_TRACKING_USERNAME and "
                "MLFLOW_TRACKING_PASSWORD, or MLFLOW_TRACKING_TOKEN)")  # fmt: skip
    if "Read timed out" in text or "timed out" in text:
        return "timed out"
    return text.splitlines()[0][:200] if text else type(exc).__name__


@contextlib.contextmanager
def no_retries() -> Iterator[None]:
    """One try, 10 s at most, for the check at the start (a URL that does not answer fails at once)."""
    keys = {"MLFLOW_HTTP_REQUEST_MAX_RETRIES": "0", "MLFLOW_HTTP_REQUEST_TIMEOUT": "10"}
    saved = {k: os.environ.get(k) for k in keys}
    os.environ.update(keys)
    try:
        yield
    finally:
        for k, v in saved.items():
            if v is None:
                os.environ.pop(k, None)
            else:
                os.environ[k] = v


def connect(uri: str, key: str = "tracker.mlflow.uri"):
    """A client of the store at `uri` (credentials already moved out of it), once it has answered."""
    client = client_class()(tracking_uri=uri)
    with no_retries():
        try:
            client.search_experiments(max_results=1)
        except Exception as exc:  # noqa: BLE001 - whatever the transport raised
            raise InputError(
                f"{key}={uri}: no MLflow tracking server answers there ({reason(exc)}); start it "
                "(docs/tracking.md), or leave the URI unset to log to a store in the run directory"
            ) from None
    return client


def experiment_id(client, name: str, uri: str) -> str:
    exp = client.get_experiment_by_name(name)
    if exp is not None:
        return exp.experiment_id
    try:
        # the UI then opens on the runs table and charts (model training), not on GenAI traces
        kind = {"mlflow.experimentKind": "custom_model_development"}
        return client.create_experiment(name, artifact_location=artifact_root(uri), tags=kind)
    except Exception:  # noqa: BLE001 - another sweep member created it meanwhile
        exp = client.get_experiment_by_name(name)
        if exp is None:
            raise
        return exp.experiment_id


def experiment_name(cfg: dict[str, Any], choices: dict[str, Any] | None) -> str:
    """The dataset (with its family where that differs) and the study (+experiment=...), if any."""
    choices = choices or {}
    ds = cfg.get("dataset") or {}
    target = str(ds.get("_target_", "run")).rsplit(".", 1)[-1]
    dataset = str(choices.get("dataset") or ds.get("name") or target)
    family = ds.get("family")
    if family and str(family) != dataset:
        dataset = f"{dataset}-{family}"
    study = choices.get("experiment")
    return f"{dataset}/{study}" if study else dataset


# -- records ---------------------------------------------------------------------------------------------
def read_record(directory: Path) -> dict[str, Any] | None:
    try:
        return json.loads((Path(directory) / RECORD).read_text())
    except (OSError, ValueError):
        return None


def write_record(directory: Path, **record: Any) -> None:
    path = Path(directory) / RECORD
    tmp = path.with_suffix(".tmp")
    tmp.write_text(json.dumps(record, indent=2) + "\n")
    tmp.replace(path)


@contextlib.contextmanager
def locked(directory: Path) -> Iterator[None]:
    """Exclusive among the processes of a sweep (members running in parallel share its parent run)."""
    fd = os.open(Path(directory) / ".mlflow.lock", os.O_RDWR | os.O_CREAT, 0o644)
    try:
        fcntl.flock(fd, fcntl.LOCK_EX)
        yield
    finally:
        os.close(fd)


def existing_run(client, record: dict[str, Any] | None, uri: str) -> str | None:
    """The recorded run's id if it is in this store and still there."""
    if not record or record.get("tracking_uri") != uri or not record.get("run_id"):
        return None
    try:
        client.get_run(record["run_id"])
    except Exception:  # noqa: BLE001 - deleted, or another store under the same name
        return None
    return record["run_id"]


def parent_run(client, sweep_dir: Path, exp_id: str, uri: str) -> str:
    """The sweep's parent run: the one its directory records, else a new one (under a lock)."""
    sweep_dir.mkdir(parents=True, exist_ok=True)
    with locked(sweep_dir):
        found = existing_run(client, read_record(sweep_dir), uri)
        if found:
            return found
        tags = {"fastmac.kind": "sweep", "fastmac.sweep_dir": str(sweep_dir)}
        run = client.create_run(exp_id, run_name=sweep_dir.name, tags=tags)
        write_record(sweep_dir, run_id=run.info.run_id, experiment_id=exp_id, tracking_uri=uri, kind="sweep")
        return run.info.run_id


# -- values ----------------------------------------------------------------------------------------------
def number(v: Any) -> float | None:
    """A finite float, or None (None, NaN, pd.NA, strings)."""
    if v is None or v is pd.NA or isinstance(v, str):
        return None
    if isinstance(v, bool | np.bool_ | int | np.integer | float | np.floating):
        f = float(v)
        return f if math.isfinite(f) else None
    return None


def flat_params(cfg: dict[str, Any], prefix: str = "") -> dict[str, str]:
    """The resolved config as `a.b.c: value` strings, without the tracker group (where URIs live)."""
    out: dict[str, str] = {}
    for k, v in cfg.items():
        key = f"{prefix}{k}"
        if key == "tracker":
            continue
        if isinstance(v, dict) and v:
            out.update(flat_params(v, key + "."))
        else:
            out[key] = redact_text(str(v))[:500]
    return out


def pair_metrics(row: dict[str, Any]) -> dict[str, float]:
    """One pair's metrics: success, failed, RE/TE, inlier ratios, kept ratio, clique, stage times."""
    out: dict[str, float | None] = {
        "pair/success": number(row.get("success")),
        "pair/failed": float(isinstance(row.get("error"), str) and bool(row.get("error"))),
    }
    for k in PAIR_KEYS:
        out[f"pair/{k}"] = number(row.get(k))
    n_in, n_kept = number(row.get("n_in")), number(row.get("n_kept"))
    out["pair/kept_ratio"] = n_kept / n_in if n_in and n_kept is not None else None
    for k, v in row.items():
        if k.startswith("t_") and k.endswith("_ms"):
            out[f"time/{k[2:]}"] = number(v)
    return {k: v for k, v in out.items() if v is not None}


def summary_metrics(summary: dict[str, Any]) -> dict[str, float]:
    out: dict[str, float | None] = {new: number(summary.get(old)) for old, new in SUMMARY_KEYS.items()}
    for k, v in summary.items():
        if k.startswith("median_") and k.endswith("_ms"):
            out[k] = number(v)
    return {k: v for k, v in out.items() if v is not None}


def log_metrics(client, run_id: str, metrics: dict[str, float], step: int = 0) -> None:
    log_steps(client, run_id, {step: metrics})


def log_steps(client, run_id: str, steps: dict[int, dict[str, float]]) -> None:
    """{step: {key: value}} in batches of 1000 values."""
    from mlflow.entities import Metric

    stamp = int(time.time() * 1000)
    batch = [Metric(k, v, stamp, step) for step, metrics in steps.items() for k, v in metrics.items()]
    for i in range(0, len(batch), 1000):
        client.log_batch(run_id, metrics=batch[i : i + 1000], synchronous=True)


def log_params(client, run_id: str, params: dict[str, str]) -> None:
    """The params the run does not have yet (a resumed run keeps its first values: MLflow's params are
    write-once, and only keys that cannot change a row, or a grown limit, may differ)."""
    from mlflow.entities import Param

    have = client.get_run(run_id).data.params
    new = [Param(k, v) for k, v in params.items() if k not in have]
    for i in range(0, len(new), 100):
        client.log_batch(run_id, params=new[i : i + 100], synchronous=True)


def run_artifacts(run_dir: Path) -> list[tuple[Path, str | None]]:
    """(file, artifact folder): the tables, the summary, the configs and the report's pair snapshots."""
    names = ("results.parquet", "summary.json", "config.yaml", "config.resumed.yaml")
    files: list[tuple[Path, str | None]] = [(run_dir / n, None) for n in names if (run_dir / n).is_file()]
    files += [(p, "pairs") for p in sorted((run_dir / "report" / "pairs").glob("*.png"))]
    return files
