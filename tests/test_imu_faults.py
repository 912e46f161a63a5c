"""IMU faults (vio_graph/filter/imu_faults.py): saturation marks, gyro repair from the vendor
orientation, vision arbitration of gate refusals, and what the smoothers make of them."""

from __future__ import annotations

import dataclasses

import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from vio_graph.filter.config import FilterConfig, ImuFaultConfig
from vio_graph.filter.eskf import SagittalEskf
from vio_graph.filter.imu_faults import ImuFaultMonitor, velocity_fault_cov
from vio_graph.filter.imu_repair import (
    NextSampleRepair,
    interpolated_axes_cov,
    keep_consistent_axes,
)
from vio_graph.geometry import GRAVITY_MPS2, matrix_from_quat_wxyz, quat_wxyz_from_matrix, rot_y
from vio_graph.smoother.config import SmootherConfig
from vio_graph.smoother.graph import KeyframeGraphBuilder, distrust_variances
from vio_graph.types import Displacement2D, ImuSample

RATE_HZ = 100.0
H = 1.0 / RATE_HZ


def _pitching(n: int, rate_fn) -> list[ImuSample]:
    """A shank pitching at rate_fn(t) (rad/s about y): vendor orientation = the true attitude,
    gyro = the true rate, specific force = gravity seen in the IMU frame."""
    out, theta = [], 0.0
    for k in range(n):
        t = k * H
        if k:
            theta += 0.5 * (rate_fn(t - H) + rate_fn(t)) * H
        R = rot_y(theta)
        f = R.T @ np.array([0.0, 0.0, GRAVITY_MPS2])
        out.append(ImuSample(t, f, np.array([0.0, rate_fn(t), 0.0]), quat_wxyz_from_matrix(R)))
    return out


def test_saturated_axis_is_marked_moved_beyond_the_rail_and_distrusted() -> None:
    mon = ImuFaultMonitor(ImuFaultConfig(), accel_range_mps2=40.0, gyro_range_radps=35.0)
    q = np.array([1.0, 0.0, 0.0, 0.0])
    ok = mon.process(ImuSample(0.0, np.array([1.0, 0.0, 9.8]), np.zeros(3), q))
    assert ok.accel_extra_sigma_mps2 == 0.0
    s = mon.process(ImuSample(0.01, np.array([-40.0, 0.0, 9.8]), np.zeros(3), q))
    # half-normal prior of sigma 0.5 x range on the hidden excess: mean 20 sqrt(2/pi) beyond
    # the rail, sigma 20 sqrt(1 - 2/pi); the unsaturated axes are untouched
    assert s.accel_mps2[0] == pytest.approx(-40.0 - 20.0 * np.sqrt(2 / np.pi))
    assert s.accel_mps2[2] == 9.8
    sd = 20.0 * np.sqrt(1 - 2 / np.pi)
    assert s.accel_extra_sigma_mps2 == pytest.approx(sd)
    # the stretch goes on: its samples are one pulse, the k-th carries sqrt(2k - 1) sigma, so
    # the variance of n samples is n^2 sigma^2 (not n sigma^2)
    more = [mon.process(ImuSample(0.01 * k, np.array([-45.0, 0.0, 9.8]), np.zeros(3), q))
            for k in (2, 3)]  # fmt: skip
    var = sum(x.accel_extra_sigma_mps2**2 for x in [s, *more])
    assert var == pytest.approx(9 * sd**2)
    assert mon.report()["accel_saturated_samples"] == 3
    # a trusted sample ends the stretch: the next clipped one starts a new one
    assert mon.process(ImuSample(0.04, np.array([1.0, 0.0, 9.8]), np.zeros(3), q)) is not None
    again = mon.process(ImuSample(0.05, np.array([40.0, 0.0, 9.8]), np.zeros(3), q))
    assert again.accel_extra_sigma_mps2 == pytest.approx(sd)
    indep = ImuFaultMonitor(
        ImuFaultConfig(saturation_correlated=False, saturation_sigma_range=1.0), 40.0, 35.0
    )
    outs = [indep.process(ImuSample(0.01 * k, np.array([40.0, 0.0, 9.8]), np.zeros(3), q))
            for k in range(3)]  # fmt: skip
    assert [o.accel_extra_sigma_mps2 for o in outs] == pytest.approx(
        [40.0 * np.sqrt(1 - 2 / np.pi)] * 3
    )
    assert outs[0].accel_mps2[0] == pytest.approx(40.0 + 40.0 * np.sqrt(2 / np.pi))


def test_saturated_sample_widens_the_filter_velocity_by_its_extra_sigma() -> None:
    def run(extra: float) -> np.ndarray:
        f = SagittalEskf(FilterConfig(integration="zoh"))
        f.initialise(0.0, (0.0, 0.0))
        q = np.array([1.0, 0.0, 0.0, 0.0])
        for k in range(1, 4):
            xa = extra if k == 2 else 0.0
            f.propagate(
                ImuSample(
                    k * H,
                    np.array([0.0, 0.0, GRAVITY_MPS2]),
                    np.zeros(3),
                    q,
                    accel_extra_sigma_mps2=xa,
                )
            )
        return f.state.P[2:4, 2:4]

    # the step onto the marked sample and the next one (trapezoid memory) lean on it
    d = run(20.0) - run(0.0)
    assert d[0, 0] == pytest.approx(2 * (20.0 * H) ** 2, rel=1e-6)


def test_gyro_spike_is_replaced_by_the_vendor_orientation_rate() -> None:
    # a heel-strike-like swing: the rate changes by 6 rad/s within 50 ms, which the vendor
    # orientation sees as well, so no sample may be flagged; then one 5 rad/s spike
    def rate(t):
        return 3.0 * np.tanh((t - 0.5) / 0.02)

    samples = _pitching(100, rate)
    spiked = list(samples)
    k = 60
    spiked[k] = ImuSample(
        samples[k].timestamp_s,
        samples[k].accel_mps2 + np.array([30.0, 0.0, 0.0]),
        samples[k].gyro_radps + np.array([0.0, 5.0, 0.0]),
        samples[k].quat_wxyz,
    )
    clean = ImuFaultMonitor(ImuFaultConfig(), None, None)
    assert all(clean.process(s) is s for s in samples)
    assert clean.n_gyro_repaired == 0
    mon = ImuFaultMonitor(ImuFaultConfig(), None, None)
    out = [mon.process(s) for s in spiked]
    assert mon.n_gyro_repaired == 1
    assert out[k].gyro_radps[1] == pytest.approx(rate(k * H), abs=0.05)
    assert out[k].gyro_extra_sigma_radps > 0
    # the corrupt packet's accelerometer is replaced by the last trusted one, distrusted
    np.testing.assert_array_equal(out[k].accel_mps2, samples[k - 1].accel_mps2)
    assert out[k].accel_extra_sigma_mps2 == ImuFaultConfig().held_accel_sigma_mps2
    assert out[k].accel_held and not samples[k].accel_held
    assert out[k + 1] is spiked[k + 1]  # the next sample is clean again


def _moving_filter(spike_mps2: float) -> tuple[SagittalEskf, float]:
    """Filter moving at 1 m/s in x over 3 IMU samples (30 ms), the middle one carrying an
    x spike of ``spike_mps2``; returns it and the interval (s)."""
    f = SagittalEskf(FilterConfig(integration="zoh"))
    f.initialise(0.0, (0.0, 0.0), v_xz=(1.0, 0.0), P0=np.diag([1e-6] * 2 + [1e-4] * 2 + [1e-4] * 4))
    q = np.array([1.0, 0.0, 0.0, 0.0])
    for k in range(1, 4):
        spike = spike_mps2 if k == 2 else 0.0
        f.propagate(ImuSample(k * H, np.array([spike, 0.0, GRAVITY_MPS2]), np.zeros(3), q))
    return f, 3 * H


def test_vision_arbitration_keeps_a_displacement_against_an_imu_spike_not_a_wrong_step() -> None:
    gate = SagittalEskf(FilterConfig()).gate_d2
    f, T = _moving_filter(60.0)  # a 60 m/s^2 spike: a 0.6 m/s jump at mid-interval
    good = Displacement2D(0.0, T, np.array([T * 1.0, 0.0]), np.eye(2) * 1e-6)
    Q = velocity_fault_cov(FilterConfig().imu_faults.velocity_fault_sigma_mps, T)
    assert f.displacement_d2(good) > gate  # the plain gate would refuse vision
    assert f.displacement_d2(good, Q) <= gate  # the IMU-fault hypothesis explains it
    f.inflate_position_velocity(Q)
    assert f.update_displacement(good)
    # vision pulls the velocity back from 1.6 m/s
    assert f.state.v_xz_mps[0] == pytest.approx(1.0, abs=0.1)
    # a wrong association (a 17 cm stair step) is not explained by one bad IMU sample
    f2, T = _moving_filter(0.0)
    wrong = Displacement2D(0.0, T, np.array([T * 1.0 + 0.17, 0.0]), np.eye(2) * 1e-6)
    assert f2.displacement_d2(wrong, Q) > gate


def test_distrusted_samples_inflate_the_preintegration_and_batch_imu_factors_are_robust() -> None:
    t = np.arange(0.0, 0.2, H)
    x = np.zeros((t.size, 2))
    x[5] = (10.0, 2.0)
    v, r = distrust_variances(t, x, 0.0, 0.1)
    assert v == pytest.approx((10.0 * H) ** 2) and r == pytest.approx((2.0 * H) ** 2)
    assert distrust_variances(t, x, 0.12, 0.2) == (0.0, 0.0)

    import gtsam

    from vio_graph.types import EstimateStatus, FrameEstimate, TerrainKind

    def factors(robust: bool, extra: float) -> gtsam.CombinedImuFactor:
        b = KeyframeGraphBuilder(SmootherConfig(), np.eye(4))
        b.robust_imu = robust
        for s in _pitching(25, lambda _t: 0.5):
            b.add_imu(
                ImuSample(
                    s.timestamp_s,
                    s.accel_mps2,
                    s.gyro_radps,
                    s.quat_wxyz,
                    accel_extra_sigma_mps2=extra if abs(s.timestamp_s - 0.1) < 1e-9 else 0.0,
                )
            )
        ups = []
        for tk in (0.05, 0.15):
            est = FrameEstimate(
                tk,
                EstimateStatus.FUSED,
                np.zeros(2),
                np.zeros(2),
                np.eye(2) * 1e-4,
                np.zeros(2),
                np.zeros(2),
                np.zeros(2),
                np.zeros(2),
                TerrainKind.LEVEL,
                True,
                {},
            )
            ups += b.add_frame(tk, True, est, None, None)
        ups += b.flush()
        g = ups[-1].factors
        return next(
            g.at(i) for i in range(g.size()) if isinstance(g.at(i), gtsam.CombinedImuFactor)
        )

    assert isinstance(factors(True, 0.0).noiseModel(), gtsam.noiseModel.Robust)
    assert not isinstance(factors(False, 0.0).noiseModel(), gtsam.noiseModel.Robust)
    # a distrusted sample in the interval loosens the velocity block of the IMU factor
    c0 = factors(False, 0.0).preintegratedMeasurements().preintMeasCov()
    c1 = factors(False, 30.0).preintegratedMeasurements().preintMeasCov()
    assert c1[6, 6] > c0[6, 6] + 0.5 * (30.0 * H) ** 2


def _imu_factor(samples: list[ImuSample], config: SmootherConfig):
    """Keyframes at 0.05 s and 0.15 s over ``samples``: the preintegrated measurements of the
    IMU factor between them."""
    import gtsam

    from vio_graph.types import EstimateStatus, FrameEstimate, TerrainKind

    b = KeyframeGraphBuilder(config, np.eye(4))
    for s in samples:
        b.add_imu(s)
    ups = []
    for tk in (0.05, 0.15):
        z2 = np.zeros(2)
        est = FrameEstimate(
            tk, EstimateStatus.FUSED, z2, z2, np.eye(2) * 1e-4, z2, z2, z2, z2,
            TerrainKind.LEVEL, True, {},
        )  # fmt: skip
        ups += b.add_frame(tk, True, est, None, None)
    ups += b.flush()
    g = ups[-1].factors
    f = next(g.at(i) for i in range(g.size()) if isinstance(g.at(i), gtsam.CombinedImuFactor))
    return f.preintegratedMeasurements()


def _imu_factor_delta_v(samples: list[ImuSample], config: SmootherConfig) -> tuple:
    """(delta v (3,), velocity covariance (3, 3), delta rotation) of :func:`_imu_factor`."""
    pim = _imu_factor(samples, config)
    return np.asarray(pim.deltaVij()), pim.preintMeasCov()[6:9, 6:9], pim.deltaRij()


def test_smoothers_interpolate_a_held_accelerometer_sample_from_its_neighbours() -> None:
    # specific force ramping by 400 m/s^2 per second in x (a heel-strike-like transient);
    # the packet at 0.10 s is corrupt and the monitor held the previous sample (4 m/s^2 of
    # hidden change: 0.04 m/s of velocity over the step if preintegrated as held)
    n, k = 25, 10
    q = np.array([1.0, 0.0, 0.0, 0.0])

    def sample(i: int) -> ImuSample:
        a = np.array([400.0 * i * H, 0.0, GRAVITY_MPS2])
        return ImuSample(i * H, a, np.zeros(3), q)

    truth = [sample(i) for i in range(n)]
    faulty = list(truth)
    sig = ImuFaultConfig().held_accel_sigma_mps2
    faulty[k] = ImuSample(
        k * H, truth[k - 1].accel_mps2, np.zeros(3), q, accel_extra_sigma_mps2=sig,
        accel_held=True,
    )  # fmt: skip
    cfg = SmootherConfig()
    dv_true, _, _ = _imu_factor_delta_v(truth, cfg)
    dv_interp, cov_interp, _ = _imu_factor_delta_v(faulty, cfg)
    off = cfg.model_copy(update={"held_accel_interpolation": False})
    dv_held, cov_held, _ = _imu_factor_delta_v(faulty, off)
    # the ramp is linear: the interpolation recovers the sample exactly; the held value
    # loses about 400 H^2 = 0.04 m/s of velocity
    np.testing.assert_allclose(dv_interp, dv_true, atol=1e-9)
    assert abs(dv_held[0] - dv_true[0]) > 0.02
    # and it is distrusted by the interpolation's sigma, not the held one
    assert cov_interp[0, 0] < cov_held[0, 0]
    _, cov_true, _ = _imu_factor_delta_v(truth, cfg)
    assert cov_interp[0, 0] > cov_true[0, 0]


def test_smoothers_can_interpolate_the_gyro_of_a_held_packet() -> None:
    import gtsam

    # pitch rate ramping by 20 rad/s per second; the corrupt packet at 0.10 s carries the
    # monitor's prediction from the vendor orientation, here 0.5 rad/s off in roll
    n, k = 25, 10

    def sample(i: int, gyro_err: float = 0.0, held: bool = False) -> ImuSample:
        g = np.array([gyro_err, 20.0 * i * H, 0.0])
        return ImuSample(
            i * H, np.array([0.0, 0.0, GRAVITY_MPS2]), g, np.array([1.0, 0.0, 0.0, 0.0]),
            accel_extra_sigma_mps2=10.0 if held else 0.0,
            gyro_extra_sigma_radps=0.5 if held else 0.0, accel_held=held,
        )  # fmt: skip

    truth = [sample(i) for i in range(n)]
    faulty = list(truth)
    faulty[k] = sample(k, gyro_err=0.5, held=True)
    on = SmootherConfig(held_gyro_interpolation=True)
    _, _, r_true = _imu_factor_delta_v(truth, on)
    _, _, r_on = _imu_factor_delta_v(faulty, on)
    _, _, r_off = _imu_factor_delta_v(faulty, SmootherConfig())
    # linear rate: the interpolation is exact; the predicted gyro leaves a roll error
    assert np.linalg.norm(gtsam.Rot3.Logmap(r_true.between(r_on))) < 1e-9
    assert np.linalg.norm(gtsam.Rot3.Logmap(r_true.between(r_off))) > 1e-3


def test_distrusted_sample_noise_enters_at_its_own_time() -> None:
    """A clipped sample at 0.06 s in the keyframe interval 0.05-0.15 s is a velocity pulse
    whose position error grows over the 0.09 s after it: its preintegrated position variance
    is (sigma h)^2 (0.09 s)^2 with the per-step distrust, and only a third of T^2 spread over
    the interval (the model before, 'spread')."""
    from vio_graph.smoother.imu_sampling import distrust_step_variances

    t = np.arange(0.0, 0.2, H)
    x = np.zeros((t.size, 2))
    x[6] = (30.0, 0.0)
    dt = np.full(10, H)  # steps 0.05-0.15 s on the samples
    vel, rot = distrust_step_variances(t, x, 0.05, dt)
    # the sample at 0.06 s covers 0.055-0.065 s: half in each of the steps around it
    assert vel[0] == pytest.approx(0.5 * (30.0 * H) ** 2) and vel[1] == pytest.approx(vel[0])
    assert vel.sum() == pytest.approx(distrust_variances(t, x, 0.05, 0.15)[0])
    assert not np.any(vel[2:]) and not np.any(rot)

    def position_var(mode: str, extra: float) -> float:
        samples = [
            dataclasses.replace(
                s, accel_extra_sigma_mps2=extra if abs(s.timestamp_s - 0.06) < 1e-9 else 0.0
            )
            for s in _pitching(25, lambda _t: 0.0)
        ]
        pim = _imu_factor(samples, SmootherConfig(distrust_noise=mode))
        return float(pim.preintMeasCov()[3, 3])

    base = position_var("per_step", 0.0)
    assert position_var("spread", 0.0) == base  # clean samples: the same factor
    pulse = (30.0 * H) ** 2 * 0.09**2
    assert position_var("per_step", 30.0) - base == pytest.approx(pulse, rel=0.1)
    assert position_var("spread", 30.0) - base == pytest.approx(
        pulse * 0.1**2 / 3 / 0.09**2, rel=0.15
    )


def _clipped_pushes(learn: bool, n_pushes: int = 6) -> tuple[list[float], list[float], object]:
    """A level IMU (z up) pushed along x by a pulse the accelerometer clips, then braked
    smoothly to rest, where a still-foot velocity observation (a stance) follows 0.3 s after
    the pulse. The pulse exceeds the 40 m/s^2 range by 50, 70, 50 m/s^2 (the lost velocity
    is 1.7 m/s; the default prior puts back 0.48 of it). Returns, per push, the filter's x
    velocity error just before the stance, the x position error the push added, measured
    just after the stance, and the learner. The monitor, filter and learner are wired as
    vio_graph/estimator.py wires them (a level, shank-aligned IMU: IMU x-z = world x-z)."""
    from vio_graph.filter.imu_faults import SaturationScaleLearner

    rng_ = 40.0
    cfg = ImuFaultConfig()
    mon = ImuFaultMonitor(cfg, accel_range_mps2=rng_, gyro_range_radps=35.0)
    learner = SaturationScaleLearner(cfg.saturation_sigma_range * rng_, 0.1, 1.0)
    f = SagittalEskf(FilterConfig(integration="zoh"))
    f.initialise(0.0, (0.0, 0.0))
    q = np.array([1.0, 0.0, 0.0, 0.0])
    pulse = np.array([90.0, 110.0, 90.0])  # true specific force (m/s^2) over 3 samples
    n_brake = 30  # then braked to rest at a constant rate over 0.3 s
    brake = -pulse.sum() / n_brake
    true_x, true_v, t = 0.0, 0.0, 0.0
    v_err, p_err = [], []
    R_xz = np.array([[1.0, 0.0, 0.0], [0.0, 0.0, 1.0]])
    for _ in range(n_pushes):
        profile = list(pulse) + [brake] * n_brake + [0.0] * 5
        for _ in range(3):  # still before the push: its velocity is known
            f.update_velocity((0.0, 0.0), np.eye(2) * 0.02**2)
        p0 = f.position_velocity()[1][0] - true_x
        for a_true in profile:
            t += H
            true_x += true_v * H + 0.5 * a_true * H**2
            true_v += a_true * H
            measured = np.clip(a_true, -rng_, rng_)
            s = mon.process(ImuSample(t, np.array([measured, 0.0, GRAVITY_MPS2]), np.zeros(3), q))
            f.propagate(s)
            if learn and (learner.active or mon.last_rail_sign.any()):
                changed = learner.add_sample(
                    t,
                    H,
                    mon.last_rail_sign,
                    mon.last_restored_mps2,
                    R_xz,
                    float(np.trace(f.cov_velocity_m2ps2())),
                    f.velocity_corrections_mps,
                )
                if changed:
                    mon.accel_scales_mps2 = learner.scales_mps2.copy()
        v_err.append(f.position_velocity()[2][0] - true_v)
        for _ in range(3):  # the stance: three frames of a still foot
            f.update_velocity((0.0, 0.0), np.eye(2) * 0.02**2)
        p_err.append(f.position_velocity()[1][0] - true_x - p0)  # what this push added
        for _ in range(30):  # standing still, the velocity variance settles
            t += H
            true_x += true_v * H
            s = mon.process(ImuSample(t, np.array([0.0, 0.0, GRAVITY_MPS2]), np.zeros(3), q))
            f.propagate(s)
            if learn and learner.active:
                if learner.add_sample(
                    t,
                    H,
                    mon.last_rail_sign,
                    mon.last_restored_mps2,
                    R_xz,
                    float(np.trace(f.cov_velocity_m2ps2())),
                    f.velocity_corrections_mps,
                ):
                    mon.accel_scales_mps2 = learner.scales_mps2.copy()
        f.update_velocity((0.0, 0.0), np.eye(2) * 0.02**2)
    return v_err, p_err, learner


def test_saturation_scale_is_learnt_from_the_velocity_the_stance_measures() -> None:
    v_off, p_off, _ = _clipped_pushes(learn=False)
    v_on, p_on, learner = _clipped_pushes(learn=True)
    c = np.sqrt(2 / np.pi)
    # the configured prior (scale 20 m/s^2: mean excess 16) puts back 0.48 of the 1.7 m/s
    # every push loses: the velocity is 1.2 m/s short until the stance, every time
    assert all(-1.3 < v < -1.1 for v in v_off)
    # learnt: the mean excess (56.7 m/s^2) / c on x, within 10 % after the first stance;
    # z was never clipped and keeps the prior's scale
    assert learner.n_evidence == 6 and learner.n_dropped == 0
    assert learner.scales_mps2[0] * c == pytest.approx(170.0 / 3, rel=0.1)
    assert learner.scales_mps2[2] == pytest.approx(20.0)
    # so from the second push on the velocity after a clipped pulse is right within 0.1 m/s
    # (instead of 1.2 m/s short) ...
    assert all(abs(v) < 0.1 for v in v_on[1:])
    # ... and the position error a push leaves after the stance is within 2 mm, where the
    # stance alone (velocity corrected, position through the cross-covariance) leaves 2 cm
    # per push; the first push, before any evidence, is as bad as without learning
    assert v_on[0] == pytest.approx(v_off[0])
    assert all(abs(p) < 0.002 for p in p_on[1:])
    assert all(p < -0.015 for p in p_off)


def test_saturation_evidence_nothing_measured_is_dropped() -> None:
    from vio_graph.filter.imu_faults import SaturationScaleLearner

    learner = SaturationScaleLearner(20.0, 0.1, 1.0)
    R_xz = np.array([[1.0, 0.0, 0.0], [0.0, 0.0, 1.0]])
    sign = np.array([1.0, 0.0, 0.0])  # x clipped at +range
    put_back = 20.0 * np.sqrt(2 / np.pi) * sign  # the prior's mean at scale 20
    zero = np.zeros(3)
    corr = np.zeros(2)
    for k in range(3):  # a clipped stretch: the velocity variance grows
        learner.add_sample(0.01 * k, H, sign, put_back, R_xz, 0.01 + 0.1 * k, corr)
    assert learner.active
    # blind: the variance stays up and a correction arrives only after the window
    for k in range(3, 120):
        assert not learner.add_sample(0.01 * k, H, zero, zero, R_xz, 0.3, corr)
    assert not learner.active and learner.n_dropped == 1 and learner.n_evidence == 0
    assert learner.scales_mps2 == pytest.approx([20.0, 20.0, 20.0])
    # the same stretch measured in time: the variance falls back and the corrections say the
    # prior put back only half (0.48 of 0.96 m/s)
    for k in range(3):
        learner.add_sample(2.0 + 0.01 * k, H, sign, put_back, R_xz, 0.01 + 0.1 * k, corr)
    learner.add_sample(2.03, H, zero, zero, R_xz, 0.21, corr)
    assert learner.add_sample(2.1, H, zero, zero, R_xz, 0.02, np.array([0.48, 0.0]))
    assert learner.n_evidence == 1
    assert 30.0 < learner.scales_mps2[0] < 40.0  # towards 40, the prior holds a little back
    assert learner.scales_mps2[1:] == pytest.approx([20.0, 20.0])


def _estimator_after(
    samples: list[ImuSample], repair: bool, per_axis: bool = True, axis_distrust: bool = False
):
    """An online estimator (filter started at the first IMU sample, no frames) fed
    ``samples``: its filter velocity (m/s) and tracked attitude at the last sample."""
    from tests.conftest import tiny_metadata
    from vio_graph.config import PipelineConfig
    from vio_graph.estimator import OnlineEstimator, RigGeometry

    cfg = PipelineConfig.model_validate(
        {
            "filter": {
                "start_at_first_frame": False,
                "imu_faults": {
                    "repair_from_next_sample": repair,
                    "keep_consistent_axes": per_axis,
                    "repaired_axis_distrust": axis_distrust,
                },
            }
        }
    )
    est = OnlineEstimator(cfg, RigGeometry.from_metadata(tiny_metadata()))
    steps = [est.add_imu(s) for s in samples]
    _, _, v = est.filter.position_velocity()
    return v, est.attitude.R_world_imu_at(samples[-1].timestamp_s), est, steps


def test_filter_repairs_a_corrupt_packet_from_the_next_sample() -> None:
    # a swinging shank: pitch rate ramping by 20 rad/s per second, specific force ramping by
    # 400 m/s^2 per second in x (heel-strike-like); the vendor orientation of the packet at
    # 0.30 s is 1 mrad off in pitch (its usual noise), so the monitor's prediction of that
    # packet's gyro (2 w_k - g_(k-1)) is 0.2 rad/s off. The packet carries a spike (30 m/s^2,
    # 5 rad/s): the monitor flags it and holds the previous accelerometer, 4 m/s^2 short
    n, k = 40, 30
    truth = _pitching(n, lambda t: 20.0 * t)
    truth = [dataclasses.replace(s, accel_mps2=s.accel_mps2 + [400.0 * s.timestamp_s, 0, 0])
             for s in truth]  # fmt: skip
    R_k = matrix_from_quat_wxyz(truth[k].quat_wxyz) @ rot_y(1e-3)
    truth[k] = dataclasses.replace(truth[k], quat_wxyz=quat_wxyz_from_matrix(R_k))
    spiked = list(truth)
    spiked[k] = dataclasses.replace(
        truth[k],
        accel_mps2=truth[k].accel_mps2 + [30.0, 0, 0],
        gyro_radps=truth[k].gyro_radps + [0, 5.0, 0],
    )
    v_true, R_true, est_clean, _ = _estimator_after(truth, repair=True)
    assert est_clean.imu_faults.n_gyro_repaired == 0
    v_on, R_on, est, steps = _estimator_after(spiked, repair=True)
    v_off, R_off, _, _ = _estimator_after(spiked, repair=False)
    assert est.imu_faults.n_gyro_repaired == 1 and est.imu_repair.n_repaired == 1
    # the other estimators still get the monitor's packet (the smoothers interpolate it)
    assert steps[k].shank.accel_held
    # the rate and the added force are linear: the interpolated gyro is the true one, so the
    # tracked attitude is the clean stream's; the interpolated specific force misses only the
    # curvature of gravity seen from the turning shank (h^2/8 |f''|, 1.8e-4 m/s here)
    assert np.linalg.norm(Rotation.from_matrix(R_true.T @ R_on).as_rotvec()) < 1e-9
    assert np.max(np.abs(v_on - v_true)) < 5e-4
    # the monitor's stand-ins alone: the held accelerometer loses ~4 m/s^2 over two
    # trapezoid half-steps (0.04 m/s), the predicted gyro tilts the attitude by ~2 mrad
    assert abs(v_off[0] - v_true[0]) > 0.02
    assert np.linalg.norm(Rotation.from_matrix(R_true.T @ R_off).as_rotvec()) > 1e-3


def test_next_sample_repair_waits_one_sample_at_most() -> None:
    q = np.array([1.0, 0.0, 0.0, 0.0])

    def s(i: int, held: bool = False) -> ImuSample:
        a = np.array([float(i), 0.0, GRAVITY_MPS2])
        sig = 10.0 if held else 0.0
        return ImuSample(i * H, a, np.zeros(3), q, sig, 0.5 if held else 0.0, held)

    rep = NextSampleRepair(5.0)
    assert [x.timestamp_s for x in rep.push(s(0))] == [0.0]
    assert rep.push(s(1, held=True)) == [] and rep.pending is not None
    # two corrupt packets in a row: both go out as the monitor left them (the second has no
    # measured sample before it), so the filter is never more than one sample late
    out = rep.push(s(2, held=True))
    assert [x.timestamp_s for x in out] == [H, 2 * H] and rep.pending is None
    assert all(x.accel_extra_sigma_mps2 == 10.0 for x in out) and out[0].accel_mps2[0] == 1
    assert [x.timestamp_s for x in rep.push(s(3))] == [3 * H]
    assert rep.push(s(4, held=True)) == []
    out = rep.push(s(5))
    assert out[0].accel_mps2[0] == pytest.approx(4.0) and out[0].accel_extra_sigma_mps2 == 5.0
    assert out[0].accel_held and rep.n_repaired == 1


def test_keep_consistent_axes_replaces_only_the_axes_that_disagree() -> None:
    interp = np.array([-40.5, 0.0, -26.4])
    # a 30 m/s^2 spike on x; y and z 0 and 2.2 m/s^2 off the interpolation (a heel strike's
    # transient the interpolation misses): with sigma 5 and p = 0.999 (3.29 sigma, 16.4)
    # only x goes
    got = keep_consistent_axes([-10.9, 0.0, -28.6], interp, 5.0, 0.999)
    np.testing.assert_array_equal(got, [-40.5, 0.0, -28.6])
    # an axis 17 m/s^2 off fails the test too; nothing measured: the stand-in throughout
    got = keep_consistent_axes([-23.5, 0.0, -28.6], interp, 5.0, 0.999)
    np.testing.assert_array_equal(got, [-40.5, 0.0, -28.6])
    np.testing.assert_array_equal(keep_consistent_axes(None, interp, 5.0, 0.999), interp)


def _heel_strike_with_one_axis_spike(n: int, k: int) -> tuple[list, list]:
    """A swinging shank whose specific force peaks at sample ``k`` (a heel-strike transient
    the interpolation between its neighbours misses by 8 m/s^2 in x and 6 in z), and the
    same stream with a spike on one accelerometer axis (y, 30 m/s^2) and one gyro axis (x,
    5 rad/s) of packet ``k`` (the simulator's spikes hit one axis of each sensor)."""
    truth = _pitching(n, lambda t: 20.0 * t)
    peak = np.zeros((n, 3))
    peak[k] = (8.0, 0.0, 6.0)
    truth = [dataclasses.replace(s, accel_mps2=s.accel_mps2 + peak[i])
             for i, s in enumerate(truth)]  # fmt: skip
    spiked = list(truth)
    spiked[k] = dataclasses.replace(
        truth[k],
        accel_mps2=truth[k].accel_mps2 + [0, 30.0, 0],
        gyro_radps=truth[k].gyro_radps + [5.0, 0, 0],
    )
    return truth, spiked


def test_filter_keeps_the_axes_of_a_repaired_packet_that_agree_with_its_neighbours() -> None:
    n, k = 40, 30
    truth, spiked = _heel_strike_with_one_axis_spike(n, k)
    v_true, R_true, _, _ = _estimator_after(truth, repair=True)
    v_on, R_on, est, steps = _estimator_after(spiked, repair=True)
    v_off, R_off, _, _ = _estimator_after(spiked, repair=True, per_axis=False)
    assert est.imu_faults.n_gyro_repaired == 1 and est.imu_repair.n_repaired == 1
    # the packet's own x, z force and pitch rate agree with the neighbours: kept, so the
    # velocity and the attitude are the clean stream's; the spiked y and roll are replaced
    assert est.imu_repair.n_axes_kept == 4
    np.testing.assert_allclose(v_on, v_true, atol=1e-9)
    assert np.linalg.norm(Rotation.from_matrix(R_true.T @ R_on).as_rotvec()) < 1e-9
    # the whole packet interpolated misses the peak: 8 m/s^2 over a trapezoid step in x
    assert abs(v_off[0] - v_true[0]) > 0.03
    # the smoothers get the monitor's stand-in with what the packet measured beside it
    np.testing.assert_allclose(steps[k].shank.measured_accel_mps2, spiked[k].accel_mps2)
    np.testing.assert_allclose(steps[k].shank.measured_gyro_radps, spiked[k].gyro_radps)


def _with_held_standin(truth: list, spiked: list, k: int) -> list:
    """The clean stream with sample ``k`` replaced by the monitor's stand-in for the spiked
    packet: the previous force held, the gyro predicted (0.5 rad/s off in pitch), the
    measurement carried beside it."""
    held = dataclasses.replace(
        spiked[k],
        accel_mps2=truth[k - 1].accel_mps2,
        gyro_radps=truth[k].gyro_radps + [0.0, 0.5, 0.0],
        accel_extra_sigma_mps2=ImuFaultConfig().held_accel_sigma_mps2,
        gyro_extra_sigma_radps=0.5,
        accel_held=True,
        measured_accel_mps2=spiked[k].accel_mps2,
        measured_gyro_radps=spiked[k].gyro_radps,
    )
    return [*truth[:k], held, *truth[k + 1 :]]


def test_smoothers_keep_the_axes_of_a_held_packet_that_agree_with_its_neighbours() -> None:
    import gtsam

    n, k = 25, 10
    truth, spiked = _heel_strike_with_one_axis_spike(n, k)
    faulty = _with_held_standin(truth, spiked, k)
    on = SmootherConfig()
    off = SmootherConfig(held_keep_consistent_axes=False)
    dv_true, _, r_true = _imu_factor_delta_v(truth, on)
    dv_on, _, r_on = _imu_factor_delta_v(faulty, on)
    dv_off, _, r_off = _imu_factor_delta_v(faulty, off)
    # kept: the clean stream's delta v and rotation; the interpolation misses the 8 m/s^2
    # peak (0.08 m/s over one sample) and the predicted gyro tilts the rotation by 5 mrad
    np.testing.assert_allclose(dv_on, dv_true, atol=1e-9)
    assert np.linalg.norm(gtsam.Rot3.Logmap(r_true.between(r_on))) < 1e-9
    assert np.linalg.norm(dv_off - dv_true) > 0.03
    assert np.linalg.norm(gtsam.Rot3.Logmap(r_true.between(r_off))) > 1e-3


def test_a_frame_after_a_repaired_packet_waits_for_its_repair(tmp_path) -> None:
    """IMU spikes at 10 Hz on a 2 s downstair walk: a repaired packet is held back until the
    next sample (filter/imu_repair.py), and a frame captured between the two waits with it,
    so every frame sees the filter at the last IMU sample before its capture time (the
    packet included) instead of extrapolating across the packet (two periods at a heel
    strike's 40 m/s^2 is 8 mm). Without the wait, the frames after a repaired packet are
    processed while it is still held."""
    from vio_graph.config import PipelineConfig
    from vio_graph.recording.reader import Recording
    from vio_graph.replay import Replay
    from vio_graph.sim import load_scenario, simulate
    from vio_graph.viz.rerun_logger import NullVisualizer

    cfg = load_scenario("downstair").model_copy(update={"duration_s": 2.0})
    cfg = cfg.model_copy(
        update={"faults": cfg.faults.model_copy(update={"imu_spike_rate_hz": 10.0})}
    )
    rec = Recording.open(simulate(cfg, seed=1, out_dir=tmp_path / "spikes"))
    replay = Replay(rec, PipelineConfig(), {"filter"}, NullVisualizer())
    seen: list[tuple[float, float, float | None]] = []  # capture time, last IMU, held packet
    frame = replay._frame

    def watched(i: int) -> None:
        online = replay.online
        seen.append((rec.frame_timestamps_s[i], online.last_imu_time_s, online.imu_held_back_s))
        frame(i)

    replay._frame = watched  # type: ignore[method-assign]
    repaired: list[float] = []
    repair = replay.online.imu_repair
    interpolate = repair.interpolate

    def noted(before, held, after):
        repaired.append(held.timestamp_s)
        return interpolate(before, held, after)

    repair.interpolate = noted  # type: ignore[method-assign]
    replay.run()
    assert replay.rerun is None and len(repaired) >= 10
    imu_t = rec.imu.timestamp_s
    waited = 0
    for t_cap, last_imu, held in seen:
        assert held is None or held > t_cap
        expected = imu_t[np.searchsorted(imu_t, t_cap, side="right") - 1]
        # the filter is at the sample before the capture or later (the one after a repaired
        # packet has been taken: it released the packet; the filter propagates only up to
        # the capture time)
        assert last_imu >= expected
        waited += expected in repaired  # the last sample before the capture was repaired
    assert waited >= 2


def _push_after_small_learnt_scale(floor: bool) -> tuple[float, float, float, float]:
    """A level IMU (z up) pushed along x by a 3-sample pulse the accelerometer clips (60, 70,
    60 m/s^2 against a 40 m/s^2 range: 0.7 m/s lost), then braked smoothly to rest over 0.3 s,
    where a still foot (three velocity observations, 0.02 m/s) follows. The monitor's x scale
    is the one a learner ends with after stretches that lost nothing (0.02 m/s^2, as on
    downstair 4 g), so the prior's mean puts back nothing. Returns the filter's x velocity
    sigma at the end of the clipped stretch and just before it, and the x velocity and
    position errors after the stance."""
    rng_ = 40.0
    cfg = ImuFaultConfig(saturation_sigma_prior_floor=floor)
    mon = ImuFaultMonitor(cfg, accel_range_mps2=rng_, gyro_range_radps=35.0)
    mon.accel_scales_mps2 = np.array([0.02, 20.0, 20.0])
    f = SagittalEskf(FilterConfig(integration="zoh"))
    f.initialise(0.0, (0.0, 0.0))
    q = np.array([1.0, 0.0, 0.0, 0.0])
    for _ in range(3):
        f.update_velocity((0.0, 0.0), np.eye(2) * 0.02**2)
    pulse = [60.0, 70.0, 60.0]
    profile = pulse + [-sum(pulse) / 30] * 30 + [0.0] * 5
    true_x, true_v, t = 0.0, 0.0, 0.0
    sig_before = float(np.sqrt(f.cov_velocity_m2ps2()[0, 0]))
    sig_clipped = sig_before
    for k, a_true in enumerate(profile):
        t += H
        true_x += true_v * H + 0.5 * a_true * H**2
        true_v += a_true * H
        s = mon.process(
            ImuSample(t, np.array([np.clip(a_true, -rng_, rng_), 0.0, GRAVITY_MPS2]),
                      np.zeros(3), q)
        )  # fmt: skip
        f.propagate(s)
        if k == len(pulse):  # the step after the stretch has leant on its last sample
            sig_clipped = float(np.sqrt(f.cov_velocity_m2ps2()[0, 0]))
    for _ in range(3):
        f.update_velocity((0.0, 0.0), np.eye(2) * 0.02**2)
    _, p, v = f.position_velocity()
    return sig_before, sig_clipped, v[0] - true_v, p[0] - true_x


def test_clipped_stretch_keeps_the_prior_sigma_when_the_learnt_scale_is_small() -> None:
    # the learnt scale is a mean loss of past stretches: with it as the sigma too, a clipped
    # stretch adds almost no velocity variance, the 0.7 m/s it lost is a 27-sigma innovation
    # at the stance, the gate refuses it and the filter keeps the wrong velocity: 26 cm of
    # position error by the end of the stance
    before, clipped, v_err, p_err = _push_after_small_learnt_scale(floor=False)
    assert clipped < 2 * before
    assert v_err < -0.6 and p_err < -0.2
    # with the prior's sigma as a floor (20 m/s^2 scale: 12 m/s^2 for the first sample, the
    # k-th sqrt(2k - 1) times it: the 3-sample stretch adds 9 times one sample's variance,
    # 3 x 12 x 10 ms = 0.36 m/s, up to twice that variance as each sample also enters the
    # next step, trapezoid memory) the variance grows while clipped, the stance is taken,
    # and the cross-covariance the stretch built carries the correction back to the position
    before, clipped, v_err, p_err = _push_after_small_learnt_scale(floor=True)
    sd = 20.0 * np.sqrt(1 - 2 / np.pi)
    assert 3 * sd * H <= clipped <= np.hypot(before, np.sqrt(2) * 3 * sd * H)
    assert abs(v_err) < 0.01
    assert abs(p_err) < 0.02


def test_smoothers_distrust_only_the_interpolated_axes_of_a_held_packet() -> None:
    """A level, still IMU (z up) whose packet k had a 30 m/s^2 spike on y: the neighbours'
    interpolation replaces y, x and z keep their measurement. With held_axis_distrust the
    interpolation's extra variance (interpolated_accel_sigma_mps2, 5 m/s^2 over one 10 ms
    step: (0.05 m/s)^2 of velocity) goes on y only; without it on all three axes."""
    n, k = 25, 10
    q = np.array([1.0, 0.0, 0.0, 0.0])
    truth = [ImuSample(i * H, np.array([0.0, 0.0, GRAVITY_MPS2]), np.zeros(3), q) for i in range(n)]
    spiked = truth[k].accel_mps2 + [0.0, 30.0, 0.0]
    held = ImuSample(
        k * H, truth[k - 1].accel_mps2, np.zeros(3), q,
        accel_extra_sigma_mps2=ImuFaultConfig().held_accel_sigma_mps2, accel_held=True,
        measured_accel_mps2=spiked, measured_gyro_radps=np.zeros(3),
    )  # fmt: skip
    faulty = [*truth[:k], held, *truth[k + 1 :]]
    on = SmootherConfig()
    off = on.model_copy(update={"held_axis_distrust": False})
    dv_true, cov_true, _ = _imu_factor_delta_v(truth, on)
    dv_on, cov_on, _ = _imu_factor_delta_v(faulty, on)
    dv_off, cov_off, _ = _imu_factor_delta_v(faulty, off)
    # the sample is recovered either way (constant force): only the covariance differs
    np.testing.assert_allclose(dv_on, dv_true, atol=1e-12)
    np.testing.assert_allclose(dv_off, dv_true, atol=1e-12)
    extra = (on.interpolated_accel_sigma_mps2 * H) ** 2  # (m/s)^2 of one distrusted step
    d_on = np.diag(cov_on - cov_true)
    d_off = np.diag(cov_off - cov_true)
    np.testing.assert_allclose(d_on[[0, 2]], 0.0, atol=1e-3 * extra)
    assert d_on[1] > 0.5 * extra
    np.testing.assert_allclose(d_off, d_on[1], rtol=1e-6)


def test_filter_distrusts_only_the_interpolated_axes_of_a_repaired_packet() -> None:
    """The heel strike with a spike on the accelerometer's y and the gyro's x: the repair
    interpolates y and keeps the measured x and z. With repaired_axis_distrust the
    interpolation's extra variance (5 m/s^2 over one 10 ms step, (0.05 m/s)^2) goes on y,
    which the sagittal filter does not carry, so its x-z velocity covariance is the clean
    stream's; without it both x and z gain about that variance."""
    n, k = 40, 30
    truth, spiked = _heel_strike_with_one_axis_spike(n, k)
    _, _, est_true, _ = _estimator_after(truth, repair=True, axis_distrust=True)
    _, _, est_on, _ = _estimator_after(spiked, repair=True, axis_distrust=True)
    _, _, est_off, _ = _estimator_after(spiked, repair=True)
    assert est_on.imu_repair.n_repaired == 1 and est_on.imu_repair.n_axes_kept == 4
    P_true, P_on, P_off = (e.filter._P[2:4, 2:4] for e in (est_true, est_on, est_off))
    np.testing.assert_allclose(P_on, P_true, rtol=1e-9, atol=1e-15)
    extra = (ImuFaultConfig().interpolated_accel_sigma_mps2 / RATE_HZ) ** 2
    assert np.trace(P_off - P_true) > 0.5 * extra


def _heel_strike_with_a_hidden_spike(n: int, k: int) -> tuple[list, list]:
    """A swinging shank whose specific force peaks at sample ``k`` 19 m/s^2 above the
    midpoint of its neighbours in x (upstair seed 2's heel strike at 3.76 s), and the same
    stream with a spike of the other sign on that axis (-30 m/s^2) and on the gyro's x
    (5 rad/s) of packet ``k``: the measured x is 11 m/s^2 below the interpolation, inside
    the per-axis test's bound (3.3 x 5 m/s^2), so the test finds no corrupt accelerometer
    axis although x is 30 m/s^2 off."""
    truth = _pitching(n, lambda t: 20.0 * t)
    peak = np.zeros((n, 3))
    peak[k] = (19.0, 0.0, 0.0)
    truth = [dataclasses.replace(s, accel_mps2=s.accel_mps2 + peak[i])
             for i, s in enumerate(truth)]  # fmt: skip
    spiked = list(truth)
    spiked[k] = dataclasses.replace(
        truth[k],
        accel_mps2=truth[k].accel_mps2 + [-30.0, 0, 0],
        gyro_radps=truth[k].gyro_radps + [5.0, 0, 0],
    )
    return truth, spiked


def test_interpolated_axes_cov_is_none_when_no_axis_was_interpolated() -> None:
    measured = np.array([1.0, 2.0, 3.0])
    np.testing.assert_array_equal(
        interpolated_axes_cov([1.0, 5.0, 3.0], measured, 25.0), np.diag([0.0, 25.0, 0.0])
    )
    # every axis kept: the variance stays on all of them (the caller's isotropic sigma)
    assert interpolated_axes_cov(measured.copy(), measured, 25.0) is None


def test_filter_keeps_distrusting_a_repaired_packet_whose_spike_it_could_not_place() -> None:
    """The heel strike hides the accelerometer's spike from the per-axis test: every axis is
    kept, x 30 m/s^2 off (0.3 m/s of velocity). With repaired_axis_distrust the kept axes
    would be trusted as measurements (no extra variance: on upstair seed 2 the filter then
    refused the next displacements and its toe x went 0.68 -> 2.73 cm); since the test found
    no axis to blame, the packet keeps the interpolation's variance on every axis, as
    without repaired_axis_distrust: (5 m/s^2 x 10 ms)^2 on x and z of the velocity, to the
    bit."""
    n, k = 40, 30
    truth, spiked = _heel_strike_with_a_hidden_spike(n, k)
    v_true, _, est_true, _ = _estimator_after(truth, repair=True, axis_distrust=True)
    v_on, _, est_on, _ = _estimator_after(spiked, repair=True, axis_distrust=True)
    _, _, est_off, _ = _estimator_after(spiked, repair=True)
    rep = est_on.imu_repair
    assert rep.n_repaired == 1 and rep.n_axes_kept == 5  # 3 accelerometer + 2 gyro axes
    # the kept x carries the spike: about 0.3 m/s of velocity error (rotated by the pitch)
    assert np.linalg.norm(v_on - v_true) > 0.2
    P_true, P_on, P_off = (e.filter._P[2:4, 2:4] for e in (est_true, est_on, est_off))
    np.testing.assert_array_equal(P_on, P_off)
    extra = (ImuFaultConfig().interpolated_accel_sigma_mps2 / RATE_HZ) ** 2
    gained = np.diag(P_on - P_true)
    assert np.all(gained > 0.5 * extra)
    # a spike the test did place (the y of _heel_strike_with_one_axis_spike) still costs
    # the sagittal velocity nothing (test_filter_distrusts_only_the_interpolated_axes...)
    truth_y, spiked_y = _heel_strike_with_one_axis_spike(n, k)
    _, _, est_ty, _ = _estimator_after(truth_y, repair=True, axis_distrust=True)
    _, _, est_y, _ = _estimator_after(spiked_y, repair=True, axis_distrust=True)
    np.testing.assert_allclose(
        est_y.filter._P[2:4, 2:4], est_ty.filter._P[2:4, 2:4], rtol=1e-9, atol=1e-15
    )


def test_smoothers_keep_distrusting_a_held_packet_whose_spike_they_could_not_place() -> None:
    """The smoothers' twin (held_axis_distrust): the hidden spike of
    _heel_strike_with_a_hidden_spike keeps the interpolation's variance on every axis of the
    preintegrated velocity, as without held_axis_distrust."""
    n, k = 25, 10
    truth, spiked = _heel_strike_with_a_hidden_spike(n, k)
    faulty = _with_held_standin(truth, spiked, k)
    on = SmootherConfig()
    assert on.held_axis_distrust
    off = on.model_copy(update={"held_axis_distrust": False})
    _, cov_true, _ = _imu_factor_delta_v(truth, on)
    dv_on, cov_on, _ = _imu_factor_delta_v(faulty, on)
    dv_off, cov_off, _ = _imu_factor_delta_v(faulty, off)
    np.testing.assert_array_equal(dv_on, dv_off)
    np.testing.assert_allclose(cov_on, cov_off, rtol=1e-12, atol=1e-18)
    extra = (on.interpolated_accel_sigma_mps2 * H) ** 2
    assert np.all(np.diag(cov_on - cov_true) > 0.5 * extra)
