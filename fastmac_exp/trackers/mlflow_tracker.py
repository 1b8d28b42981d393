"""MLflow tracker: a dashboard a lab hosts itself (`mlflow server`), or a store in the run directory.

    python run.py tracker=mlflow tracker.mlflow.uri=http://mlflow.lab:5000
    python run.py -m tracker=mlflow_and_rerun sampler=highpass,random     (one parent run, one child each)

What is logged: the resolved config as flattened params (`sampler.name`, `ratio`, `dataset.family`, ...,
plus each Hydra group's choice under its own name); one step per pair (its index) with `pair/*` (success,
failed, RE, TE, inlier ratios, kept ratio, clique) and `time/*_ms`; at the end the summary (`rr`, `re_deg`,
`te_cm`, `failed_pairs`, `median_<stage>_ms`, ...) and the artifacts (results.parquet, summary.json,
config.yaml, the report's pair snapshots when they exist).

A sweep's members are children of one parent run named after the sweep directory (tag
mlflow.parentRunId), so the UI's compare view shows the sweep. A run's MLflow run id is kept in
`<run_dir>/mlflow_run.json`: a resumed run continues that run. With no URI, the store is SQLite in the run
directory (a sweep's: in the sweep directory), `mlflow ui --backend-store-uri sqlite:///<dir>/mlflow.db`.

A server that does not answer at the start stops the run before its first pair (InputError: exit 2). One
that goes away during the run costs no result: the rows are on disk before a pair is logged; the tracker
stops sending, says at the end what was not logged, and `python -m fastmac_exp.report --to-mlflow
<run_dir>` sends it later.
"""

from __future__ import annotations

import logging
import os
from pathlib import Path
from typing import Any

import pandas as pd

from fastmac_exp.pipeline import PairOutcome
from fastmac_exp.trackers import mlflow_store as store
from fastmac_exp.trackers.base import Tracker
from fastmac_exp.trackers.redact import redact_logs
from fastmac_exp.trackers.wandb_tracker import hydra_context

log = logging.getLogger(__name__)


class MlflowTracker(Tracker):
    """Log a run to MLflow.

    uri: a tracking server (http(s)://host:port, user:password@ allowed: it is moved to the environment
    and never written), or any store URI mlflow takes; null: MLFLOW_TRACKING_URI if set, else SQLite in
    the run (sweep) directory.
    experiment: null: the dataset and the study (+experiment=...). name: null: the override dirname in a
    sweep, else the run directory's name. tags: extra run tags.
    """

    name = "mlflow"

    def __init__(
        self,
        uri: str | None = None,
        experiment: str | None = None,
        name: str | None = None,
        tags: dict[str, Any] | None = None,
    ) -> None:
        store.client_class()  # the install command now, not at the first pair
        redact_logs()
        self.uri = uri
        self.experiment = experiment
        self.run_name = name
        self.tags = {str(k): str(v) for k, v in (tags or {}).items()}
        self.client = None
        self.run_id: str | None = None
        self.parent_id: str | None = None
        self.clean_uri: str | None = None
        self.run_dir: Path | None = None
        self.lost: str | None = None  # why the server stopped answering, once it has
        self.unlogged = 0  # pairs not logged since
        self.logged = 0

    # -- lifecycle -------------------------------------------------------------------------------------
    def start(self, cfg: dict[str, Any], run_dir: Path, names: list[str]) -> None:
        run_dir = Path(run_dir)
        self.run_dir = run_dir
        ctx = hydra_context()
        sweep_dir = Path(ctx["sweep_dir"]) if ctx.get("multirun") and ctx.get("sweep_dir") else None
        uri = self.uri or os.environ.get("MLFLOW_TRACKING_URI")
        uri = store.use_uri(uri) if uri else store.local_store(sweep_dir or run_dir)
        self.clean_uri = uri
        client = store.connect(uri)  # InputError (exit 2) before the first pair
        exp_name = self.experiment or store.experiment_name(cfg, ctx.get("choices"))
        exp_id = store.experiment_id(client, exp_name, uri)
        if sweep_dir is not None:
            self.parent_id = store.parent_run(client, sweep_dir, exp_id, uri)
        run_id = store.existing_run(client, store.read_record(run_dir), uri)
        if run_id is not None:  # a resume: the same MLflow run goes on
            client.update_run(run_id, status="RUNNING")
        else:
            tags = {"fastmac.run_dir": str(run_dir), **self.tags}
            if self.parent_id:
                tags[store.PARENT_TAG] = self.parent_id
            name = self.run_name or (member_name(ctx.get("override_dirname")) if sweep_dir else None)
            name = name or run_dir.name
            run_id = client.create_run(exp_id, run_name=name, tags=tags).info.run_id
            store.write_record(run_dir, run_id=run_id, experiment_id=exp_id, tracking_uri=uri, kind="run",
                               parent_run_id=self.parent_id)  # fmt: skip
        self.client, self.run_id = client, run_id
        params = store.flat_params(cfg)
        params.update({g: str(c) for g, c in (ctx.get("choices") or {}).items() if g not in params})
        params["num_pairs"] = str(len(names))
        self._send(store.log_params, params)

    def _send(self, fn, *args: Any) -> bool:
        """Call fn(client, run_id, *args) unless the server has gone away; a failure marks it gone."""
        if self.client is None or self.lost is not None:
            return False
        try:
            fn(self.client, self.run_id, *args)
            return True
        except Exception as exc:  # noqa: BLE001 - the results are on disk; logging must not stop the run
            self.lost = store.reason(exc)
            log.warning("mlflow: %s stopped answering (%s); the run goes on and keeps every result in %s",
                        self.clean_uri, self.lost, self.run_dir)  # fmt: skip
            return False

    def log_pair(self, outcome: PairOutcome) -> None:
        if self.client is None:
            return
        row = outcome.row
        if self._send(store.log_metrics, store.pair_metrics(row), int(row.get("index") or 0)):
            self.logged += 1
        else:
            self.unlogged += 1

    def finish(self, table: pd.DataFrame, summary: dict[str, Any]) -> None:
        if self.client is None:
            return
        ok = self._send(store.log_metrics, store.summary_metrics(summary))
        for path, folder in store.run_artifacts(self.run_dir):
            ok = ok and self._send(lambda c, r, p=path, f=folder: c.log_artifact(r, str(p), f))
        status = "FINISHED" if summary.get("complete", True) else "KILLED"
        ok = ok and self._send(lambda c, r: c.set_terminated(r, status))
        self.client = None
        if not ok:
            log.warning(
                "mlflow: %d of %d pairs, the summary and the artifacts were not logged to %s (%s); "
                "nothing is lost: the results are in %s; send them with: python -m fastmac_exp.report "
                "--to-mlflow %s",
                self.unlogged, self.unlogged + self.logged, self.clean_uri, self.lost, self.run_dir,
                self.run_dir,
            )  # fmt: skip


def member_name(override_dirname: str | None) -> str:
    """A sweep member's run name: its overrides (ratio=0.1,sampler=random) less the tracker's own."""
    return ",".join(o for o in (override_dirname or "").split(",") if o and not o.startswith("tracker"))


def close_parent(sweep_dir: Path, uri: str | None, table_text: str | None = None) -> None:
    """The end of a sweep: its parent run gets the members' table and is marked finished."""
    record = store.read_record(sweep_dir)
    if not record or record.get("kind") != "sweep":
        return
    clean = store.use_uri(uri) if uri else record["tracking_uri"]
    try:
        client = store.connect(clean)
        if table_text:
            client.log_text(record["run_id"], table_text, "sweep_summary.txt")
        client.set_terminated(record["run_id"], "FINISHED")
    except Exception as exc:  # noqa: BLE001 - the sweep's results are on disk (InputError included)
        log.warning("mlflow: could not close the sweep's parent run: %s", store.reason(exc))
