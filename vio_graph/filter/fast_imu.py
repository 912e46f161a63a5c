"""Scalar closed forms for the per-IMU-sample hot path (no numpy per-call overhead).

Every function here has a numpy reference that stays the documented definition and is what
the tests compare against (tests/test_fast_imu.py, to 1e-12):

===============================  ==========================================================
here                             reference
===============================  ==========================================================
:func:`quat_matrix`              ``geometry.matrix_from_quat_wxyz``
:func:`sagittal_rotation_fast`   ``filter.eskf.sagittal_rotation`` (remove_yaw, pitch_of)
:func:`rotvec_matrix`            ``scipy Rotation.from_rotvec(v).as_matrix()``
:func:`matrix_rotvec`            ``scipy Rotation.from_matrix(R).as_rotvec()``
:func:`pitch_offset_quat`        ``quat_wxyz_from_matrix(with_pitch_offset(R(q), b))``
:func:`mat3_quat`                ``geometry.quat_wxyz_from_matrix`` (same operations: equal
                                 bit for bit)
===============================  ==========================================================

A sample costs a few microseconds this way instead of the ~100 us of small-array numpy
calls (docs/performance.md, "IMU propagation"). Angles in radians, quaternions [w, x, y, z].
"""

from __future__ import annotations

import math
from types import ModuleType

import numpy as np
from numpy.typing import ArrayLike, NDArray

Mat3 = tuple[float, float, float, float, float, float, float, float, float]  # row-major


def quat_matrix(q: ArrayLike) -> Mat3:
    """Row-major rotation matrix of quaternion ``q`` = [w, x, y, z] (normalised here)."""
    w, x, y, z = np.asarray(q, dtype=float).tolist()
    n = math.sqrt(w * w + x * x + y * y + z * z)
    w, x, y, z = w / n, x / n, y / n, z / n
    return (
        1 - 2 * (y * y + z * z),
        2 * (x * y - w * z),
        2 * (x * z + w * y),
        2 * (x * y + w * z),
        1 - 2 * (x * x + z * z),
        2 * (y * z - w * x),
        2 * (x * z - w * y),
        2 * (y * z + w * x),
        1 - 2 * (x * x + y * y),
    )


def _heading(m: Mat3) -> tuple[float, float, float]:
    """(cos, sin) of the heading that ``geometry.remove_yaw`` removes, and the sign (+1 or -1)
    of the (yaw or yaw + pi) branch it picks (the one leaving the larger R[1, 1])."""
    yaw = math.atan2(m[3], m[0])
    c, s = math.cos(yaw), math.sin(yaw)
    a11 = -s * m[1] + c * m[4]  # (rot_z(-yaw) R)[1, 1]; the yaw + pi branch gives -a11
    return c, s, (-1.0 if -a11 > a11 else 1.0)


def sagittal_pitch(q: ArrayLike) -> float:
    """Pitch (rad) of eq. 5's sagittal rotation for vendor orientation ``q`` (see
    ``filter.eskf.sagittal_rotation``: heading removed, flipped ZYX solution turned back)."""
    w, x, y, z = np.asarray(q, dtype=float).tolist()
    n = math.sqrt(w * w + x * x + y * y + z * z)
    w, x, y, z = w / n, x / n, y / n, z / n
    # the entries of quat_matrix that the pitch needs
    m0, m1, m2 = 1 - 2 * (y * y + z * z), 2 * (x * y - w * z), 2 * (x * z + w * y)
    m3, m4, m5 = 2 * (x * y + w * z), 1 - 2 * (x * x + z * z), 2 * (y * z - w * x)
    m8 = 1 - 2 * (x * x + y * y)
    yaw = math.atan2(m3, m0)
    c, s = math.cos(yaw), math.sin(yaw)
    a11 = -s * m1 + c * m4  # (rot_z(-yaw) R)[1, 1]; the yaw + pi branch gives -a11
    g02 = c * m2 + s * m5  # row 0 of the yaw-free rotation, column 2
    if -a11 > a11:  # remove_yaw picks the yaw + pi branch: rows 0 and 1 change sign, and
        g02 = -g02  # then R[1, 1] > 0, so sagittal_rotation's flip does not apply
    return math.atan2(g02, m8)


def sagittal_rotation_fast(q: ArrayLike) -> NDArray[np.float64]:
    """(2, 2) [[cos, sin], [-sin, cos]] of :func:`sagittal_pitch`; equals
    ``filter.eskf.sagittal_rotation(q)`` to rounding."""
    p = sagittal_pitch(q)
    c, s = math.cos(p), math.sin(p)
    return np.array([[c, s], [-s, c]])


def rotvec_mat3(wx: float, wy: float, wz: float) -> Mat3:
    """Rodrigues' formula for one rotation vector (rad) -> row-major 3x3 tuple."""
    th2 = wx * wx + wy * wy + wz * wz
    if th2 < 1e-12:  # Taylor to third order; error < 1e-18 below 1e-6 rad
        a = 1.0 - th2 / 6.0
        b = 0.5 - th2 / 24.0
    else:
        th = math.sqrt(th2)
        a = math.sin(th) / th
        b = (1.0 - math.cos(th)) / th2
    xx, yy, zz = wx * wx, wy * wy, wz * wz
    xy, xz, yz = wx * wy, wx * wz, wy * wz
    return (
        1.0 - b * (yy + zz),
        b * xy - a * wz,
        b * xz + a * wy,
        b * xy + a * wz,
        1.0 - b * (xx + zz),
        b * yz - a * wx,
        b * xz - a * wy,
        b * yz + a * wx,
        1.0 - b * (xx + yy),
    )


def rotvec_matrix(wx: float, wy: float, wz: float) -> NDArray[np.float64]:
    """:func:`rotvec_mat3` as a (3, 3) array."""
    return np.array(rotvec_mat3(wx, wy, wz)).reshape(3, 3)


def mat3_mul(a: Mat3, b: Mat3) -> Mat3:
    """a @ b for row-major 3x3 tuples."""
    a0, a1, a2, a3, a4, a5, a6, a7, a8 = a
    b0, b1, b2, b3, b4, b5, b6, b7, b8 = b
    return (
        a0 * b0 + a1 * b3 + a2 * b6,
        a0 * b1 + a1 * b4 + a2 * b7,
        a0 * b2 + a1 * b5 + a2 * b8,
        a3 * b0 + a4 * b3 + a5 * b6,
        a3 * b1 + a4 * b4 + a5 * b7,
        a3 * b2 + a4 * b5 + a5 * b8,
        a6 * b0 + a7 * b3 + a8 * b6,
        a6 * b1 + a7 * b4 + a8 * b7,
        a6 * b2 + a7 * b5 + a8 * b8,
    )


def mat3_tmul(a: Mat3, b: Mat3) -> Mat3:
    """a^T @ b for row-major 3x3 tuples."""
    a0, a1, a2, a3, a4, a5, a6, a7, a8 = a
    return mat3_mul((a0, a3, a6, a1, a4, a7, a2, a5, a8), b)


def mat3_rotvec(m: Mat3) -> tuple[float, float, float]:
    """Rotation vector (rad) of a row-major rotation: quaternion by Shepperd's method (largest
    of w, x, y, z first), w >= 0, then 2 atan2(|v|, w) v / |v|."""
    m00, m01, m02, m10, m11, m12, m20, m21, m22 = m
    tr = m00 + m11 + m22
    if tr >= m00 and tr >= m11 and tr >= m22:
        w = 0.5 * math.sqrt(max(0.0, 1.0 + tr))
        f = 0.25 / w
        x, y, z = (m21 - m12) * f, (m02 - m20) * f, (m10 - m01) * f
    elif m00 >= m11 and m00 >= m22:
        x = 0.5 * math.sqrt(max(0.0, 1.0 + m00 - m11 - m22))
        f = 0.25 / x
        w, y, z = (m21 - m12) * f, (m01 + m10) * f, (m02 + m20) * f
    elif m11 >= m22:
        y = 0.5 * math.sqrt(max(0.0, 1.0 - m00 + m11 - m22))
        f = 0.25 / y
        w, x, z = (m02 - m20) * f, (m01 + m10) * f, (m12 + m21) * f
    else:
        z = 0.5 * math.sqrt(max(0.0, 1.0 - m00 - m11 + m22))
        f = 0.25 / z
        w, x, y = (m10 - m01) * f, (m02 + m20) * f, (m12 + m21) * f
    if w < 0.0:
        w, x, y, z = -w, -x, -y, -z
    n = math.sqrt(w * w + x * x + y * y + z * z)
    w, x, y, z = w / n, x / n, y / n, z / n
    v = math.sqrt(x * x + y * y + z * z)
    if v < 1e-12:
        k = 2.0 / w  # angle / |v| -> 2 / w
    else:
        k = 2.0 * math.atan2(v, w) / v
    return k * x, k * y, k * z


def matrix_rotvec(R: NDArray[np.float64]) -> tuple[float, float, float]:
    """:func:`mat3_rotvec` of a (3, 3) array."""
    return mat3_rotvec(tuple(np.asarray(R, dtype=float).ravel().tolist()))


def remove_yaw_mat3(m: Mat3) -> Mat3:
    """``geometry.remove_yaw`` of one row-major rotation: rot_z(-yaw') @ R with yaw' the
    heading or heading + pi, whichever leaves the larger R[1, 1]."""
    c, s, sign = _heading(m)
    c, s = sign * c, sign * s  # rot_z(-(yaw + pi)) = -rot_z(-yaw) on the x-y rows
    m0, m1, m2, m3, m4, m5, m6, m7, m8 = m
    return (
        c * m0 + s * m3,
        c * m1 + s * m4,
        c * m2 + s * m5,
        -s * m0 + c * m3,
        -s * m1 + c * m4,
        -s * m2 + c * m5,
        m6,
        m7,
        m8,
    )


def rot_y_mat3(angle_rad: float) -> Mat3:
    """``geometry.rot_y`` of one angle (rad), row-major."""
    c, s = math.cos(angle_rad), math.sin(angle_rad)
    return (c, 0.0, s, 0.0, 1.0, 0.0, -s, 0.0, c)


def pitch_offset_quat(q: ArrayLike, offset_rad: float) -> NDArray[np.float64]:
    """Quaternion [w, x, y, z] (w >= 0) of ``attitude.with_pitch_offset(R(q), offset_rad)``:
    R(q) turned by ``offset_rad`` about the lateral axis of its own ground frame, i.e. about
    the world axis rot_z(yaw') e_y with yaw' the heading ``remove_yaw`` removes."""
    w, x, y, z = np.asarray(q, dtype=float).tolist()
    n = math.sqrt(w * w + x * x + y * y + z * z)
    w, x, y, z = w / n, x / n, y / n, z / n
    c, s, sign = _heading(quat_matrix((w, x, y, z)))
    ux, uy = -sign * s, sign * c  # rot_z(yaw') e_y, yaw' = yaw or yaw + pi
    h = 0.5 * offset_rad
    cw, sw = math.cos(h), math.sin(h)
    aw, ax, ay = cw, sw * ux, sw * uy  # az = 0
    # Hamilton product (aw, ax, ay, 0) (x) (w, x, y, z)
    rw = aw * w - ax * x - ay * y
    rx = aw * x + ax * w + ay * z
    ry = aw * y + ay * w - ax * z
    rz = aw * z + ax * y - ay * x
    if rw < 0.0:
        rw, rx, ry, rz = -rw, -rx, -ry, -rz
    return np.array([rw, rx, ry, rz])


def mat3_quat(m: Mat3) -> NDArray[np.float64]:
    """Unit quaternion [w, x, y, z] (w >= 0) of a row-major rotation: the operations of
    ``geometry.quat_wxyz_from_matrix`` in the same order, on Python floats (the same result bit
    for bit, without its per-call numpy overhead)."""
    m00, m01, m02, m10, m11, m12, m20, m21, m22 = m
    tr = m00 + m11 + m22
    if tr > 0:
        s = 2.0 * math.sqrt(tr + 1.0)
        w, x, y, z = 0.25 * s, (m21 - m12) / s, (m02 - m20) / s, (m10 - m01) / s
    elif m00 > m11 and m00 > m22:
        s = 2.0 * math.sqrt(1.0 + m00 - m11 - m22)
        w, x, y, z = (m21 - m12) / s, 0.25 * s, (m01 + m10) / s, (m02 + m20) / s
    elif m11 > m22:
        s = 2.0 * math.sqrt(1.0 + m11 - m00 - m22)
        w, x, y, z = (m02 - m20) / s, (m01 + m10) / s, 0.25 * s, (m12 + m21) / s
    else:
        s = 2.0 * math.sqrt(1.0 + m22 - m00 - m11)
        w, x, y, z = (m10 - m01) / s, (m02 + m20) / s, (m12 + m21) / s, 0.25 * s
    if w < 0:
        w, x, y, z = -w, -x, -y, -z
    n = math.sqrt(w * w + x * x + y * y + z * z)
    return np.array([w / n, x / n, y / n, z / n])


_F64 = np.dtype(np.float64)


def as_f64(a: ArrayLike) -> NDArray[np.float64]:
    """``np.asarray(a, dtype=np.float64)``, returning a float64 array itself without numpy's
    own checks (~0.5 us a call, several times an IMU sample on the compiled path)."""
    if a.__class__ is np.ndarray and a.dtype is _F64:
        return a
    return np.asarray(a, dtype=np.float64)


#: [False] keeps the per-sample path in Python even when the compiled front end is on (the
#: benchmarks time both; benchmarks/bench_frontend.py)
USE_COMPILED = [True]


def imu_kernels() -> ModuleType | None:
    """The compiled kernels of this path (``vio_graph.filter.compiled_imu``, numba), or None.

    On exactly when the compiled front end is (``frontend.icp.compiled_kernels``: numba
    installed, and ``VIO_GRAPH_COMPILED=1``, or unset on a recording long enough to win back
    numba's start-up) and :data:`USE_COMPILED` says so. Decided once per filter / tracker /
    detector / clock model / fault monitor / smoother graph builder, when it is built."""
    from vio_graph.frontend.icp import compiled_kernels

    if not USE_COMPILED[0] or compiled_kernels() is None:
        return None
    from vio_graph.filter import compiled_imu

    return compiled_imu
