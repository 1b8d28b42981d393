"""What a user sees on the console: failure reasons in the summary, non-zero exit codes for runs that
cannot work, clean messages for configuration errors (no Hydra traceback)."""

from __future__ import annotations

import os
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

REPO = Path(__file__).resolve().parents[1]


def run(*overrides: str, tmp: Path) -> subprocess.CompletedProcess:
    cmd = [sys.executable, "run.py", *overrides, "tracker=none", "progress=false"]
    if not any(o.startswith("hydra.run.dir=") for o in overrides):
        cmd.append(f"hydra.run.dir={tmp / 'run'}")
    env = {**os.environ, "PYTHONPATH": str(REPO)}
    return subprocess.run(cmd, cwd=REPO, env=env, capture_output=True, text=True, timeout=120)


def _not_clouds(tmp: Path, *names: str) -> list[Path]:
    """Files that exist (so the run starts) but fail when a pair reads them."""
    paths = [tmp / n for n in names]
    for p in paths:
        p.write_text("not a point cloud\n")
    return paths


def test_every_pair_failed_exits_non_zero_and_says_why(tmp_path):
    a, b = _not_clouds(tmp_path, "a.xyz", "b.xyz")
    p = run("dataset=pairs", f"dataset.source={a}", f"dataset.target={b}", tmp=tmp_path)
    assert p.returncode == 1, p.stderr[-2000:]
    out = p.stdout + p.stderr
    assert f"failed x1: InputError: {a}, line 1: 'not' is not a number" in out
    assert "every pair failed" in out


def test_a_missing_input_file_is_refused_before_the_run_starts(tmp_path):
    """A missing file is a config error (exit 2, its absolute path, no run directory), not a failed pair."""
    (b,) = _not_clouds(tmp_path, "b.xyz")
    p = run("dataset=pairs", "dataset.source=nosuch_a.ply", f"dataset.target={b}", tmp=tmp_path)
    out = p.stdout + p.stderr
    assert p.returncode == 2, out[-2000:]
    assert f"dataset.source: no such file: {REPO / 'nosuch_a.ply'}" in out
    assert not (tmp_path / "run").exists()


def test_empty_and_headless_input_files_are_refused_before_the_run_starts(tmp_path):
    """Issue 49 item 4: an empty file (or a .ply that is no PLY) is a config error like a missing one: exit
    2 and its path before a run directory exists, not a failed pair in a run directory."""
    (b,) = _not_clouds(tmp_path, "b.xyz")
    empty = tmp_path / "empty.ply"
    empty.write_bytes(b"")
    p = run("dataset=pairs", f"dataset.source={empty}", f"dataset.target={b}", tmp=tmp_path)
    out = p.stdout + p.stderr
    assert p.returncode == 2, out[-2000:]
    assert f"dataset.source: an empty file (0 bytes): {empty}" in out and "Traceback" not in out
    assert not (tmp_path / "run").exists()
    headless = tmp_path / "xyz.ply"
    headless.write_text("0 0 0\n1 1 1\n")
    gt_empty = tmp_path / "gt.txt"
    gt_empty.write_text("")
    p = run("dataset=pairs", f"dataset.source={b}", f"dataset.target={headless}", tmp=tmp_path)
    assert (
        p.returncode == 2
        and "dataset.target: not a PLY file (it does not start with 'ply'" in p.stdout + p.stderr
    )
    p = run(
        "dataset=pairs", f"dataset.source={b}", f"dataset.target={b}", f"dataset.gt={gt_empty}", tmp=tmp_path
    )
    assert p.returncode == 2 and f"dataset.gt: an empty file (0 bytes): {gt_empty}" in p.stdout + p.stderr
    assert not (tmp_path / "run").exists()


def test_dropped_points_are_said_on_the_console_and_in_run_log(tmp_path):
    """Issue 49 item 4: points at the origin and NaN rows are dropped with a line saying how many of what
    was read, and why (a 3-point cloud whose origin point vanished said '2 point(s) ... (from 2)')."""
    src, tgt, gt = _blob_pair(tmp_path)
    pts = np.load(src)
    np.save(src, np.r_[pts, np.zeros((3, 3)), np.full((2, 3), np.nan)])
    p = run("dataset=pairs", f"dataset.source={src}", f"dataset.target={tgt}", tmp=tmp_path)
    assert p.returncode == 0, p.stderr[-2000:]
    said = (
        f"source cloud {src}: read {len(pts) + 5} points, dropped 5: 2 not finite (NaN/inf); 3 exactly at "
        "(0, 0, 0), taken for invalid LiDAR returns (dataset.drop_zeros=false keeps them)"
    )
    assert said in p.stdout + p.stderr and said in (tmp_path / "run" / "run.log").read_text()
    assert f"target cloud {tgt}: read" not in p.stdout + p.stderr  # nothing dropped, nothing said


def test_an_unknown_option_value_is_refused_before_the_run_starts(tmp_path):
    p = run("mac.search=bnbb", tmp=tmp_path)
    out = p.stdout + p.stderr
    assert p.returncode == 2 and "mac.search must be one of auto, bnb, enumerate, got 'bnbb'" in out
    assert not (tmp_path / "run").exists()


def test_config_value_errors_exit_2_with_our_message(tmp_path):
    p = run("dataset.family=kiti", tmp=tmp_path)
    out = p.stdout + p.stderr
    assert p.returncode == 2
    assert "family must be one of" in out and "Error in call to target" not in out
    p = run("limit=0", tmp=tmp_path)
    assert p.returncode == 2 and "limit must be >= 1" in p.stdout + p.stderr
    p = run("dataset.limit=3", tmp=tmp_path)  # where the key used to be: say where it is now
    assert p.returncode == 2 and "write limit=3" in p.stdout + p.stderr


def sweep(*overrides: str, sweep_dir: Path) -> subprocess.CompletedProcess:
    cmd = [sys.executable, "run.py", "-m", *overrides, "tracker=none", "progress=false",
           f"hydra.sweep.dir={sweep_dir}"]  # fmt: skip
    env = {**os.environ, "PYTHONPATH": str(REPO)}
    return subprocess.run(cmd, cwd=REPO, env=env, capture_output=True, text=True, timeout=300)


def test_a_sweep_goes_on_past_a_member_whose_pairs_all_failed_and_resumes_with_auto(tmp_path):
    """A sweep member in which every pair fails (here: files that are no clouds) is a measurement, not the
    end of the sweep; rerunning the same sweep into the same directory needs resume=auto and keeps every
    row once."""
    import pandas as pd

    (tmp_path / "in").mkdir()
    a, b, c = _not_clouds(tmp_path / "in", "a.xyz", "b.xyz", "c.xyz")
    # absolute paths in the members' names would make directories of their slashes: number them instead
    args = (
        "dataset=pairs",
        f"dataset.source={a},{b}",
        f"dataset.target={c}",
        "hydra.sweep.subdir=${hydra.job.num}",
    )
    first = sweep(*args, sweep_dir=tmp_path / "sweep")
    assert first.returncode == 0, first.stderr[-2000:]
    members = sorted(p.parent for p in (tmp_path / "sweep").glob("*/results.jsonl"))
    assert len(members) == 2  # the second member ran after the first one failed on every pair
    again = sweep(*args, sweep_dir=tmp_path / "sweep")
    assert again.returncode != 0 and "already holds results" in again.stdout + again.stderr
    resumed = sweep(*args, "resume=auto", sweep_dir=tmp_path / "sweep")
    assert resumed.returncode == 0, resumed.stderr[-2000:]
    assert (
        sorted(p.parent for p in (tmp_path / "sweep").glob("*/results.jsonl")) == members
    )  # no new directories
    for m in members:
        rows = pd.read_csv(m / "results.csv")
        assert len(rows) == 1 and rows["error"].str.contains("is not a number").all()


def test_a_launcher_without_its_plugin_names_the_package(tmp_path):
    """Without the cluster extra, each cluster launcher says what to install (not Hydra's "Could not
    load"); hydra-ray-launcher's own `ray` option says why it cannot be installed and what to use."""
    import importlib.util

    plugins = [
        ("slurm", "hydra_plugins.hydra_submitit_launcher"),
        ("submitit_local", "hydra_plugins.hydra_submitit_launcher"),
        ("ray_cluster", "ray"),
        ("ray", "hydra_plugins.hydra_ray_launcher"),
    ]
    for launcher, module in plugins:
        try:
            installed = importlib.util.find_spec(module) is not None
        except ModuleNotFoundError:
            installed = False
        if installed:
            continue  # the plugin is there: nothing to explain
        p = sweep(f"hydra/launcher={launcher}", "limit=1", sweep_dir=tmp_path / launcher)
        out = p.stdout + p.stderr
        assert p.returncode == 2, out[-2000:]
        assert "pip install -e '.[cluster]' -c constraints.txt" in out and "Could not load" not in out
        if launcher == "ray":
            assert "cloudpickle<3" in out and "hydra/launcher=ray_cluster" in out


def test_help_says_what_the_app_does_and_lists_the_groups():
    env = {**os.environ, "PYTHONPATH": str(REPO)}
    cmd = [sys.executable, "run.py", "--help"]
    p = subprocess.run(cmd, cwd=REPO, env=env, capture_output=True, text=True, timeout=60)
    assert p.returncode == 0
    out = p.stdout
    assert out.startswith("fastmac-exp: FastMAC")
    for line in ("sampler: allpass,", "method: fastmac20,", "experiment: descriptor_robustness,",
                 "hydra/launcher (sweeps): local", "python run.py sampler=highpass ratio=0.05",
                 "limit (the first N pairs; null = all)"):  # fmt: skip
        assert line in out, line
    assert "Powered by Hydra" not in out  # not Hydra's generic text


def test_runs_with_a_parts_key_set_are_named_for_it_and_run_log_holds_the_summary(tmp_path):
    """Issue 49 item 8: sampler.scores=exact and descriptor.impl=open3d runs got the default run's directory
    name and header; run.log held none of the summary the console showed."""
    runs = tmp_path / "runs"
    p = run("limit=1", "sampler.scores=exact", "descriptor.impl=open3d", _default_run_dir(runs), tmp=tmp_path)
    assert p.returncode == 0, p.stderr[-2000:]
    (made,) = runs.iterdir()
    assert made.name.endswith("_fpfh_highpass_0.2_scores=exact_impl=open3d"), made.name
    header = p.stdout.splitlines()[0]
    assert header.endswith("protocol=honest sampler.scores=exact descriptor.impl=open3d"), header
    log = (made / "run.log").read_text()
    for line in p.stdout.splitlines():  # every line of the console's summary
        assert line in log, line
    p = run("limit=1", _default_run_dir(runs), tmp=tmp_path)  # the default run: a name of its own
    assert p.returncode == 0 and len(list(runs.iterdir())) == 2
    assert sorted(d.name.endswith("_highpass_0.2") for d in runs.iterdir()) == [False, True]


def test_version_is_fastmac_exps():
    """Issue 49 item 7: --version printed Hydra's version."""
    from fastmac_exp import __version__

    p = subprocess.run([sys.executable, "run.py", "--version"], cwd=REPO, capture_output=True, text=True,
                       timeout=120)  # fmt: skip
    assert p.returncode == 0 and p.stdout.startswith(f"fastmac-exp {__version__} (Hydra "), p.stdout


def test_summary_says_when_describe_times_come_from_the_cache(tmp_path):
    cache = f"cache.dir={tmp_path / 'cache'}"
    first = run("limit=1", cache, tmp=tmp_path / "a")
    assert first.returncode == 0, first.stderr[-2000:]
    assert "from the cache" not in first.stdout and "  describe " in first.stdout
    second = run("limit=1", cache, tmp=tmp_path / "b")
    assert second.returncode == 0, second.stderr[-2000:]
    assert "describe (all from the cache: original times)" in second.stdout


def test_the_timings_add_up_to_the_pairs_end_to_end_time(tmp_path):
    """Issue 49 item 2: every stage a pair spends time in has a name in the row and the summary (the
    resolution and the loading were in none: describe + total was 91-101 ms of a 258-275 ms pair), they sum
    to the row's end-to-end time, and `total` is shown as what it is, sampling + MAC."""
    import pandas as pd

    p = run("limit=1", tmp=tmp_path)
    assert p.returncode == 0, p.stderr[-2000:]
    row = pd.read_csv(tmp_path / "run" / "results.csv").iloc[0]
    stages = ["load", "resolution", "describe", "sampling", "graph", "cliques", "selection", "pose", "other",
              "check", "evaluate"]  # fmt: skip
    assert [c for c in row.index if c.startswith("t_")] == [f"t_{s}_ms" for s in stages] + [
        "t_total_ms", "t_end_to_end_ms"]  # fmt: skip
    assert all(row[f"t_{s}_ms"] >= 0 for s in stages)
    assert sum(row[f"t_{s}_ms"] for s in stages) == pytest.approx(row["t_end_to_end_ms"], rel=1e-9)
    assert sum(row[f"t_{s}_ms"] for s in ("sampling", "graph", "cliques", "selection", "pose")) <= row[
        "t_total_ms"]  # fmt: skip
    lines = p.stdout.splitlines()
    (i,) = [k for k, ln in enumerate(lines) if ln.startswith("median ms: ")]
    assert all(f"  {s} " in f" {lines[i]} " for s in stages[1:]) and lines[i].startswith("median ms: load ")
    assert f"end to end {row['t_end_to_end_ms']:.1f} (every stage)" in lines[i + 1]
    assert f"sampling + MAC {row['t_total_ms']:.1f} (the papers' total)" in lines[i + 1]


def _default_run_dir(tmp: Path) -> str:
    """conf/config.yaml's hydra.run.dir with outputs/runs moved under tmp (the same name pattern)."""
    import yaml

    pattern = yaml.safe_load((REPO / "conf" / "config.yaml").read_text())["hydra"]["run"]["dir"]
    return "hydra.run.dir='" + pattern.replace("outputs/runs", str(tmp)) + "'"  # quoted: the comma


def test_run_directory_names_say_descriptor_and_the_ratio_used_and_failed_runs_leave_none(tmp_path):
    runs = tmp_path / "runs"
    p = run("sampler=none", "limit=1", _default_run_dir(runs), tmp=tmp_path)
    assert p.returncode == 0, p.stderr[-2000:]
    (made,) = runs.iterdir()
    assert made.name.endswith("_synthetic-3dmatch_fpfh_none_1.0"), made.name
    assert "Warning" not in p.stderr, p.stderr[-2000:]  # the lock callback resolves the default name cleanly
    counted = run("samples=300", "limit=1", _default_run_dir(tmp_path / "counted"), tmp=tmp_path)
    assert counted.returncode == 0, counted.stderr[-2000:]
    assert next((tmp_path / "counted").iterdir()).name.endswith("_highpass_k300")
    # a config error and a resume= run leave no directory of their own
    bad = run("dataset.family=kiti", _default_run_dir(runs), tmp=tmp_path)
    assert bad.returncode == 2
    again = run("sampler=none", "limit=1", f"resume={made}", _default_run_dir(runs), tmp=tmp_path)
    assert again.returncode == 0, again.stderr[-2000:]
    assert [d.name for d in runs.iterdir()] == [made.name]
    assert list(made.glob("run.resumed-*.log"))  # the resumed run's log went with its results


def test_run_names_and_the_header_say_the_family_and_a_backend_other_than_cpp(tmp_path):
    runs = tmp_path / "runs"
    p = run("dataset.family=kitti", "backend=python", "limit=1", _default_run_dir(runs), tmp=tmp_path)
    assert p.returncode == 0, p.stderr[-2000:]
    (made,) = runs.iterdir()
    assert made.name.endswith("_synthetic-kitti_fpfh_highpass_0.2_python"), made.name
    assert (
        "dataset=synthetic family=kitti descriptor=fpfh sampler=highpass ratio=0.2 backend=python" in p.stdout
    )


def test_a_key_typo_gets_the_closest_key_not_a_plus_suggestion(tmp_path):
    p = run("dataset.famly=kitti", tmp=tmp_path)
    out = p.stdout + p.stderr
    assert p.returncode == 2
    assert "unknown config key 'dataset.famly'; did you mean 'dataset.family'?" in out
    assert "+dataset.famly" not in out
    for typo in ("+ratoi=0.1", "ratoi=0.1"):  # Hydra itself suggests the `+` form, which adds an unused key
        p = run(typo, tmp=tmp_path)
        out = p.stdout + p.stderr
        assert p.returncode == 2 and "unknown config key 'ratoi'; did you mean 'ratio'?" in out, out[-2000:]
    assert not (tmp_path / "run").exists()


def test_run_keys_are_checked_before_the_run_starts(tmp_path):
    """One bad key through the console (exit 2, the message, no run directory); the others through the
    same check in this process (a Hydra start-up each was 3 s of the fast suite)."""
    import re

    import pytest
    from hydra import compose, initialize_config_dir

    from fastmac_exp.errors import InputError
    from fastmac_exp.resources import config_dir
    from fastmac_exp.run.checks import check_run_keys

    p = run("seed=abc", tmp=tmp_path)
    out = p.stdout + p.stderr
    assert p.returncode == 2 and "Traceback" not in out, out[-2000:]
    assert "seed must be a whole number >= 0, got 'abc' (config key: seed)" in out
    assert not (tmp_path / "run").exists()
    with initialize_config_dir(config_dir=str(config_dir()), version_base="1.3"):
        for override, message in [
            ("seed=1.5", "seed must be a whole number >= 0, got 1.5"),
            ("seed=-1", "seed must be a whole number >= 0, got -1"),
            ("limit=abc", "limit must be >= 1 (null = every pair), got 'abc' (config key: limit)"),
            ("workers=0", "workers must be a whole number >= 1, got 0 (config key: workers)"),
            ("mac.max_nodes=abc", "graph/mac override of the wrong type"),
        ]:
            with pytest.raises(InputError, match=re.escape(message)):
                check_run_keys(compose("config", overrides=[override]))


def test_workers_are_capped_at_the_pairs_to_run(tmp_path):
    p = run("workers=64", "limit=2", tmp=tmp_path)
    assert p.returncode == 0, p.stderr[-2000:]
    assert "workers=64: 2 pair(s) to run, so 2 worker(s)" in p.stdout + p.stderr


def test_an_unwritable_run_directory_is_a_clear_error(tmp_path):
    blocker = tmp_path / "file"
    blocker.write_text("not a directory")
    p = run("limit=1", f"hydra.run.dir={blocker / 'run'}", tmp=tmp_path)
    out = p.stdout + p.stderr
    assert p.returncode == 2 and "Traceback" not in out, out[-2000:]
    assert f"cannot write the run directory {blocker / 'run'}" in out
    done = tmp_path / "done"
    assert run("limit=1", f"hydra.run.dir={done}", tmp=tmp_path).returncode == 0
    (done / "results.jsonl").rename(done / "moved.jsonl")
    (done / "results.jsonl").mkdir()  # what a resume cannot append to (root ignores permission bits)
    p = run("limit=2", f"resume={done}", tmp=tmp_path)
    out = p.stdout + p.stderr
    assert p.returncode == 2 and "Traceback" not in out and f"cannot write in {done}" in out, out[-2000:]


def test_parallel_sweep_members_print_whole_summaries(tmp_path):
    """Two joblib workers share the console: every summary block arrives in one piece."""
    p = sweep("hydra/launcher=local", "sampler=highpass,random", "limit=1", sweep_dir=tmp_path)
    assert p.returncode == 0, p.stderr[-2000:]
    lines = p.stdout.splitlines()
    starts = [
        i for i, ln in enumerate(lines) if ln.startswith("dataset=synthetic family=3dmatch descriptor=fpfh")
    ]
    assert len(starts) == 2
    for i in starts:  # the block's lines follow each other, each one whole
        assert lines[i + 1].startswith("pairs: 1  registered:")
        assert lines[i + 2].startswith("RR: ") and lines[i + 3].startswith("median ms: ")
        assert lines[i + 4].strip().startswith("end to end ")
        j = i + 5
        while lines[j].startswith("failed x"):  # a failed pair's reason, if any
            j += 1
        assert lines[j].startswith("results: ")
    # the sweep ends with one table of its members and the command to run next
    table = p.stdout[p.stdout.index(f"sweep {tmp_path}:") :].splitlines()
    assert table[1].split() == ["member", "pairs", "RR", "%", "RE", "deg", "TE", "cm", "ms", "failed"]
    assert table[2].startswith("0_sampler=highpass") and table[3].startswith("1_sampler=random")
    assert table[4] == f"next: python -m fastmac_exp.report {tmp_path}"


def test_the_package_finds_its_configs_and_models_without_the_repository_layout(tmp_path):
    """What a wheel install relies on: configs and models are found through the package (resources.py),
    and `python -m fastmac_exp` is the same app as run.py (its --help), run from another directory."""
    from fastmac_exp.descriptors.onnx_descriptor import DEFAULT_MODEL, resolve_model_path
    from fastmac_exp.resources import MODELS_DIR, PACKAGE_DIR, config_dir

    assert (config_dir() / "config.yaml").is_file()
    assert resolve_model_path(DEFAULT_MODEL) == MODELS_DIR / "fcgf_lite.onnx"
    assert MODELS_DIR.parent == PACKAGE_DIR
    p = subprocess.run([sys.executable, "-m", "fastmac_exp", "--help"], capture_output=True, text=True,
                       timeout=120, cwd=tmp_path)  # fmt: skip
    assert p.returncode == 0 and "python run.py sampler=highpass ratio=0.05" in p.stdout


def test_samples_keeps_a_count_and_the_row_says_which_scores_ran(tmp_path):
    import pandas as pd

    p = run("limit=2", "samples=300", "dataset.family=kitti", f"cache.dir={tmp_path / 'cache'}", tmp=tmp_path)
    assert p.returncode == 0, p.stderr[-2000:]
    rows = pd.read_csv(tmp_path / "run" / "results.csv")
    assert (rows["n_kept"] == 300).all() and (rows["samples"] == 300).all()
    assert np.allclose(rows["ratio"], 300 / rows["n_in"])
    assert set(rows["scores"]) <= {"exact", "estimate"}
    forced = run("limit=1", "samples=300", "sampler.scores=estimate", f"cache.dir={tmp_path / 'cache'}",
                 tmp=tmp_path / "est")  # fmt: skip
    assert forced.returncode == 0, forced.stderr[-2000:]
    row = pd.read_csv(tmp_path / "est" / "run" / "results.csv").iloc[0]
    assert row["scores"] == "estimate" and row["anchors"] >= 32
    bad = run("samples=2", tmp=tmp_path / "bad")
    assert bad.returncode == 2 and "samples must be" in bad.stdout + bad.stderr
    bad = run("sampler.scores=approx", tmp=tmp_path / "bad2")
    assert bad.returncode == 2 and "sampler.scores must be one of" in bad.stdout + bad.stderr


def _blob_pair(tmp: Path) -> tuple[Path, Path, np.ndarray]:
    """A bumpy closed surface (FPFH finds matches on it) and the same surface under a known pose."""
    from fastmac_exp.geometry.transforms import random_rotation

    rng = np.random.default_rng(0)
    u, v = rng.uniform(0, 2 * np.pi, 8000), rng.uniform(0, np.pi, 8000)
    r = 1.5 + 0.3 * np.sin(3 * u) * np.sin(2 * v)
    pts = np.stack([r * np.cos(u) * np.sin(v), r * np.sin(u) * np.sin(v), r * np.cos(v)], 1)
    gt = np.eye(4)
    gt[:3, :3], gt[:3, 3] = random_rotation(rng), [0.3, -0.2, 0.1]
    np.save(tmp / "src.npy", pts)
    np.save(tmp / "tgt.npy", pts @ gt[:3, :3].T + gt[:3, 3])
    return tmp / "src.npy", tmp / "tgt.npy", gt


def test_a_pair_without_ground_truth_says_not_scored_and_gives_its_pose(tmp_path):
    """No GT: not a failure; the summary prints the estimated pose with its confidence and writes it as a
    4x4 file that dataset.gt reads back (the pair then registers against it exactly)."""
    from fastmac_exp.geometry.metrics import pose_errors
    from fastmac_exp.io import read_matrix

    src, tgt, gt = _blob_pair(tmp_path)
    p = run("dataset=pairs", f"dataset.source={src}", f"dataset.target={tgt}", tmp=tmp_path)
    assert p.returncode == 0, p.stderr[-2000:]
    out = p.stdout
    assert "pairs: 1  no ground truth (not scored): 1  failed with an error: 0" in out
    assert "RR: no ground truth: not scored" in out and "RR: 0.0%" not in out
    pose_path = tmp_path / "run" / "poses" / "src+tgt.txt"
    assert "src+tgt: no ground truth: not scored; clique of " in out
    assert f"source -> target, {pose_path}):" in out
    pose = read_matrix(pose_path)
    assert pose_errors(pose, gt, 5.0, 0.1).success  # the estimate is the right one
    p = run("dataset=pairs", f"dataset.source={src}", f"dataset.target={tgt}", f"dataset.gt={pose_path}",
            tmp=tmp_path / "again")  # fmt: skip
    assert p.returncode == 0, p.stderr[-2000:]
    assert "pairs: 1  registered: 1 of 1  failed with an error: 0" in p.stdout


def test_pairs_of_kitti_bin_files_take_the_kitti_family_and_say_so(tmp_path):
    """Issue 49 item 6: dataset=pairs with Velodyne .bin files ran under family=3dmatch without a word
    (707 ms to describe instead of 147 ms with dataset.family=kitti)."""
    import pandas as pd

    src, tgt, _ = _blob_pair(tmp_path)
    bins = []
    for path in (src, tgt):  # a 90 m outdoor-sized blob as float32 x y z reflectance
        pts = np.load(path) * 30.0
        np.c_[pts, np.ones(len(pts))].astype("<f4").tofile(path.with_suffix(".bin"))
        bins.append(path.with_suffix(".bin"))
    p = run("dataset=pairs", f"dataset.source={bins[0]}", f"dataset.target={bins[1]}", tmp=tmp_path)
    out = p.stdout + p.stderr
    assert p.returncode in (0, 1), out[-2000:]  # registered or not: the family is the point here
    assert (
        "src+tgt: family=kitti (the files are KITTI Velodyne .bin scans; dataset.family=3dmatch for the "
        "indoor rules)" in out
    )
    assert "family=kitti descriptor=fpfh" in p.stdout  # the summary's header
    assert pd.read_csv(tmp_path / "run" / "results.csv")["family"].tolist() == ["kitti"]


def test_group_mistakes_get_one_line_and_exit_2(tmp_path):
    """Issue 42 item 5: a group outside the defaults without its +, an unknown option of a group."""
    cases = {
        "method=mac": "method is a config group that the defaults do not include: add it with a +, "
        "+method=mac",
        "sampler=nosuch": "unknown sampler 'nosuch' (choose one of allpass, deterministic, fps, highpass,",
        "+method=fastmac": "unknown method 'fastmac'; did you mean 'fastmac20' or 'fastmac20_turboreg' or "
        "'fastmac50'? (choose one of ",
    }
    for override, message in cases.items():
        p = run(override, tmp=tmp_path)
        out = (p.stdout + p.stderr).strip()
        assert p.returncode == 2, (override, out[-2000:])
        assert len(out.splitlines()) == 1 and out.startswith(message), (override, out)
        assert not (tmp_path / "run").exists()


def test_every_sweep_member_is_checked_before_the_first_starts(tmp_path):
    """Issue 42 item 7: member 1's ratio is refused before member 0 runs: one line, exit 2, no directory."""
    p = sweep("ratio=0.2,1.5", "limit=1", sweep_dir=tmp_path / "S")
    out = (p.stdout + p.stderr).strip()
    assert p.returncode == 2, out[-2000:]
    assert out == (
        "sweep member 1 (ratio=1.5): ratio must be a number in (0, 1] or auto, got 1.5 (config key: ratio); "
        "no member was started"
    )
    assert not (tmp_path / "S").exists()


def test_devices_and_providers_are_checked_before_anything_is_created(tmp_path):
    """Issue 42 item 4: a GPU this machine lacks, a device name torch does not know, a provider onnxruntime
    does not know: one line, exit 2, no run directory."""
    import torch

    cases = {
        "sampler.device=gpu": "sampler.device must be cpu or cuda (cuda:N for the N-th GPU), got 'gpu'",
        "descriptor.execution_providers=[cdua,cpu]": (
            "descriptor.execution_providers: unknown provider 'cdua'"
        ),
    }
    if not torch.cuda.is_available():
        cases["sampler.device=cuda"] = "sampler.device=cuda, but torch"
    else:
        cases["sampler.device=cuda"] = "sampler.device=cuda is the torch engine's: add sampler.impl=torch"
    for override, message in cases.items():
        extra = ("descriptor=fcgf_lite",) if "execution_providers" in override else ()
        p = run(*extra, override, tmp=tmp_path)
        out = (p.stdout + p.stderr).strip()
        assert p.returncode == 2 and message in out, (override, out[-2000:])
        assert len(out.splitlines()) == 1, out
        assert not (tmp_path / "run").exists()


def test_the_row_says_which_engine_computed_the_samplers_signals(tmp_path):
    import pandas as pd

    p = run("limit=1", "sampler.impl=torch", tmp=tmp_path)
    assert p.returncode == 0, p.stderr[-2000:]
    assert pd.read_csv(tmp_path / "run" / "results.csv")["engine"].tolist() == ["torch:cpu"]
