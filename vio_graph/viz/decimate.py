"""Fewer points for a line plot, keeping what the eye sees: the extremes of every stretch.

A figure a few thousand pixels wide cannot show more than a few thousand points per line, but
matplotlib still transforms, clips and legend-tests every one of them. :func:`plot_indices`
picks a subset: the series is split into equal stretches (buckets) and each keeps its first
and last sample and the samples of its minimum and maximum in every column, in time order.
Peaks, steps and gaps (non-finite samples) survive; a line drawn through the subset covers the
same pixels as the full line to within a bucket's width. Pure numpy, no plotting.
"""

from __future__ import annotations

import numpy as np
from numpy.typing import NDArray

#: points per line the run figures draw at most (about 1.5 per pixel of a 1,400 px figure)
MAX_LINE_POINTS = 2000


def plot_indices(
    values: NDArray[np.floating], max_points: int = MAX_LINE_POINTS
) -> NDArray[np.intp]:
    """Sorted indices of the rows of ``values`` ((N,) or (N, D)) to draw: all of them when
    N <= ``max_points``; else, per bucket of consecutive rows, the first and last row, the
    rows of the minimum and maximum of each column and the first non-finite row (so a gap
    still breaks the line). At most ``max_points`` indices (``max_points`` >= 2 + 2 D + 1).

    Raises:
        ValueError: ``values`` is not 1-D or 2-D, or ``max_points`` is too small for D.
    """
    v = np.asarray(values, dtype=float)
    if v.ndim == 1:
        v = v[:, None]
    if v.ndim != 2:
        raise ValueError(f"values must be (N,) or (N, D), got shape {np.shape(values)}")
    n, d = v.shape
    per_bucket = 3 + 2 * d  # first, last, one gap, min and max per column
    if max_points < per_bucket:
        raise ValueError(f"max_points={max_points} < {per_bucket} needed for {d} columns")
    if n <= max_points:
        return np.arange(n, dtype=np.intp)
    n_buckets = max_points // per_bucket
    size = -(-n // n_buckets)  # ceil: rows per bucket
    n_buckets = -(-n // size)
    pad = n_buckets * size - n
    finite = np.isfinite(v)
    lo = np.pad(np.where(finite, v, np.inf), ((0, pad), (0, 0)), constant_values=np.inf)
    hi = np.pad(np.where(finite, v, -np.inf), ((0, pad), (0, 0)), constant_values=-np.inf)
    starts = np.arange(n_buckets) * size
    picks = [starts, np.minimum(starts + size - 1, n - 1)]
    for k in range(d):
        picks.append(starts + np.argmin(lo[:, k].reshape(n_buckets, size), axis=1))
        picks.append(starts + np.argmax(hi[:, k].reshape(n_buckets, size), axis=1))
    gaps = np.pad(~finite.all(axis=1), (0, pad)).reshape(n_buckets, size)
    has_gap = gaps.any(axis=1)
    picks.append((starts + np.argmax(gaps, axis=1))[has_gap])
    idx = np.unique(np.concatenate(picks))
    return idx[idx < n].astype(np.intp)
