"""TerrainMap2D: merging, thinning, outlier rejection and rebuilding from refined poses."""

from __future__ import annotations

import numpy as np
import pytest

from tests.test_mapping_synth import camera_track, observe, stair_profile
from vio_graph.errors import MappingError
from vio_graph.mapping.config import MapConfig
from vio_graph.mapping.local_map import TerrainMap2D, merge_points


def _stair_map(seed: int = 0, noise_m: float = 0.0025) -> tuple[TerrainMap2D, np.ndarray]:
    terrain = stair_profile(0.147, 0.28, 5, up=True)
    cams = camera_track(terrain, -0.3, 1.8, step_m=0.02)
    profiles = observe(terrain, cams, noise_m, np.random.default_rng(seed))
    terrain_map = TerrainMap2D(MapConfig())
    for i, (cam, prof) in enumerate(zip(cams, profiles, strict=True)):
        terrain_map.add_keyframe(0.1 * i, cam, prof)
    return terrain_map, cams


def test_merge_points_known_cells() -> None:
    # two keyframes hit the same 5 mm cell, a third point sits alone in another cell
    points = np.array([[0.001, 0.001], [0.003, 0.002], [0.0021, 0.0041], [0.101, 0.0]])
    kf = np.array([0, 1, 1, 0])
    cells = merge_points(points, kf, MapConfig(cell_size_m=0.005, min_keyframes_per_cell=2))
    assert len(cells) == 1
    np.testing.assert_allclose(cells.points_xz_m, [[0.0061 / 3, 0.0071 / 3]], atol=1e-12)
    assert cells.point_counts.tolist() == [3]
    assert cells.keyframe_counts.tolist() == [2]
    cells1 = merge_points(points, kf, MapConfig(cell_size_m=0.005, min_keyframes_per_cell=1))
    assert len(cells1) == 2
    np.testing.assert_allclose(cells1.points_xz_m[1], [0.101, 0.0], atol=1e-12)


def test_map_points_lie_on_the_stairs_and_are_thinned() -> None:
    terrain_map, _ = _stair_map()
    raw, _ = terrain_map.raw_points_xz_m()
    pts = terrain_map.points_xz_m
    assert raw.shape[0] > 10_000
    # thinning: at most a few cells per 5 mm of surface (~0.2 m of profile per metre of x)
    length_m = np.ptp(pts[:, 0]) + 5 * 0.147
    assert pts.shape[0] < 4 * length_m / 0.005
    assert pts.shape[0] < raw.shape[0] / 5
    # every map point is within a few noise sigmas of the true profile
    profile = np.asarray(stair_profile(0.147, 0.28, 5).profile_xz_m)
    dense = np.concatenate(
        [np.linspace(a, b, 400) for a, b in zip(profile[:-1], profile[1:], strict=True)]
    )
    dist = np.min(np.linalg.norm(pts[:, None, :] - dense[None, ::4, :], axis=2), axis=1)
    assert np.max(dist) < 0.012
    assert np.median(dist) < 0.003


def test_single_keyframe_outliers_never_reach_the_map() -> None:
    terrain_map, cams = _stair_map()
    before = terrain_map.points_xz_m
    rng = np.random.default_rng(5)
    spurious_world = np.column_stack([rng.uniform(0.0, 1.5, 30), rng.uniform(0.8, 1.2, 30)])
    terrain_map.add_keyframe(999.0, cams[10], spurious_world - cams[10])
    after = terrain_map.points_xz_m
    assert after.shape == before.shape
    assert np.max(after[:, 1]) < 0.75


def test_update_poses_moves_the_map() -> None:
    terrain_map, cams = _stair_map(noise_m=0.0)
    before = terrain_map.points_xz_m
    shift = np.array([0.1234, -0.0567])
    moved = terrain_map.update_poses([(0.1 * i, cam + shift) for i, cam in enumerate(cams)])
    assert moved == len(cams)
    after = terrain_map.points_xz_m
    # the merged map is rebuilt: same surface, shifted (cells re-grid, so compare by nearest
    # neighbour and by the count-weighted centroid, which the grid preserves)
    expected = before + shift
    dist = np.min(np.linalg.norm(after[:, None, :] - expected[None, :, :], axis=2), axis=1)
    assert np.median(dist) < 0.002 and np.max(dist) < 0.012  # shift is 0.136 m
    raw_before, _ = _stair_map(noise_m=0.0)[0].raw_points_xz_m()
    raw_after, _ = terrain_map.raw_points_xz_m()
    np.testing.assert_allclose(raw_after, raw_before + shift, atol=1e-12)
    # the smoother's (timestamp, camera_xz, cov) tuples and dicts work too
    assert terrain_map.update_poses({0.0: cams[0], 12345.0: cams[0]}) == 1
    terrain_map.update_poses([(0.1 * i, cam, np.eye(2)) for i, cam in enumerate(cams)])
    np.testing.assert_allclose(terrain_map.points_xz_m, before, atol=1e-9)


def test_max_keyframes_forgets_the_oldest() -> None:
    terrain_map = TerrainMap2D(MapConfig(max_keyframes=3, min_keyframes_per_cell=1))
    for i in range(5):
        terrain_map.add_keyframe(float(i), [float(i), 0.0], [[0.0, 0.0]])
    assert [kf.timestamp_s for kf in terrain_map.keyframes] == [2.0, 3.0, 4.0]
    np.testing.assert_allclose(np.sort(terrain_map.points_xz_m[:, 0]), [2.0, 3.0, 4.0])


def test_bad_input_raises_mapping_error() -> None:
    terrain_map = TerrainMap2D()
    with pytest.raises(MappingError):
        terrain_map.add_keyframe(0.0, [0.0, 0.0, 0.0], [[0.0, 0.0]])
    with pytest.raises(MappingError):
        terrain_map.add_keyframe(0.0, [0.0, 0.0], np.zeros((4, 3)))
    terrain_map.add_keyframe(0.0, [0.0, 0.0], np.zeros((0, 2)))
    assert terrain_map.points_xz_m.shape == (0, 2)


def test_in_order_keyframes_are_found_and_replaced_like_a_fresh_map() -> None:
    # the sorted-stamp cache grows in a buffer while keyframes come in time order; a stamp
    # added again (within the match tolerance) replaces its keyframe, wherever it is, and
    # an out-of-order or forgotten keyframe rebuilds the cache: every lookup agrees with a
    # search over the stored keyframes
    rng = np.random.default_rng(3)
    prof = np.array([[0.3, -0.4], [0.35, -0.4]])
    terrain_map = TerrainMap2D(MapConfig(max_keyframes=150))
    stamps = np.cumsum(rng.uniform(0.02, 0.05, 400))
    for k, t in enumerate(stamps):
        terrain_map.add_keyframe(t, [0.01 * k, 0.0], prof)
        if k % 37 == 36:  # the same stamp again, and one before the last: replaced / sorted
            terrain_map.add_keyframe(stamps[k - 3] + 1e-7, [9.0, 9.0], prof)
            terrain_map.add_keyframe(stamps[k - 1] - 1e-3, [0.5, 0.5], prof)
        stored = np.array([kf.timestamp_s for kf in terrain_map.keyframes])
        assert np.all(np.diff(stored) > 0)
        assert len(terrain_map) == min(150, len(stored))
        for t_probe in (t, stamps[max(0, k - 3)], t + 1.0):
            i = terrain_map._find(t_probe)
            near = np.flatnonzero(np.abs(stored - t_probe) <= MapConfig().timestamp_match_tol_s)
            assert (i is None) == (near.size == 0)
            if i is not None:
                assert i in near.tolist()
    replaced = [kf for kf in terrain_map.keyframes if kf.camera_xz_m[0] == 9.0]
    assert len(replaced) == sum(1 for k in range(250, 400) if k % 37 == 36)
