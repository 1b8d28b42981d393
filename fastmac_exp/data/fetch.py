"""fetch and verify: a data set's files from the registry into the data home, each recorded in the
manifest as it lands (a fetch started again skips what is there and resumes what was cut), then the
structure check; verify re-reads every recorded file against its size and sha256."""

from __future__ import annotations

import logging
import os
from dataclasses import dataclass
from pathlib import Path

import requests

from fastmac_exp.data.checks import run_check
from fastmac_exp.data.download import FetchError, check_space, fetch_file, keep_aside, new_session, sha256_of
from fastmac_exp.data.home import Manifest, data_home, dataset_dir, downloads_dir, quarantine_dir
from fastmac_exp.data.kitti import fcgf_scan_members, fetch_members
from fastmac_exp.data.sources import DataSet, Registry, SourceFile, human_size, load_registry
from fastmac_exp.data.unpack import place_file, unpack_zip, zip_problem
from fastmac_exp.errors import InputError

log = logging.getLogger("fastmac_exp.data")


@dataclass
class Options:
    home: Path
    registry: Registry
    progress: bool = True
    whole_archives: bool = False
    session: requests.Session | None = None


def options(home: Path | None = None, registry: Registry | None = None, **kw) -> Options:
    return Options(home=home or data_home(), registry=registry or load_registry(), **kw)


def is_complete(name: str, home: Path) -> bool:
    return Manifest(dataset_dir(name, home)).complete


def fetch(name: str, opt: Options) -> str:
    """Fetch data set `name` (and the data sets it needs); the structure check's summary."""
    ds = opt.registry.get(name)
    if not ds.fetchable:
        raise InputError(f"{name}: {ds.title} cannot be fetched by a script. {ds.manual or ''}".strip())
    for dep in ds.needs:
        if not is_complete(dep, opt.home):
            log.info("%s needs %s: fetching it first", name, dep)
            fetch(dep, opt)
    folder = dataset_dir(name, opt.home)
    man = Manifest(folder)
    todo = [f for f in ds.files if man.source(f.name) is None]
    if todo and len(todo) == len(ds.files):
        check_space(opt.home, ds.size, f"fetch {name} ({human_size(ds.size)})")
    session = opt.session or new_session()
    for sf in ds.files:
        if man.source(sf.name) is not None:
            log.info("%s: %s already fetched", name, sf.path)
            continue
        entry = _fetch_one(ds, sf, folder, opt, session)
        man.record(sf.name, entry)
        if not entry.get("pinned", True):
            log.info("%s: %s sha256 %s (recorded; pin it in a sources file)", name, sf.path, entry["sha256"])
    summary = run_check(ds.check, folder, opt.home)
    man.finish(summary)
    log.info("%s: complete in %s: %s", name, folder, summary)
    return summary


def _fetch_one(ds: DataSet, sf: SourceFile, folder: Path, opt: Options, session) -> dict:
    select = sf.selects
    if sf.select == "kitti-fcgf-scans":
        wanted = fcgf_scan_members(folder)
        select = wanted.__contains__
    if sf.remote and not opt.whole_archives:
        url, files = fetch_members(sf.urls, folder, select, sf.archive_size, opt.progress, session)
        return {"url": url, "members": len(files), "files": files, "pinned": True}
    dest = downloads_dir(opt.home) / ds.name / sf.name
    validate = (lambda p: zip_problem(p, select)) if sf.unpack == "zip" else None
    got = None
    if dest.is_file():  # downloaded and checked before an interruption, not yet unpacked
        why = validate(dest) if validate else None
        if why is None and (sf.sha256 is None or sha256_of(dest) == sf.sha256):
            got = (sf.urls[0] + " (downloaded earlier)", dest.stat().st_size, sha256_of(dest))
        else:
            keep_aside(dest, quarantine_dir(opt.home), why or "sha256 mismatch")
    if got is None:
        f = fetch_file(
            sf.urls, dest, quarantine_dir(opt.home), sf.size, sf.sha256, validate, opt.progress, session
        )
        got = (f.url, f.size, f.sha256)
    if sf.unpack == "zip":
        files = unpack_zip(dest, folder, select)
        os.unlink(dest)
    else:
        files = place_file(dest, folder, sf.path)
    url, size, digest = got
    return {"url": url, "size": size, "sha256": digest, "pinned": sf.sha256 is not None, "files": files}


def verify(name: str, opt: Options) -> list[str]:
    """Lines of a verification: every recorded file's size and sha256, then the structure check; raises
    InputError naming the first files that differ."""
    ds = opt.registry.get(name)
    folder = dataset_dir(name, opt.home)
    man = Manifest(folder)
    if not man.data["sources"]:
        raise InputError(f"{name}: nothing in {folder}; {fetch_hint(ds)}")
    bad, lines = [], []
    for src_name, entry in man.data["sources"].items():
        pin = next((f.sha256 for f in ds.files if f.name == src_name), None)
        if pin and entry.get("sha256") and entry["sha256"] != pin:
            bad.append(f"{src_name}: fetched with sha256 {entry['sha256']}, the registry pins {pin}")
        if entry.get("sha256"):
            lines.append(f"{src_name}  sha256 {entry['sha256']}  ({'pinned' if pin else 'recorded'})")
    files = man.files()
    for rel, want in files.items():
        p = folder / rel
        if not p.is_file():
            bad.append(f"{p} missing")
        elif p.stat().st_size != want["size"]:
            bad.append(f"{p}: {p.stat().st_size} bytes, {want['size']} recorded")
        elif sha256_of(p) != want["sha256"]:
            bad.append(f"{p}: sha256 differs from the one recorded at the fetch")
    if bad:
        more = f" (and {len(bad) - 5} more)" if len(bad) > 5 else ""
        raise InputError(f"{name}: {len(bad)} file(s) differ: " + "; ".join(bad[:5]) + more)
    lines.append(f"{len(files)} files match their recorded size and sha256")
    lines.append(f"structure: {run_check(ds.check, folder, opt.home)}")
    return lines


def fetch_hint(ds: DataSet) -> str:
    if ds.fetchable:
        return f"fetch it with: fastmac-exp data fetch {ds.name}  (about {human_size(ds.size)})"
    return ds.manual or f"add it with: fastmac-exp data add {ds.name} FILE_OR_DIR"


__all__ = ["FetchError", "Options", "fetch", "fetch_hint", "is_complete", "options", "verify"]
