"""Depth errors that bend the surfaces (simulated multipath, wiggling, depth scale) and the
level aiding's bend test: tread tilt against riser lean (sim/tof.py, frontend/level.py
measure_face_lean, filter/attitude.SurfaceBendTest, the estimator's use of it)."""

from __future__ import annotations

import math

import numpy as np
import pytest

from vio_graph.config import PipelineConfig
from vio_graph.filter.attitude import SurfaceBendTest
from vio_graph.frontend.level import measure_face_lean, measure_surface_tilt
from vio_graph.sim import load_scenario, simulate_trial
from vio_graph.sim.tof import concave_corners_xz


def _rotate_xz(points: np.ndarray, angle_rad: float) -> np.ndarray:
    c, s = np.cos(angle_rad), np.sin(angle_rad)
    x, z = points[:, 0], points[:, 1]
    return np.stack([c * x - s * z, s * x + c * z], axis=1)


def _stairs(rng: np.random.Generator, noise_m: float = 0.0008) -> np.ndarray:
    """Camera-relative profile of two steps up: floor, riser, tread, riser, tread."""
    parts = [
        np.stack([np.linspace(0.25, 0.6, 110), np.full(110, -0.45)], axis=1),
        np.stack([np.full(45, 0.6), np.linspace(-0.45, -0.303, 45)], axis=1),
        np.stack([np.linspace(0.6, 0.88, 90), np.full(90, -0.303)], axis=1),
        np.stack([np.full(45, 0.88), np.linspace(-0.303, -0.156, 45)], axis=1),
        np.stack([np.linspace(0.88, 1.16, 90), np.full(90, -0.156)], axis=1),
    ]
    p = np.concatenate(parts)
    return p + rng.normal(0, noise_m, p.shape)


def _with_multipath(p: np.ndarray, corners: np.ndarray, bias_m: float, decay_m: float):
    """Points pushed away from the camera (the origin) along their rays near the corners."""
    r = np.min(np.linalg.norm(p[:, None, :] - corners[None], axis=2), axis=1)
    ray = p / np.linalg.norm(p, axis=1, keepdims=True)
    return p + (bias_m * np.exp(-r / decay_m))[:, None] * ray


def test_concave_corners_of_stairs_up_and_down() -> None:
    up = np.array([[0, 0], [1, 0], [1, 0.15], [1.28, 0.15], [1.28, 0.3], [2, 0.3]], float)
    np.testing.assert_array_equal(concave_corners_xz(up), [[1.0, 0.0], [1.28, 0.15]])
    down = np.array([[0, 0.3], [1, 0.3], [1, 0.15], [1.28, 0.15], [1.28, 0], [2, 0]], float)
    np.testing.assert_array_equal(concave_corners_xz(down), [[1.0, 0.15], [1.28, 0.0]])
    assert concave_corners_xz(np.array([[0, 0], [2, 0]], float)).shape == (0, 2)


@pytest.mark.parametrize("tilt_deg", [-2.0, 0.0, 1.5])
def test_a_rotation_tilts_treads_and_leans_risers_alike(tilt_deg: float) -> None:
    p = _rotate_xz(_stairs(np.random.default_rng(4)), math.radians(tilt_deg))
    tread = measure_surface_tilt(p, np.random.default_rng(0), end_trim_m=0.025)
    face = measure_face_lean(p, np.random.default_rng(1), level=tread)
    assert tread is not None and face is not None and face.n_lines == 2
    assert abs(math.degrees(tread.tilt_rad) - tilt_deg) < 0.1
    assert abs(math.degrees(face.tilt_rad) - tilt_deg) < 0.3
    assert face.sigma_rad > 0


def test_multipath_tilts_treads_and_leans_risers_in_opposite_senses() -> None:
    rng = np.random.default_rng(5)
    clean = _stairs(rng)
    corners = np.array([[0.6, -0.45], [0.88, -0.303]])
    bent = _with_multipath(clean, corners, 0.015, 0.05)
    tread = measure_surface_tilt(bent, np.random.default_rng(0), end_trim_m=0.025)
    face = measure_face_lean(bent, np.random.default_rng(1), level=tread)
    assert tread is not None and face is not None
    # the treads fall towards their back corner, the risers' feet are pushed forward
    assert math.degrees(tread.tilt_rad) < -0.3
    assert math.degrees(face.tilt_rad) > 0.3
    d = tread.tilt_rad - face.tilt_rad
    assert d * d > 9 * (tread.sigma_rad**2 + face.sigma_rad**2)  # one frame already says so


def test_no_face_lean_without_a_face() -> None:
    rng = np.random.default_rng(6)
    floor = np.stack([np.linspace(0.2, 1.0, 200), np.full(200, -0.45)], axis=1)
    assert measure_face_lean(floor + rng.normal(0, 1e-3, floor.shape), rng) is None
    assert measure_face_lean(np.zeros((4, 2)), rng) is None


def test_bend_test_passes_rigid_pairs_and_flags_a_persistent_disagreement() -> None:
    rng = np.random.default_rng(7)
    test = SurfaceBendTest(memory_s=1.0, sigmas=3.0)
    sd = math.radians(0.5)
    t = 0.0
    for _ in range(300):  # 10 s of rigid surfaces: both see the same pitch error + noise
        t += 1 / 30
        pitch = math.radians(1.0) * math.sin(t)
        test.add(t, pitch + rng.normal(0, sd), sd**2, pitch + rng.normal(0, sd), sd**2)
        assert not test.bent(t)
    for k in range(30):  # surfaces bent: 1.5 deg apart
        t += 1 / 30
        test.add(t, math.radians(-0.75) + rng.normal(0, sd), sd**2, math.radians(0.75), sd**2)
        if k >= 10:
            assert test.bent(t)
    assert test.mean_rad() is not None and math.degrees(test.mean_rad()) < -0.5
    # no face seen for a while: the evidence fades and the verdict with it
    assert not test.bent(t + 10.0)


def test_bend_test_needs_a_few_frames_and_rejects_bad_settings() -> None:
    test = SurfaceBendTest(memory_s=1.0, sigmas=3.0)
    assert not test.bent(0.0) and test.mean_rad() is None
    test.add(0.0, 0.1, 1e-6, -0.1, 1e-6)  # one huge disagreement alone is not a verdict
    assert not test.bent(0.0)
    test.add(0.1, float("nan"), 1e-6, 0.0, 1e-6)  # ignored
    assert test.n_pairs == 1
    with pytest.raises(ValueError):
        SurfaceBendTest(memory_s=0.0, sigmas=3.0)


def _render_pair(**camera) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """One noise-free frame without and with the given systematic depth errors, and the
    camera-frame z of the hit points (m) for reference."""
    cfg = load_scenario("upstair")
    base = cfg.camera.model_copy(update={"noise": False})
    cfg0 = cfg.model_copy(update={"duration_s": 2.0, "camera": base})
    cfg1 = cfg.model_copy(update={"duration_s": 2.0, "camera": base.model_copy(update=camera)})
    t0, t1 = simulate_trial(cfg0, 1), simulate_trial(cfg1, 1)
    i = t0.n_frames // 2
    rng = np.random.default_rng(0)
    d0, _ = t0.camera.render(t0.camera_position_m[i], t0.R_world_cam[i], rng)
    d1, _ = t1.camera.render(t1.camera_position_m[i], t1.R_world_cam[i], rng)
    return d0.astype(float), d1.astype(float), np.asarray(t0.camera_position_m[i])


def test_depth_scale_and_wiggling_errors_are_what_they_say() -> None:
    d0, d1, _ = _render_pair(depth_scale_error=0.01)
    both = (d0 > 0) & (d1 > 0)
    assert both.sum() > 1000
    np.testing.assert_allclose(d1[both], 1.01 * d0[both], rtol=1e-6)
    d0, d1, _ = _render_pair(wiggling_amplitude_m=0.005, wiggling_period_m=0.5)
    both = (d0 > 0) & (d1 > 0)
    np.testing.assert_allclose(
        d1[both] - d0[both], 0.005 * np.sin(2 * np.pi * d0[both] / 0.5), atol=2e-7
    )


def test_multipath_lengthens_depths_near_concave_corners_only() -> None:
    d0, d1, _ = _render_pair(multipath_bias_m=0.02, multipath_decay_m=0.05)
    both = (d0 > 0) & (d1 > 0)
    excess = d1[both] - d0[both]
    assert excess.min() > -1e-6 and excess.max() <= 0.02 + 1e-6
    assert excess.max() > 0.005  # the corners are in view and read long
    assert np.median(excess) < 0.002  # most of the frame is far from any corner


def test_bend_test_is_on_by_default_and_reported(short_upstair) -> None:
    cfg = PipelineConfig()
    assert cfg.filter.level_aiding.bend_test
    from vio_graph.config import load_config
    from vio_graph.recording.reader import Recording
    from vio_graph.replay import Replay
    from vio_graph.viz.rerun_logger import NullVisualizer

    replay = Replay(Recording.open(short_upstair), load_config(None), {"filter"}, NullVisualizer())
    replay.run()
    test = replay.online.bend_test
    assert test is not None and test.n_pairs > 30  # risers seen on most frames
    assert test.n_bent_frames == 0 and test.n_resets == 0  # clean depth: never bent


@pytest.fixture(scope="module")
def multipath_upstair(tmp_path_factory: pytest.TempPathFactory):
    """A 5 s upstair trial (seed 3) whose depths carry 2 cm of multipath in the corners."""
    from vio_graph.sim import simulate

    cfg = load_scenario("upstair")
    cam = cfg.camera.model_copy(update={"multipath_bias_m": 0.02, "multipath_decay_m": 0.05})
    cfg = cfg.model_copy(update={"duration_s": 5.0, "camera": cam})
    return simulate(cfg, seed=3, out_dir=tmp_path_factory.mktemp("rec") / "mpi")


def _pitch_error_and_report(rec_path, **level_aiding):
    from vio_graph.evaluation.run_metrics import shank_pitch_error_deg
    from vio_graph.recording.reader import Recording
    from vio_graph.replay import Replay
    from vio_graph.viz.rerun_logger import NullVisualizer

    cfg = PipelineConfig()
    la = cfg.filter.level_aiding.model_copy(update=level_aiding)
    cfg = cfg.model_copy(update={"filter": cfg.filter.model_copy(update={"level_aiding": la})})
    rec = Recording.open(rec_path)
    replay = Replay(rec, cfg, {"filter"}, NullVisualizer())
    lg = replay.run()
    err = shank_pitch_error_deg(rec.groundtruth, np.asarray(lg.t_s), np.asarray(lg.shank_pitch_imu))
    return err, replay.online.health_report()


def test_multipath_is_caught_and_the_pitch_kept_off_the_bend(multipath_upstair) -> None:
    """Against ground truth: with 2 cm of multipath the treads tilt by ~1 deg and, fused,
    bias the pitch beyond the IMU's own attitude error. The bend test flags the surfaces and
    warns; their tilts are then shrunk towards the IMU's pitch, and the pitch error is
    smaller than with every tilt fused, and not far from the IMU's own (the vendor model's
    error on this seed is itself ~1 deg)."""
    fused, _ = _pitch_error_and_report(multipath_upstair, bend_test=False)
    on, report = _pitch_error_and_report(multipath_upstair, bend_test=True)
    imu, _ = _pitch_error_and_report(multipath_upstair, enabled=False)
    assert on["rms"] < fused["rms"] - 0.1, (on, fused)
    assert on["rms"] < imu["rms"] + 0.15, (on, imu)
    assert any("level surfaces looked bent" in w for w in report["warnings"])


def test_bend_test_counts_judged_frames_and_onsets() -> None:
    test = SurfaceBendTest(memory_s=1.0, sigmas=3.0)
    sd2 = math.radians(0.5) ** 2
    verdicts = []
    t = 0.0
    for k in range(40):
        t += 1 / 30
        if k < 20:  # bent: 2 deg apart
            test.add(t, math.radians(-1.0), sd2, math.radians(1.0), sd2)
        verdicts.append(test.judge(t if k < 20 else t + 10.0))  # then the evidence fades
    bent = [b for b, _ in verdicts]
    onsets = [o for _, o in verdicts]
    first = bent.index(True)
    assert 4 <= first <= 6  # ~5 (decayed) frames are needed before any verdict
    assert all(bent[first:20]) and not any(bent[20:])
    assert onsets.count(True) == 1 and onsets[first]
    assert test.n_bent_frames == 20 - first and test.n_resets == 1
