"""Convert SpinNet's published weights into the shipped ONNX models and check the conversion.

    cd /work/main && python descriptors/spinnet/export.py            # ~2 min, 1 thread
    python descriptors/spinnet/export.py --weights /path/to/spinnet --out /tmp/spinnet

Reads `<weights>/{3DMatch,KITTI}_best.pkl` (default `<repo>/../shared/models/spinnet`, copied from
QingyongHu/SpinNet@5581e7d1, see its README and descriptors/spinnet/MODEL_CARD.md) and writes
`spinnet_3dmatch.onnx`, `spinnet_kitti.onnx` (into fastmac_exp/models/) and `descriptors/spinnet/export.json`
(checksums, parameters, the checks' numbers).

Steps: load each state dict into descriptors/spinnet/nets.py's `SpinNetReference` with strict=True -> fold
into `SpinNetExport` -> torch.onnx.export (opset 17, the keypoint count dynamic) -> checks on real patches
(redkitchen cloud_bin_0 for 3DMatch, KITTI 00 frame 94 for KITTI; seeded random patches when absent):
(a) the C++ grouping (`spinnet_group_cells`) against the torch brute-force ball query (equal), (b) the
runtime path (C++ grouping + onnxruntime + L2 norm) against the plain torch forward of the published
weights (`SpinNetReference.forward_aligned`, unfolded BatchNorm, upstream's masks and padding); the script
fails when the largest descriptor difference exceeds --tolerance (1e-5).
"""

from __future__ import annotations

import argparse
import hashlib
import json
import sys
import time
from dataclasses import asdict
from pathlib import Path

import numpy as np

HERE = Path(__file__).resolve().parent
REPO = HERE.parents[1]
if str(REPO) not in sys.path:
    sys.path.insert(0, str(REPO))

import torch  # noqa: E402

from descriptors.spinnet.nets import SpinNetExport, SpinNetReference, load_published, patch_flops  # noqa: E402
from fastmac_exp.descriptors.spinnet import SpinNetParams, grid_for, group_cells  # noqa: E402

UPSTREAM = "QingyongHu/SpinNet"
UPSTREAM_COMMIT = "5581e7d184bc3b4d525d5b5e58777ea04dfdc9ab"
SHARED = REPO.parent / "shared"
SHARED_WEIGHTS = SHARED / "models" / "spinnet"
OPSET = 17
LICENCE = (
    "research use only: SpinNet (Ao, Hu, Yang, Markham, Guo, CVPR 2021), weights from QingyongHu/SpinNet "
    "(MIT LICENSE file; the README shows CC BY-NC-SA 4.0); credit the paper"
)
PARAMS = {
    "3dmatch": SpinNetParams(family="3dmatch", align="pca", reference_voxel=0.05, downsample=0.01, des_r=0.3,
                             rad_n=9, ele_n=40, azi_n=80, voxel_r=0.04, samples=30, patch_points=2048),
    "kitti": SpinNetParams(family="kitti", align="none", reference_voxel=0.3, downsample=0.0, des_r=2.0,
                           rad_n=9, ele_n=30, azi_n=60, voxel_r=0.3, samples=30, patch_points=2048),
}  # fmt: skip
FILES = {"3dmatch": "3DMatch_best.pkl", "kitti": "KITTI_best.pkl"}
CHECK_CLOUDS = {
    "3dmatch": SHARED / "data" / "teaser_3dmatch_redkitchen" / "cloud_bin_0.ply",
    "kitti": SHARED / "data" / "kitti_seq00_scancontext" / "000094.bin",
}


def sha256(path: Path) -> str:
    return hashlib.sha256(Path(path).read_bytes()).hexdigest()


def reference(family: str, weights: Path) -> tuple[SpinNetReference, dict]:
    p = PARAMS[family]
    ref = SpinNetReference(p.des_r, p.rad_n, p.azi_n, p.ele_n, p.voxel_r, p.samples).eval()
    return ref, load_published(ref, weights / FILES[family])


def check_patches(family: str, n: int = 6, seed: int = 3) -> tuple[np.ndarray, str]:
    """Aligned patches `(n, 2048, 3)` float32 of `n` keypoints of a real cloud through the runtime's own
    preprocessing (SpinNetDescriptor.patches), or seeded random ones when the cloud is absent."""
    p = PARAMS[family]
    path = CHECK_CLOUDS[family]
    if path.exists():
        from fastmac_exp.descriptors.patches import keypoints
        from fastmac_exp.descriptors.spinnet import SpinNetDescriptor
        from fastmac_exp.io import read_points

        pts = np.asarray(read_points(path), dtype=np.float64)
        d = SpinNetDescriptor(progress=False)

        class _M:  # the preprocessing needs the parameters only
            params = p

        state, _ = d._state(_M, p.align, pts, ("check",))
        _, kp = keypoints(pts, p.reference_voxel)
        kp = kp[np.random.default_rng(seed).choice(len(kp), n, replace=False)]
        return d.patches(_M, state, kp, p.align).astype(np.float32), path.name
    rng = np.random.default_rng(seed)
    pts = rng.normal(size=(n, p.patch_points, 3)) * p.des_r / 3
    pts = pts / np.maximum(1.0, np.linalg.norm(pts, axis=2, keepdims=True) / p.des_r)
    pts[:, -1] = 0
    return pts.astype(np.float32), "random"


def export_family(family: str, weights: Path, out: Path, tol: float) -> dict:
    import onnxruntime as ort

    p = PARAMS[family]
    ref, loaded = reference(family, weights)
    exp = SpinNetExport(ref).eval()
    path = out / f"spinnet_{family}.onnx"
    dummy = torch.zeros(2, p.size, 3)
    with torch.no_grad():
        torch.onnx.export(exp, (dummy,), str(path), input_names=["cells"], output_names=["descriptors"],
                          dynamic_axes={"cells": {0: "M"}, "descriptors": {0: "M"}}, opset_version=OPSET,
                          do_constant_folding=True, dynamo=False)  # fmt: skip
    import onnx

    model = onnx.load(str(path))
    src = f"pre-trained_models/{FILES[family]} ({sha256(weights / FILES[family])[:16]})"
    meta = {"fastmac.preprocess": "spinnet", "fastmac.name": "spinnet", "fastmac.precision": "float32",
            "fastmac.licence": LICENCE, "spinnet.upstream": f"{UPSTREAM}@{UPSTREAM_COMMIT[:8]}",
            "spinnet.source_file": src}  # fmt: skip
    meta.update({f"spinnet.{k}": v for k, v in asdict(p).items()})
    del model.metadata_props[:]
    for k, v in meta.items():
        model.metadata_props.add(key=k, value=str(v))
    model.doc_string = f"SpinNet descriptor ({family} weights), converted by descriptors/spinnet/export.py"
    onnx.checker.check_model(model)
    onnx.save(model, str(path))

    aligned, cloud = check_patches(family)
    grid_for(p)  # the one-off candidate-cell table, outside the timing (the stored JSON predates this line)
    t0 = time.perf_counter()
    cells = group_cells(aligned, p)
    t_group = (time.perf_counter() - t0) / len(aligned)
    with torch.no_grad():
        ref_cells = ref.group(torch.from_numpy(aligned)).numpy()
        t0 = time.perf_counter()
        want = ref.forward_cells(torch.from_numpy(ref_cells)).numpy()
        t_torch = (time.perf_counter() - t0) / len(aligned)
    want = want / np.linalg.norm(want, axis=1, keepdims=True)
    opts = ort.SessionOptions()
    opts.intra_op_num_threads = 1
    sess = ort.InferenceSession(str(path), opts, providers=["CPUExecutionProvider"])
    sess.run(None, {"cells": cells[:1]})
    t0 = time.perf_counter()
    got = sess.run(None, {"cells": cells})[0]
    t_ort = (time.perf_counter() - t0) / len(aligned)
    got = got / np.linalg.norm(got, axis=1, keepdims=True)
    diff = float(np.abs(got - want).max())
    cells_diff = float(np.abs(cells - ref_cells).max())
    rec = {
        "weights": {"file": FILES[family], "sha256": sha256(weights / FILES[family]), **loaded},
        "params": asdict(p),
        "onnx": {"file": path.name, "sha256": sha256(path), "bytes": path.stat().st_size, "opset": OPSET},
        "check": {
            "cloud": cloud,
            "keypoints": len(aligned),
            "grouping_max_abs_diff_cpp_vs_torch": cells_diff,
            "descriptor_max_abs_diff_onnx_vs_torch": diff,
            "tolerance": tol,
        },
        "seconds_per_keypoint_1_thread_loaded": {
            "grouping_cpp": t_group,
            "torch_reference": t_torch,
            "onnxruntime": t_ort,
        },  # fmt: skip
        "network_gmac_per_keypoint": patch_flops(asdict(p)) / 1e9,
    }
    if diff > tol or cells_diff > 1e-6:
        raise SystemExit(f"{family}: ONNX vs torch {diff:.3g} (cells {cells_diff:.3g}) exceeds the tolerance")
    return rec


def main(argv: list[str] | None = None) -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--weights", type=Path, default=SHARED_WEIGHTS)
    ap.add_argument("--out", type=Path, default=REPO / "fastmac_exp" / "models")
    ap.add_argument("--records", type=Path, default=HERE)
    ap.add_argument("--tolerance", type=float, default=1e-5)
    ap.add_argument("--family", choices=sorted(PARAMS), action="append")
    args = ap.parse_args(argv)
    torch.set_num_threads(1)
    args.out.mkdir(parents=True, exist_ok=True)
    record = {"upstream": f"{UPSTREAM}@{UPSTREAM_COMMIT}", "licence": LICENCE, "families": {}}
    for fam in args.family or sorted(PARAMS):
        record["families"][fam] = export_family(fam, args.weights, args.out, args.tolerance)
        print(json.dumps(record["families"][fam], indent=1, default=str))
    (args.records / "export.json").write_text(json.dumps(record, indent=1, default=str) + "\n")


if __name__ == "__main__":
    main()
