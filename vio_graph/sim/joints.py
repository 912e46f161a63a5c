"""Joint-angle sensors: thigh IMU pitch (hip flexion, correlated ~1 deg error) and knee/ankle
encoders (14-bit quantisation + ~0.05 deg white noise), sampled with the IMU clock."""

from __future__ import annotations

import numpy as np
from numpy.typing import NDArray

from vio_graph.recording.streams import JointTable
from vio_graph.sim.config import JointSensorConfig
from vio_graph.sim.gait import LegMotion
from vio_graph.sim.imu import _gauss_markov


def _encoder(angle_rad: NDArray, bits: int, noise_rad: float, rng, noise: bool) -> NDArray:
    lsb = 2 * np.pi / (2**bits)
    a = angle_rad + (rng.normal(0, noise_rad, angle_rad.shape) if noise else 0.0)
    return np.round(a / lsb) * lsb


def simulate_joints(
    motion: LegMotion, cfg: JointSensorConfig, timestamp_s: NDArray, rng: np.random.Generator
) -> JointTable:
    """Joint table at ``timestamp_s`` (N,): radians, signs of vio_graph.kinematics."""
    t = np.asarray(timestamp_s, dtype=float)
    hip, knee, ankle = motion.joint_angles(t)
    if cfg.noise:
        dt = float(np.median(np.diff(t))) if t.size > 1 else 0.01
        hip = (
            hip
            + _gauss_markov(
                rng, t.size, 1, np.radians(cfg.thigh_pitch_error_deg), cfg.thigh_error_tau_s, dt
            )[:, 0]
        )
    noise_rad = np.radians(cfg.encoder_noise_deg)
    return JointTable(
        timestamp_s=t.copy(),
        thigh_pitch_rad=hip,
        knee_rad=_encoder(knee, cfg.encoder_bits, noise_rad, rng, cfg.noise),
        ankle_rad=_encoder(ankle, cfg.encoder_bits, noise_rad, rng, cfg.noise),
    )
