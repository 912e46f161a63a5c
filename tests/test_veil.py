"""The front end's veil test (frontend.veil.veil_drops, frontend.projection.veil_window_px):
mixed pixels strung along the viewing ray through a nosing leave the slice; the nosing, the
treads on either side of it and a floor seen at a grazing angle stay."""

from __future__ import annotations

import numpy as np
import pytest
from pydantic import ValidationError

from vio_graph.errors import FrontendError
from vio_graph.frontend.config import ProjectionConfig
from vio_graph.frontend.veil import veil_drops

F_PX = 110.0  # vertical focal length: one pixel row is 1 / F_PX rad
SIGMA_M = 0.002


def _cast(phi: np.ndarray, segments: list[tuple[float, float, float, float]]) -> np.ndarray:
    """Range along the profile rays at elevation angles ``phi`` (rad, from the camera at the
    origin, x forward, z up) to the first of the segments (x0, z0, x1, z1); inf = no hit."""
    d = np.stack([np.cos(phi), np.sin(phi)], axis=-1)
    best = np.full(phi.shape, np.inf)
    for x0, z0, x1, z1 in segments:
        e = np.array([x1 - x0, z1 - z0])
        den = d[:, 0] * -e[1] - d[:, 1] * -e[0]
        with np.errstate(divide="ignore", invalid="ignore"):
            t = (x0 * -e[1] - z0 * -e[0]) / den  # ray parameter (range)
            s = (d[:, 0] * z0 - d[:, 1] * x0) / den  # segment parameter
        hit = np.isfinite(t) & (t > 0) & (s >= 0) & (s <= 1)
        best = np.where(hit & (t < best), t, best)
    return best


def _descent_profile(seed: int = 3) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """A camera 0.5 m above an upper tread looks down over a nosing at x = 0.6 m onto the tread
    0.17 m below. 12 slice columns per row, rows one pixel apart; the pixels whose row
    neighbours span more than 4 cm are mixed with probability 0.6, uniformly between the
    extremes (as the simulator does). Returns the points (N, 2), the mixed mask, the clean
    ranges and the index of the nosing's point (nearest return on the nosing's ray)."""
    rng = np.random.default_rng(seed)
    segments = [(0.1, -0.5, 0.6, -0.5), (0.6, -0.5, 0.6, -0.67), (0.6, -0.67, 1.6, -0.67)]
    rows = np.arange(-0.95, -0.45, 1.0 / F_PX)  # elevation angles of the pixel rows, rad
    r_rows = _cast(rows, segments)
    keep = np.isfinite(r_rows)
    rows, r_rows = rows[keep], r_rows[keep]
    lo = np.minimum(np.minimum(np.roll(r_rows, 1), np.roll(r_rows, -1)), r_rows)
    hi = np.maximum(np.maximum(np.roll(r_rows, 1), np.roll(r_rows, -1)), r_rows)
    lo[[0, -1]], hi[[0, -1]] = r_rows[[0, -1]], r_rows[[0, -1]]
    n_col = 12
    phi = np.repeat(rows, n_col)
    clean = np.repeat(r_rows, n_col)
    jump = np.repeat(hi - lo > 0.04, n_col)
    mixed = jump & (rng.random(phi.size) < 0.6)
    w = rng.random(phi.size)
    r = np.where(mixed, w * np.repeat(lo, n_col) + (1 - w) * np.repeat(hi, n_col), clean)
    r = r + rng.normal(0.0, SIGMA_M, r.size)
    pts = np.column_stack([r * np.cos(phi), r * np.sin(phi)])
    nosing_phi = np.arctan2(-0.5, 0.6)
    on_nosing_ray = np.abs(phi - nosing_phi) < 1.0 / F_PX
    near = np.nonzero(on_nosing_ray & ~mixed)[0]
    nosing = near[np.argmin(clean[near])]
    return pts, mixed, clean, nosing


def test_veil_dropped_nosing_and_treads_kept() -> None:
    pts, mixed, clean, nosing = _descent_profile()
    drop = veil_drops(pts, SIGMA_M, 2.0 / F_PX, 75.0, 3.0, 1.0 / F_PX)
    r = np.hypot(pts[:, 0], pts[:, 1])
    # a veil point far from both surfaces along its ray (beyond the grazing allowance)
    tol = r * np.tan(np.radians(75.0)) * 1.5 / F_PX + 3 * np.sqrt(2) * SIGMA_M  # 1 row away
    in_veil = mixed & (r - 0.78 > tol) & (r.max() > r)
    ray_far = np.hypot(0.6 * 0.67 / 0.5, 0.67)  # the nosing's ray meets the lower tread
    in_veil &= (ray_far - r > tol) & (np.abs(np.arctan2(pts[:, 1], pts[:, 0]) + 0.6947) < 0.02)
    assert in_veil.sum() >= 5
    assert drop[in_veil].mean() > 0.9
    # every surface point stays, the nosing's own point among them
    assert not drop[~mixed].any()
    assert not drop[nosing]
    # the heights the slice keeps: no kept point between the two treads beyond the nosing
    kept = ~drop
    between = (pts[:, 0] > 0.62) & (pts[:, 1] > -0.64) & (pts[:, 1] < -0.53)
    assert np.count_nonzero(kept & between) <= np.count_nonzero(drop & between) // 4
    assert clean.shape == r.shape


def test_grazing_floor_kept() -> None:
    """A floor 0.25 m below the camera out to 74 deg incidence, 8 columns per row, 3 mm noise:
    its range grows fast along the rays, but within the grazing allowance."""
    rng = np.random.default_rng(5)
    phi = np.repeat(np.arange(-1.2, -0.28, 1.0 / F_PX), 8)
    r = _cast(phi, [(0.05, -0.25, 3.0, -0.25)])
    assert np.all(np.isfinite(r))
    r = r + rng.normal(0.0, 0.003, r.size)
    pts = np.column_stack([r * np.cos(phi), r * np.sin(phi)])
    assert not veil_drops(pts, 0.003, 2.0 / F_PX, 75.0, 3.0, 1.0 / F_PX).any()


def test_two_returns_are_not_a_veil() -> None:
    """Two points on one ray (a nosing and the tread behind it) leave no point in between."""
    pts = np.array([[0.6, -0.5], [0.804, -0.67]])
    assert not veil_drops(pts, 0.002, 0.01, 75.0, 3.0).any()
    assert veil_drops(np.zeros((0, 2)), 0.002, 0.01, 75.0, 3.0).shape == (0,)


def test_per_point_sigma_widens_the_allowance() -> None:
    pts = np.array([[0.6, -0.5], [0.7, -0.5834], [0.804, -0.67]])  # one ray, 0.78-1.05 m
    assert veil_drops(pts, 0.002, 0.005, 75.0, 3.0).tolist() == [False, True, False]
    assert not veil_drops(pts, np.array([0.002, 0.05, 0.002]), 0.005, 75.0, 3.0).any()


@pytest.mark.parametrize(
    ("kwargs", "match"),
    [
        ({"points_xz_m": np.zeros((4, 3))}, "must be"),
        ({"points_xz_m": np.array([[0.5, -0.5], [np.nan, 0.1]])}, "finite"),
        ({"sigma_m": -0.001}, "sigma_m"),
        ({"sigma_m": np.ones(3)}, "scalar or"),
        ({"window_rad": 0.0}, "window_rad"),
        ({"max_incidence_deg": 90.0}, "max_incidence_deg"),
        ({"k_sigma": -1.0}, "k_sigma"),
        ({"ray_tol_rad": -0.001}, "ray_tol_rad"),
    ],
)
def test_bad_input_raises(kwargs: dict, match: str) -> None:
    args = {
        "points_xz_m": np.array([[0.6, -0.5], [0.7, -0.58], [0.8, -0.67], [0.9, -0.67]]),
        "sigma_m": 0.002,
        "window_rad": 0.01,
        "max_incidence_deg": 75.0,
        "k_sigma": 3.0,
    }
    args.update(kwargs)
    with pytest.raises(FrontendError, match=match):
        veil_drops(**args)


def test_config_validates_the_veil_fields() -> None:
    assert ProjectionConfig().veil_window_px is None  # off by default
    assert ProjectionConfig(veil_window_px=1.5).veil_window_px == 1.5
    bad_fields = (
        {"veil_window_px": 0.0},
        {"veil_max_incidence_deg": 90.0},
        {"veil_k_sigma": -1},
        {"veil_ray_tol_px": -0.5},
    )
    for bad in bad_fields:
        with pytest.raises(ValidationError):
            ProjectionConfig(**bad)


def _stair_down_frame(seed: int = 11) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """A depth image looking down a staircase from its top landing (2 mm noise) with 60 % of
    the pixels at a > 4 cm jump mixed uniformly between their 3x3 extremes."""
    from vio_graph.frontend.synthetic import (
        camera_rotation,
        pico_flexx_K,
        render_depth,
        stair_polyline,
    )

    K = pico_flexx_K()
    R = camera_rotation(0.7)
    stairs = stair_polyline("stair_down", n_steps=4, start_x_m=0.6)
    cam = np.array([0.0, 4 * 0.147 + 0.45])
    depth, conf = render_depth(stairs, cam, R, K, noise_m=0.002, rng=np.random.default_rng(1))
    rng = np.random.default_rng(seed)
    far = np.where(depth > 0, depth, 10.0)
    pad = np.pad(far, 1, mode="edge")
    h, w = depth.shape
    win = [pad[1 + dy : 1 + dy + h, 1 + dx : 1 + dx + w] for dy in (-1, 0, 1) for dx in (-1, 0, 1)]
    zmax, zmin = np.max(win, axis=0), np.min(win, axis=0)
    mixed = (depth > 0) & (zmax < 10.0) & (zmax - zmin > 0.04) & (rng.random(depth.shape) < 0.6)
    wgt = rng.random(depth.shape)
    depth = np.where(mixed, wgt * zmin + (1 - wgt) * zmax, depth).astype(np.float32)
    return depth, conf, K, R


def test_veil_in_a_rendered_slice_and_the_front_end() -> None:
    """A rendered stair seen from its top landing: the veil test drops most raw slice points
    between two treads (the risers face away: any point off the tread heights, the landing at
    z = -0.45 m and each 0.147 m below, lies in a veil), keeps the points at the first nosing
    (x = 0.6 m), the landing, the first tread and the floor; the front end with it on still
    finds the nosing's corner. A known limit: the treads of steps 2 and 3, seen as strips of
    two or three pixel rows between a nosing and the tread beyond the next one, lie between
    two returns of the bundle and lose points too."""
    from vio_graph.frontend.config import FrontendConfig
    from vio_graph.frontend.frontend import VisualFrontend
    from vio_graph.frontend.projection import sagittal_slice_from_depth
    from vio_graph.types import DepthFrame

    depth, conf, K, R = _stair_down_frame()
    raw = sagittal_slice_from_depth(depth, conf, K, R)
    drop = veil_drops(raw, 0.003, 2.0 / K[1, 1], 75.0, 3.0, 1.0 / K[1, 1])
    off_tread = np.min(np.abs(raw[:, 1:] + 0.45 + 0.147 * np.arange(5)), axis=1)
    veil = off_tread > 0.015
    assert veil.sum() >= 30
    assert drop[veil].mean() > 0.6
    at_nosing = np.hypot(raw[:, 0] - 0.6, raw[:, 1] + 0.45) < 0.01
    assert at_nosing.sum() >= 5 and not drop[at_nosing].any()
    x = raw[:, 0]
    assert not drop[~veil & ((x < 0.9) | (x > 1.45))].any()
    assert drop[~veil].mean() < 0.02
    for proj in ({}, {"veil_window_px": 2.0, "veil_ray_tol_px": 1.0}):
        fe = VisualFrontend(FrontendConfig(projection=ProjectionConfig(**proj)))
        corner = fe.process(DepthFrame(0, 0.0, depth, conf), K, R).corner
        assert corner is not None
        np.testing.assert_allclose(corner.edge_xz_m, [0.6, -0.45], atol=0.03)
