"""The data home: $FASTMAC_DATA, else the platform's user data directory (platformdirs), holding one
folder per data set, its manifest (what was fetched, each file's size and sha256), the downloads in
progress and the archives that failed their checks (kept aside, never deleted)."""

from __future__ import annotations

import json
import os
import time
from pathlib import Path
from typing import Any

from fastmac_exp.atomic import temp_name
from fastmac_exp.resources import HOME_ENV, data_home  # noqa: F401 - the data home's one definition

MANIFEST = "manifest.json"


def dataset_dir(name: str, home: Path | None = None) -> Path:
    return (home or data_home()) / name


def downloads_dir(home: Path | None = None) -> Path:
    return (home or data_home()) / "downloads"


def quarantine_dir(home: Path | None = None) -> Path:
    return (home or data_home()) / "quarantine"


def write_json(path: Path, data: Any) -> None:
    """Whole-file write: a reader sees the old manifest or the new one."""
    path.parent.mkdir(parents=True, exist_ok=True)
    tmp = temp_name(path)
    try:
        tmp.write_text(json.dumps(data, indent=1, sort_keys=True) + "\n")
        os.replace(tmp, path)
    except BaseException:
        tmp.unlink(missing_ok=True)
        raise


class Manifest:
    """<data set>/manifest.json: per source file, where it came from, its size and sha256, and the files
    it put into the folder with theirs; `complete` once the whole data set passed its structure check."""

    def __init__(self, folder: Path) -> None:
        self.path = folder / MANIFEST
        self.data: dict[str, Any] = {"sources": {}, "complete": False}
        if self.path.is_file():
            self.data = json.loads(self.path.read_text())

    @property
    def complete(self) -> bool:
        return bool(self.data.get("complete"))

    def source(self, name: str) -> dict[str, Any] | None:
        return self.data["sources"].get(name)

    def record(self, name: str, entry: dict[str, Any]) -> None:
        self.data["sources"][name] = {**entry, "at": time.strftime("%Y-%m-%dT%H:%M:%S")}
        self.data["complete"] = False
        self.save()

    def finish(self, check: str) -> None:
        self.data["complete"] = True
        self.data["check"] = check
        self.save()

    def files(self) -> dict[str, dict[str, Any]]:
        """Every file the sources put into the folder: relative path -> {size, sha256}."""
        out: dict[str, dict[str, Any]] = {}
        for entry in self.data["sources"].values():
            out.update(entry.get("files", {}))
        return out

    def save(self) -> None:
        write_json(self.path, self.data)
