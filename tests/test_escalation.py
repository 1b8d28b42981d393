"""register()'s escalation (issue 48 items 3-4): the loop's rules on stand-in attempts, then the facade on
correspondences and clouds whose first try is not trusted."""

from __future__ import annotations

import numpy as np
import pytest

from fastmac_exp import register
from fastmac_exp.errors import InputError
from fastmac_exp.escalation import STEPS, Step, available_steps, escalate
from fastmac_exp.geometry.transforms import random_rotation
from fastmac_exp.types import Correspondences, RegistrationResult


def _result(trusted: bool, confidence: float, error: str = "") -> RegistrationResult:
    eye = np.eye(4)
    return RegistrationResult(pose=eye, pose_unrefined=eye, kept=np.zeros(0, int), clique=np.zeros(0, int),
                              trusted=trusted, confidence=confidence, error=error)  # fmt: skip


def test_the_loop_stops_at_the_first_trusted_step_and_says_what_each_cost():
    seen = []
    verdicts = {"a": (False, 0.5), "b": (True, 0.999), "c": (True, 1.0)}

    def attempt(step):
        seen.append(step.name)
        return _result(*verdicts[step.name])

    res = escalate(attempt, [Step("a"), Step("b"), Step("c")])
    assert seen == ["a", "b"] and res.step == "b" and res.trusted
    assert [s["step"] for s in res.escalation] == ["a", "b"]
    assert all(s["ms"] >= 0 for s in res.escalation)


def test_no_trusted_step_returns_the_most_confident_pose_untrusted():
    verdicts = {"a": (False, 0.5), "b": (False, 0.9), "c": (False, 0.0)}
    res = escalate(lambda s: _result(*verdicts[s.name]), [Step("a"), Step("b"), Step("c")])
    assert res.step == "b" and not res.trusted and len(res.escalation) == 3
    # a failed step (no pose) never beats a pose
    res = escalate(lambda s: _result(False, 0.0, "no clique") if s.name == "b" else _result(False, 0.0),
                   [Step("a"), Step("b")])  # fmt: skip
    assert res.step == "a"


def test_the_budget_stops_new_steps_and_says_so():
    res = escalate(lambda s: _result(False, 0.1), [Step("a"), Step("b")], budget_s=0.0)
    assert res.step == "a"
    assert res.escalation[1]["step"] == "b" and "budget" in res.escalation[1]["error"]


def test_the_steps_are_ordered_by_cost_and_the_describing_ones_need_clouds():
    names = [s.name for s in STEPS]
    assert names[:3] == ["first", "samples_auto", "mac_all"] and names[-1] == "learned"
    corr_steps = [s.name for s in available_steps(clouds=False, fpfh=True)]
    assert corr_steps == ["first", "samples_auto", "mac_all"]
    other = [s.name for s in available_steps(clouds=True, fpfh=False)]
    assert "mutual" not in other and "finer_voxel" not in other and "mac_fixed_resolution" in other


def _scarce(n: int = 3000, inliers: int = 90, seed: int = 0):
    """Correspondences with 3 % inliers under a known pose."""
    rng = np.random.default_rng(seed)
    gt = np.eye(4)
    gt[:3, :3], gt[:3, 3] = random_rotation(rng), [0.4, -0.2, 0.3]
    src = rng.uniform(0, 3, (n, 3))
    tgt = rng.uniform(0, 3, (n, 3))
    tgt[:inliers] = src[:inliers] @ gt[:3, :3].T + gt[:3, 3] + rng.normal(0, 0.01, (inliers, 3))
    return Correspondences(src, tgt), gt


def test_register_escalates_from_a_sampler_that_misses_the_inliers_to_mac_on_every_match():
    """random@1 % keeps ~1 of the 90 inliers: no trusted pose; samples=auto is refused for the random
    sampler (recorded, not raised); MAC on every correspondence finds the pose and trusts it."""
    corr, gt = _scarce()
    first = register(corr, sampler="random", ratio=0.01, escalate="off")
    assert not first.trusted
    res = register(corr, sampler="random", ratio=0.01)
    assert res.trusted and res.step == "mac_all"
    steps = [s["step"] for s in res.escalation]
    assert steps == ["first", "samples_auto", "mac_all"]
    assert res.escalation[1]["error"]  # random has no samples=auto
    assert np.abs(res.pose - gt).max() < 0.05
    # the kept step's stages and the steps not kept ("escalation") add up to the call's end_to_end
    t = res.timings
    assert t["escalation"] > 0
    assert sum(v for k, v in t.items() if k not in ("total", "end_to_end")) == pytest.approx(t["end_to_end"])


def test_a_trusted_first_try_does_not_escalate():
    corr, gt = _scarce(n=1000, inliers=200)
    res = register(corr)
    assert res.trusted and res.step == "first" and len(res.escalation) == 1


def test_bad_escalation_arguments_are_refused():
    corr, _ = _scarce(n=200, inliers=50)
    with pytest.raises(InputError, match="escalate must be one of"):
        register(corr, escalate="always")
    with pytest.raises(InputError, match="budget_s"):
        register(corr, budget_s=-1)
    with pytest.raises(InputError, match="unknown option"):  # the user's own mistake is raised, not escalated
        register(corr, sampler_ratio=0.3)


def test_the_default_descriptors_options_need_no_name_and_clouds_escalate_past_their_graph():
    """register(src, tgt, mutual=True): FPFH's option without descriptor="fpfh" (it was refused)."""
    import tempfile
    from pathlib import Path

    from tests.test_cli import _blob_pair

    with tempfile.TemporaryDirectory() as d:
        s, t, gt = _blob_pair(Path(d))
        src, tgt = np.load(s), np.load(t)
    res = register(src, tgt, mutual=True, escalate="off")
    assert res.ok and res.trusted
    assert np.abs(res.pose - gt).max() < 0.1


def test_run_py_escalates_an_untrusted_pair_and_its_row_says_how(tmp_path):
    """run.py escalate=auto on two unrelated clouds: no step is trusted; the row names the step whose pose
    it kept and lists every step, tried or stopped by the budget (which steps fit in it depends on the
    machine, so only the set is checked); escalate=off (the default) keeps the first try alone."""
    import json

    import pandas as pd

    from tests.test_cli import run

    rng = np.random.default_rng(0)
    np.save(tmp_path / "a.npy", rng.uniform(0, 3, (20000, 3)))
    np.save(tmp_path / "b.npy", rng.uniform(0, 3, (20000, 3)))
    keys = ("dataset=pairs", f"dataset.source={tmp_path / 'a.npy'}", f"dataset.target={tmp_path / 'b.npy'}")
    p = run(*keys, "escalate=auto", "escalate_budget_s=1", tmp=tmp_path)
    assert p.returncode == 0, p.stderr[-2000:]
    row = pd.read_csv(tmp_path / "run" / "results.csv").iloc[0]
    assert not bool(row["trusted"])
    steps = json.loads(row["escalation"])
    names = [s["step"] for s in steps]
    assert names[0] == "first" and set(names) == {s.name for s in available_steps(clouds=True, fpfh=True)}
    assert row["escalation_step"] in names and row["t_escalation_ms"] > 0
    assert all(s["ms"] > 0 or "budget" in s["error"] for s in steps)
    p = run(*keys, tmp=tmp_path / "off")
    assert p.returncode == 0, p.stderr[-2000:]
    assert "escalation_step" not in pd.read_csv(tmp_path / "off" / "run" / "results.csv").columns
    p = run(*keys, "escalate=sometimes", tmp=tmp_path / "bad")
    assert p.returncode == 2 and "escalate must be auto or off" in p.stdout + p.stderr
