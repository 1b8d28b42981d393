"""The project's own metric functions: RE/TE and success at the thresholds' boundaries (spec 6), the honest
and the reference protocol (spec 5.4), and the run summary."""

from __future__ import annotations

import numpy as np
import pandas as pd
import pytest

from fastmac_exp.geometry.metrics import pose_errors, summarize
from fastmac_exp.pipeline import evaluate
from fastmac_exp.types import Pair, RegistrationResult


def pose(angle_deg: float = 0.0, t=(0.0, 0.0, 0.0)) -> np.ndarray:
    """A rotation about z by angle_deg, then a translation t (metres)."""
    a = np.deg2rad(angle_deg)
    p = np.eye(4)
    p[:2, :2] = [[np.cos(a), -np.sin(a)], [np.sin(a), np.cos(a)]]
    p[:3, 3] = t
    return p


def test_errors_are_measured_in_degrees_and_centimetres():
    e = pose_errors(pose(10.0, (0.03, 0.04, 0.0)), np.eye(4), 15.0, 0.3)
    assert e.re_deg == pytest.approx(10.0, abs=1e-9)
    assert e.te_cm == pytest.approx(5.0, abs=1e-9)
    assert e.success


@pytest.mark.parametrize(
    ("angle", "te_m", "success"),
    [
        (14.999, 0.0, True),
        (15.001, 0.0, False),
        (0.0, 0.2999, True),
        (0.0, 0.3001, False),
        (14.999, 0.2999, True),
    ],
)
def test_success_thresholds_boundaries(angle, te_m, success):
    assert pose_errors(pose(angle, (te_m, 0, 0)), np.eye(4), 15.0, 0.30).success is success


@pytest.mark.parametrize(
    ("angle", "te_m", "success"), [(4.99, 0.59, True), (5.01, 0.1, False), (1, 0.61, False)]
)
def test_kitti_thresholds(angle, te_m, success):
    assert pose_errors(pose(angle, (0, te_m, 0)), np.eye(4), 5.0, 0.60).success is success


def test_gt_off_orthonormal_does_not_floor_the_rotation_error():
    gt = np.eye(4)
    gt[:3, :3] *= 1.0005  # like 3DMatch gt.log entries
    assert pose_errors(np.eye(4), gt, 15.0, 0.3).re_deg < 1e-6


def _result(refined: np.ndarray, unrefined: np.ndarray) -> RegistrationResult:
    return RegistrationResult(pose=refined, pose_unrefined=unrefined, kept=np.arange(3), clique=np.arange(3))


@pytest.mark.parametrize(
    ("refined", "unrefined", "honest", "reference"),
    [
        (pose(1.0), pose(1.0), True, True),
        (pose(20.0), pose(1.0), False, True),  # the GT-assisted rule also accepts the unrefined pose
        (pose(1.0), pose(20.0), True, True),
        (pose(20.0), pose(25.0), False, False),
    ],
)
def test_honest_and_reference_protocols(refined, unrefined, honest, reference):
    pair = Pair(name="p", gt=np.eye(4), family="3dmatch")
    for protocol, want in (("honest", honest), ("reference", reference)):
        verdict = evaluate(pair, _result(refined, unrefined), protocol)
        assert verdict.success is want, protocol
        # RE/TE are the refined pose's under both protocols (as the reference reports them)
        assert verdict.re_deg == pytest.approx(pose_errors(refined, np.eye(4), 15, 0.3).re_deg)


def test_summary_counts_failed_pairs_as_not_registered():
    table = pd.DataFrame(
        {
            "success": [True, False, None, True],
            "error": ["", "", "RegistrationFailed: no edge", ""],
            "re_deg": [1.0, 30.0, np.nan, 3.0],
            "te_cm": [2.0, 90.0, np.nan, 4.0],
            "t_total_ms": [10.0, 20.0, np.nan, 30.0],
        }
    )
    s = summarize(table)
    assert s["pairs"] == 4 and s["failed"] == 1 and s["registered"] == 2
    assert s["RR"] == pytest.approx(0.5)
    assert s["RE_deg"] == pytest.approx(2.0) and s["TE_cm"] == pytest.approx(3.0)  # successful pairs only
    assert s["median_total_ms"] == pytest.approx(20.0)
