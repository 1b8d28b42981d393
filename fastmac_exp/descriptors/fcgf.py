"""FCGF (Choy, Park, Koltun, ICCV 2019), the paper's learned descriptor, from a published checkpoint the user
brings: `descriptor=fcgf descriptor.checkpoint=PATH` (or FCGF_CHECKPOINT=PATH).

No MinkowskiEngine: the checkpoint is identified and checked (fcgf_checkpoint.py), converted once into an
ONNX graph (fcgf_onnx.py) kept in the data home (`$FASTMAC_DATA`, else platformdirs' user data dir for
fastmac-exp, under `fcgf/`), and run by onnxruntime. Describing one cloud (FCGF's util/misc.py
`extract_features`): the finite points voxelised at the checkpoint's voxel size (coordinates floor(xyz /
voxel), the first point of each voxel its keypoint), an all-ones input feature, the kernel maps of the four
levels (fcgf_maps.py), one forward pass; rows unit-normalised when the checkpoint says normalize_feature
(and here in any case, for the cosine matching). Matching is the shared front-end path (nearest neighbour,
`mutual`, `max_correspondences`), graph_key fcgf.
"""

from __future__ import annotations

import logging
import os
from pathlib import Path

import numpy as np

from fastmac_exp.descriptors.base import FeatureDescriptor
from fastmac_exp.descriptors.fcgf_maps import unet_maps, voxelize
from fastmac_exp.descriptors.fcgf_onnx import onnx_feeds
from fastmac_exp.descriptors.fcgf_plan import NetConfig
from fastmac_exp.descriptors.keypoints import clean_points, require_keypoints
from fastmac_exp.descriptors.matching import correspondences_from_kept_sources, match_descriptors
from fastmac_exp.descriptors.onnx_descriptor import SessionPickling, open_session
from fastmac_exp.errors import InputError
from fastmac_exp.resources import data_home
from fastmac_exp.types import Correspondences, Pair

log = logging.getLogger(__name__)

ENV_CHECKPOINT = "FCGF_CHECKPOINT"
CONVERTER_VERSION = 1  # bump when the ONNX graph changes: cached models of another version are rebuilt
NO_CHECKPOINT = (
    "descriptor=fcgf needs one of FCGF's published checkpoints (a ResUNetBN2C .pth of "
    "https://github.com/chrischoy/FCGF#model-zoo; this machine cannot download it): set "
    "descriptor.checkpoint=PATH or FCGF_CHECKPOINT=PATH (descriptor=fcgf_lite is the small model shipped "
    "here)"
)


def cached_model_path(sha256: str) -> Path:
    return data_home() / "fcgf" / f"{sha256[:16]}-v{CONVERTER_VERSION}.onnx"


def convert(checkpoint, path: Path) -> Path:
    """Write the ONNX model of a checked checkpoint to `path` (atomically: a reader sees all or nothing)."""
    from fastmac_exp.atomic import temp_name
    from fastmac_exp.descriptors.fcgf_onnx import build_model

    c = checkpoint.cfg
    meta = {
        "fastmac.preprocess": "fcgf",
        "fcgf.sha256": checkpoint.ids.sha256,
        "fcgf.source": checkpoint.known.file if checkpoint.known else checkpoint.path.name,
        "fcgf.voxel_size": repr(checkpoint.voxel_size),
        "fcgf.conv1_kernel_size": str(c.conv1_kernel_size),
        "fcgf.out_channels": str(c.out_channels),
        "fcgf.normalize_feature": str(c.normalize_feature),
        "fcgf.converter_version": str(CONVERTER_VERSION),
    }
    model = build_model(checkpoint.state, c, meta)
    path.parent.mkdir(parents=True, exist_ok=True)
    tmp = temp_name(path)
    try:
        tmp.write_bytes(model.SerializeToString())
        os.replace(tmp, path)
    except BaseException:
        tmp.unlink(missing_ok=True)
        raise
    return path


class FcgfDescriptor(SessionPickling, FeatureDescriptor):
    """FCGF's ResUNetBN2C from a published checkpoint (module docstring).

    `checkpoint`: the .pth (None: $FCGF_CHECKPOINT; neither: InputError saying how). `sha256`: accept a
    checkpoint this project has no hash of, by its sha256 (the refusal prints it). `voxel_size`: None = the
    checkpoint's (what it was trained at; the pair's voxel size does not apply). `threads`: onnxruntime
    intra-op threads (0: its default). `max_correspondences`, `mutual`, `execution_providers` as the other
    ONNX front ends."""

    name = "fcgf"
    default_graph_key = "fcgf"

    def __init__(
        self,
        checkpoint: str | os.PathLike | None = None,
        sha256: str | None = None,
        voxel_size: float | None = None,
        max_correspondences: int = 5000,
        mutual: bool = False,
        threads: int = 1,
        execution_providers="auto",
        graph_key: str | None = None,
    ) -> None:
        super().__init__(graph_key)
        checkpoint = checkpoint or os.environ.get(ENV_CHECKPOINT) or None
        if checkpoint is None:
            raise InputError(NO_CHECKPOINT)
        if voxel_size is not None and not voxel_size > 0:
            raise InputError(f"fcgf voxel_size must be positive or null (the checkpoint's), got {voxel_size}")
        if max_correspondences < 0 or threads < 0:
            raise InputError(
                f"fcgf max_correspondences and threads must be >= 0, got {max_correspondences}, {threads}"
            )
        self.checkpoint = Path(checkpoint).expanduser()
        self.sha256 = sha256
        self.max_correspondences = int(max_correspondences)
        self.mutual = bool(mutual)
        self.threads = int(threads)
        self.execution_providers = execution_providers
        self.model_path = self._model()
        self._session = None
        self._open()
        self.voxel_size = float(voxel_size) if voxel_size is not None else self.checkpoint_voxel

    def _model(self) -> Path:
        """The cached ONNX model of the checkpoint, converted on first use."""
        from fastmac_exp.descriptors.fcgf_checkpoint import file_ids, load_checkpoint, published

        if not self.checkpoint.is_file():
            raise InputError(f"FCGF checkpoint {self.checkpoint} does not exist. {NO_CHECKPOINT}")
        ids = file_ids(self.checkpoint)
        trusted = self.sha256 is not None and self.sha256.lower() == ids.sha256
        path = cached_model_path(ids.sha256)
        if path.is_file() and (trusted or published(ids) is not None):
            return path
        ck = load_checkpoint(self.checkpoint, self.sha256)  # refuses an unknown file, saying what it found
        log.info("fcgf: converting %s (%s) to %s", self.checkpoint, ck.describe(), path)
        return convert(ck, path)

    def _open(self) -> None:
        import onnxruntime as ort

        opts = ort.SessionOptions()
        if self.threads:
            opts.intra_op_num_threads = self.threads
        try:
            sess = open_session(self.model_path, opts, self.execution_providers, "descriptor fcgf")
        except Exception as exc:  # noqa: BLE001 - onnxruntime raises several types for a bad file
            raise InputError(
                f"cached FCGF model {self.model_path} could not be loaded ({exc}); delete it to convert again"
            ) from exc
        meta = sess.get_modelmeta().custom_metadata_map or {}
        if meta.get("fastmac.preprocess") != "fcgf" or meta.get("fcgf.converter_version") != str(
            CONVERTER_VERSION
        ):
            raise InputError(
                f"{self.model_path} is not an FCGF model of this version; delete it to convert again"
            )
        self.cfg = NetConfig(
            1,
            int(meta["fcgf.conv1_kernel_size"]),
            int(meta["fcgf.out_channels"]),
            meta["fcgf.normalize_feature"] == "True",
        )
        self.checkpoint_voxel = float(meta["fcgf.voxel_size"])
        self.metadata = dict(meta)
        self.input_names = [i.name for i in sess.get_inputs()]
        self._session = sess

    def keypoints(
        self, points: np.ndarray, voxel: float, what: str = "cloud"
    ) -> tuple[np.ndarray, np.ndarray]:
        """(the cleaned cloud, its keypoints: the first point of each voxel)."""
        pts = clean_points(points, what)
        coords, first = voxelize(pts, voxel)
        require_keypoints(coords, len(pts), voxel, what, "descriptor=fcgf")
        return pts, pts[first]

    def features(
        self, points: np.ndarray, voxel: float, what: str = "cloud"
    ) -> tuple[np.ndarray, np.ndarray]:
        """Keypoints (M, 3) float64 (the first point of each voxel) and unit features (M, D) float32."""
        if self._session is None:
            self._open()
        pts = clean_points(points, what)
        coords, first = voxelize(pts, voxel)
        require_keypoints(coords, len(pts), voxel, what, "descriptor=fcgf")
        maps = unet_maps(coords, self.cfg.conv1_kernel_size)
        feats = np.ones((len(coords), 1), dtype=np.float32)
        y = self._session.run(None, onnx_feeds(feats, maps, self.input_names))[0]
        norm = np.linalg.norm(y, axis=1, keepdims=True)
        return pts[first], (y / np.where(norm > 0, norm, 1.0)).astype(np.float32)

    def features_of(
        self, cloud: np.ndarray, kp: np.ndarray, rows: np.ndarray, what: str = "cloud"
    ) -> np.ndarray:
        """The features of keypoints `rows` (the network runs on the whole cloud: one pass describes all)."""
        return self.features(cloud, self.voxel_size, what)[1][rows]

    def __call__(self, pair: Pair, rng: np.random.Generator) -> Correspondences:
        # one-way matching: only the capped source keypoints are matched (a fragment has ~20k at 2.5 cm)
        return correspondences_from_kept_sources(self, pair, rng, match_descriptors)


__all__ = ["FcgfDescriptor", "cached_model_path", "convert", "data_home"]
