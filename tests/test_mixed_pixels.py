"""The front end's mixed-pixel test (frontend.projection.mixed_pixel_jump_m): pixels that
straddle a nosing and return a depth between it and the tread below leave the slice, the
surface pixels on either side of the edge (and a floor seen at a grazing angle) stay."""

from __future__ import annotations

import numpy as np
import pytest

from vio_graph.config import PipelineConfig
from vio_graph.errors import FrontendError
from vio_graph.frontend.config import ProjectionConfig
from vio_graph.frontend.projection import (
    drop_mixed_pixels,
    mixed_pixel_drops,
    sagittal_slice_from_depth,
)

H, W = 120, 64
K = np.array([[110.0, 0.0, W / 2], [0.0, 110.0, H / 2], [0.0, 0.0, 1.0]])


def _nosing_over_tread() -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Looking down over a nosing: an upper tread at 0.60 m depth in rows < 60, the lower tread
    0.18 m farther below (rows >= 60), each tilted slightly (depth grows down the image).
    Returns the clean depth, the depth with mixed pixels along the edge, and their mask."""
    rows = np.arange(H, dtype=np.float64)[:, None]
    depth = 0.60 + 0.001 * rows + np.zeros((1, W))
    depth[60:] += 0.18
    rng = np.random.default_rng(7)
    noisy = depth + rng.normal(0.0, 0.002, depth.shape)  # ~2 mm axial noise
    # the pixels at the edge see both surfaces: 60 % of them mixed, uniformly in between
    mixed = np.zeros(depth.shape, dtype=bool)
    mixed[59:61] = rng.random((2, W)) < 0.6
    near, far = depth[59, 0], depth[60, 0]
    w = rng.random(depth.shape)
    noisy = np.where(mixed, w * near + (1 - w) * far, noisy)
    return depth.astype(np.float32), noisy.astype(np.float32), mixed


def test_mixed_pixels_are_dropped_and_edge_pixels_kept() -> None:
    clean, noisy, mixed = _nosing_over_tread()
    conf = np.full(noisy.shape, 200, dtype=np.uint8)
    out = drop_mixed_pixels(noisy, conf, jump_m=0.04, abs_tol_m=0.01, rel_tol=0.01)
    dropped = out == 0
    # a mixed depth within the tolerance of a surface is no mixed pixel for the slice
    tol = 0.01 + 0.01 * noisy
    clearly = mixed & (noisy - clean[59:60].max() > tol) & (clean[60:61].min() - noisy > tol)
    assert clearly.sum() > 20
    assert dropped[clearly].mean() > 0.9
    # surface pixels, also those at the edge itself (rows 59 and 60), stay
    assert dropped[~mixed].mean() < 0.005
    edge_rows = np.zeros_like(mixed)
    edge_rows[59:61] = True
    assert dropped[edge_rows & ~mixed].mean() < 0.02
    assert np.all(conf == 200)  # the input is not modified


def test_lower_tread_height_recovered_in_the_slice() -> None:
    """The lower tread's points in the slice: with the mixed pixels, some sit above it (between
    the nosing and the tread); with the test, its level is within 2 mm of the clean one."""
    clean, noisy, _ = _nosing_over_tread()
    conf = np.full(noisy.shape, 200, dtype=np.uint8)
    eye = np.eye(3)

    def near_tread_depth(depth: np.ndarray, c: np.ndarray) -> np.ndarray:
        pts = sagittal_slice_from_depth(depth, c, K, eye, half_width_m=0.05, min_depth_m=0.1)
        z = pts[:, 1]  # camera-frame depth along the optical axis (identity rotation)
        return z[z > 0.60 + 0.001 * 60 + 0.01]  # everything past the nosing's depth

    cleaned = drop_mixed_pixels(noisy, conf, 0.04, 0.01, 0.01)
    truth = near_tread_depth(clean, conf)
    before = near_tread_depth(noisy, conf)
    after = near_tread_depth(noisy, cleaned)
    # the points clearly between the nosing and the lower tread (> 2 cm from both): mixed
    # pixels only (a mixed depth close to the nosing's is kept, it extends the nosing by a
    # pixel)
    nosing, tread = 0.60 + 0.001 * 59, 0.60 + 0.001 * 60 + 0.18
    between = lambda z: ((z > nosing + 0.02) & (z < tread - 0.02)).sum()  # noqa: E731
    assert between(before) >= 3
    assert between(after) == 0

    # the lower tread's level next to the edge (mean depth of its first 6 rows, 0.84-0.846 m,
    # and of anything nearer than them past the nosing): pulled towards the nosing before,
    # within 1 mm of the clean image's after
    def edge_level(z: np.ndarray) -> float:
        return float(z[(z > nosing + 0.02) & (z < tread + 0.006)].mean())

    assert edge_level(truth) - edge_level(before) > 0.01
    assert abs(edge_level(after) - edge_level(truth)) < 0.001
    assert after.size > 0.95 * truth.size


def test_floor_at_a_grazing_angle_is_kept() -> None:
    """A floor far away seen at a grazing angle spans several cm in 3x3 pixels; its pixels lie
    between their neighbours' extremes but on the plane through them: none is dropped."""
    v = np.arange(H, dtype=np.float64)[:, None] - H / 2 + 0.5
    # plane y_C = 0.4 m at depth z: z = 0.4 * f / v for rows below the centre; above: far wall
    depth = np.where(v > 4, 0.4 * 110.0 / np.maximum(v, 1.0), 2.0) + np.zeros((1, W))
    rng = np.random.default_rng(3)
    depth = (depth + rng.normal(0.0, 0.001, depth.shape)).astype(np.float32)
    conf = np.full(depth.shape, 200, dtype=np.uint8)
    inner = np.zeros(depth.shape, dtype=bool)
    inner[1:-1, 1:-1] = True
    rows, cols = np.nonzero((v > 6) & inner)
    span = np.abs(depth[rows - 1, cols] - depth[rows + 1, cols])
    assert (span > 0.04).sum() > 100  # the test's jump is crossed on the plane
    drops = mixed_pixel_drops(depth, conf, rows, cols, 0.04, 0.01, 0.01)
    assert drops.mean() < 0.01


def test_config_and_bad_input() -> None:
    assert PipelineConfig().frontend.projection.mixed_pixel_jump_m is None  # off by default
    with pytest.raises(ValueError):
        ProjectionConfig(mixed_pixel_jump_m=0.0)
    with pytest.raises(FrontendError):
        drop_mixed_pixels(np.zeros((4, 4), np.float32), np.zeros((4, 5), np.uint8), 0.04, 0.01, 0)
