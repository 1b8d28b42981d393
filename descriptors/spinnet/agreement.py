"""Which INT8 variant of SpinNet agrees with float32, and what it costs (issue 50): the table of
descriptors/spinnet/MODEL_CARD.md, section INT8.

    nice -n 5 python descriptors/spinnet/agreement.py --json descriptors/spinnet/agreement.json
    python descriptors/spinnet/agreement.py --families 3dmatch --variants minmax first_float --held-out 1

Held-out clouds: the synthetic pairs `--held-out-from` .. of `--seed` (default pairs 2, 3, 4 of seed 1000;
pair 2 is quantize.py's held-out pair, pairs 0 and 1 its calibration pairs), at `--keypoints-3dmatch` /
`--keypoints-kitti` a cloud (400 FPS / 1,000 random: the counts of issue 50's "today" and of the held-out
check before). Each cloud's model inputs (the runtime's keypoints, patches and C++ pooling) are computed once
and kept in `.cache/spinnet_agreement/`; the float32 reference is the pooled float model (quantize.py's step
1, the shipped float32 model's outputs to 1e-5). Every variant is made from the pooled float model by
`quantize.py`'s `build` (calibrated on synthetic clouds only: `--seed`'s pairs 0 and 1, and for the larger
calibrations further pairs of seed `--seed + 1`; never a held-out pair, never a real one) and scored on the
held-out clouds against the float32 reference:

- `same_nearest_target`: the share of source keypoints whose nearest target descriptor (largest cosine) is
  the same for the variant as for float32 (quantize.py's check), pooled over the held-out pairs; also per pair
  and target -> source;
- `cosine_mean` / `cosine_min` of a keypoint's two descriptors;
- `network_s_a_keypoint`: the network alone on the same `--time-keypoints` inputs, batch 8, one onnxruntime
  thread, every variant once a round for `--time-rounds` rounds (side by side; the median).

Two rows are not INT8 models but the metric's noise floor: `float32_input_rounded` (float32 with only its
input rounded to the shipped INT8 model's input grid, the first thing INT8 does) and `float32_input_jitter`
(float32 with uniform noise of half that step added to its positive inputs, seeded).
"""

from __future__ import annotations

import argparse
import json
import os
import statistics
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

HERE = Path(__file__).resolve().parent
REPO = HERE.parents[1]
if str(REPO) not in sys.path:
    sys.path.insert(0, str(REPO))

from benchmarks.machine import cpu_model  # noqa: E402
from descriptors.buffer.quantize import synthetic_clouds  # noqa: E402
from descriptors.spinnet.quantize import (  # noqa: E402
    MODELS,
    VARIANTS,
    agreement,
    build,
    calibration_inputs,
    cloud_inputs,
    point_weights,
    pooled_model,
    session,
)
from fastmac_exp.descriptors.spinnet import SHIPPED, SHIPPED_INT8, SpinNetDescriptor  # noqa: E402

CACHE = REPO / ".cache" / "spinnet_agreement"
NOISE = ("float32_input_rounded", "float32_input_jitter")


def held_out_inputs(family: str, pairs: list, n: int, seed: int, weights: np.ndarray) -> list[tuple]:
    """Per held-out pair (source inputs, target inputs), memory-mapped from the cache."""
    out = []
    d = SpinNetDescriptor(threads=1, progress=False, keypoints=n, cache_clouds=0)
    for pair in pairs:
        both = []
        for side, cloud in (("src", pair.src_cloud), ("tgt", pair.tgt_cloud)):
            path = CACHE / f"{family}_s{seed}_{pair.meta['index']:03d}_{side}_{n}_v1.npy"
            if not path.exists():
                path.parent.mkdir(parents=True, exist_ok=True)
                part = path.with_suffix(".part.npy")
                np.save(part, cloud_inputs(d, family, cloud, pair.voxel_size, weights))
                os.replace(part, path)  # an interrupted run leaves no truncated cache
            both.append(np.load(path, mmap_mode="r"))
        out.append(tuple(both))
    return out


def run(sess, x: np.ndarray, batch: int = 8, divisors=None) -> np.ndarray:
    """Unit descriptors of the inputs `x` (divided by `divisors` per channel), `batch` keypoints a run."""
    name = sess.get_inputs()[0].name
    d = np.float32(1) if divisors is None else np.asarray(divisors, np.float32)
    rows = [
        sess.run(None, {name: np.ascontiguousarray(x[s : s + batch] / d)})[0] for s in range(0, len(x), batch)
    ]
    y = np.concatenate(rows).astype(np.float64)
    return (y / np.linalg.norm(y, axis=1, keepdims=True)).astype(np.float32)


def input_grid(family: str) -> tuple[float, int]:
    """The shipped INT8 model's input scale and zero point (its one QuantizeLinear)."""
    import onnx
    from onnx import numpy_helper as nh

    from fastmac_exp.descriptors.onnx_descriptor import resolve_model_path

    m = onnx.load(str(resolve_model_path(SHIPPED_INT8[family])))
    init = {t.name: nh.to_array(t) for t in m.graph.initializer}
    q = next(n for n in m.graph.node if n.op_type == "QuantizeLinear")
    return float(init[q.input[1]]), int(init[q.input[2]])


def perturbed(x: np.ndarray, bias: np.ndarray, how: str, scale: float, zero: int, rng) -> np.ndarray:
    """Pooled inputs whose model input relu(x + bias) is rounded to the INT8 input grid ("rounded") or
    jittered by up to half its step ("jitter"), returned as pooled inputs again (minus the bias)."""
    y = np.maximum(np.asarray(x, np.float32) + bias, 0)
    if how == "rounded":
        y = (np.clip(np.round(y / scale) + zero, 0, 255) - zero) * scale
    else:
        y = np.where(y > 0, np.maximum(y + rng.uniform(-scale / 2, scale / 2, y.shape), 0), 0)
    return (y - bias).astype(np.float32)


def score(ref: list[tuple], got: list[tuple]) -> dict:
    per_pair = [agreement(list(r), list(g)) for r, g in zip(ref, got, strict=True)]
    back = [
        agreement(list(r)[::-1], list(g)[::-1])["same_nearest_target"] for r, g in zip(ref, got, strict=True)
    ]
    src = sum(len(r[0]) for r in ref)
    cos = np.concatenate([(a * b).sum(1) for r, g in zip(ref, got, strict=True) for a, b in zip(r, g)])
    return {
        "same_nearest_target": round(
            sum(p["same_nearest_target"] * len(r[0]) for p, r in zip(per_pair, ref, strict=True)) / src, 4
        ),
        "same_nearest_target_per_pair": [p["same_nearest_target"] for p in per_pair],
        "same_nearest_source_per_pair": back,
        "cosine_mean": round(float(cos.mean()), 5),
        "cosine_min": round(float(cos.min()), 5),
        "source_keypoints": src,
    }


def main(argv: list[str] | None = None) -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--families", nargs="+", default=["3dmatch", "kitti"])
    ap.add_argument(
        "--variants", nargs="+", default=list(VARIANTS) + list(NOISE), help=f"of {list(VARIANTS)}"
    )
    ap.add_argument("--seed", type=int, default=1000)
    ap.add_argument("--held-out-from", type=int, default=2)
    ap.add_argument("--held-out", type=int, default=3, help="held-out pairs")
    ap.add_argument("--keypoints-3dmatch", type=int, default=400)
    ap.add_argument("--keypoints-kitti", type=int, default=1000)
    ap.add_argument("--time-keypoints", type=int, default=32)
    ap.add_argument("--time-rounds", type=int, default=3)
    ap.add_argument("--keep", type=Path, default=None, help="keep each variant's model in this folder")
    ap.add_argument("--json", type=Path, default=None)
    args = ap.parse_args(argv)
    unknown = [v for v in args.variants if v not in VARIANTS and v not in NOISE]
    if unknown:
        ap.error(f"unknown variants {unknown}; known: {list(VARIANTS) + list(NOISE)}")
    import onnxruntime as ort

    record = {
        "cpu": cpu_model(),
        "onnxruntime": ort.__version__,
        "load_average_at_start": round(os.getloadavg()[0], 2),
        "seed": args.seed,
        "held_out_pairs": list(range(args.held_out_from, args.held_out_from + args.held_out)),
        "families": {},
    }
    for family in args.families:
        n = getattr(args, f"keypoints_{family}")
        pairs = synthetic_clouds(family, args.held_out_from + args.held_out, args.seed)[args.held_out_from :]
        pooled = pooled_model(MODELS / Path(SHIPPED[family]).name)
        weights, bias = point_weights(pooled)
        held = held_out_inputs(family, pairs, n, args.seed, weights)
        ref_path = CACHE / f"{family}_s{args.seed}_{args.held_out_from}-{args.held_out}_{n}_float32_v1.npz"
        if ref_path.exists():
            z = np.load(ref_path)
            ref = [(z[f"{i}_src"], z[f"{i}_tgt"]) for i in range(len(held))]
        else:
            fl = session(pooled)
            ref = [(run(fl, s), run(fl, t)) for s, t in held]
            np.savez(
                ref_path, **{f"{i}_{k}": a for i, r in enumerate(ref) for k, a in zip(("src", "tgt"), r)}
            )
        calib_cache: dict = {}
        rows, sessions = {}, {}
        with tempfile.TemporaryDirectory() as tmp:
            for name in args.variants:
                t0 = time.perf_counter()
                if name in NOISE:
                    scale, zero = input_grid(family)
                    rng = np.random.default_rng(7)
                    how = name.rsplit("_", 1)[1]
                    fl = session(pooled)
                    got = [tuple(run(fl, perturbed(x, bias, how, scale, zero, rng)) for x in p) for p in held]
                    rows[name] = score(ref, got) | {"input_scale": scale}
                else:
                    spec = VARIANTS[name]
                    key = (spec.calib_pairs, spec.calib_keypoints)
                    if key not in calib_cache:
                        calib_cache[key] = calibration_inputs(family, spec, args.seed, weights)
                    dst = (args.keep or Path(tmp)) / f"spinnet_{family}_{name}.onnx"
                    dst.parent.mkdir(parents=True, exist_ok=True)
                    info = build(pooled, dst, calib_cache[key], spec, Path(tmp) / f"calib_{name}.json")
                    sessions[name] = session(dst)
                    div = info["input_divisors"]
                    got = [
                        (run(sessions[name], s, divisors=div), run(sessions[name], t, divisors=div))
                        for s, t in held
                    ]
                    rows[name] = score(ref, got) | info
                rows[name]["seconds_to_make_and_score"] = round(time.perf_counter() - t0, 1)
                print(family, name, json.dumps(rows[name]), flush=True)
            sessions = {"float32": session(pooled), **sessions}
            x = np.ascontiguousarray(held[0][0][: args.time_keypoints])
            times = {k: [] for k in sessions}
            for _ in range(args.time_rounds):
                for k, s in sessions.items():
                    t0 = time.perf_counter()
                    run(s, x)
                    times[k].append((time.perf_counter() - t0) / len(x))
            for k, v in times.items():
                rows.setdefault(k, {})["network_s_a_keypoint"] = round(statistics.median(v), 5)
            base = rows["float32"]["network_s_a_keypoint"]
            for k in times:
                rows[k]["network_x_float32"] = round(base / rows[k]["network_s_a_keypoint"], 2)
        record["families"][family] = {"keypoints_a_cloud": n, "rows": rows}
    record["load_average_at_end"] = round(os.getloadavg()[0], 2)
    print(json.dumps(record, indent=1))
    if args.json:
        args.json.write_text(json.dumps(record, indent=1) + "\n")


if __name__ == "__main__":
    main()
