"""Leg-chain velocity bridge across a saturated accelerometer stretch (filter/leg_bridge.py)."""

from __future__ import annotations

import gtsam
import numpy as np
import pytest
from gtsam.symbol_shorthand import V

from vio_graph.filter.config import FilterConfig, ImuFaultConfig
from vio_graph.filter.eskf import SagittalEskf
from vio_graph.filter.imu_faults import ImuFaultMonitor
from vio_graph.filter.leg_bridge import (
    LegChainBridge,
    chain_velocity_discretisation_xz,
    chain_velocity_second_difference_xz,
    chain_velocity_xz,
)
from vio_graph.geometry import GRAVITY_MPS2, rotate_xz
from vio_graph.smoother.config import FactorFamilies, SmootherConfig
from vio_graph.smoother.graph import KeyframeGraphBuilder
from vio_graph.smoother.synthetic import make_swinging_shank_trial
from vio_graph.types import ImuSample, JointAngles, VelocityObservation

THIGH_M = 0.43
CAM_IN_SHANK = np.array([0.07, -0.05])
RATE_HZ = 100.0


def _angles(t):
    """A push-off-like swing: hip flexion and knee flexion (rad) as smooth functions of t."""
    thigh = 0.2 + 0.5 * np.sin(2.0 * t)
    knee = 0.3 + 0.9 * np.sin(3.0 * t + 0.4)
    return thigh, knee


def _joints(t0: float, t1: float) -> list[JointAngles]:
    ts = np.arange(round(t0 * RATE_HZ), round(t1 * RATE_HZ) + 1) / RATE_HZ
    return [JointAngles(float(t), *map(float, _angles(t)), 0.0) for t in ts]


def _camera_rel_hip(t):
    thigh, knee = _angles(t)
    return rotate_xz(-thigh, np.array([0.0, -THIGH_M])) + rotate_xz(knee - thigh, CAM_IN_SHANK)


def _true_rel_velocity(t: float) -> np.ndarray:
    h = 1e-6
    return (_camera_rel_hip(t + h) - _camera_rel_hip(t - h)) / (2 * h)


def test_chain_velocity_is_the_derivative_of_the_chain() -> None:
    joints = _joints(0.0, 1.0)
    for t in (0.2, 0.505, 0.8):
        v = chain_velocity_xz(joints, t, THIGH_M, CAM_IN_SHANK)
        assert v is not None
        # central difference over 10 ms of angles changing at up to 2.7 rad/s
        np.testing.assert_allclose(v, _true_rel_velocity(t), atol=5e-3)
    # not covered by a joint sample a period after t: no answer yet
    assert chain_velocity_xz(joints, 0.995, THIGH_M, CAM_IN_SHANK) is None


def test_bridge_restores_the_velocity_a_clipped_stretch_lost() -> None:
    """The hip moves at a constant 1.0 m/s; the filter tracks the camera exactly until a
    5-sample stretch clips 1.5 m/s of x velocity away. The bridge's observation after the
    stretch is the true camera velocity (to the central difference), with the covariance
    of the filter before the stretch plus the hip and rate terms."""
    v_hip = np.array([1.0, 0.0])
    bridge = LegChainBridge(THIGH_M, CAM_IN_SHANK, hip_accel_sigma_mps2=3.0, rate_sigma_mps=0.1)
    joints = _joints(0.0, 1.0)
    P0 = np.eye(2) * 0.02**2
    lost = np.zeros(2)
    corrections = np.zeros(2)
    ts = np.arange(40, 52) / RATE_HZ  # samples 0.40 .. 0.51 s
    clipped = {0.43, 0.44, 0.45, 0.46, 0.47}
    obs = None
    for t in ts:
        sat = round(t, 2) in clipped
        if sat:
            # the filter's velocity before propagating with the sample
            bridge.before_saturated(t - 0.01, v_hip + _true_rel_velocity(t - 0.01) + lost, P0)
            lost = lost + np.array([-0.3, 0.0])
            continue
        assert not sat
        v_filter = v_hip + _true_rel_velocity(t) + lost
        if bridge.active:
            bridge.after_trusted(t, v_filter, corrections)
            obs = bridge.observation(joints, v_filter, corrections) or obs
    assert obs is not None and bridge.n_observations == 1
    assert obs.timestamp_s == pytest.approx(0.48)
    np.testing.assert_allclose(obs.velocity_xz_mps, v_hip + _true_rel_velocity(0.48), atol=0.01)
    # window: the last trusted sample before (0.42 s) to the first after (0.48 s)
    expected_var = 0.02**2 + (3.0 * 0.06) ** 2 + 0.1**2
    np.testing.assert_allclose(obs.cov, np.eye(2) * expected_var, atol=1e-12)
    # the same as a change from the velocity before the stretch (0.42 s), without the
    # filter's own covariance there
    true_change = _true_rel_velocity(0.48) - _true_rel_velocity(0.42)
    np.testing.assert_allclose(obs.change_xz_mps, true_change, atol=0.01)
    np.testing.assert_allclose(obs.change_cov, np.eye(2) * (expected_var - 0.02**2), atol=1e-12)


def test_bridge_does_nothing_without_saturation() -> None:
    bridge = LegChainBridge(THIGH_M, CAM_IN_SHANK, 3.0, 0.1)
    joints = _joints(0.0, 1.0)
    assert not bridge.active
    assert bridge.observation(joints, np.zeros(2), np.zeros(2)) is None
    assert bridge.n_stretches == 0


def test_bridge_without_joints_gives_up() -> None:
    bridge = LegChainBridge(THIGH_M, CAM_IN_SHANK, 3.0, 0.1, max_wait_s=0.1)
    bridge.before_saturated(0.40, np.zeros(2), np.eye(2))
    for k in range(41, 60):
        bridge.after_trusted(k / RATE_HZ, np.zeros(2), np.zeros(2))
        assert bridge.observation([], np.zeros(2), np.zeros(2)) is None
    assert not bridge.active and bridge.n_unbridged == 1


def test_smoothers_put_the_bridge_velocity_on_the_keyframe() -> None:
    """A keyframe carrying the bridge's camera velocity gets one prior on its IMU velocity,
    v_cam - omega x (R p_cam) with the gyro at the keyframe time; switched off by
    ``smoother.factors.saturation_bridge``."""
    T = np.eye(4)
    T[:3, 3] = [0.02, 0.0, 0.05]  # camera in IMU axes, m
    v_cam = np.array([2.4, 1.1])
    counts = {}
    for on in (True, False):
        cfg = SmootherConfig(factors=FactorFamilies(saturation_bridge=on))
        b = KeyframeGraphBuilder(cfg, T)
        q = np.array([1.0, 0.0, 0.0, 0.0])
        for k in range(12):
            gyro = np.array([0.0, 3.0, 0.0])
            b.add_imu(ImuSample(0.01 * k, np.array([0.0, 0.0, 9.81]), gyro, q))
        est = make_swinging_shank_trial(0.2).filter_estimates[0]
        assert b.add_frame(0.05, True, est, None, None, np.eye(3))
        ob = VelocityObservation(0.1, v_cam, np.eye(2) * 0.2**2)
        ups = b.add_frame(0.1, True, est, None, [ob], np.eye(3))
        g = ups[0].factors
        priors = [
            g.at(k).prior()
            for k in range(g.size())
            if isinstance(g.at(k), gtsam.PriorFactorVector)
            and g.at(k).keys()[0] == V(1)
            and np.linalg.norm(g.at(k).prior()) > 0
        ]
        counts[on] = len(priors)
        if on:
            expected = np.r_[v_cam[0], 0.0, v_cam[1]] - np.cross([0.0, 3.0, 0.0], T[:3, 3])
            np.testing.assert_allclose(priors[0], expected, atol=1e-9)
    assert counts == {True: 1, False: 0}


def _two_bridged_stretches(relative: bool) -> tuple[list[float], float, float]:
    """A level IMU (z up) whose filter starts at rest while the truth moves at 0.1 m/s
    (sigma 0.1 m/s: the velocity error is correlated with the position it drifts). Two
    3-sample pulses (+-60/70/60 m/s^2 against a 40 m/s^2 range, 0.7 m/s each) are clipped;
    after each the chain observes the true velocity change to 0.05 m/s, then a still foot
    gives the true velocity (three observations, 0.02 m/s). Returns the filter's x velocity
    error after each bridge and its x velocity and position errors after the stance."""
    h, rng_ = 0.01, 40.0
    mon = ImuFaultMonitor(ImuFaultConfig(), accel_range_mps2=rng_, gyro_range_radps=35.0)
    f = SagittalEskf(FilterConfig(integration="zoh", init_velocity_sigma_mps=0.1))
    f.initialise(0.0, (0.0, 0.0))
    q = np.array([1.0, 0.0, 0.0, 0.0])
    push = [60.0, 70.0, 60.0]
    profile = [0.0] * 10 + push + [0.0] * 20 + [-a for a in push] + [0.0] * 20
    stretch_end = {10: 12, 33: 35}  # first clipped sample -> last
    true_x, true_v, t = 0.0, 0.1, 0.0
    end, v_start, P_start, true_v0 = -1, np.zeros(2), np.eye(2), 0.0
    after_bridge = []
    cov = np.eye(2) * 0.05**2
    for k, a_true in enumerate(profile):
        if k in stretch_end:
            _, _, v_start = f.position_velocity()
            P_start, true_v0, end = f.cov_velocity_m2ps2(), true_v, stretch_end[k] + 1
            if relative:
                f.clone_velocity()
        t += h
        true_x += true_v * h + 0.5 * a_true * h**2
        true_v += a_true * h
        f.propagate(
            mon.process(
                ImuSample(t, np.array([np.clip(a_true, -rng_, rng_), 0.0, GRAVITY_MPS2]),
                          np.zeros(3), q)
            )
        )  # fmt: skip
        if k == end:  # the first trusted sample after the stretch closes it
            change = np.array([true_v - true_v0, 0.0])
            if relative:
                assert f.update_velocity_change(change, cov)
                assert not f.has_velocity_clone
            else:
                assert f.update_velocity(v_start + change, P_start + cov)
            after_bridge.append(float(f.position_velocity()[2][0] - true_v))
    for _ in range(3):
        f.update_velocity((true_v, 0.0), np.eye(2) * 0.02**2)
    _, p, v = f.position_velocity()
    return after_bridge, float(v[0] - true_v), float(p[0] - true_x)


def test_relative_bridge_keeps_the_velocity_error_from_before_the_stretch() -> None:
    """The chain measures the change across a stretch, not the velocity before it. As a
    change against a copy of the filter's velocity (``saturation_bridge_relative``) the
    clip's loss is restored and the filter's earlier error (-0.1 m/s) is left as it was,
    still correlated with the position it drifted: the stance then takes the position back
    to about a centimetre. As a velocity with the filter's own covariance at the start, the
    filter's estimate counts twice: each bridge pulls the velocity by a fraction of the
    clip's loss and shrinks the variance, the stance's correction stays in the velocity,
    and 4 cm of the 6 cm drift remain."""
    after, v_err, p_err = _two_bridged_stretches(relative=True)
    np.testing.assert_allclose(after, [-0.1, -0.1], atol=0.005)
    assert abs(v_err) < 0.002 and abs(p_err) < 0.015
    after, v_err, p_err = _two_bridged_stretches(relative=False)
    assert abs(v_err) < 0.002 and p_err < -0.035


def test_smoothers_put_the_bridge_change_between_the_keyframes() -> None:
    """With the change (``smoother.factors.saturation_bridge_relative``) the bridge becomes
    one factor V(i) - V(k) between the keyframe before the stretch (k = 1) and the one after
    it (i = 2): the camera's velocity change moved to the IMU with the gyro at each keyframe,
    change - omega_i x (R p) + omega_k x (R p), with the chain's covariance alone; no prior
    on V(i). Without the flag, or without a keyframe at ``since_timestamp_s``, the prior."""
    T = np.eye(4)
    T[:3, 3] = [0.02, 0.0, 0.05]  # camera in IMU axes, m
    change = np.array([-1.3, 0.6])
    change_cov = np.diag([0.05**2, 0.07**2])
    q = np.array([1.0, 0.0, 0.0, 0.0])
    est = make_swinging_shank_trial(0.2).filter_estimates[0]

    def gyro(t: float) -> np.ndarray:  # pitch rate 1.85 rad/s at k, 4.85 at i
        return np.array([0.0, 30.0 * t - 1.0, 0.0])

    def built(relative: bool, since: float) -> gtsam.NonlinearFactorGraph:
        cfg = SmootherConfig(factors=FactorFamilies(saturation_bridge_relative=relative))
        b = KeyframeGraphBuilder(cfg, T)
        ups = []
        for k in range(31):
            t = 0.01 * k
            ups += b.add_imu(ImuSample(t, np.array([0.0, 0.0, 9.81]), gyro(t), q))
            if k in (4, 9, 19):  # frames at 0.045, 0.095 and 0.195 s, all keyframes
                ob = VelocityObservation(
                    0.2, np.array([2.4, 1.1]), np.eye(2) * 0.2**2, since, change, change_cov
                )
                obs = [ob] if k == 19 else None
                ups += b.add_frame(t + 0.005, True, est, None, obs, np.eye(3))
        assert [u.index for u in ups] == [0, 1, 2]
        return ups[2].factors

    g = built(True, 0.095)
    between = [g.at(n) for n in range(g.size()) if isinstance(g.at(n), gtsam.BetweenFactorVector)]
    assert len(between) == 1
    assert list(between[0].keys()) == [V(1), V(2)]
    p = T[:3, 3]
    lever = np.cross(gyro(0.195), p) - np.cross(gyro(0.095), p)  # i's minus k's
    expected = np.r_[change[0], 0.0, change[1]] - lever
    np.testing.assert_allclose(between[0].measured(), expected, atol=1e-9)
    cov = np.linalg.inv(between[0].noiseModel().information())
    np.testing.assert_allclose(cov[np.ix_([0, 2], [0, 2])], change_cov, atol=1e-12)
    assert not any(
        isinstance(g.at(n), gtsam.PriorFactorVector)
        and g.at(n).keys()[0] == V(2)
        and np.linalg.norm(g.at(n).prior()) > 0
        for n in range(g.size())
    )
    for relative, since in ((False, 0.095), (True, 0.155)):  # off; no keyframe at 0.155 s
        g = built(relative, since)
        assert not any(isinstance(g.at(n), gtsam.BetweenFactorVector) for n in range(g.size()))
        priors = [
            g.at(n)
            for n in range(g.size())
            if isinstance(g.at(n), gtsam.PriorFactorVector)
            and g.at(n).keys()[0] == V(2)
            and np.linalg.norm(g.at(n).prior()) > 0
        ]
        assert len(priors) == 1


def test_smoothers_change_starts_at_a_keyframe_before_the_first_clipped_sample() -> None:
    """The change handed to the smoothers starts at the last keyframe at or before the
    filter's time at the stretch's start (one inside the first clipped sample's interval is
    skipped: the change from it is not measured), with the filter's IMU change from it (its
    velocity change minus its corrections); none with a clipped sample since that keyframe."""
    from collections import deque
    from types import SimpleNamespace

    from vio_graph.estimator import OnlineEstimator

    est = SimpleNamespace(
        _bridge_kfs=deque(
            [
                (0.95, 0.94, np.array([1.0, 0.0]), np.array([0.1, 0.0])),
                (1.05, 1.04, np.array([1.2, 0.1]), np.array([0.3, 0.0])),
            ]
        ),
        _last_saturated_s=0.5,
        filter=SimpleNamespace(velocity_corrections_mps=np.array([0.4, 0.0])),
    )
    rule = OnlineEstimator._change_since_keyframe
    # keyframe 1.05 s lies after the filter's 1.04 s: the change starts at 0.95 s
    t_k, change = rule(est, 1.04, np.array([1.6, 0.2]))
    assert t_k == 0.95
    np.testing.assert_allclose(change, [1.6 - 1.0 - 0.3, 0.2])
    t_k, change = rule(est, 1.06, np.array([1.6, 0.2]))
    assert t_k == 1.05
    np.testing.assert_allclose(change, [1.6 - 1.2 - 0.1, 0.1])
    est._last_saturated_s = 1.0  # a clipped sample after the 0.95 s keyframe's filter time
    assert rule(est, 1.04, np.array([1.6, 0.2])) is None
    assert rule(est, 0.90, np.array([1.6, 0.2])) is None  # no keyframe before


# A push-off the joints' 100 Hz does not resolve: the shank's angular acceleration steps
# from 0 to 600 rad/s^2 at 0.45 s (a joint sample) and back to 0 at 0.48 s; the thigh is still.
KINK_T0, KINK_T2, KINK_ALPHA = 0.45, 0.48, 600.0
THIGH_RAD = 0.2


def _kink_shank(t: float) -> float:
    """The shank segment pitch (rad) at t: 2 rad/s, plus the pulse's angle."""
    s = min(max(t - KINK_T0, 0.0), KINK_T2 - KINK_T0)
    return -0.3 + 2.0 * t + 0.5 * KINK_ALPHA * s**2 + KINK_ALPHA * s * max(t - KINK_T2, 0.0)


def _kink_joints() -> list[JointAngles]:
    ts = np.arange(30, 61) / RATE_HZ
    # knee = shank pitch + thigh pitch (chain_velocity_xz's sign convention)
    return [JointAngles(float(t), THIGH_RAD, _kink_shank(t) + THIGH_RAD, 0.0) for t in ts]


def _kink_true_velocity(t: float) -> np.ndarray:
    """The camera's velocity relative to the hip (m/s), exact: the shank's pitch rate
    (right-sided at a kink) times the derivative of the rotated camera offset."""
    s = min(max(t - KINK_T0, 0.0), KINK_T2 - KINK_T0)
    rate = 2.0 + KINK_ALPHA * s
    th = _kink_shank(t)
    return rate * np.array(
        [-np.sin(th) * CAM_IN_SHANK[0] + np.cos(th) * CAM_IN_SHANK[1],
         -np.cos(th) * CAM_IN_SHANK[0] - np.sin(th) * CAM_IN_SHANK[1]]
    )  # fmt: skip


def test_chain_discretisation_sigma_is_the_central_difference_error() -> None:
    """At an acceleration step the central difference is the mean of the velocity over
    [t-h, t+h], off by a h/4, and half the second difference of the chain velocity is a
    h/4 too: the estimate is the error, to the rotation's curvature (which it adds). On
    the smooth swing (angles at up to 2.7 rad/s) it is a few mm/s, at least the error."""
    joints = _kink_joints()
    for t in (KINK_T0, KINK_T2):
        d = chain_velocity_discretisation_xz(joints, t, THIGH_M, CAM_IN_SHANK)
        v = chain_velocity_xz(joints, t, THIGH_M, CAM_IN_SHANK)
        assert d is not None and v is not None
        err = np.abs(v - _kink_true_velocity(t))
        # a h/4 in norm: 0.086 m x 600 rad/s^2 x 10 ms / 4 = 0.13 m/s
        assert 0.10 < np.linalg.norm(err) < 0.16
        # at least the error on each axis, and the same size (the rest is the pitch rate
        # turning the offset's derivative: the pulse's centripetal change)
        assert np.all(d >= err) and d < 1.5 * np.linalg.norm(err)
    smooth = _joints(0.0, 1.0)
    for t in (0.2, 0.505, 0.8):
        d = chain_velocity_discretisation_xz(smooth, t, THIGH_M, CAM_IN_SHANK)
        v = chain_velocity_xz(smooth, t, THIGH_M, CAM_IN_SHANK)
        assert d is not None and v is not None
        assert d < 0.005 and np.all(d + 1e-4 >= np.abs(v - _true_rel_velocity(t)))
    # two periods needed on each side
    assert chain_velocity_discretisation_xz(joints, 0.59, THIGH_M, CAM_IN_SHANK) is None
    assert chain_velocity_xz(joints, 0.59, THIGH_M, CAM_IN_SHANK) is not None


def _kink_bridge(discretisation: bool, fourth_order: bool = False):
    """The pulse clipped from 0.45 to 0.48 s, the filter's velocity exact before it."""
    bridge = LegChainBridge(
        THIGH_M,
        CAM_IN_SHANK,
        1.0,
        0.02,
        discretisation_sigma=discretisation,
        fourth_order=fourth_order,
    )
    joints = _kink_joints()
    bridge.before_saturated(KINK_T0, _kink_true_velocity(KINK_T0), np.eye(2) * 1e-4)
    obs = None
    for k in range(48, 60):
        t = k / RATE_HZ
        v = _kink_true_velocity(t)
        bridge.after_trusted(t, v, np.zeros(2))
        obs = obs or bridge.observation([j for j in joints if j.timestamp_s <= t], v, np.zeros(2))
    assert obs is not None
    return obs


def test_bridge_sigma_holds_the_discretisation_of_an_unresolved_push_off() -> None:
    """The chain's change over the pulse is short by about a h/2 (0.2-0.3 m/s: the two ends'
    central differences each average the step). With the hip's and encoders' terms alone
    (0.04 m/s per axis here) that miss is 3-7 sigma: a filter's chi-square gate refuses the
    bridge or, passed, it is taken as if exact. With the discretisation sigma it is within
    1.5 sigma per axis; the observation waits one joint period longer (0.5 s vs 0.49 s)."""
    off, on = _kink_bridge(False), _kink_bridge(True)

    def miss_of(obs):  # against the true change from the stretch's start to the observation
        return obs.change_xz_mps - (
            _kink_true_velocity(obs.timestamp_s) - _kink_true_velocity(KINK_T0)
        )

    miss = miss_of(on)
    np.testing.assert_allclose(miss, miss_of(off), atol=1e-9)  # the same chain change
    assert 0.15 < np.linalg.norm(miss) < 0.35
    z_off = np.abs(miss) / np.sqrt(np.diag(off.change_cov))
    z_on = np.abs(miss) / np.sqrt(np.diag(on.change_cov))
    assert z_off.max() > 3.0 and np.all(z_on < 1.5)
    # the added variance is the two ends' estimates, per axis
    added = np.diag(on.change_cov - off.change_cov)
    joints = _kink_joints()
    d0 = chain_velocity_discretisation_xz(joints, KINK_T0, THIGH_M, CAM_IN_SHANK)
    d2 = chain_velocity_discretisation_xz(joints, KINK_T2, THIGH_M, CAM_IN_SHANK)
    assert d0 is not None and d2 is not None
    np.testing.assert_allclose(added, [d0**2 + d2**2] * 2, rtol=1e-12)
    assert on.change_cov[0, 1] == off.change_cov[0, 1] == 0.0
    assert off.timestamp_s == pytest.approx(0.49) and on.timestamp_s == pytest.approx(0.50)


def test_five_point_chain_velocity_takes_out_the_smooth_part_of_the_error() -> None:
    """``fourth_order``: the chain velocity at the ends is D - D''/6, the five-point
    derivative. On the smooth swing its error is under 0.1 mm/s (the central difference's
    is up to a few mm/s). At the pulse's steps the error left is a h/6 instead of a h/4
    (the change misses by two thirds of what it did), and the sigma is a third of the
    second difference instead of half, still covering the miss."""
    smooth = _joints(0.0, 1.0)
    for t in (0.2, 0.505, 0.8):
        d = chain_velocity_second_difference_xz(smooth, t, THIGH_M, CAM_IN_SHANK)
        v = chain_velocity_xz(smooth, t, THIGH_M, CAM_IN_SHANK)
        assert d is not None and v is not None
        assert np.abs(v - d / 6.0 - _true_rel_velocity(t)).max() < 1e-4
    central, five = _kink_bridge(True), _kink_bridge(True, fourth_order=True)

    def miss_of(obs):
        return obs.change_xz_mps - (
            _kink_true_velocity(obs.timestamp_s) - _kink_true_velocity(KINK_T0)
        )

    ratio = np.linalg.norm(miss_of(five)) / np.linalg.norm(miss_of(central))
    assert 0.55 < ratio < 0.8
    assert np.all(np.abs(miss_of(five)) / np.sqrt(np.diag(five.change_cov)) < 1.5)
    base = (1.0 * (KINK_T2 - KINK_T0)) ** 2 + 0.02**2  # the hip's and encoders' terms
    np.testing.assert_allclose(
        (np.diag(five.change_cov) - base) / (np.diag(central.change_cov) - base),
        (1 / 3) ** 2 / (1 / 2) ** 2,
        rtol=1e-9,
    )


def test_smoothers_bridge_noise_holds_the_chain_discretisation() -> None:
    """``smoother.factors.saturation_bridge_discretisation``: the smoothers' bridge noise
    gets the term the filter's ``discretisation_sigma`` would add (the pulse's unresolved
    ends, a h/4 each), computed from the stretch's ends the observation names, while the
    filter's own observation is left as it was. On the unresolved pulse the change misses
    by 3-7 of its stated sigmas without the term and by under 1.5 with it; the joints must
    cover each end by two periods; a bridge whose noise already holds it adds nothing.
    The graph's prior on V(i) then has the observation's covariance plus that term in x-z
    (option on), or the observation's alone (off)."""
    bridge = LegChainBridge(THIGH_M, CAM_IN_SHANK, 1.0, 0.02)
    joints = _kink_joints()
    bridge.before_saturated(KINK_T0, _kink_true_velocity(KINK_T0), np.eye(2) * 1e-4)
    obs = None
    for k in range(48, 60):
        t = k / RATE_HZ
        bridge.after_trusted(t, _kink_true_velocity(t), np.zeros(2))
        obs = obs or bridge.observation([j for j in joints if j.timestamp_s <= t],
                                        _kink_true_velocity(t), np.zeros(2))  # fmt: skip
    assert obs is not None and obs.stretch_s == pytest.approx((KINK_T0, KINK_T2))
    disc = bridge.discretisation_cov(joints, *obs.stretch_s)
    assert disc is not None
    np.testing.assert_allclose(disc, _kink_bridge(True).change_cov - obs.change_cov, atol=1e-12)
    miss = obs.change_xz_mps - (_kink_true_velocity(obs.timestamp_s) - _kink_true_velocity(KINK_T0))
    assert (np.abs(miss) / np.sqrt(np.diag(obs.change_cov))).max() > 3.0
    assert np.all(np.abs(miss) / np.sqrt(np.diag(obs.change_cov + disc)) < 1.5)
    # the joints up to one period after the end do not give the end's second difference
    early = [j for j in joints if j.timestamp_s <= KINK_T2 + 1.5 / RATE_HZ]
    assert bridge.discretisation_cov(early, *obs.stretch_s) is None
    already = LegChainBridge(THIGH_M, CAM_IN_SHANK, 1.0, 0.02, discretisation_sigma=True)
    assert np.all(already.discretisation_cov(joints, *obs.stretch_s) == 0.0)

    T = np.eye(4)
    T[:3, 3] = [0.02, 0.0, 0.05]
    q = np.array([1.0, 0.0, 0.0, 0.0])
    est = make_swinging_shank_trial(0.2).filter_estimates[0]
    cov = np.array([[0.15**2, 0.001], [0.001, 0.12**2]])
    extra = np.eye(2) * 0.5**2
    for on in (True, False):
        cfg = SmootherConfig(factors=FactorFamilies(saturation_bridge_discretisation=on))
        b = KeyframeGraphBuilder(cfg, T)
        for k in range(12):
            b.add_imu(ImuSample(0.01 * k, np.array([0.0, 0.0, 9.81]), np.zeros(3), q))
        assert b.add_frame(0.05, True, est, None, None, np.eye(3))
        ob = VelocityObservation(0.1, np.array([2.4, 1.1]), cov, discretisation_cov=extra)
        g = b.add_frame(0.1, True, est, None, [ob], np.eye(3))[0].factors
        (prior,) = [
            g.at(k)
            for k in range(g.size())
            if isinstance(g.at(k), gtsam.PriorFactorVector)
            and g.at(k).keys()[0] == V(1)
            and np.linalg.norm(g.at(k).prior()) > 0
        ]
        C = prior.noiseModel().covariance()
        np.testing.assert_allclose(C[np.ix_([0, 2], [0, 2])], cov + extra if on else cov,
                                   atol=1e-12)  # fmt: skip
        assert C[1, 1] == pytest.approx(1.0)
