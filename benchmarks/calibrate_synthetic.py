"""Calibrate the synthetic dataset's difficulty against real pairs: FPFH inlier ratios side by side.

For every real indoor pair (3DMatch / 3DLoMatch fragments) and outdoor pair (KITTI 95->94, 199->198,
small_gicp; KITTI 198->94 reported apart as the near-zero-overlap case) in ../shared/data/pairs.json,
and for N synthetic pairs per family, it computes FPFH correspondences with the same front end
(fastmac_exp.descriptors.fpfh.FPFHDescriptor, voxel 0.05 indoor / 0.3 outdoor, one-way NN, capped at
5000) and the inlier ratio under GT (error < 0.1 m indoor, < 0.6 m outdoor), plus the overlap measured
the same way for both (fastmac_exp.datasets.synthetic.overlap_fraction).

    PYTHONPATH=. python benchmarks/calibrate_synthetic.py [--pairs 16] [--seed 0] [--data ../shared/data]
        [--families 3dmatch,3dlomatch,kitti] [--extra kitti:motion_range=1,10]

The real data is read in place (research-only licence), never copied. Without it the real side is
skipped and only the synthetic distributions are printed.
"""

from __future__ import annotations

import argparse
import json
import sys
import time
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

from fastmac_exp.datasets.scenes import rotation_angle_deg  # noqa: E402
from fastmac_exp.datasets.synthetic import (  # noqa: E402
    OVERLAP_MEASURE,
    SyntheticDataset,
    overlap_fraction,
)
from fastmac_exp.descriptors.fpfh import FPFHDescriptor  # noqa: E402
from fastmac_exp.families import FAMILIES  # noqa: E402
from fastmac_exp.types import Pair  # noqa: E402

# real pair id -> (group, family whose rules apply)
REAL_GROUPS = {
    "3dm_redkitchen_6_to_0_geotransformer": ("real indoor", "3dmatch"),
    "3dm_redkitchen_4_to_0_teaser_fullres": ("real indoor", "3dmatch"),
    "3dlm_redkitchen_7_to_0_mac_fullres": ("real indoor", "3dlomatch"),
    "kitti00_95_to_94": ("real outdoor", "kitti"),
    "kitti00_199_to_198": ("real outdoor", "kitti"),
    "lidar_smallgicp_source_to_target": ("real outdoor", "kitti"),
    "kitti00_198_to_94_lowoverlap": ("real outdoor low-overlap", "kitti"),
}


def load_cloud(path: Path) -> np.ndarray:
    from fastmac_exp._open3d import o3d

    if path.suffix == ".npy":
        pts = np.load(path, allow_pickle=False)
    elif path.suffix == ".bin":
        pts = np.fromfile(path, dtype=np.float32).reshape(-1, 4)[:, :3]
    else:
        pts = np.asarray(o3d.io.read_point_cloud(str(path)).points)
    pts = np.asarray(pts, dtype=np.float64)
    return pts[np.isfinite(pts).all(axis=1) & (np.abs(pts).sum(axis=1) > 0)]  # drop (0,0,0) invalid returns


def load_gt(path: Path) -> np.ndarray:
    return np.load(path, allow_pickle=False) if path.suffix == ".npy" else np.loadtxt(path)


ORIENT = {"normals": "open3d"}


def measure(pair: Pair, rng_seed: int = 0) -> dict:
    kind = FAMILIES[pair.family].kind
    t0 = time.perf_counter()
    fpfh = FPFHDescriptor(voxel_size=FAMILIES[pair.family].voxel_size, orient_normals=ORIENT["normals"])
    corr = fpfh(pair, np.random.default_rng(rng_seed))
    t_fpfh = time.perf_counter() - t0
    vox, rad = OVERLAP_MEASURE[kind]
    return {
        "n": len(corr),
        "ir": corr.inlier_ratio,
        "overlap": overlap_fraction(pair.src_cloud, pair.tgt_cloud, pair.gt, vox, rad),
        "rot": rotation_angle_deg(pair.gt[:3, :3]),
        "trans": float(np.linalg.norm(pair.gt[:3, 3])),
        "fpfh_s": t_fpfh,
    }


def real_rows(data: Path) -> list[dict]:
    index = json.loads((data / "pairs.json").read_text())
    rows = []
    for entry in index["pairs"]:
        if entry["id"] not in REAL_GROUPS:
            continue
        group, family = REAL_GROUPS[entry["id"]]
        pair = Pair(
            name=entry["id"],
            family=family,
            gt=load_gt(data / entry["gt"]),
            src_cloud=load_cloud(data / entry["source"]),
            tgt_cloud=load_cloud(data / entry["target"]),
            voxel_size=FAMILIES[family].voxel_size,
            inlier_threshold=FAMILIES[family].inlier_threshold,
        )
        rows.append({"group": group, "pair": entry["id"], **measure(pair)})
        print(f"  {group:26s} {entry['id']:40s} IR {rows[-1]['ir']:.3f}", file=sys.stderr, flush=True)
    return rows


def synthetic_rows(family: str, n: int, seed: int, label: str, **kwargs) -> list[dict]:
    ds = SyntheticDataset(family=family, num_pairs=n, seed=seed, cache_dir=None, **kwargs)
    rows = []
    for i in range(n):
        t0 = time.perf_counter()
        pair = ds.load(i)
        gen = time.perf_counter() - t0
        rows.append({"group": label, "pair": pair.name, "gen_s": gen, **measure(pair)})
        print(f"  {label:26s} {pair.name:40s} IR {rows[-1]['ir']:.3f}", file=sys.stderr, flush=True)
    return rows


def summarize(rows: list[dict]) -> None:
    print("\nPer pair")
    print(
        f"| {'group':40s} | {'pair':38s} | {'N corr':>6s} | {'inlier ratio':>12s} | {'overlap':>7s} "
        f"| {'GT rot deg':>10s} | {'GT trans m':>10s} |"
    )
    print(f"|{'-' * 42}|{'-' * 40}|{'-' * 8}|{'-' * 14}|{'-' * 9}|{'-' * 12}|{'-' * 12}|")
    for r in rows:
        print(
            f"| {r['group']:40s} | {r['pair']:38s} | {r['n']:6d} | {r['ir']:12.4f} | {r['overlap']:7.3f} "
            f"| {r['rot']:10.1f} | {r['trans']:10.2f} |"
        )
    print("\nDistributions (FPFH inlier ratio under GT; overlap = fraction of source points near the target)")
    print(
        f"| {'group':40s} | {'pairs':>5s} | {'IR min':>7s} | {'IR median':>9s} | {'IR max':>7s} "
        f"| {'IR mean':>7s} | {'overlap median':>14s} | {'gen s/pair':>10s} | {'fpfh s/pair':>11s} |"
    )
    print(f"|{'-' * 42}|{'-' * 7}|{'-' * 9}|{'-' * 11}|{'-' * 9}|{'-' * 9}|{'-' * 16}|{'-' * 12}|{'-' * 13}|")
    groups = list(dict.fromkeys(r["group"] for r in rows))
    for g in groups:
        rs = [r for r in rows if r["group"] == g]
        ir = np.array([r["ir"] for r in rs])
        ov = np.array([r["overlap"] for r in rs])
        gen = np.mean([r["gen_s"] for r in rs]) if "gen_s" in rs[0] else float("nan")
        fp = np.mean([r["fpfh_s"] for r in rs])
        gen_s = "-" if np.isnan(gen) else f"{gen:.2f}"
        print(
            f"| {g:40s} | {len(rs):5d} | {ir.min():7.4f} | {np.median(ir):9.4f} | {ir.max():7.4f} "
            f"| {ir.mean():7.4f} | {np.median(ov):14.3f} | {gen_s:>10s} | {fp:11.2f} |"
        )


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--pairs", type=int, default=16, help="synthetic pairs per family")
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--data", type=Path, default=ROOT.parent / "shared" / "data")
    ap.add_argument("--families", default="3dmatch,3dlomatch,kitti")
    ap.add_argument(
        "--extra",
        action="append",
        default=[],
        help="an extra synthetic variant, e.g. kitti:motion_range=1,10 (repeatable)",
    )
    ap.add_argument(
        "--orient-normals",
        choices=["open3d", "origin"],
        default="open3d",
        help="FPFH normal orientation (FPFHDescriptor.orient_normals)",
    )
    args = ap.parse_args(argv)
    ORIENT["normals"] = args.orient_normals

    rows: list[dict] = []
    if (args.data / "pairs.json").exists():
        rows += real_rows(args.data)
    else:
        print(f"real data not found at {args.data}; skipping the real pairs", file=sys.stderr)
    for family in [f for f in args.families.split(",") if f]:
        rows += synthetic_rows(family, args.pairs, args.seed, f"synthetic {family}")
    for spec in args.extra:
        family, _, kv = spec.partition(":")
        kwargs: dict = {}
        for item in [s for s in kv.split(";") if s]:
            key, _, value = item.partition("=")
            vals = [float(v) for v in value.split(",")]
            kwargs[key] = vals if len(vals) > 1 else vals[0]
        rows += synthetic_rows(family, args.pairs, args.seed, f"synthetic {family} {kv}", **kwargs)
    summarize(rows)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
