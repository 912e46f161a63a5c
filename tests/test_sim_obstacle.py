"""Obstacles stepped over or onto (gait.obstacle_step_on_depth_m) and the plausibility bound
on the shank's specific force (vio_graph.sim.plausibility): a 25 x 50 cm platform is stepped
onto with a human shank motion, an obstacle forced to be stepped over at that depth is
refused with an error naming its parameters, and the default terrains keep their footholds."""

from __future__ import annotations

import numpy as np
import pytest

from vio_graph.errors import ConfigError, ImplausibleMotionError
from vio_graph.sim import load_scenario
from vio_graph.sim.gait import MAX_REACH_FRACTION
from vio_graph.sim.plausibility import MAX_SHANK_SPECIFIC_FORCE_G, shank_specific_force_g
from vio_graph.sim.trial import _terrain_and_gait, provenance_config, rig_transforms
from vio_graph.sweep import condition_by_name, condition_scenario


def _obstacle(height_m: float, depth_m: float, **gait):
    cfg = load_scenario("obstacle")
    terrain = cfg.terrain.model_copy(
        update={"obstacle_height_m": height_m, "obstacle_depth_m": depth_m}
    )
    return cfg.model_copy(update={"terrain": terrain, "gait": cfg.gait.model_copy(update=gait)})


def _footholds(name: str, seed: int) -> list[tuple[float, float]]:
    cfg = load_scenario(name) if "_" not in name else condition_scenario(condition_by_name(name))
    _, m = _terrain_and_gait(cfg, seed)
    return [s.toe_xz_m for s in m.strides]


@pytest.mark.parametrize("seed", [1000, 1001, 1002])
def test_deep_platform_is_stepped_onto_with_a_human_shank_motion(seed) -> None:
    """obstacle_25x50: the instrumented foot stands on the top (heel and toe on it), steps up
    there with an ascent swing and down off it with a descent swing; the shank IMU's
    specific force stays below 8 g (stepped over it peaked at 61-68 g), the sole never cuts
    the terrain and the leg never overstretches."""
    cfg = condition_scenario(condition_by_name("obstacle_25x50"))
    terrain, m = _terrain_and_gait(cfg, seed)
    xf, h, d = cfg.terrain.approach_length_m, 0.25, 0.50
    foot = m.leg.toe_in_foot_xz_m[0] - m.leg.heel_in_foot_xz_m[0]
    on_top = [s for s in m.strides if abs(s.toe_xz_m[1] - h) < 1e-9]
    assert len(on_top) == 1
    top = on_top[0]
    assert xf < top.toe_xz_m[0] - foot and top.toe_xz_m[0] < xf + d
    assert (top.arrive_kind, top.swing_kind) == ("ascent", "descent")
    assert "obstacle" not in {s.swing_kind for s in m.strides}
    # the foot rests flat on the top between foot flat and heel-off
    flat = (m.t_s > top.t_flat_s) & (m.t_s < top.t_heel_off_s)
    np.testing.assert_allclose(m.toe_xz_m[flat, 1], h, atol=1e-9)
    np.testing.assert_allclose(m.heel_xz_m[flat, 1], h, atol=1e-9)
    _, _, imu_xz = rig_transforms(cfg.rig)
    _, force_g = shank_specific_force_g(m, imu_xz, cfg.duration_s)
    assert force_g.max() < 8.0
    fr = np.linspace(0.0, 1.0, 15)[None, :, None]
    sole = m.heel_xz_m[:, None, :] * (1 - fr) + m.toe_xz_m[:, None, :] * fr
    gap = sole[..., 1] - terrain.height_at(sole[..., 0].ravel()).reshape(sole.shape[:2])
    assert gap.min() > -1e-6
    reach = np.linalg.norm(m.hip_xz_m - m.ankle_xz_m, axis=1) / (
        m.leg.thigh_length_m + m.leg.shank_length_m
    )
    assert reach.max() < MAX_REACH_FRACTION


def test_obstacle_stepped_over_beyond_reach_is_refused() -> None:
    """The same platform stepped over (obstacle_step_on_depth_m raised past its depth): the
    leading foothold is out of the leg's reach, the swing folds back on itself (61 g on seed
    1000) and the simulator refuses it, naming the obstacle and the rule."""
    cfg = _obstacle(0.25, 0.50, obstacle_step_on_depth_m=0.60)
    with pytest.raises(ImplausibleMotionError, match="obstacle_depth_m = 0.50") as err:
        _terrain_and_gait(cfg, 1000)
    assert "gait.obstacle_step_on_depth_m = 0.60" in str(err.value)
    assert "obstacle swing" in str(err.value)
    assert err.value.peak_g > 3 * MAX_SHANK_SPECIFIC_FORCE_G
    assert 2.0 < err.value.t_s < 2.7  # in the swing over the obstacle


def test_plausibility_check_can_be_switched_off_and_is_saved_when_set() -> None:
    """gait.max_shank_specific_force_g: None simulates the folded swing (for stress tests that
    clip the accelerometer on purpose); a lower bound refuses the paper obstacle (4.6 g)."""
    cfg = _obstacle(0.25, 0.50, obstacle_step_on_depth_m=0.60, max_shank_specific_force_g=None)
    _, m = _terrain_and_gait(cfg, 1000)
    assert "obstacle" in {s.swing_kind for s in m.strides}
    assert provenance_config(cfg)["gait"]["max_shank_specific_force_g"] is None
    low = _obstacle(0.14, 0.13, max_shank_specific_force_g=3.0)
    with pytest.raises(ImplausibleMotionError, match="max_shank_specific_force_g = 3 g"):
        _terrain_and_gait(low, 1)
    assert "max_shank_specific_force_g" not in provenance_config(load_scenario("obstacle"))["gait"]


def test_platform_too_short_for_the_foot_is_a_config_error() -> None:
    """Deeper than the step-on rule but shorter than a foot (0.27 m): neither over nor onto."""
    cfg = _obstacle(0.14, 0.27, obstacle_step_on_depth_m=0.20)
    with pytest.raises(ConfigError, match="obstacle_step_on_depth_m"):
        _terrain_and_gait(cfg, 1)


def test_default_terrains_keep_their_footholds() -> None:
    """Known answers from before the step-on rule (atol 1e-9): the paper obstacle (14 x 13
    cm), the sweep's 20 x 30 cm obstacle (stepped over: not deeper than 0.30 m) and upstair."""
    want = {
        ("obstacle", 1): [1.5124224567796654, 2.0488532100124766, 3.0983272432368296],
        ("obstacle_20x30", 1000): [1.510051886512131, 2.046215788572867, 3.2815055199886816],
        ("upstair", 1): [1.21, 1.75218654334581, 2.3123272432368296, 2.8734982199637016],
    }
    for (name, seed), xs in want.items():
        got = _footholds(name, seed)[: len(xs)]
        np.testing.assert_allclose([g[0] for g in got], xs, rtol=0.0, atol=1e-9)
    up_z = [z for _, z in _footholds("upstair", 1)[:4]]
    np.testing.assert_allclose(up_z, [0.0, 0.147, 0.441, 0.735], atol=1e-12)


def test_plausibility_bound_holds_on_the_paper_scenarios() -> None:
    """The bound is far above what the default gait gives (2-11 g over the sweep)."""
    for name in ("upstair", "downstair", "level", "obstacle"):
        cfg = load_scenario(name)
        _, m = _terrain_and_gait(cfg, 1)
        _, _, imu_xz = rig_transforms(cfg.rig)
        _, force_g = shank_specific_force_g(m, imu_xz, cfg.duration_s)
        assert force_g.max() < 0.6 * MAX_SHANK_SPECIFIC_FORCE_G, name


def test_step_on_depth_saved_only_when_set() -> None:
    """Recordings of scenarios that leave the rule at its default save the same config as
    before the field existed; a set value is saved."""
    cfg = load_scenario("obstacle")
    assert "obstacle_step_on_depth_m" not in provenance_config(cfg)["gait"]
    set_cfg = _obstacle(0.14, 0.13, obstacle_step_on_depth_m=0.4)
    assert provenance_config(set_cfg)["gait"]["obstacle_step_on_depth_m"] == 0.4


def test_shank_peaks_benchmark_lists_the_platform_both_ways() -> None:
    """benchmarks/sim_shank_peaks.py bypasses the check: stepped over (the rule raised), the
    25 x 50 cm platform is listed over the bound; stepped onto (the default), under it."""
    import sys
    from pathlib import Path

    sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "benchmarks"))
    import sim_shank_peaks

    over = sim_shank_peaks.shank_peaks("obstacle_25x50", 1000, step_on_depth_m=0.6)
    onto = sim_shank_peaks.shank_peaks("obstacle_25x50", 1000)
    assert over["peak_g"] > MAX_SHANK_SPECIFIC_FORCE_G > 2 * onto["peak_g"]
    assert "obstacle" in over["swings"] and "obstacle" not in onto["swings"]
    assert onto["swings"][1:3] == ["ascent", "descent"]
    small = sim_shank_peaks.shank_peaks("obstacle_25x50", 1000, obstacle_m=(0.14, 0.13))
    assert "obstacle" in small["swings"]  # 13 cm deep: stepped over


def test_implausible_stair_gait_names_the_stair_and_the_cadence() -> None:
    """Twice the cadence with the via-point swing on upstair (43 g on seed 1): the error names
    the stair's rise and tread and the gait fields that made it violent."""
    cfg = load_scenario("upstair")
    gait = cfg.gait.model_copy(update={"cadence_scale": 2.0, "swing_model": "via_points"})
    with pytest.raises(ImplausibleMotionError, match="ascent swing") as err:
        _terrain_and_gait(cfg.model_copy(update={"gait": gait}), 1)
    msg = str(err.value)
    for name in ("terrain.stair_rise_m = 0.147", "gait.cadence_scale = 2", "via_points"):
        assert name in msg
    assert err.value.peak_g > MAX_SHANK_SPECIFIC_FORCE_G
