"""Scene helpers for visualisation: a terrain mesh from a sagittal profile."""

from __future__ import annotations

import numpy as np
from numpy.typing import NDArray


def extrude_profile(
    profile_xz_m: NDArray[np.float64], width_m: float = 1.0
) -> tuple[NDArray[np.float64], NDArray[np.int64]]:
    """Extrude a sagittal polyline (N, 2) across y in [-w/2, w/2]: vertices (2N, 3) and
    triangles (2(N-1), 3) of the surface."""
    p = np.asarray(profile_xz_m, dtype=float)
    n = p.shape[0]
    left = np.column_stack([p[:, 0], np.full(n, width_m / 2), p[:, 1]])
    right = np.column_stack([p[:, 0], np.full(n, -width_m / 2), p[:, 1]])
    verts = np.vstack([left, right])
    i = np.arange(n - 1)
    tris = np.vstack(
        [np.column_stack([i, i + 1, n + i]), np.column_stack([i + 1, n + i + 1, n + i])]
    )
    return verts, tris
