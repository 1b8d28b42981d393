"""Convert BUFFER's published weights into the shipped ONNX models and check the conversion.

    cd /work/main && python descriptors/buffer/export.py          # ~1 min, 1 thread
    python descriptors/buffer/export.py --weights /path/to/buffer --out /tmp/buffer

Reads `<weights>/{3dmatch,kitti}/{Ref,Desc}_best.pth` (default `<repo>/../shared/models/buffer`, BUFFER's
files from aosheng1996/BUFFER@6f905699, see its README and descriptors/buffer/MODEL_CARD.md) and writes

- `buffer_3dmatch_ref.onnx`: the Ref network (`Ref.*` of 3dmatch/Ref_best.pth);
- `buffer_3dmatch_desc.onnx`: the Desc network (`Desc.*` of 3dmatch/Desc_best.pth), axis-aligned patches;
- `buffer_kitti_desc.onnx`: the KITTI Desc network (`Desc.*` of kitti/Desc_best.pth); upstream keeps the
  LiDAR's z axis for KITTI, so no Ref model is needed (kitti/Ref_best.pth is checked, not exported);
- `export.json` (beside this script): checksums of every input and output, the neighbour limits, the
  checks' numbers.

Steps: load the tensors into descriptors/buffer/nets.py's reference modules with strict=True (no missing
or unexpected key) -> calibrate the Ref's neighbour limits with upstream's rule (calibrate_neighbors:
per layer the 80th percentile of the neighbour counts, counts of 34 = ceil(4/3 pi 2^3) and more left out)
on the 3DMatch fragment redkitchen cloud_bin_0 (the first fragment of upstream's first test pair; its
partner cloud_bin_1 is not available here) or take them from --limits -> fold into the export modules
-> torch.onnx.export (opset 17, every point count dynamic) -> onnxruntime against the reference modules
on fixed inputs (real patches and graphs of that fragment when it is there, seeded random ones
otherwise): the script fails when the largest difference exceeds --tolerance (1e-4).
"""

from __future__ import annotations

import argparse
import hashlib
import json
import sys
import time
from pathlib import Path

import numpy as np

HERE = Path(__file__).resolve().parent
REPO = HERE.parents[1]
if str(REPO) not in sys.path:
    sys.path.insert(0, str(REPO))

import torch  # noqa: E402

from descriptors.buffer.nets import (  # noqa: E402
    DescExport,
    DescReference,
    RefExport,
    RefReference,
    load_published,
)
from fastmac_exp.descriptors.buffer import (  # noqa: E402
    REF_INPUTS,
    BufferParams,
    align_rotations,
    cut_patches,
    grid_subsample,
    group_cells,
    oriented_normals,
    radius_neighbors,
    ref_inputs,
)

UPSTREAM = "aosheng1996/BUFFER"
UPSTREAM_COMMIT = "6f905699b9b187c52eafcda0b95a283d6b52b9b2"
SHARED_WEIGHTS = REPO.parent / "shared" / "models" / "buffer"
CALIB_CLOUD = REPO.parent / "shared" / "data" / "teaser_3dmatch_redkitchen" / "cloud_bin_0.ply"
# the limits the shipped model was exported with (what --calib-cloud gives; used when it is absent)
SHIPPED_LIMITS = (19, 18, 20)
OPSET = 17
LICENCE = (
    "research use only: BUFFER (Ao et al., CVPR 2023), weights from aosheng1996/BUFFER (MIT LICENSE file; "
    "the README shows CC BY-NC-SA 4.0); credit the paper"
)
PARAMS = {
    "3dmatch": BufferParams(
        family="3dmatch",
        align="ref",
        reference_voxel=0.05,
        downsample=0.02,
        voxel_size_0=0.035,
        max_points=30000,
        des_r=0.3,
        ref_model="buffer_3dmatch_ref.onnx",
    ),
    "kitti": BufferParams(
        family="kitti",
        align="none",
        reference_voxel=0.3,
        downsample=0.05,
        voxel_size_0=0.3,
        max_points=40000,
        des_r=3.0,
        ref_model="",
    ),
}
CONV_RADIUS = 2.0
HIST_N = int(np.ceil(4 / 3 * np.pi * CONV_RADIUS**3))  # 34


def sha256(path: Path) -> str:
    return hashlib.sha256(Path(path).read_bytes()).hexdigest()


def load_cloud(path: Path) -> np.ndarray:
    from fastmac_exp.io import read_points

    return np.asarray(read_points(path), dtype=np.float64)


def ref_cloud(points: np.ndarray, params: BufferParams, seed: int = 0) -> tuple[np.ndarray, np.ndarray]:
    """Upstream's test-time preprocessing: 0.02 m grid, shuffled, 0.035 m grid, shuffled, capped."""
    from fastmac_exp.descriptors.patches import voxel_down

    rng = np.random.default_rng(seed)
    cloud = voxel_down(points, params.downsample)
    cloud = cloud[rng.permutation(len(cloud))]
    pts = voxel_down(cloud, params.voxel_size_0)
    pts = pts[rng.permutation(len(pts))][: params.max_points]
    return cloud, pts


def calibrate_limits(pts: np.ndarray, voxel0: float, keep_ratio: float = 0.8) -> tuple[int, int, int]:
    """Upstream calibrate_neighbors on one cloud: per layer, the number of bins of the neighbour-count
    histogram (counts 0..33, neighbours truncated at 34) whose cumulative count stays below keep_ratio."""
    r0 = voxel0 * CONV_RADIUS
    layers = [pts]
    layers.append(grid_subsample(layers[0], 2 * r0 / CONV_RADIUS))
    layers.append(grid_subsample(layers[1], 4 * r0 / CONV_RADIUS))
    out = []
    for i, p in enumerate(layers):
        nb = radius_neighbors(p, p, r0 * 2**i, HIST_N)
        counts = (nb < len(p)).sum(axis=1)
        hist = np.bincount(counts, minlength=HIST_N)[:HIST_N]
        cum = np.cumsum(hist)
        out.append(int(np.sum(cum < keep_ratio * cum[-1])))
    return tuple(out)


def _export(module: torch.nn.Module, args: tuple, path: Path, names_in, names_out, dynamic) -> None:
    module.eval()
    with torch.no_grad():
        torch.onnx.export(
            module,
            args,
            str(path),
            input_names=list(names_in),
            output_names=list(names_out),
            dynamic_axes=dynamic,
            opset_version=OPSET,
            do_constant_folding=True,
            dynamo=False,
        )


def _set_metadata(path: Path, meta: dict, doc: str) -> None:
    import onnx

    model = onnx.load(str(path))
    del model.metadata_props[:]
    for k, v in meta.items():
        model.metadata_props.add(key=k, value=str(v))
    model.doc_string = doc
    onnx.checker.check_model(model)
    onnx.save(model, str(path))


def _ort(path: Path):
    import onnxruntime as ort

    opts = ort.SessionOptions()
    opts.intra_op_num_threads = 1
    return ort.InferenceSession(str(path), opts, providers=["CPUExecutionProvider"])


def fixed_patches(cloud, pts, params: BufferParams, axes=None, n: int = 96, seed: int = 1) -> np.ndarray:
    """Grouped Desc inputs for `n` keypoints of a real cloud (aligned by `axes` when given)."""
    from scipy.spatial import cKDTree

    rng = np.random.default_rng(seed)
    pick = rng.choice(len(pts), size=min(n, len(pts)), replace=False)
    kp = pts[pick]
    patch = cut_patches(cloud, cKDTree(cloud), kp, params.des_r, params.patch_points) - kp[:, None, :]
    if axes is not None:
        patch = patch @ align_rotations(axes[pick])
    return group_cells(patch / params.des_r, params)


def golden_grouped(n: int = 8, size: int = 4200, seed: int = 7) -> np.ndarray:
    """Fixed Desc inputs from PCG64's uniform doubles only (a stream numpy keeps stable): points in
    [-1, 1]^3, a fifth of the slots empty (0)."""
    u = np.random.default_rng(seed).random((n, size, 4))
    x = u[..., :3] * 2 - 1
    x[u[..., 3] < 0.2] = 0
    return x.astype(np.float32)


def golden_cloud(seed: int = 11) -> tuple[np.ndarray, np.ndarray]:
    """Fixed Ref input cloud: a room corner seen from the origin (floor z = -1.2, walls x = 2.0 and
    y = 1.6, a 0.5 m box on the floor), ~2 cm spacing, with exact normals facing the origin."""
    u = np.random.default_rng(seed).random((4, 6000, 2))
    floor = np.stack([0.8 + 1.2 * u[0, :, 0], -0.4 + 2.0 * u[0, :, 1], np.full(6000, -1.2)], 1)
    wall_x = np.stack([np.full(6000, 2.0), -0.4 + 2.0 * u[1, :, 0], -1.2 + 1.5 * u[1, :, 1]], 1)
    wall_y = np.stack([0.8 + 1.2 * u[2, :, 0], np.full(6000, 1.6), -1.2 + 1.5 * u[2, :, 1]], 1)
    top = np.stack([1.2 + 0.5 * u[3, :1500, 0], 0.3 + 0.5 * u[3, :1500, 1], np.full(1500, -0.7)], 1)
    side = np.stack([np.full(1500, 1.2), 0.3 + 0.5 * u[3, 1500:3000, 0], -1.2 + 0.5 * u[3, 1500:3000, 1]], 1)
    pts = np.concatenate([floor, wall_x, wall_y, top, side])
    normals = np.concatenate(
        [np.tile(n, (len(b), 1)) for n, b in zip([[0, 0, 1], [-1, 0, 0], [0, -1, 0], [0, 0, 1], [-1, 0, 0]],
                                                 [floor, wall_x, wall_y, top, side], strict=True)]
    ).astype(np.float64)  # fmt: skip
    return pts, normals


def random_grouped(n: int, params: BufferParams, seed: int = 2) -> np.ndarray:
    """Seeded random Desc inputs: points in the unit ball, 20 % empty slots."""
    rng = np.random.default_rng(seed)
    x = rng.normal(size=(n, params.size, 3))
    x *= (rng.uniform(0, 1, (n, params.size, 1)) ** (1 / 3)) / np.linalg.norm(x, axis=2, keepdims=True)
    x[rng.uniform(size=(n, params.size)) < 0.2] = 0
    return x.astype(np.float32)


def ref_batch_reference(feed: dict, pts: np.ndarray, voxel0: float, limits) -> dict:
    """The reference module's inputs for the same cloud: full upsample matrices (only column 0 is used)."""
    r0 = voxel0 * CONV_RADIUS
    p = [feed[f"points{i}"].astype(np.float64) for i in range(3)]
    ups = [torch.from_numpy(radius_neighbors(p[i], p[i + 1], 2 * r0 * 2**i, limits[i])) for i in range(2)]
    return {
        "normals": torch.from_numpy(feed["normals"]),
        "points": [torch.from_numpy(feed[f"points{i}"]) for i in range(3)],
        "neighbors": [torch.from_numpy(feed[f"neighbors{i}"]) for i in range(3)],
        "pools": [torch.from_numpy(feed[f"pools{i}"]) for i in range(2)],
        "upsamples": ups,
    }


def export_family(family: str, weights: Path, out: Path, calib: Path | None, limits, tol: float) -> dict:
    params = PARAMS[family]
    rec: dict = {"family": family, "params": params.__dict__.copy()}
    desc_pth = weights / family / "Desc_best.pth"
    ref_pth = weights / family / "Ref_best.pth"
    rec["inputs"] = {str(p.relative_to(weights)): sha256(p) for p in (ref_pth, desc_pth)}
    desc_ref = DescReference()
    rec["desc_load"] = load_published(desc_ref, desc_pth, "Desc")
    ref_ref = RefReference()
    rec["ref_load"] = load_published(ref_ref, ref_pth, "Ref")  # loads for KITTI too (not exported)
    desc_ref.eval()
    ref_ref.eval()
    cloud = pts = None
    if calib is not None and calib.is_file():
        cloud, pts = ref_cloud(load_cloud(calib), params)
        rec["calibration_cloud"] = {"file": calib.name, "sha256": sha256(calib), "ref_points": len(pts)}
    provenance = {
        "buffer.source": f"{UPSTREAM}@{UPSTREAM_COMMIT}",
        "buffer.licence": LICENCE,
        "buffer.paper": "Ao, Hu, Wang, Xu, Guo: BUFFER, CVPR 2023",
    }
    axes = None
    if params.align == "ref":
        if limits is None:
            if pts is None:
                print(f"no calibration cloud ({calib}): using the shipped limits {SHIPPED_LIMITS}")
                limits = SHIPPED_LIMITS
            else:
                limits = calibrate_limits(pts, params.voxel_size_0)
        rec["neighbor_limits"] = list(limits)
        ref_path = out / params.ref_model
        exp = RefExport(ref_ref).eval()
        if pts is None:  # no real fragment: trace and check on the synthetic corner
            pts = golden_cloud()[0]
        feed = ref_inputs(pts, oriented_normals(pts), params.voxel_size_0, CONV_RADIUS, limits)
        names = [n for n, _, _ in REF_INPUTS]
        dyn = {n: {d: f"{n}_{d}" for d in range(r)} for n, _, r in REF_INPUTS}
        dyn["axis"] = {0: "N0"}
        _export(exp, tuple(torch.from_numpy(feed[n]) for n in names), ref_path, names, ["axis"], dyn)
        meta = dict(provenance)
        meta.update(
            {
                "buffer.neighbor_limits": ",".join(str(v) for v in limits),
                "buffer.conv_radius": CONV_RADIUS,
                "buffer.voxel_size_0": params.voxel_size_0,
                "buffer.source_file": f"ThreeDMatch/snapshot/06132318/Ref/best.pth ({sha256(ref_pth)[:16]})",
            }
        )
        _set_metadata(
            ref_path, meta, "BUFFER Ref (reference-axis network), 3DMatch weights, fastmac-exp export"
        )
        got = _ort(ref_path).run(None, feed)[0]
        with torch.no_grad():
            want = ref_ref(ref_batch_reference(feed, pts, params.voxel_size_0, limits)).numpy()
            want_exp = exp(*(torch.from_numpy(feed[n]) for n in names)).numpy()
        nw = want / np.linalg.norm(want, axis=1, keepdims=True)
        ng = got / np.linalg.norm(got, axis=1, keepdims=True)
        rec["ref_check"] = {
            "points": len(pts),
            "max_abs_diff_raw": float(np.abs(got - want).max()),
            "max_abs_diff_export_vs_reference": float(np.abs(want_exp - want).max()),
            "max_abs_diff_unit_axis": float(np.abs(ng - nw).max()),
            "raw_norm_median": float(np.median(np.linalg.norm(want, axis=1))),
        }
        rec["ref_onnx"] = {
            "file": ref_path.name,
            "sha256": sha256(ref_path),
            "bytes": ref_path.stat().st_size,
        }
        if rec["ref_check"]["max_abs_diff_unit_axis"] > tol:
            raise SystemExit(f"Ref: onnxruntime differs from the torch reference by {rec['ref_check']}")
        gp, gn = golden_cloud()
        gfeed = ref_inputs(gp, gn, params.voxel_size_0, CONV_RADIUS, limits)
        with torch.no_grad():
            gwant = ref_ref(ref_batch_reference(gfeed, gp, params.voxel_size_0, limits)).numpy()
        ggot = _ort(ref_path).run(None, gfeed)[0]
        rec["ref_check"]["golden_max_abs_diff"] = float(np.abs(ggot - gwant).max())
        rec["golden_ref"] = {"cloud_seed": 11, "points": len(gp), "first_axes": gwant[:64].round(6).tolist()}
        axes = nw.copy()
        flip = np.einsum("ij,ij->i", axes, pts) > 0
        axes[flip] *= -1
    desc_path = out / f"buffer_{family}_desc.onnx"
    exp_d = DescExport(desc_ref).eval()
    dummy = torch.from_numpy(random_grouped(2, params))
    _export(
        exp_d,
        (dummy,),
        desc_path,
        ["grouped"],
        ["descriptors"],
        {"grouped": {0: "M"}, "descriptors": {0: "M"}},
    )
    meta = {"fastmac.preprocess": "buffer"}
    meta.update({f"buffer.{k}": v for k, v in params.__dict__.items()})
    meta.update(provenance)
    snap = {"3dmatch": "ThreeDMatch/snapshot/06132318", "kitti": "KITTI/snapshot/06050001"}[family]
    meta["buffer.source_file"] = f"{snap}/Desc/best.pth ({sha256(desc_pth)[:16]})"
    _set_metadata(
        desc_path, meta, f"BUFFER Desc (cylindrical patch descriptor), {family} weights, fastmac-exp export"
    )
    sess = _ort(desc_path)
    checks = {"random": random_grouped(128, params)}
    if cloud is not None:
        checks["real_patches"] = fixed_patches(cloud, pts, params, axes)
    checks["golden"] = golden_grouped()
    rec["desc_check"] = {}
    for name, x in checks.items():
        got = sess.run(None, {"grouped": x})[0]
        with torch.no_grad():
            want = desc_ref(torch.from_numpy(x)).numpy()
        rec["desc_check"][name] = {"patches": len(x), "max_abs_diff": float(np.abs(got - want).max())}
        if rec["desc_check"][name]["max_abs_diff"] > tol:
            raise SystemExit(
                f"Desc {family}: onnxruntime differs from the torch reference: {rec['desc_check']}"
            )
        if name == "golden":
            rec["golden_desc"] = {"seed": 7, "n": len(x), "outputs": want.round(7).tolist()}
    rec["desc_onnx"] = {
        "file": desc_path.name,
        "sha256": sha256(desc_path),
        "bytes": desc_path.stat().st_size,
    }
    return rec


def main(argv: list[str] | None = None) -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--weights", default=str(SHARED_WEIGHTS))
    ap.add_argument("--out", default=str(REPO / "fastmac_exp" / "models"))
    ap.add_argument("--families", nargs="+", default=["3dmatch", "kitti"], choices=sorted(PARAMS))
    ap.add_argument("--calib-cloud", default=str(CALIB_CLOUD))
    ap.add_argument("--limits", default=None, help="Ref neighbour limits a,b,c instead of calibrating")
    ap.add_argument("--tolerance", type=float, default=1e-4)
    args = ap.parse_args(argv)
    torch.set_num_threads(1)
    weights, out = Path(args.weights), Path(args.out)
    if not (weights / "3dmatch" / "Desc_best.pth").is_file():
        raise SystemExit(f"BUFFER weights not found under {weights} (expected 3dmatch/Desc_best.pth ...)")
    out.mkdir(parents=True, exist_ok=True)
    limits = tuple(int(v) for v in args.limits.split(",")) if args.limits else None
    calib = Path(args.calib_cloud) if args.calib_cloud else None
    t0 = time.perf_counter()
    record = {
        "upstream": f"{UPSTREAM}@{UPSTREAM_COMMIT}",
        "torch": torch.__version__,
        "opset": OPSET,
        "families": {},
    }
    import onnx
    import onnxruntime

    record["onnx"], record["onnxruntime"] = onnx.__version__, onnxruntime.__version__
    for fam in args.families:
        record["families"][fam] = export_family(fam, weights, out, calib, limits, args.tolerance)
        print(json.dumps(record["families"][fam], indent=1, default=str))
    record["seconds"] = round(time.perf_counter() - t0, 1)
    records = HERE if out.resolve() == (REPO / "fastmac_exp" / "models").resolve() else out
    (records / "export.json").write_text(json.dumps(record, indent=1, default=str) + "\n")
    names = ", ".join(sorted(p.name for p in out.glob("buffer_*.onnx")))
    print(f"wrote {names} in {out} ({record['seconds']} s)")


if __name__ == "__main__":
    main()
