"""Sweeps through the cluster launchers give the results of a serial sweep (pip install -e ".[cluster]").

The same tiny sweep (2 synthetic pairs x samplers highpass, random at ratio 0.2) runs serially (Hydra's
basic launcher), through submitit's local executor (Slurm's code path minus the scheduler) and through
hydra/launcher=ray_cluster against a one-machine Ray cluster that the test starts on 127.0.0.1 and stops.
Every sweep starts from empty caches of its own, so the launchers' workers describe the pairs themselves
(and the members of one sweep race on the same cache keys). Tables are compared member by member with
the timing columns dropped (t_*_ms, and the report's medians of them: they measure this machine's load)
and `describe_cached` (which member happened to describe a pair first: with members in parallel, both
may; serially, the second always reads the first one's entry). Everything else must be equal, exactly.
Skipped without the cluster extra (CI's plain install); .ci/run installs it and runs this file.
"""

from __future__ import annotations

import os
import secrets
import shutil
import signal
import socket
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import pandas as pd
import pytest

REPO = Path(__file__).resolve().parents[1]
SWEEP = ("limit=2", "sampler=highpass,random", "ratio=0.2")
# one BLAS thread per process: the members share the machine's cores
THREADS = {"OPENBLAS_NUM_THREADS": "1", "OMP_NUM_THREADS": "1", "MKL_NUM_THREADS": "1"}
# `ray start` clusters use token authentication; the driver then needs this too (docs/cluster.md)
# `ray start` turns token authentication on; a fresh HOME has no ~/.ray/auth_token, so the test's head and
# its driver share a token of their own
RAY_ENV = {"RAY_AUTH_MODE": "token", "RAY_AUTH_TOKEN": secrets.token_hex(32), "RAY_USAGE_STATS_ENABLED": "0"}


def run_sweep(root: Path, *launcher: str, env: dict[str, str] | None = None, timeout: int = 300) -> Path:
    """The sweep into root/sweep, with its own empty caches under root; returns the sweep directory."""
    sweep_dir = root / "sweep"
    cmd = [sys.executable, "run.py", "-m", *SWEEP, *launcher, "tracker=none", "progress=false",
           f"hydra.sweep.dir={sweep_dir}", f"cache.dir={root / 'corr'}",
           f"dataset.cache_dir={root / 'synthetic'}"]  # fmt: skip
    full_env = {**os.environ, **THREADS, "PYTHONPATH": str(REPO), **(env or {})}
    p = subprocess.run(cmd, cwd=REPO, env=full_env, capture_output=True, text=True, timeout=timeout)
    assert p.returncode == 0, (p.stdout + p.stderr)[-4000:]
    return sweep_dir


def member_tables(sweep_dir: Path) -> dict[str, pd.DataFrame]:
    """{member directory name: its results table without the timing columns}."""
    tables = {}
    for csv in sorted(sweep_dir.glob("*/results.csv")):
        t = pd.read_csv(csv)
        drop = [c for c in t.columns if c.endswith("_ms") or c == "describe_cached"]
        tables[csv.parent.name] = t.drop(columns=drop)
    return tables


def assert_same_results(got: Path, want: Path) -> None:
    """Same members (directory names), each with the same rows and values as the serial sweep's."""
    g, w = member_tables(got), member_tables(want)
    assert sorted(g) == sorted(w), f"members differ: {sorted(g)} vs serial {sorted(w)}"
    for name in w:
        pd.testing.assert_frame_equal(g[name], w[name], check_exact=True, obj=f"member {name}")


def report_table(sweep_dir: Path) -> pd.DataFrame:
    out = sweep_dir.parent / "report"
    cmd = [sys.executable, "-m", "fastmac_exp.report", str(sweep_dir), "--out", str(out), "--no-plots"]
    env = {**os.environ, **THREADS, "PYTHONPATH": str(REPO)}
    p = subprocess.run(cmd, cwd=REPO, env=env, capture_output=True, text=True, timeout=120)
    assert p.returncode == 0, (p.stdout + p.stderr)[-4000:]
    t = pd.read_csv(out / "report.csv")
    return t.drop(columns=[c for c in t.columns if c.endswith("_ms")])


@pytest.fixture(scope="module")
def serial(tmp_path_factory) -> Path:
    pytest.importorskip("hydra_plugins.hydra_submitit_launcher")  # nothing to compare without the extra
    sweep_dir = run_sweep(tmp_path_factory.mktemp("serial"), "hydra/launcher=basic")
    tables = member_tables(sweep_dir)
    assert len(tables) == 2 and all(len(t) == 2 for t in tables.values()), tables
    for name, t in tables.items():  # each member's rows in its own directory
        assert (t["sampler"] == ("highpass" if "sampler=highpass" in name else "random")).all()
        assert (t["error"].astype("string").fillna("") == "").all(), t["error"]
    return sweep_dir


def test_the_comparison_catches_a_wrong_or_missing_member(serial, tmp_path):
    copy = tmp_path / "sweep"
    shutil.copytree(serial, copy)
    assert_same_results(copy, serial)
    first, second = sorted(p.parent for p in copy.glob("*/results.csv"))
    t = pd.read_csv(first / "results.csv")
    t.loc[0, "re_deg"] += 1e-9
    t.to_csv(first / "results.csv", index=False)
    with pytest.raises(AssertionError):
        assert_same_results(copy, serial)
    shutil.rmtree(first)
    with pytest.raises(AssertionError, match="members differ"):
        assert_same_results(copy, serial)


def test_submitit_local_sweep_matches_the_serial_sweep(serial, tmp_path):
    pytest.importorskip("hydra_plugins.hydra_submitit_launcher")
    got = run_sweep(tmp_path, "hydra/launcher=submitit_local", "hydra.launcher.timeout_min=10")
    assert list(got.glob(".submitit/*/*_log.out"))  # the members really ran as submitit jobs
    assert_same_results(got, serial)
    pd.testing.assert_frame_equal(report_table(got), report_table(serial))


def _free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


@pytest.fixture(scope="module")
def ray_head():
    """A one-machine Ray cluster (2 CPUs) on 127.0.0.1, started here and stopped (its process group
    killed) at the end; bounded: 120 s to come up."""
    pytest.importorskip("ray")
    ray_exe = Path(sys.executable).with_name("ray")
    port = _free_port()
    temp = Path(tempfile.mkdtemp(prefix="ray", dir="/tmp"))  # short: Ray's socket paths are length-limited
    log_path = temp / "head.log"
    env = {**os.environ, **THREADS, **RAY_ENV, "PYTHONPATH": str(REPO)}
    cmd = [str(ray_exe), "start", "--head", "--block", "--node-ip-address=127.0.0.1", f"--port={port}",
           "--num-cpus=2", "--include-dashboard=false", "--disable-usage-stats",
           f"--temp-dir={temp}"]  # fmt: skip
    with open(log_path, "w") as log:
        proc = subprocess.Popen(cmd, cwd=REPO, env=env, stdout=log, stderr=subprocess.STDOUT,
                                start_new_session=True)  # fmt: skip
    try:
        deadline = time.monotonic() + 120
        while "Ray runtime started" not in log_path.read_text():
            if proc.poll() is not None or time.monotonic() > deadline:
                pytest.fail(f"the Ray head did not start:\n{log_path.read_text()[-3000:]}")
            time.sleep(0.5)
        yield f"127.0.0.1:{port}"
    finally:
        for sig, wait in ((signal.SIGTERM, 10), (signal.SIGKILL, 10)):
            try:
                os.killpg(proc.pid, sig)
            except ProcessLookupError:
                break
            try:
                proc.wait(timeout=wait)
                time.sleep(1)  # the head's children share its process group: let them go too
            except subprocess.TimeoutExpired:
                continue
        try:
            os.killpg(proc.pid, signal.SIGKILL)  # anything of the group still alive
        except ProcessLookupError:
            pass
        shutil.rmtree(temp, ignore_errors=True)


def test_ray_cluster_sweep_by_address_matches_the_serial_sweep(serial, ray_head, tmp_path):
    got = run_sweep(tmp_path, "hydra/launcher=ray_cluster", f"hydra.launcher.address={ray_head}", env=RAY_ENV)
    assert_same_results(got, serial)
    pd.testing.assert_frame_equal(report_table(got), report_table(serial))


def test_ray_cluster_without_a_cluster_says_how_to_start_one(tmp_path):
    pytest.importorskip("ray")
    cmd = [sys.executable, "run.py", "-m", "limit=1", "hydra/launcher=ray_cluster",
           f"hydra.launcher.address=127.0.0.1:{_free_port()}",
           "tracker=none", f"hydra.sweep.dir={tmp_path / 'sweep'}"]  # fmt: skip
    env = {**os.environ, **THREADS, **RAY_ENV, "PYTHONPATH": str(REPO)}
    p = subprocess.run(cmd, cwd=REPO, env=env, capture_output=True, text=True, timeout=90)
    out = p.stdout + p.stderr
    assert p.returncode != 0
    assert "cannot connect to a Ray cluster at '127.0.0.1:" in out and "ray start --head" in out, out[-3000:]
