"""INT8 versions of the shipped BUFFER Desc models (`descriptor.precision=int8`), by onnxruntime's static
quantisation of the 3-D/2-D convolutions.

    python descriptors/buffer/quantize.py           # ~2 min; writes fastmac_exp/models/*_int8.onnx

Per family: the float32 Desc model `fastmac_exp/models/buffer_<family>_desc.onnx` -> onnxruntime's
`quant_pre_process` -> `quantize_static` (QOperator format, the Conv nodes only, weights int8 per output
channel, activations uint8 per tensor, min-max calibration) on the model inputs of `--calib-keypoints`
random keypoints of the source and target clouds of synthetic pairs of that family generated with a seed
that no evaluation uses (`--seed`, default 1000; no real pair and no GT is used) -> the float model's
metadata copied over, plus `fastmac.precision = int8` and the float model's sha256. The point MLP, the
attention pool and the normalisation stay float32. Checked on keypoints of a further synthetic pair
(not calibrated on): cosine of the int8 and float32 descriptors, and the share of keypoints whose
nearest float32 descriptor (among the pair's other cloud's) is unchanged.
Record: `quantize.json` beside this script.
"""

from __future__ import annotations

import argparse
import hashlib
import json
import sys
import tempfile
from pathlib import Path

import numpy as np

HERE = Path(__file__).resolve().parent
REPO = HERE.parents[1]
if str(REPO) not in sys.path:
    sys.path.insert(0, str(REPO))

from fastmac_exp.descriptors.buffer import SHIPPED, BufferDescriptor  # noqa: E402
from fastmac_exp.descriptors.patches import keypoints  # noqa: E402

MODELS = REPO / "fastmac_exp" / "models"


def sha256(path: Path) -> str:
    return hashlib.sha256(path.read_bytes()).hexdigest()


class _Recorder:
    """Stands in for the Desc session: records the model inputs, returns the float model's outputs."""

    def __init__(self, sess) -> None:
        self.sess, self.inputs = sess, []

    def run(self, names, feed):
        self.inputs.append(next(iter(feed.values())))
        return self.sess.run(names, feed)


def model_inputs(family: str, clouds: list[tuple[np.ndarray, float]], n: int, seed: int) -> np.ndarray:
    """The Desc inputs `(k, 4200, 3)` of `n` random keypoints of each cloud."""
    d = BufferDescriptor(threads=1, progress=False, cache_clouds=0)
    model = d.model_for(family)
    rec = _Recorder(model.desc)
    model.desc = rec
    rng = np.random.default_rng(seed)
    for points, voxel in clouds:
        pts, kp = keypoints(points, voxel)
        rows = np.sort(rng.choice(len(kp), size=min(n, len(kp)), replace=False))
        d.describe(model, pts, kp, voxel / model.params.reference_voxel, rows=rows)
    return np.concatenate(rec.inputs)


def synthetic_clouds(family: str, pairs: int, seed: int) -> list:
    from fastmac_exp.datasets.synthetic import SyntheticDataset

    ds = SyntheticDataset(
        family=family, num_pairs=pairs, seed=seed, cache_dir=str(REPO / ".cache" / "synthetic")
    )
    return [ds.load(i) for i in range(pairs)]


def quantize(
    src: Path,
    dst: Path,
    calib: np.ndarray,
    input_name: str,
    fuse: bool = True,
    moves: tuple[str, ...] | None = None,
    source: Path | None = None,
    quant_format: str = "QOperator",
    **options,
) -> None:
    """`src` quantised into `dst` (module docstring), the metadata of `source` (default `src`: the float
    model the int8 one stands for) copied with its sha256. `moves`: the data-movement ops fuse_requantize
    may look through (None: MOVES); `quant_format` "QOperator" or "QDQ" (no fusing: onnxruntime fuses a
    QDQ graph itself); `options` go to quantize_static (e.g. nodes_to_exclude)."""
    import onnx
    from onnxruntime.quantization import CalibrationDataReader, QuantFormat, QuantType, quantize_static
    from onnxruntime.quantization.shape_inference import quant_pre_process

    class Reader(CalibrationDataReader):
        def __init__(self) -> None:
            self.i = 0

        def get_next(self):
            if self.i >= len(calib):
                return None
            batch = calib[self.i : self.i + 64]
            self.i += 64
            return {input_name: batch}

    with tempfile.TemporaryDirectory() as tmp:
        pre = Path(tmp) / "pre.onnx"
        quant_pre_process(str(src), str(pre))
        quantize_static(
            str(pre),
            str(dst),
            Reader(),
            quant_format=getattr(QuantFormat, quant_format),
            op_types_to_quantize=["Conv"],
            per_channel=True,
            activation_type=QuantType.QUInt8,
            weight_type=QuantType.QInt8,
            **options,
        )
    source = src if source is None else source
    meta = {p.key: p.value for p in onnx.load(str(source)).metadata_props}
    meta.update({"fastmac.precision": "int8", "fastmac.quantized_from_sha256": sha256(source)})
    model = onnx.load(str(dst))
    if fuse and quant_format == "QOperator":
        meta["fastmac.int8_fused_chains"] = str(fuse_requantize(model, MOVES if moves is None else moves))
        onnx.checker.check_model(model)
    del model.metadata_props[:]
    for k, v in sorted(meta.items()):
        model.metadata_props.add(key=k, value=v)
    onnx.save(model, str(dst))


MOVES = ("Slice", "Concat")  # data movement: commutes with an elementwise (de)quantisation


def fuse_requantize(model, moves: tuple[str, ...] = MOVES):
    """Keeps the convolution stack in uint8 (issue 31): onnxruntime's QOperator quantisation leaves each
    `QLinearConv -> DequantizeLinear -> Relu -> Slice / Concat (the azimuth's circular padding) ->
    QuantizeLinear -> QLinearConv` in float32 between the convolutions. Where the QuantizeLinear's zero
    point is 0 (it was calibrated on the Relu's non-negative output), the convolution is given that
    QuantizeLinear's scale and zero point instead: its saturation at 0 is the Relu, the padding copies
    uint8, and the DequantizeLinear, Relu and QuantizeLinear go. A chain without the Relu (SpinNet's last
    convolutions) is fused whatever the zero point: the QuantizeLinear's rounding and saturation are the
    convolution's own. The padding of the first convolution's float input is quantised before it instead
    of after (the same values). The convolutions' weights and activation scales are the calibrated ones;
    each output is rounded once, at the finer post-Relu scale, instead of twice. `moves`: the data-movement
    ops looked through (SpinNet adds its Reshape). Returns how many chains were rewritten; the model is
    changed in place."""
    from onnx import helper
    from onnx import numpy_helper as nh

    g = model.graph
    init = {t.name: t for t in g.initializer}
    names = set()
    for i, n in enumerate(g.node):  # nodes are told apart by name below
        if not n.name or n.name in names:
            n.name = f"{n.op_type}_{i}_{n.output[0]}"
        names.add(n.name)

    def consumers(name):
        return [n for n in g.node if name in n.input]

    def producer(name):
        return next((n for n in g.node if name in n.output), None)

    def rename(old, new):
        for n in consumers(old):
            for i, x in enumerate(n.input):
                if x == old:
                    n.input[i] = new

    def moves_to_one_q(start):
        """The Slice / Concat nodes from `start` to exactly one QuantizeLinear (and it), or None."""
        frontier, seen, qs = [start], {}, {}
        while frontier:
            for n in consumers(frontier.pop()):
                if n.op_type in moves:
                    if n.name not in seen:
                        seen[n.name] = n
                        frontier.append(n.output[0])
                elif n.op_type == "QuantizeLinear":
                    qs[n.name] = n
                else:
                    return None
        return (list(seen.values()), next(iter(qs.values()))) if len(qs) == 1 else None

    gone, fused = set(), 0
    for conv in list(g.node):
        if conv.op_type != "QLinearConv":
            continue
        (dq, *more) = consumers(conv.output[0]) or [None]
        if dq is None or more or dq.op_type != "DequantizeLinear":
            continue
        (relu, *more) = consumers(dq.output[0]) or [None]
        if relu is None or more or relu.op_type != "Relu":
            relu = None  # the no-Relu chain: the DequantizeLinear straight into the padding
        start = dq.output[0] if relu is None else relu.output[0]
        found = moves_to_one_q(start)
        if found is None or (relu is not None and int(nh.to_array(init[found[1].input[2]])) != 0):
            continue
        _, q = found
        conv.input[6], conv.input[7] = q.input[1], q.input[2]  # y_scale, y_zero_point
        rename(start, conv.output[0])
        rename(q.output[0], conv.output[0] if q.input[0] == start else q.input[0])
        gone.update(n.name for n in (dq, relu, q) if n is not None)
        fused += 1
    nodes = [n for n in g.node if n.name not in gone]
    # the first convolution's input: float -> Slice / Concat -> Quantize becomes Quantize -> Slice / Concat
    for q in nodes:
        pad = producer(q.input[0]) if q.op_type == "QuantizeLinear" else None
        if pad is None or pad.op_type != "Concat":
            continue
        roots, stack = set(), [pad]
        while stack:  # back over the padding to the float tensors it copies
            n = stack.pop()
            for x in n.input if n.op_type == "Concat" else n.input[:1]:
                p = producer(x)
                if p is not None and p.op_type in moves:
                    stack.append(p)
                else:
                    roots.add(x)
        if len(roots) != 1:
            continue
        root = roots.pop()
        found = moves_to_one_q(root)
        if found is None or found[1].name != q.name:
            continue
        early = helper.make_node("QuantizeLinear", [root, q.input[1], q.input[2]], [root + "_quantized"])
        early.name = root + "_QuantizeLinear"
        for n in found[0]:
            for i, x in enumerate(n.input):
                if x == root and (n.op_type == "Concat" or i == 0):
                    n.input[i] = early.output[0]
        rename(q.output[0], q.input[0])
        at = next((i + 1 for i, n in enumerate(nodes) if root in n.output), 0)  # 0: a graph input
        nodes = [*nodes[:at], early, *[n for n in nodes[at:] if n.name != q.name]]
        fused += 1
        break
    del g.node[:]
    g.node.extend(nodes)
    drop_unused_initializers(g)
    del g.value_info[:]  # types changed from float to uint8 along the padding; onnxruntime infers them
    return fused


def drop_unused_initializers(g) -> None:
    """Remove the graph's initializers that no node reads (left over after nodes were removed)."""
    used = {x for n in g.node for x in n.input}
    keep = [t for t in g.initializer if t.name in used]
    del g.initializer[:]
    g.initializer.extend(keep)


def check(family: str, dst: Path, pair) -> dict:
    """int8 against float32 on the keypoints of one held-out pair."""
    import onnxruntime as ort

    fl = BufferDescriptor(threads=1, progress=False)
    q = BufferDescriptor(threads=1, progress=False, precision="int8")
    assert q.model_for(family).desc_path == dst
    out = {}
    feats = {}
    for name, d in (("float32", fl), ("int8", q)):
        feats[name] = [
            d.features(c, pair.voxel_size, family=family, scale=1.0)[1][:1500]
            for c in (pair.src_cloud, pair.tgt_cloud)
        ]
    cos = np.concatenate([(a * b).sum(1) for a, b in zip(feats["float32"], feats["int8"], strict=True)])
    nn_f = np.argmax(feats["float32"][0] @ feats["float32"][1].T, axis=1)
    nn_q = np.argmax(feats["int8"][0] @ feats["int8"][1].T, axis=1)
    out["keypoints"] = int(len(cos))
    out["cosine_mean"] = round(float(cos.mean()), 5)
    out["cosine_min"] = round(float(cos.min()), 5)
    out["same_nearest_target"] = round(float((nn_f == nn_q).mean()), 4)
    out["onnxruntime"] = ort.__version__
    return out


def fuse_shipped(args) -> None:
    """fuse_requantize on the shipped int8 models, in place: the same weights and calibrated scales; the
    record keeps its calibration and gains the unfused model's sha256 and a new held-out check."""
    import onnx

    path = Path(args.json)
    record = json.loads(path.read_text())
    for family in args.families:
        rec = record["families"][family]
        dst = MODELS / rec["int8_model"]
        model = onnx.load(str(dst))
        meta = {p.key: p.value for p in model.metadata_props}
        if "fastmac.int8_fused_chains" in meta:
            print(family, "already fused")
            continue
        unfused = sha256(dst)
        meta["fastmac.int8_fused_chains"] = str(fuse_requantize(model))
        meta["fastmac.int8_fused_from_sha256"] = unfused
        del model.metadata_props[:]
        for k, v in sorted(meta.items()):
            model.metadata_props.add(key=k, value=v)
        onnx.checker.check_model(model)
        onnx.save(model, str(dst))
        pairs = synthetic_clouds(family, args.calib_pairs + 1, args.seed)
        rec.update(
            {
                "int8_unfused_sha256": unfused,
                "int8_sha256": sha256(dst),
                "int8_bytes": dst.stat().st_size,
                "fused_chains": int(meta["fastmac.int8_fused_chains"]),
                "held_out_unfused": rec.get("held_out"),
                "held_out": check(family, dst, pairs[-1]),
            }
        )
        print(family, json.dumps(rec), flush=True)
    path.write_text(json.dumps(record, indent=1) + "\n")


def main(argv: list[str] | None = None) -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--families", nargs="+", default=["3dmatch", "kitti"])
    ap.add_argument("--seed", type=int, default=1000, help="synthetic pairs' seed (no evaluation uses it)")
    ap.add_argument("--calib-pairs", type=int, default=2)
    ap.add_argument("--calib-keypoints", type=int, default=128, help="per cloud")
    ap.add_argument("--out", default=str(MODELS))
    ap.add_argument("--json", default=str(HERE / "quantize.json"))
    ap.add_argument(
        "--fuse-shipped",
        action="store_true",
        help="only apply fuse_requantize to the shipped int8 models (same calibration) and update the record",
    )
    ap.add_argument("--no-fuse", action="store_true", help="leave the float32 chains between convolutions")
    args = ap.parse_args(argv)
    import onnxruntime as ort

    if args.fuse_shipped:
        fuse_shipped(args)
        return
    record = {"onnxruntime": ort.__version__, "seed": args.seed, "families": {}}
    for family in args.families:
        src = MODELS / Path(SHIPPED[family]).name
        dst = Path(args.out) / (src.stem + "_int8.onnx")
        pairs = synthetic_clouds(family, args.calib_pairs + 1, args.seed)
        clouds = [(c, p.voxel_size) for p in pairs[:-1] for c in (p.src_cloud, p.tgt_cloud)]
        calib = model_inputs(family, clouds, args.calib_keypoints, args.seed)
        name = BufferDescriptor(progress=False).model_for(family).input_name
        quantize(src, dst, calib, name, fuse=not args.no_fuse)
        rec = {
            "float_model": src.name,
            "float_sha256": sha256(src),
            "int8_model": dst.name,
            "int8_sha256": sha256(dst),
            "int8_bytes": dst.stat().st_size,
            "calibration": f"{len(calib)} keypoints, {len(clouds)} synthetic {family} clouds",
            "held_out": check(family, dst, pairs[-1]) if dst.parent == MODELS else None,
        }
        record["families"][family] = rec
        print(family, json.dumps(rec), flush=True)
    Path(args.json).write_text(json.dumps(record, indent=1) + "\n")


if __name__ == "__main__":
    main()
