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

from collections import deque

import numpy as np
from numpy.typing import ArrayLike, NDArray


class StanceDetector:
    """Ankle-acceleration window detector; see the module docstring."""

    def __init__(
        self, ankle_in_imu_m: ArrayLike, accel_threshold_mps2: float, window_s: float
    ) -> None:
        self._r = np.asarray(ankle_in_imu_m, dtype=float).reshape(3)
        self._thr = float(accel_threshold_mps2)
        self._window_s = float(window_s)
        self._prev: tuple[float, NDArray[np.float64]] | None = None
        self._recent: deque[tuple[float, float]] = deque()  # (t, |a_ankle|)

    def add_imu(
        self,
        timestamp_s: float,
        accel_mps2: ArrayLike,
        gyro_radps: ArrayLike,
        R_sagittal: NDArray[np.float64],
        gravity_xz_mps2: ArrayLike,
    ) -> float:
        """Add one IMU sample; returns |a_ankle| (m/s^2) for this sample.

        ``R_sagittal`` (2, 2) maps IMU (x, z) to ground (x, z) (filter.eskf.sagittal_rotation);
        ``gravity_xz_mps2`` the gravity vector in the ground x-z plane (e.g. (0, -9.81)).
        """
        t = float(timestamp_s)
        w = np.asarray(gyro_radps, dtype=float)
        f = np.asarray(accel_mps2, dtype=float)
        r = self._r
        alpha = np.zeros(3)
        if self._prev is not None and t > self._prev[0]:
            alpha = (w - self._prev[1]) / (t - self._prev[0])
        self._prev = (t, w.copy())
        f_ankle = f + _cross3(alpha, r) + _cross3(w, _cross3(w, r))
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


def _cross3(a: NDArray[np.float64], b: NDArray[np.float64]) -> NDArray[np.float64]:
    return np.array(
        [a[1] * b[2] - a[2] * b[1], a[2] * b[0] - a[0] * b[2], a[0] * b[1] - a[1] * b[0]]
    )
