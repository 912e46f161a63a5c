"""Stairs the regular simulator never built: rises and treads that vary step to step (drawn
from the trial's seed), a first riser of another height, open risers. The truth (profile,
edges) must follow the drawn stair, the feet must stand on the actual treads, and the map
must report each step's own rise and tread.

Short trials and small stairs only (the test machine is small)."""

from __future__ import annotations

import numpy as np
import pytest

from tests.test_mapping_synth import camera_track, observe
from vio_graph.errors import ConfigError
from vio_graph.evaluation.map_accuracy import compare_to_truth
from vio_graph.mapping.local_map import TerrainMap2D
from vio_graph.mapping.steps import estimate_terrain_geometry
from vio_graph.recording.metadata import TerrainInfo
from vio_graph.sim import load_scenario, simulate_trial
from vio_graph.sim.config import TerrainConfig
from vio_graph.sim.gait import simulate_gait
from vio_graph.sim.terrain import build_terrain, stair_steps
from vio_graph.sim.trial import provenance_config

RISE_M, TREAD_M = 0.147, 0.28
JITTER = {"rise_jitter_m": 0.015, "tread_jitter_m": 0.02}


def _rises_treads(edges_xz_m: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Nosing-to-nosing rises (abs dz) and treads (dx) of consecutive edges."""
    d = np.diff(np.asarray(edges_xz_m), axis=0)
    return np.abs(d[:, 1]), d[:, 0]


@pytest.mark.parametrize("kind", ["stair_up", "stair_down"])
def test_irregular_steps_are_the_drawn_ones_and_reproducible(kind: str) -> None:
    cfg = TerrainConfig(kind=kind, n_steps=10, **JITTER)
    t1 = build_terrain(cfg, np.random.default_rng(7))
    t2 = build_terrain(cfg, np.random.default_rng(7))
    t3 = build_terrain(cfg, np.random.default_rng(8))
    np.testing.assert_array_equal(t1.edges_xz_m, t2.edges_xz_m)
    np.testing.assert_array_equal(t1.profile_xz_m, t2.profile_xz_m)
    assert not np.array_equal(t1.edges_xz_m, t3.edges_xz_m)
    assert t1.irregular
    # the known answer: the same draws as stair_steps (rises first, then treads)
    rng = np.random.default_rng(7)
    rises = RISE_M + rng.uniform(-0.015, 0.015, 10)
    treads = TREAD_M + rng.uniform(-0.02, 0.02, 10)
    steps = np.array(stair_steps(cfg, np.random.default_rng(7)))
    np.testing.assert_allclose(steps[:, 1] - steps[:, 2], rises, atol=1e-12)
    np.testing.assert_allclose(np.diff(steps[:, 0]), treads[:9], atol=1e-12)
    # the truth follows them: edges are the nosings, the profile's risers have the rises
    np.testing.assert_array_equal(t1.edges_xz_m, steps[:, :2])
    p = t1.profile_xz_m
    vertical = np.abs(np.diff(p[:, 0])) < 1e-12
    np.testing.assert_allclose(np.abs(np.diff(p[:, 1]))[vertical], rises, atol=1e-12)
    r, t = _rises_treads(t1.edges_xz_m)
    assert np.all(np.abs(r - RISE_M) <= 0.015 + 1e-12) and np.ptp(r) > 0.01
    assert np.all(np.abs(t - TREAD_M) <= 0.02 + 1e-12) and np.ptp(t) > 0.01
    # the height under each tread's middle is its nosing height (ascent) / next (descent)
    mid = 0.5 * (t1.edges_xz_m[:-1, 0] + t1.edges_xz_m[1:, 0])
    z_tread = t1.edges_xz_m[:-1, 1] if kind == "stair_up" else t1.edges_xz_m[1:, 1]
    np.testing.assert_allclose(t1.height_at(mid), z_tread, atol=1e-12)


def test_regular_stairs_are_unchanged_and_need_no_generator() -> None:
    cfg = TerrainConfig(kind="stair_up", n_steps=4)
    t = build_terrain(cfg)
    assert not t.irregular
    np.testing.assert_array_equal(
        t.edges_xz_m, [(1.5 + i * TREAD_M, (i + 1) * RISE_M) for i in range(4)]
    )
    with pytest.raises(Exception, match="random generator"):
        build_terrain(cfg.model_copy(update=JITTER))
    with pytest.raises(ConfigError, match="rise"):
        build_terrain(cfg.model_copy(update={"first_rise_m": 0.01}), np.random.default_rng(0))


@pytest.mark.parametrize("kind", ["stair_up", "stair_down"])
def test_first_and_last_rise(kind: str) -> None:
    cfg = TerrainConfig(kind=kind, n_steps=5, first_rise_m=0.19, last_rise_m=0.12)
    t = build_terrain(cfg)
    steps = np.array(stair_steps(cfg))
    np.testing.assert_allclose(steps[:, 1] - steps[:, 2], [0.19, RISE_M, RISE_M, RISE_M, 0.12])
    np.testing.assert_allclose(np.diff(t.edges_xz_m[:, 0]), TREAD_M)
    top = 0.19 + 3 * RISE_M + 0.12
    assert t.profile_xz_m[-1, 1] == pytest.approx(top if kind == "stair_up" else -top)


def test_provenance_leaves_the_new_fields_out_at_their_defaults() -> None:
    cfg = load_scenario("upstair")
    saved = provenance_config(cfg)
    assert "rise_jitter_m" not in saved["terrain"] and "open_risers" not in saved["terrain"]
    assert "contact" not in saved
    irregular = cfg.model_copy(update={"terrain": cfg.terrain.model_copy(update=JITTER)})
    saved = provenance_config(irregular)
    assert saved["terrain"]["rise_jitter_m"] == 0.015
    assert "first_rise_m" not in saved["terrain"]


@pytest.mark.parametrize("scenario", ["upstair", "downstair"])
def test_feet_stand_on_the_actual_irregular_treads(scenario: str) -> None:
    cfg = load_scenario(scenario)
    terrain = build_terrain(
        cfg.terrain.model_copy(update={"n_steps": 8, **JITTER}), np.random.default_rng(3)
    )
    m = simulate_gait(terrain, cfg.gait, cfg.rig, 7.0, np.random.default_rng(2))
    fr = np.linspace(0, 1, 15)
    sole = (
        m.heel_xz_m[:, None, :] * (1 - fr[None, :, None])
        + m.toe_xz_m[:, None, :] * fr[None, :, None]
    )
    gap = sole[..., 1] - terrain.height_at(sole[..., 0].ravel()).reshape(sole.shape[:2])
    assert gap.min() > -0.002  # the sole never cuts a tread or a nosing
    # in stance (foot flat: heel and toe both still) the sole rests on the tread under it
    flat = m.stance_mask(m.t_s, "heel") & m.stance_mask(m.t_s, "toe")
    heel, toe = m.heel_xz_m[flat], m.toe_xz_m[flat]
    ground = np.maximum(terrain.height_at(heel[:, 0]), terrain.height_at(toe[:, 0]))
    np.testing.assert_allclose(np.minimum(heel[:, 1], toe[:, 1]), ground, atol=0.003)
    # the foot stood on several distinct tread heights, each a drawn one
    levels = np.unique(np.round(ground, 4))
    assert levels.size >= 4
    heights = np.concatenate([[0.0], terrain.edges_xz_m[:, 1], terrain.profile_xz_m[-1:, 1]])
    assert all(np.min(np.abs(heights - z)) < 1e-3 for z in levels)


def test_open_risers_let_rays_pass_under_the_nosings() -> None:
    """A camera before an open-riser stair sees the floor under the treads (z = 0, beyond
    the first nosing); with closed risers nothing below a tread is visible there."""
    from vio_graph.sim.tof import TofCamera
    from vio_graph.sim.trial import R_shank_cam

    cfg = load_scenario("upstair")
    seen = {}
    for open_risers in (False, True):
        tc = cfg.terrain.model_copy(update={"n_steps": 4, "open_risers": open_risers})
        terrain = build_terrain(tc)
        cam = TofCamera(cfg.camera.model_copy(update={"noise": False}), terrain)
        R = R_shank_cam(10.0)
        pos = np.array([terrain.feature_x_m - 0.4, 0.0, 0.25])
        depth, _ = cam.render(pos, R, np.random.default_rng(0))
        v, u = np.nonzero(depth > 0)
        z = depth[v, u].astype(float)
        p_c = np.stack([(u - cam.cx) / cam.fx * z, (v - cam.cy) / cam.fy * z, z], 1)
        p_w = p_c @ R.T + pos
        under = (p_w[:, 0] > terrain.feature_x_m + 0.02) & (p_w[:, 2] < 0.10)
        seen[open_risers] = int(under.sum())
        # the walking surface (truth) is the same either way
        np.testing.assert_array_equal(
            terrain.profile_xz_m,
            build_terrain(tc.model_copy(update={"open_risers": False})).profile_xz_m,
        )
    assert seen[False] == 0 and seen[True] > 50
    with pytest.raises(ConfigError, match="open_risers"):
        build_terrain(
            cfg.terrain.model_copy(update={"open_risers": True, "nosing_overhang_m": 0.02})
        )


def test_short_irregular_trial_truth_and_seed() -> None:
    cfg = load_scenario("upstair")
    cfg = cfg.model_copy(
        update={
            "duration_s": 2.0,
            "terrain": cfg.terrain.model_copy(update={"n_steps": 6, **JITTER}),
            "camera": cfg.camera.model_copy(update={"width_px": 32, "height_px": 24}),
        }
    )
    a, b, c = simulate_trial(cfg, 5), simulate_trial(cfg, 5), simulate_trial(cfg, 6)
    np.testing.assert_array_equal(a.metadata.terrain.edges_xz_m, b.metadata.terrain.edges_xz_m)
    assert a.metadata.terrain.edges_xz_m != c.metadata.terrain.edges_xz_m
    np.testing.assert_array_equal(a.metadata.terrain.edges_xz_m, a.terrain.edges_xz_m)
    np.testing.assert_array_equal(a.metadata.terrain.profile_xz_m, a.terrain.profile_xz_m)
    assert a.metadata.terrain.params["rise_jitter_m"] == 0.015


@pytest.mark.parametrize("up", [True, False], ids=["up", "down"])
@pytest.mark.parametrize("seed", [0, 1])
def test_map_reports_each_irregular_step_within_3mm(up: bool, seed: int) -> None:
    """The map of an irregular stair (rises 14.7 +- 1.5 cm, treads 28 +- 2 cm) gives each
    step its own rise and tread, not a mean: per-step errors within 3 mm."""
    tc = TerrainConfig(
        kind="stair_up" if up else "stair_down", approach_length_m=0.5, n_steps=5, **JITTER
    )
    terrain = build_terrain(tc, np.random.default_rng(100 + seed))
    info = TerrainInfo(
        kind=terrain.kind,
        params=terrain.params,
        profile_xz_m=[tuple(p) for p in terrain.profile_xz_m.tolist()],
        edges_xz_m=[tuple(p) for p in terrain.edges_xz_m.tolist()],
    )
    x_end = float(terrain.edges_xz_m[-1, 0]) + 0.3
    cams = camera_track(info, -0.3, x_end, step_m=0.015)
    profiles = observe(info, cams, 0.0025, np.random.default_rng(seed))
    terrain_map = TerrainMap2D()
    for i, (cam, prof) in enumerate(zip(cams, profiles, strict=True)):
        terrain_map.add_keyframe(0.1 * i, cam, prof)
    geometry = estimate_terrain_geometry(terrain_map.points_xz_m, terrain_map.point_counts)
    assert len(geometry.steps) == 5
    steps = np.array(stair_steps(tc, np.random.default_rng(100 + seed)))
    true_r, true_t = steps[:, 1] - steps[:, 2], np.diff(steps[:, 0])
    rises = np.array([s.rise_m for s in geometry.steps])
    treads = np.array([s.tread_m for s in geometry.steps[:-1]])
    np.testing.assert_allclose(rises, true_r, atol=0.003)
    np.testing.assert_allclose(treads, true_t, atol=0.003)
    report = compare_to_truth(geometry, info)
    assert report["n_steps_matched"] == 5
    assert report["rise_mae_mm"] < 2.0 and report["tread_mae_mm"] < 2.0
    # the steps really differ: a single mean rise would be off by more than the bound
    assert np.max(np.abs(true_r - true_r.mean())) > 0.005
