"""`fastmac-exp data` against a real HTTP server on 127.0.0.1 serving archives in the upstream layouts
(tests/data_fixtures.py): fetch, resume after a cut, a server without ranges, a corrupted archive kept
aside, a 404 then a working mirror, add from local archives, KITTI's members by range requests, and the
headline command on the fetched fixture. Nothing here leaves the machine."""

from __future__ import annotations

import hashlib
import json
import logging
import os
import subprocess
import sys
from pathlib import Path

import pandas as pd
import pytest

from fastmac_exp.data import fetch as fetch_mod
from fastmac_exp.data.add import add
from fastmac_exp.data.download import FetchError, fetch_file
from fastmac_exp.data.fetch import Options, fetch, verify
from fastmac_exp.data.home import Manifest
from fastmac_exp.data.kitti import NeedsWholeArchive, fcgf_test_pairs, scan_member
from fastmac_exp.data.sources import load_registry
from fastmac_exp.datasets.mac_layout import SCENES_3DMATCH
from fastmac_exp.errors import InputError
from tests.data_fixtures import (
    FixtureServer,
    kitti_archives,
    lomatch_files,
    sources_file,
    threedmatch_archives,
)

REPO = Path(__file__).resolve().parents[1]


@pytest.fixture(scope="module")
def archives():
    return threedmatch_archives()


@pytest.fixture
def server(archives):
    with FixtureServer() as s:
        for name, data in archives.items():
            s.files[f"/a/{name}"] = data
            s.files[f"/b/{name}"] = data
        for rel, data in lomatch_files(archives).items():
            s.files[f"/lo/{rel}"] = data
        for name, data in kitti_archives().items():
            s.files[f"/kitti/{name}"] = data
        yield s


def _sources(tmp_path: Path, server: FixtureServer, first: str = "a", lomatch_pins: bool = False) -> Path:
    lo = {}
    if lomatch_pins:
        files = [
            {
                "path": rel,
                "mirrors": "lomatch-gt",
                "unpack": "none",
                "size": len(server.files[f"/lo/{rel}"]),
                "sha256": hashlib.sha256(server.files[f"/lo/{rel}"]).hexdigest(),
            }
            for rel in sorted(k.removeprefix("/lo/") for k in server.files if k.startswith("/lo/"))
        ]
        lo = {"3dlomatch": {"title": "fixture", "needs": ["3dmatch"], "check": "lomatch", "files": files}}
    return sources_file(
        tmp_path / "sources.yaml",
        {
            "princeton-fragments": [f"{server.base}/{first}/", f"{server.base}/b/"],
            "lomatch-gt": [f"{server.base}/bad-lo/", f"{server.base}/lo/"],
            "kitti-odometry": [f"{server.base}/kitti/"],
        },
        lo,
    )


def _opt(tmp_path: Path, server: FixtureServer, **kw) -> Options:
    return Options(
        home=tmp_path / "home", registry=load_registry(_sources(tmp_path, server, **kw)), progress=False
    )


def _served(server: FixtureServer, prefix: str) -> int:
    return sum(n for p, n in server.served.items() if p.startswith(prefix))


def _env(tmp_path: Path, sources: Path | None) -> dict[str, str]:
    env = {**os.environ, "PYTHONPATH": str(REPO), "FASTMAC_DATA": str(tmp_path / "home")}
    env.pop("FASTMAC_DATA_SOURCES", None)
    if sources is not None:
        env["FASTMAC_DATA_SOURCES"] = str(sources)
    return env


# -- the two README commands on the fixture --
def test_fetch_then_headline_command_runs_with_no_other_key(tmp_path, server, archives):
    env = _env(tmp_path, _sources(tmp_path, server))
    f = subprocess.run(
        [sys.executable, "-m", "fastmac_exp", "data", "fetch", "3dmatch"],
        cwd=tmp_path,
        env=env,
        capture_output=True,
        text=True,
        timeout=120,
    )
    assert f.returncode == 0, f.stderr
    assert "3dmatch: complete: 8 scenes, 16 fragments, 8 pairs" in f.stdout
    assert "run it: python run.py dataset=3dmatch" in f.stdout
    assert _served(server, "/a/") == sum(len(d) for d in archives.values()) and _served(server, "/b/") == 0
    home = tmp_path / "home" / "3dmatch"
    assert (home / SCENES_3DMATCH[0] / "cloud_bin_1.ply").is_file() and not list(home.rglob("*.part"))
    r = subprocess.run(
        [sys.executable, str(REPO / "run.py"), "sampler=highpass", "ratio=0.05", "dataset=3dmatch"],
        cwd=tmp_path,
        env=env,
        capture_output=True,
        text=True,
        timeout=300,
    )
    assert r.returncode == 0, r.stdout + r.stderr
    run_dir = next((tmp_path / "outputs" / "runs").iterdir())
    rows = pd.read_csv(run_dir / "results.csv")
    assert len(rows) == 8 and set(rows.descriptor) == {"fpfh"} and rows.error.isna().all()
    summary = json.loads((run_dir / "summary.json").read_text())
    assert summary["RR"] == pytest.approx(rows.success.mean())
    assert rows.success.mean() >= 0.75, rows[["pair", "re_deg", "te_cm"]]  # the GT's direction is right
    assert "raw fragments" in r.stdout + r.stderr


def test_without_data_the_run_names_the_fetch_command_and_exits_2(tmp_path):
    r = subprocess.run(
        [sys.executable, str(REPO / "run.py"), "dataset=3dmatch"],
        cwd=tmp_path,
        env=_env(tmp_path, None),
        capture_output=True,
        text=True,
        timeout=120,
    )
    out = r.stdout + r.stderr
    assert r.returncode == 2
    assert "fastmac-exp data fetch 3dmatch  (about 1.3 GB)" in out and "Traceback" not in out
    r = subprocess.run(
        [sys.executable, "-m", "fastmac_exp.data", "path", "3dlomatch"],
        cwd=tmp_path,
        env=_env(tmp_path, None),
        capture_output=True,
        text=True,
        timeout=60,
    )
    assert r.returncode == 1 and r.stdout.strip() == str(tmp_path / "home" / "3dlomatch")


# -- resumable, atomic --
def test_a_cut_connection_resumes_where_it_stopped(tmp_path, server, archives):
    name = f"{SCENES_3DMATCH[0]}.zip"
    server.cut[f"/a/{name}"], server.cuts[f"/a/{name}"] = 5000, 2
    got = fetch_file([f"{server.base}/a/{name}"], tmp_path / name, tmp_path / "q", progress=False)
    assert got.path.read_bytes() == archives[name]
    assert server.served[f"/a/{name}"] == len(archives[name])  # nothing sent twice
    ranges = [r for m, p, r in server.requests if p == f"/a/{name}"]
    assert ranges == [None, "bytes=5000-", "bytes=10000-"]


def test_an_interrupted_fetch_started_again_downloads_only_what_is_missing(tmp_path, server, archives):
    opt = _opt(tmp_path, server)
    third = f"/a/{SCENES_3DMATCH[1]}.zip"
    server.cut[third], server.cuts[third] = 3000, 99  # this mirror keeps dropping it; the other has none
    server.missing.add(third.replace("/a/", "/b/"))
    with pytest.raises(FetchError, match="no mirror delivered"):
        fetch("3dmatch", opt)
    assert (opt.home / "downloads" / "3dmatch" / f"{SCENES_3DMATCH[1]}.zip.part").is_file()
    before = dict(server.served)
    server.cuts[third] = 0
    fetch("3dmatch", opt)
    again = {p: n - before.get(p, 0) for p, n in server.served.items()}
    total = sum(len(d) for d in archives.values())
    assert sum(again.values()) == total - sum(before.values())  # only the missing bytes, once
    assert again.get(f"/a/{SCENES_3DMATCH[0]}.zip", 0) == 0
    assert Manifest(opt.home / "3dmatch").complete


def test_a_server_without_range_support_starts_the_file_over(tmp_path, server, archives, caplog):
    name = f"{SCENES_3DMATCH[2]}.zip"
    server.ranges = False
    server.cut[f"/a/{name}"], server.cuts[f"/a/{name}"] = 4000, 1
    with caplog.at_level(logging.WARNING, "fastmac_exp.data"):
        got = fetch_file([f"{server.base}/a/{name}"], tmp_path / name, tmp_path / "q", progress=False)
    assert got.path.read_bytes() == archives[name]
    assert server.served[f"/a/{name}"] == 4000 + len(archives[name])
    assert "ignores range requests" in caplog.text


# -- checks and mirrors --
def test_a_corrupted_archive_is_kept_aside_and_the_next_mirror_used(tmp_path, server, archives, caplog):
    name = f"{SCENES_3DMATCH[0]}-evaluation.zip"
    server.files[f"/a/{name}"] = archives[name][:-40] + b"\0" * 40  # the zip's directory is gone
    opt = _opt(tmp_path, server)
    with caplog.at_level(logging.WARNING, "fastmac_exp.data"):
        fetch("3dmatch", opt)
    kept = list((opt.home / "quarantine").glob(f"{name}.*"))
    assert len(kept) == 2 and any(k.read_bytes() == server.files[f"/a/{name}"] for k in kept)
    assert (
        "not a readable zip" in caplog.text
        and f"trying the next mirror {server.base}/b/{name}" in caplog.text
    )
    assert Manifest(opt.home / "3dmatch").source(name)["url"] == f"{server.base}/b/{name}"


def test_a_404_goes_to_the_next_mirror_in_one_line(tmp_path, server, caplog):
    opt = _opt(tmp_path, server, first="gone", lomatch_pins=True)
    with caplog.at_level(logging.WARNING, "fastmac_exp.data"):
        fetch("3dlomatch", opt)  # needs 3dmatch: fetched first, from the second mirror
    lines = [r.getMessage() for r in caplog.records]
    first = f"{server.base}/gone/{SCENES_3DMATCH[0]}.zip"
    assert (
        f"{first}: HTTP 404 Not Found; trying the next mirror {server.base}/b/{SCENES_3DMATCH[0]}.zip"
        in lines
    )
    assert Manifest(opt.home / "3dlomatch").complete and Manifest(opt.home / "3dmatch").complete
    assert all("\n" not in line for line in lines)


def test_a_sha256_mismatch_is_refused_and_kept(tmp_path, server):
    rel = f"{SCENES_3DMATCH[3]}/gt.log"
    server.files[f"/bad-lo/{rel}"] = server.files[f"/lo/{rel}"].replace(b"0\t1\t2", b"0\t1\t3")
    opt = _opt(tmp_path, server, lomatch_pins=True)
    fetch("3dlomatch", opt)
    kept = list((opt.home / "quarantine").glob(f"{SCENES_3DMATCH[3]}__gt.log.*.why.txt"))
    assert len(kept) == 1 and "sha256" in kept[0].read_text()
    assert (opt.home / "3dlomatch" / rel).read_bytes() == server.files[f"/lo/{rel}"]


def test_no_mirror_left_is_one_error_naming_what_to_do(tmp_path, server):
    server.missing |= {p for p in server.files if p.startswith(("/a/", "/b/"))}
    with pytest.raises(FetchError) as e:
        fetch("3dmatch", _opt(tmp_path, server))
    msg = str(e.value)
    assert "\n" not in msg and f"{server.base}/a/" in msg and f"{server.base}/b/" in msg and "data add" in msg


def test_a_fetch_larger_than_the_free_disk_is_refused(tmp_path, server):
    path = sources_file(
        tmp_path / "s.yaml",
        {"princeton-fragments": [f"{server.base}/a/"]},
        {
            "3dmatch": {
                "title": "t",
                "size": 10**18,
                "check": "fragments",
                "files": [{"path": f"{SCENES_3DMATCH[0]}.zip", "mirrors": "princeton-fragments"}],
            }
        },
    )
    with pytest.raises(FetchError, match="needs 1000000000.00 GB"):
        fetch("3dmatch", Options(home=tmp_path / "h", registry=load_registry(path), progress=False))
    assert not server.served


def test_verify_finds_a_changed_file_and_the_structure_check_a_missing_one(tmp_path, server):
    opt = _opt(tmp_path, server)
    fetch("3dmatch", opt)
    assert verify("3dmatch", opt)[-1] == "structure: 8 scenes, 16 fragments, 8 pairs"
    ply = opt.home / "3dmatch" / SCENES_3DMATCH[4] / "cloud_bin_0.ply"
    ply.write_bytes(ply.read_bytes()[:-12] + b"\0" * 12)
    with pytest.raises(InputError, match=r"1 file\(s\) differ: .*cloud_bin_0\.ply: sha256"):
        verify("3dmatch", opt)
    ply.unlink()
    with pytest.raises(InputError, match=r"cloud_bin_0\.ply missing"):
        fetch_mod.run_check("fragments", opt.home / "3dmatch", opt.home)


# -- add --
def test_add_from_local_archives_and_folders(tmp_path, archives, server):
    downloads = tmp_path / "dl"
    downloads.mkdir()
    for name, data in archives.items():
        (downloads / name).write_bytes(data)
    opt = Options(home=tmp_path / "home", registry=load_registry(), progress=False)
    assert add("3dmatch", downloads, opt) == "8 scenes, 16 fragments, 8 pairs"
    geo = tmp_path / "GeoTransformer" / "data" / "3DMatch" / "metadata" / "benchmarks"
    for rel, data in lomatch_files(archives).items():  # GeoTransformer's tree holds both benchmarks
        for bench, payload in (("3DLoMatch", data), ("3DMatch", b"not this one\n")):
            (geo / bench / rel).parent.mkdir(parents=True, exist_ok=True)
            (geo / bench / rel).write_bytes(payload)
    assert add("3dlomatch", geo, opt).startswith("8 scenes, 8 pairs")
    with pytest.raises(InputError, match="recognised none of kitti's files; add takes KITTI's"):
        add("kitti", downloads, opt)
    assert not server.served


# -- KITTI: members by range requests --
def test_kitti_fetches_only_the_scans_of_the_test_pairs(tmp_path, server):
    opt = _opt(tmp_path, server)
    summary = fetch("kitti", opt)
    root = opt.home / "kitti" / "dataset"
    pairs = fcgf_test_pairs(root)
    scans = {scan_member(s, f) for s, a, b in pairs for f in (a, b)}
    have = {p.relative_to(opt.home / "kitti").as_posix() for p in root.rglob("*.bin")}
    assert (
        have == scans
        and len(pairs) == 3 * 2
        and summary.endswith(f"{len(pairs)} pairs over {len(scans)} scans")
    )
    velo = len(server.files["/kitti/data_odometry_velodyne.zip"])
    assert _served(server, "/kitti/data_odometry_velodyne.zip") < velo / 4
    before = dict(server.served)
    fetch("kitti", opt)  # complete: nothing is fetched again
    assert server.served == before


def test_kitti_without_range_support_says_the_archive_size(tmp_path, server):
    server.ranges = False
    opt = _opt(tmp_path, server)
    with pytest.raises(NeedsWholeArchive, match="does not answer HTTP range requests.*4.0 MB"):
        fetch("kitti", opt)
    opt.whole_archives = True
    fetch("kitti", opt)
    assert len(list((opt.home / "kitti" / "dataset").rglob("*.bin"))) == 12


# -- the front end follows what the data home holds --
def _mac_layout(root: Path) -> Path:
    """MAC's released 3DMatch layout, one pair a scene: dataload.txt, A+B@corr.txt, @label.txt, @GTmat.txt."""
    import numpy as np

    rng = np.random.default_rng(0)
    for scene in SCENES_3DMATCH:
        d = root / scene
        d.mkdir(parents=True)
        (d / "dataload.txt").write_text("cloud_bin_1+cloud_bin_0\n")
        src = rng.uniform(0, 2, (60, 3))
        np.savetxt(d / "cloud_bin_1+cloud_bin_0@corr.txt", np.c_[src, src + [0.5, 0, 0]])
        np.savetxt(d / "cloud_bin_1+cloud_bin_0@label.txt", np.ones(60), fmt="%d")
        gt = np.eye(4)
        gt[0, 3] = 0.5
        np.savetxt(d / "cloud_bin_1+cloud_bin_0@GTmat.txt", gt)
    return root


def test_the_front_end_is_picked_by_what_is_there(tmp_path, server, monkeypatch):
    from hydra import compose, initialize_config_dir

    from fastmac_exp.descriptors.fpfh import FPFHDescriptor
    from fastmac_exp.descriptors.precomputed import PrecomputedDescriptor
    from fastmac_exp.resources import config_dir
    from fastmac_exp.run.experiment import Components

    opt = _opt(tmp_path, server)
    monkeypatch.setenv("FASTMAC_DATA", str(opt.home))

    def parts(*overrides):
        with initialize_config_dir(str(config_dir()), version_base="1.3"):
            return Components(compose("config", overrides=["dataset=3dmatch", *overrides]))

    fetch("3dmatch", opt)
    raw = parts()
    assert isinstance(raw.descriptor, FPFHDescriptor) and len(raw.names()) == 8
    with pytest.raises(InputError, match="descriptor=precomputed needs MAC's released fpfh correspondences"):
        parts("descriptor=precomputed")
    assert add("mac-3dmatch", _mac_layout(tmp_path / "mac"), opt) == "8 pairs (descriptor fpfh)"
    pre = parts()  # the default fpfh, with MAC's FPFH correspondences there: those are read
    assert (
        isinstance(pre.descriptor, PrecomputedDescriptor) and pre.dataset.chosen["front_end"] == "precomputed"
    )
    assert pre._cache_parts["data"] != raw._cache_parts["data"]  # the cache tells the two apart
    assert pre.dataset.load(0).correspondences is not None
    forced = parts("dataset.front_end=raw")
    assert isinstance(forced.descriptor, FPFHDescriptor) and forced.dataset.load(0).src_cloud is not None
