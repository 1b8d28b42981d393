"""Benchmark of the C++ core against the Python reference (MAC stages, sampling, memory, dense graphs).

    python benchmarks/bench_core.py [--quick] [--sizes 1000 5000] [--ratios 1 0.2] [--threads 0]
                                    [--no-python] [--no-dense] [--no-outdoor | --outdoor-only]
                                    [--no-turboreg | --turboreg-only] [--json out.json]
    python benchmarks/bench_core.py --keep-only [bench_keep.py's options]   # issue 41: large inputs by keep

TurboReg section (issue 32): backend=turboreg, MAC, FastMAC@20 and FastMAC@20 + TurboReg end to end on the
10 real reference sets of ../shared/data/turboreg_reference (indoor and outdoor, <= 5,000 FPFH
correspondences), medians of interleaved rounds, with TurboReg's stages and peak RSS growth; without
--quick also 50,000 synthetic 3DMatch-like correspondences with every one kept (max_N null).

Outdoor section (issue 11): for every outdoor pair in ../shared/data (KITTI, LiDAR, Apollo) and every
synthetic KITTI-like pair, FPFH with 5,000 correspondences; then, end to end from the correspondences
(sampling + MAC), medians of repeated runs: MAC@100% and FastMAC@20/@5 with the branch-and-bound
selection (the default), and the same with the full enumeration of maximal cliques (one run, 10 s
wall-clock cap), with the selected cliques compared. Then the ratios and the targets.

For each correspondence source (synthetic 3DMatch-like scenes; FPFH matches of the real 3DMatch pair
`3dm_redkitchen_4_to_0_teaser_fullres` when ../shared/data exists), each N and each sampling ratio:
FastMAC's high-pass sampler scores all N correspondences and keeps floor(N * ratio) (ratio 1 keeps
all), then MAC runs on the kept ones. Per stage it prints the median wall time in ms of the cpp and
python backends, their ratio and the peak RSS of the cpp run. Then the dense (numpy N x N W and
W * (W @ W)) against the sparse (C++) graph construction, and the targets.

The Python backend is skipped from N >= 10,000 (minutes per run); real FPFH data exists only up to the
number of keypoints of the pair (~5,000 at a 5 cm voxel).
"""

from __future__ import annotations

import argparse
import contextlib
import json
import os
import statistics
import sys
import time
from dataclasses import dataclass, field, replace
from pathlib import Path

import numpy as np

REPO = Path(__file__).resolve().parents[1]
if str(REPO) not in sys.path:
    sys.path.insert(0, str(REPO))

from fastmac_exp import core as cpp  # noqa: E402
from fastmac_exp.backends.cpp import CppBackend  # noqa: E402
from fastmac_exp.datasets.planted import planted  # noqa: E402
from fastmac_exp.errors import FastMacError  # noqa: E402
from fastmac_exp.geometry.transforms import rotation_error_deg  # noqa: E402
from fastmac_exp.params import GraphParams, MacParams  # noqa: E402
from fastmac_exp.types import Correspondences  # noqa: E402

DATA = REPO.parent / "shared" / "data"
REAL_PAIR = "3dm_redkitchen_4_to_0_teaser_fullres"
STAGES = ("graph", "cliques", "selection", "pose")
PYTHON_MAX_N = 10_000  # the Python backend is skipped from here on
DENSE_MAX_N = 10_000
# MAC on tens of thousands of correspondences with a large consistent group has ~1e8 maximal cliques
# (a 4000-inlier synthetic cluster); such runs get a time limit on the clique search, reported as a cap.
CAP_FROM_KEPT = 20_000
CAP_SECONDS = 30.0

# 3DMatch + FPFH (spec table 2.2): Gaussian kernel, alpha = 10 * 0.006, thr 0.995; inliers at 0.1 m.
PARAMS = MacParams(graph=GraphParams("gaussian", alpha=0.06, tau=0.1, threshold=0.995), inlier_threshold=0.1)


# ---------------------------------------------------------------------------------------------------
# correspondences


synthetic = planted  # the benchmark's name for it


def real_fpfh() -> tuple[Correspondences, np.ndarray] | None:
    """FPFH matches of the real 3DMatch pair (voxel 0.05, normals r 0.1/30, FPFH r 0.25/100, one-way NN)."""
    pairs_file = DATA / "pairs.json"
    if not pairs_file.exists():
        return None
    pairs = json.loads(pairs_file.read_text())
    entries = pairs.get("pairs", pairs) if isinstance(pairs, dict) else pairs
    entry = next((p for p in entries if isinstance(p, dict) and p.get("id") == REAL_PAIR), None)
    if entry is None:
        print(f"[real] pair {REAL_PAIR} not in {pairs_file}; skipped")
        return None
    from scipy.spatial import cKDTree

    from fastmac_exp._open3d import o3d

    def features(path: Path) -> tuple[np.ndarray, np.ndarray]:
        pcd = o3d.io.read_point_cloud(str(path)).voxel_down_sample(0.05)
        pcd.estimate_normals(o3d.geometry.KDTreeSearchParamHybrid(radius=0.1, max_nn=30))
        f = o3d.pipelines.registration.compute_fpfh_feature(
            pcd, o3d.geometry.KDTreeSearchParamHybrid(radius=0.25, max_nn=100)
        )
        feat = np.asarray(f.data).T
        feat = feat / np.maximum(np.linalg.norm(feat, axis=1, keepdims=True), 1e-12)
        return np.asarray(pcd.points), feat

    ps, fs = features(DATA / entry["source"])
    pt, ft = features(DATA / entry["target"])
    _, nn = cKDTree(ft).query(fs)
    gt = np.loadtxt(DATA / entry["gt"])
    src, tgt = ps, pt[nn]
    labels = np.linalg.norm(src @ gt[:3, :3].T + gt[:3, 3] - tgt, axis=1) < PARAMS.inlier_threshold
    return Correspondences(src, tgt, labels=labels), gt


# ---------------------------------------------------------------------------------------------------
# measurement


def reset_peak_rss() -> bool:
    """Reset the kernel's peak-RSS counter of this process (Linux >= 4.0); False where unsupported."""
    try:
        Path("/proc/self/clear_refs").write_text("5")
        return True
    except OSError:
        return False


def peak_rss_mb() -> float:
    try:
        for line in Path("/proc/self/status").read_text().splitlines():
            if line.startswith("VmHWM:"):
                return int(line.split()[1]) / 1024.0
    except OSError:
        pass
    import resource

    return resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024.0


@dataclass
class Row:
    source: str
    n: int
    ratio: float
    k: int = 0
    inlier_ratio_kept: float = float("nan")
    cpp: dict[str, float] = field(default_factory=dict)  # stage -> median ms
    python: dict[str, float] = field(default_factory=dict)
    python_note: str = ""
    peak_rss_mb: float = float("nan")
    re_deg: float = float("nan")
    te_cm: float = float("nan")
    n_cliques: int = 0
    cap_hit: str = ""
    error: str = ""


def median_stages(runs: list[dict[str, float]]) -> dict[str, float]:
    if not runs:
        return {}
    out = {k: statistics.median(r[k] for r in runs) for k in runs[0]}
    out["mac"] = statistics.median(sum(r[s] for s in STAGES) for r in runs)
    return out


def sampler(impl: str):
    try:
        from fastmac_exp.samplers import GraphFilterSampler
    except ImportError:
        return None
    return GraphFilterSampler("highpass", impl=impl)


def sample(corr: Correspondences, ratio: float, impl: str, seed: int) -> tuple[np.ndarray, float]:
    """Kept indices and sampling time (ms): the high-pass sampler, or a random subset without one."""
    n = len(corr)
    k = n if ratio >= 1 else int(np.floor(n * ratio + 1e-9))
    rng = np.random.default_rng(seed)
    if k >= n:
        return np.arange(n), 0.0
    s = sampler(impl)
    t0 = time.perf_counter()
    if s is None:
        idx = rng.choice(n, k, replace=False)
    else:
        idx = s.sample(corr, ratio, PARAMS.graph, "3dmatch", rng).indices
    return np.asarray(idx), (time.perf_counter() - t0) * 1e3


def params_for(k: int) -> MacParams:
    return replace(PARAMS, time_limit_s=CAP_SECONDS) if k >= CAP_FROM_KEPT else PARAMS


def run_backend(backend, corr: Correspondences, reps: int) -> tuple[list[dict[str, float]], object]:
    runs, res = [], None
    for _ in range(reps):
        res = backend.register(corr, params_for(len(corr)))
        runs.append(dict(res.timings))
    return runs, res


def bench_config(
    source: str, corr: Correspondences, gt: np.ndarray, ratio: float, args, python_backend
) -> Row:
    n = len(corr)
    row = Row(source=source, n=n, ratio=ratio)
    reps = args.reps if n < PYTHON_MAX_N else 1
    cpp_backend = CppBackend(num_threads=args.threads)

    # cpp: sampling (high-pass scores on all n) + MAC on the kept ones; peak RSS over both
    reset_peak_rss()
    samp_ms, idx = [], None
    for r in range(reps if ratio < 1 else 1):
        idx, ms = sample(corr, ratio, "cpp", seed=r)
        samp_ms.append(ms)
    kept = corr.subset(idx)
    row.k = len(kept)
    if kept.labels is not None and len(kept):
        row.inlier_ratio_kept = float(kept.labels.mean())
    try:
        runs, res = run_backend(cpp_backend, kept, reps)
    except FastMacError as exc:
        row.error = f"cpp: {exc}"
        return row
    row.peak_rss_mb = peak_rss_mb()
    row.cpp = median_stages(runs)
    row.cpp["sampling"] = statistics.median(samp_ms)
    row.n_cliques = res.n_cliques
    row.cap_hit = res.cap_hit
    row.re_deg = rotation_error_deg(res.pose[:3, :3], gt[:3, :3])
    row.te_cm = float(np.linalg.norm(res.pose[:3, 3] - gt[:3, 3]) * 100)

    # python on the same kept correspondences
    if python_backend is None:
        row.python_note = "n/a"
    elif n >= PYTHON_MAX_N:
        row.python_note = "skipped"
    else:
        py_samp = sample(corr, ratio, "python", seed=0)[1] if ratio < 1 else 0.0
        try:
            runs, res_py = run_backend(python_backend, kept, args.python_reps)
            row.python = median_stages(runs)
            row.python["sampling"] = py_samp
            if res_py.n_cliques != res.n_cliques or not np.array_equal(res_py.clique, res.clique):
                row.python_note = "DIFFERENT RESULT"
        except FastMacError as exc:
            row.python_note = f"failed: {exc}"
    return row


def sparse_graph_ms(corr: Correspondences, threads: int) -> float:
    """Median ms of the C++ core building W and G (graph_edges)."""
    times = []
    for _ in range(5):
        t0 = time.perf_counter()
        cpp.graph_edges(corr.src, corr.tgt, PARAMS.graph, num_threads=threads)
        times.append((time.perf_counter() - t0) * 1e3)
    return statistics.median(times)


def dense_graph_ms(corr: Correspondences) -> float:
    """ms of numpy building the dense N x N W and G = W * (W @ W)."""
    src, tgt, gp = corr.src, corr.tgt, PARAMS.graph
    n = len(src)
    t0 = time.perf_counter()
    w = np.empty((n, n))
    for a in range(0, n, 1024):  # row blocks keep the temporaries small
        b = min(n, a + 1024)
        dp = np.linalg.norm(src[a:b, None] - src[None], axis=2)
        dq = np.linalg.norm(tgt[a:b, None] - tgt[None], axis=2)
        s = np.exp(-((dp - dq) ** 2) / (2.0 * gp.alpha**2))
        w[a:b] = np.where(s >= gp.threshold, s, 0.0)
    np.fill_diagonal(w, 0.0)
    g = w * (w @ w)
    del w, g
    return (time.perf_counter() - t0) * 1e3


# ---------------------------------------------------------------------------------------------------
# report


def fmt(x: float, width: int = 8) -> str:
    if x != x:  # nan
        return "-".rjust(width)
    if x >= 1000:
        return f"{x:,.0f}".rjust(width)
    return f"{x:.1f}".rjust(width) if x >= 10 else f"{x:.2f}".rjust(width)


def print_table(rows: list[Row], header: bool = True) -> None:
    head = (
        f"{'source':9} {'N':>6} {'ratio':>5} {'kept':>6} {'inl%':>5} | {'sample':>8} {'graph':>8} "
        f"{'cliques':>8} {'select':>8} {'pose':>8} {'MAC':>8} | {'py MAC':>9} {'py samp':>9} "
        f"{'py/cpp':>7} | {'peakMB':>7} {'RE°':>5} {'TEcm':>5} {'#cliq':>7}"
    )
    if header:
        print(head)
        print("-" * len(head))
    for r in rows:
        if r.error:
            print(f"{r.source:9} {r.n:6d} {r.ratio:5.2f} {r.k:6d}  {r.error}")
            continue
        c, p = r.cpp, r.python
        if p:
            py_mac, py_samp = fmt(p["mac"], 9), fmt(p["sampling"], 9)
            speed = f"{p['mac'] / c['mac']:7.1f}" if c["mac"] > 0 else "      -"
        else:
            py_mac, py_samp, speed = r.python_note.rjust(9), "".rjust(9), "".rjust(7)
        if p and r.python_note:
            speed = r.python_note[:7]
        print(
            f"{r.source:9} {r.n:6d} {r.ratio:5.2f} {r.k:6d} {100 * r.inlier_ratio_kept:5.1f} | "
            f"{fmt(c['sampling'])} {fmt(c['graph'])} {fmt(c['cliques'])} {fmt(c['selection'])} "
            f"{fmt(c['pose'])} {fmt(c['mac'])} | {py_mac} {py_samp} {speed} | "
            f"{fmt(r.peak_rss_mb, 7)} {r.re_deg:5.1f} {r.te_cm:5.1f} {r.n_cliques:7d}"
            + (f"  cap: {r.cap_hit}" if r.cap_hit else "")
        )


# ---------------------------------------------------------------------------------------------------
# outdoor: real KITTI/LiDAR pairs and synthetic KITTI-like pairs, branch and bound against enumeration

ENUM_CAP_S = 10.0


def outdoor_pairs(quick: bool, keep=None) -> list[tuple[str, Correspondences, np.ndarray]]:
    """(name, 5,000 FPFH correspondences with labels, GT) of the outdoor pairs: real ones, then synthetic
    (keep: a test on 'real:<pair>' / 'syn:<pair>', the pairs described; default all)."""
    from fastmac_exp.datasets.synthetic import SyntheticDataset
    from fastmac_exp.datasets.user_pairs import SharedRealPairs
    from fastmac_exp.descriptors.fpfh import FPFHDescriptor

    describe = FPFHDescriptor(max_correspondences=5000)
    out = []
    sets = []
    if (DATA / "pairs.json").exists():
        sets.append(("real", SharedRealPairs(root=str(DATA), category="outdoor")))
    else:
        print(f"[outdoor] no shared data at {DATA}: real outdoor pairs skipped")
    sets.append(("syn", SyntheticDataset(family="kitti", num_pairs=3 if quick else 8)))
    for tag, ds in sets:
        for i, name in enumerate(ds.names()):
            if keep is not None and not keep(f"{tag}:{name}"):
                continue
            pair = ds.load(i)
            corr = describe(pair, np.random.default_rng(0))
            pair.label(corr)
            out.append((f"{tag}:{name}", corr, pair.gt))
    return out


@dataclass
class OutdoorRow:
    name: str
    inlier_ratio: float
    ms: dict[str, float] = field(default_factory=dict)  # method -> median ms end to end
    cap: dict[str, str] = field(default_factory=dict)
    same: dict[str, str] = field(default_factory=dict)  # ratio -> selections auto, bnb == enumeration?
    re_deg: dict[str, float] = field(default_factory=dict)
    nodes: dict[str, int] = field(default_factory=dict)
    sampling_ms: dict[str, float] = field(default_factory=dict)  # auto's median sampling ms, by ratio
    used: dict[str, str] = field(default_factory=dict)  # ratio -> the search auto ran


def outdoor_run(corr: Correspondences, ratio: float, search: str, reps: int, threads: int):
    """Median ms of sampling + MAC, the last result and its selected cliques (res["sampling_ms"]: the
    median ms of the sampling alone)."""
    from fastmac_exp.params import mac_params_for

    params = mac_params_for("kitti", "fpfh", mac_overrides={"search": search})
    if search == "enumerate":
        params = replace(params, time_limit_s=ENUM_CAP_S)
    core = cpp.core()
    times, sampling, res = [], [], None
    for _ in range(reps):
        t0 = time.perf_counter()
        if ratio < 1:
            s = sampler("cpp")
            # the same draw every repeat, and for both searches, so that their selections compare
            idx = s.sample(corr, ratio, params.graph, "kitti", np.random.default_rng(0)).indices
        else:
            idx = np.arange(len(corr))
        sampling.append((time.perf_counter() - t0) * 1e3)
        kept = corr.subset(np.asarray(idx))
        g = params.graph
        res = core.mac(
            kept.src, kept.tgt, g.kernel, g.alpha, g.tau, g.threshold, params.inlier_threshold,
            min_clique_size=params.min_clique_size, search=search, max_nodes=params.max_nodes,
            time_limit_s=params.time_limit_s, num_threads=threads, return_selected=True,
            # only for auto: compare_cores.py runs this with builds of the core that predate it
            **({"enumerate_budget": params.enumerate_budget} if search == "auto" else {}),
        )  # fmt: skip
        times.append((time.perf_counter() - t0) * 1e3)
    res["sampling_ms"] = statistics.median(sampling)  # of the same repeats: the split of the total
    return statistics.median(times), res


def bench_outdoor(args) -> list[OutdoorRow]:
    t0 = time.perf_counter()
    pairs = outdoor_pairs(args.quick)
    took = time.perf_counter() - t0
    print(f"\nOutdoor: {len(pairs)} pairs described (FPFH, 5,000 correspondences) in {took:.0f} s")
    head = (
        f"{'pair':34} {'inl%':>5} | {'MAC auto':>8} {'bnb':>8} {'enum':>9} | {'FM20 auto':>9} {'bnb':>8} "
        f"{'enum':>9} | {'FM5 auto':>8} | {'FM20/MAC':>8} | same 100/20 | RE100 RE20"
    )
    print(head)
    print("-" * len(head))
    rows = []
    for name, corr, gt in pairs:
        row = OutdoorRow(name=name, inlier_ratio=float(corr.labels.mean()))
        for ratio in (1.0, 0.2, 0.05):
            key = {1.0: "100", 0.2: "20", 0.05: "5"}[ratio]
            results = {}
            # auto (the default) and bnb, repeated; the enumeration once (capped), as the reference
            for search, reps in (("auto", args.reps), ("bnb", args.reps), ("enumerate", 1)):
                if ratio == 0.05 and search != "auto":
                    continue
                tag = {"auto": "auto", "bnb": "bnb", "enumerate": "enum"}[search] + key
                try:
                    ms, res = outdoor_run(corr, ratio, search, reps, args.threads)
                except FastMacError as exc:
                    row.cap[tag] = f"failed: {exc}"
                    continue
                row.ms[tag] = ms
                row.cap[tag] = res["cap_hit"]
                results[search] = res
            if "auto" not in results:
                continue
            res = results["auto"]
            row.sampling_ms[key] = float(res["sampling_ms"])
            row.nodes[key] = int(res["search_nodes"])
            row.used[key] = str(res.get("search_used", "?"))
            row.re_deg[key] = rotation_error_deg(res["pose"][:3, :3], gt[:3, :3])
            eres = results.get("enumerate")
            if eres is None:
                continue
            if eres["cap_hit"]:
                row.same[key] = "capped"
            else:
                ref = [tuple(c) for c in eres["selected"]]
                same = all(
                    [tuple(c) for c in results[s]["selected"]] == ref for s in ("auto", "bnb") if s in results
                )
                row.same[key] = "yes" if same else "NO"
        m = row.ms

        def cell(k, w=8, m=m, row=row):
            txt = fmt(m.get(k, float("nan")), w)
            return txt + ("*" if row.cap.get(k) else " ")

        fm_over_mac = f"{m['auto20'] / m['auto100']:8.2f}" if "auto20" in m and "auto100" in m else "       -"
        print(
            f"{name[:34]:34} {100 * row.inlier_ratio:5.1f} | {cell('auto100')}{cell('bnb100')}"
            f"{cell('enum100', 8)} | {cell('auto20', 9)}{cell('bnb20')}{cell('enum20', 8)} | "
            f"{cell('auto5')} | {fm_over_mac} | "
            f"{row.same.get('100', '-'):>4}/{row.same.get('20', '-'):<4}   | "
            f"{row.re_deg.get('100', float('nan')):5.2f} {row.re_deg.get('20', float('nan')):5.2f}  "
            f"auto ran {row.used.get('100', '-')}/{row.used.get('20', '-')}/{row.used.get('5', '-')}"
        )
        sys.stdout.flush()
        rows.append(row)
    legend = (
        "ms = median wall time of sampling + MAC from the correspondences. auto: the default search\n"
        "(the enumeration within mac.enumerate_budget, else the branch and bound; 'auto ran' says which,\n"
        "at 100/20/5 %); bnb: branch and bound; enum: every maximal clique, one run, capped at\n"
        f"{ENUM_CAP_S:g} s; '*' = a cap was hit. same = auto's and bnb's selected cliques both identical\n"
        "to the enumeration's (capped: the enumeration did not finish)."
    )
    print(legend)
    print()
    print("Outdoor targets (medians over the pairs of each set)")
    for tag, label in (("real:", "real KITTI/LiDAR/Apollo"), ("syn:", "synthetic KITTI-like")):
        sel = [r for r in rows if r.name.startswith(tag)]
        if not sel:
            continue

        def med(k, sel=sel):
            vals = [r.ms[k] for r in sel if k in r.ms]
            return statistics.median(vals) if vals else float("nan")

        worst = max(max(r.ms.get(k, 0) for k in ("auto100", "auto20", "auto5")) for r in sel)
        fm20 = sorted((r for r in sel if "auto20" in r.ms), key=lambda r: r.ms["auto20"])
        print(
            f"  {label} ({len(sel)} pairs): MAC@100 {med('auto100'):.0f} ms (target < 150), FastMAC@20 "
            f"{med('auto20'):.0f} ms (target < 30), FastMAC@5 {med('auto5'):.0f} ms; FastMAC@20 / MAC = "
            f"{med('auto20') / med('auto100'):.2f}; bnb: MAC {med('bnb100'):.0f}, "
            f"FastMAC@20 {med('bnb20'):.0f} ms; "
            f"enumeration / auto: MAC {med('enum100') / med('auto100'):.1f}x, "
            f"FastMAC@20 {med('enum20') / med('auto20'):.1f}x (enumeration capped at {ENUM_CAP_S:g} s); "
            f"slowest pair {worst:.0f} ms"
        )
        if fm20:  # where FastMAC@20's time goes, pair by pair (sampling + MAC on the kept)
            parts = []
            for r in fm20:
                sampled = r.sampling_ms["20"]
                parts.append(f"{r.name.split(':', 1)[1][:16]} {sampled:.0f}+{r.ms['auto20'] - sampled:.0f}")
            split = ", ".join(parts)
            print(f"    FastMAC@20 sampling + MAC ms, fastest to slowest: {split}")
        disagree = [r.name for r in sel if "NO" in r.same.values()]
        verdict = "yes" if not disagree else disagree
        print(f"    selections identical where the enumeration finished: {verdict}")
    bench_products([(name, corr) for name, corr, _ in pairs], args)
    bench_outdoor_large(args)
    return rows


@contextlib.contextmanager
def core_switch(name: str, value: str | None):
    """The core's environment switch `name` (FASTMAC_DENSE_CORE, FASTMAC_TRIANGLES, ...) set to `value`
    (None: unset, the default) for the block, then restored."""
    old = os.environ.get(name)
    if value is None:
        os.environ.pop(name, None)
    else:
        os.environ[name] = value
    try:
        yield
    finally:
        if old is None:
            os.environ.pop(name, None)
        else:
            os.environ[name] = old


def signals_ms(
    corr: Correspondences,
    reps: int,
    threads: int,
    single: bool,
    dense: bool,
    threshold: float | None = None,
    triangles: str | None = None,
) -> tuple[float, int]:
    """Median ms of the sampler's graph and signals (graph_signals), and the dense core's size.
    threshold=1.0 leaves no edge: what remains is the first-order screen over all N^2 / 2 pairs.
    triangles: FASTMAC_TRIANGLES (on | off; None: the default, by the core's gate)."""
    from dataclasses import replace

    from fastmac_exp.params import mac_params_for

    g = mac_params_for("kitti", "fpfh").graph
    g = g if threshold is None else replace(g, threshold=threshold)
    dense_core = core_switch("FASTMAC_DENSE_CORE", "on" if dense else "off")
    with dense_core, core_switch("FASTMAC_TRIANGLES", triangles):
        times, out = [], None
        for _ in range(reps):
            t0 = time.perf_counter()
            out = cpp.graph_signals(corr.src, corr.tgt, g, single=single, num_threads=threads)
            times.append((time.perf_counter() - t0) * 1e3)
    return statistics.median(times), int(out.dense_core)


def bench_products(pairs: list[tuple[str, Correspondences]], args) -> None:
    """The sampler's second-order graph (issue 11, item 3): sparse gathers against the dense-core product."""
    print("\nSampler graph + signals (graph_signals, 5,000 correspondences, KITTI/FPFH kernel), median ms")
    head = (
        f"{'pair':34} {'core':>5} | {'screen':>7} {'sparse':>8} {'core f64':>9} {'core f32':>9} "
        f"{'listing':>8} | {'x f64':>6} {'x f32':>6} | {'sgemm':>6}"
    )
    print(head)
    print("-" * len(head))
    for name, corr in pairs:
        screen, _ = signals_ms(corr, args.reps, args.threads, single=True, dense=True, threshold=1.0)
        sp_ms, _ = signals_ms(corr, args.reps, args.threads, single=False, dense=False)
        d64, m = signals_ms(corr, args.reps, args.threads, single=False, dense=True)
        d32, _ = signals_ms(corr, args.reps, args.threads, single=True, dense=True, triangles="off")
        tri, _ = signals_ms(corr, args.reps, args.threads, single=True, dense=True, triangles="on")
        print(
            f"{name[:34]:34} {m:5d} | {screen:7.1f} {sp_ms:8.1f} {d64:9.1f} {d32:9.1f} {tri:8.1f} | "
            f"{sp_ms / d64:6.1f} {sp_ms / d32:6.1f} | {sgemm_ms(m, args.reps):6.1f}"
        )
        sys.stdout.flush()
    print("screen: the first-order screen alone (threshold 1: no edge); sparse: every product by gathers")
    print("(FASTMAC_DENSE_CORE=off); core: the dense core's products as a matrix product in float64 or")
    print("float32 (the sampler's default, as FastMAC's torch code); listing: core f32 with the rest by the")
    print("triangle listing (FASTMAC_TRIANGLES=on; by default it starts at 2^21 entries outside the core, so")
    print("not on these pairs); core = its nodes; sgemm: numpy's")
    print(
        "(OpenBLAS) full float32 product of a core-sized matrix, its BLAS threads: a reference for the core"
    )


def sgemm_ms(m: int, reps: int) -> float:
    """Median ms of numpy's float32 m x m matrix product (the dense core's work done by OpenBLAS, in full)."""
    a = np.random.default_rng(0).random((m, m), dtype=np.float32)
    times = []
    for _ in range(max(1, reps)):
        t0 = time.perf_counter()
        a @ a
        times.append((time.perf_counter() - t0) * 1e3)
    return statistics.median(times)


def bench_outdoor_large(args) -> None:
    """50,000 outdoor-scale correspondences at ratio 0.05, end to end (sampling + MAC), one run each."""
    from fastmac_exp.params import mac_params_for

    print("\n50,000 outdoor correspondences (60 x 60 x 4 m, noise 0.1 m, KITTI/FPFH kernel), ratio 0.05")
    params = mac_params_for("kitti", "fpfh")
    g = params.graph
    for inl in (0.02, 0.05, 0.1):
        corr, gt = synthetic(50_000, inlier_ratio=inl, noise=0.1, seed=1, room=(60.0, 60.0, 4.0))
        # the sampler's graph by the per-edge gathers (FASTMAC_TRIANGLES=off), then as by default
        with core_switch("FASTMAC_TRIANGLES", "off"):
            t0 = time.perf_counter()
            sampler("cpp").sample(corr, 0.05, g, "kitti", np.random.default_rng(0))
            t_gathers = (time.perf_counter() - t0) * 1e3
        t0 = time.perf_counter()
        idx = sampler("cpp").sample(corr, 0.05, g, "kitti", np.random.default_rng(0)).indices
        t_s = (time.perf_counter() - t0) * 1e3
        kept = corr.subset(np.asarray(idx))
        t1 = time.perf_counter()
        res = cpp.core().mac(
            kept.src, kept.tgt, g.kernel, g.alpha, g.tau, g.threshold, params.inlier_threshold,
            min_clique_size=params.min_clique_size, max_nodes=params.max_nodes, num_threads=args.threads,
        )  # fmt: skip
        t_m = (time.perf_counter() - t1) * 1e3
        re = rotation_error_deg(res["pose"][:3, :3], gt[:3, :3])
        print(
            f"  inliers {100 * inl:4.1f} %: sampling {t_s:6.0f} ms + MAC on {len(kept)} "
            f"({100 * kept.labels.mean():.0f} % "
            f"inliers) {t_m:5.0f} ms = {t_s + t_m:6.0f} ms (target < 1000); RE {re:.2f} deg; "
            f"sampling by per-edge gathers {t_gathers:6.0f} ms ({t_gathers / t_s:.2f}x)"
            + (f"; cap {res['cap_hit']}" if res["cap_hit"] else "")
        )
        sys.stdout.flush()


def main(argv: list[str] | None = None) -> int:
    argv = sys.argv[1:] if argv is None else argv
    if "--keep-only" in argv:  # issue 41's large inputs by keep size (benchmarks/bench_keep.py, its options)
        from benchmarks.bench_keep import main as keep_main

        return keep_main([a for a in argv if a != "--keep-only"])
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--quick", action="store_true", help="N up to 5000, ratios 1 and 0.2, fewer repeats")
    ap.add_argument("--sizes", type=int, nargs="*", default=None)
    ap.add_argument("--ratios", type=float, nargs="*", default=None)
    ap.add_argument("--reps", type=int, default=None, help="cpp repeats per configuration (median)")
    ap.add_argument("--python-reps", type=int, default=1)
    ap.add_argument("--threads", type=int, default=0, help="cpp threads (0 = automatic)")
    ap.add_argument("--no-python", action="store_true")
    ap.add_argument("--no-dense", action="store_true")
    ap.add_argument("--no-outdoor", action="store_true", help="skip the outdoor section")
    ap.add_argument("--outdoor-only", action="store_true", help="only the outdoor section")
    ap.add_argument(
        "--products-only", action="store_true", help="only the sampler-graph table of the outdoor pairs"
    )
    ap.add_argument("--turboreg-only", action="store_true", help="only the TurboReg section (issue 32)")
    ap.add_argument("--no-turboreg", action="store_true", help="skip the TurboReg section")
    ap.add_argument("--json", type=Path, default=None, help="also write the rows here")
    ap.add_argument("--scores-only", action="store_true", help="only the estimated-scores section (issue 29)")
    ap.add_argument("--max-n", type=int, default=1_000_000, help="largest N of the estimated-scores section")
    args = ap.parse_args(argv)
    sizes = args.sizes or ([1000, 2500, 5000] if args.quick else [1000, 2500, 5000, 10000, 50000])
    ratios = args.ratios or ([1.0, 0.2] if args.quick else [1.0, 0.5, 0.2, 0.05])
    args.reps = args.reps or (3 if args.quick else 5)

    if not cpp.available():
        print(cpp.BUILD_HINT.format(why="import failed"))
        return 1
    core = cpp.core()
    if args.scores_only:
        bench_scores(args)
        return 0
    if args.products_only:
        bench_products([(name, corr) for name, corr, _ in outdoor_pairs(args.quick)], args)
        return 0
    if args.turboreg_only:
        rows = bench_turboreg(args)
        if args.json:
            args.json.write_text(json.dumps(rows, indent=1, default=float))
        return 0
    if args.outdoor_only:
        args.reps = args.reps or 3
        rows = bench_outdoor(args)
        if args.json:
            args.json.write_text(json.dumps([r.__dict__ for r in rows], indent=1, default=float))
        return 0
    threads = args.threads or core.default_threads()
    print(
        f"fastmac_exp C++ core: {core.parallel_backend} backend, {threads} thread(s) "
        f"(one below N={core.serial_below} unless --threads), params: {PARAMS.graph}, "
        f"inlier threshold {PARAMS.inlier_threshold} m"
    )
    python_backend = None
    if not args.no_python:
        try:
            from fastmac_exp.backends.python_mac import PythonBackend

            python_backend = PythonBackend()
        except ImportError as exc:
            print(f"python backend unavailable ({exc}); cpp only")

    sources: list[tuple[str, object]] = [("synthetic", None)]
    real = None
    if DATA.exists():
        t0 = time.perf_counter()
        real = real_fpfh()
        if real is not None:
            sources.append(("real", real))
            print(
                f"real FPFH correspondences of {REAL_PAIR}: {len(real[0])} "
                f"({100 * real[0].inlier_ratio:.1f}% inliers), {time.perf_counter() - t0:.1f} s to compute"
            )
    else:
        print(f"no shared data at {DATA}: real-data rows skipped")

    rows: list[Row] = []
    for name, data in sources:
        for n in sizes:
            if name == "real":
                corr_all, gt = data
                if n > len(corr_all):
                    print(f"[real] N={n}: only {len(corr_all)} FPFH correspondences at a 5 cm voxel; skipped")
                    continue
                idx = np.random.default_rng(0).permutation(len(corr_all))[:n]
                corr = corr_all.subset(idx)
            else:
                corr, gt = synthetic(n, seed=n)
            for ratio in ratios:
                row = bench_config(name, corr, gt, ratio, args, python_backend)
                rows.append(row)
                print_table([row], header=len(rows) == 1)  # progress; the full table follows
                sys.stdout.flush()

    print()
    print("Per-stage median wall time (ms); MAC = graph + cliques + selection + pose; sampling = high-pass")
    print("scores on all N + draw (0 at ratio 1); py/cpp = python MAC / cpp MAC; peakMB = peak RSS of the")
    print(
        "cpp sampling + MAC; RE/TE of the refined cpp pose against the GT. MAC on >= "
        f"{CAP_FROM_KEPT} kept rows runs with time_limit_s={CAP_SECONDS:g} ('cap')."
    )
    print()
    print_table(rows)

    # before the dense comparison: OpenBLAS threads keep spinning after its big matrix products
    signals_line = ""
    if real is not None and len(real[0]) >= 5000:
        corr = real[0].subset(np.random.default_rng(0).permutation(len(real[0]))[:5000])
        times = []
        for _ in range(10):
            t0 = time.perf_counter()
            cpp.graph_signals(corr.src, corr.tgt, PARAMS.graph, num_threads=args.threads)
            times.append((time.perf_counter() - t0) * 1e3)
        signals_line = (
            f"  graph_signals on 5000 real: median {statistics.median(times):.1f} ms, "
            f"best {min(times):.1f} ms (a few ms)"
        )

    if not args.no_dense:
        print()
        print("Graph construction, W and G = W * (W @ W): dense numpy N x N against the sparse C++ core (ms)")
        print(f"{'source':9} {'N':>6} | {'dense':>9} {'sparse':>8} {'ratio':>7}")
        configs = []
        for name, data in sources:
            for n in sizes:
                if n > DENSE_MAX_N or (args.quick and n > 5000):
                    continue
                if name == "real":
                    if n > len(data[0]):
                        continue
                    corr = data[0].subset(np.random.default_rng(0).permutation(len(data[0]))[:n])
                else:
                    corr = synthetic(n, seed=n)[0]
                configs.append((name, n, corr))
        # all sparse timings first: after numpy's big matrix products OpenBLAS threads keep spinning
        sparse = [sparse_graph_ms(corr, args.threads) for _, _, corr in configs]
        for (name, n, corr), sp_ms in zip(configs, sparse):
            dense = dense_graph_ms(corr)
            print(f"{name:9} {n:6d} | {dense:9.1f} {sp_ms:8.2f} {dense / sp_ms:7.0f}")

    print()
    print("Targets")
    if signals_line:
        print(signals_line)
    for r in rows:
        if r.source == "real" and r.n == 5000 and r.ratio == 1.0 and r.cpp:
            speed = f"{r.python['mac'] / r.cpp['mac']:.0f}x" if r.python else r.python_note
            print(
                f"  MAC, 5000 real FPFH, ratio 1: {r.cpp['mac']:.1f} ms (< 150), "
                f"{speed} faster than python (>= 20x)"
            )
        if r.n == 50000 and abs(r.ratio - 0.05) < 1e-9 and r.cpp:
            print(
                f"  50,000 {r.source} at ratio 0.05: peak RSS {r.peak_rss_mb / 1024:.2f} GiB (< 4), "
                f"sampling {r.cpp['sampling']:.0f} ms + MAC on {r.k}: {r.cpp['mac']:.0f} ms"
            )
    outdoor = [] if args.no_outdoor else bench_outdoor(args)
    turbo = [] if args.no_turboreg else bench_turboreg(args)
    if args.json:
        data = {
            "indoor": [r.__dict__ for r in rows],
            "outdoor": [r.__dict__ for r in outdoor],
            "turboreg": turbo,
        }
        args.json.write_text(json.dumps(data, indent=1, default=float))
        print(f"rows written to {args.json}")
    return 0


# ---------------------------------------------------------------------------------------------------
# TurboReg (issue 32): backend=turboreg beside MAC and FastMAC on the same inputs

TURBO_METHODS = ("turboreg", "mac", "fastmac20", "fastmac20_turboreg")


def turbo_inputs() -> list[tuple[str, str, Correspondences, np.ndarray]]:
    """(name, family, correspondences, GT): the 10 fixed sets of ../shared/data/turboreg_reference (real
    indoor and outdoor pairs, the project's FPFH, <= 5,000 correspondences each)."""
    ref = DATA / "turboreg_reference" / "turboreg_reference.json"
    if not ref.exists():
        print(f"[turboreg] no {ref}: real pairs skipped")
        return []
    out = []
    for name, e in json.loads(ref.read_text())["pairs"].items():
        z = np.load(ref.parent / e["file"], allow_pickle=True)
        out.append((name, str(z["family"]), Correspondences(z["src"], z["tgt"], labels=z["labels"]), z["gt"]))
    return out


def turbo_once(method: str, corr: Correspondences, family: str, max_n="family"):
    """(ms end to end from the correspondences, result, peak RSS growth in MB) of one method, one run."""
    from fastmac_exp.backends.turboreg import TurboRegBackend
    from fastmac_exp.params import mac_params_for
    from fastmac_exp.pipeline import register_correspondences
    from fastmac_exp.samplers import GraphFilterSampler, NoSampler

    params = mac_params_for(family, "fpfh")
    backend = TurboRegBackend(max_N=max_n) if method.endswith("turboreg") else CppBackend()
    fast = method.startswith("fastmac20")
    smp = GraphFilterSampler("highpass") if fast else NoSampler()
    base = peak_rss_mb() if reset_peak_rss() else float("nan")
    t0 = time.perf_counter()
    res, _ = register_correspondences(corr, params, smp, backend, 0.2 if fast else 1.0, family,
                                      np.random.default_rng(0), sample_graph=params.graph)  # fmt: skip
    ms = (time.perf_counter() - t0) * 1e3
    return ms, res, peak_rss_mb() - base


TURBO_MEMORY = """
import sys, numpy as np
from pathlib import Path
from fastmac_exp.backends.turboreg import TurboRegBackend
from fastmac_exp.params import mac_params_for
from fastmac_exp.types import Correspondences
def hwm():
    lines = Path("/proc/self/status").read_text().splitlines()
    return next(int(x.split()[1]) / 1024 for x in lines if x.startswith("VmHWM:"))
z = np.load(sys.argv[1], allow_pickle=True)
corr, params = Correspondences(z["src"], z["tgt"]), mac_params_for(str(z["family"]), "fpfh")
backend = TurboRegBackend()
base = hwm()
backend.register(corr, params)
print(hwm(), hwm() - base)
"""


def turbo_memory(npz: Path) -> tuple[float, float]:
    """(peak RSS, its growth during the call) in MB of TurboReg alone on one reference set, in a fresh
    process (in this one, memory freed by earlier runs stays mapped: keep_freed_memory)."""
    import subprocess

    cmd = [sys.executable, "-c", TURBO_MEMORY, str(npz)]
    out = subprocess.run(cmd, capture_output=True, text=True, cwd=REPO)
    try:
        peak, growth = (float(v) for v in out.stdout.split()[-2:])
        return peak, growth
    except ValueError:
        return float("nan"), float("nan")


def bench_turboreg(args) -> list[dict]:
    """Interleaved rounds (medians) of TurboReg, MAC, FastMAC@20 and FastMAC@20 + TurboReg on the real
    reference sets; then 50,000 synthetic 3DMatch-like correspondences with every one kept (max_N null)."""
    from fastmac_exp.families import family as family_record
    from fastmac_exp.geometry.metrics import pose_errors

    reps = args.reps or 3
    threads = cpp.core().default_threads()
    print(f"\nTurboReg (backend=turboreg) beside MAC and FastMAC@20, end to end, medians of {reps} "
          f"interleaved rounds, {threads} thread(s); ms (success), TurboReg's stages and its peak RSS "
          "growth")  # fmt: skip
    print(f"  {'pair':38s} {'N':>5s} | {'TurboReg':>12s} {'MAC':>12s} {'FastMAC20':>12s} {'F20+TR':>12s} | "
          f"{'MAC/TR':>6s} | TR graph/pivots/hyp/pose ms | TR MB (fresh process; 50k: in this "
          "one)")  # fmt: skip
    rows = []
    inputs = [(name, fam, corr, gt, "family") for name, fam, corr, gt in turbo_inputs()]
    if not args.quick:
        corr, gt = synthetic(50_000, seed=50_000)
        inputs.append(("synthetic 3DMatch-like, all", "3dmatch", corr, gt, None))
    for name, fam, corr, gt, max_n in inputs:
        runs = {m: [] for m in TURBO_METHODS}
        big = len(corr) > 10_000
        methods = TURBO_METHODS
        for _ in range(1 if big else reps):
            for m in methods:
                try:
                    ms, res, mb = turbo_once(m, corr, fam, max_n)
                    rec = family_record(fam)
                    ok = pose_errors(res.pose, gt, rec.re_thresh_deg, rec.te_thresh_m).success
                    runs[m].append((ms, ok, res.timings, mb))
                except FastMacError as exc:
                    runs[m].append((float("nan"), False, {}, float("nan")))
                    print(f"    {m}: {exc}")
        med = {m: statistics.median(r[0] for r in runs[m]) for m in methods}
        ok = {m: runs[m][-1][1] for m in methods}
        tr = runs["turboreg"][-1][2]
        stages = "/".join(f"{statistics.median(r[2].get(s, float('nan')) for r in runs['turboreg']):.1f}"
                          for s in ("graph", "pivots", "hypotheses", "pose"))  # fmt: skip
        npz = DATA / "turboreg_reference" / f"{name}.npz"
        mb = turbo_memory(npz)[1] if npz.exists() else max(r[3] for r in runs["turboreg"])
        cells = " ".join(f"{med[m]:8.1f} ({'y' if ok[m] else 'n'})" for m in methods)
        print(f"  {name[:38]:38s} {len(corr):5d} | {cells} | {med['mac'] / med['turboreg']:6.2f} | "
              f"{stages:>27s} | {mb:5.0f}")  # fmt: skip
        rows.append(
            {
                "pair": name,
                "family": fam,
                "n": len(corr),
                "ms": med,
                "success": ok,
                "turboreg_mb": mb,
                "turboreg_stages": {s: tr.get(s) for s in ("graph", "pivots", "hypotheses", "pose")},
            }
        )
        sys.stdout.flush()
    indoor = [r["ms"]["turboreg"] for r in rows if r["family"] != "kitti" and r["n"] <= 10_000]
    outdoor = [r["ms"]["turboreg"] for r in rows if r["family"] == "kitti"]
    mbs = [r["turboreg_mb"] for r in rows if r["n"] <= 10_000]
    if indoor:
        print(f"  targets: TurboReg indoor max {max(indoor):.1f} ms (< 20), outdoor max "
              f"{max(outdoor or [0]):.1f} ms "
              f"(< 40), peak RSS growth max {max(mbs):.0f} MB (< 200)")  # fmt: skip
    for r in rows:
        if r["n"] > 10_000:
            print(f"  50,000 with every correspondence: {r['ms']['turboreg']:.0f} ms (< 2000)")
    return rows


# ---------------------------------------------------------------------------------------------------
# estimated sampler scores (issue 29)


def fastmac_once(corr, params, scores: str, ratio: float, family: str, seed: int, samples=None):
    """(sampling ms, end-to-end ms, result, sample) of FastMAC's high-pass sampler + C++ MAC, one run."""
    from fastmac_exp.pipeline import register_correspondences
    from fastmac_exp.samplers import GraphFilterSampler, NoSampler

    sampler = NoSampler() if scores == "none" else GraphFilterSampler(scores=scores)
    t0 = time.perf_counter()
    res, s = register_correspondences(
        corr, params, sampler, CppBackend(), ratio, family, np.random.default_rng(seed),
        sample_graph=params.graph, samples=samples,
    )  # fmt: skip
    total = (time.perf_counter() - t0) * 1e3
    return s.timings.get("sampling", 0.0), total, res, s


def kiss_once(corr, params) -> float | None:
    try:
        from fastmac_exp.backends.peers import KissMatcherBackend

        backend = KissMatcherBackend()
    except Exception:  # noqa: BLE001 - the peer is optional (the dev extra has it)
        return None
    t0 = time.perf_counter()
    try:
        backend.register(corr, params)
    except FastMacError:
        pass
    return (time.perf_counter() - t0) * 1e3


def scores_pairs_table(pairs, reps: int, title: str) -> dict[str, list[float]]:
    """FastMAC@20 with exact and estimated (auto) scores, MAC@100 and KISS-Matcher, interleaved reps."""
    from fastmac_exp.params import mac_params_for

    print(
        f"\n{title}: medians of {reps} interleaved rounds, ms (exact = the scores every earlier "
        f"core computed)"
    )
    print(f"  {'pair':40s} {'auto':>8s} {'samp ex':>8s} {'samp est':>8s} {'F@20 ex':>8s} {'F@20 est':>8s} "
          f"{'MAC@100':>8s} {'KISS':>8s} {'MAC/F20':>8s} {'KISS/F20':>8s} "
          f"{'kept inl ex/est':>16s}")  # fmt: skip
    cols: dict[str, list[float]] = {
        k: [] for k in ("samp_ex", "samp_est", "f20_ex", "f20_est", "mac", "kiss")
    }
    for name, corr, family, sgraph_res in pairs:
        params = mac_params_for(family, "fpfh")
        sparams = replace(params, graph=mac_params_for(family, "fpfh", sgraph_res).graph)
        t = {k: [] for k in cols}
        kept = {"exact": [], "auto": []}
        used = ""
        for r in range(reps):
            for mode in ("exact", "auto"):
                ts, tt, _, s = fastmac_once(corr, sparams, mode, 0.2, family, r)
                key = "ex" if mode == "exact" else "est"
                t[f"samp_{key}"].append(ts)
                t[f"f20_{key}"].append(tt)
                kept[mode].append(corr.labels[s.indices].mean() if corr.labels is not None else np.nan)
                used = s.scores_used if mode == "auto" else used
            t["mac"].append(fastmac_once(corr, params, "none", 1.0, family, r)[1])
            k = kiss_once(corr, params)
            if k is not None:
                t["kiss"].append(k)
        med = {k: (statistics.median(v) if v else float("nan")) for k, v in t.items()}
        for k in cols:
            cols[k].append(med[k])
        print(f"  {name[:40]:40s} {used:>8s} {med['samp_ex']:8.1f} {med['samp_est']:8.1f} "
            f"{med['f20_ex']:8.1f} "
              f"{med['f20_est']:8.1f} {med['mac']:8.1f} {med['kiss']:8.1f} "
              f"{med['mac'] / med['f20_est']:7.1f}x "
              f"{med['kiss'] / med['f20_est']:7.1f}x "
              f"{np.mean(kept['exact']):7.3f}/{np.mean(kept['auto']):.3f}")  # fmt: skip
        sys.stdout.flush()
    return cols


def large_case(n: int, inl: float, ratio: float, samples, scores: str, seed: int = 1):
    """bench_core's outdoor-like scene at n correspondences: (sampling ms, total ms, RE deg, kept inlier
    ratio, peak RSS MB, the result)."""
    from fastmac_exp.params import mac_params_for

    corr, gt = synthetic(n, inlier_ratio=inl, noise=0.1, seed=seed, room=(60.0, 60.0, 4.0))
    params = mac_params_for("kitti", "fpfh")
    reset_peak_rss()
    ts, tt, res, s = fastmac_once(corr, params, scores, ratio, "kitti", 0, samples=samples)
    re = rotation_error_deg(res.pose[:3, :3], gt[:3, :3])
    te = float(np.linalg.norm(res.pose[:3, 3] - gt[:3, 3]))
    ok = re < 5.0 and te < 0.6  # KITTI's success thresholds
    return ts, tt, re, ok, float(corr.labels[s.indices].mean()), peak_rss_mb(), res


def bench_scores(args) -> None:
    """Issue 29's targets: exact against estimated scores side by side, then 50,000 to 1,000,000."""
    from fastmac_exp.datasets.user_pairs import SharedRealPairs
    from fastmac_exp.descriptors.fpfh import FPFHDescriptor

    reps = args.reps or 3
    print(
        "Estimated sampler scores (sampler.scores): FastMAC@20 exact vs auto (estimate where auto picks it)"
    )
    describe = FPFHDescriptor(max_correspondences=5000)
    groups: dict[str, list] = {"outdoor": [], "object": [], "indoor": []}
    if (DATA / "pairs.json").exists():
        ds = SharedRealPairs(root=str(DATA))
        for i, name in enumerate(ds.names()):
            pair = ds.load(i)
            corr = pair.label(describe(pair, np.random.default_rng(0)))
            groups[pair.scene].append((name, corr, pair.family, pair.sampler_resolution))
    else:
        print(f"  no shared data at {DATA}: the real pairs are skipped")
    dense = ("kitti00_95_to_94", "kitti00_199_to_198", "lidar_smallgicp_source_to_target")
    for scene, title in (("outdoor", "Real outdoor pairs, 5,000 FPFH correspondences"),
                         ("object", "Object pairs (bunny, dragon), 5,000 FPFH correspondences"),
                         ("indoor", "Real indoor pairs, 5,000 FPFH correspondences")):  # fmt: skip
        if not groups[scene]:
            continue
        cols = scores_pairs_table(groups[scene], reps, title)
        names = [p[0] for p in groups[scene]]
        if scene == "outdoor":
            d = [i for i, nm in enumerate(names) if nm in dense]
            for i in d:
                print(f"  target {names[i]}: F@20 {cols['f20_est'][i]:.1f} ms (< 30), sampler "
                      f"{cols['samp_est'][i]:.1f} ms (< 10), MAC@100 / F@20 "
                      f"{cols['mac'][i] / cols['f20_est'][i]:.1f}x "
                      f"(>= 5), KISS / F@20 {cols['kiss'][i] / cols['f20_est'][i]:.1f}x (>= 3)")  # fmt: skip
            print(
                f"  target median of the {len(names)} real outdoor pairs: F@20 "
                f"{statistics.median(cols['f20_est']):.1f} ms (< 20); exact "
                f"{statistics.median(cols['f20_ex']):.1f}"
            )
        if scene == "object":
            for i, nm in enumerate(names):
                print(f"  target {nm}: F@20 {cols['f20_est'][i]:.1f} ms <= MAC@100 {cols['mac'][i]:.1f} ms")
        if scene == "indoor":
            print(
                f"  target indoor: MAC@100 median {statistics.median(cols['mac']):.1f} ms, F@20 "
                f"{statistics.median(cols['f20_est']):.1f} ms (both < 30)"
            )

    print("\n50,000 outdoor-like correspondences (bench_core's scene), end to end, one run each")
    for inl in (0.02, 0.05, 0.1):
        for label, ratio, samples, scores in (("ratio 0.05 auto", 0.05, None, "auto"),
                                              ("samples=2500 auto", 0.05, 2500, "auto"),
                                              ("ratio 0.05 exact", 0.05, None, "exact")):  # fmt: skip
            ts, tt, re, ok, kin, rss, res = large_case(50_000, inl, ratio, samples, scores)
            print(f"  {100 * inl:4.1f} % inliers, {label:18s}: sampling {ts:7.0f} + MAC "
                f"{tt - ts:6.0f} = {tt:7.0f} ms "
                  f"(target < 500), kept inliers {kin:.3f}, RE {re:.2f} deg, {'ok' if ok else 'FAILED'}, "
                  f"peak RSS {rss:.0f} MB{'; cap ' + res.cap_hit if res.cap_hit else ''}")  # fmt: skip
            sys.stdout.flush()

    print("\nGrowth: the estimated sampler, and end to end with samples=5000 and samples=1000, 5 % inliers")
    sizes = [s for s in (10_000, 20_000, 50_000, 100_000, 200_000, 500_000, 1_000_000) if s <= args.max_n]
    t_s, t_t, t_1 = [], [], []
    for n in sizes:
        ts, tt, re, ok, kin, rss, res = large_case(n, 0.05, 0.05, 5000, "estimate")
        ts1, tt1, re1, ok1, kin1, _, res1 = large_case(n, 0.05, 0.05, 1000, "estimate")
        t_s.append(ts)
        t_t.append(tt)
        t_1.append(tt1)
        print(
            f"  N {n:9,d}: sampling {ts:7.0f} ms; samples=5000: end to end {tt:7.0f} ms, "
            f"kept inliers {kin:.3f}, "
            f"{'ok' if ok else 'FAILED'}{' (cap ' + res.cap_hit + ')' if res.cap_hit else ''}; samples=1000: "
            f"{tt1:6.0f} ms, kept inliers {kin1:.3f}, {'ok' if ok1 else 'FAILED'}; peak RSS {rss:.0f} MB"
        )
        sys.stdout.flush()
    if len(sizes) >= 2:
        fit = {k: np.polyfit(np.log(sizes), np.log(v), 1)[0] for k, v in (("s", t_s), ("t", t_t), ("1", t_1))}
        print(
            f"  fitted growth exponent: sampler {fit['s']:.2f}, end to end {fit['t']:.2f} (samples=5000) and "
            f"{fit['1']:.2f} (samples=1000); goal <= 1.3"
        )
    for n, target in ((200_000, 2000), (1_000_000, 10_000)):
        if n > args.max_n:
            continue
        for inl in (0.02, 0.1):
            ts, tt, re, ok, kin, rss, res = large_case(n, inl, 0.05, 5000, "auto")
            print(f"  target N {n:,d} at {100 * inl:.0f} % inliers, samples=5000: {tt:.0f} ms (< {target}), "
                  f"peak RSS {rss:.0f} MB (< 4096), {'registered' if ok else 'FAILED'} (RE {re:.2f} deg)"
                  + (f"; cap {res.cap_hit}" if res.cap_hit else ""))  # fmt: skip
            sys.stdout.flush()


if __name__ == "__main__":
    sys.exit(main())
