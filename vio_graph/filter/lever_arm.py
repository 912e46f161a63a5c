"""Specific force transferred along a rigid lever arm (IMU -> camera, IMU -> ankle).

A point at ``r`` (m, IMU frame) on the rigid shank feels the IMU's specific force plus the
tangential term ``alpha x r`` and the centripetal term ``omega x (omega x r)``; the angular
acceleration ``alpha`` comes from finite differences of consecutive gyro samples (valid at the
middle of their interval). The SP-ESKF uses it for the camera centre, the stance detector for
the ankle; each sums the terms in its own order.
"""

from __future__ import annotations

import numpy as np
from numpy.typing import NDArray

from vio_graph.geometry import cross3


def angular_acceleration(
    t_s: float,
    gyro_radps: NDArray[np.float64],
    prev_t_s: float | None,
    prev_gyro_radps: NDArray[np.float64] | None,
) -> NDArray[np.float64]:
    """(gyro - previous gyro) / dt (rad/s^2, (3,)); zeros without a previous sample or dt."""
    if prev_t_s is None or prev_gyro_radps is None or not t_s > prev_t_s:
        return np.zeros(3)
    return (gyro_radps - prev_gyro_radps) / (t_s - prev_t_s)


def lever_arm_terms(
    gyro_radps: NDArray[np.float64], alpha_radps2: NDArray[np.float64], r_m: NDArray[np.float64]
) -> tuple[NDArray[np.float64], NDArray[np.float64]]:
    """(centripetal ``omega x (omega x r)``, tangential ``alpha x r``), m/s^2, IMU frame."""
    return cross3(gyro_radps, cross3(gyro_radps, r_m)), cross3(alpha_radps2, r_m)
