"""The safety monitor's terrain: a per-x-bin height map built from the keyframe profiles seen
so far (pure: arrays in, arrays out; no I/O).

Map. Each keyframe's sagittal profile (camera-relative, world axes) is placed at the
keyframe's camera position; per x bin (width ``bin_m``, bin ``b`` spans
``[b bin_m, b bin_m + bin_m]``) the keyframe's surface height is the mean of its points
within ``top_band_m`` of the bin's highest point (a riser's bin keeps its top). A bin keeps
the last ``capacity`` keyframe heights; its height is their median (or mean) and it is *used*
once ``min_keyframes`` keyframes saw it, or earlier, once ``agree_keyframes`` keyframes saw it
and their heights agree (all kept heights within ``agree_m`` of each other): a surface seen
twice at the same height is terrain, while the mixed pixels of a ToF camera scatter over
heights from view to view and wait for ``min_keyframes`` views and the median. Each bin also
keeps the mean camera position covariance of the keyframes that saw it (the relative-pose part
of the clearance sigma).

View ceilings (``view_ceilings``). A keyframe's height in a bin says there is a surface at
that height and free space above it only as high as the keyframe's view reached over the bin:
the top of its field of view (the steepest upward line of sight to any of its points,
:func:`view_ceilings`). A camera low in front of a stair whose nosing overhangs sees the lower
tread under the nosing and its set-back riser, while the lip is above its field of view; most
keyframes of an approach are such views, and their median put the nosing edge at the riser,
3 cm too far forward. A kept height whose ceiling is below the bin's reference height less
``top_band_m`` therefore takes no part in the bin's statistic (it still counts as a view for
:meth:`OnlineHeightMap._used_rule`). The reference is the bin's second-highest kept height
(the highest when the bin has one): a surface must be reported by two keyframes before it
censors the others, so one view's mixed pixel at the edge of its field of view does not
outvote the views below it. The two highest heights' own ceilings are never below them, so
a bin always keeps a statistic.

Foot contact. A foot standing on the terrain is a measurement of it too: no terrain is above
its sole. :meth:`OnlineHeightMap.add_contact` (called on stance frames) lowers each bin under
the sole to the sole's height plus a margin when the bin's height exceeds that by less than
``max_excess_m`` (the mixed pixels of a hidden strip, not a step the foot estimate overlaps);
the bin keeps that *cap* (the lowest contact so far) for the keyframes that see it later. A
contact never raises a bin and never marks an unseen bin as seen.

Queries. The monitor asks the map, per frame, for the used bins overlapping an x range
(:meth:`OnlineHeightMap.window`), the height sigma and camera covariance of one bin (by its
bin index ``b``), the bin just before an x (:meth:`OnlineHeightMap.bin_below`) and the edges
of the whole map (:meth:`OnlineHeightMap.edges`). Two classes give the same answers:

- :class:`OnlineHeightMap`, the reference: after each keyframe the profile of the whole map is
  rebuilt (:meth:`OnlineHeightMap.profile`) and its edges found over all of it; a window is
  cut from that profile. Per keyframe, work grows with the length of the map.
- :class:`IncrementalHeightMap`: a window is read from the bin arrays by index
  (``b = floor(x / bin_m)``), and after a keyframe only the edges of the part of the map it
  changed are found again. The edge scan (:func:`~vio_graph.safety.clearance.edge_runs`) is
  left to right with a one-transition memory, so it restarts cleanly after a *quiet stretch*:
  consecutive used bins without a height change above ``SLOPE_STEP_M`` spanning more than
  ``MAX_TRANSITION_BIN_M`` (no transition continues across it and none joins one before it).
  The scan is re-run from the last quiet stretch before the keyframe's bins to the first one
  after them, and its edges replace those whose transition starts in between. Per keyframe,
  work grows with the keyframe's profile, not with the map.

tests/test_safety_incremental.py replays recordings through both and requires equal outputs.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from types import ModuleType

import numpy as np
from numpy.typing import ArrayLike, NDArray

from vio_graph.safety import clearance
from vio_graph.safety.clearance import (
    MAX_TRANSITION_BIN_M,
    SLOPE_STEP_M,
    Edges,
    HeightProfile,
    edge_runs,
)

NAN = float("nan")


@dataclass(frozen=True)
class MapWindow:
    """Used bins of the map over an x range: their ``profile`` and bin index ``bins`` (B,)
    (``b`` spans ``[b bin_m, b bin_m + bin_m]``), for :meth:`OnlineHeightMap.bin_cov_at` and
    :meth:`OnlineHeightMap.bin_sigma`."""

    profile: HeightProfile
    bins: NDArray[np.int64]


class OnlineHeightMap:
    """Per-x-bin terrain height from keyframe profiles (growable arrays, bin ``bin_m``);
    the reference implementation of the queries (module docstring).

    ``statistic``: ``"median"`` (the bin's height is the median over keyframes, its scatter
    the scaled median absolute deviation: robust to the mixed pixels a ToF camera leaves
    between a nosing and the tread below it, which each keyframe puts into different bins) or
    ``"mean"`` (mean and standard deviation). ``edge_min_rise_m`` / ``edge_max_gap_m``: the
    edges' parameters (:func:`~vio_graph.safety.clearance.edge_runs`). ``agree_keyframes`` /
    ``agree_m``: the early use of bins whose views agree (module docstring; off when
    ``agree_keyframes >= min_keyframes``).
    """

    def __init__(
        self,
        bin_m: float,
        min_keyframes: int,
        top_band_m: float = 0.01,
        statistic: str = "median",
        capacity: int = 24,
        edge_min_rise_m: float = 0.04,
        edge_max_gap_m: float = 0.15,
        agree_keyframes: int | None = None,
        agree_m: float = 0.0,
        view_ceilings: bool = True,
    ) -> None:
        if statistic not in ("median", "mean"):
            raise ValueError(f"statistic must be 'median' or 'mean', got {statistic!r}")
        self.bin_m = bin_m
        self.top_band_m = top_band_m
        self.min_keyframes = min_keyframes
        self.agree_keyframes = min_keyframes if agree_keyframes is None else agree_keyframes
        self.agree_m = agree_m
        self.statistic = statistic
        self.capacity = max(int(capacity), min_keyframes)
        self.edge_min_rise_m = edge_min_rise_m
        self.edge_max_gap_m = edge_max_gap_m
        self.view_ceilings = view_ceilings
        #: keyframes added so far (the caches below are of this version)
        self.version = 0
        self._i0 = 0  # bin index of array element 0
        self._z = np.full((0, self.capacity), np.nan)  # per bin: the keyframes' heights, m
        # the same sorted, NaN after them (kept by the compiled keyframe step only)
        self._zs = np.full((0, self.capacity), np.nan)
        # per bin and kept height: the keyframe's view ceiling there (view_ceilings), m
        self._u = np.full((0, self.capacity), np.inf)
        self._n = np.zeros(0, np.int64)  # keyframes that saw the bin (all, not only kept)
        self._used = np.zeros(0, bool)  # _used_rule
        self._mid = np.zeros(0)  # per bin: the height over the kept keyframes, m
        self._se2 = np.zeros(0)  # per bin: its squared standard error, m^2
        self._cov = np.zeros((0, 3))  # sum of (Pxx, Pxz, Pzz)
        self._cap = np.zeros(0)  # per bin: the lowest foot-contact height (+inf: none), m
        self._buf: list[NDArray] = []  # the buffers the arrays above view (_grow)
        self._off = 0  # buffer element of array element 0
        self.max_excess_m = 0.0  # excess over a cap that contact removes (0: none yet)
        self._profile: tuple[float, HeightProfile] | None = None  # (map_sigma_m, profile)
        self._profile_bins = np.zeros(0, np.int64)  # bin index of each profile bin
        self._edges: tuple[int, Edges, tuple[int, float, float]] | None = None

    # the bin arrays (attribute, fill value of a bin no keyframe saw)
    _ARRAYS = (
        ("_z", NAN),
        ("_zs", NAN),
        ("_u", math.inf),
        ("_n", 0),
        ("_used", False),
        ("_mid", 0.0),
        ("_se2", 0.0),
        ("_cov", 0.0),
        ("_cap", math.inf),
    )

    def _grow(self, i_min: int, i_max: int) -> None:
        """Extend the bin arrays to hold bins ``i_min``..``i_max`` (and 1 m more at the side
        that needs it). The arrays are views of length ``n`` (the map's bins) into buffers
        (``_buf``, element 0 of the views at buffer element ``_off``) which, when they run
        out, are copied into new ones with room for half the map more at that side: growing
        costs amortised O(1) per bin, not the O(length) copy of every array each metre, and
        the same arrays, values and ``_i0`` as padding each array by the metre it needs."""
        n = self._n.shape[0]
        if n and self._i0 <= i_min and i_max < self._i0 + n:
            return  # (the bins are held: most calls)
        margin = int(np.ceil(1.0 / self.bin_m))
        if n == 0:
            self._i0 = i_min - margin
        # grow by at least 1 m at the side that needs it (amortised, not per keyframe)
        lo = self._i0 if i_min >= self._i0 else i_min - margin
        hi = self._i0 + n if i_max < self._i0 + n else i_max + 1 + margin
        size = self._buf[0].shape[0] if self._buf else 0
        a = self._off - (self._i0 - lo)  # buffer element of bin lo
        views = [getattr(self, name) for name, _ in self._ARRAYS]
        if a < 0 or a + (hi - lo) > size:  # a new buffer, with room on the growing side
            spare = (hi - lo) // 2  # half the map: amortised O(1) per bin
            left = spare if a < 0 else a
            right = spare if a + (hi - lo) > size else size - (a + (hi - lo))
            size, a = left + (hi - lo) + right, left
            shifted = a + (self._i0 - lo)  # where the current bins go
            bufs = []
            for (_, fill), v in zip(self._ARRAYS, views, strict=True):
                buf = np.full((size, *v.shape[1:]), fill, dtype=v.dtype)
                buf[shifted : shifted + n] = v
                bufs.append(buf)
            self._buf = bufs
        else:  # the buffers hold the new bins already (at their fill values): the arrays
            # are views of them, written only in place
            assert all(v.base is buf for buf, v in zip(self._buf, views, strict=True))
        for (name, _), buf in zip(self._ARRAYS, self._buf, strict=True):
            setattr(self, name, buf[a : a + (hi - lo)])
        self._off = a
        self._i0 = lo

    def add_keyframe(
        self, camera_xz_m: ArrayLike, profile_xz_m: ArrayLike, cov_position_m2: ArrayLike
    ) -> tuple[int, int] | None:
        """Add one keyframe: its profile (N, 2) relative to the camera, world axes, m.
        Returns the first and last bin index it changed (None: no finite point)."""
        rel = np.asarray(profile_xz_m, dtype=float).reshape(-1, 2)
        rel = rel[np.all(np.isfinite(rel), axis=1)]
        if rel.shape[0] == 0:
            return None
        pts = rel + np.asarray(camera_xz_m, dtype=float)[None]
        idx = np.floor(pts[:, 0] / self.bin_m).astype(np.int64)
        order = np.lexsort((-pts[:, 1], idx))  # by bin, highest point first
        idx, z = idx[order], pts[order, 1]
        first = np.r_[True, idx[1:] != idx[:-1]]
        bins = idx[first]
        grp = np.cumsum(first) - 1  # group of every point
        top_each = z[first][grp]
        band = z >= top_each - self.top_band_m  # points near the bin's top (riser bins)
        top = np.bincount(grp[band], weights=z[band], minlength=bins.size) / np.bincount(
            grp[band], minlength=bins.size
        )
        self._grow(int(bins[0]), int(bins[-1]))
        j = bins - self._i0
        slot = self._n[j] % self.capacity  # the oldest height makes room
        self._z[j, slot] = top
        if self.view_ceilings:
            cam = np.asarray(camera_xz_m, dtype=float)
            self._u[j, slot] = view_ceilings(
                rel, float(cam[0]), float(cam[1]), bins, self.bin_m, top
            )
        self._n[j] += 1
        self._used[j] = self._used_rule(self._n[j], self._z[j])
        self._mid[j], self._se2[j] = self._bin_stats(self._z[j], self._u[j])
        self._mid[j] = self._capped(self._mid[j], self._cap[j])
        P = np.asarray(cov_position_m2, dtype=float)
        self._cov[j] += np.array([P[0, 0], P[0, 1], P[1, 1]])
        self._profile = None
        self.version += 1
        return int(bins[0]), int(bins[-1])

    def _capped(self, mid: NDArray[np.float64], cap: NDArray[np.float64]) -> NDArray:
        """Bin heights with the foot-contact caps applied (module docstring)."""
        lower = (mid > cap) & (mid < cap + self.max_excess_m)
        return np.where(lower, cap, mid)

    def add_contact(
        self, heel_xz_m: ArrayLike, toe_xz_m: ArrayLike, margin_m: float, max_excess_m: float
    ) -> tuple[int, int] | None:
        """A foot standing with its sole on the heel-toe line (world, m): caps the bins
        under it at the sole's height (at the bin's centre) + ``margin_m``; bins above
        that by ``max_excess_m`` or more keep their height. Returns the first and last bin
        index whose height changed (None: none did)."""
        h = np.asarray(heel_xz_m, dtype=float)
        o = np.asarray(toe_xz_m, dtype=float)
        if not (np.all(np.isfinite(h)) and np.all(np.isfinite(o))) or o[0] == h[0]:
            return None
        self.max_excess_m = max_excess_m
        b0 = int(math.floor(min(h[0], o[0]) / self.bin_m))
        b1 = int(math.floor(max(h[0], o[0]) / self.bin_m))
        self._grow(b0, b1)
        b = np.arange(b0, b1 + 1)
        j = b - self._i0
        xc = (b + 0.5) * self.bin_m
        zc = h[1] + (o[1] - h[1]) * (xc - h[0]) / (o[0] - h[0]) + margin_m
        lower = zc < self._cap[j]
        j, zc = j[lower], zc[lower]
        old_cap = self._cap[j]
        self._cap[j] = zc
        seen = self._n[j] > 0
        j, zc, old_cap = j[seen], zc[seen], old_cap[seen]
        if j.size == 0:
            return None
        stat = self._bin_stats(self._z[j], self._u[j])[0]
        apply = (stat > zc) & (stat < zc + max_excess_m)
        # a bin the old cap held whose excess over the new one is a step's: its own height
        # (only these take the statistic again, so the compiled map's heights stay its own)
        was_capped = self._mid[j] == old_cap
        mid = np.where(apply, zc, np.where(was_capped, stat, self._mid[j]))
        moved = mid != self._mid[j]
        if not moved.any():
            return None
        j = j[moved]
        self._mid[j] = mid[moved]
        self._profile = None
        self.version += 1
        return int(j[0]) + self._i0, int(j[-1]) + self._i0

    def _used_rule(self, n: NDArray[np.int64], Z: NDArray[np.float64]) -> NDArray[np.bool_]:
        """Per bin (count ``n``, kept heights ``Z`` as in :meth:`_bin_stats`): used once
        ``min_keyframes`` keyframes saw it, or ``agree_keyframes`` whose heights agree within
        ``agree_m``."""
        spread = np.nanmax(Z, axis=1) - np.nanmin(Z, axis=1)
        return (n >= self.min_keyframes) | ((n >= self.agree_keyframes) & (spread <= self.agree_m))

    def _bin_stats(
        self, Z: NDArray[np.float64], U: NDArray[np.float64] | None = None
    ) -> tuple[NDArray, NDArray]:
        """Height and its squared standard error per row of ``Z`` (bins x kept keyframes,
        NaN where empty; every row has at least one height), over the heights whose view
        ceiling (``U``, same shape) reaches the row's second-highest height (its highest
        when it has one) less ``top_band_m`` (module docstring: a keyframe that could not see
        that high is no evidence against a surface there)."""
        if U is not None:
            # the reference: the second-highest kept height (the highest when the row has
            # one), so that a single view's height (a mixed pixel) censors no other view
            k = np.sum(np.isfinite(Z), axis=1)
            top = np.sort(Z, axis=1)[np.arange(Z.shape[0]), np.maximum(k - 2, 0)]
            Z = np.where(U < top[:, None] - self.top_band_m, np.nan, Z)
        n = np.sum(np.isfinite(Z), axis=1)
        if self.statistic == "mean":
            mid = np.nanmean(Z, axis=1)
            return mid, np.nanvar(Z, axis=1) / n
        r, lo, hi = np.arange(Z.shape[0]), (n - 1) // 2, n // 2
        S = np.sort(Z, axis=1)  # NaN last
        mid = (S[r, lo] + S[r, hi]) / 2
        D = np.sort(np.abs(Z - mid[:, None]), axis=1)
        # scaled MAD (a Gaussian's sigma) and the median's standard error (x1.2533)
        sd = 1.4826 * (D[r, lo] + D[r, hi]) / 2
        return mid, (1.2533 * sd) ** 2 / n

    def profile(self, map_sigma_m: float) -> HeightProfile:
        """The used bins of the whole map (rebuilt after each keyframe)."""
        if self._profile is not None and self._profile[0] == map_sigma_m:
            return self._profile[1]
        j = np.flatnonzero(self._used)
        self._profile_bins = j + self._i0
        self._profile = (map_sigma_m, self._bins_profile(j, map_sigma_m))
        return self._profile[1]

    def _full_profile(self) -> HeightProfile:
        """:meth:`profile` with whatever sigma floor it was last asked for (x and z only)."""
        return self.profile(0.0 if self._profile is None else self._profile[0])

    def _bins_profile(self, j: NDArray[np.int64], map_sigma_m: float) -> HeightProfile:
        """The profile of the bins at array elements ``j`` (ascending)."""
        sig = np.sqrt(self._se2[j] + map_sigma_m**2)
        x_lo = ((j + self._i0) * self.bin_m).astype(np.float64)
        return HeightProfile(x_lo, x_lo + self.bin_m, self._mid[j], sig)

    def bin_cov(self, k: int) -> NDArray[np.float64]:
        """Mean keyframe camera covariance (2, 2) of bin ``k`` of :meth:`profile`."""
        return self.bin_cov_at(int(self._profile_bins[k]))

    def bin_cov_at(self, b: int) -> NDArray[np.float64]:
        """Mean keyframe camera covariance (2, 2) of the bin with index ``b``, m^2."""
        c = self._cov[b - self._i0] / float(self._n[b - self._i0])
        return np.array([[c[0], c[1]], [c[1], c[2]]])

    def bin_cov_rows(self, k: NDArray[np.int64]) -> NDArray[np.float64]:
        """:meth:`bin_cov` of many bins of :meth:`profile` at once, as rows (Pxx, Pxz, Pzz),
        (K, 3), m^2."""
        return self.bin_cov_rows_at(self._profile_bins[k])

    def bin_cov_rows_at(self, b: NDArray[np.int64]) -> NDArray[np.float64]:
        """:meth:`bin_cov_at` of the bins with indices ``b`` (K,), as rows (K, 3), m^2."""
        e = b - self._i0
        return self._cov[e] / self._n[e][:, None]

    def bin_cov_sums(self) -> tuple[NDArray[np.float64], NDArray[np.int64], int]:
        """The per-bin covariance sums (B, 3), keyframe counts (B,) and the bin index of
        element 0: :meth:`bin_cov_at` of bin b is sums[b - i0] / counts[b - i0]."""
        return self._cov, self._n, self._i0

    def bin_cov_mean(self, b: int) -> tuple[float, float, float]:
        """(xx, xz, zz) of :meth:`bin_cov_at`, m^2."""
        xx, xz, zz = (self._cov[b - self._i0] / float(self._n[b - self._i0])).tolist()
        return xx, xz, zz

    def bin_sigma(self, b: int, map_sigma_m: float) -> float:
        """1-sigma (m) of the height of the bin with index ``b``: its standard error over
        the keyframes, floored by ``map_sigma_m`` in quadrature."""
        return math.sqrt(self._se2[b - self._i0] + map_sigma_m**2)

    def window(self, x_min_m: float, x_max_m: float, map_sigma_m: float) -> MapWindow:
        """The used bins overlapping [x_min_m, x_max_m] (as :meth:`HeightProfile.window`)."""
        full = self.profile(map_sigma_m)
        i0 = int(np.searchsorted(full.x_hi_m, x_min_m, side="left"))
        i1 = int(np.searchsorted(full.x_lo_m, x_max_m, side="right"))
        s = slice(i0, max(i0, i1))
        prof = HeightProfile(full.x_lo_m[s], full.x_hi_m[s], full.z_m[s], full.sigma_m[s])
        return MapWindow(prof, self._profile_bins[s])

    def bin_below(self, x_m: float) -> int:
        """Index of the last used bin starting before ``x_m`` (the first used bin if none),
        -1 for an empty map."""
        full = self._full_profile()
        if len(full) == 0:
            return -1
        k = int(np.searchsorted(full.x_lo_m, x_m)) - 1
        return int(self._profile_bins[min(max(k, 0), len(full) - 1)])

    def edges(self) -> Edges:
        """The edges of the whole map (cached until the next keyframe)."""
        return self._cached_edges()[1]

    def edge_summary(self) -> tuple[int, float, float]:
        """:meth:`Edges.summary` of :meth:`edges` (cached until the next keyframe)."""
        return self._cached_edges()[2]

    def _cached_edges(self) -> tuple[int, Edges, tuple[int, float, float]]:
        if self._edges is None or self._edges[0] != self.version:
            e = self._find_edges()
            self._edges = (self.version, e, e.summary())
        return self._edges

    def _find_edges(self) -> Edges:
        return edge_runs(self._full_profile(), self.edge_min_rise_m, self.edge_max_gap_m)[0]


class IncrementalHeightMap(OnlineHeightMap):
    """:class:`OnlineHeightMap` with the queries answered from the bins near them and the
    edges updated over the part of the map a keyframe changed (module docstring); same
    answers, per-frame work independent of the map's length. ``kernels``: the compiled
    module (vio_graph/safety/compiled.py) for the keyframe step, the window and the edge
    scan, or None (numpy)."""

    def __init__(
        self,
        bin_m: float,
        min_keyframes: int,
        top_band_m: float = 0.01,
        statistic: str = "median",
        capacity: int = 24,
        edge_min_rise_m: float = 0.04,
        edge_max_gap_m: float = 0.15,
        kernels: ModuleType | None = None,
        agree_keyframes: int | None = None,
        agree_m: float = 0.0,
        view_ceilings: bool = True,
    ) -> None:
        super().__init__(
            bin_m,
            min_keyframes,
            top_band_m,
            statistic,
            capacity,
            edge_min_rise_m,
            edge_max_gap_m,
            agree_keyframes,
            agree_m,
            view_ceilings,
        )
        self._kernels = kernels
        self._geometry = clearance if kernels is None else kernels
        self._edge_xz = np.zeros((0, 2))
        self._edge_rise = np.zeros(0)
        self._edge_first = np.zeros(0, np.int64)  # bin index where each edge's scan starts

    def add_keyframe(
        self,
        camera_xz_m: ArrayLike,
        profile_xz_m: ArrayLike,
        cov_position_m2: ArrayLike,
        bin_tops: tuple[NDArray[np.int64], NDArray[np.float64]] | None = None,
    ) -> tuple[int, int] | None:
        """As :meth:`OnlineHeightMap.add_keyframe`; ``bin_tops``: the compiled
        ``keyframe_tops`` of this keyframe when the caller has it (compiled path only)."""
        if self._kernels is None:
            changed = super().add_keyframe(camera_xz_m, profile_xz_m, cov_position_m2)
        else:
            changed = self._add_keyframe_compiled(
                camera_xz_m, profile_xz_m, cov_position_m2, bin_tops
            )
        if changed is not None:
            self._rescan_edges(*changed)
        return changed

    def add_contact(
        self, heel_xz_m: ArrayLike, toe_xz_m: ArrayLike, margin_m: float, max_excess_m: float
    ) -> tuple[int, int] | None:
        """As :meth:`OnlineHeightMap.add_contact`, with the edges of the changed bins
        scanned again (compiled, median statistic: the caps and heights in one kernel call,
        ``contact_caps``, the same floats)."""
        if self._kernels is not None and self.statistic == "median":
            changed = self._add_contact_compiled(heel_xz_m, toe_xz_m, margin_m, max_excess_m)
        else:
            changed = super().add_contact(heel_xz_m, toe_xz_m, margin_m, max_excess_m)
        if changed is not None:
            self._rescan_edges(*changed)
        return changed

    def _add_contact_compiled(
        self, heel_xz_m: ArrayLike, toe_xz_m: ArrayLike, margin_m: float, max_excess_m: float
    ) -> tuple[int, int] | None:
        """:meth:`OnlineHeightMap.add_contact` (median statistic) through the kernel."""
        assert self._kernels is not None
        hx, hz = np.asarray(heel_xz_m, dtype=float).reshape(-1).tolist()
        ox, oz = np.asarray(toe_xz_m, dtype=float).reshape(-1).tolist()
        if not all(map(math.isfinite, (hx, hz, ox, oz))) or ox == hx:
            return None
        self.max_excess_m = max_excess_m
        b0 = math.floor(min(hx, ox) / self.bin_m)
        b1 = math.floor(max(hx, ox) / self.bin_m)
        self._grow(b0, b1)
        first, last = self._kernels.contact_caps(
            hx, hz, ox, oz, float(margin_m), float(max_excess_m), b0, b1, self._i0,
            self.bin_m, self._z, self._u, self._n, self._mid, self._cap, self.top_band_m,
        )  # fmt: skip
        if first < 0:
            return None
        self._profile = None
        self.version += 1
        return int(first) + self._i0, int(last) + self._i0

    def _add_keyframe_compiled(
        self,
        camera_xz_m: ArrayLike,
        profile_xz_m: ArrayLike,
        cov_position_m2: ArrayLike,
        bin_tops: tuple[NDArray[np.int64], NDArray[np.float64]] | None,
    ) -> tuple[int, int] | None:
        """:meth:`OnlineHeightMap.add_keyframe` through the compiled kernels."""
        assert self._kernels is not None
        if bin_tops is None:
            rel = np.asarray(profile_xz_m, dtype=float).reshape(-1, 2)
            cam = np.asarray(camera_xz_m, dtype=float)
            bin_tops = self._kernels.keyframe_tops(
                rel, float(cam[0]), float(cam[1]), self.bin_m, self.top_band_m
            )
        bins, tops = bin_tops
        if bins.shape[0] == 0:
            return None
        self._grow(int(bins[0]), int(bins[-1]))
        ceil = np.full(bins.shape[0], np.inf)
        if self.view_ceilings:
            rel = np.asarray(profile_xz_m, dtype=float).reshape(-1, 2)
            rel = rel[np.all(np.isfinite(rel), axis=1)]
            cam = np.asarray(camera_xz_m, dtype=float)
            ceil = view_ceilings(rel, float(cam[0]), float(cam[1]), bins, self.bin_m, tops)
        self._kernels.add_tops(
            self._z,
            self._zs,
            self._n,
            self._used,
            self._mid,
            self._se2,
            self._cov,
            bins - self._i0,
            tops,
            self.min_keyframes,
            self.agree_keyframes,
            self.agree_m,
            self.statistic == "median",
            np.asarray(cov_position_m2, dtype=float),
            self._cap,
            self.max_excess_m,
            self._u,
            ceil,
            self.top_band_m,
        )
        self._profile = None
        self.version += 1
        return int(bins[0]), int(bins[-1])

    def joined_compiled(
        self, edge_xz_m: NDArray[np.float64], edge_rise_m: NDArray, edge_first: NDArray
    ) -> None:
        """After the compiled ``keyframe_step`` updated the bin arrays in place: the
        re-scanned edges (xz (E, 2), rise (E,), first bin index (E,)) and the caches'
        version."""
        self._edge_xz, self._edge_rise, self._edge_first = edge_xz_m, edge_rise_m, edge_first
        self._profile = None
        self.version += 1

    def _elements(self, x_min_m: float, x_max_m: float) -> tuple[int, int]:
        """The array elements [a0, a1) holding every bin that overlaps [x_min_m, x_max_m]
        (finite): bins beyond them lie a bin or more outside the range."""
        b = self.bin_m
        n = self._n.shape[0]
        a0 = min(max(math.floor(x_min_m / b) - 2 - self._i0, 0), n)
        a1 = min(max(math.floor(x_max_m / b) + 3 - self._i0, a0), n)
        return a0, a1

    def bridged_gap(self, x_min_m: float, x_max_m: float, max_gap_m: float) -> bool:
        """Whether the window over [x_min_m, x_max_m] (:meth:`window`) may hold a strip
        that :func:`~vio_graph.safety.clearance.gap_terrain` fills (a gap between consecutive
        bins wider than its tolerance and at most ``max_gap_m``): answered by the compiled
        kernel without building the window; True (ask gap_terrain) without the kernels or
        for a range that is not finite."""
        if self._kernels is None or not (math.isfinite(x_min_m) and math.isfinite(x_max_m)):
            return True
        a0, a1 = self._elements(x_min_m, x_max_m)
        return bool(
            self._kernels.window_bridged_gap(
                self._used, self._i0, self.bin_m, a0, a1, x_min_m, x_max_m, max_gap_m
            )
        )

    def window(self, x_min_m: float, x_max_m: float, map_sigma_m: float) -> MapWindow:
        if not (math.isfinite(x_min_m) and math.isfinite(x_max_m)):
            return super().window(x_min_m, x_max_m, map_sigma_m)
        b = self.bin_m
        a0, a1 = self._elements(x_min_m, x_max_m)
        if self._kernels is not None:
            lo, hi, z, sig, bins = self._kernels.window_bins(
                self._used, self._mid, self._se2, a0, a1, self._i0, b, x_min_m, x_max_m, map_sigma_m
            )
            return MapWindow(HeightProfile(lo, hi, z, sig), bins)
        j = a0 + np.flatnonzero(self._used[a0:a1])
        x_lo = ((j + self._i0) * b).astype(np.float64)
        j = j[(x_lo + b >= x_min_m) & (x_lo <= x_max_m)]
        return MapWindow(self._bins_profile(j, map_sigma_m), j + self._i0)

    def bin_below(self, x_m: float) -> int:
        if not math.isfinite(x_m):
            return super().bin_below(x_m)
        if self._kernels is not None:
            found, b = self._kernels.bin_below(self._used, self._i0, self.bin_m, x_m)
            return int(b) if found else -1
        # bins from this index on start after x_m
        hi = min(max(int(np.floor(x_m / self.bin_m)) + 2 - self._i0, 0), self._n.shape[0])
        span = 64
        while True:
            a = max(hi - span, 0)
            j = a + np.flatnonzero(self._used[a:hi])
            j = j[(j + self._i0) * self.bin_m < x_m]
            if j.size:
                return int(j[-1]) + self._i0
            if a == 0:  # no used bin starts before x_m: the first used bin, if any
                j = np.flatnonzero(self._used)
                return int(j[0]) + self._i0 if j.size else -1
            span *= 4

    def _find_edges(self) -> Edges:
        return Edges(self._edge_xz, self._edge_rise)

    def _cached_edges(self) -> tuple[int, Edges, tuple[int, float, float]]:
        # kept while the edge arrays are the same objects: the compiled re-scan hands back
        # the arrays it was given when the edges did not change (most keyframes)
        c = self._edges
        if c is None or c[1].xz_m is not self._edge_xz or c[1].rise_m is not self._edge_rise:
            e = self._find_edges()
            k = self._kernels
            if k is not None and len(e) <= k.PAIRWISE_MAX_N:  # (the same floats, one call)
                summary = k.edge_summary(e.xz_m, e.rise_m)
            else:
                summary = e.summary()
            c = self._edges = (self.version, e, summary)
        return c

    def _step(self, p: int, q: int) -> bool:
        """Consecutive used bins (array elements p < q) form a transition pair
        (:func:`edge_runs`: height change above ``SLOPE_STEP_M``, gap within the max)."""
        b, i0 = self.bin_m, self._i0
        gap = (q + i0) * b - ((p + i0) * b + b)
        return bool(gap <= self.edge_max_gap_m and abs(self._mid[q] - self._mid[p]) > SLOPE_STEP_M)

    def _quiet_stretch(self, used: list[int]) -> int | None:
        """Walking the used bins (array elements) ``used`` in order, away from the changed
        part of the map: the element at the far end of the first quiet stretch (module
        docstring), None if the walk ends first."""
        if not used:
            return None
        b, i0 = self.bin_m, self._i0
        end = used[0]  # the stretch so far runs from ``end`` (near side) to ``used[k]``
        for prev, cur in zip(used[:-1], used[1:], strict=True):
            p, q = (prev, cur) if prev < cur else (cur, prev)
            if self._step(p, q):
                end = cur
                continue
            lo, hi = (end, cur) if end < cur else (cur, end)
            if (hi + i0) * b + b - (lo + i0) * b > MAX_TRANSITION_BIN_M:
                return max(cur, end)  # the stretch's right end: where the scan starts/stops
        return None

    def _rescan_edges(self, b_first: int, b_last: int) -> None:
        """Re-run the edge scan over the bins from the quiet stretch before ``b_first`` to
        the one after ``b_last`` (bin indices) and splice its edges in."""
        lo_e, hi_e = b_first - self._i0, b_last - self._i0
        if self._kernels is not None:
            self._edge_xz, self._edge_rise, self._edge_first = self._kernels.rescan_edges(
                self._used,
                self._mid,
                self._i0,
                self.bin_m,
                lo_e,
                hi_e,
                self.edge_min_rise_m,
                self.edge_max_gap_m,
                SLOPE_STEP_M,
                MAX_TRANSITION_BIN_M,
                self._edge_xz,
                self._edge_rise,
                self._edge_first,
            )
            return
        n = self._n.shape[0]
        start = stop = None
        span = 64
        while start is None:  # the scan's first element: the near end of a quiet stretch
            a = max(lo_e - span, 0)
            before = (a + np.flatnonzero(self._used[a:lo_e]))[::-1].tolist()
            start = self._quiet_stretch(before)
            if a == 0:
                break
            span *= 4
        span = 64
        while stop is None:
            a = min(hi_e + 1 + span, n)
            after = (hi_e + 1 + np.flatnonzero(self._used[hi_e + 1 : a])).tolist()
            stop = self._quiet_stretch(after)
            if a == n:
                break
            span *= 4
        lo = 0 if start is None else start
        hi = n - 1 if stop is None else stop
        j = lo + np.flatnonzero(self._used[lo : hi + 1])
        mid, first = self._geometry.edge_runs(
            self._bins_profile(j, 0.0), self.edge_min_rise_m, self.edge_max_gap_m
        )
        first_b = j[first] + self._i0
        lo_b = -np.inf if start is None else lo + self._i0
        hi_b = np.inf if stop is None else hi + self._i0
        keep_l = self._edge_first < lo_b
        keep_r = self._edge_first >= hi_b
        self._edge_xz = np.concatenate([self._edge_xz[keep_l], mid.xz_m, self._edge_xz[keep_r]])
        self._edge_rise = np.concatenate(
            [self._edge_rise[keep_l], mid.rise_m, self._edge_rise[keep_r]]
        )
        self._edge_first = np.concatenate(
            [self._edge_first[keep_l], first_b, self._edge_first[keep_r]]
        )


def view_ceilings(
    rel_xz_m: NDArray[np.float64],
    cam_x_m: float,
    cam_z_m: float,
    bins: NDArray[np.int64],
    bin_m: float,
    tops_m: NDArray[np.float64],
) -> NDArray[np.float64]:
    """Per bin a keyframe saw (index ``bins``, its height ``tops_m``): the highest its view
    reaches over the bin, m. The keyframe's steepest upward (least downward) line of sight
    is that to the point of its profile (``rel_xz_m``, camera-relative, finite rows) with the
    largest z / x ahead of the camera; over the bin it reaches the camera's height plus that
    slope times the x offset of the bin's nearer (for a downward slope) end. A surface higher
    than that over the bin (a nosing above the lower tread seen under it, or the part of a
    riser above the top of the camera's field of view) was out of this keyframe's sight.
    Never below the keyframe's own height there; +inf without a point ahead."""
    x, z = rel_xz_m[:, 0], rel_xz_m[:, 1]
    ahead = x > 1e-6
    if not ahead.any():
        return np.full(bins.shape[0], np.inf)
    slope = float(np.max(z[ahead] / x[ahead]))
    x_lo = bins * bin_m
    u = cam_z_m + np.maximum(slope * (x_lo - cam_x_m), slope * (x_lo + bin_m - cam_x_m))
    return np.maximum(u, tops_m)
