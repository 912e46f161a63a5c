"""Handing freed heap memory back to the operating system (glibc ``malloc_trim``), and
pausing CPython's cyclic garbage collector while a run starts up.

A long batch run frees a few hundred MiB at once when the full-batch solve ends (GTSAM's
linearised systems and Bayes trees of every Levenberg-Marquardt iteration). glibc keeps
freed memory in its heap for reuse; what later stages allocate lands in it only where the
sizes fit, so without a trim the process's resident memory after the solve stays at the
solve's peak, and the next stages grow from there (docs/performance-log.md, "Batch memory").
``malloc_trim(0)`` returns every whole free page of the heap; it changes no allocation still
in use, so no result.

A run's start-up (its imports, the configuration, opening the recording, numba loading the
first cached kernels) creates ~200,000 objects that live until the process ends; the cyclic
collector's passes over them (~300 young, ~30 middle-generation and 2 full collections
during the start-up of a 30 s run) free almost nothing (~1,300 objects) and cost
~0.15-0.25 s of CPU a run (docs/performance-log.md, "A whole run outside the estimator").
:func:`collection_paused_for_start_up` turns the collector off for that start-up;
:func:`start_up_done`, called when the replay starts, moves what then exists out of the
collector's generations (``gc.freeze``) and turns it back on, so that later passes look only
at what the run itself creates; the objects go back to the collector when the paused block
ends (``gc.unfreeze``). At the interpreter's exit everything is frozen again
(:func:`_freeze_for_exit`): the collections of CPython's shutdown would otherwise pass over
all of it once more. Collection frees memory only; no result depends on it."""

from __future__ import annotations

import atexit
import contextlib
import ctypes
import ctypes.util
import functools
import gc
import sys
from collections.abc import Iterator


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


#: the start-up pause of this process: None, "paused" (collector off) or "frozen" (on again,
#: the start-up's objects frozen)
_start_up: str | None = None
#: whether :func:`_freeze_for_exit` is registered with ``atexit`` (once a process)
_exit_freeze_registered = False


def _freeze_for_exit() -> None:
    """At interpreter exit (an ``atexit`` handler, registered by :func:`freeze_at_exit`):
    freeze every object, so that the full collections CPython runs while it shuts down
    (~0.19 s of CPU after a 30 s run, over the ~150,000 objects a run leaves) skip them; the
    process's end frees that memory anyway. Files and outputs are closed by then (every
    writer closes its own), so nothing is left for a collected object's finaliser to do."""
    gc.freeze()


def freeze_at_exit() -> None:
    """Register :func:`_freeze_for_exit` with ``atexit`` (once). Only the console script's
    own process does this (``vio_graph.cli.main``): a program that imports vio_graph, or calls
    a command in-process, keeps its own shutdown as it was."""
    global _exit_freeze_registered
    if not _exit_freeze_registered:
        atexit.register(_freeze_for_exit)
        _exit_freeze_registered = True


@contextlib.contextmanager
def collection_paused_for_start_up() -> Iterator[None]:
    """Run the block with the cyclic garbage collector paused until :func:`start_up_done`
    (which the replay calls when it starts; without it, until the block ends). The
    collector is left as it was if it is off, if objects are already frozen (``gc.freeze``
    by the caller) or inside another such block. On leaving the block it is on again and
    the objects :func:`start_up_done` froze are back in its generations."""
    global _start_up
    if _start_up is not None or not gc.isenabled() or gc.get_freeze_count():
        yield
        return
    gc.disable()
    _start_up = "paused"
    try:
        yield
    finally:
        state, _start_up = _start_up, None
        if state == "frozen":
            gc.unfreeze()
        gc.enable()


def start_up_done() -> None:
    """The start-up of a run is over: inside :func:`collection_paused_for_start_up`, freeze
    the objects that exist now (``gc.freeze``) and turn the collector on; otherwise
    nothing."""
    global _start_up
    if _start_up == "paused":
        gc.freeze()
        gc.enable()
        _start_up = "frozen"
