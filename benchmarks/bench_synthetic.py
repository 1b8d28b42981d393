"""Seconds to generate the synthetic dataset's default pairs (uncached), per family: the timing that was a
test (tests/test_synthetic.py) and failed under load. Run it on a quiet machine and report the CPU and
the load average with it.

    PYTHONPATH=. python benchmarks/bench_synthetic.py [--pairs 2] [--families 3dmatch,kitti,3dlomatch]
"""

from __future__ import annotations

import argparse
import os
import platform
import sys
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

from fastmac_exp.datasets.synthetic import SyntheticDataset  # noqa: E402


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--pairs", type=int, default=2)
    ap.add_argument("--families", default="3dmatch,kitti,3dlomatch")
    args = ap.parse_args(argv)
    print(f"cpu: {platform.processor() or platform.machine()}  load average: {os.getloadavg()}")
    for family in args.families.split(","):
        ds = SyntheticDataset(family=family, num_pairs=args.pairs, cache_dir=None)
        for i in range(args.pairs):
            t0 = time.perf_counter()
            pair = ds.load(i)
            s = time.perf_counter() - t0
            points = f"{len(pair.src_cloud)} + {len(pair.tgt_cloud)} points"
            print(f"{family:10s} pair {i}: {s:6.2f} s  ({points})")
    return 0


if __name__ == "__main__":
    sys.exit(main())
