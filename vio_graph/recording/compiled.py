"""The reader's conversion of a stored depth frame in one compiled (numba) pass.

A frame stored as integer depth units (uint16, ``depth_mm.npy``) becomes float32 metres, its
valid mask (depth > 0) and the three counts the reader's unit checks use. The numpy path of
:meth:`vio_graph.recording.reader.Recording._convert` (five passes over the frame) is the
reference: the same floats (each unit converted to float32 exactly and multiplied by the
float32 scale, one IEEE single-precision product, as numpy's ``multiply(..., dtype=float32)``
does), the same mask and counts (the thresholds compared in float32, as numpy compares a
float32 array with a Python float). tests/test_recording.py compares the two bit for bit.
Imported only where numba is installed and the compiled paths are on
(:func:`vio_graph.frontend.icp.compiled_kernels`).
"""

from __future__ import annotations

import numba
import numpy as np


@numba.njit(cache=True)
def depth_from_units(raw, scale, far_m, near_m, out, valid):  # pragma: no cover - compiled
    """``out = float32(raw) * scale`` and ``valid = out > 0`` over C-contiguous arrays of one
    shape; returns (pixels with ``out > 0``, with ``out > far_m``, with ``out < near_m``),
    each counted over every pixel. ``scale``, ``far_m``, ``near_m``: float32."""
    r = raw.ravel()
    o = out.ravel()
    v = valid.ravel()
    n_valid = 0
    n_far = 0
    n_near = 0
    for k in range(r.size):
        d = np.float32(r[k]) * scale
        o[k] = d
        ok = d > 0
        v[k] = ok
        if ok:
            n_valid += 1
        if d > far_m:
            n_far += 1
        if d < near_m:
            n_near += 1
    return n_valid, n_far, n_near
