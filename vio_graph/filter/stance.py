"""Online stance detection for the instrumented leg (no look-ahead).

During the foot's stance the ankle joint does not move (foot flat on the ground), so the
acceleration of the ankle point is zero and its velocity is zero. The shank IMU sees the
ankle through the lever arm r (ankle in the IMU frame):

    f_ankle = f_imu + alpha x r + omega x (omega x r)          (specific force at the ankle)
    a_ankle = R (f_ankle)_xz + g                               (ground frame, gravity removed)

with alpha from finite differences of the gyro. :class:`StanceDetector` flags stance when
|a_ankle| stayed below ``accel_threshold_mps2`` over the last ``window_s`` AND the ankle speed
predicted from the filter (camera velocity + pitch rate x lever) is below
``speed_threshold_mps``; the speed test stops the detector from firing in smooth swing
phases with little acceleration, the acceleration test from trusting a drifted filter
velocity. Pure algorithm: no I/O.
"""

from __future__ import annotations

import math
from collections import deque

import numpy as np
from numpy.typing import ArrayLike, NDArray

from vio_graph.filter.fast_imu import imu_kernels
from vio_graph.filter.gating import mahalanobis2_2d
from vio_graph.filter.lever_arm import angular_acceleration, lever_arm_terms
from vio_graph.types import Displacement2D


class StanceDetector:
    """Ankle-acceleration window detector; see the module docstring."""

    def __init__(
        self, ankle_in_imu_m: ArrayLike, accel_threshold_mps2: float, window_s: float
    ) -> None:
        self._r = np.asarray(ankle_in_imu_m, dtype=float).reshape(3)
        self._thr = float(accel_threshold_mps2)
        self._window_s = float(window_s)
        self._prev: tuple[float, tuple[float, float, float]] | None = None  # (t, gyro)
        self._r_xyz = tuple(self._r.tolist())
        self._recent: deque[tuple[float, float]] = deque()  # (t, |a_ankle|)
        self._kernels = imu_kernels()  # compiled add_imu_quat, or None
        #: True if :meth:`add_imu_quat` runs compiled (numba, ``fast_imu.imu_kernels``)
        self.compiled = self._kernels is not None
        # add_imu_quat's previous sample: [has one, t, gyro x, y, z]
        self._prev_arr = np.zeros(5)

    def add_imu(
        self,
        timestamp_s: float,
        accel_mps2: ArrayLike,
        gyro_radps: ArrayLike,
        R_sagittal: NDArray[np.float64],
        gravity_xz_mps2: ArrayLike,
        trusted: bool = True,
    ) -> float | None:
        """Add one IMU sample; returns |a_ankle| (m/s^2) for this sample.

        ``R_sagittal`` (2, 2) maps IMU (x, z) to ground (x, z) (filter.eskf.sagittal_rotation);
        ``gravity_xz_mps2`` the gravity vector in the ground x-z plane (e.g. (0, -9.81)).
        ``trusted=False`` (a packet the fault monitor repaired: its gyro predicted, its
        accelerometer held, ImuSample.accel_held) gives no vote: the sample is left out of the
        window and the next angular acceleration is differenced across it (returns None).
        A repaired gyro is 0.4-0.6 rad/s off, which through the finite-difference angular
        acceleration and the 0.4 m lever reads as ~20 m/s^2 at the ankle, so every repaired
        spike ended the quiet window for its whole length.
        """
        t = float(timestamp_s)
        if not trusted:
            return None
        gx, gy, gz = np.asarray(gyro_radps, dtype=float).tolist()
        fx, _, fz = np.asarray(accel_mps2, dtype=float).tolist()
        if self._prev is not None and t > self._prev[0]:
            h = t - self._prev[0]
            pgx, pgy, pgz = self._prev[1]
            alx, aly, alz = (gx - pgx) / h, (gy - pgy) / h, (gz - pgz) / h
        else:
            alx = aly = alz = 0.0
        self._prev = (t, (gx, gy, gz))
        rx, ry, rz = self._r_xyz
        # geometry.cross3's products in its order: w x (w x r), alpha x r
        cx, cy, cz = gy * rz - gz * ry, gz * rx - gx * rz, gx * ry - gy * rx
        fx = fx + (aly * rz - alz * ry) + (gy * cz - gz * cy)
        fz = fz + (alx * ry - aly * rx) + (gx * cy - gy * cx)
        (r00, r01), (r10, r11) = np.asarray(R_sagittal, dtype=float).tolist()
        gwx, gwz = np.asarray(gravity_xz_mps2, dtype=float).tolist()
        mag = math.hypot(r00 * fx + r01 * fz + gwx, r10 * fx + r11 * fz + gwz)
        self._recent.append((t, mag))
        while self._recent and self._recent[0][0] < t - self._window_s:
            self._recent.popleft()
        return mag

    def add_imu_quat(
        self,
        timestamp_s: float,
        accel_mps2: ArrayLike,
        gyro_radps: ArrayLike,
        quat_wxyz: ArrayLike,
        gravity_xz_mps2: ArrayLike,
        trusted: bool = True,
    ) -> float | None:
        """:meth:`add_imu` with the sagittal rotation of the vendor orientation ``quat_wxyz``
        computed inside, compiled (filter/compiled_imu.py; needs ``compiled``)."""
        t = float(timestamp_s)
        if not trusted:
            return None
        assert self._kernels is not None, "add_imu_quat needs the compiled kernels"
        mag = self._kernels.stance_ankle_accel(
            t,
            self._prev_arr,
            np.asarray(accel_mps2, dtype=np.float64),
            np.asarray(gyro_radps, dtype=np.float64),
            np.asarray(quat_wxyz, dtype=np.float64),
            self._r,
            np.asarray(gravity_xz_mps2, dtype=np.float64),
        )
        self._recent.append((t, mag))
        while self._recent[0][0] < t - self._window_s:
            self._recent.popleft()
        return mag

    def record(self, t_s: float, mag: float) -> None:
        """Append |a_ankle| ``mag`` (m/s^2) at ``t_s`` to the window, as :meth:`add_imu_quat`
        does after its kernel (for a caller that ran ``compiled_imu.stance_ankle_accel`` on
        ``_prev_arr`` itself: ``compiled_imu.sample_step``)."""
        self._recent.append((t_s, mag))
        while self._recent[0][0] < t_s - self._window_s:
            self._recent.popleft()

    def add_imu_reference(
        self,
        timestamp_s: float,
        accel_mps2: ArrayLike,
        gyro_radps: ArrayLike,
        R_sagittal: NDArray[np.float64],
        gravity_xz_mps2: ArrayLike,
        trusted: bool = True,
    ) -> float | None:
        """numpy reference of :meth:`add_imu` (same |a_ankle| to rounding)."""
        t = float(timestamp_s)
        if not trusted:
            return None
        w = np.asarray(gyro_radps, dtype=float)
        f = np.asarray(accel_mps2, dtype=float)
        prev_t = None if self._prev is None else self._prev[0]
        prev_w = None if self._prev is None else np.array(self._prev[1])
        alpha = angular_acceleration(t, w, prev_t, prev_w)
        gx, gy, gz = w.tolist()
        self._prev = (t, (gx, gy, gz))
        centripetal, tangential = lever_arm_terms(w, alpha, self._r)
        f_ankle = f + tangential + centripetal
        a = R_sagittal @ f_ankle[[0, 2]] + np.asarray(gravity_xz_mps2, dtype=float)
        mag = float(np.hypot(a[0], a[1]))
        self._recent.append((t, mag))
        while self._recent and self._recent[0][0] < t - self._window_s:
            self._recent.popleft()
        return mag

    def quiet(self) -> bool:
        """True if the window is (nearly) full and every |a_ankle| in it is below threshold."""
        if len(self._recent) < 2 or self._recent[-1][0] - self._recent[0][0] < 0.8 * self._window_s:
            return False
        return max(m for _, m in self._recent) < self._thr


class StanceConsistencyTest:
    """Tests the stance hypothesis "the ankle has not moved since onset" against vision.

    The acceleration detector above only proposes a stance; a slow swing (ankle accelerations
    of 1-6 m/s^2, as in step-to-step stair gaits) looks quiet to it. If the ankle is still,
    the camera moves only because the shank turns about it:

        camera(t1) - camera(t0) = lever(t0) - lever(t1),   lever = ankle - camera (ground axes)

    so every visual displacement of the camera is a test of the hypothesis. Two chi-square
    tests (2 dof) decide, with the displacement's own covariance plus the lever's:

    - frame to frame: the displacement of this frame against the lever change of this frame;
    - since onset: the sum of the displacements since the stance began (a chain, restarted
      when a frame has no displacement) against the lever change over the same interval, so a
      slow drift that passes frame by frame is still caught.

    When vision disagrees the hypothesis is rejected and the caller ends the stance (a new
    anchor may start at the next frame). Without a displacement there is nothing to test and
    the hypothesis stands. Pure algorithm: no I/O.

    ``weighted_chain`` (``filter.stance_test_weighted_chain``): the since-onset test weighs
    each link by what it resolves instead of summing the links. The plain sum carries every
    link's covariance for the rest of the stance, so one link that is blind along an axis
    (an ICP displacement whose x is unobservable, sigma ~1 m, e.g. only treads in view)
    makes the chain blind along that axis until the stance ends, and the ankle's motion
    that passes frame by frame (0.6-0.8 cm a frame against a 0.3 cm frame sigma) is never
    caught. Weighted, the chain estimates the ankle's mean motion per frame since onset,
    u = (sum W_k)^-1 sum W_k r_k with W_k = C_k^-1 and r_k each link's residual, and tests
    u against its covariance (sum W_k)^-1 + L / n^2 (L the lever term of the sum, n links):
    a blind link gets no weight along its blind axis. With equal link covariances this is
    the summed test exactly, (sum r)^T (n C + L)^-1 (sum r).
    """

    def __init__(
        self, gate_d2: float, lever_sigma_m: float, floor_m: float, weighted_chain: bool = False
    ) -> None:
        self._gate_d2 = float(gate_d2)
        self._lever_var = 2.0 * float(lever_sigma_m) ** 2  # two lever evaluations per test
        self._floor_var = float(floor_m) ** 2
        self._lever_cov = np.eye(2) * self._lever_var  # (2, 2) m^2
        self._floor_cov = np.eye(2) * self._floor_var
        self._prev: tuple[float, NDArray[np.float64]] | None = None  # (t, lever) last frame
        self._chain: tuple[NDArray, NDArray, NDArray] | None = None  # (lever0, sum d, sum C)
        self._weighted = bool(weighted_chain)
        # weighted chain: (sum W_k, sum W_k r_k, n links)
        self._wchain: tuple[NDArray, NDArray, int] | None = None
        self.last_d2: float = 0.0  #: largest Mahalanobis^2 of the last test (diagnostics)
        #: True if the last call had a displacement to test (False: nothing was tested)
        self.tested: bool = False

    def reset(self) -> None:
        """Forget the chain (the stance ended or was rejected)."""
        self._chain = None
        self._wchain = None

    def motion_cov(self) -> NDArray[np.float64] | None:
        """Covariance (m^2, 2x2) with which the chain since onset resolves an ankle motion
        over the whole chain (the sum's covariance plus the lever term; weighted: n^2 times
        the mean motion's covariance plus the lever term); None without a chain (nothing
        tested since onset). A motion m is one the chain would have rejected if
        m^T motion_cov^-1 m exceeds the gate."""
        if self._weighted:
            if self._wchain is None:
                return None
            sw, _, n = self._wchain
            return n**2 * np.linalg.inv(sw) + self._lever_cov
        if self._chain is None:
            return None
        return self._chain[2] + self._lever_cov

    def resolves(self, motion_xz_m: NDArray[np.float64]) -> bool:
        """True if the chain since onset would have rejected a still ankle had the ankle moved
        by ``motion_xz_m`` (m) over it: the visual test has the power to side with the anchor
        against a disagreement of that size. False without a chain."""
        cov = self.motion_cov()
        if cov is None:
            return False
        return mahalanobis2_2d(cov, np.asarray(motion_xz_m, dtype=float)) > self._gate_d2

    def test(
        self, t_s: float, lever_xz_m: NDArray[np.float64], displacement: Displacement2D | None
    ) -> bool:
        """True if this frame's visual displacement (None: none) agrees with a still ankle.

        ``lever_xz_m`` is ankle - camera (m, ground axes) at this frame (time ``t_s``); the
        lever of the previous call is used when the displacement starts at that frame (else
        nothing can be tested). Call once per frame, in or out of stance.
        """
        lever = np.asarray(lever_xz_m, dtype=float)
        prev, self._prev = self._prev, (float(t_s), lever)
        self.last_d2 = 0.0
        self.tested = False
        if displacement is None or prev is None or abs(displacement.t0_s - prev[0]) > 1e-6:
            self._chain = None
            self._wchain = None
            return True
        self.tested = True
        prev_lever = prev[1]
        d = np.asarray(displacement.delta_xz_m, dtype=float)
        C = np.asarray(displacement.cov_m2, dtype=float) + self._floor_cov
        r1 = d - (prev_lever - lever)
        d2_frame = mahalanobis2_2d(C + self._lever_cov, r1)
        if self._weighted:
            W = np.linalg.inv(C)
            sw, swr, n = (
                (W, W @ r1, 1)
                if self._wchain is None
                else (self._wchain[0] + W, self._wchain[1] + W @ r1, self._wchain[2] + 1)
            )
            self._wchain = (sw, swr, n)
            cov_u = np.linalg.inv(sw)
            u = cov_u @ swr
            d2_chain = mahalanobis2_2d(cov_u + self._lever_cov / n**2, u)
            self.last_d2 = max(d2_frame, d2_chain)
            return self.last_d2 <= self._gate_d2
        lever0, sum_d, sum_C = (
            (prev_lever, d, C)
            if self._chain is None
            else (self._chain[0], self._chain[1] + d, self._chain[2] + C)
        )
        self._chain = (lever0, sum_d, sum_C)
        r = sum_d - (lever0 - lever)
        d2_chain = mahalanobis2_2d(sum_C + self._lever_cov, r)
        self.last_d2 = max(d2_frame, d2_chain)
        return self.last_d2 <= self._gate_d2


class FootRotationTest:
    """Tests the stance hypothesis "the ankle has not moved since onset" against the foot's
    own rotation (shank pitch + ankle encoder = foot pitch).

    A foot on the ground can only turn about a point of contact: the heel while it comes
    down after heel strike (loading response), the toe at heel-off or in a toe-first
    landing. The ankle then moves by (foot rotation) x (ankle - contact), at least
    ``contact_distance_m`` (the nearer of heel and toe) per radian: in a slow loading
    response (foot flattening at ~1 rad/s, ankle accelerations well under the detector's
    threshold) that is 8-10 cm/s, a motion that the camera displacement, ~1 cm a frame,
    barely resolves. The foot pitch change since onset, turned into that ankle motion, is
    tested (chi-square, 1 dof) against the ankle sigma the anchor assumes (pitch-change
    error of shank and encoder, slip), so a foot that turns more than the anchor tolerates
    ends the stance. Like :class:`StanceConsistencyTest`, the first tested frame is measured
    against the previous frame (the stance's onset is itself tested). Without an ankle
    angle (no joints stream) there is nothing to test and the hypothesis stands.
    Pure algorithm: no I/O.
    """

    def __init__(
        self, gate_d2: float, contact_distance_m: float, pitch_sigma_rad: float, slip_sigma_m: float
    ) -> None:
        self._gate_d2 = float(gate_d2)
        self._r = float(contact_distance_m)
        # two pitch evaluations (onset and now), each with the pitch-change error, plus slip
        self._var_m2 = 2.0 * (self._r * float(pitch_sigma_rad)) ** 2 + float(slip_sigma_m) ** 2
        self._prev: float | None = None  # foot pitch (rad) at the previous frame
        self._onset: float | None = None  # foot pitch (rad) the stance is measured from
        self.last_d2: float = 0.0  #: Mahalanobis^2 of the last test (diagnostics)

    def reset(self) -> None:
        """Forget the onset (the stance ended or was rejected)."""
        self._onset = None

    def test(self, foot_pitch_rad: float | None) -> bool:
        """True if the foot has not turned since onset by more than a still ankle allows.
        ``foot_pitch_rad`` is shank pitch + ankle angle at this frame (None: no joints).
        Call once per frame, in or out of stance."""
        prev, self._prev = self._prev, foot_pitch_rad
        self.last_d2 = 0.0
        if foot_pitch_rad is None or prev is None:
            self._onset = None
            return True
        if self._onset is None:
            self._onset = prev
        motion_m = self._r * (foot_pitch_rad - self._onset)
        self.last_d2 = motion_m**2 / self._var_m2
        return self.last_d2 <= self._gate_d2
