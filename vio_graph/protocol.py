"""The estimator protocol: what the replay hands every estimator, and what it gets back.

The online estimator (:class:`vio_graph.estimator.OnlineEstimator`: front end + SP-ESKF) turns
the raw streams into two typed records, one per IMU sample (:class:`ImuStep`) and one per depth
frame (:class:`FrameRecord`). Every estimator the replay compares -- the filter itself, the
IMU-only and ICP-only baselines, the fixed-lag and the batch smoother -- takes those same
records through the same three calls and answers with a camera path:

    for each IMU sample:   step = online.add_imu(sample);        e.add_imu(step)   for every e
    for each depth frame:  record = online.process_frame(frame); e.add_frame(record)
    at the end:            e.finish(); e.camera_path(frame_times_s, filter_xz_m)

What a smoother needs from the front end and the filter (the corrected IMU sample in shank
axes, the attitude the measurements were built with, the displacement, the corner and stance
observations, the filter's estimate as initial guess) travels in these records, so no
estimator reads another's attributes.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass, field
from typing import TYPE_CHECKING, Any, Protocol, runtime_checkable

import numpy as np
from numpy.typing import NDArray

from vio_graph.growable import GrowableArray
from vio_graph.types import (
    CornerObservation,
    Displacement2D,
    FrameEstimate,
    FrameObservation,
    ImuSample,
    LevelObservation,
    StanceObservation,
    VelocityObservation,
)

if TYPE_CHECKING:
    from vio_graph.frontend.frontend import FrontendResult


class ImuStep:
    """One IMU sample as every estimator receives it.

    ``shank``: the sample as measured, turned into shank axes (any IMU mount; vendor
    orientation untouched). ``corrected``: the same sample with the level-surface pitch offset
    applied to its orientation, i.e. what the SP-ESKF propagated with (equal to ``shank``
    while the offset is unset). Read-only by convention, as the samples.

    The online estimator's compiled path hands the corrected orientation only
    (:meth:`with_quat`): ``corrected`` is then built on first use, and an estimator that
    needs only its fields (the smoothers) reads ``shank`` and :attr:`corrected_quat_wxyz`
    without building it (one ImuSample costs ~1.5 us, a tenth of the sample's budget).
    """

    __slots__ = ("shank", "_corrected", "_quat", "shank_but_quat")

    def __init__(self, shank: ImuSample, corrected: ImuSample) -> None:
        self.shank = shank
        self._corrected: ImuSample | None = corrected
        self._quat: NDArray[np.float64] = corrected.quat_wxyz
        #: True if ``corrected`` is ``shank`` with :attr:`corrected_quat_wxyz`, everything
        #: else the same (a step made by :meth:`with_quat`)
        self.shank_but_quat = False

    @classmethod
    def with_quat(cls, shank: ImuSample, quat_wxyz: NDArray[np.float64]) -> ImuStep:
        """The step whose corrected sample is ``shank`` with the orientation ``quat_wxyz``
        (same time, same everything else), built when first asked for."""
        step = cls.__new__(cls)
        step.shank = shank
        step._corrected = None
        step._quat = quat_wxyz
        step.shank_but_quat = True
        return step

    @property
    def corrected(self) -> ImuSample:
        c = self._corrected
        if c is None:
            s = self.shank
            c = self._corrected = ImuSample(
                s.timestamp_s,
                s.accel_mps2,
                s.gyro_radps,
                self._quat,
                s.accel_extra_sigma_mps2,
                s.gyro_extra_sigma_radps,
                s.accel_held,
                s.measured_accel_mps2,
                s.measured_gyro_radps,
                s.accel_extra_cov_m2ps4,
            )
        return c

    @property
    def corrected_quat_wxyz(self) -> NDArray[np.float64]:
        """``corrected.quat_wxyz`` without building ``corrected``."""
        return self._quat

    @property
    def timestamp_s(self) -> float:
        return self.shank.timestamp_s


@dataclass(frozen=True)
class FrameRecord:
    """One depth frame as every estimator receives it: the online estimate and what it was
    built from.

    ``estimate``: the filter's answer (camera, leg points, status, keyframe flag, timings).
    ``frontend``: the front end's result as fused (profile, terrain, corner, ICP, rejection
    reason; after any fault injection). ``displacement``: the camera displacement the filter
    was given this frame (None if none passed). ``corner``: the corner observation with the track
    id of its (re-identified) landmark; ``stance``: the stance anchor (ankle minus camera
    through the leg) when the frame was anchored, else None. ``R_world_imu`` (3, 3): the
    attitude, heading removed and level-aided, that the displacement and observations were
    built with. ``shank_pitch_imu_rad`` / ``shank_pitch_chain_rad`` / ``ankle_rad``: the leg
    angles (rad) the kinematics used; ``in_stance``: the frame was anchored in stance.
    """

    estimate: FrameEstimate
    frontend: FrontendResult
    displacement: Displacement2D | None
    corner: CornerObservation | None
    stance: StanceObservation | None
    R_world_imu: NDArray[np.float64]
    shank_pitch_imu_rad: float
    shank_pitch_chain_rad: float
    ankle_rad: float
    in_stance: bool
    #: the leg-chain bridge's camera velocity after a saturated stretch, on the first
    #: keyframe after it (vio_graph/filter/leg_bridge.py), else None
    velocity: VelocityObservation | None = None
    #: the level surfaces of the slice as the filter's height landmarks (associated by
    #: height, vio_graph/filter/level_landmarks.py); empty when none was found or fused
    levels: tuple[LevelObservation, ...] = ()
    #: (t0_s, t1_s, accel_sigma_mps2): the filter found the IMU wrong over [t0, t1] (a
    #: lost-track displacement it widened its velocity for, estimator._widen_for_relocalised):
    #: the smoothers add this accelerometer sigma to those samples, else None
    imu_distrust: tuple[float, float, float] | None = None

    @property
    def timestamp_s(self) -> float:
        return self.estimate.timestamp_s

    @property
    def is_keyframe(self) -> bool:
        return self.estimate.is_keyframe

    def observations(
        self, stance_anchors: bool = True, levels: bool = True
    ) -> list[FrameObservation]:
        """The observations of this frame: the corner, then (``stance_anchors``) the stance
        anchor, then the bridge's velocity, then (``levels``) the level surface with the
        smallest variance, each if present."""
        obs: list[FrameObservation] = [] if self.corner is None else [self.corner]
        if stance_anchors and self.stance is not None:
            obs.append(self.stance)
        if self.velocity is not None:
            obs.append(self.velocity)
        if levels and self.levels:
            # the best-measured surface only: the lines of one slice share the error of the
            # tilt they were levelled with, which independent factors would count once per
            # line (paper scenarios, 3 seeds: smoother toe z 0.29 -> 0.25 cm against every
            # line; docs/method.md, "Height landmarks in the smoothers")
            obs.append(min(self.levels, key=lambda o: o.var_m2))
        return obs


@dataclass
class EstimatorReport:
    """What an estimator adds to metrics.json: ``latency_ms`` entries (merged into the run's
    latency block) and top-level ``metrics`` entries."""

    latency_ms: dict[str, Any] = field(default_factory=dict)
    metrics: dict[str, Any] = field(default_factory=dict)


@runtime_checkable
class Estimator(Protocol):
    """One estimator driven by the replay (see the module docstring).

    ``name`` is its mode name in the results (``filter``, ``imu_only``, ``icp_only``,
    ``smoother``, ``batch``). The calls may raise :class:`vio_graph.errors.EstimationError`;
    the replay then stops feeding that estimator and records the failure.
    """

    name: str

    def add_imu(self, step: ImuStep) -> None:
        """One IMU sample (timestamps strictly increasing)."""

    def add_frame(self, record: FrameRecord) -> None:
        """One depth frame, after every IMU sample stamped at or before it."""

    def finish(self) -> None:
        """The recording ended: complete what is pending (and solve, for the batch)."""

    def camera_path(
        self, frame_times_s: NDArray[np.float64], filter_xz_m: NDArray[np.float64]
    ) -> NDArray[np.float64]:
        """Camera x-z (N, 2), metres, at every replayed frame. ``filter_xz_m`` (N, 2) is the
        filter's path at ``frame_times_s`` (s): keyframe smoothers spread their keyframe
        corrections over it. Raises EstimationError if there is no usable answer."""

    def report(self) -> EstimatorReport:
        """Latency and diagnostics for metrics.json (empty for most estimators)."""


class FilterTrack:
    """The online filter's own answer, kept per frame like every other estimator's (the
    filter runs inside :class:`~vio_graph.estimator.OnlineEstimator`, which made the
    records; this only keeps its camera positions)."""

    name = "filter"

    def __init__(self) -> None:
        self._path = GrowableArray((2,))  # camera x-z per frame

    def add_imu(self, step: ImuStep) -> None:
        pass

    def add_frame(self, record: FrameRecord) -> None:
        self._path.append(record.estimate.camera_xz_m)

    def finish(self) -> None:
        pass

    def camera_path(
        self, frame_times_s: NDArray[np.float64], filter_xz_m: NDArray[np.float64]
    ) -> NDArray[np.float64]:
        return np.asarray(self._path)

    def report(self) -> EstimatorReport:
        return EstimatorReport()


def path_of_frames(
    path: Sequence[NDArray[np.float64]] | GrowableArray, n_frames: int, name: str
) -> NDArray[np.float64]:
    """A per-frame path kept by an estimator, checked to cover all ``n_frames`` frames."""
    from vio_graph.errors import EstimationError

    if len(path) != n_frames:
        raise EstimationError(f"{name} has {len(path)} of {n_frames} frames")
    return np.asarray(path)
