"""``filter.imu_faults.saturation_axis_distrust_single``: the filter puts a clipped sample's
extra variance on its railed axis only while the stretch has railed that one axis, so that
vision's view of the other ground axis fixes the stretch's share on it; a stretch that rails
two axes keeps the isotropic variance, and nothing changes without a clipped sample."""

from __future__ import annotations

import numpy as np
import pytest

from vio_graph.filter.config import FilterConfig, ImuFaultConfig
from vio_graph.filter.eskf import SagittalEskf
from vio_graph.filter.imu_faults import ImuFaultMonitor, railed_axis
from vio_graph.geometry import GRAVITY_MPS2, quat_wxyz_from_matrix, rot_y
from vio_graph.types import ImuSample

H = 0.01  # 100 Hz
RANGE = 40.0  # m/s^2
PUSH_MPS2 = 80.0  # along the shank's own axis, 50 ms: a 4 m/s velocity change
PUSH_S = (0.10, 0.15)


def _push(pitch_rad: float, push_axes: tuple[float, float], clip: bool) -> list[ImuSample]:
    """A shank held at ``pitch_rad`` (no rotation), still for 0.1 s, then pushed by
    PUSH_MPS2 along ``push_axes`` (weights on its x and z axes) for 50 ms; the accelerometer
    clips at RANGE when ``clip`` and the fault monitor marks it (its prior puts back a guess
    of the excess, not the truth)."""
    R = rot_y(pitch_rad)
    q = quat_wxyz_from_matrix(R)
    mon = ImuFaultMonitor(ImuFaultConfig(), accel_range_mps2=RANGE, gyro_range_radps=35.0)
    wx, wz = push_axes
    out = []
    for k in range(61):
        t = k * H
        on = PUSH_S[0] <= t < PUSH_S[1] - 1e-9
        f = R.T @ np.array([0.0, 0.0, GRAVITY_MPS2])
        if on:
            f = f + PUSH_MPS2 * np.array([wx, 0.0, wz])
        if clip:
            f = np.clip(f, -RANGE, RANGE)
        out.append(mon.process(ImuSample(t, f, np.zeros(3), q)))
    return out


def _true_velocity_xz(pitch_rad: float, push_axes: tuple[float, float], t: float) -> np.ndarray:
    R = rot_y(pitch_rad)
    tau = float(np.clip(t - PUSH_S[0], 0.0, PUSH_S[1] - PUSH_S[0]))
    v = R @ (PUSH_MPS2 * tau * np.array([push_axes[0], 0.0, push_axes[1]]))
    return v[[0, 2]]


def _filter(single: bool, pitch_rad: float, push_axes=(0.0, 1.0), clip=True) -> SagittalEskf:
    """The filter over :func:`_push`, started at rest with the truth, with a velocity
    observation every 0.1 s that measures z to 1 cm/s and says nothing of x (1 m/s), as the
    frames over a level floor do."""
    cfg = FilterConfig(imu_faults=ImuFaultConfig(saturation_axis_distrust_single=single))
    f = SagittalEskf(cfg)
    P0 = np.diag([1e-6, 1e-6, 1e-6, 1e-6, 1e-6, 1e-6, 1e-8, 1e-8])
    f.initialise(0.0, (0.0, 0.0), gravity_xz=(0.0, -GRAVITY_MPS2), P0=P0)
    for s in _push(pitch_rad, push_axes, clip):
        f.propagate(s)
        t = float(s.timestamp_s)
        if k_obs(t):
            v = _true_velocity_xz(pitch_rad, push_axes, t)
            f.update_velocity(v, np.diag([1.0, 1e-4]), gate=False)
    return f


def k_obs(t: float) -> bool:
    return abs(t / 0.1 - round(t / 0.1)) < 1e-6 and t > 0.0


@pytest.mark.parametrize("pitch_deg", [30.0, -45.0])
def test_a_single_axis_stretch_lets_vision_z_fix_the_x_share(pitch_deg: float) -> None:
    """A push along the shank's z axis (pitched 30-45 deg) clips z for 5 samples and loses
    most of 4 m/s; the prior puts back a guess. With the variance on the railed axis only,
    the z observations fix the loss along the known direction and with it x (to 2 cm/s at
    0.6 s); with the isotropic variance x keeps the prior's error (tenths of a m/s)."""
    pitch = np.deg2rad(pitch_deg)
    truth = _true_velocity_xz(pitch, (0.0, 1.0), 0.6)
    err_single = _filter(True, pitch).state.v_xz_mps[0] - truth[0]
    err_iso = _filter(False, pitch).state.v_xz_mps[0] - truth[0]
    assert abs(err_single) < 0.02
    assert abs(err_iso) > 0.2


def test_a_two_axis_stretch_and_a_clean_stream_are_unchanged() -> None:
    """A push on both axes rails x and z: the option leaves the filter's state and
    covariance exactly as without it; so does a push within the range."""
    pitch = np.deg2rad(30.0)
    for axes, clip in (((0.7, 0.7), True), ((0.0, 0.3), False)):
        on = _filter(True, pitch, axes, clip).state
        off = _filter(False, pitch, axes, clip).state
        np.testing.assert_array_equal(on.P, off.P)
        np.testing.assert_array_equal(on.v_xz_mps, off.v_xz_mps)


def test_railed_axis_is_the_single_railed_axis_or_none() -> None:
    R = rot_y(0.3)
    one = R @ np.diag([0.0, 0.0, 4.0]) @ R.T
    np.testing.assert_allclose(abs(railed_axis(one) @ R[:, 2]), 1.0, atol=1e-12)
    assert railed_axis(np.diag([4.0, 0.0, 1.0])) is None
    assert railed_axis(np.zeros((3, 3))) is None
    s = _push(0.3, (0.0, 1.0), True)[11]  # inside the clipped z push
    assert s.accel_extra_cov_m2ps4 is not None
    np.testing.assert_allclose(abs(railed_axis(s.accel_extra_cov_m2ps4)[2]), 1.0, atol=1e-12)
