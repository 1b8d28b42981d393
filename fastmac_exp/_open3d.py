"""Import Open3D through here: its Linux wheel needs libusb-1.0.so.0, which a bare machine lacks.

The `libusb-package` wheel ships that library; loading it first lets the dynamic linker resolve
Open3D's dependency by soname, so no system package is needed.
"""

from __future__ import annotations

import ctypes
import os


def _preload_libusb() -> None:
    try:
        ctypes.CDLL("libusb-1.0.so.0")
        return
    except OSError:
        pass
    try:
        import libusb_package
    except ImportError:
        return
    path = os.path.join(os.path.dirname(libusb_package.__file__), "libusb-1.0.so")
    if os.path.exists(path):
        ctypes.CDLL(path, mode=ctypes.RTLD_GLOBAL)


_preload_libusb()
import open3d as o3d  # noqa: E402

o3d.utility.set_verbosity_level(o3d.utility.VerbosityLevel.Error)

__all__ = ["o3d"]
