"""Reliability: degenerate input, interrupted runs resumed with nothing lost or duplicated."""

from __future__ import annotations

import json
import os
import signal
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

from fastmac_exp.backends.python_mac import PythonBackend
from fastmac_exp.errors import InputError, RegistrationFailed
from fastmac_exp.params import mac_params_for
from fastmac_exp.pipeline import register_correspondences
from fastmac_exp.run.results import read_rows
from fastmac_exp.samplers import NoSampler
from fastmac_exp.types import Correspondences
from tests.children import cpu_seconds, exits_within_cpu, has_rows, popen, spent, wait_until

REPO = Path(__file__).resolve().parents[1]


def _run(corr):
    return register_correspondences(corr, mac_params_for("3dmatch", "fpfh"), NoSampler(), PythonBackend())


@pytest.mark.parametrize("n", [0, 1, 2])
def test_too_few_correspondences(n):
    with pytest.raises(RegistrationFailed, match="at least 3"):
        _run(Correspondences(np.zeros((n, 3)), np.zeros((n, 3))))


def test_duplicated_points_are_refused():
    pts = np.tile([[1.0, 2.0, 3.0]], (20, 1))
    with pytest.raises(RegistrationFailed, match="duplicated or collinear"):
        _run(Correspondences(pts, pts + 1.0))


def test_collinear_points_are_refused():
    pts = np.outer(np.linspace(0, 1, 30), [1.0, 2.0, 0.5])
    with pytest.raises(RegistrationFailed, match="collinear"):
        _run(Correspondences(pts, pts + [0.1, 0, 0]))


@pytest.mark.parametrize("bad", [np.nan, np.inf, 1e12])
def test_non_finite_or_absurd_coordinates(bad):
    pts = np.random.default_rng(0).uniform(0, 1, (10, 3))
    tgt = pts.copy()
    tgt[4, 2] = bad
    with pytest.raises(InputError, match="row 4"):
        _run(Correspondences(pts, tgt))


def test_shape_errors_are_clear():
    with pytest.raises(InputError, match=r"shape \(N, 3\)"):
        Correspondences(np.zeros((4, 2)), np.zeros((4, 2)))
    with pytest.raises(InputError, match="same number of rows"):
        Correspondences(np.zeros((4, 3)), np.zeros((5, 3)))


SCRIPT = """
import sys, threading
sys.path.insert(0, {repo!r})
from omegaconf import OmegaConf
from fastmac_exp.run.experiment import run_experiment
from tests import conftest

class StopsAtFour(conftest.ListDataset):
    # the first run blocks for good loading pair 4: the kill lands after exactly 4 rows, however loaded
    # the machine is
    def load(self, i):
        if i >= 4 and {block!r}:
            threading.Event().wait()
        return super().load(i)
conftest.StopsAtFour = StopsAtFour
cfg = OmegaConf.create({{
    "dataset": {{"_target_": "tests.conftest.StopsAtFour", "num_pairs": 12, "n": 200}},
    "descriptor": {{"_target_": "fastmac_exp.descriptors.precomputed.PrecomputedDescriptor"}},
    "sampler": {{"_target_": "fastmac_exp.samplers.RandomSampler"}},
    "backend": {{"_target_": "fastmac_exp.backends.python_mac.PythonBackend"}},
    "ratio": 0.8, "seed": 0, "protocol": "honest", "fail_fast": False, "resume": {resume!r},
    "workers": 1, "progress": False, "graph": {{}}, "mac": {{}}, "tracker": {{}},
}})
run_experiment(cfg, {run_dir!r})
"""


@pytest.mark.signals
def test_sigkill_mid_run_then_resume_gives_one_row_per_pair(tmp_path):
    run_dir = tmp_path / "run"
    code = SCRIPT.format(repo=str(REPO), resume=None, run_dir=str(run_dir), block=True)
    proc = subprocess.Popen([sys.executable, "-c", code], cwd=REPO, start_new_session=True)
    log = run_dir / "results.jsonl"
    try:
        wait_until(has_rows(log, 4), proc, "4 rows")
    finally:
        os.killpg(proc.pid, signal.SIGKILL)
        proc.wait()
    done_before = read_rows(log)
    assert len(done_before) == 4
    finished = {r["pair"]: r for r in done_before}

    code = SCRIPT.format(repo=str(REPO), resume=str(run_dir), run_dir=str(tmp_path / "unused"), block=False)
    subprocess.run([sys.executable, "-c", code], cwd=REPO, check=True, timeout=120)
    rows = [json.loads(line) for line in log.read_text().splitlines()]
    names = [r["pair"] for r in rows]
    assert sorted(names) == [f"pair_{i:03d}" for i in range(12)]  # no gaps, no duplicates
    for r in rows:  # pairs finished before the kill were kept, not recomputed
        if r["pair"] in finished:
            assert r["t_total_ms"] == finished[r["pair"]]["t_total_ms"]
    summary = json.loads((run_dir / "summary.json").read_text())
    assert summary["pairs"] == 12 and summary["complete"]


HARD_SCRIPT = """
import sys
import numpy as np
sys.path.insert(0, {repo!r})
from omegaconf import OmegaConf
from fastmac_exp.run.experiment import run_experiment
from fastmac_exp.types import Correspondences, Pair
from tests import conftest

class EasyThenHard(conftest.ListDataset):
    # pair 1: 300 inliers whose noise makes about half of their pairs compatible (KITTI kernel): a
    # random-graph-like core with an astronomical number of maximal cliques
    def load(self, i):
        if i == 0:
            return super().load(i)
        rng = np.random.default_rng(1)
        src = rng.uniform(0, 40, (300, 3))
        tgt = src + rng.normal(scale=0.08, size=(300, 3))
        return Pair(name="hard", gt=np.eye(4), correspondences=Correspondences(src, tgt), family="kitti")
conftest.EasyThenHard = EasyThenHard
cfg = OmegaConf.create({{
    "dataset": {{"_target_": "tests.conftest.EasyThenHard", "num_pairs": 2, "n": 200}},
    "descriptor": {{"_target_": "fastmac_exp.descriptors.precomputed.PrecomputedDescriptor"}},
    "sampler": {{"_target_": "fastmac_exp.samplers.NoSampler"}},
    "backend": {{"_target_": "fastmac_exp.backends.cpp.CppBackend"}},
    "ratio": 1.0, "seed": 0, "protocol": "honest", "fail_fast": False, "resume": None,
    "workers": 1, "progress": False, "graph": {{}}, "tracker": {{}},
    "mac": {{"search": "enumerate", "reduction": False, "max_cliques": 0, "time_limit_s": 0}},
}})
run_experiment(cfg, {run_dir!r})
"""


@pytest.mark.signals
def test_ctrl_c_inside_a_clique_search_stops_the_run_and_keeps_finished_pairs(tmp_path):
    """SIGINT while the C++ core enumerates an astronomically large clique set (it cannot finish): the
    search stops, the finished pair is on disk, the process exits with KeyboardInterrupt."""
    run_dir = tmp_path / "run"
    code = HARD_SCRIPT.format(repo=str(REPO), run_dir=str(run_dir))
    proc = popen([sys.executable, "-c", code], cwd=REPO, stderr=subprocess.PIPE, text=True)
    log = run_dir / "results.jsonl"
    try:
        wait_until(has_rows(log), proc, "the first row")
        wait_until(spent(proc, 1.0), proc, "the signal")  # a second of CPU into the hard pair's search
        at_signal = cpu_seconds(proc.pid)
        proc.send_signal(signal.SIGINT)
        exits_within_cpu(proc, at_signal, 3.0)  # without the signal, no end
        text = proc.stderr.read()
    finally:
        if proc.poll() is None:
            proc.kill()
    assert proc.returncode != 0
    assert "KeyboardInterrupt" in text and "interrupted:" in text, text[-2000:]
    rows = read_rows(log)
    assert [r["pair"] for r in rows] == ["pair_000"]
