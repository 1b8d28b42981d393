"""Zip members into a data set's folder: only safe relative paths, each file written whole (a temporary
name, then a rename), with its size and sha256 for the manifest."""

from __future__ import annotations

import hashlib
import os
import shutil
import zipfile
from collections.abc import Callable, Iterable
from pathlib import Path, PurePosixPath
from typing import IO

from fastmac_exp.atomic import temp_name
from fastmac_exp.errors import InputError

CHUNK = 1 << 20
SKIP = ("__MACOSX/",)


def safe_member(name: str) -> str | None:
    """The member's path if it is a plain relative file path inside the archive, else None."""
    p = PurePosixPath(name)
    if name.endswith("/") or name.startswith(SKIP) or p.is_absolute() or ".." in p.parts or not p.parts:
        return None
    return str(p)


def members(zf: zipfile.ZipFile, select: Callable[[str], bool]) -> list[zipfile.ZipInfo]:
    return [i for i in zf.infolist() if safe_member(i.filename) and select(i.filename)]


def zip_problem(path: Path, select: Callable[[str], bool]) -> str | None:
    """None for a readable zip holding selected members with good CRCs, else what is wrong."""
    try:
        with zipfile.ZipFile(path) as zf:
            chosen = members(zf, select)
            if not chosen:
                return "the archive holds none of the expected files"
            for info in chosen:
                with zf.open(info) as f:  # reading to the end checks the member's CRC-32
                    while f.read(CHUNK):
                        pass
    except (zipfile.BadZipFile, zipfile.LargeZipFile, EOFError, OSError) as exc:
        return f"not a readable zip archive ({exc})"
    return None


def write_whole(src: IO[bytes], dest: Path) -> dict[str, int | str]:
    """Copy a stream into `dest` through a temporary file; its size and sha256."""
    dest.parent.mkdir(parents=True, exist_ok=True)
    tmp = temp_name(dest)
    h = hashlib.sha256()
    n = 0
    try:
        with open(tmp, "wb") as out:
            for block in iter(lambda: src.read(CHUNK), b""):
                out.write(block)
                h.update(block)
                n += len(block)
        os.replace(tmp, dest)
    except BaseException:
        tmp.unlink(missing_ok=True)
        raise
    return {"size": n, "sha256": h.hexdigest()}


def unpack_zip(
    archive: Path, folder: Path, select: Callable[[str], bool], rename: Callable[[str], str] = str
) -> dict[str, dict[str, int | str]]:
    """Extract the selected members into `folder` (at `rename(member)`); relative path -> size, sha256."""
    out = {}
    with zipfile.ZipFile(archive) as zf:
        for info in members(zf, select):
            rel = rename(safe_member(info.filename) or "")
            with zf.open(info) as src:
                out[rel] = write_whole(src, folder / rel)
    return out


def place_file(src: Path, folder: Path, rel: str, move: bool = True) -> dict[str, dict[str, int | str]]:
    """A single downloaded file into the folder at `rel`."""
    dest = folder / rel
    dest.parent.mkdir(parents=True, exist_ok=True)
    with open(src, "rb") as f:
        entry = write_whole(f, dest)
    if move:
        src.unlink()
    return {rel: entry}


def copy_tree(files: Iterable[tuple[Path, str]], folder: Path) -> dict[str, dict[str, int | str]]:
    """(source file, relative destination) pairs copied into `folder` whole."""
    out = {}
    for src, rel in files:
        if not src.is_file():
            raise InputError(f"{src}: not a file")
        with open(src, "rb") as f:
            out[rel] = write_whole(f, folder / rel)
    return out


def remove_tree(path: Path) -> None:
    shutil.rmtree(path, ignore_errors=True)
