"""Geometric terrain classifier on the smoothed sagittal profile.

The paper classifies the terrain with a CNN from its earlier work [9]; vio_graph uses a
transparent geometric rule on the 2D profile instead, which needs no training data.

Rule
----
1. **Levels.** Horizontal surfaces are found greedily: for every point, count the profile
   points within +-``level_band_m`` of its height (vectorised with ``searchsorted`` on the
   sorted heights); the best band whose points span at least ``min_level_length_m`` in x
   (5th-95th percentile extent) and hold ``min_level_points`` is a level at the median height of
   its points; its points are removed and the search repeats (at most ``max_levels``). A band
   is split into separate levels at x gaps larger than ``level_gap_m`` (the floor in front of
   and behind an obstacle are two levels at the same height).
   Because the profile is grid-thinned, point counts are proportional to surface length, so a
   riser seen head-on does not outvote a tread.
2. **Sequence.** Levels are sorted by their median x (near to far). Consecutive height
   differences smaller than ``min_step_m`` are "same height".
3. **Class.**
   - fewer than ``min_points`` points, no level, or any upward height difference larger than
     ``max_step_m`` (a wall) -> UNKNOWN (large DOWNWARD differences are allowed: going down,
     the intermediate treads are often hidden);
   - all levels at the same height -> LEVEL if at most ``max_unexplained_fraction`` of the
     points are outside every level, else UNKNOWN (something non-horizontal is in view);
   - heights go up and come back to the first level's height (low-high-low) -> OBSTACLE;
   - heights only go up -> STAIR_UP, except a single raised level shorter than
     ``obstacle_max_depth_m`` that is the farthest level and has lower profile points beyond
     it (the floor behind the box) -> OBSTACLE (a 13 cm box top vs a 28 cm tread; a tread cut
     by the field of view has nothing lower beyond it);
   - heights only go down -> STAIR_DOWN;
   - anything else -> UNKNOWN.

4. **Faces (vertical segments).** A single frame often holds only one level and a riser: a
   tread with the next riser rising at its far end (the tread above is out of view), a riser
   dropping at the near end of a tread, or, from a low camera, the floor and a row of risers
   whose treads are seen too obliquely to return. Rule 3 would call those LEVEL or UNKNOWN.
   Points outside every level are grouped along x (split at gaps above ``face_gap_m``); the
   points of a group within ``face_max_width_m`` / 2 of its median x are its core (a short
   piece of tread attached to a riser is left out), and a core of at least
   ``min_face_points`` points spanning at least ``min_step_m`` in height is a face. A face
   rises (going away from the camera) when the surface just before it (within
   ``face_context_m``) is nearer its bottom than its top, or, without one, the surface just
   after it is nearer its top, or, without either, the nearest face (the previous one, else
   the next) is lower before it or higher after it; otherwise it drops; a lone face with
   nothing beside it is left out. A face taller than ``max_step_m`` is a wall and leaves the
   class UNKNOWN. When the levels alone give LEVEL or UNKNOWN (not a wall), the faces decide:
   only rising -> STAIR_UP, only dropping -> STAIR_DOWN, rising then dropping -> OBSTACLE. The
   decision uses only the geometry of the frame (levels separated by a rise, a vertical
   segment between them), no proportions.

5. **Stand surface.** A frame that still holds one level height only (LEVEL by steps 1-4) is
   compared with the surface the instrumented foot last stood on (the estimator's heel / toe
   at stance, relative to the predicted camera; ``stand_level``): the nearest level at least
   ``min_step_m`` below it -> STAIR_DOWN (the view is the floor or tread below the step the
   foot stands on, its drop out of view or in the nosing's shadow), above it -> STAIR_UP (or
   OBSTACLE by the short raised level rule of step 3), else LEVEL. The front end looks for
   corners on the class of steps 1-4 only: the stand surface says which way the terrain
   goes, it puts no edge in the frame. With ``obstacle_far_side``, a frame whose levels only
   go down, from a nearest level at least ``min_step_m`` above the stand surface to a
   farthest level back at its height, is OBSTACLE: the camera past the near edge of a box
   sees its top and the floor beyond at the height the foot stands on (a descending foot
   last stood on the highest tread in view, so nothing is above it).

6. **The obstacle seen before** (``obstacle_memory``, :func:`recall_obstacle`). An obstacle
   seen with the floor beside it (a frame that steps 1-4 call OBSTACLE, with a floor level
   and a top level) is remembered: the floor's and the top's heights and the top's x
   extent, placed with the sum of the predicted camera displacements. A later frame that
   steps 1-5 call LEVEL or a stair, whose levels are all either that floor or that top
   (overlapping the top in x) with one on the top, is OBSTACLE: the same box with its far
   side out of view or in its own shadow. A level at any other height leaves the class as
   it is; a level above the top, or a foot that stood on another surface since, forgets the
   obstacle. Like step 5, this sets the reported class only (no corners).

Known limits: a floor and one rising face (an obstacle whose top is out of view) is called
STAIR_UP, and so is a floor and a raised top whose far side was never seen (a deep platform
approached with its far edge beyond the view); a stair tread cut short by the field of view
can look like an obstacle top; a box seen from above (camera past its near edge) looks like
STAIR_DOWN unless the stand surface (step 5) says the floor beyond is the one the foot
stands on.
"""

from __future__ import annotations

import math
from bisect import bisect_left
from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np
from numpy.typing import NDArray

from vio_graph.errors import FrontendError
from vio_graph.frontend.config import TerrainConfig
from vio_graph.frontend.icp import compiled_kernels
from vio_graph.surface import floor_beyond_slab_mask, seen_under_mask, under_levels_mask
from vio_graph.types import TerrainKind


@dataclass(frozen=True)
class Level:
    """A horizontal surface of the profile: median height, robust x extent, point count."""

    height_m: float
    x_min_m: float
    x_max_m: float
    x_median_m: float
    n_points: int

    @property
    def length_m(self) -> float:
        return self.x_max_m - self.x_min_m


def _median_sorted(values: list[float], lo: int, hi: int) -> float:
    """np.median of the sorted values[lo:hi] (hi > lo): the middle value or the mean of the
    middle two, computed as np.median does ((a + b) / 2)."""
    n = hi - lo
    mid = lo + n // 2
    return values[mid] if n % 2 else (values[mid - 1] + values[mid]) / 2


def _percentile_sorted(values: list[float], q: float) -> float:
    """np.percentile(values, q) (linear method) of sorted values, as numpy computes it:
    virtual index (n - 1) * q / 100, the last value at or beyond the end, else the lerp
    a + (b - a) g, or b - (b - a)(1 - g) when g >= 0.5. The same float, without the ~30 us
    of np.percentile's dispatch."""
    n = len(values)
    virtual = (n - 1) * (q / 100)
    if virtual >= n - 1:
        return values[-1]
    j = math.floor(virtual)
    g = virtual - j
    a, b = values[j], values[j + 1]
    diff = b - a
    return b - diff * (1 - g) if g >= 0.5 else a + diff * g


def _robust_extent(xs: NDArray[np.float64]) -> tuple[float, float, float]:
    """5th, 50th and 95th percentile (nearest rank) of sorted values."""
    n = xs.size - 1
    return float(xs[int(0.05 * n)]), float(xs[n // 2]), float(xs[int(np.ceil(0.95 * n))])


def find_levels(profile_xz_m: NDArray[np.float64], config: TerrainConfig) -> list[Level]:
    """Greedy extraction of horizontal levels (rule step 1), sorted by median x.

    Compiled (``compiled.find_levels``, numba) when the front end's kernels are on: the same
    levels bit for bit as :func:`find_levels_reference` (tests/test_frontend_fastpaths.py).

    Args:
        profile_xz_m: (N, 2) smoothed profile, metres.

    Returns:
        Levels, near (small x) to far.
    """
    kernels = compiled_kernels()
    if kernels is None:
        return find_levels_reference(profile_xz_m, config)
    pts = np.ascontiguousarray(profile_xz_m, dtype=float)
    rows = kernels.find_levels_xz(  # sorted by height inside
        pts,
        float(config.level_band_m),
        int(config.max_levels),
        int(config.min_level_points),
        float(config.level_gap_m),
        float(config.min_level_length_m),
    ).tolist()
    levels = [Level(h, x_lo, x_hi, x_med, int(n)) for h, x_lo, x_hi, x_med, n in rows]
    return sorted(levels, key=lambda lv: lv.x_median_m)


def find_levels_reference(profile_xz_m: NDArray[np.float64], config: TerrainConfig) -> list[Level]:
    """numpy path of :func:`find_levels`."""
    pts = np.asarray(profile_xz_m, dtype=float)
    band = config.level_band_m
    order = np.argsort(pts[:, 1])
    z = pts[order, 1]
    x = pts[order, 0]
    alive = np.ones(z.size, dtype=bool)
    levels: list[Level] = []
    for _ in range(config.max_levels):
        za, xa = z[alive], x[alive]  # still sorted by z
        if za.size < config.min_level_points:
            break
        counts = np.searchsorted(za, za + band, "right") - np.searchsorted(za, za - band, "left")
        zl = za.tolist()  # scalar work below on Python floats (same values, same arithmetic)
        found = False
        tried: list[float] = []
        # best few DISTINCT bands: a riser band can out-count a short tread; skip it then
        for i in np.argsort(-counts, kind="stable").tolist():
            if counts[i] < config.min_level_points or len(tried) >= 3:
                break
            zi = zl[i]
            if any(abs(zi - h) <= band for h in tried):
                continue
            tried.append(zi)
            # bisect_left == np.searchsorted(..., "left") on the sorted heights
            height = _median_sorted(zl, bisect_left(zl, zi - band), bisect_left(zl, zi + band))
            lo, hi = bisect_left(zl, height - band), bisect_left(zl, height + band)
            xs = np.sort(xa[lo:hi])
            # runs of x split at gaps larger than level_gap_m
            ends = [*(np.flatnonzero(np.diff(xs) > config.level_gap_m) + 1).tolist(), xs.size]
            start = 0
            for end in ends:
                if end - start >= config.min_level_points:
                    x_lo, x_med, x_hi = _robust_extent(xs[start:end])
                    if x_hi - x_lo >= config.min_level_length_m:
                        levels.append(Level(height, x_lo, x_hi, x_med, end - start))
                        found = True
                start = end
            if found:
                idx_alive = np.flatnonzero(alive)
                alive[idx_alive[lo:hi]] = False
                break
        if not found:
            break
    return sorted(levels, key=lambda lv: lv.x_median_m)


def classify_levels(
    levels: Sequence[Level], n_points: int, config: TerrainConfig, lower_beyond: bool = False
) -> TerrainKind:
    """Rule steps 2-3 on levels sorted near to far (see the module docstring).

    ``lower_beyond``: the profile has points beyond the farthest level that are lower than it
    by at least ``min_step_m`` (the floor behind an obstacle).
    """
    if n_points < config.min_points or not levels:
        return TerrainKind.UNKNOWN
    # plain floats: a handful of levels (same arithmetic as the numpy form, less overhead)
    heights = [lv.height_m for lv in levels]
    steps = [b - a for a, b in zip(heights[:-1], heights[1:], strict=True)]
    if any(s > config.max_step_m for s in steps):
        return TerrainKind.UNKNOWN
    significant = [s for s in steps if abs(s) >= config.min_step_m]
    if not significant:
        explained = sum(lv.n_points for lv in levels)
        if n_points - explained <= config.max_unexplained_fraction * n_points:
            return TerrainKind.LEVEL
        return TerrainKind.UNKNOWN
    if all(s > 0 for s in significant):
        raised = [lv for lv in levels if lv.height_m - heights[0] >= config.min_step_m]
        if (
            len(significant) == 1
            and len(raised) == 1
            and raised[0] is levels[-1]
            and raised[0].length_m < config.obstacle_max_depth_m
            and lower_beyond
        ):
            return TerrainKind.OBSTACLE
        return TerrainKind.STAIR_UP
    if all(s < 0 for s in significant):
        return TerrainKind.STAIR_DOWN
    # up then back down to the first level: low-high-low (the signs never go up again)
    first_up = significant[0] > 0
    back_to_start = abs(heights[-1] - heights[0]) < config.min_step_m
    ups = [s > 0 for s in significant]
    if first_up and back_to_start and all(a >= b for a, b in zip(ups[:-1], ups[1:], strict=True)):
        return TerrainKind.OBSTACLE
    return TerrainKind.UNKNOWN


@dataclass(frozen=True)
class Face:
    """A vertical segment of the profile: x (median), z range, and whether it rises away from
    the camera (+1) or drops (-1); 0 for a wall (taller than ``max_step_m``)."""

    x_m: float
    z_lo_m: float
    z_hi_m: float
    direction: int


def find_faces(
    pts: NDArray[np.float64], levels: Sequence[Level], config: TerrainConfig
) -> list[Face]:
    """Vertical segments among the points outside every level (rule step 4), near to far."""
    band = config.level_band_m
    in_level = np.zeros(pts.shape[0], dtype=bool)
    for lv in levels:
        in_level |= (
            (np.abs(pts[:, 1] - lv.height_m) <= band)
            & (pts[:, 0] >= lv.x_min_m - config.level_gap_m)
            & (pts[:, 0] <= lv.x_max_m + config.level_gap_m)
        )
    rest = pts[~in_level]
    if rest.shape[0] < config.min_face_points:
        return []
    rest = rest[np.argsort(rest[:, 0], kind="stable")]
    breaks = np.flatnonzero(np.diff(rest[:, 0]) > config.face_gap_m) + 1
    # (x, z_lo, z_hi, direction or None when no surface or earlier face orients it)
    found: list[tuple[float, float, float, int | None]] = []
    starts, ends = np.concatenate(([0], breaks)), np.concatenate((breaks, [rest.shape[0]]))
    for lo, hi in zip(starts, ends, strict=True):
        grp = rest[lo:hi]
        if grp.shape[0] < config.min_face_points:
            continue
        x_med = _median_sorted(grp[:, 0].tolist(), 0, grp.shape[0])  # sorted by x
        core = grp[np.abs(grp[:, 0] - x_med) <= 0.5 * config.face_max_width_m]
        if core.shape[0] < config.min_face_points:
            continue
        zs = np.sort(core[:, 1]).tolist()
        z_lo, z_hi = _percentile_sorted(zs, 5), _percentile_sorted(zs, 95)
        if z_hi - z_lo < config.min_step_m:
            continue
        x_lo_g, x_hi_g = float(core[:, 0].min()), float(core[:, 0].max())
        ctx = config.face_context_m
        before = pts[
            (pts[:, 0] < x_lo_g - 0.5 * config.face_gap_m) & (pts[:, 0] >= x_lo_g - ctx), 1
        ]
        after = pts[(pts[:, 0] > x_hi_g + 0.5 * config.face_gap_m) & (pts[:, 0] <= x_hi_g + ctx), 1]
        mid = 0.5 * (z_lo + z_hi)
        direction: int | None = None
        if z_hi - z_lo > config.max_step_m:
            direction = 0  # a wall, not a step
        elif before.size >= config.min_face_points:
            direction = 1 if _median_sorted(np.sort(before).tolist(), 0, before.size) < mid else -1
        elif after.size >= config.min_face_points:
            direction = 1 if _median_sorted(np.sort(after).tolist(), 0, after.size) > mid else -1
        found.append((float(x_med), float(z_lo), float(z_hi), direction))
    # A face with no surface beside it (a row of risers whose treads are seen too obliquely
    # to return, e.g. a level camera at tread height) takes its direction from the nearest
    # face: a higher face farther away means the surface rises. A lone face stays unoriented
    # and is left out.
    faces: list[Face] = []
    for i, (x, z_lo, z_hi, direction) in enumerate(found):
        if direction is None:
            mid = 0.5 * (z_lo + z_hi)
            if i > 0:
                direction = 1 if 0.5 * (found[i - 1][1] + found[i - 1][2]) < mid else -1
            elif i + 1 < len(found):
                direction = 1 if 0.5 * (found[i + 1][1] + found[i + 1][2]) > mid else -1
            else:
                continue
        faces.append(Face(x, z_lo, z_hi, direction))
    return faces


def classify_faces(faces: Sequence[Face]) -> TerrainKind:
    """Rule step 4: the class the faces give (UNKNOWN when they give none)."""
    dirs = [f.direction for f in faces]
    if not dirs or 0 in dirs:
        return TerrainKind.UNKNOWN
    if all(d > 0 for d in dirs):
        return TerrainKind.STAIR_UP
    if all(d < 0 for d in dirs):
        return TerrainKind.STAIR_DOWN
    first_down = dirs.index(-1)
    if dirs[0] > 0 and all(d < 0 for d in dirs[first_down:]):
        return TerrainKind.OBSTACLE
    return TerrainKind.UNKNOWN


def classify_terrain(
    profile_xz_m: NDArray[np.float64],
    config: TerrainConfig | None = None,
    stand_height_m: float | None = None,
) -> tuple[TerrainKind, list[Level]]:
    """Terrain class of a smoothed sagittal profile and the levels it was decided from.

    Args:
        profile_xz_m: (N, 2) smoothed profile relative to the camera, ground axes, metres.
        stand_height_m: height of the surface the foot last stood on, relative to the camera
            (ground axes), metres; None = unknown (rule step 5 off).

    Returns:
        (kind, levels sorted near to far).
    """
    config = TerrainConfig() if config is None else config
    pts = np.asarray(profile_xz_m, dtype=float).reshape(-1, 2)
    if pts.shape[0] < config.min_points:
        return TerrainKind.UNKNOWN, []
    levels = find_levels(pts, config)
    lower_beyond = _lower_beyond(pts, levels, config)
    kind = classify_levels(levels, pts.shape[0], config, lower_beyond)
    if (
        kind in (TerrainKind.LEVEL, TerrainKind.UNKNOWN)
        and config.use_faces
        and not (_has_wall(levels, config))
    ):
        by_faces = classify_faces(find_faces(pts, levels, config))
        if by_faces != TerrainKind.UNKNOWN:
            kind = by_faces
    if stand_height_m is not None:
        kind = classify_against_stand(pts, kind, levels, stand_height_m, config)
    return kind, levels


def points_under_levels(
    profile_xz_m: NDArray[np.float64], levels: Sequence[Level], config: TerrainConfig
) -> NDArray[np.bool_]:
    """(N,) True for points beneath a level of the same profile (``vio_graph.surface``,
    camera at the origin): at least ``min_step_m`` below the level and more than
    ``under_level_margin_m`` inside its robust x extent, a line of sight that passes at least
    ``min_step_m`` under it more than ``level_band_m`` inside that extent, or a point within
    ``min_step_m`` of a lower level that the level overlaps."""
    margin = config.under_level_margin_m
    if margin is None or not levels:
        return np.zeros(np.shape(profile_xz_m)[0], dtype=bool)
    heights = [lv.height_m for lv in levels]
    x_lo = [lv.x_min_m for lv in levels]
    x_hi = [lv.x_max_m for lv in levels]
    kernels = compiled_kernels()
    if kernels is None:
        return under_levels_mask(
            profile_xz_m,
            heights,
            x_lo,
            x_hi,
            margin,
            config.min_step_m,
            config.min_step_m,
            sight_margin_m=config.level_band_m,
        )
    pts = np.asarray(profile_xz_m, dtype=float).reshape(-1, 2)
    return kernels.under_levels(  # the same mask bit for bit (tests/test_frontend_fastpaths.py)
        np.ascontiguousarray(pts[:, 0]),
        np.ascontiguousarray(pts[:, 1]),
        np.array(heights, dtype=float),
        np.array(x_lo, dtype=float),
        np.array(x_hi, dtype=float),
        float(margin),
        float(config.min_step_m),
        float(config.min_step_m),
        float(config.level_band_m),
        True,
    )


def points_seen_under(
    profile_xz_m: NDArray[np.float64], levels: Sequence[Level], config: TerrainConfig
) -> NDArray[np.bool_]:
    """(N,) True for points seen beneath a surface of the same profile that is no level, with
    ``under_sight_min_points`` (``vio_graph.surface``): a line of sight that passed
    ``min_step_m`` under that many profile points more than ``under_level_margin_m`` nearer
    (``seen_under_mask``: e.g. under the front of a tread whose top is out of view), or the
    floor beyond a level that it runs under and lies in front of (``floor_beyond_slab_mask``)."""
    margin = config.under_level_margin_m
    n = np.shape(profile_xz_m)[0]
    if margin is None or config.under_sight_min_points is None:
        return np.zeros(n, dtype=bool)
    kernels = compiled_kernels()
    if kernels is None:
        under = seen_under_mask(
            profile_xz_m, margin, config.min_step_m, config.under_sight_min_points
        )
    else:  # the same mask bit for bit (tests/test_frontend_fastpaths.py): the sight test
        # and the floor beyond a slab in one compiled call
        pts = np.asarray(profile_xz_m, dtype=float).reshape(-1, 2)
        return kernels.seen_under_floor(
            np.ascontiguousarray(pts[:, 0]),
            np.ascontiguousarray(pts[:, 1]),
            float(margin),
            float(config.min_step_m),
            int(config.under_sight_min_points),
            np.array([lv.height_m for lv in levels], dtype=float),
            np.array([lv.x_min_m for lv in levels], dtype=float),
            np.array([lv.x_max_m for lv in levels], dtype=float),
            float(config.min_step_m),
            int(config.min_level_points),
        )
    if levels:
        under |= floor_beyond_slab_mask(
            profile_xz_m,
            [lv.height_m for lv in levels],
            [lv.x_min_m for lv in levels],
            [lv.x_max_m for lv in levels],
            margin,
            config.min_step_m,
            config.min_step_m,
            config.min_level_points,
        )
    return under


def _lower_beyond(pts: NDArray[np.float64], levels: Sequence[Level], config: TerrainConfig) -> bool:
    """Profile points beyond the farthest level, lower than it by at least ``min_step_m``,
    that are a surface behind it, not only a face: they span at least ``min_level_length_m``
    in x (the floor behind an obstacle; a face seen through a gap under a tread that is out
    of view, e.g. a landing's front under open risers, is a vertical strip)."""
    if not levels:
        return False
    last = levels[-1]
    far = pts[pts[:, 0] > last.x_max_m + config.level_gap_m]  # selected once
    lower = far[far[:, 1] < last.height_m - config.min_step_m]
    if lower.shape[0] == 0:
        return False
    return bool(lower[:, 0].max() - lower[:, 0].min() >= config.min_level_length_m)


def classify_against_stand(
    profile_xz_m: NDArray[np.float64],
    kind: TerrainKind,
    levels: Sequence[Level],
    stand_height_m: float,
    config: TerrainConfig,
) -> TerrainKind:
    """Rule step 5: a frame whose levels are all at one height (``kind`` LEVEL by steps 1-4)
    against the surface the foot last stood on (``stand_height_m``, relative to the camera);
    any other ``kind`` is returned as it is, and so is every kind with ``stand_level`` off.

    The nearest level decides: within ``min_step_m`` of the stand surface -> LEVEL; lower ->
    STAIR_DOWN (the frame sees the floor or tread below the step the foot stands on, whose
    drop is out of view or in the shadow of the nosing); higher -> STAIR_UP, or OBSTACLE by
    the short raised level rule of step 3. No ``max_step_m`` here: the stand surface and the
    level seen need not be neighbours (step over step, the swinging foot looks at the tread
    two rises above the one it left, 36 cm on 18 cm stairs), and a level seen from above is
    below the camera, which bounds the difference anyway."""
    if (
        kind is TerrainKind.STAIR_DOWN
        and config.stand_level
        and config.obstacle_far_side
        and _far_side_down(profile_xz_m, levels, stand_height_m, config)
    ):
        return TerrainKind.OBSTACLE
    if kind is not TerrainKind.LEVEL or not config.stand_level or not levels:
        return kind
    rise = levels[0].height_m - stand_height_m
    if abs(rise) < config.min_step_m:
        return TerrainKind.LEVEL
    if rise < 0:
        return TerrainKind.STAIR_DOWN
    top = levels[-1]
    if (
        len(levels) == 1
        and top.length_m < config.obstacle_max_depth_m
        and _lower_beyond(np.asarray(profile_xz_m, dtype=float).reshape(-1, 2), levels, config)
    ):
        return TerrainKind.OBSTACLE
    return TerrainKind.STAIR_UP


def _far_side_down(
    profile_xz_m: NDArray[np.float64],
    levels: Sequence[Level],
    stand_height_m: float,
    config: TerrainConfig,
) -> bool:
    """Levels that go down from a raised top to the floor the foot stands on, the floor
    reappearing where the top's far edge stops hiding it.

    The last level at least ``min_step_m`` above the stand surface is the top, the next level
    beyond it within ``min_step_m`` of the stand surface the floor. The ray from the camera
    over the top's far edge meets the floor at ``x_e * z_floor / z_top`` (heights relative to
    the camera, below it); the nearest floor point beyond the top must lie within
    ``level_gap_m`` of that: a box's far side hides only its own shadow. A floor seen much
    farther (e.g. through the gap under an open-riser tread, with the next tread hiding the
    rest) is not this evidence. A descending stair seen by the foot that last stood on its
    upper tread has no level above that tread."""
    step = config.min_step_m
    raised = [i for i, lv in enumerate(levels) if lv.height_m - stand_height_m >= step]
    if not raised or raised[0] != 0 or raised[-1] + 1 >= len(levels):
        return False
    top, floor = levels[raised[-1]], levels[raised[-1] + 1]
    if abs(floor.height_m - stand_height_m) >= step or top.height_m >= 0.0:
        return False
    pts = np.asarray(profile_xz_m, dtype=float).reshape(-1, 2)
    band, gap = config.level_band_m, config.level_gap_m
    # the top's last point (its robust extent stops short of the edge)
    on_top = pts[
        (np.abs(pts[:, 1] - top.height_m) <= band)
        & (pts[:, 0] >= top.x_min_m - gap)
        & (pts[:, 0] <= top.x_max_m + gap)
    ]
    edge_x = float(on_top[:, 0].max()) if on_top.shape[0] else top.x_max_m
    on_floor = pts[(pts[:, 0] > edge_x) & (np.abs(pts[:, 1] - floor.height_m) <= band)]
    if on_floor.shape[0] == 0:
        return False
    shadow_end_m = edge_x * floor.height_m / top.height_m
    return float(on_floor[:, 0].min()) <= shadow_end_m + gap


@dataclass(frozen=True)
class SeenObstacle:
    """An obstacle seen with the floor beside it, placed in the front end's dead-reckoned
    frame (the sum of the predicted camera displacements; its origin is arbitrary): the
    floor's and the top's heights and the top's x extent, metres."""

    floor_z_m: float
    top_z_m: float
    top_x_min_m: float
    top_x_max_m: float
    stand_z_m: float | None = None  # the surface the foot stood on then (None: unknown)


def seen_obstacle(
    levels: Sequence[Level],
    camera_xz_m: NDArray[np.float64],
    config: TerrainConfig,
    stand_z_m: float | None = None,
) -> SeenObstacle | None:
    """The obstacle a frame classified OBSTACLE shows: its lowest level is the floor, its
    highest the top (at least ``min_step_m`` higher), placed at the camera position
    ``camera_xz_m``; None without two such levels (e.g. an obstacle decided by its faces)."""
    if len(levels) < 2:
        return None
    floor = min(levels, key=lambda lv: lv.height_m)
    top = max(levels, key=lambda lv: lv.height_m)
    if top.height_m - floor.height_m < config.min_step_m:
        return None
    cx, cz = float(camera_xz_m[0]), float(camera_xz_m[1])
    return SeenObstacle(
        floor.height_m + cz, top.height_m + cz, top.x_min_m + cx, top.x_max_m + cx, stand_z_m
    )


def recall_obstacle(
    kind: TerrainKind,
    levels: Sequence[Level],
    camera_xz_m: NDArray[np.float64],
    seen: SeenObstacle | None,
    config: TerrainConfig,
    stand_z_m: float | None = None,
    frame_kind: TerrainKind | None = None,
) -> tuple[TerrainKind, SeenObstacle | None]:
    """Rule step 6 (``obstacle_memory``): the obstacle seen before decides a frame that shows
    only part of it.

    A frame whose own geometry (``frame_kind``, rule steps 1-4; default ``kind``) says
    OBSTACLE replaces the remembered obstacle (when its levels give a floor and a top); an
    OBSTACLE of step 5 (the stand surface) is not remembered: on open risers the floor seen
    through the gap behind a tread passes the far-side test of step 5. A later frame
    classified LEVEL, STAIR_UP or STAIR_DOWN whose every level is
    either the remembered floor or the remembered top (heights within ``min_step_m``, or half
    the obstacle's height when lower; the top also overlapping the remembered top in x within
    ``level_gap_m``), with at least one on the top, is OBSTACLE: the same box seen with its far
    side out of view or in its own shadow. A level at any other height leaves the class as it
    is; one at least ``min_step_m`` above the remembered top (the next tread of a stair) also
    forgets the obstacle, and so does a foot that has stood on a surface ``min_step_m`` or
    more off the one it stood on when the obstacle was seen (it climbed a step).

    Args:
        camera_xz_m: (2,) camera position in the frame ``seen`` was placed in, metres.
        stand_z_m: height of the surface the foot last stood on, same frame (None: unknown).

    Returns:
        (class, the obstacle to remember); (``kind``, None) with ``obstacle_memory`` off.
    """
    if not config.obstacle_memory:
        return kind, None
    if (
        seen is not None
        and seen.stand_z_m is not None
        and stand_z_m is not None
        and abs(stand_z_m - seen.stand_z_m) >= config.min_step_m
    ):
        seen = None  # the foot stands on another surface now
    if kind is TerrainKind.OBSTACLE:
        own = kind if frame_kind is None else frame_kind
        new = seen_obstacle(levels, camera_xz_m, config, stand_z_m)
        return kind, (seen if new is None or own is not TerrainKind.OBSTACLE else new)
    if seen is None or not levels or kind not in _RECALL_KINDS:
        return kind, seen
    cx, cz = float(camera_xz_m[0]), float(camera_xz_m[1])
    tol = min(config.min_step_m, 0.5 * (seen.top_z_m - seen.floor_z_m))
    gap = config.level_gap_m
    x_lo, x_hi = seen.top_x_min_m, seen.top_x_max_m
    on_top = False
    for lv in levels:
        z = lv.height_m + cz
        if abs(z - seen.floor_z_m) < tol:
            continue
        lo, hi = lv.x_min_m + cx, lv.x_max_m + cx
        overlaps = lo <= seen.top_x_max_m + gap and hi >= seen.top_x_min_m - gap
        if abs(z - seen.top_z_m) < tol and overlaps:
            on_top = True
            x_lo, x_hi = min(x_lo, lo), max(x_hi, hi)
            continue
        if z - seen.top_z_m >= config.min_step_m:
            return kind, None  # a surface above the top: a stair, not that obstacle
        return kind, seen
    if not on_top:
        return kind, seen
    stand = seen.stand_z_m if seen.stand_z_m is not None else stand_z_m
    return TerrainKind.OBSTACLE, SeenObstacle(seen.floor_z_m, seen.top_z_m, x_lo, x_hi, stand)


_RECALL_KINDS = (TerrainKind.LEVEL, TerrainKind.STAIR_UP, TerrainKind.STAIR_DOWN)


def _has_wall(levels: Sequence[Level], config: TerrainConfig) -> bool:
    """An upward height difference between consecutive levels above ``max_step_m``."""
    h = [lv.height_m for lv in levels]
    return any(b - a > config.max_step_m for a, b in zip(h[:-1], h[1:], strict=True))


@dataclass(frozen=True)
class ConfusionTable:
    """Counts of (true, predicted) terrain classes.

    ``counts[i, j]`` = frames whose true class is ``labels[i]`` and predicted ``labels[j]``.
    """

    labels: tuple[TerrainKind, ...]
    counts: NDArray[np.int64]

    @property
    def total(self) -> int:
        return int(self.counts.sum())

    @property
    def accuracy(self) -> float:
        """Fraction of frames on the diagonal (nan when empty)."""
        return float(np.trace(self.counts) / self.total) if self.total else float("nan")

    def recall(self) -> dict[TerrainKind, float]:
        """Per true class: correct / frames of that class (nan when the class is absent)."""
        rows = self.counts.sum(axis=1)
        with np.errstate(invalid="ignore", divide="ignore"):
            r = np.diag(self.counts) / rows
        return {lab: float(v) for lab, v in zip(self.labels, r, strict=True)}

    def as_rows(self) -> list[list[str]]:
        """Printable table: header row then one row per true class."""
        head = ["true \\ predicted", *[lab.value for lab in self.labels]]
        body = [
            [lab.value, *[str(int(c)) for c in row]]
            for lab, row in zip(self.labels, self.counts, strict=True)
        ]
        return [head, *body]


def confusion_table(
    true: Sequence[TerrainKind | str], predicted: Sequence[TerrainKind | str]
) -> ConfusionTable:
    """Confusion table over all TerrainKind labels from paired true/predicted classes.

    Raises:
        FrontendError: if the sequences differ in length or hold an unknown label.
    """
    if len(true) != len(predicted):
        raise FrontendError(f"{len(true)} true labels but {len(predicted)} predictions")
    labels = tuple(TerrainKind)
    index = {lab: i for i, lab in enumerate(labels)}
    counts = np.zeros((len(labels), len(labels)), dtype=np.int64)
    if len(true):
        try:
            ti = np.array([index[TerrainKind(t)] for t in true])
            pi = np.array([index[TerrainKind(p)] for p in predicted])
        except ValueError as exc:
            raise FrontendError(f"unknown terrain label: {exc}") from exc
        np.add.at(counts, (ti, pi), 1)
    return ConfusionTable(labels=labels, counts=counts)
