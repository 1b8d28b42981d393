"""Evaluate the learned descriptor against FPFH on the same keypoints, then MAC with each.

    cd /work/main && PYTHONPATH=. python -m descriptors.evaluate       # 20 + 20 held-out + 3 real pairs
    PYTHONPATH=. python -m descriptors.evaluate --synthetic-pairs 4 --lomatch-pairs 0 --no-real   # quick

Held-out synthetic pairs: SyntheticDataset families "3dmatch" (overlap 30-100 %) and "3dlomatch" (10-30 %,
never trained on), seed 0, the project's default evaluation seed, disjoint from training (seed 1000)
and validation (seed 2000). Real pairs: the indoor entries of
<repo>/../shared/data/pairs.json (3DMatch / 3DLoMatch, read by path; skipped when absent).

Both descriptors take the same keypoints (Open3D voxel downsampling at --voxel, 0.05 m) and match one
way by nearest neighbour, capped at 5000 correspondences with the same rng. Per pair and descriptor:
inlier ratio (error under GT < 0.1 m), feature-match recall (FMR: fraction of pairs with inlier ratio
> 5 %), MAC registration (NoSampler, backend "auto", graph parameters of params.mac_params_for(family,
descriptor)) judged by RE < 15 deg and TE < 0.3 m.
"""

from __future__ import annotations

import argparse
import json
import sys
import time
from pathlib import Path

import numpy as np

REPO = Path(__file__).resolve().parent.parent
if str(REPO) not in sys.path:
    sys.path.insert(0, str(REPO))

from fastmac_exp.descriptors.onnx_descriptor import DEFAULT_MODEL, OnnxDescriptor  # noqa: E402
from fastmac_exp.errors import FastMacError  # noqa: E402
from fastmac_exp.metrics import pose_errors  # noqa: E402
from fastmac_exp.params import INLIER_THRESHOLD, SUCCESS_THRESHOLDS, mac_params_for  # noqa: E402
from fastmac_exp.types import Pair  # noqa: E402

EVAL_SEED = 0
SHARED = REPO.parent / "shared" / "data"


def real_indoor_pairs(root: Path, voxel: float) -> list[Pair]:
    index = root / "pairs.json"
    if not index.is_file():
        print(f"real pairs: {index} not found, skipping them")
        return []
    from fastmac_exp.io import load_cloud, read_matrix

    pairs = []
    for e in json.loads(index.read_text())["pairs"]:
        if e.get("category") != "indoor":
            continue
        family = "3dlomatch" if "3dlomatch" in (e["id"] + e.get("dataset", "")).lower() else "3dmatch"
        try:
            src, tgt = load_cloud(root / e["source"]), load_cloud(root / e["target"])
            gt = read_matrix(root / e["gt"])
        except (FastMacError, OSError) as exc:
            print(f"real pair {e['id']}: skipped ({exc})")
            continue
        re_t, te_t = SUCCESS_THRESHOLDS[family]
        pairs.append(
            Pair(
                name=e["id"],
                family=family,
                gt=gt,
                src_cloud=src,
                tgt_cloud=tgt,
                voxel_size=voxel,
                inlier_threshold=INLIER_THRESHOLD[family],
                re_thresh_deg=re_t,
                te_thresh_m=te_t,
            )
        )
    return pairs


def evaluate_pair(pair: Pair, descriptors: dict, backend, seed: int) -> dict:
    from fastmac_exp.pipeline import register_correspondences
    from fastmac_exp.samplers import NoSampler

    row: dict = {"pair": pair.name, "family": pair.family}
    keypoints = {}
    for key, desc in descriptors.items():
        t0 = time.perf_counter()
        corr = desc(pair, np.random.default_rng(seed))
        row[f"{key}_ms"] = (time.perf_counter() - t0) * 1e3
        row[f"{key}_n"] = len(corr)
        row[f"{key}_ir"] = corr.inlier_ratio
        keypoints[key] = corr
        params = mac_params_for(pair.family, key)
        try:
            res, _ = register_correspondences(
                corr, params, NoSampler(), backend, family=pair.family, rng=np.random.default_rng(seed)
            )
            pe = pose_errors(res.pose, pair.gt, pair.re_thresh_deg, pair.te_thresh_m)
            row[f"{key}_re"], row[f"{key}_te"], row[f"{key}_ok"] = pe.re_deg, pe.te_cm, pe.success
        except FastMacError as exc:
            row[f"{key}_re"], row[f"{key}_te"], row[f"{key}_ok"] = float("nan"), float("nan"), False
            row[f"{key}_err"] = str(exc)
    return row


def summarize(rows: list[dict], keys: list[str]) -> dict:
    out = {}
    for k in keys:
        ir = np.array([r[f"{k}_ir"] for r in rows])
        ok = np.array([r[f"{k}_ok"] for r in rows])
        out[k] = {
            "pairs": len(rows),
            "mean_ir": float(ir.mean()),
            "median_ir": float(np.median(ir)),
            "fmr": float(np.mean(ir > 0.05)),
            "registered": int(ok.sum()),
            "median_ms": float(np.median([r[f"{k}_ms"] for r in rows])),
        }
    return out


def print_table(title: str, rows: list[dict], keys: list[str]) -> None:
    print(f"\n### {title}\n")
    head = "| pair | " + " | ".join(f"{k} IR | {k} RE/TE | {k} ok" for k in keys) + " |"
    print(head)
    print("|" + "---|" * (1 + 3 * len(keys)))
    for r in rows:
        cells = []
        for k in keys:
            cells += [
                f"{r[f'{k}_ir']:.3f}",
                f"{r[f'{k}_re']:.1f} deg / {r[f'{k}_te']:.1f} cm",
                "yes" if r[f"{k}_ok"] else "no",
            ]
        print(f"| {r['pair']} | " + " | ".join(cells) + " |")
    s = summarize(rows, keys)
    print(
        "\n| descriptor | pairs | mean IR | median IR | FMR (IR > 5%) | registered (RE<15, TE<0.3) | "
        "describe ms (median) |"
    )
    print("|---|---|---|---|---|---|---|")
    for k in keys:
        v = s[k]
        print(
            f"| {k} | {v['pairs']} | {v['mean_ir']:.4f} | {v['median_ir']:.4f} | {v['fmr']:.2f} | "
            f"{v['registered']}/{v['pairs']} | {v['median_ms']:.0f} |"
        )


def main(argv: list[str] | None = None) -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--model", default=DEFAULT_MODEL)
    ap.add_argument("--synthetic-pairs", type=int, default=20)
    ap.add_argument("--seed", type=int, default=EVAL_SEED, help="synthetic evaluation seed")
    ap.add_argument("--voxel", type=float, default=0.05)
    ap.add_argument("--lomatch-pairs", type=int, default=20, help="held-out low-overlap pairs (3dlomatch)")
    ap.add_argument("--no-real", action="store_true")
    ap.add_argument("--real-root", default=str(SHARED))
    ap.add_argument("--cache-dir", default=str(REPO / ".cache" / "synthetic"))
    ap.add_argument("--backend", default="auto")
    ap.add_argument("--json", default=None, help="write the rows and summaries here")
    args = ap.parse_args(argv)

    from fastmac_exp.datasets.synthetic import SyntheticDataset
    from fastmac_exp.descriptors.fpfh import FPFHDescriptor
    from fastmac_exp.registry import make_backend

    descriptors = {
        "fcgf": OnnxDescriptor(args.model, voxel_size=args.voxel),
        "fpfh": FPFHDescriptor(voxel_size=args.voxel),
    }
    keys = list(descriptors)
    backend = make_backend(args.backend)
    print(f"model {descriptors['fcgf'].model_path}; backend {type(backend).__name__}; voxel {args.voxel} m")
    report: dict = {}
    for family, n in (("3dmatch", args.synthetic_pairs), ("3dlomatch", args.lomatch_pairs)):
        if not n:
            continue
        ds = SyntheticDataset(family=family, num_pairs=n, seed=args.seed, cache_dir=args.cache_dir)
        rows = []
        for i in range(len(ds)):
            rows.append(evaluate_pair(ds.load(i), descriptors, backend, seed=i))
            r = rows[-1]
            print(
                f"  {r['pair']}: " + ", ".join(f"{k} IR {r[f'{k}_ir']:.3f} ok {r[f'{k}_ok']}" for k in keys),
                flush=True,
            )
        print_table(f"Held-out synthetic indoor pairs ({family}, seed {args.seed})", rows, keys)
        report[f"synthetic_{family}"] = {"rows": rows, "summary": summarize(rows, keys)}
    if not args.no_real:
        real = real_indoor_pairs(Path(args.real_root), args.voxel)
        if real:
            rows = [evaluate_pair(p, descriptors, backend, seed=0) for p in real]
            print_table("Real indoor pairs (3DMatch / 3DLoMatch, shared/data)", rows, keys)
            report["real"] = {"rows": rows, "summary": summarize(rows, keys)}
    if args.json:
        Path(args.json).write_text(json.dumps(report, indent=1, default=str))


if __name__ == "__main__":
    main()
