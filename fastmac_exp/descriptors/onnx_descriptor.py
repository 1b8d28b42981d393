"""Learned-descriptor front end: multi-scale local patches in a local reference frame (LRF), embedded by
an ONNX model (the shipped `descriptors/fcgf_lite.onnx`, a small network trained here, not the published
FCGF; its model card is descriptors/MODEL_CARD.md). BUFFER's published models have their own front end
(fastmac_exp/descriptors/buffer.py, `descriptor=buffer`).

Runtime path: numpy/scipy preprocessing + onnxruntime inference; torch is never imported here (the
training recipe `descriptors/train.py` imports this preprocessing, so training and runtime cannot drift).

Preprocessing of one cloud (lengths in metres; `voxel` = the pair's voxel size unless configured):

1. keypoints: Open3D voxel downsampling at `voxel` (exactly the FPFH front end's keypoints);
2. per scale s (shipped model: s=0 with K=64, R=6 voxel on the cloud at 1 voxel, i.e. the keypoints
   themselves; s=1 with K=48, R=12 voxel on the cloud at 2.5 voxel): the K nearest support points of each
   keypoint within R; empty slots repeat the nearest point (duplicates do not change a max-pool);
3. LRF per scale (numpy, before the network): z = smallest eigenvector of the patch covariance weighted
   by R - d, signed so that the patch lies mostly below the keypoint (sum w p.z <= 0); x = the TOLDI
   direction, the tangent-plane projections weighted by (R - d)^2 (p.z)^2 (fallback: the largest
   eigenvector, signed by the weighted majority of projections); y = z cross x;
4. per point features (features="lrf_n"): x, y, z of the point relative to the keypoint in the LRF,
   divided by R (so inside the unit ball, unitless); |n.z| and |n.r| where n is the point's unoriented
   normal (10 nearest support points) and r the unit radial direction in the tangent plane (sign-free,
   in [0, 1]); with two scales, a last channel holding the scale index s (0. or 1.).

Model contract (checked when the model is opened; a model that does not fit raises InputError naming
what was expected and what was found):

- exactly one input, float32, rank 3, `(M, K, C)`: M = number of keypoints (dynamic), K = points per
  patch over all scales (64 + 48 = 112 for the shipped model), C = channels (5 + 1 = 6);
  K and C may be fixed in the graph (then they must match) or dynamic;
- exactly one output, float32, rank 2, `(M, D)`: D = 32 for the shipped model; rows unit-norm (the
  runtime re-normalises defensively).

The preprocessing parameters travel in the model's `metadata_props` (`fastmac.k`, `fastmac.radius_factor`,
`fastmac.support_factor`, `fastmac.features`, `fastmac.k2`, `fastmac.radius_factor2`,
`fastmac.support_factor2`); missing keys take the PatchParams defaults; constructor arguments override.
"""

from __future__ import annotations

import logging
import os
from dataclasses import dataclass
from pathlib import Path

import numpy as np
from scipy.spatial import cKDTree

from fastmac_exp.descriptors.base import FeatureDescriptor
from fastmac_exp.descriptors.matching import correspondences_from_features
from fastmac_exp.errors import InputError
from fastmac_exp.types import Correspondences, Pair

log = logging.getLogger(__name__)

DEFAULT_MODEL = "descriptors/fcgf_lite.onnx"
MIN_POINTS = 10
META_PREFIX = "fastmac."


# ----------------------------------------------------------------------------------------------------
# preprocessing (numpy / scipy; shared with the training recipe)


@dataclass(frozen=True)
class PatchParams:
    """How patches are cut (lengths are factors of the voxel size).

    Scale 1: the `k` nearest points of the cloud downsampled at `support_factor * voxel`, within
    R1 = `radius_factor * voxel`. Scale 2 (when `k2 > 0`): `k2` points of the cloud at
    `support_factor2 * voxel` within R2 = `radius_factor2 * voxel`, and a scale-flag channel.
    """

    k: int = 64
    radius_factor: float = 6.0
    support_factor: float = 1.0
    features: str = "lrf_n"
    k2: int = 48
    radius_factor2: float = 12.0
    support_factor2: float = 2.5

    def __post_init__(self) -> None:
        if self.features not in FEATURES:
            raise InputError(f"patch features must be one of {sorted(FEATURES)}, got {self.features!r}")
        if self.k < 4 or not (self.k2 == 0 or self.k2 >= 4):
            raise InputError(f"patch sizes must be at least 4 (k2 = 0: one scale), got {self.k}, {self.k2}")
        factors = (self.radius_factor, self.support_factor, self.radius_factor2, self.support_factor2)
        if not all(f > 0 for f in factors):
            raise InputError(f"radius and support factors must be positive, got {factors}")

    @property
    def size(self) -> int:
        """K of the model input: points per patch over all scales."""
        return self.k + self.k2

    @property
    def channels(self) -> int:
        """C of the model input."""
        return FEATURES[self.features] + (1 if self.k2 else 0)

    def scales(self) -> list[tuple[int, float, float]]:
        """(k, radius_factor, support_factor) per scale."""
        out = [(self.k, self.radius_factor, self.support_factor)]
        if self.k2:
            out.append((self.k2, self.radius_factor2, self.support_factor2))
        return out


def voxel_down(points: np.ndarray, voxel: float) -> np.ndarray:
    """Open3D voxel downsampling (centroid per voxel), the FPFH front end's keypoints."""
    from fastmac_exp._open3d import o3d

    pcd = o3d.geometry.PointCloud(o3d.utility.Vector3dVector(np.ascontiguousarray(points, dtype=np.float64)))
    return np.asarray(pcd.voxel_down_sample(float(voxel)).points, dtype=np.float64)


def clean_points(points: np.ndarray, what: str = "cloud") -> np.ndarray:
    pts = np.asarray(points, dtype=np.float64)
    if pts.ndim != 2 or pts.shape[1] != 3:
        raise InputError(f"{what} must have shape (N, 3), got {pts.shape}")
    return pts[np.isfinite(pts).all(axis=1)]


def local_frames(local: np.ndarray, valid: np.ndarray, radius: float) -> np.ndarray:
    """LRFs of patches: `local (M, K, 3)` offsets, `valid (M, K)` -> `(M, 3, 3)`, rows x y z."""
    d = np.linalg.norm(local, axis=2)
    w = np.where(valid, np.clip(radius - d, 0.0, None), 0.0)  # (M, K)
    wsum = w.sum(axis=1)
    wsum = np.where(wsum > 0, wsum, 1.0)
    cov = np.matmul((local * w[:, :, None]).transpose(0, 2, 1), local) / wsum[:, None, None]
    _, vecs = np.linalg.eigh(cov)  # ascending eigenvalues; columns are eigenvectors
    z = vecs[:, :, 0]
    h = np.matmul(local, z[:, :, None])[:, :, 0]
    flip = (w * h).sum(axis=1) > 0  # patch should lie below the keypoint: sum w p.z <= 0
    z = np.where(flip[:, None], -z, z)
    h = np.where(flip[:, None], -h, h)
    tang = local - h[:, :, None] * z[:, None, :]
    wx = w * w * h * h
    x = np.matmul(wx[:, None, :], tang)[:, 0, :]
    nx = np.linalg.norm(x, axis=1)
    # fallback: largest eigenvector, signed by the majority of projections
    e = vecs[:, :, 2]
    s = (w * np.sign(np.matmul(local, e[:, :, None])[:, :, 0])).sum(axis=1)
    e = np.where((s < 0)[:, None], -e, e)
    scale = np.sqrt(np.einsum("mk,mk->m", wx, np.einsum("mki,mki->mk", tang, tang))) + 1e-12
    weak = nx < 1e-3 * scale + 1e-12
    x = np.where(weak[:, None], e, x / np.where(nx > 0, nx, 1.0)[:, None])
    # re-orthogonalise x against z, then y = z x x
    x = x - np.einsum("mi,mi->m", x, z)[:, None] * z
    x /= np.linalg.norm(x, axis=1, keepdims=True) + 1e-12
    y = np.cross(z, x)
    return np.stack([x, y, z], axis=1)


def point_normals(points: np.ndarray, k: int = 10, tree: cKDTree | None = None) -> np.ndarray:
    """Unoriented unit normals (smallest covariance eigenvector of the k nearest points), `(N, 3)`."""
    tree = tree if tree is not None else cKDTree(points)
    k = min(k, len(points))
    _, idx = tree.query(points, k=k)
    nb = points[idx.reshape(len(points), -1)]
    nb = nb - nb.mean(axis=1, keepdims=True)
    cov = np.matmul(nb.transpose(0, 2, 1), nb)
    return np.linalg.eigh(cov)[1][:, :, 0]


FEATURES = {"lrf": 3, "lrf_n": 5, "cyl": 4}


def scale_patches(
    keypoints: np.ndarray,
    support: np.ndarray,
    radius: float,
    k: int,
    features: str,
    tree: cKDTree | None = None,
    normals: np.ndarray | None = None,
) -> np.ndarray:
    """One scale's patches: `(M, k, FEATURES[features])` float32 (see the module docstring)."""
    kp = np.asarray(keypoints, dtype=np.float64)
    if len(kp) == 0:
        return np.zeros((0, k, FEATURES[features]), dtype=np.float32)
    tree = tree if tree is not None else cKDTree(support)
    kk = min(k, len(support))
    dist, idx = tree.query(kp, k=kk, distance_upper_bound=radius)
    if kk == 1:
        dist, idx = dist[:, None], idx[:, None]
    valid = np.isfinite(dist)
    valid[:, 0] = True  # the nearest support point (the keypoint's own voxel) always counts
    idx = np.where(valid, idx, idx[:, :1])  # pad with the nearest point: a max-pool ignores duplicates
    if kk < k:  # tiny clouds
        idx = np.concatenate([idx, np.repeat(idx[:, :1], k - kk, axis=1)], axis=1)
        valid = np.concatenate([valid, np.zeros((len(kp), k - kk), dtype=bool)], axis=1)
    local = support[idx] - kp[:, None, :]
    frames = local_frames(local, valid, radius)
    xyz = np.matmul(local, frames.transpose(0, 2, 1)) / radius
    if features == "lrf":
        return xyz.astype(np.float32)
    if normals is None:
        normals = point_normals(support, tree=tree)
    n = np.matmul(normals[idx], frames.transpose(0, 2, 1))  # neighbour normals in the LRF (unsigned)
    rho = np.sqrt(xyz[:, :, 0] ** 2 + xyz[:, :, 1] ** 2)
    nz = np.abs(n[:, :, 2])
    nr = np.abs(n[:, :, 0] * xyz[:, :, 0] + n[:, :, 1] * xyz[:, :, 1]) / np.maximum(rho, 1e-9)
    nr = np.where(rho > 1e-9, nr, 0.0)
    if features == "lrf_n":
        return np.concatenate([xyz, nz[..., None], nr[..., None]], axis=2).astype(np.float32)
    return np.stack([rho, xyz[:, :, 2], nz, nr], axis=2).astype(np.float32)


def extract_patches(
    keypoints: np.ndarray, supports: list[np.ndarray], voxel: float, params: PatchParams
) -> np.ndarray:
    """Model input `(M, params.size, params.channels)` float32 for `keypoints`; one support cloud a scale."""
    parts = []
    for s, ((k, rf, _), support) in enumerate(zip(params.scales(), supports, strict=True)):
        x = scale_patches(keypoints, support, rf * voxel, k, params.features)
        if params.k2:
            x = np.concatenate([x, np.full(x.shape[:2] + (1,), float(s), dtype=np.float32)], axis=2)
        parts.append(x)
    return np.concatenate(parts, axis=1)


def support_clouds(points: np.ndarray, keypoints: np.ndarray, voxel: float, params: PatchParams) -> list:
    """The support cloud of each scale (the keypoints themselves where the support factor is 1)."""
    return [keypoints if sf == 1.0 else voxel_down(points, sf * voxel) for _, _, sf in params.scales()]


def cloud_patches(
    points: np.ndarray, voxel: float, params: PatchParams, what: str = "cloud"
) -> tuple[np.ndarray, np.ndarray]:
    """Keypoints `(M, 3)` float64 and their model input `(M, K, C)` float32 for one cloud."""
    if voxel is None or not voxel > 0:
        raise InputError(f"descriptor voxel size must be positive, got {voxel}")
    pts = clean_points(points, what)
    kp = voxel_down(pts, voxel)
    if len(kp) < MIN_POINTS:
        raise InputError(
            f"{what} has {len(kp)} point(s) after voxel downsampling at {voxel} m (from {len(pts)}); "
            f"the descriptor needs at least {MIN_POINTS}. Is the voxel size right for the cloud's units?"
        )
    return kp, extract_patches(kp, support_clouds(pts, kp, voxel, params), voxel, params)


# ----------------------------------------------------------------------------------------------------
# matching


def match_descriptors(
    src_feat: np.ndarray, tgt_feat: np.ndarray, mutual: bool = False, chunk: int = 2048
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Exact nearest target descriptor for every source descriptor (unit vectors: max cosine).

    Returns `(src_idx, tgt_idx, euclidean feature distance)`; `mutual` keeps only pairs that are each
    other's nearest neighbour. Brute force in chunks (faster than a k-d tree in 32 dimensions).
    """
    s = np.ascontiguousarray(src_feat, dtype=np.float32)
    t = np.ascontiguousarray(tgt_feat, dtype=np.float32)

    def nearest(a: np.ndarray, b: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        idx = np.empty(len(a), dtype=np.int64)
        sim = np.empty(len(a), dtype=np.float32)
        for i in range(0, len(a), chunk):
            block = a[i : i + chunk] @ b.T
            j = np.argmax(block, axis=1)
            idx[i : i + chunk] = j
            sim[i : i + chunk] = block[np.arange(len(j)), j]
        return idx, sim

    nn_idx, sim = nearest(s, t)
    dist = np.sqrt(np.clip(2.0 - 2.0 * sim.astype(np.float64), 0.0, None))
    src_idx = np.arange(len(s))
    if mutual:
        back, _ = nearest(t, s)
        keep = back[nn_idx] == src_idx
        src_idx, nn_idx, dist = src_idx[keep], nn_idx[keep], dist[keep]
    return src_idx, nn_idx, dist


# ----------------------------------------------------------------------------------------------------
# the front end


def repo_root() -> Path:
    """The repository root: the parent of the fastmac_exp package."""
    return Path(__file__).resolve().parents[2]


def resolve_model_path(model: str | os.PathLike) -> Path:
    """`model` as given when it exists (absolute, or relative to the cwd), else relative to the repo root."""
    p = Path(os.path.expanduser(str(model)))
    if p.is_file():
        return p
    tried = [str(p.resolve()) if not p.is_absolute() else str(p)]
    if not p.is_absolute():
        q = repo_root() / p
        if q.is_file():
            return q
        tried.append(str(q))
    raise InputError(
        f"ONNX descriptor model {str(model)!r} not found (tried {' and '.join(tried)}). Train and export "
        f"it with `python -m descriptors.train`, or set descriptor.model to an existing .onnx file"
    )


def _shape_str(shape) -> str:
    return "(" + ", ".join(str(d) if d is not None else "?" for d in shape) + ")"


def _fixed(d) -> int | None:
    return d if isinstance(d, int) else None


class OnnxDescriptor(FeatureDescriptor):
    """Learned local descriptors from an ONNX model (default: the shipped `descriptors/fcgf_lite.onnx`).

    Keypoints are the voxel-downsampled cloud (the pair's voxel size unless `voxel_size` is given),
    each described by the model from its LRF patch (module docstring: the input/output contract).
    Matching: nearest neighbour in descriptor space, source -> target (`mutual=True`: both ways);
    `max_correspondences` caps the output by a random subset drawn with the call's rng (0 = no cap).
    `k`, `radius_factor`, `support_factor` override the model's metadata (normally leave them None).
    `threads`: onnxruntime intra-op threads (default 1, the fastest on this shared 2-core machine; 0: all
    cores); `batch_size`: patches per onnxruntime run.
    `name` (the results rows' descriptor label) is the model's `fastmac.name` metadata, else its file
    name without extension ("fcgf_lite" for the shipped model). `alias`: the config name this front end
    was reached under when that is not the model's name (conf/descriptor/fcgf.yaml); a warning says so.
    """

    name = "fcgf_lite"
    default_graph_key = "fcgf"

    def __init__(
        self,
        model: str | os.PathLike = DEFAULT_MODEL,
        voxel_size: float | None = None,
        max_correspondences: int = 5000,
        mutual: bool = False,
        k: int | None = None,
        radius_factor: float | None = None,
        support_factor: float | None = None,
        threads: int = 1,
        batch_size: int = 8192,
        alias: str | None = None,
        graph_key: str | None = None,
    ) -> None:
        super().__init__(graph_key)
        if voxel_size is not None and not voxel_size > 0:
            raise InputError(
                f"onnx descriptor voxel_size must be positive or None (use the pair's), got {voxel_size}"
            )
        if max_correspondences < 0:
            raise InputError(f"max_correspondences must be >= 0 (0 = no cap), got {max_correspondences}")
        if threads < 0 or batch_size < 1:
            raise InputError(f"threads must be >= 0 and batch_size >= 1, got {threads}, {batch_size}")
        self.model = str(model)
        self.model_path = resolve_model_path(model)
        self.voxel_size = voxel_size
        self.max_correspondences = int(max_correspondences)
        self.mutual = bool(mutual)
        self.threads = int(threads)
        self.batch_size = int(batch_size)
        self._overrides = {"k": k, "radius_factor": radius_factor, "support_factor": support_factor}
        self._session = None
        self._open()
        self.alias = alias
        if alias and alias != self.name:
            log.warning(
                "descriptor=%s is an alias of %s (%s), a model trained in this project, not the published "
                "FCGF network; results are labelled %s",
                alias,
                self.name,
                self.model_path.name,
                self.name,
            )

    # -- model loading and the contract

    def _open(self) -> None:
        import onnxruntime as ort

        opts = ort.SessionOptions()
        if self.threads:
            opts.intra_op_num_threads = self.threads
        try:
            sess = ort.InferenceSession(str(self.model_path), opts, providers=["CPUExecutionProvider"])
        except Exception as exc:  # noqa: BLE001 - onnxruntime raises several types for a bad file
            raise InputError(f"ONNX descriptor model {self.model_path} could not be loaded: {exc}") from exc
        meta = sess.get_modelmeta().custom_metadata_map or {}
        if meta.get(META_PREFIX + "preprocess", "lrf_patches") != "lrf_patches":
            raise InputError(
                f"ONNX descriptor model {self.model_path} expects the {meta[META_PREFIX + 'preprocess']!r} "
                f"preprocessing, not this front end's LRF patches"
                + (
                    " (use descriptor=buffer descriptor.model=...)"
                    if meta[META_PREFIX + "preprocess"] == "buffer"
                    else ""
                )
            )
        self.name = meta.get(META_PREFIX + "name") or self.model_path.stem

        def meta_value(key: str, cast, default):
            raw = meta.get(META_PREFIX + key)
            if raw is None:
                return default
            try:
                return cast(raw)
            except ValueError as exc:
                raise InputError(
                    f"model {self.model_path}: metadata {META_PREFIX}{key}={raw!r} is not valid"
                ) from exc

        base = PatchParams()
        values = {
            "k": meta_value("k", int, base.k),
            "radius_factor": meta_value("radius_factor", float, base.radius_factor),
            "support_factor": meta_value("support_factor", float, base.support_factor),
            "features": meta_value("features", str, base.features),
            "k2": meta_value("k2", int, base.k2),
            "radius_factor2": meta_value("radius_factor2", float, base.radius_factor2),
            "support_factor2": meta_value("support_factor2", float, base.support_factor2),
        }
        values.update({key: v for key, v in self._overrides.items() if v is not None})
        self.params = PatchParams(**values)
        self.metadata = dict(meta)
        self._check_contract(sess)
        self._session = sess

    def _check_contract(self, sess) -> None:
        channels, size = self.params.channels, self.params.size
        want_in = f"one float32 input of rank 3, (M, {size}, {channels}) with M dynamic"
        want_out = "one float32 output of rank 2, (M, D)"
        ins, outs = sess.get_inputs(), sess.get_outputs()
        found_in = ", ".join(f"{i.name!r}: {i.type} {_shape_str(i.shape)}" for i in ins) or "none"
        found_out = ", ".join(f"{o.name!r}: {o.type} {_shape_str(o.shape)}" for o in outs) or "none"
        problems = []
        if len(ins) != 1:
            problems.append(f"{len(ins)} inputs")
        else:
            i = ins[0]
            if i.type != "tensor(float)":
                problems.append(f"input {i.name!r} has type {i.type}")
            if len(i.shape) != 3:
                problems.append(f"input {i.name!r} has rank {len(i.shape)}")
            else:
                if _fixed(i.shape[0]) is not None:
                    problems.append(f"input {i.name!r} has a fixed batch dimension {i.shape[0]}")
                if _fixed(i.shape[1]) not in (None, size):
                    problems.append(f"input {i.name!r} has K = {i.shape[1]}, the patch size is {size}")
                if _fixed(i.shape[2]) not in (None, channels):
                    problems.append(
                        f"input {i.name!r} has {i.shape[2]} channels, the patch features have {channels}"
                    )
        if len(outs) != 1:
            problems.append(f"{len(outs)} outputs")
        else:
            o = outs[0]
            if o.type != "tensor(float)":
                problems.append(f"output {o.name!r} has type {o.type}")
            if len(o.shape) != 2:
                problems.append(f"output {o.name!r} has rank {len(o.shape)}")
        if problems:
            raise InputError(
                f"ONNX descriptor model {self.model_path} does not fit the descriptor contract "
                f"({'; '.join(problems)}). Expected {want_in} and {want_out}; found inputs [{found_in}] "
                f"and outputs [{found_out}]"
            )
        self.input_name = ins[0].name
        self.output_dim = _fixed(outs[0].shape[1])

    def __getstate__(self) -> dict:  # onnxruntime sessions do not pickle (joblib launchers)
        state = self.__dict__.copy()
        state["_session"] = None
        return state

    def __setstate__(self, state: dict) -> None:
        self.__dict__.update(state)

    # -- inference

    def embed(self, patches: np.ndarray) -> np.ndarray:
        """Descriptors `(M, D)` float32, unit-norm, for model inputs `(M, K, C)`."""
        if self._session is None:
            self._open()
        x = np.ascontiguousarray(patches, dtype=np.float32)
        outs = []
        for i in range(0, len(x), self.batch_size):
            y = self._session.run(None, {self.input_name: x[i : i + self.batch_size]})[0]
            if y.ndim != 2 or y.shape[0] != len(x[i : i + self.batch_size]):
                raise InputError(
                    f"ONNX descriptor model {self.model_path} returned shape {y.shape} for "
                    f"{len(x[i : i + self.batch_size])} patches; expected (M, D)"
                )
            outs.append(np.asarray(y, dtype=np.float32))
        d = self.output_dim or (outs[0].shape[1] if outs else 32)
        y = np.concatenate(outs) if outs else np.zeros((0, d), dtype=np.float32)
        norm = np.linalg.norm(y, axis=1, keepdims=True)
        return y / np.where(norm > 0, norm, 1.0)

    def features(
        self, points: np.ndarray, voxel: float, what: str = "cloud"
    ) -> tuple[np.ndarray, np.ndarray]:
        """Keypoints `(M, 3)` float64 and descriptors `(M, D)` float32 of one cloud."""
        kp, patches = cloud_patches(points, voxel, self.params, what=what)
        return kp, self.embed(patches)

    def __call__(self, pair: Pair, rng: np.random.Generator) -> Correspondences:
        return correspondences_from_features(self, pair, rng, match_descriptors)
