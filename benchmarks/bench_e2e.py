"""Raw clouds to a pose, side by side in one run, on every real pair of ../shared/data (issue 40).

    python benchmarks/bench_e2e.py [--reps 3] [--ids ID ...] [--no-kiss] [--no-ransac] [--no-open3d]
                                   [--no-startup] [--no-inliers] [--learned buffer fcgf fcgf_lite spinnet]
                                   [--threads 0] [--json out.json]

Methods, each from the two raw clouds (as loaded: no voxel grid applied before the clock starts):
- project (core FPFH): what `fastmac_exp.register` and `run.py` do with the default front end: MAC's
  mesh resolution from the clouds where the family uses it, FPFH in the C++ core (keypoints, normals,
  features of the 5,000 source keypoints the cap keeps and of every target keypoint, exact matching),
  then FastMAC@20 + MAC (C++ backend). Stages: resolution, describe, registration (sampling + MAC).
- project (Open3D FPFH): the same with descriptor.impl=open3d (Open3D's FPFH for every keypoint).
- KISS-Matcher: its whole pipeline, KISSMatcher(KISSMatcherConfig(voxel)).estimate(src, tgt) (its own
  voxel grid, features, matching and solver); the clouds' conversion to its input lists is not timed.
- project (buffer / fcgf / fcgf_lite / spinnet), with --learned: the project with a learned front end
  (its config's defaults) in place of FPFH. fcgf takes $FCGF_CHECKPOINT; without it, random weights in the
  published checkpoints' shapes (3DMatch: conv1 7 at 2.5 cm; KITTI: conv1 5 at 30 cm): the describe cost
  holds, the poses are meaningless.
- Open3D FPFH + RANSAC: Open3D's voxel grid, normals and FPFH (the project's parameters), then
  registration_ransac_based_on_feature_matching with 100,000 iterations (confidence 0.999).

Each pair's methods run interleaved, `--reps` rounds after one warm-up round; the table gives medians
(ms, wall clock) and the pose errors of the last round with the pair's success thresholds. Then the
ratios to KISS-Matcher, the inlier ratio of the core's correspondences against Open3D's (every source
keypoint, one-way nearest neighbour, no cap: the same keypoints, so the same count), and the first call a
one-shot user pays: `import fastmac_exp` and `run.py` on one KITTI pair in a fresh process.
Prints the CPU model and the load average; an absolute time is a claim about that machine.
"""

from __future__ import annotations

import argparse
import json
import os
import statistics
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

REPO = Path(__file__).resolve().parents[1]
if str(REPO) not in sys.path:
    sys.path.insert(0, str(REPO))

from benchmarks.machine import cpu_model, load  # noqa: E402
from fastmac_exp import core  # noqa: E402
from fastmac_exp.backends.peers import kiss_matcher_pose  # noqa: E402
from fastmac_exp.descriptors.fpfh import FPFHDescriptor, fpfh_features, match_features  # noqa: E402
from fastmac_exp.errors import FastMacError  # noqa: E402
from fastmac_exp.geometry.metrics import pose_errors  # noqa: E402
from fastmac_exp.geometry.offset import describe_moved  # noqa: E402
from fastmac_exp.geometry.resolution import COMPUTED_FAMILIES, resolution_for  # noqa: E402
from fastmac_exp.params import mac_params_for  # noqa: E402
from fastmac_exp.pipeline import register_correspondences  # noqa: E402
from fastmac_exp.types import Pair  # noqa: E402

DATA = REPO.parent / "shared" / "data"
RATIO = 0.2
METHODS = ("project", "project_open3d", "kiss_matcher", "open3d_ransac")
LABELS = {
    "project": "project (core FPFH)",
    "project_open3d": "project (Open3D FPFH)",
    "kiss_matcher": "KISS-Matcher",
    "open3d_ransac": "Open3D FPFH+RANSAC",
}


# ---------------------------------------------------------------------------------------------------
# the methods: each returns (pose, {stage: ms})


def learned_descriptor(spec: str):
    """A learned front end by its config name, with the config's defaults (conf/descriptor/NAME.yaml)
    and any `NAME:key=value,key=value` overrides (`buffer:threads=2`); fcgf without FCGF_CHECKPOINT:
    random checkpoint-shaped models (`RandomFcgf`)."""
    import yaml
    from hydra.utils import instantiate
    from omegaconf import OmegaConf

    name, _, overrides = spec.partition(":")
    if name == "fcgf" and not os.environ.get("FCGF_CHECKPOINT"):
        if overrides:
            raise SystemExit("fcgf with random weights takes no overrides")
        return RandomFcgf()
    node = OmegaConf.load(REPO / "conf" / "descriptor" / f"{name}.yaml")
    for item in filter(None, overrides.split(",")):
        key, eq, value = item.partition("=")
        if not eq or key not in node:
            raise SystemExit(f"--learned {spec}: {item!r} is not key=value with a key of {name}.yaml")
        node[key] = yaml.safe_load(value) if value else None  # typed as YAML would type it
    if "cache_clouds" in node:  # BUFFER, SpinNet: each round describes again (else the rounds time a cache)
        node.cache_clouds = 0
    return instantiate(node)


# the published checkpoints' shapes (FCGF's model zoo): 3DMatch conv1 7 at 2.5 cm, KITTI conv1 5 at 30 cm
FCGF_SHAPES = {"3dmatch": (7, 32, True, 0.025), "kitti": (5, 32, True, 0.3)}


class RandomFcgf:
    """descriptor=fcgf with random weights in the published checkpoints' shapes, one per family, written
    as FCGF-format checkpoints (and converted) in a temporary data home: the describe cost of the real
    network without its weights (the correspondences, and so the poses, are meaningless)."""

    name, graph_key = "fcgf", "fcgf"

    def __init__(self, seed: int = 0) -> None:
        import torch

        from fastmac_exp.descriptors.fcgf import FcgfDescriptor
        from fastmac_exp.descriptors.fcgf_checkpoint import file_ids
        from fastmac_exp.descriptors.fcgf_plan import NetConfig, expected_shapes

        self._home = tempfile.TemporaryDirectory(prefix="fcgf_random_")
        old = os.environ.get("FASTMAC_DATA")
        os.environ["FASTMAC_DATA"] = self._home.name
        g = torch.Generator().manual_seed(seed)
        self.by_family = {}
        try:
            for family, (k1, out, norm, voxel) in FCGF_SHAPES.items():
                cfg = NetConfig(1, k1, out, norm)
                state = {}
                for key, shape in expected_shapes(cfg).items():
                    if key.endswith("num_batches_tracked"):
                        state[key] = torch.tensor(0)
                    elif key.endswith(("running_var", "bn.weight")):
                        state[key] = 0.5 + torch.rand(shape, generator=g)
                    else:
                        state[key] = torch.randn(shape, generator=g) * 0.1
                config = {"model": "ResUNetBN2C", "voxel_size": voxel, "conv1_kernel_size": k1,
                          "model_n_out": out, "normalize_feature": norm}  # fmt: skip
                path = Path(self._home.name) / f"random_{family}.pth"
                torch.save({"state_dict": state, "config": config}, path)
                self.by_family[family] = FcgfDescriptor(str(path), sha256=file_ids(path).sha256)
        finally:
            if old is None:
                os.environ.pop("FASTMAC_DATA", None)
            else:
                os.environ["FASTMAC_DATA"] = old

    def __call__(self, pair: Pair, rng):
        return self.by_family["kitti" if pair.family == "kitti" else "3dmatch"](pair, rng)


def project_once(
    pair: Pair, impl: str, seed: int = 0, descriptor=None
) -> tuple[np.ndarray, dict[str, float]]:
    from fastmac_exp.backends.cpp import CppBackend
    from fastmac_exp.samplers import make_sampler

    rng = np.random.default_rng(seed)
    t0 = time.perf_counter()
    resolution = pair.resolution
    if pair.meta.get("category") != "object" and pair.family in COMPUTED_FAMILIES:  # computed, as at load
        resolution = resolution_for(pair.family, pair.src_cloud, pair.tgt_cloud)
    t1 = time.perf_counter()
    desc = FPFHDescriptor(impl=impl) if descriptor is None else descriptor
    corr = describe_moved(desc, pair, rng)
    t2 = time.perf_counter()
    overrides = {"inlier_threshold": pair.inlier_threshold}
    params = mac_params_for(pair.family, desc.graph_key, resolution, mac_overrides=overrides)
    sample_graph = mac_params_for(pair.family, desc.graph_key, pair.sampler_resolution).graph
    sampler, backend = make_sampler("highpass"), CppBackend()
    result, _ = register_correspondences(
        corr, params, sampler, backend, RATIO, pair.family, rng, sample_graph=sample_graph
    )
    t3 = time.perf_counter()
    ms = {"resolution": (t1 - t0) * 1e3, "describe": (t2 - t1) * 1e3, "registration": (t3 - t2) * 1e3}
    ms["total"] = (t3 - t0) * 1e3
    return result.pose, ms


def kiss_once(pair: Pair, inputs) -> tuple[np.ndarray, dict[str, float]]:
    import kiss_matcher

    src, tgt = inputs
    t0 = time.perf_counter()
    matcher = kiss_matcher.KISSMatcher(kiss_matcher.KISSMatcherConfig(pair.voxel_size))
    sol = matcher.estimate(src, tgt)
    ms = (time.perf_counter() - t0) * 1e3
    pose = kiss_matcher_pose(sol)
    return (np.full((4, 4), np.nan) if pose is None else pose), {"total": ms}


def ransac_once(pair: Pair, seed: int = 0) -> tuple[np.ndarray, dict[str, float]]:
    from fastmac_exp._open3d import o3d

    reg = o3d.pipelines.registration
    t0 = time.perf_counter()
    clouds = []
    for pts in (pair.src_cloud, pair.tgt_cloud):
        pcd = o3d.geometry.PointCloud(o3d.utility.Vector3dVector(pts)).voxel_down_sample(pair.voxel_size)
        pcd.estimate_normals(o3d.geometry.KDTreeSearchParamHybrid(radius=2 * pair.voxel_size, max_nn=30))
        pcd.orient_normals_towards_camera_location(np.zeros(3))
        search = o3d.geometry.KDTreeSearchParamHybrid(radius=5 * pair.voxel_size, max_nn=100)
        f = reg.compute_fpfh_feature(pcd, search)
        clouds.append((pcd, f))
    t1 = time.perf_counter()
    o3d.utility.random.seed(seed)
    out = reg.registration_ransac_based_on_feature_matching(
        clouds[0][0], clouds[1][0], clouds[0][1], clouds[1][1], False, pair.inlier_threshold,
        reg.TransformationEstimationPointToPoint(False), 3,
        [reg.CorrespondenceCheckerBasedOnEdgeLength(0.9),
         reg.CorrespondenceCheckerBasedOnDistance(pair.inlier_threshold)],
        reg.RANSACConvergenceCriteria(100_000, 0.999),
    )  # fmt: skip
    t2 = time.perf_counter()
    ms = {"describe": (t1 - t0) * 1e3, "registration": (t2 - t1) * 1e3, "total": (t2 - t0) * 1e3}
    return np.asarray(out.transformation).copy(), ms


# ---------------------------------------------------------------------------------------------------


def run_pair(pair: Pair, methods: list[str], reps: int, learned: dict | None = None) -> dict[str, dict]:
    kiss_inputs = None
    if "kiss_matcher" in methods:
        kiss_inputs = (
            [p.astype(np.float32).reshape(3, 1) for p in pair.src_cloud],
            [q.astype(np.float32).reshape(3, 1) for q in pair.tgt_cloud],
        )
    calls = {
        "project": lambda: project_once(pair, "core"),
        "project_open3d": lambda: project_once(pair, "open3d"),
        "kiss_matcher": lambda: kiss_once(pair, kiss_inputs),
        "open3d_ransac": lambda: ransac_once(pair),
    }
    for name, desc in (learned or {}).items():
        calls[name] = lambda desc=desc: project_once(pair, "core", descriptor=desc)
    runs: dict[str, list[dict[str, float]]] = {m: [] for m in methods}
    poses: dict[str, np.ndarray] = {}
    for r in range(reps + 1):  # round 0 warms up
        for m in methods:
            try:
                pose, ms = calls[m]()
            except (FastMacError, RuntimeError) as exc:  # a peer may refuse a pair (KISS-Matcher: voxel)
                pose, ms = np.full((4, 4), np.nan), {"total": float("nan")}
                if r:
                    print(f"  {pair.name}: {LABELS[m]} failed: {exc}")
            if r:
                runs[m].append(ms)
                poses[m] = pose
    out = {}
    for m in methods:
        stages = sorted({k for run in runs[m] for k in run})
        med = {k: statistics.median(run.get(k, float("nan")) for run in runs[m]) for k in stages}
        pose = poses[m]
        if pair.gt is not None and np.isfinite(pose).all():
            err = pose_errors(pose, pair.gt, pair.re_thresh_deg, pair.te_thresh_m)
            re, te, ok = err.re_deg, err.te_cm, err.success
        else:
            re, te, ok = float("nan"), float("nan"), False
        out[m] = {"ms": med, "re_deg": re, "te_cm": te, "success": ok}
    return out


def inlier_ratios(pair: Pair) -> tuple[float, float, int]:
    """Inlier ratio of every source keypoint's one-way match, core vs Open3D FPFH (the same keypoints)."""
    ratios = []
    for impl in ("core", "open3d"):
        ks, fs = fpfh_features(pair.src_cloud, pair.voxel_size, impl=impl)
        kt, ft = fpfh_features(pair.tgt_cloud, pair.voxel_size, impl=impl)
        si, ti, _ = match_features(fs, ft)
        err = np.linalg.norm(ks[si] @ pair.gt[:3, :3].T + pair.gt[:3, 3] - kt[ti], axis=1)
        ratios.append(float((err < pair.inlier_threshold).mean()))
    return ratios[0], ratios[1], len(ks)


def startup(kitti: Pair | None) -> dict[str, float]:
    py = sys.executable
    best = min(_wall([py, "-c", "import fastmac_exp"]) for _ in range(3))
    out = {"import_s": best}
    if kitti is not None:
        src, tgt = kitti.meta.get("source_file"), kitti.meta.get("target_file")
        with tempfile.TemporaryDirectory() as tmp:
            runs = []
            for k in range(2):  # a fresh run directory each time, and no correspondence cache: describe runs
                runs.append(_wall([py, str(REPO / "run.py"), "dataset=pairs", f"dataset.source={src}",
                                   f"dataset.target={tgt}", "dataset.family=kitti", "tracker=none",
                                   "progress=false", "cache.correspondences=false",
                                   f"hydra.run.dir={tmp}/run{k}"]))  # fmt: skip
            out["cli_kitti_pair_s"] = min(runs)
    return out


def _wall(cmd: list[str]) -> float:
    t0 = time.perf_counter()
    subprocess.run(cmd, check=True, capture_output=True, cwd=REPO)
    return time.perf_counter() - t0


def fmt(x: float) -> str:
    return "-" if x is None or not np.isfinite(x) else (f"{x:,.0f}" if x >= 100 else f"{x:.1f}")


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--reps", type=int, default=3)
    ap.add_argument("--ids", nargs="+", default=None, help="only these pairs.json ids")
    ap.add_argument("--no-kiss", action="store_true")
    ap.add_argument("--no-ransac", action="store_true")
    ap.add_argument("--no-open3d", action="store_true", help="skip the project with Open3D's FPFH")
    ap.add_argument("--no-startup", action="store_true")
    ap.add_argument("--no-inliers", action="store_true")
    ap.add_argument(
        "--learned",
        nargs="*",
        default=[],
        metavar="NAME[:k=v,...]",
        help="also the project with these learned front ends (buffer, fcgf, fcgf_lite, spinnet), each with "
        "optional overrides of its config (buffer:threads=2,batch_size=32); a name may repeat",
    )
    ap.add_argument("--threads", type=int, default=0, help="the core's threads (OMP_NUM_THREADS; 0: all)")
    ap.add_argument("--json", type=Path, default=None)
    args = ap.parse_args(argv)
    if not (DATA / "pairs.json").is_file():
        print(f"no real pairs: {DATA / 'pairs.json'} not found (shared data beside the repository)")
        return 0
    if not core.available():
        print("the C++ core is not built: pip install -e .")
        return 1
    if args.threads:
        os.environ["OMP_NUM_THREADS"] = str(args.threads)
    from fastmac_exp.datasets.user_pairs import SharedRealPairs

    methods = [m for m in METHODS if not (
        (m == "kiss_matcher" and args.no_kiss) or (m == "open3d_ransac" and args.no_ransac)
        or (m == "project_open3d" and args.no_open3d))]  # fmt: skip
    if "kiss_matcher" in methods:
        try:
            import kiss_matcher  # noqa: F401
        except ImportError:
            print("kiss-matcher is not installed (pip install kiss-matcher): its column is skipped")
            methods.remove("kiss_matcher")
    learned = {f"project_{spec}": learned_descriptor(spec) for spec in args.learned}
    for key in learned:
        LABELS[key] = f"project ({key[8:]})"
    methods += list(learned)
    ds = SharedRealPairs(root=DATA, ids=args.ids)
    print(f"bench_e2e: {cpu_model()}, {os.cpu_count()} cores, core threads {core.core().default_threads()}, "
          f"load {load()}, reps {args.reps} (+1 warm-up), FastMAC@{RATIO:g}")  # fmt: skip
    head = f"{'pair':34s} {'pts src/tgt':>15s} {'method':22s} {'resol.':>7s} {'describe':>9s} "
    head += f"{'regist.':>8s} {'total ms':>9s} {'RE deg':>7s} {'TE cm':>7s} ok"
    print(head)
    results = {}
    kitti = None
    for i in range(len(ds)):
        pair = ds.load(i)
        if kitti is None and pair.name.startswith("kitti"):
            kitti = pair
        res = run_pair(pair, methods, args.reps, learned)
        points = [len(pair.src_cloud), len(pair.tgt_cloud)]
        results[pair.name] = {"points": points, "family": pair.family, **res}
        for m in methods:
            r = res[m]
            ms = r["ms"]
            cells = [fmt(ms.get(k)) for k in ("resolution", "describe", "registration", "total")]
            err = f"{fmt(r['re_deg']):>7s} {fmt(r['te_cm']):>7s} {'yes' if r['success'] else 'NO'}"
            print(f"{pair.name[:34]:34s} {points[0]:>7,}/{points[1]:<7,} {LABELS[m]:22s} {cells[0]:>7s} "
                  f"{cells[1]:>9s} {cells[2]:>8s} {cells[3]:>9s} {err}")  # fmt: skip
        sys.stdout.flush()
    if "kiss_matcher" in methods:
        print("\nKISS-Matcher / project (core FPFH), end to end:")
        for name, r in results.items():
            p, k = r["project"]["ms"]["total"], r["kiss_matcher"]["ms"]["total"]
            if not np.isfinite(k):
                print(f"  {name:34s}   -     (KISS-Matcher gave no pose)")
                continue
            print(
                f"  {name:34s} {k / p:5.2f}x   (registered: project {r['project']['success']}, "
                f"KISS-Matcher {r['kiss_matcher']['success']})"
            )
    if not args.no_inliers:
        print("\nInlier ratio of every source keypoint's one-way match, core vs Open3D FPFH:")
        for i in range(len(ds)):
            pair = ds.load(i)
            c, o, n = inlier_ratios(pair)
            rel = (c - o) / o * 100 if o > 0 else float("nan")
            results[pair.name]["inlier_ratio"] = {"core": c, "open3d": o, "keypoints": n}
            print(f"  {pair.name:34s} keypoints {n:>6,}  core {c:.4f}  open3d {o:.4f}  ({rel:+.2f} %)")
    if not args.no_startup:
        st = startup(kitti)
        results["startup"] = st
        print(f"\nfirst call: import fastmac_exp {st['import_s']:.2f} s (best of 3)"
              + (f"; run.py on one KITTI pair {st['cli_kitti_pair_s']:.2f} s wall, process start included"
                 if "cli_kitti_pair_s" in st else ""))  # fmt: skip
    print(f"\nload at the end {load()}")
    if args.json:
        args.json.write_text(json.dumps({"cpu": cpu_model(), "results": results}, indent=1, default=float))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
