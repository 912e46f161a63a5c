"""ToF depth camera (pmd pico flexx2, Mode 5) by ray casting the terrain mesh with open3d.

Noise recipe (Cai et al. 2024; pmd royale; values and sources in
docs/simulator.md): lateral jitter of each pixel's sample
position (~0.86 px), mixed depths at occlusion edges, axial noise
sigma_z(z, theta) = a + b z + c z^2 + d z^2.7 theta^2 / (pi/2 - theta)^2, royale's
flying-pixel rule, grazing incidence (> 75 deg) dropped, out-of-range pixels invalid,
confidence from sigma. Depth is along the optical axis, 0 where invalid.
"""

from __future__ import annotations

import numpy as np
from numpy.typing import NDArray

from vio_graph.o3d import open3d
from vio_graph.recording.metadata import CameraModel
from vio_graph.sim.config import CameraConfig
from vio_graph.sim.terrain import Terrain

#: (frame, edge) pairs per chunk of ``TofCamera.edges_visible`` (bounds its memory)
EDGE_RAYS_PER_CHUNK = 1 << 18


def axial_sigma_m(
    z_m: NDArray, incidence_rad: NDArray, coeffs: tuple[float, float, float, float]
) -> NDArray[np.float64]:
    """Axial depth noise sd (m) of the Cai (2024) model for depth z (m), incidence (rad)."""
    a, b, c, d = coeffs
    th = np.clip(incidence_rad, 0.0, np.pi / 2 - 1e-3)
    return a + b * z_m + c * z_m**2 + d * z_m**2.7 * th**2 / (np.pi / 2 - th) ** 2


def _extremes_3x3(a: NDArray) -> tuple[NDArray, NDArray]:
    """Maximum and minimum over each pixel's 3x3 neighbourhood (H, W), the border repeated:
    equal to scipy.ndimage's ``maximum_filter`` / ``minimum_filter`` with ``size=3``
    (``reflect`` mode repeats the edge pixel for a 3-wide window), a few times faster."""
    p = np.pad(a, 1, mode="edge")
    h, w = a.shape
    rows_max = np.maximum(np.maximum(p[:, :w], p[:, 1 : w + 1]), p[:, 2:])
    rows_min = np.minimum(np.minimum(p[:, :w], p[:, 1 : w + 1]), p[:, 2:])
    zmax = np.maximum(np.maximum(rows_max[:h], rows_max[1 : h + 1]), rows_max[2:])
    zmin = np.minimum(np.minimum(rows_min[:h], rows_min[1 : h + 1]), rows_min[2:])
    return zmax, zmin


def concave_corners_xz(profile_xz_m: NDArray) -> NDArray[np.float64]:
    """(K, 2) vertices of a terrain profile (x increasing, solid below) where it turns up
    into the solid: the inner corners where a tread or floor meets the riser above it, or
    (descending) a riser meets the tread below it. Multipath collects there."""
    p = np.asarray(profile_xz_m, float)
    if p.shape[0] < 3:
        return np.zeros((0, 2))
    a, b = p[1:-1] - p[:-2], p[2:] - p[1:-1]
    cross = a[:, 0] * b[:, 1] - a[:, 1] * b[:, 0]
    return p[1:-1][cross > 1e-9]


class TofCamera:
    """Pinhole ToF camera over a terrain. ``render`` is pure given its generator."""

    def __init__(self, cfg: CameraConfig, terrain: Terrain) -> None:
        self.cfg = cfg
        self.fx = 0.5 * cfg.width_px / np.tan(np.radians(cfg.hfov_deg) / 2)
        self.fy = 0.5 * cfg.height_px / np.tan(np.radians(cfg.vfov_deg) / 2)
        self.cx = 0.5 * (cfg.width_px - 1)
        self.cy = 0.5 * (cfg.height_px - 1)
        o3d = open3d()
        self._o3d = o3d
        self.scene = o3d.t.geometry.RaycastingScene()
        self.scene.add_triangles(
            o3d.core.Tensor(terrain.vertices_m.astype(np.float32)),
            o3d.core.Tensor(terrain.triangles.astype(np.uint32)),
        )
        v, u = np.mgrid[0 : cfg.height_px, 0 : cfg.width_px]
        self._u, self._v = u.astype(float), v.astype(float)
        self._terrain = terrain
        mesh = terrain.mesh_profile_xz_m
        # edge-gap bands are placed on this outline; with open risers the mesh outline is the
        # floor under the flight, so they use the walking surface (the treads) instead
        open_risers = bool(terrain.params.get("open_risers", 0))
        self._surface_xz = terrain.profile_xz_m if mesh is None or open_risers else mesh
        self._concave_xz = concave_corners_xz(self._surface_xz)

    def camera_model(self) -> CameraModel:
        c = self.cfg
        return CameraModel(
            width_px=c.width_px,
            height_px=c.height_px,
            fx_px=self.fx,
            fy_px=self.fy,
            cx_px=self.cx,
            cy_px=self.cy,
            depth_unit_m=c.depth_unit_m,
            min_range_m=c.min_range_m,
            max_range_m=c.max_range_m,
            frame_rate_hz=c.frame_rate_hz,
        )

    def cast(
        self, position_m: NDArray, R_world_cam: NDArray, u_px: NDArray, v_px: NDArray
    ) -> tuple[NDArray, NDArray, NDArray]:
        """Depth along the optical axis (inf = miss), world normals and camera-frame ray
        directions (z = 1) for pixel positions (H, W)."""
        d_c = np.stack(
            [(u_px - self.cx) / self.fx, (v_px - self.cy) / self.fy, np.ones_like(u_px)], axis=-1
        )
        d_w = d_c @ np.asarray(R_world_cam).T
        rays = np.concatenate([np.broadcast_to(position_m, d_w.shape), d_w], axis=-1)
        ans = self.scene.cast_rays(self._o3d.core.Tensor(rays.astype(np.float32)), nthreads=0)
        t_hit = ans["t_hit"].numpy().astype(np.float64)
        normals = ans["primitive_normals"].numpy().astype(np.float64)
        return t_hit, normals, d_c

    def render(
        self, position_m: NDArray, R_world_cam: NDArray, rng: np.random.Generator
    ) -> tuple[NDArray[np.float32], NDArray[np.uint8]]:
        """One frame: depth_m (H, W) float32 (0 invalid) and confidence (H, W) uint8.

        Same arithmetic as ``cast`` + the noise recipe written with whole-image reductions
        (tests/test_tof_render.py keeps that form as the reference and checks equality bit
        for bit): the 3-vector dot products and norms are summed left to right as numpy's
        ``sum(axis=-1)`` does, the 3x3 min/max filter is taken over shifted views (edge
        padding equals scipy's ``reflect`` mode for size 3), the rays are cast to float32 in
        place. The random draws are the same and in the same order.
        """
        c = self.cfg
        u, v = self._u, self._v
        if c.noise and c.lateral_noise_px > 0:
            u = u + rng.normal(0, c.lateral_noise_px, u.shape)
            v = v + rng.normal(0, c.lateral_noise_px, v.shape)
        position = np.asarray(position_m, float)
        R = np.asarray(R_world_cam)
        d_c = np.stack([(u - self.cx) / self.fx, (v - self.cy) / self.fy, np.ones_like(u)], axis=-1)
        d_w = d_c @ R.T
        rays = np.empty(d_w.shape[:-1] + (6,), dtype=np.float32)
        rays[..., :3] = position
        rays[..., 3:] = d_w
        ans = self.scene.cast_rays(self._o3d.core.Tensor(rays), nthreads=0)
        t_hit = ans["t_hit"].numpy().astype(np.float64)
        n_w = ans["primitive_normals"].numpy().astype(np.float64)
        hit = np.isfinite(t_hit)
        z_true = np.where(hit, t_hit, 0.0)
        dx, dy, dz = d_w[..., 0], d_w[..., 1], d_w[..., 2]
        dot = (n_w[..., 0] * dx + n_w[..., 1] * dy) + n_w[..., 2] * dz
        cos_inc = np.abs(dot) / np.sqrt((dx * dx + dy * dy) + dz * dz)
        incidence = np.arccos(np.clip(cos_inc, 0.0, 1.0))
        z = self._systematic(z_true, hit, position, d_w)
        if c.noise:
            far = np.where(hit, t_hit, 10.0)  # misses behave like a far background
            zmax, zmin = _extremes_3x3(far)
            mixed = hit & (zmax - zmin > c.mixed_pixel_jump_m)
            mixed &= rng.random(z.shape) < c.mixed_pixel_probability
            w = rng.random(z.shape)
            z = np.where(mixed, w * zmin + (1 - w) * zmax, z)
        sigma = axial_sigma_m(z, incidence, c.axial_coeffs)
        if c.noise:
            z = z + sigma * rng.standard_normal(z.shape)
        valid = hit & (incidence < np.radians(c.max_incidence_deg)) & (sigma < c.max_noise_m)
        dcx, dcy = d_c[..., 0], d_c[..., 1]
        rng_m = z * np.sqrt((dcx * dcx + dcy * dcy) + 1.0)  # |d_c|, d_c z = 1
        valid &= (rng_m >= c.min_range_m) & (rng_m <= c.max_range_m)
        if c.noise:
            valid &= ~self._flying(np.where(valid, z, 0.0))
        if c.edge_gap_m is not None:  # drawn last: the rest of the frame is unchanged
            band = self.edge_gap_mask(
                position,
                R_world_cam,
                d_c,
                z_true,
                n_w,
                rng.uniform(*c.edge_gap_m, self._terrain.edges_xz_m.shape[0]),
            )
            valid &= ~band
        depth = np.where(valid, z, 0.0).astype(np.float32)
        conf = np.where(valid, np.clip(np.round(255 * (1 - sigma / c.max_noise_m)), 1, 255), 0)
        return depth, conf.astype(np.uint8)

    def _systematic(
        self, z_true: NDArray, hit: NDArray, position: NDArray, d_w: NDArray
    ) -> NDArray:
        """Deterministic depth errors of real ToF cameras (all off by default, then
        ``z_true`` itself is returned): the multipath excess near concave corners, the
        wiggling error and a depth scale error, in that order. No random draws."""
        c = self.cfg
        if not (c.multipath_bias_m or c.wiggling_amplitude_m or c.depth_scale_error):
            return z_true
        z = z_true.copy()
        if c.multipath_bias_m and self._concave_xz.shape[0]:
            # hit points in the world's x-z plane (depth is along a ray with camera z = 1)
            px = position[0] + z_true * d_w[..., 0]
            pz = position[2] + z_true * d_w[..., 2]
            near = self._concave_xz[np.abs(self._concave_xz[:, 0] - position[0]) < 4.0]
            if near.shape[0]:
                r2 = np.full(z.shape, np.inf)
                for cx, cz in near:
                    np.minimum(r2, (px - cx) ** 2 + (pz - cz) ** 2, out=r2)
                excess = c.multipath_bias_m * np.exp(-np.sqrt(r2) / c.multipath_decay_m)
                z = np.where(hit, z + excess, z)
        if c.wiggling_amplitude_m:
            wiggle = c.wiggling_amplitude_m * np.sin(
                2 * np.pi * z / c.wiggling_period_m + c.wiggling_phase_rad
            )
            z = np.where(hit, z + wiggle, z)
        if c.depth_scale_error:
            z = z * (1.0 + c.depth_scale_error)
        return z

    def edge_gap_bands(
        self, position_m: NDArray, band_m: NDArray
    ) -> list[tuple[NDArray, NDArray, float]]:
        """Missing bands behind the convex edges as seen from ``position_m`` (3,): per edge
        within range, (start point S (2,), unit direction w (2,) along the surface, length m)
        in the world x-z plane. The plane through the camera centre and an edge (a line along
        y) is the same in every y slice, so the construction is 2-D: the ray C -> E either
        enters the solid right after E (the camera sees the tread behind the nosing: the band
        starts at E on that tread) or passes E and lands on a farther surface at S (the band
        starts there, on the side not hidden by the edge)."""
        C = np.array([position_m[0], position_m[2]])
        edges = self._terrain.edges_xz_m
        prof = self._surface_xz
        A, B = prof[:-1], prof[1:]
        out: list[tuple[NDArray, NDArray, float]] = []
        for E, b in zip(edges, band_m, strict=True):
            d = E - C
            dist = float(np.hypot(*d))
            if dist < 1e-6 or dist > self.cfg.max_range_m + 0.1:
                continue
            u = d / dist
            sgn = 1.0 if d[0] >= 0 else -1.0
            q = E + 1e-4 * u
            if q[1] < self._terrain.height_at(np.array([q[0]]))[0] - 1e-9:
                out.append((E.copy(), np.array([sgn, 0.0]), float(b)))
                continue
            # first surface hit beyond E: C + s d = A + r (B - A), s > 1, 0 <= r <= 1
            seg = B - A
            den = d[0] * (-seg[:, 1]) - d[1] * (-seg[:, 0])
            ok = np.abs(den) > 1e-12
            den = np.where(ok, den, 1.0)
            rel = A - C
            s_par = (rel[:, 0] * (-seg[:, 1]) - rel[:, 1] * (-seg[:, 0])) / den
            r_par = (d[0] * rel[:, 1] - d[1] * rel[:, 0]) / den
            cand = ok & (s_par > 1.0 + 1e-6) & (r_par >= -1e-9) & (r_par <= 1 + 1e-9)
            if not np.any(cand):
                continue
            k = int(np.argmin(np.where(cand, s_par, np.inf)))
            S = C + s_par[k] * d
            w = seg[k] / np.hypot(*seg[k])

            def side(p: NDArray, d: NDArray = d, C: NDArray = C) -> float:
                return float(d[0] * (p[1] - C[1]) - d[1] * (p[0] - C[0]))

            solid = [E + np.array([dx, -1e-3]) for dx in (-1e-3, 1e-3)]
            inside = [p for p in solid if p[1] < self._terrain.height_at(np.array([p[0]]))[0]]
            if not inside:
                continue
            if np.sign(side(S + 1e-3 * w)) == np.sign(side(inside[0])):
                w = -w
            out.append((S, w, float(b)))
        return out

    def edge_gap_mask(
        self,
        position_m: NDArray,
        R_world_cam: NDArray,
        d_c: NDArray,
        z_m: NDArray,
        normals_w: NDArray,
        band_m: NDArray,
    ) -> NDArray[np.bool_]:
        """Pixels (H, W) whose true surface point lies in one of the bands of
        ``edge_gap_bands`` (within 2 mm of the surface, on a face parallel to it)."""
        mask = np.zeros(z_m.shape, dtype=bool)
        bands = self.edge_gap_bands(position_m, band_m)
        if not bands:
            return mask
        d_w = d_c @ np.asarray(R_world_cam).T
        P = np.asarray(position_m)[[0, 2]] + z_m[..., None] * d_w[..., [0, 2]]
        n_xz = normals_w[..., [0, 2]]
        hit = z_m > 0
        for S, w, b in bands:
            nrm = np.array([-w[1], w[0]])
            rel = P - S
            along = rel @ w
            m = hit & (np.abs(rel @ nrm) < 0.002) & (along >= -1e-4) & (along <= b)
            m &= np.abs(n_xz @ nrm) > 0.9
            mask |= m
        return mask

    def _flying(self, z: NDArray) -> NDArray[np.bool_]:
        """royale's flying-pixel rule: jump to both horizontal (or both vertical) neighbours
        above a threshold rising linearly from 0.018 m (<= 1 m) to 0.14 m (>= 4.5 m)."""
        t0, t1 = self.cfg.flying_pixel_thresholds_m
        thr = np.interp(z, [1.0, 4.5], [t0, t1])
        p = np.pad(z, 1, mode="edge")
        left, right = p[1:-1, :-2], p[1:-1, 2:]
        up, down = p[:-2, 1:-1], p[2:, 1:-1]
        horiz = (np.abs(z - left) > thr) & (np.abs(z - right) > thr)
        vert = (np.abs(z - up) > thr) & (np.abs(z - down) > thr)
        return (z > 0) & (horiz | vert)

    def edges_visible(
        self,
        positions_m: NDArray,
        R_world_cam: NDArray,
        edges_world_m: NDArray,
        margin_px: float = 2.0,
    ) -> NDArray[np.bool_]:
        """(F, E): edge point e is inside the image, within range and not occluded in frame f.

        positions_m (F, 3), R_world_cam (F, 3, 3), edges_world_m (E, 3).
        """
        F, E = positions_m.shape[0], edges_world_m.shape[0]
        if E == 0:
            return np.zeros((F, 0), dtype=bool)
        # a long trial has many frames and many edges: frames in chunks of EDGE_RAYS_PER_CHUNK
        # keep the (F, E, 3) arrays small; every ray is cast on its own, so chunking changes
        # nothing
        step = max(1, EDGE_RAYS_PER_CHUNK // E)
        if F > step:
            return np.concatenate(
                [
                    self.edges_visible(
                        positions_m[a : a + step],
                        R_world_cam[a : a + step],
                        edges_world_m,
                        margin_px,
                    )
                    for a in range(0, F, step)
                ]
            )
        rel = edges_world_m[None, :, :] - positions_m[:, None, :]  # (F, E, 3)
        p_c = np.einsum("fji,fej->fei", R_world_cam, rel)
        z = p_c[..., 2]
        zs = np.where(z > 1e-6, z, 1.0)
        u = self.fx * p_c[..., 0] / zs + self.cx
        v = self.fy * p_c[..., 1] / zs + self.cy
        rng_m = np.linalg.norm(rel, axis=-1)
        c = self.cfg
        inside = (z > 1e-6) & (u >= margin_px) & (u <= c.width_px - 1 - margin_px)
        inside &= (v >= margin_px) & (v <= c.height_px - 1 - margin_px)
        inside &= (rng_m >= c.min_range_m) & (rng_m <= c.max_range_m)
        # only the (frame, edge) pairs in view need the occlusion ray (each ray on its own)
        out = np.zeros((F, E), dtype=bool)
        if not inside.any():
            return out
        pos = np.broadcast_to(positions_m[:, None, :], rel.shape)[inside]
        rays = np.concatenate([pos, rel[inside]], -1)
        ans = self.scene.cast_rays(self._o3d.core.Tensor(rays.astype(np.float32)), nthreads=0)
        t_hit = ans["t_hit"].numpy()
        out[inside] = t_hit >= 1.0 - 0.01 / np.maximum(rng_m[inside], 1e-6)
        return out
