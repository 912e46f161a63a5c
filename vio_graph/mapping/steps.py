"""Step and obstacle geometry from the 2D terrain map.

Method (all in the world x-z plane, x = walking direction):

1. **Horizontal levels** (treads, floor, landing, obstacle top). Greedy z-window search, the
   1D analogue of the paper's "horizontal line with most inliers" RANSAC (Sec. II.B, Fig. 2):
   find the z window of half-height ``level_tolerance_m`` holding the most map cells, take its
   cells out of the pool, split them along x at gaps wider than ``max_gap_m`` and keep the
   pieces at least ``min_level_length_m`` long. Repeat until no window holds
   ``min_level_cells`` cells. A vertical face only puts a few cells of one x column into any
   window, so it never makes a level; a piece must also be a z peak: hold at least
   ``min_level_contrast`` times the weight of the windows (``2 level_tolerance_m`` high)
   just above and just below its own z spread (same x range); this rejects the middle of risers
   blurred along x by pose noise. Level heights are count-weighted means of the cells
   within 2.5 robust sigma of the window median.
2. **Steps.** Levels are sorted along x; neighbours closer than ``min_rise_m`` in z merge.
   Each change of level between x-neighbours is a step; its rise is the level difference.
   Its nosing (the convex corner) is at the height of the higher level and at

   * up steps (face towards the camera, i.e. towards -x): the x of the riser, a robust mean
     of the map cells between the two levels (``riser_margin_m`` away from both), when at
     least ``min_riser_cells`` are seen; otherwise the start edge of the upper level;
   * down steps (the face points away from a forward-looking camera and is not observed):
     the end edge of the upper level.

   Level edges use the 50 % rule, robust to noise blur: with ``rho`` the weight per metre in
   a reference window (``edge_reference_m``) inside the level and ``W_beyond`` the weight of
   the outermost ``edge_blur_m`` of cells, ``edge = window_end + W_beyond / rho``.
   Tread depth of a step = x distance from its nosing to the nosing of the next step (same
   direction, sharing a level); the last step of a run has none.
3. **Obstacles**: a level higher (by ``min_rise_m``) than both x-neighbours and at most
   ``max_obstacle_depth_m`` deep. Height = top minus the mean of the neighbouring ground
   levels; depth = back edge x minus front edge x (front: riser rule, back: edge rule).

Uncertainties are one standard deviation of the estimate: level height from the cell scatter
over sqrt(cells); riser x likewise; an edge from the relative count error of ``rho`` and the
cell spacing; rise and tread combine their two ends in quadrature.

Pure module: no file I/O.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Literal

import numpy as np
from numpy.typing import ArrayLike, NDArray

from vio_graph.errors import MappingError
from vio_graph.mapping.config import StepConfig
from vio_graph.surface import under_levels_mask
from vio_graph.types import TerrainKind

_ROBUST_SIGMA_PER_MAD = 1.4826


# ---------------------------------------------------------------------------------------------
# result types
@dataclass(frozen=True)
class LevelSegment:
    """A horizontal piece of the map (tread, floor, landing, obstacle top).

    ``z_m`` height and ``z_std_m`` its standard error; ``x_start_m``/``x_end_m`` the extent
    of its cells; ``x_start_edge_m``/``x_end_edge_m`` the 50 %-rule edge estimates with
    standard error ``edge_std_m``; all metres, world frame.
    """

    z_m: float
    z_std_m: float
    x_start_m: float
    x_end_m: float
    x_start_edge_m: float
    x_end_edge_m: float
    edge_std_m: float
    n_cells: int
    weight: float

    @property
    def length_m(self) -> float:
        return self.x_end_edge_m - self.x_start_edge_m


@dataclass(frozen=True)
class RiserSegment:
    """A vertical face seen between two levels: x position (m) and its standard error."""

    x_m: float
    x_std_m: float
    z_bottom_m: float
    z_top_m: float
    n_cells: int


@dataclass(frozen=True)
class StepGeometry:
    """One step, counted along +x (walking direction) from 0.

    ``direction``: "up" when the terrain rises along +x. ``rise_m``: height difference of the
    two levels. ``tread_m``: x distance from this nosing to the next step's nosing, None for
    the last step of a run. ``nosing_xz_m`` (2,): convex corner, world frame;
    ``nosing_std_xz_m`` (2,) its standard errors. All metres.
    """

    index: int
    direction: Literal["up", "down"]
    rise_m: float
    rise_std_m: float
    tread_m: float | None
    tread_std_m: float | None
    nosing_xz_m: NDArray[np.float64]
    nosing_std_xz_m: NDArray[np.float64]
    lower_z_m: float
    upper_z_m: float
    riser_observed: bool


@dataclass(frozen=True)
class ObstacleGeometry:
    """A raised block: ``height_m`` above the surrounding ground, ``depth_m`` along x, and its
    two top edges (``front_edge_xz_m`` at smaller x), all metres, world frame, with standard
    errors (``*_std_*``)."""

    height_m: float
    height_std_m: float
    depth_m: float
    depth_std_m: float
    front_edge_xz_m: NDArray[np.float64]
    back_edge_xz_m: NDArray[np.float64]
    front_edge_std_xz_m: NDArray[np.float64]
    back_edge_std_xz_m: NDArray[np.float64]
    ground_z_m: float
    top_z_m: float


@dataclass(frozen=True)
class TerrainGeometry:
    """Everything extracted from one map: the terrain kind, steps (x order), obstacles, and
    the levels and risers they were built from."""

    kind: TerrainKind
    steps: tuple[StepGeometry, ...]
    obstacles: tuple[ObstacleGeometry, ...]
    levels: tuple[LevelSegment, ...]
    risers: tuple[RiserSegment, ...]

    @property
    def mean_rise_m(self) -> float | None:
        """Mean rise over the steps (m), None without steps."""
        return float(np.mean([s.rise_m for s in self.steps])) if self.steps else None

    @property
    def mean_tread_m(self) -> float | None:
        """Mean tread depth over steps that have one (m), None without."""
        treads = [s.tread_m for s in self.steps if s.tread_m is not None]
        return float(np.mean(treads)) if treads else None

    @property
    def edges_xz_m(self) -> NDArray[np.float64]:
        """(K, 2) every convex corner (nosings and obstacle top edges), sorted by x."""
        edges = [s.nosing_xz_m for s in self.steps]
        for ob in self.obstacles:
            edges += [ob.front_edge_xz_m, ob.back_edge_xz_m]
        if not edges:
            return np.zeros((0, 2))
        arr = np.asarray(edges, dtype=np.float64)
        return arr[np.argsort(arr[:, 0], kind="stable")]


# ---------------------------------------------------------------------------------------------
# helpers
def _weighted_median(values: NDArray[np.float64], weights: NDArray[np.float64]) -> float:
    order = np.argsort(values)
    cum = np.cumsum(weights[order])
    return float(values[order][np.searchsorted(cum, 0.5 * cum[-1])])


def _robust_mean(
    values: NDArray[np.float64], weights: NDArray[np.float64], floor_m: float
) -> tuple[float, float, NDArray[np.bool_]]:
    """Weighted mean of the values within 2.5 robust sigma of the weighted median.

    Returns (mean, standard error = scatter / sqrt(n kept), kept mask).
    """
    med = _weighted_median(values, weights)
    sigma = _ROBUST_SIGMA_PER_MAD * float(np.median(np.abs(values - med)))
    keep = np.abs(values - med) <= max(2.5 * sigma, floor_m)
    v, w = values[keep], weights[keep]
    mean = float(np.average(v, weights=w))
    scatter = float(np.sqrt(np.average((v - mean) ** 2, weights=w)))
    return mean, max(scatter, 1e-4) / np.sqrt(max(int(keep.sum()), 1)), keep


def _edge(
    x: NDArray[np.float64],
    w: NDArray[np.float64],
    column_m: float,
    beyond_m: float,
    reference_m: float,
    at_end: bool,
) -> tuple[float, float]:
    """50 %-rule edge of a level's cells (x, weights): (edge x, standard error), metres.

    Weights are summed per x column of width ``column_m`` (the map's cell size, so columns
    never alias with the cells). The outermost ``beyond_m`` of columns hold the blurred edge,
    with total weight ``W``; the ``reference_m`` of columns before them give the interior
    weight per metre as a fitted line ``rho(x)`` (the density of a real scan drifts along a
    tread). The edge is ``split + L`` with ``W = integral of rho over [split, split + L]``.
    Its error is ``L`` times the relative error of ``rho`` (column scatter / sqrt(columns)).

    The rule assumes the end is observed as densely as the interior. Where it is not (the
    end of a tread seen from many more keyframes than its middle, as from a camera low on
    the shank that passes over it), ``W`` over ``rho`` can reach centimetres past the last
    cell; the edge is kept within ``beyond_m`` of the outermost cell, the width the blurred
    edge is defined to occupy.
    """
    if not at_end:
        edge, std = _edge(-x, w, column_m, beyond_m, reference_m, at_end=True)
        return -edge, std
    column = np.floor(x / column_m).astype(np.int64)
    last = int(column.max())
    n_beyond = max(1, int(round(beyond_m / column_m)))
    n_ref = int(round(reference_m / column_m))
    n_span = last - int(column.min()) + 1
    # keep at least two thirds of a short level as reference
    n_beyond = min(n_beyond, max(1, n_span // 3))
    n_ref = min(n_ref, n_span - n_beyond)
    if n_ref < 2:
        return float(x.max()), column_m * n_span
    split = (last - n_beyond + 1) * column_m
    mass = float(w[column > last - n_beyond].sum())
    ref_cols = last - n_beyond - np.arange(n_ref)  # nearest first
    in_ref = (column <= ref_cols[0]) & (column > ref_cols[0] - n_ref)
    rho = np.bincount(ref_cols[0] - column[in_ref], weights=w[in_ref], minlength=n_ref)
    rho = rho / column_m  # weight per metre in each reference column
    centres = (ref_cols + 0.5) * column_m - split  # negative
    mean_rho = float(np.mean(rho))
    if mean_rho <= 0:
        return float(x.max()), column_m * n_span
    length = mass / mean_rho
    if n_ref >= 4:
        slope, rho0 = np.polyfit(centres, rho, 1)
        # solve mass = rho0 L + slope L^2 / 2, trusting the line only where it stays positive
        if rho0 > 0.5 * mean_rho:
            disc = rho0**2 + 2.0 * slope * mass
            if abs(slope) * length < 1e-9 * rho0:
                length = mass / rho0
            elif disc >= 0:
                length = float((-rho0 + np.sqrt(disc)) / slope)
    rel_err = float(np.std(rho) / mean_rho) / np.sqrt(n_ref)
    std = float(np.hypot(length * rel_err, column_m / np.sqrt(12.0)))
    outer = float(x.max())
    return min(max(split + length, outer - beyond_m), outer + beyond_m), std


def _as_points(
    points_xz_m: ArrayLike, weights: ArrayLike | None
) -> tuple[NDArray[np.float64], NDArray[np.float64]]:
    pts = np.asarray(points_xz_m, dtype=np.float64)
    if pts.size == 0:
        pts = pts.reshape(0, 2)
    if pts.ndim != 2 or pts.shape[1] != 2:
        raise MappingError(f"points_xz_m must have shape (M, 2), got {pts.shape}")
    w = np.ones(pts.shape[0]) if weights is None else np.asarray(weights, dtype=np.float64)
    if w.shape != (pts.shape[0],) or np.any(w < 0):
        raise MappingError("weights must be (M,) and non-negative")
    finite = np.all(np.isfinite(pts), axis=1) & np.isfinite(w) & (w > 0)
    return pts[finite], w[finite]


# ---------------------------------------------------------------------------------------------
# step 1: horizontal levels
#: positions per block of find_levels' window counts (the block maxima make the search for the
#: best window cost ~sqrt of the points instead of all of them)
_LEVEL_BLOCK = 512


def find_levels(
    points_xz_m: ArrayLike, weights: ArrayLike | None = None, config: StepConfig | None = None
) -> tuple[LevelSegment, ...]:
    """Horizontal levels of a map, sorted by x start (method step 1 in the module docstring).

    The same levels, bit for bit, as :func:`find_levels_reference` (the plain statement of the
    search, kept as the tested reference), at a cost that grows with the points near each level
    instead of with all points per level: the window counts are kept over the heights sorted
    once and updated only where a removed band touches them, and the points in a piece's x span
    come from the x order (a 10-minute trial's map has ~1000 levels).

    Args:
        points_xz_m: (M, 2) map points, world frame, metres.
        weights: (M,) non-negative weights (raw point counts per map cell), default ones.
        config: thresholds.
    """
    cfg = config if config is not None else StepConfig()
    pts, w = _as_points(points_xz_m, weights)
    tol = cfg.level_tolerance_m
    n = pts.shape[0]
    by_z = np.argsort(pts[:, 1], kind="stable")
    z = pts[by_z, 1]  # heights in sorted order; position p holds point by_z[p]
    by_x = np.argsort(pts[:, 0], kind="stable")
    x_by_x = pts[by_x, 0]
    remaining = np.ones(n, dtype=bool)  # by sorted position
    n_remaining = n
    # counts[p]: remaining points at positions >= p with height <= z[p] + 2 tol (the sliding
    # window of the reference over the remaining heights); -1 once p is removed
    hi = np.searchsorted(z, z + 2 * tol, side="right")
    # padded to whole blocks, with each block's maximum kept: the best window is the first
    # maximum of the block maxima, then of that block (as a scan of all counts finds it)
    n_blocks = max(1, -(-n // _LEVEL_BLOCK))
    counts = np.full(n_blocks * _LEVEL_BLOCK, -1, dtype=np.int64)
    counts[:n] = hi - np.arange(n)
    blocks = counts.reshape(n_blocks, _LEVEL_BLOCK)
    block_max = blocks.max(axis=1)
    levels: list[LevelSegment] = []
    n_searches = 0
    while cfg.max_levels is None or n_searches < cfg.max_levels:
        n_searches += 1
        if n_remaining < cfg.min_level_cells or n_remaining == 0:
            break
        blk = int(np.argmax(block_max))
        best = blk * _LEVEL_BLOCK + int(np.argmax(blocks[blk]))  # first maximum, height order
        if counts[best] < cfg.min_level_cells:
            break
        z_centre = z[best] + tol
        # the band |z - z_centre| <= tol is contiguous in height order (z - z_centre is
        # monotone); the exact test on a slightly wider slice finds it
        a = int(np.searchsorted(z, z_centre - 2 * tol, side="left"))
        b = int(np.searchsorted(z, z_centre + 2 * tol, side="right"))
        in_band = (np.abs(z[a:b] - z_centre) <= tol) & remaining[a:b]
        removed = np.flatnonzero(in_band) + a  # positions
        if removed.size == 0:
            # heights on a grid can put every point of the window a rounding error outside
            # the band (the reference then searches the same window forever): take the window
            window = np.arange(best, hi[best])
            removed = window[remaining[window]]
        remaining[removed] = False
        n_remaining -= removed.size
        counts[removed] = -1
        # windows that reach into the removed positions lose them: p < b_rm, hi[p] > a_rm
        a_rm, b_rm = int(removed[0]), int(removed[-1]) + 1
        p0 = int(np.searchsorted(hi, a_rm, side="right"))
        mark = np.zeros(b_rm - a_rm, dtype=np.int64)
        mark[removed - a_rm] = 1
        gone = np.concatenate(([0], np.cumsum(mark)))  # removed positions before a_rm + i
        ps = np.arange(p0, b_rm)
        ps = ps[remaining[ps]]
        lo = np.clip(ps, a_rm, b_rm) - a_rm
        up = np.clip(hi[ps], a_rm, b_rm) - a_rm
        counts[ps] -= gone[up] - gone[lo]
        b0, b1 = p0 // _LEVEL_BLOCK, (b_rm - 1) // _LEVEL_BLOCK + 1  # blocks touched
        block_max[b0:b1] = blocks[b0:b1].max(axis=1)
        members = np.sort(by_z[removed])  # original index order, as the reference
        # split along x at gaps, keep long enough pieces
        members = members[np.argsort(pts[members, 0], kind="stable")]
        breaks = np.flatnonzero(np.diff(pts[members, 0]) > cfg.max_gap_m) + 1
        for piece in np.split(members, breaks):
            if piece.size < cfg.min_level_cells:
                continue
            x_piece = pts[piece, 0]
            if x_piece[-1] - x_piece[0] < cfg.min_level_length_m:
                continue
            # flatness: a level is a z peak; a (blurred) vertical face continues above/below
            z_piece = pts[piece, 1]
            z_med = float(np.median(z_piece))
            half = max(tol, 2.5 * _ROBUST_SIGMA_PER_MAD * float(np.median(np.abs(z_piece - z_med))))
            i0 = int(np.searchsorted(x_by_x, x_piece[0], side="left"))
            i1 = int(np.searchsorted(x_by_x, x_piece[-1], side="right"))
            in_x = np.sort(by_x[i0:i1])  # x_piece[0] <= x <= x_piece[-1], original order
            dz, w_x = pts[in_x, 1] - z_med, w[in_x]
            above = float(w_x[(dz > half) & (dz <= half + 2 * tol)].sum())
            below = float(w_x[(dz < -half) & (dz >= -half - 2 * tol)].sum())
            if float(w[piece].sum()) < cfg.min_level_contrast * max(above, below):
                continue
            levels.append(_make_level(pts[piece], w[piece], cfg))
    levels.sort(key=lambda lv: lv.x_start_m)
    return tuple(levels)


def find_levels_reference(
    points_xz_m: ArrayLike, weights: ArrayLike | None = None, config: StepConfig | None = None
) -> tuple[LevelSegment, ...]:
    """:func:`find_levels` as first written: every search scans all remaining points (the
    tested reference of the incremental version).

    Args:
        points_xz_m: (M, 2) map points, world frame, metres.
        weights: (M,) non-negative weights (raw point counts per map cell), default ones.
        config: thresholds.
    """
    cfg = config if config is not None else StepConfig()
    pts, w = _as_points(points_xz_m, weights)
    tol = cfg.level_tolerance_m
    remaining = np.ones(pts.shape[0], dtype=bool)
    levels: list[LevelSegment] = []
    n_searches = 0
    # the heights sorted once: each search takes the remaining ones from this order (the
    # same sorted values as sorting the remaining heights anew, without a sort per level;
    # a long trial's map has ~1000 levels)
    by_z = np.argsort(pts[:, 1], kind="stable")
    z_by_z = pts[by_z, 1]
    # each search removes at least min_level_cells cells, so the loop ends without a cap
    while cfg.max_levels is None or n_searches < cfg.max_levels:
        n_searches += 1
        idx = np.flatnonzero(remaining)
        if idx.size < cfg.min_level_cells:
            break
        # the z window with most cells (sliding window over sorted heights)
        z_sorted = z_by_z[remaining[by_z]]
        counts = np.searchsorted(z_sorted, z_sorted + 2 * tol, side="right") - np.arange(
            z_sorted.size
        )
        best = int(np.argmax(counts))
        if counts[best] < cfg.min_level_cells:
            break
        z_centre = z_sorted[best] + tol
        members = idx[np.abs(pts[idx, 1] - z_centre) <= tol]
        remaining[members] = False
        # split along x at gaps, keep long enough pieces
        members = members[np.argsort(pts[members, 0], kind="stable")]
        breaks = np.flatnonzero(np.diff(pts[members, 0]) > cfg.max_gap_m) + 1
        for piece in np.split(members, breaks):
            if piece.size < cfg.min_level_cells:
                continue
            x_piece = pts[piece, 0]
            if x_piece[-1] - x_piece[0] < cfg.min_level_length_m:
                continue
            # flatness: a level is a z peak; a (blurred) vertical face continues above/below
            z_piece = pts[piece, 1]
            z_med = float(np.median(z_piece))
            half = max(tol, 2.5 * _ROBUST_SIGMA_PER_MAD * float(np.median(np.abs(z_piece - z_med))))
            in_x = (pts[:, 0] >= x_piece[0]) & (pts[:, 0] <= x_piece[-1])
            dz, w_x = pts[in_x, 1] - z_med, w[in_x]
            above = float(w_x[(dz > half) & (dz <= half + 2 * tol)].sum())
            below = float(w_x[(dz < -half) & (dz >= -half - 2 * tol)].sum())
            if float(w[piece].sum()) < cfg.min_level_contrast * max(above, below):
                continue
            levels.append(_make_level(pts[piece], w[piece], cfg))
    levels.sort(key=lambda lv: lv.x_start_m)
    return tuple(levels)


def _make_level(pts: NDArray[np.float64], w: NDArray[np.float64], cfg: StepConfig) -> LevelSegment:
    z_m, z_std_m, keep = _robust_mean(pts[:, 1], w, floor_m=0.002)
    x, wk = pts[keep, 0], w[keep]
    args = (cfg.column_width_m, cfg.edge_blur_m, cfg.edge_reference_m)
    start, std_start = _edge(x, wk, *args, at_end=False)
    end, std_end = _edge(x, wk, *args, at_end=True)
    return LevelSegment(
        z_m=z_m,
        z_std_m=z_std_m,
        x_start_m=float(x.min()),
        x_end_m=float(x.max()),
        x_start_edge_m=start,
        x_end_edge_m=end,
        edge_std_m=max(std_start, std_end),
        n_cells=int(keep.sum()),
        weight=float(wk.sum()),
    )


def _merge_levels(levels: tuple[LevelSegment, ...], cfg: StepConfig) -> list[LevelSegment]:
    """Merge x-neighbours closer than ``min_rise_m`` in height (e.g. split by an occlusion)."""
    merged: list[LevelSegment] = []
    for lv in levels:
        if merged and abs(lv.z_m - merged[-1].z_m) < cfg.min_rise_m:
            a = merged[-1]
            total = a.weight + lv.weight
            merged[-1] = LevelSegment(
                z_m=(a.z_m * a.weight + lv.z_m * lv.weight) / total,
                z_std_m=float(np.hypot(a.z_std_m * a.weight, lv.z_std_m * lv.weight) / total),
                x_start_m=min(a.x_start_m, lv.x_start_m),
                x_end_m=max(a.x_end_m, lv.x_end_m),
                x_start_edge_m=min(a.x_start_edge_m, lv.x_start_edge_m),
                x_end_edge_m=max(a.x_end_edge_m, lv.x_end_edge_m),
                edge_std_m=max(a.edge_std_m, lv.edge_std_m),
                n_cells=a.n_cells + lv.n_cells,
                weight=total,
            )
        else:
            merged.append(lv)
    return merged


# ---------------------------------------------------------------------------------------------
# step 2: risers, nosings, steps
def fit_riser(
    points_xz_m: NDArray[np.float64],
    weights: NDArray[np.float64],
    before: LevelSegment,
    after: LevelSegment,
    config: StepConfig,
    x_order: tuple[NDArray[np.intp], NDArray[np.float64]] | None = None,
) -> RiserSegment | None:
    """Robust x of the vertical face between two x-neighbouring levels, or None if too few
    map cells lie between them (``riser_margin_m`` away from both heights).

    ``x_order``: the points' order by x (stable argsort) and their x in that order, if the
    caller has them: the cells in the x window are then found by bisection instead of a scan
    of every point (the same cells, in the same order, so the same answer)."""
    z_lo, z_hi = sorted((before.z_m, after.z_m))
    x_lo = min(before.x_end_m, after.x_start_m) - config.riser_x_window_m
    x_hi = max(before.x_end_m, after.x_start_m) + config.riser_x_window_m
    if x_order is None:
        cand = np.flatnonzero((points_xz_m[:, 0] >= x_lo) & (points_xz_m[:, 0] <= x_hi))
    else:
        order, x_sorted = x_order
        i0 = int(np.searchsorted(x_sorted, x_lo, side="left"))
        i1 = int(np.searchsorted(x_sorted, x_hi, side="right"))
        cand = np.sort(order[i0:i1])
    z_cand = points_xz_m[cand, 1]
    box = cand[(z_cand > z_lo + config.riser_margin_m) & (z_cand < z_hi - config.riser_margin_m)]
    if box.size < config.min_riser_cells:
        return None
    x_m, x_std_m, keep = _robust_mean(points_xz_m[box, 0], weights[box], floor_m=0.003)
    if int(keep.sum()) < config.min_riser_cells:
        return None
    z_box = points_xz_m[box, 1][keep]
    return RiserSegment(
        x_m=x_m,
        x_std_m=x_std_m,
        z_bottom_m=float(z_box.min()),
        z_top_m=float(z_box.max()),
        n_cells=int(keep.sum()),
    )


@dataclass(frozen=True)
class _Transition:
    index: int  # transition between levels[index] and levels[index + 1]
    up: bool
    nosing_xz_m: NDArray[np.float64]
    nosing_std_xz_m: NDArray[np.float64]
    riser: RiserSegment | None


def _transition(
    i: int,
    levels: list[LevelSegment],
    pts: NDArray[np.float64],
    w: NDArray[np.float64],
    cfg: StepConfig,
    x_order: tuple[NDArray[np.intp], NDArray[np.float64]] | None = None,
) -> _Transition:
    a, b = levels[i], levels[i + 1]
    up = b.z_m > a.z_m
    riser = fit_riser(pts, w, a, b, cfg, x_order) if up else None
    if up:
        top = b
        if riser is not None:
            x, sx = riser.x_m, riser.x_std_m
        else:
            x, sx = b.x_start_edge_m, b.edge_std_m
    else:
        top = a
        x, sx = a.x_end_edge_m, a.edge_std_m
    return _Transition(
        index=i,
        up=up,
        nosing_xz_m=np.array([x, top.z_m]),
        nosing_std_xz_m=np.array([sx, top.z_std_m]),
        riser=riser,
    )


#: passes of the walking-surface rule: dropping the floor under a flight can leave pieces of
#: it that form levels of their own, found under the treads on the next pass
_UNDER_LEVEL_PASSES = 3


def under_levels_by_window(
    pts: NDArray[np.float64],
    z: NDArray[np.float64],
    lo: NDArray[np.float64],
    hi: NDArray[np.float64],
    margin_m: float,
    drop_m: float,
) -> NDArray[np.bool_]:
    """``under_levels_mask(pts, z, lo, hi, margin_m, drop_m, drop_m)`` (vio_graph/surface.py;
    no line of sight: a map), bit for bit, one level's x window at a time.

    Without a line of sight and with ``margin_m`` >= 0 both of its rules flag a point only
    through a level A whose x extent [lo, hi] holds it (beneath A: strictly inside the extent
    less the margin; near a lower level B under A: inside the extent), and A's levels B
    overlap A in x. So the call for A's window of the x-sorted points, with the levels that
    overlap A's extent, flags those points as the whole call does through A, and through
    the other levels it passes at most what the whole call flags (their lower levels among
    fewer); the union over all levels is the whole call's mask. Each level then costs its
    window, not the points x levels of the whole call and its pair list over all levels in
    Python (~1 s of CPU on a 10-minute map: 176,000 points, 745 levels)."""
    n = pts.shape[0]
    if margin_m < 0 or n == 0 or z.size == 0:
        return under_levels_mask(pts, z, lo, hi, margin_m, drop_m, drop_m)
    by_x = np.argsort(pts[:, 0], kind="stable")
    xs = pts[by_x, 0]
    under = np.zeros(n, dtype=bool)
    for a in range(z.size):
        i0 = int(np.searchsorted(xs, lo[a], side="left"))
        i1 = int(np.searchsorted(xs, hi[a], side="right"))
        if i1 <= i0:
            continue
        near = np.flatnonzero((hi >= lo[a]) & (lo <= hi[a]))  # A itself among them
        rows = by_x[i0:i1]
        under[rows] |= under_levels_mask(
            pts[rows], z[near], lo[near], hi[near], margin_m, drop_m, drop_m
        )
    return under


def under_junctions_mask(
    pts: NDArray[np.float64],
    z: NDArray[np.float64],
    lo: NDArray[np.float64],
    hi: NDArray[np.float64],
    margin_m: float,
    drop_m: float,
    gap_m: float,
) -> NDArray[np.bool_]:
    """(N,) True for map points beneath the junction of two abutting levels.

    Levels A and C abut when C starts within ``gap_m`` of A's end (an x gap narrower than the
    one that splits a level is no gap in the surface). A point with x from ``margin_m`` before
    A's end to ``margin_m`` past C's start and at least ``drop_m`` below the lower of the two is
    under the walking surface. These are the strips the rule "more than ``margin_m`` inside a
    level's extent" (:func:`vio_graph.surface.under_levels_mask`) leaves out; it leaves them
    for a riser set back under its own nosing, and a riser spans the two levels' heights, so
    it is never ``drop_m`` below the lower one: a point there is the floor seen through an
    open riser (no line of sight in a map, but a floor 1.5 m below two treads that meet is not
    the walking surface). Pure; all metres, world frame.
    """
    n = pts.shape[0]
    under = np.zeros(n, dtype=bool)
    if n == 0 or z.size < 2:
        return under
    by_x = np.argsort(pts[:, 0], kind="stable")
    xs = pts[by_x, 0]
    by_lo = np.argsort(lo, kind="stable")
    lo_sorted = lo[by_lo]
    for a in range(z.size):
        j0 = int(np.searchsorted(lo_sorted, hi[a] - gap_m, side="left"))
        j1 = int(np.searchsorted(lo_sorted, hi[a] + gap_m, side="right"))
        x_lo = max(lo[a], hi[a] - margin_m)  # the strip starts in A whichever C abuts it
        for c in by_lo[j0:j1]:
            if c == a or lo[c] <= lo[a]:
                continue
            x_hi = min(hi[c], lo[c] + margin_m)
            i0 = int(np.searchsorted(xs, x_lo, side="left"))
            i1 = int(np.searchsorted(xs, x_hi, side="right"))
            if i1 <= i0:
                continue
            rows = by_x[i0:i1]
            under[rows[pts[rows, 1] < min(z[a], z[c]) - drop_m]] = True
    return under


def estimate_terrain_geometry(
    points_xz_m: ArrayLike,
    weights: ArrayLike | None = None,
    config: StepConfig | None = None,
    kind_hint: TerrainKind | None = None,
) -> TerrainGeometry:
    """Segment a 2D map into levels and risers and measure steps / obstacles.

    Args:
        points_xz_m: (M, 2) map points (e.g. ``TerrainMap2D.points_xz_m``), world, metres.
        weights: (M,) weights (``TerrainMap2D.point_counts``), default ones.
        config: thresholds (``StepConfig``).
        kind_hint: with ``TerrainKind.OBSTACLE`` a raised last level also counts as an
            obstacle top (its far side not yet seen); otherwise unused.

    Returns:
        ``TerrainGeometry`` with the detected kind: LEVEL (one level), STAIR_UP/STAIR_DOWN
        (all steps one way, no obstacle), OBSTACLE (obstacles, no steps), else UNKNOWN.
    """
    cfg = config if config is not None else StepConfig()
    pts, w = _as_points(points_xz_m, weights)
    levels = _merge_levels(find_levels(pts, w, cfg), cfg)
    margin = cfg.under_level_margin_m
    for _ in range(_UNDER_LEVEL_PASSES if margin is not None else 0):
        assert margin is not None
        drop = cfg.min_rise_m + cfg.level_tolerance_m
        z = np.array([lv.z_m for lv in levels], dtype=float)
        lo = np.array([lv.x_start_m for lv in levels], dtype=float)
        hi = np.array([lv.x_end_m for lv in levels], dtype=float)
        under = under_levels_by_window(pts, z, lo, hi, margin, drop)
        if cfg.under_junctions:
            under |= under_junctions_mask(pts, z, lo, hi, margin, drop, cfg.max_gap_m)
        if not under.any():
            break
        # the walking surface only (open risers): find the levels again without them
        pts, w = pts[~under], w[~under]
        levels = _merge_levels(find_levels(pts, w, cfg), cfg)
    if not levels:
        return TerrainGeometry(TerrainKind.UNKNOWN, (), (), (), ())
    by_x = np.argsort(pts[:, 0], kind="stable")
    x_order = (by_x, pts[by_x, 0])
    transitions = [_transition(i, levels, pts, w, cfg, x_order) for i in range(len(levels) - 1)]
    risers = tuple(t.riser for t in transitions if t.riser is not None)

    # obstacles: a plateau higher than both neighbours and not too deep
    consumed: set[int] = set()
    obstacles: list[ObstacleGeometry] = []
    for j in range(1, len(levels)):
        up_into = transitions[j - 1]
        has_back = j < len(levels) - 1
        if not up_into.up or (has_back and transitions[j].up):
            continue
        if not has_back and kind_hint is not TerrainKind.OBSTACLE:
            continue
        if j - 1 in consumed:
            continue
        top = levels[j]
        if has_back:
            back_xz, back_std = transitions[j].nosing_xz_m, transitions[j].nosing_std_xz_m
            grounds = [levels[j - 1], levels[j + 1]]
        else:
            back_xz = np.array([top.x_end_edge_m, top.z_m])
            back_std = np.array([top.edge_std_m, top.z_std_m])
            grounds = [levels[j - 1]]
        depth = float(back_xz[0] - up_into.nosing_xz_m[0])
        if depth > cfg.max_obstacle_depth_m:
            continue
        ground_z = float(np.mean([g.z_m for g in grounds]))
        ground_std = float(np.sqrt(np.sum([g.z_std_m**2 for g in grounds])) / len(grounds))
        obstacles.append(
            ObstacleGeometry(
                height_m=top.z_m - ground_z,
                height_std_m=float(np.hypot(top.z_std_m, ground_std)),
                depth_m=depth,
                depth_std_m=float(np.hypot(back_std[0], up_into.nosing_std_xz_m[0])),
                front_edge_xz_m=up_into.nosing_xz_m.copy(),
                back_edge_xz_m=back_xz.copy(),
                front_edge_std_xz_m=up_into.nosing_std_xz_m.copy(),
                back_edge_std_xz_m=back_std.copy(),
                ground_z_m=ground_z,
                top_z_m=top.z_m,
            )
        )
        consumed.update({j - 1, j} if has_back else {j - 1})

    # steps: every other transition; tread = distance to the next nosing of the same run
    free = [t for t in transitions if t.index not in consumed]
    steps: list[StepGeometry] = []
    for k, t in enumerate(free):
        a, b = levels[t.index], levels[t.index + 1]
        nxt = free[k + 1] if k + 1 < len(free) else None
        tread_m: float | None = None
        tread_std_m: float | None = None
        if nxt is not None and nxt.index == t.index + 1 and nxt.up == t.up:
            tread_m = float(abs(nxt.nosing_xz_m[0] - t.nosing_xz_m[0]))
            tread_std_m = float(np.hypot(nxt.nosing_std_xz_m[0], t.nosing_std_xz_m[0]))
        steps.append(
            StepGeometry(
                index=k,
                direction="up" if t.up else "down",
                rise_m=float(abs(b.z_m - a.z_m)),
                rise_std_m=float(np.hypot(a.z_std_m, b.z_std_m)),
                tread_m=tread_m,
                tread_std_m=tread_std_m,
                nosing_xz_m=t.nosing_xz_m,
                nosing_std_xz_m=t.nosing_std_xz_m,
                lower_z_m=min(a.z_m, b.z_m),
                upper_z_m=max(a.z_m, b.z_m),
                riser_observed=t.riser is not None,
            )
        )

    if not transitions:
        kind = TerrainKind.LEVEL
    elif obstacles and not steps:
        kind = TerrainKind.OBSTACLE
    elif steps and not obstacles and all(s.direction == "up" for s in steps):
        kind = TerrainKind.STAIR_UP
    elif steps and not obstacles and all(s.direction == "down" for s in steps):
        kind = TerrainKind.STAIR_DOWN
    else:
        kind = TerrainKind.UNKNOWN
    return TerrainGeometry(kind, tuple(steps), tuple(obstacles), tuple(levels), risers)
