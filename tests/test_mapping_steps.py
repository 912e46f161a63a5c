"""Step and obstacle geometry recovered from maps of known synthetic terrain."""

from __future__ import annotations

import numpy as np
import pytest

from tests.test_mapping_synth import camera_track, observe, obstacle_profile, stair_profile
from vio_graph.evaluation.map_accuracy import compare_to_truth
from vio_graph.mapping.config import StepConfig
from vio_graph.mapping.local_map import TerrainMap2D
from vio_graph.mapping.steps import (
    TerrainGeometry,
    estimate_terrain_geometry,
    find_levels,
    find_levels_reference,
    fit_riser,
)
from vio_graph.recording.metadata import TerrainInfo
from vio_graph.types import TerrainKind

NOISE_M = 0.0025  # per-point noise of the profiles (x and z)
KEYFRAME_STEP_M = 0.015  # paper: keyframes every 0.01-0.05 m of camera motion


def _map(terrain: TerrainInfo, x_end_m: float, seed: int, noise_m: float = NOISE_M):
    cams = camera_track(terrain, -0.3, x_end_m, step_m=KEYFRAME_STEP_M)
    profiles = observe(terrain, cams, noise_m, np.random.default_rng(seed))
    terrain_map = TerrainMap2D()
    for i, (cam, prof) in enumerate(zip(cams, profiles, strict=True)):
        terrain_map.add_keyframe(0.1 * i, cam, prof)
    return terrain_map


def _geometry(terrain: TerrainInfo, x_end_m: float, seed: int, **kw) -> TerrainGeometry:
    terrain_map = _map(terrain, x_end_m, seed, **kw)
    return estimate_terrain_geometry(terrain_map.points_xz_m, terrain_map.point_counts)


STAIRS = [
    pytest.param(0.147, 0.28, True, 1.8, id="up-147x280"),
    pytest.param(0.17, 0.25, True, 1.6, id="up-170x250"),
    pytest.param(0.147, 0.28, False, 1.8, id="down-147x280"),
    pytest.param(0.17, 0.25, False, 1.6, id="down-170x250"),
]


@pytest.mark.parametrize("rise_m, tread_m, up, x_end_m", STAIRS)
@pytest.mark.parametrize("seed", [0, 1])
def test_stairs_recovered_within_2mm_and_nosings_within_5mm(
    rise_m: float, tread_m: float, up: bool, x_end_m: float, seed: int
) -> None:
    terrain = stair_profile(rise_m, tread_m, 5, up=up)
    geometry = _geometry(terrain, x_end_m, seed)
    assert geometry.kind is (TerrainKind.STAIR_UP if up else TerrainKind.STAIR_DOWN)
    assert len(geometry.steps) == 5
    assert [s.direction for s in geometry.steps] == ["up" if up else "down"] * 5
    # every riser where an ascending camera sees it, none when descending (occluded)
    assert all(s.riser_observed == up for s in geometry.steps)
    rises = np.array([s.rise_m for s in geometry.steps])
    treads = np.array([s.tread_m for s in geometry.steps[:-1]])
    assert geometry.steps[-1].tread_m is None
    np.testing.assert_allclose(rises, rise_m, atol=0.002)
    np.testing.assert_allclose(treads, tread_m, atol=0.002)
    nosings = np.array([s.nosing_xz_m for s in geometry.steps])
    np.testing.assert_allclose(nosings, np.asarray(terrain.edges_xz_m), atol=0.005)
    # stated uncertainties are positive and not wildly off (errors within 5 sigma + 0.5 mm)
    stds = np.array([s.nosing_std_xz_m for s in geometry.steps])
    assert np.all(stds > 0)
    assert np.all(np.abs(nosings - np.asarray(terrain.edges_xz_m)) < 5 * stds + 5e-4)

    report = compare_to_truth(geometry, terrain)
    assert report["kind_correct"] is True
    assert report["n_steps_matched"] == 5
    assert report["matched_edge_index"] == [0, 1, 2, 3, 4]
    assert report["rise_mae_mm"] < 2.0 and report["tread_mae_mm"] < 2.0
    assert report["nosing_max_mm"] < 5.0
    assert report["tread_error_mm"][-1] is None
    np.testing.assert_allclose(report["rise_error_mm"], 1000 * (rises - rise_m), atol=1e-9)


@pytest.mark.parametrize("seed", [0, 1, 2])
def test_obstacle_height_and_depth_within_5mm(seed: int) -> None:
    terrain = obstacle_profile(0.14, 0.13)
    geometry = _geometry(terrain, 1.0, seed)
    assert geometry.kind is TerrainKind.OBSTACLE
    assert geometry.steps == ()
    (obstacle,) = geometry.obstacles
    assert obstacle.height_m == pytest.approx(0.14, abs=0.005)
    assert obstacle.depth_m == pytest.approx(0.13, abs=0.005)
    np.testing.assert_allclose(obstacle.front_edge_xz_m, [0.5, 0.14], atol=0.005)
    np.testing.assert_allclose(obstacle.back_edge_xz_m, [0.63, 0.14], atol=0.005)
    report = compare_to_truth(geometry, terrain)
    (ob_report,) = report["obstacles"]
    assert abs(ob_report["height_error_mm"]) < 5 and abs(ob_report["depth_error_mm"]) < 5
    assert ob_report["height_error_mm"] == pytest.approx(1000 * (obstacle.height_m - 0.14))


def test_noiseless_ideal_profile_gives_exact_geometry() -> None:
    # dense noiseless samples of the true polyline: every number is known exactly
    terrain = stair_profile(0.15, 0.3, 3, up=True)
    profile = np.asarray(terrain.profile_xz_m)
    pieces = []
    for a, b in zip(profile[:-1], profile[1:], strict=True):
        n = max(2, int(np.linalg.norm(b - a) / 0.005))
        pieces.append(a + (b - a) * (np.arange(n)[:, None] + 0.5) / n)
    points = np.concatenate(pieces)
    geometry = estimate_terrain_geometry(points)
    assert geometry.kind is TerrainKind.STAIR_UP
    assert [round(s.rise_m, 9) for s in geometry.steps] == [0.15, 0.15, 0.15]
    assert [s.tread_m for s in geometry.steps[:2]] == pytest.approx([0.3, 0.3], abs=1e-6)
    np.testing.assert_allclose(
        [s.nosing_xz_m for s in geometry.steps], terrain.edges_xz_m, atol=1e-6
    )


def test_level_ground_has_no_steps() -> None:
    rng = np.random.default_rng(3)
    x = np.arange(0.0, 1.5, 0.005)
    points = np.column_stack([x, rng.normal(0.0, 0.002, x.size)])
    geometry = estimate_terrain_geometry(points)
    assert geometry.kind is TerrainKind.LEVEL
    assert geometry.steps == () and geometry.obstacles == ()
    (level,) = geometry.levels
    assert abs(level.z_m) < 0.001
    assert level.x_start_edge_m == pytest.approx(0.0, abs=0.004)
    assert level.x_end_edge_m == pytest.approx(1.5, abs=0.004)


def test_edge_of_a_densely_seen_end_stays_near_the_last_cell() -> None:
    """A level whose first 1.5 cm hold ten times the weight per metre of its interior (its
    end seen from many more keyframes): the 50 % rule alone puts the edge 13.5 cm before the
    first cell; kept within edge_blur_m of it (camera 20 cm below the knee, seed 1000: a
    nosing 54 mm off, now 17 mm)."""
    x = np.arange(0.0, 0.3, 0.005) + 0.0025
    w = np.where(x < 0.015, 10.0, 1.0)
    points = np.column_stack([x, np.zeros_like(x)])
    (level,) = estimate_terrain_geometry(points, w).levels
    blur = StepConfig().edge_blur_m
    assert level.x_start_edge_m == pytest.approx(x.min() - blur, abs=1e-9)
    # uniform weights: the rule is inside the clamp and unchanged
    (plain,) = estimate_terrain_geometry(points, np.ones_like(x)).levels
    assert x.min() - blur < plain.x_start_edge_m == pytest.approx(0.0, abs=0.004)


def test_spurious_points_do_not_create_steps() -> None:
    terrain = stair_profile(0.147, 0.28, 5, up=True)
    cams = camera_track(terrain, -0.3, 1.8, step_m=KEYFRAME_STEP_M)
    rng = np.random.default_rng(7)
    profiles = observe(terrain, cams, NOISE_M, rng)
    terrain_map = TerrainMap2D()
    for i, (cam, prof) in enumerate(zip(cams, profiles, strict=True)):
        # a few flying pixels per frame, and every 10th frame a fake 6 cm "tread" in mid-air
        junk = np.column_stack([rng.uniform(0.2, 1.2, 5), rng.uniform(-0.5, 0.2, 5)])
        if i % 10 == 0:
            junk = np.vstack([junk, np.column_stack([np.linspace(0.3, 0.36, 12), [-0.1] * 12])])
        terrain_map.add_keyframe(0.1 * i, cam, np.vstack([prof, junk]))
    geometry = estimate_terrain_geometry(terrain_map.points_xz_m, terrain_map.point_counts)
    assert geometry.kind is TerrainKind.STAIR_UP
    assert len(geometry.steps) == 5
    np.testing.assert_allclose([s.rise_m for s in geometry.steps], 0.147, atol=0.002)

    # even without the map's keyframe filter, a few isolated points make no level
    points = terrain_map.points_xz_m
    extra = np.column_stack([rng.uniform(0.0, 1.5, 8), rng.uniform(0.8, 1.0, 8)])
    geometry2 = estimate_terrain_geometry(np.vstack([points, extra]))
    assert len(geometry2.steps) == 5
    assert len(find_levels(np.vstack([points, extra]))) == 6


def test_partial_stair_gives_no_tread_for_the_last_step_and_empty_map_is_unknown() -> None:
    geometry = estimate_terrain_geometry(np.zeros((0, 2)))
    assert geometry.kind is TerrainKind.UNKNOWN and geometry.levels == ()
    # floor and one tread only: one step, rise known, tread unknown
    x1 = np.arange(0.0, 0.5, 0.005)
    x2 = np.arange(0.5, 0.78, 0.005)
    zr = np.arange(0.0, 0.147, 0.005)
    points = np.concatenate(
        [
            np.column_stack([x1, np.zeros_like(x1)]),
            np.column_stack([np.full_like(zr, 0.5), zr]),
            np.column_stack([x2, np.full_like(x2, 0.147)]),
        ]
    )
    geometry = estimate_terrain_geometry(points)
    (step,) = geometry.steps
    assert step.rise_m == pytest.approx(0.147, abs=1e-9)
    assert step.tread_m is None
    assert step.nosing_xz_m[0] == pytest.approx(0.5, abs=1e-9)
    # with the obstacle hint, a raised last level is an obstacle seen from the front
    hinted = estimate_terrain_geometry(points, kind_hint=TerrainKind.OBSTACLE)
    assert hinted.kind is TerrainKind.OBSTACLE
    assert hinted.obstacles[0].height_m == pytest.approx(0.147, abs=1e-9)


def test_config_rejects_inconsistent_thresholds() -> None:
    with pytest.raises(ValueError):
        StepConfig(level_tolerance_m=0.05, min_rise_m=0.03)
    with pytest.raises(ValueError):
        StepConfig(unknown_field=1)  # type: ignore[call-arg]


@pytest.mark.parametrize("up", [True, False])
def test_pose_noise_blurs_but_does_not_invent_levels(up: bool) -> None:
    # keyframe positions off by 1 cm (1 sigma, independent): risers smear over several cm of
    # x, which must not turn their middle into extra "treads"
    terrain = stair_profile(0.147, 0.28, 5, up=up)
    rng = np.random.default_rng(11)
    cams = camera_track(terrain, -0.3, 1.8, step_m=KEYFRAME_STEP_M)
    profiles = observe(terrain, cams, NOISE_M, rng)
    terrain_map = TerrainMap2D()
    for i, (cam, prof) in enumerate(zip(cams, profiles, strict=True)):
        terrain_map.add_keyframe(0.1 * i, cam + rng.normal(0.0, 0.01, 2), prof)
    geometry = estimate_terrain_geometry(terrain_map.points_xz_m, terrain_map.point_counts)
    assert len(geometry.levels) == 6
    assert geometry.kind is (TerrainKind.STAIR_UP if up else TerrainKind.STAIR_DOWN)
    # rise errors are limited by the pose noise (~1 cm / sqrt(keyframes seeing a tread))
    np.testing.assert_allclose([s.rise_m for s in geometry.steps], 0.147, atol=0.012)
    report = compare_to_truth(geometry, terrain)
    assert report["n_steps_matched"] == 5 and report["nosing_max_mm"] < 15
    if not up:
        return  # descending: the risers are occluded, nothing to smear
    # ascending, without the flatness test the blurred risers do produce spurious levels
    loose = estimate_terrain_geometry(
        terrain_map.points_xz_m,
        terrain_map.point_counts,
        StepConfig(min_level_contrast=1.0),
    )
    assert len(loose.levels) > 6


@pytest.mark.parametrize("seed", [0, 1, 2])
@pytest.mark.parametrize("up", [True, False])
def test_find_levels_equals_the_reference_search(seed: int, up: bool) -> None:
    """The incremental search returns the reference's levels bit for bit (same floats), with
    the map's counts, unit and fractional weights, on a map with flying pixels."""
    terrain = stair_profile(0.147, 0.28, 8, up=up)
    terrain_map = _map(terrain, 2.6, seed)
    rng = np.random.default_rng(seed)
    points = np.vstack(
        [
            terrain_map.points_xz_m,
            np.column_stack([rng.uniform(0, 2.5, 40), rng.uniform(-1, 1, 40)]),
        ]
    )
    counts = np.concatenate([terrain_map.point_counts, np.ones(40)])
    for weights in (counts, None, rng.uniform(0.1, 2.0, points.shape[0])):
        levels = find_levels(points, weights)
        assert len(levels) >= 8
        assert levels == find_levels_reference(points, weights)
    capped = StepConfig(max_levels=3)
    assert find_levels(points, counts, capped) == find_levels_reference(points, counts, capped)
    # risers: the x window found by bisection in the x order gives the scan's answer
    cfg = StepConfig()
    by_x = np.argsort(points[:, 0], kind="stable")
    levels = sorted(find_levels(points, counts), key=lambda lv: lv.x_start_m)
    risers = [
        (
            fit_riser(points, counts, a, b, cfg),
            fit_riser(points, counts, a, b, cfg, (by_x, points[by_x, 0])),
        )
        for a, b in zip(levels[:-1], levels[1:], strict=True)
    ]
    if up:  # fit_riser measures rising transitions only
        assert sum(r is not None for r, _ in risers) >= 7
    assert all(scan == fast for scan, fast in risers)


def test_find_levels_on_a_height_grid_ends() -> None:
    """Heights on a 5 mm grid (ties, window ends a rounding error outside the band): the
    search still ends and finds the 3 planted levels, each once."""
    x = np.arange(0, 0.6, 0.005)
    points = np.vstack(
        [np.column_stack([x + 0.7 * k, np.full(x.size, 0.15 * k)]) for k in range(3)]
    )
    levels = find_levels(np.round(points / 0.005) * 0.005)
    assert [round(lv.z_m, 3) for lv in levels] == [0.0, 0.15, 0.3]
    # random points on the grid: the reference searches one window forever here
    grid = np.round(np.random.default_rng(0).random((5000, 2)) * [3, 0.5] / 0.005) * 0.005
    assert len(find_levels(grid)) > 0


@pytest.mark.parametrize("seed", [0, 1, 2])
def test_under_levels_by_window_equals_the_whole_call(seed: int) -> None:
    """mapping.steps.under_levels_by_window (one level's x window of the sorted points at a
    time) gives surface.under_levels_mask's mask bit for bit: open-riser treads over a floor
    that runs under several of them, a landing over a wall, levels that touch or overlap
    by less than the margin, points on the extents' ends and on end + margin, NaN points,
    and a map where nothing is beneath a level."""
    from vio_graph.mapping.steps import under_levels_by_window
    from vio_graph.surface import under_levels_mask

    rng = np.random.default_rng(seed)
    n_treads = 12
    tread_lo = 0.5 + 0.28 * np.arange(n_treads)
    z = np.concatenate([0.15 * (1 + np.arange(n_treads)), [0.0, 0.0, 1.9, -0.4]])
    lo = np.concatenate([tread_lo, [-0.5, 2.0, 3.9, 1.0]])
    hi = np.concatenate([tread_lo + 0.25, [2.0, 4.5, 6.0, 1.04]])
    lo[3] = hi[2]  # two treads touching
    pts = np.column_stack([rng.uniform(-1.0, 6.5, 4000), rng.uniform(-0.6, 2.2, 4000)])
    pts[rng.integers(0, 4000, 15)] = np.nan
    pts[rng.integers(0, 4000, 15), 1] = np.nan
    # on every extent's ends (and a margin in) at every level's height: the window's edges
    ends = np.concatenate([lo, hi, lo + 0.05, hi - 0.05])
    pts = np.vstack([pts, np.column_stack([np.repeat(ends, z.size), np.tile(z, ends.size)])])
    for margin, drop in ((0.05, 0.06), (0.0, 0.1), (0.2, 0.02), (0.01, 0.5)):
        want = under_levels_mask(pts, z, lo, hi, margin, drop, drop)
        got = under_levels_by_window(pts, z, lo, hi, margin, drop)
        assert want.any() and not want.all()
        np.testing.assert_array_equal(got, want)
    above = pts[np.isfinite(pts[:, 1])].copy()
    above[:, 1] = 5.0  # nothing beneath any level
    assert not under_levels_by_window(above, z, lo, hi, 0.05, 0.06).any()
    np.testing.assert_array_equal(
        under_levels_by_window(pts, z, lo, hi, -0.05, 0.06),
        under_levels_mask(pts, z, lo, hi, -0.05, 0.06, 0.06),
    )


def _open_riser_map_with_floor_at_a_junction() -> tuple[np.ndarray, np.ndarray]:
    """A map of an open-riser flight (rise 0.15 m, tread 0.28 m, 5 treads, then a landing):
    the treads and landing every 5 mm, no riser points (open), and the floor (z 0) seen
    through the last open riser only within 45 mm either side of the junction of the last
    tread and the landing, the strips the beneath-a-level rule leaves out (weight 3 per floor
    cell, 30 per surface cell)."""
    rise, tread, n = 0.15, 0.28, 5
    pts, w = [], []
    for i in range(n + 1):
        x0 = 0.5 + i * tread
        x1 = x0 + (tread if i < n else 1.5) - 0.005
        xs = np.arange(x0, x1, 0.005)
        pts.append(np.column_stack([xs, np.full(xs.size, rise * (i + 1))]))
        w.append(np.full(xs.size, 30.0))
    floor_x = np.arange(0.5 + n * tread - 0.045, 0.5 + n * tread + 0.046, 0.005)
    pts.append(np.column_stack([floor_x, np.zeros(floor_x.size)]))
    w.append(np.full(floor_x.size, 3.0))
    floor_x = np.arange(-0.5, 0.5, 0.005)  # the floor before the flight
    pts.append(np.column_stack([floor_x, np.zeros(floor_x.size)]))
    w.append(np.full(floor_x.size, 30.0))
    return np.vstack(pts), np.concatenate(w)


def test_floor_under_the_junction_of_two_treads_is_not_a_level() -> None:
    """The floor seen through an open riser at the junction of the last tread and the landing
    (sweep open_risers seed 1002, batch attitude: 8 floor cells at x 4.573-4.624 m) is not the
    walking surface: with the junction rule the flight reads 6 up steps of 0.15 m (floor to
    landing); without it that floor is a level of its own between the tread and the landing
    (a 0.9 m "rise") and the map's kind is not a stair."""
    pts, w = _open_riser_map_with_floor_at_a_junction()
    geo = estimate_terrain_geometry(pts, w, StepConfig())
    assert geo.kind is TerrainKind.STAIR_UP
    assert len(geo.steps) == 6
    np.testing.assert_allclose([s.rise_m for s in geo.steps], 0.15, atol=1e-6)
    without = estimate_terrain_geometry(pts, w, StepConfig(under_junctions=False))
    assert without.kind is not TerrainKind.STAIR_UP
    assert max(s.rise_m for s in without.steps) > 0.5


def test_under_junctions_mask_keeps_risers_and_steps_down() -> None:
    """mapping.steps.under_junctions_mask flags only points ``drop`` below both abutting
    levels within the margin of their junction: a riser between them (at the heights between
    the two levels), the lower level's own cells, points beyond the margin and junctions of
    levels farther apart than the gap are kept."""
    from vio_graph.mapping.steps import under_junctions_mask

    z = np.array([0.15, 0.30, 0.0])
    lo = np.array([0.0, 0.28, 1.0])  # the third level starts 0.42 m after the second's end
    hi = np.array([0.275, 0.58, 2.0])
    pts = np.array(
        [
            [0.27, 0.0],  # floor under the junction, 5 mm before tread 1's end: under
            [0.30, 0.05],  # 20 mm into tread 2, 0.1 m below the lower: under
            [0.32, 0.0],  # 40 mm into tread 2: under (within the 50 mm margin)
            [0.34, 0.0],  # 60 mm into tread 2: left to the beneath-a-level rule
            [0.20, 0.0],  # 75 mm before tread 1's end: left to the beneath-a-level rule
            [0.278, 0.22],  # the riser between the two treads: kept
            [0.27, 0.15],  # tread 1 itself: kept
            [0.27, 0.12],  # 30 mm below tread 1 (less than the drop): kept
            [0.60, -0.5],  # past tread 2's end, the next level is not abutting: kept
        ]
    )
    got = under_junctions_mask(pts, z, lo, hi, margin_m=0.05, drop_m=0.04, gap_m=0.03)
    np.testing.assert_array_equal(got, [True, True, True, False, False, False, False, False, False])
