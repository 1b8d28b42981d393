"""The MLflow tracker against a real tracking server (pip install -e ".[mlflow]"; skipped without it).

One `mlflow server` per module, on 127.0.0.1 (a free port) with a SQLite store and an artifact root in a
temporary directory, started here and stopped (its process group killed) at the end. Against it: a
two-member sweep (one parent, two children, their params, rr, the parquet artifact; a password in the URI
found in no file of the sweep and not on the console), then one member resumed (the same MLflow run goes
on), then a sweep that never logged sent afterwards by `report --to-mlflow` (twice: no step twice), a URL
where no server answers (exit 2 before the first pair), and a server that goes away mid-run (every row is on
disk, the end says what was not logged, and `report --to-mlflow` sends it once the server is back). The
helpers' tests need no server.
"""

from __future__ import annotations

import json
import logging
import os
import signal
import socket
import subprocess
import sys
import time
import urllib.request
from pathlib import Path

import pandas as pd
import pytest

from fastmac_exp.errors import InputError
from fastmac_exp.trackers.redact import redact, redact_text, split_credentials

REPO = Path(__file__).resolve().parents[1]
THREADS = {"OPENBLAS_NUM_THREADS": "1", "OMP_NUM_THREADS": "1", "MKL_NUM_THREADS": "1"}
FAST = ("limit=2", "descriptor=oracle")  # correspondences drawn from the GT: no FPFH to wait for
SECRET = "s3cret-Pw9"  # the password the sweep's URI carries; no file or console line may show it


# -- no server needed -------------------------------------------------------------------------------------
def test_credentials_are_split_off_and_redacted():
    clean = ("https://mlflow.lab:5000/x", "ana", "p@ss")
    assert split_credentials("https://ana:p%40ss@mlflow.lab:5000/x") == clean
    assert split_credentials("http://127.0.0.1:5000") == ("http://127.0.0.1:5000", None, None)
    assert split_credentials("sqlite:////tmp/a@b/mlflow.db")[1] is None  # no netloc: nothing to split
    line = "uri=http://ana:pw@host:5000 and https://tok@x.org/a, mail a@b.c"
    assert redact_text(line) == "uri=http://***@host:5000 and https://***@x.org/a, mail a@b.c"
    assert (
        redact_text(r"tracker.mlflow.uri=http\://ana\:pw@h\:5000")
        == r"tracker.mlflow.uri=http\://***@h\:5000"
    )
    assert redact({"t": {"uri": "http://u:pw@h"}, "l": ["http://u:pw@h"], "n": 1}) == {
        "t": {"uri": "http://***@h"}, "l": ["http://***@h"], "n": 1}  # fmt: skip


def test_params_and_metrics_from_a_config_and_rows():
    from fastmac_exp.trackers import mlflow_store as store

    cfg = {"ratio": 0.2, "sampler": {"name": "highpass", "estimate": {"anchors": 8}}, "samples": None,
           "tracker": {"mlflow": {"uri": "http://u:pw@h"}}, "dataset": {"family": "kitti"}}  # fmt: skip
    params = store.flat_params(cfg)
    assert params == {"ratio": "0.2", "sampler.name": "highpass", "sampler.estimate.anchors": "8",
                      "samples": "None", "dataset.family": "kitti"}  # fmt: skip
    row = {"index": 3, "success": True, "error": "", "re_deg": 1.5, "te_cm": float("nan"), "n_in": 200,
           "n_kept": 50, "inlier_ratio_kept": 0.4, "t_graph_ms": 2.0, "t_total_ms": pd.NA}  # fmt: skip
    m = store.pair_metrics(row)
    assert m == {"pair/success": 1.0, "pair/failed": 0.0, "pair/re_deg": 1.5, "pair/n_in": 200.0,
                 "pair/n_kept": 50.0, "pair/inlier_ratio_kept": 0.4, "pair/kept_ratio": 0.25,
                 "time/graph_ms": 2.0}  # fmt: skip
    assert store.pair_metrics({"index": 0, "error": "RuntimeError: x", "success": False})["pair/failed"] == 1
    s = store.summary_metrics({"RR": 0.5, "RE_deg": 2.0, "TE_cm": float("nan"), "failed": 1,
                               "median_total_ms": 9.0, "dataset": "x"})  # fmt: skip
    assert s == {"rr": 0.5, "re_deg": 2.0, "failed_pairs": 1.0, "median_total_ms": 9.0}
    assert store.experiment_name({"dataset": {"family": "3dmatch"}}, {"dataset": "synthetic"}) == (
        "synthetic-3dmatch"
    )
    assert store.experiment_name({}, {"dataset": "kitti", "experiment": "sampling_strategy"}) == (
        "kitti/sampling_strategy"
    )


def test_without_mlflow_the_choice_is_a_one_line_error(monkeypatch):
    import builtins

    from hydra import compose, initialize_config_dir

    from fastmac_exp.run.experiment import _make_trackers

    real_import = builtins.__import__

    def no_mlflow(name, *args, **kwargs):
        if name == "mlflow" or name.startswith("mlflow."):
            raise ImportError("No module named 'mlflow'")
        return real_import(name, *args, **kwargs)

    monkeypatch.setattr(builtins, "__import__", no_mlflow)
    with initialize_config_dir(config_dir=str(REPO / "conf"), version_base="1.3"):
        cfg = compose("config", overrides=["tracker=mlflow_and_rerun"])
    with pytest.raises(Exception) as info:
        _make_trackers(cfg)
    err = info.value.__cause__ or info.value
    assert isinstance(err, InputError)
    install = 'pip install -e ".[mlflow]" -c constraints.txt'
    assert str(err) == f"tracker=mlflow needs the mlflow extra, not installed here: {install}"


def test_tracker_configs():
    from hydra import compose, initialize_config_dir

    with initialize_config_dir(config_dir=str(REPO / "conf"), version_base="1.3"):
        both = compose("config", overrides=["tracker=mlflow_and_rerun"]).tracker
        alone = compose("config", overrides=["tracker=mlflow"]).tracker
    assert both.mlflow.enabled and both.rerun.enabled and not both.wandb.enabled
    assert list(alone) == ["mlflow"] and alone.mlflow.uri is None and alone.mlflow.experiment is None


# -- against a server -------------------------------------------------------------------------------------
def _free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


class Server:
    """`mlflow server` on 127.0.0.1:port with its store in `root`; start() waits for /health (90 s)."""

    def __init__(self, root: Path, port: int | None = None) -> None:
        self.root, self.port = root, port or _free_port()
        self.url = f"http://127.0.0.1:{self.port}"
        self.proc: subprocess.Popen | None = None

    def start(self) -> Server:
        exe = Path(sys.executable).with_name("mlflow")
        cmd = [str(exe), "server", "--host", "127.0.0.1", "--port", str(self.port), "--workers", "1",
               "--backend-store-uri", f"sqlite:///{self.root / 'mlflow.db'}",
               "--artifacts-destination", str(self.root / "artifacts")]  # fmt: skip
        log = open(self.root / "server.log", "a")  # noqa: SIM115 - the server's, closed with it
        self.proc = subprocess.Popen(cmd, cwd=self.root, stdout=log, stderr=subprocess.STDOUT,
                                     start_new_session=True)  # fmt: skip
        deadline = time.monotonic() + 90
        while True:
            try:
                with urllib.request.urlopen(self.url + "/health", timeout=2) as r:
                    if r.status == 200:
                        return self
            except OSError:
                pass
            if self.proc.poll() is not None or time.monotonic() > deadline:
                self.stop()
                pytest.fail("mlflow server did not start:\n" + (self.root / "server.log").read_text()[-3000:])
            time.sleep(0.3)

    def stop(self) -> None:
        if self.proc is not None and self.proc.poll() is None:
            os.killpg(self.proc.pid, signal.SIGTERM)
            try:
                self.proc.wait(5)
            except subprocess.TimeoutExpired:
                os.killpg(self.proc.pid, signal.SIGKILL)
                self.proc.wait()
        self.proc = None


@pytest.fixture(scope="module")
def server(tmp_path_factory):
    pytest.importorskip("mlflow")
    srv = Server(tmp_path_factory.mktemp("mlflow-server")).start()
    yield srv
    srv.stop()


@pytest.fixture(scope="module")
def caches(tmp_path_factory) -> list[str]:
    """The module's own correspondence cache; the synthetic scans are the checkout's (.cache/synthetic), as
    for the CLI's tests."""
    return [f"cache.dir={tmp_path_factory.mktemp('caches') / 'corr'}"]


def run_py(*args: str, env: dict[str, str] | None = None, timeout: int = 300) -> subprocess.CompletedProcess:
    full_env = {**os.environ, **THREADS, "PYTHONPATH": str(REPO), **(env or {})}
    cmd = [sys.executable, "run.py", *args, "progress=false"]
    return subprocess.run(cmd, cwd=REPO, env=full_env, capture_output=True, text=True, timeout=timeout)


def client(url: str):
    from mlflow.tracking import MlflowClient

    return MlflowClient(url)


def runs_of(c, name: str) -> list:
    exp = c.get_experiment_by_name(name)
    return [] if exp is None else list(c.search_runs([exp.experiment_id]))


@pytest.fixture(scope="module")
def sweep(server, caches, tmp_path_factory) -> tuple[Path, subprocess.CompletedProcess]:
    """A two-member sweep logged through a URI that carries a user and password."""
    sweep_dir = tmp_path_factory.mktemp("sweep") / "sweep"
    uri = f"http://ana:{SECRET}@127.0.0.1:{server.port}"
    p = run_py("-m", *FAST, "sampler=highpass,random", "tracker=mlflow_and_rerun",
               f"tracker.mlflow.uri={uri}", "tracker.mlflow.experiment=sweep-test",
               "tracker.rerun.max_pairs=1", f"hydra.sweep.dir={sweep_dir}", *caches)  # fmt: skip
    assert p.returncode == 0, (p.stdout + p.stderr)[-4000:]
    return sweep_dir, p


def test_a_sweep_is_one_parent_with_a_child_per_member(server, sweep, tmp_path):
    sweep_dir, _ = sweep
    c = client(server.url)
    runs = runs_of(c, "sweep-test")
    parents = [r for r in runs if "mlflow.parentRunId" not in r.data.tags]
    children = [r for r in runs if "mlflow.parentRunId" in r.data.tags]
    assert len(parents) == 1 and len(children) == 2
    parent = parents[0]
    assert parent.info.run_name == "sweep" and parent.info.status == "FINISHED"
    assert json.loads((sweep_dir / "mlflow_run.json").read_text())["run_id"] == parent.info.run_id
    assert {r.data.tags["mlflow.parentRunId"] for r in children} == {parent.info.run_id}
    assert "sweep_summary.txt" in [a.path for a in c.list_artifacts(parent.info.run_id)]
    members = {d.name: d for d in sweep_dir.iterdir() if (d / "summary.json").is_file()}
    assert len(members) == 2
    for r in children:
        [member] = [d for n, d in members.items() if r.info.run_name in n]  # N_<overrides>
        name = r.info.run_name  # the member's overrides less the tracker's
        assert name.startswith("descriptor=oracle,sampler=") and "tracker" not in name and "limit" not in name
        assert json.loads((member / "mlflow_run.json").read_text())["run_id"] == r.info.run_id
        summary = json.loads((member / "summary.json").read_text())
        p = r.data.params
        assert p["sampler"] == summary["sampler"] and p["ratio"] == "0.2" and p["limit"] == "2"
        assert p["dataset"] == "synthetic" and p["dataset.family"] == "3dmatch" and p["seed"] == "0"
        assert p["descriptor"] == "oracle" and p["backend"] == "cpp" and p["num_pairs"] == "2"
        assert r.data.metrics["rr"] == pytest.approx(summary["RR"])
        assert r.data.metrics["median_total_ms"] == pytest.approx(summary["median_total_ms"])
        assert r.info.status == "FINISHED"
        table = pd.read_parquet(member / "results.parquet")
        steps = {m.step: m.value for m in c.get_metric_history(r.info.run_id, "pair/re_deg")}
        assert steps == pytest.approx(dict(zip(table["index"], table["re_deg"])))
        arts = [a.path for a in c.list_artifacts(r.info.run_id)]
        assert {"results.parquet", "summary.json", "config.yaml"} <= set(arts)
        got = Path(c.download_artifacts(r.info.run_id, "results.parquet", str(tmp_path / r.info.run_id)))
        assert got.read_bytes() == (member / "results.parquet").read_bytes()
    assert {r.data.params["sampler"] for r in children} == {"highpass", "random"}


def test_no_secret_in_any_file_or_on_the_console(sweep):
    sweep_dir, p = sweep
    assert "127.0.0.1" in (sweep_dir / "multirun.yaml").read_text()  # the URI is there, its password not
    files = [f for f in sweep_dir.rglob("*") if f.is_file()]
    assert len(files) > 20  # configs, logs, tables, .hydra/, the recordings
    leaks = [str(f) for f in files if SECRET.encode() in f.read_bytes()]
    assert leaks == []
    assert SECRET not in p.stdout + p.stderr
    assert "***@127.0.0.1" in p.stdout + p.stderr  # Hydra's launcher names the overrides, redacted


def test_a_resumed_member_continues_its_own_run(server, sweep, caches):
    sweep_dir, _ = sweep
    member = next(d for d in sorted(sweep_dir.iterdir()) if (d / "summary.json").is_file())
    record = json.loads((member / "mlflow_run.json").read_text())
    c = client(server.url)
    before = {r.info.run_id for r in runs_of(c, "sweep-test")}
    sampler = json.loads((member / "summary.json").read_text())["sampler"]
    env = {"MLFLOW_TRACKING_USERNAME": "ana", "MLFLOW_TRACKING_PASSWORD": SECRET}
    p = run_py(*FAST, "limit=3", f"sampler={sampler}", "tracker=mlflow", f"tracker.mlflow.uri={server.url}",
               "tracker.mlflow.experiment=sweep-test", f"resume='{member}'", *caches, env=env)  # fmt: skip
    assert p.returncode == 0, (p.stdout + p.stderr)[-4000:]
    assert {r.info.run_id for r in runs_of(c, "sweep-test")} == before  # no second run
    assert json.loads((member / "mlflow_run.json").read_text())["run_id"] == record["run_id"]
    run = c.get_run(record["run_id"])
    assert run.info.status == "FINISHED" and run.data.tags["mlflow.parentRunId"] == record["parent_run_id"]
    steps = sorted(m.step for m in c.get_metric_history(record["run_id"], "pair/failed"))
    assert steps == [0, 1, 2]  # the two pairs of the sweep and the resume's third, each once
    summary = json.loads((member / "summary.json").read_text())
    assert summary["pairs"] == 3 and run.data.metrics["pairs"] == 3
    assert run.data.metrics["rr"] == pytest.approx(summary["RR"])
    assert "config.resumed.yaml" in [a.path for a in c.list_artifacts(record["run_id"])]


def test_report_sends_a_sweep_that_never_logged(server, caches, tmp_path):
    sweep_dir = tmp_path / "sweep"
    p = run_py("-m", *FAST, "sampler=highpass,random", "tracker=none", f"hydra.sweep.dir={sweep_dir}",
               *caches)  # fmt: skip
    assert p.returncode == 0, (p.stdout + p.stderr)[-4000:]
    env = {**os.environ, **THREADS, "PYTHONPATH": str(REPO)}
    cmd = [sys.executable, "-m", "fastmac_exp.report", str(sweep_dir), "--no-plots", "--snapshots", "0",
           "--to-mlflow", "--mlflow-uri", server.url]  # fmt: skip
    for _ in range(2):  # the second time sends nothing twice
        p = subprocess.run(cmd, cwd=REPO, env=env, capture_output=True, text=True, timeout=120)
        assert p.returncode == 0, (p.stdout + p.stderr)[-3000:]
    c = client(server.url)
    parent_id = json.loads((sweep_dir / "mlflow_run.json").read_text())["run_id"]
    runs = runs_of(c, "synthetic-3dmatch")
    children = [r for r in runs if r.data.tags.get("mlflow.parentRunId") == parent_id]
    assert len(children) == 2 and {r.data.params["sampler"] for r in children} == {"highpass", "random"}
    for r in children:
        assert sorted(m.step for m in c.get_metric_history(r.info.run_id, "pair/failed")) == [0, 1]
        assert "rr" in r.data.metrics and r.info.status == "FINISHED"
    assert "report" in [a.path for a in c.list_artifacts(parent_id)]


def test_an_unreachable_server_stops_the_run_before_its_first_pair(caches, tmp_path):
    pytest.importorskip("mlflow")
    url = f"http://127.0.0.1:{_free_port()}"
    p = run_py(*FAST, "tracker=mlflow", f"tracker.mlflow.uri={url}", f"hydra.run.dir={tmp_path / 'run'}",
               *caches)  # fmt: skip
    assert p.returncode == 2, (p.stdout + p.stderr)[-3000:]
    errors = [line for line in (p.stdout + p.stderr).splitlines() if url in line]
    assert errors and "no MLflow tracking server answers there" in errors[0], p.stderr[-2000:]
    assert not (tmp_path / "run" / "results.jsonl").exists()


@pytest.mark.slow  # ~40 s: the server starts twice
def test_a_server_that_goes_away_mid_run_loses_nothing(server, caches, tmp_path, monkeypatch, caplog):
    from hydra import compose, initialize_config_dir

    from fastmac_exp.run.experiment import run_experiment
    from fastmac_exp.trackers.mlflow_tracker import MlflowTracker

    srv = server  # stopped mid-run and started again on its port and store (this module's last test)
    try:
        with initialize_config_dir(config_dir=str(REPO / "conf"), version_base="1.3"):
            overrides = [*FAST, "limit=3", "tracker=mlflow", f"tracker.mlflow.uri={srv.url}",
                         "tracker.mlflow.experiment=lost", "progress=false", *caches]  # fmt: skip
            cfg = compose("config", overrides=overrides)
        real_log_pair = MlflowTracker.log_pair

        def log_then_stop(self, outcome):
            real_log_pair(self, outcome)
            if outcome.row["index"] == 0:
                srv.stop()  # gone after the first pair

        monkeypatch.setattr(MlflowTracker, "log_pair", log_then_stop)
        run_dir = tmp_path / "run"
        with caplog.at_level(logging.WARNING):
            table, summary = run_experiment(cfg, run_dir)
        assert len(table) == 3 and summary["complete"]
        assert len(pd.read_parquet(run_dir / "results.parquet")) == 3
        assert json.loads((run_dir / "summary.json").read_text())["pairs"] == 3
        said = caplog.text
        assert "stopped answering" in said
        assert f"2 of 3 pairs, the summary and the artifacts were not logged to {srv.url}" in said
        assert f"python -m fastmac_exp.report --to-mlflow {run_dir}" in said

        srv.start()  # back, on the same port and store: the upload completes the same run
        monkeypatch.undo()
        env = {**os.environ, **THREADS, "PYTHONPATH": str(REPO)}
        cmd = [sys.executable, "-m", "fastmac_exp.report", str(run_dir), "--no-plots", "--to-mlflow"]
        p = subprocess.run(cmd, cwd=REPO, env=env, capture_output=True, text=True, timeout=120)
        assert p.returncode == 0, (p.stdout + p.stderr)[-3000:]
        c = client(srv.url)
        [run] = runs_of(c, "lost")
        assert run.info.run_id == json.loads((run_dir / "mlflow_run.json").read_text())["run_id"]
        assert sorted(m.step for m in c.get_metric_history(run.info.run_id, "pair/failed")) == [0, 1, 2]
        assert run.data.metrics["rr"] == pytest.approx(summary["RR"]) and run.info.status == "FINISHED"
        arts = [a.path for a in c.list_artifacts(run.info.run_id)]
        assert "results.parquet" in arts and "report" in arts
    finally:
        if srv.proc is None:
            srv.start()
