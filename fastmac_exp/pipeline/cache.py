"""On-disk cache of descriptor output, so sweeps over samplers and ratios describe each pair once.

Keyed by everything that determines the correspondences (dataset config, pair, descriptor config, seed);
files are .npz read with allow_pickle=False; an unreadable entry is recomputed, never trusted. Entries are
written whole (fastmac_exp.atomic), so many workers can share one cache directory on a shared filesystem.
"""

from __future__ import annotations

import hashlib
import json
import logging
import os
from pathlib import Path
from typing import Any

import numpy as np

from fastmac_exp.atomic import save_npz
from fastmac_exp.types import Correspondences

log = logging.getLogger(__name__)


class CorrespondenceCache:
    def __init__(self, root: str | os.PathLike | None, enabled: bool = True) -> None:
        self.root = Path(root) if root else None
        self.enabled = bool(enabled and root)

    @staticmethod
    def key(parts: dict[str, Any]) -> str:
        blob = json.dumps(parts, sort_keys=True, default=str)
        return hashlib.sha1(blob.encode()).hexdigest()[:20]

    def _path(self, key: str) -> Path:
        assert self.root is not None
        return self.root / key[:2] / f"{key}.npz"

    def load(self, key: str) -> tuple[Correspondences, float] | None:
        if not self.enabled:
            return None
        path = self._path(key)
        if not path.exists():
            return None
        try:
            with np.load(path, allow_pickle=False) as z:
                labels = z["labels"] if z["has_labels"] else None
                corr = Correspondences(z["src"], z["tgt"], labels=labels)
                return corr, float(z["describe_ms"])
        except Exception as exc:  # noqa: BLE001 - a broken entry is recomputed
            log.warning("correspondence cache entry %s is unreadable (%s); recomputing", path, exc)
            return None

    def save(self, key: str, corr: Correspondences, describe_ms: float) -> None:
        if not self.enabled:
            return
        labels = corr.labels if corr.labels is not None else np.zeros(0, bool)
        save_npz(self._path(key), src=corr.src, tgt=corr.tgt, labels=labels,
                 has_labels=corr.labels is not None, describe_ms=describe_ms)  # fmt: skip
