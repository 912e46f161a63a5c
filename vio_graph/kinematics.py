"""Sagittal forward kinematics of the instrumented leg (paper Section II.D, Fig. 3).

The leg is a serial chain of rotations about +y (see docs/conventions.md):

- thigh segment pitch   = -thigh_pitch_rad            (thigh_pitch_rad = hip flexion, + forward)
- shank segment pitch   = thigh segment pitch + knee_rad      (knee_rad = flexion, +)
- foot segment pitch    = shank segment pitch + ankle_rad     (ankle_rad = plantarflexion, +)

``R_w_shank = rot_y(shank pitch)``. The shank frame has its origin at the knee joint centre and
its z axis pointing from the ankle to the knee; the foot frame has its origin at the ankle, x
along the sole towards the toe, z up when the foot is flat. Works for the able-bodied leg and
for a prosthesis whose foot is a bent link: heel and toe are fixed points in the foot frame.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from numpy.typing import ArrayLike, NDArray

from vio_graph.geometry import rotate_xz


@dataclass(frozen=True)
class LegModel:
    """Link lengths (metres) and foot points of the instrumented leg.

    ``heel_in_foot_xz_m`` / ``toe_in_foot_xz_m``: (x, z) of the heel and toe contact points in
    the foot frame (origin at the ankle joint).
    """

    thigh_length_m: float
    shank_length_m: float
    heel_in_foot_xz_m: tuple[float, float]
    toe_in_foot_xz_m: tuple[float, float]


def shank_pitch_rad(thigh_pitch_rad: ArrayLike, knee_rad: ArrayLike) -> NDArray[np.float64]:
    """Shank segment pitch (rad, + = knee ahead of ankle) from hip flexion and knee flexion."""
    return np.asarray(knee_rad, dtype=float) - np.asarray(thigh_pitch_rad, dtype=float)


@dataclass(frozen=True)
class LegPoints:
    """World (x, z) positions in metres, each (N, 2)."""

    knee_xz_m: NDArray[np.float64]
    ankle_xz_m: NDArray[np.float64]
    heel_xz_m: NDArray[np.float64]
    toe_xz_m: NDArray[np.float64]


def leg_points_from_knee(
    leg: LegModel,
    knee_xz_m: ArrayLike,
    shank_pitch: ArrayLike,
    ankle_rad: ArrayLike,
) -> LegPoints:
    """Ankle, heel and toe from the knee position, shank pitch and ankle angle (eq. of Fig. 3).

    Args:
        knee_xz_m: (N, 2) or (2,) knee joint centre in the world frame, metres.
        shank_pitch: (N,) or scalar shank segment pitch, rad.
        ankle_rad: (N,) or scalar ankle plantarflexion, rad.
    """
    knee = np.atleast_2d(np.asarray(knee_xz_m, dtype=float))
    th_s = np.atleast_1d(np.asarray(shank_pitch, dtype=float))
    th_f = th_s + np.atleast_1d(np.asarray(ankle_rad, dtype=float))
    ankle = knee + rotate_xz(th_s, np.array([0.0, -leg.shank_length_m]))
    heel = ankle + rotate_xz(th_f, np.array(leg.heel_in_foot_xz_m))
    toe = ankle + rotate_xz(th_f, np.array(leg.toe_in_foot_xz_m))
    return LegPoints(knee_xz_m=knee, ankle_xz_m=ankle, heel_xz_m=heel, toe_xz_m=toe)


def knee_from_camera(
    camera_xz_m: ArrayLike, shank_pitch: ArrayLike, camera_in_shank_xz_m: ArrayLike
) -> NDArray[np.float64]:
    """Knee position from the camera optical centre, using the knee <- camera extrinsic.

    ``camera_in_shank_xz_m`` is the camera centre in the shank frame (origin at the knee).
    """
    cam = np.atleast_2d(np.asarray(camera_xz_m, dtype=float))
    th_s = np.atleast_1d(np.asarray(shank_pitch, dtype=float))
    return cam - rotate_xz(th_s, np.asarray(camera_in_shank_xz_m, dtype=float))


def _cos_sin(angle_rad: float) -> tuple[float, float]:
    """cos and sin of one angle as :func:`~vio_graph.geometry.rotate_xz` takes them (numpy's
    ufuncs on a (1,) array, so the same floats as the vectorised chain)."""
    a = np.array([angle_rad], dtype=float)
    return float(np.cos(a)[0]), float(np.sin(a)[0])


def leg_points_single(
    leg: LegModel,
    camera_xz_m: ArrayLike,
    camera_in_shank_xz_m: ArrayLike,
    shank_pitch_imu_rad: float,
    shank_pitch_rad: float,
    ankle_rad: float,
) -> LegPoints:
    """:func:`knee_from_camera` then :func:`leg_points_from_knee` for one pose (the online
    estimator's frame), on Python floats: the same products and sums per axis as the
    vectorised functions, so the same floats (tests/test_kinematics_single.py); each point
    (1, 2). ``shank_pitch_imu_rad`` places the knee from the camera, ``shank_pitch_rad``
    (the IMU's or the encoder chain's) the rest of the leg."""
    cx, cz = (float(v) for v in np.asarray(camera_xz_m, dtype=float).reshape(2))
    ux, uz = (float(v) for v in np.asarray(camera_in_shank_xz_m, dtype=float).reshape(2))
    c, s = _cos_sin(float(shank_pitch_imu_rad))
    kx, kz = cx - (c * ux + s * uz), cz - (-s * ux + c * uz)
    th_s = float(shank_pitch_rad)
    th_f = th_s + float(ankle_rad)
    if th_s != float(shank_pitch_imu_rad):
        c, s = _cos_sin(th_s)
    L = -leg.shank_length_m
    ax, az = kx + (c * 0.0 + s * L), kz + (-s * 0.0 + c * L)
    c, s = _cos_sin(th_f)
    hx, hz = (float(v) for v in leg.heel_in_foot_xz_m)
    tx, tz = (float(v) for v in leg.toe_in_foot_xz_m)
    return LegPoints(
        knee_xz_m=np.array([[kx, kz]]),
        ankle_xz_m=np.array([[ax, az]]),
        heel_xz_m=np.array([[ax + (c * hx + s * hz), az + (-s * hx + c * hz)]]),
        toe_xz_m=np.array([[ax + (c * tx + s * tz), az + (-s * tx + c * tz)]]),
    )
