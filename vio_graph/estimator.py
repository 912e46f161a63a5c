"""The online estimator: what a prosthesis controller runs, one estimate per depth frame.

Feed it IMU samples, joint angles and depth frames in time order (no look-ahead); each depth
frame returns a :class:`vio_graph.types.FrameEstimate` with the camera, knee, ankle, heel and
toe positions, velocity, covariance, status and per-stage timings. The CLI's replay loop
(``vio_graph.replay``) drives exactly this object: :meth:`OnlineEstimator.add_imu` returns the
:class:`~vio_graph.protocol.ImuStep` and :meth:`OnlineEstimator.process_frame` the
:class:`~vio_graph.protocol.FrameRecord` that every other estimator (baselines, smoothers)
then takes (vio_graph/protocol.py).

Per frame, in the paper's order (Section II):
  1. attitude: the latest IMU orientation, heading removed -> R_ground_cam (eq. 2);
  2. IMU prediction of the camera displacement since the previous frame (ICP's T_0);
  3. front end: slice, smoothing, terrain, corners, ICP, gating (eq. 1-4);
  4. pitch correction from the level surfaces in the slice (frontend/level.py; used by
     everything after it, and the previous slice is re-expressed with it), then the
     SP-ESKF correction with the displacement (eq. 8) -- or IMU-only if none passed;
     then landmarks (``_fuse_landmarks``, each switchable in FilterConfig):
     a. corner landmarks (``corner_landmarks``): the front end's corner observation (corner
        minus camera, track id kept for the same physical corner) is a landmark in the
        filter state (SagittalEskf.update_landmark: augmented at first sight with the
        current position uncertainty, relative measurement afterwards). A landmark is kept
        for ``corner_memory_s`` after its last sight, and a new track that lands on a
        remembered corner is re-identified as it (``corner_reidentify_radius_m``). It bounds
        drift while the corner is in view and when the shank looks back at it.
     b. stance anchoring (``stance_anchor``): filter/stance.py flags the foot's stance from
        the ankle acceleration seen by the shank IMU (lever arm to the ankle, no
        look-ahead); during a stance the ankle fixed at its onset is a landmark observed
        through the leg, ankle - camera = R_shank (ankle_in_shank - camera_in_shank), with
        R_shank the IMU shank pitch; ungated (``stance_gate``) so that a velocity drifted
        during a blind swing cannot lock the anchor out. It makes x observable on level
        ground and on stair descent, where risers face away.
     c. height landmarks (``level_landmarks``, filter/level_landmarks.py): the height of
        every level surface the level aiding finds in the slice (tread, landing, floor) is
        a z-only landmark (SagittalEskf.update_height_landmark), associated by height. Several
        are in view at once, so the camera height is handed from surface to surface by
        co-observation; one corner a frame cannot do that, and the displacements' and
        anchors' sub-millimetre per-step biases otherwise add up over a long stair.
     Measured (toe ATE x cm, filter, displacements only -> + corners -> + stance):
     downstair s1 31.8 -> 7.9 -> 4.9, upstair s4 29.5 -> 15.6 -> 3.6, level s1 524 -> 4.1
     (stance alone; measured when the landmarks were introduced, with ``vio-graph run
     --mode filter`` and the switches above turned off in turn).
  5. knee from the camera and the knee <- camera extrinsic; ankle, heel, toe by forward
     kinematics from the thigh IMU and the joint encoders (Fig. 3);
  6. keyframe decision (the map is built after the replay from the keyframe profiles,
     vio_graph/mapping/);
  7. safety outputs (``config.safety``, vio_graph/safety/): toe clearance to the terrain
     seen so far, the next edge ahead, the predicted minimum clearance and near-trip
     warning, the placement on the tread at landing (``FrameEstimate.safety``).
"""

from __future__ import annotations

import dataclasses
import math
import time
from collections import deque
from collections.abc import Callable
from dataclasses import dataclass
from functools import cached_property
from typing import TypeVar

import numpy as np
from numpy.typing import ArrayLike, NDArray

from vio_graph.config import PipelineConfig
from vio_graph.errors import EstimationError
from vio_graph.filter.attitude import (
    AttitudeTracker,
    PitchOffsetFilter,
    SurfaceBendTest,
    VendorPitchVariance,
    pitch_disagreement_rad,
    with_pitch_offset,
)
from vio_graph.filter.corner_landmarks import CornerLandmarks
from vio_graph.filter.eskf import SagittalEskf
from vio_graph.filter.fast_imu import (
    Mat3,
    as_f64,
    mat3_mul,
    mat3_quat,
    pitch_offset_quat,
    remove_yaw_mat3,
    rot_y_mat3,
    sagittal_rotation_fast,
)
from vio_graph.filter.gating import chi2_2dof_quantile, chi2_quantile
from vio_graph.filter.imu_faults import (
    ImuFaultMonitor,
    SaturationScaleLearner,
    velocity_fault_cov,
)
from vio_graph.filter.imu_repair import NextSampleRepair
from vio_graph.filter.leg_bridge import LegChainBridge
from vio_graph.filter.level_landmarks import LevelLandmarks
from vio_graph.filter.stance import FootRotationTest, StanceConsistencyTest, StanceDetector
from vio_graph.filter.time_offset import ClockModel, FrameStampTest, TimeOffsetEstimator
from vio_graph.frontend.frontend import FrontendResult, VisualFrontend
from vio_graph.frontend.level import SurfaceTilt, measure_face_lean, measure_surface_tilt
from vio_graph.geometry import (
    invert_transform,
    matrix_from_quat_wxyz,
    pitch_of,
    quat_wxyz_from_matrix,
    remove_yaw,
    rot_y,
)
from vio_graph.health import HealthLimits, HealthMonitor, input_fault_context
from vio_graph.keyframes import KeyframeSelector
from vio_graph.kinematics import (
    LegModel,
    LegPoints,
    knee_from_camera,
    leg_points_from_knee,
    leg_points_single,
    shank_pitch_rad,
)
from vio_graph.protocol import FrameRecord, ImuStep
from vio_graph.recording.metadata import RecordingMetadata
from vio_graph.safety.online import SafetyMonitor
from vio_graph.types import (
    ContactSample,
    CornerObservation,
    DepthFrame,
    Displacement2D,
    EstimateStatus,
    FrameEstimate,
    ImuSample,
    JointAngles,
    LandmarkKey,
    LevelObservation,
    StanceObservation,
    VelocityObservation,
)

#: what the front end's tracker says when ICP disagrees with the IMU prediction
_PREDICTION_REFUSAL = "disagrees with the IMU prediction"
#: the 2x2 identity, never written: ``_I2 * v`` is ``np.eye(2) * v`` (a new array) without
#: building the identity each frame (~1 us a call, several calls a frame)
_I2 = np.eye(2)

_T = TypeVar("_T")


def reference_pitch_offset_quat(
    quat_wxyz: NDArray[np.float64], offset_rad: float
) -> NDArray[np.float64]:
    """numpy reference of ``fast_imu.pitch_offset_quat`` (the tests compare the two)."""
    R = with_pitch_offset(matrix_from_quat_wxyz(quat_wxyz), offset_rad)
    return quat_wxyz_from_matrix(R)


#: per-IMU-sample closed forms (filter/fast_imu.py); the tests swap in the numpy references
#: (``reference_pitch_offset_quat``, ``filter.eskf.sagittal_rotation``) and compare states.
_pitch_offset_quat = pitch_offset_quat
_sagittal_rotation = sagittal_rotation_fast


def _saturated(sample: ImuSample) -> bool:
    """The fault monitor marked an accelerometer axis of ``sample`` at its rail (an extra
    sigma on a measured, not held, accelerometer)."""
    return sample.accel_extra_sigma_mps2 > 0.0 and not sample.accel_held


def _median_finite(values: list[float]) -> float:
    """np.median of finite floats (at least one): the middle value, or the two middle ones
    summed and halved, as np.median's mean of two rounds them (the same float)."""
    v = sorted(values)
    n = len(v)
    m = n // 2
    return v[m] if n % 2 else (v[m - 1] + v[m]) / 2.0


def _pooled(
    pool: NDArray[np.float64], at: int, size: int, arr: NDArray[np.float64] | None
) -> NDArray[np.float64]:
    """The view ``pool[at:at + size]`` holding the values of ``arr`` (size ``size``): a state
    array moved into the one-call kernel's pool (``compiled_imu.POOL_*``)."""
    if arr is None or arr.shape != (size,):
        raise EstimationError(f"state array of shape {size} expected for the kernel's pool")
    view = pool[at : at + size]
    view[:] = arr
    return view


def _replaced(sample: ImuSample, timestamp_s: float, quat_wxyz: NDArray[np.float64]) -> ImuSample:
    """``dataclasses.replace(sample, timestamp_s=..., quat_wxyz=...)`` without its field
    introspection (a few microseconds on the per-sample path). (Skipping the frozen
    ``__init__`` by filling the instance's ``__dict__`` builds it 3x faster, but a
    materialised ``__dict__`` makes every later attribute read ~3x slower, and every
    estimator reads the sample: tried and measured, not kept.)"""
    return ImuSample(
        timestamp_s,
        sample.accel_mps2,
        sample.gyro_radps,
        quat_wxyz,
        sample.accel_extra_sigma_mps2,
        sample.gyro_extra_sigma_radps,
        sample.accel_held,
        sample.measured_accel_mps2,
        sample.measured_gyro_radps,
        sample.accel_extra_cov_m2ps4,
    )


@dataclass(frozen=True)
class RigGeometry:
    """What the estimator needs to know about the sensors and the leg (from metadata).

    The IMU may be mounted with any rotation (``imu_T_cam`` as measured). Everything inside
    the estimator works with a *shank-aligned IMU*: the IMU's origin with the shank's axes
    (x anterior, z knee-ward, y lateral). :meth:`imu_in_shank_axes` turns each sample into
    it (accelerometer, gyro and vendor orientation rotated by ``R_shank_imu``) and
    ``shank_imu_T_cam`` is the camera in it, so the sagittal strapdown, the stance detector,
    the slice's ground frame and the smoothers' preintegration never depend on the mount.
    """

    K: NDArray[np.float64]
    imu_T_cam: NDArray[np.float64]
    knee_T_cam: NDArray[np.float64]
    leg: LegModel
    #: declared sensor ranges (m/s^2, rad/s) and nominal rates (Hz); None: unknown
    accel_range_mps2: float | None = None
    gyro_range_radps: float | None = None
    imu_rate_hz: float | None = None
    frame_rate_hz: float | None = None

    @classmethod
    def from_metadata(cls, meta: RecordingMetadata) -> RigGeometry:
        return cls(
            K=meta.camera.intrinsic_matrix(),
            imu_T_cam=meta.extrinsics.imu_T_cam_matrix(),
            knee_T_cam=meta.extrinsics.knee_T_cam_matrix(),
            leg=meta.leg.leg_model(),
            accel_range_mps2=meta.imu.accel_range_mps2,
            gyro_range_radps=meta.imu.gyro_range_radps,
            imu_rate_hz=meta.imu.rate_hz,
            frame_rate_hz=meta.camera.frame_rate_hz,
        )

    @cached_property
    def R_shank_imu(self) -> NDArray[np.float64]:
        """Rotation from the mounted IMU's axes to the shank's (exactly I when they agree
        within 1e-9, so a shank-aligned mount is used bit for bit as recorded)."""
        R = (self.knee_T_cam @ invert_transform(self.imu_T_cam))[:3, :3]
        return np.eye(3) if np.allclose(R, np.eye(3), atol=1e-9) else R

    @cached_property
    def imu_is_shank_aligned(self) -> bool:
        return bool(np.array_equal(self.R_shank_imu, np.eye(3)))

    @cached_property
    def shank_imu_T_cam(self) -> NDArray[np.float64]:
        """Camera pose in the shank-aligned IMU frame (IMU origin, shank axes), 4x4."""
        if self.imu_is_shank_aligned:
            return np.asarray(self.imu_T_cam, dtype=float)
        T = np.eye(4)
        T[:3, :3] = self.R_shank_imu @ self.imu_T_cam[:3, :3]
        T[:3, 3] = self.R_shank_imu @ self.imu_T_cam[:3, 3]
        return T

    def imu_in_shank_axes(self, sample: ImuSample) -> ImuSample:
        """``sample`` expressed in the shank-aligned IMU frame (the sample itself if the
        mount is shank-aligned): f' = R f, w' = R w, R_world_imu' = R_world_imu R^T."""
        if self.imu_is_shank_aligned:
            return sample
        R = self.R_shank_imu
        q = quat_wxyz_from_matrix(matrix_from_quat_wxyz(sample.quat_wxyz) @ R.T)
        ma, mg = sample.measured_accel_mps2, sample.measured_gyro_radps
        xc = sample.accel_extra_cov_m2ps4
        return dataclasses.replace(
            sample,
            accel_mps2=R @ np.asarray(sample.accel_mps2, dtype=float),
            gyro_radps=R @ np.asarray(sample.gyro_radps, dtype=float),
            quat_wxyz=q,
            measured_accel_mps2=None if ma is None else R @ np.asarray(ma, dtype=float),
            measured_gyro_radps=None if mg is None else R @ np.asarray(mg, dtype=float),
            accel_extra_cov_m2ps4=None if xc is None else R @ np.asarray(xc, dtype=float) @ R.T,
        )

    @property
    def R_imu_cam(self) -> NDArray[np.float64]:
        """Camera axes in the shank-aligned IMU frame."""
        return self.shank_imu_T_cam[:3, :3]

    @cached_property
    def R_knee_imu(self) -> NDArray[np.float64]:
        """Shank-aligned IMU axes in the knee frame (the identity up to rounding)."""
        return (self.knee_T_cam @ invert_transform(self.shank_imu_T_cam))[:3, :3]

    @property
    def camera_in_shank_xz_m(self) -> NDArray[np.float64]:
        return self.knee_T_cam[[0, 2], 3].copy()

    def shank_pitch_rad(self, R_world_imu: NDArray[np.float64]) -> float:
        """Shank segment pitch (rad) from the IMU attitude (heading removed)."""
        return float(pitch_of(R_world_imu @ self.R_knee_imu.T))

    def leg_points(
        self,
        camera_xz_m: ArrayLike,
        shank_pitch_imu_rad: ArrayLike,
        shank_pitch_chain_rad: ArrayLike,
        ankle_rad: ArrayLike,
        use_encoders: bool,
    ) -> LegPoints:
        """Knee, ankle, heel and toe (N, 2) by forward kinematics (Fig. 3): the knee from the
        camera through knee_T_cam with the IMU shank pitch; the rest of the chain with the IMU
        pitch or, ``use_encoders``, with thigh IMU pitch minus knee encoder (the paper's)."""
        knee = knee_from_camera(camera_xz_m, shank_pitch_imu_rad, self.camera_in_shank_xz_m)
        shank = shank_pitch_chain_rad if use_encoders else shank_pitch_imu_rad
        return leg_points_from_knee(self.leg, knee, shank, ankle_rad)

    def leg_points_one(
        self,
        camera_xz_m: ArrayLike,
        shank_pitch_imu_rad: float,
        shank_pitch_chain_rad: float,
        ankle_rad: float,
        use_encoders: bool,
    ) -> LegPoints:
        """:meth:`leg_points` for one pose on Python floats (the online estimator's frame;
        :func:`~vio_graph.kinematics.leg_points_single`, the same floats); each point (1, 2)."""
        shank = shank_pitch_chain_rad if use_encoders else shank_pitch_imu_rad
        return leg_points_single(
            self.leg, camera_xz_m, self.camera_in_shank_xz_m, shank_pitch_imu_rad, shank, ankle_rad
        )


def _turn_cov_m2(p_xz_m: ArrayLike, var_rad2: float) -> NDArray[np.float64]:
    """Covariance (m^2, 2x2) of where a point at ``p_xz_m`` from the camera lands when the
    slice is turned by a small angle of variance ``var_rad2`` (rad^2) about the camera: it
    moves along perp(p) = (z, -x) by the angle times |p|."""
    x, z = np.asarray(p_xz_m, dtype=float)
    perp = np.array([z, -x])
    return np.outer(perp, perp) * var_rad2


class OnlineEstimator:
    """SP-ESKF front end + fusion + kinematics + keyframes, frame by frame."""

    def __init__(
        self,
        config: PipelineConfig,
        rig: RigGeometry,
        initial_camera_xz_m: NDArray[np.float64] | None = None,
    ) -> None:
        self.config = config
        self.rig = rig
        self.frontend = VisualFrontend(config.frontend)
        self.filter = SagittalEskf(config.filter, rig.shank_imu_T_cam)
        self.attitude = AttitudeTracker(config.filter.attitude)
        self.pitch_offset = PitchOffsetFilter(config.filter.level_aiding)
        #: the vendor orientation's pitch error variance, estimated online
        #: (``filter.attitude.vendor_pitch_sigma_deg: auto``), or None
        self.vendor_pitch_variance = (
            VendorPitchVariance(config.filter.attitude.vendor_sigma_memory_s)
            if config.filter.attitude.vendor_pitch_sigma_deg == "auto"
            else None
        )
        self._level_rng = np.random.default_rng(config.frontend.seed)
        # the faces' RANSAC draws from its own stream: the level fits' draws stay as they were
        self._face_rng = np.random.default_rng([config.frontend.seed, 1])
        la = config.filter.level_aiding
        self.bend_test = SurfaceBendTest(la.bend_memory_s, la.bend_sigmas) if la.bend_test else None
        #: the level surfaces also carry their ray-fitted heights, for the smoothers only
        #: (smoother.height_landmark_heights)
        self._smoother_ray_heights = (
            config.smoother.factors.height_landmarks
            and config.smoother.height_landmark_heights == "ray_fit"
        )
        #: this frame's level-surface tilt measurement (None if no level surface was found)
        self.surface_tilt: SurfaceTilt | None = None
        self.keyframes = KeyframeSelector(config.keyframes)
        #: toe clearance, placement, terrain ahead (vio_graph/safety/online.py), or None
        self.safety = SafetyMonitor(config.safety) if config.safety.enabled else None
        self._p0 = (
            np.zeros(2) if initial_camera_xz_m is None else np.asarray(initial_camera_xz_m, float)
        )
        # the latest sample taken, in shank axes (its time and gyro are read): the corrected one
        # (pitch offset applied), or on the one-call path the measured one (same time, gyro)
        self._last_imu: ImuSample | None = None
        # R_world_imu's last answer: (t s, pitch offset rad, latest IMU sample, row-major R)
        self._attitude_memo: tuple[float, float, ImuSample, Mat3] | None = None
        #: the latest sample the fault monitor did not repair (its gyro is a measurement)
        self._last_trusted_imu: ImuSample | None = None
        self._last_taken_s: float | None = None  # stamp of the latest sample the filter took
        self._last_joints: JointAngles | None = None
        self._last_contact: ContactSample | None = None
        self._prev_frame: tuple[float, NDArray[np.float64]] | None = None  # (t, camera xz)
        # pitch correction (rad) made after the previous frame's slice was taken: the front end
        # re-expresses that slice with it before the next ICP
        self._ground_turn_rad = 0.0
        self._imu_ms = 0.0
        fc = config.filter
        # ankle (knee frame (0, 0, -L_shank)) in the IMU frame, for the stance detector
        imu_T_knee = invert_transform(rig.knee_T_cam @ invert_transform(rig.shank_imu_T_cam))
        ankle_in_imu = (imu_T_knee @ np.array([0.0, 0.0, -rig.leg.shank_length_m, 1.0]))[:3]
        self._stance = StanceDetector(
            ankle_in_imu, fc.stance_accel_threshold_mps2, fc.stance_window_s
        )
        self._stance_n = 0  # id of the current / next stance anchor
        # id of the current / next stance as the smoothers see it: an anchor restarted for the
        # filter's attitude (stance_attitude_reanchor) stays the same stance for the graphs,
        # whose own attitude at each keyframe observes the ankle
        self._stance_episode = 0
        self._stance_offset_rad = 0.0  # level-surface pitch offset when the anchor started
        # this frame's stance anchor (ankle - camera) as an observation, None outside stance
        self._stance_observation: StanceObservation | None = None
        # this frame's corner observation, track id replaced by its landmark's (re-identified)
        self._corner_observation: CornerObservation | None = None
        #: this frame's level surfaces as the height landmarks they were associated with
        #: (handed to the smoothers with the frame)
        self._level_observations: tuple[LevelObservation, ...] = ()
        self._corners = CornerLandmarks(
            fc.corner_reidentify_radius_m, fc.corner_memory_s, fc.max_corner_landmarks
        )
        self._levels = LevelLandmarks(
            fc.level_reidentify_m,
            fc.level_memory_s,
            fc.max_level_landmarks,
            fc.level_one_landmark_per_surface,
        )
        self._in_stance = False
        # the surface the foot last stood on (world z, m): the median over the stance's frames
        # of the lower of heel and toe; the terrain classifier compares one-level frames with
        # it (frontend.terrain.stand_level)
        self._stand_z_m: float | None = None
        self._stance_sole_z_m: list[float] = []
        self._refused_in_row = 0  # displacements refused by the gate in a row
        # the IMU interval this frame found wrong, for the smoothers (FrameRecord.imu_distrust)
        self._imu_distrust: tuple[float, float, float] | None = None
        self._imu_period_s = 1.0 / rig.imu_rate_hz if rig.imu_rate_hz else 0.01
        # the front end's latest displacement (fused or not), None before the first
        self._prev_visual: Displacement2D | None = None
        self._last_fix_t: float | None = None  # time of the last fused displacement (s)
        #: consistency of the fused estimate (vio_graph/health.py); see :meth:`health_report`
        self.health = HealthMonitor(HealthLimits(floor_m=fc.measurement_noise_floor_m))
        #: ankle minus camera in the shank frame (x, z), m, and the sigma (m) of the
        #: ankle-from-camera lever that a pitch-change error stance_pitch_sigma_rad makes
        self._ankle_from_camera_shank_m = (
            np.array([0.0, -rig.leg.shank_length_m]) - rig.camera_in_shank_xz_m
        )
        self._lever_sigma_m = fc.stance_pitch_sigma_rad * float(
            np.hypot(*self._ankle_from_camera_shank_m)
        )
        self._stance_test = StanceConsistencyTest(
            chi2_2dof_quantile(fc.stance_test_probability) if fc.stance_test else np.inf,
            self._lever_sigma_m,
            fc.measurement_noise_floor_m,
            fc.stance_test_weighted_chain,
        )
        # the foot turns about its heel or toe: the nearer one bounds the ankle's motion
        contact_m = min(
            float(np.hypot(*rig.leg.heel_in_foot_xz_m)), float(np.hypot(*rig.leg.toe_in_foot_xz_m))
        )
        self._foot_test = FootRotationTest(
            chi2_quantile(fc.stance_test_probability, 1) if fc.stance_foot_test else np.inf,
            contact_m,
            fc.stance_pitch_sigma_rad,
            fc.stance_slip_sigma_m,
        )
        #: stance bookkeeping for the health report: frames the detector proposed, refused by
        #: vision (displacement or foot rotation), of those by the foot rotation, refused by
        #: the anchor gate, gate refusals overridden by vision, anchored
        self.stance_stats = {
            "candidate_frames": 0,
            "vision_refused": 0,
            "foot_refused": 0,
            "gate_refused": 0,
            "vision_overrides": 0,
            "override_unpowered": 0,
            "attitude_reanchors": 0,
            "anchored_frames": 0,
            "velocity_fused": 0,
        }
        self._init_fault_handling()
        self._init_fused_sample_step()

    def _init_fused_sample_step(self) -> None:
        """The compiled one-call path of :meth:`_advance_imu` (``compiled_imu.sample_step``):
        set up when the attitude tracker, the filter's propagation and the stance detector
        all run compiled, with the tracked attitude as the strapdown's (the defaults on long
        recordings). :attr:`n_fused_samples` counts the samples it took."""
        fc = self.config.filter
        att, k = self.attitude, self.attitude._kernels
        self._fused_ws: NDArray[np.float64] | None = None
        # the tracker's (R, gyro) tuples last copied into the workspace
        self._fused_att: tuple = (None, None)
        self.n_fused_samples = 0
        # compiled_imu.imu_input's constants, when add_imu takes it (_init_one_call_input)
        self._input_consts: NDArray[np.float64] | None = None
        self.n_one_call_samples = 0
        if (
            k is None
            or not self._stance.compiled
            or att.config.source != "complementary"
            or fc.strapdown_attitude != "tracked"
        ):
            return
        ws = np.zeros(k.POOL_SIZE)  # the workspace, then imu_input's pool (POOL_* slots)
        if not self.filter.compiled_propagation_constants(ws):
            return
        ws[k.WS_GRAVITY : k.WS_GRAVITY + 2] = fc.gravity_xz_mps2
        ws[k.WS_R_ANKLE : k.WS_R_ANKLE + 3] = self._stance._r
        self._fused_ws = ws
        self._fused_step = k.sample_step
        # the workspace's slots: the tracker's R and gyro, the quaternion out, |a_ankle| out
        self._fused_slots = (slice(k.WS_R, k.WS_GYRO + 3), slice(k.WS_Q, k.WS_Q + 4), k.WS_MAG)
        self._fused_anchor = bool(fc.stance_anchor)
        self._init_one_call_input()

    def _init_one_call_input(self) -> None:
        """The compiled one-call path of :meth:`add_imu` (``compiled_imu.imu_input``: IMU
        clock model, fault check and :meth:`_advance_imu_fused`'s kernel in one call): set up
        when all three run compiled and the IMU is mounted shank-aligned (the defaults on long
        recordings). :attr:`n_one_call_samples` counts the samples it took to the end."""
        self._input_consts = None
        self.n_one_call_samples = 0
        k = self.attitude._kernels
        clock = self.imu_clock
        if (
            k is None
            or self._fused_ws is None
            or clock is None
            or not self.rig.imu_is_shank_aligned
        ):
            return
        pool = self._fused_ws
        c = pool[k.POOL_IN : k.POOL_IN + k.IN_SIZE]
        if not clock.compiled_constants(c, k) or not self.imu_faults.compiled_constants(c, k):
            return
        c[k.IN_TIME_CONSTANT] = self.attitude.time_constant_s
        c[k.IN_PITCH_TIME_CONSTANT] = self.attitude.pitch_time_constant_s
        # the small state arrays the kernel updates become views of its pool, their values
        # kept: one argument instead of five (the other paths update the same memory)
        mon, stance = self.imu_faults, self._stance
        clock._st = _pooled(pool, k.POOL_CLK, k.CLK_SIZE, clock._st)
        mon._prev_arr = _pooled(pool, k.POOL_FAULT, k.FAULT_PREV_SIZE, mon._prev_arr)
        stance._prev_arr = _pooled(pool, k.POOL_STANCE, k.STANCE_PREV_SIZE, stance._prev_arr)
        self.filter.adopt_memory(_pooled(pool, k.POOL_MEM, k.MEM_SIZE, self.filter._mem))
        self._input_consts = c
        self._input_kernel = k.imu_input
        self._input_outcomes = (k.IN_FAULT, k.IN_CLEAN)
        self._input_out = pool[k.POOL_OUT : k.POOL_OUT + 7]
        assert (k.OUT_GAP, k.OUT_PREV, k.OUT_PX, k.OUT_GYR_SAT) == (0, 1, 2, 6)

    def health_report(self) -> dict:
        """Is the estimate in trouble? Shares of refused displacements and of stance frames,
        departure of the fused path from visual odometry, the consistency of the filter's
        own innovations per measurement family (``innovations``), and warning lines naming
        the likely cause (vio_graph/health.py)."""
        rep = self.health.report(float(np.degrees(self.pitch_offset.offset_rad)))
        to = self.time_offset
        if to.contradicted():
            assert to.latched_at is not None  # contradicted() needs it
            t0, td0, sigma0 = to.latched_at
            rep["ok"] = False
            rep["warnings"].append(
                f"WARNING: the camera-IMU time offset was applied at {1e3 * td0:.1f} ms "
                f"(1-sigma {1e3 * sigma0:.1f} ms) from {t0:.2f} s, but the estimate is now "
                f"{1e3 * to.td_s:.1f} +- {1e3 * to.sigma_s:.1f} ms: frames fused in between "
                f"(and, early in a trial, the re-run ones) were re-stamped by a wrong offset, "
                f"which shifts the estimate by the speed times the error. Likely cause: "
                f"level-surface tilts noisier than their sigmas (time_offset."
                f"consistency_scale) at the start; check a run with "
                f"filter.time_offset.estimate false if the rig is synchronised."
            )
        bend = self.bend_test
        if bend is not None and bend.n_bent_frames:
            mean = bend.mean_rad()
            rep["warnings"].append(
                f"WARNING: the level surfaces looked bent on {bend.n_bent_frames} frames of "
                f"{self.health.n_frames} (treads and risers disagreed on the slice's tilt, "
                f"last weighted mean {math.degrees(mean or 0.0):+.1f} deg): a pitch error turns "
                f"both alike, so there their tilt was weighed against the IMU's own attitude "
                f"as a biased pitch measurement (shrunk by the disagreement) and kept from the "
                f"camera-IMU time offset. Likely cause: systematic depth "
                f"errors of the camera (multipath in the tread-riser corners, range "
                f"'wiggling', dark or shiny surfaces); metric maps and heights near the "
                f"corners are less certain too."
            )
        if not rep.get("innovations_consistent", True):
            stamp = self.stamp_test.report() if self.stamp_test is not None else None
            found = input_fault_context(self.imu_faults.report(), stamp)
            if found:
                rep["warnings"].append(
                    "WARNING: the inputs of this run had faults that make the IMU prediction, "
                    "and so the innovations above, less reliable than the noise settings say: "
                    + "; ".join(found)
                    + ". They may be the cause rather than the depth noise."
                )
        rep["stance"] = dict(self.stance_stats)
        fs = self.filter.state
        rep["landmarks"] = {"accepted": fs.n_landmark_accepted, "rejected": fs.n_landmark_rejected}
        return rep

    def _init_fault_handling(self) -> None:
        """IMU fault monitor, clock models and the time-offset estimator
        (filter/imu_faults.py, filter/time_offset.py)."""
        fc, rig = self.config.filter, self.rig
        to = fc.time_offset
        self.imu_faults = ImuFaultMonitor(
            fc.imu_faults, rig.accel_range_mps2, rig.gyro_range_radps, rig.imu_rate_hz
        )
        fi = fc.imu_faults
        self.saturation_learner = (
            SaturationScaleLearner(
                fi.saturation_sigma_range * rig.accel_range_mps2,
                fi.saturation_explained_fraction,
                fi.saturation_evidence_window_s,
                per_side=fi.saturation_learn_per_side,
            )
            if fi.enabled and fi.saturation_learn_scale and rig.accel_range_mps2
            else None
        )
        #: leg-chain velocity bridge across saturated accelerometer stretches, or None
        self.saturation_bridge = (
            LegChainBridge(
                rig.leg.thigh_length_m,
                rig.camera_in_shank_xz_m,
                fi.saturation_bridge_hip_accel_mps2,
                fi.saturation_bridge_rate_sigma_mps,
                discretisation_sigma=fi.saturation_bridge_discretisation_sigma,
                fourth_order=fi.saturation_bridge_fourth_order,
            )
            if fi.enabled and fi.saturation_bridge and rig.accel_range_mps2
            else None
        )
        self.n_bridge_fused = 0  # bridge observations the filter took (gate passed)
        #: the latest fused bridge observation not yet given to a keyframe: (velocity, cov,
        #: the filter's velocity and summed corrections just before it was fused), then the
        #: keyframe before the stretch (s) and the velocity change from it to the observation
        #: and its covariance, or None (no keyframe before the stretch), then the stretch's
        #: start and end (s; for the smoothers' discretisation term)
        self._bridge_carry: tuple | None = None
        #: with the bridge: the last keyframes (time s, the filter's time s, velocity and
        #: summed corrections then), and at a stretch's start the keyframe before it with the
        #: filter's IMU velocity change from it to the start, for the smoothers' change
        #: (smoother.factors.saturation_bridge_relative); the last clipped sample's time (s)
        self._bridge_kfs: deque[tuple[float, float, NDArray, NDArray]] = deque(maxlen=4)
        self._bridge_pre: tuple[float, NDArray] | None = None
        self._last_saturated_s = -math.inf
        per_axis = fi.keep_consistent_axes
        self.imu_repair = (
            NextSampleRepair(
                fi.interpolated_accel_sigma_mps2,
                fi.gyro_ahrs_sigma_radps if per_axis else None,
                fi.consistent_axis_probability if per_axis else None,
                fi.repaired_axis_distrust,
            )
            if fi.enabled and fi.repair_from_next_sample
            else None
        )
        #: a held packet carries its measurement for the per-axis repair (the filter's and
        #: the smoothers', ``smoother.held_keep_consistent_axes``)
        self.keep_measured_axes = fi.enabled and (
            per_axis or self.config.smoother.held_keep_consistent_axes
        )
        self.imu_clock = (
            ClockModel(1.0 / rig.imu_rate_hz, to.clock_window, to.gap_periods, to.imu_clock_model)
            if rig.imu_rate_hz
            else None
        )
        self.frame_clock = (
            ClockModel(
                1.0 / rig.frame_rate_hz,
                to.clock_window,
                to.gap_periods,
                to.camera_clock_model is not False,
                to.camera_clock_rate_prior_ppm,
            )
            if rig.frame_rate_hz
            else None
        )
        # 'auto': vision decides between the stamps and the clock line (FrameStampTest)
        self.stamp_test = (
            FrameStampTest(chi2_quantile(fc.gate_probability or 0.999, 2))
            if to.camera_clock_model == "auto" and self.frame_clock is not None
            else None
        )
        la = fc.level_aiding
        self.time_offset = TimeOffsetEstimator(
            to, np.radians(la.initial_sigma_deg), np.radians(la.drift_deg_per_sqrt_s)
        )
        self.n_imu_inconsistent = 0  # displacements vision kept against the IMU
        self._joint_hist: deque[JointAngles] = deque(maxlen=32)
        self._frame_joints: JointAngles | None = None  # joints at a re-stamped frame time
        self._frame_on_line = False  # this frame re-stamped to the camera clock line
        #: (``time_offset.frame_time_rotation_sigma``) per recent frame time (s): the
        #: covariance (m^2, 2x2) its time's uncertainty gives a displacement ending or starting
        #: there, and this frame's slice rotation variance (rad^2)
        self._time_terms: deque[tuple[float, NDArray[np.float64]]] = deque(maxlen=8)
        self._frame_rot_var_rad2 = 0.0
        self._imu_queue: deque[ImuSample] = deque()  # received, not yet propagated
        self._stance_queue: deque[ImuSample] = deque()  # received, not yet in the detector
        self._filter_started = False
        self._filter_start_s = -np.inf  # the filter's first time (s, IMU clock)
        self._last_frame_t: float | None = None  # previous frame time on the IMU clock
        #: frames stamped (camera clock, s) at or before this have already given their tilt
        #: to the time-offset estimator (set by the retroactive re-run, vio_graph/replay.py)
        self.td_counted_until_s = -np.inf

    def _learn_saturation(self, learner: SaturationScaleLearner, shank: ImuSample) -> None:
        """Feed the saturation learner one sample (clipped, or in the evidence window after
        a clipped stretch) and hand the monitor the scales it learnt."""
        mon = self.imu_faults
        prev = self._last_imu
        h = 0.0 if prev is None else shank.timestamp_s - prev.timestamp_s
        # IMU axes -> shank axes -> world x-z (the sagittal rotation of the shank's attitude)
        R_xz = _sagittal_rotation(shank.quat_wxyz) @ self.rig.R_shank_imu[[0, 2], :]
        # axes whose prior the tangent capped (imu_faults.saturation_tangent_cap) say nothing
        # about the learnt scale
        free = ~mon.last_capped
        if learner.add_sample(
            shank.timestamp_s,
            h,
            mon.last_rail_sign * free,
            mon.last_restored_mps2 * free,
            R_xz,
            float(np.trace(self.filter.cov_velocity_m2ps2())),
            self.filter.velocity_corrections_mps,
        ):
            mon.accel_scales_mps2 = learner.scales_mps2.copy()

    def fault_report(self) -> dict:
        """IMU faults, time offset and timestamp problems, for metrics.json."""
        rep: dict = {
            "imu_faults": {
                **self.imu_faults.report(),
                "vision_kept_against_imu": self.n_imu_inconsistent,
            },
            "time_offset": self.time_offset.report(),
            "timestamps": {},
        }
        learner = self.saturation_learner
        if learner is not None and (learner.n_evidence or learner.n_dropped):
            rep["imu_faults"]["saturation_scale_mps2"] = [
                round(float(v), 3) for v in learner.scales_mps2
            ]
            rep["imu_faults"]["saturation_stretches_measured"] = learner.n_evidence
            rep["imu_faults"]["saturation_stretches_unmeasured"] = learner.n_dropped
        bridge = self.saturation_bridge
        if bridge is not None and bridge.n_stretches:
            rep["imu_faults"]["saturation_bridge"] = {
                "stretches": bridge.n_stretches,
                "observations": bridge.n_observations,
                "fused": self.n_bridge_fused,
                "unbridged": bridge.n_unbridged,
            }
        for name, clock in (("imu", self.imu_clock), ("camera", self.frame_clock)):
            if clock is not None:
                rep["timestamps"][name] = clock.report()
        if self.stamp_test is not None and "camera" in rep["timestamps"]:
            rep["timestamps"]["camera"]["stamp_test"] = self.stamp_test.report()
        return rep

    # ------------------------------------------------------------------ inputs
    def add_imu(self, sample: ImuSample) -> ImuStep | None:
        """Propagate with one IMU sample (any mount); returns it as the other estimators take
        it: in shank axes, as measured and with the level-surface pitch offset applied. None
        if its stamp is at or before the previous one (dropped and reported in
        :meth:`fault_report`, never fused, not passed on)."""
        t0 = time.perf_counter()
        if (
            self._input_consts is not None
            and not sample.accel_held
            and self._filter_started
            and self.attitude._R is not None
            and not self._imu_queue
            and not self._stance_queue
            and self.time_offset.applied_s <= 0.0
            and (self.imu_repair is None or self.imu_repair.pending is None)
            and (self.saturation_bridge is None or not self.saturation_bridge.active)
        ):
            return self._add_imu_one_call(sample, t0)
        if self.imu_clock is not None:  # jitter smoothing and gap / backward-stamp report
            t_clock = self.imu_clock.correct(sample.timestamp_s)
            if t_clock is None:
                return None
            if t_clock != sample.timestamp_s:
                sample = _replaced(sample, t_clock, sample.quat_wxyz)
        measured = sample
        sample = self.imu_faults.process(sample)  # saturation marks, gyro repair (IMU axes)
        return self._add_checked(measured, sample, t0)

    def _add_imu_one_call(self, sample: ImuSample, t0: float) -> ImuStep | None:
        """:meth:`add_imu` with the IMU clock model, the fault check and, for a clean sample,
        :meth:`_advance_imu_fused`'s kernel in one compiled call (``compiled_imu.imu_input``;
        the caller checked the preconditions that do not depend on the sample's time).
        Whatever the kernel leaves undone (a fault to handle, a time the fused step does not
        take) continues on the general path from where it stopped, so the same bits as the
        separate calls."""
        att, filt, mon, ws = self.attitude, self.filter, self.imu_faults, self._fused_ws
        clock = self.imu_clock
        assert ws is not None and clock is not None and att._R is not None
        if att._R is not self._fused_att[0] or att._gyro_radps is not self._fused_att[1]:
            ws[self._fused_slots[0]] = att._R + att._gyro_radps  # the general path moved it
        acc, gyr = as_f64(sample.accel_mps2), as_f64(sample.gyro_radps)
        stamp = float(sample.timestamp_s)
        last = self._last_imu
        outcome, t, code, d2, moved, R = self._input_kernel(
            ws,  # with the clock's, the monitor's, the stance's and the filter's state
            clock._buf,
            clock.compiled_corrections(),
            filt._x,
            filt._P,
            acc,
            gyr,
            as_f64(sample.quat_wxyz),
            stamp,
            mon._acc_run,
            att._t_s,
            filt._t_s,
            self._filter_start_s,
            -math.inf if last is None else last.timestamp_s,
            self.pitch_offset.offset_rad,
            float(sample.accel_extra_sigma_mps2),
            self._fused_anchor,
        )
        out = self._input_out  # the kernel's outputs for the rare paths (OUT_* slots)
        if code:  # a gap, or a stamp at or before the previous one (dropped)
            clock.compiled_event(stamp, code, float(out[0]), float(out[1]))
            if code < 0:
                return None
        if t != sample.timestamp_s:
            sample = _replaced(sample, t, sample.quat_wxyz)
        fault, clean = self._input_outcomes
        if outcome == fault:
            px, py, pz, acc_sat, gyr_sat = out[2:7].tolist()
            checked = mon.finish_compiled(
                sample, acc, gyr, d2, px, py, pz, acc_sat != 0.0, gyr_sat != 0.0
            )
            return self._add_checked(sample, checked, t0)
        mon.clean_compiled(acc, d2)
        if outcome == clean:
            return self._add_checked(sample, sample, t0)
        # the fused step ran: what push() does with a sample that passes straight through
        if self.imu_repair is not None:
            self.imu_repair.passed(sample)
        q = self._fused_done(sample, t, R, moved, gyr, self._fused_anchor)
        self.n_one_call_samples += 1
        # the latest sample: only its time (and, trusted, its gyro) is read, which the
        # sample in shank axes shares with the corrected one (built when a consumer asks)
        self._last_imu = sample
        self._imu_ms += (time.perf_counter() - t0) * 1e3
        return ImuStep.with_quat(sample, q)

    def _add_checked(self, measured: ImuSample, sample: ImuSample, t0: float) -> ImuStep:
        """:meth:`add_imu` from the fault monitor's output ``sample`` (``measured``: its input,
        after the clock model) on: IMU axes to shank axes, the repair from the next sample,
        the filter and the stance detector."""
        if sample.accel_held and sample is not measured and self.keep_measured_axes:
            # a stand-in for a corrupt packet: keep what the packet said, so that the
            # repair from the next sample can keep its axes that agree with the neighbours
            sample = dataclasses.replace(
                sample,
                measured_accel_mps2=np.asarray(measured.accel_mps2, dtype=float),
                measured_gyro_radps=np.asarray(measured.gyro_radps, dtype=float),
            )
        shank = self.rig.imu_in_shank_axes(sample)  # any IMU mount -> shank axes
        if self._last_imu is not None and shank.timestamp_s <= self._last_imu.timestamp_s:
            raise EstimationError(
                f"IMU sample at {shank.timestamp_s:.6f} s is not after "
                f"{self._last_imu.timestamp_s:.6f} s"
            )
        # a repaired packet waits for the next sample (filter/imu_repair.py)
        ready = [shank] if self.imu_repair is None else self.imu_repair.push(shank)
        corrected = None
        for s in ready:
            c = self._advance_imu(s)
            if s is shank:
                corrected = c
        if corrected is None:  # held back: the attitude tracked up to the sample before it
            corrected = self._as_corrected(shank)
        self._last_imu = corrected
        self._imu_ms += (time.perf_counter() - t0) * 1e3
        return ImuStep(shank=shank, corrected=corrected)

    def _as_corrected(self, sample: ImuSample) -> ImuSample:
        """``sample`` (shank axes) with the attitude the strapdown uses at its time."""
        if self.config.filter.strapdown_attitude == "tracked":
            return self._with_tracked_attitude(sample)
        return self.corrected_imu(sample)  # the offset applied once, for the strapdown

    def _advance_imu(self, sample: ImuSample) -> ImuSample:
        """Feed one sample (shank axes) to the attitude tracker, the filter's queue and the
        stance detector; returns it as the filter propagates with it."""
        if self._fused_ws is not None:
            corrected = self._advance_imu_fused(sample)
            if corrected is not None:
                return corrected
        shank = sample  # shank axes, before the strapdown's attitude (the saturation learner)
        self.attitude.add(sample)  # vendor orientation; R_world_imu applies the pitch offset
        self._last_taken_s = sample.timestamp_s
        sample = self._as_corrected(sample)
        self._imu_queue.append(sample)
        # camera stamps late by td > 0: the filter stays td behind the IMU stream, so that a
        # re-stamped frame finds it at (not past) its capture time
        t_filter = sample.timestamp_s - max(self.time_offset.applied_s, 0.0)
        self._propagate_until(t_filter)
        learner = self.saturation_learner
        # any() of the list: ndarray.any() costs a few microseconds a sample
        if learner is not None and (learner.active or any(self.imu_faults.last_rail_sign.tolist())):
            self._learn_saturation(learner, shank)
        # the stance detector and the stance's pitch rate follow the filter, not the IMU
        # stream: with late camera stamps a frame's quiet window and gyro would otherwise end
        # td after its capture time
        self._stance_queue.append(sample)
        self._advance_stance_until(t_filter)
        return sample

    def _advance_imu_fused(self, sample: ImuSample) -> ImuSample | None:
        """:meth:`_advance_imu` in one compiled call (``compiled_imu.sample_step``) when the
        sample is propagated and handed to the stance detector at once: the tracker has an
        attitude, no sample is queued, no camera-IMU offset holds the filter back and the
        filter has started. Returns None (nothing changed) otherwise; the caller then takes
        the general path. The same kernels in the same order, so the same bits."""
        att, filt, ws = self.attitude, self.filter, self._fused_ws
        assert ws is not None
        t = sample.timestamp_s
        dt = t - att._t_s
        if (
            att._R is None
            or dt < 0.0
            or self._imu_queue
            or self._stance_queue
            or self.time_offset.applied_s > 0.0
            or not self._filter_started
            or t < self._filter_start_s - 1e-9
        ):
            return None
        dt_filter = t - filt._t_s
        if dt_filter < -1e-9 or not math.isfinite(t):
            return None  # propagate() raises there: the general path says so
        bridge = self.saturation_bridge
        if bridge is not None and (bridge.active or _saturated(sample)):
            return None  # the general path, which feeds the bridge (same kernels, same bits)
        if sample.accel_extra_cov_m2ps4 is not None or filt._prev_xc is not None:
            return None  # the general path adds the clipped axes' variance (ESKF.propagate)
        att_slots = self._fused_slots[0]
        if att._R is not self._fused_att[0] or att._gyro_radps is not self._fused_att[1]:
            ws[att_slots] = att._R + att._gyro_radps  # the general path moved the tracker
        gyr = as_f64(sample.gyro_radps)
        stance = self._fused_anchor and not sample.accel_held
        R, moved = self._fused_step(
            ws,
            filt._x,
            filt._P,
            filt._mem,
            self._stance._prev_arr,
            as_f64(sample.accel_mps2),
            gyr,
            as_f64(sample.quat_wxyz),
            t,
            dt,
            min(1.0, dt / att.time_constant_s),
            min(1.0, dt / att.pitch_time_constant_s),
            self.pitch_offset.offset_rad,
            dt_filter,
            float(sample.accel_extra_sigma_mps2),
            stance,
        )
        return _replaced(sample, t, self._fused_done(sample, t, R, moved, gyr, stance))

    def _fused_done(
        self,
        sample: ImuSample,
        t: float,
        R: Mat3,
        moved: int,
        gyr: NDArray[np.float64],
        stance: bool,
    ) -> NDArray[np.float64]:
        """The bookkeeping after ``compiled_imu.sample_step`` ran on ``sample`` (shank axes)
        at ``t`` and returned the tracker's new ``R`` and the propagation's code ``moved``
        (``stance``: it fed the stance detector); returns the orientation the sample was
        propagated with (its corrected quaternion, a new array)."""
        att, ws = self.attitude, self._fused_ws
        assert ws is not None
        _, q_slots, mag_slot = self._fused_slots
        g = tuple(gyr.tolist())
        att._R, att._t_s, att._gyro_radps = R, t, g
        att.vendor_quat_wxyz = sample.quat_wxyz
        att._recent.append((t, R, g))
        self._fused_att = (R, g)
        self._last_taken_s = t
        q = ws[q_slots].copy()
        self.filter.propagated_compiled(t, moved)
        learner = self.saturation_learner
        if learner is not None and (learner.active or any(self.imu_faults.last_rail_sign.tolist())):
            self._learn_saturation(learner, sample)
        if stance:
            self._stance.record(t, float(ws[mag_slot]))
        if not sample.accel_held:
            self._last_trusted_imu = sample  # its gyro is read (the corrected one's too)
        self.n_fused_samples += 1
        return q

    def add_joints(self, sample: JointAngles) -> None:
        self._last_joints = sample
        self._joint_hist.append(sample)

    def add_contact(self, sample: ContactSample) -> None:
        """Foot contact from a sensor (load cell, heel switch). With
        ``filter.stance_contact`` propose or confirm, once any sample has arrived the latest
        one proposes the stance instead of the acceleration detector (propose) or with it
        (confirm); vision still tests it (StanceConsistencyTest) and the anchor gate still
        applies. With off (the default) it is kept and not used."""
        self._last_contact = sample

    @property
    def in_stance(self) -> bool:
        """True if the latest frame was anchored in stance (detector and vision agreed)."""
        return self._in_stance

    @property
    def initialised(self) -> bool:
        return self._last_imu is not None

    @property
    def last_imu_time_s(self) -> float | None:
        """Stamp (s, IMU clock) of the latest IMU sample the filter has taken (None before
        the first). A repaired packet held back for the next sample (filter/imu_repair.py) is
        not taken yet: a frame captured after it waits for the next sample, so the filter
        never extrapolates across the packet (its state there becomes the interpolation's)."""
        if self.imu_repair is not None and self.imu_repair.pending is not None:
            return self._last_taken_s
        return None if self._last_imu is None else self._last_imu.timestamp_s

    @property
    def imu_held_back_s(self) -> float | None:
        """Stamp (s, IMU clock) of a repaired packet held back for the next sample
        (filter/imu_repair.py), None if there is none: a frame captured after it should wait
        for the next sample (:class:`vio_graph.replay.Replay` does)."""
        pending = None if self.imu_repair is None else self.imu_repair.pending
        return None if pending is None else pending.timestamp_s

    def corrected_imu(self, sample: ImuSample) -> ImuSample:
        """``sample`` with its vendor orientation turned by the level-surface pitch offset
        (FilterConfig.level_aiding); the sample itself when the offset is not set yet."""
        b = self.pitch_offset.offset_rad
        if not self.pitch_offset.initialised or b == 0.0:
            return sample
        return dataclasses.replace(sample, quat_wxyz=_pitch_offset_quat(sample.quat_wxyz, b))

    def _with_tracked_attitude(self, sample: ImuSample) -> ImuSample:
        """``sample`` carrying the tracked attitude at its time (filter/attitude.py, heading
        removed, level-surface pitch offset applied) instead of the vendor orientation."""
        att = self.attitude
        k = att._kernels
        t = sample.timestamp_s
        if k is not None and att.config.source != "vendor" and t >= att._t_s:
            # compiled: the tracker's latest attitude extrapolated to t (0 s here), heading
            # removed, level-surface offset applied, as a quaternion
            R = att._R
            assert R is not None
            b = self.pitch_offset.offset_rad
            q = np.array(k.tracked_quat(R, att._gyro_radps, t - att._t_s, b))
        else:
            q = mat3_quat(self._level_aided_attitude_mat3(t))
        return _replaced(sample, t, q)

    def _with_tracked_attitude_reference(self, sample: ImuSample) -> ImuSample:
        """numpy reference of :meth:`_with_tracked_attitude` (the tests compare the two)."""
        R = remove_yaw(self.attitude.R_world_imu_at(sample.timestamp_s))
        b = self.pitch_offset.offset_rad
        R = rot_y(b) @ R if b != 0.0 else R
        return dataclasses.replace(sample, quat_wxyz=quat_wxyz_from_matrix(R))

    def _level_aided_attitude_mat3(self, t_s: float) -> Mat3:
        """Row-major tracked attitude at ``t_s``, heading removed, level-surface offset
        applied (scalar closed forms)."""
        G = remove_yaw_mat3(self.attitude.R_world_imu_at_mat3(t_s))
        b = self.pitch_offset.offset_rad
        return mat3_mul(rot_y_mat3(b), G) if b != 0.0 else G

    def _level_aided_attitude(self, t_s: float) -> NDArray[np.float64]:
        """(3, 3) tracked attitude at ``t_s``, heading removed, level-surface offset applied."""
        return np.array(self._level_aided_attitude_mat3(t_s)).reshape(3, 3)

    def R_world_imu(self, t_s: float | None = None) -> NDArray[np.float64]:
        """Attitude at ``t_s`` (default: the latest IMU sample) with the heading removed (the
        paper's ground frame); ``config.filter.attitude`` says how (filter/attitude.py)."""
        if self._last_imu is None:
            raise EstimationError("no IMU sample yet")
        t = self._last_imu.timestamp_s if t_s is None else t_s
        # a frame asks for the same attitude up to four times: remembered while the time, the
        # pitch offset and the latest IMU sample (the attitude tracker's input) are the same
        b, last, memo = self.pitch_offset.offset_rad, self._last_imu, self._attitude_memo
        if memo is None or memo[0] != t or memo[1] != b or memo[2] is not last:
            memo = self._attitude_memo = (t, b, last, self._level_aided_attitude_mat3(t))
        return np.array(memo[3]).reshape(3, 3)

    def R_world_imu_reference(self, t_s: float | None = None) -> NDArray[np.float64]:
        """numpy reference of :meth:`R_world_imu` (the tests compare the two)."""
        if self._last_imu is None:
            raise EstimationError("no IMU sample yet")
        t = self._last_imu.timestamp_s if t_s is None else t_s
        R = remove_yaw(self.attitude.R_world_imu_at(t))
        b = self.pitch_offset.offset_rad
        return rot_y(b) @ R if b != 0.0 else R

    def _position_at(self, t_s: float) -> tuple[NDArray[np.float64], NDArray[np.float64]]:
        """Filter camera position (m) and velocity extrapolated to ``t_s`` (few ms at most)."""
        t, p, v = self.filter.position_velocity()
        return p + v * (t_s - t), v

    # ------------------------------------------------------------------ per frame
    def add_frame(
        self,
        frame: DepthFrame,
        R_ground_cam_override: NDArray[np.float64] | None = None,
        transform_result=None,
    ) -> tuple[FrameEstimate, FrontendResult]:
        """Process one depth frame (after every IMU / joint sample stamped at or before it);
        returns the estimate and the front end's result (see :meth:`process_frame`)."""
        record = self.process_frame(frame, R_ground_cam_override, transform_result)
        return record.estimate, record.frontend

    def process_frame(
        self,
        frame: DepthFrame,
        R_ground_cam_override: NDArray[np.float64] | None = None,
        transform_result=None,
    ) -> FrameRecord:
        """Process one depth frame (after every IMU / joint sample stamped at or before it);
        returns the frame's record for the other estimators (vio_graph/protocol.py).

        ``R_ground_cam_override`` (3, 3) replaces the IMU attitude of eq. 2 (diagnostics only,
        e.g. ``benchmarks/eval_frontend.py --attitude gt``). ``transform_result`` (testing
        hook) may replace the front end's result before fusion, e.g. to inject wrong
        associations (``PipelineConfig.inject``).
        """
        if not self.initialised:
            raise EstimationError("a depth frame arrived before any IMU sample")
        stamp = frame.timestamp_s  # as recorded (camera clock)
        frame = self._restamp(frame)
        t = frame.timestamp_s
        self._propagate_until(t)
        self._advance_stance_until(t)
        if self.config.filter.start_at_first_frame:
            self._start_filter_at(t)
        if not self._filter_started:
            raise EstimationError("a depth frame arrived before any IMU sample")
        timings: dict[str, float] = {"imu_propagation": self._imu_ms}
        self._imu_ms = 0.0
        # 1. attitude at the frame time -> ground frame of eq. 2
        R_world_imu = self.R_world_imu(t)
        R_ground_cam = R_world_imu @ self.rig.R_imu_cam
        if R_ground_cam_override is not None:
            R_ground_cam = np.asarray(R_ground_cam_override, dtype=float)
        # 2. IMU-predicted camera displacement since the previous frame (ICP's T_0)
        p_pred, _ = self._position_at(t)
        pred_delta = pred_cov = None
        if self._prev_frame is not None:
            t_prev, p_prev = self._prev_frame
            dt = t - t_prev
            pred_delta = p_pred - p_prev
            pred_cov = self.filter.cov_velocity_m2ps2() * dt**2 + _I2 * (0.5 * 2.0 * dt**2) ** 2
        # 3. front end (eq. 1-4)
        stand_rel = None
        if self._stand_z_m is not None and self.config.frontend.terrain.stand_level:
            stand_rel = self._stand_z_m - float(p_pred[1])
        result = self.frontend.process(
            frame,
            self.rig.K,
            R_ground_cam,
            pred_delta,
            pred_cov,
            self._ground_turn_rad,
            stand_rel,
        )
        self._ground_turn_rad = 0.0
        timings.update({f"frontend_{k}": v for k, v in result.timings_ms.items()})
        self._frame_time_terms(t, result.profile_xz_m)
        # 4. fusion: level surfaces -> pitch of the attitude (used from here on), then eq. 8
        t0 = time.perf_counter()
        self.surface_tilt = None
        if self.config.filter.level_aiding.enabled and R_ground_cam_override is None:
            step = self._level_aiding(t, result.profile_xz_m)
            if stamp > self.td_counted_until_s:
                self._update_time_offset(t, step)
            if step != 0.0:
                self._ground_turn_rad = step  # this frame, seen from the next one
                R_world_imu = self.R_world_imu(t)
        if transform_result is not None:
            result = transform_result(result)
        accepted = refused = False
        prev_visual = self._prev_visual
        if result.displacement is not None:
            self._prev_visual = result.displacement
        if result.displacement is not None:
            d2, fused = self._test_frame_stamps(t, self._with_time_terms(result.displacement))
            n_refused = self.filter.n_gate_refusals
            if result.relocalised and self._widen_for_relocalised(t, fused, d2, prev_visual):
                d2 = None  # the state's covariance changed
            self._arbitrate_imu(fused, d2)
            accepted = self._as_family(t, "displacement", self.filter.update_displacement, fused)
            refused = self.filter.n_gate_refusals > n_refused
            if accepted:
                self._last_fix_t = t
            if result.relocalised:
                self._count_relocalised(t, accepted)
            self._recover_if_locked_out(refused, t)
        else:
            self.filter.clone_position(t)
            if _PREDICTION_REFUSAL in (result.rejection_reason or ""):
                # the front end's gate on the same IMU prediction refused ICP: for the
                # lock-out it counts like a refusal of the filter's gate
                self._recover_if_locked_out(True, t)
        self._fuse_landmarks(t, result, R_world_imu)
        camera_xz, velocity = self._position_at(t)
        if self.stamp_test is not None:
            self.stamp_test.end_frame(velocity)
        corner_seen = result.observation is not None and self.config.filter.corner_landmarks
        self.health.add_frame(
            t,
            camera_xz,
            result.displacement,
            accepted,
            self._in_stance,
            corner_seen,
            refused=refused,
            velocity_sigma_x_mps=math.sqrt(max(self.filter.variance(2), 0.0)),
            distrusted_imu_samples=self.imu_faults.n_distrusted,
            camera_fixed_pixels=result.n_camera_fixed,
        )
        timings["fusion"] = (time.perf_counter() - t0) * 1e3
        # 5. kinematics (Fig. 3)
        t0 = time.perf_counter()
        pts = self.leg_points(camera_xz, R_world_imu)
        self._note_stand_surface(pts)
        timings["kinematics"] = (time.perf_counter() - t0) * 1e3
        # 6. keyframes
        anchored = None if self._stance_observation is None else self._stance_episode
        is_kf = self.keyframes.is_keyframe(t, camera_xz, anchored)
        self._prev_frame = (t, camera_xz)
        bridge_velocity = None
        disc_cov, wait = None, False
        if is_kf and self._bridge_carry is not None:
            disc_cov, wait = self._bridge_discretisation()
        if is_kf and self._bridge_carry is not None and not wait:
            # the bridge's velocity carried to this frame by the IMU alone: the filter's
            # velocity change since minus what its measurements corrected
            v_obs, cov_obs, v_before, corr_before, pre, _ = self._bridge_carry
            imu_change = velocity - v_before - (self.filter.velocity_corrections_mps - corr_before)
            if pre is None:
                bridge_velocity = VelocityObservation(
                    t, v_obs + imu_change, cov_obs, discretisation_cov=disc_cov
                )
            else:  # also as the change from the keyframe before the stretch
                t_kf, change, change_cov = pre
                bridge_velocity = VelocityObservation(
                    t,
                    v_obs + imu_change,
                    cov_obs,
                    t_kf,
                    change + imu_change,
                    change_cov,
                    discretisation_cov=disc_cov,
                )
            self._bridge_carry = None
        if is_kf and self.saturation_bridge is not None:
            self._bridge_kfs.append(
                (t, self.filter._t_s, velocity, self.filter.velocity_corrections_mps.copy())
            )
        # 7. safety outputs: the foot against the terrain seen so far (safety/online.py)
        safety = None
        if self.safety is not None:
            t0 = time.perf_counter()
            safety = self.safety.update(
                t,
                camera_xz,
                self.filter.cov_position_m2(),
                pts.heel_xz_m[0],
                pts.toe_xz_m[0],
                self._in_stance,
                result.profile_xz_m if is_kf else None,
            )
            timings["safety"] = (time.perf_counter() - t0) * 1e3
        status = self.filter.status
        if result.displacement is None and status is EstimateStatus.FUSED:
            status = EstimateStatus.IMU_ONLY
        estimate = FrameEstimate(
            timestamp_s=t,
            status=status,
            camera_xz_m=camera_xz,
            velocity_xz_mps=velocity,
            cov_position_m2=self.filter.cov_position_m2(),
            knee_xz_m=pts.knee_xz_m[0],
            ankle_xz_m=pts.ankle_xz_m[0],
            heel_xz_m=pts.heel_xz_m[0],
            toe_xz_m=pts.toe_xz_m[0],
            terrain=result.terrain,
            is_keyframe=is_kf,
            timings_ms=timings,
            safety=safety,
            cov_velocity_m2ps2=self.filter.cov_velocity_m2ps2(),
        )
        # the attitude the displacement and observations were built with (level-aided)
        R_world_imu = self.R_world_imu(t)
        imu_pitch, chain_pitch, ankle = self.leg_angles(R_world_imu)
        return FrameRecord(
            estimate=estimate,
            frontend=result,
            displacement=result.displacement,
            corner=self._corner_observation,
            stance=self._stance_observation,
            levels=self._level_observations,
            R_world_imu=R_world_imu,
            shank_pitch_imu_rad=imu_pitch,
            shank_pitch_chain_rad=chain_pitch,
            ankle_rad=ankle,
            in_stance=self._in_stance,
            velocity=bridge_velocity,
            imu_distrust=self._take_imu_distrust(),
        )

    def _note_stand_surface(self, pts) -> None:
        """Height of the surface under the foot while it stands: the lower of heel and toe
        (at heel strike and heel-off only one of them touches), median over the stance so
        far; kept after the stance ends until the next one."""
        if not self._in_stance:
            self._stance_sole_z_m.clear()
            return
        z = min(float(pts.heel_xz_m[0][1]), float(pts.toe_xz_m[0][1]))
        self._stance_sole_z_m.append(z)
        if math.isnan(z) or self._stand_z_m is None or math.isnan(self._stand_z_m):
            self._stand_z_m = float(np.median(self._stance_sole_z_m))
        else:  # finite values: np.median's middle value(s) without its ~15 us of dispatch
            self._stand_z_m = _median_finite(self._stance_sole_z_m)

    def _advance_stance_until(self, t_s: float) -> None:
        """Feed the stance detector the queued IMU samples stamped at or before ``t_s`` and
        keep the latest trusted one (its gyro gives the stance's pitch rate)."""
        q = self._stance_queue
        anchor = self.config.filter.stance_anchor
        while q and q[0].timestamp_s <= t_s + 1e-9:
            sample = q.popleft()
            if anchor:
                if self._stance.compiled:  # the sagittal rotation inside, compiled
                    self._stance.add_imu_quat(
                        sample.timestamp_s,
                        sample.accel_mps2,
                        sample.gyro_radps,
                        sample.quat_wxyz,
                        self.config.filter.gravity_xz_mps2,
                        trusted=not sample.accel_held,
                    )
                else:
                    self._stance.add_imu(
                        sample.timestamp_s,
                        sample.accel_mps2,
                        sample.gyro_radps,
                        _sagittal_rotation(sample.quat_wxyz),
                        self.config.filter.gravity_xz_mps2,
                        trusted=not sample.accel_held,
                    )
            if not sample.accel_held:
                self._last_trusted_imu = sample

    def _propagate_until(self, t_s: float) -> None:
        """Propagate the filter with the queued IMU samples stamped at or before ``t_s``."""
        q = self._imu_queue
        at_frame = self.config.filter.start_at_first_frame
        while q and q[0].timestamp_s <= t_s + 1e-9:
            s = q.popleft()
            if self._filter_started:
                # a sample whose clock-line time is before the first frame although its raw
                # stamp came after it (stamp jitter with a re-stamped frame) is a sample
                # before the start: it only feeds the attitude, as the others before it
                if s.timestamp_s >= self._filter_start_s - 1e-9:
                    bridge = self.saturation_bridge
                    if bridge is None:
                        self.filter.propagate(s)
                    else:
                        self._propagate_bridged(bridge, s)
            elif not at_frame:
                self.filter.initialise(s.timestamp_s, self._p0)
                self._filter_started = True
            # else: before the first frame the samples only feed the attitude and detectors

    def _propagate_bridged(self, bridge: LegChainBridge, s: ImuSample) -> None:
        """:meth:`SagittalEskf.propagate` with the leg-chain bridge fed: a saturated sample
        opens a stretch (the filter's velocity before it), the first trusted one after it
        closes it, and once the joints cover its end the chain's observation of the
        velocity is fused, gated (filter/leg_bridge.py). Nothing is done on a clean stream
        beyond the test of the sample's mark."""
        filt = self.filter
        fi = self.config.filter.imu_faults
        saturated = _saturated(s)
        if saturated:
            t, _, v = filt.position_velocity()
            if not bridge.opened:
                if fi.saturation_bridge_relative:
                    filt.clone_velocity()  # the start of the change the chain will observe
                self._bridge_pre = self._change_since_keyframe(t, v)
            self._last_saturated_s = s.timestamp_s
            bridge.before_saturated(t, v, filt.cov_velocity_m2ps2())
            self._bridge_carry = None  # its IMU-only carry would cross this stretch
        filt.propagate(s)
        if saturated or not bridge.active:
            return
        t, _, v = filt.position_velocity()
        bridge.after_trusted(t, v, filt.velocity_corrections_mps)
        obs = bridge.observation(self._joint_hist, v, filt.velocity_corrections_mps)
        if obs is not None:
            before = (v, filt.velocity_corrections_mps.copy())
            if fi.saturation_bridge_relative and filt.has_velocity_clone:
                fused = self._as_family(
                    t,
                    "bridge",
                    filt.update_velocity_change,
                    obs.change_xz_mps,
                    obs.change_cov,
                    fi.saturation_bridge_gate,
                )
            else:
                fused = self._as_family(
                    t,
                    "bridge",
                    filt.update_velocity,
                    obs.velocity_xz_mps,
                    obs.cov,
                    obs.timestamp_s,
                    fi.saturation_bridge_gate,
                )
            if fused:
                self.n_bridge_fused += 1
                # for the smoothers, at the next keyframe (process_frame)
                pre = self._bridge_pre
                self._bridge_carry = (
                    obs.velocity_xz_mps,
                    obs.cov,
                    *before,
                    None if pre is None else (pre[0], pre[1] + obs.change_xz_mps, obs.change_cov),
                    obs.stretch_s,
                )
        if not bridge.active:
            filt.drop_velocity_clone()  # observed, or given up (no joints in time)

    def _bridge_discretisation(self) -> tuple[NDArray | None, bool]:
        """For a keyframe that would carry the fused bridge to the smoothers:
        the chain's discretisation covariance at the stretch's ends
        (``LegChainBridge.discretisation_cov``) and whether to wait for a later keyframe
        because the joints do not cover the ends yet (at most the bridge's wait, 0.1 s,
        after the stretch's end). (None, False) with
        ``smoother.factors.saturation_bridge_discretisation`` off: the smoothers' bridge as
        before."""
        bridge, carry = self.saturation_bridge, self._bridge_carry
        if (
            bridge is None
            or carry is None
            or carry[5] is None
            or not self.config.smoother.factors.saturation_bridge_discretisation
        ):
            return None, False
        t0, t2 = carry[5]
        cov = bridge.discretisation_cov(self._joint_hist, t0, t2)
        if cov is None and self.filter._t_s - t2 <= bridge.max_wait_s:
            return None, True
        return cov, False

    def _change_since_keyframe(self, t_s: float, v: NDArray) -> tuple[float, NDArray] | None:
        """At a stretch's start (the filter's time ``t_s`` before its first clipped sample,
        its velocity ``v``): the last keyframe at or before ``t_s`` and the filter's IMU
        velocity change from it to ``t_s`` (its velocity change minus its corrections), or
        None. A keyframe inside the clipped sample's interval is skipped (the change from it
        is not measured), and so is one with a clipped sample since: that stretch's loss is
        not in the IMU's change, and its bridge was a correction."""
        corr = self.filter.velocity_corrections_mps
        for t_k, tf_k, v_k, c_k in reversed(self._bridge_kfs):
            if t_k <= t_s + 1e-9:
                if self._last_saturated_s > tf_k + 1e-9:
                    return None
                return t_k, v - v_k - (corr - c_k)
        return None

    def _start_filter_at(self, t_s: float) -> None:
        """Start the filter at the first frame's time (``filter.start_at_first_frame``): the
        trajectory's origin is that frame, and its clone carries no velocity uncertainty."""
        if not self._filter_started:
            self.filter.initialise(t_s, self._p0)
            self._filter_started = True
            self._filter_start_s = t_s

    def _restamp(self, frame: DepthFrame) -> DepthFrame:
        """The frame on the IMU clock: stamp minus the applied camera-IMU offset (and the
        camera clock model, if on); the joints are taken at that time."""
        self._frame_joints = None
        t = frame.timestamp_s
        self._frame_on_line = False
        if self.frame_clock is not None:
            t_clock = self.frame_clock.correct(t)
            if self.stamp_test is not None:
                self.stamp_test.note_frame(None if t_clock is None else t_clock - t)
                if self.stamp_test.use_line and t_clock is not None:
                    t = t_clock
                    self._frame_on_line = True
            elif t_clock is not None:
                t = t_clock
                self._frame_on_line = self.frame_clock.smooth
        t = t - self.time_offset.applied_s
        if self._last_frame_t is not None:
            # the applied offset jumps once (0 -> td when it becomes significant): keep the
            # frames in order, at least half a frame period apart
            period = 1.0 / self.rig.frame_rate_hz if self.rig.frame_rate_hz else 2e-3
            t = max(t, self._last_frame_t + 0.5 * period)
        self._last_frame_t = t
        if t == frame.timestamp_s:
            return frame
        self._frame_joints = self._joints_at(t)
        return dataclasses.replace(frame, timestamp_s=t)

    def _landmark_time_cov(self, t_s: float) -> NDArray[np.float64] | None:
        """The covariance (m^2, 2x2) a landmark measured on this frame gains from the
        uncertainty of the frame's time (``time_offset.landmark_time_sigma``): v v^T
        sigma_t^2 with v the filter's camera velocity at ``t_s`` and sigma_t^2 the frame
        stamps' mean square distance to their clock line, in full when the frame is on the
        line (what the line cannot remove, a capture jitter, is bounded by that scatter), times
        the frame-stamp test's probability of the line when it is on its stamp. None when
        off or the stamps are on their line.

        Why: on prosthesis upstair seed 3 under 2 ms of clock jitter, two level surfaces
        were first seen at 1.52 s in the first fast swing (vz 2.8 m/s) on a frame whose line
        time was 2.2 ms after its capture: their heights started 6 mm off, and every later
        sighting pulled the camera's height towards them (filter toe z 0.20 -> 1.09 cm)."""
        if not self.config.filter.time_offset.landmark_time_sigma:
            return None
        var = self._frame_time_var_s2()
        if var <= 0.0:
            return None
        v = self._position_at(t_s)[1]
        return np.outer(v, v) * var

    def _frame_time_var_s2(self) -> float:
        """Variance (s^2) of this frame's time: the frame stamps' mean square distance to
        their clock line, in full when the frame is on the line, times the frame-stamp test's
        probability of the line when it is on its stamp; 0 without a frame clock model."""
        if self.frame_clock is None:
            return 0.0
        var = self.frame_clock.scatter_var_s2()
        if not self._frame_on_line:
            test = self.stamp_test
            if test is None:
                return 0.0
            var *= test.other_probability(False)
        return max(var, 0.0)

    def _frame_time_terms(self, t_s: float, profile_xz_m: NDArray[np.float64]) -> None:
        """(``time_offset.frame_time_rotation_sigma``) What this frame's time uncertainty
        sigma_t does to what it measures: its attitude, taken at its time, turns the slice by
        omega e for a time error e (omega the latest gyro rate, rad/s), a point at p from the
        camera moving by about omega e perp(p). Keeps the rotation variance
        omega^2 sigma_t^2 (rad^2) for this frame's tilt, level and corner measurements, and
        the covariance (m^2) a displacement gets from this end: omega^2 sigma_t^2 perp(c)
        perp(c)^T at the profile's centroid c. The position's own term v v^T sigma_t^2 is
        left out: on jittered obstacle trials it made the filter worse
        (``landmark_time_sigma`` adds it to the landmarks). sigma_t^2 as there
        (:meth:`_frame_time_var_s2`): the stamps' scatter about their clock line, weighted by
        the frame-stamp test's probability of the line on frames kept at their stamps."""
        self._frame_rot_var_rad2 = 0.0
        if not self.config.filter.time_offset.frame_time_rotation_sigma:
            return
        var = self._frame_time_var_s2()
        if var <= 0.0 or self._last_imu is None:
            return  # no term: a displacement from or to this frame gains nothing
        w = np.asarray(self._last_imu.gyro_radps, dtype=float)
        rot_var = float(w @ w) * var
        self._frame_rot_var_rad2 = rot_var
        if len(profile_xz_m):
            centroid = np.mean(np.asarray(profile_xz_m, dtype=float), axis=0)
            self._time_terms.append((t_s, _turn_cov_m2(centroid, rot_var)))

    def _with_time_terms(self, d: Displacement2D) -> Displacement2D:
        """The displacement with its two frames' time terms (:meth:`_frame_time_terms`)
        added to its covariance; unchanged when off or when neither frame has them."""
        if not self.config.filter.time_offset.frame_time_rotation_sigma:
            return d
        add = np.zeros((2, 2))
        for t, cov in self._time_terms:
            if t == d.t0_s or t == d.t1_s:
                add = add + cov
        if not add.any():
            return d
        return dataclasses.replace(d, cov_m2=np.asarray(d.cov_m2, dtype=float) + add)

    def _test_frame_stamps(
        self, t_s: float, d: Displacement2D
    ) -> tuple[float | None, Displacement2D]:
        """Feed the frame-stamp test (``camera_clock_model: auto``): the displacement's gate
        statistic under the frame times in use and under the other choice, whose IMU
        prediction differs by u (time_offset.FrameStampTest). Returns the first (None if not
        computed; the filter is unchanged, so :meth:`_arbitrate_imu` need not recompute it)
        and the displacement to fuse: with ``stamp_ambiguity_cov`` its covariance holds the
        other choice's shift with the test's posterior probability of it
        (``FrameStampTest.ambiguity_cov``; the gate statistic is then None)."""
        test = self.stamp_test
        if test is None:
            return None, d
        u = test.shift(self.filter.position_velocity()[2])  # the velocity _position_at gives
        if u is None:
            return None, d
        # r_line = r_stamp - u: the other hypothesis moves the measurement by -u (or +u)
        moved = np.asarray(d.delta_xz_m, dtype=float) + (u if test.use_line else -u)
        pair = self.filter.displacement_d2_pair(d, moved)  # one H, V for both hypotheses
        if pair is None:
            return None, d
        line_in_use = test.use_line  # this frame's times (the test may switch on it)
        test.add(*pair)
        if not self.config.filter.time_offset.stamp_ambiguity_cov:
            return pair[0], d
        wider = dataclasses.replace(d, cov_m2=d.cov_m2 + test.ambiguity_cov(u, line_in_use))
        return None, wider

    def _joints_at(self, t_s: float) -> JointAngles | None:
        """Joint angles interpolated at ``t_s`` from the recent samples (held beyond them)."""
        hist = self._joint_hist
        if not hist:
            return None
        ts = np.array([j.timestamp_s for j in hist])
        vals = [
            np.interp(t_s, ts, [getattr(j, f) for j in hist])
            for f in ("thigh_pitch_rad", "knee_rad", "ankle_rad")
        ]
        return JointAngles(t_s, float(vals[0]), float(vals[1]), float(vals[2]))

    def _test_frame_tilt(self, t: float, tilt_rad: float, sigma_rad: float) -> None:
        """(``time_offset.stamp_test_tilts``) Feed this frame's level-surface tilt to the
        frame-stamp test (FrameStampTest.add_tilt), before the pitch offset fuses it. The
        slice was rotated with the current pitch offset and re-stamped by the applied
        camera-IMU offset, so under the frame time in use the tilt is expected at
        -omega (td - td_applied) (omega the shank pitch rate, td the offset's estimate), with
        the variance of the pitch offset, of the tilt (with the level aiding's floor) and
        omega^2 that of td. The time-offset filter's own pitch state is not used: the final
        pass of a replay holds it at the end of the recording."""
        test = self.stamp_test
        if test is None or not self.config.filter.time_offset.stamp_test_tilts:
            return
        to = self.time_offset
        rate = self._pitch_rate_at(t)
        floor = math.radians(self.config.filter.level_aiding.measurement_floor_deg)
        y = tilt_rad + rate * (to.td_s - to.applied_s)
        s = self.pitch_offset.var_rad2 + sigma_rad**2 + floor**2 + rate**2 * to.sigma_s**2
        test.add_tilt(y, s, rate, self.config.filter.level_aiding.gate_sigmas**2)

    def _pitch_rate_at(self, t: float) -> float:
        """The shank's pitch rate at time t (s): the attitude tracker's gyro at t in world axes,
        about y (rad/s); :meth:`_pitch_rate_radps` is the latest trusted sample's."""
        return float((self.R_world_imu(t) @ self.attitude.gyro_at(t))[1])

    def _update_time_offset(self, t: float, step_rad: float) -> None:
        """Feed this frame's level-surface tilt to the time-offset estimator
        (filter/time_offset.py) with the pitch offset it was measured with and the shank pitch
        rate at the frame time."""
        tilt = self.surface_tilt
        if tilt is None or tilt.bent or not self.config.filter.time_offset.estimate:
            return
        b_before = self.pitch_offset.offset_rad - step_rad
        rate = self._pitch_rate_at(t)
        floor = math.radians(self.config.filter.level_aiding.measurement_floor_deg)
        self.time_offset.update(
            t, tilt.tilt_rad, float(np.hypot(tilt.sigma_rad, floor)), b_before, rate
        )

    def _arbitrate_imu(self, d, d2: float | None = None) -> None:
        """Vision against the IMU over one displacement interval (filter/imu_faults.py): if the
        gate would refuse ``d`` but accepts it once a velocity jump of one corrupted IMU
        sample is allowed, the IMU is the odd one out and the filter's position/velocity
        covariance is widened by that jump before the update. ``d2``: the filter's
        ``displacement_d2(d)`` if already computed on the current state."""
        cfg = self.config.filter.imu_faults
        if not (cfg.enabled and cfg.vision_arbitration):
            return
        if d2 is None:
            d2 = self.filter.displacement_d2(d)
        if d2 is None or d2 <= self.filter.gate_d2:
            return
        Q = velocity_fault_cov(cfg.velocity_fault_sigma_mps, float(d.t1_s - d.t0_s))
        d2_fault = self.filter.displacement_d2(d, Q)
        if d2_fault is not None and d2_fault <= self.filter.gate_d2:
            self.filter.inflate_position_velocity(Q)
            self.n_imu_inconsistent += 1

    def _widen_for_relocalised(
        self, t: float, d, d2: float | None, prev: Displacement2D | None
    ) -> bool:
        """A displacement from the front end's lost-track search that the gate would refuse.
        The IMU-seeded registration failed and the unseeded search found this displacement;
        if it continues the previous frame's visual displacement ``prev`` (vision agrees
        with itself, :meth:`_continues`), the filter's velocity (the seed) is what went
        wrong: its variance is widened to twice the velocity error the disagreement implies,
        as an error held over the displacement's interval (SagittalEskf.inflate_velocity
        ``since_s``), and the update re-anchors it. Returns True if it widened."""
        if d2 is None:
            d2 = self.filter.displacement_d2(d)
        if d2 is None or d2 <= self.filter.gate_d2 or self._prev_frame is None:
            return False
        _, p_prev = self._prev_frame
        dt = float(d.t1_s - d.t0_s)
        if dt <= 0.0 or not self._continues(d, prev):
            return False
        p_now, _ = self._position_at(t)
        v_err = (np.asarray(d.delta_xz_m, dtype=float) - (p_now - p_prev)) / dt
        # the error built up over this displacement's interval: the position carries dt x dv
        # (and the clone, at its start, none), so the displacement corrects the velocity
        sigma_v = 2.0 * float(np.hypot(*v_err))
        self.filter.inflate_velocity(sigma_v, dt)
        # for the smoothers: the accelerometer sigma per sample whose sum over the interval's
        # samples (independent, period p) gives that velocity sigma: sigma_v / sqrt(dt p)
        p = self._imu_period_s
        self._imu_distrust = (float(d.t0_s), float(d.t1_s), sigma_v / math.sqrt(dt * p))
        return True

    def _continues(self, d, prev: Displacement2D | None) -> bool:
        """Does displacement ``d``'s velocity continue the latest earlier visual displacement
        ``prev``'s (ending at most ``frontend.tracker.max_frame_gap_s`` before ``d`` starts),
        within ``filter.relocalised_max_accel_mps2`` times the time between their middles?
        (Vision consistent with itself; False without ``prev``.)"""
        if prev is None:
            return False
        gap = float(d.t0_s) - float(prev.t1_s)  # frames without a displacement between them
        if not -1e-6 <= gap <= self.config.frontend.tracker.max_frame_gap_s:
            return False
        v = np.asarray(d.delta_xz_m, dtype=float) / float(d.t1_s - d.t0_s)
        v_prev = np.asarray(prev.delta_xz_m, dtype=float) / float(prev.t1_s - prev.t0_s)
        between_s = 0.5 * float(d.t0_s + d.t1_s - prev.t0_s - prev.t1_s)
        a_max = self.config.filter.relocalised_max_accel_mps2
        return float(np.hypot(*(v - v_prev))) <= a_max * between_s

    def _take_imu_distrust(self) -> tuple[float, float, float] | None:
        """This frame's IMU distrust for the smoothers (FrameRecord.imu_distrust), once."""
        out, self._imu_distrust = self._imu_distrust, None
        return out

    def _count_relocalised(self, t_s: float, fused: bool) -> None:
        """Health bookkeeping of a displacement from the front end's lost-track search."""
        h = self.health
        h.n_relocalised += 1
        h.n_relocalised_fused += int(fused)
        if fused and h.first_relocalised_s is None:
            h.first_relocalised_s = t_s

    def _recover_if_locked_out(self, refused: bool, t_s: float) -> None:
        """Gate lock-out recovery. A chi-square gate at p = 0.999 refuses a correct
        displacement by chance once in a thousand; ``lockout_refusals`` refusals in a row
        mean the filter's own state (a velocity gone wrong) is what disagrees with vision,
        and every later measurement would be refused too. The velocity covariance is then
        widened to its initial sigma so that the next displacement re-anchors it (counted in
        ``health.recoveries``)."""
        self._refused_in_row = self._refused_in_row + 1 if refused else 0
        n = self.config.filter.lockout_refusals
        if n is not None and self._refused_in_row >= n:
            since = 0.0
            if self.config.filter.lockout_since_last_fix and self._last_fix_t is not None:
                since = t_s - self._last_fix_t
            self.filter.inflate_velocity(self.config.filter.init_velocity_sigma_mps, since)
            self.health.n_recoveries += 1
            self._refused_in_row = 0

    def _level_aiding(self, t: float, profile_xz_m: NDArray[np.float64]) -> float:
        """Measure the tilt of the level surfaces in this frame's profile and update the
        pitch offset (frontend/level.py, filter/attitude.PitchOffsetFilter); returns the
        change of the offset (rad)."""
        cfg = self.config.filter.level_aiding
        self.pitch_offset.predict(t)
        self.surface_tilt = measure_surface_tilt(
            profile_xz_m,
            self._level_rng,
            math.radians(cfg.max_tilt_deg),
            cfg.inlier_m,
            cfg.min_points,
            cfg.min_extent_m,
            cfg.max_lines,
            cfg.correlated_points,
            cfg.end_trim_m,
            cfg.ray_fit,
            self.frontend.grid_cell_m / math.sqrt(12.0),
            self._smoother_ray_heights,
        )
        step = 0.0
        if self.surface_tilt is not None:
            if self._surfaces_bent(t, profile_xz_m):
                # a biased pitch measurement: shrunk towards the IMU's own pitch by how far
                # the bias may reach, and not given to the time-offset estimator
                self.surface_tilt = dataclasses.replace(self.surface_tilt, bent=True)
                tilt_rad, sigma_rad = self._bent_tilt(self.surface_tilt)
            else:
                tilt_rad, sigma_rad = self._tilt_to_fuse(t, self.surface_tilt)
                self._test_frame_tilt(t, tilt_rad, sigma_rad)
            if self._frame_rot_var_rad2 > 0.0:
                sigma_rad = math.sqrt(sigma_rad * sigma_rad + self._frame_rot_var_rad2)
            step = self.pitch_offset.update(tilt_rad, sigma_rad)
        if self.config.filter.attitude.vendor_pitch_sigma_deg is not None:
            self._weigh_attitude_pull(t)
        return step

    def _bent_tilt(self, tilt: SurfaceTilt) -> tuple[float, float]:
        """The residual tilt (rad) and its sigma (rad) to fuse from bent surfaces.

        What the treads measure is m = b + tilt (b the current pitch offset): the IMU
        attitude's pitch error e plus the bend's bias beta on the treads. The bend test's
        mean disagreement dbar is the treads' bias minus the faces' (of opposite signs);
        nothing in a frame says how it splits between them, so the treads' share is taken
        as half: beta ~ N(0, (dbar / 2)^2). With e ~ N(0, sigma_v^2)
        (``bend_vendor_sigma_deg``) the posterior of e given m has the mean k m and the
        variance k (dbar / 2)^2, k = sigma_v^2 / (sigma_v^2 + (dbar / 2)^2). The fused
        residual is k m - b, with that variance added to the fit's: a slight bend still
        corrects the attitude, a strong one leaves it mostly to the IMU."""
        assert self.bend_test is not None
        dbar = 0.5 * (self.bend_test.mean_rad() or 0.0)
        var_v = math.radians(self.config.filter.level_aiding.bend_vendor_sigma_deg) ** 2
        k = var_v / (var_v + dbar * dbar)
        b = self.pitch_offset.offset_rad
        residual = k * (b + tilt.tilt_rad) - b
        return residual, math.sqrt(tilt.sigma_rad**2 + k * dbar * dbar)

    def _surfaces_bent(self, t: float, profile_xz_m: NDArray[np.float64]) -> bool:
        """Feed this frame's tilt and face lean to the bend test (``level_aiding.bend_test``)
        and say whether the surfaces are bent (their tilt then is not a pitch measurement)."""
        test, tilt = self.bend_test, self.surface_tilt
        if test is None or tilt is None:
            return False
        cfg = self.config.filter.level_aiding
        face = measure_face_lean(
            profile_xz_m,
            self._face_rng,
            math.radians(cfg.max_tilt_deg),
            cfg.inlier_m,
            cfg.face_min_points,
            cfg.face_min_extent_m,
            cfg.max_lines,
            cfg.correlated_points,
            cfg.end_trim_m,
            tilt,
        )
        if face is not None:
            test.add(t, tilt.tilt_rad, tilt.sigma_rad**2, face.tilt_rad, face.sigma_rad**2)
        bent, onset = test.judge(t)
        if onset and self.config.filter.time_offset.estimate:
            # the tilts fused so far measured the bend too: drop what they taught the
            # camera-IMU time offset (the pitch offset is left to the shrunk tilts from here)
            self.time_offset.forget()
        return bent

    def _weigh_attitude_pull(self, t: float) -> None:
        """The attitude tracker's pull towards the vendor about the pitch axis, weighed against
        the pitch offset's variance (``filter.attitude.vendor_pitch_sigma_deg``,
        AttitudeTracker.weigh_pull), also in the one-call IMU input's constants. With
        ``auto``, the vendor's disagreement with the level-aided pitch at the latest IMU
        sample first goes to the vendor's variance estimate (VendorPitchVariance)."""
        var = math.inf
        if self.pitch_offset.initialised:
            # not below the tilts' floor: what the line fits miss is shared by the frames
            # (a tread's slant, a far tread's slope), so it does not average out
            floor = math.radians(self.config.filter.level_aiding.measurement_floor_deg)
            var = max(self.pitch_offset.var_rad2, floor * floor)
        att, vendor_var = self.attitude, self.vendor_pitch_variance
        if vendor_var is not None and var < math.inf and att._R is not None:
            q = att.vendor_quat_wxyz
            if q is not None:
                d = pitch_disagreement_rad(att._R, q) - self.pitch_offset.offset_rad
                vendor_var.add(att._t_s, d, var)
        tau = att.weigh_pull(var, None if vendor_var is None else vendor_var.var_rad2)
        kernels = self.attitude._kernels
        if self._input_consts is not None and kernels is not None:
            self._input_consts[kernels.IN_PITCH_TIME_CONSTANT] = tau

    def _tilt_to_fuse(self, t: float, tilt: SurfaceTilt) -> tuple[float, float]:
        """The tilt (rad) and its sigma (rad) the pitch offset fuses for the surface tilt
        measured at ``t``: the measurement itself (a seam for diagnostics that replace it)."""
        return tilt.tilt_rad, tilt.sigma_rad

    def _fuse_landmarks(
        self, t: float, result: FrontendResult, R_world_imu: NDArray[np.float64]
    ) -> None:
        """Corner landmarks and the stance ankle anchor (FilterConfig.corner_landmarks /
        stance_anchor; SagittalEskf.update_landmark)."""
        fc = self.config.filter
        obs = result.observation
        self._corner_observation = obs
        self._level_observations = ()
        if fc.corner_landmarks:
            key = None
            if obs is not None:
                key = self._corners.key(obs, self._position_at(t)[0], self.filter)
                # the smoothers see the re-identified corner under one track id too (the
                # observation itself when its track keeps its own id)
                if key.id != obs.track_id:
                    self._corner_observation = dataclasses.replace(obs, track_id=key.id)
                self._corners.saw(key, t)
            self._corners.forget(t, key, self.filter)
            if obs is not None:
                assert key is not None  # set above for every observation
                cov = np.asarray(obs.cov_m2, float) + _I2 * fc.corner_landmark_sigma_m**2
                time_cov = self._landmark_time_cov(t)
                if time_cov is not None:
                    cov = cov + time_cov
                if self._frame_rot_var_rad2 > 0.0:
                    cov = cov + _turn_cov_m2(obs.corner_rel_xz_m, self._frame_rot_var_rad2)
                self._as_family(
                    t, "corner", self.filter.update_landmark, key, obs.corner_rel_xz_m, cov, t
                )
        if fc.level_landmarks:
            self._as_family(t, "level", self._fuse_levels, t)
            if result.n_camera_fixed:
                # something moves with the camera (frontend/camera_fixed.py): a "level
                # surface" may be that object, at a fixed height below the lens, which would
                # hold the smoothers' height to the camera's own (the simulated occluding foot:
                # smoother / batch toe z 1.6 / 0.5 -> 4.0 / 5.1 cm); the smoothers skip them
                self._level_observations = ()
        if fc.stance_anchor:
            self._as_family(t, "stance", self._fuse_stance, t, result, R_world_imu)

    def _as_family(self, t_s: float, family: str, update: Callable[..., _T], *args: object) -> _T:
        """``update(*args)`` with the filter updates it makes handed to the health report's
        consistency test as measurements of ``family``; updates made since the last hand-over
        (by anything else) go first, as ``"other"``. Returns what ``update`` returns."""
        self._note_innovations(t_s, "other")
        out = update(*args)
        self._note_innovations(t_s, family)
        return out

    def _note_innovations(self, t_s: float, family: str) -> None:
        """Hand the filter's updates since the last call to the health report's consistency
        test as measurements of ``family`` (read-only: the estimate is not touched)."""
        if not self.filter.innovations:  # nothing since the last hand-over (most calls)
            return
        items = self.filter.take_innovations()
        if items:
            self.health.add_innovations(t_s, family, items)

    def _fuse_levels(self, t: float) -> None:
        """Height landmarks (FilterConfig.level_landmarks): every level surface of this
        frame's slice (self.surface_tilt.lines) is associated by height with a remembered one
        (filter/level_landmarks.py) and fused as its height relative to the camera
        (SagittalEskf.update_height_landmark), with the line's sigma and the displacements'
        noise floor in quadrature."""
        lines = () if self.surface_tilt is None else self.surface_tilt.lines
        camera_z = float(self._position_at(t)[0][1])
        taken: set[LandmarkKey] = set()
        made: dict[LandmarkKey, float] = {}
        found = []
        # a height whose sigma reaches a third of the association window cannot be told from
        # the next surface's (short, grazing lines far down a descent: 2-5 cm off)
        max_sigma = self.config.filter.level_reidentify_m / 3.0
        for line in lines:
            if line.sigma_m > max_sigma:
                continue
            key = self._levels.key(camera_z + line.height_m, self.filter, taken, made)
            if key is not None:
                taken.add(key)
                found.append((key, line))
        self._levels.forget(t, taken, self.filter)
        floor = self.config.filter.measurement_noise_floor_m
        time_cov = self._landmark_time_cov(t)
        if time_cov is not None:  # a height is z only
            floor = math.sqrt(floor**2 + float(time_cov[1, 1]))
        for key, _ in found:
            self._levels.saw(key, t)
        if not self.config.filter.level_shared_tilt:
            new = [not self.filter.has_landmark(key) for key, _ in found]
            rv = self._frame_rot_var_rad2
            var = [line.sigma_m**2 + floor**2 + rv * line.x_mid_m**2 for _, line in found]
            fused = [
                self.filter.update_height_landmark(key, line.height_m, v, t)
                for (key, line), v in zip(found, var, strict=True)
            ]
            self._hand_levels(t, found, new, fused, var)
            return
        if not found:
            return
        # the slope error the heights share (the fit's sigma as a slope, and the tilt floor
        # the pitch aiding gives the same measurement), and each line's own noise
        assert self.surface_tilt is not None  # lines come from it
        st = self.surface_tilt
        slope_sigma = st.sigma_rad * (1.0 + math.tan(st.tilt_rad) ** 2)
        tilt_floor = math.radians(self.config.filter.level_aiding.measurement_floor_deg)
        tilt_var = slope_sigma**2 + tilt_floor**2 + self._frame_rot_var_rad2
        new = [not self.filter.has_landmark(key) for key, _ in found]
        fused = self.filter.update_height_landmarks(
            [key for key, _ in found],
            [line.height_m for _, line in found],
            [line.noise_sigma_m**2 + floor**2 for _, line in found],
            [line.x_mid_m for _, line in found],
            tilt_var,
            t,
        )
        # the smoothers take each surface alone: its own noise and the shared tilt's share
        # (their correlation within the slice is not kept)
        self._hand_levels(
            t,
            found,
            new,
            fused,
            [line.noise_sigma_m**2 + floor**2 + tilt_var * line.x_mid_m**2 for _, line in found],
        )

    def _hand_levels(
        self, t: float, found, new: list[bool], fused: list[bool], var_m2: list[float]
    ) -> None:
        """This frame's level surfaces for the smoothers (``smoother.factors.height_landmarks``;
        nothing is built when it is off), each with its height variance ``var_m2`` (m^2):
        those the filter fused, and first sights it took in as new height landmarks; not those
        its innovation gate refused (a surface the filter's own state contradicts), nor stale
        ones."""
        if not self.config.smoother.factors.height_landmarks:
            return
        # smoother.height_landmark_heights 'ray_fit': the ray-fitted height (the filter
        # fused its own, line.height_m)
        self._level_observations = tuple(
            LevelObservation(
                t,
                key.id,
                line.height_m if line.ray_height_m is None else line.ray_height_m,
                v,
                line.x_mid_m,
            )
            for (key, line), n, f, v in zip(found, new, fused, var_m2, strict=True)
            if f or (n and self.filter.has_landmark(key))
        )

    def _stance_lever(self, R_world_imu: NDArray[np.float64], theta: float | None = None):
        """ankle - camera through the shank (m, ground axes): R_shank (ankle_in_shank -
        camera_in_shank), and its derivative by the shank pitch. ``theta``: the shank pitch
        of ``R_world_imu`` (rad) if the caller has it already."""
        if theta is None:
            theta = self.rig.shank_pitch_rad(R_world_imu)
        u0, u1 = self._ankle_from_camera_shank_m.tolist()
        # geometry.rotate_xz written out on scalars (the same products and sums, no stack)
        c, s = np.cos(theta), np.sin(theta)
        lever = np.array([c * u0 + s * u1, -s * u0 + c * u1])
        # d lever/d theta = R'(theta) u = R(theta) (u_z, -u_x)
        dlever = np.array([c * u1 + s * -u0, -s * u1 + c * -u0])
        return lever, dlever

    def _fuse_stance(
        self, t: float, result: FrontendResult, R_world_imu: NDArray[np.float64]
    ) -> None:
        """Stance anchor: the ankle fixed at stance onset is a landmark seen through the leg.

        The acceleration detector (or the contact channel) proposes a stance; the visual
        displacement of this frame (and the chain of them since onset) must agree with a still
        ankle (StanceConsistencyTest), and the anchor observation itself is chi-square gated
        when ``stance_gate``. A gate refusal is arbitrated: if vision tested and confirmed the
        still ankle in this frame, the filter's velocity is the odd one out and the anchor is
        taken; otherwise (no visual evidence) the stance ends, its anchor
        is marginalised and a new one may start at the next frame. So a wrong stance cannot
        pin the estimate, and a velocity drifted in a blind swing cannot lock the anchor out.
        """
        fc = self.config.filter
        theta = self.rig.shank_pitch_rad(R_world_imu)  # the lever's and the foot's, once
        lever, dlever = self._stance_lever(R_world_imu, theta)
        agrees = self._stance_test.test(t, lever, result.displacement)
        foot_still = self._foot_test.test(self._foot_pitch_rad(R_world_imu, theta))
        if self._last_contact is None or fc.stance_contact == "off":
            candidate = self._stance.quiet()
        elif fc.stance_contact == "confirm":
            candidate = self._last_contact.loaded and self._stance.quiet()
        else:
            candidate = self._last_contact.loaded
        if candidate and fc.stance_speed_threshold_mps is not None:
            rate = self._pitch_rate_radps(R_world_imu)
            _, v_cam = self._position_at(t)
            candidate = float(np.hypot(*(v_cam + rate * dlever))) < fc.stance_speed_threshold_mps
        stats = self.stance_stats
        stats["candidate_frames"] += int(candidate)
        stats["vision_refused"] += int(candidate and not (agrees and foot_still))
        stats["foot_refused"] += int(candidate and agrees and not foot_still)
        stance = candidate and agrees and foot_still
        key = LandmarkKey("ankle", self._stance_n)
        sig2 = self._lever_sigma_m**2 + fc.stance_slip_sigma_m**2  # the anchor's variance
        if (
            fc.stance_attitude_reanchor
            and stance
            and self._in_stance
            and self.filter.has_landmark(key)
        ):
            # the anchor holds the ankle seen through the attitude of its onset; the level
            # surfaces have turned that attitude since (pitch offset) by more than the anchor's
            # own sigma allows over this lever: the anchor would drag the camera by the turn
            # times the lever, so it ends here and a new one starts at this frame
            turn = abs(self.pitch_offset.offset_rad - self._stance_offset_rad)
            if turn * float(np.hypot(*lever)) > np.sqrt(sig2):
                self.filter.drop_landmark(key)
                self._stance_n += 1
                self._stance_test.reset()
                key = LandmarkKey("ankle", self._stance_n)
                stats["attitude_reanchors"] += 1
        self._stance_observation = None
        if stance:
            first = not self.filter.has_landmark(key)
            if first:
                self._stance_offset_rad = self.pitch_offset.offset_rad
            fused = self.filter.update_landmark(key, lever, _I2 * sig2, t, fc.stance_gate)
            if not (first or fused) and self._stance_test.tested:
                # the gate says the filter and the anchor disagree, while vision has just
                # confirmed the still ankle: two sensors against the filter's velocity (which
                # drifts in every swing without vision), so the anchor is taken, if vision
                # could have seen the disagreement (a refused update left the state as it
                # was: this is the anchor's innovation, the ankle motion since onset that
                # the filter's camera implies)
                innovation = lever - (self.filter.landmark_xz(key) - self._position_at(t)[0])
                if fc.stance_override_needs_power and not self._stance_test.resolves(innovation):
                    stats["override_unpowered"] += 1
                else:
                    fused = self.filter.update_landmark(key, lever, _I2 * sig2, t, False)
                    stats["vision_overrides"] += 1
            if first or fused:
                stats["anchored_frames"] += 1
                velocity = None
                if fc.stance_velocity_sigma_mps is not None:
                    velocity = self._fuse_stance_velocity(t, R_world_imu, dlever)
                # the same anchor, as a landmark observation the smoother can use
                self._stance_observation = StanceObservation(
                    timestamp_s=t,
                    stance_id=self._stance_episode,
                    ankle_rel_xz_m=lever.copy(),
                    cov_m2=_I2 * sig2,
                    camera_velocity_xz_mps=None if velocity is None else velocity[0],
                    velocity_cov=None if velocity is None else velocity[1],
                )
            else:
                stats["gate_refused"] += 1
                stance = False
        if not stance:
            if self._in_stance:  # the stance ended: its anchor leaves the state
                self.filter.drop_landmark(key)
                self._stance_n += 1
                self._stance_episode += 1
            self._stance_test.reset()
            self._foot_test.reset()
        self._in_stance = stance

    def _foot_pitch_rad(
        self, R_world_imu: NDArray[np.float64], theta: float | None = None
    ) -> float | None:
        """Foot pitch (rad): the IMU shank pitch (the one the stance lever uses; ``theta`` if
        the caller has it) plus the ankle encoder at this frame; None without a joints
        stream."""
        j = self._frame_joints if self._frame_joints is not None else self._last_joints
        if j is None:
            return None
        if theta is None:
            theta = self.rig.shank_pitch_rad(R_world_imu)
        return theta + float(j.ankle_rad)

    def _pitch_rate_radps(self, R_world_imu: NDArray[np.float64]) -> float:
        """The shank's pitch rate (rad/s, about the ground frame's lateral axis) from the
        latest IMU sample's gyro that is a measurement (a repaired packet's gyro is a
        prediction, 0.4-0.6 rad/s off: through the 0.4 m stance lever 0.2 m/s of stance
        velocity)."""
        imu = self._last_trusted_imu if self._last_trusted_imu is not None else self._last_imu
        assert imu is not None  # a frame comes after an IMU sample
        return float((R_world_imu @ np.asarray(imu.gyro_radps, float))[1])

    def _fuse_stance_velocity(
        self, t: float, R_world_imu: NDArray[np.float64], dlever: NDArray[np.float64]
    ) -> tuple[NDArray[np.float64], NDArray[np.float64]] | None:
        """The still ankle's velocity: v_cam + pitch rate x d lever/d pitch = 0, so the camera
        moves at -rate x dlever (m/s, ground axes). Gated, and never forced: a stance the
        detector proposes in the slow part of a swing passes the vision test and would zero
        a velocity that is not zero (a detector flagging every frame: toe 8 cm forced, within
        2 cm gated)."""
        fc = self.config.filter
        assert fc.stance_velocity_sigma_mps is not None
        rate = self._pitch_rate_radps(R_world_imu)
        v_cam = -rate * np.asarray(dlever, dtype=float)
        cov = _I2 * fc.stance_velocity_sigma_mps**2
        fused = self.filter.update_velocity(v_cam, cov, t, fc.stance_gate)
        self.stance_stats["velocity_fused"] += int(fused)
        return (v_cam, cov) if fused else None

    def leg_points(self, camera_xz_m: NDArray[np.float64], R_world_imu: NDArray[np.float64]):
        """Knee, ankle, heel, toe (world x-z) for a camera position, using the latest joints
        (one pose on Python floats: :meth:`RigGeometry.leg_points_one`, the same floats as
        ``RigGeometry.leg_points``)."""
        imu_pitch, chain_pitch, ankle = self.leg_angles(R_world_imu)
        use_enc = self.config.kinematics.shank_pitch_source == "encoders"
        return self.rig.leg_points_one(camera_xz_m, imu_pitch, chain_pitch, ankle, use_enc)

    def leg_angles(self, R_world_imu: NDArray[np.float64]) -> tuple[float, float, float]:
        """(IMU shank pitch, thigh-IMU-minus-knee-encoder shank pitch, ankle) in rad, from the
        latest joint sample (without one: the IMU pitch and a neutral ankle)."""
        imu_pitch = self.rig.shank_pitch_rad(R_world_imu)
        j = self._frame_joints if self._frame_joints is not None else self._last_joints
        if j is None:
            return imu_pitch, imu_pitch, 0.0
        return imu_pitch, float(shank_pitch_rad(j.thigh_pitch_rad, j.knee_rad)), j.ankle_rad
