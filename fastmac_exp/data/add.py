"""add: file a data set the user already has (a per-scene zip, Predator's or GeoTransformer's archive or
folder, a folder of raw fragments with gt.log, a folder in MAC's precomputed layout, KITTI's official zips
or dataset/ folder) into the data home, by recognising each file's path, then the structure check.

Zips inside a given folder are read too, so a folder of the 16 downloaded 3DMatch zips adds in one go."""

from __future__ import annotations

import logging
import re
import zipfile
from collections.abc import Callable, Iterator
from pathlib import Path
from typing import IO

from fastmac_exp.data.checks import run_check
from fastmac_exp.data.fetch import Options
from fastmac_exp.data.home import Manifest, dataset_dir
from fastmac_exp.data.kitti import KITTI_SEQUENCES, fcgf_scan_members
from fastmac_exp.data.unpack import safe_member, write_whole
from fastmac_exp.datasets.mac_layout import LOMATCH_SUFFIX, SCENES_3DMATCH
from fastmac_exp.errors import InputError

log = logging.getLogger("fastmac_exp.data")

_SCENE = "(" + "|".join(re.escape(s) for s in SCENES_3DMATCH) + ")"
_SEQ = "(" + "|".join(f"{s:02d}" for s in KITTI_SEQUENCES) + ")"
_LO = re.compile(r"3DLoMatch|3dlomatch", re.I)
_MAC_FILE = r"(dataload(?:_fcgf)?\.txt|[^/]+@(?:corr|label|GTmat)(?:_fcgf)?\.txt|cloud_bin_\d+\.ply)"

# data set -> [(pattern over a file's path inside what was given, destination template)]
RULES: dict[str, list[tuple[re.Pattern, str]]] = {
    "3dmatch": [
        (re.compile(rf"(?:^|/){_SCENE}/(?:fragments/)?(cloud_bin_\d+\.ply)$"), r"\1/\2"),
        (re.compile(rf"(?:^|/){_SCENE}-evaluation/(gt\.log|gt\.info)$"), r"\1-evaluation/\2"),
        (re.compile(rf"(?:^|/){_SCENE}/(gt\.log|gt\.info)$"), r"\1-evaluation/\2"),
    ],
    "3dlomatch": [(re.compile(rf"(?:^|/){_SCENE}(?:{LOMATCH_SUFFIX})?/(gt\.log|gt\.info)$"), r"\1/\2")],
    "kitti": [
        (re.compile(rf"(?:^|/)(?:dataset/)?(poses/{_SEQ}\.txt)$"), r"dataset/\1"),
        (
            re.compile(rf"(?:^|/)(?:dataset/)?(sequences/{_SEQ}/(?:calib\.txt|velodyne/\d{{6}}\.bin))$"),
            r"dataset/\1",
        ),
    ],
    "mac-3dmatch": [(re.compile(rf"(?:^|/){_SCENE}/{_MAC_FILE}$"), r"\1/\2")],
    "mac-3dlomatch": [
        (re.compile(rf"(?:^|/){_SCENE}{LOMATCH_SUFFIX}/{_MAC_FILE}$"), rf"\1{LOMATCH_SUFFIX}/\2")
    ],
    "mac-kitti": [(re.compile(r"(?:^|/)(\d+)/([A-Za-z0-9_]+@(?:corr|gtmat|gtlabel)\.txt)$"), r"\1/\2")],
}
FORMS = {
    "3dmatch": "the 3DMatch toolbox's per-scene zips (<scene>.zip, <scene>-evaluation.zip) or a folder of "
    "them, Predator's 3dmatch.zip, or a folder <scene>/cloud_bin_*.ply with <scene>-evaluation/gt.log or "
    "<scene>/gt.log",
    "3dlomatch": "a folder (or zip) of <scene>/gt.log: GeoTransformer's "
    "data/3DMatch/metadata/benchmarks/3DLoMatch "
    "or Predator's configs/benchmarks/3DLoMatch",
    "kitti": "KITTI's data_odometry_{poses,calib,velodyne}.zip or their unpacked dataset/ folder",
    "mac-3dmatch": "a folder (or zip) in MAC's layout: <scene>/dataload.txt and <scene>/A+B@corr.txt ...",
    "mac-3dlomatch": "a folder (or zip) in MAC's layout with <scene>_3dlomatch/ folders",
    "mac-kitti": "a folder (or zip) of numbered pair folders <i>/<desc>@corr.txt ... "
    "(or correspondence_<desc>/)",
}


def _entries(path: Path) -> Iterator[tuple[str, Callable[[], IO[bytes]]]]:
    """(relative path, opener) of every file in a zip or a folder, zips inside a folder included."""
    if path.is_file() and zipfile.is_zipfile(path):
        zf = zipfile.ZipFile(path)
        for info in zf.infolist():
            name = safe_member(info.filename)
            if name:
                yield name, (lambda i=info: zf.open(i))
    elif path.is_dir():
        for p in sorted(path.rglob("*")):
            if p.is_file() and p.suffix == ".zip" and zipfile.is_zipfile(p):
                yield from _entries(p)
            elif p.is_file():
                yield p.relative_to(path).as_posix(), (lambda q=p: open(q, "rb"))
    else:
        raise InputError(f"{path}: not a folder or a zip archive")


def _destination(name: str, rel: str) -> str | None:
    if name == "3dmatch" and _LO.search(rel):
        return None  # 3DLoMatch's logs are another data set
    for pattern, template in RULES[name]:
        m = pattern.search(rel)
        if m:
            return m.expand(template)
    return None


def add(name: str, path: Path, opt: Options) -> str:
    """Copy what `path` holds of data set `name` into the data home; the structure check's summary."""
    if name not in RULES:
        raise InputError(f"unknown data set {name!r} for add; choose one of {', '.join(RULES)}")
    path = Path(path).expanduser()
    if not path.exists():
        raise InputError(f"{path}: no such file or folder")
    found = [(rel, dest, op) for rel, op in _entries(path) if (dest := _destination(name, rel))]
    if name == "3dlomatch" and any(_LO.search(rel) for rel, _, _ in found):
        found = [f for f in found if _LO.search(f[0])]  # GeoTransformer's folder holds 3DMatch's logs too
    if not found:
        raise InputError(f"{path}: recognised none of {name}'s files; add takes {FORMS[name]}")
    folder = dataset_dir(name, opt.home)
    files = {}
    if name == "kitti":
        scans = [f for f in found if "/velodyne/" in f[1]]
        for _, dest, op in [f for f in found if f not in scans]:
            with op() as src:
                files[dest] = write_whole(src, folder / dest)
        wanted = fcgf_scan_members(folder)
        found = [f for f in scans if f[1] in wanted]
    for _, dest, op in found:
        with op() as src:
            files[dest] = write_whole(src, folder / dest)
    log.info("%s: %d files from %s into %s", name, len(files), path, folder)
    man = Manifest(folder)
    man.record(f"add:{path.name}", {"url": str(path.resolve()), "files": files, "pinned": False})
    summary = run_check(opt.registry.get(name).check, folder, opt.home)
    man.finish(summary)
    return summary
