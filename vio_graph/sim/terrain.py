"""Terrain: a sagittal profile (polyline in the world x-z plane) extruded into a triangle mesh.

Pure: builds arrays only. The ToF model turns the mesh into an open3d RaycastingScene.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from numpy.typing import NDArray

from vio_graph.errors import ConfigError, SimulationError
from vio_graph.sim.config import TerrainConfig

_BACK_MARGIN_M = 1.0  # floor behind the start so a camera looking down never sees a hole


@dataclass(frozen=True)
class Terrain:
    """The true terrain.

    ``profile_xz_m``: (P, 2) polyline, x non-decreasing (risers are vertical segments).
    ``edges_xz_m``: (E, 2) convex corners (stair nosings, obstacle top edges).
    ``vertices_m`` (V, 3) / ``triangles`` (T, 3) int32: the extruded mesh, world frame.
    ``feature_x_m``: x of the first feature (first riser / edge / obstacle front face).
    ``mesh_profile_xz_m``: the profile that was extruded when it differs from
    ``profile_xz_m`` (nosing overhang: risers set back under the treads; open risers: the
    floor under the flight, the tread slabs being extra parts of the mesh), else None.
    ``irregular``: stairs whose rises / treads differ step to step (``stair_steps``).
    ``mesh_parts_xz_m``: closed outlines extruded besides the profile (open-riser treads).
    """

    kind: str
    profile_xz_m: NDArray[np.float64]
    edges_xz_m: NDArray[np.float64]
    vertices_m: NDArray[np.float64]
    triangles: NDArray[np.int32]
    feature_x_m: float
    params: dict[str, float | int | str]
    mesh_profile_xz_m: NDArray[np.float64] | None = None  # extruded profile (nosing undercut)
    irregular: bool = False  # stairs whose steps differ (jitter, first / last rise)
    mesh_parts_xz_m: tuple[NDArray[np.float64], ...] = ()  # closed outlines (open-riser treads)

    def height_at(self, x_m: NDArray[np.float64]) -> NDArray[np.float64]:
        """Terrain height (N,) under x (N,): the top of the profile (max over vertical risers).

        Each x is tested only against the profile segments whose x span (widened by 1e-12 m)
        holds it, found by bisection (the profile's x is non-decreasing); the arithmetic per
        segment and the max over them are those of the test against every segment
        (``_height_at_all_segments``, the reference in tests/test_sim.py), so the heights are
        the same to the bit at O(N log P) instead of O(N P)."""
        x = np.atleast_1d(np.asarray(x_m, dtype=float))
        p = self.profile_xz_m
        x0, x1, z0, z1 = p[:-1, 0], p[1:, 0], p[:-1, 1], p[1:, 1]
        if np.any(x1 < x0):  # not the sorted profile bisection needs
            return self._height_at_all_segments(x)
        # segment k holds x iff x >= x0[k] - 1e-12 (a prefix of k) and x <= x1[k] + 1e-12
        # (a suffix of k): the candidates are k in [lo, hi)
        hi = np.searchsorted(x0 - 1e-12, x, side="right")
        lo = np.searchsorted(x1 + 1e-12, x, side="left")
        span = np.where(x1 - x0 > 0, x1 - x0, 1.0)
        z = np.full(x.shape, -np.inf)
        width = int((hi - lo).max()) if x.size else 0
        for j in range(width):
            k = lo + j
            ok = k < hi
            k = np.where(ok, k, 0)
            frac = np.clip((x - x0[k]) / span[k], 0.0, 1.0)
            dx = x1[k] - x0[k]
            z_seg = np.where(dx > 0, z0[k] + frac * (z1[k] - z0[k]), np.maximum(z0[k], z1[k]))
            z = np.where(ok, np.maximum(z, z_seg), z)
        z = np.where(x < p[0, 0], p[0, 1], z)
        return np.where(x > p[-1, 0], p[-1, 1], z)

    def _height_at_all_segments(self, x_m: NDArray[np.float64]) -> NDArray[np.float64]:
        """``height_at`` by testing every x against every segment (N x P memory)."""
        x = np.atleast_1d(np.asarray(x_m, dtype=float))
        p = self.profile_xz_m
        x0, x1, z0, z1 = p[:-1, 0], p[1:, 0], p[:-1, 1], p[1:, 1]
        inside = (x[:, None] >= x0[None] - 1e-12) & (x[:, None] <= x1[None] + 1e-12)
        span = np.where(x1 - x0 > 0, x1 - x0, 1.0)
        frac = np.clip((x[:, None] - x0[None]) / span[None], 0.0, 1.0)
        z_seg = np.where(x1 - x0 > 0, z0 + frac * (z1 - z0), np.maximum(z0, z1))
        z = np.where(inside, z_seg, -np.inf).max(axis=1)
        z = np.where(x < p[0, 0], p[0, 1], z)
        return np.where(x > p[-1, 0], p[-1, 1], z)

    def tread_spans(self) -> NDArray[np.float64]:
        """Horizontal segments (K, 3): x_start, x_end, z, in x order."""
        p = self.profile_xz_m
        flat = np.abs(p[1:, 1] - p[:-1, 1]) < 1e-9
        keep = flat & (p[1:, 0] - p[:-1, 0] > 1e-9)
        return np.stack([p[:-1, 0][keep], p[1:, 0][keep], p[:-1, 1][keep]], axis=1)


def build_profile(
    cfg: TerrainConfig, rng: np.random.Generator | None = None
) -> tuple[NDArray[np.float64], NDArray[np.float64]]:
    """The true sagittal profile (P, 2) and convex edges (E, 2) for ``cfg``.

    The profile is the walking surface seen from above (x non-decreasing): with a nosing
    overhang the riser is drawn at the nosing tip, i.e. the space under the nosing counts as
    solid (what the feet and the map see); open risers likewise. ``build_mesh_profile`` gives
    the undercut. ``rng`` draws the per-step deviations of irregular stairs
    (``rise_jitter_m``, ``tread_jitter_m``); it is needed only when they are set.
    """
    return _profiles(cfg, rng)[:2]


def build_mesh_profile(
    cfg: TerrainConfig, rng: np.random.Generator | None = None
) -> NDArray[np.float64]:
    """The profile that is extruded into the mesh (P', 2): equal to ``build_profile`` without
    overhang; with ``nosing_overhang_m`` > 0 each riser is set back under a protruding tread
    slab of ``nosing_thickness_m`` (x then steps back, so it is not monotonic). With open
    risers it is the floor under the stair (the tread slabs are separate parts)."""
    return _profiles(cfg, rng)[2]


def is_irregular(cfg: TerrainConfig) -> bool:
    """True if the stair's steps are not all alike (jitter or a different first/last rise)."""
    return (
        cfg.rise_jitter_m > 0
        or cfg.tread_jitter_m > 0
        or cfg.first_rise_m is not None
        or cfg.last_rise_m is not None
    )


def stair_steps(
    cfg: TerrainConfig, rng: np.random.Generator | None = None
) -> list[tuple[float, float, float]]:
    """Per riser in walking order (all flights): nosing x, upper z, lower z (m).

    Regular stairs keep the closed-form positions (x0 + i t, z0 +- i r). Irregular stairs
    (``is_irregular``) accumulate drawn rises and treads: riser k's height is
    ``stair_rise_m`` + U(-rise_jitter_m, rise_jitter_m) (``first_rise_m`` / ``last_rise_m``
    replace the first / last), each nosing-to-nosing tread ``stair_tread_m`` +
    U(-tread_jitter_m, tread_jitter_m), and the next flight starts ``flight_landing_m`` past
    the last nosing of the previous one. Rises are drawn first, then treads, from ``rng``.
    """
    xf = cfg.approach_length_m
    r, t, n, nf = cfg.stair_rise_m, cfg.stair_tread_m, cfg.n_steps, cfg.n_flights
    up = cfg.kind == "stair_up"
    out: list[tuple[float, float, float]] = []
    if not is_irregular(cfg):
        span = (n - 1) * t + cfg.flight_landing_m
        for f in range(nf):
            x0 = xf + f * span
            z0 = f * n * r if up else -f * n * r
            for i in range(n):
                if up:
                    out.append((x0 + i * t, z0 + (i + 1) * r, z0 + i * r))
                else:
                    out.append((x0 + i * t, z0 - i * r, z0 - (i + 1) * r))
        return out
    if (cfg.rise_jitter_m > 0 or cfg.tread_jitter_m > 0) and rng is None:
        raise SimulationError("irregular stairs (rise / tread jitter) need a random generator")
    m = n * nf
    rises = np.full(m, r)
    if cfg.rise_jitter_m > 0:
        rises = rises + rng.uniform(-cfg.rise_jitter_m, cfg.rise_jitter_m, m)
    if cfg.first_rise_m is not None:
        rises[0] = cfg.first_rise_m
    if cfg.last_rise_m is not None:
        rises[-1] = cfg.last_rise_m
    treads = np.full(m, t)  # treads[k]: nosing k to nosing k + 1 (within a flight)
    if cfg.tread_jitter_m > 0:
        treads = treads + rng.uniform(-cfg.tread_jitter_m, cfg.tread_jitter_m, m)
    if np.any(rises <= 0.02) or np.any(treads <= 0.05):
        raise ConfigError(
            "terrain: rise_jitter_m / tread_jitter_m / first_rise_m / last_rise_m leave a "
            f"rise of {rises.min():.3f} m or a tread of {treads.min():.3f} m"
        )
    x, z = xf, 0.0
    for k in range(m):
        if k > 0:
            x += cfg.flight_landing_m if k % n == 0 else float(treads[k - 1])
        zn = z + float(rises[k]) if up else z - float(rises[k])
        out.append((x, zn, z) if up else (x, z, zn))
        z = zn
    return out


def _profiles(
    cfg: TerrainConfig, rng: np.random.Generator | None = None
) -> tuple[
    NDArray[np.float64], NDArray[np.float64], NDArray[np.float64], list[NDArray[np.float64]]
]:
    """Profile, edges, extruded profile and the separately extruded closed parts (open-riser
    tread slabs)."""
    xf = cfg.approach_length_m
    pts: list[tuple[float, float]] = [(-_BACK_MARGIN_M, 0.0), (xf, 0.0)]
    mesh: list[tuple[float, float]] = [(-_BACK_MARGIN_M, 0.0)]
    parts: list[NDArray[np.float64]] = []
    edges: list[tuple[float, float]] = []
    o = cfg.nosing_overhang_m
    stair = cfg.kind in ("stair_up", "stair_down")
    th = cfg.nosing_thickness_m
    steps = stair_steps(cfg, rng) if stair else []
    rise_min = min((zh - zl for _, zh, zl in steps), default=cfg.stair_rise_m)
    if stair and (o > 0 or cfg.open_risers) and th >= rise_min:
        raise ConfigError(
            f"terrain.nosing_thickness_m ({th} m) must be below the lowest riser "
            f"({rise_min:.3f} m, terrain.stair_rise_m {cfg.stair_rise_m} m)"
        )
    if stair and o > 0 and cfg.open_risers:
        raise ConfigError("terrain: open_risers and nosing_overhang_m > 0 cannot be combined")
    if cfg.kind == "stair_up":
        for k, (x, ze, zl) in enumerate(steps):
            pts += [(x, ze)] if k == 0 else [(x, zl), (x, ze)]
            edges.append((x, ze))
            if o > 0:  # riser set back by o under the nosing
                mesh += [(x + o, zl), (x + o, ze - th), (x, ze - th), (x, ze)]
            elif not cfg.open_risers:
                mesh += [(x, zl), (x, ze)]
        x_top, z_top = edges[-1]
        pts.append((x_top + cfg.landing_length_m, z_top))
        if cfg.open_risers:
            # floor under the whole flight; treads are slabs from each nosing to the next
            # riser line; the top landing is a slab over a wall one tread behind its edge
            back = x_top + cfg.stair_tread_m
            mesh += [(back, 0.0), (back, z_top - th), (x_top, z_top - th), (x_top, z_top)]
            for (x, ze, _), (x_next, _, _) in zip(steps[:-1], steps[1:], strict=True):
                parts.append(_slab(x, x_next, ze, th))
        mesh.append((x_top + cfg.landing_length_m, z_top))
    elif cfg.kind == "stair_down":
        for k, (x, ze, zl) in enumerate(steps):
            if k > 0:
                pts.append((x, ze))
            pts.append((x, zl))
            edges.append((x, ze))
            if o > 0:  # riser set back by o under the nosing (towards -x)
                mesh += [(x, ze), (x, ze - th), (x - o, ze - th), (x - o, zl)]
            elif not cfg.open_risers:
                mesh += [(x, ze), (x, zl)]
        x_bot = edges[-1][0]
        z_bot = pts[-1][1]
        pts.append((x_bot + cfg.landing_length_m, z_bot))
        if cfg.open_risers:
            # upper landing: a slab over a wall one tread behind its edge; the lower floor
            # runs under the whole flight; treads are slabs from the riser line to the nosing
            x0 = steps[0][0]
            back = x0 - cfg.stair_tread_m
            mesh += [(x0, 0.0), (x0, -th), (back, -th), (back, z_bot)]
            for (x_prev, _, _), (x, ze, _) in zip(steps[:-1], steps[1:], strict=True):
                parts.append(_slab(x_prev, x, ze, th))
        mesh.append((x_bot + cfg.landing_length_m, z_bot))
    elif cfg.kind == "obstacle":
        h, d = cfg.obstacle_height_m, cfg.obstacle_depth_m
        pts += [(xf, h), (xf + d, h), (xf + d, 0.0), (xf + d + cfg.exit_length_m, 0.0)]
        edges += [(xf, h), (xf + d, h)]
    elif cfg.kind == "level":
        pts.append((xf + cfg.exit_length_m, 0.0))
    else:  # pragma: no cover - pydantic restricts kind
        raise SimulationError(f"unknown terrain kind {cfg.kind!r}")
    profile = np.asarray(pts, dtype=float)
    if np.any(np.diff(profile[:, 0]) < -1e-12):
        raise SimulationError("terrain profile x must be non-decreasing")
    undercut = stair and (o > 0 or cfg.open_risers)
    mesh_profile = np.asarray(mesh, dtype=float) if undercut else profile
    return profile, np.asarray(edges, dtype=float).reshape(-1, 2), mesh_profile, parts


def _slab(x_a: float, x_b: float, z_top: float, thickness: float) -> NDArray[np.float64]:
    """Closed outline (5, 2) of a tread slab from x_a to x_b with its top at z_top."""
    return np.array(
        [
            (x_a, z_top),
            (x_b, z_top),
            (x_b, z_top - thickness),
            (x_a, z_top - thickness),
            (x_a, z_top),
        ]
    )


def extrude_profile(
    profile_xz_m: NDArray[np.float64], width_m: float, side_walls: bool, wall_height_m: float
) -> tuple[NDArray[np.float64], NDArray[np.int32]]:
    """Extrude a profile (P, 2) across y in [-width/2, width/2]: vertices (V, 3), triangles.

    Each profile segment becomes a quad (two triangles); walls are vertical quads from the
    profile up by ``wall_height_m`` at y = +-width/2.
    """
    p = np.asarray(profile_xz_m, dtype=float)
    seg = np.linalg.norm(np.diff(p, axis=0), axis=1) > 1e-12
    a, b = p[:-1][seg], p[1:][seg]
    hw = 0.5 * width_m
    quads = [_quads(a, b, -hw, hw)]
    if side_walls:
        for y in (-hw, hw):
            quads.append(_wall_quads(a, b, y, wall_height_m))
    q = np.concatenate(quads, axis=0)  # (Q, 4, 3)
    vertices = q.reshape(-1, 3)
    base = 4 * np.arange(q.shape[0])[:, None]
    tris = np.concatenate([base + [0, 1, 2], base + [0, 2, 3]], axis=0).astype(np.int32)
    return vertices, tris


def _quads(a: NDArray, b: NDArray, y0: float, y1: float) -> NDArray[np.float64]:
    n = a.shape[0]
    q = np.zeros((n, 4, 3))
    q[:, 0] = np.stack([a[:, 0], np.full(n, y0), a[:, 1]], 1)
    q[:, 1] = np.stack([b[:, 0], np.full(n, y0), b[:, 1]], 1)
    q[:, 2] = np.stack([b[:, 0], np.full(n, y1), b[:, 1]], 1)
    q[:, 3] = np.stack([a[:, 0], np.full(n, y1), a[:, 1]], 1)
    return q


def _wall_quads(a: NDArray, b: NDArray, y: float, height: float) -> NDArray[np.float64]:
    n = a.shape[0]
    top = max(a[:, 1].max(), b[:, 1].max()) + height
    q = np.zeros((n, 4, 3))
    q[:, 0] = np.stack([a[:, 0], np.full(n, y), a[:, 1]], 1)
    q[:, 1] = np.stack([b[:, 0], np.full(n, y), b[:, 1]], 1)
    q[:, 2] = np.stack([b[:, 0], np.full(n, y), np.full(n, top)], 1)
    q[:, 3] = np.stack([a[:, 0], np.full(n, y), np.full(n, top)], 1)
    return q


def build_terrain(cfg: TerrainConfig, rng: np.random.Generator | None = None) -> Terrain:
    """Profile, edges and extruded mesh for a terrain configuration. ``rng`` draws the steps
    of irregular stairs (``stair_steps``); regular terrain does not use it."""
    profile, edges, mesh_profile, parts = _profiles(cfg, rng)
    vertices, tris = extrude_profile(mesh_profile, cfg.width_m, cfg.side_walls, cfg.wall_height_m)
    for part in parts:  # open-riser tread slabs (no side walls of their own)
        v, tr = extrude_profile(part, cfg.width_m, False, cfg.wall_height_m)
        tris = np.concatenate([tris, tr + vertices.shape[0]]).astype(np.int32)
        vertices = np.concatenate([vertices, v])
    params: dict[str, float | int | str] = {"approach_length_m": cfg.approach_length_m}
    if cfg.kind in ("stair_up", "stair_down"):
        params.update(
            rise_m=cfg.stair_rise_m,
            tread_m=cfg.stair_tread_m,
            n_steps=cfg.n_steps,
            landing_length_m=cfg.landing_length_m,
        )
        if cfg.n_flights > 1:
            params.update(n_flights=cfg.n_flights, flight_landing_m=cfg.flight_landing_m)
        if cfg.nosing_overhang_m > 0:
            params.update(
                nosing_overhang_m=cfg.nosing_overhang_m, nosing_thickness_m=cfg.nosing_thickness_m
            )
        if cfg.open_risers:
            params.update(open_risers=1, nosing_thickness_m=cfg.nosing_thickness_m)
        for key in ("rise_jitter_m", "tread_jitter_m", "first_rise_m", "last_rise_m"):
            value = getattr(cfg, key)
            if value:  # irregular stairs: the drawn steps are in the profile and edges
                params[key] = value
    elif cfg.kind == "obstacle":
        params.update(height_m=cfg.obstacle_height_m, depth_m=cfg.obstacle_depth_m)
    return Terrain(
        kind=cfg.kind,
        profile_xz_m=profile,
        edges_xz_m=edges,
        vertices_m=vertices,
        triangles=tris,
        feature_x_m=cfg.approach_length_m,
        params=params,
        mesh_profile_xz_m=None if mesh_profile is profile else mesh_profile,
        irregular=cfg.kind in ("stair_up", "stair_down") and is_irregular(cfg),
        mesh_parts_xz_m=tuple(parts),
    )
