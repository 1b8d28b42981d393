"""One timed SpinNet description of one real cloud, for descriptors/spinnet/bench.py.

    <checkout>/.venv/bin/python descriptors/spinnet/describe_once.py --repo <checkout> --family 3dmatch \
        --cloud ../shared/data/teaser_3dmatch_redkitchen/cloud_bin_0.ply --voxel 0.05 --keypoints 400

Prints one JSON line: seconds a cloud and a keypoint from an empty cache, the network's and the preparation's
part. It imports `fastmac_exp` from the interpreter's own install (never from this file's checkout: the
script's folder, not the repository root, is on sys.path), so the same script times any build, e.g. the code
of an older commit in its own worktree and venv (`bench.py --against`); `--repo` names the checkout that
build must come from, and a run that imports another one stops. Uses only what SpinNet's front end has had
since it landed (`SpinNetDescriptor(threads, progress, keypoints, sampling, batch_size, cache_clouds)`,
`features`, `last_timings`, `grid_for`), plus `precision` where the build has it.
"""

from __future__ import annotations

import argparse
import inspect
import json
import sys
import time
from pathlib import Path

import numpy as np


def speed(
    family: str,
    cloud: Path,
    voxel: float,
    threads: int,
    precision: str = "float32",
    batch_size: int = 8,
    keypoints: int | None = None,
    model: str | None = None,
    lanes: str | None = None,
) -> dict:
    """Describe `cloud` (the model's default keypoints, or `keypoints`) from an empty cache and time it; the
    model session and the once-a-process cell table are built before the clock starts. `model`: the path of
    the model to run instead of the shipped one of `precision`."""
    from fastmac_exp.descriptors.spinnet import SpinNetDescriptor, grid_for
    from fastmac_exp.io import read_points

    pts = np.asarray(read_points(cloud), dtype=np.float64)
    kwargs = {"threads": threads, "progress": False, "batch_size": batch_size, "cache_clouds": 0}
    if keypoints is not None:
        kwargs["keypoints"] = keypoints
    accepted = inspect.signature(SpinNetDescriptor).parameters
    if "lanes" in accepted:  # the runs before lanes existed ran one batch at a time
        kwargs["lanes"] = 1 if lanes is None else (lanes if lanes == "auto" else int(lanes))
    elif lanes not in (None, "1"):
        raise SystemExit(f"this build's SpinNetDescriptor has no lanes, asked {lanes!r}")
    if "precision" in accepted:
        kwargs["precision"] = precision
    elif precision != "float32":
        raise SystemExit(
            f"this build's SpinNetDescriptor has no precision (only float32), asked {precision!r}"
        )
    if model is not None:
        key = f"model_{family}" + ("_int8" if precision == "int8" else "")
        if key not in accepted:
            raise SystemExit(f"this build's SpinNetDescriptor has no {key} to take {model}")
        kwargs[key] = model
    d = SpinNetDescriptor(**kwargs)
    m = d.load(family)
    t0 = time.perf_counter()
    grid_for(m.params)
    t_grid = time.perf_counter() - t0
    t0 = time.perf_counter()
    kp, _ = d.features(pts, voxel, family=family)
    total = time.perf_counter() - t0
    t = d.last_timings
    n = len(kp)
    return {
        "cloud": Path(cloud).name,
        "points": len(pts),
        "keypoints": n,
        "model": str(m.desc_path),
        "cell_table_s_once_a_process": round(t_grid, 2),
        "seconds_a_cloud": round(total, 3),
        "seconds_a_keypoint": round(total / n, 5),
        "network_s_a_keypoint": round(t["network_s"] / n, 5),
        "patches_and_grouping_s_a_keypoint": round(t["patches_s"] / n, 5),
        "wait_for_patches_s_a_keypoint": (
            round(t["wait_for_patches_s"] / n, 5) if "wait_for_patches_s" in t else None  # serial before
        ),
    }


def main(argv: list[str] | None = None) -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--repo", type=Path, required=True, help="the checkout fastmac_exp must be imported from")
    ap.add_argument("--family", required=True, choices=["3dmatch", "kitti"])
    ap.add_argument("--cloud", type=Path, required=True)
    ap.add_argument("--voxel", type=float, required=True)
    ap.add_argument("--threads", type=int, default=1)
    ap.add_argument("--precision", default="float32")
    ap.add_argument("--batch-size", type=int, default=8)
    ap.add_argument("--keypoints", type=int, default=None)
    ap.add_argument("--model", default=None)
    ap.add_argument("--lanes", default=None, help="auto or a count (default 1, as before lanes existed)")
    args = ap.parse_args(argv)
    import fastmac_exp

    where = Path(fastmac_exp.__file__).resolve()
    if args.repo.resolve() not in where.parents:
        raise SystemExit(f"fastmac_exp was imported from {where}, not from the checkout {args.repo}")
    out = speed(
        args.family, args.cloud, args.voxel, args.threads, args.precision, args.batch_size, args.keypoints,
        args.model, args.lanes,
    )  # fmt: skip
    print(json.dumps(out | {"fastmac_exp": str(where.parent)}), flush=True)


if __name__ == "__main__":
    sys.exit(main())
