"""Leg-chain velocity bridge across a saturated accelerometer stretch (pure, no I/O).

While the accelerometer sits at its rail the filter's velocity rests on the saturation prior
(vio_graph/filter/imu_faults.py), which misses a push-off's loss by up to 0.4 m/s. The leg
gives a second view of the same velocity change: the camera is carried by the chain
hip -> thigh -> knee -> shank -> camera, so

    v_cam = v_hip + d/dt [R(th_thigh) (0, -L_thigh) + R(th_shank) c_shank]

(``c_shank`` the camera in the shank frame, the angles from the thigh pitch and the knee
encoder, vio_graph/kinematics.py). The hip, carried by the other leg, moves smoothly: over
the 30-70 ms of a clipped stretch its velocity changes by 0.03-0.26 m/s (simulated upstair,
seeds 1-2; RMS 0.10-0.15) while the shank's push-off changes the camera's by 1-3.5 m/s. So
with the hip's velocity held, the camera's velocity change over a stretch is the change of
the chain term, and the camera's velocity after the stretch is its velocity before plus that
change (:meth:`LegChainBridge.observation`). The foot is no help here: at the clipped samples
the simulated toe and heel both move at 0.6-4.6 m/s (the push-off clips after toe-off), so a
foot-contact constraint does not hold.

The observation's noise is honest: the hip's change (``hip_accel_sigma_mps2`` times the
stretch's length) and the encoders' rate noise (``rate_sigma_mps``) on each axis; optionally
(off by default, docs/robustness.md) also the chain velocity's own discretisation error at
each end, estimated from the joints (:func:`chain_velocity_discretisation_xz`), and the ends
by the five-point derivative (``fourth_order``). The filter
fuses it as the change it is (``BridgeObservation.change_xz_mps``, against a copy of its
velocity at the stretch's start: ``SagittalEskf.update_velocity_change``), so its own error
from before the stretch is not counted again; as a velocity (``velocity_xz_mps``, for the
smoothers' prior and ``saturation_bridge_relative: false``) the noise also holds the filter's
velocity covariance before the stretch. The filter gates it with its chi-square test, so
vision, the saturation prior and the chain arbitrate. It acts only across a stretch the fault
monitor flagged as saturated: a clean recording never opens one.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np
from numpy.typing import ArrayLike, NDArray

from vio_graph.types import JointAngles


@dataclass(frozen=True)
class BridgeObservation:
    """The camera velocity (m/s, ground x-z) at ``timestamp_s`` the chain implies, and its
    covariance ((m/s)^2)."""

    timestamp_s: float
    velocity_xz_mps: NDArray[np.float64]
    cov: NDArray[np.float64]
    #: the same as a change (m/s) from the velocity at the stretch's start to now, and its
    #: covariance without the filter's own velocity covariance at the start ((m/s)^2)
    change_xz_mps: NDArray[np.float64]
    change_cov: NDArray[np.float64]
    #: the clipped stretch's start and end (the filter's times, s), for
    #: :meth:`LegChainBridge.discretisation_cov`; None if not given
    stretch_s: tuple[float, float] | None = None


def _rot_deriv(theta: float, u: NDArray[np.float64]) -> NDArray[np.float64]:
    """d/dtheta of geometry.rotate_xz(theta, u) = R'(theta) u."""
    c, s = np.cos(theta), np.sin(theta)
    return np.array([-s * u[0] + c * u[1], -c * u[0] - s * u[1]])


def chain_velocity_xz(
    joints: Sequence[JointAngles],
    t_s: float,
    thigh_length_m: float,
    camera_in_shank_xz_m: ArrayLike,
) -> NDArray[np.float64] | None:
    """The camera's velocity relative to the hip (m/s, ground x-z) at ``t_s``, from the joint
    samples by a central difference over their period; None unless samples cover ``t_s``
    on both sides by one period."""
    if len(joints) < 3:
        return None
    ts = np.array([j.timestamp_s for j in joints])
    h = float(np.median(np.diff(ts)))
    if not h > 0 or ts[0] > t_s - h + 1e-9 or ts[-1] < t_s + h - 1e-9:
        return None
    thigh = np.array([-j.thigh_pitch_rad for j in joints])  # thigh segment pitch
    shank = np.array([j.knee_rad - j.thigh_pitch_rad for j in joints])  # shank segment pitch
    th_t = float(np.interp(t_s, ts, thigh))
    th_s = float(np.interp(t_s, ts, shank))
    rate_t = (np.interp(t_s + h, ts, thigh) - np.interp(t_s - h, ts, thigh)) / (2 * h)
    rate_s = (np.interp(t_s + h, ts, shank) - np.interp(t_s - h, ts, shank)) / (2 * h)
    u_thigh = np.array([0.0, -float(thigh_length_m)])
    c = np.asarray(camera_in_shank_xz_m, dtype=float)
    return rate_t * _rot_deriv(th_t, u_thigh) + rate_s * _rot_deriv(th_s, c)


def chain_velocity_second_difference_xz(
    joints: Sequence[JointAngles],
    t_s: float,
    thigh_length_m: float,
    camera_in_shank_xz_m: ArrayLike,
) -> NDArray[np.float64] | None:
    """D(t+h) - 2 D(t) + D(t-h) (m/s, ground x-z): the second difference of the chain
    velocity :func:`chain_velocity_xz` (D) over the joints' period h; None unless samples
    cover ``t_s`` on both sides by two periods. ``D(t) - this / 6`` is the five-point
    (fourth-order) derivative."""
    ts = [j.timestamp_s for j in joints]
    if len(ts) < 5:
        return None
    h = float(np.median(np.diff(ts)))
    if not h > 0:
        return None
    vs = [
        chain_velocity_xz(joints, t_s + k * h, thigh_length_m, camera_in_shank_xz_m)
        for k in (-1, 0, 1)
    ]
    if vs[0] is None or vs[1] is None or vs[2] is None:
        return None
    return vs[2] - 2.0 * vs[1] + vs[0]


def chain_velocity_discretisation_xz(
    joints: Sequence[JointAngles],
    t_s: float,
    thigh_length_m: float,
    camera_in_shank_xz_m: ArrayLike,
) -> float | None:
    """The sigma (m/s, per ground axis, the same on x and z) of :func:`chain_velocity_xz`
    at ``t_s`` from its own discretisation, estimated from the joints: half the norm of the
    second difference of the chain velocity over the neighbouring joint periods,
    ||D(t+h) - 2 D(t) + D(t-h)|| / 2 (D the central difference, h the joints' period);
    None unless samples cover ``t_s`` on both sides by two periods. The norm, not each
    axis: the error points along the velocity's change, which turns with the shank during
    a push-off, so one axis's second difference can be smaller than that axis's error.

    The central difference is the mean of the velocity over [t-h, t+h]. For a velocity
    that is smooth at the joints' rate its error is h^2 v''/6 and the second difference
    is h^2 v'', so the estimate is 3x the error. For an acceleration that steps at t (a
    push-off or a heel strike within one joint period, which is what clips an
    accelerometer) the error is a h/4 and the second difference a h/2: the estimate is
    the error. So it bounds the error in both cases without a constant fitted to a gait;
    it is the first-order analogue of the fourth differences the smoothers use for the
    IMU's own discretisation."""
    d2v = chain_velocity_second_difference_xz(joints, t_s, thigh_length_m, camera_in_shank_xz_m)
    return None if d2v is None else float(np.linalg.norm(d2v)) / 2.0


class LegChainBridge:
    """Opens at the first saturated sample, closes at the first trusted one after it, and
    gives one velocity observation per stretch once the joints cover its end.

    Call :meth:`before_saturated` before the filter propagates with a saturated sample,
    :meth:`after_trusted` after it propagated with a trusted one while :attr:`active`, then
    :meth:`observation` with the joint history. Nothing is stored on a clean stream.
    """

    def __init__(
        self,
        thigh_length_m: float,
        camera_in_shank_xz_m: ArrayLike,
        hip_accel_sigma_mps2: float,
        rate_sigma_mps: float,
        max_wait_s: float = 0.1,
        discretisation_sigma: bool = False,
        fourth_order: bool = False,
    ) -> None:
        self._lt = float(thigh_length_m)
        self._disc = bool(discretisation_sigma)
        self._fourth = bool(fourth_order)
        self._c = np.asarray(camera_in_shank_xz_m, dtype=float).reshape(2)
        self._a_sig = float(hip_accel_sigma_mps2)
        self._r_sig = float(rate_sigma_mps)
        self._max_wait_s = float(max_wait_s)
        self._now_s = -np.inf  # the filter's time at the last after_trusted
        self._start: tuple[float, NDArray, NDArray] | None = None  # open stretch: t, v, P_v
        # a closed stretch waiting for its joints: (start, end) states
        self._pending: tuple[tuple, tuple] | None = None
        self.n_stretches = 0  #: stretches closed
        self.n_observations = 0  #: observations handed out
        self.n_unbridged = 0  #: stretches without joints in time (or interrupted)

    @property
    def max_wait_s(self) -> float:
        """How long (s) after a stretch's end the observation waits for the joints."""
        return self._max_wait_s

    @property
    def active(self) -> bool:
        """True while a stretch is open or waits for its joints."""
        return self._start is not None or self._pending is not None

    @property
    def opened(self) -> bool:
        """True while a stretch is open (a saturated sample since the last trusted one)."""
        return self._start is not None

    def before_saturated(
        self, t_s: float, velocity_xz_mps: ArrayLike, cov_velocity: ArrayLike
    ) -> None:
        """Call before the filter propagates with a saturated sample (the filter's time,
        velocity and velocity covariance then): opens a stretch unless one is open."""
        if self._start is not None:
            return
        if self._pending is not None:  # a new stretch before the last one was bridged
            self._pending = None
            self.n_unbridged += 1
        self._start = (
            float(t_s),
            np.array(velocity_xz_mps, dtype=float),
            np.array(cov_velocity, dtype=float),
        )

    def after_trusted(
        self, t_s: float, velocity_xz_mps: ArrayLike, corrections_mps: ArrayLike
    ) -> None:
        """Call after the filter propagated with a trusted sample while :attr:`active`: the
        first one after a stretch closes it (the filter's time, velocity and summed velocity
        corrections then); later ones only advance the time."""
        self._now_s = float(t_s)
        if self._start is not None:
            self._pending = (
                self._start,
                (
                    float(t_s),
                    np.array(velocity_xz_mps, dtype=float),
                    np.array(corrections_mps, dtype=float),
                ),
            )
            self._start = None
            self.n_stretches += 1

    def observation(
        self,
        joints: Sequence[JointAngles],
        velocity_now_xz_mps: ArrayLike,
        corrections_now_mps: ArrayLike,
    ) -> BridgeObservation | None:
        """The pending stretch's observation of the camera velocity now, or None (nothing
        pending, or its joints not in yet). The chain's change applies from the stretch's
        start to its end; from the end to now the filter's own IMU propagation is trusted
        (its velocity change minus the corrections measurements made since)."""
        if self._pending is None:
            return None
        (t0, v0, P0), (t2, v2, c2) = self._pending
        k0 = chain_velocity_xz(joints, t0, self._lt, self._c)
        k2 = chain_velocity_xz(joints, t2, self._lt, self._c)
        d0: NDArray | None = np.zeros(2)
        d2: NDArray | None = np.zeros(2)
        if (self._disc or self._fourth) and k0 is not None and k2 is not None:
            d0 = chain_velocity_second_difference_xz(joints, t0, self._lt, self._c)
            d2 = chain_velocity_second_difference_xz(joints, t2, self._lt, self._c)
        if k0 is None or k2 is None or d0 is None or d2 is None:
            if self._now_s - t2 > self._max_wait_s:
                self._pending = None
                self.n_unbridged += 1
            return None
        self._pending = None
        corrected = np.asarray(corrections_now_mps, float) - c2
        since = np.asarray(velocity_now_xz_mps, float) - v2 - corrected
        # the discretisation's error at each end: between D''/6 (a velocity smooth at the
        # joints' rate) and D''/2 (an acceleration step); the five-point derivative takes
        # out the first, its sigma is the rest (chain_velocity_discretisation_xz)
        if self._fourth:
            k0, k2 = k0 - d0 / 6.0, k2 - d2 / 6.0
        frac = 1.0 / 3.0 if self._fourth else 0.5
        disc_var = (frac * np.linalg.norm(d0)) ** 2 + (frac * np.linalg.norm(d2)) ** 2
        change = (k2 - k0) + since
        hip = self._a_sig * (t2 - t0)
        change_cov = np.eye(2) * (hip**2 + self._r_sig**2 + (disc_var if self._disc else 0.0))
        self.n_observations += 1
        return BridgeObservation(
            self._now_s, v0 + change, P0 + change_cov, change, change_cov, (t0, t2)
        )

    def discretisation_cov(
        self, joints: Sequence[JointAngles], t0_s: float, t2_s: float
    ) -> NDArray[np.float64] | None:
        """The covariance ((m/s)^2, 2x2, ground x-z) of the chain's change across the stretch
        from ``t0_s`` to ``t2_s`` from its own discretisation at the two ends: the term the
        filter adds to the bridge's noise with ``discretisation_sigma`` (the same fraction of
        each end's second difference, :func:`chain_velocity_discretisation_xz`). Zero if the
        observation already holds it (``discretisation_sigma`` on); None while the joints do
        not cover both ends by two periods. For the smoothers
        (``smoother.factors.saturation_bridge_discretisation``): the filter's own fusion
        is left as configured."""
        if self._disc:
            return np.zeros((2, 2))
        d0 = chain_velocity_second_difference_xz(joints, t0_s, self._lt, self._c)
        d2 = chain_velocity_second_difference_xz(joints, t2_s, self._lt, self._c)
        if d0 is None or d2 is None:
            return None
        frac = 1.0 / 3.0 if self._fourth else 0.5
        return np.eye(2) * ((frac * np.linalg.norm(d0)) ** 2 + (frac * np.linalg.norm(d2)) ** 2)
