"""SpinNet's inlier ratio against its keypoint count on the real pairs of ../shared/data, for the default.

    python descriptors/spinnet/keypoints_study.py --json descriptors/spinnet/keypoints.json

Per family, the counts are compared on the `choose` pairs and reported on the `held_out` ones (none of which
calibrated the int8 models: those saw synthetic clouds only). One-way nearest-neighbour matching, seed 0, the
inlier ratio of the correspondences FastMAC receives (within the pair's GT threshold), and the seconds a pair
took to describe (both clouds, from an empty cache, the machine's load printed).
"""

from __future__ import annotations

import argparse
import json
import os
import sys
import time
from pathlib import Path

import numpy as np

REPO = Path(__file__).resolve().parents[2]
if str(REPO) not in sys.path:
    sys.path.insert(0, str(REPO))

from fastmac_exp.datasets.user_pairs import SharedRealPairs  # noqa: E402
from fastmac_exp.descriptors.buffer import forget_described_clouds  # noqa: E402
from fastmac_exp.descriptors.spinnet import SpinNetDescriptor  # noqa: E402

DATA = REPO.parent / "shared" / "data"
PAIRS = {
    "3dmatch": {
        "choose": ["3dm_redkitchen_6_to_0_geotransformer", "3dm_redkitchen_4_to_0_teaser_fullres"],
        "held_out": ["3dlm_redkitchen_7_to_0_mac_fullres", "3dm_homeat_38_to_2"],
    },
    "kitti": {"choose": ["kitti00_95_to_94"], "held_out": ["kitti00_5_to_0"]},
}


def run(family: str, counts: list[int], precision: str) -> dict:
    out = {}
    for role, ids in PAIRS[family].items():
        ds = SharedRealPairs(root=DATA, ids=ids)
        for i in range(len(ds)):
            pair = ds.load(i)
            for n in counts:
                forget_described_clouds()
                d = SpinNetDescriptor(keypoints=n, precision=precision, progress=False)
                t0 = time.perf_counter()
                corr = d(pair, np.random.default_rng(0))
                row = {
                    "role": role,
                    "keypoints": n,
                    "inlier_ratio": round(float(corr.inlier_ratio), 4),
                    "correspondences": len(corr),
                    "describe_s": round(time.perf_counter() - t0, 1),
                    "load": round(os.getloadavg()[0], 2),
                }
                out.setdefault(pair.name, []).append(row)
                print(family, pair.name, json.dumps(row), flush=True)
    return out


def main(argv=None) -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--families", nargs="+", default=list(PAIRS))
    ap.add_argument("--counts-3dmatch", type=int, nargs="+", default=[400, 1000])
    ap.add_argument("--counts-kitti", type=int, nargs="+", default=[1000, 2500])
    ap.add_argument("--precision", default="int8")
    ap.add_argument("--json", type=Path, default=None)
    args = ap.parse_args(argv)
    counts = {"3dmatch": args.counts_3dmatch, "kitti": args.counts_kitti}
    out = {"precision": args.precision, "cpus": os.cpu_count(), "pairs": {}}
    for fam in args.families:
        out["pairs"][fam] = run(fam, counts[fam], args.precision)
    if args.json:
        args.json.write_text(json.dumps(out, indent=1) + "\n")


if __name__ == "__main__":
    main()
