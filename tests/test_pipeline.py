"""One pair through the pipeline, the library API, the experiment loop and its results files."""

from __future__ import annotations

import json

import numpy as np
import pandas as pd
import pytest
from omegaconf import OmegaConf

from fastmac_exp.api import register
from fastmac_exp.backends.python_mac import PythonBackend
from fastmac_exp.descriptors.base import Descriptor  # noqa: F401 - interface import must work
from fastmac_exp.descriptors.precomputed import PrecomputedDescriptor
from fastmac_exp.errors import InputError
from fastmac_exp.params import mac_params_for
from fastmac_exp.pipeline import register_correspondences
from fastmac_exp.run.experiment import run_experiment
from fastmac_exp.run.results import COLUMNS, load_table
from fastmac_exp.samplers import GraphFilterSampler, NoSampler
from fastmac_exp.types import Correspondences
from tests.conftest import make_correspondences


def test_register_correspondences_maps_indices_back():
    corr, gt = make_correspondences(n=800, inlier_ratio=0.1, seed=11)
    res, sample = register_correspondences(
        corr, mac_params_for("3dmatch", "fpfh"), GraphFilterSampler(impl="python"), PythonBackend(), ratio=0.2
    )
    assert len(res.kept) == 160
    assert set(res.clique.tolist()) <= set(res.kept.tolist())
    assert corr.labels[res.clique].all()
    assert {"sampling", "graph", "cliques", "selection", "pose", "total"} <= set(res.timings)
    assert np.allclose(res.pose, gt, atol=0.05)


def test_library_register_on_correspondences():
    corr, gt = make_correspondences(n=600, inlier_ratio=0.1, seed=12)
    res = register(corr, sampler="highpass", ratio=0.5, backend="python", seed=1)
    assert np.allclose(res.pose, gt, atol=0.05)


def test_library_register_flags_what_it_cannot_trust_instead_of_raising():
    """No pose found (FastMAC@5 on 1,000 outliers keeps 50 with no second-order edge): a result flagged as
    failed. A pose of unrelated clouds maps about its clique's size within the inlier threshold, a right
    one far more: `inliers` says which."""
    corr, _ = make_correspondences(n=1000, inlier_ratio=0.0, seed=0)
    res = register(corr, sampler="random", ratio=0.05, escalate="off")
    assert not res.ok and "no second-order edge" in res.error and np.isnan(res.pose).all()
    wider = register(corr, sampler="random", ratio=0.05)  # the escalation finds a pose, and trusts none
    assert not wider.trusted and wider.escalation[0]["error"] == res.error
    good, gt = make_correspondences(n=1000, inlier_ratio=0.1, seed=1)
    res = register(good, ratio=0.2)
    assert res.ok and res.inliers == 100 and np.allclose(res.pose, gt, atol=0.05)
    rng = np.random.default_rng(0)
    unrelated = register(rng.uniform(0, 3, (20000, 3)), rng.uniform(0, 3, (20000, 3)), voxel_size=0.05)
    assert unrelated.ok and unrelated.inliers <= 2 * len(unrelated.clique)


def test_library_register_refuses_bad_input_with_what_is_wrong():
    pts = np.random.default_rng(0).uniform(0, 3, (500, 3))
    with pytest.raises(InputError, match=r"source must be an \(N, 3\) array of points, got shape \(5,\)"):
        register(np.zeros(5), pts)
    with pytest.raises(InputError, match="voxel_size must be positive or None"):
        register(pts, pts, voxel_size=0.0)
    for n in (0, 1, 2):
        with pytest.raises(
            InputError, match=f"^{n} correspondence\\(s\\): a clique, and a pose, needs at least 3"
        ):
            register(Correspondences(pts[:n], pts[:n] + 1.0))


def _cfg(tmp_path, **over):
    base = {
        "dataset": {"_target_": "tests.conftest.ListDataset", "num_pairs": 4},
        "descriptor": {"_target_": "fastmac_exp.descriptors.precomputed.PrecomputedDescriptor"},
        "sampler": {"_target_": "fastmac_exp.samplers.GraphFilterSampler", "impl": "python"},
        "backend": {"_target_": "fastmac_exp.backends.python_mac.PythonBackend"},
        "ratio": 0.5, "seed": 0, "protocol": "honest", "fail_fast": False, "resume": None, "workers": 1,
        "progress": False, "graph": {}, "mac": {}, "tracker": {},
    }  # fmt: skip
    cfg = OmegaConf.merge(OmegaConf.create(base), OmegaConf.create(over))
    return cfg


def test_experiment_writes_rows_tables_and_summary(tmp_path):
    table, summary = run_experiment(_cfg(tmp_path), tmp_path / "run")
    assert len(table) == 4 and list(table.columns[: len(COLUMNS)]) == COLUMNS
    assert table["success"].all()
    for f in ("results.jsonl", "results.csv", "results.parquet", "summary.json", "config.yaml"):
        assert (tmp_path / "run" / f).exists(), f
    saved = json.loads((tmp_path / "run" / "summary.json").read_text())
    assert saved["RR"] == 1.0 and saved["pairs"] == 4 and saved["complete"]
    pd.testing.assert_frame_equal(load_table(tmp_path / "run"), table, check_dtype=False)


def test_bad_pair_is_recorded_and_run_continues(tmp_path):
    cfg = _cfg(tmp_path, dataset={"bad": [1]})
    table, summary = run_experiment(cfg, tmp_path / "run")
    assert len(table) == 4 and summary["failed"] == 1 and summary["RR"] == 0.75
    bad = table.set_index("pair").loc["pair_001"]
    assert "not finite" in bad["error"] and "row 5" in bad["error"] and not bad["success"]


def test_fail_fast_stops(tmp_path):
    cfg = _cfg(tmp_path, dataset={"bad": [1]}, fail_fast=True)
    with pytest.raises(Exception, match="not finite"):
        run_experiment(cfg, tmp_path / "run")


def test_same_seed_same_results_and_workers_agree(tmp_path):
    t1, _ = run_experiment(_cfg(tmp_path), tmp_path / "a")
    t2, _ = run_experiment(_cfg(tmp_path, workers=2), tmp_path / "b")
    how_it_ran = ("workers", "oversubscribed")  # like the timings: not what was measured
    cols = [c for c in t1.columns if not c.startswith("t_") and c not in how_it_ran]
    pd.testing.assert_frame_equal(t1[cols], t2[cols])


def test_none_sampler_records_ratio_one(tmp_path):
    cfg = _cfg(tmp_path, sampler={"_target_": "fastmac_exp.samplers.NoSampler", "impl": None})
    cfg.sampler = {"_target_": "fastmac_exp.samplers.NoSampler"}
    table, _ = run_experiment(cfg, tmp_path / "run")
    assert (table["ratio"] == 1.0).all() and (table["n_kept"] == table["n_in"]).all()
    assert NoSampler().name == "none"


def test_correspondence_cache_changes_no_result(tmp_path):
    from fastmac_exp.descriptors.oracle import OracleDescriptor
    from fastmac_exp.pipeline import run_pair
    from fastmac_exp.pipeline.cache import CorrespondenceCache
    from fastmac_exp.types import Pair

    rng = np.random.default_rng(0)
    cloud = rng.uniform(0, 3, (3000, 3))
    pair = Pair(name="p", gt=np.eye(4), src_cloud=cloud, tgt_cloud=cloud + 0.0)
    cache = CorrespondenceCache(tmp_path / "cache")
    desc = OracleDescriptor(num_correspondences=400, inlier_ratio=0.2)
    args = (pair, desc, GraphFilterSampler(impl="python"), PythonBackend(), 0.5)
    first = run_pair(*args, np.random.default_rng([0, 1]), cache=cache, cache_key="k")
    second = run_pair(*args, np.random.default_rng([0, 1]), cache=cache, cache_key="k")
    plain = run_pair(*args, np.random.default_rng([0, 1]))
    assert second.row.get("describe_cached") and not first.row.get("describe_cached")
    for out in (second, plain):
        assert out.row["pose"] == first.row["pose"] and out.row["n_kept"] == first.row["n_kept"]
        np.testing.assert_array_equal(out.result.kept, first.result.kept)
    assert second.row["t_describe_ms"] == first.row["t_describe_ms"]
    # a corrupted entry is recomputed, not trusted
    entry = next((tmp_path / "cache").rglob("*.npz"))
    entry.write_bytes(b"garbage")
    third = run_pair(*args, np.random.default_rng([0, 1]), cache=cache, cache_key="k")
    assert not third.row.get("describe_cached") and third.row["pose"] == first.row["pose"]


@pytest.mark.parametrize("ratio", [0, 1.5, -0.2, "abc"])
def test_impossible_ratio_fails_before_any_pair(tmp_path, ratio):
    from fastmac_exp.errors import InputError

    with pytest.raises(InputError, match="config key: ratio"):
        run_experiment(_cfg(tmp_path, ratio=ratio), tmp_path / "run")
    assert not (tmp_path / "run" / "results.jsonl").exists()


@pytest.mark.parametrize("name", ["ransac", "fgr", "kiss_matcher"])
def test_peer_backends_through_the_pipeline(name):
    from hydra.utils import instantiate

    from fastmac_exp.backends import peers

    backend = {
        "ransac": lambda: peers.RansacBackend(max_iterations=2000),
        "fgr": peers.FGRBackend,
        "kiss_matcher": lambda: instantiate({"_target_": "fastmac_exp.backends.peers.KissMatcherBackend"}),
    }[name]()
    corr, gt = make_correspondences(n=500, inlier_ratio=0.2, noise=0.005, seed=13)
    res, _ = register_correspondences(corr, mac_params_for("3dmatch", "fpfh"), NoSampler(), backend)
    assert np.allclose(res.pose, gt, atol=0.1), name


def test_rerun_into_a_used_directory_needs_resume(tmp_path):
    from fastmac_exp.errors import InputError

    run_experiment(_cfg(tmp_path), tmp_path / "run")
    with pytest.raises(InputError, match="resume="):
        run_experiment(_cfg(tmp_path, ratio=0.3), tmp_path / "run")


def test_failed_pair_keeps_what_was_measured(tmp_path):
    # a ratio that leaves fewer samples than a clique needs fails in the sampler, after describing
    cfg = _cfg(tmp_path, ratio=0.005)
    table, summary = run_experiment(cfg, tmp_path / "run")
    assert summary["failed"] == 4
    assert (table["n_in"] == 300).all() and table["inlier_ratio_in"].notna().all()
    assert table["error"].str.contains("fewer than the 3").all()


def test_pair_row_keeps_what_was_measured_and_leaves_out_the_rest():
    """A row's dict holds the fields a stage set (None included) and none it did not reach; timings
    become t_<stage>_ms columns just before the pose; an unknown field is refused."""
    from fastmac_exp.pipeline.row import PairRow

    row = PairRow(index=3, pair="p", dataset="d", descriptor="fpfh", sampler="highpass", backend="cpp",
                  ratio=0.2, seed=0, protocol="honest")  # fmt: skip
    row.set(scene="s", family="kitti", inliers_in=None)
    d = row.to_dict()
    assert d["inliers_in"] is None and "n_kept" not in d and "success" not in d and "pose" not in d
    assert list(d)[:10] == ["index", "pair", "dataset", "descriptor", "sampler", "backend", "ratio", "seed",
                            "protocol", "error"]  # fmt: skip
    row.timings = {"describe": 1.0, "total": 2.0}
    row.pose = "1 0 0 0"
    assert list(row.to_dict())[-3:] == ["t_describe_ms", "t_total_ms", "pose"]
    with pytest.raises(AttributeError, match="no field 'n_kep'"):
        row.set(n_kep=3)


class CostlyDescriptor(PrecomputedDescriptor):
    cost_note = "about an hour a pair"


def test_a_costly_descriptor_says_what_it_costs_when_the_run_starts(tmp_path, caplog):
    from fastmac_exp.descriptors.buffer import BufferDescriptor

    assert "a pair" in BufferDescriptor.cost_note and "INT8" in BufferDescriptor.cost_note
    cfg = _cfg(tmp_path, descriptor={"_target_": "tests.test_pipeline.CostlyDescriptor"})
    with caplog.at_level("WARNING", logger="fastmac_exp.run.experiment"):
        run_experiment(cfg, tmp_path / "run")
    assert any("about an hour a pair" in r.getMessage() for r in caplog.records)


def test_a_stopwatch_times_its_stages_back_to_back(monkeypatch):
    """Issue 49 item 2: each lap starts where the last ended, a lap timed inside is split into its parts
    and the rest, and end_to_end is the whole span."""
    from fastmac_exp.pipeline import stopwatch

    clock = iter([10.0, 10.5, 12.0, 12.25, 13.0])
    monkeypatch.setattr(stopwatch.time, "perf_counter", lambda: next(clock))
    watch = stopwatch.Stopwatch()  # 10.0
    watch.lap("load")  # 10.5
    watch.lap("describe")  # 12.0
    watch.lap("evaluate")  # 12.25
    parts = stopwatch.registration_parts({"sampling": 200.0, "graph": 300.0, "total": 999.0})
    watch.lap_in_parts(parts)  # 13.0: 750 ms, of which sampling and graph timed 500 inside
    want = {"load": 500.0, "describe": 1500.0, "evaluate": 250.0, "other": 250.0, "sampling": 200.0,
            "graph": 300.0, "total": 999.0, "end_to_end": 3000.0}  # fmt: skip
    assert watch.timings(total=999.0) == pytest.approx(want)


def test_register_names_every_stage_and_they_add_up():
    """Issue 49 item 2: register() on two clouds: the set-up, the cleaning and MAC's mesh resolution have a
    stage each (they were in none), and the stages sum to end_to_end, which is within the call's time."""
    import time

    import fastmac_exp
    from fastmac_exp.geometry.metrics import PAIR_STAGES

    rng = np.random.default_rng(0)
    src = rng.uniform(0, 2, (4000, 3))
    t0 = time.perf_counter()
    result = fastmac_exp.register(src, src + [0.1, 0.0, 0.0], backend="python")
    wall = (time.perf_counter() - t0) * 1e3
    t = result.timings
    stages = [k for k in t if k not in ("total", "end_to_end")]
    assert stages == ["setup", "clean", "resolution", "describe", "other", "sampling", "graph", "cliques",
                      "selection", "pose", "check"]  # fmt: skip
    assert set(stages) <= set(PAIR_STAGES) and all(t[k] >= 0 for k in stages)
    assert sum(t[k] for k in stages) == pytest.approx(t["end_to_end"], rel=1e-12)
    assert t["end_to_end"] <= wall and t["total"] <= t["end_to_end"]
