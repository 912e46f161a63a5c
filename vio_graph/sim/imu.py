"""IMU model: Xsens MTi-1 specific force and angular rate at the IMU's lever arm on the shank.

The true signals are analytic derivatives of the gait splines (gravity, tangential and
centripetal terms of the swinging shank); errors follow the MTi-1 datasheet (docs/simulator.md):
white noise, turn-on bias plus bias random walk, saturation, and the vendor orientation with
time-correlated roll/pitch (1 deg RMS) and heading (2 deg RMS) errors.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from numpy.typing import NDArray
from scipy.signal import lfilter

from vio_graph.geometry import GRAVITY_MPS2, quat_wxyz_from_matrix, rot_x, rot_y, rot_z
from vio_graph.recording.streams import ImuStateTable, ImuTable
from vio_graph.sim.config import ImuConfig
from vio_graph.sim.gait import LegMotion


@dataclass(frozen=True)
class ImuTruth:
    """True IMU motion at ``timestamp_s`` (N,): world position (N, 3), velocity (N, 3),
    acceleration (N, 3), R_world_imu (N, 3, 3), angular rate in the IMU frame (N, 3)."""

    timestamp_s: NDArray[np.float64]
    position_m: NDArray[np.float64]
    velocity_mps: NDArray[np.float64]
    accel_mps2: NDArray[np.float64]
    R_world_imu: NDArray[np.float64]
    gyro_radps: NDArray[np.float64]

    @property
    def specific_force_mps2(self) -> NDArray[np.float64]:
        """f = R_world_imu^T (a - g), g = (0, 0, -9.81) m/s^2, in the IMU frame (N, 3)."""
        a_minus_g = self.accel_mps2 + np.array([0.0, 0.0, GRAVITY_MPS2])
        return np.einsum("nji,nj->ni", self.R_world_imu, a_minus_g)


def _xz_to_3d(xz: NDArray) -> NDArray[np.float64]:
    out = np.zeros((xz.shape[0], 3))
    out[:, 0], out[:, 2] = xz[:, 0], xz[:, 1]
    return out


def imu_truth(
    motion: LegMotion,
    timestamp_s: NDArray,
    imu_in_shank_xz_m: NDArray,
    R_shank_imu: NDArray | None = None,
) -> ImuTruth:
    """True IMU kinematics: the IMU point is fixed in the shank frame (origin at the knee)."""
    t = np.asarray(timestamp_s, dtype=float)
    R_s_i = np.eye(3) if R_shank_imu is None else np.asarray(R_shank_imu, dtype=float)
    pos = _xz_to_3d(motion.shank_point(t, imu_in_shank_xz_m, 0))
    vel = _xz_to_3d(motion.shank_point(t, imu_in_shank_xz_m, 1))
    acc = _xz_to_3d(motion.shank_point(t, imu_in_shank_xz_m, 2))
    R_w_i = rot_y(motion.shank_pitch(t)) @ R_s_i
    omega_s = np.zeros((t.size, 3))
    omega_s[:, 1] = motion.shank_pitch(t, 1)
    gyro = omega_s @ R_s_i  # R_s_i^T omega_s, row-wise
    return ImuTruth(t, pos, vel, acc, R_w_i, gyro)


def _gauss_markov(
    rng: np.random.Generator, n: int, dims: int, sigma: float, tau_s: float, dt_s: float
) -> NDArray[np.float64]:
    """Stationary first-order Gauss-Markov noise (n, dims) with RMS ``sigma``."""
    a = np.exp(-dt_s / tau_s)
    w = rng.standard_normal((n, dims)) * sigma * np.sqrt(1 - a * a)
    w[0] = rng.standard_normal(dims) * sigma
    return lfilter([1.0], [1.0, -a], w, axis=0)


def simulate_imu(
    motion: LegMotion,
    cfg: ImuConfig,
    duration_s: float,
    imu_in_shank_xz_m: NDArray,
    rng: np.random.Generator,
    R_shank_imu: NDArray | None = None,
) -> tuple[ImuTable, ImuStateTable, ImuTruth]:
    """IMU samples at ``cfg.rate_hz`` over [0, duration_s] and the true IMU state table.

    ``R_shank_imu``: IMU axes in the shank frame (None: aligned with the shank). Specific
    force, rate, biases, noise and the vendor orientation are all in the IMU axes."""
    dt = 1.0 / cfg.rate_hz
    t = np.arange(0.0, duration_s + 0.5 * dt, dt)
    truth = imu_truth(motion, t, imu_in_shank_xz_m, R_shank_imu)
    n = t.size
    accel = truth.specific_force_mps2.copy()
    gyro = truth.gyro_radps.copy()
    acc_bias = np.zeros((n, 3))
    gyro_bias = np.zeros((n, 3))
    R_out = truth.R_world_imu
    if cfg.noise:
        acc_bias = rng.normal(0, cfg.accel_turn_on_bias_mps2, 3) + np.cumsum(
            rng.normal(0, cfg.accel_bias_rw * np.sqrt(dt), (n, 3)), axis=0
        )
        gyro_bias = rng.normal(0, cfg.gyro_turn_on_bias_radps, 3) + np.cumsum(
            rng.normal(0, cfg.gyro_bias_rw * np.sqrt(dt), (n, 3)), axis=0
        )
        accel = (
            accel + acc_bias + rng.normal(0, cfg.accel_noise_density * np.sqrt(cfg.rate_hz), (n, 3))
        )
        gyro = (
            gyro + gyro_bias + rng.normal(0, cfg.gyro_noise_density * np.sqrt(cfg.rate_hz), (n, 3))
        )
        # vendor orientation: R_err (world frame) @ R_true, errors correlated in time
        rp = _gauss_markov(
            rng, n, 2, np.radians(cfg.orientation_rms_deg), cfg.orientation_error_tau_s, dt
        )
        yaw = _gauss_markov(
            rng, n, 1, np.radians(cfg.heading_rms_deg), cfg.orientation_error_tau_s, dt
        )[:, 0]
        if cfg.random_heading_offset:
            yaw = yaw + rng.uniform(-np.pi, np.pi)
        R_err = np.stack([rot_z(yaw[k]) @ rot_y(rp[k, 1]) @ rot_x(rp[k, 0]) for k in range(n)])
        R_out = R_err @ truth.R_world_imu
    accel = np.clip(accel, -cfg.accel_range_mps2, cfg.accel_range_mps2)
    gyro = np.clip(gyro, -cfg.gyro_range_radps, cfg.gyro_range_radps)
    imu = ImuTable(t, accel, gyro, quat_wxyz_from_matrix(R_out))
    state = ImuStateTable(
        timestamp_s=t,
        position_m=truth.position_m,
        velocity_mps=truth.velocity_mps,
        quat_wxyz=quat_wxyz_from_matrix(truth.R_world_imu),
        accel_bias_mps2=acc_bias,
        gyro_bias_radps=gyro_bias,
    )
    return imu, state, truth
