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
  the frame time it is extrapolated like ``"vendor_extrapolated"``.

The class is pure (no I/O) and keeps only the latest sample.
"""

from __future__ import annotations

import numpy as np
from numpy.typing import NDArray
from scipy.spatial.transform import Rotation

from vio_graph.errors import EstimationError
from vio_graph.filter.config import AttitudeConfig
from vio_graph.geometry import matrix_from_quat_wxyz
from vio_graph.types import ImuSample


def _rotvec_matrix(rotvec: NDArray[np.float64]) -> NDArray[np.float64]:
    return Rotation.from_rotvec(rotvec).as_matrix()


class AttitudeTracker:
    """R_world_imu at any time after the latest IMU sample (module docstring).

    Feed every IMU sample with :meth:`add`; :meth:`R_world_imu_at` gives the attitude at a
    frame time (seconds) at or after the latest sample.
    """

    def __init__(self, config: AttitudeConfig | None = None) -> None:
        self.config = AttitudeConfig() if config is None else config
        self._R: NDArray[np.float64] | None = None
        self._t_s = 0.0
        self._gyro_radps = np.zeros(3)

    def add(self, imu: ImuSample) -> None:
        """Advance to ``imu.timestamp_s`` with the sample's gyro rate and vendor orientation."""
        R_vendor = matrix_from_quat_wxyz(imu.quat_wxyz)
        gyro = np.asarray(imu.gyro_radps, dtype=float)
        t = float(imu.timestamp_s)
        if self._R is None or self.config.source != "complementary":
            self._R = R_vendor
        else:
            dt = t - self._t_s
            if dt < 0:
                raise EstimationError(f"IMU sample at {t:.6f} s is older than {self._t_s:.6f} s")
            R = self._R @ _rotvec_matrix(0.5 * (self._gyro_radps + gyro) * dt)
            k = min(1.0, dt / self.config.time_constant_s)
            err = Rotation.from_matrix(R.T @ R_vendor).as_rotvec()
            R = R @ _rotvec_matrix(k * err)
            self._R = R
        self._t_s, self._gyro_radps = t, gyro

    @property
    def initialised(self) -> bool:
        return self._R is not None

    def R_world_imu_at(self, t_s: float) -> NDArray[np.float64]:
        """(3, 3) R_world_imu at ``t_s`` (heading included; the caller removes it)."""
        if self._R is None:
            raise EstimationError("no IMU sample yet")
        if self.config.source == "vendor":
            return self._R.copy()
        dt = max(0.0, float(t_s) - self._t_s)
        return self._R @ _rotvec_matrix(self._gyro_radps * dt)
