"""grid_thin: the dense bincount path and the sparse (np.unique) path give the same cells."""

from __future__ import annotations

import numpy as np

from vio_graph.frontend import smoothing
from vio_graph.frontend.smoothing import grid_thin


def _reference(pts: np.ndarray, cell_m: float) -> np.ndarray:
    ij = np.floor(pts / cell_m).astype(np.int64)
    ij -= ij.min(axis=0)
    key = ij[:, 0] * (int(ij[:, 1].max()) + 1) + ij[:, 1]
    _, inverse, counts = np.unique(key, return_inverse=True, return_counts=True)
    sx = np.bincount(inverse, weights=pts[:, 0], minlength=counts.size)
    sz = np.bincount(inverse, weights=pts[:, 1], minlength=counts.size)
    return np.column_stack([sx, sz]) / counts[:, None]


def test_known_cells() -> None:
    pts = np.array([[0.001, 0.001], [0.003, 0.002], [0.012, 0.001], [0.001, 0.011]])
    out = grid_thin(pts, 0.01)
    assert np.allclose(out, [[0.002, 0.0015], [0.001, 0.011], [0.012, 0.001]])


def test_dense_and_sparse_paths_equal_the_sorting_reference(monkeypatch) -> None:
    rng = np.random.default_rng(7)
    cases = [
        rng.normal(size=(int(rng.integers(1, 3000)), 2)) * rng.uniform(0.01, 1.0) for _ in range(30)
    ]
    for pts in cases:
        assert np.array_equal(grid_thin(pts, 0.005), _reference(pts, 0.005))
    monkeypatch.setattr(smoothing, "_MAX_DENSE_CELLS", 0)  # force the sparse path
    for pts in cases:
        assert np.array_equal(grid_thin(pts, 0.005), _reference(pts, 0.005))
