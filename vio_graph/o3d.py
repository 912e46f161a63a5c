"""Import open3d, making sure its libusb-1.0 dependency is loadable.

open3d's pybind module links against ``libusb-1.0.so.0``. Minimal Debian images lack it, so
before importing open3d we load the copy shipped by the PyPI package ``libusb-package`` into the
process with RTLD_GLOBAL; the dynamic linker then resolves open3d's dependency by SONAME.
"""

from __future__ import annotations

import ctypes
import ctypes.util
import functools
from pathlib import Path
from types import ModuleType


def _preload_libusb() -> None:
    if ctypes.util.find_library("usb-1.0"):
        return
    try:
        import libusb_package
    except ImportError:  # pragma: no cover - it is a hard dependency
        return
    for name in ("libusb-1.0.so", "libusb-1.0.so.0"):
        candidate = Path(libusb_package.__file__).parent / name
        if candidate.exists():
            ctypes.CDLL(str(candidate), mode=ctypes.RTLD_GLOBAL)
            return


@functools.cache
def open3d() -> ModuleType:
    """Return the open3d module (imported once, lazily)."""
    _preload_libusb()
    import open3d as o3d

    return o3d
