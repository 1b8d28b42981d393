"""INT8 versions of the shipped SpinNet models (`descriptor.precision=int8`): the point MLP's product and max
moved into the C++ core, the convolutions quantised by onnxruntime, their requantisation fused.

    python descriptors/spinnet/quantize.py         # ~5 min; writes fastmac_exp/models/spinnet_*_int8.onnx

Per family, from the shipped float32 model `fastmac_exp/models/spinnet_<family>.onnx` (descriptors/spinnet/
export.py, from the published weights):

1. `pooled_model`: the graph from the max over each cell's samples on. In the float model the point MLP
   (cells x 30 samples x 3 -> 16, its bias, the max over the samples) was half of the time a keypoint (a
   (M, 864,000, 16) float32 tensor, written and read again); its bias commutes with the max, so the model now
   takes `(M, cells, 16)`, each cell's max of `slot @ W`, which the C++ core computes while grouping
   (`spinnet_pool_cells`, no grouped cells in memory), and adds the bias itself. `W` (3 x 16 float32) travels
   as the metadata `spinnet.point_weights` (JSON, exact), with `spinnet.input = pooled`;
2. onnxruntime's `quant_pre_process` -> `quantize_static` (QOperator, the Conv nodes only, weights int8 per
   output channel, activations uint8 per tensor, min-max calibration) on the pooled inputs of 32 random
   keypoints of the source and target clouds of synthetic pairs 0 and 1 of the family, generated with a
   seed no evaluation uses (`--seed`, default 1000; no real pair and no GT is used); the convolutions of
   the variant's `float_convs` stay float32 (`--variant`, `VARIANTS`; the default `first_last4_float`
   keeps the first and the last four, which cost the most agreement and little time:
   descriptors/spinnet/agreement.py, MODEL_CARD.md);
3. BUFFER's `fuse_requantize` (descriptors/buffer/quantize.py): the quantised convolutions stay in uint8
   from one to the next, Relu, padding and the reshape between the 3-D and 2-D stacks included;
4. checked on CHECK_KEYPOINTS keypoints of each cloud of pair 2 (not calibrated on) through the front end:
   cosine of the int8 and float32 descriptors and the share of source keypoints whose nearest target
   descriptor is unchanged.

`--variant minmax` makes the models before (every convolution in uint8). Record: `quantize.json`.
"""

from __future__ import annotations

import argparse
import json
import sys
import tempfile
from dataclasses import asdict, dataclass
from pathlib import Path

import numpy as np

HERE = Path(__file__).resolve().parent
REPO = HERE.parents[1]
if str(REPO) not in sys.path:
    sys.path.insert(0, str(REPO))

from descriptors.buffer.quantize import MOVES, drop_unused_initializers, quantize, sha256, synthetic_clouds  # noqa: E402
from fastmac_exp.descriptors.spinnet import SHIPPED, SpinNetDescriptor, pool_cells  # noqa: E402

MODELS = REPO / "fastmac_exp" / "models"
SPINNET_MOVES = (*MOVES, "Reshape")  # the (M, C, 1, E, A) -> (M, C, E, A) reshape between the stacks


def pooled_model(src: Path):
    """The float model `src` from its max over the samples on (module docstring, step 1): input `pooled`
    `(M, cells, F)`; the shape computations on the batch size replaced by constants (Reshape's 0 copies M)."""
    import onnx
    from onnx import TensorProto, helper
    from onnx import numpy_helper as nh

    model = onnx.load(str(src))
    g = model.graph
    meta = {p.key: p.value for p in model.metadata_props}
    cells_in = g.input[0].name
    init = {t.name: t for t in g.initializer}
    matmul = next(n for n in g.node if n.op_type == "MatMul" and n.input[1] in init)
    add = next(n for n in g.node if n.op_type == "Add" and n.input[0] == matmul.output[0])
    pool = next(n for n in g.node if n.op_type == "ReduceMax" and n.input[0] == add.output[0])
    w = nh.to_array(init[matmul.input[1]]).astype(np.float32)
    b = nh.to_array(init[add.input[1]]).astype(np.float32).reshape(-1)
    rad, ele, azi = (int(meta[f"spinnet.{k}"]) for k in ("rad_n", "ele_n", "azi_n"))
    f = w.shape[1]
    g.initializer.append(nh.from_array(b, "pooled_bias"))
    biased = helper.make_node("Add", ["pooled", "pooled_bias"], ["pooled_biased"], name="pooled_bias_add")
    for n in g.node:
        for i, x in enumerate(n.input):
            if x == pool.output[0]:
                n.input[i] = biased.output[0]
    producer = {o: n for n in g.node for o in n.output}
    consts = []
    for n in g.node:  # the reshapes: shapes computed from the input's batch size -> constants
        if n.op_type != "Reshape":
            continue
        data = n.input[0]
        src_node = producer.get(data)
        if src_node is not None and src_node.op_type == "Transpose":  # (M, F, cells) -> (M, F, rad, ele, azi)
            shape = [0, f, rad, ele, azi]
        elif data == cells_in:
            continue  # the cells' reshape goes with the point MLP
        elif any(p.op_type == "ReduceMax" for p in [src_node] if p is not None):
            shape = [0, -1]  # the descriptors
        else:  # the 3-D stack's (M, C, 1, ele, azi) -> (M, C, ele, azi)
            conv3 = [t for t in g.initializer if t.name.endswith(".weight") and len(t.dims) == 5]
            shape = [0, int(conv3[-1].dims[0]), ele, azi]
        name = f"{n.output[0]}_shape"
        consts.append(nh.from_array(np.asarray(shape, np.int64), name))
        n.input[1] = name
    g.initializer.extend(consts)
    nodes = [biased, *g.node]
    needed, keep = {o.name for o in g.output}, []
    for n in reversed(nodes):  # what the outputs need, back from them
        if any(o in needed for o in n.output):
            keep.append(n)
            needed.update(n.input)
    keep.reverse()
    del g.node[:]
    g.node.extend(keep)
    drop_unused_initializers(g)
    del g.input[:]
    g.input.append(helper.make_tensor_value_info("pooled", TensorProto.FLOAT, ["M", rad * ele * azi, f]))
    del g.value_info[:]
    meta.update({"spinnet.input": "pooled", "spinnet.point_weights": json.dumps(w.tolist())})
    del model.metadata_props[:]
    for k, v in sorted(meta.items()):
        model.metadata_props.add(key=k, value=v)
    onnx.checker.check_model(model)
    return model


@dataclass(frozen=True)
class Variant:
    """One way of quantising the pooled float model (descriptors/spinnet/agreement.py scores them).
    `float_convs`: the convolutions (0..10, in graph order) left in float32; `calibrate`: onnxruntime's
    calibration method (MinMax, Percentile, Entropy, Distribution) and `percentile` for Percentile;
    `calib_pairs` synthetic pairs (the seed's pairs 0 and 1, then pairs of seed + 1) at `calib_keypoints`
    random keypoints a cloud; `format` QOperator (fused requantisation) or QDQ; `equalize`: the exponent
    of the per-channel activation equalisation (`equalize`; 0: none)."""

    float_convs: tuple[int, ...] = ()
    calibrate: str = "MinMax"
    percentile: float = 99.999
    calib_pairs: int = 2
    calib_keypoints: int = 32
    format: str = "QOperator"
    equalize: float = 0.0


CONVS = 11
VARIANTS = {
    "minmax": Variant(),  # the recipe before (issue 50's first INT8 models)
    **{f"only_conv{i}": Variant(float_convs=tuple(j for j in range(CONVS) if j != i)) for i in range(CONVS)},
    **{f"float_conv{i}": Variant(float_convs=(i,)) for i in range(CONVS)},
    "first_last_float": Variant(float_convs=(0, 10)),
    "last3_float": Variant(float_convs=(8, 9, 10)),
    "first_last3_float": Variant(float_convs=(0, 8, 9, 10)),
    "first2_last3_float": Variant(float_convs=(0, 1, 8, 9, 10)),
    "first_last4_float": Variant(float_convs=(0, 7, 8, 9, 10)),
    "first_last3_float_percentile": Variant(float_convs=(0, 8, 9, 10), calibrate="Percentile"),
    "first_last4_float_percentile": Variant(float_convs=(0, 7, 8, 9, 10), calibrate="Percentile"),
    "percentile_99.99": Variant(calibrate="Percentile", percentile=99.99),
    "percentile_99.999": Variant(calibrate="Percentile", percentile=99.999),
    "entropy": Variant(calibrate="Entropy"),
    "calib_x4": Variant(calib_pairs=4, calib_keypoints=64),
    "qdq": Variant(format="QDQ"),
    "equalized_0.5": Variant(equalize=0.5),
    "equalized_1": Variant(equalize=1.0),
    "last3_float_equalized_0.5": Variant(float_convs=(8, 9, 10), equalize=0.5),
    "last3_float_equalized_1": Variant(float_convs=(8, 9, 10), equalize=1.0),
    "last3_float_calib_x4": Variant(float_convs=(8, 9, 10), calib_pairs=4, calib_keypoints=64),
}
DEFAULT = "first_last4_float"


def session(model, threads: int = 1):
    """An onnxruntime CPU session of a model (path or ModelProto) on `threads` threads."""
    import onnxruntime as ort

    opts = ort.SessionOptions()
    opts.intra_op_num_threads = threads
    src = model.SerializeToString() if hasattr(model, "SerializeToString") else str(model)
    return ort.InferenceSession(src, opts, providers=["CPUExecutionProvider"])


def point_weights(pooled) -> tuple[np.ndarray, np.ndarray]:
    """The pooled model's point MLP product `W` (3, F) (metadata) and its bias (F,) (the first Add)."""
    from onnx import numpy_helper as nh

    meta = {p.key: p.value for p in pooled.metadata_props}
    bias = next(t for t in pooled.graph.initializer if t.name == "pooled_bias")
    return np.asarray(json.loads(meta["spinnet.point_weights"]), np.float32), nh.to_array(bias)


def cloud_inputs(d: SpinNetDescriptor, family: str, points: np.ndarray, voxel: float, weights, rows=None):
    """The pooled inputs `(k, cells, F)` of the keypoints `d` picks in a cloud (`rows` of them, or all), by
    the runtime's own preprocessing (its keypoints, patch cloud, patches and alignment)."""
    model = d.load(family)
    p = model.params
    pts, kp = d.keypoints(points, voxel, family=family)
    kp = kp if rows is None else kp[rows]
    scale = d.scale_for(model, voxel)
    state, _ = d._state(model, p.align, pts / scale, ("inputs",))
    out = [pool_cells(d.patches(model, state, kp[s : s + 8] / scale, p.align), p, weights) for s in
           range(0, len(kp), 8)]  # fmt: skip
    return np.concatenate(out) if out else np.zeros((0, p.cells, weights.shape[1]), np.float32)


def model_inputs(family: str, clouds: list, n: int, seed: int, weights: np.ndarray) -> np.ndarray:
    """The pooled inputs of `n` random voxel keypoints of each cloud (calibration)."""
    d = SpinNetDescriptor(threads=1, progress=False, cache_clouds=0, keypoints=0)
    rng = np.random.default_rng(seed)
    out = []
    for points, voxel in clouds:
        m = len(d.keypoints(points, voxel, family=family)[1])
        rows = np.sort(rng.choice(m, size=min(n, m), replace=False))
        out.append(cloud_inputs(d, family, points, voxel, weights, rows))
    return np.concatenate(out)


def calibration_inputs(family: str, spec: Variant, seed: int, weights: np.ndarray) -> np.ndarray:
    """`spec`'s calibration inputs: pairs 0 and 1 of `seed` (the pairs before the held-out ones), then
    pairs of `seed + 1`; synthetic only."""
    pairs = synthetic_clouds(family, min(spec.calib_pairs, 2), seed)
    if spec.calib_pairs > 2:
        pairs += synthetic_clouds(family, spec.calib_pairs - 2, seed + 1)
    clouds = [(c, p.voxel_size) for p in pairs for c in (p.src_cloud, p.tgt_cloud)]
    return model_inputs(family, clouds, spec.calib_keypoints, seed, weights)


EQUALIZED = 9  # the inputs of convolutions 0..8 (after them no Relu and, in the default, float32)


def activation_ranges(pooled, calib: np.ndarray) -> list[np.ndarray]:
    """Per channel the largest value of the inputs of the convolutions 0..EQUALIZED-1 (Relu outputs, padded)
    over the calibration inputs, float32 model."""
    import onnx

    m = onnx.ModelProto()
    m.CopyFrom(pooled)
    convs = [n for n in m.graph.node if n.op_type == "Conv"][:EQUALIZED]
    del m.graph.output[:]
    m.graph.output.extend(onnx.ValueInfoProto(name=c.input[0]) for c in convs)
    sess = session(m)
    top = [None] * len(convs)
    for s in range(0, len(calib), 8):
        for i, y in enumerate(sess.run(None, {"pooled": calib[s : s + 8]})):
            r = y.max(axis=tuple(a for a in range(y.ndim) if a != 1))
            top[i] = r if top[i] is None else np.maximum(top[i], r)
    return top


def equalize(pooled, calib: np.ndarray, alpha: float):
    """Per-channel activation equalisation of the pooled float model, exact in float: the quantised
    activations are per tensor, so a channel of small values gets few of its 256 steps. The channel c of
    the input of convolution k (k < EQUALIZED) is divided by s_c = (r_c / max r) ** alpha (r: its calibrated
    range), and the weights that read it (convolution k's input channel c) multiplied by s_c; the division
    goes into what makes the channel: convolution k-1's output channel c (weights and bias; its per-output-
    channel weight quantisation does not change) or, for k = 0, the point MLP's column c and bias (the C++
    pooling's max commutes with a positive scale), with the Relu, padding and reshape between commuting with
    it too. Returns the new model (the metadata's point weights changed) and the input's divisors."""
    import onnx
    from onnx import numpy_helper as nh

    m = onnx.ModelProto()
    m.CopyFrom(pooled)
    init = {t.name: t for t in m.graph.initializer}
    convs = [n for n in m.graph.node if n.op_type == "Conv"]
    arr = {name: nh.to_array(init[name]).astype(np.float64) for c in convs for name in c.input[1:3]}
    w_pt, b_pt = (x.astype(np.float64) for x in point_weights(m))
    first = None
    for k, r in enumerate(activation_ranges(pooled, calib)):
        s = np.where(r > 0, (r / r.max()) ** alpha, 1.0)
        arr[convs[k].input[1]] *= s.reshape(1, -1, *[1] * (arr[convs[k].input[1]].ndim - 2))
        if k == 0:
            w_pt, b_pt, first = w_pt / s, b_pt / s, s
        else:
            w, b = convs[k - 1].input[1:3]
            arr[w] /= s.reshape(-1, *[1] * (arr[w].ndim - 1))
            arr[b] /= s
    for name, a in arr.items():
        init[name].CopyFrom(nh.from_array(a.astype(np.float32), name))
    init["pooled_bias"].CopyFrom(nh.from_array(b_pt.astype(np.float32), "pooled_bias"))
    meta = {p.key: p.value for p in m.metadata_props}
    meta["spinnet.point_weights"] = json.dumps(w_pt.astype(np.float32).tolist())
    meta["fastmac.int8_equalized"] = str(alpha)
    del m.metadata_props[:]
    for k, v in sorted(meta.items()):
        m.metadata_props.add(key=k, value=v)
    onnx.checker.check_model(m)
    return m, first.astype(np.float32)


def build(pooled, dst: Path, calib: np.ndarray, spec: Variant, calib_cache: Path | None = None) -> dict:
    """`spec`'s INT8 model of the pooled float model (a ModelProto) into `dst`; what it is, with
    `input_divisors`: what the model's inputs are divided by against `pooled`'s (equalisation; 1 without)."""
    import onnx
    from onnxruntime.quantization import CalibrationMethod

    divisors = np.ones(point_weights(pooled)[0].shape[1], np.float32)
    if spec.equalize:
        pooled, divisors = equalize(pooled, calib, spec.equalize)
        calib = calib / divisors

    convs = [n.name for n in pooled.graph.node if n.op_type == "Conv"]
    if len(convs) != CONVS:
        raise ValueError(f"expected {CONVS} convolutions in the pooled model, found {len(convs)}")
    options = {"calibrate_method": getattr(CalibrationMethod, spec.calibrate)}
    if spec.calibrate == "Percentile":
        options["extra_options"] = {"CalibPercentile": spec.percentile}
    if spec.float_convs:
        options["nodes_to_exclude"] = [convs[i] for i in spec.float_convs]
    if calib_cache is not None:
        options["calibration_cache_path"] = str(calib_cache)
    with tempfile.TemporaryDirectory() as tmp:
        src = Path(tmp) / "pooled.onnx"
        onnx.save(pooled, str(src))
        quantize(src, dst, calib, "pooled", moves=SPINNET_MOVES, quant_format=spec.format, **options)
    ops = [n.op_type for n in onnx.load(str(dst)).graph.node]
    return {
        "ops": {k: ops.count(k) for k in ("QLinearConv", "Conv", "QuantizeLinear", "DequantizeLinear")},
        "float_convs": list(spec.float_convs),
        "calibration_keypoints": len(calib),
        "bytes": dst.stat().st_size,
        "input_divisors": divisors.tolist(),
    }


CHECK_KEYPOINTS = {"3dmatch": 400, "kitti": 1000}  # a cloud: the defaults before issue 50's INT8


def check(family: str, pair) -> dict:
    """The shipped int8 model against float32 through the front end, on CHECK_KEYPOINTS keypoints of each
    cloud of one held-out pair."""
    import onnxruntime as ort

    feats = {}
    for precision in ("float32", "int8"):
        d = SpinNetDescriptor(
            threads=1, progress=False, precision=precision, cache_clouds=0, keypoints=CHECK_KEYPOINTS[family]
        )
        feats[precision] = [
            d.features(c, pair.voxel_size, family=family)[1] for c in (pair.src_cloud, pair.tgt_cloud)
        ]
    return agreement(feats["float32"], feats["int8"]) | {"onnxruntime": ort.__version__}


def agreement(a: list[np.ndarray], b: list[np.ndarray]) -> dict:
    """Cosine of the unit descriptors row by row (both clouds) and the share of source rows whose nearest
    target row is the same for `a` (source, target) and `b`."""
    cos = np.concatenate([(x * y).sum(1) for x, y in zip(a, b, strict=True)])
    nn_a = np.argmax(a[0] @ a[1].T, axis=1)
    nn_b = np.argmax(b[0] @ b[1].T, axis=1)
    return {
        "keypoints": int(len(cos)),
        "cosine_mean": round(float(cos.mean()), 5),
        "cosine_min": round(float(cos.min()), 5),
        "same_nearest_target": round(float((nn_a == nn_b).mean()), 4),
    }


def main(argv: list[str] | None = None) -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--families", nargs="+", default=["3dmatch", "kitti"])
    ap.add_argument("--seed", type=int, default=1000, help="synthetic pairs' seed (no evaluation uses it)")
    ap.add_argument("--variant", choices=list(VARIANTS), default=DEFAULT, help="how (Variant, VARIANTS)")
    ap.add_argument("--out", default=str(MODELS))
    ap.add_argument("--json", default=str(HERE / "quantize.json"))
    args = ap.parse_args(argv)
    import onnx
    import onnxruntime as ort

    spec = VARIANTS[args.variant]
    record = {
        "onnxruntime": ort.__version__,
        "seed": args.seed,
        "variant": args.variant,
        "spec": asdict(spec),
        "families": {},
    }
    for family in args.families:
        src = MODELS / Path(SHIPPED[family]).name
        dst = Path(args.out) / (src.stem + "_int8.onnx")
        model = pooled_model(src)
        calib = calibration_inputs(family, spec, args.seed, point_weights(model)[0])
        info = build(model, dst, calib, spec)
        m = onnx.load(str(dst))  # the record names the shipped float model, not the temporary pooled one
        meta = {p.key: p.value for p in m.metadata_props}
        meta["fastmac.quantized_from_sha256"] = sha256(src)
        meta["fastmac.int8_variant"] = args.variant
        del m.metadata_props[:]
        for k, v in sorted(meta.items()):
            m.metadata_props.add(key=k, value=v)
        onnx.save(m, str(dst))
        held_out = synthetic_clouds(family, 3, args.seed)[2]  # after the two calibration pairs
        rec = {
            "float_model": src.name,
            "float_sha256": sha256(src),
            "int8_model": dst.name,
            "int8_sha256": sha256(dst),
            "int8_bytes": dst.stat().st_size,
            "fused_chains": int(meta.get("fastmac.int8_fused_chains", 0)),
            "ops": info["ops"],
            "calibration": f"{len(calib)} keypoints, {2 * spec.calib_pairs} synthetic {family} clouds",
            "held_out": check(family, held_out) if dst.parent == MODELS else None,
        }
        record["families"][family] = rec
        print(family, json.dumps(rec), flush=True)
    Path(args.json).write_text(json.dumps(record, indent=1) + "\n")


if __name__ == "__main__":
    main()
