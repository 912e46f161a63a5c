"""Ingestion interface shared by the fixed-lag and the batch smoother.

Both smoothers follow the estimator protocol (vio_graph/protocol.py): per IMU sample an
:class:`~vio_graph.protocol.ImuStep` (the level-aided sample in shank axes is used), per depth
frame a :class:`~vio_graph.protocol.FrameRecord` (the filter's estimate as initial guess, the
displacement, the corner and stance observations and the attitude they were built with), so
one replay loop drives every estimator and the comparison is like for like. Below the
protocol, :meth:`KeyframeSmootherBase.feed_imu` / :meth:`KeyframeSmootherBase.feed_frame` take
the same inputs one by one (synthetic trials and tests use them).
"""

from __future__ import annotations

import time
from abc import ABC, abstractmethod
from collections.abc import Callable, Sequence
from typing import NamedTuple

import numpy as np
from numpy.typing import ArrayLike, NDArray

from vio_graph.errors import EstimationError
from vio_graph.protocol import EstimatorReport, FrameRecord, ImuStep
from vio_graph.smoother.config import SmootherConfig
from vio_graph.smoother.graph import KeyframeGraphBuilder, KeyframeUpdate
from vio_graph.types import Displacement2D, FrameEstimate, FrameObservation, ImuSample


class KeyframeEstimate(NamedTuple):
    """Refined camera position of one keyframe (world x-z, metres), its 2x2 covariance and
    the refined IMU attitude ``R_world_imu`` (3, 3, heading removed; None if unsolved).

    ``cov_m2`` is NaN where the solver gives no marginal (e.g. BatchFixedLagSmoother).
    """

    timestamp_s: float
    camera_xz_m: NDArray[np.float64]
    cov_m2: NDArray[np.float64]
    R_world_imu: NDArray[np.float64] | None = None


class KeyframeSmootherBase(ABC):
    """Common ingestion (the protocol's ``add_imu`` / ``add_frame`` / ``finish``, or
    ``feed_imu`` / ``feed_frame`` / ``flush``) and per-frame output (``camera_path`` /
    ``frame_trajectory``).

    Subclasses consume :class:`KeyframeUpdate` batches and report refined keyframes.
    """

    name: str

    def __init__(self, config: SmootherConfig, imu_T_cam: ArrayLike) -> None:
        self.config = config
        self._builder = KeyframeGraphBuilder(config, imu_T_cam)
        self.imu_p_cam_m = self._builder.imu_p_cam_m
        #: wall time (ms) spent building each keyframe's factors (preintegration included)
        self.build_times_ms: list[float] = []
        self._kf_times_s: list[float] = []
        self._kf_filter_xz: list[NDArray[np.float64]] = []
        #: the attitude each keyframe's factors were built with (its prior), oldest first
        self._kf_prior_R: list[NDArray[np.float64]] = []

    # ---- the estimator protocol ----------------------------------------------------------------
    def add_imu(self, step: ImuStep) -> None:
        """One IMU sample: the level-aided sample in shank axes (what the filter used)."""
        if step.shank_but_quat:  # the corrected sample's fields without building it
            t0 = time.perf_counter()
            updates = self._builder.add_imu(step.shank, step.corrected_quat_wxyz)
            if updates:
                self._dispatch(updates, t0)
        else:
            self.feed_imu(step.corrected)

    def add_frame(self, record: FrameRecord) -> None:
        """One depth frame: the filter's estimate, displacement, corner and (if
        ``config.factors.stance_anchors``) stance observations, with the attitude they were
        built with."""
        if record.imu_distrust is not None:
            self._builder.distrust_imu(*record.imu_distrust)
        self.feed_frame(
            record.timestamp_s,
            record.is_keyframe,
            record.estimate,
            record.displacement,
            record.observations(
                self.config.factors.stance_anchors, self.config.factors.height_landmarks
            ),
            record.R_world_imu,
        )

    def finish(self) -> None:
        """Insert a keyframe still waiting for IMU data."""
        self.flush()

    def camera_path(
        self, frame_times_s: NDArray[np.float64], filter_xz_m: NDArray[np.float64]
    ) -> NDArray[np.float64]:
        """See :meth:`frame_trajectory`."""
        return self.frame_trajectory(frame_times_s, filter_xz_m)

    @abstractmethod
    def report(self) -> EstimatorReport: ...

    # ---- ingestion, one input at a time --------------------------------------------------------
    def feed_imu(self, sample: ImuSample) -> None:
        """Feed one IMU sample (timestamps strictly increasing)."""
        t0 = time.perf_counter()
        updates = self._builder.add_imu(sample)
        self._dispatch(updates, t0)

    def feed_frame(
        self,
        timestamp_s: float,
        is_keyframe: bool,
        filter_estimate: FrameEstimate | None,
        displacement: Displacement2D | None,
        observation: FrameObservation | Sequence[FrameObservation] | None,
        R_world_imu: ArrayLike | None = None,
    ) -> None:
        """Feed one depth frame's outputs.

        ``R_world_imu`` (3, 3): the attitude (heading removed) the front end and the filter
        used for this frame; pass it so that the graph maps the world-frame displacement and
        observations with the rotation they were built with (None: the IMU stream's AHRS,
        which differs from it by the filter's attitude processing, see
        ``KeyframeGraphBuilder.add_frame``).

        Non-keyframes only extend the displacement chain (their landmark observations are not
        used). A keyframe becomes a node once IMU data reaches its time; ``filter_estimate`` is
        its initial guess (None: IMU prediction from the previous keyframe).
        """
        t0 = time.perf_counter()
        updates = self._builder.add_frame(
            timestamp_s, is_keyframe, filter_estimate, displacement, observation, R_world_imu
        )
        self._dispatch(updates, t0)

    def flush(self) -> None:
        """Insert a keyframe still waiting for IMU data (the last IMU sample is held)."""
        t0 = time.perf_counter()
        self._dispatch(self._builder.flush(), t0)

    def _dispatch(self, updates: list[KeyframeUpdate], t0: float) -> None:
        if not updates:
            return
        self.build_times_ms.append((time.perf_counter() - t0) * 1e3)
        for u in updates:
            self._kf_times_s.append(u.timestamp_s)
            self._kf_filter_xz.append(u.filter_camera_xz_m)
            self._kf_prior_R.append(np.asarray(u.R_world_imu, dtype=float).reshape(3, 3))
            self._consume(u)

    @abstractmethod
    def _consume(self, update: KeyframeUpdate) -> None: ...

    # ---- outputs -------------------------------------------------------------------------------
    @abstractmethod
    def keyframe_estimates(self, with_covariance: bool = True) -> list[KeyframeEstimate]:
        """Latest refined camera x-z of every keyframe added so far, oldest first."""

    def frame_trajectory(
        self, frame_times_s: ArrayLike, filter_xz_m: ArrayLike
    ) -> NDArray[np.float64]:
        """Per-frame camera x-z (N, 2): filter estimate + smoother correction.

        The correction (refined minus initial-guess camera position) is known at keyframes and
        linearly interpolated in time (held constant before the first / after the last
        keyframe), so all estimators are evaluated on the same frame timestamps.
        """
        t = np.asarray(frame_times_s, dtype=float).reshape(-1)
        f = np.asarray(filter_xz_m, dtype=float).reshape(-1, 2)
        if t.shape[0] != f.shape[0]:
            raise EstimationError(f"{t.shape[0]} frame times but {f.shape[0]} filter positions")
        est = self.keyframe_estimates(with_covariance=False)
        if not est:
            raise EstimationError("no keyframe in the smoother yet")
        kt = np.array([e.timestamp_s for e in est])
        corr = np.array([e.camera_xz_m for e in est]) - np.asarray(self._kf_filter_xz)
        ok = np.all(np.isfinite(corr), axis=1)  # keyframes a failed update never solved
        if not ok.any():
            raise EstimationError("no solved keyframe in the smoother")
        kt, corr = kt[ok], corr[ok]
        return f + np.stack([np.interp(t, kt, corr[:, 0]), np.interp(t, kt, corr[:, 1])], -1)

    def shank_pitch_path(
        self,
        frame_times_s: ArrayLike,
        filter_pitch_rad: ArrayLike,
        pitch_of: Callable[[NDArray[np.float64]], float],
    ) -> NDArray[np.float64]:
        """Per-frame shank pitch (N,) in radians from this smoother's own refined attitude:
        the filter's per-frame pitch plus the smoother's correction.

        ``pitch_of`` maps an IMU attitude R_world_imu (3, 3) to the shank pitch (rad; the
        rig's geometry, e.g. ``RigGeometry.shank_pitch_rad``). At each solved keyframe the
        correction is pitch_of(refined) - pitch_of(prior), the prior being the attitude the
        keyframe's factors were built with (the filter's, level-aided); it is linearly
        interpolated in time between keyframes (held before the first / after the last), as
        the camera correction of :meth:`frame_trajectory` is. The refined attitude carries
        what the filter cannot use at that frame: later keyframes through the gyro, and the
        gravity direction the accelerometer shows once vision fixes the motion.
        """
        t = np.asarray(frame_times_s, dtype=float).reshape(-1)
        p = np.asarray(filter_pitch_rad, dtype=float).reshape(-1)
        if t.shape[0] != p.shape[0]:
            raise EstimationError(f"{t.shape[0]} frame times but {p.shape[0]} filter pitches")
        est = self.keyframe_estimates(with_covariance=False)
        kt, corr = [], []
        for e, R0 in zip(est, self._kf_prior_R, strict=True):
            if e.R_world_imu is None or not np.all(np.isfinite(e.R_world_imu)):
                continue  # a keyframe a failed update never solved
            d = pitch_of(e.R_world_imu) - pitch_of(R0)
            kt.append(e.timestamp_s)
            corr.append(float(np.arctan2(np.sin(d), np.cos(d))))
        if not kt:
            raise EstimationError("no solved keyframe in the smoother")
        return p + np.interp(t, np.asarray(kt), np.asarray(corr))
