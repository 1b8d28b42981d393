"""SpinNet's cost on a CPU and its rotation invariance, for descriptors/spinnet/MODEL_CARD.md.

    python descriptors/spinnet/bench.py --json descriptors/spinnet/speed.json
    python descriptors/spinnet/bench.py --against /work/wt-spin-base --repeats 3 --json speed_against.json

Describes a real 3DMatch fragment (redkitchen cloud_bin_0, farthest-point keypoints) and a KITTI scan (seq 00
frame 94, random keypoints) at `--keypoints-3dmatch` / `--keypoints-kitti` a cloud (400 / 1,000 by default:
the counts of the code before issue 50, so that every build describes the same keypoints), from an empty
cache, each run in a fresh process (`describe_once.py`): seconds a cloud, per keypoint, the network's and the
preparation's part (patches + C++ grouping or pooling; `wait_for_patches` is what the network waited for it).
`--runs` are this checkout's (precision:onnxruntime threads[/lanes]); `--against PATH` adds the runs
`--against-runs` of another checkout's build, run by that checkout's own interpreter (`PATH/.venv/bin/python`,
e.g. an older commit in its own worktree), so both builds are measured side by side in one run: `--repeats`
rounds, every run once a round, the order rotated each round, so that a change of the machine's load falls on
all runs alike. Ratios: seconds a keypoint of the yardstick (the other build's first run, else this build's
first run) and of this build's first run over each run's, per round (paired) and of the medians. Prints the
CPU model and the load average before and after. Then rotation invariance at each of this build's precisions
(in this process): the fragment and 40 of its keypoints rotated about the sensor; the mean cosine between a
keypoint's descriptors before and after, and how often the rotated keypoint's descriptor is the nearest of the
40. Needs ../shared/data; a shared machine only makes it slower.
"""

from __future__ import annotations

import argparse
import json
import os
import statistics
import subprocess
import sys
from pathlib import Path

import numpy as np

REPO = Path(__file__).resolve().parents[2]
if str(REPO) not in sys.path:
    sys.path.insert(0, str(REPO))

from benchmarks.machine import cpu_model  # noqa: E402
from fastmac_exp.descriptors.patches import voxel_down  # noqa: E402
from fastmac_exp.descriptors.spinnet import SpinNetDescriptor  # noqa: E402
from fastmac_exp.io import read_points  # noqa: E402

DATA = REPO.parent / "shared" / "data"
CLOUDS = {
    "3dmatch": (DATA / "teaser_3dmatch_redkitchen" / "cloud_bin_0.ply", 0.05),
    "kitti": (DATA / "kitti_seq00_scancontext" / "000094.bin", 0.3),
}
ONCE = Path(__file__).resolve().parent / "describe_once.py"


def random_rotation(rng: np.random.Generator) -> np.ndarray:
    q, r = np.linalg.qr(rng.normal(size=(3, 3)))
    q *= np.sign(np.diag(r))
    return q if np.linalg.det(q) > 0 else -q


def parse_run(text: str) -> tuple[str, int, str | None, str]:
    """precision:threads[/lanes][:DIR], DIR holding spinnet_<family>_int8.onnx (quantize.py --out DIR);
    lanes: batches run at once ("auto" or a count; 1 where not given, as before lanes existed)."""
    prec, _, rest = text.partition(":")
    threads, _, folder = rest.partition(":")
    threads, _, lanes = threads.partition("/")
    lanes = lanes or "1"
    if (
        prec not in ("float32", "int8")
        or not threads.isdigit()
        or not (lanes == "auto" or (lanes.isdigit() and int(lanes) >= 1))
        or (folder and prec != "int8")
    ):
        raise argparse.ArgumentTypeError(
            "a run is precision:threads[/lanes][:DIR] (float32|int8 : >= 0 [/ auto | >= 1] [: int8 models' "
            f"folder]), got {text!r}"
        )
    if folder and not Path(folder).is_dir():
        raise argparse.ArgumentTypeError(f"run {text!r}: no folder {folder}")
    return prec, int(threads), folder or None, lanes


def describe_once(
    python: str, repo: Path, family: str, prec: str, threads: int, folder, args, lanes="1"
) -> dict:
    """One run in a fresh process of `python` (whose fastmac_exp must come from `repo`); `folder`: where the
    int8 model is (None: the shipped one); `lanes` is passed on where it is not 1 (builds before lanes run
    one batch at a time)."""
    path, voxel = CLOUDS[family]
    cmd = [
        python, str(ONCE), "--repo", str(repo), "--family", family, "--cloud", str(path),
        "--voxel", str(voxel), "--threads", str(threads), "--precision", prec,
        "--batch-size", str(args.batch_size), "--keypoints", str(getattr(args, f"keypoints_{family}")),
    ]  # fmt: skip
    if folder:
        cmd += ["--model", str(Path(folder) / f"spinnet_{family}_int8.onnx")]
    if lanes != "1":
        cmd += ["--lanes", lanes]
    done = subprocess.run(cmd, cwd=repo, capture_output=True, text=True)
    if done.returncode != 0:
        raise SystemExit(f"{' '.join(cmd)} failed ({done.returncode}):\n{done.stderr[-2000:]}{done.stdout}")
    out = json.loads(done.stdout.strip().splitlines()[-1])
    return out | {"load_average": round(os.getloadavg()[0], 2)}


def rotation(threads: int, precision: str, folder: str | None, n: int = 40) -> dict:
    path, voxel = CLOUDS["3dmatch"]
    pts = np.asarray(read_points(path), dtype=np.float64)
    kp = voxel_down(pts, voxel)
    kp = kp[np.random.default_rng(5).choice(len(kp), n, replace=False)]
    rot = random_rotation(np.random.default_rng(21))
    extra = {"model_3dmatch_int8": str(Path(folder) / "spinnet_3dmatch_int8.onnx")} if folder else {}
    d = SpinNetDescriptor(threads=threads, progress=False, precision=precision, **extra)
    model = d.load("3dmatch")
    a = d.describe(model, pts, kp, 1.0)
    b = d.describe(model, pts @ rot.T, kp @ rot.T, 1.0)
    return {
        "keypoints": n,
        "rotation_deg": round(float(np.degrees(np.arccos((np.trace(rot) - 1) / 2))), 1),
        "mean_cosine": round(float(np.mean(np.sum(a * b, axis=1))), 4),
        "top1": round(float(np.mean(np.argmax(b @ a.T, axis=1) == np.arange(n))), 4),
    }


def ratios(rounds: dict, yard: str, families: list[str]) -> dict:
    """Per run and family: the yardstick's seconds a keypoint over the run's, paired by round (min, median,
    max) and of the medians."""
    out = {}
    for key, per_family in rounds.items():
        out[key] = {}
        for fam in families:
            a = [r["seconds_a_keypoint"] for r in rounds[yard][fam]]
            b = [r["seconds_a_keypoint"] for r in per_family[fam]]
            paired = sorted(x / y for x, y in zip(a, b, strict=True))
            out[key][fam] = {
                "of_medians": round(statistics.median(a) / statistics.median(b), 2),
                "paired_min_median_max": [round(paired[0], 2), round(statistics.median(paired), 2),
                                          round(paired[-1], 2)],
            }  # fmt: skip
    return out


def main(argv=None) -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument(
        "--runs",
        nargs="+",
        type=parse_run,
        default=[parse_run(r) for r in ("float32:1", "int8:1", "int8:2", "int8:0/auto")],
        help="this checkout's runs, precision:onnxruntime threads[/lanes][:folder of int8 models] (the "
        "first: this build's yardstick; threads 0: onnxruntime's default, or one a lane with lanes; "
        "int8:0/auto is the config's default: one-thread sessions, a lane a core)",
    )
    ap.add_argument("--against", type=Path, default=None, help="another checkout, built in PATH/.venv")
    ap.add_argument("--against-python", default=None, help="its interpreter (default PATH/.venv/bin/python)")
    ap.add_argument(
        "--against-runs",
        nargs="+",
        type=parse_run,
        default=[parse_run(r) for r in ("float32:1", "float32:2")],
        help="the other build's runs (the first: the yardstick of every ratio)",
    )
    ap.add_argument("--repeats", type=int, default=1, help="rounds, every run once a round")
    ap.add_argument("--keypoints-3dmatch", type=int, default=400)
    ap.add_argument("--keypoints-kitti", type=int, default=1000)
    ap.add_argument("--batch-size", type=int, default=8)
    ap.add_argument("--families", nargs="+", default=list(CLOUDS), choices=list(CLOUDS))
    ap.add_argument("--no-rotation", action="store_true", help="skip the rotation-invariance check")
    ap.add_argument("--json", type=Path, default=None)
    args = ap.parse_args(argv)
    if args.repeats < 1:
        ap.error("--repeats must be >= 1")
    runs = [("this", REPO, sys.executable, *run) for run in args.runs]
    other = []
    if args.against is not None:
        python = args.against_python or str(args.against / ".venv" / "bin" / "python")
        if not Path(python).exists():
            ap.error(f"--against: no interpreter {python} (build that checkout in its own .venv)")
        if any(run[2] for run in args.against_runs) or any(run[3] != "1" for run in args.against_runs):
            ap.error("--against-runs take the other build's own models (no folder) and one lane")
        other = [("against", args.against.resolve(), python, *run) for run in args.against_runs]
    runs = other + runs
    label = {
        run: f"{run[0]}_{run[3]}_threads{run[4]}"
        + (f"_lanes{run[6]}" if run[6] != "1" else "")
        + (f"_{Path(run[5]).name}" if run[5] else "")
        for run in runs
    }
    out = {
        "cpu": cpu_model(),
        "cpus": os.cpu_count(),
        "batch_size": args.batch_size,
        "keypoints": {f: getattr(args, f"keypoints_{f}") for f in args.families},
        "this": str(REPO),
        "against": None if args.against is None else str(args.against.resolve()),
        "load_average_at_start": round(os.getloadavg()[0], 2),
        "rounds": {label[run]: {f: [] for f in args.families} for run in runs},
    }
    jobs = [(run, fam) for run in runs for fam in args.families]
    for r in range(args.repeats):
        k = r % len(jobs)
        for run, fam in jobs[k:] + jobs[:k]:
            res = describe_once(run[2], run[1], fam, run[3], run[4], run[5], args, run[6])
            out["rounds"][label[run]][fam].append(res)
            print(f"round {r} {label[run]} {fam}", json.dumps(res), flush=True)
    out["median_seconds_a_keypoint"] = {
        key: {f: statistics.median(x["seconds_a_keypoint"] for x in v[f]) for f in args.families}
        for key, v in out["rounds"].items()
    }
    yard = label[runs[0]]
    this_first = label[next(run for run in runs if run[0] == "this")]
    out["ratio_to_" + yard] = ratios(out["rounds"], yard, args.families)
    if this_first != yard:
        out["ratio_to_" + this_first] = ratios(out["rounds"], this_first, args.families)
    if not args.no_rotation:
        out["rotation_invariance"] = {
            label[run]: rotation(1, run[3], run[5])
            for run in runs
            if run[0] == "this" and run[4] == 1 and run[6] == "1"
        }
    out["load_average_at_end"] = round(os.getloadavg()[0], 2)
    print(json.dumps({k: v for k, v in out.items() if k != "rounds"}, indent=1))
    if args.json:
        args.json.write_text(json.dumps(out, indent=1) + "\n")


if __name__ == "__main__":
    main()
