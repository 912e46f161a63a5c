"""Frame-to-frame association on periodic stairs, the IMU gate, and the whole front end."""

from __future__ import annotations

import numpy as np
import pytest

from vio_graph.frontend.config import FrontendConfig, TrackerConfig
from vio_graph.frontend.corners import CornerFeature, extract_corner
from vio_graph.frontend.frontend import VisualFrontend
from vio_graph.frontend.smoothing import smooth_profile
from vio_graph.frontend.synthetic import (
    camera_rotation,
    pico_flexx_K,
    raycast_profile,
    render_depth,
    stair_edges,
    stair_polyline,
)
from vio_graph.frontend.terrain import classify_terrain
from vio_graph.frontend.tracker import CornerTracker
from vio_graph.types import DepthFrame, TerrainKind

STAIRS = stair_polyline("stair_up", start_x_m=0.6, n_steps=6)  # rise 0.147, tread 0.28
NOSINGS = stair_edges(STAIRS)
STEP = NOSINGS[2] - NOSINGS[1]
# a gate wide enough for the paper's mean-difference association to follow a corner at 15 fps
WIDE_GATE = TrackerConfig(same_corner_gate_m=0.25)


def _view(camera_xz: np.ndarray, x_lo: float, x_hi: float, seed: int):
    """Smoothed profile seen from ``camera_xz`` whose field of view covers world x in
    (x_lo, x_hi), and its corner."""
    prof = raycast_profile(
        STAIRS,
        camera_xz,
        pitch_down_rad=0.6,
        fov_rad=1.2,
        n_rays=1500,
        noise_m=0.003,
        rng=np.random.default_rng(seed),
    )
    world_x = prof[:, 0] + camera_xz[0]
    profile = smooth_profile(prof[(world_x > x_lo) & (world_x < x_hi)])
    terrain, _ = classify_terrain(profile)
    corner = extract_corner(profile, np.random.default_rng(0), terrain=terrain)
    return profile, terrain, corner


def _periodic_pair(delta_xz: np.ndarray):
    """Frame 0 tracks nosing 1; the camera moves by delta and frame 1 only sees nosing 2."""
    c0 = np.array([0.3, 0.60])
    c1 = c0 + delta_xz
    n1, n2 = NOSINGS[1], NOSINGS[2]
    prof0, terr0, corner0 = _view(c0, n1[0] - 0.15, n2[0] + 0.08, seed=1)
    prof1, terr1, corner1 = _view(c1, n1[0] + 0.08, n2[0] + 0.20, seed=2)
    assert terr0 == terr1 == TerrainKind.STAIR_UP
    assert isinstance(corner0, CornerFeature) and isinstance(corner1, CornerFeature)
    # the premise: frame 0 sees nosing 1, frame 1 sees the NEXT nosing
    assert np.linalg.norm(corner0.edge_xz_m + c0 - n1) < 0.003
    assert np.linalg.norm(corner1.edge_xz_m + c1 - n2) < 0.003
    return (prof0, corner0), (prof1, corner1)


# 30 fps (12 cm) and 15 fps (24 cm) swing displacements between frames, along the stair slope
SWING = {"30fps_12cm": np.array([0.10, 0.066]), "15fps_24cm": np.array([0.20, 0.13])}


@pytest.mark.parametrize("name", list(SWING))
def test_naive_nearest_corner_association_is_one_step_off(name: str) -> None:
    delta = SWING[name]
    (p0, f0), (p1, f1) = _periodic_pair(delta)
    tracker = CornerTracker(WIDE_GATE)
    tracker.update(0.0, p0, f0)
    out = tracker.update(1 / 30, p1, f1, predicted_delta_xz_m=None)
    assert out.displacement is not None and out.same_corner  # the paper's gate accepts it
    # ... and the displacement is wrong by exactly one step (tread and rise)
    np.testing.assert_allclose(out.displacement.delta_xz_m, delta - STEP, atol=0.005)
    assert np.linalg.norm(out.displacement.delta_xz_m - delta) > 0.25


@pytest.mark.parametrize("name", list(SWING))
def test_imu_seeded_gated_tracker_gets_the_displacement(name: str) -> None:
    delta = SWING[name]
    (p0, f0), (p1, f1) = _periodic_pair(delta)
    tracker = CornerTracker(WIDE_GATE)
    first = tracker.update(0.0, p0, f0)
    assert first.displacement is None and first.reason == "no previous frame"
    imu_error = np.array([0.015, -0.012])  # a realistic one-frame IMU prediction error
    out = tracker.update(1 / 30, p1, f1, delta + imu_error, np.eye(2) * 0.02**2)
    assert out.reason is None and out.displacement is not None
    assert np.linalg.norm(out.displacement.delta_xz_m - delta) < 0.005
    assert out.displacement.t0_s == 0.0 and out.displacement.t1_s == pytest.approx(1 / 30)
    # a different physical corner: new track id, observation is the corner minus the camera
    assert not out.same_corner and out.track_id != first.track_id
    assert out.observation is not None and out.observation.track_id == out.track_id
    np.testing.assert_allclose(out.observation.corner_rel_xz_m, f1.edge_xz_m)


def test_paper_mode_features_only_cannot_measure_across_a_corner_change() -> None:
    (p0, f0), (p1, f1) = _periodic_pair(SWING["30fps_12cm"])
    tracker = CornerTracker(TrackerConfig(icp_target="features"))
    tracker.update(0.0, p0, f0)
    out = tracker.update(1 / 30, p1, f1, SWING["30fps_12cm"], np.eye(2) * 0.02**2)
    assert out.displacement is None and "corner changed" in (out.reason or "")


def test_same_corner_keeps_its_track_id() -> None:
    c0 = np.array([0.3, 0.60])
    delta = np.array([0.05, 0.03])
    n1 = NOSINGS[1]
    p0, _, f0 = _view(c0, n1[0] - 0.15, n1[0] + 0.25, seed=3)
    p1, _, f1 = _view(c0 + delta, n1[0] - 0.15, n1[0] + 0.25, seed=4)
    tracker = CornerTracker()
    a = tracker.update(0.0, p0, f0)
    b = tracker.update(1 / 30, p1, f1, delta, np.eye(2) * 0.01**2)
    assert b.same_corner and b.track_id == a.track_id
    assert b.displacement is not None
    assert np.linalg.norm(b.displacement.delta_xz_m - delta) < 0.003


def test_prediction_half_a_step_off_gives_no_seeded_displacement() -> None:
    """With T0 half a stair period off, the seeded ICP cannot produce a result that passes the
    checks; the unseeded lost-track search (relocalise_after_frames) finds the true one."""
    delta = SWING["30fps_12cm"]
    (p0, f0), (p1, f1) = _periodic_pair(delta)
    outs = []
    for after in (None, 0):
        tracker = CornerTracker(WIDE_GATE.model_copy(update={"relocalise_after_frames": after}))
        tracker.update(0.0, p0, f0)
        outs.append(tracker.update(1 / 30, p1, f1, delta + 0.5 * STEP, np.eye(2) * 0.01**2))
    seeded, searched = outs
    assert seeded.displacement is None and seeded.icp is not None and seeded.reason
    assert searched.relocalised and searched.displacement is not None
    assert np.linalg.norm(searched.displacement.delta_xz_m - delta) < 0.005


def test_gate_rejects_moved_terrain_but_accepts_it_without_gate() -> None:
    """Frame 1 sees terrain shifted up by 5 cm (e.g. a wrong frame): ICP is self-consistent
    but disagrees with the IMU; with the gate disabled the wrong displacement gets through."""
    c0, delta = np.array([0.3, 0.60]), np.array([0.05, 0.03])
    n1 = NOSINGS[1]
    p0, _, f0 = _view(c0, n1[0] - 0.15, n1[0] + 0.25, seed=5)
    shift = np.array([0.0, 0.05])
    p1, _, f1 = _view(c0 + delta - shift, n1[0] - 0.15, n1[0] + 0.25, seed=6)  # = terrain + shift
    outs = []
    for gate, after in ((TrackerConfig().gate_chi2, None), (1e9, None), (13.8, 0)):
        tracker = CornerTracker(TrackerConfig(gate_chi2=gate, relocalise_after_frames=after))
        tracker.update(0.0, p0, f0)
        outs.append(tracker.update(1 / 30, p1, f1, delta, np.eye(2) * 0.005**2))
    gated, ungated, searched = outs
    assert gated.displacement is None and "IMU prediction" in (gated.reason or "")
    assert ungated.displacement is not None
    np.testing.assert_allclose(ungated.displacement.delta_xz_m, delta - shift, atol=0.004)
    # the lost-track search (relocalise_after_frames) hands the same displacement on: the
    # filter's gate and its continuity rule decide (estimator._widen_for_relocalised)
    assert searched.relocalised and searched.displacement is not None
    np.testing.assert_allclose(searched.displacement.delta_xz_m, delta - shift, atol=0.004)


def test_no_displacement_without_corner_or_after_a_gap() -> None:
    p0, _, f0 = _view(np.array([0.3, 0.6]), 0.7, 1.2, seed=7)
    tracker = CornerTracker()
    assert tracker.update(0.0, p0, None).reason == "no corner in this frame"
    assert tracker.update(1 / 30, p0, f0, np.zeros(2)).displacement is not None
    assert tracker.update(1.0, p0, f0, np.zeros(2)).reason == "frame gap too large"


# --- the whole front end on rendered depth images --------------------------------------------


def test_visual_frontend_tracks_a_rendered_stair_sequence() -> None:
    K = pico_flexx_K()
    R_world_cam = camera_rotation(0.7)
    rng = np.random.default_rng(0)
    cams = [np.array([0.0, 0.45]) + i * np.array([0.012, 0.006]) for i in range(6)]
    frontend = VisualFrontend(FrontendConfig())
    results = []
    for i, cam in enumerate(cams):
        depth, conf = render_depth(STAIRS, cam, R_world_cam, K, noise_m=0.004, rng=rng)
        pred = None if i == 0 else cams[i] - cams[i - 1] + np.array([0.004, -0.003])
        results.append(
            frontend.process(
                DepthFrame(i, i / 30, depth, conf), K, R_world_cam, pred, np.eye(2) * 0.01**2
            )
        )
    assert all(r.terrain == TerrainKind.STAIR_UP for r in results)
    assert results[0].displacement is None and results[0].corner is not None
    for r in results[1:]:
        assert r.displacement is not None, r.rejection_reason
        assert np.linalg.norm(r.displacement.delta_xz_m - [0.012, 0.006]) < 0.002
        assert r.observation is not None
        assert r.observation.track_id == results[0].observation.track_id
        assert set(r.timings_ms) == {
            "projection",
            "smoothing",
            "terrain",
            "corners",
            "icp",
            "total",
        }
    # the tracked corner is a true nosing
    nosing_err = np.linalg.norm(NOSINGS - (results[-1].corner.edge_xz_m + cams[-1]), axis=1)
    assert nosing_err.min() < 0.003
