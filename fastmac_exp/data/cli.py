"""`fastmac-exp data list | fetch NAME | add NAME FILE_OR_DIR | verify NAME | path NAME` (also
`python -m fastmac_exp.data ...`). Exit 0 on success, 1 when a download or a check fails, 2 on bad input;
every failure is one line on stderr."""

from __future__ import annotations

import argparse
import logging
import sys
from pathlib import Path

from fastmac_exp.data.add import FORMS, add
from fastmac_exp.data.download import FetchError
from fastmac_exp.data.fetch import fetch, fetch_hint, options, verify
from fastmac_exp.data.home import Manifest, data_home, dataset_dir
from fastmac_exp.data.kitti import NeedsWholeArchive
from fastmac_exp.data.sources import human_size
from fastmac_exp.errors import InputError

log = logging.getLogger("fastmac_exp.data")
RUN_HINT = {
    "3dmatch": "3dmatch",
    "3dlomatch": "3dlomatch",
    "kitti": "kitti",
    "mac-3dmatch": "3dmatch",
    "mac-3dlomatch": "3dlomatch",
    "mac-kitti": "kitti",
}


def parser() -> argparse.ArgumentParser:
    p = argparse.ArgumentParser(
        prog="fastmac-exp data",
        description="The benchmarks' data in the data home ($FASTMAC_DATA, else the user data folder; "
        "docs/data.md).",
    )
    sub = p.add_subparsers(dest="command", required=True)
    ls = sub.add_parser("list", help="the data sets, their size and what the data home holds")
    ls.add_argument("--urls", action="store_true", help="every file's mirrors, in the order they are tried")
    f = sub.add_parser("fetch", help="download, check and file a data set (resumes an interrupted fetch)")
    f.add_argument("name")
    f.add_argument(
        "--whole-archives",
        action="store_true",
        help="download whole archives where only members are needed (a server without range requests)",
    )
    f.add_argument("--no-progress", action="store_true", help="no progress bars")
    a = sub.add_parser("add", help="file a copy you have (zip or folder) into the data home")
    a.add_argument("name")
    a.add_argument("path", type=Path)
    v = sub.add_parser("verify", help="re-check every fetched file's size and sha256, then the structure")
    v.add_argument("name")
    pa = sub.add_parser("path", help="print the data set's folder (exit 1 when it is not complete)")
    pa.add_argument("name")
    return p


def _status(name: str) -> str:
    man = Manifest(dataset_dir(name))
    if man.complete:
        return "complete"
    return "partial (fetch again to finish)" if man.data["sources"] else "-"


def cmd_list(args, opt) -> int:
    print(f"data home: {opt.home}")
    print(f"{'name':<14} {'size':>9}  {'in the home':<12} what")
    for ds in opt.registry.datasets.values():
        size = human_size(ds.size) if ds.fetchable else "add only"
        print(f"{ds.name:<14} {size:>9}  {_status(ds.name):<12} {ds.title}")
        if args.urls:
            for sf in ds.files:
                pin = f" sha256 {sf.sha256[:16]}..." if sf.sha256 else ""
                print(f"    {sf.path}{pin}\n" + "".join(f"      {u}\n" for u in sf.urls), end="")
            if ds.manual:
                print(f"    {ds.manual}")
    return 0


def cmd_fetch(args, opt) -> int:
    ds = opt.registry.get(args.name)
    if ds.fetchable:
        print(
            f"fetch {ds.name}: {ds.title}\n  {len(ds.files)} files, about {human_size(ds.size)}, into "
            f"{dataset_dir(ds.name, opt.home)}\n  licence: {ds.licence}"
        )
    try:
        summary = fetch(args.name, opt)
    except NeedsWholeArchive as exc:
        if (
            not sys.stdin.isatty()
            or input(f"{exc}\nDownload the whole archive ({human_size(exc.size)})? [y/N] ")[:1].lower() != "y"
        ):
            raise
        opt.whole_archives = True
        summary = fetch(args.name, opt)
    print(f"{ds.name}: complete: {summary}")
    for src, entry in Manifest(dataset_dir(ds.name, opt.home)).data["sources"].items():
        if entry.get("sha256"):
            print(f"  {src}  sha256 {entry['sha256']}  ({'pinned' if entry.get('pinned') else 'recorded'})")
    print(f"run it: python run.py dataset={RUN_HINT.get(ds.name, ds.name)}")
    return 0


def cmd_add(args, opt) -> int:
    summary = add(args.name, args.path, opt)
    print(f"{args.name}: complete in {dataset_dir(args.name, opt.home)}: {summary}")
    print(f"run it: python run.py dataset={RUN_HINT.get(args.name, args.name)}")
    return 0


def cmd_verify(args, opt) -> int:
    for line in verify(args.name, opt):
        print(line)
    print(f"{args.name}: verified")
    return 0


def cmd_path(args, opt) -> int:
    ds = opt.registry.get(args.name)
    print(dataset_dir(ds.name, opt.home))
    if _status(ds.name) != "complete":
        print(f"{ds.name} is not complete there; {fetch_hint(ds)}", file=sys.stderr)
        return 1
    return 0


COMMANDS = {"list": cmd_list, "fetch": cmd_fetch, "add": cmd_add, "verify": cmd_verify, "path": cmd_path}


def main(argv: list[str] | None = None) -> int:
    args = parser().parse_args(argv)
    handler = logging.StreamHandler(sys.stderr)
    handler.setFormatter(logging.Formatter("%(message)s"))
    log.addHandler(handler)
    log.setLevel(logging.INFO)
    log.propagate = False
    try:
        opt = options(
            home=data_home(), progress=not getattr(args, "no_progress", False) and sys.stderr.isatty()
        )
        if getattr(args, "whole_archives", False):
            opt.whole_archives = True
        return COMMANDS[args.command](args, opt)
    except FetchError as exc:
        print(f"error: {exc}", file=sys.stderr)
        return 1
    except InputError as exc:
        print(f"error: {exc}", file=sys.stderr)
        return 2
    except KeyboardInterrupt:
        print("interrupted: run the same command again to resume", file=sys.stderr)
        return 130
    finally:
        log.removeHandler(handler)


__all__ = ["FORMS", "main"]
