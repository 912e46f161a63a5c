"""The recording's depth noise, measured on its own profiles, and the thinning cell it asks for.

The grid thinning (``vio_graph.frontend.smoothing``) keeps one centroid per ``grid_cell_m``
cell. A cell much smaller than the profile's noise band spreads one surface over several rows
of cells: the thinned profile keeps a noisy band instead of a line, kNN smoothing averages
within the band, and ICP counts every occupied cell as an independent pair. The 5 mm default
is about twice the pico flexx2's profile noise (2-3 mm); a camera twice as noisy needs about
twice the cell (``docs/generalisation.md``, ``tof_noise_2x``).

Measurement (per frame; numpy, or numba kernels with the same answers). The levels the terrain
classifier found on the smoothed profile say where the horizontal surfaces are; the RAW slice
points within ``band_m`` of a level (inside its x extent) are fitted by a straight line z = a +
b x (a slightly tilted attitude tilts the level, which the line takes out), and the residuals
about the lines of all levels, pooled, give the frame's noise as 1.4826 x their median absolute
deviation (robust to the points of a riser foot or a nosing that fall in the band). The
vertical scatter of a horizontal surface is the profile noise the cell is compared with.

Tracking (:class:`DepthNoiseTracker`). The per-frame values are noisy and a frame may have no
level; the tracker keeps the median of the last ``window`` frame values and, once it has
``warmup`` of them, asks for the cell ``ratio`` x sigma, never below the configured cell (a
cleaner camera than the one the defaults were set on keeps them) nor above ``max_cell_m``.
The cell in use changes only when the asked cell differs from it by more than
``hysteresis`` (relative), so a recording whose noise is steady keeps one cell.
"""

from __future__ import annotations

import math
from collections import deque
from collections.abc import Iterable

import numpy as np
from numpy.typing import NDArray

from vio_graph.frontend.icp import compiled_kernels

#: MAD -> standard deviation of a normal distribution
_MAD_TO_SIGMA = 1.4826


def level_residuals(
    points_xz_m: NDArray[np.float64],
    levels: Iterable[tuple[float, float, float]],
    band_m: float,
    min_points: int = 20,
    max_range_m: float = np.inf,
) -> NDArray[np.float64]:
    """z residuals of the points about a straight line fitted to each level's band.

    Args:
        points_xz_m: (N, 2) raw (unthinned, unsmoothed) profile points, metres.
        levels: (height_m, x_min_m, x_max_m) of each horizontal level.
        band_m: points within this of a level's height (and inside its x extent) are its own.
        min_points: levels with fewer points in their band are skipped.
        max_range_m: only points nearer the camera (the origin) than this count, m.

    Returns:
        (M,) residuals z - (a + b x), metres, pooled over the levels (empty if none).

    With the front end's kernels on, the points of each band are picked in one compiled pass
    (``compiled.level_bands``) and the lines fitted by the same numpy calls as
    :func:`level_residuals_reference`: the same residuals bit for bit.
    """
    kernels = compiled_kernels()
    if kernels is None:
        return level_residuals_reference(points_xz_m, levels, band_m, min_points, max_range_m)
    pts = np.asarray(points_xz_m, dtype=float).reshape(-1, 2)
    lv = np.asarray(list(levels), dtype=float).reshape(-1, 3)
    bx, bz, counts = kernels.level_bands(
        pts[:, 0],  # strided views: the kernel reads them in place
        pts[:, 1],
        float(max_range_m),
        bool(np.isfinite(max_range_m)),
        np.ascontiguousarray(lv[:, 0]),
        np.ascontiguousarray(lv[:, 1]),
        np.ascontiguousarray(lv[:, 2]),
        float(band_m),
    )
    out: list[NDArray[np.float64]] = []
    for k, n_own in enumerate(counts.tolist()):
        if n_own < max(min_points, 3):
            continue
        out.append(_line_residuals(bx[k, :n_own], bz[k, :n_own]))
    return np.concatenate(out) if out else np.zeros(0)


def level_noise_sigma(
    points_xz_m: NDArray[np.float64],
    levels: Iterable[tuple[float, float, float]],
    band_m: float,
    min_points: int = 20,
    max_range_m: float = np.inf,
) -> float:
    """The frame's depth noise: ``robust_sigma(level_residuals(...))`` (same arguments; nan
    without residuals). With the front end's kernels on, the bands, the line fits and the
    median absolute deviation in one compiled call (``compiled.level_noise``), the same float
    as :func:`level_noise_sigma_reference` (tests/test_frontend_fastpaths.py)."""
    kernels = compiled_kernels()
    if kernels is None:
        return level_noise_sigma_reference(points_xz_m, levels, band_m, min_points, max_range_m)
    pts = np.ascontiguousarray(points_xz_m, dtype=float).reshape(-1, 2)
    lv = np.array(levels if isinstance(levels, list) else list(levels), dtype=float)
    residuals, mad, ok = kernels.level_noise(
        pts,
        float(max_range_m),
        bool(math.isfinite(max_range_m)),
        lv.reshape(-1, 3),
        float(band_m),
        max(int(min_points), 3),
    )
    if not ok:  # a NaN or an infinity among the residuals
        return robust_sigma_reference(residuals)
    return float(_MAD_TO_SIGMA * mad)


def level_noise_sigma_reference(
    points_xz_m: NDArray[np.float64],
    levels: Iterable[tuple[float, float, float]],
    band_m: float,
    min_points: int = 20,
    max_range_m: float = np.inf,
) -> float:
    """numpy path of :func:`level_noise_sigma`."""
    residuals = level_residuals_reference(points_xz_m, levels, band_m, min_points, max_range_m)
    return robust_sigma_reference(residuals)


def _line_residuals(xs: NDArray[np.float64], zs: NDArray[np.float64]) -> NDArray[np.float64]:
    """z residuals about the least-squares line z = a + b x of the points (contiguous).
    The means as ``ndarray.mean`` computes them (the same sum divided by the count, the same
    floats) without its Python wrapper (~2.5 us a call)."""
    xc = xs - np.add.reduce(xs) / xs.size
    zc = zs - np.add.reduce(zs) / zs.size  # once: the same floats the fit and residuals used
    sxx = float(xc @ xc)
    slope = float(xc @ zc) / sxx if sxx > 0 else 0.0
    return zc - slope * xc


def level_residuals_reference(
    points_xz_m: NDArray[np.float64],
    levels: Iterable[tuple[float, float, float]],
    band_m: float,
    min_points: int = 20,
    max_range_m: float = np.inf,
) -> NDArray[np.float64]:
    """numpy path of :func:`level_residuals`."""
    pts = np.asarray(points_xz_m, dtype=float).reshape(-1, 2)
    if np.isfinite(max_range_m):
        pts = pts[np.hypot(pts[:, 0], pts[:, 1]) < max_range_m]
    out: list[NDArray[np.float64]] = []
    for height, x_lo, x_hi in levels:
        x, z = pts[:, 0], pts[:, 1]
        own = (np.abs(z - height) <= band_m) & (x >= x_lo) & (x <= x_hi)
        if int(own.sum()) < max(min_points, 3):
            continue
        out.append(_line_residuals(x[own], z[own]))
    return np.concatenate(out) if out else np.zeros(0)


def robust_sigma(residuals_m: NDArray[np.float64]) -> float:
    """1.4826 x median absolute deviation (nan for an empty input).

    Compiled (``compiled.median_abs_deviation``: both medians by selection, O(n), no sort)
    when the front end's kernels are on and the values are finite: the same float as
    :func:`robust_sigma_reference` (tests/test_frontend_fastpaths.py)."""
    r = np.asarray(residuals_m, dtype=float).ravel()
    kernels = compiled_kernels()
    if kernels is None or r.size == 0:
        return robust_sigma_reference(r)
    mad, ok = kernels.median_abs_deviation(np.ascontiguousarray(r))
    if not ok:  # a NaN or an infinity
        return robust_sigma_reference(r)
    return float(_MAD_TO_SIGMA * mad)


def robust_sigma_reference(residuals_m: NDArray[np.float64]) -> float:
    """numpy path of :func:`robust_sigma`."""
    r = np.asarray(residuals_m, dtype=float).ravel()
    if r.size == 0:
        return float("nan")
    return float(_MAD_TO_SIGMA * np.median(np.abs(r - np.median(r))))


def _median(values: Iterable[float]) -> float:
    """np.median of finite floats (nan if none), without its per-call overhead: the middle
    value, or the two middle ones summed and halved, as np.median's mean of them rounds."""
    v = sorted(values)
    n = len(v)
    if n == 0:
        return float("nan")
    m = n // 2
    return float(v[m]) if n % 2 else (v[m - 1] + v[m]) / 2.0


class DepthNoiseTracker:
    """Median of the recent per-frame noise values and the thinning cell they ask for."""

    def __init__(
        self,
        base_cell_m: float,
        ratio: float,
        max_cell_m: float,
        warmup: int,
        window: int,
        hysteresis: float,
    ) -> None:
        self.base_cell_m = float(base_cell_m)
        self.ratio = float(ratio)
        self.max_cell_m = max(float(max_cell_m), self.base_cell_m)
        self.warmup = int(warmup)
        self.hysteresis = float(hysteresis)
        self._values: deque[float] = deque(maxlen=max(int(window), 1))
        self._sigma: float | None = None  # sigma_m of the current values, once asked for
        self.cell_m = self.base_cell_m

    def reset(self) -> None:
        """Forget the measurements and go back to the configured cell."""
        self._values.clear()
        self._sigma = None
        self.cell_m = self.base_cell_m

    @property
    def sigma_m(self) -> float:
        """Median of the recent frame values, metres (nan before the first one); computed
        once per new value (the front end asks for it several times a frame)."""
        if self._sigma is None:
            self._sigma = _median(self._values)
        return self._sigma

    def asked_cell_m(self) -> float:
        """The cell the current noise asks for (the configured cell before the warm-up)."""
        if len(self._values) < self.warmup:
            return self.base_cell_m
        return min(max(self.ratio * self.sigma_m, self.base_cell_m), self.max_cell_m)

    def update(self, sigma_m: float) -> float:
        """Add one frame's noise value (nan = no measurement) and return the cell to use."""
        if np.isfinite(sigma_m):
            self._values.append(float(sigma_m))
            self._sigma = None
        asked = self.asked_cell_m()
        if abs(asked - self.cell_m) > self.hysteresis * self.cell_m:
            self.cell_m = asked
        return self.cell_m
