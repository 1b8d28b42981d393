"""Open3D's Linux wheel needs libusb-1.0.so.0, which a bare machine lacks; the `libusb-package` wheel ships
that library. Loading it first (by path, RTLD_GLOBAL) lets the dynamic linker resolve Open3D's dependency
by soname, so no system package is needed. `import fastmac_exp` does it (ctypes only, no Open3D), so a
library user's own `import open3d` works after it."""

from __future__ import annotations

import ctypes
import os


def preload_libusb() -> None:
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
