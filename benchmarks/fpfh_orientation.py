"""FPFH inlier ratio with Open3D's +z normal orientation against orientation towards the sensor (origin),
on every real pair of ../shared/data (5,000 correspondences, the dataset's voxel and thresholds).

    python benchmarks/fpfh_orientation.py [--data ../shared/data]   # prints a markdown table
"""

from __future__ import annotations

import sys
from pathlib import Path

import numpy as np

REPO = Path(__file__).resolve().parents[1]
if str(REPO) not in sys.path:
    sys.path.insert(0, str(REPO))

from fastmac_exp.datasets.user_pairs import SharedRealPairs  # noqa: E402
from fastmac_exp.descriptors.fpfh import FPFHDescriptor  # noqa: E402
from fastmac_exp.geometry.transforms import rotation_error_deg  # noqa: E402


def main(argv: list[str] | None = None) -> int:
    import argparse

    from fastmac_exp.errors import FastMacError

    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--data", default=str(REPO.parent / "shared" / "data"), help="the shared data folder")
    args = ap.parse_args(argv)
    try:
        return table(SharedRealPairs(root=args.data))
    except FastMacError as exc:  # missing data, an unreadable pair: one line, not a traceback
        print(f"fpfh_orientation: {exc}", file=sys.stderr)
        return 2


def table(ds: SharedRealPairs) -> int:
    ds.names()  # the index is read (and a missing one refused) before the table starts
    print("| pair | family | GT rotation (°) | inlier ratio, +z (open3d) | towards origin | ratio |")
    print("|---|---|---:|---:|---:|---:|")
    for i, name in enumerate(ds.names()):
        pair = ds.load(i)
        ratios = []
        for orient in ("open3d", "origin"):
            corr = FPFHDescriptor(orient_normals=orient, max_correspondences=5000)(
                pair, np.random.default_rng(0)
            )
            pair.label(corr)
            ratios.append(float(corr.labels.mean()))
        rot = rotation_error_deg(pair.gt[:3, :3], np.eye(3))
        gain = f"{ratios[1] / ratios[0]:.2f}" if ratios[0] > 0 else "-"
        print(f"| {name} | {pair.family} | {rot:.1f} | {ratios[0]:.4f} | {ratios[1]:.4f} | {gain} |")
    return 0


if __name__ == "__main__":
    sys.exit(main())
