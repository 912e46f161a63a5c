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
  (``imu_sampling.common_frame_samples``, default; ``imu_sampling.midpoint_samples`` averages
  in the moving frame and loses (omega dt)^2/24 of gravity). Noise: MTi-1 datasheet
  densities, bias random walks, plus the sampled-signal model error
  (``imu_sampling.discretization_velocity_var``).
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

import functools
import math
from collections import deque
from collections.abc import Callable, Sequence
from dataclasses import dataclass, field

import gtsam
import numpy as np
from gtsam.symbol_shorthand import B, L, V, X
from numpy.typing import ArrayLike, NDArray

from vio_graph.errors import EstimationError
from vio_graph.filter.fast_imu import as_f64
from vio_graph.filter.gating import chi2_quantile
from vio_graph.filter.imu_repair import interpolated_axes_cov, keep_consistent_axes
from vio_graph.geometry import cross3, matrix_from_quat_wxyz, remove_yaw, skew
from vio_graph.smoother.config import SmootherConfig
from vio_graph.smoother.imu_sampling import (
    SAMPLERS,
    TIME_TOL_S,
    compiled_discretization_var,
    compiled_sampler,
    discretization_rotation_var,
    discretization_velocity_var,
    distrust_step_covariances,
    distrust_step_variances,
    distrust_variances,
    make_preintegration_params,
    set_white_noise,
    so3_exp,
)
from vio_graph.types import (
    CornerObservation,
    Displacement2D,
    FrameEstimate,
    FrameObservation,
    ImuSample,
    LandmarkKey,
    LevelObservation,
    StanceObservation,
    VelocityObservation,
)

#: Sigma used for "unconstrained" axes of a prior (tangent units).
LOOSE_SIGMA = 1e4

_EIGH_LO: np.ufunc | None
try:  # the gufunc np.linalg.eigh calls (UPLO="L"); private, so looked up defensively
    from numpy.linalg import _umath_linalg

    _EIGH_LO = _umath_linalg.eigh_lo
except (ImportError, AttributeError):  # pragma: no cover - other numpy layouts
    _EIGH_LO = None

__all__ = [
    "B",
    "L",
    "V",
    "X",
    "KeyframeGraphBuilder",
    "KeyframeUpdate",
    "camera_xz_cov_from_pose_cov",
    "imu_position_from_camera",
    "robust_noise",
]


# ----------------------------------------------------------------------------------------------
# noise models and frame conversions
# ----------------------------------------------------------------------------------------------
def robust_noise(
    config: SmootherConfig,
    base: gtsam.noiseModel.Base,
    kernel: str | None = None,
    threshold: float | None = None,
) -> gtsam.noiseModel.Base:
    """Wrap ``base`` in an M-estimator (threshold in whitened units); by default the
    configured ``robust_kernel`` / ``robust_threshold``."""
    kernel = config.robust_kernel if kernel is None else kernel
    threshold = config.robust_threshold if threshold is None else threshold
    est = _m_estimator(kernel, float(threshold))
    return base if est is None else gtsam.noiseModel.Robust.Create(est, base)


@functools.lru_cache(maxsize=16)
def _m_estimator(kernel: str, threshold: float) -> gtsam.noiseModel.mEstimator.Base | None:
    """The M-estimator of ``kernel`` (None for none), one object per (kernel, threshold): it
    holds only its threshold, so every robust noise model can share it."""
    if kernel == "huber":
        return gtsam.noiseModel.mEstimator.Huber.Create(threshold)
    if kernel == "cauchy":
        return gtsam.noiseModel.mEstimator.Cauchy.Create(threshold)
    if kernel == "geman_mcclure":
        return gtsam.noiseModel.mEstimator.GemanMcClure.Create(threshold)
    return None


def _cov3_from_xz(cov_xz_m2: ArrayLike, config: SmootherConfig) -> NDArray[np.float64]:
    """3x3 world covariance from a 2x2 x-z covariance: symmetrised, floored, loose lateral y."""
    c = np.asarray(cov_xz_m2, dtype=float).reshape(2, 2)
    c = 0.5 * (c + c.T)
    floor = config.min_measurement_sigma_m**2
    w, U = _eigh(c)
    c = (U * np.maximum(w, floor)) @ U.T
    C3 = np.zeros((3, 3))
    _put_xz(C3, c)
    C3[1, 1] = config.lateral_measurement_sigma_m**2
    return C3


def _put_xz(C3: NDArray[np.float64], c: NDArray[np.float64]) -> None:
    """C3[np.ix_([0, 2], [0, 2])] = c, element by element (np.ix_ costs ~10 us a call)."""
    C3[0, 0], C3[0, 2], C3[2, 0], C3[2, 2] = c[0, 0], c[0, 1], c[1, 0], c[1, 1]


def _eigh(c: NDArray[np.float64]) -> tuple[NDArray[np.float64], NDArray[np.float64]]:
    """``np.linalg.eigh(c)`` of a float64 matrix through the LAPACK gufunc it wraps: the same
    call and result, without ~15 us of argument handling (two calls per keyframe)."""
    if _EIGH_LO is None:
        return np.linalg.eigh(c)
    return _EIGH_LO(c, signature="d->dd")


def _between_noise(C_trans: NDArray[np.float64], config: SmootherConfig) -> gtsam.noiseModel.Base:
    """6x6 Gaussian [rotation, translation] for a BetweenFactorPose3, robustified."""
    cov = np.zeros((6, 6))
    cov[:3, :3] = _rotation_block(config.measurement_rotation_sigma_rad)
    cov[3:, 3:] = 0.5 * (C_trans + C_trans.T)
    return robust_noise(config, gtsam.noiseModel.Gaussian.Covariance(cov))


@functools.lru_cache(maxsize=8)
def _rotation_block(sigma_rad: float) -> NDArray[np.float64]:
    """The rotation block (3x3, read-only) of :func:`_between_noise`, made once per sigma."""
    m = np.eye(3) * sigma_rad**2
    m.flags.writeable = False
    return m


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
    return np.array([[C[0, 0], C[0, 2]], [C[2, 0], C[2, 2]]])


def _vec(v: ArrayLike, n: int) -> NDArray[np.float64]:
    """``np.asarray(v, dtype=float).reshape(n)``: ``v`` itself if it is a float64 array of
    shape (n,) (the reshape would be a view of it)."""
    a = as_f64(v)
    return a if a.shape == (n,) else a.reshape(n)


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
    #: position in ``factors`` of the IMU factor from keyframe index-1 if its interval holds
    #: a packet the fault monitor repaired (``ImuSample.accel_held``), else None
    flagged_imu_factor: int | None = None


@dataclass
class _FactorBatch:
    """The factors (with their keys), initial values and key timestamps of one keyframe."""

    stamps: dict[int, float]
    graph: gtsam.NonlinearFactorGraph = field(default_factory=gtsam.NonlinearFactorGraph)
    values: gtsam.Values = field(default_factory=gtsam.Values)
    keys: list[list[int]] = field(default_factory=list)
    flagged_imu: int | None = None  # position of an IMU factor over a repaired packet

    def add(self, factor: gtsam.NonlinearFactor, factor_keys: list[int]) -> None:
        self.graph.add(factor)
        self.keys.append(factor_keys)


@dataclass
class _GraphLevel:
    """A height landmark of the graph's own association
    (``factors.height_landmark_association`` 'graph'): its key and world height (m): the
    surface last associated with it, or the smoother's estimate once it has solved it."""

    key: LandmarkKey
    z_m: float


@dataclass
class DeferredLevel:
    """A level observation the batch holds back until its first solve (graph association):
    keyframe index, time (s), the observation, the keyframe's attitude (its rotation and
    matrix) and its guessed IMU position (m, world)."""

    index: int
    timestamp_s: float
    observation: LevelObservation
    rot: gtsam.Rot3
    R_world_imu: NDArray[np.float64]
    t_guess_m: NDArray[np.float64]


@dataclass
class _Pending:
    timestamp_s: float
    estimate: FrameEstimate | None
    displacement: tuple[NDArray[np.float64], NDArray[np.float64]] | None
    observations: list[FrameObservation]
    R_world_imu: NDArray[np.float64] | None = None


def repaired_in(
    times_s: NDArray[np.float64], repaired: Sequence[bool], t0_s: float, t1_s: float
) -> bool:
    """Whether a repaired packet (``ImuSample.accel_held`` on arrival) touches the interval
    [t0_s, t1_s]: its sample period overlaps it (the touch rule of ``distrust_variances``)."""
    if not any(repaired):
        return False
    r = np.asarray(repaired, dtype=bool)
    h = float(np.median(np.diff(times_s))) if times_s.size > 1 else t1_s - t0_s
    touch = (times_s > t0_s - h + TIME_TOL_S) & (times_s < t1_s + h - TIME_TOL_S)
    return bool(np.any(r & touch))


@dataclass
class FirstVelocityPrior:
    """The first keyframe's velocity prior as built (its position in keyframe 0's factors,
    value and noise) and the relaxed noise it is given if it fails the test of
    :meth:`KeyframeGraphBuilder.first_velocity_fails`."""

    position: int
    value: NDArray[np.float64]
    noise: gtsam.noiseModel.Base
    relaxed_noise: gtsam.noiseModel.Base | None

    def relaxed_factor(self) -> gtsam.PriorFactorVector | None:
        """The same prior with the relaxed noise (None if there is none)."""
        if self.relaxed_noise is None:
            return None
        return gtsam.PriorFactorVector(V(0), self.value, self.relaxed_noise)


def _gyro_interp(t_s: float, times_s: Sequence[float], gyro: Sequence) -> NDArray[np.float64]:
    """The body rate (rad/s, (3,)) at ``t_s``, per axis linear between the samples
    (``times_s`` ascending, ``gyro`` one (3,) sample each; clamped at the ends)."""
    ts = np.asarray(times_s)
    g = np.asarray(gyro, dtype=float)
    return np.array([np.interp(t_s, ts, g[:, a]) for a in range(3)])


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
        # the parameters of the keyframe interval being integrated when its noise differs from
        # ``_params``: one object, its two white-noise covariances set anew per interval (a
        # fresh object per keyframe cost ~40 us). Reusing it is safe because GTSAM reads the
        # covariances only while integrating: a CombinedImuFactor takes its noise model from
        # the finished preintegration when it is built
        self._interval_params = make_preintegration_params(config)
        self._compiled_steps = compiled_sampler(config.preintegration)  # numba, or None
        self._compiled_dvar = compiled_discretization_var()  # numba, or None
        self._imu_t: list[float] = []
        self._imu_a: list[NDArray[np.float64]] = []
        self._imu_g: list[NDArray[np.float64]] = []
        self._imu_q: list[NDArray[np.float64]] = []
        self._imu_x: list[tuple[float, float]] = []  # extra (accel, gyro) sigma per sample
        # a saturated sample's extra accelerometer covariance on its clipped axes (3, 3), or
        # None (the extra accel sigma on every axis); kept only with saturation_axis_distrust
        self._imu_c: list[NDArray[np.float64] | None] = []
        self._imu_h: list[bool] = []  # accelerometer held over a corrupted packet (not measured)
        self._imu_r: list[bool] = []  # a corrupted packet the monitor repaired (stays marked)
        # what a held packet measured (accel, gyro), for the per-axis keep; None otherwise
        self._imu_m: list[tuple[NDArray[np.float64], NDArray[np.float64]] | None] = []
        self._interpolate_held_on = bool(config.held_accel_interpolation)
        #: wrap IMU factors in SmootherConfig.imu_robust_kernel (the batch smoother sets it;
        #: iSAM2 keeps a factor's first linearisation, and a poor initial guess would leave
        #: good IMU factors down-weighted: upstair s1 smoother toe x 1.33 -> 1.6-2.0 cm)
        self.robust_imu = False
        self._pending: _Pending | None = None
        self._n_keyframes = 0
        #: keyframe indices i whose IMU interval (i-1 -> i) holds a repaired packet
        self.flagged_intervals: list[int] = []
        #: the first keyframe's velocity prior (set with keyframe 0) and that keyframe's time
        self.first_velocity_prior: FirstVelocityPrior | None = None
        self._first_kf_time_s: float | None = None
        self._interval_flagged = False  # set by _preintegrate for the interval it integrated
        self._last_kf_time_s: float | None = None
        self._last_kf_R: NDArray[np.float64] | None = None
        # recent keyframes for the bridge's velocity change (factors.saturation_bridge_relative):
        # time, index, R_world_imu and the IMU times and gyro samples around it (s, rad/s)
        self._recent_kf: deque[tuple[float, int, NDArray[np.float64], list, list]] = deque(
            maxlen=64
        )
        # chained displacement since the last keyframe: start, end, sum (2,), cov (2, 2)
        self._chain: tuple[float, float, NDArray[np.float64], NDArray[np.float64]] | None = None
        # corner track / stance -> its GTSAM key L(j); landmarks of either kind so far
        self._landmark_of: dict[LandmarkKey, int] = {}
        #: a height landmark's x (m, world) as its node was created: the height factors'
        #: unweighted x refers to it
        self._level_x_m: dict[int, float] = {}
        self._n_landmarks = 0
        # factors.height_landmark_association 'graph': the graph's own height landmarks (by
        # key), their count, the guessed IMU z (m) of recent keyframes and the refined minus
        # guessed z of the newest keyframe the smoother solved
        self._graph_levels: dict[int, _GraphLevel] = {}
        self._n_graph_levels = 0
        self._guess_z_m: deque[tuple[int, float]] = deque(maxlen=8)
        self._graph_dz_m = 0.0
        #: set by the batch smoother: with the graph association, level observations wait in
        #: ``deferred_levels`` for a first solve (:meth:`associate_deferred_levels`)
        self.defer_levels = False
        self.deferred_levels: list[DeferredLevel] = []
        # latest refined state of the newest keyframe (set by the smoother after each update)
        # (pose, velocity): made into a gtsam.NavState only when a prediction needs it
        self._latest_nav: tuple[gtsam.Pose3, NDArray[np.float64]] | None = None
        self._latest_bias = gtsam.imuBias.ConstantBias()
        # constant-sigma noise models, made once (keyed by their sigmas, so a changed config
        # still gets its own): building one costs as much as the factor using it
        self._noise_cache: dict[tuple[object, ...], gtsam.noiseModel.Base] = {}

    def _diagonal(self, *sigmas: float) -> gtsam.noiseModel.Base:
        """``noiseModel.Diagonal.Sigmas(sigmas)``, shared by every factor with these sigmas."""
        nm = self._noise_cache.get(sigmas)
        if nm is None:
            nm = gtsam.noiseModel.Diagonal.Sigmas(np.array(sigmas, dtype=float))
            self._noise_cache[sigmas] = nm
        return nm

    def _isotropic(self, sigma: float) -> gtsam.noiseModel.Base:
        """``noiseModel.Isotropic.Sigma(3, sigma)``, shared likewise."""
        key = ("isotropic3", sigma)
        nm = self._noise_cache.get(key)
        if nm is None:
            nm = gtsam.noiseModel.Isotropic.Sigma(3, sigma)
            self._noise_cache[key] = nm
        return nm

    # ---- feedback from the smoother ------------------------------------------------------------
    def set_latest_state(
        self,
        pose: gtsam.Pose3,
        velocity_mps: NDArray[np.float64],
        bias: gtsam.imuBias.ConstantBias,
        index: int | None = None,
    ) -> None:
        """Latest estimate of the newest keyframe: used to predict when no filter guess exists.
        With its ``index``, its refined minus guessed height also moves the following
        keyframes' guessed heights for the graph's association of level surfaces."""
        self._latest_nav = (pose, np.asarray(velocity_mps, dtype=float))
        self._latest_bias = bias
        if index is not None:
            for k, z in self._guess_z_m:
                if k == index:
                    self._graph_dz_m = float(pose.translation()[2]) - z
                    break

    @property
    def graph_level_keys(self) -> list[int]:
        """Keys of the graph's own height landmarks (graph association), for
        :meth:`set_level_heights`."""
        return list(self._graph_levels)

    def set_level_heights(self, heights_m: dict[int, float]) -> None:
        """The smoother's current estimates of its height landmarks' world z (m), by key."""
        for k, z in heights_m.items():
            g = self._graph_levels.get(k)
            if g is not None:
                g.z_m = float(z)

    def forget_landmarks(self, landmark_keys: Sequence[int]) -> None:
        """Landmarks marginalised by a fixed-lag smoother: a re-seen track or stance gets a new
        L(j)."""
        dead = set(landmark_keys)
        self._landmark_of = {lk: k for lk, k in self._landmark_of.items() if k not in dead}
        for k in dead:
            self._level_x_m.pop(k, None)
            self._graph_levels.pop(k, None)

    # ---- ingestion -----------------------------------------------------------------------------
    def add_imu(
        self, sample: ImuSample, quat_wxyz: NDArray[np.float64] | None = None
    ) -> list[KeyframeUpdate]:
        """Buffer one IMU sample (with the orientation ``quat_wxyz`` instead of its own, if
        given); returns the keyframe it completes, if any."""
        t = float(sample.timestamp_s)
        imu_t = self._imu_t
        if imu_t and t <= imu_t[-1]:
            raise EstimationError(f"IMU timestamps not increasing: {t} after {imu_t[-1]}")
        imu_t.append(t)
        # np.asarray(v, dtype=float).reshape(n) without numpy's conversion checks (~1 us a
        # sample): the float64 array itself when it has that shape, as the view did
        self._imu_a.append(_vec(sample.accel_mps2, 3))
        self._imu_g.append(_vec(sample.gyro_radps, 3))
        self._imu_q.append(_vec(sample.quat_wxyz if quat_wxyz is None else quat_wxyz, 4))
        self._imu_x.append(
            (float(sample.accel_extra_sigma_mps2), float(sample.gyro_extra_sigma_radps))
        )
        xc = sample.accel_extra_cov_m2ps4
        self._imu_c.append(
            None if xc is None or not self.config.saturation_axis_distrust else np.asarray(xc)
        )
        held = bool(sample.accel_held)
        h = self._imu_h
        # a held run just before this measured sample (what _interpolate_held looks for)
        after_held = not held and self._interpolate_held_on and bool(h) and h[-1]
        h.append(held)
        self._imu_r.append(held)
        ma, mg = sample.measured_accel_mps2, sample.measured_gyro_radps
        self._imu_m.append(
            None
            if ma is None or mg is None
            else (np.asarray(ma, dtype=float).reshape(3), np.asarray(mg, dtype=float).reshape(3))
        )
        if after_held:
            self._interpolate_held()
        pending = self._pending
        if pending is not None and t >= pending.timestamp_s - TIME_TOL_S:
            return [self._complete_pending()]
        return []

    def add_frame(
        self,
        timestamp_s: float,
        is_keyframe: bool,
        filter_estimate: FrameEstimate | None,
        displacement: Displacement2D | None,
        observation: FrameObservation | Sequence[FrameObservation] | None,
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
            obs: list[FrameObservation] = []
        elif isinstance(
            observation,
            (CornerObservation, StanceObservation, VelocityObservation, LevelObservation),
        ):
            obs = [observation]
        else:
            obs = list(observation)
        R_meas = None if R_world_imu is None else np.asarray(R_world_imu, dtype=float).reshape(3, 3)
        self._pending = _Pending(t, filter_estimate, disp, obs, R_meas)
        if self._imu_t and self._imu_t[-1] >= t - TIME_TOL_S:
            out.append(self._complete_pending())
        return out

    def distrust_imu(self, t0_s: float, t1_s: float, accel_sigma_mps2: float) -> None:
        """Add ``accel_sigma_mps2`` (m/s^2, extra sigma per sample) to the buffered samples
        whose period touches [t0_s, t1_s] (s), where the filter found the IMU wrong. Samples
        already preintegrated into a keyframe factor keep theirs."""
        ts = self._imu_t
        for m in range(len(ts) - 1, -1, -1):
            period = ts[m + 1] - ts[m] if m + 1 < len(ts) else 0.0
            if ts[m] + period < t0_s:
                break
            if ts[m] <= t1_s + TIME_TOL_S:
                xa, xg = self._imu_x[m]
                self._imu_x[m] = (max(xa, float(accel_sigma_mps2)), xg)

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
        cov = (
            np.asarray(d.cov_m2, dtype=float).reshape(2, 2)
            + np.eye(2) * self.config.frame_displacement_sigma_m**2
        )
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
        return _gyro_interp(t_s, self._imu_t, self._imu_g)

    def _lever_velocity(self, R: NDArray[np.float64], gyro_radps: NDArray) -> NDArray:
        """omega x (R p_cam) (m/s, world): the camera's velocity minus the IMU's, for the
        IMU attitude ``R`` and body rate ``gyro_radps``."""
        return cross3(R @ gyro_radps, R @ self.imu_p_cam_m)

    def _new_landmark_key(self, lkey: LandmarkKey) -> int:
        """The next GTSAM key L(j) for a corner track or a stance, remembered."""
        k = L(self._n_landmarks)
        self._n_landmarks += 1
        self._landmark_of[lkey] = k
        return k

    def _landmark_node(
        self, batch: _FactorBatch, lkey: LandmarkKey, guess_m: NDArray[np.float64]
    ) -> int:
        """The GTSAM key of landmark ``lkey``; a new one gets its node at ``guess_m`` (world,
        m; y set to 0) and a weak prior (rotation and y held, x and z loose)."""
        lk = self._landmark_of.get(lkey)
        if lk is not None:
            return lk
        cfg = self.config
        lk = self._new_landmark_key(lkey)
        lm = np.array(guess_m, dtype=float)
        lm[1] = 0.0
        lm_pose = gtsam.Pose3(gtsam.Rot3(), lm)
        batch.values.insert(lk, pose3=lm_pose)
        sig = self._diagonal(
            *[cfg.landmark_rotation_sigma_rad] * 3,
            cfg.landmark_position_sigma_m,
            cfg.landmark_lateral_sigma_m,
            cfg.landmark_position_sigma_m,
        )
        batch.add(gtsam.PriorFactorPose3(lk, lm_pose, sig), [lk])
        return lk

    def _complete_pending(self) -> KeyframeUpdate:
        """Turn the pending keyframe into its node, initial values and factors, in this
        order: first-keyframe priors or the motion factors from the previous keyframe (IMU,
        displacement), attitude and sagittal-plane priors, landmark observations."""
        pend = self._pending
        assert pend is not None
        self._pending = None
        if not self._imu_t:
            raise EstimationError(f"keyframe at {pend.timestamp_s} s has no IMU data before it")
        i = self._n_keyframes
        t = pend.timestamp_s
        R_i = pend.R_world_imu if pend.R_world_imu is not None else self._attitude_at(t)
        pim = self._preintegrate(t) if i > 0 else None
        cam_xz, t_guess, v_guess = self._initial_guess(pend, t, R_i, pim)
        pose_guess = gtsam.Pose3(gtsam.Rot3.ClosestTo(R_i), t_guess)
        batch = _FactorBatch({X(i): t, V(i): t, B(i): t})
        # keyword overloads: pybind tries Values.insert's ~46 overloads in order, and the
        # positional bias insert alone cost ~0.1 ms
        batch.values.insert(X(i), pose3=pose_guess)
        batch.values.insert(V(i), v_guess)
        batch.values.insert(B(i), constant_bias=self._latest_bias)

        if i == 0:
            self._first_kf_time_s = t
            self._add_first_priors(batch, pose_guess, v_guess, pend.estimate)
        else:
            self._add_motion(batch, i, pend, R_i, pim, v_guess)
        self._add_attitude_and_plane(batch, i, pose_guess, t_guess)
        self._guess_z_m.append((i, float(t_guess[2])))
        if self.config.factors.landmarks:
            self._add_landmarks(batch, i, t, pend.observations, R_i, t_guess)

        self._n_keyframes += 1
        self._last_kf_time_s = t
        self._last_kf_R = R_i
        if self.config.factors.saturation_bridge_relative:
            self._recent_kf.append((t, i, R_i, self._imu_t[-2:], self._imu_g[-2:]))
        self._trim_imu(t)
        if self._latest_nav is None or pend.estimate is not None:
            self._latest_nav = (pose_guess, v_guess)
        return KeyframeUpdate(
            index=i,
            timestamp_s=t,
            factors=batch.graph,
            values=batch.values,
            timestamps=batch.stamps,
            R_world_imu=R_i,
            filter_camera_xz_m=np.asarray(cam_xz, dtype=float).reshape(2),
            factor_keys=batch.keys,
            flagged_imu_factor=batch.flagged_imu,
        )

    def _preintegrate(self, t: float) -> gtsam.PreintegratedCombinedMeasurements:
        """GTSAM preintegration from the previous keyframe to ``t`` (s) over the step means
        of ``config.preintegration``, with the sampled-signal model error in its noise."""
        cfg = self.config
        assert self._last_kf_time_s is not None
        ts = np.asarray(self._imu_t)
        acc = np.asarray(self._imu_a)  # (one conversion for the sampler and the model error)
        t0 = self._last_kf_time_s
        if self._compiled_steps is not None and ts.size and t > t0:
            a_mid, g_mid, dt = self._compiled_steps(
                ts, acc, np.asarray(self._imu_g), t0, t, TIME_TOL_S, cfg.preintegration_substeps
            )
        else:
            sampler = SAMPLERS[cfg.preintegration]
            a_mid, g_mid, dt = sampler(
                ts, acc, np.asarray(self._imu_g), t0, t, cfg.preintegration_substeps
            )
        params = self._params
        # (every sample trusted, the usual case: skip the array work, the answer is (0, 0))
        if any(xa > 0 or xg > 0 for xa, xg in self._imu_x):
            x_vel, x_rot = distrust_variances(ts, self._imu_x, t0, t)
        else:
            x_vel = x_rot = 0.0
        # a repaired packet among the distrusted samples touching the interval (saturated
        # stretches are the saturation prior's business, imu_faults.py)
        self._interval_flagged = (x_vel > 0 or x_rot > 0) and repaired_in(ts, self._imu_r, t0, t)
        per_step = cfg.distrust_noise == "per_step" and (x_vel > 0 or x_rot > 0)
        gain_a, gain_g = cfg.imu_discretization_gain, cfg.gyro_discretization_gain
        if gain_a > 0 or gain_g > 0 or x_vel > 0 or x_rot > 0:
            dvar = rvar = 0.0
            gyr = np.asarray(self._imu_g) if gain_g > 0 else None
            if self._compiled_dvar is not None and ts.size:
                dvar = self._compiled_dvar(ts, acc, t0, t, TIME_TOL_S)
                if gyr is not None:
                    rvar = self._compiled_dvar(ts, gyr, t0, t, TIME_TOL_S)
            else:
                dvar = discretization_velocity_var(ts, acc, t0, t)
                if gyr is not None:
                    rvar = discretization_rotation_var(ts, gyr, t0, t)
            extra = gain_a**2 * dvar
            extra_rot = gain_g**2 * rvar
            spread_vel, spread_rot = (0.0, 0.0) if per_step else (x_vel, x_rot)
            params = self._interval_params
            set_white_noise(params, cfg, extra + spread_vel, t - t0, extra_rot + spread_rot)
        pim = gtsam.PreintegratedCombinedMeasurements(params, self._latest_bias)
        if per_step:
            # GTSAM adds (accelerometer covariance) x dt of velocity variance per step and
            # reads the covariance from the (shared) params at every step: raise it for the
            # steps the distrusted samples fall in, then put it back
            vel_var, rot_var = distrust_step_variances(ts, self._imu_x, self._last_kf_time_s, dt)
            vel_cov = distrust_step_covariances(
                ts, self._imu_x, self._imu_c, self._last_kf_time_s, dt
            )
            # copies: the getters return views of the params' own matrices
            acc0 = np.array(params.getAccelerometerCovariance(), dtype=float, copy=True)
            gyr0 = np.array(params.getGyroscopeCovariance(), dtype=float, copy=True)
            for k, (a_k, g_k, dt_k, vv, rv) in enumerate(
                zip(a_mid, g_mid, dt, vel_var, rot_var, strict=True)
            ):
                distrusted = vv > 0 or rv > 0
                if distrusted:
                    cov_k = np.eye(3) * vv if vel_cov is None else vel_cov[k]
                    params.setAccelerometerCovariance(acc0 + cov_k / dt_k)
                    params.setGyroscopeCovariance(gyr0 + np.eye(3) * (rv / dt_k))
                pim.integrateMeasurement(a_k, g_k, float(dt_k))
                if distrusted:
                    params.setAccelerometerCovariance(acc0)
                    params.setGyroscopeCovariance(gyr0)
        else:  # the usual case: the same steps, without the per-step checks
            for k, dt_k in enumerate(dt.tolist()):
                pim.integrateMeasurement(a_mid[k], g_mid[k], dt_k)
        return pim

    def _initial_guess(
        self,
        pend: _Pending,
        t: float,
        R_i: NDArray[np.float64],
        pim: gtsam.PreintegratedCombinedMeasurements | None,
    ) -> tuple[NDArray[np.float64], NDArray[np.float64], NDArray[np.float64]]:
        """Camera x-z, IMU position and IMU velocity guesses (world, m and m/s): the filter's
        estimate, else the IMU prediction from the newest solved keyframe."""
        p_ic = self.imu_p_cam_m
        if pend.estimate is not None:
            cam_xz = np.asarray(pend.estimate.camera_xz_m, dtype=float).reshape(2)
            t_guess = imu_position_from_camera(cam_xz, R_i, p_ic)
            v_cam = _xz_to_3(pend.estimate.velocity_xz_mps)
            v_guess = v_cam - R_i @ cross3(self._gyro_at(t), p_ic)
            v_guess[1] = 0.0
        else:
            assert pim is not None and self._latest_nav is not None
            nav = pim.predict(gtsam.NavState(*self._latest_nav), self._latest_bias)
            t_guess = np.asarray(nav.pose().translation(), dtype=float).copy()
            v_guess = np.asarray(nav.velocity(), dtype=float).copy()
            cam_xz = (t_guess + R_i @ p_ic)[[0, 2]]
        return cam_xz, t_guess, v_guess

    def _add_first_priors(
        self,
        batch: _FactorBatch,
        pose_guess: gtsam.Pose3,
        v_guess: NDArray[np.float64],
        estimate: FrameEstimate | None = None,
    ) -> None:
        """First keyframe: tight pose prior, velocity prior at the guess (as uncertain as the
        filter says its guess is, ``first_velocity_filter_cov``), zero-bias prior."""
        cfg = self.config
        sig = self._diagonal(*[cfg.first_attitude_sigma_rad] * 3, *[cfg.first_position_sigma_m] * 3)
        batch.add(gtsam.PriorFactorPose3(X(0), pose_guess, sig), [X(0)])
        noise: gtsam.noiseModel.Base = gtsam.noiseModel.Isotropic.Sigma(
            3, cfg.first_velocity_sigma_mps
        )
        if (
            cfg.first_velocity_filter_cov
            and estimate is not None
            and estimate.cov_velocity_m2ps2 is not None
        ):
            cov = np.eye(3) * cfg.first_velocity_sigma_mps**2
            cov[np.ix_([0, 2], [0, 2])] += np.asarray(estimate.cov_velocity_m2ps2, dtype=float)
            noise = gtsam.noiseModel.Gaussian.Covariance(cov)
        est = _m_estimator(cfg.first_velocity_kernel, float(cfg.first_velocity_kernel_threshold))
        if est is not None:
            noise = gtsam.noiseModel.Robust.Create(est, noise)
        self.first_velocity_prior = FirstVelocityPrior(
            len(batch.keys),
            np.asarray(v_guess, dtype=float).copy(),
            noise,
            self._relaxed_velocity_noise(estimate),
        )
        batch.add(gtsam.PriorFactorVector(V(0), v_guess, noise), [V(0)])
        bsig = np.r_[[cfg.accel_bias_prior_sigma_mps2] * 3, [cfg.gyro_bias_prior_sigma_radps] * 3]
        batch.add(
            gtsam.PriorFactorConstantBias(
                B(0), gtsam.imuBias.ConstantBias(), gtsam.noiseModel.Diagonal.Sigmas(bsig)
            ),
            [B(0)],
        )

    def _relaxed_velocity_noise(
        self, estimate: FrameEstimate | None
    ) -> gtsam.noiseModel.Base | None:
        """The first velocity prior's noise with the filter's velocity covariance at that frame
        added in x-z (what the guess is really worth), for :meth:`first_velocity_fails`;
        None if the prior already carries it or the filter gave none."""
        cfg = self.config
        if (
            not cfg.first_velocity_test
            or cfg.first_velocity_filter_cov
            or estimate is None
            or estimate.cov_velocity_m2ps2 is None
        ):
            return None
        cov = np.eye(3) * cfg.first_velocity_sigma_mps**2
        cov[np.ix_([0, 2], [0, 2])] += np.asarray(estimate.cov_velocity_m2ps2, dtype=float)
        return gtsam.noiseModel.Gaussian.Covariance(cov)

    def first_velocity_testable(self, update: KeyframeUpdate) -> bool:
        """Whether ``update`` calls for the first velocity prior's test: its IMU factor spans
        a packet the fault monitor repaired, within the fixed-lag window of the first
        keyframe (``smoother.first_velocity_test``). A clean trial never calls for it."""
        fv = self.first_velocity_prior
        return (
            fv is not None
            and fv.relaxed_noise is not None
            and update.flagged_imu_factor is not None
            and self._first_kf_time_s is not None
            and update.timestamp_s - self._first_kf_time_s <= self.config.smoother_lag_s()
        )

    def first_velocity_fails(self, v0_mps: ArrayLike) -> bool:
        """Chi-square test (3 dof, ``smoother.first_velocity_test_probability``) of the first
        velocity prior at the estimate ``v0_mps`` of V(0): the prior is the filter's start
        guess, which the IMU chain to the later keyframes normally outvotes; when that chain
        spans a repaired packet, what the chain and vision say about V(0) decides instead
        (docs/method.md, IMU faults and clocks)."""
        fv = self.first_velocity_prior
        assert fv is not None
        base = fv.noise.noise() if isinstance(fv.noise, gtsam.noiseModel.Robust) else fv.noise
        w = base.whiten(np.asarray(v0_mps, dtype=float).reshape(3) - fv.value)
        d2 = float(w @ w)
        return d2 > chi2_quantile(self.config.first_velocity_test_probability, 3)

    def _add_motion(
        self,
        batch: _FactorBatch,
        i: int,
        pend: _Pending,
        R_i: NDArray[np.float64],
        pim: gtsam.PreintegratedCombinedMeasurements | None,
        v_guess: NDArray[np.float64],
    ) -> None:
        """Keyframe i-1 -> i: the IMU factor (also the bias random walk) or, without it, a
        bias chain and a weak velocity walk; the chained ICP displacement (eq. 3-4)."""
        cfg, fam = self.config, self.config.factors
        p_ic = self.imu_p_cam_m
        if fam.imu:
            assert pim is not None
            f_imu: gtsam.NoiseModelFactor = gtsam.CombinedImuFactor(
                X(i - 1), V(i - 1), X(i), V(i), B(i - 1), B(i), pim
            )
            if self.robust_imu and cfg.imu_robust_kernel != "none":
                f_imu = f_imu.cloneWithNewNoiseModel(
                    robust_noise(
                        cfg, f_imu.noiseModel(), cfg.imu_robust_kernel, cfg.imu_robust_threshold
                    )
                )
            if self._interval_flagged:
                batch.flagged_imu = len(batch.keys)
                self.flagged_intervals.append(i)
            batch.add(f_imu, [X(i - 1), V(i - 1), X(i), V(i), B(i - 1), B(i)])
        else:  # keep the bias chain connected without the IMU
            bsig = self._diagonal(
                *[cfg.accel_bias_prior_sigma_mps2] * 3, *[cfg.gyro_bias_prior_sigma_radps] * 3
            )
            batch.add(
                gtsam.BetweenFactorConstantBias(B(i - 1), B(i), gtsam.imuBias.ConstantBias(), bsig),
                [B(i - 1), B(i)],
            )
            if not (fam.displacement and pend.displacement is not None):
                # velocity otherwise unconstrained: weak random walk between keyframes
                batch.add(
                    gtsam.BetweenFactorVector(V(i - 1), V(i), np.zeros(3), self._isotropic(1.0)),
                    [V(i - 1), V(i)],
                )
        if fam.displacement and pend.displacement is not None:
            assert self._last_kf_R is not None
            R_h = self._last_kf_R
            d3 = _xz_to_3(pend.displacement[0])
            dt_imu = d3 - (R_i - R_h) @ p_ic  # IMU motion in world axes
            meas = gtsam.Pose3(gtsam.Rot3.ClosestTo(R_h.T @ R_i), R_h.T @ dt_imu)
            C3 = _cov3_from_xz(pend.displacement[1], cfg)
            noise = _between_noise(R_i.T @ C3 @ R_i, cfg)
            batch.add(gtsam.BetweenFactorPose3(X(i - 1), X(i), meas, noise), [X(i - 1), X(i)])
        if not fam.imu:
            batch.add(
                gtsam.PriorFactorVector(V(i), v_guess, self._isotropic(LOOSE_SIGMA)),
                [V(i)],
            )

    def _add_attitude_and_plane(
        self, batch: _FactorBatch, i: int, pose_guess: gtsam.Pose3, t_guess: NDArray[np.float64]
    ) -> None:
        """Attitude prior (AHRS, heading removed), sagittal-plane priors on position (with the
        optional weak absolute x-z) and velocity."""
        cfg, fam = self.config, self.config.factors
        if fam.attitude and i > 0:
            sig = self._diagonal(*[cfg.attitude_sigma_rad] * 3, *[LOOSE_SIGMA] * 3)
            batch.add(gtsam.PriorFactorPose3(X(i), pose_guess, sig), [X(i)])
        if (fam.planar or fam.weak_position) and i > 0:
            s_xz = cfg.weak_position_sigma_m if fam.weak_position else LOOSE_SIGMA
            s_y = cfg.lateral_position_sigma_m if fam.planar else LOOSE_SIGMA
            batch.add(
                gtsam.PoseTranslationPrior3D(X(i), t_guess, self._diagonal(s_xz, s_y, s_xz)),
                [X(i)],
            )
        if fam.planar:
            sig = self._diagonal(LOOSE_SIGMA, cfg.lateral_velocity_sigma_mps, LOOSE_SIGMA)
            batch.add(gtsam.PriorFactorVector(V(i), np.zeros(3), sig), [V(i)])

    def _add_landmarks(
        self,
        batch: _FactorBatch,
        i: int,
        t: float,
        observations: list[FrameObservation],
        R_i: NDArray[np.float64],
        t_guess: NDArray[np.float64],
    ) -> None:
        """Corner landmarks and stance anchors (long-span constraints): a new landmark gets
        its node at the observed position and a weak prior; every observation a robust
        BetweenFactorPose3 from X(i)."""
        if not observations:  # (most keyframes: skip the rotation below)
            return
        cfg = self.config
        p_ic = self.imu_p_cam_m
        rot_i = gtsam.Rot3.ClosestTo(R_i)
        for ob in observations:
            if isinstance(ob, VelocityObservation):
                if cfg.factors.saturation_bridge:
                    self._add_bridge_velocity(batch, i, t, ob, R_i)
                continue
            if isinstance(ob, LevelObservation):
                self._add_height_landmark(batch, i, t, ob, rot_i, R_i, t_guess)
                continue
            cov = np.asarray(ob.cov_m2, dtype=float).reshape(2, 2)
            if isinstance(ob, StanceObservation):
                lkey = LandmarkKey("ankle", ob.stance_id)
                o3 = _xz_to_3(ob.ankle_rel_xz_m)
            else:
                lkey = LandmarkKey("corner", ob.track_id)
                o3 = _xz_to_3(ob.corner_rel_xz_m)
                cov = cov + np.eye(2) * cfg.corner_landmark_sigma_m**2
            lk = self._landmark_node(batch, lkey, t_guess + R_i @ p_ic + o3)
            meas = gtsam.Pose3(rot_i.inverse(), R_i.T @ o3 + p_ic)
            noise = _between_noise(_cov3_from_xz(cov, cfg), cfg)
            batch.add(gtsam.BetweenFactorPose3(X(i), lk, meas, noise), [X(i), lk])
            batch.stamps[lk] = t
            if (
                cfg.factors.stance_velocity
                and isinstance(ob, StanceObservation)
                and ob.camera_velocity_xz_mps is not None
                and ob.velocity_cov is not None
            ):
                self._add_stance_velocity(batch, i, t, ob, R_i)

    def _add_height_landmark(
        self,
        batch: _FactorBatch,
        i: int,
        t: float,
        ob: LevelObservation,
        rot_i: gtsam.Rot3,
        R_i: NDArray[np.float64],
        t_guess: NDArray[np.float64],
        graph_z_m: float | None = None,
    ) -> None:
        """A level surface as a z-only landmark L(j) (a Pose3 like the corners', its x, y and
        rotation held by its weak prior), associated across keyframes by the filter's height
        landmarks (filter.level_landmarks) or, with ``factors.height_landmark_association``
        'graph', by the graph's own height (:meth:`_graph_level_key`; ``graph_z_m`` the
        keyframe's IMU z the graph solved, else its guess moved by the newest solved
        keyframe's correction).

        The factor is a BetweenFactorPose3 from L(j) to X(i), not from X(i) as a corner's:
        its translation error is then R_i^T (world error) (R_L = I, R_i the attitude the
        observation was built with, a constant), and only the world-z component of it is
        weighted (a rank-one square-root information along R_i^T e_z; rotation, x and y carry
        nothing: a height says nothing about where along the surface it was seen). From X(i)
        the error would turn with the keyframe's refined rotation, and the landmark's free x,
        metres from the keyframe on a long floor, would leak into z (1 m x 0.3 deg = 5 mm).
        Robustified with ``height_landmark_kernel`` (by default the displacements' kernel)."""
        cfg = self.config
        # world vector camera -> the surface point seen, and landmark -> IMU origin
        o3 = np.array([float(ob.x_rel_m), 0.0, float(ob.height_rel_m)])
        lever = R_i @ self.imu_p_cam_m + o3
        surface_z_m: float | None = None  # the surface's world z (graph association), m
        if cfg.factors.height_landmark_association == "graph":
            if self.defer_levels and graph_z_m is None:
                self.deferred_levels.append(
                    DeferredLevel(i, t, ob, rot_i, R_i, np.array(t_guess, dtype=float))
                )
                return
            z_kf = float(t_guess[2]) + self._graph_dz_m if graph_z_m is None else graph_z_m
            surface_z_m = z_kf + float(lever[2])
            lkey = self._graph_level_key(surface_z_m)
        else:
            lkey = LandmarkKey("level", ob.level_id)
        new = lkey not in self._landmark_of
        lk = self._landmark_node(batch, lkey, t_guess + lever)
        if new:
            self._level_x_m[lk] = float(t_guess[0] + lever[0])
            if surface_z_m is not None:  # (graph association)
                self._graph_levels[lk] = _GraphLevel(lkey, surface_z_m)
        sigma = math.sqrt(max(float(ob.var_m2), cfg.min_measurement_sigma_m**2))
        sqrt_info = np.zeros((6, 6))
        # one upper-triangular row (GTSAM keeps only the upper triangle): world z in the
        # measurement's frame, R_i^T e_z, over its sigma
        sqrt_info[3, 3:] = R_i[2, :] / sigma
        base = gtsam.noiseModel.Gaussian.SqrtInformation(sqrt_info)
        if cfg.height_landmark_kernel == "default":
            noise = robust_noise(cfg, base)
        else:
            noise = robust_noise(
                cfg, base, cfg.height_landmark_kernel, cfg.height_landmark_kernel_threshold
            )
        # the unweighted x: the keyframe's guessed x from the landmark's (which its prior
        # keeps where it started), not the surface point's lever. The error is Pose3's
        # Logmap, whose translation turns with the rotation error (v = t - omega x t / 2 +
        # ...): an x residual of metres (a floor followed for 20 s) times the smoothed and
        # the filter's attitudes' difference leaked millimetres into z, and x drifted
        meas_t = -lever
        meas_t[0] = float(t_guess[0]) - self._level_x_m[lk]
        meas = gtsam.Pose3(rot_i, meas_t)
        batch.add(gtsam.BetweenFactorPose3(lk, X(i), meas, noise), [lk, X(i)])
        batch.stamps[lk] = t

    def _graph_level_key(self, surface_z_m: float) -> LandmarkKey:
        """The graph's association of a surface at world height ``surface_z_m`` (m): the
        nearest live height landmark if within ``height_landmark_gate_m`` and clearly nearest
        (the next at least twice as far; the filter's rule, filter/level_landmarks.py), else
        a new one. An associated landmark's height follows the surface (until the smoother's
        next estimate, :meth:`set_level_heights`), so slow drift of the batch's first
        solution does not split it."""
        gate = self.config.height_landmark_gate_m
        ranked = sorted((abs(surface_z_m - g.z_m), k) for k, g in self._graph_levels.items())
        if ranked and ranked[0][0] <= gate:
            if len(ranked) == 1 or ranked[1][0] >= 2.0 * ranked[0][0]:
                g = self._graph_levels[ranked[0][1]]
                g.z_m = surface_z_m
                return g.key
        lkey = LandmarkKey("level", self._n_graph_levels)
        self._n_graph_levels += 1
        return lkey

    def associate_deferred_levels(
        self, z_of: Callable[[int], float]
    ) -> tuple[gtsam.NonlinearFactorGraph, gtsam.Values]:
        """The batch's held-back level observations (graph association), associated in time
        order by the keyframes' IMU z from ``z_of(index)`` (m, the first solution): their
        factors and the new landmarks' initial values (at the observed surfaces)."""
        batch = _FactorBatch({})
        for d in self.deferred_levels:
            z_kf = float(z_of(d.index))
            t_at = np.array(d.t_guess_m, dtype=float)
            t_at[2] = z_kf  # the new landmark's node at the surface the solution sees
            self._add_height_landmark(
                batch, d.index, d.timestamp_s, d.observation, d.rot, d.R_world_imu, t_at, z_kf
            )
        self.deferred_levels = []
        return batch.graph, batch.values

    def _add_stance_velocity(
        self,
        batch: _FactorBatch,
        i: int,
        t: float,
        ob: StanceObservation,
        R_i: NDArray[np.float64],
    ) -> None:
        """V(i) from the still ankle: v_ankle = v_imu + omega x (ankle - imu) = 0, world axes,
        loose laterally; with the filter's sigma (``ob.velocity_cov``), only where the filter
        fused its own stance velocity (it passed the filter's gate).

        omega is the gyro interpolated to the keyframe time (the keyframe is completed once
        an IMU sample at or after it has arrived), for the whole lever IMU -> camera -> ankle.
        The filter's ``camera_velocity_xz_mps`` is causal: it uses the latest gyro sample,
        up to one IMU period (10 ms) before the frame, and in stance the shank's pitch rate
        changes by 15-20 rad/s^2 at 1.5x cadence; with that rate for the camera-ankle part
        and the interpolated one for the IMU-camera part, the prior was off by 0.03 m/s rms
        (up to 0.07, sweep cadence_1.5 s1000, against the true IMU velocity); with one
        interpolated rate, 0.002-0.005 m/s."""
        assert ob.camera_velocity_xz_mps is not None and ob.velocity_cov is not None
        omega = R_i @ self._gyro_at(t)
        imu_to_ankle = R_i @ self.imu_p_cam_m + _xz_to_3(ob.ankle_rel_xz_m)
        v_imu = -cross3(omega, imu_to_ankle)
        vc = np.asarray(ob.velocity_cov, dtype=float).reshape(2, 2)
        cov3 = np.diag([0.0, 1.0, 0.0])
        _put_xz(cov3, vc)
        batch.add(
            gtsam.PriorFactorVector(V(i), v_imu, gtsam.noiseModel.Gaussian.Covariance(cov3)),
            [V(i)],
        )

    def _add_bridge_velocity(
        self,
        batch: _FactorBatch,
        i: int,
        t: float,
        ob: VelocityObservation,
        R_i: NDArray[np.float64],
    ) -> None:
        """The leg-chain bridge across a saturated stretch (filter/leg_bridge.py) on the
        keyframe velocities, moved from the camera to the IMU with the gyro interpolated to
        each keyframe's time (v_imu = v_cam - omega x (R p_cam)); loose laterally.

        With ``factors.saturation_bridge_relative`` and the keyframe before the stretch still
        known: V(i) - V(k) = the camera velocity change the filter's IMU (before and after
        the stretch) and the chain (across it) measured, with the chain's covariance alone.
        Otherwise V(i) gets the bridge's velocity as a prior, which rests on the filter's own
        velocity before the stretch: information the graph already holds (the same vision),
        counted twice. Either noise also holds ``ob.discretisation_cov`` (the chain's own
        discretisation error at the stretch's ends) with
        ``factors.saturation_bridge_discretisation``."""
        lever_i = self._lever_velocity(R_i, self._gyro_at(t))  # v_cam - v_imu at keyframe i
        cov3 = np.diag([0.0, 1.0, 0.0])
        # the chain's own discretisation error at the stretch's ends, if handed over
        # (factors.saturation_bridge_discretisation): a push-off the joints do not resolve
        disc = np.zeros((2, 2))
        if self.config.factors.saturation_bridge_discretisation and (
            ob.discretisation_cov is not None
        ):
            disc = np.asarray(ob.discretisation_cov, dtype=float).reshape(2, 2)
        k = self._keyframe_before_bridge(ob)
        if k is not None:
            k_index, lever_k = k
            assert ob.change_xz_mps is not None and ob.change_cov is not None
            dv_imu = _xz_to_3(ob.change_xz_mps) - lever_i + lever_k
            _put_xz(cov3, np.asarray(ob.change_cov, dtype=float).reshape(2, 2) + disc)
            batch.add(
                gtsam.BetweenFactorVector(
                    V(k_index), V(i), dv_imu, gtsam.noiseModel.Gaussian.Covariance(cov3)
                ),
                [V(k_index), V(i)],
            )
            return
        v_imu = _xz_to_3(ob.camera_velocity_xz_mps) - lever_i
        _put_xz(cov3, np.asarray(ob.cov, dtype=float).reshape(2, 2) + disc)
        batch.add(
            gtsam.PriorFactorVector(V(i), v_imu, gtsam.noiseModel.Gaussian.Covariance(cov3)),
            [V(i)],
        )

    def _keyframe_before_bridge(
        self, ob: VelocityObservation
    ) -> tuple[int, NDArray[np.float64]] | None:
        """The index of the keyframe ``ob``'s velocity change starts at and its lever-arm
        velocity omega x (R p_cam) (m/s, world), or None (the relative form is off, the
        observation has no change, or that keyframe is no longer remembered)."""
        if (
            not self.config.factors.saturation_bridge_relative
            or ob.since_timestamp_s is None
            or ob.change_xz_mps is None
            or ob.change_cov is None
        ):
            return None
        for t_k, k_index, R_k, ts, gs in reversed(self._recent_kf):
            if abs(t_k - ob.since_timestamp_s) < TIME_TOL_S:
                return k_index, self._lever_velocity(R_k, _gyro_interp(t_k, ts, gs))
        return None

    def _interpolate_held(self) -> None:
        """The newest sample is a measurement: replace the held accelerometer samples just
        before it (ImuSample.accel_held, set by the fault monitor over a corrupted packet) by
        the linear interpolation in time between the trusted samples either side, with
        ``interpolated_accel_sigma_mps2`` as their extra sigma (and their gyro too, if
        ``held_gyro_interpolation``). Runs before the sample can
        complete a keyframe, so the preintegration that follows uses the interpolation."""
        k = len(self._imu_h) - 1
        j = k
        while j > 0 and self._imu_h[j - 1]:
            j -= 1
        if j == k or j == 0:  # nothing held, or no trusted sample before the run (trimmed)
            return
        t0, a0 = self._imu_t[j - 1], self._imu_a[j - 1]
        t1, a1 = self._imu_t[k], self._imu_a[k]
        g0, g1 = self._imu_g[j - 1], self._imu_g[k]
        cfg = self.config
        sig = cfg.interpolated_accel_sigma_mps2
        gyro = cfg.held_gyro_interpolation
        for m in range(j, k):
            w = (self._imu_t[m] - t0) / (t1 - t0)
            self._imu_a[m] = (1.0 - w) * a0 + w * a1
            sig_g = self._imu_x[m][1]
            g_interp = (1.0 - w) * g0 + w * g1
            if gyro:
                self._imu_g[m] = g_interp
                sig_g = cfg.interpolated_gyro_sigma_radps
            measured = self._imu_m[m]
            cov = None
            if cfg.held_keep_consistent_axes and measured is not None:
                # axes whose measurement agrees with the neighbours keep it (one-axis spike)
                p, sg = cfg.held_axis_probability, cfg.interpolated_gyro_sigma_radps
                self._imu_a[m] = keep_consistent_axes(measured[0], self._imu_a[m], sig, p)
                ok = keep_consistent_axes(measured[1], g_interp, sg, p) == measured[1]
                self._imu_g[m] = np.where(ok, measured[1], self._imu_g[m])
                if cfg.held_axis_distrust:
                    # the kept axes are measurements: the extra variance on the others only
                    cov = interpolated_axes_cov(self._imu_a[m], measured[0], sig * sig)
            self._imu_x[m] = (sig, sig_g)
            self._imu_c[m] = cov
            self._imu_h[m] = False

    def _trim_imu(self, t: float) -> None:
        """Keep the IMU samples at or before the keyframe at ``t`` (s) that the next interval
        needs (one for the interpolation, four for the fourth differences of its first
        samples)."""
        ts = np.asarray(self._imu_t)
        k0 = max(0, int(np.searchsorted(ts, t - TIME_TOL_S, side="right")) - 4)
        del self._imu_t[:k0], self._imu_a[:k0], self._imu_g[:k0], self._imu_q[:k0]
        del self._imu_x[:k0], self._imu_h[:k0], self._imu_m[:k0], self._imu_r[:k0]
        del self._imu_c[:k0]
