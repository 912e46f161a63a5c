"""Smoothing of the 2D sagittal profile (paper Section II.A.1, last sentence).

The paper smooths the projected cloud "using the k-Nearest Neighbor algorithm". vio_graph
replaces every point by the mean of its k nearest neighbours (itself included), which averages
ToF range noise along the surface while keeping corners within about k/2 grid cells.

Before that, an optional grid thinning keeps one point per ``cell_m`` x ``cell_m`` cell of the
x-z plane (the centroid of the points in the cell). It makes the cost independent of how close
the camera is to the ground, and it makes point counts proportional to surface length, which
the terrain classifier and RANSAC rely on (a 28 cm tread then outweighs a 14.7 cm riser even
when the camera sees the riser head-on).
"""

from __future__ import annotations

from typing import TYPE_CHECKING

import numpy as np
from numpy.typing import NDArray

from vio_graph.frontend.icp import compiled_kernels

if TYPE_CHECKING:  # scipy is imported where a KD-tree is built (numpy paths only)
    from scipy.spatial import cKDTree

#: above this many cells in the bounding box, grid_thin sorts the keys instead of counting
#: into a dense array (memory bound: 4e6 cells = 3 arrays of 32 MB at most)
_MAX_DENSE_CELLS = 4_000_000


def grid_thin(points_xz_m: NDArray[np.float64], cell_m: float) -> NDArray[np.float64]:
    """Centroid of the points in each occupied ``cell_m`` square cell.

    Args:
        points_xz_m: (N, 2) points, metres.
        cell_m: cell size, metres; <= 0 returns a copy of the input.

    Returns:
        (M, 2) centroids, M <= N, ordered by cell (x-major).

    Compiled (``compiled.grid_thin``, numba) when numba is installed: the same sums in the
    same order, so the same centroids bit for bit as :func:`grid_thin_reference`.
    """
    pts = np.asarray(points_xz_m, dtype=float)
    if cell_m <= 0 or pts.shape[0] == 0:
        return pts.copy()
    kernels = compiled_kernels()
    if kernels is not None and pts.ndim == 2 and pts.shape[1] == 2:
        return kernels.grid_thin(np.ascontiguousarray(pts), float(cell_m), _MAX_DENSE_CELLS)
    return grid_thin_reference(pts, cell_m)


def grid_thin_reference(points_xz_m: NDArray[np.float64], cell_m: float) -> NDArray[np.float64]:
    """numpy path of :func:`grid_thin` (bincounts over the occupied cells)."""
    pts = np.asarray(points_xz_m, dtype=float)
    if cell_m <= 0 or pts.shape[0] == 0:
        return pts.copy()
    x, z = pts[:, 0], pts[:, 1]
    ix = np.floor(x / cell_m).astype(np.int64)
    iz = np.floor(z / cell_m).astype(np.int64)
    ix -= ix.min()
    iz -= iz.min()
    n_z = int(iz.max()) + 1
    key = ix * n_z + iz
    n_cells = (int(ix.max()) + 1) * n_z
    if n_cells > _MAX_DENSE_CELLS:  # sparse over a huge extent: sort instead
        _, inverse, counts = np.unique(key, return_inverse=True, return_counts=True)
        sum_x = np.bincount(inverse, weights=x, minlength=counts.size)
        sum_z = np.bincount(inverse, weights=z, minlength=counts.size)
        return np.column_stack([sum_x, sum_z]) / counts[:, None]
    # dense cell key: an occupancy mask gives the occupied cells in sorted key order (same
    # cells, order and sums as np.unique, without the sort); a lookup table numbers them so
    # the sums are bincounts over the occupied cells only, not over the whole bounding box
    occupied_mask = np.zeros(n_cells, dtype=bool)
    occupied_mask[key] = True
    occupied = np.flatnonzero(occupied_mask)
    cell_number = np.empty(n_cells, dtype=np.intp)  # only read at occupied cells
    cell_number[occupied] = np.arange(occupied.size)
    inverse = cell_number[key]
    counts = np.bincount(inverse, minlength=occupied.size)
    sum_x = np.bincount(inverse, weights=x, minlength=occupied.size)
    sum_z = np.bincount(inverse, weights=z, minlength=occupied.size)
    return np.column_stack([sum_x, sum_z]) / counts[:, None]


def knn_smooth(
    points_xz_m: NDArray[np.float64], k: int, tree: cKDTree | None = None
) -> NDArray[np.float64]:
    """Replace each point by the mean of its k nearest neighbours (itself included).

    Args:
        points_xz_m: (N, 2) points, metres.
        k: neighbours averaged; clipped to N. k = 1 returns a copy.
        tree: optional prebuilt KD-tree of ``points_xz_m``.

    Returns:
        (N, 2) smoothed points in the input order.

    Compiled (``compiled.knn_smooth``, numba) when numba is installed and no tree is given:
    the same neighbours summed in the same order (equal to :func:`knn_smooth_reference` to
    rounding; a tie at the k-th neighbour runs the numpy path).
    """
    pts = np.asarray(points_xz_m, dtype=float)
    k = min(int(k), pts.shape[0])
    if k <= 1:
        return pts.copy()
    kernels = compiled_kernels() if tree is None else None
    if kernels is not None and pts.ndim == 2 and pts.shape[1] == 2:
        out, status = kernels.knn_smooth(np.ascontiguousarray(pts), k)
        if status == 0:
            return out
    return knn_smooth_reference(pts, k, tree)


def knn_smooth_reference(
    points_xz_m: NDArray[np.float64], k: int, tree: cKDTree | None = None
) -> NDArray[np.float64]:
    """numpy path of :func:`knn_smooth` (one KD-tree query)."""
    pts = np.asarray(points_xz_m, dtype=float)
    k = min(int(k), pts.shape[0])
    if k <= 1:
        return pts.copy()
    from scipy.spatial import cKDTree

    tree = cKDTree(pts) if tree is None else tree
    _, idx = tree.query(pts, k=k)
    # mean over the neighbours, summed in the query's order (bit-identical to
    # pts[idx].mean(axis=1) without its (N, k, 2) temporary)
    x, z = pts[:, 0], pts[:, 1]
    sum_x, sum_z = x[idx[:, 0]], z[idx[:, 0]]
    for c in range(1, k):
        sum_x = sum_x + x[idx[:, c]]
        sum_z = sum_z + z[idx[:, c]]
    return np.column_stack([sum_x, sum_z]) / k


def smooth_profile(
    points_xz_m: NDArray[np.float64], k: int = 5, cell_m: float = 0.005, min_points: int = 10
) -> NDArray[np.float64]:
    """Grid thinning (``cell_m``) then kNN smoothing (``k``) of a sagittal profile.

    Returns:
        (M, 2) smoothed profile, metres; unsmoothed (but thinned) if fewer than ``min_points``.
    """
    thinned = grid_thin(points_xz_m, cell_m)
    if thinned.shape[0] < min_points:
        return thinned
    return knn_smooth(thinned, k)
