"""The reader's conversion of a stored depth frame in one compiled (numba) pass.

A frame stored as integer depth units (uint16, ``depth_mm.npy``) becomes float32 metres, its
valid mask (depth > 0) and the three counts the reader's unit checks use. The numpy path of
:meth:`vio_graph.recording.reader.Recording._convert` (five passes over the frame) is the
reference: the same floats (each unit converted to float32 exactly and multiplied by the
float32 scale, one IEEE single-precision product, as numpy's ``multiply(..., dtype=float32)``
does), the same mask and counts (the thresholds compared in float32, as numpy compares a
float32 array with a Python float). tests/test_recording.py compares the two bit for bit.
Imported only where numba is installed and the compiled paths are on
(:func:`vio_graph.frontend.icp.compiled_kernels`). Measured on the 2-core EPYC: ~9 us less a
frame (a 60 s recording's frames read between cache-evicting work, 64 -> 55 us CPU), against
~4 ms a process pays once to load the cached kernel: even at about the 450 frames from which
a replay turns the compiled paths on.
"""

from __future__ import annotations

import numba
import numpy as np


@numba.njit(cache=True)
def depth_from_units(raw, scale, far_m, near_m, out, valid):  # pragma: no cover - compiled
    """``out = float32(raw) * scale`` and ``valid = out > 0`` over (H, W) arrays of one
    shape; returns (pixels with ``out > 0``, with ``out > far_m``, with ``out < near_m``),
    each counted over every pixel. ``scale``, ``far_m``, ``near_m``: float32."""
    n_valid = 0
    n_far = 0
    n_near = 0
    for i in range(raw.shape[0]):
        for j in range(raw.shape[1]):
            d = np.float32(raw[i, j]) * scale
            out[i, j] = d
            ok = d > 0
            valid[i, j] = ok
            if ok:
                n_valid += 1
            if d > far_m:
                n_far += 1
            if d < near_m:
                n_near += 1
    return n_valid, n_far, n_near
