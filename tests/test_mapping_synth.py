"""Synthetic sagittal terrain and a 2D ray-cast camera for the mapping tests.

The helpers build true profiles (polylines, x increasing) with their convex edges, and
observe them from known camera positions with a fan of rays (occlusion included: risers of
a descending stair and the shadow behind a nosing are not seen), plus Gaussian noise.
"""

from __future__ import annotations

import numpy as np
import pytest

from vio_graph.recording.metadata import TerrainInfo


def stair_profile(
    rise_m: float, tread_m: float, n_steps: int, up: bool = True, x0_m: float = 0.5
) -> TerrainInfo:
    """A straight stair of ``n_steps`` risers starting at ``x0_m``, 1.5 m floor / landing."""
    pts: list[tuple[float, float]] = [(-1.0, 0.0)]
    edges: list[tuple[float, float]] = []
    sign = 1.0 if up else -1.0
    for k in range(n_steps):
        x = x0_m + k * tread_m
        z_before, z_after = sign * k * rise_m, sign * (k + 1) * rise_m
        pts += [(x, z_before), (x, z_after)]
        edges.append((x, max(z_before, z_after)))
    pts.append((x0_m + (n_steps - 1) * tread_m + 1.5, sign * n_steps * rise_m))
    return TerrainInfo(
        kind="stair_up" if up else "stair_down",
        params={"rise_m": rise_m, "tread_m": tread_m, "n_steps": n_steps},
        profile_xz_m=pts,
        edges_xz_m=edges,
    )


def obstacle_profile(height_m: float, depth_m: float, x0_m: float = 0.5) -> TerrainInfo:
    """A block of ``height_m`` x ``depth_m`` on level ground, front face at ``x0_m``."""
    x1 = x0_m + depth_m
    pts = [(-1.0, 0.0), (x0_m, 0.0), (x0_m, height_m), (x1, height_m), (x1, 0.0), (x1 + 1.5, 0.0)]
    return TerrainInfo(
        kind="obstacle",
        params={"height_m": height_m, "depth_m": depth_m},
        profile_xz_m=pts,
        edges_xz_m=[(x0_m, height_m), (x1, height_m)],
    )


def ray_cast(
    profile_xz_m: np.ndarray,
    camera_xz_m: np.ndarray,
    pitch_down_rad: float = np.deg2rad(45.0),
    fov_rad: float = np.deg2rad(56.0),
    n_rays: int = 172,
    max_range_m: float = 2.0,
) -> np.ndarray:
    """Nearest hits (K, 2) of a fan of rays from ``camera_xz_m`` on the polyline, world."""
    p0, p1 = profile_xz_m[:-1], profile_xz_m[1:]
    seg = p1 - p0  # (S, 2)
    angles = -pitch_down_rad + np.linspace(-fov_rad / 2, fov_rad / 2, n_rays)
    d = np.stack([np.cos(angles), np.sin(angles)], axis=1)  # (R, 2)
    # solve c + t d = p0 + u seg for every (ray, segment)
    w = p0[None, :, :] - camera_xz_m[None, None, :]  # (1, S, 2)
    denom = d[:, None, 0] * seg[None, :, 1] - d[:, None, 1] * seg[None, :, 0]  # (R, S)
    with np.errstate(divide="ignore", invalid="ignore"):
        t = (w[..., 0] * seg[None, :, 1] - w[..., 1] * seg[None, :, 0]) / denom
        u = (w[..., 0] * d[:, None, 1] - w[..., 1] * d[:, None, 0]) / denom
    valid = (np.abs(denom) > 1e-12) & (t > 0) & (t < max_range_m) & (u >= 0) & (u <= 1)
    t = np.where(valid, t, np.inf)
    t_min = t.min(axis=1)
    hit = np.isfinite(t_min)
    return camera_xz_m[None, :] + t_min[hit, None] * d[hit]


def camera_track(
    terrain: TerrainInfo,
    x_start_m: float,
    x_end_m: float,
    step_m: float = 0.02,
    height_m: float = 0.45,
) -> np.ndarray:
    """(K, 2) camera positions every ``step_m`` along x, ``height_m`` above the terrain."""
    profile = np.asarray(terrain.profile_xz_m)
    xs = np.arange(x_start_m, x_end_m, step_m)
    # terrain height under x: the last profile vertex at or before x (treads are flat)
    idx = np.searchsorted(profile[:, 0], xs, side="right") - 1
    return np.stack([xs, profile[idx, 1] + height_m], axis=1)


def observe(
    terrain: TerrainInfo,
    cameras_xz_m: np.ndarray,
    noise_m: float,
    rng: np.random.Generator,
) -> list[np.ndarray]:
    """Noisy profiles relative to each camera (list of (N_k, 2))."""
    profile = np.asarray(terrain.profile_xz_m)
    out = []
    for cam in cameras_xz_m:
        hits = ray_cast(profile, cam)
        out.append(hits - cam + rng.normal(0.0, noise_m, size=hits.shape))
    return out


# -- tests of the helpers themselves ---------------------------------------------------------
def test_ray_cast_hits_a_flat_floor_at_the_right_place() -> None:
    floor = np.array([[-5.0, 0.0], [5.0, 0.0]])
    cam = np.array([0.0, 0.5])
    hits = ray_cast(floor, cam, pitch_down_rad=np.pi / 2, fov_rad=0.0, n_rays=1)
    np.testing.assert_allclose(hits, [[0.0, 0.0]], atol=1e-12)
    hits = ray_cast(floor, cam, pitch_down_rad=np.pi / 4, fov_rad=0.0, n_rays=1)
    np.testing.assert_allclose(hits, [[0.5, 0.0]], atol=1e-12)


def test_descending_risers_are_occluded_ascending_risers_seen() -> None:
    for up in (False, True):
        terrain = stair_profile(0.15, 0.3, 3, up=up)
        cams = camera_track(terrain, 0.0, 1.0, step_m=0.1)
        hits = np.concatenate([ray_cast(np.asarray(terrain.profile_xz_m), c) for c in cams])
        on_riser = np.zeros(hits.shape[0], dtype=bool)
        for x_edge, z_edge in terrain.edges_xz_m:
            on_riser |= (np.abs(hits[:, 0] - x_edge) < 1e-9) & (hits[:, 1] < z_edge - 1e-6)
        assert hits.shape[0] > 500
        assert on_riser.any() == up


@pytest.mark.parametrize("up", [True, False])
def test_stair_profile_edges_are_profile_vertices(up: bool) -> None:
    terrain = stair_profile(0.147, 0.28, 5, up=up)
    profile = np.asarray(terrain.profile_xz_m)
    assert np.all(np.diff(profile[:, 0]) >= 0)
    for edge in terrain.edges_xz_m:
        assert np.min(np.linalg.norm(profile - np.asarray(edge), axis=1)) < 1e-12
