"""Simulator variety (issue 9, item 4 and item 3's ToF artefact): gait families, stairs with
flights and nosing overhang, rotated IMU mounts, camera mounts, missing bands behind edges.

Short trials and small images only (the test machine is small)."""

from __future__ import annotations

import numpy as np
import pytest

from vio_graph.errors import ConfigError
from vio_graph.geometry import invert_transform, matrix_from_quat_wxyz
from vio_graph.sim import load_scenario, simulate_trial
from vio_graph.sim.config import ScenarioConfig
from vio_graph.sim.gait import MAX_REACH_FRACTION, simulate_gait
from vio_graph.sim.terrain import build_terrain


def _with(cfg: ScenarioConfig, **sections) -> ScenarioConfig:
    """Copy of ``cfg`` with section fields updated: _with(cfg, gait={...}, duration_s=3)."""
    upd = {}
    for key, val in sections.items():
        upd[key] = getattr(cfg, key).model_copy(update=val) if isinstance(val, dict) else val
    return cfg.model_copy(update=upd)


def _sole_gap(terrain, m) -> float:
    fr = np.linspace(0, 1, 15)
    sole = (
        m.heel_xz_m[:, None, :] * (1 - fr[None, :, None])
        + m.toe_xz_m[:, None, :] * fr[None, :, None]
    )
    return float(
        (sole[..., 1] - terrain.height_at(sole[..., 0].ravel()).reshape(sole.shape[:2])).min()
    )


def _max_stance_speed(m) -> float:
    dt = m.t_s[1] - m.t_s[0]
    worst = 0.0
    for point, xz in (("heel", m.heel_xz_m), ("toe", m.toe_xz_m)):
        speed = np.linalg.norm(np.gradient(xz, dt, axis=0), axis=1)
        mask = m.stance_mask(m.t_s, point)
        mask[1:-1] &= mask[:-2] & mask[2:]
        worst = max(worst, float(speed[mask].max()))
    return worst


def _gait(cfg: ScenarioConfig, duration_s: float, seed: int = 2):
    terrain = build_terrain(cfg.terrain)
    return terrain, simulate_gait(
        terrain, cfg.gait, cfg.rig, duration_s, np.random.default_rng(seed)
    )


# ------------------------------------------------------------------ gait families


def test_cadence_scale_stretches_every_phase() -> None:
    base = load_scenario("upstair")
    _, m1 = _gait(base, 6.0)
    _, m2 = _gait(_with(base, gait={"cadence_scale": 0.5}), 12.0)
    for a, b in zip(m1.strides[:4], m2.strides[:4], strict=True):
        assert b.t_next_s - b.t_contact_s == pytest.approx(
            2 * (a.t_next_s - a.t_contact_s), rel=1e-12
        )
        assert b.t_toe_off_s - b.t_contact_s == pytest.approx(
            2 * (a.t_toe_off_s - a.t_contact_s), rel=1e-12
        )
        assert b.toe_xz_m == a.toe_xz_m  # same footholds, same seed
    # same path at half the speed with the via-point swing (the toe's path is planned in
    # space): the ankle at 2 t is the ankle at t (to 1 mm: the hip smoothing window is fixed
    # in seconds, which changes the swing foot pitch slightly). The joint-space swing (the
    # default) follows the hip through the leg's angles, so its path moves by ~2 cm.
    via = {"swing_model": "via_points"}
    _, m1 = _gait(_with(base, gait=via), 6.0)
    _, m2 = _gait(_with(base, gait={**via, "cadence_scale": 0.5}), 12.0)
    t = np.linspace(0.5, 5.5, 51)
    np.testing.assert_allclose(m2.ankle(2 * t), m1.ankle(t), atol=1e-3)
    # accelerations scale with cadence^2
    acc1 = np.abs(m1.ankle(t, 2)).max()
    acc2 = np.abs(m2.ankle(2 * t, 2)).max()
    assert acc2 == pytest.approx(acc1 / 4, rel=0.05)


def test_slow_step_to_step_with_pauses_and_weight_shift() -> None:
    cfg = load_scenario("upstair_step_to_step_slow")
    terrain, m = _gait(cfg, 40.0, seed=4)
    assert _sole_gap(terrain, m) > -1e-6
    assert _max_stance_speed(m) < 1e-6
    reach = np.linalg.norm(m.hip_xz_m - m.ankle_xz_m, axis=1) / (
        m.leg.thigh_length_m + m.leg.shank_length_m
    )
    assert reach.max() < MAX_REACH_FRACTION
    # holds: 2.5-8 s standing with the foot flat and the ankle fixed, the shank swaying
    assert len(m.holds_s) >= 3
    dt = m.t_s[1] - m.t_s[0]
    ankle_speed = np.linalg.norm(np.gradient(m.ankle_xz_m, dt, axis=0), axis=1)
    for t0, t1 in m.holds_s:
        assert 2.5 <= t1 - t0 <= 8.0
        h = (m.t_s > t0) & (m.t_s < min(t1, m.t_s[-1]))
        assert ankle_speed[h].max() < 1e-9
        assert np.abs(m.foot_pitch_rad[h]).max() < 1e-9  # flat on the tread
        sway = np.degrees(np.ptp(m.shank_pitch_rad[h])) / 2  # weight shift, 1-3 deg
        assert 0.2 < sway <= 3.0 + 1e-6, sway
        rate = np.abs(np.gradient(m.shank_pitch_rad[h], dt))
        assert np.degrees(rate.max()) < 2 * np.pi * 0.5 * 3.0 * 1.6  # slow (<= 0.5 Hz)
    # swings of a slow gait: ~1.4 s, gentle ankle accelerations (issue 9: 1.3-6 m/s^2)
    acc = np.linalg.norm(m.ankle(m.t_s, 2), axis=1)
    climbs = [s for s in m.strides[1:] if s.t_next_s < m.t_s[-1]]
    assert len(climbs) >= 2
    for s in climbs:
        assert 1.2 < s.t_next_s - s.t_toe_off_s < 1.6
        sw = (m.t_s > s.t_toe_off_s) & (m.t_s < s.t_next_s)
        assert 1.3 < acc[sw].mean() < 6.0


@pytest.mark.parametrize("lead", ["instrumented", "contralateral"])
def test_step_to_step_both_feet_end_on_the_same_tread(lead) -> None:
    cfg = _with(load_scenario("upstair"), gait={"pattern": "step_to_step", "leading_leg": lead})
    terrain, m = _gait(cfg, 8.0)
    assert _sole_gap(terrain, m) > -1e-6
    assert _max_stance_speed(m) < 1e-6
    climbs = [s for s in m.strides[1:] if s.swing_kind == "ascent"]
    assert len(climbs) >= 3
    for s in climbs:
        # one tread per cycle: the instrumented foot rises by one riser per stride
        assert s.next_toe_xz_m[1] - s.toe_xz_m[1] == pytest.approx(0.147, abs=1e-9)
        if lead == "instrumented":  # instrumented steps up first, the other joins it
            assert s.contra_toe_xz_m == s.toe_xz_m
            assert s.t_contact_s < s.t_contra_contact_s < s.t_toe_off_s
        else:  # the other foot steps up first, the instrumented joins on that tread
            assert s.contra_toe_xz_m == s.next_toe_xz_m
            assert s.t_contra_contact_s < s.t_toe_off_s < s.t_next_s


# ------------------------------------------------------------------ stairs


@pytest.mark.parametrize("kind", ["stair_up", "stair_down"])
@pytest.mark.parametrize(
    ("rise", "tread"), [(0.10, 0.22), (0.20, 0.22), (0.10, 0.35), (0.20, 0.35)]
)
@pytest.mark.parametrize("pattern", ["step_over_step", "step_to_step"])
def test_gait_is_feasible_over_rise_and_tread_range(kind, rise, tread, pattern) -> None:
    cfg = _with(
        load_scenario("upstair"),
        terrain={
            "kind": kind,
            "stair_rise_m": rise,
            "stair_tread_m": tread,
            "n_steps": 5,
            "n_flights": 2,
            "flight_landing_m": 1.0,
            "nosing_overhang_m": 0.03,
        },
        gait={"pattern": pattern},
    )
    terrain, m = _gait(cfg, 7.0)
    assert _sole_gap(terrain, m) > -1e-6
    assert _max_stance_speed(m) < 1e-6
    reach = np.linalg.norm(m.hip_xz_m - m.ankle_xz_m, axis=1) / (
        m.leg.thigh_length_m + m.leg.shank_length_m
    )
    assert reach.max() < MAX_REACH_FRACTION
    # the trial really climbs / descends the stairs
    dz = m.ankle_xz_m[-1, 1] - m.ankle_xz_m[0, 1]
    assert abs(dz) > 2 * rise and np.sign(dz) == (1 if kind == "stair_up" else -1)


def test_multi_flight_overhang_terrain_and_truth() -> None:
    from vio_graph.evaluation.map_accuracy import compare_to_truth
    from vio_graph.mapping.steps import StepGeometry, TerrainGeometry, TerrainKind

    cfg = _with(
        load_scenario("upstair"),
        duration_s=1.0,
        terrain={"n_steps": 4, "n_flights": 3, "flight_landing_m": 0.9, "nosing_overhang_m": 0.025},
        camera={"width_px": 28, "height_px": 22},
    )
    trial = simulate_trial(cfg, 1)
    t = trial.terrain
    e = t.edges_xz_m
    assert e.shape == (12, 2)
    dx = np.diff(e[:, 0])
    np.testing.assert_allclose(dx, [0.28] * 3 + [0.9] + [0.28] * 3 + [0.9] + [0.28] * 3)
    np.testing.assert_allclose(np.diff(e[:, 1]), 0.147)
    # walking surface: nosing tips at the edges, x non-decreasing (metadata contract)
    assert np.all(np.diff(t.profile_xz_m[:, 0]) >= 0)
    np.testing.assert_allclose(t.height_at(e[:, 0] + 1e-4), e[:, 1])
    np.testing.assert_allclose(t.height_at(e[:, 0] - 1e-4), e[:, 1] - 0.147)
    # the mesh has the undercut: risers 2.5 cm behind the nosing tips
    mp = t.mesh_profile_xz_m
    risers = mp[1:][(np.abs(np.diff(mp[:, 0])) < 1e-12) & (np.diff(mp[:, 1]) > 0.05)]
    np.testing.assert_allclose(np.sort(risers[:, 0]), np.sort(e[:, 0] + 0.025))
    # a perfect map matches the recorded truth exactly (flights: no tread across landings)
    steps = []
    for i, edge in enumerate(e):
        top = i % 4 == 3
        steps.append(
            StepGeometry(
                index=i,
                direction="up",
                rise_m=0.147,
                rise_std_m=0.001,
                tread_m=None if top else float(e[i + 1, 0] - edge[0]),
                tread_std_m=0.001,
                nosing_xz_m=edge.copy(),
                nosing_std_xz_m=np.full(2, 0.001),
                lower_z_m=edge[1] - 0.147,
                upper_z_m=edge[1],
                riser_observed=True,
            )
        )
    geo = TerrainGeometry(TerrainKind.STAIR_UP, tuple(steps), (), (), ())
    rep = compare_to_truth(geo, trial.metadata.terrain)
    assert rep["n_steps_matched"] == 12
    assert rep["rise_mae_mm"] == pytest.approx(0.0, abs=1e-6)
    assert rep["tread_mae_mm"] == pytest.approx(0.0, abs=1e-6)
    assert rep["nosing_max_mm"] == pytest.approx(0.0, abs=1e-6)


def test_too_short_landing_is_a_config_error_naming_the_field() -> None:
    cfg = _with(
        load_scenario("upstair"), terrain={"n_steps": 3, "n_flights": 2, "flight_landing_m": 0.2}
    )
    with pytest.raises(ConfigError, match="flight_landing_m"):
        _gait(cfg, 5.0)
    with pytest.raises(ConfigError, match="nosing_thickness_m"):
        build_terrain(
            cfg.terrain.model_copy(update={"nosing_overhang_m": 0.02, "nosing_thickness_m": 0.2})
        )


def test_overhang_nosing_is_rendered_with_its_undercut() -> None:
    """A camera below the nosing height sees the tread slab's underside: depth points at
    the nosing thickness below the tread, between the tip and the set-back riser."""
    from vio_graph.sim.tof import TofCamera
    from vio_graph.sim.trial import R_shank_cam

    cfg = load_scenario("upstair")
    tc = cfg.terrain.model_copy(update={"nosing_overhang_m": 0.03, "n_steps": 3})
    terrain = build_terrain(tc)
    cam = TofCamera(cfg.camera.model_copy(update={"noise": False}), terrain)
    # shank upright, camera 2 cm above the floor, 12 cm before the nosing, 30 deg up
    R = R_shank_cam(-30.0)
    pos = np.array([terrain.feature_x_m - 0.12, 0.0, 0.02])
    depth, _ = cam.render(pos, R, np.random.default_rng(0))
    v, u = np.nonzero(depth > 0)
    z = depth[v, u].astype(float)
    p_c = np.stack([(u - cam.cx) / cam.fx * z, (v - cam.cy) / cam.fy * z, z], 1)
    p_w = p_c @ R.T + pos
    x0 = terrain.feature_x_m
    under = (
        (np.abs(p_w[:, 2] - (0.147 - 0.03)) < 1e-3)
        & (p_w[:, 0] > x0 + 1e-3)
        & (p_w[:, 0] < x0 + 0.03 - 1e-3)
    )
    assert under.sum() > 5


# ------------------------------------------------------------------ rig


@pytest.mark.parametrize(
    ("axes", "rpy"),
    [
        ("shank", (90.0, 0.0, 0.0)),
        ("shank", (0.0, 90.0, 0.0)),
        ("shank", (0.0, 0.0, 90.0)),
        ("shank", (180.0, 0.0, 0.0)),
        ("shank", (17.0, -33.0, 121.0)),
        ("camera", (0.0, 0.0, 0.0)),
    ],
)
def test_rotated_imu_is_the_default_imu_seen_in_rotated_axes(axes, rpy) -> None:
    base = _with(
        load_scenario("upstair"),
        duration_s=2.0,
        imu={"noise": False},
        camera={"width_px": 28, "height_px": 22},
    )
    rot = _with(base, rig={"imu_axes": axes, "imu_rotation_rpy_deg": rpy})
    a, b = simulate_trial(base, 3), simulate_trial(rot, 3)
    # extrinsics: knee_T_cam unchanged, the IMU rotation is what imu_T_cam says
    ka, kb = np.array(a.metadata.extrinsics.knee_T_cam), np.array(b.metadata.extrinsics.knee_T_cam)
    np.testing.assert_array_equal(ka, kb)
    knee_T_imu_b = kb @ invert_transform(np.array(b.metadata.extrinsics.imu_T_cam))
    knee_T_imu_a = ka @ invert_transform(np.array(a.metadata.extrinsics.imu_T_cam))
    R_si = knee_T_imu_b[:3, :3]
    np.testing.assert_allclose(knee_T_imu_b[:3, 3], knee_T_imu_a[:3, 3], atol=1e-12)
    np.testing.assert_allclose(R_si @ R_si.T, np.eye(3), atol=1e-12)
    if axes == "camera":
        np.testing.assert_allclose(
            np.array(b.metadata.extrinsics.imu_T_cam)[:3, :3], np.eye(3), atol=1e-12
        )
    # signals rotated back by the extrinsic rotation are the shank-aligned ones
    np.testing.assert_allclose(b.imu.accel_mps2 @ R_si.T, a.imu.accel_mps2, atol=1e-9)
    np.testing.assert_allclose(b.imu.gyro_radps @ R_si.T, a.imu.gyro_radps, atol=1e-9)
    Ra = np.stack([matrix_from_quat_wxyz(q) for q in a.imu.quat_wxyz])
    Rb = np.stack([matrix_from_quat_wxyz(q) for q in b.imu.quat_wxyz])
    np.testing.assert_allclose(Rb @ R_si.T, Ra, atol=1e-9)
    Rgt = np.stack([matrix_from_quat_wxyz(q) for q in b.groundtruth.imu_state.quat_wxyz])
    np.testing.assert_allclose(Rgt, Rb, atol=1e-9)
    np.testing.assert_allclose(
        b.groundtruth.imu_state.position_m, a.groundtruth.imu_state.position_m, atol=1e-12
    )
    assert np.abs(b.imu.accel_mps2 - a.imu.accel_mps2).max() > 1.0  # really rotated


def test_rotated_imu_with_noise_keeps_the_noise_in_imu_axes() -> None:
    base = _with(load_scenario("upstair"), duration_s=1.0, camera={"width_px": 28, "height_px": 22})
    rot = _with(base, rig={"imu_rotation_rpy_deg": (30.0, 0.0, 0.0)})
    a, b = simulate_trial(base, 3), simulate_trial(rot, 3)
    err_a = a.imu.accel_mps2 - a.imu_truth.specific_force_mps2
    err_b = b.imu.accel_mps2 - b.imu_truth.specific_force_mps2
    np.testing.assert_allclose(err_b, err_a, atol=1e-12)  # same draws, in the IMU axes


@pytest.mark.parametrize(
    ("kind", "z_m", "pitch_deg"),
    [
        ("stair_up", -0.08, 0.0),
        ("stair_up", -0.20, 40.0),
        ("stair_down", -0.08, 40.0),
        ("stair_down", -0.20, 0.0),
    ],
)
def test_camera_mounts_8_to_20_cm_below_knee_see_the_stairs(kind, z_m, pitch_deg) -> None:
    """Usable frames: a step in view (valid depth on two stair levels, or on a riser and a
    level) in most frames over a few strides."""
    name = "upstair" if kind == "stair_up" else "downstair"
    cfg = _with(
        load_scenario(name),
        duration_s=5.0,
        rig={"camera_in_shank_xz_m": (0.07, z_m), "camera_pitch_down_deg": pitch_deg},
        camera={"noise": False, "width_px": 56, "height_px": 43},
    )
    trial = simulate_trial(cfg, 1)
    cam, ter = trial.camera, trial.terrain
    levels = np.concatenate([[0.0], ter.edges_xz_m[:, 1]])
    seen = []
    for i in range(5, trial.n_frames, 10):
        depth, _ = trial.render_frame(i)
        v, u = np.nonzero(depth > 0)
        z = depth[v, u].astype(float)
        p_c = np.stack([(u - cam.cx) / cam.fx * z, (v - cam.cy) / cam.fy * z, z], 1)
        p_w = p_c @ trial.R_world_cam[i].T + trial.camera_position_m[i]
        on_tread = np.isclose(p_w[:, 2], ter.height_at(p_w[:, 0]), atol=2e-3) & (
            np.abs(p_w[:, 1]) < 0.55
        )
        counts = [np.sum(on_tread & (np.abs(p_w[:, 2] - lv) < 2e-3)) for lv in levels]
        riser = (
            np.any(np.abs(p_w[:, 0][:, None] - ter.edges_xz_m[:, 0][None]) < 2e-3, axis=1)
            & ~on_tread
            & (np.abs(p_w[:, 1]) < 0.55)
        )
        n_levels = sum(c >= 20 for c in counts)
        seen.append(n_levels >= 2 or (n_levels >= 1 and riser.sum() >= 20))
    assert np.mean(seen) >= 0.6, np.mean(seen)


# ------------------------------------------------------------------ ToF missing bands


@pytest.mark.parametrize("name", ["upstair", "downstair"])
def test_edge_gap_removes_only_the_band_behind_each_nosing(name) -> None:
    lo, hi = 0.03, 0.06
    base = _with(
        load_scenario(name),
        duration_s=2.0,
        camera={"noise": False, "width_px": 112, "height_px": 86},
    )
    gap = _with(base, camera={"edge_gap_m": (lo, hi)})
    a, b = simulate_trial(base, 1), simulate_trial(gap, 1)
    cam, ter = a.camera, a.terrain
    removed_total = 0
    for i in (10, 30, 50):
        da, _ = a.render_frame(i)
        db, cb = b.render_frame(i)
        kept = db > 0
        np.testing.assert_array_equal(db[kept], da[kept])  # the rest is unchanged
        assert not np.any(kept & (da == 0))
        assert np.all(cb[~kept] == 0)
        bands = cam.edge_gap_bands(a.camera_position_m[i], np.full(ter.edges_xz_m.shape[0], lo))
        v, u = np.nonzero(da > 0)
        z = da[v, u].astype(float)
        p_c = np.stack([(u - cam.cx) / cam.fx * z, (v - cam.cy) / cam.fy * z, z], 1)
        p_w = (p_c @ a.R_world_cam[i].T + a.camera_position_m[i])[:, [0, 2]]
        removed = ~kept[v, u]
        removed_total += removed.sum()
        in_any = np.zeros(p_w.shape[0], dtype=bool)
        for S, w, _ in bands:
            rel = p_w - S
            along, across = rel @ w, np.abs(rel @ np.array([-w[1], w[0]]))
            # no valid point left on the surface within the shortest band behind the edge
            inner = (across < 1e-3) & (along > 2e-3) & (along < lo - 2e-3)
            assert not np.any(inner & ~removed)
            in_any |= (across < 2.5e-3) & (along > -2e-3) & (along < hi + 2e-3)
        # and every removed point lies within the longest band of some edge
        assert np.all(in_any[removed])
        if name == "upstair":  # the band is on the tread behind the ascending nosing
            pts = p_w[removed]
            k = np.argmin(np.abs(pts[:, 0][:, None] - ter.edges_xz_m[:, 0][None]), axis=1)
            near = ter.edges_xz_m[k]
            ok = (np.abs(pts[:, 1] - near[:, 1]) < 2e-3) & (pts[:, 0] - near[:, 0] > -1e-3)
            assert np.all(ok | (pts[:, 0] - near[:, 0] < hi + 3e-3))
    assert removed_total > 100


def test_edge_gap_off_by_default() -> None:
    assert ScenarioConfig().camera.edge_gap_m is None


# ------------------------------------------------------------------ scenarios


def test_slow_scenario_runs_at_15_fps() -> None:
    cfg = load_scenario("upstair_step_to_step_slow")
    assert cfg.gait.pattern == "step_to_step" and cfg.gait.pause_range_s == (2.5, 8.0)
    assert 0.11 <= cfg.terrain.stair_rise_m <= 0.12
    cfg = _with(
        cfg, duration_s=6.0, camera={"frame_rate_hz": 15.0, "width_px": 56, "height_px": 43}
    )
    trial = simulate_trial(cfg, 2)
    assert trial.n_frames == 90
    np.testing.assert_allclose(np.diff(trial.frame_timestamps_s).mean(), 1 / 15, rtol=1e-3)
    depth, _ = trial.render_frame(45)
    assert (depth > 0).mean() > 0.3


def test_long_scenario_covers_two_minutes() -> None:
    cfg = load_scenario("upstair_long")
    assert cfg.duration_s >= 120.0 and cfg.terrain.n_flights > 1
    terrain = build_terrain(cfg.terrain)
    m = simulate_gait(terrain, cfg.gait, cfg.rig, cfg.duration_s, np.random.default_rng(1))
    assert m.t_s[-1] >= cfg.duration_s
    assert _sole_gap(terrain, m) > -1e-6
    # it climbs most of the flights (never off the terrain)
    assert m.ankle_xz_m[-1, 1] > 0.6 * terrain.edges_xz_m[-1, 1]
