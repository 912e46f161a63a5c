"""The simulator's long-trial paths give the same numbers as the direct forms they replaced.

``Terrain.height_at`` bisects for the segments under each x instead of testing every
segment, the foot motion takes each stride phase as a slice of the sorted time grid instead
of a mask over the whole grid, the swing pitch looks only at the swings near the times asked
for, and ``TofCamera.edges_visible`` casts rays only for the edges in view, a chunk of frames
at a time. A 10-minute trial has ~900 edges and ~900 strides, where each of those was O(N x P)
time or memory; the recordings of the existing scenarios must not change.
"""

from __future__ import annotations

from types import SimpleNamespace

import numpy as np
import pytest

from vio_graph.sim import load_scenario, simulate_trial
from vio_graph.sim.gait import _SwingPitch, _TimeSpans
from vio_graph.sim.terrain import build_terrain


@pytest.mark.parametrize(
    ("scenario", "update"),
    [
        ("upstair", {}),
        ("downstair", {"n_flights": 3}),
        ("upstair", {"nosing_overhang_m": 0.03}),
        ("obstacle", {}),
        ("level", {}),
    ],
)
def test_height_at_equals_every_segment_test(scenario: str, update: dict) -> None:
    cfg = load_scenario(scenario)
    terrain = build_terrain(cfg.terrain.model_copy(update=update))
    p = terrain.profile_xz_m
    rng = np.random.default_rng(0)
    x = np.concatenate(
        [
            rng.uniform(p[0, 0] - 0.5, p[-1, 0] + 0.5, 5000),
            p[:, 0],  # on the vertices (risers: two segments meet)
            p[:, 0] + 1e-12,
            p[:, 0] - 1e-12,
            np.nextafter(p[:, 0], np.inf),
            [np.nan],
        ]
    )
    fast, ref = terrain.height_at(x), terrain._height_at_all_segments(x)
    np.testing.assert_array_equal(fast, ref)
    assert np.isfinite(fast[:-1]).all()
    # a riser's top: the max over the vertical segment and the treads either side
    if terrain.edges_xz_m.size:
        e = terrain.edges_xz_m[0]
        assert terrain.height_at(np.array([e[0]]))[0] == pytest.approx(e[1], abs=1e-12)


def test_time_spans_equal_masks() -> None:
    rng = np.random.default_rng(1)
    t = np.sort(np.round(rng.uniform(0, 10, 3000), 2))  # sorted, with repeated times
    spans = _TimeSpans(t)
    unsorted = _TimeSpans(t[::-1])
    bounds = np.concatenate([rng.uniform(-1, 11, 200), t[rng.integers(0, t.size, 200)]])
    for a, b in rng.choice(bounds, size=(300, 2)):
        for closed in (False, True):
            mask = (t >= a) & ((t <= b) if closed else (t < b))
            np.testing.assert_array_equal(t[spans(a, b, closed)], t[mask])
            np.testing.assert_array_equal(unsorted(a, b, closed), mask[::-1])


def test_swing_pitch_near_swings_equal_all_swings() -> None:
    """Asking with a NaN in t takes the path over every swing; the other times must get the
    same weight and target as without it (the path over the nearby swings only)."""
    gait = load_scenario("upstair").gait
    rng = np.random.default_rng(2)
    starts = np.cumsum(rng.uniform(0.8, 1.2, 40))
    kinds = [k for k, a in gait.swing_ankle_deg.items() if a is not None]
    strides = [
        SimpleNamespace(t_toe_off_s=t0, t_next_s=t0 + rng.uniform(0.3, 1.5), swing_kind=k)
        for t0, k in zip(starts, rng.choice(kinds, starts.size), strict=True)
    ]  # some swings overlap the next one: the later swing wins, as over all swings
    sp = _SwingPitch(lambda t: np.zeros_like(t), strides, lambda t: t, (0.5, 40.0), gait)
    t = np.linspace(-0.5, 45.0, 9001)
    for chunk in (t, t[500:530], t[:1], t[8990:], t[4000:4001]):
        w, a = sp.weight_and_target(chunk)
        w_all, a_all = sp.weight_and_target(np.append(chunk, np.nan))
        np.testing.assert_array_equal(w, w_all[:-1])
        np.testing.assert_array_equal(a, a_all[:-1])
    w, a = sp.weight_and_target(t)
    assert 0.3 < np.mean(w > 0) < 0.95 and np.any(a != 0)  # swings are found and weighted


def test_edges_visible_chunked_equals_one_batch(monkeypatch) -> None:
    import vio_graph.sim.tof as tof

    cfg = load_scenario("upstair_long").model_copy(update={"duration_s": 20.0})
    trial = simulate_trial(cfg, 2)
    cam = trial.camera
    e = trial.terrain.edges_xz_m
    edges = np.column_stack([e[:, 0], np.zeros(len(e)), e[:, 1]])
    pos, R = trial.camera_position_m, trial.R_world_cam
    monkeypatch.setattr(tof, "EDGE_RAYS_PER_CHUNK", 50 * len(edges))  # chunks of 50 frames
    vis = cam.edges_visible(pos, R, edges)
    # reference: every (frame, edge) ray cast in one batch, as before
    rel = edges[None, :, :] - pos[:, None, :]
    p_c = np.einsum("fji,fej->fei", R, rel)
    z = p_c[..., 2]
    zs = np.where(z > 1e-6, z, 1.0)
    u = cam.fx * p_c[..., 0] / zs + cam.cx
    v = cam.fy * p_c[..., 1] / zs + cam.cy
    rng_m = np.linalg.norm(rel, axis=-1)
    c = cam.cfg
    inside = (z > 1e-6) & (u >= 2.0) & (u <= c.width_px - 3.0)
    inside &= (v >= 2.0) & (v <= c.height_px - 3.0)
    inside &= (rng_m >= c.min_range_m) & (rng_m <= c.max_range_m)
    rays = np.concatenate([np.broadcast_to(pos[:, None, :], rel.shape), rel], -1)
    ans = cam.scene.cast_rays(cam._o3d.core.Tensor(rays.astype(np.float32)), nthreads=0)
    ref = inside & (ans["t_hit"].numpy() >= 1.0 - 0.01 / np.maximum(rng_m, 1e-6))
    np.testing.assert_array_equal(vis, ref)
    assert 0.2 < ref.any(axis=1).mean() <= 1.0
