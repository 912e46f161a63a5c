"""Baselines compared like for like with the SP-ESKF: both follow the estimator protocol
(vio_graph/protocol.py: ``add_imu`` / ``add_frame`` / ``finish`` / ``camera_path``), built on
the filter's surface (``initialise`` / ``propagate`` / ``update_displacement`` / ``state``).

* :class:`ImuDeadReckoning` -- the SP-ESKF propagation (eq. 6-7) and nothing else.
* :class:`IcpOdometry` -- the chain of ICP displacements, no IMU; holds the last position
  while no displacement comes.
"""

from __future__ import annotations

import math

import numpy as np
from numpy.typing import ArrayLike, NDArray

from vio_graph.errors import EstimationError
from vio_graph.filter.config import FilterConfig
from vio_graph.filter.eskf import ERROR_STATE_DIM, FilterState, SagittalEskf
from vio_graph.growable import GrowableArray
from vio_graph.protocol import EstimatorReport, FrameRecord, ImuStep, path_of_frames
from vio_graph.types import Displacement2D, EstimateStatus, ImuSample


def _pair(a: ArrayLike) -> tuple[float, float]:
    """A 2-vector's two values as Python floats (as ``np.asarray(a, float).reshape(2)`` holds
    them; a ValueError if ``a`` does not hold two)."""
    x, z = np.asarray(a, dtype=float).reshape(2).tolist()
    return x, z


class PathKeeper:
    """The protocol half shared by the baselines: start at ``initial_camera_xz_m`` on the first
    IMU sample, keep one camera position per frame."""

    name: str

    def __init__(self, initial_camera_xz_m: ArrayLike | None) -> None:
        self._p0 = (
            np.zeros(2)
            if initial_camera_xz_m is None
            else np.asarray(initial_camera_xz_m, dtype=float)
        )
        self._started = False
        self._path = GrowableArray((2,))  # camera x-z per frame

    def initialise(
        self, timestamp_s: float, p_xz: ArrayLike, v_xz: ArrayLike = (0.0, 0.0), **kwargs: object
    ) -> None:
        raise NotImplementedError

    def propagate(self, imu: ImuSample) -> None:
        raise NotImplementedError

    def update_displacement(self, d: Displacement2D) -> bool:
        raise NotImplementedError

    def add_imu(self, step: ImuStep) -> None:
        """The sample in shank axes as measured (no level-surface pitch offset)."""
        if not self._started:
            self.initialise(step.shank.timestamp_s, self._p0)
            self._started = True
        else:
            self.propagate(step.shank)

    def add_frame(self, record: FrameRecord) -> None:
        if record.displacement is not None:
            self.update_displacement(record.displacement)
        self._path.append(self._camera_at(record.timestamp_s))

    def _camera_at(self, t_s: float) -> NDArray[np.float64]:
        raise NotImplementedError

    def finish(self) -> None:
        pass

    def camera_path(
        self, frame_times_s: NDArray[np.float64], filter_xz_m: NDArray[np.float64]
    ) -> NDArray[np.float64]:
        return path_of_frames(self._path, len(frame_times_s), self.name)

    def report(self) -> EstimatorReport:
        return EstimatorReport()


class ImuDeadReckoning(PathKeeper):
    """IMU-only integration of the camera position: the filter without corrections.

    Displacements are counted as received but never used (``n_rejected`` stays 0;
    ``n_stale`` counts them). Status is always IMU_ONLY after initialisation. Per frame the
    camera position is extrapolated from the last IMU sample to the frame time.
    """

    name = "imu_only"

    def __init__(
        self,
        config: FilterConfig | None = None,
        imu_T_cam: ArrayLike | None = None,
        initial_camera_xz_m: ArrayLike | None = None,
    ):
        super().__init__(initial_camera_xz_m)
        self._eskf = SagittalEskf(config, imu_T_cam)
        self._n_ignored = 0

    def initialise(
        self, timestamp_s: float, p_xz: ArrayLike, v_xz: ArrayLike = (0.0, 0.0), **kwargs: object
    ) -> None:
        """Same arguments as :meth:`SagittalEskf.initialise`."""
        self._eskf.initialise(timestamp_s, p_xz, v_xz, **kwargs)  # type: ignore[arg-type]

    def propagate(self, imu: ImuSample) -> None:
        """Eq. 6-7 propagation to ``imu.timestamp_s``."""
        self._eskf.propagate(imu)

    def update_displacement(self, d: Displacement2D) -> bool:
        """Ignored (dead reckoning); returns False."""
        self._n_ignored += 1
        return False

    def _camera_at(self, t_s: float) -> NDArray[np.float64]:
        # :attr:`state`'s position and velocity without its two snapshots (P and counters
        # copied twice a frame: ~15 us of the replay's per-frame bookkeeping)
        t0_s, p_xz, v_xz = self._eskf.position_velocity()
        return p_xz + v_xz * (t_s - t0_s)

    @property
    def state(self) -> FilterState:
        s = self._eskf.state
        status = (
            EstimateStatus.INITIALISING
            if s.status is EstimateStatus.INITIALISING
            else EstimateStatus.IMU_ONLY
        )
        return FilterState(
            timestamp_s=s.timestamp_s,
            p_xz_m=s.p_xz_m,
            v_xz_mps=s.v_xz_mps,
            accel_bias_xz_mps2=s.accel_bias_xz_mps2,
            gravity_xz_mps2=s.gravity_xz_mps2,
            P=s.P,
            status=status,
            n_imu=s.n_imu,
            n_stale=self._n_ignored,
        )


class IcpOdometry(PathKeeper):
    """Camera position as the running sum of ICP displacements (no IMU).

    The position covariance is the sum of the displacement covariances; the velocity is the
    last displacement divided by its duration. ``propagate`` only advances the clock.
    Displacements are chained whatever their ``t0_s``: motion during a gap without
    displacements is lost (the odometry has nothing to bridge it with).
    """

    name = "icp_only"

    def __init__(self, fused_timeout_s: float = 0.1, initial_camera_xz_m: ArrayLike | None = None):
        super().__init__(initial_camera_xz_m)
        self._fused_timeout_s = float(fused_timeout_s)
        self._initialised = False
        self._t_s = 0.0
        # position, velocity and the covariance's four entries as Python floats: the same
        # sums and quotients as on (2,) and (2, 2) arrays, element by element (IEEE), without
        # ~15 us of small-array calls per frame
        self._p = (0.0, 0.0)
        self._v = (0.0, 0.0)
        self._cov = (0.0, 0.0, 0.0, 0.0)
        self._last_t1_s = -np.inf
        self._n_imu = 0
        self._n_acc = 0

    def initialise(
        self, timestamp_s: float, p_xz: ArrayLike, v_xz: ArrayLike = (0.0, 0.0), **_: object
    ) -> None:
        """Start at camera position ``p_xz`` (m) at ``timestamp_s`` (s)."""
        self._t_s = float(timestamp_s)
        self._p = _pair(p_xz)
        self._v = _pair(v_xz)
        self._cov = (0.0, 0.0, 0.0, 0.0)
        self._last_t1_s = self._t_s
        self._initialised = True

    def propagate(self, imu: ImuSample) -> None:
        """Advance the clock only (the position is held)."""
        if not self._initialised:
            raise EstimationError("propagate() called before initialise()")
        self._t_s = max(self._t_s, float(imu.timestamp_s))
        self._n_imu += 1

    def update_displacement(self, d: Displacement2D) -> bool:
        """Add ``d.delta_xz_m`` to the position; always accepted."""
        if not self._initialised:
            raise EstimationError("update_displacement() called before initialise()")
        dx, dz = _pair(d.delta_xz_m)
        if not (math.isfinite(dx) and math.isfinite(dz)):
            raise EstimationError("displacement holds NaN or inf")
        px, pz = self._p
        self._p = (px + dx, pz + dz)
        c00, c01, c10, c11 = np.asarray(d.cov_m2, dtype=float).reshape(4).tolist()
        a00, a01, a10, a11 = self._cov
        self._cov = (a00 + c00, a01 + c01, a10 + c10, a11 + c11)
        dur = float(d.t1_s) - float(d.t0_s)
        self._v = (dx / dur, dz / dur) if dur > 0 else self._v
        self._last_t1_s = float(d.t1_s)
        self._t_s = max(self._t_s, self._last_t1_s)
        self._n_acc += 1
        return True

    def _camera_at(self, t_s: float) -> NDArray[np.float64]:
        return np.array(self._p)  # :attr:`state`'s position, without building the snapshot

    @property
    def state(self) -> FilterState:
        if not self._initialised:
            status = EstimateStatus.INITIALISING
        elif self._t_s - self._last_t1_s <= self._fused_timeout_s:
            status = EstimateStatus.FUSED
        else:
            status = EstimateStatus.IMU_ONLY
        P = np.zeros((ERROR_STATE_DIM, ERROR_STATE_DIM))
        P[:2, :2] = np.reshape(self._cov, (2, 2))
        return FilterState(
            timestamp_s=self._t_s,
            p_xz_m=np.array(self._p),
            v_xz_mps=np.array(self._v),
            accel_bias_xz_mps2=np.zeros(2),
            gravity_xz_mps2=np.zeros(2),
            P=P,
            status=status,
            n_imu=self._n_imu,
            n_accepted=self._n_acc,
        )
