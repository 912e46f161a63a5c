"""gait.swing_model: the via-point swing (the default before 2026-12-05) is unchanged; the
joint-space swing (the default) keeps
the stance foot fixed, never cuts the terrain, clears nosings as configured and moves the
camera point within the bounds of published shank kinematics."""

from __future__ import annotations

import numpy as np
import pytest
from pydantic import ValidationError

from vio_graph.sim import load_scenario
from vio_graph.sim.config import GaitConfig
from vio_graph.sim.gait import MAX_REACH_FRACTION, simulate_gait
from vio_graph.sim.terrain import build_terrain

G_MPS2 = 9.81


def _motion(name: str, duration_s: float = 4.0, seed: int = 3, **gait):
    cfg = load_scenario(name)
    cfg = cfg.model_copy(update={"gait": cfg.gait.model_copy(update=gait)})
    terrain = build_terrain(cfg.terrain)
    m = simulate_gait(terrain, cfg.gait, cfg.rig, duration_s, np.random.default_rng(seed))
    return cfg, terrain, m


@pytest.fixture(scope="module")
def joint_space():
    return {
        name: _motion(name, swing_model="joint_space")
        for name in ("upstair", "level", "downstair", "upstair_near_trip")
    }


def _close(got, want) -> None:
    np.testing.assert_allclose(np.asarray(got, dtype=float), want, rtol=0.0, atol=1e-9)


def test_via_point_swing_unchanged() -> None:
    """Known answers: samples of the via-point motion (seed 3, 4 s) as the via-point swing
    produced them before the option existed (bit for bit on the machine that recorded them;
    1e-9 here, so that another CPU's LAPACK rounding does not fail it)."""
    idx = [500, 1500, 2500, 3500]
    _, _, up = _motion("upstair", swing_model="via_points")
    _close(
        up.knee_rad[idx],
        [
            0.7959980160158131,
            0.7892470596246499,
            1.7259217273460687,
            0.7026924059030639,
        ],
    )
    _close(
        up.ankle_xz_m[idx].ravel(),
        [
            0.9789999999999999,
            0.06825,
            1.5334131771589146,
            0.21553030527423317,
            1.8657218076304443,
            0.6455037376362788,
            2.14112861465941,
            0.5872362244165452,
        ],
    )
    _, _, lv = _motion("level", swing_model="via_points")
    _close(
        lv.knee_rad[idx],
        [
            0.7781631675982187,
            0.35032023348090746,
            0.5053520499285459,
            0.6321801151370686,
        ],
    )
    _, _, default = _motion("upstair")
    _, _, explicit = _motion("upstair", swing_model="joint_space")
    np.testing.assert_array_equal(explicit.ankle_xz_m, default.ankle_xz_m)
    assert GaitConfig().swing_model == "joint_space"


@pytest.mark.parametrize("name", ["upstair", "level", "downstair", "upstair_near_trip"])
def test_joint_space_stance_foot_fixed_and_sole_above_terrain(joint_space, name) -> None:
    _, terrain, m = joint_space[name]
    dt = m.t_s[1] - m.t_s[0]
    for point, xz in (("heel", m.heel_xz_m), ("toe", m.toe_xz_m)):
        speed = np.linalg.norm(np.gradient(xz, dt, axis=0), axis=1)
        mask = m.stance_mask(m.t_s, point)
        mask[1:-1] &= mask[:-2] & mask[2:]
        assert mask.sum() > 0.2 * mask.size
        assert speed[mask].max() < 1e-6
    fr = np.linspace(0, 1, 15)
    sole = (
        m.heel_xz_m[:, None, :] * (1 - fr[None, :, None])
        + m.toe_xz_m[:, None, :] * fr[None, :, None]
    )
    gap = sole[..., 1] - terrain.height_at(sole[..., 0].ravel()).reshape(sole.shape[:2])
    assert gap.min() > -1e-6
    reach = np.linalg.norm(m.hip_xz_m - m.ankle_xz_m, axis=1) / (
        m.leg.thigh_length_m + m.leg.shank_length_m
    )
    assert reach.max() < MAX_REACH_FRACTION


def _toe_crossings(terrain, m) -> list[list[float]]:
    """Per ascending swing: toe height above each nosing when the toe passes over it."""
    out = []
    for s in m.strides:
        sel = (m.t_s > s.t_toe_off_s) & (m.t_s < s.t_next_s)
        toe = m.toe_xz_m[sel]
        if s.swing_kind != "ascent" or toe.shape[0] < 2 or m.t_s[-1] < s.t_next_s:
            continue
        row = []
        for xe, ze in terrain.edges_xz_m:
            d = toe[:, 0] - xe
            k = np.flatnonzero((d[:-1] < 0) & (d[1:] >= 0))
            row += [float(toe[i, 1] - ze) for i in k]
        out.append(row)
    return out


@pytest.mark.parametrize(
    ("name", "clearance_m"), [("upstair", 0.045), ("upstair_near_trip", 0.012)]
)
def test_joint_space_toe_clears_each_nosing_as_configured(joint_space, name, clearance_m) -> None:
    cfg, terrain, m = joint_space[name]
    assert cfg.gait.toe_clearance_nosing_m == clearance_m
    rows = _toe_crossings(terrain, m)
    assert len(rows) >= 3
    for row in rows:  # one or two nosings per swing; the lowest crossing is the target
        assert len(row) in (1, 2)
        assert min(row) == pytest.approx(clearance_m, abs=0.004)


def _camera_figures(cfg, m):
    t = m.t_s[(m.t_s > 0.05) & (m.t_s < 4.0)]
    cam = np.asarray(cfg.rig.camera_in_shank_xz_m)
    v = m.shank_point(t, cam, 1)
    a = m.shank_point(t, cam, 2)
    force_g = np.hypot(a[:, 0], a[:, 1] + G_MPS2) / G_MPS2
    knee_rate = np.degrees(np.abs(np.gradient(m.knee_rad, m.t_s)))
    return np.hypot(v[:, 0], v[:, 1]).max(), np.percentile(force_g, 99), knee_rate.max()


@pytest.mark.parametrize("name", ["upstair", "level"])
def test_joint_space_camera_motion_within_published_bounds(joint_space, name) -> None:
    """Shank-worn IMUs read a few g in swing; a point below the knee moves at ~2-3 m/s at
    most; knee angular rate peaks ~400-600 deg/s. The via-point swing exceeds these."""
    cfg, _, m = joint_space[name]
    speed, force_p99, knee_rate = _camera_figures(cfg, m)
    assert speed < 3.3
    assert force_p99 < 5.0
    assert knee_rate < 660.0
    cfg_vp, _, m_vp = _motion(name, swing_model="via_points")
    speed_vp, force_vp, _ = _camera_figures(cfg_vp, m_vp)
    assert force_p99 < force_vp and speed < speed_vp


@pytest.mark.parametrize(
    "gait",
    [
        {"pause_range_s": (0.5, 1.2)},
        {"pattern": "step_to_step"},
        {"pattern": "step_to_step", "leading_leg": "instrumented"},
    ],
)
def test_joint_space_with_pauses_and_step_to_step(gait) -> None:
    _, terrain, m = _motion("upstair", duration_s=6.0, swing_model="joint_space", **gait)
    dt = m.t_s[1] - m.t_s[0]
    speed = np.linalg.norm(np.gradient(m.toe_xz_m, dt, axis=0), axis=1)
    mask = m.stance_mask(m.t_s, "toe")
    mask[1:-1] &= mask[:-2] & mask[2:]
    assert speed[mask].max() < 1e-6
    gap = m.toe_xz_m[:, 1] - terrain.height_at(m.toe_xz_m[:, 0])
    assert gap.min() > -1e-6


def test_peak_knee_fraction_outside_the_swing_is_rejected() -> None:
    with pytest.raises(ValidationError, match="swing_peak_knee_fraction"):
        GaitConfig(swing_peak_knee_fraction={"level": 0.9})
    with pytest.raises(ValidationError):
        GaitConfig(swing_model="min_jerk")


def test_swing_stats_benchmark_compares_the_models() -> None:
    """benchmarks/sim_swing_stats.py: scenario specs parse, bad ones are refused, and on the
    reference upstair the joint-space swing is the gentler one with the configured clearance."""
    import sys
    from pathlib import Path

    sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "benchmarks"))
    import sim_swing_stats

    assert sim_swing_stats.parse_spec("configs/upstair.yaml") == ("configs/upstair.yaml", 1, None)
    assert sim_swing_stats.parse_spec("a.yaml:7:1.2") == ("a.yaml", 7, 1.2)
    with pytest.raises(ValueError, match="path"):
        sim_swing_stats.parse_spec("a.yaml:1:1.0:2")
    with pytest.raises(ValueError):
        sim_swing_stats.parse_spec("a.yaml:one")
    via = sim_swing_stats.swing_stats("upstair", 1, "via_points")
    js = sim_swing_stats.swing_stats("upstair", 1, "joint_space")
    assert js["force_p99_g"] < 5.0 < via["force_p99_g"]
    assert js["peak_speed_mps"] < via["peak_speed_mps"]
    assert js["sole_gap_min_m"] > -1e-6
    assert js["edge_clearance_m"][0] == pytest.approx(0.045, abs=0.004)
