"""Timestamps: camera-IMU time offset, IMU clock model, gaps and stamps that go backwards.

**Camera-IMU time offset** (:class:`TimeOffsetEstimator`). A depth frame stamped t was
captured at t - td on the IMU clock (td > 0: the camera's stamps are late). The slice of
that frame is rotated into the ground frame with the IMU attitude at the time the estimator
believes it was captured, t - td_applied; the shank turns at up to 5-8 rad/s, so an offset
error tilts the slice by w (td - td_applied), w the shank pitch rate. Level surfaces (floor,
treads, obstacle tops) measure that tilt (frontend/level.py; the level aiding uses the same
measurement for the slowly drifting pitch error b of the vendor orientation). With the
level aiding's current offset b_k, the measured residual tilt y_k and the applied td:

    m_k = y_k + b_k - w_k td_applied = b - w_k td + noise

a linear model in (b, td) whose regressor w_k changes sign twice per stride, so a 2-state
Kalman filter (b a random walk like the level aiding's, td a constant with a tiny random
walk, each measurement chi-square gated) separates them within a few strides. Why this and
not a td state in the SP-ESKF driven by the displacements (VINS-Mono, OpenVINS): in the
sagittal filter the displacement residual carries td only through the velocity change over
a frame, (v1 - v0) td, about 1 mm for 10 ms, the same size as the filter's own velocity
errors (0.2-0.3 m/s lag, FilterConfig.accel_noise_sigma_mps2), so it is confounded with
them; the tilt channel is first order in the rotation rate (10 ms at 5 rad/s = 2.9 deg
against a tilt noise of ~0.1 deg), independent of the filter's velocity, and cannot be
biased by it. The same idea as VINS-Mono's (Qin & Shen, IROS 2018: the feature velocity
times td), with the level line as the feature. td is applied (frames re-stamped
t - td_applied) once it is ``apply_sigmas`` sigmas away from 0, so a synchronised rig keeps
its stamps untouched (the sigma scaled by the tilts' consistency, and not before the gate is
armed: :meth:`TimeOffsetEstimator._accepted`).

**Clock model** (:class:`ClockModel`). IMU samples are taken on the sensor's crystal at a
nominal rate; transport (USB, I2C) adds jitter to the host stamps. A least-squares line
t_k = a + T k over the last ``clock_window`` samples (k counted from the nominal period)
gives each sample the line's value at k instead of its stamp: the jitter averages out, a
clock drift (T off nominal) is kept, and no sample is corrected on its own. For the depth
frames (30 Hz, so a window fills slowly) the slope can carry a prior about the nominal rate
(``camera_clock_rate_prior_ppm``, :meth:`ClockModel._fit_rate_prior`): the free line's
newest end is off by its slope error times half the window, twice the intercept's error.
A stamp more than ``gap_periods`` periods after the previous one is a gap (reported, the
fit restarts); a stamp at or before the previous one is reported and the sample dropped,
never fused.
Between gaps consecutive samples are one period apart: jitter is assumed below
(``gap_periods`` - 1) periods, so a single missing sample is a gap.

**Depth-frame stamps: as recorded or on the clock line?** (:class:`FrameStampTest`). Whether a
frame stamp that wanders off the camera's clock line is a transport delay (the frame was
taken on the line: smooth the stamp) or a capture that really happened then (a camera whose
exposure start jitters: keep the stamp) depends on the camera, so vision decides. With
delta_k = line_k - stamp_k, the IMU-predicted displacement between two frames moves by
u_k = v_k delta_k - v_{k-1} delta_{k-1} (v the filter's velocity) when the line times are used
instead of the stamps. Each frame's displacement is tested against both predictions with the
filter's gate statistic (capped at the gate), and the log-likelihood ratio
sum (d2_stamp - d2_line) / 2 decides, like a sequential probability ratio test: the line
times are used once it exceeds ln 100, the stamps again once it falls below -ln 100 (it is
clamped to twice that, so either switch stays possible). Stamps as recorded until then.
"""

from __future__ import annotations

from collections import deque
from types import ModuleType

import numpy as np
from numpy.typing import NDArray

from vio_graph.filter.config import TimeOffsetConfig
from vio_graph.filter.fast_imu import imu_kernels
from vio_graph.filter.gating import chi2_quantile

_add_reduce = np.add.reduce
_KEEP_TOL_S = 1e-6  # a stamp within this of the clock model is kept bit for bit
_MIN_FIT = 20  # samples before the line's slope is fitted (else the nominal period)
_MAX_REPORTED = 20  # gaps / backward stamps listed individually
#: accepted tilts before the gate (and the decision to apply td) is armed: with fewer, the
#: residuals cannot yet tell whether the tilt sigmas are right
_WARM_UP = 10


class ClockModel:
    """Recursive line fit of one stream's stamps (module docstring)."""

    def __init__(
        self,
        nominal_period_s: float,
        window: int,
        gap_periods: float,
        smooth: bool = True,
        rate_prior_ppm: float | None = None,
    ) -> None:
        self.period_s = float(nominal_period_s)
        #: prior sd of the clock's period about the nominal one (s per period), or None (the
        #: slope is fitted freely): see :meth:`_fit_rate_prior`
        self.period_prior_s = (
            None if rate_prior_ppm is None else float(rate_prior_ppm) * 1e-6 * self.period_s
        )
        self.window = int(window)
        self.gap_periods = float(gap_periods)
        self.smooth = smooth
        self._pts: deque[tuple[int, float]] = deque(maxlen=self.window)
        # the same stamps in a flat buffer for the fast fit: the newest line's stamps are
        # _buf[_pos - _n:_pos], at consecutive k (a gap starts a new line)
        self._buf = np.empty(2 * self.window)
        self._pos = 0
        self._n = 0
        self._ar = np.arange(self.window, dtype=float)
        self._xc, self._xc_n = self._ar, -1  # centred x of the last window size fitted
        self._k = 0
        self._last_stamp: float | None = None
        self._last_out: float | None = None
        self.gaps: list[dict[str, float]] = []
        self.n_gaps = 0
        self.gap_total_s = 0.0
        self.n_backwards = 0
        self.backwards: list[dict[str, float]] = []
        # every correction (s), for the report's RMS: a float64 buffer grown by doubling
        # (8 bytes a sample; a list of floats costs 32)
        self._corr = np.empty(1024)
        self._n_corr = 0
        # compiled correct(), or None; the rate prior is fitted in numpy only (frame stamps)
        self._kernels = imu_kernels() if self.period_prior_s is None else None
        # correct()'s state when compiled (compiled_imu.CLK_* slots) instead of the attributes
        self._st = None if self._kernels is None else np.zeros(self._kernels.CLK_SIZE)

    def correct(self, stamp_s: float) -> float | None:
        """The time to use for a sample stamped ``stamp_s`` (s), or None if the stamp is at or
        before the previous one (the sample must be dropped)."""
        t = float(stamp_s)
        if self._kernels is not None:
            return self._correct_compiled(t)
        if self._last_stamp is not None and t <= self._last_stamp:
            self.n_backwards += 1
            if len(self.backwards) < _MAX_REPORTED:
                self.backwards.append({"t_s": t, "jump_s": t - self._last_stamp})
            return None
        if self._last_stamp is not None:
            dt = t - self._last_stamp
            if dt > self.gap_periods * self.period_s:
                self.n_gaps += 1
                self.gap_total_s += dt
                if len(self.gaps) < _MAX_REPORTED:
                    self.gaps.append({"t_s": self._last_stamp, "duration_s": dt})
                self._pts.clear()  # the clock may have jumped: a new line
                self._n = 0
                self._k += max(1, int(round(dt / self.period_s)))
            else:
                # consecutive samples: counting periods from jittered stamps (or from the
                # line's value at the previous sample, which the newest point pulls) miscounts
                # a whole period now and then under 2 ms of jitter at 100 Hz
                self._k += 1
        self._last_stamp = t
        self._pts.append((self._k, t))
        if self._pos == self._buf.size:  # keep the newest window - 1 stamps, at the front
            keep = self.window - 1
            self._buf[:keep] = self._buf[self._pos - keep : self._pos]
            self._pos = keep
        self._buf[self._pos] = t
        self._pos += 1
        self._n = min(self._n + 1, self.window)
        out = self._fit(t) if self.smooth else t
        if self._last_out is not None and out <= self._last_out:
            out = t if t > self._last_out else self._last_out + 0.5 * self.period_s
        self._last_out = out
        if self._n_corr == self._corr.size:
            self._corr = np.concatenate([self._corr, np.empty(self._corr.size)])
        self._corr[self._n_corr] = out - t
        self._n_corr += 1
        return out

    def _correct_compiled(self, t: float) -> float | None:
        """:meth:`correct` in one compiled call (filter/compiled_imu.py); the reports here."""
        k, st = self._kernels, self._st
        assert k is not None and st is not None
        corr = self.compiled_corrections()
        out, code, dt, prev = k.clock_correct(
            st,
            self._buf,
            corr,
            t,
            self.period_s,
            self.gap_periods,
            self.window,
            self.smooth,
            _MIN_FIT,
            _KEEP_TOL_S,
        )
        if code:
            self.compiled_event(t, code, dt, prev)
        return None if code < 0 else out

    def compiled_constants(self, c: NDArray[np.float64], k: ModuleType) -> bool:
        """Write :meth:`correct`'s constants into ``c`` (``compiled_imu.IN_*`` slots of the
        module ``k``) for a caller that runs ``compiled_imu.clock_correct`` itself on
        ``_st``, ``_buf`` and :meth:`compiled_corrections` (``compiled_imu.imu_input``);
        False (nothing written) if the model is not compiled."""
        if self._kernels is None or self._st is None:
            return False
        c[k.IN_PERIOD], c[k.IN_GAP_PERIODS] = self.period_s, self.gap_periods
        c[k.IN_WINDOW], c[k.IN_SMOOTH] = self.window, 1.0 if self.smooth else 0.0
        c[k.IN_MIN_FIT], c[k.IN_KEEP_TOL] = _MIN_FIT, _KEEP_TOL_S
        return True

    def compiled_corrections(self) -> NDArray[np.float64]:
        """The corrections buffer with room for one more (grown by doubling): what
        ``compiled_imu.clock_correct`` writes into."""
        assert self._st is not None and self._kernels is not None
        if int(self._st[self._kernels.CLK_N_CORR]) == self._corr.size:
            self._corr = np.concatenate([self._corr, np.empty(self._corr.size)])
        return self._corr

    def compiled_event(self, t: float, code: int, dt: float, prev: float) -> None:
        """Report what ``compiled_imu.clock_correct`` found at the stamp ``t`` (s): code -1 a
        stamp ``dt`` s at or before the previous one, 1 a gap of ``dt`` s after the stamp
        ``prev``, 0 nothing."""
        if code < 0:
            self.n_backwards += 1
            if len(self.backwards) < _MAX_REPORTED:
                self.backwards.append({"t_s": t, "jump_s": dt})
        elif code > 0:
            self.n_gaps += 1
            self.gap_total_s += dt
            if len(self.gaps) < _MAX_REPORTED:
                self.gaps.append({"t_s": prev, "duration_s": dt})

    def _fit(self, t: float) -> float:
        """The clock line's value at the newest sample: :meth:`_fit_reference` with the line
        fitted in closed form (the stamps sit at consecutive k, so the x sums are known);
        equal to rounding (tests/test_fast_imu.py)."""
        n = self._n
        if self.period_prior_s is not None and n >= _MIN_FIT:
            return self._fit_rate_prior(t)
        if self._kernels is not None:  # compiled (filter/compiled_imu.py)
            icpt = self._kernels.clock_line(self._buf, self._pos, n, self.period_s, _MIN_FIT)
            return t if abs(icpt - t) < _KEEP_TOL_S else float(icpt)
        ts = self._buf[self._pos - n : self._pos]
        # np.mean's value without its dispatch (~6 us a call): the same pairwise sum, then
        # one float64 division by n
        if n >= _MIN_FIT:
            # x = k - k_newest = -(n-1) .. 0: mean -(n-1)/2, sum of squared deviations
            # n (n^2 - 1) / 12
            half = 0.5 * (n - 1)
            my = float(_add_reduce(ts)) / n
            if self._xc_n != n:  # x - mean(x), the same subtraction, once per window size
                self._xc, self._xc_n = self._ar[:n] - half, n
            sxy = float(self._xc @ (ts - my))
            icpt = my + (sxy / (n * (n * n - 1) / 12.0)) * half  # the line at the newest k
        else:
            icpt = float(_add_reduce(ts + self.period_s * (n - 1 - self._ar[:n]))) / n
        return t if abs(icpt - t) < _KEEP_TOL_S else float(icpt)

    def _fit_rate_prior(self, t: float) -> float:
        """The line's value at the newest sample with the period drawn to the nominal one by
        its prior: the slope's deviation from nominal is the least-squares one shrunk by
        s^2 / sigma_T^2 (s^2 the stamps' scatter about the free line, sigma_T the prior's
        sd of the period), the posterior mean under a Gaussian prior on the rate.

        Why: the free line's value at its newest end carries the slope's error times half
        the window, about 2 s / sqrt(n) against s / sqrt(n) with the slope known; 2 ms of
        scatter on a 30 Hz camera leaves the free line 0.7 ms off (sd) after 1.5 s, and that
        error is shared by every frame until the window refills. A crystal is within tens of
        ppm of its rate (33 ms * 100 ppm = 3.3 us a frame), which a few seconds of 2 ms
        scatter cannot measure, while stamps without scatter (s ~ 0) still fit the slope
        freely, so a drifting clock is followed."""
        n = self._n
        ts = self._buf[self._pos - n : self._pos]
        half = 0.5 * (n - 1)
        xc = np.arange(n, dtype=float) - half
        r = ts - self.period_s * xc  # off the nominal line (k counted from the centre)
        rc = r - float(np.mean(r))
        sxx = n * (n * n - 1) / 12.0
        sxr = float(xc @ rc)
        s2 = max(float(rc @ rc) - sxr * sxr / sxx, 0.0) / max(n - 2, 1)
        assert self.period_prior_s is not None
        lam = s2 / self.period_prior_s**2 if self.period_prior_s > 0 else np.inf
        dev = sxr / (sxx + lam)
        icpt = float(np.mean(r)) + (self.period_s + dev) * half
        return t if abs(icpt - t) < _KEEP_TOL_S else icpt

    def _fit_reference(self, t: float) -> float:
        """numpy reference of :meth:`_fit` (np.polyfit)."""
        k = np.array([p[0] for p in self._pts], dtype=float)
        ts = np.array([p[1] for p in self._pts])
        if k.size >= _MIN_FIT:
            _, icpt = np.polyfit(k - k[-1], ts, 1)  # the line's value at the newest k
        else:
            icpt = float(np.mean(ts - self.period_s * (k - k[-1])))
        return t if abs(icpt - t) < _KEEP_TOL_S else float(icpt)

    def _recorded_corrections(self) -> NDArray[np.float64]:
        """Every correction (line value - stamp, s) recorded so far (a view; the compiled
        correct() counts them in its state instead of ``_n_corr``)."""
        n = self._n_corr if self._st is None or self._kernels is None else int(self._st[-1])
        return self._corr[:n]

    def scatter_var_s2(self) -> float:
        """Mean square (s^2) of the last ``window`` stamps' distances to their line values:
        how far apart the two candidate times of a sample (stamp, clock line) are; 0 for
        stamps on their line (bit for bit kept)."""
        c = self._recorded_corrections()[-self.window :]
        return float(c @ c) / c.size if c.size else 0.0

    def report(self) -> dict:
        c = self._recorded_corrections()
        return {
            "gaps": self.n_gaps,
            "gap_total_s": self.gap_total_s,
            "gap_list": self.gaps,
            "backwards": self.n_backwards,
            "backwards_list": self.backwards,
            "correction_rms_s": float(np.sqrt(np.mean(c**2))) if c.size else 0.0,
            "correction_max_s": float(np.max(np.abs(c))) if c.size else 0.0,
        }


def centred_clock_line(
    stamps_s: NDArray[np.float64],
    period_s: float,
    half_window: int,
    gap_periods: float,
    keep_tol_s: float = _KEEP_TOL_S,
    ahead: int | None = None,
) -> NDArray[np.float64] | None:
    """Each stamp replaced by a clock line fitted around it (offline, both sides).

    The online :class:`ClockModel` evaluates its line at the newest sample: its error is
    about 2 sigma / sqrt(n) at the end of an n-sample fit, and over the first samples of a
    stream it has few to average (2 ms of jitter at 100 Hz: 0.3-0.7 ms in the first 2 s,
    0.2-0.5 ms after). A recording is known as a whole, so here the line for sample j is
    the least-squares fit over samples j - ``half_window`` .. j + ``half_window`` (clipped at
    the segment's ends; k counted in nominal periods as online), evaluated at j: error about
    sigma / sqrt(2 half_window + 1) inside. A crystal's rate changes over minutes, so a line
    over tens of seconds stays straight to well under a microsecond. Segments are split at
    gaps (more than ``gap_periods`` periods, as online). Returns None (the stamps stay as they
    are, bit for bit) when every stamp is within ``keep_tol_s`` of its line, i.e. the stamps
    have no jitter, or when a stamp is at or before its predecessor (left to the online
    model, which drops and reports it). ``ahead`` (samples) caps the samples used after j
    (default ``half_window``): a fixed-lag smoother, whose estimate of a time is final one
    lag later, may look that far ahead and no further.
    """
    t = np.asarray(stamps_s, dtype=float)
    if t.size < 3 or half_window < 1:
        return None
    ahead = half_window if ahead is None else max(0, min(ahead, half_window))
    dt = np.diff(t)
    if np.any(dt <= 0):
        return None
    cuts = np.flatnonzero(dt > gap_periods * period_s) + 1
    out = np.empty_like(t)
    for seg in np.split(np.arange(t.size), cuts):
        n_seg = seg.size
        x = np.arange(n_seg, dtype=float)  # periods since the segment's first sample
        r = t[seg] - (t[seg[0]] + period_s * x)  # off the nominal line: small numbers
        # prefix sums (x integer: its sums are exact in float64 up to 9e15)
        zero = np.zeros(1)
        cx = np.concatenate([zero, np.cumsum(x)])
        cxx = np.concatenate([zero, np.cumsum(x * x)])
        cr = np.concatenate([zero, np.cumsum(r)])
        cxr = np.concatenate([zero, np.cumsum(x * r)])
        lo = np.maximum(np.arange(n_seg) - half_window, 0)
        hi = np.minimum(np.arange(n_seg) + ahead, n_seg - 1) + 1
        m = (hi - lo).astype(float)
        sx, sxx = cx[hi] - cx[lo], cxx[hi] - cxx[lo]
        sr, sxr = cr[hi] - cr[lo], cxr[hi] - cxr[lo]
        den = m * sxx - sx * sx
        slope = np.divide(m * sxr - sx * sr, den, out=np.zeros(n_seg), where=den > 0)
        fit = (sr - slope * sx) / m + slope * x
        out[seg] = t[seg[0]] + period_s * x + fit
    if np.max(np.abs(out - t)) < keep_tol_s:
        return None
    if np.any(np.diff(out) <= 0):  # cannot happen for jitter below half a period
        return None
    return out


class TimeOffsetEstimator:
    """2-state Kalman filter on (pitch error b (rad), camera-IMU offset td (s)); see the
    module docstring."""

    def __init__(
        self, config: TimeOffsetConfig, initial_b_sigma_rad: float, b_drift_rad_per_sqrt_s: float
    ) -> None:
        self.config = config
        self._P0 = np.diag([initial_b_sigma_rad**2, config.initial_sigma_s**2])
        self.n_forgotten = 0  #: times :meth:`forget` dropped what the tilts had taught
        self._q = np.array([b_drift_rad_per_sqrt_s**2, config.drift_s_per_sqrt_s**2])
        self._gate = chi2_quantile(config.gate_probability, 1)
        self._t_s: float | None = None
        self.n_rejected = 0
        self._start_from_prior()

    def _start_from_prior(self) -> None:
        """The estimate at its prior: nothing learnt, applied or latched (start, forget)."""
        self.x = np.zeros(2)
        self.P = self._P0.copy()
        self.applied_s = 0.0  #: td the fusion uses now (s)
        self._latched = False
        self.n_updates = 0
        # consistency of the tilts with their sigmas: the normalised innovations y^2 / s of
        # every tested tilt (accepted or refused, each capped at the gate), summed
        self._nis_sum = 0.0
        self._nis_n = 0
        #: (time s, td s, scaled sigma s) when td was first applied, None before
        self.latched_at: tuple[float, float, float] | None = None

    @property
    def td_s(self) -> float:
        return float(self.x[1])

    @property
    def sigma_s(self) -> float:
        return float(np.sqrt(self.P[1, 1]))

    def update(
        self,
        t_s: float,
        tilt_rad: float,
        tilt_sigma_rad: float,
        offset_b_rad: float,
        pitch_rate_radps: float,
    ) -> bool:
        """One level-surface tilt ``tilt_rad`` measured on a slice rotated with the pitch
        offset ``offset_b_rad`` and re-stamped by :attr:`applied_s`; ``pitch_rate_radps`` the
        shank pitch rate (ground frame) at the frame. Returns False if gated out.

        The 2-state update on Python floats (a scalar measurement, H = [1, -rate]); the
        numpy form is :meth:`update_reference` (the same estimate to rounding, compared in
        tests/test_time_offset.py)."""
        p00, p01, p10, p11 = self.P.ravel().tolist()
        if self._t_s is not None and t_s > self._t_s:
            q0, q1 = self._q.tolist()
            dt = t_s - self._t_s
            p00 += q0 * dt
            p11 += q1 * dt
        self._t_s = t_s if self._t_s is None else max(self._t_s, t_s)
        m = tilt_rad + offset_b_rad - pitch_rate_radps * self.applied_s
        h = -pitch_rate_radps
        x0, x1 = self.x.tolist()
        y = m - (x0 + h * x1)
        hp0, hp1 = p00 + h * p10, p01 + h * p11  # H P
        s = float(hp0 + hp1 * h + tilt_sigma_rad**2)
        self._note_nis(y * y / s)
        if self.n_updates > _WARM_UP and y * y > self._gate * s:
            self.P = np.array([[p00, p01], [p10, p11]])
            self.n_rejected += 1
            return False
        k0, k1 = (p00 + p01 * h) / s, (p10 + p11 * h) / s  # K = P H^T / s
        self.x = np.array([x0 + k0 * y, x1 + k1 * y])
        a00, a01, a10, a11 = p00 - k0 * hp0, p01 - k0 * hp1, p10 - k1 * hp0, p11 - k1 * hp1
        off = 0.5 * (a01 + a10)
        self.P = np.array([[a00, off], [off, a11]])  # symmetrised, as 0.5 (P + P^T)
        self._accepted()
        return True

    def update_reference(
        self,
        t_s: float,
        tilt_rad: float,
        tilt_sigma_rad: float,
        offset_b_rad: float,
        pitch_rate_radps: float,
    ) -> bool:
        """numpy reference of :meth:`update`."""
        if self._t_s is not None and t_s > self._t_s:
            self.P[np.diag_indices(2)] += self._q * (t_s - self._t_s)
        self._t_s = t_s if self._t_s is None else max(self._t_s, t_s)
        m = tilt_rad + offset_b_rad - pitch_rate_radps * self.applied_s
        H = np.array([1.0, -pitch_rate_radps])
        r = tilt_sigma_rad**2
        y = m - H @ self.x
        s = float(H @ self.P @ H + r)
        self._note_nis(float(y * y) / s)
        if self.n_updates > _WARM_UP and y * y > self._gate * s:
            self.n_rejected += 1
            return False
        K = self.P @ H / s
        self.x = self.x + K * y
        self.P = self.P - np.outer(K, H @ self.P)
        self.P = 0.5 * (self.P + self.P.T)
        self._accepted()
        return True

    def _note_nis(self, nis: float) -> None:
        self._nis_sum += min(nis, self._gate)
        self._nis_n += 1

    @property
    def consistency_scale(self) -> float:
        """sqrt of the tilts' variance factor, at least 1: the mean normalised innovation
        (y^2 / s, expected 1 when the tilt sigmas are right; each capped at the gate) of the
        tilts tested so far. The a posteriori variance factor of least squares: tilts that
        scatter more than their sigmas say make td less certain than its covariance says."""
        if self._nis_n == 0:
            return 1.0
        return float(np.sqrt(max(1.0, self._nis_sum / self._nis_n)))

    def _accepted(self) -> None:
        """Count an accepted update; td is applied once it is ``apply_sigmas`` sigmas from
        zero and stays applied (latched), following the estimate from then on. The sigma is
        scaled by :attr:`consistency_scale`, and nothing is applied before the gate is armed
        (``_WARM_UP`` accepted tilts): applying td re-stamps every frame after (and, early in
        a trial, re-runs the ones before), so the decision waits until the tilts' residuals
        can say whether their sigmas hold. With doubled ToF noise on 18 x 24 cm stairs the
        tilts scattered 1.2-1.5x their sigmas (mean y^2 / s 1.5-2.4; 0.2-0.6 on clean trials),
        and td was applied from the second tilt on at |td| 19-43 ms (true 0) on 7 of 9 seeds
        (docs/generalisation.md, held-out combinations)."""
        self.n_updates += 1
        if self.config.estimate:
            sigma = self.sigma_s * self.consistency_scale
            armed = self.n_updates > _WARM_UP
            if not self._latched and armed and abs(self.td_s) > self.config.apply_sigmas * sigma:
                self._latched = True
                self.latched_at = (float(self._t_s or 0.0), self.td_s, sigma)
            if self._latched:
                self.applied_s = self.td_s

    def forget(self) -> None:
        """Drop what the tilts taught (the level surfaces turned out bent by depth errors,
        ``filter.attitude.SurfaceBendTest``: their tilts measured the bend, not the pitch
        and the stamps): back to the prior, unapplied and unlatched, warming up again."""
        self._start_from_prior()
        self.n_forgotten += 1

    def final_offset_s(self) -> float:
        """The offset a replay holds over the whole recording once it has seen every frame
        (``rerun_final``): the estimate if it is still ``apply_sigmas`` scaled sigmas from
        zero, else 0 (the tilts seen since refute the offset once applied: the stamps are
        left as recorded)."""
        sigma = self.sigma_s * self.consistency_scale
        return self.td_s if abs(self.td_s) > self.config.apply_sigmas * sigma else 0.0

    def hold(self, td_s: float) -> None:
        """Apply ``td_s`` and keep it: the final pass of a replay (``rerun_final``), which
        does not count its tilts again (the replay stops the updates)."""
        self.applied_s = float(td_s)

    @property
    def latched(self) -> bool:
        """True once td has been applied (it stays applied)."""
        return self._latched

    def carry_over(self, other: TimeOffsetEstimator) -> None:
        """Take ``other``'s estimate, covariance, applied offset and counts (the retroactive
        re-run of vio_graph/replay.py starts with what the first pass learnt)."""
        self.x = other.x.copy()
        self.P = other.P.copy()
        self._t_s = other._t_s
        self.applied_s = other.applied_s
        self._latched = other._latched
        self.n_updates = other.n_updates
        self.n_rejected = other.n_rejected
        self._nis_sum = other._nis_sum
        self._nis_n = other._nis_n
        self.latched_at = other.latched_at
        self.n_forgotten = other.n_forgotten

    def contradicted(self) -> bool:
        """True if td was applied and the estimate has since moved from the value applied
        then by more than ``apply_sigmas`` of that value's (scaled) sigma: the frames fused
        in between were re-stamped by an offset the later tilts refute."""
        if self.latched_at is None:
            return False
        _, td0, sigma0 = self.latched_at
        return abs(self.td_s - td0) > self.config.apply_sigmas * sigma0

    def report(self) -> dict:
        return {
            "estimate_s": self.td_s,
            "sigma_s": self.sigma_s,
            "applied_s": self.applied_s,
            "updates": self.n_updates,
            "rejected": self.n_rejected,
            "consistency_scale": self.consistency_scale,
            "applied_from": None
            if self.latched_at is None
            else dict(zip(("t_s", "td_s", "sigma_s"), self.latched_at, strict=True)),
            "contradicted": self.contradicted(),
            "forgotten": self.n_forgotten,
        }


class FrameStampTest:
    """Sequential test between frame stamps as recorded and the clock line (module doc).

    Per frame: :meth:`note_frame` with delta = line - stamp (s) when the frame is re-stamped,
    :meth:`shift` with the filter's velocity at the frame for u (m; None without a previous
    frame), :meth:`add` with the gate statistics of the displacement under the hypothesis in
    use and under the other one, :meth:`end_frame` with the velocity after the update.
    """

    def __init__(self, cap_d2: float, threshold: float = float(np.log(100.0))) -> None:
        self.cap_d2 = float(cap_d2)
        self.threshold = float(threshold)
        self.llr = 0.0  # log-likelihood ratio, line over stamps
        self.llr_total = 0.0  # the same sum over every frame tested, not clamped
        self.use_line = False
        self.n_switches = 0
        self.n_tested = 0
        self.n_tilts = 0  # of which level-surface tilts (add_tilt)
        self._delta_s: float | None = None
        self._prev: tuple[float, NDArray[np.float64]] | None = None  # (delta, velocity)

    def note_frame(self, delta_s: float | None) -> None:
        self._delta_s = None if delta_s is None else float(delta_s)

    def shift(self, velocity_xz_mps: NDArray[np.float64]) -> NDArray[np.float64] | None:
        """u (2,): how much the IMU-predicted displacement since the previous frame grows
        when line times replace the stamps (first order in the velocities)."""
        if self._delta_s is None or self._prev is None:
            return None
        d0, v0 = self._prev
        return np.asarray(velocity_xz_mps, dtype=float) * self._delta_s - v0 * d0

    def add_tilt(
        self, residual_rad: float, var_rad2: float, pitch_rate_radps: float, cap_d2: float
    ) -> None:
        """One level-surface tilt as evidence (``time_offset.stamp_test_tilts``): the slice
        is rotated with the attitude at the frame's time, so moving that time by e turns the
        measured tilt by -omega e (omega the shank pitch rate, the sign of the time-offset
        model m = b - omega td). ``residual_rad`` is the tilt's innovation under the frame
        time in use (variance ``var_rad2``); under the other
        choice it is moved by -+omega delta (delta = line - stamp). Each statistic capped at
        ``cap_d2``. Without a re-stamping (delta unknown) nothing is added."""
        if self._delta_s is None or not var_rad2 > 0.0:
            return
        shift = pitch_rate_radps * self._delta_s
        other = residual_rad + (shift if self.use_line else -shift)
        self._add(residual_rad**2 / var_rad2, other**2 / var_rad2, cap_d2)
        self.n_tilts += 1

    def add(self, d2_in_use: float, d2_other: float) -> None:
        """One displacement's gate statistics under the hypothesis in use and the other."""
        self._add(d2_in_use, d2_other, self.cap_d2)

    def _add(self, d2_in_use: float, d2_other: float, cap_d2: float) -> None:
        a, b = min(d2_in_use, cap_d2), min(d2_other, cap_d2)
        d2_stamp, d2_line = (b, a) if self.use_line else (a, b)
        lim = 2.0 * self.threshold
        self.llr = min(max(self.llr + 0.5 * (d2_stamp - d2_line), -lim), lim)
        self.llr_total += 0.5 * (d2_stamp - d2_line)
        self.n_tested += 1
        if not self.use_line and self.llr > self.threshold:
            self.use_line, self.n_switches = True, self.n_switches + 1
        elif self.use_line and self.llr < -self.threshold:
            self.use_line, self.n_switches = False, self.n_switches + 1

    def other_probability(self, line_in_use: bool | None = None) -> float:
        """Posterior probability (equal priors) of the frame times not in use, 1 / (1 +
        exp(-+llr)): 0.5 before any evidence, 1/101 at the switching threshold.
        ``line_in_use``: the choice a frame was stamped with (default: the current one; a
        frame whose own evidence switched the test was stamped with the other)."""
        line = self.use_line if line_in_use is None else line_in_use
        llr = -self.llr if line else self.llr  # log odds, other over in use
        return float(1.0 / (1.0 + np.exp(-llr)))

    def ambiguity_cov(
        self, u: NDArray[np.float64], line_in_use: bool | None = None
    ) -> NDArray[np.float64]:
        """The covariance (m^2, 2x2) a displacement fused under the frame times in use
        carries for the other choice: with probability p its prediction is off by u, so the
        measurement's second moment about it grows by p u u^T. Vanishes as the test decides
        (p -> 0); half of u u^T while it has seen no evidence."""
        u = np.asarray(u, dtype=float)
        return self.other_probability(line_in_use) * np.outer(u, u)

    def end_frame(self, velocity_xz_mps: NDArray[np.float64]) -> None:
        if self._delta_s is not None:
            self._prev = (self._delta_s, np.asarray(velocity_xz_mps, dtype=float).copy())
        else:
            self._prev = None

    def report(self) -> dict:
        return {
            "stamps": "clock line" if self.use_line else "as recorded",
            "log_likelihood_ratio_line": self.llr,
            "log_likelihood_ratio_line_total": self.llr_total,
            "switches": self.n_switches,
            "frames_tested": self.n_tested,
            "tilts_tested": self.n_tilts,
        }
