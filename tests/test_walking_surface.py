"""The walking-surface rule (vio_graph.surface): returns from beneath a tread (open risers:
the floor under the flight seen through the gaps) leave the frame's profile and the map;
stairs with closed risers (with or without nosing overhang) lose no point."""

from __future__ import annotations

import numpy as np
import pytest

from vio_graph.evaluation.map_accuracy import compare_to_truth
from vio_graph.frontend.config import TerrainConfig as FrontTerrainConfig
from vio_graph.frontend.smoothing import smooth_profile
from vio_graph.frontend.terrain import classify_terrain, points_seen_under, points_under_levels
from vio_graph.mapping.local_map import TerrainMap2D
from vio_graph.mapping.steps import estimate_terrain_geometry
from vio_graph.recording.metadata import TerrainInfo
from vio_graph.sim.config import TerrainConfig
from vio_graph.sim.terrain import build_terrain
from vio_graph.surface import floor_beyond_slab_mask, seen_under_mask, under_levels_mask
from vio_graph.types import TerrainKind


def _segments(terrain) -> np.ndarray:
    """(S, 2, 2) every segment of the terrain's mesh outlines (profile and open-riser parts)."""
    mesh = terrain.mesh_profile_xz_m
    outlines = [terrain.profile_xz_m if mesh is None else mesh, *terrain.mesh_parts_xz_m]
    return np.concatenate([np.stack([o[:-1], o[1:]], axis=1) for o in outlines])


def _cast(segments: np.ndarray, cam: np.ndarray, pitch_down_deg: float = 35.0, n: int = 200):
    """Nearest hits (K, 2) of a fan of 56 deg from ``cam`` on the segments, world x-z."""
    p0, seg = segments[:, 0], segments[:, 1] - segments[:, 0]
    ang = np.radians(-pitch_down_deg) + np.linspace(-0.49, 0.49, n)
    d = np.stack([np.cos(ang), np.sin(ang)], axis=1)
    w = p0[None] - cam[None, None]
    den = d[:, None, 0] * seg[None, :, 1] - d[:, None, 1] * seg[None, :, 0]
    with np.errstate(divide="ignore", invalid="ignore"):
        t = (w[..., 0] * seg[None, :, 1] - w[..., 1] * seg[None, :, 0]) / den
        u = (w[..., 0] * d[:, None, 1] - w[..., 1] * d[:, None, 0]) / den
    ok = (np.abs(den) > 1e-12) & (t > 1e-6) & (t < 2.4) & (u >= 0) & (u <= 1)
    t = np.where(ok, t, np.inf).min(axis=1)
    hit = np.isfinite(t)
    return cam + t[hit, None] * d[hit]


def _frames(open_risers: bool, kind: str = "stair_up", overhang_m: float = 0.0, seed: int = 0):
    """Camera-relative noisy, smoothed profiles along a 6-step stair (and its terrain)."""
    terrain = build_terrain(
        TerrainConfig(
            kind=kind,
            approach_length_m=0.5,
            n_steps=6,
            open_risers=open_risers,
            nosing_overhang_m=overhang_m,
        )
    )
    segs = _segments(terrain)
    rng = np.random.default_rng(seed)
    out = []
    for x in np.arange(-0.2, 1.8, 0.05):
        cam = np.array([x, float(terrain.height_at(np.array([x]))[0]) + 0.45])
        hits = _cast(segs, cam) - cam
        hits = hits + rng.normal(0, 0.002, hits.shape)
        out.append((cam, smooth_profile(hits, 8, 0.005, 10)))
    return terrain, out


@pytest.mark.parametrize("kind", ["stair_up", "stair_down"])
@pytest.mark.parametrize("overhang_m", [0.0, 0.03])
def test_closed_risers_lose_no_point(kind: str, overhang_m: float) -> None:
    cfg = FrontTerrainConfig()
    _, frames = _frames(False, kind, overhang_m)
    for _, prof in frames:
        _, levels = classify_terrain(prof, cfg)
        assert not points_under_levels(prof, levels, cfg).any()
        assert not points_seen_under(prof, levels, cfg).any()


def test_open_risers_floor_seen_under_the_treads_is_dropped_and_the_frame_is_a_stair() -> None:
    cfg = FrontTerrainConfig()
    terrain, frames = _frames(True)
    n_under, kinds_before, kinds_after = 0, [], []
    for cam, prof in frames:
        kind, levels = classify_terrain(prof, cfg)
        under = points_under_levels(prof, levels, cfg)
        kinds_before.append(kind)
        if under.any():
            world = prof[under] + cam
            # the dropped points are the floor (z = 0) or the wall under the landing, all
            # below the walking surface
            surface = terrain.height_at(world[:, 0])
            assert np.all(world[:, 1] < surface - 0.03)
            n_under += int(under.sum())
            kind, _ = classify_terrain(prof[~under], cfg)
        kinds_after.append(kind)
    assert n_under > 100
    up_before = np.mean([k is TerrainKind.STAIR_UP for k in kinds_before])
    up_after = np.mean([k is TerrainKind.STAIR_UP for k in kinds_after])
    assert up_after > up_before + 0.2 and up_after > 0.7


def test_mask_known_answers() -> None:
    # a tread at z 0.3 over x [1, 1.3], a floor level at 0 under it over x [0.5, 2]
    levels = ([0.3, 0.0], [1.0, 0.5], [1.3, 2.0])
    pts = np.array(
        [
            [1.15, 0.0],  # floor under the tread's middle: under
            [1.02, 0.0],  # floor under the tread's first 2 cm: on a level under it: under
            [1.02, 0.15],  # a riser point at the tread's start, on no level: kept
            [1.5, 0.0],  # floor beyond the tread: kept
            [1.15, 0.28],  # slab underside 2 cm below: kept
        ]
    )
    mask = under_levels_mask(pts, *levels, margin_m=0.05, drop_m=0.04, band_m=0.04)
    assert mask.tolist() == [True, True, False, False, False]
    # line of sight from the origin (camera) at z 0.5: a point at (1.6, -0.4) relative is
    # seen under a tread at -0.1 over [0.5, 1.0]; one at (0.8, -0.4) only if inside it
    rel = np.array([[1.6, -0.4], [0.6, -0.05], [2.0, -0.1]])
    mask = under_levels_mask(
        rel, [-0.1], [0.5], [1.0], margin_m=0.05, drop_m=0.04, band_m=0.04, sight_margin_m=0.02
    )
    assert mask.tolist() == [True, False, False]


@pytest.mark.parametrize("seed", [0, 1])
def test_open_riser_map_gives_each_step(seed: int) -> None:
    """A map of an open-riser stair (the floor under the flight seen in every keyframe) is a
    stair up with every rise and tread within 3 mm, as the closed stair's."""
    terrain = build_terrain(TerrainConfig(approach_length_m=0.5, n_steps=5, open_risers=True))
    segs = _segments(terrain)
    rng = np.random.default_rng(seed)
    tmap = TerrainMap2D()
    xs = np.arange(-0.3, float(terrain.edges_xz_m[-1, 0]) + 0.3, 0.015)
    for i, x in enumerate(xs):
        cam = np.array([x, float(terrain.height_at(np.array([x]))[0]) + 0.45])
        hits = _cast(segs, cam, pitch_down_deg=45.0, n=172)
        tmap.add_keyframe(0.1 * i, cam, hits - cam + rng.normal(0, 0.0025, hits.shape))
    geometry = estimate_terrain_geometry(tmap.points_xz_m, tmap.point_counts)
    assert geometry.kind is TerrainKind.STAIR_UP
    assert len(geometry.steps) == 5
    info = TerrainInfo(
        kind=terrain.kind,
        params=terrain.params,
        profile_xz_m=[tuple(p) for p in terrain.profile_xz_m.tolist()],
        edges_xz_m=[tuple(p) for p in terrain.edges_xz_m.tolist()],
    )
    report = compare_to_truth(geometry, info)
    assert report["n_steps_matched"] == 5
    assert report["rise_mae_mm"] < 3.0 and report["tread_mae_mm"] < 3.0


@pytest.mark.parametrize("open_risers", [False, True], ids=["closed", "open"])
def test_frontend_profile_is_the_walking_surface(open_risers: bool) -> None:
    """A rendered frame of a stair (camera 45 cm above the first tread, pitched 60 deg down:
    two treads in view and, with open risers, the floor under them): the front end's profile
    loses that floor and the frame is a stair up; with closed risers the profile is every
    smoothed slice point. (Frames whose upper tread is out of view show a tread and the floor
    beyond it, as a ledge would: docs/method.md section 1.)"""
    from vio_graph.frontend.frontend import VisualFrontend
    from vio_graph.frontend.projection import sagittal_slice_from_depth
    from vio_graph.sim.config import CameraConfig
    from vio_graph.sim.tof import TofCamera
    from vio_graph.sim.trial import R_shank_cam
    from vio_graph.types import DepthFrame

    terrain = build_terrain(TerrainConfig(n_steps=5, open_risers=open_risers))
    cam = TofCamera(CameraConfig(noise=False), terrain)
    R = R_shank_cam(60.0)
    pos = np.array([terrain.feature_x_m + 0.1, 0.0, 0.147 + 0.45])
    depth, conf = cam.render(pos, R, np.random.default_rng(0))
    K = np.array([[cam.fx, 0, cam.cx], [0, cam.fy, cam.cy], [0, 0, 1.0]])
    fe = VisualFrontend()
    res = fe.process(DepthFrame(0, 0.0, depth, conf), K, R)
    world = res.profile_xz_m + pos[[0, 2]]
    below = world[:, 1] < terrain.height_at(world[:, 0]) - 0.04
    assert not below.any()
    assert res.terrain is TerrainKind.STAIR_UP
    cfg = fe.config
    pc = cfg.projection
    raw = sagittal_slice_from_depth(
        depth, conf, K, R, pc.half_width_m, pc.min_depth_m, pc.max_depth_m, pc.min_confidence
    )
    full = smooth_profile(
        raw, cfg.smoothing.k_neighbours, cfg.smoothing.grid_cell_m, cfg.smoothing.min_points
    )
    full_world = full + pos[[0, 2]]
    full_below = full_world[:, 1] < terrain.height_at(full_world[:, 0]) - 0.04
    if open_risers:
        assert full_below.sum() > 10  # the floor under the flight was in the slice
        assert res.profile_xz_m.shape[0] < full.shape[0]
    else:
        np.testing.assert_array_equal(res.profile_xz_m, full)


def test_seen_under_mask_known_answers() -> None:
    # camera at the origin; the 3 cm front of a tread at x 0.7 (z -0.18 .. -0.15, its top out
    # of view), a tread at z -0.3 over x [0.4, 0.69] and the floor at z -0.45 beyond
    front = np.column_stack([np.full(7, 0.7), np.linspace(-0.18, -0.15, 7)])
    tread = np.column_stack([np.linspace(0.4, 0.69, 30), np.full(30, -0.3)])
    floor = np.array([[1.3, -0.45], [1.5, -0.45]])  # line of sight passes 6-8 cm under front
    mask = seen_under_mask(np.vstack([front, tread, floor]), 0.05, 0.04, 3)
    assert not mask[:37].any() and mask[37:].all()
    # with two points of the front only, no occluder count of 3
    mask = seen_under_mask(np.vstack([front[:2], tread, floor]), 0.05, 0.04, 3)
    assert not mask.any()
    # a box top at z -0.3 over x [0.5, 0.63] and the floor behind it seen over its top
    box = np.column_stack([np.linspace(0.5, 0.63, 20), np.full(20, -0.3)])
    behind = np.column_stack([np.linspace(1.2, 1.5, 10), np.full(10, -0.45)])
    assert not seen_under_mask(np.vstack([box, behind]), 0.05, 0.04, 3).any()


def test_floor_beyond_slab_mask_known_answers() -> None:
    # levels near to far: floor (z -0.41) in front of and under a tread (z -0.265) over
    # x [0.33, 0.59], the floor again beyond it (x 0.98 .. 1.5)
    z, lo, hi = [-0.41, -0.265, -0.41], [0.26, 0.33, 0.98], [0.45, 0.59, 1.5]
    near = np.column_stack([np.linspace(0.26, 0.32, 12), np.full(12, -0.41)])
    under = np.column_stack([np.linspace(0.4, 0.45, 10), np.full(10, -0.41)])
    tread = np.column_stack([np.linspace(0.33, 0.59, 40), np.full(40, -0.265)])
    far = np.column_stack([np.linspace(0.98, 1.5, 40), np.full(40, -0.41)])
    pts = np.vstack([near, under, tread, far])
    mask = floor_beyond_slab_mask(pts, z, lo, hi, 0.05, 0.04, 0.04, 8)
    assert mask[-40:].all() and not mask[:-40].any()
    # descent: the floor nearer than the lowest tread lies under the tread above it (a level
    # at -0.2 over [0.0, 0.3]): not the walking surface in front, nothing is dropped
    upper = np.column_stack([np.linspace(0.0, 0.3, 40), np.full(40, -0.2)])
    pts = np.vstack([upper, near - [0.2, 0.0], under, tread, far])
    z2, lo2, hi2 = [-0.2, -0.41, -0.265, -0.41], [0.0, 0.06, 0.33, 0.98], [0.3, 0.45, 0.59, 1.5]
    assert not floor_beyond_slab_mask(pts, z2, lo2, hi2, 0.05, 0.04, 0.04, 8).any()


def test_face_seen_beyond_a_tread_is_no_floor_behind_an_obstacle() -> None:
    # two treads (z -0.28 over x [0.22, 0.37], z -0.135 over [0.38, 0.5]) and, far beyond, a
    # vertical strip seen through the gap under the next tread (z -0.3 .. -0.22 at x 1.5)
    cfg = FrontTerrainConfig()
    t1 = np.column_stack([np.linspace(0.22, 0.37, 30), np.full(30, -0.28)])
    t2 = np.column_stack([np.linspace(0.385, 0.5, 24), np.full(24, -0.135)])
    strip = np.column_stack([np.full(12, 1.5), np.linspace(-0.3, -0.22, 12)])
    kind, _ = classify_terrain(np.vstack([t1, t2, strip]), cfg)
    assert kind is TerrainKind.STAIR_UP
    # the same raised level with a glimpse of floor behind it (6 points over 10 cm, too few
    # for a level): an obstacle
    floor = np.column_stack([np.linspace(0.8, 0.9, 6), np.full(6, -0.28)])
    kind, _ = classify_terrain(np.vstack([t1, t2, floor]), cfg)
    assert kind is TerrainKind.OBSTACLE
