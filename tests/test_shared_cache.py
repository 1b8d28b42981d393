"""Caches shared by many workers: processes racing to write and read the same keys never meet a torn or
mixed entry. Each writer writes its own, internally consistent value (a stronger check than the equal
values that real workers write), so a reader must get either a miss or exactly one writer's value."""

from __future__ import annotations

import multiprocessing as mp
import time
from pathlib import Path

import numpy as np
import pytest

from fastmac_exp import atomic
from fastmac_exp.datasets.synthetic import load_cached, save_cached
from fastmac_exp.pipeline.cache import CorrespondenceCache
from fastmac_exp.types import Correspondences

N_PROCS, SECONDS, KEYS = 4, 3.0, ("k0", "k1")


def value(writer: int, key: str) -> np.ndarray:
    """Writer w's array for a key: its size and every element depend on (w, key), 1-3 MB."""
    n = 40_000 + 20_000 * writer + 7 * int(key[1:])
    return np.full((n, 3), 1000.0 * writer + int(key[1:]), dtype=np.float64)


def _corr_cache(root: Path) -> CorrespondenceCache:
    return CorrespondenceCache(root / "corr")


def _synthetic_path(root: Path, key: str) -> Path:
    return root / "synthetic" / f"3dmatch_s0_{key}.npz"


def _check_corr(got, key: str) -> str | None:
    corr, ms = got
    w = int(round(ms))
    want = value(w, key)
    same = (np.array_equal(corr.src, want) and np.array_equal(corr.tgt, want + 1)
            and corr.labels is not None and len(corr.labels) == len(want) and corr.labels.all())  # fmt: skip
    return None if same else f"correspondences {key}: not writer {w}'s value"


def _check_synthetic(got, key: str) -> str | None:
    w = int(got["meta"]["writer"])
    want = value(w, key)
    same = np.array_equal(got["src"], want) and np.array_equal(got["tgt"], want + 2)
    return None if same and np.array_equal(got["gt"], np.eye(4) * w) else f"synthetic {key}: mixed value"


def race(root: str, writer: int, seconds: float, queue) -> None:
    """Write and read both caches' keys in a loop; report every problem and the counts."""
    root = Path(root)
    cache = _corr_cache(root)
    problems, reads, hits, writes = [], 0, 0, 0
    end = time.monotonic() + seconds
    i = 0
    while time.monotonic() < end:
        key = KEYS[i % len(KEYS)]
        v = value(writer, key)
        if (i + writer) % 2 == 0:
            cache.save(key, Correspondences(v, v + 1, labels=np.ones(len(v), bool)), float(writer))
            save_cached(_synthetic_path(root, key), {"src": v, "tgt": v + 2, "gt": np.eye(4) * writer,
                                                     "meta": {"writer": writer}})  # fmt: skip
            writes += 1
        spath = _synthetic_path(root, key)
        for name, path, check in (
            ("correspondences", cache._path(key), _check_corr),
            ("synthetic", spath, _check_synthetic),
        ):
            existed = path.exists()  # once written, an entry is only ever replaced, never removed
            got = cache.load(key) if name == "correspondences" else load_cached(spath)
            reads += 1
            if got is None:
                if existed:
                    problems.append(f"{name} {key}: the file existed but did not load (torn or mixed)")
                continue
            hits += 1
            problem = check(got, key)
            if problem:
                problems.append(problem)
        i += 1
    queue.put({"writer": writer, "problems": problems[:5], "n_problems": len(problems), "reads": reads,
               "hits": hits, "writes": writes})  # fmt: skip


def run_race(root: Path) -> list[dict]:
    ctx = mp.get_context("spawn")
    queue = ctx.Queue()
    procs = [ctx.Process(target=race, args=(str(root), w, SECONDS, queue)) for w in range(N_PROCS)]
    for p in procs:
        p.start()
    reports = [queue.get(timeout=120) for _ in procs]
    for p in procs:
        p.join(timeout=30)
        assert p.exitcode == 0, f"racer exited with {p.exitcode}"
    return reports


def test_processes_racing_on_the_same_keys_see_misses_or_whole_values(tmp_path, caplog):
    reports = run_race(tmp_path)
    problems = [p for r in reports for p in r["problems"]]
    assert not problems, problems
    assert sum(r["writes"] for r in reports) >= 2 * N_PROCS  # they did race
    assert sum(r["hits"] for r in reports) >= N_PROCS
    leftovers = [p.name for p in tmp_path.rglob("*.tmp")]
    assert not leftovers, leftovers  # every writer renamed its own temp file


def test_the_race_check_catches_a_torn_entry(tmp_path):
    """The checks above can fail: a truncated entry is an existing file that does not load."""
    cache = _corr_cache(tmp_path)
    v = value(0, "k0")
    cache.save("k0", Correspondences(v, v + 1, labels=np.ones(len(v), bool)), 0.0)
    path = cache._path("k0")
    path.write_bytes(path.read_bytes()[: path.stat().st_size // 2])
    assert path.exists() and cache.load("k0") is None
    spath = _synthetic_path(tmp_path, "k0")
    save_cached(spath, {"src": v, "tgt": v + 2, "gt": np.eye(4), "meta": {"writer": 0}})
    data = bytearray(spath.read_bytes())
    data[len(data) // 2] ^= 0xFF  # one flipped byte in the middle of the arrays: a mixed file
    spath.write_bytes(bytes(data))
    assert load_cached(spath) is None


def test_temp_names_are_unique_per_writer_and_a_failed_write_leaves_nothing(tmp_path, monkeypatch):
    target = tmp_path / "x.npz"
    names = {atomic.temp_name(target) for _ in range(100)}
    assert len(names) == 100 and all(n.parent == tmp_path and n.name.startswith(".x.npz.") for n in names)

    def boom(*args, **kwargs):
        raise OSError("disk full")

    monkeypatch.setattr(atomic.os, "fsync", boom)
    with pytest.raises(OSError, match="disk full"):
        atomic.save_npz(target, a=np.zeros(3))
    assert list(tmp_path.iterdir()) == []
