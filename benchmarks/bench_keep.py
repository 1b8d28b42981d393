"""FastMAC on large inputs by the size of its keep (issue 41), stage by stage: bench_core's --keep-only.

    python benchmarks/bench_core.py --keep-only [--cases lidar kitti95 p200k2 ...] [--configs r0.2 auto ...]
                                                [--timeout 120] [--old /path/_mac_core.so] [--kiss]

Inputs: every FPFH keypoint of the real LiDAR pair (voxel 0.05 m, ~28,500 one-way matches) and of KITTI
00 95->94 (voxel 0.075 m, ~68,000), described once and cached in .cache/bench_keep/; bench_core's planted
outdoor-like scene (60 x 60 x 4 m, noise 0.1 m) at 200,000 and 1,000,000 correspondences with 2 % and
10 % inliers. Configurations: ratio 0.2, ratio 0.05, samples=2500, samples=auto, and a random keep of
auto's size (the "random keep + MAC" peer); --kiss adds KISS-Matcher on all N (tens of seconds on the real
ones); --unbounded adds each run without MAC's product-work bound (the exact products at any keep size,
as before issue 41). Each run is a fresh process (a warm-up call first, then the timed one), killed past
--timeout; with
--old, every run is made with the old core and this one alternately (FASTMAC_CORE_SO), so both see the
same load. Prints the CPU model and the load average before and after each input.
"""

from __future__ import annotations

import json
import os
import subprocess
import sys
import time
from pathlib import Path

import numpy as np

REPO = Path(__file__).resolve().parents[1]
if str(REPO) not in sys.path:
    sys.path.insert(0, str(REPO))

from benchmarks.machine import cpu_model, load  # noqa: E402

DATA = REPO.parent / "shared" / "data"
CACHE = REPO / ".cache" / "bench_keep"
REAL = {"lidar": ("lidar_smallgicp_source_to_target", 0.05), "kitti95": ("kitti00_95_to_94", 0.075)}
PLANTED = {"p200k2": (200_000, 0.02), "p200k10": (200_000, 0.10), "p1m2": (1_000_000, 0.02),
           "p1m10": (1_000_000, 0.10)}  # fmt: skip
CONFIGS = {"r0.2": (0.2, None), "r0.05": (0.05, None), "k2500": (0.2, 2500), "auto": (0.2, "auto")}
STAGES = ("sampling", "graph", "cliques", "selection", "pose")


def real_input(case: str) -> Path | None:
    """The cached npz (src, tgt, labels, gt, family, resolution) of a real input, described if missing."""
    name, voxel = REAL[case]
    path = CACHE / f"{name}_v{voxel}.npz"
    if path.exists():
        return path
    if not (DATA / "pairs.json").exists():
        return None
    from fastmac_exp.datasets.user_pairs import SharedRealPairs
    from fastmac_exp.descriptors.fpfh import FPFHDescriptor

    ds = SharedRealPairs(root=str(DATA))
    pair = ds.load(ds.names().index(name))
    corr = pair.label(FPFHDescriptor(voxel_size=voxel, max_correspondences=0)(pair, np.random.default_rng(0)))
    CACHE.mkdir(parents=True, exist_ok=True)
    np.savez(path, src=corr.src, tgt=corr.tgt, labels=corr.labels, gt=pair.gt, family=pair.family,
             resolution=pair.resolution, sampler_resolution=pair.sampler_resolution,
             re=pair.re_thresh_deg, te=pair.te_thresh_m)  # fmt: skip
    return path


def load_case(case: str):
    """(correspondences, gt, MAC params, sampler graph, family, RE / TE thresholds)."""
    from fastmac_exp.datasets.planted import planted
    from fastmac_exp.params import mac_params_for
    from fastmac_exp.types import Correspondences

    if case in PLANTED:
        n, inl = PLANTED[case]
        corr, gt = planted(n, inlier_ratio=inl, noise=0.1, seed=1, room=(60.0, 60.0, 4.0))
        params = mac_params_for("kitti", "fpfh")
        return corr, gt, params, params.graph, "kitti", 5.0, 0.6
    z = np.load(real_input(case))
    fam = str(z["family"])
    corr = Correspondences(z["src"], z["tgt"], labels=z["labels"].astype(bool))
    params = mac_params_for(fam, "fpfh", float(z["resolution"]))
    sgraph = mac_params_for(fam, "fpfh", float(z["sampler_resolution"])).graph
    return corr, z["gt"], params, sgraph, fam, float(z["re"]), float(z["te"])


def run_case(case: str, config: str, samples_override: int | None, bound: bool = True) -> dict:
    """One timed run (after a warm-up with samples=auto on 10,000 of the same correspondences, which runs
    the estimated scores, the keep's rule and MAC), in this process; bound=False:
    MAC without its product-work bound (mac.max_product_work=0, the exact products at any size)."""
    from dataclasses import replace

    from fastmac_exp import core
    from fastmac_exp.backends.cpp import CppBackend
    from fastmac_exp.geometry.metrics import pose_errors
    from fastmac_exp.pipeline import register_correspondences
    from fastmac_exp.samplers import GraphFilterSampler, RandomSampler

    corr, gt, params, sgraph, fam, re_t, te_t = load_case(case)
    if not bound:
        params = replace(params, max_product_work=0)
    warm = corr.subset(np.arange(min(10_000, len(corr))))
    try:
        register_correspondences(warm, params, GraphFilterSampler(), CppBackend(), 0.2, fam,
                                 np.random.default_rng(0), sample_graph=sgraph, samples="auto")  # fmt: skip
    except Exception:  # noqa: BLE001 - the warm-up only loads code and pages
        pass
    if config == "kiss":
        from fastmac_exp.backends.peers import KissMatcherBackend

        t0 = time.perf_counter()
        res = KissMatcherBackend().register(corr, params)
        total = (time.perf_counter() - t0) * 1e3
        err = pose_errors(res.pose, gt, re_t, te_t)
        return {"total": total, "k": len(corr), "ok": bool(err.success), "re": err.re_deg}
    if config == "random":
        sampler, ratio, samples = RandomSampler(), 0.2, samples_override
    else:
        (ratio, samples), sampler = CONFIGS[config], GraphFilterSampler()
    Path("/proc/self/clear_refs").write_text("5") if Path("/proc/self/clear_refs").exists() else None
    t0 = time.perf_counter()
    rng = np.random.default_rng(1)
    res, s = register_correspondences(corr, params, sampler, CppBackend(), ratio, fam, rng,
                                      sample_graph=sgraph, samples=samples)  # fmt: skip
    total = (time.perf_counter() - t0) * 1e3
    err = pose_errors(res.pose, gt, re_t, te_t)
    rss = 0.0
    for line in Path("/proc/self/status").read_text().splitlines():
        if line.startswith("VmHWM:"):
            rss = int(line.split()[1]) / 1024.0
    out = {k: float(res.timings.get(k, 0.0)) for k in STAGES}
    out.update(total=total, k=len(s.indices), kept_inl=float(corr.labels[s.indices].mean()),
               ok=bool(err.success), re=float(err.re_deg), cap=res.cap_hit or "", rss=rss, core=s.core,
               scores=s.scores_used, bf16=bool(core.core().bf16_cores()))  # fmt: skip
    return out


def child(case: str, config: str, timeout: float, so: str | None, samples: int | None = None,
          bound: bool = True) -> dict:  # fmt: skip
    env = dict(os.environ)
    if so:
        env["FASTMAC_CORE_SO"] = so
    cmd = [sys.executable, str(Path(__file__).resolve()), "--child", case, config, str(samples or 0),
           str(int(bound))]  # fmt: skip
    try:
        p = subprocess.run(cmd, capture_output=True, text=True, timeout=timeout, env=env, cwd=REPO)
    except subprocess.TimeoutExpired:
        return {"error": f"> {timeout:.0f} s"}
    lines = [ln for ln in p.stdout.splitlines() if ln.startswith("{")]
    if p.returncode != 0 or not lines:
        return {"error": (p.stderr.strip().splitlines() or ["failed"])[-1][:120]}
    return json.loads(lines[-1])


def cell(r: dict) -> str:
    if "error" in r:
        return f"{r['error']}"
    stages = " + ".join(f"{r.get(k, 0):.0f}" for k in STAGES if k in r)
    extra = f" core {r['core']}" if r.get("core") else ""
    return (f"{r['total']:8.0f} ms  k {r['k']:7d}  ({stages})  kept inl {r.get('kept_inl', float('nan')):.2f}"
            f"  {'ok' if r['ok'] else 'FAILED'} RE {r['re']:.2f}  RSS {r.get('rss', 0):.0f} MB"
            f"{extra}{'  cap ' + r['cap'] if r.get('cap') else ''}")  # fmt: skip


def main(argv: list[str] | None = None) -> int:
    import argparse

    argv = sys.argv[1:] if argv is None else argv
    if argv[:1] == ["--child"]:
        case, config, samples, bound = argv[1], argv[2], int(argv[3]), bool(int(argv[4]))
        print(json.dumps(run_case(case, config, samples or None, bound)))
        return 0
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--cases", nargs="*", default=list(REAL) + list(PLANTED))
    ap.add_argument("--configs", nargs="*", default=list(CONFIGS) + ["random"])
    ap.add_argument("--timeout", type=float, default=120.0, help="seconds a run may take before it is killed")
    ap.add_argument(
        "--old", default=None, help="an older core's _mac_core*.so, run alternately with this one"
    )
    ap.add_argument("--kiss", action="store_true", help="also KISS-Matcher on every correspondence")
    ap.add_argument(
        "--unbounded",
        action="store_true",
        help="also each run without MAC's product-work bound (mac.max_product_work=0), alternately",
    )
    args = ap.parse_args(argv)
    print(f"FastMAC by keep size (issue 41); CPU: {cpu_model()}, {os.cpu_count()} logical CPUs; stages ms: "
          f"{' + '.join(STAGES)}")  # fmt: skip
    builds = [("new", None, True)] + ([("old", args.old, True)] if args.old else [])
    builds += [("unbounded", None, False)] if args.unbounded else []
    for case in args.cases:
        if case in REAL and real_input(case) is None:
            print(f"{case}: no shared data at {DATA}; skipped")
            continue
        corr = load_case(case)[0]
        print(f"\n{case}: N {len(corr):,d}, {100 * corr.labels.mean():.1f} % inliers; load average {load()}")
        auto_k: dict[str, int] = {}
        for config in args.configs + (["kiss"] if args.kiss else []):
            for tag, so, bound in builds[::-1]:  # old (or unbounded) first, then new
                if config == "random" and tag not in auto_k:
                    r = {"error": "no auto run to size it"}
                else:
                    r = child(case, config, args.timeout, so, auto_k.get(tag) if config == "random" else None,
                              bound)  # fmt: skip
                if config == "auto" and "k" in r:
                    auto_k[tag] = r["k"]
                label = f"{config}{' (' + tag + ')' if len(builds) > 1 else ''}"
                print(f"  {label:14s} {cell(r)}")
                sys.stdout.flush()
        print(f"  load average after {case}: {load()}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
