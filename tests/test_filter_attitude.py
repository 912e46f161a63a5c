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


def _drifting_vendor(n: int, rate_radps: float) -> list[ImuSample]:
    """A still body (level, gyro zero) whose vendor orientation drifts in pitch at
    ``rate_radps`` (the MTi-1's time-correlated orientation error), 100 Hz."""
    return [
        ImuSample(
            0.01 * k,
            np.array([0.0, 0.0, GRAVITY_MPS2]),
            np.zeros(3),
            quat_wxyz_from_matrix(rot_y(rate_radps * 0.01 * k)),
        )
        for k in range(n)
    ]


def test_weighed_pull_follows_a_drifting_vendor_error_less() -> None:
    """Known answer: a vendor pitch error ramping at 1 deg/s for 2 s reaches the tracked
    attitude as the ramp's lag behind a first-order pull, r (t - tau (1 - exp(-t / tau))):
    1.135 deg with the 1 s pull; with the pull weighed against a level-aided offset known to
    0.25 deg (vendor 1 deg: tau = 1 x (0.25^2 + 1) / 0.25^2 = 17 s) 0.113 deg."""
    rate = np.radians(1.0)
    errors = {}
    for sigma in (None, 1.0):
        tracker = AttitudeTracker(AttitudeConfig(vendor_pitch_sigma_deg=sigma))
        tau = tracker.weigh_pull(np.radians(0.25) ** 2)
        assert tau == (1.0 if sigma is None else 17.0 * 1.0)
        for s in _drifting_vendor(201, rate):
            tracker.add(s)
        errors[sigma] = np.degrees(_angle_between(tracker.R_world_imu_at(2.0), np.eye(3)))
    for sigma, tau in ((None, 1.0), (1.0, 17.0)):
        expected = np.degrees(rate) * (2.0 - tau * (1.0 - np.exp(-2.0 / tau)))
        assert abs(errors[sigma] - expected) < 0.01 * expected
    assert errors[1.0] < 0.12 < 1.1 < errors[None]


def test_weighed_pull_returns_to_the_time_constant_without_an_offset() -> None:
    """No level-aided offset yet (infinite variance) or a lost one (variance far above the
    vendor's): the pull is the configured one, or close to it."""
    tracker = AttitudeTracker(AttitudeConfig(time_constant_s=1.0, vendor_pitch_sigma_deg=1.0))
    assert tracker.weigh_pull(float("inf")) == 1.0
    assert tracker.weigh_pull(np.radians(10.0) ** 2) < 1.02
    assert tracker.weigh_pull(np.radians(1.0) ** 2) == 2.0
