"""Foot-to-terrain geometry (pure: arrays in, numbers out; no state, no I/O).

The terrain is a *height field* of x bins (:class:`HeightProfile`): bin ``i`` is the solid
column ``[x_lo_i, x_hi_i] x (-inf, z_i]`` (world x-z, metres). The online map
(vio_graph/safety/online.py) and the true terrain (:meth:`HeightProfile.from_polyline`, the
simulator's profile) use the same representation, so estimate and truth go through the same
functions.

The foot is the heel-toe segment (the rig's heel and toe contact points); the sole's thickness
is subtracted from the distance. Definitions (docs/method.md, "Foot-to-terrain safety"):

- clearance: signed distance from the foot segment to the union of the columns minus the sole
  thickness (negative: the foot is inside the terrain);
- nosing clearance: signed distance from the foot segment to the next edge ahead (the first
  edge with x beyond the toe minus ``toe_pass_m``: the edge the toe is about to cross or
  crossing), negative when the edge is above the foot's line;
- placement: x distances of heel and toe to the nosing and the back edge of the tread under
  the foot, positive on the tread's side of the edge.
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import dataclass
from statistics import NormalDist

import numpy as np
from numpy.typing import ArrayLike, NDArray

#: bins closer than this (m) are contiguous (their bounds are products of the bin size)
UNSEEN_TOLERANCE_M = 1e-9


@dataclass(frozen=True)
class HeightProfile:
    """Known terrain as x bins sorted by x: ``x_lo_m``, ``x_hi_m``, ``z_m`` (B,) and the
    1-sigma of each bin's height ``sigma_m`` (B,), metres."""

    x_lo_m: NDArray[np.float64]
    x_hi_m: NDArray[np.float64]
    z_m: NDArray[np.float64]
    sigma_m: NDArray[np.float64]

    def __len__(self) -> int:
        return int(self.z_m.shape[0])

    @classmethod
    def from_polyline(cls, profile_xz_m: ArrayLike, max_bin_m: float = 0.005) -> HeightProfile:
        """The height field under a polyline (P, 2), x non-decreasing, risers vertical:
        one bin per level segment, sloped segments cut into bins of at most ``max_bin_m``."""
        p = np.asarray(profile_xz_m, dtype=float)
        if p.ndim != 2 or p.shape[1] != 2 or p.shape[0] < 2:
            raise ValueError(f"profile_xz_m must have shape (P>=2, 2), got {p.shape}")
        if np.any(np.diff(p[:, 0]) < -1e-9):
            raise ValueError("profile_xz_m must have non-decreasing x")
        lo, hi, z = [], [], []
        for (x0, z0), (x1, z1) in zip(p[:-1], p[1:], strict=True):
            if x1 - x0 <= 1e-12:
                continue  # a riser: the columns either side carry it
            n = 1 if abs(z1 - z0) < 1e-12 else int(np.ceil((x1 - x0) / max_bin_m))
            edges = np.linspace(x0, x1, n + 1)
            lo += list(edges[:-1])
            hi += list(edges[1:])
            zc = z0 + (z1 - z0) * ((edges[:-1] + edges[1:]) / 2 - x0) / (x1 - x0)
            z += list(zc)
        a = np.asarray
        return cls(a(lo, float), a(hi, float), a(z, float), np.zeros(len(z)))

    def window(self, x_min_m: float, x_max_m: float) -> HeightProfile:
        """The bins overlapping [x_min_m, x_max_m]."""
        i0 = int(np.searchsorted(self.x_hi_m, x_min_m, side="left"))
        i1 = int(np.searchsorted(self.x_lo_m, x_max_m, side="right"))
        s = slice(i0, max(i0, i1))
        return HeightProfile(self.x_lo_m[s], self.x_hi_m[s], self.z_m[s], self.sigma_m[s])


@dataclass(frozen=True)
class Clearance:
    """Signed distance (m) from the foot to the terrain, the closest foot and terrain points
    (world x-z, m), the bin index of the terrain point and the unit direction from the terrain
    point to the foot (the gradient of the distance by the foot position)."""

    distance_m: float
    foot_xz_m: NDArray[np.float64]
    terrain_xz_m: NDArray[np.float64]
    bin: int
    normal_xz: NDArray[np.float64]


NO_CLEARANCE = Clearance(
    float("nan"), np.full(2, np.nan), np.full(2, np.nan), -1, np.full(2, np.nan)
)


def _point_to_columns(p: NDArray[np.float64], prof: HeightProfile):
    """Signed distance (B,) from point ``p`` (2,) to each column and the closest column
    points (B, 2): outside, the Euclidean distance; inside, minus the distance to the nearest
    way out of the terrain (to the nearest point of a column top above the point, or sideways
    to where the terrain is lower than the point, into an unmapped gap between bins, or past
    the known bins' ends), set on the column holding the point."""
    px, pz = float(p[0]), float(p[1])
    cx = np.minimum(np.maximum(px, prof.x_lo_m), prof.x_hi_m)
    cz = np.minimum(pz, prof.z_m)
    d = np.hypot(px - cx, pz - cz)
    inside = (px >= prof.x_lo_m) & (px <= prof.x_hi_m) & (pz < prof.z_m)
    if not inside.any():
        return d, np.stack([cx, cz], axis=1)
    k = int(np.flatnonzero(inside)[0])
    low = prof.z_m <= pz
    # an unmapped gap between bins is a way out too: its terrain is not known to hold the
    # point in (a foot placed a few cm behind the hidden strip of a nosing is not 10 cm deep)
    gap = prof.x_lo_m[1:] > prof.x_hi_m[:-1] + UNSEEN_TOLERANCE_M
    gap_lo, gap_hi = prof.x_hi_m[:-1][gap], prof.x_lo_m[1:][gap]
    left = np.concatenate(
        [prof.x_hi_m[low & (prof.x_hi_m <= px)], gap_hi[gap_hi <= px], [prof.x_lo_m[0]]]
    )
    right = np.concatenate(
        [prof.x_lo_m[low & (prof.x_lo_m >= px)], gap_lo[gap_lo >= px], [prof.x_hi_m[-1]]]
    )
    xl, xr = float(left.max()), float(right.min())
    # up: the nearest point on the tops of the columns higher than the point
    high = np.flatnonzero(prof.z_m > pz)
    tx = np.minimum(np.maximum(px, prof.x_lo_m[high]), prof.x_hi_m[high])
    up = np.hypot(tx - px, prof.z_m[high] - pz)
    j = int(np.argmin(up))
    depth = [float(up[j]), px - xl, xr - px]
    way = int(np.argmin(depth))
    d = np.where(inside, np.inf, d)
    d[k] = -depth[way]
    cx[k], cz[k] = [(float(tx[j]), float(prof.z_m[high[j]])), (xl, pz), (xr, pz)][way]
    return d, np.stack([cx, cz], axis=1)


def _corners_to_segment(
    a: NDArray[np.float64], b: NDArray[np.float64], corners: NDArray[np.float64]
):
    """Signed distance (C,) from points ``corners`` (C, 2) to segment a-b and the closest
    segment points (C, 2); negative when the corner lies above the segment within its x span
    (the terrain pokes through the foot): minus the smaller of the lift and the slide that
    would free it."""
    ab = b - a
    L2 = float(ab @ ab)
    s = (
        np.zeros(len(corners))
        if L2 == 0
        else np.minimum(np.maximum(((corners - a) @ ab) / L2, 0.0), 1.0)
    )
    q = a[None] + s[:, None] * ab[None]
    d = np.hypot(*(corners - q).T)
    x0, x1 = min(a[0], b[0]), max(a[0], b[0])
    if x1 - x0 > 1e-12:
        z_line = a[1] + (corners[:, 0] - a[0]) * ab[1] / ab[0]
        above = (corners[:, 0] > x0) & (corners[:, 0] < x1) & (corners[:, 1] > z_line)
        # the way out: lift the foot, or slide it until the corner leaves its x span
        depth = np.minimum(
            corners[:, 1] - z_line, np.minimum(corners[:, 0] - x0, x1 - corners[:, 0])
        )
        d = np.where(above, -depth, d)
    return d, q


def foot_clearance(
    heel_xz_m: ArrayLike, toe_xz_m: ArrayLike, prof: HeightProfile, sole_thickness_m: float = 0.0
) -> Clearance:
    """Signed distance (m) from the heel-toe segment, thickened by the sole, to the terrain.

    Exact for separated shapes (the distance between a segment and a convex column is reached
    at a vertex of one of them: heel or toe against the column, or a column top corner against
    the segment); when they overlap, minus the deepest penetration of those vertices.
    NaN (:data:`NO_CLEARANCE`) when ``prof`` is empty.
    """
    if len(prof) == 0:
        return NO_CLEARANCE
    a = np.asarray(heel_xz_m, dtype=float)
    b = np.asarray(toe_xz_m, dtype=float)
    B = len(prof)
    dh, ch = _point_to_columns(a, prof)
    dt, ct = _point_to_columns(b, prof)
    corners = np.concatenate(
        [np.stack([prof.x_lo_m, prof.z_m], 1), np.stack([prof.x_hi_m, prof.z_m], 1)]
    )
    dc, qc = _corners_to_segment(a, b, corners)
    d_all = np.concatenate([dh, dt, dc])
    k = int(np.argmin(d_all))
    if k < B:
        foot, terr, col = a, ch[k], k
    elif k < 2 * B:
        foot, terr, col = b, ct[k - B], k - B
    else:
        foot, terr, col = qc[k - 2 * B], corners[k - 2 * B], (k - 2 * B) % B
    dist = float(d_all[k])
    diff = foot - terr
    n = float(np.hypot(*diff))
    normal = diff / n if n > 1e-9 else np.array([0.0, 1.0])
    if dist < 0:
        normal = np.array([0.0, 1.0]) if n <= 1e-9 else -normal
    return Clearance(
        dist - sole_thickness_m,
        np.asarray(foot, float).copy(),
        np.asarray(terr, float).copy(),
        col,
        normal,
    )


def edge_clearance(
    heel_xz_m: ArrayLike, toe_xz_m: ArrayLike, edge_xz_m: ArrayLike, sole_thickness_m: float = 0.0
) -> Clearance:
    """Signed distance (m) from the foot segment to one edge point (2,) (negative when the
    edge is above the foot's line within its x span), minus the sole thickness."""
    ax, az = (float(v) for v in np.asarray(heel_xz_m, dtype=float))
    bx, bz = (float(v) for v in np.asarray(toe_xz_m, dtype=float))
    ex, ez = (float(v) for v in np.asarray(edge_xz_m, dtype=float))
    d, qx, qz = _edge_distance(ax, az, bx, bz, ex, ez)
    n = math.sqrt((qx - ex) * (qx - ex) + (qz - ez) * (qz - ez))
    nx, nz = ((qx - ex) / n, (qz - ez) / n) if n > 1e-9 else (0.0, 1.0)
    if d < 0:
        nx, nz = -nx, -nz
    return Clearance(
        d - sole_thickness_m, np.array([qx, qz]), np.array([ex, ez]), -1, np.array([nx, nz])
    )


#: :func:`edge_runs`: a bin pair whose height changes by more than this is part of a riser, m
SLOPE_STEP_M = 0.004
#: :func:`edge_runs`: widest bin inside a transition, and the x span that joins two, m
MAX_TRANSITION_BIN_M = 0.03


@dataclass(frozen=True)
class Edges:
    """Risers / edges of a height field: the edge point (E, 2) on the upper side of the
    height change (a stair nosing, an obstacle's top edge) and the signed rise (E,) (+ up
    in +x), metres."""

    xz_m: NDArray[np.float64]
    rise_m: NDArray[np.float64]

    def __len__(self) -> int:
        return int(self.rise_m.shape[0])

    def summary(self) -> tuple[int, float, float]:
        """(number of edges, mean |rise| m, mean spacing between consecutive edges m)."""
        n = len(self)
        # np.mean is np.add.reduce / n: the same numbers without its per-call set-up
        rise = float(np.add.reduce(np.abs(self.rise_m))) / n if n else float("nan")
        x = self.xz_m[:, 0]
        tread = float(np.add.reduce(x[1:] - x[:-1])) / (n - 1) if n >= 2 else float("nan")
        return n, rise, tread


def edge_runs(
    prof: HeightProfile,
    min_rise_m: float,
    max_gap_m: float,
    slope_step_m: float = SLOPE_STEP_M,
    max_transition_bin_m: float = MAX_TRANSITION_BIN_M,
) -> tuple[Edges, NDArray[np.int64]]:
    """Height changes of at least ``min_rise_m`` between consecutive known bins.

    Consecutive bin pairs whose height changes by more than ``slope_step_m`` with the same
    sign form one transition (a smoothed nosing spreads over a few bins); pairs more than
    ``max_gap_m`` apart are not connected, and a bin wider than ``max_transition_bin_m`` (a
    tread of the exact profile) ends the transition; two transitions of the same sign at most
    ``max_transition_bin_m`` apart are one (a riser with a noisy bin in it). The edge sits at
    the transition's largest jump, on its upper side, at the height of the transition's top.

    Also returns, per edge, the index of the first bin of its transition (E,): the scan is
    left to right, so the incremental map (safety/height_map.py) re-runs it on the changed
    part of a map only.
    """
    n = len(prof)
    if n < 2:
        return Edges(np.zeros((0, 2)), np.zeros(0)), np.zeros(0, np.int64)
    dz = np.diff(prof.z_m)
    gap = prof.x_lo_m[1:] - prof.x_hi_m[:-1]
    step = np.where(gap <= max_gap_m, np.sign(dz) * (np.abs(dz) > slope_step_m), 0)
    runs: list[list[int]] = []  # [first pair, last pair, sign]
    width = (prof.x_hi_m - prof.x_lo_m).tolist()
    nz = np.flatnonzero(step).tolist()  # only the changing pairs are visited
    step_l = step.tolist()
    p = 0
    while p < len(nz):
        i = j = nz[p]
        s = int(step_l[i])
        p += 1
        while j + 1 < n - 1 and step_l[j + 1] == s and width[j + 1] <= max_transition_bin_m:
            j += 1
            p += 1
        # a riser interrupted by a bin or two of noise: continue the previous run
        if (
            runs
            and runs[-1][2] == s
            and prof.x_hi_m[i] - prof.x_lo_m[runs[-1][1] + 1] <= max_transition_bin_m
        ):
            runs[-1][1] = j
        else:
            runs.append([i, j, s])
    out_xz, out_rise, out_first = [], [], []
    for i, j, s in runs:
        rise = float(prof.z_m[j + 1] - prof.z_m[i])
        if abs(rise) < min_rise_m:
            continue
        k = i + int(np.argmax(np.abs(dz[i : j + 1]) * (np.sign(dz[i : j + 1]) == s)))
        if s > 0:  # rising in +x: nosing at the left end of the upper bin
            out_xz.append((prof.x_lo_m[k + 1], prof.z_m[j + 1]))
        else:  # falling: nosing at the right end of the upper bin
            out_xz.append((prof.x_hi_m[k], prof.z_m[i]))
        out_rise.append(rise)
        out_first.append(i)
    first = np.asarray(out_first, np.int64)
    if not out_xz:
        return Edges(np.zeros((0, 2)), np.zeros(0)), first
    return Edges(np.asarray(out_xz, float), np.asarray(out_rise, float)), first


def find_edges(
    prof: HeightProfile,
    min_rise_m: float,
    max_gap_m: float,
    slope_step_m: float = SLOPE_STEP_M,
    max_transition_bin_m: float = MAX_TRANSITION_BIN_M,
) -> Edges:
    """The edges of :func:`edge_runs` (height changes of at least ``min_rise_m``)."""
    return edge_runs(prof, min_rise_m, max_gap_m, slope_step_m, max_transition_bin_m)[0]


def next_edge_index(edges: Edges, x_m: float) -> int:
    """Index of the first edge with x beyond ``x_m`` (-1 if none)."""
    if len(edges) == 0:
        return -1
    k = int(np.searchsorted(edges.xz_m[:, 0], x_m, side="right"))
    return k if k < len(edges) else -1


def next_edge_indices(edges: Edges, x_m: ArrayLike) -> NDArray[np.int64]:
    """:func:`next_edge_index` for many x (m) at once -> (N,) indices, -1 where none."""
    x = np.asarray(x_m, dtype=float)
    if len(edges) == 0:
        return np.full(x.shape, -1, np.int64)
    k = np.searchsorted(edges.xz_m[:, 0], x, side="right").astype(np.int64)
    return np.where(k < len(edges), k, -1)


@dataclass(frozen=True)
class Placement:
    """Where the foot stands on its tread: x distances (m) of heel and toe to the tread's
    nosing and back edge, positive on the tread's side (NaN where the edge is unknown)."""

    heel_to_nosing_m: float
    toe_to_nosing_m: float
    heel_to_back_m: float
    toe_to_back_m: float

    def as_array(self) -> NDArray[np.float64]:
        return np.array(
            [self.heel_to_nosing_m, self.toe_to_nosing_m, self.heel_to_back_m, self.toe_to_back_m]
        )


NO_PLACEMENT = Placement(*(float("nan"),) * 4)


def placement_on_tread(
    heel_xz_m: ArrayLike,
    toe_xz_m: ArrayLike,
    prof: HeightProfile,
    tolerance_m: float,
    max_gap_m: float,
    min_rise_m: float,
) -> Placement:
    """Placement of the foot on the tread it stands on.

    The tread is the run of known bins within ``tolerance_m`` of the bin under the foot's x
    span whose height is nearest the sole's (the lower of heel and toe): the surface the foot
    rests on (a heel overhanging a nosing stands on the upper tread). At each end, the next
    known bin (within ``max_gap_m``) decides: lower by ``min_rise_m`` or more -> that end is
    the nosing, higher -> the back edge (riser of the next step up); no such bin -> unknown.
    A drop followed (gaps within ``max_gap_m``) by a bin higher than the tread by
    ``min_rise_m`` is a back edge at that bin: the lower bins are terrain seen under the next
    tread through an open riser (or a gap in the tread), not a nosing.
    """
    if len(prof) == 0:
        return NO_PLACEMENT
    heel = np.asarray(heel_xz_m, dtype=float)
    toe = np.asarray(toe_xz_m, dtype=float)
    xa, xb = min(heel[0], toe[0]), max(heel[0], toe[0])
    under = np.flatnonzero((prof.x_hi_m >= xa) & (prof.x_lo_m <= xb))
    if under.size == 0:
        return NO_PLACEMENT
    z_sole = min(heel[1], toe[1])  # the foot rests on the surface nearest its sole
    z_top = prof.z_m[under][np.argmin(np.abs(prof.z_m[under] - z_sole))]
    top = under[np.abs(prof.z_m[under] - z_top) <= tolerance_m]
    mid = (prof.x_lo_m[top] + prof.x_hi_m[top]) / 2
    c = int(top[np.argmin(np.abs(mid - (xa + xb) / 2))])
    z0 = prof.z_m[c]
    n = len(prof)

    def end(i: int, direction: int) -> float:
        """x of bin ``i``'s end facing ``direction`` (m)."""
        return prof.x_hi_m[i] if direction > 0 else prof.x_lo_m[i]

    def gap(i: int, j: int) -> float:
        """Free x between bin ``i`` and its neighbour ``j`` on either side (m)."""
        return prof.x_lo_m[j] - prof.x_hi_m[i] if j > i else prof.x_lo_m[i] - prof.x_hi_m[j]

    def extend(direction: int) -> tuple[float, int]:
        """(boundary x, -1 lower / +1 higher / 0 unknown neighbour) in ``direction``."""
        i = c
        while True:
            j = i + direction
            x_b = end(i, direction)
            if j < 0 or j >= n or gap(i, j) > max_gap_m:
                return x_b, 0
            dz = prof.z_m[j] - z0
            if abs(dz) <= tolerance_m:
                i = j
                continue
            # a gradual transition: look past intermediate bins for the full rise
            k, kind = j, 0
            while 0 <= k < n and abs(prof.z_m[k] - z0) < min_rise_m and abs(k - j) < 5:
                k += direction
            if 0 <= k < n and abs(prof.z_m[k] - z0) >= min_rise_m:
                kind = 1 if prof.z_m[k] > z0 else -1
            if kind == -1:
                # a drop followed, within the window, by terrain higher than the tread is no
                # nosing: the lower bins are what a low camera saw *under* the next tread
                # (open risers) or a gap in this one; the tread ends where the rise starts
                m = k
                while 0 <= m + direction < n and gap(m, m + direction) <= max_gap_m:
                    m += direction
                    if prof.z_m[m] - z0 >= min_rise_m:
                        return end(m, -direction), 1
            return x_b, kind

    x_left, k_left = extend(-1)
    x_right, k_right = extend(+1)
    nosing = back = None  # (x, sign): distance = sign * (p_x - x)
    if k_left == -1 and k_right != -1:
        nosing = (x_left, 1.0)
    elif k_right == -1 and k_left != -1:
        nosing = (x_right, -1.0)
    elif k_left == -1 and k_right == -1:
        nosing = (x_right, -1.0)  # a platform: the nosing ahead
    if k_right == 1 and (nosing is None or nosing[1] > 0):
        back = (x_right, -1.0)
    elif k_left == 1 and (nosing is None or nosing[1] < 0):
        back = (x_left, 1.0)

    def dist(edge: tuple[float, float] | None, p: NDArray[np.float64]) -> float:
        return float("nan") if edge is None else float(edge[1] * (p[0] - edge[0]))

    return Placement(dist(nosing, heel), dist(nosing, toe), dist(back, heel), dist(back, toe))


def clearance_sigma(
    normal_xz: NDArray[np.float64],
    cov_relative_m2: NDArray[np.float64] | Sequence[Sequence[float]],
    map_sigma_m: float,
    foot_sigma_m: float,
) -> float:
    """Linearised 1-sigma (m) of a clearance: the foot-minus-terrain position covariance
    (2, 2) projected on the distance's gradient ``normal_xz``, plus the terrain height's
    sigma along the normal's vertical part and the foot-outline sigma."""
    nx, nz = float(normal_xz[0]), float(normal_xz[1])
    if not (math.isfinite(nx) and math.isfinite(nz)):
        return float("nan")
    C = cov_relative_m2
    var = (
        nx * nx * float(C[0][0])
        + 2 * nx * nz * float(C[0][1])
        + nz * nz * float(C[1][1])
        + (map_sigma_m * nz) ** 2
        + foot_sigma_m**2
    )
    return max(var, 0.0) ** 0.5


#: the mass of a Gaussian within 1 sigma of its mean (erf(1 / sqrt 2))
ONE_SIGMA_MASS = math.erf(1.0 / math.sqrt(2.0))
_STD_NORMAL = NormalDist()


def non_penetrating(
    clearance_m: float, sigma_m: float, contact_sigma_m: float = math.inf
) -> tuple[float, float]:
    """The clearance and its 1-sigma given that the foot is never inside the terrain.

    With the computed clearance ``c`` and its sigma ``s`` as a Gaussian N(c, s^2) for the
    true clearance, and the true clearance >= 0 (a foot is never inside the ground), the
    posterior is that Gaussian truncated at 0. Its most probable value is ``max(c, 0)``; for
    ``c < 0`` the 1-sigma returned is the width ``q`` of [0, q], which holds the same share
    of the truncated posterior as +-1 sigma of a Gaussian (0.683):
    ``Phi((q - c) / s) = 1 - (1 - 0.683) Q(-c / s)``, ``Q`` the upper tail. At ``c = 0``
    this is ``s``; it falls like ``1.15 s^2 / |c|`` as the penetration grows. A clamped
    clearance reports the foot in contact; ``contact_sigma_m`` bounds its sigma by that of a
    contact (the monitor passes the foot outline's, ``safety.foot_sigma_m``, for
    ``non_penetration_sigma: contact``). For ``c >= 0`` (or NaN / a non-positive sigma) both
    are returned unchanged (m)."""
    c, s = float(clearance_m), float(sigma_m)
    if not c < 0.0:  # (NaN stays NaN)
        return c, s
    if not s > 0.0:
        return 0.0, s
    a = min(-c / s, 30.0)  # the penetration in sigmas (beyond 30 the tail underflows)
    tail = 0.5 * math.erfc(a / math.sqrt(2.0))  # Q(a)
    q = s * (-_STD_NORMAL.inv_cdf((1.0 - ONE_SIGMA_MASS) * tail) - a)
    return 0.0, min(q, float(contact_sigma_m))


def coverage(heel_xz_m: ArrayLike, toe_xz_m: ArrayLike, prof: HeightProfile) -> float:
    """Share (0-1) of the foot's x span under which the terrain is known."""
    xa = min(float(np.asarray(heel_xz_m)[0]), float(np.asarray(toe_xz_m)[0]))
    xb = max(float(np.asarray(heel_xz_m)[0]), float(np.asarray(toe_xz_m)[0]))
    if len(prof) == 0 or xb <= xa:
        return 0.0 if len(prof) == 0 else 1.0
    ov = np.minimum(prof.x_hi_m, xb) - np.maximum(prof.x_lo_m, xa)
    return float(np.sum(np.maximum(ov, 0.0)) / (xb - xa))


def unseen_distance(
    x_a_m: float,
    x_b_m: float,
    prof: HeightProfile,
    x_min_m: float,
    x_max_m: float,
    max_gap_m: float = 0.0,
) -> float:
    """Horizontal distance (m) from the foot's x span [``x_a_m``, ``x_b_m``] to the nearest x
    in [``x_min_m``, ``x_max_m``] that the bins of ``prof`` leave unseen, from the heel
    forward (x >= ``x_a_m``: the foot walks forward, out of the terrain behind it); inf if
    none. Gaps between bins up to ``max_gap_m`` wide count as seen (the strip a nosing hides
    from a camera above it, bridged like the edges are); the window beyond the first and last
    bin does not. Terrain the map has not seen can be anywhere in height, so it can come no
    closer to the foot than this: a clearance larger than it is not known."""
    gap = math.inf
    edge = float(x_min_m)  # the x up to which the bins so far cover the window
    first = True
    for lo, hi in zip(prof.x_lo_m.tolist(), prof.x_hi_m.tolist(), strict=True):
        if lo > max(edge, x_a_m) + UNSEEN_TOLERANCE_M and (first or lo - edge > max_gap_m):
            gap = min(gap, max(0.0, edge - x_b_m))  # (edge, lo) is unseen
        edge, first = max(edge, hi), False
    if edge < x_max_m - UNSEEN_TOLERANCE_M:
        gap = min(gap, max(0.0, edge - x_b_m))
    return gap


def gap_terrain(
    prof: HeightProfile,
    bins: NDArray[np.int64],
    max_gap_m: float,
    riser_from_x_m: float = math.inf,
) -> tuple[HeightProfile, NDArray[np.int64], HeightProfile, NDArray[np.int64]]:
    """What the strips between consecutive bins of ``prof`` hold, for the strips the map
    bridges (gaps wider than :data:`UNSEEN_TOLERANCE_M` and at most ``max_gap_m``, which
    :func:`unseen_distance` counts seen): there a nosing hid the terrain from the camera,
    and the walking surface runs on between the heights of the surfaces seen either side.
    Returns (floors, their bins, risers, their bins); each column takes the height and the
    bin index (from ``bins``) of the neighbour it comes from.

    - floors: every strip holds terrain at least as high as its lower neighbour (a column
      at that height over the whole strip);
    - risers: a strip that rises (lower neighbour before it) holds a riser up to its higher
      neighbour somewhere inside it, at or beyond ``riser_from_x_m`` (where the foot ends:
      the foot is not inside the terrain); the column at the higher neighbour's height from
      there to the strip's end is the nearest that unseen riser can be. A strip that drops
      (higher neighbour before it) is the shadow of the nosing that ends the higher surface:
      the drop starts where the camera saw that surface end, no riser column."""
    lo, hi, z, sg = prof.x_lo_m, prof.x_hi_m, prof.z_m, prof.sigma_m
    b = np.asarray(bins)
    if len(prof) < 2:
        empty = HeightProfile(lo[:0], hi[:0], z[:0], sg[:0])
        return empty, b[:0], empty, b[:0]
    gap = lo[1:] - hi[:-1]
    i = np.flatnonzero((gap > UNSEEN_TOLERANCE_M) & (gap <= max_gap_m))
    rises = z[i] <= z[i + 1]
    low = np.where(rises, i, i + 1)
    floors = HeightProfile(hi[i], lo[i + 1], z[low], sg[low])
    r = i[rises]
    r_lo = np.maximum(hi[r], riser_from_x_m)
    keep = r_lo < lo[r + 1]
    r, r_lo = r[keep], r_lo[keep]
    risers = HeightProfile(r_lo, lo[r + 1], z[r + 1], sg[r + 1])
    return floors, b[low], risers, b[r + 1]


def _edge_distance(
    ax: float, az: float, bx: float, bz: float, ex: float, ez: float
) -> tuple[float, float, float]:
    """Scalar :func:`_corners_to_segment` for one point: (signed distance, closest x, z)."""
    dx, dz = bx - ax, bz - az
    L2 = dx * dx + dz * dz
    s = 0.0 if L2 == 0 else min(max(((ex - ax) * dx + (ez - az) * dz) / L2, 0.0), 1.0)
    qx, qz = ax + s * dx, az + s * dz
    d = math.sqrt((ex - qx) * (ex - qx) + (ez - qz) * (ez - qz))
    if abs(dx) > 1e-12 and min(ax, bx) < ex < max(ax, bx):
        z_line = az + (ex - ax) * dz / dx
        if ez > z_line:
            d = -min(ez - z_line, ex - min(ax, bx), max(ax, bx) - ex)
    return d, qx, qz


def _point_segment(px: float, pz: float, ax: float, az: float, bx: float, bz: float) -> float:
    dx, dz = bx - ax, bz - az
    L2 = dx * dx + dz * dz
    s = 0.0 if L2 == 0 else min(max(((px - ax) * dx + (pz - az) * dz) / L2, 0.0), 1.0)
    ux, uz = px - ax - s * dx, pz - az - s * dz
    return math.sqrt(ux * ux + uz * uz)


def _segments_cross(
    ax: float, az: float, bx: float, bz: float, cx: float, cz: float, dx: float, dz: float
) -> bool:
    def orient(px: float, pz: float, qx: float, qz: float, rx: float, rz: float) -> float:
        return (qx - px) * (rz - pz) - (qz - pz) * (rx - px)

    o1, o2 = orient(ax, az, bx, bz, cx, cz), orient(ax, az, bx, bz, dx, dz)
    o3, o4 = orient(cx, cz, dx, dz, ax, az), orient(cx, cz, dx, dz, bx, bz)
    return o1 * o2 < 0 and o3 * o4 < 0


def predicted_min_edge_clearance(
    heel_xz_m: ArrayLike,
    toe_xz_m: ArrayLike,
    velocity_xz_mps: ArrayLike,
    horizon_s: float,
    steps: int,
    edge_xz_m: ArrayLike,
    sole_thickness_m: float = 0.0,
) -> float:
    """Minimum of :func:`edge_clearance` over the horizon [0, ``horizon_s``], the foot
    translated at the constant velocity ``velocity_xz_mps`` (m; NaN if the velocity is
    unknown). Exact over the continuous horizon: relative to the foot, the edge moves along
    the segment e - v tau, so the minimum is the distance between that segment and the foot
    segment (negative, the deepest signed value at the horizon's ends or 0, when they cross).
    ``steps`` is unused (kept for a sampled variant's signature)."""
    vx, vz = (float(v) for v in np.asarray(velocity_xz_mps, dtype=float))
    if not (np.isfinite(vx) and np.isfinite(vz)):
        return float("nan")
    ax, az = (float(v) for v in np.asarray(heel_xz_m, dtype=float))
    bx, bz = (float(v) for v in np.asarray(toe_xz_m, dtype=float))
    ex, ez = (float(v) for v in np.asarray(edge_xz_m, dtype=float))
    fx, fz = ex - vx * horizon_s, ez - vz * horizon_s  # the edge at the horizon, foot-relative
    d0 = _edge_distance(ax, az, bx, bz, ex, ez)[0]
    d1 = _edge_distance(ax, az, bx, bz, fx, fz)[0]
    best = min(
        d0, d1, _point_segment(ax, az, ex, ez, fx, fz), _point_segment(bx, bz, ex, ez, fx, fz)
    )
    if _segments_cross(ax, az, bx, bz, ex, ez, fx, fz):
        best = min(best, 0.0)
    return best - sole_thickness_m


def edge_clearance_many(
    heel_xz_m: ArrayLike, toe_xz_m: ArrayLike, edge_xz_m: ArrayLike, sole_thickness_m: float = 0.0
) -> NDArray[np.float64]:
    """:func:`edge_clearance`'s distance for T foot poses (heel, toe (T, 2)) to one edge
    point (2,) -> (T,) m: :func:`edge_clearance_rows` with that edge on every row."""
    a = np.asarray(heel_xz_m, dtype=float).reshape(-1, 2)
    e = np.broadcast_to(np.asarray(edge_xz_m, dtype=float).reshape(2), a.shape)
    return edge_clearance_rows(a, toe_xz_m, e, sole_thickness_m)


def edge_clearance_rows(
    heel_xz_m: ArrayLike, toe_xz_m: ArrayLike, edge_xz_m: ArrayLike, sole_thickness_m: float = 0.0
) -> NDArray[np.float64]:
    """:func:`edge_clearance`'s distance for T foot poses (heel, toe (T, 2)), each against its
    own edge point (T, 2) -> (T,) m; the same numbers bit for bit (offline evaluation over a
    whole trial at once). Squares are products and roots ``sqrt`` here, in
    :func:`_edge_distance` and in the compiled kernels: both are correctly rounded in IEEE
    arithmetic, so every path gives the same bits whatever the numpy or C library version
    (``pow`` / ``np.power`` are not correctly rounded and differ between them)."""
    a = np.asarray(heel_xz_m, dtype=float).reshape(-1, 2)
    b = np.asarray(toe_xz_m, dtype=float).reshape(-1, 2)
    e = np.asarray(edge_xz_m, dtype=float).reshape(-1, 2)
    ax, az, bx, bz, ex, ez = a[:, 0], a[:, 1], b[:, 0], b[:, 1], e[:, 0], e[:, 1]
    dx, dz = bx - ax, bz - az
    L2 = dx * dx + dz * dz
    with np.errstate(divide="ignore", invalid="ignore"):
        s = np.where(
            L2 == 0,
            0.0,
            np.minimum(np.maximum(((ex - ax) * dx + (ez - az) * dz) / L2, 0.0), 1.0),
        )
        qx, qz = ax + s * dx, az + s * dz
        d = np.sqrt((ex - qx) * (ex - qx) + (ez - qz) * (ez - qz))
        lo, hi = np.minimum(ax, bx), np.maximum(ax, bx)
        z_line = az + (ex - ax) * dz / dx
        above = (np.abs(dx) > 1e-12) & (lo < ex) & (ex < hi) & (ez > z_line)
        depth = np.minimum(np.minimum(ez - z_line, ex - lo), hi - ex)
    return np.where(above, -depth, d) - sole_thickness_m


def clearance_many(
    heel_xz_m: ArrayLike, toe_xz_m: ArrayLike, prof: HeightProfile, sole_thickness_m: float = 0.0
) -> NDArray[np.float64]:
    """:func:`foot_clearance`'s distance for T foot poses at once (heel, toe (T, 2)) -> (T,)
    metres (NaN when ``prof`` is empty)."""
    a = np.asarray(heel_xz_m, dtype=float).reshape(-1, 2)
    b = np.asarray(toe_xz_m, dtype=float).reshape(-1, 2)
    if len(prof) == 0:
        return np.full(a.shape[0], np.nan)
    lo, hi, z = prof.x_lo_m[None], prof.x_hi_m[None], prof.z_m[None]

    def point(p: NDArray[np.float64]) -> NDArray[np.float64]:
        px, pz = p[:, :1], p[:, 1:]
        d = np.hypot(px - np.clip(px, lo, hi), pz - np.minimum(pz, z))
        inside = (px >= lo) & (px <= hi) & (pz < z)
        return np.where(inside, pz - z, d).min(axis=1)

    cx = np.concatenate([prof.x_lo_m, prof.x_hi_m])[None]  # (1, 2B)
    cz = np.concatenate([prof.z_m, prof.z_m])[None]
    ab = b - a
    L2 = np.maximum(np.sum(ab * ab, axis=1, keepdims=True), 1e-18)
    s = np.minimum(
        np.maximum(((cx - a[:, :1]) * ab[:, :1] + (cz - a[:, 1:]) * ab[:, 1:]) / L2, 0.0), 1.0
    )
    qx, qz = a[:, :1] + s * ab[:, :1], a[:, 1:] + s * ab[:, 1:]
    dc = np.hypot(cx - qx, cz - qz)
    x0, x1 = np.minimum(a[:, :1], b[:, :1]), np.maximum(a[:, :1], b[:, :1])
    slope = np.where(
        np.abs(ab[:, :1]) > 1e-12,
        ab[:, 1:] / np.where(np.abs(ab[:, :1]) > 1e-12, ab[:, :1], 1.0),
        0.0,
    )
    z_line = a[:, 1:] + (cx - a[:, :1]) * slope
    above = (cx > x0) & (cx < x1) & (cz > z_line) & (x1 - x0 > 1e-12)
    dc = np.where(above, z_line - cz, dc).min(axis=1)
    return np.minimum(np.minimum(point(a), point(b)), dc) - sole_thickness_m


def predicted_min_clearance(
    heel_xz_m: ArrayLike,
    toe_xz_m: ArrayLike,
    velocity_xz_mps: ArrayLike,
    horizon_s: float,
    steps: int,
    prof: HeightProfile,
    sole_thickness_m: float = 0.0,
) -> float:
    """Minimum clearance (m) over the next ``horizon_s``: the foot outline translated at the
    constant velocity ``velocity_xz_mps`` (the toe's), evaluated at ``steps`` times evenly in
    (0, horizon_s] and now. NaN if the profile is empty or the velocity unknown."""
    v = np.asarray(velocity_xz_mps, dtype=float)
    if len(prof) == 0 or not np.all(np.isfinite(v)):
        return float("nan")
    tau = np.linspace(0.0, horizon_s, steps + 1)[:, None]
    a = np.asarray(heel_xz_m, dtype=float)[None] + v[None] * tau
    b = np.asarray(toe_xz_m, dtype=float)[None] + v[None] * tau
    return float(np.min(clearance_many(a, b, prof, sole_thickness_m)))
