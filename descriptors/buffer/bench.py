"""BUFFER's cost on a CPU: the code before the speed work (commit 6333dc0), the code and int8 models of
98f33b2 (before the second round of issue 31), and today's, side by side in one run (run from git), and the
inlier ratios on the real pairs.

    python descriptors/buffer/bench.py              # speed: a 3DMatch fragment and a KITTI scan, 3 repeats
    python descriptors/buffer/bench.py --inliers    # + IR on every real pair, float32 and int8
    python descriptors/buffer/bench.py --json out.json --reps 5 --threads 1 [--skip-before]

Speed (needs ../shared/data): per fragment, the target cloud of 3dm_redkitchen_4_to_0_teaser_fullres
(5,208 keypoints) and of kitti00_95_to_94 (17,355 keypoints), and per pair (both clouds, as a run
describes them). "before" describes every keypoint of both clouds in float32 (the code of 6333dc0,
imported from `git show`); 98f33b2 and "now" describe the keypoints the pair needs (the 5,000 source
keypoints the correspondence cap keeps, every target keypoint), "now" in float32 and in int8; "matched"
is the config's default since issue 50 (`match_keypoints: auto`, mutual: at most 1,000 / 5,000 keypoints
of each cloud, descriptors/buffer/matched.py; its "target fragment" column still describes every keypoint,
as `features` does). The variants
run interleaved, each repeat on a fresh descriptor (no cloud cache carried over, the onnxruntime sessions
opened before the clock starts); medians of `--reps`, wall and CPU seconds of the process (the patch
preparation runs in a second thread beside onnxruntime, so CPU > wall), and the 1-minute load average.
The machine is shared: only the ratios within one run mean much.

Inliers (`--inliers`): every pair of ../shared/data/pairs.json, correspondences drawn with seed 0 as
descriptors/evaluate.py does; IR of float32 now (equal to before: tests/test_buffer_descriptor.py) and of
int8, against descriptors/evaluation_real.json's BUFFER column (the code before).
"""

from __future__ import annotations

import argparse
import importlib.util
import json
import os
import statistics
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

REPO = Path(__file__).resolve().parents[2]
if str(REPO) not in sys.path:
    sys.path.insert(0, str(REPO))

from fastmac_exp.descriptors.buffer import BufferDescriptor, forget_described_clouds  # noqa: E402

SHARED = REPO.parent / "shared" / "data"
BEFORE = "6333dc0"  # the code before issue 31's speed work
PREVIOUS = "98f33b2"  # the code before the second round (VNNI machine: patch index, uint8 convolution chain)
CASES = (
    ("3dm_redkitchen_4_to_0_teaser_fullres", "3DMatch"),
    ("kitti00_95_to_94", "KITTI"),
)


def git_file(commit: str, path: str) -> bytes:
    return subprocess.run(
        ["git", "-C", str(REPO), "show", f"{commit}:{path}"], check=True, capture_output=True
    ).stdout


def old_module(commit: str = BEFORE):
    """fastmac_exp/descriptors/buffer.py as it was at `commit`, imported under another name."""
    src = git_file(commit, "fastmac_exp/descriptors/buffer.py").decode()
    path = Path(tempfile.mkdtemp()) / f"buffer_{commit}.py"
    path.write_text(src)
    spec = importlib.util.spec_from_file_location(f"buffer_{commit}", path)
    mod = importlib.util.module_from_spec(spec)
    sys.modules[spec.name] = mod  # dataclasses look their module up
    spec.loader.exec_module(mod)
    return mod


def load_pair(pid: str):
    from fastmac_exp.datasets.user_pairs import SharedRealPairs

    return SharedRealPairs(root=SHARED, ids=[pid]).load(0)


def previous_int8(commit: str = PREVIOUS) -> dict:
    """The int8 model files as they were at `commit` (written to a temporary folder): model_*_int8 paths."""
    out, folder = {}, Path(tempfile.mkdtemp())
    for fam in ("3dmatch", "kitti"):
        name = f"buffer_{fam}_desc_int8.onnx"
        (folder / name).write_bytes(git_file(commit, f"fastmac_exp/models/{name}"))
        out[f"model_{fam}_int8"] = str(folder / name)
    ref = "fastmac_exp/models/buffer_3dmatch_ref.onnx"  # looked up beside the Desc model otherwise
    (folder / Path(ref).name).write_bytes(git_file(commit, ref))
    return out


def speed(reps: int, threads: int, skip_before: bool = False) -> dict:
    makers = {}
    if not skip_before:
        old = old_module()
        makers["before (6333dc0, float32, every keypoint)"] = lambda: old.BufferDescriptor(
            threads=threads, progress=False
        )
    prev, prev_models = old_module(PREVIOUS), previous_int8()
    makers[f"{PREVIOUS} int8 (its code and models)"] = lambda: prev.BufferDescriptor(
        threads=threads, progress=False, precision="int8", **prev_models
    )
    makers["now float32"] = lambda: BufferDescriptor(threads=threads, progress=False)
    makers["now int8"] = lambda: BufferDescriptor(threads=threads, progress=False, precision="int8")
    makers["now int8, matched (the config's)"] = lambda: BufferDescriptor(
        threads=threads, progress=False, precision="int8", match_keypoints="auto", mutual=True
    )
    out = {}
    for pid, label in CASES:
        try:
            pair = load_pair(pid)
        except Exception as exc:  # noqa: BLE001 - the benchmark skips a pair it cannot read
            print(f"{pid}: unavailable ({exc})")
            continue
        times = {name: {k: [] for k in ("fragment", "pair", "fragment_cpu", "pair_cpu")} for name in makers}
        counts, loads = {}, [os.getloadavg()[0]]
        for _ in range(reps):
            for name, make in makers.items():  # interleaved: each repeat runs every variant once
                forget_described_clouds()  # the described clouds are the process's: none carried over
                d = make()
                d.model_for(pair.family)  # sessions opened outside the timing
                t, c = time.perf_counter(), time.process_time()
                d.features(pair.tgt_cloud, pair.voxel_size, "target", family=pair.family, scale=1.0)
                times[name]["fragment"].append(time.perf_counter() - t)
                times[name]["fragment_cpu"].append(time.process_time() - c)
                forget_described_clouds()
                d = make()
                d.model_for(pair.family)
                t, c = time.perf_counter(), time.process_time()
                d(pair, np.random.default_rng(0))
                times[name]["pair"].append(time.perf_counter() - t)
                times[name]["pair_cpu"].append(time.process_time() - c)
                loads.append(os.getloadavg()[0])
                counts[name] = [t["keypoints"] for t in d.timings_log]
        res = {}
        for name in makers:
            res[name] = {
                **{f"{k}_s": round(statistics.median(v), 2) for k, v in times[name].items()},
                "pair_keypoints_described": counts[name],
            }
        out[f"{label} ({pid})"] = {**res, "load_average_1min": [round(x, 2) for x in loads]}
        base = res[next(iter(makers))]
        print(f"\n{label}: {pid}, median of {reps}, {threads or 'all'} onnxruntime thread(s)")
        print(f"  load average (1 min) during the run: {min(loads):.1f} .. {max(loads):.1f}")
        print(
            f"  {'':44s} {'target fragment':>16s} {'pair (src+tgt)':>15s}  {'CPU s frag / pair':>17s}"
            "  keypoints described (src, tgt)"
        )
        for name, r in res.items():
            print(
                f"  {name:44s} {r['fragment_s']:7.2f} s ({base['fragment_s'] / r['fragment_s']:4.1f}x)"
                f" {r['pair_s']:7.2f} s ({base['pair_s'] / r['pair_s']:4.1f}x)"
                f"  {r['fragment_cpu_s']:7.2f} / {r['pair_cpu_s']:6.2f}",
                r["pair_keypoints_described"],
                flush=True,
            )
    return out


def inliers(threads: int) -> dict:
    from fastmac_exp.datasets.user_pairs import SharedRealPairs

    before = json.loads((REPO / "descriptors" / "evaluation_real.json").read_text())["real"]["rows"]
    before = {r["pair"]: r["descriptors"]["buffer"]["ir"] for r in before}
    ds = SharedRealPairs(root=SHARED)
    variants = {
        "float32": BufferDescriptor(threads=threads, progress=False),
        "int8": BufferDescriptor(threads=threads, progress=False, precision="int8"),
    }
    rows = []
    print(f"\n{'pair':42s} {'before':>7s} {'float32':>8s} {'int8':>7s}  seconds float32 / int8")
    for i in range(len(ds)):
        pair = ds.load(i)
        row = {"pair": pair.name, "before": before.get(pair.name)}
        for name, d in variants.items():
            t = time.perf_counter()
            corr = d(pair, np.random.default_rng(0))
            row[name] = float(corr.inlier_ratio)
            row[f"{name}_s"] = round(time.perf_counter() - t, 2)
        rows.append(row)
        print(
            f"{pair.name:42s} {row['before'] or float('nan'):7.3f} {row['float32']:8.3f} {row['int8']:7.3f}  "
            f"{row['float32_s']:.1f} / {row['int8_s']:.1f}",
            flush=True,
        )
    mean = {k: float(np.mean([r[k] for r in rows])) for k in ("float32", "int8")}
    known = [r for r in rows if r["before"] is not None]
    mean["before"] = float(np.mean([r["before"] for r in known])) if known else None
    mean["int8_vs_float32_relative"] = mean["int8"] / mean["float32"] - 1
    print(
        f"mean IR over {len(rows)} pairs:",
        json.dumps({k: round(v, 4) for k, v in mean.items() if v is not None}),
    )
    return {"rows": rows, "mean": mean, "pairs": len(rows)}


def main(argv: list[str] | None = None) -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--reps", type=int, default=3)
    ap.add_argument("--threads", type=int, default=0, help="onnxruntime intra-op threads (0: all cores)")
    ap.add_argument("--inliers", action="store_true", help="also IR on every real pair")
    ap.add_argument("--no-speed", action="store_true")
    ap.add_argument("--skip-before", action="store_true", help=f"leave out {BEFORE}'s float32 code (slow)")
    ap.add_argument("--json", default=None)
    args = ap.parse_args(argv)
    if not (SHARED / "pairs.json").is_file():
        sys.exit(f"no real pairs at {SHARED}")
    report = {"before": BEFORE, "previous": PREVIOUS, "threads": args.threads}
    if not args.no_speed:
        report["speed"] = speed(args.reps, args.threads, args.skip_before)
    if args.inliers:
        report["inliers"] = inliers(args.threads)
    if args.json:
        Path(args.json).write_text(json.dumps(report, indent=1) + "\n")


if __name__ == "__main__":
    main()
