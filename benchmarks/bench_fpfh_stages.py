"""FPFH on a KITTI pair stage by stage, and the same stages of another build of the core side by side
(issue 50 item 1).

    python benchmarks/bench_fpfh_stages.py [--rounds 3] [--against DIR] [--pair 000095 000094]

The pair (../shared/data/kitti_seq00_scancontext, voxel 0.3 m) goes through what FPFHDescriptor does with
the core: the voxel keypoints of both clouds, the cap's 5,000 source rows, the FPFH of those rows (normals
and histograms of the keypoint cloud they need) and of every target keypoint, and the matching (the exact
nearest target feature of each source feature). Each round runs one fresh process per build (this
checkout's, and with --against the `_mac_core` extension in DIR, e.g. a copy of the installed one taken
before a change), interleaved, each timing its stages over 3 calls after a warm-up (medians, ms). The
features and matches of every build are hashed: the builds must agree bit for bit. Prints the CPU model
and the load average.
"""

from __future__ import annotations

import argparse
import hashlib
import json
import statistics
import subprocess
import sys
import time
from pathlib import Path

import numpy as np

REPO = Path(__file__).resolve().parents[1]
if str(REPO) not in sys.path:
    sys.path.insert(0, str(REPO))

from benchmarks.machine import cpu_model, load  # noqa: E402

DATA = REPO.parent / "shared" / "data" / "kitti_seq00_scancontext"
VOXEL, CAP = 0.3, 5000
STAGES = ("voxel grid (both)", "FPFH source rows", "FPFH target (all)", "normalise", "matching")


def _core(against: str | None):
    if against is None:
        from fastmac_exp import core

        return core.core()
    import importlib.util

    (so,) = Path(against).glob("_mac_core*.so")
    spec = importlib.util.spec_from_file_location("_mac_core", so)
    mod = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(mod)
    return mod


def _stages(C, src: np.ndarray, tgt: np.ndarray) -> tuple[dict[str, float], str]:
    """One pass (FPFHDescriptor's arithmetic on the core's calls); the stage seconds and the output's hash."""
    from fastmac_exp.descriptors.matching import capped_rows

    t = [time.perf_counter()]
    skp = C.voxel_downsample(src, VOXEL)
    tkp = C.voxel_downsample(tgt, VOXEL)
    rows = capped_rows(len(skp), CAP, np.random.default_rng(0))
    t.append(time.perf_counter())
    args = (2 * VOXEL, 30, 5 * VOXEL, 100, np.zeros(3))
    in_core = hasattr(C, "unit_rows")  # a build that normalises in the core (else numpy, as it did)
    unit = {"normalize": True} if in_core else {}
    _, sf = C.fpfh_describe(skp, *args, np.ascontiguousarray(rows, dtype=np.int64), **unit)
    t.append(time.perf_counter())
    _, tf = C.fpfh_describe(tkp, *args, None, **unit)
    t.append(time.perf_counter())
    for f in () if in_core else (sf, tf):
        norm = np.linalg.norm(f, axis=1, keepdims=True)
        f /= np.where(norm > 0, norm, 1.0)
    t.append(time.perf_counter())
    nn, _, _ = C.nearest_rows_fast(sf, tf)
    t.append(time.perf_counter())
    h = hashlib.sha256()
    for a in (skp, tkp, sf, tf, nn):
        h.update(np.ascontiguousarray(a).tobytes())
    return {s: t[i + 1] - t[i] for i, s in enumerate(STAGES)}, h.hexdigest()[:16]


def child(against: str | None, ids: list[str]) -> None:
    from fastmac_exp.io import load_cloud

    C = _core(against)
    src, tgt = (load_cloud(DATA / f"{i}.bin") for i in ids)
    _stages(C, src, tgt)
    runs = [_stages(C, src, tgt) for _ in range(3)]
    assert len({h for _, h in runs}) == 1, "a build is not deterministic"
    ms = {s: 1e3 * statistics.median(r[0][s] for r in runs) for s in STAGES}
    print(json.dumps({"ms": ms, "hash": runs[0][1], "points": [len(src), len(tgt)]}))


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--rounds", type=int, default=3)
    ap.add_argument("--against", default=None, help="a folder holding another build's _mac_core*.so")
    ap.add_argument("--pair", nargs=2, default=["000095", "000094"], metavar=("SOURCE", "TARGET"))
    ap.add_argument("--child", nargs="?", const="", default=None, help=argparse.SUPPRESS)
    args = ap.parse_args(argv)
    if args.child is not None:
        child(args.child or None, args.pair)
        return 0
    if not all((DATA / f"{i}.bin").is_file() for i in args.pair):
        print(f"no KITTI pair: {DATA} lacks {args.pair} (shared data beside the repository)")
        return 0
    builds = {"this checkout": ""} | ({f"--against {args.against}": args.against} if args.against else {})
    out: dict[str, list[dict]] = {b: [] for b in builds}
    for _ in range(args.rounds):
        for name, path in builds.items():
            cmd = [sys.executable, __file__, "--pair", *args.pair, "--child", *([path] if path else [])]
            res = subprocess.run(cmd, capture_output=True, text=True, check=True, cwd=REPO)
            out[name].append(json.loads(res.stdout.strip().splitlines()[-1]))
    pts = next(iter(out.values()))[0]["points"]
    print(f"CPU: {cpu_model()}   load average: {load()}   KITTI {args.pair[0]}->{args.pair[1]} "
          f"({pts[0]} / {pts[1]} points), voxel {VOXEL} m, {CAP} source rows; medians of {args.rounds} "
          "processes x 3 calls (ms)")  # fmt: skip
    names = list(builds)
    print(f"{'stage':<22}" + "".join(f"{n:>28}" for n in names) + ("   ratio" if len(names) == 2 else ""))
    total = {n: 0.0 for n in names}
    for s in (*STAGES, "total"):
        vals = {}
        for n in names:
            per = [r["ms"][s] for r in out[n]] if s != "total" else [sum(r["ms"].values()) for r in out[n]]
            vals[n] = statistics.median(per)
            total[n] += vals[n] if s != "total" else 0.0
        ratio = f"   {vals[names[1]] / vals[names[0]]:.2f}x" if len(names) == 2 else ""
        print(f"{s:<22}" + "".join(f"{vals[n]:>28.2f}" for n in names) + ratio)
    hashes = {n: {r["hash"] for r in out[n]} for n in names}
    same = len(set().union(*hashes.values())) == 1
    print(f"keypoints, features and matches: {'bit-identical' if same else 'DIFFER'} across builds {hashes}")
    return 0 if same else 1


if __name__ == "__main__":
    raise SystemExit(main())
