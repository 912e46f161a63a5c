"""Factor-graph construction for the sagittal camera + IMU smoother (pure, no I/O).

The graph extends the paper's SP-ESKF (eq. 5-8: IMU propagation corrected by ICP
displacements) into a smoothing problem over keyframes, and adds long-span constraints from
stair-nosing / obstacle corners seen from many keyframes.

Nodes (``gtsam.symbol_shorthand``)::

    X(i)  Pose3 of the IMU in the world frame (R_world_imu, world position), keyframe i
    V(i)  IMU velocity in the world frame (3,), m/s
    B(i)  imuBias.ConstantBias [accel (m/s^2), gyro (rad/s)] at keyframe i
    L(j)  Pose3 landmark of a corner track or of a stance anchor (the ankle planted during one
          stance): translation = its position (world, m); rotation fixed at identity by a
          tight prior (it only makes the built-in BetweenFactorPose3 usable as a "point seen
          from a pose" factor). One numbering for both kinds, in order of first sight (keys
          decide GTSAM's elimination order; a symbol of their own for anchors would change
          the last bits of every result)

Factors::

      prior(X0,V0,B0)      attitude+planar      attitude+planar
           |                    |                    |
          X0 --- IMU(0,1) ---- X1 --- IMU(1,2) ---- X2 ...    IMU = CombinedImuFactor
          V0 -------/          V1 -------/          V2         (also links B(i) -> B(i+1))
          B0 ------/           B1 ------/           B2
           \\____ disp(0,1) ___/ \\____ disp(1,2) ___/          disp = BetweenFactorPose3
           \\          |          /                             (robust)
            \\-------- L(j) -----/                             obs = BetweenFactorPose3
                    (prior y=0)                                 (robust)

- IMU: GTSAM's own preintegration (``PreintegrationCombinedParams.MakeSharedU(g)``, z up) fed
  with step means: curvature-corrected means of consecutive samples (and samples interpolated
  at the keyframe times), the specific force averaged in the frame of the interval's start
  (:func:`common_frame_samples`, default; :func:`midpoint_samples` averages in the moving
  frame and loses (omega dt)^2/24 of gravity). Noise: MTi-1 datasheet densities, bias random
  walks, plus the sampled-signal model error (:func:`discretization_velocity_var`).
- Displacement (paper's ICP output, eq. 3-4, chained frame to frame between keyframes with
  summed covariance): the camera moves by d (world x-z), the camera sits at
  ``c = t + R imu_p_cam``, so the IMU moves by ``t_j - t_i = d - (R_j - R_i) imu_p_cam``
  with the AHRS rotations. It enters as a BetweenFactorPose3 whose translation is that motion
  in frame i; the rotation part is the AHRS relative rotation with a loose sigma. The
  translation covariance is the front end's 2x2 (floored), rotated into frame j (where GTSAM
  expresses the error), with a loose lateral axis. Huber/Cauchy kernel.
- Landmark observation (corner minus camera position, world x-z): BetweenFactorPose3(X(i),
  L(j)) with translation ``R_i^T o + imu_p_cam``; with the landmark rotation fixed at identity
  the translation error is in world axes, so the front end's covariance enters unrotated.
  A stance observation (ankle minus camera) enters the same way, without the extra corner
  sigma.
- Attitude: PriorFactorPose3 on the rotation only (AHRS with heading removed, inflated sigma,
  huge translation sigma).
- Sagittal-plane priors: world-y of every keyframe position (PoseTranslationPrior3D; with
  ``factors.weak_position`` it also carries a weak absolute x-z prior at the initial guess,
  off by default because over a long trial those priors add up and pull the path towards
  the filter's drift) and world-y of every velocity (PriorFactorVector, loose on x and z).
  Landmarks get y = 0 and a weak x-z prior.
- First keyframe: tight pose prior, velocity prior at the filter's estimate, zero-bias prior.

All factors are GTSAM built-ins (no Python CustomFactor on the hot path).
"""

from __future__ import annotations

from collections.abc import Callable, Sequence
from dataclasses import dataclass, field

import gtsam
import numpy as np
from gtsam.symbol_shorthand import B, L, V, X
from numpy.typing import ArrayLike, NDArray

from vio_graph.errors import EstimationError
from vio_graph.geometry import matrix_from_quat_wxyz, remove_yaw, skew
from vio_graph.smoother.config import SmootherConfig
from vio_graph.types import (
    CornerObservation,
    Displacement2D,
    FrameEstimate,
    ImuSample,
    LandmarkKey,
    LandmarkObservation,
    StanceObservation,
)

#: Sigma used for "unconstrained" axes of a prior (tangent units).
LOOSE_SIGMA = 1e4
#: Two timestamps closer than this are the same instant (s).
TIME_TOL_S = 1e-6

__all__ = [
    "B",
    "L",
    "V",
    "X",
    "KeyframeGraphBuilder",
    "KeyframeUpdate",
    "camera_xz_cov_from_pose_cov",
    "imu_position_from_camera",
    "make_preintegration_params",
    "discretization_velocity_var",
    "midpoint_samples",
    "common_frame_samples",
    "robust_noise",
    "so3_exp",
]


# ----------------------------------------------------------------------------------------------
# small numeric helpers
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
    times_s: ArrayLike, accel_mps2: ArrayLike, gyro_radps: ArrayLike, t0_s: float, t1_s: float
) -> tuple[NDArray[np.float64], NDArray[np.float64], NDArray[np.float64], NDArray[np.float64]]:
    """Checked IMU arrays and the step knots over [t0_s, t1_s]: t0, the samples strictly
    inside, t1."""
    t = np.asarray(times_s, dtype=float)
    a = np.asarray(accel_mps2, dtype=float).reshape(-1, 3)
    g = np.asarray(gyro_radps, dtype=float).reshape(-1, 3)
    if t.size == 0:
        raise EstimationError("no IMU samples to preintegrate")
    if t1_s <= t0_s:
        raise EstimationError(f"empty preintegration interval [{t0_s}, {t1_s}]")
    inner = t[(t > t0_s + TIME_TOL_S) & (t < t1_s - TIME_TOL_S)]
    return t, a, g, np.concatenate([[t0_s], inner, [t1_s]])


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
) -> tuple[NDArray[np.float64], NDArray[np.float64], NDArray[np.float64]]:
    """Midpoint-rule IMU steps covering [t0_s, t1_s] (gtsam-notes, "IMU preintegration").

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
    t, a, g, knots = _imu_knots(times_s, accel_mps2, gyro_radps, t0_s, t1_s)
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
    t, a, g, knots = _imu_knots(times_s, accel_mps2, gyro_radps, t0_s, t1_s)
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
) -> tuple[NDArray[np.float64], NDArray[np.float64], NDArray[np.float64]]:
    """Raw IMU steps covering [t0_s, t1_s]: each step uses the last sample at or before its
    start (what feeding samples straight into ``integrateMeasurement`` does). Same outputs
    as :func:`midpoint_samples`; kept as the ablation's baseline."""
    t, a, g, knots = _imu_knots(times_s, accel_mps2, gyro_radps, t0_s, t1_s)
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


def distrust_variances(
    times_s: Sequence[float], extra_sigmas: Sequence[tuple[float, float]], t0_s: float,
    t1_s: float
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


def make_preintegration_params(
    config: SmootherConfig, extra_velocity_var_m2ps2: float = 0.0, duration_s: float = 1.0,
    extra_rotation_var_rad2: float = 0.0,
) -> gtsam.PreintegrationCombinedParams:
    """GTSAM combined preintegration parameters (z up, MTi-1 noise densities squared).

    ``extra_velocity_var_m2ps2`` (the model error of the sampled signal over an interval of
    ``duration_s``, :func:`discretization_velocity_var` times the gain squared, plus the
    distrust of saturated or repaired samples) is spread over the interval as extra
    accelerometer white noise; ``extra_rotation_var_rad2`` likewise as gyro noise.
    """
    p = gtsam.PreintegrationCombinedParams.MakeSharedU(config.gravity_mps2)
    acc_var = config.accel_noise_density_mps2_per_sqrt_hz**2 + extra_velocity_var_m2ps2 / duration_s
    p.setAccelerometerCovariance(np.eye(3) * acc_var)
    gyr_var = config.gyro_noise_density_radps_per_sqrt_hz**2 + extra_rotation_var_rad2 / duration_s
    p.setGyroscopeCovariance(np.eye(3) * gyr_var)
    p.setIntegrationCovariance(np.eye(3) * config.integration_sigma_m**2)
    p.setBiasAccCovariance(np.eye(3) * config.accel_bias_rw_mps3_per_sqrt_hz**2)
    p.setBiasOmegaCovariance(np.eye(3) * config.gyro_bias_rw_radps2_per_sqrt_hz**2)
    return p


def robust_noise(config: SmootherConfig, base: gtsam.noiseModel.Base,
                 kernel: str | None = None, threshold: float | None = None
                 ) -> gtsam.noiseModel.Base:
    """Wrap ``base`` in an M-estimator (threshold in whitened units); by default the
    configured ``robust_kernel`` / ``robust_threshold``."""
    kernel = config.robust_kernel if kernel is None else kernel
    threshold = config.robust_threshold if threshold is None else threshold
    if kernel == "huber":
        est = gtsam.noiseModel.mEstimator.Huber.Create(threshold)
    elif kernel == "cauchy":
        est = gtsam.noiseModel.mEstimator.Cauchy.Create(threshold)
    else:
        return base
    return gtsam.noiseModel.Robust.Create(est, base)


def _cov3_from_xz(cov_xz_m2: ArrayLike, config: SmootherConfig) -> NDArray[np.float64]:
    """3x3 world covariance from a 2x2 x-z covariance: symmetrised, floored, loose lateral y."""
    c = np.asarray(cov_xz_m2, dtype=float).reshape(2, 2)
    c = 0.5 * (c + c.T)
    floor = config.min_measurement_sigma_m**2
    w, U = np.linalg.eigh(c)
    c = (U * np.maximum(w, floor)) @ U.T
    C3 = np.zeros((3, 3))
    C3[np.ix_([0, 2], [0, 2])] = c
    C3[1, 1] = config.lateral_measurement_sigma_m**2
    return C3


def _between_noise(
    C_trans: NDArray[np.float64], config: SmootherConfig
) -> gtsam.noiseModel.Base:
    """6x6 Gaussian [rotation, translation] for a BetweenFactorPose3, robustified."""
    cov = np.zeros((6, 6))
    cov[:3, :3] = np.eye(3) * config.measurement_rotation_sigma_rad**2
    cov[3:, 3:] = 0.5 * (C_trans + C_trans.T)
    return robust_noise(config, gtsam.noiseModel.Gaussian.Covariance(cov))


def _xz_to_3(v_xz: ArrayLike, y: float = 0.0) -> NDArray[np.float64]:
    v = np.asarray(v_xz, dtype=float).reshape(2)
    return np.array([v[0], y, v[1]])


def imu_position_from_camera(
    camera_xz_m: ArrayLike, R_world_imu: NDArray[np.float64], imu_p_cam_m: NDArray[np.float64]
) -> NDArray[np.float64]:
    """IMU world position (3,) with y = 0 from a camera x-z position: t = c - R imu_p_cam."""
    off = R_world_imu @ imu_p_cam_m
    c = np.asarray(camera_xz_m, dtype=float).reshape(2)
    return np.array([c[0] - off[0], 0.0, c[1] - off[2]])


def camera_from_pose(
    pose: gtsam.Pose3, imu_p_cam_m: NDArray[np.float64]
) -> tuple[NDArray[np.float64], NDArray[np.float64]]:
    """World rotation R (3x3) of an IMU pose and the camera position (3,): c = t + R p."""
    R = pose.rotation().matrix()
    return R, np.asarray(pose.translation()) + R @ imu_p_cam_m


def camera_xz_cov_from_pose_cov(
    R_world_imu: NDArray[np.float64], pose_cov: NDArray[np.float64], imu_p_cam_m: ArrayLike
) -> NDArray[np.float64]:
    """2x2 world x-z covariance of the camera position from a Pose3 marginal (6x6).

    GTSAM's Pose3 tangent is [rotation, translation] in the body frame, so with
    ``T' = T Exp(xi)`` the camera c = t + R p moves by ``R (v - [p]x w)``.
    """
    px = skew(imu_p_cam_m)
    J = R_world_imu @ np.hstack([-px, np.eye(3)])
    C = J @ pose_cov @ J.T
    return C[np.ix_([0, 2], [0, 2])]


# ----------------------------------------------------------------------------------------------
# incremental graph builder shared by the fixed-lag and the batch smoother
# ----------------------------------------------------------------------------------------------
@dataclass
class KeyframeUpdate:
    """Everything one new keyframe adds to the graph.

    ``timestamps`` maps every key created or re-observed by this keyframe to its time (s), the
    input GTSAM's fixed-lag smoothers need.
    """

    index: int
    timestamp_s: float
    factors: gtsam.NonlinearFactorGraph
    values: gtsam.Values
    timestamps: dict[int, float]
    R_world_imu: NDArray[np.float64]
    filter_camera_xz_m: NDArray[np.float64]
    factor_keys: list[list[int]] = field(default_factory=list)


@dataclass
class _Pending:
    timestamp_s: float
    estimate: FrameEstimate | None
    displacement: tuple[NDArray[np.float64], NDArray[np.float64]] | None
    observations: list[LandmarkObservation]
    R_world_imu: NDArray[np.float64] | None = None


class KeyframeGraphBuilder:
    """Turns the shared ingestion stream into per-keyframe factor/value/timestamp batches.

    A keyframe given to :meth:`add_frame` is completed once an IMU sample at or after its time
    has arrived (so that preintegration can interpolate to the keyframe time), or when the
    next frame arrives / :meth:`flush` is called (then the last IMU sample is held).
    """

    def __init__(self, config: SmootherConfig, imu_T_cam: ArrayLike) -> None:
        T = np.asarray(imu_T_cam, dtype=float)
        if T.shape != (4, 4):
            raise EstimationError(f"imu_T_cam must be 4x4, got {T.shape}")
        self.config = config
        self.imu_p_cam_m = T[:3, 3].copy()
        self._params = make_preintegration_params(config)
        self._imu_t: list[float] = []
        self._imu_a: list[NDArray[np.float64]] = []
        self._imu_g: list[NDArray[np.float64]] = []
        self._imu_q: list[NDArray[np.float64]] = []
        self._imu_x: list[tuple[float, float]] = []  # extra (accel, gyro) sigma per sample
        #: wrap IMU factors in SmootherConfig.imu_robust_kernel (the batch smoother sets it;
        #: iSAM2 keeps a factor's first linearisation, and a poor initial guess would leave
        #: good IMU factors down-weighted: upstair s1 smoother toe x 1.33 -> 1.6-2.0 cm)
        self.robust_imu = False
        self._pending: _Pending | None = None
        self._n_keyframes = 0
        self._last_kf_time_s: float | None = None
        self._last_kf_R: NDArray[np.float64] | None = None
        # chained displacement since the last keyframe: start, end, sum (2,), cov (2, 2)
        self._chain: tuple[float, float, NDArray[np.float64], NDArray[np.float64]] | None = None
        # corner track / stance -> its GTSAM key L(j); landmarks of either kind so far
        self._landmark_of: dict[LandmarkKey, int] = {}
        self._n_landmarks = 0
        # latest refined state of the newest keyframe (set by the smoother after each update)
        self._latest_nav: gtsam.NavState | None = None
        self._latest_bias = gtsam.imuBias.ConstantBias()

    # ---- feedback from the smoother ------------------------------------------------------------
    def set_latest_state(
        self, pose: gtsam.Pose3, velocity_mps: NDArray[np.float64], bias: gtsam.imuBias.ConstantBias
    ) -> None:
        """Latest estimate of the newest keyframe: used to predict when no filter guess exists."""
        self._latest_nav = gtsam.NavState(pose, np.asarray(velocity_mps, dtype=float))
        self._latest_bias = bias

    def forget_landmarks(self, landmark_keys: Sequence[int]) -> None:
        """Landmarks marginalised by a fixed-lag smoother: a re-seen track or stance gets a new
        L(j)."""
        dead = set(landmark_keys)
        self._landmark_of = {lk: k for lk, k in self._landmark_of.items() if k not in dead}

    # ---- ingestion -----------------------------------------------------------------------------
    def add_imu(self, sample: ImuSample) -> list[KeyframeUpdate]:
        """Buffer one IMU sample; returns the keyframe it completes, if any."""
        t = float(sample.timestamp_s)
        if self._imu_t and t <= self._imu_t[-1]:
            raise EstimationError(f"IMU timestamps not increasing: {t} after {self._imu_t[-1]}")
        self._imu_t.append(t)
        self._imu_a.append(np.asarray(sample.accel_mps2, dtype=float).reshape(3))
        self._imu_g.append(np.asarray(sample.gyro_radps, dtype=float).reshape(3))
        self._imu_q.append(np.asarray(sample.quat_wxyz, dtype=float).reshape(4))
        self._imu_x.append((float(sample.accel_extra_sigma_mps2),
                            float(sample.gyro_extra_sigma_radps)))
        if self._pending is not None and t >= self._pending.timestamp_s - TIME_TOL_S:
            return [self._complete_pending()]
        return []

    def add_frame(
        self,
        timestamp_s: float,
        is_keyframe: bool,
        filter_estimate: FrameEstimate | None,
        displacement: Displacement2D | None,
        observation: LandmarkObservation | Sequence[LandmarkObservation] | None,
        R_world_imu: ArrayLike | None = None,
    ) -> list[KeyframeUpdate]:
        """Ingest one depth frame's outputs; returns completed keyframes (0, 1 or 2).

        ``R_world_imu`` (3, 3, heading removed) is the attitude the front end and the filter
        used for this frame's displacement and observations. The graph must map them with
        that same rotation: they are world-frame vectors built with it, so any difference to
        the rotation used here tilts them. None: the AHRS of the IMU stream
        (:meth:`_attitude_at`).
        """
        out: list[KeyframeUpdate] = []
        if self._pending is not None:
            out.append(self._complete_pending())
        t = float(timestamp_s)
        if self._last_kf_time_s is not None and t <= self._last_kf_time_s + TIME_TOL_S:
            raise EstimationError(f"frame at {t} s is not after the last keyframe")
        if displacement is not None:
            self._chain_displacement(displacement)
        if not is_keyframe:
            return out
        if self._n_keyframes == 0 and filter_estimate is None:
            raise EstimationError("the first keyframe needs a filter estimate (initial state)")
        disp = None
        if (
            self._chain is not None
            and self._last_kf_time_s is not None
            and abs(self._chain[0] - self._last_kf_time_s) < TIME_TOL_S
            and abs(self._chain[1] - t) < TIME_TOL_S
        ):
            disp = (self._chain[2], self._chain[3])
        self._chain = (t, t, np.zeros(2), np.zeros((2, 2)))
        if observation is None:
            obs: list[LandmarkObservation] = []
        elif isinstance(observation, (CornerObservation, StanceObservation)):
            obs = [observation]
        else:
            obs = list(observation)
        R_meas = None if R_world_imu is None else np.asarray(R_world_imu, dtype=float).reshape(3, 3)
        self._pending = _Pending(t, filter_estimate, disp, obs, R_meas)
        if self._imu_t and self._imu_t[-1] >= t - TIME_TOL_S:
            out.append(self._complete_pending())
        return out

    def flush(self) -> list[KeyframeUpdate]:
        """Complete a pending keyframe now (holding the last IMU sample if needed)."""
        return [self._complete_pending()] if self._pending is not None else []

    @property
    def n_keyframes(self) -> int:
        return self._n_keyframes

    # ---- internals -----------------------------------------------------------------------------
    def _chain_displacement(self, d: Displacement2D) -> None:
        """Append a frame-to-frame displacement to the chain if it continues it."""
        delta = np.asarray(d.delta_xz_m, dtype=float).reshape(2)
        cov = np.asarray(d.cov_m2, dtype=float).reshape(2, 2) \
            + np.eye(2) * self.config.frame_displacement_sigma_m**2
        if self._chain is not None and abs(d.t0_s - self._chain[1]) < TIME_TOL_S:
            s, _, acc, acc_cov = self._chain
            self._chain = (s, float(d.t1_s), acc + delta, acc_cov + cov)
        else:  # gap in the chain: restart (only useful if it starts at the last keyframe)
            self._chain = (float(d.t0_s), float(d.t1_s), delta, cov)

    def _attitude_at(self, t_s: float) -> NDArray[np.float64]:
        """AHRS R_world_imu at t (nearest sample, rotated by its gyro), heading removed."""
        ts = np.asarray(self._imu_t)
        k = int(np.argmin(np.abs(ts - t_s)))
        R = matrix_from_quat_wxyz(self._imu_q[k]) @ so3_exp(self._imu_g[k] * (t_s - ts[k]))
        return remove_yaw(R)

    def _gyro_at(self, t_s: float) -> NDArray[np.float64]:
        ts = np.asarray(self._imu_t)
        g = np.asarray(self._imu_g)
        return np.array([np.interp(t_s, ts, g[:, i]) for i in range(3)])

    def _new_landmark_key(self, lkey: LandmarkKey) -> int:
        """The next GTSAM key L(j) for a corner track or a stance, remembered."""
        k = L(self._n_landmarks)
        self._n_landmarks += 1
        self._landmark_of[lkey] = k
        return k

    def _complete_pending(self) -> KeyframeUpdate:
        pend = self._pending
        assert pend is not None
        self._pending = None
        if not self._imu_t:
            raise EstimationError(f"keyframe at {pend.timestamp_s} s has no IMU data before it")
        cfg, fam = self.config, self.config.factors
        i = self._n_keyframes
        t = pend.timestamp_s
        R_i = pend.R_world_imu if pend.R_world_imu is not None else self._attitude_at(t)
        p_ic = self.imu_p_cam_m
        graph = gtsam.NonlinearFactorGraph()
        values = gtsam.Values()
        stamps: dict[int, float] = {X(i): t, V(i): t, B(i): t}

        # -- IMU preintegration from the previous keyframe (midpoint rule) --
        pim = None
        if i > 0:
            assert self._last_kf_time_s is not None
            ts = np.asarray(self._imu_t)
            sampler = {"midpoint_curvature": midpoint_samples,
                       "common_frame": common_frame_samples,
                       "raw": held_samples}[self.config.preintegration]
            a_mid, g_mid, dt = sampler(
                ts, np.asarray(self._imu_a), np.asarray(self._imu_g), self._last_kf_time_s, t
            )
            params = self._params
            x_vel, x_rot = distrust_variances(ts, self._imu_x, self._last_kf_time_s, t)
            if cfg.imu_discretization_gain > 0 or x_vel > 0 or x_rot > 0:
                extra = cfg.imu_discretization_gain**2 * discretization_velocity_var(
                    ts, np.asarray(self._imu_a), self._last_kf_time_s, t)
                params = make_preintegration_params(cfg, extra + x_vel, t - self._last_kf_time_s,
                                                    x_rot)
            pim = gtsam.PreintegratedCombinedMeasurements(params, self._latest_bias)
            for a_k, g_k, dt_k in zip(a_mid, g_mid, dt, strict=True):
                pim.integrateMeasurement(a_k, g_k, float(dt_k))

        # -- initial guess: the filter's estimate, else the IMU prediction --
        if pend.estimate is not None:
            cam_xz = np.asarray(pend.estimate.camera_xz_m, dtype=float).reshape(2)
            t_guess = imu_position_from_camera(cam_xz, R_i, p_ic)
            v_cam = _xz_to_3(pend.estimate.velocity_xz_mps)
            v_guess = v_cam - R_i @ np.cross(self._gyro_at(t), p_ic)
            v_guess[1] = 0.0
        else:
            assert pim is not None and self._latest_nav is not None
            nav = pim.predict(self._latest_nav, self._latest_bias)
            t_guess = np.asarray(nav.pose().translation(), dtype=float).copy()
            v_guess = np.asarray(nav.velocity(), dtype=float).copy()
            cam_xz = (t_guess + R_i @ p_ic)[[0, 2]]
        rot_i = gtsam.Rot3.ClosestTo(R_i)
        pose_guess = gtsam.Pose3(rot_i, t_guess)
        values.insert(X(i), pose_guess)
        values.insert(V(i), v_guess)
        values.insert(B(i), self._latest_bias)

        keys: list[list[int]] = []

        def add(factor: gtsam.NonlinearFactor, fkeys: list[int]) -> None:
            graph.add(factor)
            keys.append(fkeys)

        # -- priors of the first keyframe --
        if i == 0:
            sig = np.r_[[cfg.first_attitude_sigma_rad] * 3, [cfg.first_position_sigma_m] * 3]
            add(gtsam.PriorFactorPose3(X(0), pose_guess, gtsam.noiseModel.Diagonal.Sigmas(sig)),
                [X(0)])
            add(gtsam.PriorFactorVector(V(0), v_guess, gtsam.noiseModel.Isotropic.Sigma(
                3, cfg.first_velocity_sigma_mps)), [V(0)])
            bsig = np.r_[
                [cfg.accel_bias_prior_sigma_mps2] * 3, [cfg.gyro_bias_prior_sigma_radps] * 3
            ]
            add(gtsam.PriorFactorConstantBias(B(0), gtsam.imuBias.ConstantBias(),
                                              gtsam.noiseModel.Diagonal.Sigmas(bsig)), [B(0)])
        else:
            # -- IMU factor (also the bias random walk B(i-1) -> B(i)) --
            if fam.imu:
                assert pim is not None
                f_imu = gtsam.CombinedImuFactor(X(i - 1), V(i - 1), X(i), V(i), B(i - 1), B(i),
                                                pim)
                if self.robust_imu and cfg.imu_robust_kernel != "none":
                    f_imu = f_imu.cloneWithNewNoiseModel(robust_noise(
                        cfg, f_imu.noiseModel(), cfg.imu_robust_kernel, cfg.imu_robust_threshold))
                add(f_imu, [X(i - 1), V(i - 1), X(i), V(i), B(i - 1), B(i)])
            else:  # keep the bias chain connected without the IMU
                bsig = np.r_[[cfg.accel_bias_prior_sigma_mps2] * 3,
                             [cfg.gyro_bias_prior_sigma_radps] * 3]
                add(gtsam.BetweenFactorConstantBias(
                    B(i - 1), B(i), gtsam.imuBias.ConstantBias(),
                    gtsam.noiseModel.Diagonal.Sigmas(bsig)), [B(i - 1), B(i)])
                if not (fam.displacement and pend.displacement is not None):
                    # velocity otherwise unconstrained: weak random walk between keyframes
                    add(gtsam.BetweenFactorVector(V(i - 1), V(i), np.zeros(3),
                                                  gtsam.noiseModel.Isotropic.Sigma(3, 1.0)),
                        [V(i - 1), V(i)])
            # -- chained ICP displacement (eq. 3-4 output) --
            if fam.displacement and pend.displacement is not None:
                assert self._last_kf_R is not None
                R_h = self._last_kf_R
                d3 = _xz_to_3(pend.displacement[0])
                dt_imu = d3 - (R_i - R_h) @ p_ic  # IMU motion in world axes
                meas = gtsam.Pose3(gtsam.Rot3.ClosestTo(R_h.T @ R_i), R_h.T @ dt_imu)
                C3 = _cov3_from_xz(pend.displacement[1], cfg)
                noise = _between_noise(R_i.T @ C3 @ R_i, cfg)
                add(gtsam.BetweenFactorPose3(X(i - 1), X(i), meas, noise), [X(i - 1), X(i)])
            if not fam.imu:
                add(gtsam.PriorFactorVector(V(i), v_guess, gtsam.noiseModel.Isotropic.Sigma(
                    3, LOOSE_SIGMA)), [V(i)])

        # -- attitude anchoring (AHRS, heading removed) --
        if fam.attitude and i > 0:
            sig = np.r_[[cfg.attitude_sigma_rad] * 3, [LOOSE_SIGMA] * 3]
            add(gtsam.PriorFactorPose3(X(i), pose_guess, gtsam.noiseModel.Diagonal.Sigmas(sig)),
                [X(i)])
        # -- sagittal plane + weak absolute position --
        if (fam.planar or fam.weak_position) and i > 0:
            s_xz = cfg.weak_position_sigma_m if fam.weak_position else LOOSE_SIGMA
            s_y = cfg.lateral_position_sigma_m if fam.planar else LOOSE_SIGMA
            add(gtsam.PoseTranslationPrior3D(
                X(i), t_guess, gtsam.noiseModel.Diagonal.Sigmas(np.array([s_xz, s_y, s_xz]))),
                [X(i)])
        if fam.planar:
            sig = np.array([LOOSE_SIGMA, cfg.lateral_velocity_sigma_mps, LOOSE_SIGMA])
            add(gtsam.PriorFactorVector(V(i), np.zeros(3), gtsam.noiseModel.Diagonal.Sigmas(sig)),
                [V(i)])

        # -- corner landmarks and stance anchors: long-span constraints --
        if fam.landmarks:
            for ob in pend.observations:
                cov = np.asarray(ob.cov_m2, dtype=float).reshape(2, 2)
                if isinstance(ob, StanceObservation):
                    lkey = LandmarkKey("ankle", ob.stance_id)
                    o3 = _xz_to_3(ob.ankle_rel_xz_m)
                else:
                    lkey = LandmarkKey("corner", ob.track_id)
                    o3 = _xz_to_3(ob.corner_rel_xz_m)
                    cov = cov + np.eye(2) * cfg.corner_landmark_sigma_m**2
                lk = self._landmark_of.get(lkey)
                if lk is None:
                    lk = self._new_landmark_key(lkey)
                    lm = t_guess + R_i @ p_ic + o3
                    lm[1] = 0.0
                    lm_pose = gtsam.Pose3(gtsam.Rot3(), lm)
                    values.insert(lk, lm_pose)
                    sig = np.r_[[cfg.landmark_rotation_sigma_rad] * 3,
                                cfg.landmark_position_sigma_m, cfg.landmark_lateral_sigma_m,
                                cfg.landmark_position_sigma_m]
                    add(gtsam.PriorFactorPose3(lk, lm_pose,
                                               gtsam.noiseModel.Diagonal.Sigmas(sig)), [lk])
                meas = gtsam.Pose3(rot_i.inverse(), R_i.T @ o3 + p_ic)
                noise = _between_noise(_cov3_from_xz(cov, cfg), cfg)
                add(gtsam.BetweenFactorPose3(X(i), lk, meas, noise), [X(i), lk])
                stamps[lk] = t

        self._n_keyframes += 1
        self._last_kf_time_s = t
        self._last_kf_R = R_i
        # keep the IMU samples at or before the keyframe that the next interval needs (one
        # for the interpolation, four for the fourth differences of its first samples)
        ts = np.asarray(self._imu_t)
        k0 = max(0, int(np.searchsorted(ts, t - TIME_TOL_S, side="right")) - 4)
        del self._imu_t[:k0], self._imu_a[:k0], self._imu_g[:k0], self._imu_q[:k0]
        del self._imu_x[:k0]
        if self._latest_nav is None or pend.estimate is not None:
            self._latest_nav = gtsam.NavState(pose_guess, v_guess)
        return KeyframeUpdate(
            index=i,
            timestamp_s=t,
            factors=graph,
            values=values,
            timestamps=stamps,
            R_world_imu=R_i,
            filter_camera_xz_m=np.asarray(cam_xz, dtype=float).reshape(2),
            factor_keys=keys,
        )
