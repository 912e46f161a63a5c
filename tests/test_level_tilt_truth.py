"""Known answers of benchmarks/eval_filter_x.py's true tilt: the tilt a slice shows when the
attitude it was rotated with is off by a known pitch, and that the front end's tilt
measurement (frontend/level.py) reads the same number off such a slice."""

from __future__ import annotations

import sys
from pathlib import Path

import numpy as np
import pytest

from vio_graph.frontend.level import measure_surface_tilt
from vio_graph.geometry import remove_yaw, rot_y

sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "benchmarks"))
from eval_filter_x import residual_tilt_rad  # noqa: E402


def _rot_z(a: float) -> np.ndarray:
    c, s = np.cos(a), np.sin(a)
    return np.array([[c, -s, 0.0], [s, c, 0.0], [0.0, 0.0, 1.0]])


@pytest.mark.parametrize("err_deg", [-3.0, -1.0, 0.0, 0.5, 2.0])
def test_residual_tilt_is_minus_the_pitch_error(err_deg: float) -> None:
    # a true attitude with heading, pitch and a little roll; the estimate off in pitch only
    R_true = (
        _rot_z(0.7)
        @ rot_y(np.radians(25.0))
        @ np.array(
            [[1.0, 0.0, 0.0], [0.0, np.cos(0.02), -np.sin(0.02)], [0.0, np.sin(0.02), np.cos(0.02)]]
        )
    )
    R_est = rot_y(np.radians(err_deg)) @ remove_yaw(R_true)
    assert residual_tilt_rad(R_est, R_true) == pytest.approx(-np.radians(err_deg), abs=1e-9)


@pytest.mark.parametrize("err_deg", [-2.0, -0.7, 1.5])
def test_front_end_measures_the_residual_tilt(err_deg: float) -> None:
    """Two level treads (world z = const) seen through an attitude off by err_deg: the slice
    holds R_est R_true^T p = rot_y(err) p, and measure_surface_tilt reads the tilt the
    benchmark calls true."""
    rng = np.random.default_rng(3)
    x = np.concatenate([np.linspace(0.10, 0.38, 60), np.linspace(0.52, 0.80, 60)])
    z = np.concatenate([np.full(60, -0.35), np.full(60, -0.18)])
    p = np.stack([x, np.zeros_like(x), z], axis=1)
    d = np.radians(err_deg)
    seen = (rot_y(d) @ p.T).T[:, [0, 2]]
    seen[:, 1] += rng.normal(0.0, 0.0005, seen.shape[0])
    st = measure_surface_tilt(seen, rng, np.radians(5.0), 0.004, 25, 0.12, 4, 5.0, 0.0)
    assert st is not None and st.n_lines == 2
    truth = residual_tilt_rad(rot_y(d), np.eye(3))
    assert truth == pytest.approx(-d)
    assert st.tilt_rad == pytest.approx(truth, abs=max(3.0 * st.sigma_rad, np.radians(0.02)))
    # the opposite convention would be off by twice the error
    assert abs(st.tilt_rad + truth) > abs(truth)


def test_true_level_of_a_line_is_the_tread_it_overlaps_most() -> None:
    """benchmarks/eval_level_heights.py's truth: the horizontal segment of the terrain
    polyline under most of a line's x extent, with the share it covers."""
    from eval_level_heights import _treads, true_level

    profile = [[-1.0, 0.0], [1.5, 0.0], [1.5, -0.147], [1.78, -0.147], [1.78, -0.294]]
    treads = _treads(np.array(profile))
    assert treads.tolist() == [[-1.0, 1.5, 0.0], [1.5, 1.78, -0.147]]
    assert true_level(treads, 1.55, 1.70) == pytest.approx((-0.147, 1.0))
    h, cover = true_level(treads, 1.40, 1.60)  # straddles the nosing: 0.1 m on each
    assert h in (0.0, -0.147) and cover == pytest.approx(0.5)
