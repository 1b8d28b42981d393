"""Import Open3D through here: its Linux wheel needs libusb-1.0.so.0, which a bare machine lacks
(fastmac_exp/_libusb.py loads the one the `libusb-package` wheel ships first)."""

from __future__ import annotations

from fastmac_exp._libusb import preload_libusb

preload_libusb()
import open3d as o3d  # noqa: E402

o3d.utility.set_verbosity_level(o3d.utility.VerbosityLevel.Error)

__all__ = ["o3d"]
