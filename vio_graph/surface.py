"""The walking surface of a sagittal profile: which points lie beneath it (pure numpy).

A profile or map seen from above has one walking surface per x. Returns from beneath a
horizontal level come from surfaces the foot cannot reach from there: the floor under
open-riser treads seen through the gap between two treads, a wall under a landing. Stairs
with closed risers have none: a riser stands at a level's end, between the two levels it
joins, and the underside of a nosing is a slab thinner than the drop asked for. The front end
(``vio_graph.frontend.frontend``) and the step extraction (``vio_graph.mapping.steps``) drop
such points only when some occur, so closed stairs give the same results as without the rule.
"""

from __future__ import annotations

import numpy as np
from numpy.typing import ArrayLike, NDArray


def _level_arrays(
    points_xz_m: ArrayLike, level_z_m: ArrayLike, level_x_lo_m: ArrayLike, level_x_hi_m: ArrayLike
) -> tuple[NDArray, NDArray, NDArray, NDArray]:
    """(N, 2) points and the levels' heights and x extents as float arrays."""
    pts = np.asarray(points_xz_m, dtype=float).reshape(-1, 2)
    z = np.asarray(level_z_m, dtype=float).ravel()
    lo = np.asarray(level_x_lo_m, dtype=float).ravel()
    hi = np.asarray(level_x_hi_m, dtype=float).ravel()
    return pts, z, lo, hi


def _beneath_levels(
    x: NDArray, pz: NDArray, z: NDArray, lo: NDArray, hi: NDArray, margin_m: float, drop_m: float
) -> NDArray[np.bool_]:
    """(N,) points at least ``drop_m`` below a level and more than ``margin_m`` inside its x
    extent on both sides."""
    beneath = np.zeros(x.shape[0], dtype=bool)
    for a in range(z.size):
        beneath |= (x > lo[a] + margin_m) & (x < hi[a] - margin_m) & (pz < z[a] - drop_m)
    return beneath


def _lower_overlapping(
    z: NDArray, lo: NDArray, hi: NDArray, a: int, margin_m: float, drop_m: float
) -> list[int]:
    """The levels B under level ``a``: at least ``drop_m`` lower and overlapping it in x by
    more than ``margin_m``."""
    return [
        b
        for b in range(z.size)
        if b != a and z[b] < z[a] - drop_m and min(hi[a], hi[b]) - max(lo[a], lo[b]) > margin_m
    ]


def under_levels_mask(
    points_xz_m: ArrayLike,
    level_z_m: ArrayLike,
    level_x_lo_m: ArrayLike,
    level_x_hi_m: ArrayLike,
    margin_m: float,
    drop_m: float,
    band_m: float,
    sight_margin_m: float | None = None,
) -> NDArray[np.bool_]:
    """(N,) True for points beneath a level (L levels: height, x extent).

    A point is beneath level A when

    - it is at least ``drop_m`` below A and more than ``margin_m`` inside A's x extent on both
      sides (any point: a face under a landing, returns under a tread); with
      ``sight_margin_m`` (a single frame's profile, camera at the origin) also when its line
      of sight passes at least ``drop_m`` under A more than ``sight_margin_m`` inside A's
      extent and the point is more than ``margin_m`` past A's start: seen through a gap
      under A (the floor under the treads ahead; a riser set back under a nosing overhang
      is nearer A's start); or
    - within A's x extent, at least ``drop_m`` below A and within ``band_m`` of a lower level
      B that overlaps A in x by more than ``margin_m`` (B is a surface under A: the floor
      under a flight of open-riser treads; its points up to A's ends go, a riser's points are
      on no such level).
    """
    pts, z, lo, hi = _level_arrays(points_xz_m, level_z_m, level_x_lo_m, level_x_hi_m)
    x, pz = pts[:, 0], pts[:, 1]
    under = _beneath_levels(x, pz, z, lo, hi, margin_m, drop_m)
    ahead = x > 1e-6
    slope = np.where(ahead, pz / np.where(ahead, x, 1.0), 0.0)
    for a in range(z.size):
        if sight_margin_m is not None and hi[a] - lo[a] > 2 * sight_margin_m:
            # the lowest point of the line of sight over A's inner extent (straight from the
            # camera to the point): at the nearer of A's inner far end and the point
            s_lo, s_hi = lo[a] + sight_margin_m, hi[a] - sight_margin_m
            x_eval = np.minimum(x, s_hi)
            # the point lies beyond the undercut a nosing may have (margin_m past A's start)
            beyond = ahead & (x > lo[a] + margin_m) & (x_eval > s_lo)
            under |= beyond & (slope * x_eval < z[a] - drop_m)
        inside = (pz < z[a] - drop_m) & (x >= lo[a]) & (x <= hi[a])
        if not inside.any():
            continue
        for b in _lower_overlapping(z, lo, hi, a, margin_m, drop_m):
            under |= inside & (np.abs(pz - z[b]) <= band_m)
    return under


def seen_under_mask(
    points_xz_m: ArrayLike, margin_m: float, drop_m: float, min_occluders: int
) -> NDArray[np.bool_]:
    """(N,) True for points of a single frame's profile (camera at the origin) seen beneath
    another surface of the same profile.

    A terrain seen from above is a height over x: every point the camera sees is seen along a
    line of sight that passes above the terrain nearer to the camera. A point P is seen
    beneath a surface when at least ``min_occluders`` profile points Q more than ``margin_m``
    nearer than P in x lie at least ``drop_m`` above P's line of sight at their x: the line
    passed under them, through a gap (the floor under open-riser treads, seen under the 3 cm
    front of a tread whose top is out of view, so that no level of the frame covers it). The
    margin leaves out a riser set back under its own nosing; closed stairs, obstacles seen
    from above and floors give no such point.
    """
    pts = np.asarray(points_xz_m, dtype=float).reshape(-1, 2)
    x, z = pts[:, 0], pts[:, 1]
    under = np.zeros(pts.shape[0], dtype=bool)
    ahead = np.flatnonzero(x > 1e-6)
    if ahead.size <= min_occluders:
        return under
    xq, zq = x[ahead], z[ahead]
    for start in range(0, ahead.size, 256):  # (chunk, M) blocks: bounded memory
        idx = ahead[start : start + 256]
        xp, zp = x[idx, None], z[idx, None]
        nearer = xq[None, :] < xp - margin_m
        above = zq[None, :] > zp / xp * xq[None, :] + drop_m
        under[idx] = np.count_nonzero(nearer & above, axis=1) >= min_occluders
    return under


def floor_beyond_slab_mask(
    points_xz_m: ArrayLike,
    level_z_m: ArrayLike,
    level_x_lo_m: ArrayLike,
    level_x_hi_m: ArrayLike,
    margin_m: float,
    drop_m: float,
    band_m: float,
    min_points: int,
) -> NDArray[np.bool_]:
    """(N,) True for the points of a floor beyond a slab it runs under (L levels: height, x
    extent; a single frame's profile, near to far).

    A level A is a slab over a lower level B when B overlaps A in x by more than ``margin_m``
    (B is seen under A: an open-riser tread over the floor) and B is also the walking surface
    in front of A (at least ``min_points`` of B's points, within ``band_m`` of its height, lie
    nearer than A's start and beneath no level). Then B's points beyond A's far end are the
    same floor running on under the flight (seen under the next treads, whose tops are out of
    view), not a surface the foot reaches after A: low-high-low is no obstacle there. A box
    hides the floor under its top; on a descent the floor nearer than the lowest tread lies
    under the treads above it, so neither gives such points.
    """
    pts, z, lo, hi = _level_arrays(points_xz_m, level_z_m, level_x_lo_m, level_x_hi_m)
    x, pz = pts[:, 0], pts[:, 1]
    out = np.zeros(pts.shape[0], dtype=bool)
    slabs = [
        (a, b) for a in range(z.size) for b in _lower_overlapping(z, lo, hi, a, margin_m, drop_m)
    ]
    if not slabs:  # no level over another (closed stairs, floors, boxes): nothing to test
        return out
    beneath = _beneath_levels(x, pz, z, lo, hi, margin_m, drop_m)
    for a, b in slabs:
        on_b = np.abs(pz - z[b]) <= band_m
        in_front = on_b & (x < lo[a]) & ~beneath
        if int(in_front.sum()) >= min_points:
            out |= on_b & (x > hi[a] + margin_m)
    return out
