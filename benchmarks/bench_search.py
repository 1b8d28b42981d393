"""The clique search alone, on the hardest clique graphs this project meets (issue 11, item 1).

    python benchmarks/bench_search.py [--cases syn:kitti_003@100 ...] [--quick] [--max-nodes 1000000]
                                      [--searches bnb auto] [--reps 3] [--threads 1] [--rebuild]
                                      [--old OTHER_BUILD.so]

bench_core.py times sampling + MAC end to end; most of that is graph building, and a change to the
search drowns in its noise. This script builds the clique graphs once (FPFH correspondences, high-pass
sampling, first- and second-order graph and the spec-2.5 reduction, all as MAC computes them), keeps them
in .cache/bench_search/, and then times only `select_cliques` on them, so one experiment on the search
takes seconds. The graphs come from the Python reference (fastmac_exp.graph and
backends/python_mac.reduce_graph), which the parity tests hold equal to the C++ core's.

Per graph it prints its structure: the nodes that can be in a clique, the edges, the nodes adjacent to all
others ("universal": every maximal clique holds them), the missing edges among the rest ("conflicts": a
clique holds at most one end of each), and the connected components of the conflict graph; then, per
search, the median ms, the search nodes and any cap. Dense outdoor graphs are near-cliques: a few hundred
nodes and tens to hundreds of conflicts, and the exact selection there is a quadratic choice over the
conflicts (docs/clique_search.md, "Why near-cliques stay hard").

Cases (name@ratio; ratio 100 = MAC on all 5,000 correspondences):
- syn:kitti_001/003/005@100: the synthetic KITTI-like pairs whose MAC@100 runs into the node budget or
  close to it; syn:kitti_002@20 (the README's pair 3 at FastMAC@20);
- real:<pair>@20 for the dense real outdoor pairs in ../shared/data (skipped when absent);
- big:2%@5, big:10%@5: 50,000 outdoor correspondences at ratio 0.05 (bench_core's large case).
"""

from __future__ import annotations

import argparse
import hashlib
import json
import os
import statistics
import subprocess
import sys
import time
from pathlib import Path

import numpy as np
import scipy.sparse as sp
from scipy.sparse.csgraph import connected_components

REPO = Path(__file__).resolve().parents[1]
for p in (REPO, REPO / "benchmarks"):
    if str(p) not in sys.path:
        sys.path.insert(0, str(p))

import bench_core  # noqa: E402

from fastmac_exp import __version__  # noqa: E402
from fastmac_exp import core as cpp  # noqa: E402
from fastmac_exp.params import mac_params_for  # noqa: E402

CACHE = REPO / ".cache" / "bench_search"
SYNTHETIC = ("syn:kitti_001@100", "syn:kitti_003@100", "syn:kitti_005@100", "syn:kitti_002@20")
REAL = ("real:lidar_smallgicp@20", "real:kitti00_199_to_198@20", "real:kitti00_95_to_94@20")
LARGE = ("big:2%@5", "big:10%@5")
QUICK = ("syn:kitti_002@20", "syn:kitti_005@100")


def parse_case(case: str) -> tuple[str, str, float]:
    """'syn:kitti_003@100' -> ('syn', 'kitti_003', 1.0)."""
    try:
        source, rest = case.split(":", 1)
        name, pct = rest.rsplit("@", 1)
        ratio = float(pct) / 100.0
    except ValueError:
        raise SystemExit(
            f"bench_search: case '{case}' is not SOURCE:NAME@PERCENT (e.g. syn:kitti_003@100)"
        ) from None
    if source not in ("syn", "real", "big") or not 0.0 < ratio <= 1.0:
        raise SystemExit(
            f"bench_search: case '{case}': source must be syn, real or big and 0 < percent <= 100"
        )
    return source, name, ratio


def correspondences(source: str, name: str):
    """The correspondences of a case (None when its data is absent): bench_core's."""
    if source == "big":
        inl = float(name.rstrip("%")) / 100.0
        corr, _ = bench_core.synthetic(50_000, inlier_ratio=inl, noise=0.1, seed=1, room=(60.0, 60.0, 4.0))
        return corr
    if source == "real" and not (bench_core.DATA / "pairs.json").exists():
        return None
    found = bench_core.outdoor_pairs(quick=False, keep=lambda key: key.startswith(f"{source}:{name}"))
    if not found:
        raise SystemExit(f"bench_search: no outdoor pair named {source}:{name}*")
    return found[0][1]


def build(case: str) -> dict | None:
    """The reduced clique graph of a case (upper edges i < j with their G), as MAC builds it."""
    from fastmac_exp.backends.python_mac import reduce_graph
    from fastmac_exp.graph import first_order, second_order

    source, name, ratio = parse_case(case)
    corr = correspondences(source, name)
    if corr is None:
        return None
    g = mac_params_for("kitti", "fpfh").graph
    if ratio < 1.0:
        # the same draw as bench_core's outdoor runs
        idx = bench_core.sampler("cpp").sample(corr, ratio, g, "kitti", np.random.default_rng(0)).indices
        corr = corr.subset(np.asarray(idx))
    G = second_order(first_order(corr.src, corr.tgt, g))
    R, reduced = reduce_graph(G)
    up = sp.triu(R, 1).tocoo()
    keep = up.data > 0
    return {
        "n": np.int64(R.shape[0]),
        "i": up.row[keep].astype(np.int64),
        "j": up.col[keep].astype(np.int64),
        "w": up.data[keep].astype(np.float64),
        "reduced": np.bool_(reduced),
    }


def load(case: str, rebuild: bool) -> dict | None:
    path = CACHE / f"{__version__}-{case.replace(':', '_').replace('%', 'pc').replace('@', '_at_')}.npz"
    if path.exists() and not rebuild:
        with np.load(path) as f:
            return {k: f[k] for k in f.files}
    graph = build(case)
    if graph is not None:
        CACHE.mkdir(parents=True, exist_ok=True)
        np.savez(path, **graph)
    return graph


def structure(graph: dict) -> dict:
    """Nodes with an edge, edges, universal nodes, conflicts among the rest and their components."""
    i, j = graph["i"], graph["j"]
    nodes = np.unique(np.concatenate([i, j]))
    m = len(nodes)
    pos = np.full(int(graph["n"]), -1)
    pos[nodes] = np.arange(m)
    adj = np.zeros((m, m), bool)
    adj[pos[i], pos[j]] = True
    adj |= adj.T
    missing = ~adj
    np.fill_diagonal(missing, False)
    universal = ~missing.any(axis=1)
    rest = np.flatnonzero(~universal)
    _, labels = connected_components(sp.csr_matrix(missing[np.ix_(rest, rest)]), directed=False)
    sizes = np.bincount(labels) if len(rest) else np.zeros(0, int)
    return {
        "nodes": m,
        "edges": len(i),
        "universal": int(universal.sum()),
        "conflicts": int(missing.sum() // 2),
        "components": len(sizes),
        "largest": int(sizes.max()) if len(sizes) else 0,
    }


def time_search(graph: dict, search: str, max_nodes: int, reps: int, threads: int) -> dict:
    times, out = [], None
    budget = mac_params_for("kitti", "fpfh").enumerate_budget
    for _ in range(reps):
        t0 = time.perf_counter()
        out = cpp.core().select_cliques(
            int(graph["n"]), graph["i"], graph["j"], graph["w"], min_size=4, search=search, max_cliques=0,
            max_nodes=max_nodes, time_limit_s=0.0, enumerate_budget=budget, num_threads=threads,
        )  # fmt: skip
        times.append((time.perf_counter() - t0) * 1e3)
    digest = hashlib.sha1(repr([tuple(int(v) for v in c) for c in out["cliques"]]).encode()).hexdigest()
    return {
        "ms": statistics.median(times),
        "nodes": int(out["search_nodes"]),
        "cap": str(out["cap_hit"]),
        "selected": len(out["cliques"]),
        "used": str(out["search_used"]),
        "digest": digest,  # of the selected cliques in order: equal selections, equal digests
    }


def time_with_core(core_so: str, case: str, search: str, args) -> dict:
    """time_search in a child process that loads another build of the core (FASTMAC_CORE_SO)."""
    cmd = [sys.executable, __file__, "--child", case, search, str(int(args.max_nodes)), str(args.reps)]
    cmd.append(str(args.threads))
    out = subprocess.run(cmd, env={**os.environ, "FASTMAC_CORE_SO": core_so}, capture_output=True, text=True)
    if out.returncode != 0:
        raise SystemExit(f"bench_search: the core {core_so} failed on {case}:\n{out.stderr[-2000:]}")
    return json.loads(out.stdout.strip().splitlines()[-1])


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--cases", nargs="*", default=None, help="default: all (see the module docstring)")
    ap.add_argument("--quick", action="store_true", help=f"only {', '.join(QUICK)}")
    ap.add_argument("--searches", nargs="*", default=["bnb", "auto"], choices=["bnb", "auto", "enumerate"])
    ap.add_argument("--max-nodes", type=float, default=1_000_000, help="mac.max_nodes (default 1,000,000)")
    ap.add_argument("--reps", type=int, default=3)
    ap.add_argument("--threads", type=int, default=1, help="search threads (steps 2-3 are serial anyway)")
    ap.add_argument("--rebuild", action="store_true", help="rebuild the cached graphs")
    ap.add_argument("--old", default=None, help="another build of the core (.so), timed beside this one")
    ap.add_argument(
        "--child", nargs=5, default=None, help=argparse.SUPPRESS
    )  # case search max_nodes reps threads
    args = ap.parse_args(argv)
    if args.child:
        case, search, max_nodes, reps, threads = args.child
        r = time_search(load(case, False), search, int(max_nodes), int(reps), int(threads))
        print(json.dumps(r))
        return 0
    if not cpp.available():
        print("bench_search: the C++ core is not built")
        return 1
    cases = args.cases or (list(QUICK) if args.quick else [*SYNTHETIC, *REAL, *LARGE])
    head = ("nodes", 6), ("edges", 7), ("univ", 5), ("confl", 6), ("comp", 5), ("big", 4)
    print(f"{'case':28s} " + " ".join(f"{h:>{w}s}" for h, w in head) + " | search")
    for case in cases:
        t0 = time.perf_counter()
        graph = load(case, args.rebuild)
        if graph is None:
            print(f"{case:28s} skipped: no shared data at {bench_core.DATA}")
            continue
        s = structure(graph)
        built = time.perf_counter() - t0
        cells = []
        for search in args.searches:
            if args.old:  # the other build first, in its own process, then this one
                o = time_with_core(args.old, case, search, args)
            r = time_search(graph, search, int(args.max_nodes), args.reps, args.threads)
            cap = f" cap {r['cap']}" if r["cap"] else ""
            ran = f" ({r['used']})" if search == "auto" else ""
            cell = f"{search}{ran} {r['ms']:8.1f} ms {r['nodes']:>9,} nodes{cap}"
            if args.old:
                ocap = " cap" if o["cap"] else ""
                same = (
                    "same"
                    if o["digest"] == r["digest"]
                    else ("differ (old capped)" if o["cap"] else "DIFFER")
                )
                ratio = o["ms"] / r["ms"]
                cell += f" <- old {o['ms']:8.1f} ms {o['nodes']:>9,} nodes{ocap} ({ratio:.1f}x, {same})"
            cells.append(cell)
        print(
            f"{case:28s} {s['nodes']:6d} {s['edges']:7d} {s['universal']:5d} {s['conflicts']:6d} "
            f"{s['components']:5d} {s['largest']:4d} | " + " | ".join(cells)
            + (f"   [graph built in {built:.0f} s]" if built > 1 else "")
        )  # fmt: skip
        sys.stdout.flush()
    print(
        "nodes: nodes with an edge; univ: adjacent to all others; confl: missing edges among the rest;\n"
        "comp/big: components of those conflicts and the largest; ms: median of the select_cliques calls\n"
        "(min clique size 4, KITTI); nodes: branch-and-bound search nodes; cap: the node budget was hit.\n"
        "--old: the other build's figures after '<- old', its time over this one's, and whether both\n"
        "selected the same cliques."
    )
    return 0


if __name__ == "__main__":
    sys.exit(main())
