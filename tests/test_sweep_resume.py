"""A sweep resumed with a higher limit continues its members; the report counts each pair once (issue 42
item 3)."""

from __future__ import annotations

import os
import shutil
import subprocess
import sys
from pathlib import Path

import pandas as pd

REPO = Path(__file__).resolve().parents[1]


def sweep(*overrides: str, cwd: Path = REPO) -> subprocess.CompletedProcess:
    cmd = [sys.executable, "run.py", "-m", *overrides, "tracker=none", "progress=false"]
    env = {**os.environ, "PYTHONPATH": str(REPO)}
    return subprocess.run(cmd, cwd=REPO, env=env, capture_output=True, text=True, timeout=300)


def test_a_sweep_resumed_with_a_higher_limit_continues_its_members(tmp_path):
    s = tmp_path / "S"
    first = sweep("ratio=0.5,0.2", "limit=1", f"hydra.sweep.dir={s}")
    assert first.returncode == 0, first.stderr[-2000:]
    again = sweep("ratio=0.5,0.2", "limit=2", "resume=auto", f"hydra.sweep.dir={s}")
    assert again.returncode == 0, again.stderr[-2000:]
    members = sorted(p.name for p in s.iterdir() if (p / "results.jsonl").exists())
    assert members == ["0_ratio=0.5", "1_ratio=0.2"], members
    for m in members:
        assert len((s / m / "results.jsonl").read_text().splitlines()) == 2
    env = {**os.environ, "PYTHONPATH": str(REPO)}
    report = subprocess.run(
        [sys.executable, "-m", "fastmac_exp.report", str(s), "--no-plots"], cwd=REPO, env=env,
        capture_output=True, text=True,
    )  # fmt: skip
    assert report.returncode == 0, report.stderr[-2000:]
    agg = pd.read_csv(s / "report" / "report.csv")
    assert agg["pairs"].tolist() == [2, 2]


def test_the_report_counts_a_pair_of_two_members_of_one_configuration_once(tmp_path, caplog):
    """Member directories of an older version named by limit (0_limit=3,... and 0_limit=4,...): the
    report merges them, with a warning, instead of counting their common pairs twice."""
    from fastmac_exp.report import make_report

    s = tmp_path / "S"
    first = sweep("ratio=0.5", "limit=1", f"hydra.sweep.dir={s}")
    assert first.returncode == 0, first.stderr[-2000:]
    (member,) = [p for p in s.iterdir() if (p / "results.jsonl").exists()]
    bigger = sweep("ratio=0.5", "limit=2", f"hydra.sweep.dir={tmp_path / 'T'}")
    assert bigger.returncode == 0, bigger.stderr[-2000:]
    (other,) = [p for p in (tmp_path / "T").iterdir() if (p / "results.jsonl").exists()]
    shutil.move(other, s / "0_limit=2,ratio=0.5")
    res = make_report(s, plots=False, snapshots=0)
    assert res["aggregate"]["pairs"].tolist() == [2]
    assert "hold one configuration (only limit differs): 1 repeated pair(s) counted once" in caplog.text
