"""Obstacles of sizes other than the paper's 14 x 13 cm box, decided from what the profile
shows of their far side (rule step 5, ``obstacle_far_side``) and from the obstacle seen
earlier (rule step 6, ``recall_obstacle``), and stairs that stay stairs. Rendered profiles
(vio_graph.frontend.synthetic), camera 45 cm above the floor."""

from __future__ import annotations

import numpy as np
import pytest

from vio_graph.frontend.config import TerrainConfig
from vio_graph.frontend.smoothing import smooth_profile
from vio_graph.frontend.synthetic import raycast_profile, stair_polyline
from vio_graph.frontend.terrain import classify_terrain, recall_obstacle, seen_obstacle
from vio_graph.types import TerrainKind

CAM_HEIGHT_M = 0.45
STAIR_RISE_M = 0.147


def _view(poly: np.ndarray, camera_xz_m: np.ndarray, pitch_down_rad: float) -> np.ndarray:
    prof = raycast_profile(
        poly,
        camera_xz_m,
        pitch_down_rad=pitch_down_rad,
        noise_m=0.003,
        rng=np.random.default_rng(1),
        n_rays=800,
    )
    return smooth_profile(prof)


def _box(height_m: float, depth_m: float) -> np.ndarray:
    return stair_polyline(
        "obstacle", start_x_m=1.0, obstacle_height_m=height_m, obstacle_depth_m=depth_m
    )


@pytest.mark.parametrize(("height_m", "depth_m"), [(0.20, 0.30), (0.25, 0.50)])
def test_a_raised_top_dropping_back_to_the_stand_floor_is_an_obstacle(
    height_m: float, depth_m: float
) -> None:
    """The camera past the box's near edge sees its top, then the floor beyond at the height
    the foot stands on: the frame alone says a step down, the stand surface says the far side
    of an obstacle (the 20 x 30 cm box was STAIR_DOWN here before)."""
    cam = np.array([1.0, CAM_HEIGHT_M])
    prof = _view(_box(height_m, depth_m), cam, 0.6)
    alone, levels = classify_terrain(prof, TerrainConfig())
    assert alone == TerrainKind.STAIR_DOWN
    # the near level is the top, the far one the floor (heights relative to the camera)
    assert levels[0].height_m + CAM_HEIGHT_M == pytest.approx(height_m, abs=0.01)
    assert levels[-1].height_m + CAM_HEIGHT_M == pytest.approx(0.0, abs=0.01)
    on_floor = -CAM_HEIGHT_M
    assert classify_terrain(prof, TerrainConfig(), on_floor)[0] == TerrainKind.OBSTACLE
    off = TerrainConfig(obstacle_far_side=False)
    assert classify_terrain(prof, off, on_floor)[0] == TerrainKind.STAIR_DOWN


def test_a_stair_down_seen_from_its_top_tread_stays_a_stair() -> None:
    """Descending, the foot last stood on the upper tread: no level is above it."""
    poly = stair_polyline("stair_down", start_x_m=1.0)
    top_z = 4 * STAIR_RISE_M
    for cam_x in np.arange(-0.4, 1.3, 0.1):
        cam = np.array([cam_x, top_z + CAM_HEIGHT_M])
        prof = _view(poly, cam, 0.6)
        kind, _ = classify_terrain(prof, TerrainConfig(), -CAM_HEIGHT_M)
        assert kind == TerrainKind.STAIR_DOWN, cam_x


def _walk(poly: np.ndarray, views: list[tuple[float, float]], config: TerrainConfig) -> list:
    """Classes of a sequence of views (camera x, pitch), the foot on the floor, with the
    obstacle memory carried from view to view."""
    seen = None
    kinds = []
    for cam_x, pitch in views:
        cam = np.array([cam_x, CAM_HEIGHT_M])
        kind, levels = classify_terrain(_view(poly, cam, pitch), config, -CAM_HEIGHT_M)
        kind, seen = recall_obstacle(kind, levels, cam, seen, config)
        kinds.append(kind)
    return kinds


def test_an_obstacle_seen_with_its_far_floor_stays_an_obstacle_when_the_far_side_is_hidden() -> (
    None
):
    """A 20 x 30 cm box: seen from 1 m with the floor behind it (floor, top, floor), then
    from closer with the shank pitched down, where the floor behind is out of view and the
    top alone looks like the first tread of a stair."""
    poly = _box(0.20, 0.30)
    cfg = TerrainConfig()
    views = [(0.0, 0.6), (0.3, 0.7), (0.4, 0.7), (0.6, 0.8)]
    # the frames alone: only the first sees the far floor
    alone = [
        classify_terrain(_view(poly, np.array([x, CAM_HEIGHT_M]), p), cfg)[0] for x, p in views
    ]
    assert alone == [TerrainKind.OBSTACLE] + [TerrainKind.STAIR_UP] * 3
    assert _walk(poly, views, cfg) == [TerrainKind.OBSTACLE] * 4
    off = TerrainConfig(obstacle_memory=False)
    assert _walk(poly, views, off) == alone
    # the remembered top is where the box is (camera-relative levels placed at the camera)
    kind, levels = classify_terrain(_view(poly, np.array([0.0, CAM_HEIGHT_M]), 0.6), cfg)
    seen = seen_obstacle(levels, np.array([0.0, CAM_HEIGHT_M]), cfg)
    assert seen is not None
    assert seen.top_z_m == pytest.approx(0.20, abs=0.01)
    assert seen.floor_z_m == pytest.approx(0.0, abs=0.01)
    assert 1.0 - 0.03 <= seen.top_x_min_m < seen.top_x_max_m <= 1.30 + 0.03


def test_a_stair_is_not_called_an_obstacle_by_the_memory() -> None:
    """Approaching a stair with the same views never gives OBSTACLE; and with a 20 cm box
    remembered at the place of the stair's first riser, a 14.7 cm tread there is another
    surface (a different height) and stays a stair."""
    cfg = TerrainConfig()
    stair = stair_polyline("stair_up", start_x_m=1.0)
    views = [(0.0, 0.6), (0.3, 0.7), (0.4, 0.7), (0.6, 0.8), (0.8, 0.7), (1.1, 0.6)]
    assert set(_walk(stair, views, cfg)) == {TerrainKind.STAIR_UP}
    cam = np.array([0.0, CAM_HEIGHT_M])
    _, box_levels = classify_terrain(_view(_box(0.20, 0.30), cam, 0.6), cfg)
    seen = seen_obstacle(box_levels, cam, cfg)
    for cam_x, pitch in views:
        cam = np.array([cam_x, CAM_HEIGHT_M])
        kind, levels = classify_terrain(_view(stair, cam, pitch), cfg, -CAM_HEIGHT_M)
        assert kind == TerrainKind.STAIR_UP
        assert recall_obstacle(kind, levels, cam, seen, cfg)[0] == TerrainKind.STAIR_UP
