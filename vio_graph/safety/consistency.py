"""Consistency of the clearance sigma with the data: does the height map predict what the
next keyframe sees? (pure: arrays in, numbers out; no I/O)

The clearance sigma's pose and map terms (docs/method.md, section 8) say how far a foot
placed by the filter now can be from a terrain bin placed by the filter at the keyframes
that saw it. A new keyframe is the same situation with the camera in place of the foot: its
profile, placed at the filter's camera position now, lands on bins the map already holds.
Per shared bin b the innovation r_b is the keyframe's height minus the map's. Two tests:

- pose: the drift of the camera since the bins were mapped moves the whole profile, so the
  keyframe's common offset o = median_b r_b observes it, with predicted variance
  ``relative_pose_scale`` x median_b |P_now - P_bin|_zz (the filter's covariance growth,
  projected on z) plus the variance of the median itself (1.2533^2 x the residuals' scaled
  MAD^2 / the number of bins);
- map: what is left per bin, r_b - o, against the bin's height variance sigma_bin^2 (its
  standard error over keyframes with the floor ``map_sigma_m``).

If the terms are right, each normalised square is chi-square with one degree of freedom; its
median over the last ``window`` keyframes over 0.4549 (the median of chi-square(1)) is the
squared scale the data put on that term. A median and not a mean: a ToF mixed pixel or a
nosing bin shifted by a bin is one large value, not a sign that every bin is off.

A pose scale above 1 says the filter's covariance grows less than its drift (the filter is
overconfident: the estimator is in trouble and says so); below 1, that it is conservative.
The map test sees the random scatter of the bins, not an error all keyframes share (a nosing
placed up to a bin off, the strip hidden behind a nosing): the floor was there for those, and
the map scale takes it down with the scatter (docs/method.md, docs/results.md). The monitor
multiplies the map term and the pose term's vertical part of every sigma by their scales (the
pose test sees heights only: the x part keeps the filter's growth unless
``pose_scale_on_x``); the foot-outline term is seen by neither test.
"""

from __future__ import annotations

import math
from collections import deque
from collections.abc import Callable
from types import ModuleType

import numpy as np
from numpy.typing import ArrayLike, NDArray

from vio_graph.safety.clearance import HeightProfile

#: median of the chi-square distribution with one degree of freedom
CHI2_1_MEDIAN = 0.4549364231195724

_NONE = np.zeros(0)  # an empty window part


def keyframe_bin_tops(
    camera_xz_m: ArrayLike, profile_xz_m: ArrayLike, bin_m: float, top_band_m: float
) -> tuple[NDArray[np.int64], NDArray[np.float64]]:
    """The keyframe's height per x bin, as the map takes it: the profile (N, 2, relative to
    the camera, world axes, m) placed at the camera; per bin ``floor(x / bin_m)`` the mean of
    the points within ``top_band_m`` of the bin's highest point. Returns (bin indices, heights
    m), sorted by bin; empty for a profile without finite points."""
    rel = np.asarray(profile_xz_m, dtype=float).reshape(-1, 2)
    rel = rel[np.all(np.isfinite(rel), axis=1)]
    if rel.shape[0] == 0:
        return np.zeros(0, np.int64), np.zeros(0)
    pts = rel + np.asarray(camera_xz_m, dtype=float)[None]
    idx = np.floor(pts[:, 0] / bin_m).astype(np.int64)
    order = np.lexsort((-pts[:, 1], idx))  # by bin, highest point first
    idx, z = idx[order], pts[order, 1]
    first = np.r_[True, idx[1:] != idx[:-1]]
    grp = np.cumsum(first) - 1
    band = z >= z[first][grp] - top_band_m
    n_bins = int(first.sum())
    top = np.bincount(grp[band], weights=z[band], minlength=n_bins) / np.bincount(
        grp[band], minlength=n_bins
    )
    return idx[first], top


def psd_abs_zz(dP_m2: NDArray[np.float64]) -> NDArray[np.float64]:
    """The zz element of |dP| (eigenvalues made non-negative) for symmetric 2x2 matrices
    given as rows (xx, xz, zz), (B, 3) -> (B,), m^2."""
    a, b, c = dP_m2[:, 0], dP_m2[:, 1], dP_m2[:, 2]
    m, r = (a + c) / 2, np.sqrt(((a - c) / 2) ** 2 + b * b)
    l1, l2 = m + r, m - r
    # unit eigenvector of l1: its z component squared; the other's is 1 minus it
    with np.errstate(invalid="ignore", divide="ignore"):
        vz2 = np.where(r > 0, (l1 - a) / (2 * r), 0.5)
    vz2 = np.clip(vz2, 0.0, 1.0)
    return np.abs(l1) * vz2 + np.abs(l2) * (1.0 - vz2)


def median_selected(values: NDArray[np.float64]) -> float:
    """``np.median`` of a 1-D float array by selection (``np.partition`` on the middle
    elements), the same value bit for bit: the middle element, or the mean of the two middle
    ones; NaN if any value is NaN. Skips ``np.median``'s generic axis handling, which costs
    more than the selection on the few hundred values of a keyframe."""
    n = values.size
    if n == 0:
        return float("nan")
    h = n // 2
    part = np.partition(values, [h - 1, h, n - 1] if n % 2 == 0 else [h, n - 1])
    if np.isnan(part[n - 1]):
        return float("nan")
    if n % 2:
        return float(part[h])
    return float((part[h - 1] + part[h]) / 2)


def _positions_of(sorted_values: NDArray[np.float64], sub: NDArray[np.float64]) -> NDArray:
    """Distinct positions in ``sorted_values`` holding the values of ``sub`` (sorted, a
    sub-multiset of it): equal values take consecutive positions from the first of theirs."""
    at = np.searchsorted(sorted_values, sub, side="left")
    if sub.size > 1:
        new_run = np.empty(sub.size, bool)
        new_run[0] = True
        np.not_equal(sub[1:], sub[:-1], out=new_run[1:])
        if not new_run.all():  # repeated values: count up within each run
            idx = np.arange(sub.size)
            at += idx - np.maximum.accumulate(np.where(new_run, idx, 0))
    return at


class _ScaleBase:
    """Arguments, validation and the clipped scale shared by the two implementations."""

    def __init__(
        self,
        window: int,
        min_keyframes: int = 5,
        scale_range: tuple[float, float] = (0.25, 4.0),
    ) -> None:
        if window < 0 or min_keyframes < 1:
            raise ValueError(
                f"window must be >= 0 and min_keyframes >= 1, got {window}, {min_keyframes}"
            )
        lo, hi = scale_range
        if not 0 < lo <= 1 <= hi:
            raise ValueError(f"scale_range must satisfy 0 < lo <= 1 <= hi, got {scale_range}")
        self.window = window
        self.min_keyframes = min_keyframes
        self.scale_range = (float(lo), float(hi))
        self._q: deque[NDArray[np.float64]] = deque(maxlen=max(window, 1))
        self._scale = 1.0

    @property
    def scale(self) -> float:
        """Factor on the sigma term (1 until ``min_keyframes`` keyframes were observed)."""
        return self._scale

    def observe(self, innovation_m: ArrayLike, predicted_var_m2: ArrayLike) -> None:
        """One keyframe's innovations (m) and their predicted variances (m^2); updates
        :attr:`scale`."""
        raise NotImplementedError

    def _normalised_squares(
        self, innovation_m: ArrayLike, predicted_var_m2: ArrayLike
    ) -> NDArray[np.float64] | None:
        r = np.asarray(innovation_m, dtype=float).reshape(-1)
        v = np.asarray(predicted_var_m2, dtype=float).reshape(-1)
        if r.shape != v.shape:
            raise ValueError(f"innovations {r.shape} and variances {v.shape} differ in shape")
        ok = np.isfinite(r) & np.isfinite(v) & (v > 0)
        if not ok.any():
            return None
        return r[ok] ** 2 / v[ok]

    def _set_scale(self, median_sq: float) -> None:
        # as float(np.clip(np.sqrt(s2), lo, hi)): sqrt is exact-rounded in both; NaN stays
        lo, hi = self.scale_range
        self._scale = min(max(math.sqrt(median_sq / CHI2_1_MEDIAN), lo), hi)


class ChiSquareScale(_ScaleBase):
    """Running scale of one sigma term from normalised squares (see module docstring).
    ``window``: keyframes whose values are kept (0 disables: the scale stays 1);
    ``min_keyframes``: keyframes observed before the scale leaves 1; ``scale_range``: the
    scale is clipped to it (a bound against a degenerate map).

    The window's values are also kept in one sorted array, updated per keyframe (the new
    keyframe's values merged in, the oldest keyframe's taken out), so the median is read at
    the middle index: the same value as :class:`ChiSquareScaleReference`'s median of the
    concatenated window (tests/test_safety_consistency.py). ``kernels``: the compiled module
    (vio_graph/safety/compiled.py) merging in one pass, or None (numpy); the same values."""

    def __init__(
        self,
        window: int,
        min_keyframes: int = 5,
        scale_range: tuple[float, float] = (0.25, 4.0),
        kernels: ModuleType | None = None,
    ) -> None:
        super().__init__(window, min_keyframes, scale_range)
        self._sorted = np.zeros(0)
        self._kernels = kernels

    def observe(self, innovation_m: ArrayLike, predicted_var_m2: ArrayLike) -> None:
        """As :meth:`ChiSquareScaleReference.observe`, the median from the sorted window."""
        if self.window == 0:
            return
        q = self._normalised_squares(innovation_m, predicted_var_m2)
        if q is None:
            return
        self.observe_sorted(np.sort(q))

    def observe_sorted(self, q: NDArray[np.float64]) -> None:
        """One keyframe's normalised squares, already filtered (finite, positive variance)
        and sorted: the window and :attr:`scale` updated (nothing for an empty ``q``)."""
        if self.window == 0 or q.size == 0:
            return
        self.accept_merged(q, self._merge(q))

    def leaving(self) -> NDArray[np.float64]:
        """The values the next keyframe takes out of the window: the oldest keyframe's when
        the window is full, else none (for a caller merging with the compiled kernels)."""
        return self._q[0] if len(self._q) == self._q.maxlen else _NONE

    def accept_merged(self, q: NDArray[np.float64], merged: NDArray[np.float64]) -> None:
        """:meth:`observe_sorted` with the merge done by the caller: ``merged`` is the
        sorted window without :meth:`leaving` and with ``q`` (non-empty)."""
        self._sorted = merged
        self._q.append(q)
        if len(self._q) >= self.min_keyframes:
            n = merged.size
            h = n // 2
            if math.isnan(merged[n - 1]):  # never: the values are squares over v > 0
                med = math.nan
            elif n % 2:
                med = float(merged[h])
            else:
                med = float((merged[h - 1] + merged[h]) / 2)
            self._set_scale(med)

    def _merge(self, q: NDArray[np.float64]) -> NDArray[np.float64]:
        """The sorted window with the oldest keyframe's values out (when the window is full)
        and ``q``'s in."""
        if self._kernels is not None:
            return self._kernels.window_merge(self._sorted, self.leaving(), q)
        srt = self._sorted
        if len(self._q) == self._q.maxlen:  # the oldest keyframe leaves the window
            keep = np.ones(srt.size, bool)
            keep[_positions_of(srt, self._q[0])] = False
            srt = srt[keep]
        # merge: q's slots in the merged array, the kept values in the others
        m = q.size
        slot = np.searchsorted(srt, q)
        slot += np.arange(m)
        merged = np.empty(srt.size + m)
        merged[slot] = q
        rest = np.ones(merged.size, bool)
        rest[slot] = False
        merged[rest] = srt
        return merged


class ChiSquareScaleReference(_ScaleBase):
    """:class:`ChiSquareScale` as first written: the window's values concatenated and their
    ``np.median`` taken at every keyframe (the reference the sorted window is tested
    against)."""

    def observe(self, innovation_m: ArrayLike, predicted_var_m2: ArrayLike) -> None:
        """One keyframe's innovations (m) and their predicted variances (m^2); updates
        :attr:`scale`."""
        if self.window == 0:
            return
        q = self._normalised_squares(innovation_m, predicted_var_m2)
        if q is None:
            return
        self._q.append(q)
        if len(self._q) >= self.min_keyframes:
            self._set_scale(float(np.median(np.concatenate(self._q))))


class MapConsistency:
    """The pose and map scales of the clearance sigma from each keyframe tested against the
    map before it joins it (see module docstring); arguments as :class:`ChiSquareScale`;
    ``reference``: the implementation as first written (:class:`ChiSquareScaleReference`,
    ``np.median``), which the default (sorted window, :func:`median_selected`) equals;
    ``kernels``: the compiled module (vio_graph/safety/compiled.py) for
    :meth:`observe_bin_tops` and the sorted windows, the same values again."""

    def __init__(
        self,
        window: int,
        min_keyframes: int = 5,
        scale_range: tuple[float, float] = (0.25, 4.0),
        reference: bool = False,
        kernels: ModuleType | None = None,
    ) -> None:
        if reference and kernels is not None:
            raise ValueError("the reference consistency test has no compiled path")
        self.pose: _ScaleBase
        self.map: _ScaleBase
        if reference:
            self.pose = ChiSquareScaleReference(window, min_keyframes, scale_range)
            self.map = ChiSquareScaleReference(window, min_keyframes, scale_range)
        else:
            self.pose = ChiSquareScale(window, min_keyframes, scale_range, kernels)
            self.map = ChiSquareScale(window, min_keyframes, scale_range, kernels)
        self._kernels = kernels
        self._median: Callable[[NDArray[np.float64]], float] = (
            (lambda a: float(np.median(a))) if reference else median_selected
        )

    @property
    def pose_scale(self) -> float:
        """Factor on the sigmas' pose term."""
        return self.pose.scale

    @property
    def map_scale(self) -> float:
        """Factor on the sigmas' map term."""
        return self.map.scale

    def observe_keyframe(
        self,
        camera_xz_m: ArrayLike,
        profile_xz_m: ArrayLike,
        cov_position_m2: ArrayLike,
        mapped: HeightProfile,
        bin_cov_rows: Callable[[NDArray[np.int64]], NDArray[np.float64]],
        bin_m: float,
        top_band_m: float,
        pose_scale: float,
        bin_tops: tuple[NDArray[np.int64], NDArray[np.float64]] | None = None,
    ) -> None:
        """Test a keyframe against the map: ``mapped`` is the map's profile (bins of width
        ``bin_m`` in use), ``bin_cov_rows(k)`` the mean keyframe camera covariance of its
        bins ``k`` as rows (Pxx, Pxz, Pzz), (K, 3); the keyframe's camera covariance
        ``cov_position_m2`` (2, 2) is now's; ``pose_scale``: the config's
        ``relative_pose_scale``; ``bin_tops``: :func:`keyframe_bin_tops` of this keyframe
        when the caller has it (the compiled path computes it in one call)."""
        if self.pose.window == 0 or len(mapped) == 0:
            return
        bins, top = (
            keyframe_bin_tops(camera_xz_m, profile_xz_m, bin_m, top_band_m)
            if bin_tops is None
            else bin_tops
        )
        mapped_bins = np.rint(mapped.x_lo_m / bin_m).astype(np.int64)
        k = np.minimum(np.searchsorted(mapped_bins, bins), len(mapped) - 1)
        hit = mapped_bins[k] == bins
        if not hit.any():
            return
        k = k[hit]
        r = top[hit] - mapped.z_m[k]
        P = np.asarray(cov_position_m2, dtype=float)
        dP = np.array([P[0, 0], (P[0, 1] + P[1, 0]) / 2, P[1, 1]])[None] - bin_cov_rows(k)
        median = self._median
        offset = median(r)
        mad_sd = 1.4826 * median(np.abs(r - offset))  # per-bin scatter, m
        v_offset = pose_scale * median(psd_abs_zz(dP)) + (1.2533 * mad_sd) ** 2 / r.size
        self.pose.observe(np.array([offset]), np.array([v_offset]))
        self.map.observe(r - offset, mapped.sigma_m[k] ** 2)

    def observe_bin_tops(
        self,
        bin_tops: tuple[NDArray[np.int64], NDArray[np.float64]],
        mapped: HeightProfile,
        mapped_bins: NDArray[np.int64],
        cov_sums: NDArray[np.float64],
        counts: NDArray[np.int64],
        i0: int,
        cov_position_m2: NDArray[np.float64],
        bin_m: float,
        pose_scale: float,
    ) -> None:
        """:meth:`observe_keyframe` in one compiled call (needs ``kernels``): the keyframe's
        :func:`keyframe_bin_tops`, the map window ``mapped`` with its bin indices
        ``mapped_bins``, the map's per-bin covariance sums (B, 3) and keyframe counts (B,)
        with bin index ``i0`` at element 0 (the mean keyframe covariance of a bin is their
        ratio); other arguments as :meth:`observe_keyframe`. The same scales, bit for bit
        (tests/test_safety_consistency.py)."""
        if self._kernels is None:
            raise ValueError("observe_bin_tops needs the compiled kernels")
        if self.pose.window == 0 or len(mapped) == 0:
            return
        P = cov_position_m2
        hit, offset, mad_sd, med_zz, m, sq = self._kernels.consistency_squares(
            bin_tops[0],
            bin_tops[1],
            mapped.x_lo_m,
            mapped.z_m,
            mapped.sigma_m,
            mapped_bins,
            cov_sums,
            counts,
            i0,
            bin_m,
            float(P[0, 0]),
            float(P[0, 1]),
            float(P[1, 0]),
            float(P[1, 1]),
        )
        if not hit:
            return
        # the offset's variance and square as observe_keyframe computes them (Python's
        # power, numpy's square)
        v_offset = pose_scale * med_zz + (1.2533 * mad_sd) ** 2 / m
        if math.isfinite(offset) and math.isfinite(v_offset) and v_offset > 0:
            assert isinstance(self.pose, ChiSquareScale)
            self.pose.observe_sorted(np.array([offset * offset / v_offset]))
        assert isinstance(self.map, ChiSquareScale)
        self.map.observe_sorted(sq)
