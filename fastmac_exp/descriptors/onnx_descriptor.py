"""Learned-descriptor front end: multi-scale local patches in a local reference frame (LRF), embedded by
an ONNX model (the shipped `fastmac_exp/models/fcgf_lite.onnx`, a small network trained here, not the
published FCGF; its model card is descriptors/fcgf_lite/MODEL_CARD.md). BUFFER's published models have
their own front end (fastmac_exp/descriptors/buffer.py, `descriptor=buffer`).

Runtime path: numpy/scipy preprocessing + onnxruntime inference; torch is never imported here (the
training recipe `descriptors/fcgf_lite/train.py` imports this preprocessing, so training and runtime cannot
drift).

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
from pathlib import Path

import numpy as np

from fastmac_exp.descriptors.base import FeatureDescriptor
from fastmac_exp.descriptors.matching import correspondences_from_features, match_descriptors
from fastmac_exp.descriptors.patches import (
    PatchParams,
    cloud_patches,
)
from fastmac_exp.errors import InputError
from fastmac_exp.resources import candidates, find_file
from fastmac_exp.types import Correspondences, Pair

log = logging.getLogger(__name__)

DEFAULT_MODEL = "models/fcgf_lite.onnx"  # relative to the package (fastmac_exp/models/)
META_PREFIX = "fastmac."
CPU = "CPUExecutionProvider"
PROVIDER_ALIASES = {"cpu": CPU, "cuda": "CUDAExecutionProvider", "tensorrt": "TensorrtExecutionProvider"}


def session_providers(requested, what: str = "ONNX model") -> list[str]:
    """The onnxruntime execution providers for `requested`: "auto" (or None) = CUDA when this onnxruntime
    has it (onnxruntime-gpu), else the CPU; or provider names in order of preference ("cuda", "tensorrt",
    "cpu" or onnxruntime's own names such as "CUDAExecutionProvider"). Providers onnxruntime lacks are
    dropped with a one-line notice; the CPU always comes last as the fallback."""
    import onnxruntime as ort

    have = ort.get_available_providers()
    auto = requested is None or requested == "auto"
    if auto:
        want = [PROVIDER_ALIASES["cuda"], CPU]
    else:
        want = [requested] if isinstance(requested, str) else list(requested)
        want = [PROVIDER_ALIASES.get(str(p).lower(), str(p)) for p in want]
    chosen = [p for p in want if p in have]
    if CPU not in chosen:
        chosen.append(CPU)
    missing = [p for p in want if p not in have and p != CPU]
    if missing and not auto:
        log.warning(
            "%s: onnxruntime %s has no %s (it has %s); running on %s",
            what,
            ort.__version__,
            ", ".join(missing),
            ", ".join(have),
            ", ".join(chosen),
        )
    return chosen


def open_session(path: Path, opts, providers, what: str):
    """An onnxruntime session on the first of `providers` that starts (session_providers); a GPU provider
    that fails to start (no device, missing CUDA libraries) falls back to the CPU with a one-line notice."""
    import onnxruntime as ort

    chosen = session_providers(providers, what)
    try:
        sess = ort.InferenceSession(str(path), opts, providers=chosen)
    except Exception as exc:  # noqa: BLE001 - onnxruntime raises several types for a bad file or device
        if chosen == [CPU]:
            raise
        log.warning(
            "%s: %s did not start (%s); running on the CPU", what, chosen[0], str(exc).splitlines()[0]
        )
        sess = ort.InferenceSession(str(path), opts, providers=[CPU])
    dropped = [p for p in chosen if p not in sess.get_providers()]
    if dropped:
        log.warning(
            "%s: onnxruntime did not start %s; running on %s",
            what,
            ", ".join(dropped),
            sess.get_providers()[0],
        )
    return sess


def resolve_model_path(model: str | os.PathLike) -> Path:
    """`model` as given when it exists (absolute, or relative to the cwd), else relative to the package."""
    found = find_file(model)
    if found is not None:
        return found
    tried = [str(c.resolve()) for c in candidates(model)]
    raise InputError(
        f"ONNX descriptor model {str(model)!r} not found (tried {' and '.join(tried)}). Train and export "
        f"it with `python descriptors/fcgf_lite/train.py`, or set descriptor.model to an existing .onnx file"
    )


def _shape_str(shape) -> str:
    return "(" + ", ".join(str(d) if d is not None else "?" for d in shape) + ")"


def _fixed(d) -> int | None:
    return d if isinstance(d, int) else None


class SessionPickling:
    """onnxruntime sessions do not pickle (joblib launchers): a copy travels without its `_session`, which
    is opened again on first use."""

    def __getstate__(self) -> dict:
        state = self.__dict__.copy()
        state["_session"] = None
        return state

    def __setstate__(self, state: dict) -> None:
        self.__dict__.update(state)


class OnnxDescriptor(SessionPickling, FeatureDescriptor):
    """Learned local descriptors from an ONNX model (default: the shipped fastmac_exp/models/fcgf_lite.onnx).

    Keypoints are the voxel-downsampled cloud (the pair's voxel size unless `voxel_size` is given),
    each described by the model from its LRF patch (module docstring: the input/output contract).
    Matching: nearest neighbour in descriptor space, source -> target (`mutual=True`: both ways);
    `max_correspondences` caps the output by a random subset drawn with the call's rng (0 = no cap).
    `k`, `radius_factor`, `support_factor` override the model's metadata (normally leave them None).
    `threads`: onnxruntime intra-op threads (default 1, the fastest on this shared 2-core machine; 0: all
    cores); `batch_size`: patches per onnxruntime run (1,024 runs as fast as 8,192 on the CPU and holds a
    KITTI scan's describe to 0.8 GB of memory instead of 3.1 GB). `execution_providers`: "auto" (a GPU through
    onnxruntime-gpu's CUDA provider when there is one, else the CPU) or a list such as ["cuda", "cpu"]
    (`session_providers`); a provider that is missing or fails to start falls back to the CPU with a notice.
    `name` (the results rows' descriptor label) is the model's `fastmac.name` metadata, else its file
    name without extension ("fcgf_lite" for the shipped model).
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
        batch_size: int = 1024,
        execution_providers="auto",
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
        self.execution_providers = execution_providers
        self._overrides = {"k": k, "radius_factor": radius_factor, "support_factor": support_factor}
        self._session = None
        self._open()

    # -- model loading and the contract

    def _open(self) -> None:
        import onnxruntime as ort

        opts = ort.SessionOptions()
        if self.threads:
            opts.intra_op_num_threads = self.threads
        try:
            sess = open_session(
                self.model_path, opts, self.execution_providers, f"descriptor {self.model_path.name}"
            )
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
