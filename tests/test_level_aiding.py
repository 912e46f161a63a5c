"""Level-surface pitch aiding: the tilt of floors and treads in the slice corrects the IMU
attitude (frontend/level.py, filter/attitude.PitchOffsetFilter, OnlineEstimator)."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

from vio_graph.config import PipelineConfig
from vio_graph.filter.attitude import PitchOffsetFilter, with_pitch_offset
from vio_graph.filter.config import LevelAidingConfig
from vio_graph.frontend.level import measure_surface_tilt
from vio_graph.geometry import remove_yaw, rot_x, rot_y, rot_z
from vio_graph.recording.reader import Recording


def _rotate_xz(points: np.ndarray, angle_rad: float) -> np.ndarray:
    """The slice as seen with an attitude whose pitch is off by -angle: rot_xz(-angle)."""
    c, s = np.cos(angle_rad), np.sin(angle_rad)
    x, z = points[:, 0], points[:, 1]
    return np.stack([c * x - s * z, s * x + c * z], axis=1)


def _stair_profile(rng: np.random.Generator, noise_m: float = 0.001) -> np.ndarray:
    """Camera-relative profile: floor 0.45 m below from 0.2 to 0.6 m, a riser, a tread."""
    floor = np.stack([np.linspace(0.2, 0.6, 120), np.full(120, -0.45)], axis=1)
    riser = np.stack([np.full(40, 0.6), np.linspace(-0.45, -0.303, 40)], axis=1)
    tread = np.stack([np.linspace(0.6, 0.88, 90), np.full(90, -0.303)], axis=1)
    p = np.concatenate([floor, riser, tread])
    return p + rng.normal(0, noise_m, p.shape)


@pytest.mark.parametrize("tilt_deg", [-4.0, -1.0, 0.0, 0.7, 3.0])
def test_tilt_of_a_tilted_stair_profile_is_recovered(tilt_deg: float) -> None:
    rng = np.random.default_rng(1)
    p = _rotate_xz(_stair_profile(rng), np.radians(tilt_deg))
    m = measure_surface_tilt(p, np.random.default_rng(0))
    assert m is not None and m.n_lines == 2  # floor and tread share the slope
    assert abs(np.degrees(m.tilt_rad) - tilt_deg) < 0.1
    assert 0 < np.degrees(m.sigma_rad) < 0.1
    # levelling with rot_y(+tilt) makes the surfaces horizontal
    lev = _rotate_xz(p, -m.tilt_rad)
    again = measure_surface_tilt(lev, np.random.default_rng(0))
    assert again is not None and abs(np.degrees(again.tilt_rad)) < 0.05


def test_no_tilt_without_a_level_surface() -> None:
    rng = np.random.default_rng(2)
    riser = np.stack([np.full(80, 0.5), np.linspace(-0.4, -0.2, 80)], axis=1)
    assert measure_surface_tilt(riser + rng.normal(0, 1e-3, riser.shape), rng) is None
    steep = _rotate_xz(_stair_profile(rng), np.radians(12.0))  # beyond max_tilt
    assert measure_surface_tilt(steep, rng) is None
    assert measure_surface_tilt(np.zeros((5, 2)), rng) is None


def test_pitch_offset_is_applied_in_the_ground_frame_with_any_heading() -> None:
    b = np.radians(1.7)
    for yaw in (-2.5, 0.0, 0.4, 3.0):
        R = rot_z(yaw) @ rot_y(np.radians(35.0)) @ rot_x(np.radians(2.0))
        Rc = with_pitch_offset(R, b)
        np.testing.assert_allclose(remove_yaw(Rc), rot_y(b) @ remove_yaw(R), atol=1e-12)
        # heading untouched
        assert np.isclose(np.arctan2(Rc[1, 0], Rc[0, 0]), np.arctan2(R[1, 0], R[0, 0]), atol=0.05)


def test_offset_filter_converges_and_rejects_outliers() -> None:
    cfg = LevelAidingConfig()
    f = PitchOffsetFilter(cfg)
    assert not f.initialised
    true_b = np.radians(2.0)
    rng = np.random.default_rng(3)
    t = 0.0
    for _ in range(90):  # 3 s of frames at 30 fps, measurements with 0.5 deg scatter
        t += 1 / 30
        f.predict(t)
        f.update(true_b - f.offset_rad + rng.normal(0, np.radians(0.5)), np.radians(0.4))
    assert f.initialised and f.n_rejected == 0
    assert abs(np.degrees(f.offset_rad - true_b)) < 0.3
    assert np.degrees(np.sqrt(f.var_rad2)) < 0.3
    # a ramp-like 8 deg reading is refused once converged; the offset does not move
    f.predict(t + 1 / 30)
    b = f.offset_rad
    assert f.update(np.radians(8.0), np.radians(0.05)) == 0.0 and f.n_rejected == 1
    assert f.offset_rad == b
    # the variance grows while no level surface is seen
    v = f.var_rad2
    f.predict(t + 2.0)
    assert f.var_rad2 > v


def test_rotating_the_previous_frame_keeps_icp_consistent() -> None:
    """The estimator corrects its pitch between two frames: told the turn (``ground_turn_rad``)
    the same view seen through the corrected attitude gives a zero displacement; without it,
    the change of attitude reads as motion."""
    from vio_graph.frontend.frontend import VisualFrontend
    from vio_graph.frontend.synthetic import (
        camera_rotation,
        pico_flexx_K,
        render_depth,
        stair_polyline,
    )
    from vio_graph.types import DepthFrame

    stairs = stair_polyline("stair_up", start_x_m=0.6, n_steps=6)
    K = pico_flexx_K()
    R_true = camera_rotation(0.7)
    cam = np.array([0.0, 0.45])
    depth, conf = render_depth(stairs, cam, R_true, K, noise_m=0.002, rng=np.random.default_rng(0))
    frame = DepthFrame(0, 0.0, depth, conf)
    R_wrong = rot_y(np.radians(-1.5)) @ R_true  # attitude off by 1.5 deg of pitch
    step = np.radians(1.5)
    shifts = {}
    for rotate in (False, True):
        fe = VisualFrontend()
        fe.process(frame, K, R_wrong)
        res = fe.process(
            DepthFrame(1, 1 / 30, depth, conf),
            K,
            rot_y(step) @ R_wrong,
            np.zeros(2),
            np.eye(2) * 0.01**2,
            step if rotate else 0.0,
        )
        assert res.displacement is not None, res.rejection_reason
        shifts[rotate] = np.linalg.norm(res.displacement.delta_xz_m)
    assert shifts[True] < 0.001  # same view, same frame: no motion
    assert shifts[False] > 0.005  # 1.5 deg at ~0.5 m reads as centimetres of motion


def _shank_pitch_error_deg(rec_path: Path, enabled: bool) -> float:
    from vio_graph.evaluation.run_metrics import shank_pitch_error_deg
    from vio_graph.replay import Replay
    from vio_graph.viz.rerun_logger import NullVisualizer

    cfg = PipelineConfig()
    la = cfg.filter.level_aiding.model_copy(update={"enabled": enabled})
    cfg = cfg.model_copy(update={"filter": cfg.filter.model_copy(update={"level_aiding": la})})
    rec = Recording.open(rec_path)
    lg = Replay(rec, cfg, {"filter"}, NullVisualizer()).run()
    return shank_pitch_error_deg(
        rec.groundtruth, np.asarray(lg.t_s), np.asarray(lg.shank_pitch_imu)
    )["rms"]


def test_level_aiding_cuts_the_shank_pitch_error_on_a_simulated_trial(short_upstair) -> None:
    """Against ground truth: the vendor-based pitch is off by ~1 deg (MTi-1 model); the
    level-aided pitch must be at least twice as accurate and within 0.5 deg RMS."""
    raw = _shank_pitch_error_deg(short_upstair, enabled=False)
    aided = _shank_pitch_error_deg(short_upstair, enabled=True)
    assert aided < 0.5 and aided < 0.5 * raw, (raw, aided)


def _densely_sampled_stairs(spacing_m: float = 0.002) -> np.ndarray:
    """Points every ``spacing_m`` along three treads and their risers (stair up, level)."""
    from vio_graph.frontend.synthetic import stair_polyline

    v = stair_polyline("stair_up", n_steps=3, start_x_m=0.3, floor_before_m=0.3, floor_after_m=0.05)
    pts = []
    for a, b in zip(v[:-1], v[1:], strict=True):
        n = max(2, int(np.hypot(*(b - a)) / spacing_m))
        pts.append(a + np.linspace(0.0, 1.0, n, endpoint=False)[:, None] * (b - a))
    return np.concatenate(pts)


def test_end_trim_removes_the_corner_rounding_bias() -> None:
    """kNN smoothing rounds every nosing down and fills every tread-riser corner up, the same
    way on each tread: untrimmed, perfectly level stairs read as tilted; with the line ends
    left out of the fit the tilt is zero within 0.05 deg."""
    from vio_graph.frontend.smoothing import smooth_profile

    prof = smooth_profile(_densely_sampled_stairs(), k=5, cell_m=0.005)
    tilt = {}
    for trim in (0.0, 0.025):
        t = measure_surface_tilt(
            prof, np.random.default_rng(0), end_trim_m=trim, correlated_points=1.0
        )
        assert t is not None
        tilt[trim] = np.degrees(t.tilt_rad)
    assert abs(tilt[0.025]) < 0.05, tilt
    assert abs(tilt[0.0]) > 2 * abs(tilt[0.025]) + 0.02, tilt


def _treads_seen_down_a_flight(
    rng: np.random.Generator, tilt_rad: float, ray_sd_m: float = 0.004, iso_sd_m: float = 0.0
) -> np.ndarray:
    """Three treads of a descent seen from a camera 0.45 m above the first, each point's ToF
    error along its ray (``ray_sd_m`` at 0.8 m, growing with range) plus ``iso_sd_m`` in x
    and z, the slice turned by ``tilt_rad`` about the camera (an attitude error: the rays
    still meet at the camera)."""
    parts = []
    for x0, x1, z in _DESCENT_TREADS:
        x = np.linspace(x0, x1, 60)
        zz = np.full_like(x, z)
        rho = np.hypot(x, zz)
        u = np.stack([x, zz], axis=1) / rho[:, None]
        rho = rho + rng.normal(0.0, ray_sd_m, rho.shape) * rho / 0.8
        parts.append(u * rho[:, None] + rng.normal(0.0, iso_sd_m, (x.size, 2)))
    c, s = np.cos(tilt_rad), np.sin(tilt_rad)
    return np.concatenate(parts) @ np.array([[c, s], [-s, c]]).T


#: (x from, x to, height) of the treads relative to the camera, m
_DESCENT_TREADS = ((0.15, 0.40, -0.45), (0.55, 0.80, -0.597), (0.95, 1.20, -0.744))


#: the slice's attitude error in the ray-fit tests (rad)
_TRUE_TILT_RAD = -np.radians(1.0)


def _mean_fit_errors(ray_sd_m: float, iso_sd_m: float, **fit) -> tuple[float, np.ndarray]:
    """Over 400 frames of :func:`_treads_seen_down_a_flight` (``ray_sd_m``, ``iso_sd_m``),
    fitted by ``measure_surface_tilt(..., **fit)``: the mean tilt error (deg) and the mean
    height error of each tread, near to far (mm)."""
    truth = np.array([z for *_, z in _DESCENT_TREADS])
    rng = np.random.default_rng(0)
    tilts, errs = [], []
    for i in range(400):
        p = _treads_seen_down_a_flight(rng, -_TRUE_TILT_RAD, ray_sd_m, iso_sd_m)
        st = measure_surface_tilt(
            p, np.random.default_rng(i), np.radians(5.0), 0.03, 25, 0.12, 4, 5.0, 0.0, **fit
        )
        assert st is not None and st.n_lines == 3
        tilts.append(st.tilt_rad)
        heights = [ln.height_m for ln in sorted(st.lines, key=lambda ln: ln.x_mid_m)]
        errs.append(np.array(heights) - truth)
    return np.degrees(np.mean(tilts) - _TRUE_TILT_RAD), np.mean(errs, axis=0) * 1e3


def test_ray_fit_reads_far_treads_without_the_slant_bias() -> None:
    """Vertical least squares regresses z on x, both noisy along the ray: on a descent the
    common slope leans towards the rays (too negative) and the heights, read at the camera
    with that slope, come out too high, the more the farther the tread. Fitted with the
    errors along the rays, slope and heights are unbiased (mean of 400 frames)."""
    true_tilt = _TRUE_TILT_RAD
    out = {ray_fit: _mean_fit_errors(0.004, 0.0, ray_fit=ray_fit) for ray_fit in ("off", "all")}
    bias_deg, err_mm = out["off"]
    assert bias_deg < -0.04  # measured -0.083 deg
    assert err_mm[2] > 0.8 and err_mm[2] > err_mm[0]  # +0.29 / +0.89 / +1.41 mm
    bias_deg, err_mm = out["all"]
    # standard errors of the means: 0.01 deg, 0.04 / 0.10 / 0.16 mm
    assert abs(bias_deg) < 0.03  # measured +0.001 deg
    assert np.all(np.abs(err_mm) < 0.5)  # measured -0.09 / -0.08 / -0.13 mm
    # "heights": the ray fit's heights, the vertical fit's tilt (what the pitch aiding takes)
    p = _treads_seen_down_a_flight(np.random.default_rng(5), -true_tilt)
    fits = {
        mode: measure_surface_tilt(
            p,
            np.random.default_rng(5),
            np.radians(5.0),
            0.03,
            25,
            0.12,
            4,
            5.0,
            0.0,
            ray_fit=mode,
        )  # fmt: skip
        for mode in ("off", "heights", "all")
    }
    assert fits["heights"].tilt_rad == fits["off"].tilt_rad
    assert [ln.height_m for ln in fits["heights"].lines] == [
        ln.height_m for ln in fits["all"].lines
    ]


@pytest.mark.parametrize("ray_sd_m", [0.0, 0.004])
def test_ray_fit_takes_the_error_that_is_not_along_the_rays(ray_sd_m: float) -> None:
    """Points with 1.5 mm of error in x and z besides (or instead of) the range error: the
    pure ray model (no isotropic part) then leans the other way (the ray through a point
    displaced off its ray is itself off), the model with the isotropic part is unbiased, and
    with no range error it is as unbiased as the vertical fit (mean of 400 frames)."""
    out = {
        mode: _mean_fit_errors(
            ray_sd_m, 0.0015, ray_fit="off" if mode == "off" else "all", isotropic_sigma_m=iso
        )
        for mode, iso in (("off", 0.0), ("pure", 0.0), ("mixed", 0.0015))
    }
    # measured (no range error / 4 mm): pure ray +0.027 / +0.026 deg, far height -0.61 /
    # -0.60 mm; mixed +0.002 / +0.002 deg, heights within 0.15 mm; vertical +0.001 / -0.088
    assert out["pure"][0] > 0.015 and out["pure"][1][2] < -0.35
    assert abs(out["mixed"][0]) < 0.015
    assert np.all(np.abs(out["mixed"][1]) < 0.3)
    if ray_sd_m == 0.0:
        assert abs(out["off"][0]) < 0.015
    else:
        assert out["off"][0] < -0.05 and out["off"][1][2] > 1.0


def test_ray_fit_is_exact_on_clean_treads_and_keeps_a_grazing_line() -> None:
    rng = np.random.default_rng(1)
    p = _treads_seen_down_a_flight(rng, 0.0)
    clean = np.concatenate(
        [np.stack([np.linspace(x0, x1, 60), np.full(60, z)], 1) for x0, x1, z in _DESCENT_TREADS]
    )
    st = measure_surface_tilt(clean, rng, ray_fit="all")
    assert st is not None and abs(st.tilt_rad) < 1e-9
    assert sorted(ln.height_m for ln in st.lines) == pytest.approx([-0.744, -0.597, -0.45])
    # a floor at the camera's height: every ray runs along it, the vertical fit is kept
    level = np.stack([np.linspace(0.3, 1.0, 80), np.zeros(80)], 1) + rng.normal(0, 1e-3, (80, 2))
    a = measure_surface_tilt(level, np.random.default_rng(2), ray_fit="off")
    b = measure_surface_tilt(level, np.random.default_rng(2), ray_fit="all")
    assert a is not None and a == b
    with pytest.raises(ValueError, match="ray_fit"):
        measure_surface_tilt(level, np.random.default_rng(2), ray_fit="yes")
    assert p.shape == (180, 2)


def test_ray_heights_ride_along_the_vertical_fit() -> None:
    """``ray_heights``: every line also carries the ray fit's height (what ray_fit 'heights'
    would have made its height_m) while height_m and the tilt stay the vertical fit's; on a
    descent the far tread's ray height is the nearer to the truth (mean of 100 frames)."""
    truth = np.array([z for *_, z in _DESCENT_TREADS])
    rng = np.random.default_rng(0)
    vertical, ray = [], []
    for i in range(100):
        p = _treads_seen_down_a_flight(rng, np.radians(1.0))
        args = (np.radians(5.0), 0.03, 25, 0.12, 4, 5.0, 0.0)
        both = measure_surface_tilt(p, np.random.default_rng(i), *args, ray_heights=True)
        off = measure_surface_tilt(p, np.random.default_rng(i), *args)
        refit = measure_surface_tilt(p, np.random.default_rng(i), *args, ray_fit="heights")
        assert both is not None and off is not None and refit is not None
        assert both.tilt_rad == pytest.approx(off.tilt_rad, abs=1e-12)
        assert [ln.height_m for ln in both.lines] == pytest.approx(
            [ln.height_m for ln in off.lines], abs=1e-12
        )
        assert [ln.ray_height_m for ln in both.lines] == [ln.height_m for ln in refit.lines]
        assert all(ln.ray_height_m is None for ln in off.lines + refit.lines)
        lines = sorted(both.lines, key=lambda ln: ln.x_mid_m)
        vertical.append([ln.height_m for ln in lines])
        ray.append([ln.ray_height_m for ln in lines])
    err_vertical_mm = (np.mean(vertical, axis=0) - truth) * 1e3
    err_ray_mm = (np.mean(ray, axis=0) - truth) * 1e3
    # measured: vertical +0.25 / +0.82 / +1.28 mm, ray -0.14 / -0.15 / -0.26 (se 0.3) mm
    assert err_vertical_mm[2] > 0.8
    assert abs(err_ray_mm[2]) < 0.5 * err_vertical_mm[2]


@pytest.mark.parametrize("heights", ["filter", "ray_fit"])
def test_the_smoothers_get_the_ray_heights_when_asked(heights: str) -> None:
    """smoother.height_landmark_heights 'ray_fit': the level surfaces handed to the
    smoothers carry the ray-fitted heights, while the filter fuses its own (vertical fit,
    LevelLine.height_m); 'filter': the filter's heights."""
    from tests.conftest import tiny_metadata
    from vio_graph.config import PipelineConfig
    from vio_graph.estimator import OnlineEstimator, RigGeometry

    cfg = PipelineConfig.model_validate(
        {"smoother": {"height_landmark_heights": heights, "factors": {"height_landmarks": True}}}
    )
    est = OnlineEstimator(cfg, RigGeometry.from_metadata(tiny_metadata()))
    est.filter.initialise(0.0, (0.0, 0.0))
    p = _treads_seen_down_a_flight(np.random.default_rng(3), np.radians(1.0))
    est._level_aiding(0.0, p)
    est._fuse_levels(0.0)
    assert est.surface_tilt is not None
    lines = {ln.x_mid_m: ln for ln in est.surface_tilt.lines}
    handed = est._level_observations
    assert len(handed) == 3  # first sights, taken in by the filter
    for obs in handed:
        line = lines[obs.x_rel_m]
        if heights == "ray_fit":
            assert obs.height_rel_m == line.ray_height_m != line.height_m
        else:
            assert obs.height_rel_m == line.height_m and line.ray_height_m is None


def test_weighed_vendor_pull_on_a_simulated_trial(short_upstair) -> None:
    """``filter.attitude.vendor_pitch_sigma_deg``: once level surfaces hold the pitch offset,
    the estimator slows the attitude's pull towards the vendor (its time constant grows well
    past the configured 1 s) and the shank pitch stays within 0.5 deg RMS of the truth."""
    from vio_graph.evaluation.run_metrics import shank_pitch_error_deg
    from vio_graph.replay import Replay
    from vio_graph.viz.rerun_logger import NullVisualizer

    cfg = PipelineConfig()
    att = cfg.filter.attitude.model_copy(update={"vendor_pitch_sigma_deg": 1.0})
    cfg = cfg.model_copy(update={"filter": cfg.filter.model_copy(update={"attitude": att})})
    rec = Recording.open(short_upstair)
    replay = Replay(rec, cfg, {"filter"}, NullVisualizer())
    lg = replay.run()
    assert replay.online.pitch_offset.n_accepted > 0
    assert replay.online.attitude.pitch_time_constant_s > 5.0
    assert replay.online.attitude.time_constant_s == 1.0  # roll and heading: as configured
    err = shank_pitch_error_deg(rec.groundtruth, np.asarray(lg.t_s), np.asarray(lg.shank_pitch_imu))
    assert err["rms"] < 0.5, err


def test_vendor_pitch_sigma_estimated_on_a_simulated_trial(short_upstair) -> None:
    """``filter.attitude.vendor_pitch_sigma_deg: auto`` on a short simulated trial whose
    vendor pitch error is 1 deg RMS (2 s correlation): the estimate is within 0.25 deg of the
    vendor's pitch error RMS over this trial (from the truth: 0.97 deg, estimated 0.88), the
    pitch pull slows past the configured 1 s, the shank pitch stays within 0.5 deg RMS, and
    metrics.json's filter section reports it (outputs.vendor_pitch_summary)."""
    from scipy.spatial.transform import Rotation

    from vio_graph.evaluation.run_metrics import shank_pitch_error_deg
    from vio_graph.outputs import vendor_pitch_summary
    from vio_graph.replay import Replay
    from vio_graph.viz.rerun_logger import NullVisualizer

    cfg = PipelineConfig()
    att = cfg.filter.attitude.model_copy(update={"vendor_pitch_sigma_deg": "auto"})
    cfg = cfg.model_copy(update={"filter": cfg.filter.model_copy(update={"attitude": att})})
    rec = Recording.open(short_upstair)
    replay = Replay(rec, cfg, {"filter"}, NullVisualizer())
    lg = replay.run()
    est = replay.online.vendor_pitch_variance
    assert est is not None and est.n > 20
    st, imu = rec.groundtruth.imu_state, rec.imu
    n = min(st.timestamp_s.size, imu.timestamp_s.size)
    assert np.array_equal(st.timestamp_s[:n], imu.timestamp_s[:n])
    R_true = Rotation.from_quat(st.quat_wxyz[:n, [1, 2, 3, 0]]).as_matrix()
    R_vendor = Rotation.from_quat(imu.quat_wxyz[:n, [1, 2, 3, 0]]).as_matrix()
    pitch_err = [
        Rotation.from_matrix(remove_yaw(v) @ remove_yaw(t).T).as_rotvec()[1]
        for v, t in zip(R_vendor, R_true, strict=True)
    ]
    true_sigma_deg = float(np.degrees(np.sqrt(np.mean(np.square(pitch_err)))))
    assert abs(est.sigma_deg - true_sigma_deg) < 0.25, (est.sigma_deg, true_sigma_deg)
    assert replay.online.attitude.pitch_time_constant_s > 2.0
    err = shank_pitch_error_deg(rec.groundtruth, np.asarray(lg.t_s), np.asarray(lg.shank_pitch_imu))
    assert err["rms"] < 0.5, err
    summary = vendor_pitch_summary(replay.online)
    assert summary["mode"] == "auto" and summary["sigma_deg"] == est.sigma_deg
    assert summary["disagreements"] == est.n


@pytest.mark.parametrize("compiled", ["0", "1"])
def test_a_line_without_x_spread_after_the_end_trim_is_no_tilt(
    compiled: str, monkeypatch: pytest.MonkeyPatch
) -> None:
    """A level line 25 cm long whose points, once its ends are trimmed, all sit at one x (a
    sweep trial's slice did this): no slope is measured (None), not a division by zero."""
    monkeypatch.setenv("VIO_GRAPH_COMPILED", compiled)  # numpy / numba paths
    profile = np.array([[0.0, 0.0], [0.25, 0.0]] + [[0.125, 0.0]] * 28)
    rng = np.random.default_rng(0)
    assert measure_surface_tilt(profile, rng, end_trim_m=0.025) is None
    assert measure_surface_tilt(profile, rng, end_trim_m=0.025, ray_fit="heights") is None
