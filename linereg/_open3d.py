"""Imports open3d after loading the libusb that its wheel needs but a fresh machine lacks."""

from __future__ import annotations

import ctypes
import functools
from types import ModuleType


@functools.cache
def open3d() -> ModuleType:
    """Returns the open3d module; libusb-1.0 comes from the ``libusb-package`` wheel, no apt needed."""
    try:
        import libusb_package

        ctypes.CDLL(str(libusb_package.get_library_path()), mode=ctypes.RTLD_GLOBAL)
    except (ImportError, OSError, TypeError):
        pass  # a system libusb may still be there; the import below says so if not
    import open3d as o3d

    return o3d
