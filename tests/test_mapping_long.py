"""Long trials: a 160-step staircase (about a 2-minute climb) mapped from keyframes.

The step extraction must find every tread of a long map (a cap on the number of level
searches once kept only 40 of them, so that consecutive detected levels were several steps
apart and the rise and tread errors were whole multiples of the true ones), and a slow drift
of the keyframe poses, as a relative-only estimator has over minutes, must not change the
local geometry (rise and tread within 5 mm, the aim for a 2-minute trial).
"""

from __future__ import annotations

from functools import lru_cache

import numpy as np
import pytest

from tests.test_mapping_synth import camera_track, ray_cast, stair_profile
from vio_graph.evaluation.map_accuracy import compare_to_truth
from vio_graph.mapping.config import StepConfig
from vio_graph.mapping.local_map import TerrainMap2D
from vio_graph.mapping.steps import estimate_terrain_geometry

RISE_M, TREAD_M, N_STEPS = 0.147, 0.28, 160
NOISE_M = 0.0025  # per-point profile noise, metres
KEYFRAME_STEP_M = 0.015  # camera travel between keyframes, metres


@lru_cache(maxsize=2)
def _long_map(drift_xz_m: tuple[float, float], seed: int) -> TerrainMap2D:
    """Keyframes along the whole stair; their poses drift linearly from 0 at the start to
    ``drift_xz_m`` (x, z metres) at the end."""
    terrain = stair_profile(RISE_M, TREAD_M, N_STEPS)
    cams = camera_track(terrain, -0.3, 0.5 + N_STEPS * TREAD_M + 0.5, step_m=KEYFRAME_STEP_M)
    profile = np.asarray(terrain.profile_xz_m)
    rng = np.random.default_rng(seed)
    profiles = []
    for cam in cams:  # ray-cast against the part of the stair within the 2 m range only
        near = np.flatnonzero(np.abs(profile[:, 0] - cam[0]) < 2.5)
        part = profile[max(near[0] - 1, 0) : near[-1] + 2]
        hits = ray_cast(part, cam)
        profiles.append(hits - cam + rng.normal(0.0, NOISE_M, size=hits.shape))
    ramp = np.linspace(0.0, 1.0, cams.shape[0])[:, None] * np.asarray(drift_xz_m)[None, :]
    terrain_map = TerrainMap2D()
    for i, (cam, prof) in enumerate(zip(cams + ramp, profiles, strict=True)):
        terrain_map.add_keyframe(0.1 * i, cam, prof)
    return terrain_map


@pytest.mark.parametrize("drift_xz_m", [(0.0, 0.0), (0.15, -0.05)], ids=["no-drift", "drift"])
def test_every_step_of_a_160_step_stair_is_recovered_within_5mm(drift_xz_m) -> None:
    terrain = stair_profile(RISE_M, TREAD_M, N_STEPS)
    terrain_map = _long_map(drift_xz_m, seed=3)
    geometry = estimate_terrain_geometry(terrain_map.points_xz_m, terrain_map.point_counts)
    assert len(geometry.levels) == N_STEPS + 1
    assert len(geometry.steps) == N_STEPS
    rises = np.array([s.rise_m for s in geometry.steps])
    treads = np.array([s.tread_m for s in geometry.steps[:-1]])
    np.testing.assert_allclose(rises, RISE_M, atol=0.005)
    np.testing.assert_allclose(treads, TREAD_M, atol=0.005)
    assert abs(rises.mean() - RISE_M) < 0.001 and abs(treads.mean() - TREAD_M) < 0.001
    report = compare_to_truth(geometry, terrain)
    assert report["rise_mae_mm"] < 5.0 and report["tread_mae_mm"] < 5.0
    if drift_xz_m == (0.0, 0.0):
        # every nosing matched to its own true edge, in order
        assert report["matched_edge_index"] == list(range(N_STEPS))


def test_a_cap_on_level_searches_loses_treads_and_multiplies_the_errors() -> None:
    # the former default (40 searches) on the same map: most treads are missing and the
    # "steps" between the detected levels span several true steps
    terrain_map = _long_map((0.0, 0.0), seed=3)
    capped = estimate_terrain_geometry(
        terrain_map.points_xz_m, terrain_map.point_counts, StepConfig(max_levels=40)
    )
    assert len(capped.levels) <= 40
    assert max(s.rise_m for s in capped.steps) > 2 * RISE_M
