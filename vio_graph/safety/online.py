"""The per-frame safety monitor: a height map from what has been seen so far, and the foot's
clearance, placement and the terrain ahead against it (no look-ahead, no I/O).

Map: vio_graph/safety/height_map.py (per x bin of ``SafetyConfig.bin_m``, the median over
keyframes of the top of each keyframe's profile in the bin; each bin also keeps the mean
camera position covariance of the keyframes that saw it, for the relative-pose part of the
sigma). The monitor asks it about the bins near the foot and the edges. With the compiled
kernels (vio_graph/safety/compiled.py) it answers from those bins only
(``IncrementalHeightMap``); in numpy it is by default the reference map, which rebuilds its
whole profile after each keyframe (on a trial of minutes no slower than the incremental
map's bookkeeping in numpy). Same outputs either way (tests/test_safety_incremental.py).

Sigma. The clearance is a function of the foot minus the terrain point. Both were placed by
the filter: the terrain at the keyframes that saw it, the foot now. The drift between the two
is modelled as a random walk, so its covariance is |P_now - P_keyframes| (eigenvalues made
non-negative), weighted by ``relative_pose_scale``; projected on the distance's gradient,
plus the bin's height scatter (standard error over keyframes, floored at ``map_sigma_m``) and
``foot_sigma_m`` (docs/method.md). The pose term's vertical part and the map term are
multiplied by the consistency scales the keyframes' heights give against the map
(safety/consistency.py); the pose term's x part keeps the filter's growth, which no test
observes (``pose_scale_on_x``).

Motion model of the prediction (``motion_model``):

- ``swing_template`` (default): the user's own previous swings. A swing runs from lift-off
  (the first frame without a stance anchor at which the toe moves faster than
  ``swing_speed_mps``) to landing (the next anchored frame, or the toe slowing below a third
  of that speed); its heel and toe positions relative to where they were at lift-off are kept
  as functions of the time since lift-off (the phase). At a swing frame with phase tau, the
  foot over the horizon is the current heel / toe plus the displacement the template made
  from tau to tau + h (median over the last ``template_swings`` swings; a template that has
  already landed by tau + h stays where it landed). Until one swing has been seen, and
  outside a swing, the constant-velocity model is used.
- ``constant_velocity``: the foot outline translates at the toe's velocity, a finite
  difference of the last two frames' toe estimates, constant over ``horizon_s``.
"""

from __future__ import annotations

import math
from collections import deque
from collections.abc import Iterator, Sequence
from dataclasses import dataclass, field, fields
from operator import attrgetter
from types import ModuleType

import numpy as np
from numpy.typing import ArrayLike, NDArray

from vio_graph.growable import GrowableArray
from vio_graph.safety import clearance
from vio_graph.safety.clearance import (
    MAX_TRANSITION_BIN_M,
    NO_CLEARANCE,
    SLOPE_STEP_M,
    Clearance,
    Edges,
    HeightProfile,
    clearance_sigma,
    gap_terrain,
    next_edge_index,
    non_penetrating,
    placement_on_tread,
    unseen_distance,
)
from vio_graph.safety.config import SafetyConfig
from vio_graph.safety.consistency import ChiSquareScale, MapConsistency
from vio_graph.safety.height_map import IncrementalHeightMap, MapWindow, OnlineHeightMap
from vio_graph.safety.prediction_error import PredictionErrors

NAN = float("nan")
_NAN2, _NAN4 = np.full(2, NAN), np.full(4, NAN)
_NO_EDGES = np.zeros((0, 2))


@dataclass(frozen=True)
class SafetyEstimate:
    """The safety outputs of one frame (metres, seconds; NaN where unknown).

    ``clearance_m`` / ``clearance_sigma_m``: foot outline to the mapped terrain, and its
    1-sigma; ``toe_line_xz_m`` (2, 2): the closest foot point and terrain point (the line the
    viewer draws). ``nosing_clearance_m`` / ``nosing_sigma_m``: foot to the next edge ahead.
    ``predicted_min_clearance_m``: minimum clearance over the horizon;
    ``predicted_min_nosing_clearance_m``: the same to the edges the toe reaches over the
    horizon from the next one on; ``near_trip_clearance_m``: its minimum over the predicted
    poses that could be a near-trip (each pose against its own next edge, the toe moving
    forward, the foot clear of that edge before; with ``warning_error_check``, the swing
    template's poses only up to the last horizon step its measured error in this swing
    allows), which the ``near_trip_warning`` tests.
    ``edge_distance_m`` / ``edge_distance_sigma_m``: x from the toe to the next edge ahead,
    ``edge_xz_m`` (2,): that edge's point;
    ``steps_seen``, ``mean_rise_m``, ``mean_tread_m``: the edges mapped so far.
    ``landing``: the foot landed at this frame; then ``placement`` (4,): heel and toe to the
    tread's nosing, heel and toe to its back edge (else NaN).
    ``pose_consistency_scale`` / ``map_consistency_scale``: the factors the keyframes'
    heights put on the sigmas' pose and map terms (safety/consistency.py; a pose scale above
    1: the filter's covariance understates its drift).
    """

    clearance_m: float
    clearance_sigma_m: float
    toe_line_xz_m: NDArray[np.float64]
    nosing_clearance_m: float
    nosing_sigma_m: float
    predicted_min_clearance_m: float
    predicted_min_nosing_clearance_m: float
    near_trip_warning: bool
    edge_distance_m: float
    edge_distance_sigma_m: float
    steps_seen: int
    mean_rise_m: float
    mean_tread_m: float
    landing: bool
    placement: NDArray[np.float64]
    edge_xz_m: NDArray[np.float64] = field(default_factory=lambda: np.full(2, np.nan))
    near_trip_clearance_m: float = NAN
    pose_consistency_scale: float = 1.0
    map_consistency_scale: float = 1.0


#: frames.csv columns of a SafetyEstimate, in order (docs/outputs.md)
CSV_COLUMNS = (
    "clearance_m",
    "clearance_sigma_m",
    "nosing_clearance_m",
    "nosing_sigma_m",
    "predicted_min_clearance_m",
    "predicted_min_nosing_clearance_m",
    "near_trip_warning",
    "edge_distance_m",
    "edge_distance_sigma_m",
    "steps_seen",
    "mean_rise_m",
    "mean_tread_m",
    "landing",
    "heel_to_nosing_m",
    "toe_to_nosing_m",
    "heel_to_back_m",
    "toe_to_back_m",
    "pose_consistency_scale",
    "map_consistency_scale",
)


#: SafetyEstimate's array fields and their shapes; its bool and int fields (SafetyLog)
_ARRAY_FIELDS = {"toe_line_xz_m": (2, 2), "placement": (4,), "edge_xz_m": (2,)}
_BOOL_FIELDS = ("near_trip_warning", "landing")
_INT_FIELDS = ("steps_seen",)


class SafetyLog:
    """The SafetyEstimate (or None) of every frame of a replay, as one float64 row a frame
    (27 numbers, 8 bytes each) instead of an object with three small arrays (~1 KB).
    Reads like the list it replaces: ``len``, truthiness, ``log[k]`` and iteration give
    SafetyEstimate objects equal field for field to the ones appended (bools and ints
    restored; every float, NaN included, stored exactly), or None."""

    def __init__(self) -> None:
        names = [f.name for f in fields(SafetyEstimate)]
        self._scalars = [n for n in names if n not in _ARRAY_FIELDS]
        self._arrays = [(n, _ARRAY_FIELDS[n]) for n in names if n in _ARRAY_FIELDS]
        width = len(self._scalars) + sum(math.prod(s) for _, s in self._arrays) + 1
        self._rows = GrowableArray((width,))  # last column: 1 = an estimate, 0 = None
        self._scalars_of = attrgetter(*self._scalars)
        self._arrays_of = attrgetter(*(n for n, _ in self._arrays))
        self._none_row = [NAN] * (width - 1) + [0.0]

    def append(self, s: SafetyEstimate | None) -> None:
        # the row as one list of Python floats written into the buffer (float64 from each
        # float exactly, array elements through tolist bit for bit), instead of a small
        # array per field joined by np.concatenate (~5 -> ~3 us a row)
        if s is None:
            self._rows.append(self._none_row)
            return
        row = list(map(float, self._scalars_of(s)))
        for a in self._arrays_of(s):
            row += np.asarray(a, float).ravel().tolist()
        row.append(1.0)
        self._rows.append(row)

    def __len__(self) -> int:
        return len(self._rows)

    def __getitem__(self, k: int) -> SafetyEstimate | None:
        row = self._rows[k]
        if row[-1] == 0.0:
            return None
        values: dict = {}
        for i, n in enumerate(self._scalars):
            v = float(row[i])
            values[n] = bool(v) if n in _BOOL_FIELDS else int(v) if n in _INT_FIELDS else v
        j = len(self._scalars)
        for n, shape in self._arrays:
            size = math.prod(shape)
            values[n] = row[j : j + size].reshape(shape).copy()
            j += size
        return SafetyEstimate(**values)

    def __iter__(self) -> Iterator[SafetyEstimate | None]:
        return (self[k] for k in range(len(self)))

    def column(self, name: str) -> NDArray[np.float64]:
        """Field ``name`` of every frame as floats, (N,) or (N, *shape) for an array field,
        NaN at frames without an estimate (bools as 0 / 1): without rebuilding the
        objects."""
        rows = self._rows.view()
        if name in self._scalars:
            return rows[:, self._scalars.index(name)].copy()
        j = len(self._scalars)
        for n, shape in self._arrays:
            size = math.prod(shape)
            if n == name:
                return rows[:, j : j + size].reshape(-1, *shape).copy()
            j += size
        raise KeyError(name)


def csv_values(s: SafetyEstimate | None) -> list[str]:
    """The frames.csv cells of ``s`` (empty cells for NaN or a frame without outputs)."""
    if s is None:
        return [""] * len(CSV_COLUMNS)
    vals: list[float | int | bool] = [
        s.clearance_m,
        s.clearance_sigma_m,
        s.nosing_clearance_m,
        s.nosing_sigma_m,
        s.predicted_min_clearance_m,
        s.predicted_min_nosing_clearance_m,
        s.near_trip_warning,
        s.edge_distance_m,
        s.edge_distance_sigma_m,
        s.steps_seen,
        s.mean_rise_m,
        s.mean_tread_m,
        s.landing,
        *s.placement,
        s.pose_consistency_scale,
        s.map_consistency_scale,
    ]
    out = []
    for v in vals:
        if isinstance(v, bool | np.bool_):
            out.append(str(int(v)))
        elif isinstance(v, int | np.integer):
            out.append(str(int(v)))
        else:
            out.append("" if not np.isfinite(v) else f"{float(v):.5f}")
    return out


def _psd_abs(M: NDArray[np.float64], scale: float = 1.0) -> list[list[float]]:
    """|scale M| for a symmetric 2x2 M: its eigenvalues made non-negative (closed form)."""
    return _psd_abs_entries(float(M[0, 0]), float((M[0, 1] + M[1, 0]) / 2), float(M[1, 1]), scale)


def _psd_abs_entries(mxx: float, mxz: float, mzz: float, scale: float) -> list[list[float]]:
    """:func:`_psd_abs` of [[mxx, mxz], [mxz, mzz]]."""
    a, b, c = scale * mxx, scale * mxz, scale * mzz
    m, r = (a + c) / 2, (((a - c) / 2) ** 2 + b * b) ** 0.5
    l1, l2 = m + r, m - r
    if l2 >= 0 or r == 0:  # already non-negative (or a multiple of I)
        return [[a, b], [b, c]] if l2 >= 0 else [[abs(a), 0.0], [0.0, abs(c)]]
    # eigenvector of l1: (b, l1 - a) or (l1 - c, b)
    vx, vz = (b, l1 - a) if abs(b) > 1e-30 or abs(l1 - a) > 1e-30 else (1.0, 0.0)
    nrm = (vx * vx + vz * vz) ** 0.5
    vx, vz = vx / nrm, vz / nrm
    s1, s2 = abs(l1), abs(l2)
    return [
        [s1 * vx * vx + s2 * vz * vz, (s1 - s2) * vx * vz],
        [(s1 - s2) * vx * vz, s1 * vz * vz + s2 * vx * vx],
    ]


def _gradient(f: NDArray[np.float64], dt_s: float) -> NDArray[np.float64]:
    """``np.gradient(f, dt_s, axis=0)`` of (T >= 2, 2) samples: central differences inside,
    one-sided at the ends (the same operations, without its generic set-up)."""
    out = np.empty_like(f)
    out[1:-1] = (f[2:] - f[:-2]) / (2.0 * dt_s)
    out[0] = (f[1] - f[0]) / dt_s
    out[-1] = (f[-1] - f[-2]) / dt_s
    return out


def _template_at(ph: NDArray[np.float64], d: NDArray[np.float64], q: NDArray) -> NDArray:
    """A swing template's heel and toe displacements (len(q), 4) at the phases q (s), linear
    between its frames and held at its ends."""
    return np.stack([np.interp(q, ph, d[:, j]) for j in range(4)], 1)


def _worse_foot_sq(e: NDArray[np.float64]) -> NDArray[np.float64]:
    """Per row of heel and toe offsets (N, 4): the larger of the heel's and the toe's squared
    distance, m^2."""
    return np.maximum(e[:, 0] ** 2 + e[:, 1] ** 2, e[:, 2] ** 2 + e[:, 3] ** 2)


def forward_motion(v_xz_mps: Sequence[float] | NDArray[np.float64], cfg: SafetyConfig) -> bool:
    """The toe moves forward faster than ``warning_min_forward_speed_mps`` and at least as
    fast as it descends (a swing crossing an edge, not a landing)."""
    vx, vz = float(v_xz_mps[0]), float(v_xz_mps[1])
    return bool(
        np.isfinite(vx) and np.isfinite(vz) and vx > cfg.warning_min_forward_speed_mps and vz > -vx
    )


def compiled_kernels(force: bool = False) -> ModuleType | None:
    """vio_graph/safety/compiled.py when the compiled paths are on: numba installed and the
    front end's switch (``VIO_GRAPH_COMPILED``; "auto" as the replay sets it, see
    :func:`vio_graph.frontend.icp.compiled_kernels`) or ``force``; else None (numpy)."""
    from vio_graph.frontend.icp import compiled_kernels as frontend_kernels

    if not force and frontend_kernels() is None:
        return None
    try:
        from vio_graph.safety import compiled
    except ImportError:  # numba not installed
        if force:
            raise
        return None
    return compiled

    def bin_cov_rows(self, k: NDArray[np.int64]) -> NDArray[np.float64]:
        """:meth:`bin_cov` of many bins at once, as rows (Pxx, Pxz, Pzz), (K, 3), m^2."""
        sums, n = self._cov_bins
        return sums[k] / n[k][:, None]


class SafetyMonitor:
    """Per-frame safety outputs from the estimate (camera, covariance, heel, toe, stance)
    and the keyframe profiles seen so far.

    ``compiled``: the compiled kernels (True), numpy (False), or as the compiled front end
    (None: :func:`compiled_kernels`). ``incremental``: the map answers from the bins near the
    foot (:class:`IncrementalHeightMap`, True) or is the reference (:class:`OnlineHeightMap`,
    whole profile rebuilt per keyframe, False); None: incremental when compiled. The
    compiled kernels need the incremental map; the reference map comes with the reference
    consistency test (:class:`MapConsistency` ``reference``). ``fused`` (compiled only): each
    step of a frame in one kernel call, else the kernels of the single operations (the
    previous compiled path, kept for the equality test and the benchmark). Same outputs in
    every combination. ``predict_clearance``: False leaves ``predicted_min_clearance_m``
    NaN without computing it (the metrics' replays of other modes' paths, which do not
    score it; no other output depends on it)."""

    def __init__(
        self,
        config: SafetyConfig,
        incremental: bool | None = None,
        compiled: bool | None = None,
        fused: bool = True,
        predict_clearance: bool = True,
    ) -> None:
        if incremental is False and compiled:
            raise ValueError("the compiled safety kernels run on the incremental map")
        self.config = config
        self.predict_clearance = predict_clearance
        kernels = None
        if incremental is not False and compiled is not False:
            kernels = compiled_kernels(force=bool(compiled))
            if kernels is not None:
                kernels.warm_up(fused=fused)  # the one-time load here, not on the first frames
        if incremental is None:
            incremental = kernels is not None
        #: the module computing the per-frame geometry: clearance (numpy) or compiled
        self.geometry: ModuleType = clearance if kernels is None else kernels
        #: compiled: each step of a frame in one kernel call (``frame_terrain``,
        #: ``swing_prediction``, ``cv_prediction``, ``keyframe_step``); False: the kernels of
        #: the single operations with Python between them (the same numbers, bit for bit;
        #: tests/test_safety_incremental.py)
        self.fused = kernels is not None and fused
        self.map: OnlineHeightMap = (
            IncrementalHeightMap(
                config.bin_m,
                config.min_keyframes,
                statistic=config.map_statistic,
                edge_min_rise_m=config.edge_min_rise_m,
                edge_max_gap_m=config.edge_max_gap_m,
                kernels=kernels,
                agree_keyframes=config.agreement_keyframes,
                agree_m=config.agreement_tolerance_m,
                view_ceilings=config.view_ceilings,
            )
            if incremental
            else OnlineHeightMap(
                config.bin_m,
                config.min_keyframes,
                statistic=config.map_statistic,
                edge_min_rise_m=config.edge_min_rise_m,
                edge_max_gap_m=config.edge_max_gap_m,
                agree_keyframes=config.agreement_keyframes,
                agree_m=config.agreement_tolerance_m,
                view_ceilings=config.view_ceilings,
            )
        )
        self._prev: tuple[float, tuple[float, float]] | None = None  # (t, toe x, z)
        self._in_stance = False
        # swing templates: (phase s (S,), heel and toe minus their lift-off positions (S, 4))
        self._templates: deque[tuple[NDArray[np.float64], NDArray[np.float64]]] = deque(
            maxlen=config.template_swings
        )
        # the templates end to end for the compiled path: phases, displacements, row starts
        self._templates_flat: tuple[NDArray, NDArray, NDArray] | None = None
        #: the templates this swing's prediction uses (indices into _templates; None: all)
        self._selected: tuple[int, ...] | None = None
        self._swing: list[tuple[float, float, float, float, float]] = []  # t, heel, toe
        self._liftoff: tuple[float, NDArray[np.float64]] | None = None  # (t, heel+toe (4,))
        self._cleared: list[float] = []  # x of the edges the foot was clear of in this swing
        #: the horizon's instants (s since now)
        self._h = np.linspace(0.0, config.horizon_s, config.horizon_steps + 1)
        #: the template predictions' own errors in the current swing, measured when their
        #: instants arrive (this swing's only: pooled with the last 3 swings', the one-step
        #: first swing onto the stair also silenced the next swing's warning of a true
        #: near-trip, 222 ms ahead from a half-right template; upstair_near_trip s1)
        self.prediction_errors = PredictionErrors(self._h, kernels=kernels)
        self.consistency = MapConsistency(
            config.consistency_window_keyframes,
            config.consistency_min_keyframes,
            config.consistency_scale_range,
            reference=not incremental,  # the reference map with the reference medians
            kernels=kernels,
        )

    def _track_swing(
        self,
        t_s: float,
        heel: NDArray[np.float64],
        toe: NDArray[np.float64],
        in_stance: bool,
        toe_speed_mps: float,
    ) -> float:
        """Keep the current swing and close it into a template when the foot lands; the
        phase (s since lift-off) of this frame, NaN outside a swing.

        Lift-off: the first frame without a stance anchor at which the toe moves faster
        than ``swing_speed_mps``; landing: the next anchored frame, or the toe slower than
        ``swing_speed_mps`` / 3 once the swing is ``template_swing_s[0]`` old (the stance
        detector anchors only part of a stance)."""
        cfg = self.config
        lo, hi = cfg.template_swing_s
        moving = math.isfinite(toe_speed_mps) and toe_speed_mps > cfg.swing_speed_mps
        if self._liftoff is None:
            if in_stance or not moving:
                return NAN
            self._liftoff = (t_s, np.concatenate([heel, toe]))
            self._swing = []
            if self._selected is not None:
                self._selected = None
                self._templates_flat = None
            self.prediction_errors.start_swing()
        tau = t_s - self._liftoff[0]
        slow = math.isfinite(toe_speed_mps) and toe_speed_mps < cfg.swing_speed_mps / 3
        if in_stance or (slow and tau >= lo) or tau > hi:
            if len(self._swing) >= 3 and lo <= tau <= hi:
                d = np.concatenate([heel, toe]) - self._liftoff[1]
                a = np.asarray([*self._swing, (tau, *d.tolist())], dtype=float)
                self._templates.append((a[:, 0], a[:, 1:]))
                self._templates_flat = None
            self._liftoff = None
            return NAN
        # heel and toe minus their lift-off positions, on Python floats (the same IEEE
        # differences as the arrays')
        (hx, hz), (tx, tz) = heel.tolist(), toe.tolist()
        lhx, lhz, ltx, ltz = self._liftoff[1].tolist()
        self._swing.append((tau, hx - lhx, hz - lhz, tx - ltx, tz - ltz))
        return tau

    def _edges_reached(self, edges: Edges, e: int, toe_x_max_m: float) -> NDArray[np.float64]:
        """The edges from the next one (index ``e``) to the last one the toe can reach over
        the horizon (x up to ``toe_x_max_m`` plus ``toe_pass_m``), (E, 2): a swing over two
        steps passes two nosings."""
        if e < 0:
            return np.zeros((0, 2))
        x = edges.xz_m[e:, 0]
        n = max(1, int(np.searchsorted(x, toe_x_max_m + self.config.toe_pass_m, side="right")))
        return edges.xz_m[e : e + n]

    def _swept(
        self,
        lo_x_m: float,
        hi_x_m: float,
        search_lo_m: float,
        search_hi_m: float,
        clearance_now_m: float,
    ) -> tuple[float, float]:
        """The x range (min, max, m) of the bins the predicted minimum clearance can come
        from, for foot poses spanning x in [lo_x_m, hi_x_m] over the horizon (the first pose
        is the current foot): the prediction's search range [search_lo_m, search_hi_m] cut
        to the bins nearer in x to the poses than the current clearance (plus the sole). A
        bin farther in x than that is farther from every pose than the current foot is from
        the terrain, and the minimum is at most that (the current pose is one of the poses,
        and the predicted distance is never above :func:`foot_clearance`'s), so leaving it
        out changes only the time."""
        d = max(clearance_now_m + self.config.sole_thickness_m, 0.0) + 1e-6  # m; 1 um rounding
        return max(search_lo_m, lo_x_m - d), min(search_hi_m, hi_x_m + d)

    def _relative_cov(
        self, P: list[list[float]], b: int, scale: float, x_factor: float = 1.0
    ) -> list[list[float]]:
        """The drift covariance between now (camera covariance ``P``) and the keyframes that
        saw bin ``b``: |P - their mean covariance| times ``scale``, its x row and column
        times ``x_factor`` (the pose consistency scale's inverse when that scale acts on the
        vertical part only), m^2."""
        cxx, cxz, czz = self.map.bin_cov_mean(b)
        mxz = ((P[0][1] - cxz) + (P[1][0] - cxz)) / 2
        R = _psd_abs_entries(P[0][0] - cxx, mxz, P[1][1] - czz, scale)
        if x_factor != 1.0:
            f = x_factor
            return [[R[0][0] * f * f, R[0][1] * f], [R[1][0] * f, R[1][1]]]
        return R

    def _add_keyframe(
        self, camera_xz_m: ArrayLike, profile_xz_m: ArrayLike, P: NDArray[np.float64]
    ) -> None:
        """A keyframe (profile (N, 2), camera-relative) tested against the map, then joining
        it (numpy)."""
        cfg = self.config
        seen = self._keyframe_window(camera_xz_m, profile_xz_m)
        if seen is not None:  # the keyframe against the map, before it joins
            self.consistency.observe_keyframe(
                camera_xz_m,
                profile_xz_m,
                P,
                seen.profile,
                lambda k: self.map.bin_cov_rows_at(seen.bins[k]),
                cfg.bin_m,
                self.map.top_band_m,
                cfg.relative_pose_scale,
            )
        self.map.add_keyframe(camera_xz_m, profile_xz_m, P)

    def _add_keyframe_compiled(
        self, camera_xz_m: ArrayLike, profile_xz_m: ArrayLike, P: NDArray[np.float64]
    ) -> None:
        """:meth:`_add_keyframe` through the compiled kernels: with a finite camera, one
        call (``keyframe_step``: the keyframe binned, tested against the map and joining it,
        the edges re-scanned); else the keyframe binned once for the test and the map."""
        cfg = self.config
        rel = np.asarray(profile_xz_m, dtype=float).reshape(-1, 2)
        cx, cz = np.asarray(camera_xz_m, dtype=float).tolist()
        m = self.map
        assert isinstance(m, IncrementalHeightMap)
        if self.fused and math.isfinite(cx) and math.isfinite(cz):
            pose, mp = self.consistency.pose, self.consistency.map
            assert isinstance(pose, ChiSquareScale) and isinstance(mp, ChiSquareScale)
            while True:
                out = self.geometry.keyframe_step(
                    rel, cx, cz, P, cfg.bin_m, m.top_band_m, cfg.map_sigma_m,
                    m._z, m._zs, m._n, m._used, m._mid, m._se2, m._cov, m._i0,
                    m.min_keyframes, m.agree_keyframes, m.agree_m, m.statistic == "median",
                    m._cap, m.max_excess_m, pose.window != 0,
                    cfg.relative_pose_scale, pose._sorted, pose.leaving(), mp._sorted,
                    mp.leaving(), m.edge_min_rise_m, m.edge_max_gap_m, SLOPE_STEP_M,
                    MAX_TRANSITION_BIN_M, m._edge_xz, m._edge_rise, m._edge_first,
                    m._u, m.view_ceilings,
                )  # fmt: skip
                if out[0] != 1:
                    break
                m._grow(int(out[1]), int(out[2]))  # (rare: by a metre or more)
            if out[0] == 2:
                if out[3].size:
                    pose.accept_merged(out[3], out[4])
                if out[5].size:
                    mp.accept_merged(out[5], out[6])
                m.joined_compiled(out[7], out[8], out[9])
            return
        tops = self.geometry.keyframe_tops(rel, cx, cz, cfg.bin_m, self.map.top_band_m)
        seen: MapWindow | None = None
        if math.isfinite(cx):
            x_lo, x_hi = self.geometry.profile_x_range(rel, cx)
            if x_lo == x_lo:  # a finite point: the map's bins under the profile
                seen = self.map.window(x_lo, x_hi, cfg.map_sigma_m)
        else:  # (NaN bounds, as numpy gives them)
            seen = self._keyframe_window(camera_xz_m, rel)
        if seen is not None:
            self.consistency.observe_bin_tops(
                tops,
                seen.profile,
                seen.bins,
                *self.map.bin_cov_sums(),
                P,
                cfg.bin_m,
                cfg.relative_pose_scale,
            )
        assert isinstance(self.map, IncrementalHeightMap)
        self.map.add_keyframe(camera_xz_m, rel, P, tops)

    def _keyframe_window(self, camera_xz_m: ArrayLike, profile_xz_m: ArrayLike) -> MapWindow | None:
        """The map's used bins under a keyframe's profile (N, 2, camera-relative): all the
        consistency test compares it with; None without a finite point."""
        rel = np.asarray(profile_xz_m, dtype=float).reshape(-1, 2)
        x = rel[np.all(np.isfinite(rel), axis=1), 0]
        if x.size == 0:
            return None
        x0 = float(np.asarray(camera_xz_m, dtype=float)[0])
        # (the points' x as the map places them: relative x plus the camera's)
        return self.map.window(
            float((x + x0).min()), float((x + x0).max()), self.config.map_sigma_m
        )

    def _window(self, x_range_m: tuple[float, float]) -> HeightProfile:
        """The map's used bins over an x range (min, max), m."""
        return self.map.window(*x_range_m, self.config.map_sigma_m).profile

    def _approach(self, edge_x_m: float, d_m: NDArray[np.float64]) -> NDArray[np.bool_]:
        """Per foot pose of a sequence starting now (clearances ``d_m`` to the edge at
        ``edge_x_m``): the foot has been at least ``near_trip_m`` from that edge since the
        stance anchor was released (earlier frames or earlier poses of the sequence). A
        near-trip is the foot coming back close to an edge it was clear of, not the foot
        lifting off the nosing it stood on. The edge is remembered as cleared (by x, within
        two bins: it is re-detected at each keyframe)."""
        tol = 2 * self.config.bin_m
        clear = np.logical_or.accumulate(d_m >= self.config.near_trip_m)
        if any(abs(x - edge_x_m) <= tol for x in self._cleared):
            return np.ones(d_m.shape, bool)
        if clear[0]:
            self._cleared.append(edge_x_m)
        return clear

    def _approach_now(self, edge_x_m: float, d_m: float) -> bool:
        """:meth:`_approach` for the current pose alone (clearance ``d_m``)."""
        if any(abs(x - edge_x_m) <= 2 * self.config.bin_m for x in self._cleared):
            return True
        if d_m >= self.config.near_trip_m:
            self._cleared.append(edge_x_m)
            return True
        return False

    @property
    def edges(self) -> Edges:
        """The edges mapped so far (updated at each keyframe)."""
        return self.map.edges()

    def _template_motion(self, tau: float, h: NDArray[np.float64]) -> NDArray[np.float64] | None:
        """Median displacement (H, 4) of heel and toe from phase tau to tau + h over the
        templates, None without a template."""
        if not self._templates or not math.isfinite(tau):
            return None
        if self.geometry is not clearance:  # compiled
            return self.geometry.template_motion(tau, h, *self._flat_templates())
        out = []
        q = np.concatenate([[tau], tau + h])  # now, then the horizon's instants
        for ph, d in self._used_templates():
            at = _template_at(ph, d, q)
            out.append(at[1:] - at[:1])
        return np.median(np.stack(out), axis=0) if len(out) > 1 else out[0]

    def _swing_edges(
        self,
        hp: NDArray[np.float64],
        tp: NDArray[np.float64],
        edges: Edges,
        e: int,
        toe_x_max: float,
    ) -> tuple[float, float]:
        """Over the predicted heel / toe poses ``hp``, ``tp`` (H, 2) of the swing template:
        the minimum clearance to the edges the toe reaches from the next one (index ``e``)
        and the minimum over the near-trip candidates (NaN if none): poses with the toe
        moving forward, tested against their own next edge, the foot clear of it first
        (:meth:`_approach`, which remembers the edges cleared). Compiled: one kernel
        (``swing_edge_risk``), the same operations."""
        cfg, g = self.config, self.geometry
        dt = cfg.horizon_s / cfg.horizon_steps
        if g is not clearance:
            pred_edge, risk, new = g.swing_edge_risk(
                hp,
                tp,
                edges.xz_m,
                e,
                toe_x_max,
                cfg.toe_pass_m,
                cfg.sole_thickness_m,
                dt,
                cfg.warning_min_forward_speed_mps,
                cfg.near_trip_m,
                2 * cfg.bin_m,
                np.asarray(self._cleared, dtype=float),
                0.5,  # (the square roots as the C library's pow, as numpy's here)
            )
            self._cleared.extend(new.tolist())  # as _approach remembers them
            return float(pred_edge), float(risk)
        pred_edge = risk = NAN
        # the predicted toe velocity: a near-trip needs forward motion at that instant
        vp = _gradient(tp, dt)
        fwd = (vp[:, 0] > cfg.warning_min_forward_speed_mps) & (vp[:, 1] > -vp[:, 0])
        # each predicted pose is tested against its own next edge (as the truth is)
        nxt = np.searchsorted(edges.xz_m[:, 0], tp[:, 0] - cfg.toe_pass_m, side="right")
        for i, ee in enumerate(self._edges_reached(edges, e, toe_x_max)):
            dd = g.edge_clearance_many(hp, tp, ee, cfg.sole_thickness_m)
            d = float(np.min(dd))
            if math.isfinite(d) and not d >= pred_edge:  # NaN-safe minimum
                pred_edge = d
            ok = fwd & (nxt == e + i) & self._approach(float(ee[0]), dd)
            if ok.any() and not float(np.min(dd[ok])) >= risk:
                risk = float(np.min(dd[ok]))
        return pred_edge, risk

    def update(
        self,
        t_s: float,
        camera_xz_m: ArrayLike,
        cov_position_m2: ArrayLike,
        heel_xz_m: ArrayLike,
        toe_xz_m: ArrayLike,
        in_stance: bool,
        keyframe_profile_xz_m: ArrayLike | None = None,
    ) -> SafetyEstimate:
        """The outputs of one frame; ``keyframe_profile_xz_m`` (N, 2, camera-relative) when
        the frame is a keyframe (it joins the map before the frame's outputs are computed)."""
        cfg, g = self.config, self.geometry
        P = np.asarray(cov_position_m2, dtype=float)
        compiled = g is not clearance
        fused = compiled and self.fused
        if keyframe_profile_xz_m is not None:
            if compiled:
                self._add_keyframe_compiled(camera_xz_m, keyframe_profile_xz_m, P)
            else:
                self._add_keyframe(camera_xz_m, keyframe_profile_xz_m, P)
        heel = np.asarray(heel_xz_m, dtype=float)
        toe = np.asarray(toe_xz_m, dtype=float)
        hx, hz = heel.tolist()
        tx, tz = toe.tolist()
        edges = self.map.edges()
        sp, sm = self.consistency.pose_scale, self.consistency.map_scale
        pose_w = cfg.relative_pose_scale * sp * sp
        # the scale is what the keyframes' vertical offsets observed: x keeps the filter's
        # growth unless configured otherwise (sp >= the clip's lower end > 0)
        pose_xf = 1.0 if cfg.pose_scale_on_x else 1.0 / sp
        # clearance to the terrain and its sigma; the next edge ahead, the clearance to it
        gapped = True  # whether the window may hold a strip the gap-floor check fills
        if fused and math.isfinite(hx + hz + tx + tz):  # (one kernel call)
            m = self.map
            c_d, fx, fz, qx, qz, sig, e, nc, nsig, ed, edsig, gapped = g.frame_terrain(
                m._used, m._mid, m._se2, m._cov, m._n, m._i0, cfg.bin_m, edges.xz_m,
                hx, hz, tx, tz, *P.ravel().tolist(), cfg.window_m, cfg.min_coverage,
                cfg.unseen_terrain_check, cfg.edge_max_gap_m, cfg.sole_thickness_m,
                cfg.map_sigma_m, cfg.foot_sigma_m, cfg.toe_pass_m, pose_w, pose_xf, sm, 0.5,
            )  # fmt: skip
        else:
            c_d, fx, fz, qx, qz, sig, e, nc, nsig, ed, edsig = self._terrain_now(
                heel, toe, P.tolist(), edges, pose_w, sm, pose_xf
            )
        if math.isfinite(c_d) and cfg.gap_floor_check and gapped:  # (else: unchanged)
            c_d, fx, fz, qx, qz, sig = self._checked_clearance(
                heel, toe, P.tolist(), (c_d, fx, fz, qx, qz, sig), pose_w, sm, pose_xf
            )
        # prediction over the horizon and the near-trip warning
        v = (NAN, NAN)  # the toe's velocity (x, z), m/s
        if self._prev is not None and t_s > self._prev[0]:
            dt, (px, pz) = t_s - self._prev[0], self._prev[1]
            v = ((tx - px) / dt, (tz - pz) / dt)
        self._prev = (t_s, (tx, tz))
        speed = float(np.hypot(v[0], v[1]))  # m/s, NaN without a previous frame
        v_known = math.isfinite(v[0]) and math.isfinite(v[1])
        check = cfg.warning_error_check and cfg.motion_model == "swing_template"
        if check:  # the earlier predictions against where the foot went
            self.prediction_errors.observe(t_s, (hx, hz, tx, tz))
        tau = self._track_swing(t_s, heel, toe, bool(in_stance), speed)
        use_template = (
            cfg.motion_model == "swing_template" and bool(self._templates) and math.isfinite(tau)
        )
        if use_template and cfg.template_match != "off":
            sel: tuple[int, ...] | None = self._matching_templates()
            if not sel and cfg.template_match == "constant_velocity":
                use_template = False  # no swing like this one seen yet: as before any swing
            if not sel or len(sel) == len(self._templates):
                sel = None  # every template (none agrees: the check decides)
            if sel != self._selected:  # another predictor: its errors are still to measure
                self._selected = sel
                self._templates_flat = None
                if check:
                    self.prediction_errors.start_swing()
        if in_stance:
            self._cleared = []
        pred = pred_edge = risk = NAN  # risk: the minimum over near-trip candidates
        # the template motion and the predicted poses, computed once for the check
        template_motion: NDArray[np.float64] | None = None
        template_poses: NDArray[np.float64] | None = None
        c_pred = c_d if self.predict_clearance else NAN  # NaN: no predicted clearance
        if use_template and fused:
            pred, pred_edge, risk, new, template_motion, template_poses = g.swing_prediction(
                tau, self._h, *self._flat_templates(), hx, hz, tx, tz, c_pred, cfg.window_m,
                cfg.sole_thickness_m, self.map._used, self.map._mid, self.map._se2,
                self.map._i0, cfg.bin_m, cfg.map_sigma_m, edges.xz_m, e, cfg.toe_pass_m,
                cfg.horizon_s / cfg.horizon_steps, cfg.warning_min_forward_speed_mps,
                cfg.near_trip_m, 2 * cfg.bin_m, np.array(self._cleared, dtype=float), 0.5,
            )  # fmt: skip
            if new.size:
                self._cleared.extend(new.tolist())  # as _approach remembers them
        elif use_template:
            motion = self._template_motion(tau, self._h)
            assert motion is not None
            template_motion = motion
            hp = heel[None] + motion[:, :2]
            tp = toe[None] + motion[:, 2:]
            # x extent of the poses (rounding is monotonic: the extreme displacement gives
            # the extreme position)
            m_lo, m_hi = motion.min(axis=0), motion.max(axis=0)
            toe_x_max = float(toe[0] + m_hi[2])
            if math.isfinite(c_pred):
                lo_x = float(min(heel[0] + m_lo[0], toe[0] + m_lo[2]))
                hi_x = float(max(heel[0] + m_hi[0], toe_x_max))
                w = cfg.window_m
                swept = self._window(self._swept(lo_x, hi_x, lo_x - w, hi_x + w, c_d))
                pred = float(np.min(g.clearance_many(hp, tp, swept, cfg.sole_thickness_m)))
            pred_edge, risk = self._swing_edges(hp, tp, edges, e, toe_x_max)
        else:
            x0, x1 = min(hx, tx) - cfg.window_m, max(hx, tx) + cfg.window_m
            sweep = None  # the x range of the bins the prediction searches
            if v_known and math.isfinite(c_pred) and speed * cfg.horizon_s < 1e-3:
                pred = c_d  # the foot moves < 1 mm over the horizon: within 1 mm of now
            elif v_known and math.isfinite(c_pred):
                dx = float(v[0]) * cfg.horizon_s  # the foot's x span over the horizon
                lo_x = float(min(heel[0], toe[0])) + min(dx, 0.0)
                hi_x = float(max(heel[0], toe[0])) + max(dx, 0.0)
                sweep = self._swept(lo_x, hi_x, x0 - abs(dx), x1 + abs(dx), c_d)
            reach_x = float(toe[0] + max(float(v[0]), 0.0) * cfg.horizon_s) if v_known else tx
            if fused and math.isfinite(hx + hz + tx + tz):  # (one kernel call)
                m = self.map
                p, pred_edge, risk, new = g.cv_prediction(
                    sweep is not None, *(sweep or (NAN, NAN)), hx, hz, tx, tz, *v,
                    cfg.horizon_s, cfg.horizon_steps, m._used, m._mid, m._se2, m._i0,
                    cfg.bin_m, cfg.map_sigma_m, cfg.sole_thickness_m, edges.xz_m, e, reach_x,
                    cfg.toe_pass_m, cfg.near_trip_m, 2 * cfg.bin_m,
                    cfg.warning_min_forward_speed_mps, np.array(self._cleared, dtype=float),
                    0.5,
                )  # fmt: skip
                if sweep is not None:
                    pred = p
                if new.size:
                    self._cleared.extend(new.tolist())  # as _approach_now remembers them
                e_reached: NDArray[np.float64] = _NO_EDGES
            else:
                if sweep is not None:
                    pred = g.predicted_min_clearance(
                        heel,
                        toe,
                        v,
                        cfg.horizon_s,
                        cfg.horizon_steps,
                        self._window(sweep),
                        cfg.sole_thickness_m,
                    )
                e_reached = self._edges_reached(edges, e, reach_x)
            for ee in e_reached:
                d = g.predicted_min_edge_clearance(
                    heel, toe, v, cfg.horizon_s, cfg.horizon_steps, ee, cfg.sole_thickness_m
                )
                if math.isfinite(d) and not d >= pred_edge:  # NaN-safe minimum
                    pred_edge = float(d)
                now = float(g.edge_clearance_many(heel, toe, ee, cfg.sole_thickness_m)[0])
                cleared = self._approach_now(float(ee[0]), now)  # (remembers it)
                if cleared and forward_motion(v, cfg) and math.isfinite(d) and not d >= risk:
                    risk = float(d)
        if use_template and check:
            risk = self._trusted_risk(
                t_s, tau, heel, toe, edges, e, risk, template_motion, template_poses
            )
        s = nsig if math.isfinite(nsig) else 0.0
        warn = bool(
            not in_stance and math.isfinite(risk) and risk - cfg.warning_sigma * s < cfg.near_trip_m
        )
        # landing: the stance starts at this frame
        landing = bool(in_stance and not self._in_stance)
        self._in_stance = bool(in_stance)
        placement = _NAN4.copy()
        if landing:
            x0, x1 = min(hx, tx) - cfg.window_m, max(hx, tx) + cfg.window_m
            placement = placement_on_tread(
                heel,
                toe,
                self._window((x0, x1)),
                cfg.tread_tolerance_m,
                cfg.edge_max_gap_m,
                cfg.edge_min_rise_m,
            ).as_array()
        n_steps, rise, tread = self.map.edge_summary()
        if in_stance and cfg.contact_map:  # the standing foot joins the map (next frames)
            margin = cfg.contact_sigmas * math.hypot(cfg.foot_sigma_m, cfg.map_sigma_m)
            self.map.add_contact(heel, toe, margin, cfg.edge_min_rise_m)
        if cfg.non_penetration:  # the foot is never inside the terrain (the output only)
            mode = cfg.non_penetration_sigma
            # a contact is the sole on a tread (a vertical way out); inside a riser's face
            # (a horizontal one) the foot is placed by the pose's x error: no contact's bound
            tread = not abs(fx - qx) > abs(fz - qz)
            bound = mode == "contact" or (mode == "tread_contact" and tread)
            contact = cfg.foot_sigma_m if bound else math.inf
            c_d, sig = non_penetrating(c_d, sig, contact)
        if in_stance and cfg.stance_contact and math.isfinite(c_d):  # standing: in contact
            c_d, sig = 0.0, min(sig, cfg.foot_sigma_m) if sig >= 0.0 else cfg.foot_sigma_m
        return SafetyEstimate(
            clearance_m=c_d,
            clearance_sigma_m=sig,
            toe_line_xz_m=np.array([[fx, fz], [qx, qz]]),
            nosing_clearance_m=nc,
            nosing_sigma_m=nsig,
            predicted_min_clearance_m=pred,
            predicted_min_nosing_clearance_m=pred_edge,
            near_trip_warning=warn,
            edge_distance_m=ed,
            edge_distance_sigma_m=edsig,
            steps_seen=n_steps,
            mean_rise_m=rise,
            mean_tread_m=tread,
            landing=landing,
            placement=placement,
            edge_xz_m=edges.xz_m[e].copy() if e >= 0 else _NAN2.copy(),
            near_trip_clearance_m=risk,
            pose_consistency_scale=sp,
            map_consistency_scale=sm,
        )

    def _trusted_risk(
        self,
        t_s: float,
        tau: float,
        heel: NDArray[np.float64],
        toe: NDArray[np.float64],
        edges: Edges,
        e: int,
        risk: float,
        motion: NDArray[np.float64] | None = None,
        poses: NDArray[np.float64] | None = None,
    ) -> float:
        """The near-trip candidates' minimum clearance (``risk`` over the whole horizon)
        restricted to the horizon steps whose measured prediction error is at most
        ``near_trip_m`` (:class:`PredictionErrors`); keeps this frame's prediction for the
        measurement. NaN when not even the first step is trusted; never below ``risk`` (the
        check only removes warnings: the last trusted pose's velocity, a one-sided
        difference, could otherwise make it a candidate the whole horizon did not have)."""
        cfg = self.config
        if motion is None:  # (update passes the template motion it computed)
            motion = self._template_motion(tau, self._h)
        assert motion is not None
        if poses is None:  # (the swing_prediction kernel returns them: the same floats)
            poses = np.concatenate([heel[None] + motion[:, :2], toe[None] + motion[:, 2:]], 1)
        m = self.prediction_errors.trusted_steps(cfg.near_trip_m)
        if cfg.warning_template_spread and m >= 1 and len(self._used_templates()) > 1:
            # a step not measured yet in this swing is as uncertain as the templates
            # disagree there (their rms distance from the median)
            bad = ~self.prediction_errors.measured() & (
                self._template_spread(tau, motion) > cfg.near_trip_m
            )
            bad[0] = False  # the current pose is the estimate itself
            if bad.any():
                m = min(m, int(np.argmax(bad)) - 1)
        self.prediction_errors.predict(t_s, poses)
        if m >= cfg.horizon_steps:
            return risk  # every step trusted: the whole horizon, as computed
        if m < 1 or not math.isfinite(risk):
            return NAN
        mo = motion[: m + 1]
        hp, tp = heel[None] + mo[:, :2], toe[None] + mo[:, 2:]
        r = self._swing_edges(hp, tp, edges, e, float(toe[0] + mo[:, 2].max()))[1]
        return r if not r < risk else risk

    def _terrain_now(
        self,
        heel: NDArray[np.float64],
        toe: NDArray[np.float64],
        Pl: list[list[float]],
        edges: Edges,
        pose_w: float,
        map_w: float,
        pose_xf: float = 1.0,
    ) -> tuple[float, float, float, float, float, float, int, float, float, float, float]:
        """The clearance to the map's bins near the foot and its sigma, and the next edge
        ahead with the clearance to it, its sigma, the x distance to it and that sigma
        (``pose_w``, ``map_w``: the sigmas' pose and map weights; ``pose_xf``: the factor on
        the pose term's x row and column, :meth:`_relative_cov`). Returns (clearance, foot
        x, z, terrain x, z, sigma, edge index or -1, edge clearance, sigma, x distance,
        sigma); NaN where unknown. Compiled: ``frame_terrain``, one call."""
        cfg, g = self.config, self.geometry
        hx, tx = float(heel[0]), float(toe[0])
        x0, x1 = min(hx, tx) - cfg.window_m, max(hx, tx) + cfg.window_m
        near = self.map.window(x0, x1, cfg.map_sigma_m)
        win = near.profile
        c = NO_CLEARANCE  # unless the terrain under the foot has been seen
        if not g.coverage(heel, toe, win) < cfg.min_coverage:
            c = g.foot_clearance(heel, toe, win, cfg.sole_thickness_m)
            if cfg.unseen_terrain_check and c.distance_m + cfg.sole_thickness_m > (
                unseen_distance(min(hx, tx), max(hx, tx), win, x0, x1, cfg.edge_max_gap_m)
            ):  # unseen terrain could be closer than the mapped terrain
                c = NO_CLEARANCE
        sig = NAN
        if c.bin >= 0:
            k = int(near.bins[c.bin])
            rel = self._relative_cov(Pl, k, pose_w, pose_xf)
            sig = clearance_sigma(
                c.normal_xz, rel, map_w * self.map.bin_sigma(k, cfg.map_sigma_m), cfg.foot_sigma_m
            )
        nc = nsig = ed = edsig = NAN
        e = next_edge_index(edges, tx - cfg.toe_pass_m)
        if e >= 0:
            ec = g.edge_clearance(heel, toe, edges.xz_m[e], cfg.sole_thickness_m)
            kb = self.map.bin_below(float(edges.xz_m[e, 0]))  # the bin at the edge
            rel = self._relative_cov(Pl, kb, pose_w, pose_xf)
            nc = ec.distance_m
            nsig = clearance_sigma(
                ec.normal_xz, rel, map_w * self.map.bin_sigma(kb, cfg.map_sigma_m), cfg.foot_sigma_m
            )
            ed = float(edges.xz_m[e, 0] - toe[0])
            edsig = (rel[0][0] + cfg.foot_sigma_m**2 + (cfg.bin_m / 2) ** 2) ** 0.5
        (fx, fz), (qx, qz) = c.foot_xz_m.tolist(), c.terrain_xz_m.tolist()
        return c.distance_m, fx, fz, qx, qz, sig, e, nc, nsig, ed, edsig

    def _checked_clearance(
        self,
        heel: NDArray[np.float64],
        toe: NDArray[np.float64],
        Pl: list[list[float]],
        now: tuple[float, float, float, float, float, float],
        pose_w: float,
        map_w: float,
        pose_xf: float,
    ) -> tuple[float, float, float, float, float, float]:
        """``now`` = (clearance, foot x, z, terrain x, z, sigma) from the mapped bins within
        ``window_m`` of the foot, checked against the strips the map bridges there
        (:func:`~vio_graph.safety.clearance.gap_terrain`, config ``gap_floor_check``): the
        clearance to their floors replaces it when smaller, and when an unseen riser in a
        rising strip could be nearer than that by more than its sigma, the clearance is
        not known (NaN). The same numpy geometry on the numpy and compiled paths."""
        cfg = self.config
        sole = cfg.sole_thickness_m
        x_a, x_b = float(min(heel[0], toe[0])), float(max(heel[0], toe[0]))
        if isinstance(self.map, IncrementalHeightMap) and not self.map.bridged_gap(
            x_a - cfg.window_m, x_b + cfg.window_m, cfg.edge_max_gap_m
        ):  # (compiled: no strip to fill, so gap_terrain would return nothing)
            return now
        near = self.map.window(x_a - cfg.window_m, x_b + cfg.window_m, cfg.map_sigma_m)
        floors, f_bins, risers, r_bins = gap_terrain(
            near.profile, near.bins, cfg.edge_max_gap_m, x_b + sole
        )
        if len(floors):
            c = clearance.foot_clearance(heel, toe, floors, sole)
            if c.distance_m < now[0]:
                now = self._clearance_tuple(c, f_bins, Pl, pose_w, map_w, pose_xf)
        if len(risers):
            c = clearance.foot_clearance(heel, toe, risers, sole)
            sig = now[5] if math.isfinite(now[5]) else 0.0
            if c.distance_m < now[0] - sig:
                return (NAN, NAN, NAN, NAN, NAN, NAN)
        return now

    def _clearance_tuple(
        self,
        c: Clearance,
        bins: NDArray[np.int64],
        Pl: list[list[float]],
        pose_w: float,
        map_w: float,
        pose_xf: float,
    ) -> tuple[float, float, float, float, float, float]:
        """(clearance, foot x, z, terrain x, z, sigma) of ``c`` (its column ``c.bin`` indexes
        ``bins``, the map's bin indices), the sigma as :meth:`_terrain_now` gives it."""
        sig = NAN
        if c.bin >= 0:
            k = int(bins[c.bin])
            rel = self._relative_cov(Pl, k, pose_w, pose_xf)
            sig = clearance_sigma(
                c.normal_xz, rel, map_w * self.map.bin_sigma(k, self.config.map_sigma_m),
                self.config.foot_sigma_m,
            )  # fmt: skip
        (fx, fz), (qx, qz) = c.foot_xz_m.tolist(), c.terrain_xz_m.tolist()
        return c.distance_m, fx, fz, qx, qz, sig

    def _flat_templates(self) -> tuple[NDArray, NDArray, NDArray]:
        """The templates end to end (compiled path): phases (S,), displacements (S, 4) and
        each template's first row (T + 1,)."""
        if self._templates_flat is None:
            used = self._used_templates()
            rows = np.cumsum([0] + [len(ph) for ph, _ in used])
            self._templates_flat = (
                np.concatenate([ph for ph, _ in used]),
                np.concatenate([d for _, d in used]),
                rows.astype(np.int64),
            )
        return self._templates_flat

    def _used_templates(self) -> list[tuple[NDArray[np.float64], NDArray[np.float64]]]:
        """The templates this swing's prediction is over: those :meth:`_matching_templates`
        selected, or all of them."""
        if self._selected is None:
            return list(self._templates)
        return [self._templates[i] for i in self._selected]

    def _matching_templates(self) -> tuple[int, ...]:
        """The templates whose heel and toe displacements since lift-off agree with this
        swing's so far: rms over this swing's frames of the larger of the heel's and the
        toe's distance (the template at the frame's phase, held at its end) at most
        ``near_trip_m``, the margin the warning tests. A one-step swing (the first step onto
        a flight) is not a two-step one's template: they part by 5-20 cm within 2-3 frames
        of lift-off."""
        a = np.asarray(self._swing, dtype=float)  # (frames, 5): phase, heel and toe
        out = []
        for i, (ph, d) in enumerate(self._templates):
            e2 = _worse_foot_sq(_template_at(ph, d, a[:, 0]) - a[:, 1:])
            if math.sqrt(float(np.mean(e2))) <= self.config.near_trip_m:
                out.append(i)
        return tuple(out)

    def _template_spread(self, tau: float, motion: NDArray[np.float64]) -> NDArray[np.float64]:
        """Per horizon step (H + 1,; 0 now): the rms over the used templates of the larger of
        the heel's and the toe's distance between that template's motion from phase tau and
        the median ``motion`` (H, 4), m."""
        q = np.concatenate([[tau], tau + self._h])
        e2 = []
        for ph, d in self._used_templates():
            at = _template_at(ph, d, q)
            e2.append(_worse_foot_sq((at[1:] - at[:1]) - motion))
        return np.concatenate([[0.0], np.sqrt(np.mean(e2, axis=0))[1:]])
