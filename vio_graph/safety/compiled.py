"""Compiled (numba) versions of the safety monitor's per-frame geometry and map updates: the
same loops as the numpy reference (vio_graph/safety/clearance.py, height_map.py), without
numpy's per-call overhead on a few hundred bins.

The public functions here have the signatures and results of their reference namesakes
(:func:`foot_clearance`, :func:`clearance_many`, :func:`edge_clearance_many`,
:func:`coverage`, :func:`edge_runs`) or of the map's steps (:func:`keyframe_tops`,
:func:`add_tops`). The arithmetic is the reference's, operation for operation; where numpy
sums or multiplies in another order (its pairwise sums, BLAS products) the answers differ by
rounding only (tests/test_safety_incremental.py: 1e-9 m).

numba is imported only here, and this module only when the compiled paths are switched on
(:func:`vio_graph.safety.online.compiled_geometry`); ``cache=True``: compiled once per
machine, then loaded from ``__pycache__``.
"""

from __future__ import annotations

import math

import numba
import numpy as np
from numpy.typing import ArrayLike, NDArray

from vio_graph.compiled_sums import pairwise_sum
from vio_graph.safety.clearance import (
    MAX_TRANSITION_BIN_M,
    NO_CLEARANCE,
    SLOPE_STEP_M,
    UNSEEN_TOLERANCE_M,
    Clearance,
    Edges,
    HeightProfile,
)

# ---------------------------------------------------------------------------------------------
# foot to terrain


def _xz(p: ArrayLike) -> tuple[float, float]:
    """An (x, z) point or vector as two floats."""
    a = np.asarray(p, dtype=float)
    return float(a[0]), float(a[1])


@numba.njit(cache=True)
def _point_to_columns(px, pz, lo, hi, z, d, cx, cz):  # pragma: no cover - compiled
    """In place: signed distance ``d`` (B,) from (px, pz) to each column and the closest
    column points ``cx``, ``cz`` (clearance._point_to_columns)."""
    B = z.shape[0]
    k = -1
    for i in range(B):
        x = min(max(px, lo[i]), hi[i])
        zz = min(pz, z[i])
        cx[i] = x
        cz[i] = zz
        d[i] = math.hypot(px - x, pz - zz)
        if k < 0 and px >= lo[i] and px <= hi[i] and pz < z[i]:
            k = i
    if k < 0:
        return
    # the way out sideways (to where the terrain is lower than the point, into an unmapped
    # gap, or past the known bins' ends) and up (the nearest point of a column top above the point)
    xl = lo[0]
    xr = hi[B - 1]
    best_up = np.inf
    tx_best = 0.0
    tz_best = 0.0
    for i in range(B):
        if i + 1 < B and lo[i + 1] > hi[i] + UNSEEN_TOLERANCE_M:  # an unmapped gap: a way out
            if lo[i + 1] <= px:
                xl = max(xl, lo[i + 1])
            if hi[i] >= px:
                xr = min(xr, hi[i])
        if z[i] <= pz:
            if hi[i] <= px:
                xl = max(xl, hi[i])
            if lo[i] >= px:
                xr = min(xr, lo[i])
        else:
            tx = min(max(px, lo[i]), hi[i])
            up = math.hypot(tx - px, z[i] - pz)
            if up < best_up:
                best_up, tx_best, tz_best = up, tx, z[i]
    for i in range(B):
        if px >= lo[i] and px <= hi[i] and pz < z[i]:
            d[i] = np.inf
    depth0, depth1, depth2 = best_up, px - xl, xr - px
    if depth1 < depth0 and depth1 <= depth2:
        d[k], cx[k], cz[k] = -depth1, xl, pz
    elif depth2 < depth0 and depth2 < depth1:
        d[k], cx[k], cz[k] = -depth2, xr, pz
    else:
        d[k], cx[k], cz[k] = -depth0, tx_best, tz_best


@numba.njit(cache=True)
def _corner_distance(ax, az, bx, bz, ex, ez):  # pragma: no cover - compiled
    """clearance._corners_to_segment for one corner: (signed distance, closest x, z)."""
    dx, dz = bx - ax, bz - az
    L2 = dx * dx + dz * dz
    s = 0.0
    if L2 != 0:
        s = min(max(((ex - ax) * dx + (ez - az) * dz) / L2, 0.0), 1.0)
    qx, qz = ax + s * dx, az + s * dz
    d = math.hypot(ex - qx, ez - qz)
    x0, x1 = min(ax, bx), max(ax, bx)
    if x1 - x0 > 1e-12:
        z_line = az + (ex - ax) * dz / dx
        if ex > x0 and ex < x1 and ez > z_line:
            d = -min(ez - z_line, min(ex - x0, x1 - ex))
    return d, qx, qz


@numba.njit(cache=True)
def _foot_clearance(ax, az, bx, bz, lo, hi, z):  # pragma: no cover - compiled
    """(distance, foot x, z, terrain x, z, column) of clearance.foot_clearance (no sole)."""
    B = z.shape[0]
    dh, ch_x, ch_z = np.empty(B), np.empty(B), np.empty(B)
    dt, ct_x, ct_z = np.empty(B), np.empty(B), np.empty(B)
    _point_to_columns(ax, az, lo, hi, z, dh, ch_x, ch_z)
    _point_to_columns(bx, bz, lo, hi, z, dt, ct_x, ct_z)
    best = np.inf
    out = (np.nan, np.nan, np.nan, np.nan, np.nan, -1)
    for i in range(B):  # heel against the columns (first minimum wins, as np.argmin)
        if dh[i] < best:
            best = dh[i]
            out = (best, ax, az, ch_x[i], ch_z[i], i)
    for i in range(B):  # toe
        if dt[i] < best:
            best = dt[i]
            out = (best, bx, bz, ct_x[i], ct_z[i], i)
    for c in range(2 * B):  # column top corners: the left ones, then the right ones
        i = c % B
        ex = lo[i] if c < B else hi[i]
        d, qx, qz = _corner_distance(ax, az, bx, bz, ex, z[i])
        if d < best:
            best = d
            out = (best, qx, qz, ex, z[i], i)
    return out


def foot_clearance(
    heel_xz_m: ArrayLike, toe_xz_m: ArrayLike, prof: HeightProfile, sole_thickness_m: float = 0.0
) -> Clearance:
    """:func:`vio_graph.safety.clearance.foot_clearance`, compiled."""
    if len(prof) == 0:
        return NO_CLEARANCE
    (ax, az), (bx, bz) = _xz(heel_xz_m), _xz(toe_xz_m)
    dist, fx, fz, tx, tz, col = _foot_clearance(ax, az, bx, bz, prof.x_lo_m, prof.x_hi_m, prof.z_m)
    ddx, ddz = fx - tx, fz - tz
    n = float(np.hypot(ddx, ddz))
    nx, nz = (ddx / n, ddz / n) if n > 1e-9 else (0.0, 1.0)
    if dist < 0:
        nx, nz = (0.0, 1.0) if n <= 1e-9 else (-nx, -nz)
    return Clearance(
        dist - sole_thickness_m, np.array([fx, fz]), np.array([tx, tz]), col, np.array([nx, nz])
    )


@numba.njit(cache=True)
def _clearance_many(a, b, lo, hi, z, sole):  # pragma: no cover - compiled
    T, B = a.shape[0], z.shape[0]
    out = np.empty(T)
    for t in range(T):
        ax, az, bx, bz = a[t, 0], a[t, 1], b[t, 0], b[t, 1]
        best = np.inf
        for px, pz in ((ax, az), (bx, bz)):  # heel and toe against the columns
            for i in range(B):
                if px >= lo[i] and px <= hi[i] and pz < z[i]:
                    v = pz - z[i]
                else:
                    v = math.hypot(px - min(max(px, lo[i]), hi[i]), pz - min(pz, z[i]))
                if v < best or v != v:
                    best = v
        abx, abz = bx - ax, bz - az
        L2 = max(abx * abx + abz * abz, 1e-18)
        x0, x1 = min(ax, bx), max(ax, bx)
        slope = abz / abx if abs(abx) > 1e-12 else 0.0
        for c in range(2 * B):  # column top corners against the segment
            i = c % B
            cx = lo[i] if c < B else hi[i]
            cz = z[i]
            s = min(max(((cx - ax) * abx + (cz - az) * abz) / L2, 0.0), 1.0)
            v = math.hypot(cx - (ax + s * abx), cz - (az + s * abz))
            z_line = az + (cx - ax) * slope
            if cx > x0 and cx < x1 and cz > z_line and x1 - x0 > 1e-12:
                v = z_line - cz
            if v < best or v != v:
                best = v
        out[t] = best - sole
    return out


#: :func:`_pose_clearance`: margin on the x gap that ends its search, m (rounding is ~1e-16)
NEAR_MARGIN_M = 1e-9


#: the squared-distance test before a hypot: a candidate whose squared distance exceeds the
#: best distance squared by this relative margin is farther than it (the rounding of the
#: squares and of hypot is ~1e-16 relative), so its hypot is not computed
SQUARED_MARGIN = 1e-9
#: below this best distance (m) the squared test is not used (its square could underflow)
SQUARED_MIN_M = 1e-100


@numba.njit(cache=True)
def _farther(dx, dz, best):  # pragma: no cover - compiled
    """Whether ``hypot(dx, dz)`` is certainly above ``best`` (from the squares, no hypot):
    False when in doubt (``best`` tiny, infinite or not positive, NaN)."""
    if not best > SQUARED_MIN_M:
        return best <= 0.0 and dx == dx and dz == dz  # a distance is never below 0
    return dx * dx + dz * dz > best * best * (1.0 + SQUARED_MARGIN)


@numba.njit(cache=True)
def _first_reaching(hi, n, x):  # pragma: no cover - compiled
    """The first of the ``n`` columns whose right end ``hi`` (ascending, m) is at or past
    ``x`` (np.searchsorted(hi[:n], x), side left); ``n`` if none."""
    k0, k1 = 0, n
    while k0 < k1:
        m = (k0 + k1) // 2
        if hi[m] < x:
            k0 = m + 1
        else:
            k1 = m
    return k0


@numba.njit(cache=True)
def _foot_clearance_near(ax, az, bx, bz, lo, hi, z):  # pragma: no cover - compiled
    """:func:`_foot_clearance` with the same result, bit for bit, without the hypot of the
    candidates that cannot be the minimum: a column whose lower bound (its x gap to the
    foot's span, or the foot's lowest point above its top) exceeds the best so far by more
    than ``NEAR_MARGIN_M`` is skipped, and a candidate's hypot is taken only when its
    squared distance does not already exceed the best (:func:`_farther`). The candidates
    are visited in the reference's order (heel, toe, left corners, right corners; the first
    minimum wins), and a candidate skipped is above a value already found, so it could not
    have been that first minimum. When the heel or the toe lies inside a column (the way-out
    search), or an input is not finite, the reference runs instead."""
    B = z.shape[0]
    finite = math.isfinite(ax + az + bx + bz)
    for i in range(B):
        if not finite:
            break
        finite = math.isfinite(lo[i] + hi[i] + z[i])
        if (ax >= lo[i] and ax <= hi[i] and az < z[i]) or (
            bx >= lo[i] and bx <= hi[i] and bz < z[i]
        ):
            finite = False  # (a point inside a column: the reference's way-out search)
    if not finite:
        return _foot_clearance(ax, az, bx, bz, lo, hi, z)
    x0, x1 = min(ax, bx), max(ax, bx)
    zmin = min(az, bz)
    # an upper bound on the minimum: the heel and the toe against the column nearest each
    bound = np.inf
    for px, pz in ((ax, az), (bx, bz)):
        k0 = _first_reaching(hi, B, px)
        for i in (k0 - 1, k0):
            if 0 <= i < B:
                v = math.hypot(px - min(max(px, lo[i]), hi[i]), pz - min(pz, z[i]))
                if v < bound:
                    bound = v
    lb = np.empty(B)  # per column: a lower bound of its candidates
    for i in range(B):
        gap = max(lo[i] - x1, x0 - hi[i])
        up = zmin - z[i]
        lb[i] = up if gap <= 0.0 else max(gap, up)
    best = np.inf
    out = (np.nan, np.nan, np.nan, np.nan, np.nan, -1)
    for side in range(2):  # heel, then toe, against the columns
        px, pz = (ax, az) if side == 0 else (bx, bz)
        for i in range(B):
            lim = min(best, bound)
            if lb[i] - NEAR_MARGIN_M > lim:
                continue
            cx = min(max(px, lo[i]), hi[i])
            cz = min(pz, z[i])
            dx, dz = px - cx, pz - cz
            if _farther(dx, dz, lim):
                continue
            v = math.hypot(dx, dz)
            if v < best:
                best = v
                out = (best, px, pz, cx, cz, i)
    dx, dz = bx - ax, bz - az
    L2 = dx * dx + dz * dz
    wide = x1 - x0 > 1e-12
    for c in range(2 * B):  # column top corners: the left ones, then the right ones
        i = c % B
        lim = min(best, bound)
        if lb[i] - NEAR_MARGIN_M > lim:
            continue
        ex, ez = (lo[i] if c < B else hi[i]), z[i]
        # _corner_distance, its hypot only when needed
        s = 0.0
        if L2 != 0:
            s = min(max(((ex - ax) * dx + (ez - az) * dz) / L2, 0.0), 1.0)
        qx, qz = ax + s * dx, az + s * dz
        above = False
        if wide:
            z_line = az + (ex - ax) * dz / dx
            if ex > x0 and ex < x1 and ez > z_line:
                above = True
                d = -min(ez - z_line, min(ex - x0, x1 - ex))
        if not above:
            if _farther(ex - qx, ez - qz, lim):
                continue
            d = math.hypot(ex - qx, ez - qz)
        if d < best:
            best = d
            out = (best, qx, qz, ex, ez, i)
    return out


@numba.njit(cache=True)
def _pose_clearance(ax, az, bx, bz, lo, hi, z, k0, best):  # pragma: no cover - compiled
    """The minimum of :func:`_clearance_many`'s candidates for one pose over the columns from
    ``k0`` up and below it down (``best``: the minimum so far), each side stopped at the
    first column apart from the foot's x span by a gap above the minimum (and above 0):
    every candidate of such a column is at least that gap (heel, toe and the segment's
    closest points lie in the span; the inside and above cases need an overlap), and the
    gaps only grow outwards, so the columns left out cannot lower it. ``NEAR_MARGIN_M``
    covers the rounding of the gap and of the closest points. Within the search, a column
    whose top is below the foot's lowest point by more than the minimum is skipped (each of
    its candidates is at least that drop), and a candidate's hypot is taken only when its
    squared distance does not already exceed the minimum (:func:`_farther`). The same
    minimum as visiting every column (a minimum does not depend on the order; no candidate
    is -0.0; every input finite)."""
    B = z.shape[0]
    abx, abz = bx - ax, bz - az
    L2 = max(abx * abx + abz * abz, 1e-18)
    x0, x1 = min(ax, bx), max(ax, bx)
    zmin = min(az, bz)
    slope = abz / abx if abs(abx) > 1e-12 else 0.0
    wide = x1 - x0 > 1e-12
    for side in range(2):
        i = k0 if side == 0 else k0 - 1
        while 0 <= i < B:
            gap = lo[i] - x1 if side == 0 else x0 - hi[i]
            if gap > NEAR_MARGIN_M and gap - NEAR_MARGIN_M > best:
                break
            zi = z[i]
            if zmin - zi - NEAR_MARGIN_M > best:  # every candidate is at least the drop
                i += 1 if side == 0 else -1
                continue
            for px, pz in ((ax, az), (bx, bz)):  # heel and toe against the column
                if px >= lo[i] and px <= hi[i] and pz < zi:
                    v = pz - zi
                else:
                    dx, dz = px - min(max(px, lo[i]), hi[i]), pz - min(pz, zi)
                    if _farther(dx, dz, best):
                        continue
                    v = math.hypot(dx, dz)
                if v < best or v != v:
                    best = v
            for cx in (lo[i], hi[i]):  # the column top's corners against the segment
                z_line = az + (cx - ax) * slope
                if cx > x0 and cx < x1 and zi > z_line and wide:
                    v = z_line - zi
                else:
                    s = min(max(((cx - ax) * abx + (zi - az) * abz) / L2, 0.0), 1.0)
                    dx, dz = cx - (ax + s * abx), zi - (az + s * abz)
                    if _farther(dx, dz, best):
                        continue
                    v = math.hypot(dx, dz)
                if v < best or v != v:
                    best = v
            i += 1 if side == 0 else -1
    return best


@numba.njit(cache=True)
def _clearance_many_near(a, b, lo, hi, z, sole):  # pragma: no cover - compiled
    """:func:`_clearance_many` visiting per pose only the columns near the foot (from the
    one under it outwards, :func:`_pose_clearance`): the same values when every input is
    finite (else the plain loop, which propagates NaN as numpy does)."""
    T, B = a.shape[0], z.shape[0]
    finite = True
    for t in range(T):
        finite = finite and math.isfinite(a[t, 0] + a[t, 1] + b[t, 0] + b[t, 1])
    for i in range(B):
        finite = finite and math.isfinite(lo[i] + hi[i] + z[i])
    if not finite:
        return _clearance_many(a, b, lo, hi, z, sole)
    out = np.empty(T)
    for t in range(T):
        ax, az, bx, bz = a[t, 0], a[t, 1], b[t, 0], b[t, 1]
        x0 = min(ax, bx)
        k0 = _first_reaching(hi, B, x0)  # the first column reaching the foot's span
        out[t] = _pose_clearance(ax, az, bx, bz, lo, hi, z, k0, np.inf) - sole
    return out


def clearance_many(
    heel_xz_m: ArrayLike, toe_xz_m: ArrayLike, prof: HeightProfile, sole_thickness_m: float = 0.0
) -> NDArray[np.float64]:
    """:func:`vio_graph.safety.clearance.clearance_many`, compiled."""
    a = np.ascontiguousarray(heel_xz_m, dtype=float).reshape(-1, 2)
    b = np.ascontiguousarray(toe_xz_m, dtype=float).reshape(-1, 2)
    if len(prof) == 0:
        return np.full(a.shape[0], np.nan)
    return _clearance_many_near(a, b, prof.x_lo_m, prof.x_hi_m, prof.z_m, float(sole_thickness_m))


@numba.njit(cache=True)
def _edge_clearance_many(a, b, ex, ez, sole, half):  # pragma: no cover - compiled
    out = np.empty(a.shape[0])
    for t in range(a.shape[0]):
        ax, az, bx, bz = a[t, 0], a[t, 1], b[t, 0], b[t, 1]
        dx, dz = bx - ax, bz - az
        L2 = dx * dx + dz * dz
        s = 0.0 if L2 == 0 else min(max(((ex - ax) * dx + (ez - az) * dz) / L2, 0.0), 1.0)
        qx, qz = ax + s * dx, az + s * dz
        d = math.sqrt((ex - qx) * (ex - qx) + (ez - qz) * (ez - qz))
        if abs(dx) > 1e-12 and min(ax, bx) < ex and ex < max(ax, bx):
            z_line = az + (ex - ax) * dz / dx
            if ez > z_line:
                d = -min(ez - z_line, ex - min(ax, bx), max(ax, bx) - ex)
        out[t] = d - sole
    return out


def edge_clearance_many(
    heel_xz_m: ArrayLike, toe_xz_m: ArrayLike, edge_xz_m: ArrayLike, sole_thickness_m: float = 0.0
) -> NDArray[np.float64]:
    """:func:`vio_graph.safety.clearance.edge_clearance_many`, compiled."""
    a = np.ascontiguousarray(heel_xz_m, dtype=float).reshape(-1, 2)
    b = np.ascontiguousarray(toe_xz_m, dtype=float).reshape(-1, 2)
    e = np.asarray(edge_xz_m, dtype=float)
    return _edge_clearance_many(a, b, float(e[0]), float(e[1]), float(sole_thickness_m), 0.5)


@numba.njit(cache=True)
def _coverage(xa, xb, lo, hi):  # pragma: no cover - compiled
    s = 0.0
    for i in range(lo.shape[0]):
        s += max(min(hi[i], xb) - max(lo[i], xa), 0.0)
    return s / (xb - xa)


@numba.njit(cache=True)
def _unseen_distance(xa, xb, lo, hi, x_min, x_max, max_gap):  # pragma: no cover - compiled
    """clearance.unseen_distance on the window's bin bounds."""
    gap = np.inf
    edge = x_min
    for i in range(lo.shape[0]):
        if lo[i] > max(edge, xa) + UNSEEN_TOLERANCE_M and (i == 0 or lo[i] - edge > max_gap):
            gap = min(gap, max(0.0, edge - xb))
        edge = max(edge, hi[i])
    if edge < x_max - UNSEEN_TOLERANCE_M:
        gap = min(gap, max(0.0, edge - xb))
    return gap


def coverage(heel_xz_m: ArrayLike, toe_xz_m: ArrayLike, prof: HeightProfile) -> float:
    """:func:`vio_graph.safety.clearance.coverage`, compiled."""
    h0, t0 = _xz(heel_xz_m)[0], _xz(toe_xz_m)[0]
    xa, xb = min(h0, t0), max(h0, t0)
    if len(prof) == 0 or xb <= xa:
        return 0.0 if len(prof) == 0 else 1.0
    return float(_coverage(xa, xb, prof.x_lo_m, prof.x_hi_m))


# ---------------------------------------------------------------------------------------------
# edges


@numba.njit(cache=True)
def _step(lo, hi, z, p, max_gap, slope_step):  # pragma: no cover - compiled
    """Sign of the transition pair p (bins p, p + 1), 0 if it is none (clearance.edge_runs)."""
    dz = z[p + 1] - z[p]
    if lo[p + 1] - hi[p] <= max_gap and abs(dz) > slope_step:
        return 1 if dz > 0 else -1
    return 0


@numba.njit(cache=True)
def _edge_runs(lo, hi, z, min_rise, max_gap, slope_step, max_bin):  # pragma: no cover
    n = z.shape[0]
    xz = np.empty((n, 2))
    rise = np.empty(n)
    first = np.empty(n, np.int64)
    m = 0
    # runs: [first pair, last pair, sign]; only the last one can still change
    r_i, r_j, r_s = -1, -1, 0
    have = False
    p = 0
    while p < n - 1:
        s = _step(lo, hi, z, p, max_gap, slope_step)
        if s == 0:
            p += 1
            continue
        i = j = p
        while (
            j + 1 < n - 1
            and _step(lo, hi, z, j + 1, max_gap, slope_step) == s
            and hi[j + 1] - lo[j + 1] <= max_bin
        ):
            j += 1
        if have and r_s == s and hi[i] - lo[r_j + 1] <= max_bin:
            r_j = j
        else:
            if have:
                m = _emit(lo, hi, z, r_i, r_j, r_s, min_rise, xz, rise, first, m)
            r_i, r_j, r_s, have = i, j, s, True
        p = j + 1
    if have:
        m = _emit(lo, hi, z, r_i, r_j, r_s, min_rise, xz, rise, first, m)
    return xz[:m], rise[:m], first[:m]


@numba.njit(cache=True)
def _emit(lo, hi, z, i, j, s, min_rise, xz, rise, first, m):  # pragma: no cover - compiled
    """Write the edge of the run of pairs i..j (sign s) at row m if it rises enough."""
    r = z[j + 1] - z[i]
    if abs(r) < min_rise:
        return m
    k, best = i, -1.0
    for q in range(i, j + 1):
        dz = z[q + 1] - z[q]
        sg = 1 if dz > 0 else (-1 if dz < 0 else 0)
        v = abs(dz) * (1.0 if sg == s else 0.0)
        if v > best:
            k, best = q, v
    if s > 0:
        xz[m, 0], xz[m, 1] = lo[k + 1], z[j + 1]
    else:
        xz[m, 0], xz[m, 1] = hi[k], z[i]
    rise[m] = r
    first[m] = i
    return m + 1


def edge_runs(
    prof: HeightProfile,
    min_rise_m: float,
    max_gap_m: float,
    slope_step_m: float = SLOPE_STEP_M,
    max_transition_bin_m: float = MAX_TRANSITION_BIN_M,
) -> tuple[Edges, NDArray[np.int64]]:
    """:func:`vio_graph.safety.clearance.edge_runs`, compiled."""
    if len(prof) < 2:
        return Edges(np.zeros((0, 2)), np.zeros(0)), np.zeros(0, np.int64)
    xz, rise, first = _edge_runs(
        prof.x_lo_m,
        prof.x_hi_m,
        prof.z_m,
        float(min_rise_m),
        float(max_gap_m),
        float(slope_step_m),
        float(max_transition_bin_m),
    )
    return Edges(xz, rise), first


# ---------------------------------------------------------------------------------------------
# the map's keyframe step


@numba.njit(cache=True)
def keyframe_tops(rel, cam_x, cam_z, bin_m, top_band_m):  # pragma: no cover - compiled
    """Per bin a keyframe's points fall in (``rel`` (N, 2) camera-relative, placed at the
    camera; non-finite rows skipped): the bin index (ascending) and the mean height of the
    points within ``top_band_m`` of its highest, summed from the highest down (the order of
    height_map.OnlineHeightMap.add_keyframe)."""
    N0 = rel.shape[0]
    px = np.empty(N0)
    pz = np.empty(N0)
    N = 0
    for k in range(N0):
        if np.isfinite(rel[k, 0]) and np.isfinite(rel[k, 1]):
            px[N] = rel[k, 0] + cam_x
            pz[N] = rel[k, 1] + cam_z
            N += 1
    idx = np.empty(N, np.int64)
    for k in range(N):
        idx[k] = np.int64(np.floor(px[k] / bin_m))
    if N == 0:
        return idx, px[:0]
    # stable counting sort by bin (a profile spans a few hundred bins; a stable argsort if
    # a stray point makes the span large)
    i_min, i_max = idx.min(), idx.max()
    if i_max - i_min > 4 * N + 4096:
        order = np.argsort(idx, kind="mergesort")
    else:
        start = np.zeros(i_max - i_min + 2, np.int64)
        for k in range(N):
            start[idx[k] - i_min + 1] += 1
        for r in range(1, start.shape[0]):
            start[r] += start[r - 1]
        order = np.empty(N, np.int64)
        for k in range(N):
            r = idx[k] - i_min
            order[start[r]] = k
            start[r] += 1
    bins = np.empty(N, np.int64)
    tops = np.empty(N)
    zs = np.empty(N)
    m = 0
    g = 0
    while g < N:
        h = g
        while h < N and idx[order[h]] == idx[order[g]]:
            h += 1
        # the group's heights, highest first, ties in input order (stable insertion sort)
        c = 0
        for q in range(g, h):
            v = pz[order[q]]
            r = c
            while r > 0 and zs[r - 1] < v:
                zs[r] = zs[r - 1]
                r -= 1
            zs[r] = v
            c += 1
        s, cnt = 0.0, 0
        for r in range(c):
            if zs[r] >= zs[0] - top_band_m:
                s += zs[r]
                cnt += 1
        bins[m] = idx[order[g]]
        tops[m] = s / cnt
        m += 1
        g = h
    return bins[:m], tops[:m]


@numba.njit(cache=True)
def view_ceilings(rel, cam_x, cam_z, bins, bin_m, tops):  # pragma: no cover - compiled
    """height_map.view_ceilings (``rel`` (N, 2), non-finite rows skipped)."""
    slope = -np.inf
    for k in range(rel.shape[0]):
        x, z = rel[k, 0], rel[k, 1]
        if np.isfinite(x) and np.isfinite(z) and x > 1e-6:
            slope = max(slope, z / x)
    u = np.empty(bins.shape[0])
    for q in range(bins.shape[0]):
        if slope == -np.inf:
            u[q] = np.inf
            continue
        x_lo = bins[q] * bin_m
        v = cam_z + max(slope * (x_lo - cam_x), slope * (x_lo + bin_m - cam_x))
        u[q] = max(v, tops[q])
    return u


@numba.njit(cache=True)
def _censored_stats(Z, U, e, top_band, median):  # pragma: no cover - compiled
    """height_map.OnlineHeightMap._bin_stats of bin element ``e`` when some kept height's
    view ceiling is below the bin's second-highest height (its highest when it has one)
    less ``top_band`` (else (NaN, NaN)): the statistic over the other heights."""
    cap = Z.shape[1]
    top1 = -np.inf
    top2 = -np.inf
    for r in range(cap):
        if Z[e, r] == Z[e, r]:
            if Z[e, r] > top1:
                top2 = top1
                top1 = Z[e, r]
            elif Z[e, r] > top2:
                top2 = Z[e, r]
    top = top2 if top2 > -np.inf else top1
    censored = False  # (most bins: no kept height censored, nothing to allocate)
    for r in range(cap):
        if Z[e, r] == Z[e, r] and U[e, r] < top - top_band:
            censored = True
            break
    if not censored:
        return np.nan, np.nan
    v = np.empty(cap)
    c = 0
    for r in range(cap):
        if Z[e, r] == Z[e, r] and not U[e, r] < top - top_band:
            v[c] = Z[e, r]
            c += 1
    full = 0
    for r in range(cap):
        if Z[e, r] == Z[e, r]:
            full += 1
    if c == full:  # (c >= 1: the two highest heights' ceilings are never below them)
        return np.nan, np.nan
    v = v[:c]
    if median:
        S = np.sort(v)
        lo, hi = (c - 1) // 2, c // 2
        m = (S[lo] + S[hi]) / 2
        D = np.sort(np.abs(v - m))
        sd = 1.4826 * (D[lo] + D[hi]) / 2
        return m, (1.2533 * sd) ** 2 / c
    m = 0.0
    for r in range(c):
        m += v[r]
    m /= c
    s = 0.0
    for r in range(c):
        s += (v[r] - m) ** 2
    return m, s / c / c


@numba.njit(cache=True)
def add_tops(
    Z,
    Zs,
    n,
    used,
    mid,
    se2,
    cov,
    j,
    tops,
    min_keyframes,
    agree_keyframes,
    agree_m,
    median,
    P,
    zcap,
    max_excess,
    U,
    ceilings,
    top_band,
):  # pragma: no cover
    """In place: the keyframe heights ``tops`` join bins at array elements ``j``, and those
    bins' count, used flag, height, squared standard error and covariance sum are updated
    (height_map.OnlineHeightMap.add_keyframe, _used_rule, _bin_stats and _capped: ``zcap``
    the bins' foot-contact caps, ``max_excess`` the largest excess they remove). ``Zs``: each
    bin's kept heights sorted (NaN after them), kept up to date here: the median is read off
    it and the median absolute deviation found by walking out from the median (no sort per
    keyframe). ``U``: the kept heights' view ceilings, ``ceilings`` this keyframe's (per
    bin of ``j``; _censored_stats, ``top_band`` the map's top_band_m)."""
    cap = Z.shape[1]
    for q in range(j.shape[0]):
        e = j[q]
        slot = n[e] % cap
        old = Z[e, slot]
        c = min(n[e], cap)  # kept heights before this one
        Z[e, slot] = tops[q]
        U[e, slot] = ceilings[q]
        n[e] += 1
        if old == old:  # the oldest height leaves the sorted copy
            r = 0
            while Zs[e, r] != old:
                r += 1
            while r < c - 1:
                Zs[e, r] = Zs[e, r + 1]
                r += 1
            c -= 1
        r = c
        while r > 0 and Zs[e, r - 1] > tops[q]:
            Zs[e, r] = Zs[e, r - 1]
            r -= 1
        Zs[e, r] = tops[q]
        c += 1
        # used: seen often enough, or seen by fewer keyframes whose heights agree
        used[e] = n[e] >= min_keyframes or (
            n[e] >= agree_keyframes and Zs[e, c - 1] - Zs[e, 0] <= agree_m
        )
        if median:
            lo, hi = (c - 1) // 2, c // 2
            m = (Zs[e, lo] + Zs[e, hi]) / 2
            # the lo-th and hi-th smallest |height - m|: merge the deviations below and above
            L = lo if Zs[e, lo] < m else lo - 1
            R = L + 1
            d_lo = d_hi = 0.0
            for k in range(hi + 1):
                if R >= c or (L >= 0 and m - Zs[e, L] <= Zs[e, R] - m):
                    d = m - Zs[e, L]
                    L -= 1
                else:
                    d = Zs[e, R] - m
                    R += 1
                if k == lo:
                    d_lo = d
                d_hi = d
            sd = 1.4826 * (d_lo + d_hi) / 2
            mid[e] = m
            se2[e] = (1.2533 * sd) ** 2 / c
        else:
            m = 0.0
            for r in range(cap):
                if Z[e, r] == Z[e, r]:
                    m += Z[e, r]
            m /= c
            v = 0.0
            for r in range(cap):
                if Z[e, r] == Z[e, r]:
                    v += (Z[e, r] - m) ** 2
            mid[e] = m
            se2[e] = v / c / c
        cm, cs = _censored_stats(Z, U, e, top_band, median)
        if cm == cm:  # some kept heights were seen from below a higher one
            mid[e], se2[e] = cm, cs
        if mid[e] > zcap[e] and mid[e] < zcap[e] + max_excess:  # a foot stood lower here
            mid[e] = zcap[e]
        cov[e, 0] += P[0, 0]
        cov[e, 1] += P[0, 1]
        cov[e, 2] += P[1, 1]


@numba.njit(cache=True)
def contact_caps(
    hx, hz, ox, oz, margin, max_excess, b0, b1, i0, bin_m, Z, U, n, mid, cap, band
):  # pragma: no cover - compiled
    """height_map.OnlineHeightMap.add_contact after its checks and the map's growth, for the
    median statistic, in place: the bins b0..b1 (bin indices) under the heel-toe line
    capped at the sole's height at their centre plus ``margin``, and the heights of the
    seen ones moved as there (the bin's censored median, :func:`_censored_stats`' rule, as
    _bin_stats takes it). Returns the first and last array element whose height changed
    (-1, -1: none)."""
    first = last = -1
    w = np.empty(Z.shape[1])
    for b in range(b0, b1 + 1):
        j = b - i0
        xc = (b + 0.5) * bin_m
        zc = hz + (oz - hz) * (xc - hx) / (ox - hx) + margin
        if not zc < cap[j]:
            continue
        old_cap = cap[j]
        cap[j] = zc
        if not n[j] > 0:
            continue
        # the second-highest kept height (the highest when only one), the heights whose
        # view ceiling reaches it less the band, their median
        top1 = -np.inf
        top2 = -np.inf
        for r in range(Z.shape[1]):
            if Z[j, r] == Z[j, r]:
                if Z[j, r] > top1:
                    top2 = top1
                    top1 = Z[j, r]
                elif Z[j, r] > top2:
                    top2 = Z[j, r]
        top = top2 if top2 > -np.inf else top1
        c = 0
        for r in range(Z.shape[1]):
            if Z[j, r] == Z[j, r] and not U[j, r] < top - band:
                w[c] = Z[j, r]
                c += 1
        S = np.sort(w[:c])
        stat = (S[(c - 1) // 2] + S[c // 2]) / 2
        if stat > zc and stat < zc + max_excess:
            new = zc
        elif mid[j] == old_cap:
            new = stat
        else:
            new = mid[j]
        if new != mid[j]:
            mid[j] = new
            if first < 0:
                first = j
            last = j
    return first, last


@numba.njit(cache=True)
def window_bins(used, mid, se2, a0, a1, i0, bin_m, x_min, x_max, map_sigma):  # pragma: no cover
    """The used bins among array elements [a0, a1) overlapping [x_min, x_max]: their x_lo,
    x_hi, height, height sigma and bin index (height_map: _bins_profile of the window)."""
    m = 0
    for e in range(a0, a1):
        if used[e]:
            x_lo = (e + i0) * bin_m
            if x_lo + bin_m >= x_min and x_lo <= x_max:
                m += 1
    lo, hi, z, sig = np.empty(m), np.empty(m), np.empty(m), np.empty(m)
    bins = np.empty(m, np.int64)
    k = 0
    s2 = map_sigma**2
    for e in range(a0, a1):
        if used[e]:
            x_lo = (e + i0) * bin_m
            if x_lo + bin_m >= x_min and x_lo <= x_max:
                lo[k], hi[k], z[k] = x_lo, x_lo + bin_m, mid[e]
                sig[k] = math.sqrt(se2[e] + s2)
                bins[k] = e + i0
                k += 1
    return lo, hi, z, sig, bins


@numba.njit(cache=True)
def window_bridged_gap(used, i0, bin_m, a0, a1, x_min, x_max, max_gap):  # pragma: no cover
    """Whether the used bins among array elements [a0, a1) overlapping [x_min, x_max] (the
    bins :func:`window_bins` returns) leave a strip between two consecutive ones wider than
    ``UNSEEN_TOLERANCE_M`` and at most ``max_gap`` wide: the strips clearance.gap_terrain
    turns into floors and risers (none: it returns nothing). The same x_lo / x_hi floats as
    :func:`window_bins`, without building the window."""
    prev_hi = np.nan
    for e in range(a0, a1):
        if used[e]:
            x_lo = (e + i0) * bin_m
            x_hi = x_lo + bin_m
            if x_hi >= x_min and x_lo <= x_max:
                if prev_hi == prev_hi:
                    gap = x_lo - prev_hi
                    if gap > UNSEEN_TOLERANCE_M and gap <= max_gap:
                        return True
                prev_hi = x_hi
    return False


@numba.njit(cache=True)
def observe_errors(t, h, poses, t0, f0, t1, f1, sums, counts):  # pragma: no cover - compiled
    """prediction_error.PredictionErrors.observe after its early returns, in one call: the
    kept instants t[r] + h[s] in (t0, t1] scored against the foot interpolated between the
    frames (``f0`` at ``t0``, ``f1`` at ``t1``; heel x, z, toe x, z), row by row (np.nonzero's
    order), their squared errors summed per step from zero and then added to ``sums`` (as
    np.bincount and ``+=``), the counts to ``counts``; the rows whose last instant has passed
    get time NaN. In place; returns (any instant scored, rows dropped)."""
    R, n = poses.shape[0], poses.shape[1]
    part = np.zeros(n)
    cnt = np.zeros(n)
    scored = False
    dropped = 0
    span = t1 - t0
    for r in range(R):
        for s in range(n):
            tt = t[r] + h[s]
            if tt > t0 and tt <= t1:
                w = (tt - t0) / span
                d0 = poses[r, s, 0] - (f0[0] + w * (f1[0] - f0[0]))
                d1 = poses[r, s, 1] - (f0[1] + w * (f1[1] - f0[1]))
                d2 = poses[r, s, 2] - (f0[2] + w * (f1[2] - f0[2]))
                d3 = poses[r, s, 3] - (f0[3] + w * (f1[3] - f0[3]))
                a, b = d0**2 + d1**2, d2**2 + d3**2
                part[s] += a if a >= b or a != a else b  # (np.maximum: NaN propagates)
                cnt[s] += 1.0
                scored = True
    if scored:
        for s in range(n):
            sums[s] += part[s]
            counts[s] += cnt[s]
    for r in range(R):
        if t[r] + h[n - 1] <= t1:
            t[r] = np.nan
            dropped += 1
    return scored, dropped


# ---------------------------------------------------------------------------------------------
# the keyframe consistency test


@numba.njit(cache=True)
def _median_select(a):  # pragma: no cover - compiled
    """:func:`_median_sorted` by selection (np.partition at the middle; for an even count
    the largest value below it is the other middle one): the same float, without sorting
    the whole array."""
    n = a.shape[0]
    if n == 0:
        return np.nan
    for i in range(n):
        if a[i] != a[i]:
            return np.nan
    h = n // 2
    part = np.partition(a, h)
    if n % 2:
        return part[h]
    below = part[0]
    for i in range(1, h):
        below = max(below, part[i])
    return (below + part[h]) / 2


@numba.njit(cache=True)
def _median_sorted(a):  # pragma: no cover - compiled
    """np.median of a 1-D array: sorted copy, the middle element or the mean of the two
    middle ones (the same float as numpy's partition-based median); NaN if any is NaN."""
    n = a.shape[0]
    if n == 0:
        return np.nan
    for i in range(n):
        if a[i] != a[i]:
            return np.nan
    s = np.sort(a)
    h = n // 2
    if n % 2:
        return s[h]
    return (s[h - 1] + s[h]) / 2


@numba.njit(cache=True)
def consistency_squares(
    bins, top, x_lo, z, sigma, wbins, cov, n, i0, bin_m, P00, P01, P10, P11
):  # pragma: no cover - compiled
    """consistency.MapConsistency.observe_keyframe up to the two scales' inputs: the
    keyframe's bins ``bins`` / heights ``top`` against the map window (``x_lo``, ``z``,
    ``sigma``, bin indices ``wbins``), the map's covariance sums ``cov`` and counts ``n``
    (array element = bin index - ``i0``). Returns (any bin shared, the common offset o, the
    residuals' scaled MAD, the median of |dP|_zz, the bins shared, the map test's
    normalised squares sorted (finite, positive variance: what ChiSquareScale keeps)); the
    offset's variance is left to the caller (Python's ``**`` differs from x*x in the last
    bit at times, and the reference squares with it)."""
    K = x_lo.shape[0]
    empty = np.zeros(0)
    if K == 0:
        return False, np.nan, np.nan, np.nan, 0, empty
    mapped = np.empty(K, np.int64)
    for i in range(K):
        mapped[i] = np.int64(np.rint(x_lo[i] / bin_m))
    # the keyframe's bins the map holds (both sorted): their heights' innovations
    M = bins.shape[0]
    r = np.empty(M)
    kk = np.empty(M, np.int64)
    m = 0
    j = 0
    for i in range(M):
        while j < K and mapped[j] < bins[i]:
            j += 1
        k = min(j, K - 1)
        if mapped[k] == bins[i]:
            r[m] = top[i] - z[k]
            kk[m] = k
            m += 1
    if m == 0:
        return False, np.nan, np.nan, np.nan, 0, empty
    r = r[:m]
    offset = _median_select(r)
    dev = np.empty(m)
    res = np.empty(m)
    zz = np.empty(m)
    pxz = (P01 + P10) / 2
    for q in range(m):
        res[q] = r[q] - offset
        dev[q] = abs(res[q])
        e = wbins[kk[q]] - i0
        c = float(n[e])
        a = P00 - cov[e, 0] / c
        b = pxz - cov[e, 1] / c
        d = P11 - cov[e, 2] / c
        # consistency.psd_abs_zz of (a, b, d)
        mm = (a + d) / 2
        h = (a - d) / 2
        rr = np.sqrt(h * h + b * b)
        l1, l2 = mm + rr, mm - rr
        vz2 = (l1 - a) / (2 * rr) if rr > 0 else 0.5
        if vz2 < 0.0:
            vz2 = 0.0
        elif vz2 > 1.0:
            vz2 = 1.0
        zz[q] = abs(l1) * vz2 + abs(l2) * (1.0 - vz2)
    mad_sd = 1.4826 * _median_select(dev)
    sq = np.empty(m)
    c = 0
    for q in range(m):
        v = sigma[kk[q]] * sigma[kk[q]]
        if np.isfinite(res[q]) and np.isfinite(v) and v > 0:
            sq[c] = res[q] * res[q] / v
            c += 1
    return True, offset, mad_sd, _median_select(zz), m, np.sort(sq[:c])


@numba.njit(cache=True)
def profile_x_range(rel, cam_x):  # pragma: no cover - compiled
    """The smallest and largest x (m) of a keyframe's finite points placed at the camera
    (``rel`` (N, 2) camera-relative, x plus ``cam_x``), NaN, NaN without one."""
    lo, hi = np.inf, -np.inf
    found = False
    for k in range(rel.shape[0]):
        if np.isfinite(rel[k, 0]) and np.isfinite(rel[k, 1]):
            x = rel[k, 0] + cam_x
            lo, hi = min(lo, x), max(hi, x)
            found = True
    if not found:
        return np.nan, np.nan
    return lo, hi


@numba.njit(cache=True)
def window_merge(srt, old, q):  # pragma: no cover - compiled
    """consistency.ChiSquareScale's sorted window after a keyframe: ``srt`` (sorted) without
    the values of ``old`` (sorted, a sub-multiset of it; empty while the window fills) and
    with those of ``q`` (sorted) merged in, one pass."""
    out = np.empty(srt.shape[0] - old.shape[0] + q.shape[0])
    i = j = k = m = 0
    while i < srt.shape[0] or k < q.shape[0]:
        if i < srt.shape[0] and j < old.shape[0] and srt[i] == old[j]:
            i += 1  # the oldest keyframe's value leaves
            j += 1
        elif k >= q.shape[0] or (i < srt.shape[0] and srt[i] <= q[k]):
            out[m] = srt[i]
            i += 1
            m += 1
        else:
            out[m] = q[k]
            k += 1
            m += 1
    return out


# ---------------------------------------------------------------------------------------------
# the swing-template prediction


@numba.njit(cache=True)
def _interp_column(q, xp, disp, s0, n, c, at):  # pragma: no cover - compiled
    """``at[:] = np.interp(q, xp, disp[s0:s0 + n, c])`` for strictly increasing ``xp`` (n),
    without the column's copy and the result's allocation: numba's (numpy's) arithmetic
    per query (outside the range the end values; at a sample point its value; else the
    slope of the interval times the offset plus the left value, from the right end if that
    is NaN), found by bisection (with increasing ``xp`` every search finds the same
    interval)."""
    for i in range(q.shape[0]):
        x = q[i]
        if x != x:
            at[i] = x
            continue
        if n == 1:
            at[i] = disp[s0, c]
            continue
        if x > xp[n - 1]:
            at[i] = disp[s0 + n - 1, c]
            continue
        if x < xp[0]:
            at[i] = disp[s0, c]
            continue
        lo, hi = 0, n - 1  # the last j with xp[j] <= x
        while lo < hi:
            m = (lo + hi + 1) // 2
            if xp[m] <= x:
                lo = m
            else:
                hi = m - 1
        j = lo
        if j == n - 1 or xp[j] == x:
            at[i] = disp[s0 + j, c]
            continue
        y0, y1 = disp[s0 + j, c], disp[s0 + j + 1, c]
        slope = (y1 - y0) / (xp[j + 1] - xp[j])
        r = slope * (x - xp[j]) + y0
        if r != r:
            r = slope * (x - xp[j + 1]) + y1
            if r != r and y0 == y1:
                r = y0
        at[i] = r


@numba.njit(cache=True)
def _median_over_templates(out):  # pragma: no cover - compiled
    """The median over templates (axis 0) of ``out`` (T, H, 4), np.median's floats; one
    template: a copy of it."""
    T, H = out.shape[0], out.shape[1]
    if T == 1:
        return out[0].copy()
    med = np.empty((H, 4))
    v = np.empty(T)
    for i in range(H):
        for c in range(4):
            for k in range(T):
                v[k] = out[k, i, c]
            v.sort()
            med[i, c] = v[T // 2] if T % 2 else (v[T // 2 - 1] + v[T // 2]) / 2
    return med


@numba.njit(cache=True)
def template_motion(tau, h, phase, disp, starts):  # pragma: no cover - compiled
    """Median displacement (H, 4) of heel and toe from phase tau to tau + h over the
    templates (online.SafetyMonitor._template_motion): template k is ``phase`` (s) and
    ``disp`` (., 4) rows ``starts[k]:starts[k + 1]``. Each column interpolated in place
    (:func:`_interp_column`; a template whose phases do not increase strictly goes
    through ``np.interp``): the floats of :func:`template_motion_reference`."""
    T, H = starts.shape[0] - 1, h.shape[0]
    q = np.empty(H + 1)
    q[0] = tau
    for i in range(H):
        q[i + 1] = tau + h[i]
    out = np.empty((T, H, 4))
    at = np.empty(H + 1)
    for k in range(T):
        s0, s1 = starts[k], starts[k + 1]
        ph = phase[s0:s1]
        increasing = s1 > s0
        for r in range(1, s1 - s0):
            if not ph[r] > ph[r - 1]:
                increasing = False
        for c in range(4):
            if increasing:
                _interp_column(q, ph, disp, s0, s1 - s0, c, at)
            else:
                at = np.interp(q, ph, np.ascontiguousarray(disp[s0:s1, c]))
            for i in range(H):
                out[k, i, c] = at[i + 1] - at[0]
    return _median_over_templates(out)


@numba.njit(cache=True)
def template_motion_reference(tau, h, phase, disp, starts):  # pragma: no cover - compiled
    """:func:`template_motion` with numba's ``np.interp`` on each column (a copy of it
    each): the reference its interpolation is tested against."""
    T, H = starts.shape[0] - 1, h.shape[0]
    q = np.empty(H + 1)
    q[0] = tau
    for i in range(H):
        q[i + 1] = tau + h[i]
    out = np.empty((T, H, 4))
    for k in range(T):
        ph = phase[starts[k] : starts[k + 1]]
        for c in range(4):
            at = np.interp(q, ph, np.ascontiguousarray(disp[starts[k] : starts[k + 1], c]))
            for i in range(H):
                out[k, i, c] = at[i + 1] - at[0]
    return _median_over_templates(out)


@numba.njit(cache=True)
def _pair_changes(used_mid, p, q, i0, bin_m, max_gap, slope_step):  # pragma: no cover
    """Used bins at array elements p < q form a transition pair (edge_runs' step != 0)."""
    gap = (q + i0) * bin_m - ((p + i0) * bin_m + bin_m)
    return gap <= max_gap and abs(used_mid[q] - used_mid[p]) > slope_step


#: edges longer than this (never: 8192 of them are 1.6 km of stairs) are summed by numpy;
#: :func:`vio_graph.compiled_sums.pairwise_sum` is numpy's pairwise summation up to its
#: 64-level stack, far beyond it
PAIRWISE_MAX_N = 8192


@numba.njit(cache=True)
def edge_summary(xz, rise):  # pragma: no cover - compiled
    """clearance.Edges.summary of edges ``xz`` (E, 2), ``rise`` (E,) with E at most
    ``PAIRWISE_MAX_N``: (number, mean |rise|, mean spacing), NaN where undefined; the same
    floats (the absolute rises and the consecutive differences summed as numpy does)."""
    n = rise.shape[0]
    mean_rise = np.nan
    tread = np.nan
    if n:
        a = np.empty(n)
        for i in range(n):
            a[i] = abs(rise[i])
        mean_rise = (0.0 + pairwise_sum(a, 0, n)) / n
    if n >= 2:
        d = np.empty(n - 1)
        for i in range(n - 1):
            d[i] = xz[i + 1, 0] - xz[i, 0]
        tread = (0.0 + pairwise_sum(d, 0, n - 1)) / (n - 1)
    return n, mean_rise, tread


@numba.njit(cache=True)
def rescan_edges(
    used, mid, i0, bin_m, e_lo, e_hi, min_rise, max_gap, slope_step, max_bin, xz, rise, first
):  # pragma: no cover - compiled
    """height_map.IncrementalHeightMap._rescan_edges in one call: the map's edges (``xz``,
    ``rise``, ``first`` bin index) after the bins at array elements [e_lo, e_hi] changed."""
    n = used.shape[0]
    # the scan's start: the right end of the first quiet stretch walking left from e_lo
    start = -1
    e = e_lo - 1
    while e >= 0 and not used[e]:
        e -= 1
    if e >= 0:
        v = w = e
        u = w - 1
        while True:
            while u >= 0 and not used[u]:
                u -= 1
            if u < 0:
                break
            if _pair_changes(mid, u, w, i0, bin_m, max_gap, slope_step):
                v = w = u
            else:
                w = u
                if (v + i0) * bin_m + bin_m - (w + i0) * bin_m > max_bin:
                    start = v
                    break
            u = w - 1
    # its stop: the right end of the first quiet stretch walking right from e_hi
    stop = -1
    e = e_hi + 1
    while e < n and not used[e]:
        e += 1
    if e < n:
        w = v = e
        u = v + 1
        while True:
            while u < n and not used[u]:
                u += 1
            if u >= n:
                break
            if _pair_changes(mid, v, u, i0, bin_m, max_gap, slope_step):
                w = v = u
            else:
                v = u
                if (v + i0) * bin_m + bin_m - (w + i0) * bin_m > max_bin:
                    stop = v
                    break
            u = v + 1
    lo = start if start >= 0 else 0
    hi = stop if stop >= 0 else n - 1
    m = 0
    for e in range(lo, hi + 1):
        if used[e]:
            m += 1
    sub = np.empty(m, np.int64)
    x_lo, x_hi, z = np.empty(m), np.empty(m), np.empty(m)
    k = 0
    for e in range(lo, hi + 1):
        if used[e]:
            sub[k] = e
            x_lo[k] = (e + i0) * bin_m
            x_hi[k] = x_lo[k] + bin_m
            z[k] = mid[e]
            k += 1
    new_xz, new_rise, new_first = _edge_runs(x_lo, x_hi, z, min_rise, max_gap, slope_step, max_bin)
    # splice: the old edges whose scan starts before lo or from hi on stay
    keep_l = 0
    keep_r = 0
    for q in range(first.shape[0]):
        if start >= 0 and first[q] < lo + i0:
            keep_l += 1
        elif stop >= 0 and first[q] >= hi + i0:
            keep_r += 1
    E = keep_l + new_rise.shape[0] + keep_r
    out_xz, out_rise, out_first = np.empty((E, 2)), np.empty(E), np.empty(E, np.int64)
    k = 0
    for q in range(first.shape[0]):
        if start >= 0 and first[q] < lo + i0:
            out_xz[k, 0], out_xz[k, 1], out_rise[k], out_first[k] = (
                xz[q, 0],
                xz[q, 1],
                rise[q],
                first[q],
            )
            k += 1
    for q in range(new_rise.shape[0]):
        out_xz[k, 0], out_xz[k, 1] = new_xz[q, 0], new_xz[q, 1]
        out_rise[k], out_first[k] = new_rise[q], sub[new_first[q]] + i0
        k += 1
    for q in range(first.shape[0]):
        if stop >= 0 and first[q] >= hi + i0:
            out_xz[k, 0], out_xz[k, 1], out_rise[k], out_first[k] = (
                xz[q, 0],
                xz[q, 1],
                rise[q],
                first[q],
            )
            k += 1
    if _same_edges(out_xz, out_rise, out_first, xz, rise, first):
        return xz, rise, first  # (unchanged: the caller keeps its arrays and their summary)
    return out_xz, out_rise, out_first


@numba.njit(cache=True)
def _same_edges(xz, rise, first, xz0, rise0, first0):  # pragma: no cover - compiled
    """The edges equal the old ones bit for bit (the same floats, signs of zeros too)."""
    if rise.shape[0] != rise0.shape[0]:
        return False
    for q in range(rise.shape[0]):
        if first[q] != first0[q]:
            return False
        for a, b in ((xz[q, 0], xz0[q, 0]), (xz[q, 1], xz0[q, 1]), (rise[q], rise0[q])):
            if not (a == b and math.copysign(1.0, a) == math.copysign(1.0, b)):
                return False
    return True


@numba.njit(cache=True)
def bin_below(used, i0, bin_m, x):  # pragma: no cover - compiled
    """height_map.IncrementalHeightMap.bin_below: (found, bin index)."""
    n = used.shape[0]
    hi = min(max(np.int64(np.floor(x / bin_m)) + 2 - i0, 0), n)
    for e in range(hi - 1, -1, -1):
        if used[e] and (e + i0) * bin_m < x:
            return True, e + i0
    for e in range(n):
        if used[e]:
            return True, e + i0
    return False, 0


@numba.njit(cache=True)
def _predicted_min(hx, hz, tx, tz, vx, vz, horizon, steps, lo, hi, z, sole):  # pragma: no cover
    T = steps + 1
    a, b = np.empty((T, 2)), np.empty((T, 2))
    step = horizon / steps
    for i in range(T):
        tau = i * step + 0.0 if i < steps else horizon  # np.linspace(0, horizon, steps + 1)
        a[i, 0], a[i, 1] = hx + vx * tau, hz + vz * tau
        b[i, 0], b[i, 1] = tx + vx * tau, tz + vz * tau
    d = _clearance_many_near(a, b, lo, hi, z, sole)
    best = d[0]
    for i in range(1, T):
        if d[i] < best or d[i] != d[i]:
            best = d[i]
            if best != best:
                break
    return best


def predicted_min_clearance(
    heel_xz_m: ArrayLike,
    toe_xz_m: ArrayLike,
    velocity_xz_mps: ArrayLike,
    horizon_s: float,
    steps: int,
    prof: HeightProfile,
    sole_thickness_m: float = 0.0,
) -> float:
    """:func:`vio_graph.safety.clearance.predicted_min_clearance`, compiled."""
    vx, vz = _xz(velocity_xz_mps)
    if len(prof) == 0 or not (math.isfinite(vx) and math.isfinite(vz)):
        return float("nan")
    return float(
        _predicted_min(
            *_xz(heel_xz_m),
            *_xz(toe_xz_m),
            vx,
            vz,
            float(horizon_s),
            int(steps),
            prof.x_lo_m,
            prof.x_hi_m,
            prof.z_m,
            float(sole_thickness_m),
        )
    )


@numba.njit(cache=True)
def _edges_reached(edges_xz, e, lim):  # pragma: no cover - compiled
    """How many edges from index ``e`` on have x <= ``lim`` (m), at least one; all of them
    when ``lim`` is NaN (searchsorted puts NaN after every edge)."""
    E = edges_xz.shape[0]
    n = 0
    for j in range(e, E):
        if edges_xz[j, 0] <= lim:
            n = j - e + 1
        else:
            break
    if lim != lim:
        n = E - e
    return max(1, n)


@numba.njit(cache=True)
def _edge_known(cleared, new, n_new, ex, tol):  # pragma: no cover - compiled
    """Whether the edge at x = ``ex`` (m) is within ``tol`` of an edge already cleared, in
    ``cleared`` or among the first ``n_new`` of ``new``."""
    for c in cleared:
        if abs(c - ex) <= tol:
            return True
    for k in range(n_new):
        if abs(new[k] - ex) <= tol:
            return True
    return False


@numba.njit(cache=True)
def _edge_distance(ax, az, bx, bz, ex, ez, half):  # pragma: no cover - compiled
    """clearance._edge_distance: (signed distance, closest x, z)."""
    dx, dz = bx - ax, bz - az
    L2 = dx * dx + dz * dz
    s = 0.0 if L2 == 0 else min(max(((ex - ax) * dx + (ez - az) * dz) / L2, 0.0), 1.0)
    qx, qz = ax + s * dx, az + s * dz
    d = math.sqrt((ex - qx) * (ex - qx) + (ez - qz) * (ez - qz))
    if abs(dx) > 1e-12 and min(ax, bx) < ex and ex < max(ax, bx):
        z_line = az + (ex - ax) * dz / dx
        if ez > z_line:
            d = -min(ez - z_line, ex - min(ax, bx), max(ax, bx) - ex)
    return d, qx, qz


def edge_clearance(
    heel_xz_m: ArrayLike, toe_xz_m: ArrayLike, edge_xz_m: ArrayLike, sole_thickness_m: float = 0.0
) -> Clearance:
    """:func:`vio_graph.safety.clearance.edge_clearance`, compiled."""
    ex, ez = _xz(edge_xz_m)
    d, qx, qz = _edge_distance(
        *_xz(heel_xz_m),
        *_xz(toe_xz_m),
        ex,
        ez,
        0.5,
    )
    n = math.sqrt((qx - ex) * (qx - ex) + (qz - ez) * (qz - ez))
    nx, nz = ((qx - ex) / n, (qz - ez) / n) if n > 1e-9 else (0.0, 1.0)
    if d < 0:
        nx, nz = -nx, -nz
    return Clearance(
        d - sole_thickness_m, np.array([qx, qz]), np.array([ex, ez]), -1, np.array([nx, nz])
    )


@numba.njit(cache=True)
def _point_segment(px, pz, ax, az, bx, bz, half):  # pragma: no cover - compiled
    dx, dz = bx - ax, bz - az
    L2 = dx * dx + dz * dz
    s = 0.0 if L2 == 0 else min(max(((px - ax) * dx + (pz - az) * dz) / L2, 0.0), 1.0)
    ux, uz = px - ax - s * dx, pz - az - s * dz
    return math.sqrt(ux * ux + uz * uz)


@numba.njit(cache=True)
def _orient(px, pz, qx, qz, rx, rz):  # pragma: no cover - compiled
    return (qx - px) * (rz - pz) - (qz - pz) * (rx - px)


@numba.njit(cache=True)
def _predicted_min_edge(ax, az, bx, bz, vx, vz, horizon, ex, ez, half):  # pragma: no cover
    fx, fz = ex - vx * horizon, ez - vz * horizon
    d0 = _edge_distance(ax, az, bx, bz, ex, ez, half)[0]
    d1 = _edge_distance(ax, az, bx, bz, fx, fz, half)[0]
    best = min(
        d0,
        d1,
        _point_segment(ax, az, ex, ez, fx, fz, half),
        _point_segment(bx, bz, ex, ez, fx, fz, half),
    )
    o1, o2 = _orient(ax, az, bx, bz, ex, ez), _orient(ax, az, bx, bz, fx, fz)
    o3, o4 = _orient(ex, ez, fx, fz, ax, az), _orient(ex, ez, fx, fz, bx, bz)
    if o1 * o2 < 0 and o3 * o4 < 0:
        best = min(best, 0.0)
    return best


def predicted_min_edge_clearance(
    heel_xz_m: ArrayLike,
    toe_xz_m: ArrayLike,
    velocity_xz_mps: ArrayLike,
    horizon_s: float,
    steps: int,
    edge_xz_m: ArrayLike,
    sole_thickness_m: float = 0.0,
) -> float:
    """:func:`vio_graph.safety.clearance.predicted_min_edge_clearance`, compiled."""
    vx, vz = _xz(velocity_xz_mps)
    if not (math.isfinite(vx) and math.isfinite(vz)):
        return float("nan")
    best = _predicted_min_edge(
        *_xz(heel_xz_m),
        *_xz(toe_xz_m),
        vx,
        vz,
        float(horizon_s),
        *_xz(edge_xz_m),
        0.5,
    )
    return float(best) - sole_thickness_m


@numba.njit(cache=True)
def swing_edge_risk(
    hp, tp, edges_xz, e, toe_x_max, toe_pass, sole, dt, min_fwd, near_trip, tol, cleared, half
):  # pragma: no cover - compiled
    """The swing-template branch's edge loop of ``online.SafetyMonitor.update`` in one call:
    over the predicted heel / toe poses ``hp``, ``tp`` (H, 2), the minimum clearance to the
    edges the toe reaches from the next one (index ``e``; ``_edges_reached``) and the
    near-trip candidates' minimum (forward toe velocity by central differences of ``tp``
    with step ``dt``, the pose's own next edge, the foot clear of that edge first:
    ``_approach`` against the edges already ``cleared`` (x, m, within ``tol``)). The same
    operations in the same order as the numpy loop, NaN as numpy's minimum propagates it.
    Returns (pred_edge, risk, the x of the edges newly cleared (K,))."""
    H = tp.shape[0]
    E = edges_xz.shape[0]
    pred_edge = np.nan
    risk = np.nan
    new = np.empty(max(E - max(e, 0), 0))
    n_new = 0
    if e < 0:
        return pred_edge, risk, new[:0]
    # forward motion per pose (np.gradient of tp, one-sided at the ends)
    fwd = np.empty(H, np.bool_)
    for t in range(H):
        if t == 0:
            vx = (tp[1, 0] - tp[0, 0]) / dt
            vz = (tp[1, 1] - tp[0, 1]) / dt
        elif t == H - 1:
            vx = (tp[H - 1, 0] - tp[H - 2, 0]) / dt
            vz = (tp[H - 1, 1] - tp[H - 2, 1]) / dt
        else:
            vx = (tp[t + 1, 0] - tp[t - 1, 0]) / (2.0 * dt)
            vz = (tp[t + 1, 1] - tp[t - 1, 1]) / (2.0 * dt)
        fwd[t] = vx > min_fwd and vz > -vx
    # each pose's next edge: searchsorted(edge x, toe x - toe_pass, side="right")
    nxt = np.empty(H, np.int64)
    for t in range(H):
        v = tp[t, 0] - toe_pass
        if v != v:
            nxt[t] = E  # NaN sorts last
            continue
        lo, hi = 0, E
        while lo < hi:
            m = (lo + hi) // 2
            if edges_xz[m, 0] <= v:
                lo = m + 1
            else:
                hi = m
        nxt[t] = lo
    # the edges reached: from e to the last with x <= toe_x_max + toe_pass (at least one)
    n = _edges_reached(edges_xz, e, toe_x_max + toe_pass)
    for i in range(n):
        ex, ez = edges_xz[e + i, 0], edges_xz[e + i, 1]
        dd = _edge_clearance_many(hp, tp, ex, ez, sole, half)
        d = np.inf
        for t in range(H):
            if dd[t] != dd[t]:
                d = np.nan
                break
            d = min(d, dd[t])
        if d == d and abs(d) < np.inf and not d >= pred_edge:
            pred_edge = d
        known = _edge_known(cleared, new, n_new, ex, tol)
        clear = np.empty(H, np.bool_)
        acc = False
        for t in range(H):
            acc = acc or dd[t] >= near_trip
            clear[t] = True if known else acc
        if not known and clear[0]:
            new[n_new] = ex
            n_new += 1
        m = np.inf
        any_ok = False
        for t in range(H):
            if fwd[t] and nxt[t] == e + i and clear[t]:
                if not any_ok:
                    any_ok = True
                if dd[t] != dd[t]:
                    m = np.nan
                elif m == m:
                    m = min(m, dd[t])
        if any_ok and not m >= risk:
            risk = m
    return pred_edge, risk, new[:n_new].copy()


def warm_up(fused: bool = False) -> None:
    """Call the monitor's kernels once on a small input, with the argument types the monitor
    uses: numba loads their machine code (compiles it, on a machine's first run) at a
    kernel's first call, which would otherwise land on the first frames.

    ``fused``: only the kernels a fused monitor (``SafetyMonitor(fused=True)``, the default)
    calls frame by frame: the fused steps (``keyframe_step``, ``frame_terrain``,
    ``swing_prediction``, ``cv_prediction``, ``swing_edge_risk``) and ``foot_clearance``,
    ``window_bins``, ``window_bridged_gap``, ``observe_errors``, ``template_motion``,
    ``edge_summary``, ``contact_caps`` and ``rescan_edges`` (a standing foot's contact
    lowering map bins, height_map.IncrementalHeightMap.add_contact). The kernels of the
    single operations, which it reaches only on rare branches (a non-finite camera), load
    at their first call instead of costing every process ~0.15-0.2 s of CPU. Otherwise
    every kernel."""
    prof = HeightProfile(
        np.array([0.0, 0.005, 0.01]), np.array([0.005, 0.01, 0.015]), np.zeros(3), np.zeros(3)
    )
    heel, toe, v = np.array([-0.2, 0.05]), np.array([0.0, 0.05]), (0.5, 0.0)
    foot_clearance(heel, toe, prof)
    if not fused:
        coverage(heel, toe, prof)
        clearance_many(heel[None], toe[None], prof)
        edge_clearance(heel, toe, np.array([0.01, 0.0]))
        edge_clearance_many(heel[None], toe[None], np.array([0.01, 0.0]))
        predicted_min_clearance(heel, toe, v, 0.3, 10, prof)
        predicted_min_edge_clearance(heel, toe, v, 0.3, 10, np.array([0.01, 0.0]))
        edge_runs(prof, 0.04, 0.15)
    n, used = np.zeros(3, np.int64), np.zeros(3, bool)
    mid, se2, cov = np.zeros(3), np.zeros(3), np.zeros((3, 3))
    Z = np.full((3, 4), np.nan)
    if not fused:
        bins, tops = keyframe_tops(np.zeros((2, 2)), 0.0, 0.0, 0.005, 0.01)
        add_tops(
            Z, Z.copy(), n, used, mid, se2, cov, bins + 1, tops, 1, 1, 0.0, True, np.eye(2),
            np.full(3, np.inf), 0.0, np.full((3, 4), np.inf), view_ceilings(
                np.zeros((2, 2)), 0.0, 0.0, bins, 0.005, tops
            ), 0.01,
        )  # fmt: skip
    window_bins(used, mid, se2, 0, 3, 0, 0.005, 0.0, 0.01, 0.003)
    window_bridged_gap(used, 0, 0.005, 0, 3, 0.0, 0.01, 0.15)
    edge_summary(np.zeros((2, 2)), np.zeros(2))
    contact_caps(
        -0.2, 0.0, 0.0, 0.0, 0.006, 0.04, 0, 1, 0, 0.005, Z, np.full((3, 4), np.inf), n, mid,
        np.full(3, np.inf), 0.01,
    )  # fmt: skip
    observe_errors(
        np.full(2, np.nan), np.zeros(3), np.zeros((2, 3, 4)), 0.0, np.zeros(4), 0.1,
        np.zeros(4), np.zeros(3), np.zeros(3),
    )  # fmt: skip
    phase = np.array([0.0, 0.1, 0.2])
    template_motion(0.05, np.linspace(0.0, 0.3, 11), phase, np.zeros((3, 4)), np.array([0, 3]))
    rescan_edges(
        used, mid, 0, 0.005, 1, 1, 0.04, 0.15, SLOPE_STEP_M, MAX_TRANSITION_BIN_M,
        np.zeros((0, 2)), np.zeros(0), np.zeros(0, np.int64),
    )  # fmt: skip
    if not fused:
        _warm_up_single_operations(used, mid, cov, n)
    z0 = np.zeros(0)
    keyframe_step(
        np.zeros((2, 2)), 0.0, 0.0, np.eye(2), 0.005, 0.01, 0.003, Z, Z.copy(), n, used, mid,
        se2, cov, 0, 1, 1, 0.0, True, np.full(3, np.inf), 0.0, True, 1.0, z0, z0, z0, z0,
        0.04, 0.15, SLOPE_STEP_M,
        MAX_TRANSITION_BIN_M, np.zeros((0, 2)), z0, np.zeros(0, np.int64),
        np.full((3, 4), np.inf), True,
    )  # fmt: skip
    used[:] = True
    n[:] = 1
    frame_terrain(
        used, mid, se2, cov, n, 0, 0.005, np.array([[0.01, 0.0]]), -0.2, 0.05, 0.0, 0.05,
        1e-4, 0.0, 0.0, 1e-4, 0.3, 0.5, True, 0.15, 0.0, 0.003, 0.005, 0.05, 1.0, 1.0, 1.0,
        0.5,
    )  # fmt: skip
    swing_prediction(
        0.05, np.linspace(0.0, 0.3, 11), phase, np.zeros((3, 4)), np.array([0, 3]),
        -0.2, 0.05, 0.0, 0.05, 0.01, 0.3, 0.0, used, mid, se2, 0, 0.005, 0.003,
        np.array([[0.01, 0.0]]), 0, 0.05, 0.03, 0.1, 0.02, 0.01, np.zeros(0), 0.5,
    )  # fmt: skip
    cv_prediction(
        True, -0.3, 0.3, -0.2, 0.05, 0.0, 0.05, 0.5, 0.0, 0.3, 10, used, mid, se2, 0, 0.005,
        0.003, 0.0, np.array([[0.01, 0.0]]), 0, 0.2, 0.05, 0.02, 0.01, 0.1, np.zeros(0), 0.5,
    )  # fmt: skip
    swing_edge_risk(
        heel[None] + np.zeros((3, 1)),
        toe[None] + np.zeros((3, 1)),
        np.array([[0.01, 0.0]]),
        0,
        0.0,
        0.05,
        0.0,
        0.03,
        0.1,
        0.02,
        0.01,
        np.zeros(0),
        0.5,
    )


def _warm_up_single_operations(used, mid, cov, n) -> None:
    """The map and consistency kernels of the single operations (:func:`warm_up`)."""
    bin_below(used, 0, 0.005, 0.01)
    x3 = np.array([0.0, 0.005, 0.01])
    b3 = np.arange(3, dtype=np.int64)
    consistency_squares(b3, x3, x3, x3, x3 + 1.0, b3, cov, n + 1, 0, 0.005, 1.0, 0.0, 0.0, 1.0)
    window_merge(x3, x3[:1], x3)
    profile_x_range(np.zeros((2, 2)), 0.0)


# ---------------------------------------------------------------------------------------------
# the monitor's per-frame step, fused
#
# The kernels below do in one call what SafetyMonitor.update did through several kernels and
# the Python between them (the same operations in the same order). Where the Python code
# takes a square root as ``x ** 0.5`` (the C library's pow), the kernels take ``x ** half``
# with ``half`` = 0.5 passed at run time: a constant exponent lets LLVM replace pow by sqrt,
# which rounds differently in the last bit on about one input in a thousand. Edge and
# segment distances take ``sqrt`` of explicit products in every path (Python, numpy and
# here): those are correctly rounded, so numpy's own ``np.power`` never enters.


@numba.njit(cache=True)
def _psd_abs(mxx, mxz, mzz, scale, half):  # pragma: no cover - compiled
    """online._psd_abs_entries: (xx, xz, zz) of |scale M|, M = [[mxx, mxz], [mxz, mzz]]."""
    a, b, c = scale * mxx, scale * mxz, scale * mzz
    m, r = (a + c) / 2, (((a - c) / 2) ** 2 + b * b) ** half
    l1, l2 = m + r, m - r
    if l2 >= 0:
        return a, b, c
    if r == 0:
        return abs(a), 0.0, abs(c)
    if abs(b) > 1e-30 or abs(l1 - a) > 1e-30:
        vx, vz = b, l1 - a
    else:
        vx, vz = 1.0, 0.0
    nrm = (vx * vx + vz * vz) ** half
    vx, vz = vx / nrm, vz / nrm
    s1, s2 = abs(l1), abs(l2)
    return s1 * vx * vx + s2 * vz * vz, (s1 - s2) * vx * vz, s1 * vz * vz + s2 * vx * vx


@numba.njit(cache=True)
def _relative_cov(cov, n, i0, b, P00, P01, P10, P11, scale, x_factor, half):  # pragma: no cover
    """online.SafetyMonitor._relative_cov of the bin with index ``b``: (xx, xz, zz), m^2."""
    e = b - i0
    c = float(n[e])
    cxx, cxz, czz = cov[e, 0] / c, cov[e, 1] / c, cov[e, 2] / c
    mxz = ((P01 - cxz) + (P10 - cxz)) / 2
    rxx, rxz, rzz = _psd_abs(P00 - cxx, mxz, P11 - czz, scale, half)
    if x_factor != 1.0:
        return rxx * x_factor * x_factor, rxz * x_factor, rzz
    return rxx, rxz, rzz


@numba.njit(cache=True)
def _sigma(nx, nz, cxx, cxz, czz, map_sigma, foot_sigma, half):  # pragma: no cover
    """clearance.clearance_sigma."""
    if not (math.isfinite(nx) and math.isfinite(nz)):
        return np.nan
    var = nx * nx * cxx + 2 * nx * nz * cxz + nz * nz * czz + (map_sigma * nz) ** 2 + foot_sigma**2
    if 0.0 > var:  # max(var, 0.0), NaN kept
        var = 0.0
    return var**half


@numba.njit(cache=True)
def _window_any(used, mid, se2, i0, bin_m, x_min, x_max, map_sigma):  # pragma: no cover
    """height_map.IncrementalHeightMap.window for any bounds (a NaN or infinite one as the
    reference map's searchsorted takes it): (x_lo, x_hi, z, sigma, bin index)."""
    n = used.shape[0]
    if x_min != x_min:  # NaN sorts last: nothing from it on
        return window_bins(used, mid, se2, 0, 0, i0, bin_m, x_min, x_max, map_sigma)
    if x_max != x_max:
        x_max = np.inf
    if math.isfinite(x_min) and math.isfinite(x_max):
        a0 = min(max(np.int64(math.floor(x_min / bin_m)) - 2 - i0, 0), n)
        a1 = min(max(np.int64(math.floor(x_max / bin_m)) + 3 - i0, a0), n)
    else:
        a0, a1 = 0, n
    return window_bins(used, mid, se2, a0, a1, i0, bin_m, x_min, x_max, map_sigma)


@numba.njit(cache=True)
def frame_terrain(
    used,
    mid,
    se2,
    cov,
    n,
    i0,
    bin_m,
    edges_xz,
    hx,
    hz,
    tx,
    tz,
    P00,
    P01,
    P10,
    P11,
    window_m,
    min_coverage,
    unseen_check,
    max_gap,
    sole,
    map_sigma,
    foot_sigma,
    toe_pass,
    pose_w,
    pose_xf,
    map_w,
    half,
):  # pragma: no cover - compiled
    """The first half of online.SafetyMonitor.update for a finite heel (hx, hz) and toe
    (tx, tz): the clearance to the map's bins near the foot (``window_m``; NaN unless
    ``min_coverage`` of the foot's span is mapped), its sigma, and the next edge ahead of
    the toe with the clearance to it, its sigma, the x distance and its sigma. The map:
    its bin arrays (``used``, ``mid``, ``se2``, ``cov`` sums, counts ``n``, bin index ``i0``
    at element 0) and edges (E, 2); ``pose_w``, ``map_w``: the sigma's pose and map weights
    (config times consistency scales), ``pose_xf`` the factor on the pose term's x row and
    column. Returns (clearance, foot x, z, terrain x, z, sigma,
    next edge index or -1, edge clearance, its sigma, edge x distance, its sigma, whether
    the window holds a strip the gap-floor check fills (:func:`window_bridged_gap` over the
    same bins, ``max_gap``; False: online.SafetyMonitor._checked_clearance would return the
    clearance unchanged))."""
    nan = np.nan
    x0, x1 = min(hx, tx) - window_m, max(hx, tx) + window_m
    lo, hi, z, _, bins = _window_any(used, mid, se2, i0, bin_m, x0, x1, map_sigma)
    nb = used.shape[0]  # (the elements _window_any and height_map._elements search)
    a0 = min(max(np.int64(math.floor(x0 / bin_m)) - 2 - i0, 0), nb)
    a1 = min(max(np.int64(math.floor(x1 / bin_m)) + 3 - i0, a0), nb)
    gapped = window_bridged_gap(used, i0, bin_m, a0, a1, x0, x1, max_gap)
    B = z.shape[0]
    c_d = fx = fz = qx = qz = sig = nan
    # coverage of the foot's x span (clearance.coverage)
    xa, xb = min(hx, tx), max(hx, tx)
    cover = 0.0
    if B > 0:
        cover = 1.0 if xb <= xa else _coverage(xa, xb, lo, hi)
    if not cover < min_coverage:
        d, fx, fz, qx, qz, col = _foot_clearance_near(hx, hz, tx, tz, lo, hi, z)
        if unseen_check and d > _unseen_distance(xa, xb, lo, hi, x0, x1, max_gap):
            col = -1  # unseen terrain could be closer than the mapped (clearance.py)
            d = fx = fz = qx = qz = nan
        ddx, ddz = fx - qx, fz - qz
        nrm = math.hypot(ddx, ddz)
        if nrm > 1e-9:
            nx, nz = ddx / nrm, ddz / nrm
        else:
            nx, nz = 0.0, 1.0
        if d < 0:
            if nrm <= 1e-9:
                nx, nz = 0.0, 1.0
            else:
                nx, nz = -nx, -nz
        c_d = d - sole
        if col >= 0:
            b = bins[col]
            rxx, rxz, rzz = _relative_cov(cov, n, i0, b, P00, P01, P10, P11, pose_w, pose_xf, half)
            bs = math.sqrt(se2[b - i0] + map_sigma**2)
            sig = _sigma(nx, nz, rxx, rxz, rzz, map_w * bs, foot_sigma, half)
    # the next edge ahead (clearance.next_edge_index)
    E = edges_xz.shape[0]
    e = -1
    nc = nsig = ed = edsig = nan
    if E > 0:
        v = tx - toe_pass
        a, c = 0, E
        if v != v:
            a = E
        while a < c:
            m = (a + c) // 2
            if edges_xz[m, 0] <= v:
                a = m + 1
            else:
                c = m
        e = a if a < E else -1
    if e >= 0:
        ex, ez = edges_xz[e, 0], edges_xz[e, 1]
        d, qx2, qz2 = _edge_distance(hx, hz, tx, tz, ex, ez, half)
        nrm = math.sqrt((qx2 - ex) * (qx2 - ex) + (qz2 - ez) * (qz2 - ez))
        if nrm > 1e-9:
            nx, nz = (qx2 - ex) / nrm, (qz2 - ez) / nrm
        else:
            nx, nz = 0.0, 1.0
        if d < 0:
            nx, nz = -nx, -nz
        found, kb = bin_below(used, i0, bin_m, ex)
        if not found:
            kb = -1
        rxx, rxz, rzz = _relative_cov(cov, n, i0, kb, P00, P01, P10, P11, pose_w, pose_xf, half)
        nc = d - sole
        bs = math.sqrt(se2[kb - i0] + map_sigma**2)
        nsig = _sigma(nx, nz, rxx, rxz, rzz, map_w * bs, foot_sigma, half)
        ed = ex - tx
        edsig = (rxx + foot_sigma**2 + (bin_m / 2) ** 2) ** half
    return c_d, fx, fz, qx, qz, sig, e, nc, nsig, ed, edsig, gapped


@numba.njit(cache=True)
def swing_prediction(
    tau,
    h,
    phase,
    disp,
    starts,
    hx,
    hz,
    tx,
    tz,
    c_d,
    window_m,
    sole,
    used,
    mid,
    se2,
    i0,
    bin_m,
    map_sigma,
    edges_xz,
    e,
    toe_pass,
    dt,
    min_fwd,
    near_trip,
    tol,
    cleared,
    half,
):  # pragma: no cover - compiled
    """The swing-template branch of online.SafetyMonitor.update in one call: the template
    motion from phase ``tau`` over the horizon instants ``h`` (:func:`template_motion`),
    the minimum clearance of the predicted poses to the bins they can reach (NaN when the
    current clearance ``c_d`` is), and :func:`swing_edge_risk` against the edges from the
    next one (index ``e``). Returns (predicted clearance, predicted edge clearance,
    near-trip clearance, the x of the edges newly cleared, the motion (H, 4), the predicted
    poses (H, 4: heel x, z, toe x, z)); the last two for the prediction check
    (online.SafetyMonitor._trusted_risk), which would otherwise compute them again."""
    motion = template_motion(tau, h, phase, disp, starts)
    H = motion.shape[0]
    hp, tp = np.empty((H, 2)), np.empty((H, 2))
    poses = np.empty((H, 4))
    m_lo, m_hi = np.empty(4), np.empty(4)
    for c in range(4):  # motion.min / max over the poses, NaN propagated
        lo_c = hi_c = motion[0, c]
        for i in range(1, H):
            v = motion[i, c]
            if v != v or lo_c != lo_c:
                lo_c = hi_c = np.nan
            else:
                lo_c, hi_c = min(lo_c, v), max(hi_c, v)
        m_lo[c], m_hi[c] = lo_c, hi_c
    for i in range(H):
        hp[i, 0], hp[i, 1] = hx + motion[i, 0], hz + motion[i, 1]
        tp[i, 0], tp[i, 1] = tx + motion[i, 2], tz + motion[i, 3]
        poses[i, 0], poses[i, 1] = hp[i, 0], hp[i, 1]
        poses[i, 2], poses[i, 3] = tp[i, 0], tp[i, 1]
    toe_x_max = tx + m_hi[2]
    pred = np.nan
    if math.isfinite(c_d):
        a, b = hx + m_lo[0], tx + m_lo[2]
        lo_x = b if b < a else a  # Python's min / max: the first unless the second wins
        a = hx + m_hi[0]
        hi_x = toe_x_max if toe_x_max > a else a
        # online.SafetyMonitor._swept
        d = c_d + sole
        if 0.0 > d:
            d = 0.0
        d += 1e-6
        s_lo, s_hi = lo_x - window_m, hi_x + window_m
        a, b = lo_x - d, hi_x + d
        x_min = a if a > s_lo else s_lo
        x_max = b if b < s_hi else s_hi
        lo, hi, z, _, _ = _window_any(used, mid, se2, i0, bin_m, x_min, x_max, map_sigma)
        if z.shape[0] > 0:
            dd = _clearance_many_near(hp, tp, lo, hi, z, sole)
            pred = dd[0]
            for i in range(1, H):  # np.min: NaN propagates
                if dd[i] != dd[i] or pred != pred:
                    pred = np.nan
                    break
                pred = min(pred, dd[i])
    pred_edge, risk, new = swing_edge_risk(
        hp, tp, edges_xz, e, toe_x_max, toe_pass, sole, dt, min_fwd, near_trip, tol, cleared, half
    )
    return pred, pred_edge, risk, new, motion, poses


@numba.njit(cache=True)
def keyframe_step(
    rel,
    cam_x,
    cam_z,
    P,
    bin_m,
    top_band,
    map_sigma,
    Z,
    Zs,
    n,
    used,
    mid,
    se2,
    cov,
    i0,
    min_keyframes,
    agree_keyframes,
    agree_m,
    median,
    zcap,
    max_excess,
    test,
    pose_scale,
    pose_sorted,
    pose_old,
    map_sorted,
    map_old,
    min_rise,
    max_gap,
    slope_step,
    max_bin,
    edge_xz,
    edge_rise,
    edge_first,
    U,
    ceilings,
):  # pragma: no cover - compiled
    """A keyframe (``rel`` (N, 2) camera-relative, camera at the finite (cam_x, cam_z),
    covariance ``P``) tested against the map and joining it, in one call: what
    online.SafetyMonitor._add_keyframe_compiled does with :func:`keyframe_tops`,
    :func:`profile_x_range`, :func:`window_bins`, :func:`consistency_squares`,
    :func:`window_merge` (both scales), :func:`add_tops` and :func:`rescan_edges`, the same
    operations in the same order. The map's arrays are updated in place. ``test``: the
    consistency test is on; ``pose_scale``: the config's ``relative_pose_scale``;
    ``*_sorted``: each scale's sorted window, ``*_old``: the values leaving it (the oldest
    keyframe's when it is full, else empty).

    Returns (status, first bin, last bin, pose values, pose window, map values, map window,
    edges xz, rise, first bin): status 0: no finite point (nothing changed); 1: the bins
    [first, last] fall outside the arrays (nothing changed: grow them and call again); 2:
    done. The values of a scale are empty when the keyframe gave it none (window unchanged).
    ``U``: the map's view ceilings (updated in place), ``ceilings``: the map's
    view_ceilings flag (False: this keyframe's are +inf).
    """
    none = np.zeros(0)
    bins, tops = keyframe_tops(rel, cam_x, cam_z, bin_m, top_band)
    B = n.shape[0]
    if bins.shape[0] == 0:
        return 0, 0, 0, none, pose_sorted, none, map_sorted, edge_xz, edge_rise, edge_first
    b_lo, b_hi = bins[0], bins[bins.shape[0] - 1]
    if B == 0 or b_lo < i0 or b_hi >= i0 + B:
        return 1, b_lo, b_hi, none, pose_sorted, none, map_sorted, edge_xz, edge_rise, edge_first
    pose_q, map_q = none, none
    pose_new, map_new = pose_sorted, map_sorted
    if test:  # the keyframe against the map's bins under it, before it joins
        x_lo, x_hi = profile_x_range(rel, cam_x)
        w_lo, _, w_z, w_sig, w_bins = _window_any(used, mid, se2, i0, bin_m, x_lo, x_hi, map_sigma)
        if w_z.shape[0] > 0:
            hit, offset, mad_sd, med_zz, m, sq = consistency_squares(
                bins, tops, w_lo, w_z, w_sig, w_bins, cov, n, i0, bin_m,
                P[0, 0], P[0, 1], P[1, 0], P[1, 1],
            )  # fmt: skip
            if hit:
                v_offset = pose_scale * med_zz + (1.2533 * mad_sd) ** 2 / m
                if math.isfinite(offset) and math.isfinite(v_offset) and v_offset > 0:
                    pose_q = np.empty(1)
                    pose_q[0] = offset * offset / v_offset
                    pose_new = window_merge(pose_sorted, pose_old, pose_q)
                if sq.shape[0] > 0:
                    map_q = sq
                    map_new = window_merge(map_sorted, map_old, sq)
    if ceilings:
        ceil = view_ceilings(rel, cam_x, cam_z, bins, bin_m, tops)
    else:
        ceil = np.full(bins.shape[0], np.inf)
    add_tops(
        Z, Zs, n, used, mid, se2, cov, bins - i0, tops, min_keyframes, agree_keyframes, agree_m,
        median, P, zcap, max_excess, U, ceil, top_band,
    )  # fmt: skip
    e_xz, e_rise, e_first = rescan_edges(
        used, mid, i0, bin_m, b_lo - i0, b_hi - i0, min_rise, max_gap, slope_step, max_bin,
        edge_xz, edge_rise, edge_first,
    )  # fmt: skip
    return 2, b_lo, b_hi, pose_q, pose_new, map_q, map_new, e_xz, e_rise, e_first


@numba.njit(cache=True)
def cv_prediction(
    swept,
    x_min,
    x_max,
    hx,
    hz,
    tx,
    tz,
    vx,
    vz,
    horizon,
    steps,
    used,
    mid,
    se2,
    i0,
    bin_m,
    map_sigma,
    sole,
    edges_xz,
    e,
    reach_x,
    toe_pass,
    near_trip,
    tol,
    min_fwd,
    cleared,
    half,
):  # pragma: no cover - compiled
    """The constant-velocity branch of online.SafetyMonitor.update in one call: with
    ``swept``, the minimum clearance over the horizon (:func:`predicted_min_clearance`) to
    the bins over [x_min, x_max] (else NaN); then, over the edges from the next one (index
    ``e``) to the last the toe reaches (x up to ``reach_x`` plus ``toe_pass``; at least
    one), the minimum of :func:`predicted_min_edge_clearance` and the near-trip candidates'
    minimum: the edges the foot is clear of now (``_approach_now`` against ``cleared``,
    within ``tol``) while the toe moves forward (``forward_motion``). Returns (predicted
    clearance, predicted edge clearance, near-trip clearance, the x of the edges newly
    cleared)."""
    pred = np.nan
    v_ok = math.isfinite(vx) and math.isfinite(vz)
    if swept:
        lo, hi, z, _, _ = _window_any(used, mid, se2, i0, bin_m, x_min, x_max, map_sigma)
        if z.shape[0] > 0 and v_ok:
            pred = _predicted_min(hx, hz, tx, tz, vx, vz, horizon, steps, lo, hi, z, sole)
    E = edges_xz.shape[0]
    pred_edge = np.nan
    risk = np.nan
    new = np.empty(max(E - max(e, 0), 0))
    n_new = 0
    if e < 0:
        return pred, pred_edge, risk, new[:0]
    n = _edges_reached(edges_xz, e, reach_x + toe_pass)  # online.SafetyMonitor._edges_reached
    fwd = v_ok and vx > min_fwd and vz > -vx
    for i in range(n):
        ex, ez = edges_xz[e + i, 0], edges_xz[e + i, 1]
        d = np.nan
        if v_ok:
            d = _predicted_min_edge(hx, hz, tx, tz, vx, vz, horizon, ex, ez, half) - sole
        if math.isfinite(d) and not d >= pred_edge:
            pred_edge = d
        # the clearance to the edge now (edge_clearance_many of the current pose)
        now = _edge_distance(hx, hz, tx, tz, ex, ez, half)[0] - sole
        known = _edge_known(cleared, new, n_new, ex, tol)
        if not known and now >= near_trip:
            new[n_new] = ex
            n_new += 1
            known = True
        if known and fwd and math.isfinite(d) and not d >= risk:
            risk = d
    return pred, pred_edge, risk, new[:n_new].copy()
