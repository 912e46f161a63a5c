"""The image-space speckle test (frontend.projection.speckle_min_agree): spurious depth pixels
at random ranges are dropped, a continuous surface with a depth edge is kept."""

from __future__ import annotations

import numpy as np

from vio_graph.config import PipelineConfig
from vio_graph.frontend.projection import drop_speckles


def _stair_like_depth(h: int = 172, w: int = 224) -> np.ndarray:
    """A tilted floor (depth growing up the image) with a riser: a 10 cm depth step at row 80."""
    rows = np.arange(h, dtype=np.float32)[:, None]
    depth = 0.5 + (h - rows) * 0.008 + np.zeros((1, w), dtype=np.float32)
    depth[:80] += 0.10
    return depth.astype(np.float32)


def test_spurious_pixels_are_dropped_and_the_surface_is_kept() -> None:
    rng = np.random.default_rng(4)
    depth = _stair_like_depth()
    conf = np.full(depth.shape, 200, dtype=np.uint8)
    spurious = rng.random(depth.shape) < 0.05
    noisy = depth.copy()
    noisy[spurious] = rng.uniform(0.1, 4.0, spurious.sum()).astype(np.float32)
    out = drop_speckles(noisy, conf, rel_tol=0.03, abs_tol_m=0.01, min_agree=2)
    dropped = out == 0
    # a spurious depth that happens to land on the surface is not an outlier
    really_off = spurious & (np.abs(noisy - depth) > 0.03 * depth + 0.01)
    assert dropped[really_off].mean() > 0.95
    inner = np.zeros_like(spurious)
    inner[1:-1, 1:-1] = True  # border pixels have 3-5 neighbours only
    assert dropped[~spurious & inner].mean() < 0.01
    # the input is not modified, invalid pixels stay invalid
    assert np.all(conf == 200)
    conf[0, 0] = 0
    assert drop_speckles(noisy, conf, 0.03, 0.01, 3)[0, 0] == 0


def test_sparse_returns_need_as_many_agreeing_neighbours_as_they_have() -> None:
    """Around dropout (every other pixel invalid) a surface pixel has 1-4 valid neighbours:
    it is kept if all of them (up to min_agree) agree; an isolated return is dropped, and so
    is a sparse one that disagrees with its only neighbour."""
    depth = _stair_like_depth(40, 40)
    conf = np.zeros(depth.shape, dtype=np.uint8)
    conf[::2, ::2] = 200  # a grid of returns: each sees none of the 8 neighbours...
    conf[10, 11] = 200  # ...except this pair
    conf[30, 31] = 200
    noisy = depth.copy()
    noisy[30, 31] += 0.5  # a pair that disagrees
    out = drop_speckles(noisy, conf, 0.03, 0.01, 2)
    assert out[10, 10] > 0 and out[10, 11] > 0  # one valid neighbour, agreeing: kept
    assert out[30, 30] == 0 and out[30, 31] == 0  # one valid neighbour, disagreeing
    assert out[20, 20] == 0  # no valid neighbour: cannot be told from a spurious return


def test_the_speckle_test_is_on_by_default() -> None:
    assert PipelineConfig().frontend.projection.speckle_min_agree == 2
