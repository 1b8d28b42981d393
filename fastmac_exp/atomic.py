"""Whole-file writes for caches that many processes, threads and hosts share on one filesystem.

A writer fills a temporary file of its own in the target's directory (host, pid, thread and a random
suffix in its name: two writers never share one, even on different hosts with equal pids), flushes and
fsyncs it, and renames it over the target. The rename is atomic on POSIX filesystems (NFS and Lustre
included), so a reader opens either no file, or one writer's complete file, never a torn or mixed one;
concurrent writers of one key just replace each other's (equal) entries. A writer killed half-way leaves
only its `.*.tmp` file behind, which no reader ever opens.
"""

from __future__ import annotations

import os
import secrets
import socket
import threading
from pathlib import Path
from typing import Any

import numpy as np


def temp_name(path: Path) -> Path:
    tag = f"{socket.gethostname()}-{os.getpid()}-{threading.get_ident()}-{secrets.token_hex(4)}"
    return path.with_name(f".{path.name}.{tag}.tmp")


def save_npz(path: str | os.PathLike, **arrays: Any) -> None:
    """np.savez(path, **arrays), atomically (see the module docstring)."""
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    tmp = temp_name(path)
    try:
        with open(tmp, "wb") as f:
            np.savez(f, **arrays)
            f.flush()
            os.fsync(f.fileno())
        os.replace(tmp, path)
    except BaseException:
        tmp.unlink(missing_ok=True)
        raise
