"""Calibrate `result.trusted` (geometry/trust.py) on the real pairs of ../shared/data and on unrelated
pairs made of them (each pair's target with the source of the next pair of the same category).

For every pair it runs the experiment's flow (FPFH, the given sampler and ratio, the C++ MAC) and prints
the evidence (correspondences explained by the pose, the clique, chance's count lambda, the confidence)
next to the GT verdict; then the false-accept count (an unrelated pair, or a real pair whose pose fails
GT, that is trusted) and the false-reject count (a real pair registered by GT, not trusted).

    PYTHONPATH=. python benchmarks/calibrate_trust.py [--data ../shared/data] [--sampler highpass]
        [--ratio 0.2] [--json out.json]
"""

from __future__ import annotations

import argparse
import dataclasses
import json
import sys
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

from fastmac_exp.backends.cpp import CppBackend  # noqa: E402
from fastmac_exp.datasets.user_pairs import SharedRealPairs  # noqa: E402
from fastmac_exp.descriptors.fpfh import FPFHDescriptor  # noqa: E402
from fastmac_exp.options import compose_run, instantiate_part  # noqa: E402
from fastmac_exp.pipeline import run_pair  # noqa: E402


def scene(entry: dict) -> str:
    """The place a pair was scanned: pairs of one place are not unrelated (several redkitchen fragments,
    KITTI 00 frames)."""
    text = f"{entry['id']} {entry['dataset']}".lower()
    for place in ("redkitchen", "kitti", "home_at", "bunny", "dragon", "apollo"):
        if place in text:
            return place
    return entry["source"].split("/")[0]


def pairs(data: str):
    ds = SharedRealPairs(root=data)
    loaded = [ds.load(i) for i in range(len(ds))]
    entries = ds._index()
    for p in loaded:
        yield "real", p
    # unrelated: each pair's target with the source of every pair of the same category from another place
    for i, p in enumerate(loaded):
        for j, src in enumerate(loaded):
            if entries[j]["category"] != entries[i]["category"] or scene(entries[j]) == scene(entries[i]):
                continue
            yield (
                "unrelated",
                dataclasses.replace(
                    p,
                    name=f"{src.name}(src)+{p.name}(tgt)",
                    src_cloud=src.src_cloud,
                    gt=None,
                    correspondences=None,
                ),
            )


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--data", default=str(ROOT.parent / "shared" / "data"))
    ap.add_argument("--sampler", default="highpass")
    ap.add_argument("--ratio", type=float, default=0.2)
    ap.add_argument("--json", default=None)
    args = ap.parse_args()
    if not (Path(args.data) / "pairs.json").is_file():
        sys.exit(f"calibrate_trust: {args.data}/pairs.json not found (pass --data)")
    sampler = instantiate_part(compose_run({"sampler": args.sampler}).sampler)
    rows = []
    print(
        f"{'kind':9s} {'pair':62s} {'N':>5s} {'inl':>5s} {'clq':>4s} {'lambda':>7s} {'conf':>8s} trusted GT"
    )
    for kind, pair in pairs(args.data):
        out = run_pair(pair, FPFHDescriptor(), sampler, CppBackend(), args.ratio, np.random.default_rng(0))
        r = out.row
        lam = out.result.chance_inliers if out.result is not None else None
        ok = r.get("success")
        rows.append({"kind": kind, "pair": pair.name, "n_in": r.get("n_in"), "inliers": r.get("pose_inliers"),
                     "clique": r.get("clique_size"), "lambda": lam, "confidence": r.get("confidence"),
                     "trusted": r.get("trusted"), "success": ok, "error": r.get("error", "")})  # fmt: skip
        print(f"{kind:9s} {pair.name[:62]:62s} {r.get('n_in', 0):5d} {r.get('pose_inliers', 0):5d} "
              f"{r.get('clique_size', 0):4d} {lam if lam is not None else float('nan'):7.2f} "
              f"{r.get('confidence', 0.0):8.6f} {str(r.get('trusted')):7s} {ok}", flush=True)  # fmt: skip
    real = [r for r in rows if r["kind"] == "real"]
    unrelated = [r for r in rows if r["kind"] == "unrelated"]
    fa_unrel = sum(bool(r["trusted"]) for r in unrelated)
    fa_wrong = sum(bool(r["trusted"]) and not r["success"] for r in real)
    fr = sum(bool(r["success"]) and not r["trusted"] for r in real)
    print(f"real pairs: {len(real)} ({sum(bool(r['success']) for r in real)} registered by GT); "
          f"unrelated pairs: {len(unrelated)}")  # fmt: skip
    print(
        f"false accepts: {fa_unrel} of {len(unrelated)} unrelated, {fa_wrong} real pair(s) with a wrong pose"
    )
    print(f"false rejects: {fr} of the registered real pairs")
    if args.json:
        Path(args.json).write_text(json.dumps(rows, indent=1, default=str))


if __name__ == "__main__":
    main()
