"""The sweep conditions added in the fourth session (obstacle, level standing, a long level
approach, dropped depth frames, a shorter user, the prosthesis rig varied): their scenarios
validate, their gait is feasible over the whole trial, and a short trial simulates with the
change visible in the recording. Small images and short trials only."""

from __future__ import annotations

import numpy as np
import pytest

from vio_graph.sim import simulate_trial
from vio_graph.sim.gait import MAX_REACH_FRACTION, simulate_gait
from vio_graph.sim.terrain import build_terrain
from vio_graph.sweep import condition_by_name, condition_scenario

NEW = (
    "obstacle_20x30",
    "obstacle_curb_8x20",
    "obstacle_25x50",
    "level_standing",
    "approach_3m",
    "dropped_frames",
    "user_1.55m",
    "prosthesis_low_camera",
)


@pytest.mark.parametrize("name", NEW)
def test_new_condition_gait_is_feasible_over_the_whole_trial(name: str) -> None:
    scen = condition_scenario(condition_by_name(name))
    terrain = build_terrain(scen.terrain)
    m = simulate_gait(terrain, scen.gait, scen.rig, scen.duration_s, np.random.default_rng(1000))
    fr = np.linspace(0, 1, 15)
    sole = (
        m.heel_xz_m[:, None, :] * (1 - fr[None, :, None])
        + m.toe_xz_m[:, None, :] * fr[None, :, None]
    )
    ground = terrain.height_at(sole[..., 0].ravel()).reshape(sole.shape[:2])
    assert float((sole[..., 1] - ground).min()) > -1e-6  # never through the terrain
    reach = np.linalg.norm(m.hip_xz_m - m.ankle_xz_m, axis=1) / (
        m.leg.thigh_length_m + m.leg.shank_length_m
    )
    assert reach.max() < MAX_REACH_FRACTION
    if scen.terrain.kind == "stair_up":  # the trial reaches the stair and climbs it
        assert m.ankle_xz_m[-1, 1] - m.ankle_xz_m[0, 1] > 2 * scen.terrain.stair_rise_m


def _short(name: str, duration_s: float):
    scen = condition_scenario(condition_by_name(name))
    cam = scen.camera.model_copy(update={"width_px": 56, "height_px": 43})
    return scen.model_copy(update={"duration_s": duration_s, "camera": cam})


def test_user_155_has_a_shorter_shank_than_the_reference() -> None:
    ref = condition_scenario(condition_by_name("reference"))
    short = condition_scenario(condition_by_name("user_1.55m"))
    rng = np.random.default_rng(0)
    a = simulate_gait(build_terrain(ref.terrain), ref.gait, ref.rig, 1.0, rng)
    b = simulate_gait(build_terrain(short.terrain), short.gait, short.rig, 1.0, rng)
    assert b.leg.shank_length_m == pytest.approx(0.246 * 1.55)
    assert b.leg.shank_length_m < a.leg.shank_length_m - 0.04


def test_dropped_frames_condition_drops_frames_and_blanks_the_blackout() -> None:
    trial = simulate_trial(_short("dropped_frames", 4.6), 1000)
    n_full = int(round(4.6 * 30))
    assert 0.8 * n_full < trial.n_frames < 0.99 * n_full  # 8 % dropped at random
    t = trial.frame_true_time_s
    inside = np.flatnonzero((t >= 4.0) & (t < 4.3))
    assert inside.size >= 5  # the 0.3 s blackout keeps most of its 9 frames
    for i in inside:
        depth, conf = trial.render_frame(int(i))
        assert not (depth > 0).any() and not conf.any()
    assert (trial.render_frame(int(inside[0]) - 1)[0] > 0).any()


def test_approach_3m_starts_with_no_stair_in_view() -> None:
    scen = condition_scenario(condition_by_name("approach_3m"))
    trial = simulate_trial(scen.model_copy(update={"duration_s": 2.0}), 1000)
    # the ground truth's per-frame "a terrain edge in view": none during the first second
    # (the first riser 3 m ahead of the toe), then the stair comes into view
    seen = trial.groundtruth.frame_edge_visible.astype(bool)
    first_s = trial.frame_true_time_s <= 1.0
    assert first_s.sum() > 25 and not seen[first_s].any()
    assert seen[~first_s].any()
