"""Evaluate the descriptors on the same keypoints (FPFH, fcgf_lite, BUFFER), then MAC and FastMAC on each.

    cd /work/main && python descriptors/evaluate.py --real \\
        --json descriptors/evaluation_real.json          # every pair of ../shared/data (buffer/MODEL_CARD.md)
    python descriptors/evaluate.py --synthetic-pairs 20 --lomatch-pairs 20 \\
        --descriptors fcgf_lite fpfh --json descriptors/fcgf_lite/evaluation.json   # fcgf_lite/MODEL_CARD.md
    python descriptors/evaluate.py --synthetic-pairs 10 --kitti-pairs 10 --descriptors buffer \\
        --thresholds 0.85 0.95 0.99 0.999                  # graph-threshold check on held-out synthetic pairs
    python descriptors/evaluate.py --speed    # BUFFER seconds per fragment, 1 and 2 threads

Real pairs: every entry of <repo>/../shared/data/pairs.json, loaded by `SharedRealPairs` with its rules
(indoor: 3DMatch/3DLoMatch family, voxel 0.05 m, inlier 0.1 m, RE 15 deg / TE 0.3 m; outdoor: KITTI,
voxel 0.3 m, inlier 0.6 m, 5 deg / 0.6 m; objects: 3DMatch rules scaled to a 15 cm object); skipped when
absent. Synthetic pairs: SyntheticDataset families 3dmatch, 3dlomatch, kitti, seed 0 (never used to
train fcgf_lite, which trained on seed 1000 and validated on 2000).

Per pair and descriptor: the keypoints are the clouds voxel-downsampled at the pair's voxel (all three
descriptors describe the same keypoints), one-way nearest neighbour, at most 5000 correspondences drawn
with the same rng (so the same source keypoints); inlier ratio (IR: error under GT below the pair's inlier
threshold); feature-match recall (FMR: pairs with IR > 5 %); registration by MAC (no sampler), FastMAC@20
and FastMAC@5 (high-pass graph-signal sampling keeping 20 % / 5 %) on the C++ backend with the graph
parameters params.mac_params_for(family, descriptor graph key, pair resolution), judged by the pair's RE/TE
thresholds (the final pose, honest protocol). Correspondences are cached in .cache/descriptor_eval (keyed by
the pair, the descriptor's settings, its model files and the seed), so a rerun only registers.
"""

from __future__ import annotations

import argparse
import hashlib
import json
import sys
import time
from pathlib import Path

import numpy as np

REPO = Path(__file__).resolve().parent.parent
if str(REPO) not in sys.path:
    sys.path.insert(0, str(REPO))

from fastmac_exp import __version__  # noqa: E402
from fastmac_exp.errors import FastMacError  # noqa: E402
from fastmac_exp.geometry.metrics import pose_errors  # noqa: E402
from fastmac_exp.params import mac_params_for  # noqa: E402
from fastmac_exp.types import Correspondences, Pair  # noqa: E402

EVAL_SEED = 0
SHARED = REPO.parent / "shared" / "data"
CACHE = REPO / ".cache" / "descriptor_eval"
METHODS = {"mac": ("none", 1.0), "fastmac20": ("highpass", 0.2), "fastmac5": ("highpass", 0.05)}
DESCRIPTORS = ("fpfh", "fcgf_lite", "buffer", "spinnet")


def make_descriptors(names, threads: int, fcgf_model: str) -> dict:
    from fastmac_exp.descriptors.buffer import BufferDescriptor
    from fastmac_exp.descriptors.fpfh import FPFHDescriptor
    from fastmac_exp.descriptors.onnx_descriptor import OnnxDescriptor
    from fastmac_exp.descriptors.spinnet import SpinNetDescriptor

    make = {
        "fpfh": lambda: FPFHDescriptor(),
        "fcgf_lite": lambda: OnnxDescriptor(fcgf_model, threads=threads),
        "buffer": lambda: BufferDescriptor(threads=threads, progress=True),
        "spinnet": lambda: SpinNetDescriptor(threads=threads, progress=True),
    }
    return {n: make[n]() for n in names}


def _files(desc) -> list[Path]:
    """The model files a descriptor reads (their checksums key the cache)."""
    if hasattr(desc, "model_path") and isinstance(desc.model_path, Path):
        return [desc.model_path]
    if hasattr(desc, "_models"):
        out = []
        for fam in ("3dmatch", "kitti"):
            m = desc.load(fam)
            out += [m.desc_path] + ([m.ref_path] if m.ref_path else [])
        return out
    return []


def cache_key(pair: Pair, tag: str, name: str, desc, seed: int) -> str:
    settings = {k: v for k, v in vars(desc).items() if isinstance(v, str | int | float | bool | type(None))}
    files = {p.name: hashlib.sha256(p.read_bytes()).hexdigest()[:16] for p in _files(desc)}
    raw = json.dumps([tag, pair.name, name, settings, files, seed, __version__], sort_keys=True, default=str)
    return hashlib.sha1(raw.encode()).hexdigest()[:20]


def describe(
    pair: Pair, tag: str, name: str, desc, seed: int, use_cache: bool
) -> tuple[Correspondences, dict]:
    path = CACHE / f"{cache_key(pair, tag, name, desc, seed)}.npz"
    if use_cache and path.is_file():
        z = np.load(path, allow_pickle=False)
        info = json.loads(str(z["info"]))
        return Correspondences(z["src"], z["tgt"], labels=z["labels"], scores=z["scores"]), info
    n_log = len(getattr(desc, "timings_log", []))
    t0 = time.perf_counter()
    corr = desc(pair, np.random.default_rng(seed))
    info = {"describe_s": time.perf_counter() - t0}
    if hasattr(desc, "timings_log"):
        info["fragments"] = [
            {
                "keypoints": t["keypoints"],
                "seconds": round(t["total_s"], 2),
                "network_s": round(t["network_s"], 2),
            }
            for t in desc.timings_log[n_log:]
        ]
    if use_cache:
        CACHE.mkdir(parents=True, exist_ok=True)
        np.savez(
            path, src=corr.src, tgt=corr.tgt, labels=corr.labels, scores=corr.scores, info=json.dumps(info)
        )
    return corr, info


def register_all(
    corr: Correspondences, pair: Pair, graph_key: str, backend, seed: int, threshold=None
) -> dict:
    from fastmac_exp.pipeline import register_correspondences
    from fastmac_exp.samplers import make_sampler

    out = {}
    overrides = {"threshold": threshold} if threshold is not None else None
    params = mac_params_for(pair.family, graph_key, pair.resolution, graph_overrides=overrides)
    for method, (sampler, ratio) in METHODS.items():
        try:
            t0 = time.perf_counter()
            res, _ = register_correspondences(
                corr, params, make_sampler(sampler), backend, ratio, pair.family, np.random.default_rng(seed)
            )
            ms = (time.perf_counter() - t0) * 1e3
            pe = pose_errors(res.pose, pair.gt, pair.re_thresh_deg, pair.te_thresh_m)
            out[method] = {
                "ok": pe.success,
                "re": round(pe.re_deg, 3),
                "te_cm": round(pe.te_cm, 2),
                "ms": round(ms),
            }
        except FastMacError as exc:
            out[method] = {"ok": False, "re": float("nan"), "te_cm": float("nan"), "error": str(exc)[:200]}
    return out


def evaluate_pair(
    pair: Pair, tag: str, descriptors: dict, backend, seed: int, thresholds, use_cache: bool
) -> dict:
    row: dict = {"pair": pair.name, "family": pair.family, "voxel": pair.voxel_size, "descriptors": {}}
    for name, desc in descriptors.items():
        corr, info = describe(pair, tag, name, desc, seed, use_cache)
        d = {"n": len(corr), "ir": corr.inlier_ratio, "graph_key": desc.graph_key, **info}
        d.update(register_all(corr, pair, desc.graph_key, backend, seed))
        if thresholds:
            d["sweep"] = {
                str(t): register_all(corr, pair, desc.graph_key, backend, seed, t) for t in thresholds
            }
        row["descriptors"][name] = d
    return row


def summarize(rows: list[dict], names) -> dict:
    out = {}
    for k in names:
        ds = [r["descriptors"][k] for r in rows]
        ir = np.array([d["ir"] for d in ds])
        s = {
            "pairs": len(ds),
            "mean_ir": float(np.mean(ir)),
            "median_ir": float(np.median(ir)),
            "fmr": float(np.mean(ir > 0.05)),
            "median_describe_s": float(np.median([d["describe_s"] for d in ds])),
        }
        for m in METHODS:
            s[f"rr_{m}"] = int(sum(d[m]["ok"] for d in ds))
        if ds and "sweep" in ds[0]:
            s["sweep"] = {
                t: {m: int(sum(d["sweep"][t][m]["ok"] for d in ds)) for m in METHODS} for t in ds[0]["sweep"]
            }
        out[k] = s
    return out


def print_table(title: str, rows: list[dict], names) -> None:
    print(f"\n### {title}\n")
    head = " | ".join(f"{k} IR | {k} MAC / @20 / @5" for k in names)
    print(f"| pair | {head} |")
    print("|" + "---|" * (1 + 2 * len(names)))
    yes = {True: "ok", False: "--"}
    for r in rows:
        cells = []
        for k in names:
            d = r["descriptors"][k]
            cells += [f"{d['ir']:.3f}", " / ".join(yes[d[m]["ok"]] for m in METHODS)]
        print(f"| {r['pair']} | " + " | ".join(cells) + " |")
    s = summarize(rows, names)
    cols = ["descriptor", "pairs", "mean IR", "median IR", "FMR", "RR MAC", "RR FastMAC@20", "RR FastMAC@5"]
    print("\n| " + " | ".join([*cols, "describe s"]) + " |")
    print("|---|---|---|---|---|---|---|---|---|")
    for k in names:
        v = s[k]
        n = v["pairs"]
        print(
            f"| {k} | {n} | {v['mean_ir']:.4f} | {v['median_ir']:.4f} | {v['fmr']:.2f} | {v['rr_mac']}/{n} | "
            f"{v['rr_fastmac20']}/{n} | {v['rr_fastmac5']}/{n} | {v['median_describe_s']:.1f} |"
        )
        for t, rr in v.get("sweep", {}).items():
            rrs = " | ".join(f"{rr[m]}/{n}" for m in METHODS)
            print(f"|   graph threshold {t} | | | | | {rrs} | |")


def run(title: str, tag: str, pairs, names, descriptors, backend, args) -> dict:
    from tqdm import tqdm

    rows = []
    bar = tqdm(pairs, desc=title, unit="pair")
    for pair in bar:
        bar.set_postfix_str(pair.name)
        rows.append(
            evaluate_pair(pair, tag, descriptors, backend, args.seed, args.thresholds, not args.no_cache)
        )
        r = rows[-1]
        bar.write(
            f"  {r['pair']}: "
            + ", ".join(
                f"{k} IR {r['descriptors'][k]['ir']:.3f} "
                + "/".join("ok" if r["descriptors"][k][m]["ok"] else "--" for m in METHODS)
                for k in names
            )
        )
    print_table(title, rows, names)
    return {"rows": rows, "summary": summarize(rows, names)}


def synthetic_pairs(family: str, n: int, seed: int, cache_dir: str):
    from fastmac_exp.datasets.synthetic import SyntheticDataset

    ds = SyntheticDataset(family=family, num_pairs=n, seed=seed, cache_dir=cache_dir)
    return (ds.load(i) for i in range(len(ds)))


def real_pairs(root: Path, ids=None):
    from fastmac_exp.datasets.user_pairs import SharedRealPairs

    ds = SharedRealPairs(root=root, ids=ids)
    return [ds.load(i) for i in range(len(ds))]


def speed(root: Path, repeats: int = 2) -> dict:
    """BUFFER's seconds per fragment on a 3DMatch fragment and a KITTI scan, onnxruntime on 1 and 2 threads
    (best of `repeats`; a shared machine only ever makes it slower)."""
    from fastmac_exp.datasets.user_pairs import SharedRealPairs
    from fastmac_exp.descriptors.buffer import BufferDescriptor

    out = {}
    for pid, what in (
        ("3dm_redkitchen_4_to_0_teaser_fullres", "3DMatch fragment"),
        ("kitti00_95_to_94", "KITTI scan"),
    ):
        try:
            pair = SharedRealPairs(root=root, ids=[pid]).load(0)
        except FastMacError as exc:
            print(f"speed: {pid} unavailable ({exc})")
            continue
        for threads in (1, 2):
            d = BufferDescriptor(threads=threads, progress=False)
            best = None
            for _ in range(repeats):
                d.features(pair.tgt_cloud, pair.voxel_size, "target", family=pair.family, scale=1.0)
                t = d.last_timings
                best = t if best is None or t["total_s"] < best["total_s"] else best
            key = f"{what}, {threads} thread{'s' * (threads > 1)}"
            out[key] = {k: (round(v, 2) if isinstance(v, float) else v) for k, v in best.items()}
            print(f"{key}: {best['keypoints']} keypoints, {best['total_s']:.1f} s ({out[key]})", flush=True)
    return out


def main(argv: list[str] | None = None) -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--descriptors", nargs="+", default=list(DESCRIPTORS), choices=DESCRIPTORS)
    ap.add_argument("--real", action="store_true", help="every real pair of pairs.json")
    ap.add_argument("--real-ids", nargs="+", default=None, help="only these pairs.json ids")
    ap.add_argument("--real-root", default=str(SHARED))
    ap.add_argument("--synthetic-pairs", type=int, default=0, help="held-out synthetic 3dmatch pairs")
    ap.add_argument("--lomatch-pairs", type=int, default=0, help="held-out synthetic 3dlomatch pairs")
    ap.add_argument("--kitti-pairs", type=int, default=0, help="held-out synthetic kitti pairs")
    ap.add_argument(
        "--seed", type=int, default=EVAL_SEED, help="synthetic seed, correspondence cap, samplers"
    )
    ap.add_argument("--thresholds", type=float, nargs="*", default=None, help="also sweep graph.threshold")
    ap.add_argument("--fcgf-model", default="fastmac_exp/models/fcgf_lite.onnx")
    ap.add_argument("--threads", type=int, default=1, help="onnxruntime threads of the learned descriptors")
    ap.add_argument("--cache-dir", default=str(REPO / ".cache" / "synthetic"))
    ap.add_argument("--no-cache", action="store_true", help="recompute the correspondences")
    ap.add_argument("--backend", default="auto")
    ap.add_argument("--speed", action="store_true", help="time BUFFER per fragment (1 and 2 threads)")
    ap.add_argument("--json", default=None, help="write the rows and summaries here")
    args = ap.parse_args(argv)
    if args.speed:
        report = {"speed": speed(Path(args.real_root))}
        if args.json:
            Path(args.json).write_text(json.dumps(report, indent=1) + "\n")
        return
    if not (args.real or args.real_ids or args.synthetic_pairs or args.lomatch_pairs or args.kitti_pairs):
        ap.error(
            "nothing to evaluate: give --real and/or --synthetic-pairs / --lomatch-pairs / --kitti-pairs"
        )
    if (args.real or args.real_ids) and not (Path(args.real_root) / "pairs.json").is_file():
        # asked for and not there: a failure before any work, not a skip and exit 0
        print(f"evaluate: --real: {Path(args.real_root) / 'pairs.json'} not found (pass --real-root DIR)",
              file=sys.stderr)  # fmt: skip
        sys.exit(2)

    from fastmac_exp.backends import make_backend

    names = list(args.descriptors)
    descriptors = make_descriptors(names, args.threads, args.fcgf_model)
    backend = make_backend(args.backend)
    print(f"descriptors {names}; backend {type(backend).__name__}; seed {args.seed}")
    report: dict = {"args": vars(args), "version": __version__}
    for family, n in (
        ("3dmatch", args.synthetic_pairs),
        ("3dlomatch", args.lomatch_pairs),
        ("kitti", args.kitti_pairs),
    ):
        if n:
            title = f"Held-out synthetic pairs ({family}, seed {args.seed})"
            pairs = synthetic_pairs(family, n, args.seed, args.cache_dir)
            report[f"synthetic_{family}"] = run(
                title, f"synthetic{args.seed}", pairs, names, descriptors, backend, args
            )
    if args.real or args.real_ids:
        pairs = real_pairs(Path(args.real_root), args.real_ids)
        if pairs:
            report["real"] = run("Real pairs (shared/data)", "real", pairs, names, descriptors, backend, args)
    if args.json:
        Path(args.json).write_text(json.dumps(report, indent=1, default=str) + "\n")


if __name__ == "__main__":
    main()
