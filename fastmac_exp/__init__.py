"""fastmac-exp: FastMAC graph-signal sampling + MAC maximal-clique registration, with an experiment shell.

Library use (no Hydra needed):

    import fastmac_exp
    src_xyz = fastmac_exp.load_cloud("source.ply")  # .ply .pcd .npy .bin (KITTI) .xyz/.txt, as the CLI reads
    result = fastmac_exp.register(src_xyz, tgt_xyz, family="3dmatch", voxel_size=0.05, ratio=0.2)
    result.pose        # 4x4, maps the source into the target
    result.timings     # ms per stage (every one, back to back), total = sampling + MAC, end_to_end
"""

from fastmac_exp._libusb import preload_libusb
from fastmac_exp.interrupts import interrupts_blocked

preload_libusb()  # before anything: a caller's own `import open3d` then works on a bare machine too
with interrupts_blocked():  # numpy's OpenBLAS starts its threads as it loads: none of them takes a Ctrl-C
    import numpy  # noqa: F401
# ruff: noqa: E402

from fastmac_exp.api import register
from fastmac_exp.errors import BackendUnavailable, FastMacError, InputError, RegistrationFailed
from fastmac_exp.io import load_cloud
from fastmac_exp.params import GraphParams, MacParams, mac_params_for
from fastmac_exp.pipeline import register_correspondences
from fastmac_exp.types import Correspondences, Pair, RegistrationResult

__version__ = "0.2.0"

__all__ = [
    "BackendUnavailable",
    "Correspondences",
    "FastMacError",
    "GraphParams",
    "InputError",
    "MacParams",
    "Pair",
    "RegistrationFailed",
    "RegistrationResult",
    "load_cloud",
    "mac_params_for",
    "register",
    "register_correspondences",
]
