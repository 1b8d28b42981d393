"""Send finished runs to MLflow afterwards (`python -m fastmac_exp.report --to-mlflow <run or sweep>`),
as `wandb sync` does for wandb: runs that were never logged, and what a run could not log while its
server was away. A run keeps its MLflow run (mlflow_run.json): only the pairs (steps) that run lacks are
sent, so a second upload adds nothing twice. A sweep's members become children of its parent run, which
also gets the report's tables and plots.
"""

from __future__ import annotations

import json
import logging
import os
from pathlib import Path
from typing import Any

from omegaconf import OmegaConf

from fastmac_exp.errors import InputError
from fastmac_exp.trackers import mlflow_store as store
from fastmac_exp.trackers.mlflow_tracker import member_name

log = logging.getLogger(__name__)


def _hydra(run_dir: Path) -> dict[str, Any]:
    """The run's Hydra choices and override dirname, from the .hydra/hydra.yaml Hydra wrote there."""
    try:
        hc = OmegaConf.load(run_dir / ".hydra" / "hydra.yaml").hydra
        return {"choices": {k: v for k, v in OmegaConf.to_container(hc.runtime.choices).items()
                            if not k.startswith("hydra/")},
                "override_dirname": str(hc.job.override_dirname or "")}  # fmt: skip
    except Exception:  # noqa: BLE001 - a run made through the API has none
        return {"choices": {}, "override_dirname": ""}


def _config(run_dir: Path) -> dict[str, Any]:
    latest = run_dir / "config.resumed.yaml"
    return OmegaConf.to_container(OmegaConf.load(latest if latest.is_file() else run_dir / "config.yaml"))


def store_uri(root: Path, runs: list[Path], uri: str | None) -> str:
    """--mlflow-uri, else the recorded store, else the runs' tracker.mlflow.uri, else MLFLOW_TRACKING_URI,
    else a SQLite store in `root`."""
    if uri:
        return store.use_uri(uri)
    for d in (root, *runs):
        record = store.read_record(d)
        if record and record.get("tracking_uri"):
            return store.use_uri(record["tracking_uri"])
    for d in runs:
        configured = OmegaConf.select(OmegaConf.load(d / "config.yaml"), "tracker.mlflow.uri", default=None)
        if configured:  # a user:password was redacted there ("***@"): the environment holds it
            return store.use_uri(str(configured).replace("***@", ""))
    if os.environ.get("MLFLOW_TRACKING_URI"):
        return store.use_uri(os.environ["MLFLOW_TRACKING_URI"])
    return store.local_store(root)


def upload_run(client, uri: str, run_dir: Path, parent: str | None) -> str:
    """Create (or find) the run's MLflow run and send what it lacks; returns its id."""
    from fastmac_exp.report import load_run

    cfg, hydra = _config(run_dir), _hydra(run_dir)
    name = (cfg.get("tracker") or {}).get("mlflow", {}).get("experiment")
    exp_id = store.experiment_id(client, name or store.experiment_name(cfg, hydra["choices"]), uri)
    run_id = store.existing_run(client, store.read_record(run_dir), uri)
    if run_id is None:
        tags = {"fastmac.run_dir": str(run_dir), **({store.PARENT_TAG: parent} if parent else {})}
        run_name = (member_name(hydra["override_dirname"]) if parent else "") or run_dir.name
        run_id = client.create_run(exp_id, run_name=run_name, tags=tags).info.run_id
        store.write_record(run_dir, run_id=run_id, experiment_id=exp_id, tracking_uri=uri, kind="run",
                           parent_run_id=parent)  # fmt: skip
    table = load_run(run_dir)
    params = store.flat_params(cfg)
    params.update({g: str(c) for g, c in hydra["choices"].items() if g not in params})
    params["num_pairs"] = str(len(table))
    store.log_params(client, run_id, params)
    have = {m.step for m in client.get_metric_history(run_id, "pair/failed")}
    rows = [r for r in table.to_dict("records") if int(r["index"]) not in have]
    store.log_steps(client, run_id, {int(r["index"]): store.pair_metrics(r) for r in rows})
    try:
        summary = json.loads((run_dir / "summary.json").read_text())
    except (OSError, ValueError):
        summary = {"complete": False}
    store.log_metrics(client, run_id, store.summary_metrics(summary))
    for path, folder in store.run_artifacts(run_dir):
        client.log_artifact(run_id, str(path), folder)
    client.set_terminated(run_id, "FINISHED" if summary.get("complete") else "KILLED")
    log.info("mlflow: %s -> run %s (%d pairs sent)", run_dir, run_id, len(rows))
    return run_id


def report_files(out_dir: Path) -> list[Path]:
    return [p for p in sorted(Path(out_dir).glob("*")) if p.suffix in (".png", ".md", ".csv")]


def upload(root: str | Path, uri: str | None = None, report_dir: Path | None = None) -> dict[str, Any]:
    """Every run below `root` (a run or a sweep directory); a sweep's report goes to its parent run."""
    from fastmac_exp.report import find_runs

    root = Path(root)
    runs = find_runs(root, exclude=[report_dir] if report_dir else [root / "report"])
    if not runs:
        raise InputError(f"--to-mlflow {root}: no run below it (no results.parquet or results.jsonl)")
    clean = store_uri(root, runs, uri)
    client = store.connect(clean, key="--mlflow-uri" if uri else "MLflow store")
    parent = None
    if root.resolve() not in {r.resolve() for r in runs}:  # a sweep: one parent, a child per member
        cfg, hydra = _config(runs[0]), _hydra(runs[0])
        name = (cfg.get("tracker") or {}).get("mlflow", {}).get("experiment")
        exp_id = store.experiment_id(client, name or store.experiment_name(cfg, hydra["choices"]), clean)
        parent = store.parent_run(client, root, exp_id, clean)
    ids = [upload_run(client, clean, r, parent) for r in runs]
    target = parent or ids[0]
    if report_dir is not None:
        for p in report_files(report_dir):
            client.log_artifact(target, str(p), "report")
    if parent:
        client.set_terminated(parent, "FINISHED")
    return {"uri": clean, "parent": parent, "runs": ids}


def upload_report(root: str | Path, report_dir: Path) -> str | None:
    """A report of a run or sweep logged live: its plots and tables go to the (parent) run."""
    record = store.read_record(Path(root))
    if not record:
        return None
    client = store.connect(store.use_uri(record["tracking_uri"]), key="MLflow store")
    for p in report_files(report_dir):
        client.log_artifact(record["run_id"], str(p), "report")
    return record["run_id"]
