"""Trackers on hand-built PairOutcomes: the .rrd read back with rerun's own reader, the offline wandb run
read back from its transaction log, and the Hydra multirun grouping."""

from __future__ import annotations

import math
from pathlib import Path

import numpy as np
import pandas as pd
import pytest

from fastmac_exp.pipeline import PairOutcome
from fastmac_exp.run.results import to_table
from fastmac_exp.samplers import SampleResult
from fastmac_exp.types import Correspondences, Pair, RegistrationResult

ROOT = Path(__file__).resolve().parents[1]


def _rot_z(deg: float) -> np.ndarray:
    a = np.deg2rad(deg)
    T = np.eye(4)
    T[:2, :2] = [[np.cos(a), -np.sin(a)], [np.sin(a), np.cos(a)]]
    T[:3, 3] = [0.3, -0.1, 0.05]
    return T


def make_outcome(
    index: int, name: str, *, clouds: bool = True, failed: bool = False, n: int = 40
) -> PairOutcome:
    """A small, fully hand-made outcome: n correspondences, the first half GT inliers."""
    rng = np.random.default_rng(index)
    gt = _rot_z(10.0 + index)
    src = rng.uniform(-1, 1, (n, 3))
    tgt = src @ gt[:3, :3].T + gt[:3, 3]
    tgt[n // 2 :] += rng.uniform(0.5, 1.0, (n - n // 2, 3))  # outliers
    labels = np.arange(n) < n // 2
    corr = Correspondences(src=src, tgt=tgt, labels=labels)
    row = {
        "index": index, "pair": name, "dataset": "toy", "descriptor": "oracle", "sampler": "highpass",
        "ratio": 0.5, "backend": "python", "seed": 0, "protocol": "honest", "error": "",
    }  # fmt: skip
    if failed:
        row.update(error="RuntimeError: boom", success=False)
        return PairOutcome(row=row)
    pair = Pair(
        name=name,
        gt=gt,
        src_cloud=rng.uniform(-1, 1, (300, 3)) if clouds else None,
        tgt_cloud=rng.uniform(-1, 1, (250, 3)) if clouds else None,
        voxel_size=0.05,
    )
    kept = np.arange(0, n, 2)
    clique = np.arange(0, n // 2, 2)
    result = RegistrationResult(
        pose=gt, pose_unrefined=gt, kept=kept, clique=clique, score=3.0, n_cliques=5, n_selected=2,
        n_edges=50, timings={"sampling": 0.5, "graph": 1.0, "cliques": 2.0, "selection": 0.25, "pose": 0.75,
                             "total": 4.5},
    )  # fmt: skip
    sample = SampleResult(indices=kept, scores=np.ones(n))
    row.update(
        n_in=n, n_kept=len(kept), inlier_ratio_in=0.5, inlier_ratio_kept=0.5, clique_size=len(clique),
        clique_inliers=len(clique), re_deg=0.1 * (index + 1), te_cm=1.0 + index, success=True,
        t_describe_ms=10.0 + index, **{f"t_{k}_ms": v for k, v in result.timings.items()},
    )  # fmt: skip
    return PairOutcome(row=row, pair=pair, corr=corr, result=result, sample=sample)


def run_tracker(tracker, run_dir: Path, outcomes: list[PairOutcome]) -> tuple[pd.DataFrame, dict]:
    names = [o.row["pair"] for o in outcomes]
    tracker.start({"ratio": 0.5, "sampler": {"name": "highpass"}, "seed": 0}, run_dir, names)
    for o in outcomes:
        tracker.log_pair(o)
    table = to_table([o.row for o in outcomes])
    summary = {"pairs": len(outcomes), "RR": 2 / 3, "RE_deg": 0.15, "complete": True, "sampler": "highpass"}
    tracker.finish(table, summary)
    return table, summary


# -- rerun ------------------------------------------------------------------------------------------------
@pytest.fixture
def strict_rerun():
    rr = pytest.importorskip("rerun")
    was = rr.strict_mode()
    rr.set_strict_mode(True)  # API misuse raises instead of logging a warning
    yield rr
    rr.set_strict_mode(was)


def _rrd_contents(path: Path) -> dict[str, set[str]]:
    """entity path -> archetype names, read with rerun's own RRD reader."""
    from rerun.chunk import RrdReader

    out: dict[str, set[str]] = {}
    for chunk in RrdReader(path).stream().to_chunks():
        batch = chunk.to_record_batch()
        kinds = {
            (f.metadata or {}).get(b"rerun:archetype", b"").decode().rsplit(".", 1)[-1]
            for f in batch.schema
            if (f.metadata or {}).get(b"rerun:kind") == b"data"
        }
        out.setdefault(chunk.entity_path, set()).update(k for k in kinds if k)
    return out


def _chunks(path: Path, entity: str) -> list:
    from rerun.chunk import RrdReader

    return [c for c in RrdReader(path).stream().to_chunks() if c.entity_path == entity]


def _column(path: Path, entity: str, column: str) -> list:
    """The first row of `column` at `entity` (static geometry is logged once)."""
    chunks = [c for c in _chunks(path, entity) if column in c.to_record_batch().schema.names]
    assert chunks, (entity, column)
    return chunks[0].to_record_batch().column(column).to_pylist()[0]


def test_rerun_per_run_recording(tmp_path, strict_rerun):
    from fastmac_exp.trackers.rerun_tracker import STAGE_BARS, RerunTracker

    outcomes = [
        make_outcome(0, "scene/a"),
        make_outcome(1, "b", clouds=False),
        make_outcome(2, "c", failed=True),
        make_outcome(3, "d"),
    ]
    tracker = RerunTracker(per="run", max_pairs=2, max_points=100)
    run_tracker(tracker, tmp_path, outcomes)
    rrd = tmp_path / "recording.rrd"
    assert rrd.is_file() and rrd.stat().st_size > 0
    got = _rrd_contents(rrd)
    a = "/pairs/" + strict_rerun.escape_entity_path_part("scene/a")
    expected = {
        "/": "AnnotationContext",
        "/legend": "TextDocument",
        f"{a}/matches/source": "Points3D",
        f"{a}/matches/target": "Points3D",
        f"{a}/matches/all": "LineStrips3D",
        f"{a}/matches/sampled": "LineStrips3D",
        f"{a}/matches/clique": "LineStrips3D",
        f"{a}/registration": "TransformAxes3D",
        f"{a}/registration/target": "Points3D",
        f"{a}/registration/source_before/source": "Points3D",
        f"{a}/registration/estimate": "Transform3D",
        f"{a}/registration/estimate/source": "Points3D",
        f"{a}/registration/gt": "Transform3D",
        f"{a}/registration/gt/source": "Points3D",
        f"{a}/stage_ms": "TextDocument",
        f"{a}/info": "TextDocument",
        "/pairs/b/matches/all": "LineStrips3D",  # no clouds: correspondences stand in
        "/pairs/b/registration/estimate/source": "Points3D",
        "/metrics/time_ms/graph": "Scalars",
        "/metrics/time_ms/total": "Scalars",
        "/metrics/describe_ms": "Scalars",
        "/metrics/re_deg": "Scalars",
        "/metrics/te_cm": "Scalars",
        "/metrics/ratio/running_rr": "Scalars",
        "/metrics/ratio/success": "Scalars",
        "/log": "TextLog",
    }
    for entity, archetype in expected.items():
        assert archetype in got.get(entity, set()), (entity, got.get(entity))
    assert (
        "TransformAxes3D" in got[f"{a}/registration/estimate"]
        and "TransformAxes3D" in got[f"{a}/registration/gt"]
    )
    assert "/metrics/time_ms/describe" not in got  # describe has its own plot: it dwarfs the other stages
    assert not any(e.startswith("/pairs/d") for e in got)  # max_pairs=2 (the failed pair has no geometry)
    assert tracker.recorded == [a.lstrip("/"), "pairs/b"]

    # the scalars of every pair sit on the `pair` timeline, at the pair indices
    chunks = _chunks(rrd, "/metrics/time_ms/graph")
    seq = sorted(v for c in chunks if not c.is_static for v in c.to_record_batch().column("pair").to_pylist())
    assert seq == [0, 1, 3]
    # a pair's geometry is static, so the second pair's views are not empty with the timeline at pair 0
    for entity in (f"{a}/matches/clique", "/pairs/b/matches/sampled", "/pairs/b/registration/target"):
        assert all(c.is_static for c in _chunks(rrd, entity)), entity
    # the pair's own stage times, describe left out, in STAGE_BARS order, each line named
    text = _column(rrd, f"{a}/stage_ms", "TextDocument:text")
    text = text[0] if isinstance(text, list) else text
    rows = [line.split("|")[1:3] for line in text.splitlines()[2:]]
    assert [r[0].strip() for r in rows] == list(STAGE_BARS) and "describe" not in text
    want = [outcomes[0].row[f"t_{s}_ms"] for s in STAGE_BARS]
    assert np.allclose([float(r[1]) for r in rows], want, atol=0.05)
    assert text.count("█") > 0
    from rerun.chunk import RrdReader

    assert len(RrdReader(rrd).blueprints()) == 1  # the default layout travels in the file


def test_rerun_lines_classes_and_hover_ids(tmp_path, strict_rerun):
    """Sampled lines are the kept set minus the clique; the clique has its own class; GT outliers are
    thinned to max_outlier_lines and drawn thinner; every line's hover label names its correspondence."""
    from fastmac_exp.trackers.rerun_tracker import CLIQUE, INLIER, OUTLIER, RerunTracker

    n = 400
    outcome = make_outcome(0, "a", n=n)  # first half inliers; kept = even ids
    outcome.result.clique = np.arange(0, 20, 2)
    tracker = RerunTracker(max_pairs=1, max_points=10_000, max_outlier_lines=30)
    run_tracker(tracker, tmp_path, [outcome])
    rrd = tmp_path / "recording.rrd"
    ids = {
        e: np.asarray(_column(rrd, f"/pairs/a/matches/{e}", "correspondence_id"))
        for e in ("all", "sampled", "clique")
    }
    cls = {e: np.asarray(_column(rrd, f"/pairs/a/matches/{e}", "LineStrips3D:class_ids")) for e in ids}
    labels = outcome.corr.labels
    # all: every inlier, 30 of the 200 outliers
    assert set(ids["all"][labels[ids["all"]]]) == set(range(n // 2))
    assert (~labels[ids["all"]]).sum() == 30
    # sampled: the kept ids without the clique, outliers thinned to 30
    kept = set(outcome.result.kept.tolist()) - set(outcome.result.clique.tolist())
    assert set(ids["sampled"]) <= kept
    assert {i for i in kept if labels[i]} <= set(ids["sampled"].tolist())
    assert (~labels[ids["sampled"]]).sum() == 30
    assert sorted(ids["clique"].tolist()) == sorted(outcome.result.clique.tolist())
    assert set(cls["clique"].tolist()) == {CLIQUE.id}
    assert np.array_equal(cls["sampled"], np.where(labels[ids["sampled"]], INLIER.id, OUTLIER.id))
    radii = np.asarray(_column(rrd, "/pairs/a/matches/sampled", "LineStrips3D:radii"))
    assert np.all(
        np.abs(radii[cls["sampled"] == OUTLIER.id]) < np.abs(radii[cls["sampled"] == INLIER.id]).min()
    )
    clique_r = np.abs(_column(rrd, "/pairs/a/matches/clique", "LineStrips3D:radii")).min()
    assert clique_r > np.abs(radii).max()
    tags = _column(rrd, "/pairs/a/matches/sampled", "LineStrips3D:labels")
    assert [int(t.split()[0][1:]) for t in tags] == ids["sampled"].tolist()
    assert all(("GT inlier" in t) == bool(labels[i]) for t, i in zip(tags, ids["sampled"], strict=True))
    assert all(" score 1" in t for t in tags)  # the sampler's scores (all 1.0 in this outcome)


@pytest.mark.parametrize(("family", "up", "expected"), [("kitti", None, "+z"), ("3dmatch", None, "-y"),
                                                        ("3dmatch", "+z", "+z")])  # fmt: skip
def test_rerun_up_axis(tmp_path, strict_rerun, family, up, expected):
    from fastmac_exp.trackers.rerun_tracker import UP_AXES, RerunTracker, match_offset

    outcome = make_outcome(0, "a")
    outcome.pair.family = family
    run_tracker(RerunTracker(max_pairs=1, up=up), tmp_path, [outcome])
    rrd = tmp_path / "recording.rrd"
    want = getattr(strict_rerun.ViewCoordinates, UP_AXES[expected]).as_arrow_array().to_pylist()[0]
    for view in ("matches", "registration"):
        assert _column(rrd, f"/pairs/a/{view}", "ViewCoordinates:xyz") == [want]
    # flat z-up scans are stacked (target above the source); anything else sits beside it along +x
    src, tgt = outcome.pair.src_cloud, outcome.pair.tgt_cloud
    off = match_offset(src, tgt, expected)
    axis = 2 if expected == "+z" else 0
    assert off[axis] > 0 and np.count_nonzero(off) == 1
    assert (tgt[:, axis] + off[axis]).min() > src[:, axis].max()


def test_rerun_bad_up_axis_is_refused():
    from fastmac_exp.trackers.rerun_tracker import RerunTracker

    with pytest.raises(ValueError, match="tracker.rerun.up"):
        RerunTracker(up="up")


def test_rerun_per_pair_files(tmp_path, strict_rerun):
    from fastmac_exp.trackers.rerun_tracker import RerunTracker

    outcomes = [make_outcome(i, f"pair/{i}") for i in range(3)]
    tracker = RerunTracker(per="pair", max_pairs=2, max_points=50)
    run_tracker(tracker, tmp_path, outcomes)
    files = sorted((tmp_path / "rerun").glob("*.rrd"))
    assert [f.name for f in files] == ["pair_0.rrd", "pair_1.rrd"]
    got = _rrd_contents(files[1])
    root = "/pairs/" + strict_rerun.escape_entity_path_part("pair/1")
    assert "Points3D" in got[f"{root}/registration/gt/source"]
    assert not any(e.startswith("/pairs/" + strict_rerun.escape_entity_path_part("pair/0")) for e in got)


def test_rerun_cli_verify(tmp_path, strict_rerun):
    """`rerun rrd verify` (the CLI that ships with the SDK) accepts the file."""
    import shutil
    import subprocess

    from fastmac_exp.trackers.rerun_tracker import RerunTracker

    exe = shutil.which("rerun")
    if exe is None:
        pytest.skip("rerun CLI not on PATH")
    run_tracker(RerunTracker(max_pairs=1, max_points=50), tmp_path, [make_outcome(0, "a")])
    cmd = [exe, "rrd", "verify", str(tmp_path / "recording.rrd")]
    proc = subprocess.run(cmd, capture_output=True, text=True, timeout=60)
    assert proc.returncode == 0, proc.stderr


# -- wandb ------------------------------------------------------------------------------------------------
def test_wandb_offline_run(tmp_path, monkeypatch):
    pytest.importorskip("wandb")
    from fastmac_exp.trackers.wandb_tracker import WandbTracker, find_offline_runs, read_offline_run

    monkeypatch.setenv("WANDB_MODE", "offline")  # belt and braces: never the network in tests
    outcomes = [make_outcome(0, "a"), make_outcome(1, "b"), make_outcome(2, "c", failed=True)]
    tracker = WandbTracker(group="g1", name="job-1", tags=["test"])
    run_tracker(tracker, tmp_path, outcomes)
    runs = find_offline_runs(tmp_path)
    assert len(runs) == 1 and runs[0].name.startswith("offline-run-")
    assert tracker.run_path == runs[0]
    data = read_offline_run(runs[0], wait_s=10)
    assert data["run"]["project"] == "fastmac-exp"
    assert data["run"]["group"] == "g1" and data["run"]["name"] == "job-1" and data["run"]["tags"] == ["test"]
    assert data["config"]["ratio"] == 0.5 and data["config"]["sampler"] == {"name": "highpass"}
    assert data["config"]["run_dir"] == str(tmp_path)
    steps = [h for h in data["history"] if "pair/index" in h]
    assert [h["pair/index"] for h in steps] == [0, 1, 2]
    assert steps[0]["pair/re_deg"] == pytest.approx(0.1) and steps[1]["pair/te_cm"] == pytest.approx(2.0)
    assert steps[0]["time/graph_ms"] == pytest.approx(1.0) and steps[1]["time/describe_ms"] == pytest.approx(
        11
    )
    assert [h["running/RR"] for h in steps] == pytest.approx([1.0, 1.0, 2 / 3])
    assert steps[2]["pair/failed"] == 1 and "pair/re_deg" not in steps[2]
    table_step = [h for h in data["history"] if "results/_type" in h]
    assert (
        table_step and table_step[0]["results/_type"] == "table-file" and table_step[0]["results/nrows"] == 3
    )
    assert data["summary"]["RR"] == pytest.approx(2 / 3) and data["summary"]["sampler"] == "highpass"
    assert data["exit_code"] == 0
    table_files = list(runs[0].glob("files/media/table/results_*.table.json"))
    assert len(table_files) == 1


def test_wandb_groups_hydra_multirun(tmp_path, monkeypatch):
    pytest.importorskip("wandb")
    from hydra import compose, initialize_config_dir
    from hydra.core.hydra_config import HydraConfig
    from hydra.types import RunMode
    from omegaconf import open_dict

    from fastmac_exp.trackers.wandb_tracker import (
        WandbTracker,
        find_offline_runs,
        hydra_context,
        read_offline_run,
    )

    monkeypatch.setenv("WANDB_MODE", "offline")
    with initialize_config_dir(config_dir=str(ROOT / "conf"), version_base="1.3"):
        cfg = compose("config", overrides=["ratio=0.1"], return_hydra_config=True)
    with open_dict(cfg):
        cfg.hydra.mode = RunMode.MULTIRUN
        cfg.hydra.sweep.dir = str(tmp_path / "sweep-2024")
        cfg.hydra.job.override_dirname = "ratio=0.1"
        cfg.hydra.job.num = 0
    HydraConfig.instance().set_config(cfg)
    try:
        ctx = hydra_context()
        assert ctx["multirun"] and ctx["override_dirname"] == "ratio=0.1"
        run_tracker(WandbTracker(), tmp_path / "job", [make_outcome(0, "a")])
    finally:
        HydraConfig.instance().cfg = None
    data = read_offline_run(find_offline_runs(tmp_path / "job")[0], wait_s=10)
    assert data["run"]["group"] == "sweep-2024" and data["run"]["name"] == "ratio=0.1"
    assert data["config"]["hydra"]["choices"]["sampler"] == "highpass"


def test_wandb_interrupted_run_exits_nonzero(tmp_path, monkeypatch):
    pytest.importorskip("wandb")
    from fastmac_exp.trackers.wandb_tracker import WandbTracker, find_offline_runs, read_offline_run

    monkeypatch.setenv("WANDB_MODE", "offline")
    tracker = WandbTracker(log_table=False)
    tracker.start({}, tmp_path, ["a", "b"])
    tracker.log_pair(make_outcome(0, "a"))
    tracker.finish(to_table([make_outcome(0, "a").row]), {"pairs": 1, "complete": False})
    data = read_offline_run(find_offline_runs(tmp_path)[0], wait_s=10)
    assert data["exit_code"] == 1 and not any("results/_type" in h for h in data["history"])


@pytest.mark.parametrize("module", ["wandb", "rerun"])
def test_missing_package_is_a_warning(module, monkeypatch, caplog, tmp_path):
    import builtins

    from fastmac_exp.trackers.rerun_tracker import RerunTracker
    from fastmac_exp.trackers.wandb_tracker import WandbTracker

    real_import = builtins.__import__

    def fake_import(name, *args, **kwargs):
        if name == module or name.startswith(module + "."):
            raise ImportError(f"No module named '{module}'")
        return real_import(name, *args, **kwargs)

    monkeypatch.setattr(builtins, "__import__", fake_import)
    with caplog.at_level("WARNING"):
        tracker = WandbTracker() if module == "wandb" else RerunTracker()
    assert f"{module} tracker disabled" in caplog.text
    run_tracker(tracker, tmp_path, [make_outcome(0, "a")])  # a no-op, no exception
    assert list(tmp_path.iterdir()) == []


def test_default_tracker_config_instantiates():
    """conf/tracker/default.yaml: wandb offline + rerun per run, built the way the experiment builds them."""
    from hydra import compose, initialize_config_dir

    from fastmac_exp.run.experiment import _make_trackers

    with initialize_config_dir(config_dir=str(ROOT / "conf"), version_base="1.3"):
        cfg = compose("config")
        none = compose("config", overrides=["tracker=none"])
    trackers = {t.name: t for t in _make_trackers(cfg)}
    assert set(trackers) == {"wandb", "rerun"}
    assert trackers["wandb"].mode == "offline"
    assert trackers["rerun"].per == "run" and trackers["rerun"].max_pairs == 4
    assert _make_trackers(none) == []


def test_helpers():
    from fastmac_exp.trackers.rerun_tracker import downsample, label_classes, safe_name, thin_outliers
    from fastmac_exp.trackers.wandb_tracker import _number

    pts = np.arange(30.0).reshape(10, 3)
    assert len(downsample(pts, 4)) == 4 and downsample(pts, 100) is pts
    assert label_classes(None, 2).tolist() == [0, 0]
    assert label_classes(np.array([True, False]), 2).tolist() == [1, 2]
    labels = np.arange(10) < 3
    thinned = thin_outliers(np.arange(10), labels, 2)
    assert thinned[:3].tolist() == [0, 1, 2] and len(thinned) == 5 and np.all(np.diff(thinned) > 0)
    assert thin_outliers(np.arange(10), labels, -1).tolist() == list(range(10))
    assert safe_name("scene/a b") == "scene_a_b"
    assert _number(True) == 1 and _number(float("nan")) is None and _number(pd.NA) is None
    assert _number(np.float32(2.5)) == 2.5 and math.isclose(_number(3), 3)


# -- headless snapshots of a recording --------------------------------------------------------------------
def test_snapshot_reads_back_what_the_recording_holds(tmp_path, strict_rerun):
    """read_pairs recovers the clouds, poses, line classes and up axis the tracker wrote (pair names
    unescaped), and render_pair draws a non-blank PNG."""
    from PIL import Image

    from fastmac_exp.trackers.rerun_snapshot import read_pairs, snapshot_recording
    from fastmac_exp.trackers.rerun_tracker import CLIQUE, RerunTracker

    outcome = make_outcome(0, "scene/a")
    outcome.pair.family = "kitti"
    outcome.result.pose = _rot_z(25.0)  # the estimate differs from the GT: both must come back
    run_tracker(RerunTracker(max_pairs=1, max_points=1000), tmp_path, [outcome])
    (geo,) = read_pairs(tmp_path / "recording.rrd")
    assert geo.name == "scene/a" and geo.up == (2, 1.0)
    assert np.allclose(geo.poses["gt"], outcome.pair.gt, atol=1e-6)
    assert np.allclose(geo.poses["estimate"], outcome.result.pose, atol=1e-6)
    assert np.allclose(geo.clouds["registration/target"], outcome.pair.tgt_cloud, atol=1e-6)
    strips, classes = geo.lines["matches/clique"]
    assert len(strips) == len(outcome.result.clique) and set(classes.tolist()) == {CLIQUE.id}
    assert np.allclose(strips[:, 0], outcome.corr.src[outcome.result.clique], atol=1e-6)
    (png,) = snapshot_recording(tmp_path / "recording.rrd", tmp_path / "snaps", titles={"scene/a": "T"})
    assert png.name == "scene_a.png"
    pixels = np.asarray(Image.open(png).convert("L"))
    assert pixels.shape[1] > 800 and (pixels < 200).mean() > 0.01  # something was drawn


def test_report_writes_pair_snapshots(tmp_path, strict_rerun):
    from fastmac_exp.report import main
    from fastmac_exp.run.results import ResultsLog
    from fastmac_exp.trackers.rerun_tracker import RerunTracker

    outcomes = [make_outcome(i, f"p{i}") for i in range(3)]
    run_tracker(RerunTracker(max_pairs=3, max_points=200), tmp_path, outcomes)
    log = ResultsLog(tmp_path)
    for o in outcomes:
        log.append(o.row)
    log.write_tables()
    assert main([str(tmp_path), "--snapshots", "2", "--no-plots"]) == 0
    pairs = sorted(p.name for p in (tmp_path / "report" / "pairs").glob("*.png"))
    assert pairs == ["p1.png", "p2.png"]  # the worst RE first (p2: 0.3 deg, p1: 0.2, p0: 0.1)
    text = (tmp_path / "report" / "report.md").read_text()
    assert "![p2](pairs/p2.png)" in text and "p1.png" in text and "p0.png" not in text
    assert main([str(tmp_path), "--snapshots", "0", "--no-plots", "--out", str(tmp_path / "r0")]) == 0
    assert not (tmp_path / "r0" / "pairs").exists()


def test_pairs_that_did_not_register_get_geometry_and_the_report_shows_them_first(tmp_path):
    """max_pairs=2 over 5 pairs, the last one not registered: it is recorded (beyond the first two
    registered ones) and its image is the report's first; then the worst RE."""
    from fastmac_exp.report import pair_snapshots
    from fastmac_exp.trackers.rerun_snapshot import read_pairs
    from fastmac_exp.trackers.rerun_tracker import RerunTracker

    outcomes = [make_outcome(i, f"p{i}") for i in range(5)]
    outcomes[4].row.update(success=False, re_deg=40.0)
    table, _ = run_tracker(RerunTracker(max_pairs=2, max_points=500), tmp_path, outcomes)
    assert [g.name for g in read_pairs(tmp_path / "recording.rrd")] == ["p0", "p1", "p4"]
    table["run"] = "."
    pngs = pair_snapshots(tmp_path, table, tmp_path / "report", max_pairs=2)
    assert [p.name for p in pngs] == ["p4.png", "p1.png"]  # not registered, then RE 0.2 before 0.1


def test_a_sweep_member_records_the_geometry_of_one_pair_by_default(tmp_path, monkeypatch):
    from fastmac_exp.trackers import rerun_tracker
    from fastmac_exp.trackers.rerun_snapshot import read_pairs

    monkeypatch.setattr(rerun_tracker, "in_multirun", lambda: True)
    outcomes = [make_outcome(i, f"p{i}") for i in range(3)]
    run_tracker(rerun_tracker.RerunTracker(max_pairs=4, max_points=200), tmp_path / "a", outcomes)
    assert [g.name for g in read_pairs(tmp_path / "a" / "recording.rrd")] == ["p0"]
    all_pairs = rerun_tracker.RerunTracker(max_pairs=4, max_points=200, sweep_max_pairs=None)
    run_tracker(all_pairs, tmp_path / "b", outcomes)
    assert [g.name for g in read_pairs(tmp_path / "b" / "recording.rrd")] == ["p0", "p1", "p2"]
