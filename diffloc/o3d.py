"""Import open3d on machines without a system libusb.

open3d's native module links against ``libusb-1.0.so.0``. The ``libusb-package`` wheel ships
that library; loading it globally before open3d is imported satisfies the dependency without a
system package. Import open3d through :func:`open3d` everywhere in diffloc.
"""

from __future__ import annotations

import ctypes
import functools
from types import ModuleType


@functools.cache
def open3d() -> ModuleType:
    """Return the imported ``open3d`` module, preloading libusb from ``libusb-package`` first."""
    try:
        import open3d as o3d  # noqa: PLC0415

        return o3d
    except ImportError as error:
        if "libusb" not in str(error):
            raise
    import libusb_package  # noqa: PLC0415

    ctypes.CDLL(str(libusb_package.get_library_path()), mode=ctypes.RTLD_GLOBAL)
    import open3d as o3d  # noqa: PLC0415

    return o3d
