"""IMU sampling for GTSAM's preintegration (pure numpy, no graph).

GTSAM integrates each IMU step with the values it is given at the step's start. Feeding the
raw samples that way costs millimetres over a keyframe interval on a swinging shank, so the
smoother hands it step means instead: knots at the keyframe times and the samples between
them (:func:`_imu_knots`), curvature-corrected step means of a locally quadratic signal
(:func:`_quadratic_step_means`), with the specific force averaged either in the frame of the
interval's start (:func:`common_frame_samples`, the default) or in the moving frame and turned
by half a step (:func:`midpoint_samples`); :func:`held_samples` is the raw baseline. The model
error that sampling leaves around gait events is estimated by
:func:`discretization_velocity_var` and enters the noise of
:func:`make_preintegration_params`.
"""

from __future__ import annotations

import functools
from collections.abc import Callable, Sequence

import gtsam
import numpy as np
from numpy.typing import ArrayLike, NDArray

from vio_graph.errors import EstimationError
from vio_graph.smoother.config import SmootherConfig

#: Two timestamps closer than this are the same instant (s).
TIME_TOL_S = 1e-6

__all__ = [
    "SAMPLERS",
    "TIME_TOL_S",
    "common_frame_samples",
    "compiled_discretization_var",
    "compiled_sampler",
    "discretization_rotation_var",
    "discretization_velocity_var",
    "distrust_step_variances",
    "held_samples",
    "make_preintegration_params",
    "midpoint_samples",
    "set_white_noise",
    "so3_exp",
]


# ----------------------------------------------------------------------------------------------
# rotations and step means
# ----------------------------------------------------------------------------------------------
def so3_exp(rotvec: ArrayLike) -> NDArray[np.float64]:
    """Rodrigues' formula, vectorised: (..., 3) rotation vectors (rad) -> (..., 3, 3)."""
    w = np.asarray(rotvec, dtype=float)
    theta = np.linalg.norm(w, axis=-1)[..., None, None]
    K = np.zeros(w.shape[:-1] + (3, 3))
    K[..., 0, 1], K[..., 0, 2] = -w[..., 2], w[..., 1]
    K[..., 1, 0], K[..., 1, 2] = w[..., 2], -w[..., 0]
    K[..., 2, 0], K[..., 2, 1] = -w[..., 1], w[..., 0]
    small = theta < 1e-8
    th = np.where(small, 1.0, theta)
    a = np.where(small, 1.0, np.sin(th) / th)
    b = np.where(small, 0.5, (1.0 - np.cos(th)) / th**2)
    return np.eye(3) + a * K + b * (K @ K)


def _second_derivative(t: NDArray[np.float64], y: NDArray[np.float64]) -> NDArray[np.float64]:
    """Second time derivative (N, 3) of sampled y (N, 3) by non-uniform central differences.

    The two end samples copy their neighbour; fewer than 3 samples give zeros.
    """
    ypp = np.zeros_like(y)
    if t.size < 3:
        return ypp
    h0, h1 = np.diff(t)[:-1, None], np.diff(t)[1:, None]
    ypp[1:-1] = 2.0 * ((y[2:] - y[1:-1]) / h1 - (y[1:-1] - y[:-2]) / h0) / (h0 + h1)
    ypp[0], ypp[-1] = ypp[1], ypp[-2]
    return ypp


def _imu_knots(
    times_s: ArrayLike,
    accel_mps2: ArrayLike,
    gyro_radps: ArrayLike,
    t0_s: float,
    t1_s: float,
    substeps: int = 1,
) -> tuple[NDArray[np.float64], NDArray[np.float64], NDArray[np.float64], NDArray[np.float64]]:
    """Checked IMU arrays and the step knots over [t0_s, t1_s]: t0, the samples strictly
    inside, t1; with ``substeps`` > 1 each of those steps split into that many equal ones
    (``SmootherConfig.preintegration_substeps``)."""
    t = np.asarray(times_s, dtype=float)
    a = np.asarray(accel_mps2, dtype=float).reshape(-1, 3)
    g = np.asarray(gyro_radps, dtype=float).reshape(-1, 3)
    if t.size == 0:
        raise EstimationError("no IMU samples to preintegrate")
    if t1_s <= t0_s:
        raise EstimationError(f"empty preintegration interval [{t0_s}, {t1_s}]")
    if substeps < 1:
        raise EstimationError(f"substeps must be >= 1, got {substeps}")
    inner = t[(t > t0_s + TIME_TOL_S) & (t < t1_s - TIME_TOL_S)]
    knots = np.concatenate([[t0_s], inner, [t1_s]])
    if substeps > 1:
        frac = np.arange(substeps) / substeps
        split = knots[:-1, None] + np.diff(knots)[:, None] * frac[None, :]
        knots = np.concatenate([split.ravel(), knots[-1:]])
    return t, a, g, knots


def _quadratic_step_means(
    t: NDArray[np.float64], knots: NDArray[np.float64]
) -> tuple[Callable[[NDArray[np.float64]], NDArray[np.float64]], NDArray[np.float64]]:
    """Step means over the knot intervals of a signal sampled at ``t``, treated as locally
    quadratic: the trapezoid minus ``dt^2/12 y''``, with knot values between samples
    interpolated with the same curvature term (y'' from central differences). Returns the
    function (N, 3) -> (K, 3) and the step lengths dt (K, 1)."""
    lo = np.clip(np.searchsorted(t, knots, side="right") - 1, 0, t.size - 1)
    hi = np.clip(lo + 1, 0, t.size - 1)
    inside = (knots > t[0]) & (knots < t[-1])
    curv = np.where(inside, 0.5 * (knots - t[lo]) * (knots - t[hi]), 0.0)[:, None]
    dt = np.diff(knots)[:, None]

    def step_means(y: NDArray[np.float64]) -> NDArray[np.float64]:
        ypp = _second_derivative(t, y)
        ypp_k = np.stack([np.interp(knots, t, ypp[:, i]) for i in range(3)], axis=-1)
        y_k = np.stack([np.interp(knots, t, y[:, i]) for i in range(3)], axis=-1)
        y_k = y_k + curv * ypp_k
        return 0.5 * (y_k[1:] + y_k[:-1]) - dt**2 / 12.0 * 0.5 * (ypp_k[1:] + ypp_k[:-1])

    return step_means, dt


def midpoint_samples(
    times_s: ArrayLike,
    accel_mps2: ArrayLike,
    gyro_radps: ArrayLike,
    t0_s: float,
    t1_s: float,
    substeps: int = 1,
) -> tuple[NDArray[np.float64], NDArray[np.float64], NDArray[np.float64]]:
    """Midpoint-rule IMU steps covering [t0_s, t1_s].

    Knots are t0, the samples strictly inside, and t1. Each step between consecutive knots gets
    the mean of the signal over the step and the mean specific force rotated by half the
    step's rotation, so that GTSAM's start-of-step integration uses the mid-step attitude.
    The signal is treated as locally quadratic: the step mean is the trapezoid minus
    ``dt^2/12 y''`` and values at t0/t1 between samples are interpolated with the same
    curvature term (y'' from central differences of the samples). On a shank turning at
    3 rad/s this removes the trapezoid's ~1e-4 rad per 0.1 s rotation error, which is 2-3
    sigma of the MTi-1 gyro noise over that time. Outside the samples the signal is held.

    Args:
        times_s: (N,) increasing sample times, s. Must be non-empty.
        accel_mps2: (N, 3) specific force in the IMU frame.
        gyro_radps: (N, 3) angular rate in the IMU frame.
    Returns:
        ``accel_mid (K, 3)``, ``gyro_mid (K, 3)``, ``dt_s (K,)`` with sum(dt) = t1 - t0.
    """
    t, a, g, knots = _imu_knots(times_s, accel_mps2, gyro_radps, t0_s, t1_s, substeps)
    step_means, dt = _quadratic_step_means(t, knots)

    g_mid = step_means(g)
    a_mean = step_means(a)
    a_mid = np.einsum("nij,nj->ni", so3_exp(0.5 * g_mid * dt), a_mean)
    return a_mid, g_mid, dt[:, 0]


def common_frame_samples(
    times_s: ArrayLike,
    accel_mps2: ArrayLike,
    gyro_radps: ArrayLike,
    t0_s: float,
    t1_s: float,
    substeps: int = 1,
) -> tuple[NDArray[np.float64], NDArray[np.float64], NDArray[np.float64]]:
    """Like :func:`midpoint_samples`, but the specific force is averaged in one frame.

    The midpoint rule averages the specific force in the moving IMU frame and then turns the
    mean by half the step's rotation. For gravity, which is fixed in the world and so turns
    at -omega in the IMU frame, that mean is short by (omega dt)^2 / 24: 2.6e-3 m/s^2 at
    8 rad/s and 100 Hz, always towards less support, so the preintegrated velocity sinks
    by ~0.3-1 mm/s per 0.1 s and a long smoothing window drifts down. Here every sample is
    first rotated into the frame of the interval's start, f_j -> R(t_j) f_j with R from the
    same per-step gyro means GTSAM integrates, the curvature-corrected step means are taken
    there (a world-fixed vector is then constant and exact), and each step's mean is handed
    back in the step-start frame, where GTSAM applies it.
    """
    t, a, g, knots = _imu_knots(times_s, accel_mps2, gyro_radps, t0_s, t1_s, substeps)
    step_means, dt = _quadratic_step_means(t, knots)

    g_mid = step_means(g)
    steps = so3_exp(g_mid * dt)  # (K, 3, 3) step rotations, as GTSAM integrates them
    R_knot = np.empty((knots.size, 3, 3))
    R_knot[0] = np.eye(3)
    for k in range(steps.shape[0]):
        R_knot[k + 1] = R_knot[k] @ steps[k]
    # rotation at each sample: from the knot at or before it (the first step's rate before t0,
    # the last step's after t1)
    k_of = np.clip(np.searchsorted(knots, t, side="right") - 1, 0, g_mid.shape[0] - 1)
    R_t = R_knot[k_of] @ so3_exp(g_mid[k_of] * (t - knots[k_of])[:, None])
    F = np.einsum("nij,nj->ni", R_t, a)  # specific force in the interval-start frame
    F_mean = step_means(F)
    a_in = np.einsum("nji,nj->ni", R_knot[:-1], F_mean)  # back into each step-start frame
    return a_in, g_mid, dt[:, 0]


def held_samples(
    times_s: ArrayLike,
    accel_mps2: ArrayLike,
    gyro_radps: ArrayLike,
    t0_s: float,
    t1_s: float,
    substeps: int = 1,
) -> tuple[NDArray[np.float64], NDArray[np.float64], NDArray[np.float64]]:
    """Raw IMU steps covering [t0_s, t1_s]: each step uses the last sample at or before its
    start (what feeding samples straight into ``integrateMeasurement`` does). Same outputs
    as :func:`midpoint_samples`; kept as the ablation's baseline."""
    t, a, g, knots = _imu_knots(times_s, accel_mps2, gyro_radps, t0_s, t1_s, substeps)
    idx = np.clip(np.searchsorted(t, knots[:-1] + TIME_TOL_S, side="right") - 1, 0, t.size - 1)
    return a[idx], g[idx], np.diff(knots)


def discretization_velocity_var(
    times_s: ArrayLike, accel_mps2: ArrayLike, t0_s: float, t1_s: float
) -> float:
    """Unscaled variance (m^2/s^2) of the velocity error that sampling the specific force
    leaves over [t0_s, t1_s]: ``sum_j (h |D4_j|)^2`` over the windows j of five consecutive
    samples that touch the interval, D4 the fourth difference (m/s^2) and h the sample period.

    A signal that is locally cubic at the sample rate has D4 ~ 0 and is integrated almost
    exactly by :func:`midpoint_samples`; gait events (heel strike, toe off) are not, and there
    the error is proportional to D4. On simulated stair gait (100 Hz) the midpoint rule's
    velocity error over 0.1 s is ~0.5 mm/s in smooth phases but 3-16 mm/s around gait events,
    10-40x GTSAM's white-noise sigma with the datasheet density; scaled by
    ``SmootherConfig.imu_discretization_gain`` this term is added to the preintegration
    covariance (:func:`make_preintegration_params`). Windows that need samples not yet
    received are left out.
    """
    t = np.asarray(times_s, dtype=float)
    a = np.asarray(accel_mps2, dtype=float).reshape(-1, 3)
    if t.size < 5:
        return 0.0
    d4 = a[:-4] - 4.0 * a[1:-3] + 6.0 * a[2:-2] - 4.0 * a[3:-1] + a[4:]
    h = (t[4:] - t[:-4]) / 4.0
    touch = (t[4:] > t0_s - TIME_TOL_S) & (t[:-4] < t1_s + TIME_TOL_S)
    return float(np.sum((h[touch, None] * d4[touch]) ** 2))


def discretization_rotation_var(
    times_s: ArrayLike, gyro_radps: ArrayLike, t0_s: float, t1_s: float
) -> float:
    """Unscaled variance (rad^2) of the rotation error that sampling the angular rate leaves
    over [t0_s, t1_s]: the sum of :func:`discretization_velocity_var` applied to the gyro,
    ``sum_j (h |D4_j|)^2`` with D4 the gyro's fourth differences (rad/s).

    The curvature-corrected step mean (:func:`_quadratic_step_means`) integrates a quartic
    signal over one step with an error of exactly (11/720) h D4 (``GYRO_DISCRETIZATION_GAIN``
    in smoother/config.py), so ``SmootherConfig.gyro_discretization_gain`` = 11/720 turns this
    sum into the rotation variance of a signal that is locally quartic at the sample rate,
    each window's error counted as independent. At 50 Hz on stair gait this is what bounds
    the preintegrated rotation around heel strikes (0.03 deg RMS per 0.1 s, ~15x the MTi-1's
    white gyro noise); at 100 Hz it is 4-30x smaller (D4 ~ h^4 in smooth phases, ~h^0 at a
    kink, and the sum is taken with h^2)."""
    return discretization_velocity_var(times_s, gyro_radps, t0_s, t1_s)


def distrust_variances(
    times_s: ArrayLike, extra_sigmas: Sequence[tuple[float, float]], t0_s: float, t1_s: float
) -> tuple[float, float]:
    """Velocity (m^2/s^2) and rotation (rad^2) variances that the distrusted samples touching
    [t0_s, t1_s] add to a preintegrated interval: sum of (sigma h)^2 over the samples, h the
    sample period (``ImuSample.accel_extra_sigma_mps2`` / ``gyro_extra_sigma_radps``, set by
    vio_graph/filter/imu_faults.py). (0, 0) when every sample is trusted."""
    x = np.asarray(extra_sigmas, dtype=float).reshape(-1, 2)
    if x.size == 0 or not np.any(x > 0):
        return 0.0, 0.0
    t = np.asarray(times_s, dtype=float)
    h = np.median(np.diff(t)) if t.size > 1 else t1_s - t0_s
    touch = (t > t0_s - h + TIME_TOL_S) & (t < t1_s + h - TIME_TOL_S)
    v = np.sum((x[touch] * h) ** 2, axis=0)
    return float(v[0]), float(v[1])


def distrust_step_variances(
    times_s: ArrayLike,
    extra_sigmas: Sequence[tuple[float, float]],
    t0_s: float,
    dt_s: ArrayLike,
) -> tuple[NDArray[np.float64], NDArray[np.float64]]:
    """Per preintegration step, the velocity (m^2/s^2) and rotation (rad^2) variances that the
    distrusted samples add: each sample's (sigma h)^2 (h the sample period) goes to the steps
    that its period [t - h/2, t + h/2] overlaps, in proportion to the overlap. Steps start at
    ``t0_s`` and last ``dt_s`` (K,). The sum over the steps is :func:`distrust_variances` for
    the samples inside the interval; unlike spreading that sum evenly over the interval, it
    keeps WHEN the distrusted samples were, so the position uncertainty a clipped heel strike
    leaves grows with the time since it, as the error does."""
    dt = np.asarray(dt_s, dtype=float).reshape(-1)
    vel, rot = np.zeros(dt.size), np.zeros(dt.size)
    x = np.asarray(extra_sigmas, dtype=float).reshape(-1, 2)
    t = np.asarray(times_s, dtype=float)
    if dt.size == 0 or x.size == 0 or not np.any(x > 0):
        return vel, rot
    h = float(np.median(np.diff(t))) if t.size > 1 else float(dt.sum())
    ends = t0_s + np.cumsum(dt)
    starts = ends - dt
    for j in np.flatnonzero(np.any(x > 0, axis=1)):
        lo, hi = t[j] - 0.5 * h, t[j] + 0.5 * h
        frac = np.clip(np.minimum(ends, hi) - np.maximum(starts, lo), 0.0, None) / h
        vel += frac * (x[j, 0] * h) ** 2
        rot += frac * (x[j, 1] * h) ** 2
    return vel, rot


def distrust_step_covariances(
    times_s: ArrayLike,
    extra_sigmas: Sequence[tuple[float, float]],
    extra_covs: Sequence[NDArray[np.float64] | None],
    t0_s: float,
    dt_s: ArrayLike,
) -> NDArray[np.float64] | None:
    """:func:`distrust_step_variances`'s velocity variance per step as a (K, 3, 3) covariance
    in the sample axes, with a saturated sample's variance on its clipped axes only
    (``extra_covs``, ``ImuSample.accel_extra_cov_m2ps4``; None: its sigma on every axis).
    None when no sample touching the steps carries a covariance (then the isotropic
    variances are the answer)."""
    dt = np.asarray(dt_s, dtype=float).reshape(-1)
    if dt.size == 0 or all(c is None for c in extra_covs):
        return None
    x = np.asarray(extra_sigmas, dtype=float).reshape(-1, 2)
    t = np.asarray(times_s, dtype=float)
    h = float(np.median(np.diff(t))) if t.size > 1 else float(dt.sum())
    ends = t0_s + np.cumsum(dt)
    starts = ends - dt
    out = np.zeros((dt.size, 3, 3))
    touched = False
    for j in np.flatnonzero(x[:, 0] > 0):
        lo, hi = t[j] - 0.5 * h, t[j] + 0.5 * h
        frac = np.clip(np.minimum(ends, hi) - np.maximum(starts, lo), 0.0, None) / h
        if not np.any(frac > 0):
            continue
        c = extra_covs[int(j)]
        if c is not None:
            touched = True
        cov_j = np.eye(3) * x[j, 0] ** 2 if c is None else np.asarray(c, dtype=float)
        out += frac[:, None, None] * (h * h) * cov_j
    return out if touched else None


_EYE3 = np.eye(3)
_EYE3.flags.writeable = False


def make_preintegration_params(
    config: SmootherConfig,
    extra_velocity_var_m2ps2: float = 0.0,
    duration_s: float = 1.0,
    extra_rotation_var_rad2: float = 0.0,
) -> gtsam.PreintegrationCombinedParams:
    """GTSAM combined preintegration parameters (z up, MTi-1 noise densities squared).

    ``extra_velocity_var_m2ps2`` (the model error of the sampled signal over an interval of
    ``duration_s``, :func:`discretization_velocity_var` times the gain squared, plus the
    distrust of saturated or repaired samples) is spread over the interval as extra
    accelerometer white noise; ``extra_rotation_var_rad2`` likewise as gyro noise.
    """
    p = gtsam.PreintegrationCombinedParams.MakeSharedU(config.gravity_mps2)
    set_white_noise(p, config, extra_velocity_var_m2ps2, duration_s, extra_rotation_var_rad2)
    integ, bias_acc, bias_omega = _constant_covariances(
        config.integration_sigma_m,
        config.accel_bias_rw_mps3_per_sqrt_hz,
        config.gyro_bias_rw_radps2_per_sqrt_hz,
    )
    p.setIntegrationCovariance(integ)
    p.setBiasAccCovariance(bias_acc)
    p.setBiasOmegaCovariance(bias_omega)
    return p


def set_white_noise(
    p: gtsam.PreintegrationCombinedParams,
    config: SmootherConfig,
    extra_velocity_var_m2ps2: float = 0.0,
    duration_s: float = 1.0,
    extra_rotation_var_rad2: float = 0.0,
) -> None:
    """Set the accelerometer and gyro covariances of ``p`` as
    :func:`make_preintegration_params` does (the only two that change between keyframes)."""
    acc_var = config.accel_noise_density_mps2_per_sqrt_hz**2 + extra_velocity_var_m2ps2 / duration_s
    # (one shared identity: a fresh np.eye per setter was most of this function's ~80 us)
    p.setAccelerometerCovariance(_EYE3 * acc_var)
    gyr_var = config.gyro_noise_density_radps_per_sqrt_hz**2 + extra_rotation_var_rad2 / duration_s
    p.setGyroscopeCovariance(_EYE3 * gyr_var)


@functools.lru_cache(maxsize=8)
def _constant_covariances(
    integration_sigma: float, accel_bias_rw: float, gyro_bias_rw: float
) -> tuple[NDArray[np.float64], NDArray[np.float64], NDArray[np.float64]]:
    """The three covariances of :func:`make_preintegration_params` that do not change from
    one keyframe to the next (the same products, made once; read-only, the setters copy)."""
    out = (
        _EYE3 * integration_sigma**2,
        _EYE3 * accel_bias_rw**2,
        _EYE3 * gyro_bias_rw**2,
    )
    for m in out:
        m.flags.writeable = False
    return out


def compiled_sampler(name: str) -> Callable[..., tuple] | None:
    """The compiled version of sampler ``name`` (``SAMPLERS``), or None: only
    "common_frame" has one (smoother/compiled_sampling.py, numba), used when the compiled
    kernels are on (``filter.fast_imu.imu_kernels``). Called as ``f(t, a, g, t0, t1,
    TIME_TOL_S, substeps)`` with float64 arrays; same outputs as the sampler to rounding."""
    from vio_graph.filter.fast_imu import imu_kernels

    if name != "common_frame" or imu_kernels() is None:
        return None
    from vio_graph.smoother.compiled_sampling import common_frame_steps

    return common_frame_steps


def compiled_discretization_var() -> Callable[..., float] | None:
    """The compiled :func:`discretization_velocity_var` (smoother/compiled_sampling.py, numba;
    the same float), or None when the compiled kernels are off. Called as ``f(t, a, t0, t1,
    TIME_TOL_S)`` with float64 arrays."""
    from vio_graph.filter.fast_imu import imu_kernels

    if imu_kernels() is None:
        return None
    from vio_graph.smoother.compiled_sampling import discretization_var

    return discretization_var


#: ``SmootherConfig.preintegration`` -> the step sampler it selects.
SAMPLERS: dict[
    str, Callable[..., tuple[NDArray[np.float64], NDArray[np.float64], NDArray[np.float64]]]
] = {
    "midpoint_curvature": midpoint_samples,
    "common_frame": common_frame_samples,
    "raw": held_samples,
}
