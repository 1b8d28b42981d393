"""One writer per run directory: an exclusive lock on `<run_dir>/run.lock` for the run's lifetime.

The lock is a `flock` on the file, so the kernel drops it when its process dies however it dies (a
SIGKILL, a crash): a lock file left behind is stale and the next run takes it over. The file holds the
owner's host and pid, which a refused run names.
"""

from __future__ import annotations

import fcntl
import json
import logging
import os
import socket
from pathlib import Path

from fastmac_exp.errors import InputError

log = logging.getLogger(__name__)

LOCK_NAME = "run.lock"


class RunLocked(InputError):
    """Another live process holds the run directory."""


class RunLock:
    """`with RunLock(run_dir):` holds the directory; a second holder is refused with RunLocked."""

    def __init__(self, run_dir: str | Path) -> None:
        self.path = Path(run_dir) / LOCK_NAME
        self._fd: int | None = None

    def acquire(self) -> RunLock:
        while True:
            fd = os.open(self.path, os.O_RDWR | os.O_CREAT, 0o644)
            try:
                fcntl.flock(fd, fcntl.LOCK_EX | fcntl.LOCK_NB)
            except BlockingIOError:
                os.close(fd)
                raise RunLocked(
                    f"{self.path.parent} is in use by another run ({owner_text(self.path)}); wait for it to "
                    "end, or choose another run directory"
                ) from None
            try:
                same = os.fstat(fd).st_ino == os.stat(self.path).st_ino
            except FileNotFoundError:
                same = False
            if same:
                break
            os.close(fd)  # the holder released (and removed) the file between our open and our lock
        stale = _read_owner(fd)
        if stale:
            log.info("taking over the stale lock of %s (that process is gone)", owner_text(self.path))
        os.ftruncate(fd, 0)
        os.pwrite(fd, json.dumps({"host": socket.gethostname(), "pid": os.getpid()}).encode(), 0)
        os.fsync(fd)
        self._fd = fd
        return self

    def release(self) -> None:
        if self._fd is None:
            return
        try:
            self.path.unlink(missing_ok=True)
        finally:
            os.close(self._fd)
            self._fd = None

    def __enter__(self) -> RunLock:
        return self.acquire()

    def __exit__(self, *exc: object) -> None:
        self.release()


def held_by(run_dir: str | Path) -> str | None:
    """Who holds `run_dir` now ('pid N on host H'), or None: a lock file whose process on this host is
    alive and holds the lock (probed with a shared lock only then: a run that is taking the lock at that
    instant cannot be refused by a probe). Another host's lock is left to `RunLock.acquire`."""
    path = Path(run_dir) / LOCK_NAME
    try:
        owner = json.loads(path.read_text() or "{}")
        pid = int(owner["pid"])
    except (OSError, ValueError, KeyError, TypeError):
        return None
    if owner.get("host") != socket.gethostname() or not _alive(pid):
        return None
    try:
        fd = os.open(path, os.O_RDONLY)
    except OSError:
        return None
    try:
        fcntl.flock(fd, fcntl.LOCK_SH | fcntl.LOCK_NB)
    except BlockingIOError:
        return owner_text(path)
    finally:
        os.close(fd)
    return None


def _alive(pid: int) -> bool:
    try:
        os.kill(pid, 0)
    except ProcessLookupError:
        return False
    except PermissionError:  # another user's process
        return True
    return True


def _read_owner(fd: int) -> dict:
    try:
        return json.loads(os.pread(fd, 4096, 0) or b"{}")
    except (ValueError, OSError):
        return {}


def owner_text(path: Path) -> str:
    """'pid 123 on host h' from a lock file, or what is known of it."""
    try:
        owner = json.loads(Path(path).read_text() or "{}")
    except (OSError, ValueError):
        owner = {}
    if not owner:
        return "owner not yet recorded"
    return f"pid {owner.get('pid')} on host {owner.get('host')}"
