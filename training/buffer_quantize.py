"""INT8 versions of the shipped BUFFER Desc models (`descriptor.precision=int8`), by onnxruntime's static
quantisation of the 3-D/2-D convolutions.

    PYTHONPATH=. python -m training.buffer_quantize           # ~2 min; writes fastmac_exp/models/*_int8.onnx

Per family: the float32 Desc model `fastmac_exp/models/buffer_<family>_desc.onnx` -> onnxruntime's
`quant_pre_process` -> `quantize_static` (QOperator format, the Conv nodes only, weights int8 per output
channel, activations uint8 per tensor, min-max calibration) on the model inputs of `--calib-keypoints`
random keypoints of the source and target clouds of synthetic pairs of that family generated with a seed
that no evaluation uses (`--seed`, default 1000; no real pair and no GT is used) -> the float model's
metadata copied over, plus `fastmac.precision = int8` and the float model's sha256. The point MLP, the
attention pool and the normalisation stay float32. Checked on keypoints of a further synthetic pair
(not calibrated on): cosine of the int8 and float32 descriptors, and the share of keypoints whose
nearest float32 descriptor (among the pair's other cloud's) is unchanged. Record: `buffer_quantize.json`.
"""

from __future__ import annotations

import argparse
import hashlib
import json
import sys
import tempfile
from pathlib import Path

import numpy as np

REPO = Path(__file__).resolve().parent.parent
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


def quantize(src: Path, dst: Path, calib: np.ndarray, input_name: str) -> None:
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
            quant_format=QuantFormat.QOperator,
            op_types_to_quantize=["Conv"],
            per_channel=True,
            activation_type=QuantType.QUInt8,
            weight_type=QuantType.QInt8,
        )
    meta = {p.key: p.value for p in onnx.load(str(src)).metadata_props}
    meta.update({"fastmac.precision": "int8", "fastmac.quantized_from_sha256": sha256(src)})
    model = onnx.load(str(dst))
    del model.metadata_props[:]
    for k, v in sorted(meta.items()):
        model.metadata_props.add(key=k, value=v)
    onnx.save(model, str(dst))


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


def main(argv: list[str] | None = None) -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--families", nargs="+", default=["3dmatch", "kitti"])
    ap.add_argument("--seed", type=int, default=1000, help="synthetic pairs' seed (no evaluation uses it)")
    ap.add_argument("--calib-pairs", type=int, default=2)
    ap.add_argument("--calib-keypoints", type=int, default=128, help="per cloud")
    ap.add_argument("--out", default=str(MODELS))
    ap.add_argument("--json", default=str(REPO / "training" / "buffer_quantize.json"))
    args = ap.parse_args(argv)
    import onnxruntime as ort

    record = {"onnxruntime": ort.__version__, "seed": args.seed, "families": {}}
    for family in args.families:
        src = MODELS / Path(SHIPPED[family]).name
        dst = Path(args.out) / (src.stem + "_int8.onnx")
        pairs = synthetic_clouds(family, args.calib_pairs + 1, args.seed)
        clouds = [(c, p.voxel_size) for p in pairs[:-1] for c in (p.src_cloud, p.tgt_cloud)]
        calib = model_inputs(family, clouds, args.calib_keypoints, args.seed)
        name = BufferDescriptor(progress=False).model_for(family).input_name
        quantize(src, dst, calib, name)
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
