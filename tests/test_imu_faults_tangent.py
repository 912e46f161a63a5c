"""Clipped accelerometer peaks (vio_graph/filter/imu_faults.py): the prior's scale capped at
the tangent's excess (``saturation_tangent_cap``) and the scale learnt per rail side
(``saturation_learn_per_side``), on injected clips with a known answer."""

from __future__ import annotations

import numpy as np
import pytest

from vio_graph.filter.config import ImuFaultConfig
from vio_graph.filter.imu_faults import ImuFaultMonitor, SaturationScaleLearner
from vio_graph.types import ImuSample

H = 0.01  # 100 Hz
RANGE = 29.4  # 3 g
Q = np.array([1.0, 0.0, 0.0, 0.0])


def _swing_peak(peak_mps2: float, half_width_s: float, sign: float = 1.0) -> np.ndarray:
    """x specific force (m/s^2) of a smooth swing peak, sign * peak * cos^2 over +-half
    width, at 100 Hz from 0.1 s before it to 0.1 s after (concave above half its height, so
    the tangent at a sample there bounds the top)."""
    t = np.arange(-half_width_s - 0.1, half_width_s + 0.1 + 1e-9, H) + 0.003  # off the grid
    u = np.clip(t / half_width_s, -1.0, 1.0)
    return sign * peak_mps2 * np.cos(0.5 * np.pi * u) ** 2


def _run(x_true: np.ndarray, cap: bool) -> tuple[float, float, np.ndarray, np.ndarray]:
    """Feed the clipped peak to a monitor: (velocity the clip lost, velocity the prior put
    back, m/s, both along the rail's side; per clipped sample the true excess and the cap)."""
    cfg = ImuFaultConfig(saturation_tangent_cap=cap)
    mon = ImuFaultMonitor(cfg, accel_range_mps2=RANGE, gyro_range_radps=35.0)
    lost = put_back = 0.0
    excess, caps = [], []
    for k, x in enumerate(x_true):
        meas = float(np.clip(x, -RANGE, RANGE))
        s = mon.process(ImuSample(k * H, np.array([meas, 0.0, 9.8]), np.zeros(3), Q))
        sign = np.sign(x)
        lost += sign * (x - meas) * H
        put_back += sign * (float(s.accel_mps2[0]) - meas) * H
        if abs(x) >= 0.99 * RANGE:
            excess.append(abs(x) - RANGE)
            caps.append(mon.last_restored_mps2[0] * sign / np.sqrt(2 / np.pi))
    return lost, put_back, np.array(excess), np.array(caps)


@pytest.mark.parametrize("peak, sign", [(33.0, 1.0), (36.0, -1.0), (42.0, 1.0)])
def test_tangent_cap_bounds_a_concave_peak_and_puts_back_about_what_it_lost(peak, sign) -> None:
    x = _swing_peak(peak, 0.06, sign)  # 3-4 clipped samples, as the simulated swing's
    lost, prior, _, _ = _run(x, cap=False)
    lost_c, capped, excess, caps = _run(x, cap=True)
    assert lost_c == pytest.approx(lost) and lost > 0.0
    # the tangent at the last unclipped sample lies above the concave top: each sample's
    # scale is at least its true excess
    assert np.all(caps >= excess - 1e-9)
    # the uncapped prior (scale half the range: 11.7 m/s^2 per sample) puts back 0.1-0.3 m/s
    # more than a barely clipped peak lost; the capped one is closer on every peak
    assert abs(capped - lost) < 0.75 * abs(prior - lost)


def test_tangent_cap_leaves_a_jump_past_the_rail_to_the_prior() -> None:
    # a heel-strike-like jump from 5 to 60 m/s^2 in one sample: the tangent before it does
    # not reach the rail, it is no concave peak, and the prior's scale stays
    x = np.array([5.0, 5.0, 5.0, 60.0, 60.0, 5.0, 5.0])
    lost, prior, _, _ = _run(x, cap=False)
    lost_c, capped, _, _ = _run(x, cap=True)
    assert capped == pytest.approx(prior)
    assert prior == pytest.approx(2 * 0.5 * RANGE * np.sqrt(2 / np.pi) * H)


def test_capped_sample_carries_the_capped_sigma_not_the_floor() -> None:
    cfg = ImuFaultConfig(saturation_tangent_cap=True)
    mon = ImuFaultMonitor(cfg, accel_range_mps2=RANGE, gyro_range_radps=35.0)
    for k, x in enumerate([20.0, 27.0, 31.0]):  # rise 7 m/s^2 per sample: tangent 34
        s = mon.process(ImuSample(k * H, np.array([min(x, RANGE), 0.0, 9.8]), np.zeros(3), Q))
    cap = 27.0 + 7.0 - RANGE
    assert s.accel_mps2[0] == pytest.approx(RANGE + cap * np.sqrt(2 / np.pi))
    assert s.accel_extra_sigma_mps2 == pytest.approx(cap * np.sqrt(1 - 2 / np.pi))
    assert mon.last_capped.tolist() == [True, False, False]


def test_scales_are_learnt_per_rail_side() -> None:
    # the forward peak loses 10 m/s^2 per clipped sample, the backward one 2.5: one scale
    # per axis learns their mix, one per side each of them
    c = np.sqrt(2 / np.pi)
    R_xz = np.array([[1.0, 0.0, 0.0], [0.0, 0.0, 1.0]])
    zero = np.zeros(3)
    learnt = {}
    for per_side in (False, True):
        lr = SaturationScaleLearner(14.7, 0.1, 1.0, per_side=per_side)
        corr = np.zeros(2)
        t = 0.0
        for j in range(20):
            sign = 1.0 if j % 2 == 0 else -1.0
            true_excess = 10.0 if sign > 0 else 2.5
            side = 0 if sign > 0 or not per_side else 3
            scale = lr.scales_mps2[side]
            put_back = np.array([sign * scale * c, 0.0, 0.0])
            for k in range(3):
                lr.add_sample(
                    t, H, np.array([sign, 0.0, 0.0]), put_back, R_xz, 0.01 + 0.1 * k, corr
                )
                t += H
            lr.add_sample(t, H, zero, zero, R_xz, 0.21, corr)
            # the stance: the velocity is measured, the correction is what the prior got wrong
            corr = corr + np.array([sign * 3 * H * (true_excess - scale * c), 0.0])
            t += 0.1
            assert lr.add_sample(t, H, zero, zero, R_xz, 0.001, corr)
            t += 0.3
        learnt[per_side] = lr.scales_mps2 * c
    assert learnt[True][0] == pytest.approx(10.0, rel=0.05)
    assert learnt[True][3] == pytest.approx(2.5, rel=0.1)
    assert learnt[False][0] == pytest.approx(6.25, rel=0.1)  # one scale: their mean
