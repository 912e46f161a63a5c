"""The front end's measured depth noise (vio_graph.frontend.noise) and the thinning cell it
sets: known injected noise recovered, the cell follows a noisier camera and leaves the
nominal one alone."""

from __future__ import annotations

import numpy as np
import pytest

from vio_graph.frontend import FrontendConfig, VisualFrontend
from vio_graph.frontend.noise import DepthNoiseTracker, level_residuals, robust_sigma
from vio_graph.frontend.synthetic import camera_rotation, pico_flexx_K, render_depth, stair_polyline
from vio_graph.types import DepthFrame


@pytest.mark.parametrize("sigma_m", [0.002, 0.005])
def test_level_residuals_recover_an_injected_sigma(sigma_m: float) -> None:
    rng = np.random.default_rng(7)
    # a floor at z -0.45 tilted by 2 deg (an attitude error), a tread at -0.30, and riser
    # points that fall in the floor's band (outliers the MAD ignores)
    x1 = rng.uniform(0.1, 0.5, 600)
    floor = np.column_stack([x1, -0.45 + np.tan(np.radians(2)) * x1])
    x2 = rng.uniform(0.55, 0.8, 400)
    tread = np.column_stack([x2, np.full(400, -0.30)])
    pts = np.vstack([floor, tread])
    pts[:, 1] += rng.normal(0.0, sigma_m, pts.shape[0])
    riser = np.column_stack([np.full(20, 0.5), np.linspace(-0.45, -0.43, 20)])
    levels = [(-0.44, 0.1, 0.5), (-0.30, 0.55, 0.8)]
    r = level_residuals(np.vstack([pts, riser]), levels, band_m=0.02)
    assert robust_sigma(r) == pytest.approx(sigma_m, rel=0.1)
    # nearer than 0.6 m only: the tread's points leave, the near part of the floor stays
    near = level_residuals(pts, levels, band_m=0.02, max_range_m=0.6)
    assert 0 < near.size < 600
    assert robust_sigma(np.zeros(0)) != robust_sigma(np.zeros(0))  # nan when empty


def test_tracker_cell_known_answers() -> None:
    t = DepthNoiseTracker(0.005, 2.0, 0.015, warmup=30, window=60, hysteresis=0.6)
    for _ in range(29):
        assert t.update(0.006) == 0.005  # warm-up: the configured cell
    assert t.update(0.006) == pytest.approx(0.012)  # 2 x 6 mm, 2.4 x the cell: changed
    t.reset()
    for _ in range(100):  # 3.5 mm asks for 7 mm, within 60 % of 5 mm: kept
        assert t.update(0.0035) == 0.005
    assert t.sigma_m == pytest.approx(0.0035)
    for _ in range(100):  # nan frames (no level) leave it alone; the cell changes once, when
        t.update(float("nan"))  # the median first asks for more than 8 mm
        t.update(0.010)
    assert 0.008 < t.cell_m <= 0.015
    fresh = DepthNoiseTracker(0.005, 2.0, 0.015, warmup=30, window=60, hysteresis=0.6)
    assert [fresh.update(0.010) for _ in range(30)][-1] == 0.015  # 2 cm asked: capped


def test_line_residuals_equal_the_fit_written_out() -> None:
    """The level line fit (each centring computed once) gives the residuals of the fit
    written out with the means recomputed, bit for bit, flat and vertical lines included."""
    from vio_graph.frontend.noise import _line_residuals

    rng = np.random.default_rng(6)
    for case in range(60):
        n = int(rng.integers(1, 400))
        x = rng.uniform(-0.5, 1.5, n) if case % 7 else np.full(n, 0.3)  # sxx = 0 too
        z = 0.1 * x + rng.normal(0.0, 0.004, n)
        xc = x - x.mean()
        sxx = float(xc @ xc)
        slope = float(xc @ (z - z.mean())) / sxx if sxx > 0 else 0.0
        assert np.array_equal(_line_residuals(x, z), z - z.mean() - slope * xc)


def test_tracker_median_is_np_median_bit_for_bit() -> None:
    """sigma_m (a sorted list's middle, cached per new value) against np.median of the
    window, over odd and even window fills, repeated values and a full window sliding."""
    rng = np.random.default_rng(4)
    t = DepthNoiseTracker(0.005, 2.0, 0.015, warmup=3, window=7, hysteresis=0.6)
    assert t.sigma_m != t.sigma_m  # nan before any value
    window: list[float] = []
    for k in range(40):
        v = float(rng.choice([0.003, 0.0041])) if k % 5 == 0 else float(rng.uniform(0.001, 0.01))
        t.update(v)
        window = (window + [v])[-7:]
        assert t.sigma_m == float(np.median(window))
        assert t.sigma_m == float(np.median(window))  # the cached value
        t.update(float("nan"))  # no value: nothing changes
        assert t.sigma_m == float(np.median(window))
    t.reset()
    t.update(0.1)
    t.update(0.2)
    assert t.sigma_m == float(np.median([0.1, 0.2]))


def _frontend_cells(noise_m: float, n_frames: int = 36) -> tuple[float, float]:
    K = pico_flexx_K(112, 86)
    R_world_cam = camera_rotation(0.6)
    stairs = stair_polyline("stair_up", start_x_m=0.6)
    fe = VisualFrontend(FrontendConfig())
    rng = np.random.default_rng(1)
    for i in range(n_frames):
        cam = np.array([0.005 * i, 0.45])
        depth, conf = render_depth(stairs, cam, R_world_cam, K, (86, 112), noise_m, rng)
        fe.process(DepthFrame(i, i / 30, depth, conf), K, R_world_cam)
    return fe.depth_noise_m, fe.grid_cell_m


def test_frontend_cell_follows_a_noisier_camera_only() -> None:
    sigma_1, cell_1 = _frontend_cells(0.002)
    sigma_3, cell_3 = _frontend_cells(0.006)
    # depth noise along the rays shows as vertical scatter of the levels in proportion
    assert sigma_3 / sigma_1 == pytest.approx(3.0, rel=0.15)
    assert cell_1 == 0.005  # nominal camera: the configured cell
    assert cell_3 == pytest.approx(2 * sigma_3, rel=0.1)  # noisier: two sigmas per cell
    assert cell_3 > 0.008
