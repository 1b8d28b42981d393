"""What a user sees on the console: failure reasons in the summary, non-zero exit codes for runs that
cannot work, clean messages for configuration errors (no Hydra traceback)."""

from __future__ import annotations

import os
import subprocess
import sys
from pathlib import Path

REPO = Path(__file__).resolve().parents[1]


def run(*overrides: str, tmp: Path) -> subprocess.CompletedProcess:
    cmd = [
        sys.executable,
        "run.py",
        *overrides,
        "tracker=none",
        "progress=false",
        f"hydra.run.dir={tmp / 'run'}",
    ]
    env = {**os.environ, "PYTHONPATH": str(REPO)}
    return subprocess.run(cmd, cwd=REPO, env=env, capture_output=True, text=True, timeout=120)


def test_every_pair_failed_exits_non_zero_and_says_why(tmp_path):
    p = run("dataset=pairs", "dataset.source=nosuch_a.ply", "dataset.target=nosuch_b.ply", tmp=tmp_path)
    assert p.returncode == 1, p.stderr[-2000:]
    out = p.stdout + p.stderr
    assert "failed x1: InputError: point cloud file not found: nosuch_a.ply" in out
    assert "every pair failed" in out


def test_config_value_errors_exit_2_with_our_message(tmp_path):
    p = run("dataset.family=kiti", tmp=tmp_path)
    out = p.stdout + p.stderr
    assert p.returncode == 2
    assert "family must be one of" in out and "Error in call to target" not in out
    p = run("dataset.limit=0", tmp=tmp_path)
    assert p.returncode == 2 and "dataset.limit must be >= 1" in p.stdout + p.stderr
