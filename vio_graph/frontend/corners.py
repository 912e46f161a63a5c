"""Corner feature extraction with RANSAC (paper Section II.A.2, Fig. 2).

Paper: fit the horizontal line with most inliers, remove its inliers, fit a second horizontal
line, compare the two lines' median heights and take the feature points at the end of the
higher line (thresholds d = 0.02 m, w = 0.05 m).

vio_graph's reading of the parts the paper leaves open:

- **Horizontal line RANSAC.** A horizontal line z = c has one parameter, so a hypothesis is one
  sampled point's height. ``n_hypotheses`` heights are drawn with the caller's
  ``np.random.Generator`` (deterministic given the seed); inliers are |z - c| <= d, counted for
  all hypotheses at once with ``searchsorted`` on the sorted heights. The winner is refined to
  the median height of its inliers (the paper's "median z coordinate") and its inliers recounted.
- **Lines are surfaces.** A line whose main run of inliers spans less than
  ``min_line_length_m`` in x is a band across a riser seen head-on (it can out-count a tread
  cut short by the field of view or by a missing band); its points are set aside and RANSAC
  runs again.
- **Second line.** Fitted on the remaining points with hypotheses at least
  ``min_line_separation_m`` from the first line, so that the noise fringe of the first surface
  (points just outside the d band) cannot become the "second line".
- **Which end.** The convex edge faces the lower line: for STAIR_UP and OBSTACLE it is the NEAR
  end (smallest x) of the higher line (stair nosing / obstacle front-top edge, with the riser or
  the obstacle face below it); for STAIR_DOWN it is the FAR end (largest x) of the higher line
  (the nosing of the tread the user stands on; the riser below faces away and is not seen).
  For other classes the end is the one on the side of the lower line's median x.
- **Which part of the line.** The higher line's inliers are split into runs at x gaps larger
  than ``max_gap_m`` and the run with most points is the tread; its extreme x at the chosen
  end, with the line's height, is the first edge estimate.
- **Nosing = riser line meets tread line.** Real ToF profiles (pico flexx2) lose a band of
  3-6 cm of tread right behind the nosing: the driver's flying-pixel filter removes the mixed
  pixels at the depth discontinuity. The end of the tread run is then 3-8 cm behind the
  nosing. So the edge is placed where the face below it (riser, nosing block, obstacle side)
  meets the tread: the face candidates are the points between ``face_top_margin_m`` and
  ``face_band_m`` (or, if too few, w) below the tread line (the top margin skips the
  corner that kNN smoothing rounds) within
  ``max_nosing_gap_m`` in front of the tread end; they are grouped into vertical lines
  (x clusters ``face_cluster_m`` wide) and the face is the line nearest the tread's edge side
  (the camera side for stairs up) with at least ``min_face_points`` points. With a nosing
  overhang the face just below the tread is the nosing block, which sits in front of the
  riser; choosing the foremost supported line puts the corner at the nosing tip, not at the
  riser. In the gravity-aligned ground frame the tread line is horizontal and the face line
  vertical, so the intersection is (face x, tread height). When no face is supported the
  edge stays at the tread end and the corner says so (``has_face`` False): the end of the
  tread alone may be the border of a missing band (on simulated stairs with 2-6 cm bands such
  corners were 2-5 cm off), so the tracker widens its x uncertainty; with
  ``near_edge_needs_face`` no such corner is given at all.
  At the far end (stairs down) the riser faces away and no face can be seen: the edge x is
  the median x of the points just below the end of the run (within d in x, d to w below),
  when there are 3, else the run end. A missing band there shortens the tread and the edge
  moves with it (a known limit: nothing in one frame shows where the tread really ended).
- **Window w.** Feature points are ALL profile points in the square window
  |x - x_edge| <= w, |z - z_edge| <= w: the last w of the tread plus the top w of the riser
  (or obstacle face) below the edge. When the tread run starts behind the nosing (a missing
  band), the window reaches that much farther along the tread, so it still holds w of
  tread. The L shape constrains both x and z in ICP.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Literal

import numpy as np
from numpy.typing import NDArray

from vio_graph.frontend.config import CornerConfig
from vio_graph.frontend.icp import compiled_kernels
from vio_graph.types import TerrainKind


@dataclass(frozen=True)
class HorizontalLine:
    """A RANSAC horizontal line z = height_m and the mask of its inliers in the input points."""

    height_m: float
    inliers: NDArray[np.bool_]

    @property
    def n_inliers(self) -> int:
        return int(self.inliers.sum())


@dataclass(frozen=True)
class CornerFeature:
    """Feature points at a terrain corner, relative to the camera, ground axes (metres).

    ``feature_points_xz_m`` (K, 2); ``mean_xz_m`` (2,) their mean (the paper's association
    quantity); ``edge_xz_m`` (2,) the edge point estimate; ``side`` which end of the higher
    line the edge is at.
    """

    feature_points_xz_m: NDArray[np.float64]
    mean_xz_m: NDArray[np.float64]
    edge_xz_m: NDArray[np.float64]
    upper_height_m: float
    lower_height_m: float
    upper_inliers: int
    lower_inliers: int
    side: Literal["near", "far"]
    has_face: bool = False
    """True when the edge x comes from a supported face line below the tread (riser / nosing
    block / obstacle side), False when it is the end of the tread run."""


def ransac_horizontal_line(
    points_xz_m: NDArray[np.float64],
    inlier_distance_m: float,
    n_hypotheses: int,
    rng: np.random.Generator,
    exclude_heights_m: tuple[float, ...] = (),
    min_separation_m: float = 0.0,
    candidates: NDArray[np.bool_] | None = None,
) -> HorizontalLine | None:
    """Horizontal line with the most inliers (|z - c| <= d) among ``candidates`` points.

    Args:
        points_xz_m: (N, 2) points, metres.
        inlier_distance_m: the paper's d.
        n_hypotheses: sampled heights.
        rng: random generator (the only source of randomness).
        exclude_heights_m: hypotheses closer than ``min_separation_m`` to these are skipped.
        candidates: (N,) mask of points that may vote and be inliers (default: all).

    Returns:
        The line refined to the median height of its inliers, or None if no point is left.

    Compiled after the random draws (``compiled.horizontal_line``, numba) when the front
    end's kernels are on: the same draws, the same line bit for bit as
    :func:`ransac_horizontal_line_reference`.
    """
    kernels = compiled_kernels()
    if kernels is None:
        return ransac_horizontal_line_reference(
            points_xz_m,
            inlier_distance_m,
            n_hypotheses,
            rng,
            exclude_heights_m,
            min_separation_m,
            candidates,
        )
    pts = np.asarray(points_xz_m, dtype=float)
    mask = np.ones(pts.shape[0], bool) if candidates is None else np.asarray(candidates, bool)
    n = int(np.count_nonzero(mask))
    if n == 0:
        return None
    draws = rng.integers(0, n, size=n_hypotheses)
    height, inliers = kernels.horizontal_line(
        pts[:, 1],
        mask,
        draws,
        np.asarray(exclude_heights_m, dtype=float).reshape(-1),
        float(min_separation_m),
        float(inlier_distance_m),
    )
    if inliers.shape[0] != pts.shape[0]:
        return None
    return HorizontalLine(height_m=float(height), inliers=inliers)


def ransac_horizontal_line_reference(
    points_xz_m: NDArray[np.float64],
    inlier_distance_m: float,
    n_hypotheses: int,
    rng: np.random.Generator,
    exclude_heights_m: tuple[float, ...] = (),
    min_separation_m: float = 0.0,
    candidates: NDArray[np.bool_] | None = None,
) -> HorizontalLine | None:
    """numpy path of :func:`ransac_horizontal_line`."""
    pts = np.asarray(points_xz_m, dtype=float)
    mask = np.ones(pts.shape[0], bool) if candidates is None else np.asarray(candidates, bool)
    z_all = pts[:, 1]
    z = np.sort(z_all[mask])
    if z.size == 0:
        return None
    hyp = z[rng.integers(0, z.size, size=n_hypotheses)]
    for h in exclude_heights_m:
        hyp = hyp[np.abs(hyp - h) >= min_separation_m]
    if hyp.size == 0:
        return None
    d = inlier_distance_m
    counts = np.searchsorted(z, hyp + d, "right") - np.searchsorted(z, hyp - d, "left")
    best = hyp[np.argmax(counts)]
    inl = z[np.abs(z - best) <= d]  # sorted: its median is the middle (np.median's value)
    height = _median_of_sorted(inl)
    return HorizontalLine(height_m=height, inliers=mask & (np.abs(z_all - height) <= d))


def _median_of_sorted(values: NDArray[np.float64]) -> float:
    """np.median of sorted values: the middle one, or (a + b) / 2 of the middle two."""
    n = values.size
    return float(values[n // 2]) if n % 2 else float((values[n // 2 - 1] + values[n // 2]) / 2)


def _largest_run(x: NDArray[np.float64], max_gap_m: float) -> NDArray[np.float64]:
    """The longest (most points) run of sorted x values without a gap > max_gap_m (compiled
    when the front end's kernels are on: ``compiled.largest_run``, the same values)."""
    kernels = compiled_kernels()
    if kernels is None:
        return _largest_run_reference(x, max_gap_m)
    return kernels.largest_run(np.ascontiguousarray(x, dtype=float), float(max_gap_m))


def _largest_run_reference(x: NDArray[np.float64], max_gap_m: float) -> NDArray[np.float64]:
    """numpy path of :func:`_largest_run`."""
    xs = np.sort(x)
    breaks = np.flatnonzero(np.diff(xs) > max_gap_m) + 1
    starts = np.concatenate(([0], breaks))
    ends = np.concatenate((breaks, [xs.size]))
    i = int(np.argmax(ends - starts))
    return xs[starts[i] : ends[i]]


def _surface_line(
    pts: NDArray[np.float64],
    cfg: CornerConfig,
    rng: np.random.Generator,
    exclude_heights_m: tuple[float, ...] = (),
    candidates: NDArray[np.bool_] | None = None,
    attempts: int = 3,
) -> HorizontalLine | None:
    """RANSAC horizontal line that is a surface, not a band across a vertical face.

    A riser seen head-on can hold more points in a 2d-tall band than a tread that the field of
    view or a missing band cut short. A line whose main run of inliers spans less than
    ``min_line_length_m`` in x is such a band: its points are removed from the candidates and
    RANSAC runs again (at most ``attempts`` times). The first attempt is the paper's line.
    """
    mask = np.ones(pts.shape[0], bool) if candidates is None else candidates.copy()
    for _ in range(attempts):
        line = ransac_horizontal_line(
            pts,
            cfg.inlier_distance_m,
            cfg.n_hypotheses,
            rng,
            exclude_heights_m,
            cfg.min_line_separation_m,
            mask,
        )
        if line is None or line.n_inliers < cfg.min_line_inliers:
            return line
        run = _largest_run(pts[line.inliers, 0], cfg.max_gap_m)
        if run[-1] - run[0] >= cfg.min_line_length_m:
            return line
        mask &= ~line.inliers
    return None


def extract_corner(
    profile_xz_m: NDArray[np.float64],
    rng: np.random.Generator,
    config: CornerConfig | None = None,
    terrain: TerrainKind = TerrainKind.UNKNOWN,
) -> CornerFeature | None:
    """Paper Fig. 2: two RANSAC horizontal lines, feature points at the higher line's edge.

    Args:
        profile_xz_m: (N, 2) smoothed profile relative to the camera, ground axes, metres.
        rng: random generator for RANSAC (deterministic given its seed).
        terrain: class of the profile; decides the end of the higher line (module docstring).

    Returns:
        The corner, or None when two lines or enough feature points are not found.
    """
    cfg = CornerConfig() if config is None else config
    pts = np.asarray(profile_xz_m, dtype=float).reshape(-1, 2)
    if pts.shape[0] < 2 * cfg.min_line_inliers:
        return None
    kernels = compiled_kernels()
    if kernels is None:
        return extract_corner_reference(pts, rng, cfg, terrain)
    # compiled: steps 1-5 below in one call (compiled.corner), the same draws from rng
    if terrain in (TerrainKind.STAIR_UP, TerrainKind.OBSTACLE):
        side_code = 0
    elif terrain == TerrainKind.STAIR_DOWN:
        side_code = 1
    else:
        side_code = 2
    found, ex, ez, h_up, h_lo, n_up, n_lo, near, has_face, in_window = kernels.corner(
        np.ascontiguousarray(pts[:, 0]),
        np.ascontiguousarray(pts[:, 1]),
        kernels.rng_ref(rng),  # a handle: much cheaper to pass than the Generator
        side_code,
        cfg.n_hypotheses,
        cfg.inlier_distance_m,
        cfg.window_m,
        cfg.min_line_separation_m,
        cfg.min_line_inliers,
        cfg.max_gap_m,
        cfg.min_line_length_m,
        cfg.max_nosing_gap_m,
        cfg.face_top_margin_m,
        cfg.face_band_m,
        cfg.face_cluster_m,
        cfg.min_face_points,
        cfg.near_edge_needs_face,
        cfg.min_feature_points,
    )
    if found != 0:
        return None
    features = pts[in_window]
    return CornerFeature(
        feature_points_xz_m=features,
        mean_xz_m=np.add.reduce(features, axis=0) / features.shape[0],  # = .mean(axis=0)
        edge_xz_m=np.array([ex, ez]),
        upper_height_m=float(h_up),
        lower_height_m=float(h_lo),
        upper_inliers=int(n_up),
        lower_inliers=int(n_lo),
        side="near" if near else "far",
        has_face=bool(has_face),
    )


def extract_corner_reference(
    pts: NDArray[np.float64],
    rng: np.random.Generator,
    cfg: CornerConfig,
    terrain: TerrainKind = TerrainKind.UNKNOWN,
) -> CornerFeature | None:
    """numpy path of :func:`extract_corner` (the reference of ``compiled.corner``); ``pts``
    (N, 2) with at least 2 ``min_line_inliers`` rows."""
    # 1. horizontal line with the most inliers
    first = _surface_line(pts, cfg, rng)
    if first is None or first.n_inliers < cfg.min_line_inliers:
        return None
    # 2. remove its inliers, fit the second horizontal line
    second = _surface_line(pts, cfg, rng, (first.height_m,), ~first.inliers)
    if second is None or second.n_inliers < cfg.min_line_inliers:
        return None
    # 3. compare the median heights: the higher line carries the edge
    upper, lower = (first, second) if first.height_m > second.height_m else (second, first)
    upper_x = pts[upper.inliers, 0]
    if terrain in (TerrainKind.STAIR_UP, TerrainKind.OBSTACLE):
        side: Literal["near", "far"] = "near"
    elif terrain == TerrainKind.STAIR_DOWN:
        side = "far"
    else:
        side = "near" if np.median(pts[lower.inliers, 0]) < np.median(upper_x) else "far"
    # 4. edge = end of the main run of the higher line, at the line's height
    run = _largest_run(upper_x, cfg.max_gap_m)
    edge = np.array([run[0] if side == "near" else run[-1], upper.height_m])
    # 4b. nosing = where the face line below the tread meets the tread line (module docstring)
    face_x = _face_line_x(pts, edge, cfg) if side == "near" else None
    if side == "near" and face_x is None and cfg.near_edge_needs_face:
        return None  # the tread end alone may be a band's border, centimetres behind the nosing
    if face_x is not None:
        edge[0] = face_x
        # tread height from the tread side only: riser points within d below the tread pull
        # the median of the band down when a gap leaves few tread points
        tread = upper.inliers & (pts[:, 0] - face_x > cfg.face_top_margin_m)
        if np.count_nonzero(tread) >= cfg.min_face_points:
            edge[1] = _median_of_sorted(np.sort(pts[tread, 1]))
    elif side == "far":
        # the far end (stairs down): the riser faces away; points just below the end (mixed
        # pixels, the rounded end) fix x better than the smoothing-rounded end of the tread
        d, w = cfg.inlier_distance_m, cfg.window_m
        below = (
            (np.abs(pts[:, 0] - edge[0]) <= d)
            & (pts[:, 1] < edge[1] - d)
            & (pts[:, 1] >= edge[1] - w)
        )
        if np.count_nonzero(below) >= 3:
            edge[0] = _median_of_sorted(np.sort(pts[below, 0]))
    # 5. feature points: square window of half-size w at the edge (tread end + riser top)
    #    (with a missing band behind the nosing the window reaches past the band on the tread
    #    side by the band's length, so that it still holds w of tread to fix z)
    dx = pts[:, 0] - edge[0]
    band = max(0.0, float(run[0]) - edge[0]) if face_x is not None else 0.0
    in_window = (
        (dx >= -cfg.window_m)
        & (dx <= cfg.window_m + band)
        & (np.abs(pts[:, 1] - edge[1]) <= cfg.window_m)
    )
    features = pts[in_window]
    if features.shape[0] < cfg.min_feature_points:
        return None
    return CornerFeature(
        feature_points_xz_m=features,
        mean_xz_m=np.add.reduce(features, axis=0) / features.shape[0],  # = .mean(axis=0)
        edge_xz_m=edge,
        upper_height_m=upper.height_m,
        lower_height_m=lower.height_m,
        upper_inliers=upper.n_inliers,
        lower_inliers=lower.n_inliers,
        side=side,
        has_face=face_x is not None,
    )


def _face_line_x(
    pts: NDArray[np.float64], tread_end_xz_m: NDArray[np.float64], cfg: CornerConfig
) -> float | None:
    """x of the vertical face line that meets the tread at its edge, or None if unsupported.

    The tread lies at x > the edge (the near end of the higher line). Candidates: points
    between ``face_top_margin_m`` and ``face_band_m`` below the tread
    height (between ``face_top_margin_m`` and ``window_m`` when that band holds too few),
    from ``max_nosing_gap_m`` before the tread end (the side away from the tread) to
    ``inlier_distance_m`` past it. Sorted by x towards the tread's edge side, they are cut into
    clusters at x steps larger than ``face_cluster_m``; the foremost cluster with at least
    ``min_face_points`` points is the face, its median x the line.
    """
    x_end, h = float(tread_end_xz_m[0]), float(tread_end_xz_m[1])
    ahead = x_end - pts[:, 0]  # > 0: in front of the tread end, away from the tread
    depth = h - pts[:, 1]
    near = (
        (ahead <= cfg.max_nosing_gap_m)
        & (ahead >= -cfg.inlier_distance_m)
        & (depth >= cfg.face_top_margin_m)
    )
    cand = near & (depth <= cfg.face_band_m)  # the face right below the tread first
    if np.count_nonzero(cand) < cfg.min_face_points:
        cand = near & (depth <= cfg.window_m)
        if np.count_nonzero(cand) < cfg.min_face_points:
            return None
    a = np.sort(ahead[cand])[::-1]  # foremost (farthest from the tread) first
    breaks = np.flatnonzero(-np.diff(a) > cfg.face_cluster_m) + 1
    starts, ends = np.concatenate(([0], breaks)), np.concatenate((breaks, [a.size]))
    for lo, hi in zip(starts, ends, strict=True):
        if hi - lo >= cfg.min_face_points:
            return float(x_end - _median_of_sorted(a[lo:hi][::-1]))
    return None
