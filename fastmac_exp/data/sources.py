"""The sources registry: which files make each benchmark and the mirrors they come from (sources.yaml
beside this module, or a file of the same shape named by $FASTMAC_DATA_SOURCES replacing its entries)."""

from __future__ import annotations

import os
import re
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import yaml

from fastmac_exp.errors import InputError

BUILTIN = Path(__file__).with_name("sources.yaml")
SOURCES_ENV = "FASTMAC_DATA_SOURCES"
UNPACK = ("zip", "none")
SELECTORS = ("kitti-fcgf-scans",)  # members named by code (fastmac_exp.data.kitti), not a pattern


@dataclass(frozen=True)
class SourceFile:
    """One file of a data set: its path under each mirror's base URL and what it must be."""

    path: str
    urls: tuple[str, ...]
    size: int | None = None
    sha256: str | None = None
    unpack: str = "zip"
    select: str | None = None
    remote: bool = False
    archive_size: int | None = None

    @property
    def name(self) -> str:
        return self.path.replace("/", "__")

    def selects(self, member: str) -> bool:
        return self.select is None or re.search(self.select, member) is not None


@dataclass(frozen=True)
class DataSet:
    name: str
    title: str
    files: tuple[SourceFile, ...] = ()
    size: int | None = None
    licence: str = ""
    home: str = ""
    needs: tuple[str, ...] = ()
    check: str = ""
    manual: str | None = None  # a data set no script can fetch: how to get it by hand

    @property
    def fetchable(self) -> bool:
        return bool(self.files)


@dataclass(frozen=True)
class Registry:
    datasets: dict[str, DataSet] = field(default_factory=dict)
    origin: tuple[str, ...] = ()

    def get(self, name: str) -> DataSet:
        if name not in self.datasets:
            raise InputError(f"unknown data set {name!r}; choose one of {', '.join(self.datasets)}")
        return self.datasets[name]


def _read(path: Path) -> dict[str, Any]:
    try:
        raw = yaml.safe_load(path.read_text())
    except (OSError, yaml.YAMLError) as exc:
        raise InputError(f"{path}: cannot read the sources file: {exc}") from None
    if not isinstance(raw, dict):
        raise InputError(f"{path}: a sources file is a mapping with 'mirrors' and 'datasets'")
    return raw


def _file(entry: dict[str, Any], mirrors: dict[str, list[str]], where: str) -> SourceFile:
    known = {"path", "mirrors", "size", "sha256", "unpack", "select", "remote", "archive_size"}
    extra = set(entry) - known
    if extra or "path" not in entry:
        raise InputError(f"{where}: a file needs 'path' and takes {sorted(known)}; got {sorted(entry)}")
    group = entry.get("mirrors")
    if group not in mirrors:
        raise InputError(f"{where}: mirrors {group!r} is not a group of 'mirrors' ({', '.join(mirrors)})")
    unpack = entry.get("unpack", "zip")
    if unpack not in UNPACK:
        raise InputError(f"{where}: unpack must be one of {UNPACK}, got {unpack!r}")
    select = entry.get("select")
    if select is not None and select not in SELECTORS:
        try:
            re.compile(select)
        except re.error as exc:
            raise InputError(f"{where}: select {select!r} is not a regular expression: {exc}") from None
    sha = entry.get("sha256")
    if sha is not None and not re.fullmatch(r"[0-9a-f]{64}", str(sha)):
        raise InputError(f"{where}: sha256 must be 64 lowercase hex digits, got {sha!r}")
    return SourceFile(
        path=str(entry["path"]),
        urls=tuple(base + str(entry["path"]) for base in mirrors[group]),
        size=None if entry.get("size") is None else int(entry["size"]),
        sha256=sha,
        unpack=unpack,
        select=select,
        remote=bool(entry.get("remote", False)),
        archive_size=None if entry.get("archive_size") is None else int(entry["archive_size"]),
    )


def load_registry(override: str | os.PathLike | None = None) -> Registry:
    """The built-in registry, with the `mirrors` groups and `datasets` entries of the override file
    ($FASTMAC_DATA_SOURCES when `override` is None) replacing those of the same name."""
    raw = _read(BUILTIN)
    origin = [str(BUILTIN)]
    override = override if override is not None else os.environ.get(SOURCES_ENV) or None
    if override is not None:
        extra = _read(Path(override))
        raw["mirrors"] = {**raw.get("mirrors", {}), **(extra.get("mirrors") or {})}
        raw["datasets"] = {**raw.get("datasets", {}), **(extra.get("datasets") or {})}
        origin.append(str(override))
    mirrors = {k: [str(u) for u in v] for k, v in raw["mirrors"].items()}
    datasets = {}
    for name, spec in raw["datasets"].items():
        where = f"sources ({' + '.join(origin)}), data set {name!r}"
        files = tuple(_file(f, mirrors, f"{where}, file {i}") for i, f in enumerate(spec.get("files") or []))
        datasets[str(name)] = DataSet(
            name=str(name),
            title=str(spec.get("title", name)),
            files=files,
            size=None if spec.get("size") is None else int(spec["size"]),
            licence=str(spec.get("licence", "")),
            home=str(spec.get("home", "")),
            needs=tuple(spec.get("needs") or ()),
            check=str(spec.get("check", "")),
            manual=spec.get("manual"),
        )
    return Registry(datasets=datasets, origin=tuple(origin))


def human_size(n: int | None) -> str:
    if n is None:
        return "size unknown"
    for unit, scale in (("GB", 1e9), ("MB", 1e6), ("kB", 1e3)):
        if n >= scale:
            return f"{n / scale:.1f} {unit}"
    return f"{n} B"
