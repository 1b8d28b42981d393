"""INT8 versions of the shipped SpinNet models (`descriptor.precision=int8`): the point MLP's product and max
moved into the C++ core, the convolutions quantised by onnxruntime, their requantisation fused.

    python descriptors/spinnet/quantize.py         # ~3 min; writes fastmac_exp/models/spinnet_*_int8.onnx

Per family, from the shipped float32 model `fastmac_exp/models/spinnet_<family>.onnx` (descriptors/spinnet/
export.py, from the published weights):

1. `pooled_model`: the graph from the max over each cell's samples on. In the float model the point MLP
   (cells x 30 samples x 3 -> 16, its bias, the max over the samples) was half of the time a keypoint (a
   (M, 864,000, 16) float32 tensor, written and read again); its bias commutes with the max, so the model now
   takes `(M, cells, 16)`, each cell's max of `slot @ W`, which the C++ core computes while grouping
   (`spinnet_pool_cells`, no grouped cells in memory), and adds the bias itself. `W` (3 x 16 float32) travels
   as the metadata `spinnet.point_weights` (JSON, exact), with `spinnet.input = pooled`;
2. onnxruntime's `quant_pre_process` -> `quantize_static` (QOperator, the Conv nodes only, weights int8 per
   output channel, activations uint8 per tensor, min-max calibration) on the pooled inputs of
   `--calib-keypoints` random keypoints of the source and target clouds of synthetic pairs of the family,
   generated with a seed no evaluation uses (`--seed`, default 1000; no real pair and no GT is used);
3. BUFFER's `fuse_requantize` (descriptors/buffer/quantize.py): the convolutions stay in uint8 from the first
   to the last, Relu, padding and the reshape between the 3-D and 2-D stacks included;
4. checked on keypoints of a further synthetic pair (not calibrated on): cosine of the int8 and float32
   descriptors and the share of source keypoints whose nearest target descriptor is unchanged.

`--format QDQ` writes the QDQ form instead (measured slower here, `quantize.json`). Record: `quantize.json`.
"""

from __future__ import annotations

import argparse
import json
import sys
import tempfile
from pathlib import Path

import numpy as np

HERE = Path(__file__).resolve().parent
REPO = HERE.parents[1]
if str(REPO) not in sys.path:
    sys.path.insert(0, str(REPO))

from descriptors.buffer.quantize import MOVES, drop_unused_initializers, quantize, sha256, synthetic_clouds  # noqa: E402
from fastmac_exp.descriptors.patches import keypoints  # noqa: E402
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


def model_inputs(family: str, clouds: list, n: int, seed: int, weights: np.ndarray) -> np.ndarray:
    """The pooled inputs `(k, cells, F)` of `n` random voxel keypoints of each cloud (the runtime's own
    preprocessing: SpinNetDescriptor's keypoints, patch cloud, patches and alignment)."""
    d = SpinNetDescriptor(threads=1, progress=False, cache_clouds=0)
    model = d.load(family)
    p = model.params
    rng = np.random.default_rng(seed)
    out = []
    for points, voxel in clouds:
        pts, kp = keypoints(points, voxel)
        scale = d.scale_for(model, voxel)
        state, _ = d._state(model, p.align, pts / scale, ("calibration",))
        rows = np.sort(rng.choice(len(kp), size=min(n, len(kp)), replace=False))
        out.append(pool_cells(d.patches(model, state, kp[rows] / scale, p.align), p, weights))
    return np.concatenate(out)


def check(family: str, pair) -> dict:
    """int8 against float32 on `keypoints` (the default count) of each cloud of one held-out pair."""
    import onnxruntime as ort

    feats = {}
    for precision in ("float32", "int8"):
        d = SpinNetDescriptor(threads=1, progress=False, precision=precision, cache_clouds=0)
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
    ap.add_argument("--calib-pairs", type=int, default=2)
    ap.add_argument("--calib-keypoints", type=int, default=32, help="per cloud")
    ap.add_argument("--format", choices=["QOperator", "QDQ"], default="QOperator")
    ap.add_argument("--out", default=str(MODELS))
    ap.add_argument("--json", default=str(HERE / "quantize.json"))
    args = ap.parse_args(argv)
    import onnx
    import onnxruntime as ort

    record = {"onnxruntime": ort.__version__, "seed": args.seed, "format": args.format, "families": {}}
    for family in args.families:
        src = MODELS / Path(SHIPPED[family]).name
        dst = Path(args.out) / (src.stem + "_int8.onnx")
        pairs = synthetic_clouds(family, args.calib_pairs + 1, args.seed)
        clouds = [(c, p.voxel_size) for p in pairs[:-1] for c in (p.src_cloud, p.tgt_cloud)]
        with tempfile.TemporaryDirectory() as tmp:
            pooled = Path(tmp) / "pooled.onnx"
            model = pooled_model(src)
            onnx.save(model, str(pooled))
            weights = np.asarray(
                json.loads({p.key: p.value for p in model.metadata_props}["spinnet.point_weights"]),
                np.float32,
            )
            calib = model_inputs(family, clouds, args.calib_keypoints, args.seed, weights)
            quantize(pooled, dst, calib, "pooled", moves=SPINNET_MOVES, quant_format=args.format)
        m = onnx.load(str(dst))  # the record names the shipped float model, not the temporary pooled one
        meta = {p.key: p.value for p in m.metadata_props}
        meta["fastmac.quantized_from_sha256"] = sha256(src)
        del m.metadata_props[:]
        for k, v in sorted(meta.items()):
            m.metadata_props.add(key=k, value=v)
        onnx.save(m, str(dst))
        rec = {
            "float_model": src.name,
            "float_sha256": sha256(src),
            "int8_model": dst.name,
            "int8_sha256": sha256(dst),
            "int8_bytes": dst.stat().st_size,
            "fused_chains": int(meta.get("fastmac.int8_fused_chains", 0)),
            "calibration": f"{len(calib)} keypoints, {len(clouds)} synthetic {family} clouds",
            "held_out": check(family, pairs[-1]) if dst.parent == MODELS else None,
        }
        record["families"][family] = rec
        print(family, json.dumps(rec), flush=True)
    Path(args.json).write_text(json.dumps(record, indent=1) + "\n")


if __name__ == "__main__":
    main()
