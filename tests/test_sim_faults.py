"""Fault injection: each configured fault shows up in the simulated data as configured."""

from __future__ import annotations

import numpy as np
import pytest

from vio_graph.sim import ScenarioConfig, load_scenario, simulate, simulate_trial
from vio_graph.sim.config import FaultsConfig


def _cfg(duration_s: float = 3.0, **faults) -> ScenarioConfig:
    cfg = load_scenario("upstair")
    cam = cfg.camera.model_copy(update={"width_px": 56, "height_px": 43})
    return cfg.model_copy(
        update={"duration_s": duration_s, "camera": cam, "faults": FaultsConfig(**faults)}
    )


@pytest.fixture(scope="module")
def clean():
    return simulate_trial(_cfg(), 4)


def test_faults_are_off_by_default_and_leave_data_unchanged(clean) -> None:
    assert FaultsConfig() == load_scenario("upstair").faults
    again = simulate_trial(_cfg(), 4)
    np.testing.assert_array_equal(again.imu.accel_mps2, clean.imu.accel_mps2)
    np.testing.assert_array_equal(again.frame_timestamps_s, clean.frame_true_time_s)
    assert clean.imu_spike_index.size == 0
    assert clean.metadata.provenance.notes == ""


def test_camera_blackout_frames_have_no_valid_pixel(clean) -> None:
    trial = simulate_trial(_cfg(camera_blackout_start_s=1.0, camera_blackout_duration_s=0.5), 4)
    t = trial.frame_true_time_s
    inside = np.flatnonzero((t >= 1.0) & (t < 1.5))
    assert inside.size == 15  # 0.5 s at 30 fps
    for i in inside[[0, 7, -1]]:
        depth, conf = trial.render_frame(int(i))
        assert not (depth > 0).any() and not conf.any()
    for i in (int(inside[0]) - 1, int(inside[-1]) + 1):  # neighbours untouched
        np.testing.assert_array_equal(trial.render_frame(i)[0], clean.render_frame(i)[0])
    faults = trial.metadata.provenance.config["faults"]
    assert faults["camera_blackout_start_s"] == 1.0
    assert faults["camera_blackout_duration_s"] == 0.5
    assert "blackout" in trial.metadata.provenance.notes


def test_dropped_frames_are_missing_and_timestamps_skip(clean) -> None:
    trial = simulate_trial(_cfg(dropped_frame_probability=0.2), 4)
    n_kept = trial.n_frames
    assert 72 - 16 < n_kept < 72 + 16  # 80 % of 90 frames +- 4 sigma of a binomial
    gaps = np.diff(trial.frame_timestamps_s) * 30.0
    assert np.sum(gaps > 1.5) > 6  # timestamps skip one period or more
    assert np.all(np.diff(trial.frame_timestamps_s) > 0)
    # a kept frame is the same frame as in the clean trial (same true time, same pixels)
    src = trial.frame_source_index
    k = int(np.flatnonzero(src < clean.n_frames)[-1])
    assert trial.frame_true_time_s[k] == pytest.approx(clean.frame_true_time_s[src[k]])
    np.testing.assert_array_equal(trial.render_frame(k)[0], clean.render_frame(int(src[k]))[0])
    assert trial.groundtruth.frame_edge_visible.size == n_kept
    assert trial.metadata.provenance.config["faults"]["dropped_frame_probability"] == 0.2


def test_spurious_points_and_occluding_blob(clean) -> None:
    trial = simulate_trial(
        _cfg(
            spurious_point_fraction=0.05,
            occluder_start_s=2.0,
            occluder_duration_s=0.5,
            occluder_depth_m=0.25,
        ),
        4,
    )
    i = 10  # before the occluder: only spurious points
    d0, d1 = clean.render_frame(i)[0], trial.render_frame(i)[0]
    changed = d0 != d1
    assert 0.045 < changed.mean() <= 0.05
    assert np.all((d1[changed] >= 0.1) & (d1[changed] <= 2.4))
    j = int(np.flatnonzero(trial.frame_true_time_s >= 2.0)[0])  # occluder on
    d, d_clean = trial.render_frame(j)[0], clean.render_frame(j)[0]
    # the blob: pixels this close that the clean frame had farther (a riser may be this close)
    near = (d > 0) & (d < 0.3) & (d != d_clean)
    assert 0.25 < near.mean() < 0.45  # ellipse area pi * 0.45 * 0.3 / 4 of the image ~ 0.42
    assert near[35, 28] and not near[5, 28]  # lower centre covered, top free
    assert (d_clean[near] > 0.3).mean() > 0.9


def test_imu_spikes_at_the_configured_rate_and_saturation(clean) -> None:
    trial = simulate_trial(
        _cfg(
            10.0,
            imu_spike_rate_hz=2.0,
            imu_spike_accel_mps2=40.0,
            imu_spike_gyro_radps=6.0,
            imu_gyro_saturation_radps=3.0,
        ),
        4,
    )
    ref = simulate_trial(_cfg(10.0), 4)
    err_a = np.abs(trial.imu.accel_mps2 - ref.imu.accel_mps2).max(axis=1)
    hit = np.flatnonzero(err_a > 20.0)
    np.testing.assert_array_equal(hit, trial.imu_spike_index)
    assert 20 - 4 * np.sqrt(20) < hit.size < 20 + 4 * np.sqrt(20)  # 2 Hz over 10 s
    np.testing.assert_allclose(err_a[hit], 40.0, atol=1e-9)
    gyro = trial.imu.gyro_radps
    assert np.abs(gyro).max() <= 3.0 + 1e-12
    assert np.abs(ref.imu.gyro_radps).max() > 3.0  # the clip really bites on the swing
    assert np.isclose(np.abs(gyro), 3.0).sum() > 5


def test_imu_knock_adds_its_acceleration_for_its_window_only(clean) -> None:
    trial = simulate_trial(_cfg(imu_knock_start_s=1.5, imu_knock_accel_mps2=60.0), 4)
    diff = trial.imu.accel_mps2 - clean.imu.accel_mps2
    hit = np.flatnonzero(np.abs(diff).max(axis=1) > 0)
    np.testing.assert_array_equal(hit, np.arange(150, 160))  # 0.1 s at 100 Hz from 1.5 s
    np.testing.assert_allclose(diff[hit], np.tile([60.0, 0.0, -60.0], (10, 1)), atol=1e-9)
    np.testing.assert_array_equal(trial.imu.gyro_radps, clean.imu.gyro_radps)


def test_time_offset_shifts_depth_stamps_and_jitter_spreads_them(clean) -> None:
    trial = simulate_trial(_cfg(camera_time_offset_s=0.015), 4)
    np.testing.assert_allclose(trial.frame_timestamps_s - trial.frame_true_time_s, 0.015)
    np.testing.assert_allclose(trial.camera_position_m, clean.camera_position_m)
    np.testing.assert_array_equal(trial.imu.timestamp_s, clean.imu.timestamp_s)
    np.testing.assert_array_equal(
        trial.groundtruth.trajectories["camera"].timestamp_s,
        clean.groundtruth.trajectories["camera"].timestamp_s,
    )
    jit = simulate_trial(_cfg(clock_jitter_s=0.002), 4)
    e_frame = jit.frame_timestamps_s - jit.frame_true_time_s
    e_imu = jit.imu.timestamp_s - clean.imu.timestamp_s
    assert 0.0015 < e_frame.std() < 0.0025 and 0.0017 < e_imu.std() < 0.0023
    assert np.all(np.diff(jit.imu.timestamp_s) > 0)
    np.testing.assert_array_equal(jit.joints.timestamp_s, jit.imu.timestamp_s)


def test_faulty_trial_writes_a_readable_recording(tmp_path) -> None:
    from vio_graph.recording.reader import Recording

    cfg = _cfg(
        1.5,
        dropped_frame_probability=0.1,
        camera_blackout_start_s=0.5,
        camera_blackout_duration_s=0.2,
        camera_time_offset_s=-0.01,
    )
    rec = Recording.open(simulate(cfg, 2, tmp_path / "rec"))
    trial = simulate_trial(cfg, 2)
    assert rec.num_frames == trial.n_frames < 45
    np.testing.assert_allclose(rec.frame_timestamps_s, trial.frame_timestamps_s, atol=1e-8)
    assert rec.metadata.provenance.config["faults"]["camera_time_offset_s"] == -0.01
    blk = np.flatnonzero((trial.frame_true_time_s >= 0.5) & (trial.frame_true_time_s < 0.7))
    assert not (rec.frame(int(blk[0])).depth_m > 0).any()
