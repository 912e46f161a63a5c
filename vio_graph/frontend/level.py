"""Tilt of the level surfaces in a sagittal profile: a pitch measurement for the attitude.

Floors, stair treads and obstacle tops are horizontal. In the paper's ground frame (eq. 2)
they should appear as horizontal lines; if they appear tilted by an angle alpha, the attitude
used to rotate the slice has a pitch error of alpha. The vendor orientation of an MTi-1 is
off by ~1 deg RMS (slowly varying), which costs twice:

* ICP on a floor only constrains the direction normal to the floor, so with the floor tilted
  by alpha a forward motion dx reads as a height change alpha * dx (2 deg over 0.6 m: 2 cm);
* the toe is ~0.45 m from the knee along the leg, so 1 deg of shank pitch moves it ~8 mm.

:func:`measure_surface_tilt` fits up to four near-horizontal lines with a shared slope
(RANSAC among pairs whose slope is within ``max_tilt_rad``, then weighted least squares on
the inliers) and returns the tilt with its standard error. ``vio_graph.filter.attitude.
PitchOffsetFilter`` turns successive measurements into a pitch correction. Pure numpy, no
I/O.

Limitation: a ramp steeper than the gate of ``PitchOffsetFilter`` is rejected, a gentler one
(< ~1 deg) biases the attitude by its slope while it is the dominant surface in view.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
from numpy.typing import NDArray

from vio_graph.frontend.icp import compiled_kernels

_add_reduce, _max_reduce, _min_reduce = np.add.reduce, np.maximum.reduce, np.minimum.reduce

#: RANSAC hypotheses (pairs of points) per line search
_N_HYPOTHESES = 48


@dataclass(frozen=True)
class SurfaceTilt:
    """Tilt (rad) of the level surfaces in a profile: positive = they rise with x, i.e. the
    slice must be rotated by rot_y(+tilt_rad) to level them. ``sigma_rad`` is the standard
    error of the least-squares slope; ``n_inliers`` and ``extent_m`` (summed x extent of the
    lines) describe the support; ``n_lines`` is how many lines were used."""

    tilt_rad: float
    sigma_rad: float
    n_inliers: int
    extent_m: float
    n_lines: int
    #: per line: (height m, its sigma m, x min m, x max m) relative to the camera, the height
    #: taken after levelling the slice by the common tilt (``LevelLine``)
    lines: tuple[LevelLine, ...] = ()
    #: the vertical faces disagree with this tilt (``filter.attitude.SurfaceBendTest``): the
    #: surfaces are bent by depth errors, the tilt is not a pitch measurement (set by the
    #: estimator; the lines' heights are kept)
    bent: bool = False


@dataclass(frozen=True)
class LevelLine:
    """A level surface in the slice (tread, landing, floor, obstacle top): its height
    relative to the camera (m, ground z, the slice levelled by the common tilt about the
    camera) with its sigma (m: the line's own residual noise over its points, correlated
    points counted as fewer, and the tilt's uncertainty at the line's distance), and its x
    extent relative to the camera (m). ``x_mid_m`` is the mean x of its points (the lever of
    the common tilt: a tilt error tau moves this height by x_mid_m * tau, the same tau for
    every line of the slice) and ``noise_sigma_m`` the part of ``sigma_m`` that is the line's
    own (residual noise only, without the tilt)."""

    height_m: float
    sigma_m: float
    x_min_m: float
    x_max_m: float
    x_mid_m: float = 0.0
    noise_sigma_m: float = 0.0
    #: the height (m, at the camera) refitted with the errors along the camera rays
    #: (:func:`_ray_refit`), when asked for (``measure_surface_tilt(ray_heights=True)``)
    ray_height_m: float | None = None


def _best_line(
    x: NDArray[np.float64],
    z: NDArray[np.float64],
    max_slope: float,
    inlier_m: float,
    rng: np.random.Generator,
) -> NDArray[np.bool_] | None:
    """Inlier mask of the near-horizontal line with the most inliers (None if none).

    The hypotheses are scored compiled (``compiled.best_line``, numba) when numba is installed:
    the same draws and arithmetic as :func:`_best_line_reference`, the same mask."""
    kernels = compiled_kernels()
    if kernels is None:
        return _best_line_reference(x, z, max_slope, inlier_m, rng)
    n = x.shape[0]
    i = rng.integers(0, n, _N_HYPOTHESES)
    j = rng.integers(0, n, _N_HYPOTHESES)
    xc, zc = np.ascontiguousarray(x, dtype=float), np.ascontiguousarray(z, dtype=float)
    a, s = kernels.best_line(xc, zc, i, j, max_slope, inlier_m)
    if a < 0:
        return None
    return np.abs(zc - zc[a] - s * (xc - xc[a])) < inlier_m


def _best_line_reference(
    x: NDArray[np.float64],
    z: NDArray[np.float64],
    max_slope: float,
    inlier_m: float,
    rng: np.random.Generator,
) -> NDArray[np.bool_] | None:
    """numpy path of :func:`_best_line` (all hypotheses' residuals at once)."""
    n = x.shape[0]
    i = rng.integers(0, n, _N_HYPOTHESES)
    j = rng.integers(0, n, _N_HYPOTHESES)
    dx = x[j] - x[i]
    ok = np.abs(dx) > 0.03
    slope = np.where(ok, (z[j] - z[i]) / np.where(ok, dx, 1.0), np.inf)
    ok &= np.abs(slope) <= max_slope
    if not ok.any():
        return None
    i, s = i[ok], slope[ok]
    resid = np.abs(z[None, :] - z[i, None] - s[:, None] * (x[None, :] - x[i, None]))
    inl = resid < inlier_m
    return inl[int(np.argmax(inl.sum(axis=1)))]


def _mean(a: NDArray[np.float64]) -> float:
    """np.mean of a non-empty 1-D float64 array without its dispatch (~6 us a call): the same
    pairwise sum (np.add.reduce), one float64 division, so the same float."""
    return float(_add_reduce(a)) / a.shape[0]


def _ptp(a: NDArray[np.float64]) -> float:
    """np.ptp of a non-empty 1-D array: max - min, the same float."""
    return float(_max_reduce(a) - _min_reduce(a))


def _refine(
    x: NDArray[np.float64], z: NDArray[np.float64], mask: NDArray[np.bool_], inlier_m: float
) -> NDArray[np.bool_]:
    """Least-squares line on the inliers, then re-select inliers once against it."""
    if mask.sum() < 3:
        return mask
    xm, zm = x[mask], z[mask]
    x0, z0 = _mean(xm), _mean(zm)
    xc = xm - x0
    s = float(xc @ (zm - z0)) / max(float(xc @ xc), 1e-12)
    return np.abs(z - z0 - s * (x - x0)) < inlier_m


def measure_surface_tilt(
    profile_xz_m: NDArray[np.float64],
    rng: np.random.Generator,
    max_tilt_rad: float = np.radians(5.0),
    inlier_m: float = 0.004,
    min_points: int = 25,
    min_extent_m: float = 0.12,
    max_lines: int = 4,
    correlated_points: float = 5.0,
    end_trim_m: float = 0.0,
    ray_fit: str = "off",
    isotropic_sigma_m: float = 0.0,
    ray_heights: bool = False,
) -> SurfaceTilt | None:
    """Common tilt of the near-horizontal lines of a profile (floor, treads, obstacle top).

    Up to ``max_lines`` lines are found one after the other (RANSAC, then least squares on the
    inliers, then their inliers are removed). The tilt is the weighted least-squares slope
    shared by all of them, each line with its own height and its own noise (from its
    residuals: ToF noise grows with range and incidence, so far treads count less).

    Args:
        profile_xz_m: (N, 2) smoothed sagittal profile in the ground frame, metres.
        rng: random generator for the RANSAC hypotheses.
        max_tilt_rad: only lines within this angle of horizontal are considered.
        inlier_m: vertical inlier distance (m).
        min_points, min_extent_m: support a line needs (inliers, x extent in metres).
        max_lines: most lines used.
        correlated_points: kNN smoothing averages ~k raw points into each profile point, so
            neighbouring points are correlated; the slope variance is multiplied by this.
        end_trim_m: the slope is fitted without the inliers this close (m, along x) to
            either end of their line. kNN smoothing rounds a convex nosing down and fills a
            concave tread-riser corner up; both ends of a stair tread are such corners, on
            the same sides on every tread, so untrimmed they tilt every tread the same way
            (a bias, not noise: it drifts the attitude, then x, on a long stair).
        ray_fit: "off" (vertical least squares), "heights" (the lines' heights refitted
            with their errors along the camera rays, :func:`_ray_refit`; the tilt stays the
            vertical fit's) or "all" (tilt and heights from the ray fit). Vertical least
            squares leans towards the rays on a surface seen at a slant (ToF errors lie along
            the ray).
        isotropic_sigma_m: the part of a profile point's error that is not along its ray
            (m, each axis; the ray fit's second variance, see :func:`_ray_refit`).
        ray_heights: also give each line the ray fit's height (``LevelLine.ray_height_m``),
            whatever ``ray_fit`` says of ``height_m`` and the tilt (for a consumer that wants
            the ray-fitted heights while the tilt and ``height_m`` stay the vertical fit's).

    Returns:
        The tilt, or None when no line has the support (e.g. only a riser in view).
    """
    p = np.asarray(profile_xz_m, dtype=float)
    if p.ndim != 2 or p.shape[0] < min_points or p.shape[1] != 2:
        return None
    kernels = compiled_kernels()
    if ray_fit not in ("off", "heights", "all"):
        raise ValueError(f"ray_fit must be 'off', 'heights' or 'all', not {ray_fit!r}")
    if kernels is None or ray_fit != "off" or ray_heights:
        return _surface_tilt_numpy(
            p,
            rng,
            max_tilt_rad,
            inlier_m,
            min_points,
            min_extent_m,
            max_lines,
            correlated_points,
            end_trim_m,
            ray_fit,
            isotropic_sigma_m,
            ray_heights,
        )
    # compiled: the whole search in one call (compiled.surface_tilt), the same draws from rng
    status, s, sigma_slope, n_inliers, rows = kernels.surface_tilt(
        np.ascontiguousarray(p[:, 0]),
        np.ascontiguousarray(p[:, 1]),
        kernels.rng_ref(rng),  # a handle: much cheaper to pass than the Generator
        _N_HYPOTHESES,
        float(np.tan(max_tilt_rad)),
        float(inlier_m),
        int(min_points),
        float(min_extent_m),
        int(max_lines),
        float(end_trim_m),
        float(correlated_points),
    )
    if status != 0:
        return None
    extent = 0.0
    levels = []
    for height, sigma, x_lo, x_hi, x_mid, noise_sigma in rows.tolist():
        extent += x_hi - x_lo
        levels.append(LevelLine(height, sigma, x_lo, x_hi, x_mid, noise_sigma))
    return SurfaceTilt(
        tilt_rad=float(np.arctan(s)),
        sigma_rad=sigma_slope / (1.0 + s * s),
        n_inliers=int(n_inliers),
        extent_m=extent,
        n_lines=len(levels),
        lines=tuple(levels),
    )


def measure_face_lean(
    profile_xz_m: NDArray[np.float64],
    rng: np.random.Generator,
    max_lean_rad: float = np.radians(5.0),
    inlier_m: float = 0.004,
    min_points: int = 12,
    min_extent_m: float = 0.06,
    max_faces: int = 4,
    correlated_points: float = 5.0,
    end_trim_m: float = 0.025,
    level: SurfaceTilt | None = None,
) -> SurfaceTilt | None:
    """Lean of the vertical faces of a profile (risers, obstacle sides), as the tilt the level
    surfaces would show under the same rotation of the slice.

    ``level``: the profile's level surfaces (:func:`measure_surface_tilt`); their points
    (within 2 ``inlier_m`` of a line, over its x extent widened by ``end_trim_m``) are left
    out first, so that the faces' RANSAC pairs are drawn from the faces.

    A pitch error of the attitude turns the whole slice: level surfaces then fall (or rise)
    with x, and vertical faces lean by the same angle. The faces are fitted as
    :func:`measure_surface_tilt` fits the level surfaces, with x and z swapped (near-vertical
    lines x = c + s z, a shared s); a rotation that gives the level surfaces the tilt tau gives
    the faces s = -tan(tau), so the returned ``tilt_rad`` is -atan(s) and is comparable with
    the level surfaces' tilt. Depth errors that bend the surfaces instead of turning them
    (multipath near the concave corners, wiggling) tilt the treads and lean the risers in
    opposite senses, which is what ``filter.attitude.SurfaceBendTest`` looks for.

    Returns None without a face of ``min_points`` points over ``min_extent_m`` of height
    (``lines`` is left empty: face heights mean nothing here).
    """
    p = np.asarray(profile_xz_m, dtype=float)
    if p.ndim != 2 or p.shape[1] != 2 or p.shape[0] < min_points:
        return None
    if level is not None and level.lines:
        slope = math.tan(level.tilt_rad)
        x, z = p[:, 0], p[:, 1]
        on_level = np.zeros(p.shape[0], dtype=bool)
        for line in level.lines:
            on_level |= (
                (np.abs(z - line.height_m - slope * x) < 2.0 * inlier_m)
                & (x > line.x_min_m - end_trim_m)
                & (x < line.x_max_m + end_trim_m)
            )
        p = p[~on_level]
        if p.shape[0] < min_points:
            return None
    lean = measure_surface_tilt(
        np.ascontiguousarray(p[:, ::-1]),
        rng,
        max_lean_rad,
        inlier_m,
        min_points,
        min_extent_m,
        max_faces,
        correlated_points,
        end_trim_m,
    )
    if lean is None:
        return None
    return SurfaceTilt(
        tilt_rad=-lean.tilt_rad,
        sigma_rad=lean.sigma_rad,
        n_inliers=lean.n_inliers,
        extent_m=lean.extent_m,
        n_lines=lean.n_lines,
    )


def _surface_tilt_numpy(
    p: NDArray[np.float64],
    rng: np.random.Generator,
    max_tilt_rad: float,
    inlier_m: float,
    min_points: int,
    min_extent_m: float,
    max_lines: int,
    correlated_points: float,
    end_trim_m: float,
    ray_fit: str = "off",
    isotropic_sigma_m: float = 0.0,
    ray_heights: bool = False,
) -> SurfaceTilt | None:
    """numpy path of :func:`measure_surface_tilt` (the reference of ``compiled.surface_tilt``;
    ``p`` checked, at least ``min_points`` rows)."""
    x, z = p[:, 0], p[:, 1]
    max_slope = float(np.tan(max_tilt_rad))
    remaining = np.ones(x.shape[0], dtype=bool)
    lines: list[NDArray[np.int64]] = []
    for _ in range(max_lines):
        idx = np.flatnonzero(remaining)
        if idx.size < min_points:
            break
        xi, zi = x[idx], z[idx]
        m = _best_line(xi, zi, max_slope, inlier_m, rng)
        if m is None:
            break
        m = _refine(xi, zi, m, inlier_m)
        sel = idx[m]
        if sel.size < min_points or _ptp(x[sel]) < min_extent_m:
            break
        remaining[sel] = False
        if end_trim_m > 0.0:
            xs = x[sel]
            sel = sel[(xs > xs.min() + end_trim_m) & (xs < xs.max() - end_trim_m)]
            if sel.size < 3:
                continue
        lines.append(sel)
    if not lines:
        return None
    # per line: centred x, z and its own noise variance (residuals of its own fit)
    szx = info = 0.0
    variances = []
    # (each line's points gathered once; np.sum / np.sqrt of floats as add.reduce / math.sqrt:
    # the same pairwise sum and the same correctly rounded root)
    line_xz = [(x[sel], z[sel]) for sel in lines]
    for xs, zs in line_xz:
        xc = xs - _mean(xs)
        zc = zs - _mean(zs)
        Sxx = float(xc @ xc)
        Szx = float(xc @ zc)
        s_k = Szx / max(Sxx, 1e-12)
        r = zc - s_k * xc
        var_k = max(float(_add_reduce(r * r)) / max(1, xs.shape[0] - 2), 1e-8)
        variances.append(var_k)
        szx += Szx / var_k
        info += Sxx / var_k
    if not info > 0.0:  # every trimmed line's points share one x: no slope to measure
        return None
    s = szx / info
    heights = [_mean(zs - s * xs) for xs, zs in line_xz]
    ray_h: list[float | None] = [None] * len(line_xz)
    if ray_fit != "off" or ray_heights:
        s_ray, refit = _ray_refit(line_xz, variances, s, heights, isotropic_sigma_m**2)
        if ray_heights:
            ray_h = list(refit)
        if ray_fit != "off":
            heights = refit
        if ray_fit == "all":
            s = s_ray
    if abs(s) > max_slope:
        return None
    sigma_slope = math.sqrt(correlated_points / info)
    levels = []
    extent = 0.0
    for (xs, _zs), var_k, h, h_ray in zip(line_xz, variances, heights, ray_h, strict=True):
        x_mid = _mean(xs)
        var_own = correlated_points * var_k / xs.shape[0]
        var_h = var_own + (x_mid * sigma_slope) ** 2
        x_lo, x_hi = float(_min_reduce(xs)), float(_max_reduce(xs))
        extent += x_hi - x_lo
        levels.append(LevelLine(h, math.sqrt(var_h), x_lo, x_hi, x_mid, math.sqrt(var_own), h_ray))
    return SurfaceTilt(
        tilt_rad=float(np.arctan(s)),
        sigma_rad=sigma_slope / (1.0 + s * s),
        n_inliers=int(sum(sel.size for sel in lines)),
        extent_m=extent,
        n_lines=len(lines),
        lines=tuple(levels),
    )


def _ray_refit(
    line_xz: list[tuple[NDArray[np.float64], NDArray[np.float64]]],
    variances: list[float],
    slope: float,
    heights: list[float],
    isotropic_var_m2: float = 0.0,
    iterations: int = 4,
) -> tuple[float, list[float]]:
    """The shared slope and the lines' heights (at x = 0, the camera) fitted with the errors
    along the camera rays.

    The profile is relative to the camera centre, so a point is p = rho u with u its ray's
    direction: u is known (the pixel), the range rho carries the ToF error. Vertical least
    squares regresses z on x, but x = rho u_x errs together with z, along u: on a surface
    seen at a slant the slope leans towards the rays (errors-in-variables), and a line's
    height, read at the camera with that slope, moves by the lean times its distance (on a
    descent the rays point down and away: far treads read high).

    Each point's error is modelled as a range error of variance v_k (line k) along its ray
    plus ``isotropic_var_m2`` in each axis (what the thinning and smoothing leave that is not
    along the ray); its vertical residual z - s x - h_k then has the variance
    D^2 = v_k (u_z - s u_x)^2 + isotropic (1 + s^2) (the point's Mahalanobis distance to the
    line), and sum (residual / D)^2 over all lines is minimised by Gauss-Newton from the
    vertical fit (``slope``, ``heights``). v_k comes from the line's vertical residual
    variance (``variances``) less the isotropic part, over the line's mean (u_z - s u_x)^2:
    a line whose scatter is no more than the isotropic part is fitted as by orthogonal
    regression, one whose scatter is mostly along the rays (far treads) as by range
    residuals. With no isotropic part this is exactly the range residual
    rho - h_k / (u_z - s u_x). Falls back to the vertical fit if a ray runs within ~3 deg
    of a line.
    """
    s = slope
    h = np.array(heights, dtype=float)
    n_lines = len(line_xz)
    rays = []
    for xs, zs in line_xz:
        rho = np.hypot(xs, zs)
        rays.append((xs, zs, xs / rho, zs / rho))
    iso = isotropic_var_m2
    for _ in range(iterations):
        A = np.zeros((n_lines + 1, n_lines + 1))
        b = np.zeros(n_lines + 1)
        for k, ((xs, zs, ux, uz), var_k) in enumerate(zip(rays, variances, strict=True)):
            a = uz - s * ux
            if float(_min_reduce(np.abs(a))) < 0.05:  # a ray within ~3 deg of the line
                return slope, list(heights)
            v_k = max(var_k - iso, 0.0) / float(np.mean(a * a))
            D = np.sqrt(v_k * a * a + iso * (1.0 + s * s))
            r = zs - s * xs - h[k]
            f = r / D
            dD = (-v_k * a * ux + iso * s) / D
            j_s = -xs / D - r * dD / (D * D)
            j_h = -1.0 / D
            A[0, 0] += float(j_s @ j_s)
            A[0, k + 1] += float(j_s @ j_h)
            A[k + 1, k + 1] += float(j_h @ j_h)
            b[0] -= float(j_s @ f)
            b[k + 1] -= float(j_h @ f)
        A[1:, 0] = A[0, 1:]
        try:
            step = np.linalg.solve(A, b)
        except np.linalg.LinAlgError:
            return slope, list(heights)
        s += float(step[0])
        h += step[1:]
    return s, h.tolist()
