"""Mixed pixels at depth edges, found by the geometry of the viewing rays (the "veil" test).

A ToF pixel whose footprint straddles a depth edge (a stair nosing over the tread below)
returns a depth between the two surfaces. Its point lies on its own viewing ray, between the
near surface and the far one; in the sagittal profile the mixed pixels of an edge form a veil
along the ray through the edge. A surface cannot do that: an opaque surface at range r hides
everything behind it on its ray, and a surface the camera keeps is seen at an incidence below
its grazing limit, so along a small bundle of rays its range changes by at most
``r * tan(max_incidence) * angle``.

The profile is relative to the camera centre (ground axes, x forward, z up). For terrain that
does not change across the slab (a stair, a kerb), a 3-D ray projects onto the profile's line
through the origin at its elevation angle, and that line meets the terrain where the ray
does: occlusion holds in the profile as it does in space. A point is a veil point when, within
``window_rad`` of its elevation angle, there is both a point nearer and a point farther than
it by more than a grazing surface and the depth noise allow: it sits between two returns on
nearly the same ray, of which at most the nearer can be the surface that ray meets. The
nearest return of a bundle (a nosing) and the farthest (the lower tread behind the edge) are
kept; so is a surface seen at a grazing angle, whose spread along the bundle is within the
allowance.

The bundle should be no wider than a ray's own uncertainty (its footprint and the sensor's
sample-position jitter): the allowance assumes one surface between the two rays, and a wider
bundle reaches across an edge to another surface. Then a far tread seen as a strip of two or
three pixel rows, between the nosing above it and the tread beyond the next nosing, lies
between two returns of the bundle and loses points as well (tests/test_veil.py).
"""

from __future__ import annotations

import numpy as np
from numpy.typing import NDArray

from vio_graph.errors import FrontendError


def veil_drops(
    points_xz_m: NDArray[np.floating],
    sigma_m: float | NDArray[np.floating],
    window_rad: float,
    max_incidence_deg: float,
    k_sigma: float,
    ray_tol_rad: float = 0.0,
) -> NDArray[np.bool_]:
    """(N,) True for the profile points that lie between two other returns on nearly the
    same viewing ray (mixed pixels at a depth edge), False for the rest.

    Args:
        points_xz_m: (N, 2) raw slice points relative to the camera centre, ground axes, m.
        sigma_m: depth noise sd of one point, m: a scalar or (N,) per point.
        window_rad: half-width of the bundle of rays a point is compared with, rad.
        max_incidence_deg: the steepest incidence at which the camera returns a surface,
            deg; between two rays ``dphi`` apart a surface's range changes by at most
            ``r * tan(max_incidence) * dphi``.
        k_sigma: the noise allowance is ``k_sigma * sqrt(sigma_i^2 + sigma_j^2)``.
        ray_tol_rad: the uncertainty of a point's own ray, rad (the pixel's footprint and the
            sensor's sample-position jitter), added to ``dphi``.

    Point i is dropped when some j and some l within ``window_rad`` of its elevation angle
    have ``r_i - r_j > tol_ij`` and ``r_l - r_i > tol_il``, with ``tol_ij = r_i *
    tan(max_incidence) * (|phi_i - phi_j| + ray_tol_rad) + k_sigma * sqrt(sigma_i^2 +
    sigma_j^2)``.
    """
    pts = np.asarray(points_xz_m, dtype=np.float64)
    if pts.ndim != 2 or pts.shape[1] != 2:
        raise FrontendError(f"points_xz_m must be (N, 2), got {pts.shape}")
    if not np.all(np.isfinite(pts)):
        raise FrontendError("points_xz_m must be finite")
    n = pts.shape[0]
    sigma = np.asarray(sigma_m, dtype=np.float64)
    if sigma.ndim == 0:
        sigma = np.full(n, float(sigma))
    elif sigma.shape != (n,):
        raise FrontendError(f"sigma_m must be a scalar or ({n},), got {sigma.shape}")
    if np.any(~np.isfinite(sigma)) or np.any(sigma < 0):
        raise FrontendError("sigma_m must be finite and >= 0")
    if not (np.isfinite(window_rad) and window_rad > 0):
        raise FrontendError(f"window_rad must be > 0, got {window_rad}")
    if not (0 < max_incidence_deg < 90):
        raise FrontendError(f"max_incidence_deg must be in (0, 90), got {max_incidence_deg}")
    if not (np.isfinite(k_sigma) and k_sigma >= 0):
        raise FrontendError(f"k_sigma must be >= 0, got {k_sigma}")
    if not (np.isfinite(ray_tol_rad) and ray_tol_rad >= 0):
        raise FrontendError(f"ray_tol_rad must be >= 0, got {ray_tol_rad}")
    if n < 3:
        return np.zeros(n, dtype=bool)
    r = np.hypot(pts[:, 0], pts[:, 1])
    phi = np.arctan2(pts[:, 1], pts[:, 0])
    order = np.argsort(phi, kind="stable")
    r_s, phi_s, s2 = r[order], phi[order], (sigma**2)[order]
    slope = np.tan(np.radians(max_incidence_deg))
    nearer = np.zeros(n, dtype=bool)
    farther = np.zeros(n, dtype=bool)
    for step in range(1, n):  # compare with the points `step` places away in angle order
        dphi = phi_s[step:] - phi_s[:-step]
        a = np.nonzero(dphi <= window_rad)[0]
        if a.size == 0:  # the gaps only grow with the step
            break
        b = a + step  # pairs (a, b), a before b in angle
        diff = r_s[b] - r_s[a]
        noise = k_sigma * np.sqrt(s2[a] + s2[b])
        spread = slope * (dphi[a] + ray_tol_rad)  # a surface's range change per metre of range
        tol_a = r_s[a] * spread + noise
        tol_b = r_s[b] * spread + noise
        farther[a] |= diff > tol_a
        nearer[a] |= -diff > tol_a
        nearer[b] |= diff > tol_b
        farther[b] |= -diff > tol_b
    drop = np.zeros(n, dtype=bool)
    drop[order] = nearer & farther
    return drop
