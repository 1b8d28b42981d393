"""Two builds of the C++ core side by side on the same correspondences, in alternating processes.

    python benchmarks/compare_cores.py --old /path/to/old/_mac_core.so [--new <installed>] [--rounds 5]

Timings on a shared (virtual) machine drift by 20-30 % between runs minutes apart, so a speed-up is only
meaningful when both builds run in the same session on the same inputs. This script describes the outdoor
pairs once (FPFH, 5,000 correspondences: the real KITTI/LiDAR/Apollo pairs of ../shared/data and the
synthetic KITTI-like ones), then runs each build in its own process (FASTMAC_CORE_SO), alternating
old/new for --rounds rounds, and prints per pair the median ms of: the sampler's graph and signals
(graph_signals), MAC@100 and FastMAC@20 (high-pass sampling + MAC on the kept 1,000; bench_core's
signals_ms and outdoor_run), with new / old.

--kept: MAC alone (the default search) on the sets FastMAC keeps, where its products are MAC's cost: the
1,000 FastMAC@20 keeps of the real dense outdoor pairs (KITTI 95->94, 199->198, LiDAR; ../shared/data) and
the near-cliques samples=2500 / samples=5000 keep of bench_core's outdoor-like scene at 50,000 and 200,000
correspondences (5 and 10 % inliers).

A build of an earlier commit, for --old (then --old /tmp/oldcore/fastmac_exp/_mac_core*.so):
    git worktree add /tmp/old <commit>
    (cd /tmp/old && pip wheel --no-deps --no-build-isolation -w /tmp/w .)
    unzip -o /tmp/w/*.whl 'fastmac_exp/_mac_core*' -d /tmp/oldcore
"""

from __future__ import annotations

import argparse
import json
import os
import statistics
import subprocess
import sys
import tempfile
from dataclasses import replace
from pathlib import Path

import numpy as np

REPO = Path(__file__).resolve().parents[1]
if str(REPO) not in sys.path:
    sys.path.insert(0, str(REPO))

# Run in the child: times one build on every saved pair with bench_core's own timers (the same calls as
# its outdoor section: graph_signals, and sampling + MAC with the branch and bound, mac.search=bnb); one
# JSON line.
CHILD = r"""
import json, sys
import numpy as np
sys.path.insert(0, "benchmarks")
import bench_core
from fastmac_exp.types import Correspondences
reps = int(sys.argv[2])
out = {}
for path in sys.argv[3:]:
    d = np.load(path)
    corr = Correspondences(src=d["src"], tgt=d["tgt"])
    bench_core.outdoor_run(corr, 0.2, "bnb", 1, 0)  # warm-up
    out[path] = {
        "signals": bench_core.signals_ms(corr, reps, 0, single=True, dense=True)[0],
        "mac100": bench_core.outdoor_run(corr, 1.0, "bnb", reps, 0)[0],
        "fastmac20": bench_core.outdoor_run(corr, 0.2, "bnb", reps, 0)[0],
    }
print(json.dumps(out))
"""

# --kept: MAC (the C++ backend, default parameters of the KITTI family) on each saved kept set.
KEPT_CHILD = r"""
import json, sys, time
import numpy as np
from fastmac_exp.backends.cpp import CppBackend
from fastmac_exp.params import mac_params_for
from fastmac_exp.types import Correspondences
reps = int(sys.argv[2])
params, backend = mac_params_for("kitti", "fpfh"), CppBackend()
out = {}
for path in sys.argv[3:]:
    d = np.load(path)
    corr = Correspondences(src=d["src"], tgt=d["tgt"])
    backend.register(corr, params)  # warm-up
    ts = []
    for _ in range(reps):
        t0 = time.perf_counter()
        backend.register(corr, params)
        ts.append((time.perf_counter() - t0) * 1e3)
    out[path] = {"mac": float(np.median(ts))}
print(json.dumps(out))
"""


def describe_pairs(work: Path) -> list[tuple[str, Path]]:
    sys.path.insert(0, str(REPO / "benchmarks"))
    import bench_core

    saved = []
    for name, corr, _gt in bench_core.outdoor_pairs(quick=False):
        path = work / f"{name.replace(':', '_')}.npz"
        np.savez(path, src=corr.src, tgt=corr.tgt)
        saved.append((name, path))
    return saved


def kept_sets(work: Path) -> list[tuple[str, Path]]:
    """The sets FastMAC keeps (module docstring), saved once; the sampler is the installed core's."""
    sys.path.insert(0, str(REPO / "benchmarks"))
    import bench_core

    from fastmac_exp.datasets.user_pairs import SharedRealPairs
    from fastmac_exp.descriptors.fpfh import FPFHDescriptor
    from fastmac_exp.params import mac_params_for

    saved = []

    def save(name, corr, idx):
        path = work / f"{name}.npz"
        np.savez(path, src=corr.src[idx], tgt=corr.tgt[idx])
        saved.append((name, path))

    if (bench_core.DATA / "pairs.json").exists():
        ds = SharedRealPairs(root=str(bench_core.DATA))
        describe = FPFHDescriptor(max_correspondences=5000)
        for i, name in enumerate(ds.names()):
            if name not in ("kitti00_95_to_94", "kitti00_199_to_198", "lidar_smallgicp_source_to_target"):
                continue
            pair = ds.load(i)
            corr = describe(pair, np.random.default_rng(0))
            params = mac_params_for(pair.family, "fpfh")
            sgraph = mac_params_for(pair.family, "fpfh", pair.sampler_resolution).graph
            sparams = replace(params, graph=sgraph)
            sample = bench_core.fastmac_once(corr, sparams, "auto", 0.2, pair.family, 0)[3]
            save(f"{name}@20", corr, sample.indices)
    for n, inl, k in ((50_000, 0.05, 2500), (50_000, 0.10, 2500), (200_000, 0.10, 5000)):
        corr, _ = bench_core.synthetic(n, inlier_ratio=inl, noise=0.1, seed=1, room=(60.0, 60.0, 4.0))
        params = mac_params_for("kitti", "fpfh")
        sample = bench_core.fastmac_once(corr, params, "auto", 1.0, "kitti", 0, samples=k)[3]
        save(f"planted{n // 1000}k_{round(inl * 100)}%_samples{k}", corr, sample.indices)
    return saved


def run_build(so: str, reps: int, paths: list[Path], child: str = CHILD) -> dict[str, dict[str, float]]:
    env = dict(os.environ, FASTMAC_CORE_SO=so)
    res = subprocess.run(
        [sys.executable, "-c", child, "x", str(reps), *map(str, paths)],
        env=env, capture_output=True, text=True, check=True, cwd=REPO,
    )  # fmt: skip
    return json.loads(res.stdout.strip().splitlines()[-1])


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--old", required=True, help="the other build's _mac_core*.so")
    ap.add_argument("--new", default=None, help="default: the installed extension")
    ap.add_argument("--rounds", type=int, default=5, help="alternating old/new processes per build")
    ap.add_argument("--reps", type=int, default=3, help="timed calls per stage in each process")
    ap.add_argument("--kept", action="store_true", help="MAC alone on the sets FastMAC keeps (docstring)")
    args = ap.parse_args(argv)
    new = args.new
    if new is None:
        import importlib.util

        new = importlib.util.find_spec("fastmac_exp._mac_core").origin
    for flag, so in (("--old", args.old), ("--new", new)):
        if not Path(so).is_file():  # else each timing process fails with a traceback
            print(f"compare_cores: {flag} {so}: no such file (a built _mac_core*.so)", file=sys.stderr)
            return 2
    with tempfile.TemporaryDirectory() as tmp:
        pairs = kept_sets(Path(tmp)) if args.kept else describe_pairs(Path(tmp))
        paths = [p for _, p in pairs]
        runs: dict[str, list[dict]] = {"old": [], "new": []}
        builds = (("old", args.old), ("new", new))
        for r in range(args.rounds):
            for tag, so in builds if r % 2 == 0 else builds[::-1]:
                runs[tag].append(run_build(so, args.reps, paths, KEPT_CHILD if args.kept else CHILD))
    stages = ("mac",) if args.kept else ("signals", "mac100", "fastmac20")
    head = f"{'pair':34} | " + " | ".join(f"{s + ' old':>14} {'new':>7} {'x':>5}" for s in stages)
    print(f"old: {args.old}\nnew: {new}")
    print(f"{args.rounds} alternating processes each, {args.reps} calls per stage")
    print(head)
    print("-" * len(head))
    ratios = {s: [] for s in stages}
    for name, path in pairs:
        cells = []
        for s in stages:
            o = statistics.median(run[str(path)][s] for run in runs["old"])
            n = statistics.median(run[str(path)][s] for run in runs["new"])
            ratios[s].append(o / n)
            cells.append(f"{o:14.1f} {n:7.1f} {o / n:5.2f}")
        print(f"{name[:34]:34} | " + " | ".join(cells))
    print("x = old / new (medians over the processes); median speed-up: " + ", ".join(
        f"{s} {statistics.median(v):.2f}x" for s, v in ratios.items()))  # fmt: skip
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
