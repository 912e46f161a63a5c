"""Handing freed heap memory back to the operating system (glibc ``malloc_trim``).

A long batch run frees a few hundred MiB at once when the full-batch solve ends (GTSAM's
linearised systems and Bayes trees of every Levenberg-Marquardt iteration). glibc keeps
freed memory in its heap for reuse; what later stages allocate lands in it only where the
sizes fit, so without a trim the process's resident memory after the solve stays at the
solve's peak, and the next stages grow from there (docs/performance-log.md, "Batch memory").
``malloc_trim(0)`` returns every whole free page of the heap; it changes no allocation still
in use, so no result."""

from __future__ import annotations

import ctypes
import ctypes.util
import functools
import sys


@functools.cache
def _malloc_trim():
    """glibc's ``malloc_trim`` or None (another C library, another platform)."""
    if not sys.platform.startswith("linux"):
        return None
    try:
        libc = ctypes.CDLL(ctypes.util.find_library("c") or "libc.so.6")
        trim = libc.malloc_trim
    except (OSError, AttributeError):  # musl and others have no malloc_trim
        return None
    trim.argtypes = [ctypes.c_size_t]
    trim.restype = ctypes.c_int
    return trim


def return_free_heap() -> bool:
    """Return the heap's free pages to the operating system; True if something was
    returned, False if nothing was (or the C library has no ``malloc_trim``)."""
    trim = _malloc_trim()
    return bool(trim(0)) if trim is not None else False
