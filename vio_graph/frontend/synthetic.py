"""Tiny synthetic terrain and ToF renderer for front-end tests and benchmarks.

Independent of ``vio_graph.sim`` on purpose: the terrain is a polyline in the world x-z plane
extruded infinitely along y, and a depth image is made by intersecting each pixel ray with the
polyline (exact, vectorised over pixels x segments). Occlusion is handled (nearest hit wins).
"""

from __future__ import annotations

import numpy as np
from numpy.typing import NDArray


def stair_polyline(
    kind: str,
    n_steps: int = 4,
    rise_m: float = 0.147,
    run_m: float = 0.28,
    start_x_m: float = 1.0,
    floor_before_m: float = 2.0,
    floor_after_m: float = 2.0,
    obstacle_height_m: float = 0.14,
    obstacle_depth_m: float = 0.13,
    nosing_overhang_m: float = 0.0,
    nosing_thickness_m: float = 0.025,
) -> NDArray[np.float64]:
    """Vertices (V, 2) of a sagittal terrain profile, x increasing, floor at z = 0.

    ``kind``: "stair_up" (first riser at ``start_x_m``), "stair_down" (top landing at
    z = n_steps * rise_m until ``start_x_m``, then steps down), "obstacle" (a box of
    ``obstacle_height_m`` x ``obstacle_depth_m`` starting at ``start_x_m``) or "level".
    ``nosing_overhang_m`` (stairs only): each tread protrudes this far past its riser, as a
    nosing block ``nosing_thickness_m`` tall (a vertical face, then the underside back to the
    riser). Riser positions stay at ``start_x_m + i * run_m``; the nosing tip moves by the
    overhang towards the lower side.
    """
    x0 = start_x_m
    if kind == "level":
        return np.array([[x0 - floor_before_m, 0.0], [x0 + floor_after_m, 0.0]])
    if kind == "obstacle":
        h, d = obstacle_height_m, obstacle_depth_m
        return np.array(
            [
                [x0 - floor_before_m, 0.0],
                [x0, 0.0],
                [x0, h],
                [x0 + d, h],
                [x0 + d, 0.0],
                [x0 + d + floor_after_m, 0.0],
            ]
        )
    sign = {"stair_up": 1.0, "stair_down": -1.0}[kind]
    z = 0.0 if sign > 0 else n_steps * rise_m
    verts = [[x0 - floor_before_m, z]]
    x = x0
    o, t = nosing_overhang_m, min(nosing_thickness_m, rise_m / 2)
    for _ in range(n_steps):
        if o <= 0:
            verts += [[x, z], [x, z + sign * rise_m]]
        elif sign > 0:  # riser up to the underside, back towards the camera, nosing face up
            verts += [[x, z], [x, z + rise_m - t], [x - o, z + rise_m - t], [x - o, z + rise_m]]
        else:  # tread out to the nosing tip, face down, underside back, riser down
            verts += [[x + o, z], [x + o, z - t], [x, z - t], [x, z - rise_m]]
        z += sign * rise_m
        x += run_m
    verts.append([x - run_m + floor_after_m, z])
    return np.asarray(verts, dtype=float)


def stair_edges(
    polyline_xz_m: NDArray[np.float64], min_surface_m: float = 0.05
) -> NDArray[np.float64]:
    """Convex corners (nosings / obstacle top edges) of a rectilinear profile, (E, 2).

    Only corners that bound a horizontal surface (tread, landing, obstacle top) at least
    ``min_surface_m`` long count: the underside corner of an overhanging nosing does not.
    """
    v = np.asarray(polyline_xz_m, dtype=float)
    d_in, d_out = v[1:-1] - v[:-2], v[2:] - v[1:-1]
    cross = d_in[:, 0] * d_out[:, 1] - d_in[:, 1] * d_out[:, 0]
    convex = cross < -1e-12  # right turn when walking along +x = convex corner

    def long_flat(d: NDArray[np.float64]) -> NDArray[np.bool_]:
        return (np.abs(d[:, 1]) < 1e-12) & (np.abs(d[:, 0]) >= min_surface_m)

    return v[1:-1][convex & (long_flat(d_in) | long_flat(d_out))]


def tread_side(polyline_xz_m: NDArray[np.float64], min_surface_m: float = 0.05) -> NDArray:
    """For each corner of :func:`stair_edges`: +1 if its horizontal surface (the tread) lies
    towards +x from the corner, -1 if towards -x."""
    v = np.asarray(polyline_xz_m, dtype=float)
    d_in, d_out = v[1:-1] - v[:-2], v[2:] - v[1:-1]
    cross = d_in[:, 0] * d_out[:, 1] - d_in[:, 1] * d_out[:, 0]
    flat_out = (np.abs(d_out[:, 1]) < 1e-12) & (np.abs(d_out[:, 0]) >= min_surface_m)
    flat_in = (np.abs(d_in[:, 1]) < 1e-12) & (np.abs(d_in[:, 0]) >= min_surface_m)
    keep = (cross < -1e-12) & (flat_in | flat_out)
    return np.where(flat_out[keep], 1.0, -1.0)


def drop_tread_band(
    points_rel_xz_m: NDArray[np.float64],
    camera_xz_m: NDArray[np.float64],
    polyline_xz_m: NDArray[np.float64],
    length_m: float,
    start_m: float = 0.0,
    height_tol_m: float = 0.015,
) -> NDArray[np.float64]:
    """Remove the band of a ToF profile that a flying-pixel filter removes at a nosing.

    Points on the tread (within ``height_tol_m`` of the nosing height) between ``start_m`` and
    ``start_m + length_m`` behind every nosing of ``polyline_xz_m`` (behind = along the tread,
    away from the riser) are dropped. ``points_rel_xz_m`` (N, 2) are relative to the camera at
    ``camera_xz_m`` (world); returns the kept points, still camera-relative.
    """
    pts = np.asarray(points_rel_xz_m, dtype=float)
    world = pts + np.asarray(camera_xz_m, dtype=float)
    drop = np.zeros(pts.shape[0], dtype=bool)
    for edge, side in zip(stair_edges(polyline_xz_m), tread_side(polyline_xz_m), strict=True):
        behind = side * (world[:, 0] - edge[0])
        drop |= (
            (behind > start_m)
            & (behind < start_m + length_m)
            & (np.abs(world[:, 1] - edge[1]) <= height_tol_m)
        )
    return pts[~drop]


def intersect_rays_polyline(
    origin_xz_m: NDArray[np.float64], dirs_xz: NDArray[np.float64], polyline_xz_m: NDArray
) -> NDArray[np.float64]:
    """Ray parameter t >= 0 of the first hit of ``origin + t * dir`` with the polyline.

    Args:
        origin_xz_m: (2,) ray origin. dirs_xz: (N, 2) directions (not necessarily unit).
        polyline_xz_m: (V, 2) vertices.

    Returns:
        (N,) t of the nearest hit, ``inf`` where a ray misses.
    """
    o = np.asarray(origin_xz_m, dtype=float)
    d = np.asarray(dirs_xz, dtype=float)[:, None, :]  # (N, 1, 2)
    a = np.asarray(polyline_xz_m, dtype=float)[:-1][None]  # (1, S, 2)
    e = np.diff(np.asarray(polyline_xz_m, dtype=float), axis=0)[None]  # (1, S, 2)
    # o + t d = a + s e  ->  t d - s e = a - o
    denom = d[..., 0] * (-e[..., 1]) - d[..., 1] * (-e[..., 0])
    ao = a - o
    with np.errstate(divide="ignore", invalid="ignore"):
        t = (ao[..., 0] * (-e[..., 1]) - ao[..., 1] * (-e[..., 0])) / denom
        s = (d[..., 0] * ao[..., 1] - d[..., 1] * ao[..., 0]) / denom
    hit = (np.abs(denom) > 1e-12) & (t > 1e-9) & (s >= 0) & (s <= 1)
    return np.where(hit, t, np.inf).min(axis=1)


def camera_rotation(pitch_down_rad: float, roll_rad: float = 0.0) -> NDArray[np.float64]:
    """R_world_cam of a camera looking along world +x, pitched down by ``pitch_down_rad`` and
    rolled about its optical axis by ``roll_rad`` (optical frame: x right, y down, z forward)."""
    c, s = np.cos(pitch_down_rad), np.sin(pitch_down_rad)
    z_c = np.array([c, 0.0, -s])
    x_c = np.array([0.0, -1.0, 0.0])
    y_c = np.cross(z_c, x_c)
    R = np.column_stack([x_c, y_c, z_c])
    cr, sr = np.cos(roll_rad), np.sin(roll_rad)
    R_roll = np.array([[cr, -sr, 0.0], [sr, cr, 0.0], [0.0, 0.0, 1.0]])  # about optical z
    return R @ R_roll


def pico_flexx_K(width_px: int = 224, height_px: int = 172) -> NDArray[np.float64]:
    """Pinhole intrinsics of a 224 x 172 ToF camera with a 62 x 49 degree field of view."""
    fx = (width_px / 2) / np.tan(np.radians(62.0) / 2)
    fy = (height_px / 2) / np.tan(np.radians(49.0) / 2)
    return np.array([[fx, 0.0, (width_px - 1) / 2], [0.0, fy, (height_px - 1) / 2], [0, 0, 1.0]])


def render_depth(
    polyline_xz_m: NDArray[np.float64],
    camera_xz_m: NDArray[np.float64],
    R_world_cam: NDArray[np.float64],
    K: NDArray[np.float64],
    shape: tuple[int, int] = (172, 224),
    noise_m: float = 0.0,
    rng: np.random.Generator | None = None,
    max_depth_m: float = 4.0,
) -> tuple[NDArray[np.float32], NDArray[np.uint8]]:
    """Depth image (H, W) float32 (0 = no return) and confidence (H, W) uint8 of the terrain.

    Depth is along the optical axis: for a ray ``d_C = K^-1 [u, v, 1]`` the hit parameter t is
    the depth. Gaussian noise of ``noise_m`` is added to valid depths.
    """
    H, W = shape
    v, u = np.mgrid[0:H, 0:W]
    rays_c = np.linalg.solve(K, np.stack([u.ravel(), v.ravel(), np.ones(H * W)]))  # (3, HW)
    rays_w = np.asarray(R_world_cam, dtype=float) @ rays_c
    t = intersect_rays_polyline(camera_xz_m, rays_w[[0, 2]].T, polyline_xz_m)
    valid = np.isfinite(t) & (t < max_depth_m)
    depth = np.where(valid, t, 0.0)
    if noise_m > 0:
        rng = np.random.default_rng(0) if rng is None else rng
        depth = np.where(valid, depth + rng.normal(0.0, noise_m, depth.shape), 0.0)
    conf = np.where(valid, 200, 0).astype(np.uint8)
    return depth.reshape(H, W).astype(np.float32), conf.reshape(H, W)


def raycast_profile(
    polyline_xz_m: NDArray[np.float64],
    camera_xz_m: NDArray[np.float64],
    pitch_down_rad: float = 0.6,
    fov_rad: float = np.radians(49.0),
    n_rays: int = 400,
    noise_m: float = 0.0,
    rng: np.random.Generator | None = None,
    max_range_m: float = 4.0,
) -> NDArray[np.float64]:
    """2D sagittal profile seen from ``camera_xz_m``: fan of rays in the x-z plane, (N, 2)
    points RELATIVE to the camera (world axes), with range noise ``noise_m`` along the ray."""
    angles = -pitch_down_rad + np.linspace(-fov_rad / 2, fov_rad / 2, n_rays)
    dirs = np.column_stack([np.cos(angles), np.sin(angles)])
    t = intersect_rays_polyline(camera_xz_m, dirs, polyline_xz_m)
    keep = np.isfinite(t) & (t < max_range_m)
    t, dirs = t[keep], dirs[keep]
    if noise_m > 0:
        rng = np.random.default_rng(0) if rng is None else rng
        t = t + rng.normal(0.0, noise_m, t.shape)
    return dirs * t[:, None]
