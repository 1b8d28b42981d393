"""workers above the cores are capped with a word, and rows say when their timings were taken
oversubscribed (issue 42 item 8). The runs are pinned to one core (taskset), so the test means the same
on any machine."""

from __future__ import annotations

import os
import shutil
import subprocess
import sys
from pathlib import Path

import pandas as pd
import pytest

REPO = Path(__file__).resolve().parents[1]
pytestmark = pytest.mark.skipif(shutil.which("taskset") is None, reason="needs taskset (util-linux)")


def _one_core(*args: str) -> subprocess.CompletedProcess:
    cmd = ["taskset", "-c", "0", sys.executable, "run.py", *args, "tracker=none", "progress=false"]
    env = {**os.environ, "PYTHONPATH": str(REPO)}
    return subprocess.run(cmd, cwd=REPO, env=env, capture_output=True, text=True, timeout=300)


def test_workers_above_the_cores_are_capped_and_said(tmp_path):
    p = _one_core("workers=64", "limit=2", f"hydra.run.dir={tmp_path / 'run'}")
    assert p.returncode == 0, p.stderr[-2000:]
    out = p.stdout + p.stderr
    assert "workers=64 is more than the 1 core(s) this run may use: capped at 1" in out
    rows = pd.read_csv(tmp_path / "run" / "results.csv")
    assert rows["workers"].tolist() == [1, 1] and not rows["oversubscribed"].any()


def test_parallel_sweep_members_on_too_few_cores_mark_their_rows(tmp_path):
    p = _one_core(
        "-m", "hydra/launcher=local", "ratio=0.5,0.2", "limit=1", f"hydra.sweep.dir={tmp_path / 'S'}"
    )
    assert p.returncode == 0, p.stderr[-2000:]
    assert "2 sweep members run at once with 1 worker(s) each on 1 core(s)" in p.stdout + p.stderr
    members = sorted((tmp_path / "S").glob("*/results.csv"))
    assert len(members) == 2
    for member in members:
        assert pd.read_csv(member)["oversubscribed"].tolist() == [True]
