"""Attitude at the frame time (filter/attitude.py): regression for the stale slice rotation
that biased the ICP displacements during swing on the simulated trials."""

from __future__ import annotations

import numpy as np
import pytest
from pydantic import ValidationError

from vio_graph.errors import EstimationError
from vio_graph.filter.attitude import AttitudeTracker, VendorPitchVariance, pitch_disagreement_rad
from vio_graph.filter.config import AttitudeConfig
from vio_graph.geometry import GRAVITY_MPS2, quat_wxyz_from_matrix, rot_x, rot_y
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


def _drifting_vendor(n: int, rate_radps: float, rot=rot_y) -> list[ImuSample]:
    """A still body (level, gyro zero) whose vendor orientation drifts at ``rate_radps``
    about the axis of ``rot`` (pitch by default; the MTi-1's time-correlated orientation
    error), 100 Hz."""
    return [
        ImuSample(
            0.01 * k,
            np.array([0.0, 0.0, GRAVITY_MPS2]),
            np.zeros(3),
            quat_wxyz_from_matrix(rot(rate_radps * 0.01 * k)),
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


def test_weighed_pull_keeps_the_time_constant_about_roll() -> None:
    """Level surfaces hold the pitch only: with the pull weighed (pitch 17 s), a vendor error
    ramping in roll reaches the tracked attitude with the 1 s pull's lag, as without the
    option (on a real shank the fast roll pull bounds the gyro bias's drift)."""
    rate = np.radians(1.0)
    tracker = AttitudeTracker(AttitudeConfig(vendor_pitch_sigma_deg=1.0))
    assert tracker.weigh_pull(np.radians(0.25) ** 2) == 17.0
    assert tracker.time_constant_s == 1.0
    for s in _drifting_vendor(201, rate, rot_x):
        tracker.add(s)
    err = np.degrees(_angle_between(tracker.R_world_imu_at(2.0), np.eye(3)))
    expected = np.degrees(rate) * (2.0 - 1.0 * (1.0 - np.exp(-2.0)))
    assert abs(err - expected) < 0.01 * expected


def test_weighed_pull_reference_matches_the_scalar_step() -> None:
    """``add_reference`` (scipy) and ``add`` give the same attitude with different pitch and
    roll gains (a vendor off in pitch and roll on a swinging shank)."""
    from vio_graph.geometry import rot_x

    a = AttitudeTracker(AttitudeConfig(vendor_pitch_sigma_deg=1.0))
    b = AttitudeTracker(AttitudeConfig(vendor_pitch_sigma_deg=1.0))
    for tr in (a, b):
        tr.weigh_pull(np.radians(0.3) ** 2)
    for k, s in enumerate(_spinning_samples(150)):
        off = rot_x(np.radians(1.0) * np.sin(0.1 * k)) @ rot_y(np.radians(2.0) * np.cos(0.05 * k))
        v = ImuSample(
            s.timestamp_s,
            s.accel_mps2,
            s.gyro_radps,
            quat_wxyz_from_matrix(off @ rot_y(RATE_RADPS * s.timestamp_s)),
        )
        a.add(v)
        b.add_reference(v)
    assert np.allclose(a.R_world_imu_at(1.49), b.R_world_imu_at(1.49), atol=1e-12)


def _gauss_markov_deg(
    rng: np.random.Generator, n: int, sigma_deg: float, tau_s: float, dt_s: float
):
    a = np.exp(-dt_s / tau_s)
    e = np.empty(n)
    e[0] = rng.standard_normal() * sigma_deg
    w = rng.standard_normal(n) * sigma_deg * np.sqrt(1.0 - a * a)
    for k in range(1, n):
        e[k] = a * e[k - 1] + w[k]
    return np.radians(e)


def test_vendor_pitch_variance_known_answers() -> None:
    """VendorPitchVariance against vendors with a known pitch error, the level-aided pitch
    itself off by N(0, 0.3 deg) at 30 frames/s (its variance given): a constant 1 deg error
    gives 1 deg; a time-correlated one (1 deg RMS, 2 s, as the MTi-1 model) gives 1 deg to
    within 10 % over 20 min with a 5 min memory; a vendor equal to the truth gives about 0,
    and the pull then stays within 5 % of the configured 1 s."""
    rng = np.random.default_rng(3)
    dt, var_level = 1.0 / 30.0, np.radians(0.3) ** 2
    n = int(1200 / dt)
    level_err = rng.standard_normal(n) * np.sqrt(var_level)
    cases = {
        "constant": np.full(n, np.radians(1.0)),
        "correlated": _gauss_markov_deg(rng, n, 1.0, 2.0, dt),
        "exact": np.zeros(n),
    }
    sigma = {}
    for name, vendor_err in cases.items():
        est = VendorPitchVariance(memory_s=300.0)
        assert est.var_rad2 is None and est.sigma_deg is None
        for k in range(n):
            est.add(k * dt, vendor_err[k] - level_err[k], var_level)
        sigma[name] = est.sigma_deg
        assert est.n == n
    assert abs(sigma["constant"] - 1.0) < 0.05, sigma
    assert abs(sigma["correlated"] - 1.0) < 0.1, sigma
    assert sigma["exact"] < 0.1, sigma
    tracker = AttitudeTracker(AttitudeConfig(vendor_pitch_sigma_deg="auto"))
    assert tracker.weigh_pull(var_level, None) == 1.0  # nothing estimated yet: as configured
    assert tracker.weigh_pull(var_level, np.radians(sigma["exact"]) ** 2) < 1.05
    tau_1deg = tracker.weigh_pull(var_level, np.radians(sigma["constant"]) ** 2)
    assert abs(tau_1deg - (0.09 + 1.0) / 0.09) < 1.5


def test_vendor_pitch_variance_forgets() -> None:
    """A vendor that was off by 2 deg and then agrees: after three memories the estimate has
    fallen below 0.5 deg (weights exp(-3) ~ 5 %: sqrt(0.05 x 4) = 0.45 deg)."""
    est = VendorPitchVariance(memory_s=10.0)
    for k in range(300):
        est.add(0.1 * k, np.radians(2.0), 0.0)
    assert abs(est.sigma_deg - 2.0) < 1e-9
    for k in range(300, 600):
        est.add(0.1 * k, 0.0, 0.0)
    assert est.sigma_deg < 0.5


def test_vendor_pitch_variance_refuses_bad_input() -> None:
    with pytest.raises(ValueError, match="memory_s"):
        VendorPitchVariance(memory_s=0.0)
    est = VendorPitchVariance(memory_s=10.0)
    est.add(1.0, 0.01, 0.0)
    with pytest.raises(EstimationError, match="older"):
        est.add(0.5, 0.01, 0.0)
    est.add(2.0, float("nan"), 0.0)  # not finite: not taken
    assert est.n == 1
    for bad in (0.0, -1.0, float("inf"), "fixed"):
        with pytest.raises(ValidationError):
            AttitudeConfig(vendor_pitch_sigma_deg=bad)
    with pytest.raises(ValidationError):
        AttitudeConfig(vendor_sigma_memory_s=0.0)


def test_pitch_disagreement_is_the_vendor_pitch_relative_to_the_tracked() -> None:
    """The shank-y rotation between the tracked attitude and the vendor's, with the shank
    pitched 60 deg (the lateral axis is the pitch axis at any pitch)."""
    R = rot_y(np.radians(60.0))
    q = quat_wxyz_from_matrix(rot_y(np.radians(61.5)))
    d = pitch_disagreement_rad(tuple(R.ravel().tolist()), q)
    assert abs(np.degrees(d) - 1.5) < 1e-9
