"""KITTI's part of the fetch: FCGF's test pairs over sequences 08-10 from the poses, and members of the
official 80 GB zip fetched one by one with HTTP range requests (remotezip), each written whole and
checked by its CRC-32 as it is read."""

from __future__ import annotations

import logging
import zipfile
from collections.abc import Callable, Sequence
from pathlib import Path

import requests
from remotezip import RangeNotSupported, RemoteIOError, RemoteZip, RemoteZipError
from tqdm import tqdm

from fastmac_exp.data.download import FetchError, check_space, sha256_of
from fastmac_exp.data.sources import human_size
from fastmac_exp.data.unpack import members, write_whole
from fastmac_exp.datasets.benchmark_files import read_kitti_poses
from fastmac_exp.datasets.fragments import FCGF_EXCLUDED, fcgf_pairs

log = logging.getLogger("fastmac_exp.data")

KITTI_SEQUENCES = (8, 9, 10)
MEMBER_RETRIES = 3


class NeedsWholeArchive(FetchError):
    """The server refuses range requests: only the whole archive could be fetched."""

    def __init__(self, message: str, size: int | None) -> None:
        super().__init__(message)
        self.size = size


def fcgf_test_pairs(root: Path, sequences: Sequence[int] = KITTI_SEQUENCES) -> list[tuple[int, int, int]]:
    """(seq, source, target) of FCGF's KITTI test protocol, walked over every frame with a pose (as FCGF
    walks its full sequences), minus its excluded pair."""
    out = []
    for seq in sequences:
        poses = read_kitti_poses(root / "poses" / f"{seq:02d}.txt")
        out += [
            (seq, a, b) for a, b in fcgf_pairs(poses, range(len(poses))) if (seq, a, b) not in FCGF_EXCLUDED
        ]
    return out


def scan_member(seq: int, frame: int) -> str:
    return f"dataset/sequences/{seq:02d}/velodyne/{frame:06d}.bin"


def fcgf_scan_members(folder: Path) -> set[str]:
    """The velodyne members the test pairs need (the poses must be in `folder` already)."""
    return {scan_member(s, f) for s, a, b in fcgf_test_pairs(folder / "dataset") for f in (a, b)}


def fetch_members(
    urls: Sequence[str],
    folder: Path,
    select: Callable[[str], bool],
    archive_size: int | None,
    progress: bool = True,
    session: requests.Session | None = None,
) -> tuple[str, dict[str, dict[str, int | str]]]:
    """The selected members of a remote zip into `folder` (members already there with their size are
    kept); (the URL used, relative path -> size and sha256)."""
    tried = []
    for k, url in enumerate(urls):
        nxt = f"trying the next mirror {urls[k + 1]}" if k + 1 < len(urls) else "no mirror left"
        try:
            with RemoteZip(url, session=session) as z:
                return url, _members_into(z, folder, select, progress)
        except RangeNotSupported:
            raise NeedsWholeArchive(
                f"{url} does not answer HTTP range requests, so the few members needed cannot be fetched "
                f"alone; the whole archive is {human_size(archive_size)}: answer yes, or run the fetch "
                "again with --whole-archives, to download it and unpack the members needed",
                archive_size,
            ) from None
        except (RemoteIOError, RemoteZipError, requests.RequestException, zipfile.BadZipFile) as exc:
            why = str(exc).splitlines()[0][:200] if str(exc) else type(exc).__name__
            log.warning("%s: %s; %s", url, why, nxt)
            tried.append(f"{url}: {why}")
    raise FetchError(f"no mirror delivered the archive's members ({'; '.join(tried)})")


def _members_into(z: zipfile.ZipFile, folder: Path, select: Callable[[str], bool], progress: bool) -> dict:
    chosen = members(z, select)
    if not chosen:
        raise RemoteZipError("the archive holds none of the members needed")
    todo = [i for i in chosen if not _have(folder / i.filename, i.file_size)]
    check_space(folder, sum(i.file_size for i in todo), "the archive's members")
    out = {}
    with tqdm(
        total=sum(i.file_size for i in todo),
        unit="B",
        unit_scale=True,
        unit_divisor=1024,
        desc=f"{len(todo)} members",
        disable=not progress or not todo,
        leave=False,
    ) as bar:
        for info in chosen:
            dest = folder / info.filename
            if info not in todo:
                out[info.filename] = {"size": info.file_size, "sha256": sha256_of(dest)}
                continue
            for attempt in range(MEMBER_RETRIES + 1):
                try:
                    with z.open(info) as src:  # zipfile checks the CRC-32 at the member's end
                        out[info.filename] = write_whole(src, dest)
                    break
                except (RemoteIOError, requests.RequestException) as exc:
                    if attempt == MEMBER_RETRIES:
                        raise
                    log.warning("%s: %s; fetching the member again", info.filename, exc)
            bar.update(info.file_size)
    return out


def _have(path: Path, size: int) -> bool:
    return path.is_file() and path.stat().st_size == size
