"""Rotation and frame helpers (pure numpy).

Frames (see docs/conventions.md):
- world ``W``: x forward (walking direction), y left, z up; gravity is -z.
- shank/IMU body ``S``: z along the shank from ankle to knee, x anterior, y left.
- camera ``C``: optical convention, x right, y down, z along the optical axis.

A rotation ``R_a_b`` (3x3) maps vectors expressed in frame b into frame a; a transform
``a_T_b`` (4x4) maps points in b into a. Sagittal angles are rotations about +y.
"""

from __future__ import annotations

import numpy as np
from numpy.typing import ArrayLike, NDArray

GRAVITY_MPS2 = 9.81


def rot_y(angle_rad: float | NDArray[np.float64]) -> NDArray[np.float64]:
    """Rotation about +y by ``angle_rad``; vectorised: (N,) angles -> (N, 3, 3).

    A positive angle tilts the body's +z axis towards world +x (for the shank: knee ahead of
    ankle) and its +x axis towards world -z.
    """
    a = np.asarray(angle_rad, dtype=float)
    c, s = np.cos(a), np.sin(a)
    if a.ndim == 0:  # one angle: the same values without the stacking (~10x cheaper)
        c, s = float(c), float(s)
        return np.array([[c, 0.0, s], [0.0, 1.0, 0.0], [-s, 0.0, c]])
    zero, one = np.zeros_like(a), np.ones_like(a)
    m = np.stack(
        [np.stack([c, zero, s], -1), np.stack([zero, one, zero], -1), np.stack([-s, zero, c], -1)],
        -2,
    )
    return m


def rot_x(angle_rad: float) -> NDArray[np.float64]:
    """Rotation about +x by ``angle_rad`` (3x3)."""
    c, s = np.cos(angle_rad), np.sin(angle_rad)
    return np.array([[1.0, 0.0, 0.0], [0.0, c, -s], [0.0, s, c]])


def rot_z(angle_rad: float) -> NDArray[np.float64]:
    """Rotation about +z by ``angle_rad`` (3x3)."""
    c, s = np.cos(angle_rad), np.sin(angle_rad)
    return np.array([[c, -s, 0.0], [s, c, 0.0], [0.0, 0.0, 1.0]])


def rot_y_xz(angle_rad: float) -> NDArray[np.float64]:
    """SO(2) rotation (2x2) of rot_y(``angle_rad``) restricted to the x-z plane:
    [[cos, sin], [-sin, cos]], mapping body (x, z) to (c x + s z, -s x + c z)."""
    c, s = np.cos(angle_rad), np.sin(angle_rad)
    return np.array([[c, s], [-s, c]])


def rotate_xz(angle_rad: ArrayLike, xz: ArrayLike) -> NDArray[np.float64]:
    """Rotate body-frame (x, z) vectors by rot_y(``angle_rad``), written out element-wise
    (vectorised: (N,) angles and/or (..., 2) vectors); returns (..., 2) world (x, z)."""
    v = np.asarray(xz, dtype=float)
    c, s = np.cos(angle_rad), np.sin(angle_rad)
    x = c * v[..., 0] + s * v[..., 1]
    z = -s * v[..., 0] + c * v[..., 1]
    return np.stack([x, z], axis=-1)


def pitch_of(R_w_b: ArrayLike) -> NDArray[np.float64] | float:
    """Sagittal pitch (rotation about +y, rad) of a rotation or a stack of rotations.

    Inverse of :func:`rot_y` for pure pitch; for general rotations it is the pitch of the
    body's z axis projected into the x-z plane.
    """
    R = np.asarray(R_w_b, dtype=float)
    return np.arctan2(R[..., 0, 2], R[..., 2, 2])


def quat_wxyz_from_matrix(R: ArrayLike) -> NDArray[np.float64]:
    """Unit quaternion(s) [w, x, y, z] with w >= 0 from rotation matrix(ces) (..., 3, 3)."""
    R = np.asarray(R, dtype=float)
    flat = R.reshape(-1, 3, 3)
    q = np.empty((flat.shape[0], 4))
    tr = np.trace(flat, axis1=1, axis2=2)
    for i, m in enumerate(flat):  # small arrays only (trajectories); clarity over speed
        if tr[i] > 0:
            s = 2.0 * np.sqrt(tr[i] + 1.0)
            q[i] = [
                0.25 * s,
                (m[2, 1] - m[1, 2]) / s,
                (m[0, 2] - m[2, 0]) / s,
                (m[1, 0] - m[0, 1]) / s,
            ]
        elif m[0, 0] > m[1, 1] and m[0, 0] > m[2, 2]:
            s = 2.0 * np.sqrt(1.0 + m[0, 0] - m[1, 1] - m[2, 2])
            q[i] = [
                (m[2, 1] - m[1, 2]) / s,
                0.25 * s,
                (m[0, 1] + m[1, 0]) / s,
                (m[0, 2] + m[2, 0]) / s,
            ]
        elif m[1, 1] > m[2, 2]:
            s = 2.0 * np.sqrt(1.0 + m[1, 1] - m[0, 0] - m[2, 2])
            q[i] = [
                (m[0, 2] - m[2, 0]) / s,
                (m[0, 1] + m[1, 0]) / s,
                0.25 * s,
                (m[1, 2] + m[2, 1]) / s,
            ]
        else:
            s = 2.0 * np.sqrt(1.0 + m[2, 2] - m[0, 0] - m[1, 1])
            q[i] = [
                (m[1, 0] - m[0, 1]) / s,
                (m[0, 2] + m[2, 0]) / s,
                (m[1, 2] + m[2, 1]) / s,
                0.25 * s,
            ]
    q[q[:, 0] < 0] *= -1.0
    q /= np.linalg.norm(q, axis=1, keepdims=True)
    return q.reshape(R.shape[:-2] + (4,))


def matrix_from_quat_wxyz(q: ArrayLike) -> NDArray[np.float64]:
    """Rotation matrix(ces) (..., 3, 3) from quaternion(s) [w, x, y, z] (normalised here)."""
    qa = np.asarray(q, dtype=float)
    qa = qa / np.linalg.norm(qa, axis=-1, keepdims=True)
    w, x, y, z = qa[..., 0], qa[..., 1], qa[..., 2], qa[..., 3]
    return np.stack(
        [
            np.stack([1 - 2 * (y * y + z * z), 2 * (x * y - w * z), 2 * (x * z + w * y)], -1),
            np.stack([2 * (x * y + w * z), 1 - 2 * (x * x + z * z), 2 * (y * z - w * x)], -1),
            np.stack([2 * (x * z - w * y), 2 * (y * z + w * x), 1 - 2 * (x * x + y * y)], -1),
        ],
        -2,
    )


def remove_yaw(R_w_b: ArrayLike) -> NDArray[np.float64]:
    """Return the rotation with its heading (yaw about world z) removed, keeping roll and pitch.

    Used to build the gravity-aligned "ground" frame of the paper's eq. 2 without trusting the
    AHRS heading (2 deg RMS on an MTi-1) and assuming walking along world +x.

    A ZYX decomposition is ambiguous once the segment pitches past 90 deg ((yaw, pitch, roll)
    and (yaw + pi, pi - pitch, roll + pi) are the same rotation). A shank or knee segment
    moves in the sagittal plane with small roll, so of the two headings we remove the one that
    leaves the smaller roll.
    """
    R = np.asarray(R_w_b, dtype=float)
    yaw = np.arctan2(R[..., 1, 0], R[..., 0, 0])

    def _unyaw(angle: NDArray[np.float64]) -> NDArray[np.float64]:
        c, s = np.cos(-angle), np.sin(-angle)
        Rz = np.zeros(R.shape)
        Rz[..., 0, 0], Rz[..., 0, 1], Rz[..., 1, 0], Rz[..., 1, 1] = c, -s, s, c
        Rz[..., 2, 2] = 1.0
        return Rz @ R

    a, b = _unyaw(yaw), _unyaw(yaw + np.pi)
    pick_b = (b[..., 1, 1] > a[..., 1, 1])[..., None, None]
    return np.where(pick_b, b, a)


def make_transform(R: ArrayLike, t: ArrayLike) -> NDArray[np.float64]:
    """4x4 homogeneous transform from a 3x3 rotation and a translation (3,)."""
    T = np.eye(4)
    T[:3, :3] = np.asarray(R, dtype=float)
    T[:3, 3] = np.asarray(t, dtype=float)
    return T


def invert_transform(T: ArrayLike) -> NDArray[np.float64]:
    """Inverse of a 4x4 rigid transform."""
    T = np.asarray(T, dtype=float)
    R, t = T[:3, :3], T[:3, 3]
    return make_transform(R.T, -R.T @ t)


def skew(v: ArrayLike) -> NDArray[np.float64]:
    """Skew-symmetric matrix of a 3-vector: skew(a) @ b == cross(a, b)."""
    x, y, z = np.asarray(v, dtype=float)
    return np.array([[0.0, -z, y], [z, 0.0, -x], [-y, x, 0.0]])


def cross3(a: NDArray[np.float64], b: NDArray[np.float64]) -> NDArray[np.float64]:
    """a x b for 3-vectors, written out: np.cross costs ~80 us per call (argument checks and
    axis moves), this ~4 us, and the filter and the stance detector call it several times per
    IMU sample. Same result bit for bit (the same products and differences)."""
    return np.array(
        [a[1] * b[2] - a[2] * b[1], a[2] * b[0] - a[0] * b[2], a[0] * b[1] - a[1] * b[0]]
    )
