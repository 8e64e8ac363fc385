"""Import open3d on machines that lack the system libusb-1.0 it links against.

The ``libusb-package`` wheel carries the library; loading it globally first lets open3d's
extension module resolve the symbol without an apt install.
"""

from __future__ import annotations

import ctypes
import functools


@functools.lru_cache(maxsize=1)
def open3d():
    """Return the ``open3d`` module (imported once)."""
    try:
        import libusb_package

        lib = libusb_package.get_library_path()
        if lib is not None:
            ctypes.CDLL(str(lib), mode=ctypes.RTLD_GLOBAL)
    except (ImportError, OSError):
        pass  # a system libusb may still be there
    import open3d as o3d

    return o3d
