"""SpinNet's cost on a CPU and its rotation invariance, for descriptors/spinnet/MODEL_CARD.md.

    cd /work/main && python descriptors/spinnet/bench.py --json descriptors/spinnet/speed.json

Describes a real 3DMatch fragment (redkitchen cloud_bin_0, 400 farthest-point keypoints, the default) and a
KITTI scan (seq 00 frame 94, 1,000 random keypoints, the default) from an empty cache with onnxruntime on
`--threads` threads, at each `--precision` in turn in one process (float32: the published weights as exported,
the grouped cells into the network; int8: the C++ pooling and the quantised convolutions): seconds a cloud,
per keypoint, the network's and the preparation's part (patches + C++ grouping or pooling, on a second thread
while the network runs: `wait_for_patches` is what the network waited for it), and the ratio to the first
precision. Prints the CPU model and the load average before and after. Then rotation invariance at each
precision: the fragment and 40 of its keypoints rotated about the sensor; the mean cosine between a keypoint's
descriptors before and after, and how often the rotated keypoint's descriptor is the nearest of the 40.
Needs ../shared/data; a shared machine only makes it slower.
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

from benchmarks.machine import cpu_model  # noqa: E402
from fastmac_exp.descriptors.patches import voxel_down  # noqa: E402
from fastmac_exp.descriptors.spinnet import SpinNetDescriptor, grid_for  # noqa: E402
from fastmac_exp.io import read_points  # noqa: E402

DATA = REPO.parent / "shared" / "data"
CLOUDS = {
    "3dmatch": (DATA / "teaser_3dmatch_redkitchen" / "cloud_bin_0.ply", 0.05),
    "kitti": (DATA / "kitti_seq00_scancontext" / "000094.bin", 0.3),
}


def random_rotation(rng: np.random.Generator) -> np.ndarray:
    q, r = np.linalg.qr(rng.normal(size=(3, 3)))
    q *= np.sign(np.diag(r))
    return q if np.linalg.det(q) > 0 else -q


def speed(family: str, threads: int, precision: str, batch_size: int) -> dict:
    path, voxel = CLOUDS[family]
    pts = np.asarray(read_points(path), dtype=np.float64)
    d = SpinNetDescriptor(
        threads=threads, progress=False, precision=precision, batch_size=batch_size, cache_clouds=0
    )
    model = d.load(family)
    t0 = time.perf_counter()
    grid_for(model.params)
    t_grid = time.perf_counter() - t0
    t0 = time.perf_counter()
    kp, _ = d.features(pts, voxel, family=family)
    total = time.perf_counter() - t0
    t = d.last_timings
    n = len(kp)
    return {
        "cloud": path.name,
        "points": len(pts),
        "keypoints": n,
        "cell_table_s_once_a_process": round(t_grid, 2),
        "seconds_a_cloud": round(total, 2),
        "seconds_a_keypoint": round(total / n, 4),
        "network_s_a_keypoint": round(t["network_s"] / n, 4),
        "patches_and_grouping_s_a_keypoint": round(t["patches_s"] / n, 4),
        "wait_for_patches_s_a_keypoint": round(t["wait_for_patches_s"] / n, 4),
    }


def rotation(threads: int, precision: str, n: int = 40) -> dict:
    path, voxel = CLOUDS["3dmatch"]
    pts = np.asarray(read_points(path), dtype=np.float64)
    kp = voxel_down(pts, voxel)
    kp = kp[np.random.default_rng(5).choice(len(kp), n, replace=False)]
    rot = random_rotation(np.random.default_rng(21))
    d = SpinNetDescriptor(threads=threads, progress=False, precision=precision)
    model = d.load("3dmatch")
    a = d.describe(model, pts, kp, 1.0)
    b = d.describe(model, pts @ rot.T, kp @ rot.T, 1.0)
    return {
        "keypoints": n,
        "rotation_deg": round(float(np.degrees(np.arccos((np.trace(rot) - 1) / 2))), 1),
        "mean_cosine": round(float(np.mean(np.sum(a * b, axis=1))), 4),
        "top1": round(float(np.mean(np.argmax(b @ a.T, axis=1) == np.arange(n))), 4),
    }


def main(argv=None) -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument(
        "--runs",
        nargs="+",
        default=["float32:1", "int8:1", "int8:2"],
        help="precision:onnxruntime threads, in order (the first is the ratios' yardstick: today's default)",
    )
    ap.add_argument("--batch-size", type=int, default=8)
    ap.add_argument("--families", nargs="+", default=list(CLOUDS))
    ap.add_argument("--json", type=Path, default=None)
    args = ap.parse_args(argv)
    runs = [(r.split(":")[0], int(r.split(":")[1])) for r in args.runs]
    out = {
        "cpu": cpu_model(),
        "batch_size": args.batch_size,
        "load_average_at_start": os.getloadavg()[0],
        "cpus": os.cpu_count(),
        "speed": {},
    }
    for prec, threads in runs:
        key = f"{prec}_threads{threads}"
        out["speed"][key] = {fam: speed(fam, threads, prec, args.batch_size) for fam in args.families}
        print(key, json.dumps(out["speed"][key]), flush=True)
    keys = list(out["speed"])
    first = keys[0]
    out["seconds_a_keypoint_ratio_to_" + first] = {
        prec: {
            fam: round(
                out["speed"][first][fam]["seconds_a_keypoint"]
                / out["speed"][prec][fam]["seconds_a_keypoint"],
                2,
            )
            for fam in args.families
        }
        for prec in keys
    }
    out["rotation_invariance"] = {prec: rotation(1, prec) for prec in dict(runs)}
    out["load_average_at_end"] = os.getloadavg()[0]
    print(json.dumps(out, indent=1))
    if args.json:
        args.json.write_text(json.dumps(out, indent=1) + "\n")


if __name__ == "__main__":
    main()
