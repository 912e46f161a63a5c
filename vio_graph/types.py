"""Frozen sample and result types shared by every layer.

Units are in the names: metres (``_m``), seconds (``_s``), radians (``_rad``), m/s^2
(``_mps2``), rad/s (``_radps``). Frames follow docs/conventions.md.
"""

from __future__ import annotations

import enum
from dataclasses import dataclass, field
from typing import Any, Literal, NamedTuple, TypeAlias

import numpy as np
from numpy.typing import NDArray


@dataclass(frozen=True)
class ImuSample:
    """One IMU output as an Xsens MTi gives it (body frame = IMU frame).

    ``quat_wxyz`` is the vendor orientation R_world_imu (gravity-aligned, heading arbitrary).
    ``accel_extra_sigma_mps2`` / ``gyro_extra_sigma_radps``: how far the estimator distrusts
    this sample beyond the sensor noise (set by vio_graph/filter/imu_faults.py for saturated
    or repaired samples; 0 = a normal sample). The filter adds them to its process noise and
    the smoothers to the preintegration covariance. ``accel_held``: the accelerometer value is
    a stand-in (the previous trusted sample, held over a corrupted packet), not a measurement;
    an estimator that sees the next sample may replace it (the smoothers interpolate it).
    ``measured_accel_mps2`` / ``measured_gyro_radps``: on such a stand-in, what the packet
    itself said (same axes as the sample), so that an estimator which sees the next sample
    can keep the axes that agree with its neighbours (filter/imu_repair.py
    :func:`keep_consistent_axes`); None on a measured sample.
    ``accel_extra_cov_m2ps4``: on a saturated sample, the saturation prior's extra
    accelerometer covariance (3, 3; same axes as the sample) with its variance on the clipped
    axes only (the others measured as usual), whose largest sigma is
    ``accel_extra_sigma_mps2``; None: the extra sigma applies to every axis.
    """

    timestamp_s: float
    accel_mps2: NDArray[np.float64]  # (3,) specific force
    gyro_radps: NDArray[np.float64]  # (3,)
    quat_wxyz: NDArray[np.float64]  # (4,)
    accel_extra_sigma_mps2: float = 0.0
    gyro_extra_sigma_radps: float = 0.0
    accel_held: bool = False
    measured_accel_mps2: NDArray[np.float64] | None = None
    measured_gyro_radps: NDArray[np.float64] | None = None
    accel_extra_cov_m2ps4: NDArray[np.float64] | None = None


@dataclass(frozen=True)
class JointAngles:
    """Thigh IMU pitch and joint encoder angles (rad), see vio_graph.kinematics for signs."""

    timestamp_s: float
    thigh_pitch_rad: float
    knee_rad: float
    ankle_rad: float


@dataclass(frozen=True)
class ContactSample:
    """Foot contact of the instrumented leg from a contact sensor (optional stream).

    ``loaded``: the sensor says the foot bears weight (a pylon load cell above its threshold,
    a heel / foot switch closed). ``force_n``: the load-cell axial force (N), or 1.0 / 0.0 for
    a switch.
    """

    timestamp_s: float
    loaded: bool
    force_n: float


@dataclass(frozen=True)
class DepthFrame:
    """One organised ToF depth image.

    ``depth_m``: (H, W) float32 depth along the optical axis in metres, 0 where invalid.
    ``confidence``: (H, W) uint8, 0 = invalid .. 255 (royale's depthConfidence).
    """

    index: int
    timestamp_s: float
    depth_m: NDArray[np.float32]
    confidence: NDArray[np.uint8]


class TerrainKind(str, enum.Enum):  # noqa: UP042 - str(member) stays 'TerrainKind.X'
    """Terrain class of the sagittal profile in front of the camera."""

    STAIR_UP = "stair_up"
    STAIR_DOWN = "stair_down"
    OBSTACLE = "obstacle"
    LEVEL = "level"
    UNKNOWN = "unknown"


class EstimateStatus(str, enum.Enum):  # noqa: UP042 - as TerrainKind
    """How an estimate was obtained."""

    FUSED = "fused"  # IMU propagation corrected by an ICP displacement
    IMU_ONLY = "imu_only"  # no usable displacement this frame
    INITIALISING = "initialising"


@dataclass(frozen=True)
class Displacement2D:
    """Camera displacement between two frames in the ground (world-aligned) x-z plane.

    ``delta_xz_m`` = camera position at ``t1_s`` minus camera position at ``t0_s``;
    ``cov_m2`` is its 2x2 covariance.
    """

    t0_s: float
    t1_s: float
    delta_xz_m: NDArray[np.float64]
    cov_m2: NDArray[np.float64]


@dataclass(frozen=True)
class CornerObservation:
    """A terrain corner (stair nosing / obstacle top edge) seen from the camera.

    ``corner_rel_xz_m``: corner minus camera position, ground-aligned axes, metres.
    ``track_id``: the same physical corner keeps its id across consecutive frames.
    """

    timestamp_s: float
    track_id: int
    corner_rel_xz_m: NDArray[np.float64]
    cov_m2: NDArray[np.float64]


@dataclass(frozen=True)
class StanceObservation:
    """The stance anchor: the ankle, fixed at stance onset, seen from the camera through the
    leg kinematics (vio_graph/estimator.py).

    ``ankle_rel_xz_m``: ankle minus camera position, ground-aligned axes, metres.
    ``stance_id``: one id per stance (the same anchor keeps it over the stance's frames).
    ``camera_velocity_xz_mps`` / ``velocity_cov``: the camera velocity a still ankle implies
    (m/s, ground axes) and its covariance ((m/s)^2), when the filter fused it
    (``filter.stance_velocity_sigma_mps``); else None.
    """

    timestamp_s: float
    stance_id: int
    ankle_rel_xz_m: NDArray[np.float64]
    cov_m2: NDArray[np.float64]
    camera_velocity_xz_mps: NDArray[np.float64] | None = None
    velocity_cov: NDArray[np.float64] | None = None


@dataclass(frozen=True)
class LevelObservation:
    """A level surface (tread, landing, floor, obstacle top) seen from the camera: a z-only
    landmark (the filter's height landmarks, vio_graph/filter/level_landmarks.py).

    ``level_id``: the filter's height landmark the surface was associated with (by height);
    the same id over the frames that re-identified it. ``height_rel_m``: surface height minus
    camera height, metres (ground axes); ``var_m2``: its variance, m^2. ``x_rel_m``: where
    along x (m, from the camera, ground axes) the surface was seen (the mean of its points):
    a pitch error of the attitude the slice was levelled with moves the height by x_rel x
    the error, so the smoothers, which refine the pitch, observe the point (x_rel, height).
    """

    timestamp_s: float
    level_id: int
    height_rel_m: float
    var_m2: float
    x_rel_m: float = 0.0


@dataclass(frozen=True)
class VelocityObservation:
    """The camera velocity (m/s, ground axes) at a keyframe from a second source, and its
    covariance ((m/s)^2): the leg-chain bridge across a saturated accelerometer stretch
    (vio_graph/filter/leg_bridge.py), carried by the filter's IMU propagation from the
    stretch's end to the frame. The smoothers put it on the keyframe's velocity, or, with
    ``change_xz_mps`` (``smoother.factors.saturation_bridge_relative``), on the change of
    velocity from the keyframe at ``since_timestamp_s`` (the last one before the stretch)."""

    timestamp_s: float
    camera_velocity_xz_mps: NDArray[np.float64]
    cov: NDArray[np.float64]
    #: the keyframe before the stretch (s), the camera velocity change (m/s, ground x-z) from
    #: it to this frame (the filter's IMU propagation before and after the stretch, the leg
    #: chain's change across it) and that change's covariance ((m/s)^2, the chain's: the
    #: hip's change and the encoders' rate noise); None without a keyframe before the stretch
    since_timestamp_s: float | None = None
    change_xz_mps: NDArray[np.float64] | None = None
    change_cov: NDArray[np.float64] | None = None
    #: the chain's own discretisation error at the stretch's two ends ((m/s)^2, 2x2;
    #: LegChainBridge.discretisation_cov), when it is not already in ``cov`` /
    #: ``change_cov``; None if not computed (``smoother.factors.saturation_bridge_discretisation``
    #: off) or the joints did not cover the ends in time
    discretisation_cov: NDArray[np.float64] | None = None


#: A landmark seen from the camera: a terrain corner or the stance ankle.
LandmarkObservation: TypeAlias = CornerObservation | StanceObservation

#: What a frame hands the smoothers besides its displacement: landmarks and the bridge's
#: velocity.
FrameObservation: TypeAlias = (
    CornerObservation | StanceObservation | VelocityObservation | LevelObservation
)


class LandmarkKey(NamedTuple):
    """Key of a landmark in the filter state: a corner (``id`` = its landmark's track id),
    the stance ankle (``id`` = the stance id) or a level surface's height (``id`` = its
    number)."""

    kind: Literal["corner", "ankle", "level"]
    id: int


@dataclass(frozen=True)
class FrameEstimate:
    """What the online estimator returns for one depth frame."""

    timestamp_s: float
    status: EstimateStatus
    camera_xz_m: NDArray[np.float64]
    velocity_xz_mps: NDArray[np.float64]
    cov_position_m2: NDArray[np.float64]
    knee_xz_m: NDArray[np.float64]
    ankle_xz_m: NDArray[np.float64]
    heel_xz_m: NDArray[np.float64]
    toe_xz_m: NDArray[np.float64]
    terrain: TerrainKind = TerrainKind.UNKNOWN
    is_keyframe: bool = False
    timings_ms: dict[str, float] = field(default_factory=dict)
    #: toe clearance, placement and terrain ahead (vio_graph/safety/online.SafetyEstimate);
    #: None when ``safety.enabled`` is off
    safety: Any = None
    #: the filter's 2x2 velocity covariance ((m/s)^2) at the frame (None if not given)
    cov_velocity_m2ps2: NDArray[np.float64] | None = None
