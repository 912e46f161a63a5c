"""In-memory tables of a recording's streams (column arrays, one row per sample)."""

from __future__ import annotations

from collections.abc import Iterator
from dataclasses import dataclass

import numpy as np
from numpy.typing import NDArray

from vio_graph.types import ContactSample, ImuSample, JointAngles


@dataclass(frozen=True)
class ImuTable:
    """IMU samples: ``timestamp_s`` (N,), ``accel_mps2`` (N, 3), ``gyro_radps`` (N, 3),
    ``quat_wxyz`` (N, 4) vendor orientation R_world_imu."""

    timestamp_s: NDArray[np.float64]
    accel_mps2: NDArray[np.float64]
    gyro_radps: NDArray[np.float64]
    quat_wxyz: NDArray[np.float64]

    def __len__(self) -> int:
        return int(self.timestamp_s.shape[0])

    def sample(self, i: int) -> ImuSample:
        return ImuSample(
            timestamp_s=float(self.timestamp_s[i]),
            accel_mps2=self.accel_mps2[i].copy(),
            gyro_radps=self.gyro_radps[i].copy(),
            quat_wxyz=self.quat_wxyz[i].copy(),
        )

    def samples(self) -> Iterator[ImuSample]:
        for i in range(len(self)):
            yield self.sample(i)


@dataclass(frozen=True)
class JointTable:
    """Joint angles (rad): thigh IMU pitch (hip flexion), knee and ankle encoders."""

    timestamp_s: NDArray[np.float64]
    thigh_pitch_rad: NDArray[np.float64]
    knee_rad: NDArray[np.float64]
    ankle_rad: NDArray[np.float64]

    def __len__(self) -> int:
        return int(self.timestamp_s.shape[0])

    def sample(self, i: int) -> JointAngles:
        return JointAngles(
            timestamp_s=float(self.timestamp_s[i]),
            thigh_pitch_rad=float(self.thigh_pitch_rad[i]),
            knee_rad=float(self.knee_rad[i]),
            ankle_rad=float(self.ankle_rad[i]),
        )

    def samples(self) -> Iterator[JointAngles]:
        for i in range(len(self)):
            yield self.sample(i)


@dataclass(frozen=True)
class ContactTable:
    """Optional foot-contact stream (contact.csv): ``timestamp_s`` (N,), ``force_n`` (N,)
    load-cell force in N (a switch: 1 closed, 0 open) and ``loaded`` (N,) bool, the force
    at or above the recording's contact threshold."""

    timestamp_s: NDArray[np.float64]
    force_n: NDArray[np.float64]
    loaded: NDArray[np.bool_]

    def __len__(self) -> int:
        return int(self.timestamp_s.shape[0])

    def sample(self, i: int) -> ContactSample:
        return ContactSample(
            float(self.timestamp_s[i]), bool(self.loaded[i]), float(self.force_n[i])
        )


@dataclass(frozen=True)
class Trajectory:
    """A timestamped 3D trajectory: ``timestamp_s`` (N,), ``position_m`` (N, 3),
    ``quat_wxyz`` (N, 4) orientation world <- body."""

    timestamp_s: NDArray[np.float64]
    position_m: NDArray[np.float64]
    quat_wxyz: NDArray[np.float64]

    def __len__(self) -> int:
        return int(self.timestamp_s.shape[0])

    @classmethod
    def from_xz(cls, timestamp_s: NDArray[np.float64], xz_m: NDArray[np.float64]) -> Trajectory:
        """A position-only trajectory in the sagittal plane (y = 0, identity orientation)."""
        xz = np.asarray(xz_m, dtype=float).reshape(-1, 2)
        pos = np.zeros((xz.shape[0], 3))
        pos[:, 0], pos[:, 2] = xz[:, 0], xz[:, 1]
        quat = np.tile([1.0, 0.0, 0.0, 0.0], (xz.shape[0], 1))
        return cls(np.asarray(timestamp_s, dtype=float).copy(), pos, quat)

    @property
    def xz_m(self) -> NDArray[np.float64]:
        return self.position_m[:, [0, 2]]

    def xz_at(self, t_s: float | NDArray[np.float64]) -> NDArray[np.float64]:
        """Position x-z (m) linearly interpolated at ``t_s`` (s; held beyond the ends): (2,)
        for one time, (N, 2) for N times."""
        return np.stack(
            [np.interp(t_s, self.timestamp_s, self.position_m[:, k]) for k in (0, 2)], axis=-1
        )


@dataclass(frozen=True)
class ImuStateTable:
    """True IMU state at the IMU timestamps (simulated recordings only): position, velocity
    and orientation of the IMU frame in the world, and the accelerometer/gyro biases."""

    timestamp_s: NDArray[np.float64]
    position_m: NDArray[np.float64]
    velocity_mps: NDArray[np.float64]
    quat_wxyz: NDArray[np.float64]
    accel_bias_mps2: NDArray[np.float64]
    gyro_bias_radps: NDArray[np.float64]


# Ground-truth trajectories a recording carries, by name (file groundtruth/<name>.tum).
GROUNDTRUTH_BODIES = ("camera", "knee", "ankle", "heel", "toe")


@dataclass(frozen=True)
class GroundTruth:
    """Motion-capture ground truth: one trajectory per body in ``GROUNDTRUTH_BODIES``,
    plus optional simulator-only extras."""

    trajectories: dict[str, Trajectory]
    imu_state: ImuStateTable | None = None
    # per depth frame: 1 if a terrain corner (nosing / obstacle edge) is in the camera's view
    frame_edge_visible: NDArray[np.int8] | None = None
