"""One file from a list of mirrors, resumably and atomically (requests + tqdm).

The bytes go to `<dest>.part`; a cut connection reconnects with `Range: bytes=<have>-` and appends, so a
download never restarts from zero while the server honours ranges (one that answers 200 to a range
request is said to, and the file starts over). Only a file that has its published size and sha256 (and
passes the caller's `validate`) is renamed to `dest`: a partial or wrong file never looks complete. A file
that fails a check is moved into the quarantine folder, not deleted, and the next mirror is tried; an
HTTP error or a refused connection goes to the next mirror at once. Every failure is one line naming the
URL and the mirror tried next.
"""

from __future__ import annotations

import hashlib
import logging
import os
import shutil
import time
from collections.abc import Callable, Sequence
from dataclasses import dataclass
from pathlib import Path

import requests
from tqdm import tqdm

from fastmac_exp.errors import InputError

log = logging.getLogger("fastmac_exp.data")

CHUNK = 1 << 20
RECONNECTS = 5  # reconnections to one mirror after cuts, each resuming where the file stands
TIMEOUT = (20, 120)  # connect, read (s)
USER_AGENT = "fastmac-exp-data"


class FetchError(InputError):
    """A download that no mirror could deliver, or that cannot start (no disk space)."""


class _MirrorFailed(Exception):
    pass


@dataclass
class Fetched:
    path: Path
    url: str
    size: int
    sha256: str


def sha256_of(path: Path) -> str:
    h = hashlib.sha256()
    with open(path, "rb") as f:
        for block in iter(lambda: f.read(CHUNK), b""):
            h.update(block)
    return h.hexdigest()


def check_space(folder: Path, need: int | None, what: str) -> None:
    """Refuse a download of `need` bytes into `folder`'s disk when less is free."""
    if not need:
        return
    probe = folder
    while not probe.exists() and probe != probe.parent:
        probe = probe.parent
    free = shutil.disk_usage(probe).free
    if free < need:
        raise FetchError(
            f"{what}: needs {need / 1e9:.2f} GB on {probe}, which has {free / 1e9:.2f} GB free; free some "
            "space or set FASTMAC_DATA to a folder on a larger disk"
        )


def keep_aside(path: Path, quarantine: Path, why: str) -> Path:
    """Move a file that failed a check into `quarantine` (with the reason beside it), never deleting it."""
    quarantine.mkdir(parents=True, exist_ok=True)
    stem = path.name.removesuffix(".part")
    kept = quarantine / f"{stem}.{time.strftime('%Y%m%d-%H%M%S')}.{os.getpid()}"
    shutil.move(str(path), kept)
    kept.with_name(kept.name + ".why.txt").write_text(why + "\n")
    return kept


def _next(urls: Sequence[str], k: int) -> str:
    return f"trying the next mirror {urls[k + 1]}" if k + 1 < len(urls) else "no mirror left"


def fetch_file(
    urls: Sequence[str],
    dest: Path,
    quarantine: Path,
    size: int | None = None,
    sha256: str | None = None,
    validate: Callable[[Path], str | None] | None = None,
    progress: bool = True,
    session: requests.Session | None = None,
) -> Fetched:
    """Download `dest` from the first mirror that delivers it whole and right; see the module docstring.
    `validate(path)` returns None for a good file, else what is wrong with it."""
    dest.parent.mkdir(parents=True, exist_ok=True)
    part = dest.with_name(dest.name + ".part")
    session = session or new_session()
    tried = []
    for k, url in enumerate(urls):
        try:
            _download(session, url, part, size, progress)
        except _MirrorFailed as exc:
            log.warning("%s: %s; %s", url, exc, _next(urls, k))
            tried.append(f"{url}: {exc}")
            continue
        got, digest = part.stat().st_size, sha256_of(part)
        why = None
        if size is not None and got != size:
            why = f"{got} bytes where {size} are published"
        elif sha256 is not None and digest != sha256:
            why = f"sha256 {digest} where {sha256} is published"
        elif validate is not None:
            why = validate(part)
        if why:
            kept = keep_aside(part, quarantine, f"{url}: {why}")
            log.warning("%s: %s; the file is kept aside as %s; %s", url, why, kept, _next(urls, k))
            tried.append(f"{url}: {why}")
            continue
        os.replace(part, dest)
        return Fetched(dest, url, got, digest)
    raise FetchError(
        f"{dest.name}: no mirror delivered it ({'; '.join(tried) or 'no mirror listed'}). Download it by "
        "hand "
        f"and file it with `fastmac-exp data add`, or list a mirror that has it in $FASTMAC_DATA_SOURCES "
        "(docs/data.md)"
    )


def new_session() -> requests.Session:
    s = requests.Session()
    s.headers["User-Agent"] = USER_AGENT
    return s


def _download(session: requests.Session, url: str, part: Path, size: int | None, progress: bool) -> None:
    """Bring `part` to the whole file from `url`, resuming through cuts; _MirrorFailed when it cannot."""
    cuts = 0
    while True:
        have = part.stat().st_size if part.exists() else 0
        if size is not None and have == size:
            return
        if size is not None and have > size:
            part.unlink()
            have = 0
        headers = {"Range": f"bytes={have}-"} if have else {}
        try:
            r = session.get(url, headers=headers, stream=True, timeout=TIMEOUT)
        except requests.RequestException as exc:
            raise _MirrorFailed(_reason(exc)) from None
        with r:
            if r.status_code == 416 and have:  # asked past the end: the part may be the whole file
                total = _total_from_range(r.headers.get("Content-Range", ""))
                if total == have:
                    return
                part.unlink()
                continue
            if r.status_code >= 400:
                raise _MirrorFailed(f"HTTP {r.status_code} {r.reason}")
            if have and r.status_code == 200:
                log.warning("%s: the server ignores range requests; starting the file over from 0", url)
                have = 0
            elif r.status_code == 206 and not r.headers.get("Content-Range", "").startswith(f"bytes {have}-"):
                raise _MirrorFailed(
                    f"answered a range from byte {have} with {r.headers.get('Content-Range')!r}"
                )
            length = r.headers.get("Content-Length")
            total = have + int(length) if length is not None else size
            check_space(part.parent, None if total is None else total - have, part.name.removesuffix(".part"))
            # A body cut short then ends the stream with what arrived (kept, and resumed below); with the
            # check on, urllib3 raises and drops the bytes it had buffered (up to a chunk).
            r.raw.enforce_content_length = False
            try:
                _stream(r, part, have, total, progress)
            except requests.RequestException:
                cuts += 1
                now = part.stat().st_size if part.exists() else 0
                if cuts > RECONNECTS:
                    raise _MirrorFailed(f"the connection was cut {cuts} times (last at byte {now})") from None
                log.warning("%s: connection cut at byte %d of %s; resuming from there", url, now, total)
                continue
        now = part.stat().st_size
        if total is not None and now < total:
            cuts += 1
            if cuts > RECONNECTS:
                raise _MirrorFailed(f"the connection was cut {cuts} times (last at byte {now})")
            log.warning("%s: the server sent %d of %d bytes; resuming from there", url, now, total)
            continue
        return


def _stream(r: requests.Response, part: Path, have: int, total: int | None, progress: bool) -> None:
    with (
        open(part, "ab" if have else "wb") as f,
        tqdm(
            total=total,
            initial=have,
            unit="B",
            unit_scale=True,
            unit_divisor=1024,
            desc=part.name.removesuffix(".part")[-40:],
            disable=not progress,
            leave=False,
        ) as bar,
    ):
        for chunk in r.iter_content(CHUNK):
            f.write(chunk)
            bar.update(len(chunk))


def _total_from_range(header: str) -> int | None:
    tail = header.rpartition("/")[2]
    return int(tail) if tail.isdigit() else None


def _reason(exc: BaseException) -> str:
    text = str(exc)
    for marker in (
        "Failed to establish a new connection:",
        "Connection refused",
        "Name or service not known",
    ):
        if marker in text:
            return marker.rstrip(":").lower() if marker.endswith(":") else marker.lower()
    return type(exc).__name__ + (f": {text[:160]}" if text else "")
