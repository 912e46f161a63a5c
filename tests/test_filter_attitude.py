"""Attitude at the frame time (filter/attitude.py): regression for the stale slice rotation
that biased the ICP displacements during swing on the simulated trials."""

from __future__ import annotations

import numpy as np

from vio_graph.filter.attitude import AttitudeTracker
from vio_graph.filter.config import AttitudeConfig
from vio_graph.geometry import GRAVITY_MPS2, quat_wxyz_from_matrix, rot_y
from vio_graph.types import ImuSample

RATE_RADPS = 6.0  # swing-phase shank rate


def _spinning_samples(n: int, offset_rad: float = 0.0) -> list[ImuSample]:
    """A body pitching at RATE_RADPS about y, sampled at 100 Hz; vendor quaternion exact (or
    off by a constant ``offset_rad``)."""
    out = []
    for k in range(n):
        t = 0.01 * k
        R = rot_y(offset_rad) @ rot_y(RATE_RADPS * t)
        out.append(
            ImuSample(
                t,
                np.array([0.0, 0.0, GRAVITY_MPS2]),
                np.array([0.0, RATE_RADPS, 0]),
                quat_wxyz_from_matrix(R),
            )
        )
    return out


def _angle_between(Ra: np.ndarray, Rb: np.ndarray) -> float:
    return float(np.arccos(np.clip((np.trace(Ra.T @ Rb) - 1) / 2, -1, 1)))


def test_attitude_is_extrapolated_to_the_frame_time_and_vendor_lags() -> None:
    t_frame = 0.2 + 0.0083  # a frame 8.3 ms after the last IMU sample
    truth = rot_y(RATE_RADPS * t_frame)
    errors = {}
    for source in ("vendor", "vendor_extrapolated", "complementary"):
        tracker = AttitudeTracker(AttitudeConfig(source=source))
        for s in _spinning_samples(21):
            tracker.add(s)
        errors[source] = _angle_between(tracker.R_world_imu_at(t_frame), truth)
    assert abs(errors["vendor"] - RATE_RADPS * 0.0083) < 1e-9  # the paper's slice lags
    assert errors["vendor_extrapolated"] < 1e-9
    assert errors["complementary"] < 1e-6


def test_complementary_attitude_converges_to_the_vendor_orientation() -> None:
    tracker = AttitudeTracker(AttitudeConfig(source="complementary", time_constant_s=0.2))
    samples = _spinning_samples(300, offset_rad=0.0)
    tracker.add(_spinning_samples(1, offset_rad=0.1)[0])  # start 0.1 rad off
    for s in samples[1:]:
        tracker.add(s)
    t = samples[-1].timestamp_s
    assert _angle_between(tracker.R_world_imu_at(t), rot_y(RATE_RADPS * t)) < 1e-3
