"""FCGF's published checkpoints as they are: identification by content hash, a safe load, the `config`
entry and the state_dict checked against ResUNetBN2C's keys and shapes (fcgf_plan.expected_shapes).

A checkpoint (FCGF's lib/trainer.py `_save_checkpoint`) is a torch pickle of {"state_dict", "config" (an
easydict.EasyDict of the training options), "optimizer", "scheduler", "epoch", "best_val", ...}. It is read
with torch's weights-only unpickler (no code from the file runs) with the EasyDict mapped to a plain dict,
so neither easydict nor MinkowskiEngine is needed. A file is identified by its sha256 or its git blob id
(the id a repository that commits it shows) against `PUBLISHED`; any other file is refused with what was
found, unless its sha256 is given as `trusted_sha256` (the user vouches for it).
"""

from __future__ import annotations

import hashlib
import os
from collections import OrderedDict
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from fastmac_exp.descriptors.fcgf_plan import CONV1_KERNELS, NetConfig, expected_shapes
from fastmac_exp.errors import InputError

MODEL_ZOO = "https://github.com/chrischoy/FCGF#model-zoo"
NODE1 = "https://node1.chrischoy.org/data/publications/fcgf/"


@dataclass(frozen=True)
class PublishedCheckpoint:
    """One checkpoint of FCGF's model zoo (README) or DGR's; hashes where this project has recorded them."""

    file: str
    dataset: str  # 3dmatch | kitti
    voxel_size: float
    out_channels: int
    normalize_feature: bool
    url: str
    sha256: str | None = None
    git_blob: str | None = None


PUBLISHED = (
    PublishedCheckpoint(
        "2019-08-19_06-17-41.pth", "3dmatch", 0.025, 32, True, NODE1 + "2019-08-19_06-17-41.pth"
    ),
    PublishedCheckpoint(
        "2019-09-18_14-15-59.pth", "3dmatch", 0.025, 16, True, NODE1 + "2019-09-18_14-15-59.pth"
    ),
    PublishedCheckpoint(
        "2019-08-16_19-21-47.pth", "3dmatch", 0.05, 32, True, NODE1 + "2019-08-16_19-21-47.pth"
    ),
    PublishedCheckpoint(
        "2019-07-31_19-30-19.pth", "kitti", 0.2, 32, False, NODE1 + "2019-07-31_19-30-19.pth"
    ),
    PublishedCheckpoint(
        "2019-07-31_19-37-00.pth",
        "kitti",
        0.3,
        32,
        False,
        NODE1 + "2019-07-31_19-37-00.pth",
        git_blob="5fdeef3cce537bab12cd1d2b5962b06c9462ba38",  # a DeepGlobalRegistration fork's pretrained/
    ),
    PublishedCheckpoint(
        "KITTI-v0.3-ResUNetBN2C-conv1-5-nout16.pth",
        "kitti",
        0.3,
        16,
        True,
        NODE1 + "KITTI-v0.3-ResUNetBN2C-conv1-5-nout16.pth",
    ),  # fmt: skip
    PublishedCheckpoint(
        "KITTI-v0.3-ResUNetBN2C-conv1-5-nout32.pth",
        "kitti",
        0.3,
        32,
        True,
        NODE1 + "KITTI-v0.3-ResUNetBN2C-conv1-5-nout32.pth",
    ),  # fmt: skip
    PublishedCheckpoint(
        "ResUNetBN2C-feat32-3dmatch-v0.05.pth",
        "3dmatch",
        0.05,
        32,
        True,
        "https://node1.chrischoy.org/data/projects/DGR/ResUNetBN2C-feat32-3dmatch-v0.05.pth",
    ),  # fmt: skip
    PublishedCheckpoint(
        "ResUNetBN2C-feat32-kitti-v0.3.pth",
        "kitti",
        0.3,
        32,
        True,
        "https://node1.chrischoy.org/data/projects/DGR/ResUNetBN2C-feat32-kitti-v0.3.pth",
    ),  # fmt: skip
)


@dataclass(frozen=True)
class FileIds:
    sha256: str
    git_blob: str  # sha1 of "blob <size>\0" + content, as git names the file


def file_ids(path: str | os.PathLike) -> FileIds:
    p = Path(path)
    sha, blob = hashlib.sha256(), hashlib.sha1()
    blob.update(f"blob {p.stat().st_size}\0".encode())
    with open(p, "rb") as f:
        while chunk := f.read(1 << 20):
            sha.update(chunk)
            blob.update(chunk)
    return FileIds(sha.hexdigest(), blob.hexdigest())


def published(ids: FileIds) -> PublishedCheckpoint | None:
    for c in PUBLISHED:
        if ids.sha256 == c.sha256 or ids.git_blob == c.git_blob:
            return c
    return None


@dataclass(frozen=True)
class Checkpoint:
    """A checked checkpoint: its ids, the published entry it is (None: trusted by its sha256), the network
    shape, the voxel size, and the state dict as float32 arrays in `expected_shapes`' shapes."""

    path: Path
    ids: FileIds
    known: PublishedCheckpoint | None
    cfg: NetConfig
    voxel_size: float
    bn_momentum: float | None
    state: dict[str, np.ndarray]

    def describe(self) -> str:
        c = self.cfg
        return (
            f"ResUNetBN2C conv1 {c.conv1_kernel_size}, {c.out_channels} channels, normalize_feature "
            f"{c.normalize_feature}, voxel {self.voxel_size} m"
        )


def _safe_globals() -> list:
    core = getattr(np, "_core", None) or np.core
    return [
        # an EasyDict unpickles as an OrderedDict: the one mapping type whose items and attributes the
        # weights-only unpickler both sets (its attribute copy of the items is dropped with the object)
        (OrderedDict, "easydict.EasyDict"),
        (core.multiarray.scalar, "numpy.core.multiarray.scalar"),
        (core.multiarray.scalar, "numpy._core.multiarray.scalar"),
        np.dtype,
        *(type(np.dtype(t)) for t in ("float64", "float32", "int64", "int32", "bool")),
    ]


def read_checkpoint(path: str | os.PathLike) -> dict:
    """The checkpoint's top-level dict, unpickled by torch's weights-only loader (InputError otherwise)."""
    import torch

    try:
        with torch.serialization.safe_globals(_safe_globals()):
            ck = torch.load(str(path), map_location="cpu", weights_only=True)
    except Exception as exc:  # noqa: BLE001 - torch raises pickle, runtime and zip errors
        first = str(exc).strip().splitlines()[0] if str(exc).strip() else type(exc).__name__
        raise InputError(
            f"FCGF checkpoint {path} could not be read as a torch checkpoint with plain data only ({first}); "
            f"FCGF's published files ({MODEL_ZOO}) can"
        ) from None
    if not isinstance(ck, dict) or "state_dict" not in ck:
        found = sorted(ck)[:8] if isinstance(ck, dict) else type(ck).__name__
        raise InputError(f"FCGF checkpoint {path} has no 'state_dict' entry (found {found})")
    return ck


CONFIG_KEYS = ("model", "voxel_size", "conv1_kernel_size", "model_n_out", "normalize_feature")


def _config(ck: dict, path) -> dict:
    cfg = ck.get("config")
    if cfg is None:
        raise InputError(f"FCGF checkpoint {path} has no 'config' entry (FCGF's trainer saves one)")
    cfg = dict(cfg) if isinstance(cfg, dict) else dict(vars(cfg))
    missing = [k for k in CONFIG_KEYS if k not in cfg]
    if missing:
        raise InputError(f"FCGF checkpoint {path}: its config lacks {', '.join(missing)}")
    if cfg["model"] != "ResUNetBN2C":
        raise InputError(
            f"FCGF checkpoint {path} is a {cfg['model']!r}; this project implements ResUNetBN2C (the "
            f"model of every checkpoint in FCGF's model zoo)"
        )
    return cfg


def checked_state(state: dict, cfg: NetConfig, path) -> dict[str, np.ndarray]:
    """The state dict as float32 arrays in `expected_shapes`; InputError naming every key that is missing,
    unexpected or of another shape. 1x1 kernels may be (in, out) (ME 0.5) or (1, in, out) (older ME), the
    final bias (1, out) or (out,)."""
    want = expected_shapes(cfg)
    problems, out = [], {}
    for key, shape in want.items():
        if key not in state:
            problems.append(f"missing {key}")
            continue
        arr = np.asarray(state[key].numpy() if hasattr(state[key], "numpy") else state[key])
        allowed = {shape}
        if key.endswith(".kernel") and len(shape) == 2:
            allowed.add((1, *shape))
        if key == "final.bias":
            allowed.add((shape[1],))
        if arr.shape not in allowed:
            problems.append(f"{key} {tuple(arr.shape)} (expected {shape})")
            continue
        out[key] = arr.reshape(shape).astype(np.int64 if key.endswith("num_batches_tracked") else np.float32)
    extra = sorted(set(state) - set(want))
    if extra:
        problems.append("unexpected " + ", ".join(extra[:6]) + (" ..." if len(extra) > 6 else ""))
    if problems:
        raise InputError(
            f"FCGF checkpoint {path}: its state_dict does not fit ResUNetBN2C (conv1 "
            f"{cfg.conv1_kernel_size}, {cfg.out_channels} channels): "
            + "; ".join(problems[:8])
            + (" ..." if len(problems) > 8 else "")
        )
    return out


def load_checkpoint(path: str | os.PathLike, trusted_sha256: str | None = None) -> Checkpoint:
    """Read, check and identify a checkpoint (module docstring)."""
    p = Path(path).expanduser()
    if not p.is_file():
        raise InputError(f"FCGF checkpoint {p} does not exist")
    ids = file_ids(p)
    ck = read_checkpoint(p)
    raw = _config(ck, p)
    state = ck["state_dict"]
    conv1 = state.get("conv1.kernel")
    k1 = int(raw["conv1_kernel_size"])
    if conv1 is None or conv1.ndim != 3 or k1 not in CONV1_KERNELS or conv1.shape[0] != k1**3:
        found = None if conv1 is None else tuple(conv1.shape)
        raise InputError(f"FCGF checkpoint {p}: conv1.kernel {found} does not fit conv1_kernel_size {k1}")
    if conv1.shape[1] != 1:
        raise InputError(
            f"FCGF checkpoint {p} takes {conv1.shape[1]} input channels; FCGF's published models (and this "
            f"front end) take 1, the voxel occupancy"
        )
    cfg = NetConfig(1, k1, int(raw["model_n_out"]), bool(raw["normalize_feature"]))
    arrays = checked_state(state, cfg, p)
    known = published(ids)
    voxel = float(raw["voxel_size"])
    found = Checkpoint(p, ids, known, cfg, voxel, raw.get("bn_momentum"), arrays)
    if known is not None:
        want = (known.voxel_size, known.out_channels, known.normalize_feature)
        if (voxel, cfg.out_channels, cfg.normalize_feature) != want:
            raise InputError(
                f"FCGF checkpoint {p} has the hash of {known.file} but not its config: {found.describe()}"
            )
    elif trusted_sha256 is None or trusted_sha256.lower() != ids.sha256:
        recorded = ", ".join(c.file for c in PUBLISHED if c.sha256 or c.git_blob)
        raise InputError(
            f"FCGF checkpoint {p} is not a published checkpoint this project has a hash of (sha256 "
            f"{ids.sha256}, git blob {ids.git_blob}; found {found.describe()}; recorded: {recorded}). If you "
            f"trust this file, set descriptor.sha256={ids.sha256}"
            + (f" (given: {trusted_sha256})" if trusted_sha256 else "")
        )
    return found
