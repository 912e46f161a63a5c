"""Known answers of benchmarks/safety_error_sources.py's truth placement: a keyframe profile
made with a wrong pitch, turned by the pitch error, is the profile the true pose would give."""

from __future__ import annotations

import importlib
import math
import sys
from pathlib import Path
from types import SimpleNamespace

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "benchmarks"))
ses = importlib.import_module("safety_error_sources")


def _rot_y(angle_rad: float) -> np.ndarray:
    """rot_y on (x, z): (0, L) -> (L sin, L cos), the shank pitch's convention."""
    c, s = math.cos(angle_rad), math.sin(angle_rad)
    return np.array([[c, s], [-s, c]])


def test_turn_known_values() -> None:
    # straight down 1 m, turned by 0.1 rad: (-sin 0.1, -cos 0.1)
    out = ses._turn(np.array([[0.0, -1.0]]), 0.1)
    np.testing.assert_allclose(out, [[-math.sin(0.1), -math.cos(0.1)]], atol=1e-15)
    # (0, L) -> (L sin, L cos), as rot_y(pitch) of the shank
    np.testing.assert_allclose(
        ses._turn(np.array([[0.0, 2.0]]), 0.3), [[2 * math.sin(0.3), 2 * math.cos(0.3)]]
    )


def test_turn_recovers_the_true_profile() -> None:
    rng = np.random.default_rng(3)
    p_cam = rng.uniform(-1.0, 1.0, (50, 2))  # points in camera axes
    true_pitch, est_pitch = 0.42, 0.42 - math.radians(1.3)
    seen_true = p_cam @ _rot_y(true_pitch).T  # ground axes with the true attitude
    seen_est = p_cam @ _rot_y(est_pitch).T  # what the filter's attitude makes of it
    assert np.max(np.abs(seen_est - seen_true)) > 0.01  # 1.3 deg at up to 1.4 m
    np.testing.assert_allclose(ses._turn(seen_est, true_pitch - est_pitch), seen_true, atol=1e-12)


def test_true_shank_pitch_from_knee_and_ankle() -> None:
    t = np.array([0.0, 1.0])
    L, pitch = 0.4, np.array([0.0, 0.25])

    def traj(xz: np.ndarray) -> SimpleNamespace:
        return SimpleNamespace(xz_at=lambda _t: xz)

    ankle = np.array([[1.0, 0.1], [2.0, 0.2]])
    knee = ankle + L * np.column_stack((np.sin(pitch), np.cos(pitch)))
    rec = SimpleNamespace(
        groundtruth=SimpleNamespace(trajectories={"knee": traj(knee), "ankle": traj(ankle)})
    )
    np.testing.assert_allclose(ses._true_shank_pitch(rec, t), pitch, atol=1e-12)


def test_keyframes_covering_finds_the_views_of_a_bin() -> None:
    """Profiles placed at their cameras: only those with a point within one bin of x count."""
    cams = {3: np.array([0.0, 0.5]), 7: np.array([1.0, 0.5]), 9: np.array([2.0, 0.5])}
    prof = {
        3: np.array([[1.0, -0.5], [1.2, -0.5]]),  # points at x = 1.0, 1.2
        7: np.array([[0.203, -0.5]]),  # x = 1.203: 3 mm from 1.2
        9: np.array([[-0.7, -0.5]]),  # x = 1.3
        11: np.array([[0.0, -0.5]]),  # no camera: not a keyframe of the run
    }
    assert ses.keyframes_covering(1.2, cams, prof, 0.005) == [3, 7]
    assert ses.keyframes_covering(1.3, cams, prof, 0.005) == [9]
    assert ses.keyframes_covering(1.25, cams, prof, 0.005) == []
