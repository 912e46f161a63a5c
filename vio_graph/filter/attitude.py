"""Camera attitude at the depth-frame time (the R of eq. 2), from the IMU.

The paper rotates each slice into the ground frame with "the Euler angle of IMU" (eq. 2).
Taken literally (``AttitudeConfig.source="vendor"``) that is the latest vendor orientation,
which in vio_graph's replay is up to one IMU period (10 ms at 100 Hz) older than the frame.
During swing the shank turns at 5-8 rad/s, so the slice is rotated by up to 0.05-0.08 rad too
little: a corner 0.6 m away moves by 3-5 cm, and the frame-to-frame displacement inherits the
difference of two such errors. The vendor orientation also carries a time-correlated error
(MTi-1: ~1 deg RMS) whose frame-to-frame change is another few mm at the corner.

Measured on the simulated upstair trial, seed 1 (``benchmarks/eval_frontend.py``, accepted
displacements vs ground truth, p95 |error| x / z): latest vendor orientation 5.3 / 6.8 mm,
true attitude at the frame time 2.4 / 1.7 mm.

Sources (``AttitudeConfig.source``):

* ``"vendor"`` -- the paper: the latest vendor orientation, as is.
* ``"vendor_extrapolated"`` -- the latest vendor orientation rotated on by the latest gyro
  rate over the time from that sample to the frame, R(t) = R_k exp([w_k (t - t_k)]x).
* ``"complementary"`` (default) -- a complementary filter on SO(3): between IMU samples the
  attitude is integrated from the gyro (mid-point rate; gyro noise and bias, 1e-3 and 2e-3
  rad/s, are negligible over a frame), and at every sample it is pulled towards the vendor
  orientation by dt / ``time_constant_s`` of the remaining rotation. Frame-to-frame rotation
  then comes from the gyro (precise), the absolute tilt from the vendor filter (bounded); at
  the frame time it is extrapolated like ``"vendor_extrapolated"``. With
  ``vendor_pitch_sigma_deg`` set, the pull about the pitch (shank y) axis is weighed against
  the level-aided pitch offset (:meth:`AttitudeTracker.weigh_pull`); roll and heading keep
  ``time_constant_s``. ``"auto"`` estimates the vendor's pitch error online
  (:class:`VendorPitchVariance`).

The class is pure (no I/O) and keeps only the latest sample.
"""

from __future__ import annotations

import math
from collections import deque

import numpy as np
from numpy.typing import NDArray

from vio_graph.errors import EstimationError
from vio_graph.filter.config import AttitudeConfig, LevelAidingConfig
from vio_graph.filter.fast_imu import (
    Mat3,
    imu_kernels,
    mat3_mul,
    mat3_rotvec,
    mat3_tmul,
    quat_matrix,
    rotvec_mat3,
)
from vio_graph.geometry import matrix_from_quat_wxyz, remove_yaw, rot_y
from vio_graph.types import ImuSample

_HISTORY_SAMPLES = 16  # IMU samples of attitude kept for past frame times (0.16 s at 100 Hz)


class AttitudeTracker:
    """R_world_imu at any time after the latest IMU sample (module docstring).

    Feed every IMU sample with :meth:`add`; :meth:`R_world_imu_at` gives the attitude at a
    frame time (seconds) at or after the latest sample.
    """

    def __init__(self, config: AttitudeConfig | None = None) -> None:
        self.config = AttitudeConfig() if config is None else config
        #: the pull's time constant about the roll and heading axes (s)
        self.time_constant_s = self.config.time_constant_s
        #: the pull's time constant about the pitch (shank y) axis in use (s):
        #: ``config.time_constant_s`` unless the caller weighs it (:meth:`weigh_pull`)
        self.pitch_time_constant_s = self.config.time_constant_s
        self._R: Mat3 | None = None  # R_world_imu, row-major
        self._t_s = 0.0
        self._gyro_radps = (0.0, 0.0, 0.0)  # rad/s, latest sample
        # recent (t, R, gyro), for frames re-stamped into the past (camera-IMU time offset)
        self._recent: deque[tuple[float, Mat3, tuple[float, float, float]]] = deque(
            maxlen=_HISTORY_SAMPLES
        )
        self._kernels = imu_kernels()  # compiled complementary step, or None
        #: the vendor orientation [w, x, y, z] of the latest sample (the one at ``_t_s``)
        self.vendor_quat_wxyz: NDArray[np.float64] | None = None

    def add(self, imu: ImuSample) -> None:
        """Advance to ``imu.timestamp_s`` with the sample's gyro rate and vendor orientation.

        Scalar closed forms (filter/fast_imu.py); :meth:`add_reference` is the numpy / scipy
        version the tests compare it with.
        """
        gx, gy, gz = np.asarray(imu.gyro_radps, dtype=float).tolist()
        t = float(imu.timestamp_s)
        if self._R is None or self.config.source != "complementary":
            self._R = quat_matrix(imu.quat_wxyz)
        elif self._kernels is not None:  # the same step compiled (filter/compiled_imu.py)
            dt = t - self._t_s
            if dt < 0:
                raise EstimationError(f"IMU sample at {t:.6f} s is older than {self._t_s:.6f} s")
            qw, qx, qy, qz = np.asarray(imu.quat_wxyz, dtype=float).tolist()
            k = min(1.0, dt / self.time_constant_s)
            kp = min(1.0, dt / self.pitch_time_constant_s)
            self._R = self._kernels.attitude_step(
                self._R, self._gyro_radps, (gx, gy, gz), (qw, qx, qy, qz), dt, k, kp
            )
        else:
            R_vendor = quat_matrix(imu.quat_wxyz)
            dt = t - self._t_s
            if dt < 0:
                raise EstimationError(f"IMU sample at {t:.6f} s is older than {self._t_s:.6f} s")
            px, py, pz = self._gyro_radps
            R = mat3_mul(
                self._R,
                rotvec_mat3(0.5 * (px + gx) * dt, 0.5 * (py + gy) * dt, 0.5 * (pz + gz) * dt),
            )
            k = min(1.0, dt / self.time_constant_s)
            kp = min(1.0, dt / self.pitch_time_constant_s)
            ex, ey, ez = mat3_rotvec(mat3_tmul(R, R_vendor))
            self._R = mat3_mul(R, rotvec_mat3(k * ex, kp * ey, k * ez))
        self._t_s, self._gyro_radps = t, (gx, gy, gz)
        self.vendor_quat_wxyz = imu.quat_wxyz
        self._recent.append((t, self._R, self._gyro_radps))

    def add_reference(self, imu: ImuSample) -> None:
        """numpy / scipy reference of :meth:`add` (same attitude to rounding)."""
        from scipy.spatial.transform import Rotation

        R_vendor = matrix_from_quat_wxyz(imu.quat_wxyz)
        gyro = np.asarray(imu.gyro_radps, dtype=float)
        t = float(imu.timestamp_s)
        if self._R is None or self.config.source != "complementary":
            R = R_vendor
        else:
            dt = t - self._t_s
            if dt < 0:
                raise EstimationError(f"IMU sample at {t:.6f} s is older than {self._t_s:.6f} s")
            R = np.array(self._R).reshape(3, 3)
            R = R @ Rotation.from_rotvec(0.5 * (np.array(self._gyro_radps) + gyro) * dt).as_matrix()
            k = min(1.0, dt / self.time_constant_s)
            kp = min(1.0, dt / self.pitch_time_constant_s)
            err = Rotation.from_matrix(R.T @ R_vendor).as_rotvec() * np.array([k, kp, k])
            R = R @ Rotation.from_rotvec(err).as_matrix()
        r = R.ravel().tolist()
        self._R = (r[0], r[1], r[2], r[3], r[4], r[5], r[6], r[7], r[8])
        gx, gy, gz = gyro.tolist()
        self._t_s, self._gyro_radps = t, (gx, gy, gz)
        self.vendor_quat_wxyz = imu.quat_wxyz
        self._recent.append((t, self._R, self._gyro_radps))

    @property
    def initialised(self) -> bool:
        return self._R is not None

    def weigh_pull(self, offset_var_rad2: float, vendor_var_rad2: float | None = None) -> float:
        """Slow the pull towards the vendor about the pitch axis by how much better the pitch
        is known without it (``AttitudeConfig.vendor_pitch_sigma_deg``): with
        ``offset_var_rad2`` the variance of the level-aided pitch offset (rad^2) and var_vendor
        the vendor's pitch error variance (the configured sigma squared, or
        ``vendor_var_rad2`` when the option is ``"auto"``: :class:`VendorPitchVariance`), the
        pitch time constant becomes ``time_constant_s`` x (var_offset + var_vendor) /
        var_offset. The two are blended as two estimates of the pitch by their variances; the
        pull is the vendor's share. Roll and heading keep ``time_constant_s``. Returns the
        pitch time constant in use (s); ``time_constant_s`` when the option is off or the
        vendor's variance is not known yet."""
        sigma_deg = self.config.vendor_pitch_sigma_deg
        tau = self.config.time_constant_s
        var_vendor = None
        if sigma_deg == "auto":
            var_vendor = vendor_var_rad2
        elif sigma_deg is not None:
            var_vendor = math.radians(sigma_deg) ** 2
        if var_vendor is not None and 0.0 < offset_var_rad2 < math.inf:
            tau *= (offset_var_rad2 + var_vendor) / offset_var_rad2
        self.pitch_time_constant_s = tau
        return tau

    def gyro_at(self, t_s: float) -> NDArray[np.float64]:
        """Gyro rate (rad/s, IMU axes) at ``t_s``, interpolated over the recent samples (held
        beyond them)."""
        recent = self._recent
        if not recent:
            return np.array(self._gyro_radps)
        # np.interp per axis, written out on the few samples kept (same branches and
        # arithmetic as numpy's: held beyond the ends, the sample itself on an exact stamp,
        # else slope * (t - t_j) + g_j); :meth:`gyro_at_reference` is the numpy form
        if t_s >= recent[-1][0]:
            return np.array(recent[-1][2])
        if t_s <= recent[0][0]:
            return np.array(recent[0][2])
        j = len(recent) - 2
        while recent[j][0] > t_s:  # the latest sample at or before t_s (frames lag a few)
            j -= 1
        t0, _, g0 = recent[j]
        if t0 == t_s:
            return np.array(g0)
        t1, _, g1 = recent[j + 1]
        out = []
        for a, b in zip(g0, g1, strict=True):
            slope = (b - a) / (t1 - t0)
            v = slope * (t_s - t0) + a
            if math.isnan(v):
                v = slope * (t_s - t1) + b
                if math.isnan(v) and a == b:
                    v = a
            out.append(v)
        return np.array(out)

    def gyro_at_reference(self, t_s: float) -> NDArray[np.float64]:
        """numpy reference of :meth:`gyro_at` (np.interp per axis)."""
        if not self._recent:
            return np.array(self._gyro_radps)
        ts = np.array([r[0] for r in self._recent])
        g = np.array([r[2] for r in self._recent])
        return np.array([np.interp(t_s, ts, g[:, i]) for i in range(3)])

    def R_world_imu_at(self, t_s: float) -> NDArray[np.float64]:
        """(3, 3) R_world_imu at ``t_s`` (heading included; the caller removes it)."""
        return np.array(self.R_world_imu_at_mat3(t_s)).reshape(3, 3)

    def R_world_imu_at_mat3(self, t_s: float) -> Mat3:
        """:meth:`R_world_imu_at` as a row-major tuple."""
        if self._R is None:
            raise EstimationError("no IMU sample yet")
        R, t_k, gyro = self._R, self._t_s, self._gyro_radps
        past = float(t_s) < self._t_s and len(self._recent) > 1
        if past:  # re-stamped frame (time offset): the latest sample at or before t_s
            for t_j, R_j, g_j in reversed(self._recent):
                R, t_k, gyro = R_j, t_j, g_j
                if t_j <= t_s:
                    break
        if self.config.source == "vendor":
            return R
        dt = float(t_s) - t_k if past else max(0.0, float(t_s) - t_k)
        gx, gy, gz = gyro
        return mat3_mul(R, rotvec_mat3(gx * dt, gy * dt, gz * dt))


def with_pitch_offset(R_world_imu: NDArray[np.float64], offset_rad: float) -> NDArray[np.float64]:
    """R_world_imu turned by ``offset_rad`` about the lateral axis of its own ground frame:
    ``remove_yaw(result) == rot_y(offset_rad) @ remove_yaw(R_world_imu)`` (heading kept)."""
    R = np.asarray(R_world_imu, dtype=float)
    G = remove_yaw(R)
    Rz = G @ R.T  # the heading removal, a rotation about world z
    return Rz.T @ rot_y(offset_rad) @ G


class PitchOffsetFilter:
    """Pitch correction of the IMU attitude from level surfaces (frontend/level.py).

    One-state Kalman filter on the offset b (rad) such that rot_y(b) @ R_ground_imu is the
    true attitude. ``predict`` adds random-walk noise (the vendor error drifts: MTi-1 ~1 deg
    RMS, correlation time of seconds); ``update`` takes the residual tilt measured on a slice
    that was already rotated with the current b, so the innovation is the measurement itself.
    Once the offset is known to better than ``initial_sigma_deg``, measurements outside
    ``gate_sigmas`` of the predicted spread are refused (a ramp, a wrongly fitted line).
    """

    def __init__(self, config: LevelAidingConfig | None = None) -> None:
        self.config = LevelAidingConfig() if config is None else config
        self.offset_rad = 0.0
        self.var_rad2 = np.radians(self.config.initial_sigma_deg) ** 2
        self._t_s: float | None = None
        self.n_accepted = 0
        self.n_rejected = 0

    @property
    def initialised(self) -> bool:
        """True once a measurement was accepted."""
        return self.n_accepted > 0

    def predict(self, t_s: float) -> None:
        if self._t_s is not None and t_s > self._t_s:
            q = np.radians(self.config.drift_deg_per_sqrt_s) ** 2
            self.var_rad2 += q * (t_s - self._t_s)
        self._t_s = t_s if self._t_s is None else max(self._t_s, t_s)

    def update(self, tilt_rad: float, sigma_rad: float) -> float:
        """Fuse a residual tilt (rad) with its sigma; returns the change of b (rad)."""
        cfg = self.config
        r = sigma_rad**2 + np.radians(cfg.measurement_floor_deg) ** 2
        s = self.var_rad2 + r
        if self.initialised and tilt_rad**2 > cfg.gate_sigmas**2 * s:
            self.n_rejected += 1
            return 0.0
        k = self.var_rad2 / s
        step = float(k * tilt_rad)
        self.offset_rad += step
        self.var_rad2 *= 1.0 - k
        self.n_accepted += 1
        return step


class SurfaceBendTest:
    """Are the level surfaces' tilts a rotation of the slice, or a bend of the surfaces?

    A pitch error of the attitude turns every surface of the slice by the same angle: the
    level surfaces' tilt and the vertical faces' lean (``frontend.level.measure_face_lean``,
    as a tilt) agree. Depth errors that depend on where a point is (multipath excess near
    the concave tread-riser corners, the wiggling error of the range) bend the surfaces
    instead, and bend treads and risers in opposite senses: their tilts then disagree, and
    the tread tilt is a biased pitch measurement that a random-walk offset would follow.

    Each frame with both gives d = tread tilt - face tilt with variance v = sum of the two
    fits' variances. The test keeps the inverse-variance weighted mean of d with weights
    forgotten exponentially over ``memory_s`` seconds; the surfaces are *bent* while that
    mean is more than ``sigmas`` of its standard error (1 / sqrt(sum of weights)) from 0,
    with at least ``min_frames`` (decayed) frames behind it. Rigid surfaces give a mean
    indistinguishable from 0 whatever the pitch error. Pure; no I/O.
    """

    def __init__(self, memory_s: float, sigmas: float, min_frames: float = 5.0) -> None:
        if not (memory_s > 0.0 and sigmas > 0.0):
            raise ValueError(f"memory_s and sigmas must be > 0, got {memory_s}, {sigmas}")
        self.memory_s = float(memory_s)
        self.sigmas = float(sigmas)
        self.min_frames = float(min_frames)
        self._t_s: float | None = None
        self._n = 0.0  # decayed frame count
        self._w = 0.0  # decayed sum of 1 / v
        self._wd = 0.0  # decayed sum of d / v
        self.n_pairs = 0
        self.n_bent_frames = 0  # frames judged bent (:meth:`judge`)
        self.n_resets = 0  # verdicts that turned to bent (:meth:`judge`'s onsets)
        self._was_bent = False  # the previous judged frame's verdict

    def _decay_to(self, t_s: float) -> None:
        if self._t_s is not None and t_s > self._t_s:
            k = math.exp(-(t_s - self._t_s) / self.memory_s)
            self._n *= k
            self._w *= k
            self._wd *= k
        if self._t_s is None or t_s > self._t_s:
            self._t_s = t_s

    def add(
        self,
        t_s: float,
        tread_tilt_rad: float,
        tread_var_rad2: float,
        face_tilt_rad: float,
        face_var_rad2: float,
    ) -> None:
        """One frame's level-surface tilt and face lean (rad) with their variances (rad^2)."""
        v = tread_var_rad2 + face_var_rad2
        d = tread_tilt_rad - face_tilt_rad
        if not (math.isfinite(d) and v > 0.0 and math.isfinite(v)):
            return
        self._decay_to(t_s)
        self._n += 1.0
        self._w += 1.0 / v
        self._wd += d / v
        self.n_pairs += 1

    def mean_rad(self) -> float | None:
        """The weighted mean disagreement (rad), None before any pair."""
        return None if self._w <= 0.0 else self._wd / self._w

    def bent(self, t_s: float) -> bool:
        """True if the surfaces seen up to ``t_s`` are bent (see the class docstring)."""
        self._decay_to(t_s)
        if self._n < self.min_frames or self._w <= 0.0:
            return False
        mean = self._wd / self._w
        return mean * mean * self._w > self.sigmas * self.sigmas

    def judge(self, t_s: float) -> tuple[bool, bool]:
        """This frame's verdict, counted: (bent, onset), onset True when the previous judged
        frame was not bent (what the earlier tilts taught may then be dropped)."""
        bent = self.bent(t_s)
        onset = bent and not self._was_bent
        self._was_bent = bent
        self.n_bent_frames += bent
        self.n_resets += onset
        return bent, onset


def pitch_disagreement_rad(R_tracked: Mat3, quat_vendor_wxyz: NDArray[np.float64]) -> float:
    """The vendor orientation's pitch (rad) relative to the tracked attitude at the same
    sample: the shank-y (pitch axis) component of the rotation vector of R_tracked^T R_vendor
    (both R_world_imu in shank axes). With the level-surface offset b (which turns the
    tracked attitude about the same axis), the vendor's pitch relative to the level-aided
    pitch is this minus b."""
    return mat3_rotvec(mat3_tmul(R_tracked, quat_matrix(quat_vendor_wxyz)))[1]


class VendorPitchVariance:
    """Online estimate of the vendor orientation's pitch error variance (rad^2), from its
    disagreement with the level-aided pitch (``vendor_pitch_sigma_deg: auto``).

    With d = vendor pitch - level-aided pitch at one IMU sample and var_level the level-aided
    pitch's own variance there, E[d^2] = var_vendor + var_level if the two errors are
    independent, so var_vendor = E[d^2 - var_level]. The expectation is a weighted mean with
    weights forgotten exponentially over ``memory_s`` seconds, floored at 0 (a vendor that
    agrees with the level-aided pitch to within the latter's own spread is taken as exact,
    and the pull stays at ``time_constant_s``). The two errors are not independent while the
    pull is fast (the tracked pitch follows the vendor, the offset only part of it), which
    makes the estimate low rather than high: the pull errs towards the configured
    ``time_constant_s``.
    """

    def __init__(self, memory_s: float) -> None:
        if not memory_s > 0.0:
            raise ValueError(f"memory_s must be > 0, got {memory_s}")
        self.memory_s = float(memory_s)
        self._t_s: float | None = None
        self._w = 0.0  # sum of the weights
        self._s = 0.0  # weighted sum of d^2 - var_level (rad^2)
        self.n = 0  # disagreements taken

    def add(self, t_s: float, disagreement_rad: float, level_var_rad2: float) -> None:
        """Take one disagreement d (rad) at ``t_s`` (s, not decreasing) with the level-aided
        pitch's variance (rad^2) there."""
        if not (math.isfinite(disagreement_rad) and math.isfinite(level_var_rad2)):
            return
        if self._t_s is not None:
            if t_s < self._t_s:
                raise EstimationError(
                    f"disagreement at {t_s:.6f} s is older than {self._t_s:.6f} s"
                )
            decay = math.exp(-(t_s - self._t_s) / self.memory_s)
            self._w *= decay
            self._s *= decay
        self._t_s = t_s
        self._w += 1.0
        self._s += disagreement_rad * disagreement_rad - level_var_rad2
        self.n += 1

    @property
    def var_rad2(self) -> float | None:
        """The vendor's pitch error variance (rad^2, >= 0), None before any disagreement."""
        if self.n == 0:
            return None
        return max(0.0, self._s / self._w)

    @property
    def sigma_deg(self) -> float | None:
        """:attr:`var_rad2` as a sigma in degrees (None before any disagreement)."""
        v = self.var_rad2
        return None if v is None else math.degrees(math.sqrt(v))
