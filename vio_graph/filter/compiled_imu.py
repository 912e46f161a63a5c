"""Compiled per-IMU-sample kernels (numba): the scalar closed forms of filter/fast_imu.py and
of the SP-ESKF propagation, attitude tracker and stance detector in one machine-code call
each, without the Python interpreter's cost per float operation.

Same arithmetic, in the same order, as the scalar Python path (``SagittalEskf.propagate``,
``AttitudeTracker.add``, ``OnlineEstimator._with_tracked_attitude``,
``StanceDetector.add_imu``), with one exception: the covariance product F_x P F_x^T is
computed in place on the rows and columns F_x touches (the first four) instead of two dense
products, so its last bits differ from numpy's matrix products. The numpy references stay
the tested definition (tests/test_fast_imu.py: a whole replay with these kernels equals the
numpy reference path to 1e-9 m).

Which path runs is decided with the compiled front end (``frontend.icp.compiled_kernels``,
``VIO_GRAPH_COMPILED``): numba and the cached kernels cost a process ~1-2 s once, which only
a long recording wins back. Imported only through :func:`imu_kernels`.

Angles in radians, quaternions [w, x, y, z], row-major 3x3 tuples.
"""

from __future__ import annotations

import math

import numba
import numpy as np

from vio_graph.compiled_sums import add_reduce

# eskf_propagate's memory of the previous sample (``SagittalEskf._mem``)
MEM_HAS_PREV = 0  # 1.0 once a sample was propagated since initialise()
MEM_T = 1  # its time (s)
MEM_RC, MEM_RS = 2, 3  # its sagittal rotation [[rc, rs], [-rs, rc]]
MEM_FX, MEM_FZ = 4, 5  # its specific force at the camera (x, z), no tangential term
MEM_GYRO = 6  # 6:9 its gyro (rad/s)
MEM_PREV_XA = 9  # its extra accelerometer sigma (m/s^2)
MEM_AW = 10  # 10:12 the last ground-frame acceleration (m/s^2)
MEM_SIZE = 12


@numba.njit(cache=True)
def _quat_matrix(w, x, y, z):
    """fast_imu.quat_matrix."""
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


@numba.njit(cache=True)
def sagittal_pitch(w, x, y, z):
    """fast_imu.sagittal_pitch of the quaternion (w, x, y, z)."""
    n = math.sqrt(w * w + x * x + y * y + z * z)
    w, x, y, z = w / n, x / n, y / n, z / n
    m0, m1, m2 = 1 - 2 * (y * y + z * z), 2 * (x * y - w * z), 2 * (x * z + w * y)
    m3, m4, m5 = 2 * (x * y + w * z), 1 - 2 * (x * x + z * z), 2 * (y * z - w * x)
    m8 = 1 - 2 * (x * x + y * y)
    yaw = math.atan2(m3, m0)
    c, s = math.cos(yaw), math.sin(yaw)
    a11 = -s * m1 + c * m4
    g02 = c * m2 + s * m5
    if -a11 > a11:
        g02 = -g02
    return math.atan2(g02, m8)


@numba.njit(cache=True)
def _rotvec_mat3(wx, wy, wz):
    """fast_imu.rotvec_mat3."""
    th2 = wx * wx + wy * wy + wz * wz
    if th2 < 1e-12:
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


@numba.njit(cache=True)
def _mat3_mul(a, b):
    """fast_imu.mat3_mul."""
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


@numba.njit(cache=True)
def _mat3_rotvec(m):
    """fast_imu.mat3_rotvec (Shepperd's method, w >= 0)."""
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
        k = 2.0 / w
    else:
        k = 2.0 * math.atan2(v, w) / v
    return k * x, k * y, k * z


@numba.njit(cache=True)
def attitude_step(R, p, g, q, dt, k, k_pitch):
    """``AttitudeTracker.add``'s complementary step: R_world_imu (row-major 9-tuple) turned by
    the mid-point gyro rate over ``dt`` (previous rate ``p``, new ``g``, rad/s), then pulled by
    ``k`` of the remaining rotation towards the vendor orientation ``q`` about the x and z
    axes and by ``k_pitch`` about the y (pitch) axis."""
    R = _mat3_mul(
        R,
        _rotvec_mat3(0.5 * (p[0] + g[0]) * dt, 0.5 * (p[1] + g[1]) * dt, 0.5 * (p[2] + g[2]) * dt),
    )
    V = _quat_matrix(q[0], q[1], q[2], q[3])
    # mat3_tmul(R, V) = R^T V
    RT = (R[0], R[3], R[6], R[1], R[4], R[7], R[2], R[5], R[8])
    ex, ey, ez = _mat3_rotvec(_mat3_mul(RT, V))
    return _mat3_mul(R, _rotvec_mat3(k * ex, k_pitch * ey, k * ez))


@numba.njit(cache=True)
def tracked_quat(R, g, dt, offset_rad):
    """``OnlineEstimator._with_tracked_attitude``'s quaternion: R_world_imu (9-tuple) extrapolated
    by the gyro ``g`` over ``dt`` (s), heading removed (``remove_yaw_mat3``), turned by
    ``rot_y(offset_rad)`` if the offset is not 0, as a unit quaternion with w >= 0
    (``fast_imu.mat3_quat``)."""
    m = _mat3_mul(R, _rotvec_mat3(g[0] * dt, g[1] * dt, g[2] * dt))
    yaw = math.atan2(m[3], m[0])
    c, s = math.cos(yaw), math.sin(yaw)
    a11 = -s * m[1] + c * m[4]
    if -a11 > a11:
        c, s = -c, -s
    m0, m1, m2, m3, m4, m5, m6, m7, m8 = m
    G = (
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
    if offset_rad != 0.0:
        cb, sb = math.cos(offset_rad), math.sin(offset_rad)
        G = _mat3_mul((cb, 0.0, sb, 0.0, 1.0, 0.0, -sb, 0.0, cb), G)
    m00, m01, m02, m10, m11, m12, m20, m21, m22 = G
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
    return w / n, x / n, y / n, z / n


@numba.njit(cache=True)
def stance_ankle_accel(t, prev, f, g, q, r, gravity_xz):
    """``StanceDetector.add_imu``'s |a_ankle| (m/s^2) with the sagittal rotation of ``q`` (4,):
    lever-arm terms of ``r`` (3,, ankle in the IMU frame, m) with the angular acceleration
    differenced from the previous sample ``prev`` = [has, t, gx, gy, gz] (none if it is not
    older than t); ``prev`` becomes this sample."""
    gx, gy, gz = g[0], g[1], g[2]
    fx, fz = f[0], f[2]
    if prev[0] > 0.0 and t > prev[1]:
        h = t - prev[1]
        alx, aly, alz = (gx - prev[2]) / h, (gy - prev[3]) / h, (gz - prev[4]) / h
    else:
        alx = aly = alz = 0.0
    prev[0], prev[1], prev[2], prev[3], prev[4] = 1.0, t, gx, gy, gz
    rx, ry, rz = r[0], r[1], r[2]
    cx, cy, cz = gy * rz - gz * ry, gz * rx - gx * rz, gx * ry - gy * rx
    fx = fx + (aly * rz - alz * ry) + (gy * cz - gz * cy)
    fz = fz + (alx * ry - aly * rx) + (gx * cy - gy * cx)
    p = sagittal_pitch(q[0], q[1], q[2], q[3])
    c, s = math.cos(p), math.sin(p)
    r00, r01, r10, r11 = c, s, -s, c
    return math.hypot(r00 * fx + r01 * fz + gravity_xz[0], r10 * fx + r11 * fz + gravity_xz[1])


@numba.njit(cache=True)
def eskf_propagate(
    x, P, mem, t, dt, f, g, q, r, lever, trapezoid, accel_sigma, xa_now, attitude_sigma, var_ab_rate
):
    """``SagittalEskf.propagate`` (eq. 6-7) on the nominal state ``x`` (8,), the covariance
    ``P`` (n, n, changed in place) and the previous sample's memory ``mem`` (MEM_* slots):
    specific force ``f`` (3,) and gyro ``g`` (3,) in IMU axes, vendor orientation ``q`` (4,),
    lever arm ``r`` (3,, camera in the IMU frame, m) applied if ``lever``. Returns 1 if the
    state moved, 0 if ``dt`` <= 0 (only the memory is updated then), -1 (nothing changed) if
    the sample holds NaN or inf."""
    ax, ay, az = f[0], f[1], f[2]
    gx, gy, gz = g[0], g[1], g[2]
    if not (
        math.isfinite(ax)
        and math.isfinite(ay)
        and math.isfinite(az)
        and math.isfinite(gx)
        and math.isfinite(gy)
        and math.isfinite(gz)
    ):
        return -1
    pitch = sagittal_pitch(q[0], q[1], q[2], q[3])
    rc, rs = math.cos(pitch), math.sin(pitch)
    tx = tz = 0.0
    has_prev = mem[MEM_HAS_PREV] > 0.0
    if lever:
        if has_prev and t > mem[MEM_T]:
            h = t - mem[MEM_T]
            pgx, pgy, pgz = mem[MEM_GYRO], mem[MEM_GYRO + 1], mem[MEM_GYRO + 2]
            alx, aly, alz = (gx - pgx) / h, (gy - pgy) / h, (gz - pgz) / h
        else:
            alx = aly = alz = 0.0
        rx, ry, rz = r[0], r[1], r[2]
        cx, cy, cz = gy * rz - gz * ry, gz * rx - gx * rz, gx * ry - gy * rx
        ax += gy * cz - gz * cy
        az += gx * cy - gy * cx
        tx, tz = aly * rz - alz * ry, alx * ry - aly * rx
    fx, fz = ax, az
    abx, abz, gwx, gwz = x[4], x[5], x[6], x[7]
    if trapezoid and has_prev:
        prc, prs, pfx, pfz = mem[MEM_RC], mem[MEM_RS], mem[MEM_FX], mem[MEM_FZ]
        b00, b01 = 0.5 * (prc + rc), 0.5 * (prs + rs)
        awx = 0.5 * ((prc * pfx + prs * pfz) + (rc * fx + rs * fz))
        awz = 0.5 * ((-prs * pfx + prc * pfz) + (-rs * fx + rc * fz))
    else:
        b00, b01 = rc, rs
        awx, awz = rc * fx + rs * fz, -rs * fx + rc * fz
    ux, uz = tx - abx, tz - abz
    awx = awx + (b00 * ux + b01 * uz) + gwx
    awz = awz + (-b01 * ux + b00 * uz) + gwz
    mem[MEM_HAS_PREV] = 1.0
    mem[MEM_T] = t
    mem[MEM_RC], mem[MEM_RS], mem[MEM_FX], mem[MEM_FZ] = rc, rs, fx, fz
    mem[MEM_GYRO], mem[MEM_GYRO + 1], mem[MEM_GYRO + 2] = gx, gy, gz
    mem[MEM_AW], mem[MEM_AW + 1] = awx, awz
    if dt <= 0.0:
        return 0

    # nominal state, eq. 6
    px, pz, vx, vz = x[0], x[1], x[2], x[3]
    dt2 = dt * dt
    x[0] = px + vx * dt + 0.5 * awx * dt2
    x[1] = pz + vz * dt + 0.5 * awz * dt2
    x[2] = vx + awx * dt
    x[3] = vz + awz * dt

    # covariance, eq. 7: P <- F P F^T, F = I except rows 0-3 (F_1 = dt, F_2 = -R_bar dt)
    f02 = dt  # F[0, 2] = F[1, 3] = F[2, 6] = F[3, 7]
    f24, f25 = -b00 * dt, -b01 * dt
    f34, f35 = b01 * dt, -b00 * dt
    n = P.shape[0]
    # rows (F P): rows 0, 1 read the old rows 2, 3, so they go first
    for j in range(n):
        P[0, j] = P[0, j] + f02 * P[2, j]
        P[1, j] = P[1, j] + f02 * P[3, j]
        P[2, j] = P[2, j] + f24 * P[4, j] + f25 * P[5, j] + f02 * P[6, j]
        P[3, j] = P[3, j] + f34 * P[4, j] + f35 * P[5, j] + f02 * P[7, j]
    # columns ((F P) F^T), same order
    for i in range(n):
        P[i, 0] = P[i, 0] + f02 * P[i, 2]
        P[i, 1] = P[i, 1] + f02 * P[i, 3]
        P[i, 2] = P[i, 2] + f24 * P[i, 4] + f25 * P[i, 5] + f02 * P[i, 6]
        P[i, 3] = P[i, 3] + f34 * P[i, 4] + f35 * P[i, 5] + f02 * P[i, 7]
    var_v = (accel_sigma * dt) ** 2
    xa = max(xa_now, mem[MEM_PREV_XA])
    mem[MEM_PREV_XA] = xa_now
    if xa > 0.0:
        var_v += (xa * dt) ** 2
    if attitude_sigma > 0:
        var_v += (math.sqrt(fx * fx + fz * fz) * attitude_sigma * dt) ** 2
    var_ab = var_ab_rate * dt
    P[2, 2] += var_v
    P[3, 3] += var_v
    P[4, 4] += var_ab
    P[5, 5] += var_ab
    return 1


def new_memory() -> np.ndarray:
    """A fresh ``mem`` for :func:`eskf_propagate` (no previous sample)."""
    return np.zeros(MEM_SIZE)


@numba.njit(cache=True)
def fault_check(prev, t, acc, gyr, q, acc_lim, gyr_lim, test, sigma2):
    """``ImuFaultMonitor.process``'s arithmetic: saturation flags of the specific force
    ``acc`` and gyro ``gyr`` (|v| >= limit on any axis) and the chi-square statistic d2 of the
    gyro against the rate predicted from consecutive vendor orientations (-1 if not tested:
    ``test`` off, or no previous sample older than ``t``), with the prediction (px, py, pz).
    ``prev`` = [has one, t, R (9, row-major), gyro (3)] is the previous sample; its R, t and
    gyro become this sample's here (the caller overwrites the gyro with its repair if it
    repairs it: a numpy slice assignment there costs more than this whole kernel's call)."""
    acc_sat = abs(acc[0]) >= acc_lim or abs(acc[1]) >= acc_lim or abs(acc[2]) >= acc_lim
    gyr_sat = abs(gyr[0]) >= gyr_lim or abs(gyr[1]) >= gyr_lim or abs(gyr[2]) >= gyr_lim
    R = _quat_matrix(q[0], q[1], q[2], q[3])
    d2 = -1.0
    px = py = pz = 0.0
    if test and prev[0] > 0.0 and t > prev[1]:
        h = t - prev[1]
        R0t = (prev[2], prev[5], prev[8], prev[3], prev[6], prev[9], prev[4], prev[7], prev[10])
        wx, wy, wz = _mat3_rotvec(_mat3_mul(R0t, R))
        px, py, pz = 2.0 * (wx / h) - prev[11], 2.0 * (wy / h) - prev[12], 2.0 * (wz / h) - prev[13]
        rx, ry, rz = gyr[0] - px, gyr[1] - py, gyr[2] - pz
        d2 = (rx * rx + ry * ry + rz * rz) / sigma2
    prev[0], prev[1] = 1.0, t
    for i in range(9):
        prev[2 + i] = R[i]
    prev[11], prev[12], prev[13] = gyr[0], gyr[1], gyr[2]
    return d2, px, py, pz, acc_sat, gyr_sat


@numba.njit(cache=True)
def clock_line(buf, pos, n, period_s, min_fit):
    """``ClockModel._fit``'s line value at the newest of the ``n`` stamps ``buf[pos - n:pos]``
    (consecutive periods): least squares from ``min_fit`` stamps on, else the mean of the
    stamps moved by whole nominal periods ``period_s``. The means are numpy's pairwise sums;
    the x-y product is summed in order (numpy's BLAS dot may round its last bit differently)."""
    ts = buf[pos - n : pos]
    if n >= min_fit:
        half = 0.5 * (n - 1)
        my = add_reduce(ts) / n
        sxy = 0.0
        for i in range(n):
            sxy += (i - half) * (ts[i] - my)
        return my + (sxy / (n * (n * n - 1) / 12.0)) * half
    tmp = np.empty(n)
    for i in range(n):
        tmp[i] = ts[i] + period_s * (n - 1 - float(i))
    return add_reduce(tmp) / n


# ClockModel's state in compiled mode (``ClockModel._st``; CLK_N_CORR stays the last slot,
# ClockModel.report reads it there). CLK_DEV: the sum over the line's stamps of how far each
# step between consecutive stamps is from the nominal period (s), see clock_correct.
CLK_HAS_LAST, CLK_LAST, CLK_K, CLK_POS, CLK_N, CLK_HAS_OUT, CLK_OUT, CLK_DEV, CLK_N_CORR = range(9)
CLK_SIZE = 9


@numba.njit(cache=True)
def clock_correct(st, buf, corr, t, period_s, gap_periods, window, smooth, min_fit, keep_tol_s):
    """``ClockModel.correct`` on the state ``st`` (CLK_* slots), the stamp buffer ``buf`` and
    the corrections ``corr`` (room for one more, checked by the caller). Returns (time to use,
    code, dt, previous stamp): code 0 for a consecutive sample, 1 after a gap of dt s (the
    line restarts), -1 for a stamp at or before the previous one (nothing changed, dt the
    jump, the time NaN)."""
    prev = st[CLK_LAST]
    code = 0
    gap = 0.0
    if st[CLK_HAS_LAST] > 0.0:
        if t <= prev:
            return np.nan, -1, t - prev, prev
        dt = t - prev
        if dt > gap_periods * period_s:
            code = 1
            gap = dt
            st[CLK_N] = 0.0
            st[CLK_K] += max(1.0, np.rint(dt / period_s))
        else:
            st[CLK_K] += 1.0
    st[CLK_HAS_LAST] = 1.0
    st[CLK_LAST] = t
    pos = int(st[CLK_POS])
    n_old = int(st[CLK_N])
    # deviation sum of the steps inside the line's window: the oldest stamp's step leaves
    # when the window is full, the new one's enters
    dev = st[CLK_DEV] if n_old > 0 else 0.0
    if n_old == window:
        lo = pos - n_old
        dev -= abs(buf[lo + 1] - buf[lo] - period_s)
    if n_old > 0:
        dev += abs(t - buf[pos - 1] - period_s)
    st[CLK_DEV] = dev
    if pos == buf.size:  # keep the newest window - 1 stamps, at the front
        keep = window - 1
        for i in range(keep):
            buf[i] = buf[pos - keep + i]
        pos = keep
    buf[pos] = t
    pos += 1
    st[CLK_POS] = pos
    n = min(n_old + 1, window)
    st[CLK_N] = n
    out = t
    # Stamps on a line of the nominal slope through the newest one leave the fit there (a
    # least-squares line, or the nominal-period mean below MIN_FIT stamps) at the newest
    # stamp: both reproduce a line exactly. Each stamp is off that line by at most the sum
    # of its steps' deviations (``dev``), and the fit's value at the newest stamp weighs the
    # stamps with |w_i| <= 4 / n, so it is within 4 dev of the newest stamp. Far below the
    # keep tolerance (1/16 of it: 4 dev <= tol / 4 leaves 3/4 of it for rounding, ~1e-11 s),
    # the fit keeps the stamp anyway: skip its O(window) sums (same output, bit for bit).
    if smooth and not dev <= keep_tol_s / 16.0:
        icpt = clock_line(buf, pos, n, period_s, min_fit)
        if not abs(icpt - t) < keep_tol_s:
            out = icpt
    if st[CLK_HAS_OUT] > 0.0 and out <= st[CLK_OUT]:
        out = t if t > st[CLK_OUT] else st[CLK_OUT] + 0.5 * period_s
    st[CLK_HAS_OUT] = 1.0
    st[CLK_OUT] = out
    nc = int(st[CLK_N_CORR])
    corr[nc] = out - t
    st[CLK_N_CORR] = nc + 1
    return out, code, gap, prev


# sample_step's workspace (one float64 array, so that a call passes few arguments: numba's
# dispatcher spends ~0.3 us on each): the attitude tracker's R (row-major) and gyro, the
# tracked quaternion out, the constants (propagation switches and noise, gravity, lever arms)
# and the stance detector's |a_ankle| out
WS_R = 0  # 0:9 R_world_imu of the attitude tracker, row-major
WS_GYRO = 9  # 9:12 its latest gyro (rad/s)
WS_Q = 12  # 12:16 the tracked quaternion at the sample (out)
WS_LEVER, WS_TRAPEZOID = 16, 17  # 1.0 / 0.0 switches of the propagation
WS_ACCEL_SIGMA, WS_ATT_SIGMA, WS_VAR_AB_RATE = 18, 19, 20
WS_GRAVITY = 21  # 21:23 gravity in the ground x-z plane (m/s^2)
WS_R_CAM = 23  # 23:26 camera in the IMU frame (m), the propagation's lever arm
WS_R_ANKLE = 26  # 26:29 ankle in the IMU frame (m), the stance detector's lever arm
WS_MAG = 29  # |a_ankle| (m/s^2, out; NaN if the detector was not fed)
WS_SIZE = 30


@numba.njit(cache=True)
def sample_step(
    ws,
    x,
    P,
    mem,
    stance_prev,
    acc,
    gyr,
    q_vendor,
    t,
    dt,
    k_att,
    k_pitch,
    offset_rad,
    dt_filter,
    xa_now,
    stance,
):
    """One IMU sample through ``OnlineEstimator._advance_imu`` in one call, for the common case
    (the sample is propagated and fed to the stance detector at once): :func:`attitude_step`
    on the tracker's attitude and previous gyro (in ``ws``, WS_* slots; both become the
    sample's), :func:`tracked_quat` at the sample's time into ``ws[WS_Q:WS_Q + 4]``,
    :func:`eskf_propagate` on ``x``, ``P``, ``mem`` with that orientation and, if ``stance``,
    :func:`stance_ankle_accel` on ``stance_prev`` into ``ws[WS_MAG]``. The same calls in the
    same order as the separate kernels, so the same bits. Returns the new R (9-tuple) and the
    propagation's code (see :func:`eskf_propagate`)."""
    R0 = (ws[0], ws[1], ws[2], ws[3], ws[4], ws[5], ws[6], ws[7], ws[8])
    g0 = (ws[WS_GYRO], ws[WS_GYRO + 1], ws[WS_GYRO + 2])
    R = attitude_step(R0, g0, gyr, q_vendor, dt, k_att, k_pitch)
    for i in range(9):
        ws[WS_R + i] = R[i]
    for i in range(3):
        ws[WS_GYRO + i] = gyr[i]
    w, qx, qy, qz = tracked_quat(R, gyr, 0.0, offset_rad)
    q = ws[WS_Q : WS_Q + 4]
    q[0], q[1], q[2], q[3] = w, qx, qy, qz
    moved = eskf_propagate(
        x,
        P,
        mem,
        t,
        dt_filter,
        acc,
        gyr,
        q,
        ws[WS_R_CAM : WS_R_CAM + 3],
        ws[WS_LEVER] != 0.0,
        ws[WS_TRAPEZOID] != 0.0,
        ws[WS_ACCEL_SIGMA],
        xa_now,
        ws[WS_ATT_SIGMA],
        ws[WS_VAR_AB_RATE],
    )
    ws[WS_MAG] = np.nan
    if stance and moved >= 0:
        ws[WS_MAG] = stance_ankle_accel(
            t,
            stance_prev,
            acc,
            gyr,
            q,
            ws[WS_R_ANKLE : WS_R_ANKLE + 3],
            ws[WS_GRAVITY : WS_GRAVITY + 2],
        )
    return R, moved


# imu_input's constants (one float64 array, built once per estimator): the IMU clock model's,
# the fault monitor's and the attitude tracker's time constants (roll / heading, pitch)
IN_PERIOD, IN_GAP_PERIODS, IN_WINDOW, IN_SMOOTH, IN_MIN_FIT, IN_KEEP_TOL = range(6)
IN_ACC_LIM, IN_GYR_LIM, IN_TEST, IN_SIGMA2, IN_GYRO_D2 = range(6, 11)
IN_TIME_CONSTANT, IN_PITCH_TIME_CONSTANT = 11, 12
IN_SIZE = 13
# imu_input's state pool: sample_step's workspace (WS_*) followed by imu_input's constants
# and the small state arrays of the clock model (ClockModel._st), the fault monitor
# (ImuFaultMonitor._prev_arr), the stance detector (StanceDetector._prev_arr) and the
# propagation (SagittalEskf._mem), which the online estimator re-points to views of it
# (OnlineEstimator._init_one_call_input): one array argument instead of six, ~0.15 us of the
# dispatcher's time each
POOL_IN = WS_SIZE  # IN_SIZE constants
POOL_CLK = POOL_IN + IN_SIZE  # CLK_SIZE
POOL_FAULT = POOL_CLK + CLK_SIZE  # FAULT_PREV_SIZE
FAULT_PREV_SIZE = 14
POOL_STANCE = POOL_FAULT + FAULT_PREV_SIZE  # STANCE_PREV_SIZE
STANCE_PREV_SIZE = 5
POOL_MEM = POOL_STANCE + STANCE_PREV_SIZE  # MEM_SIZE
# imu_input's outputs the caller reads only on the rare paths (a clock event, a fault), in
# the pool instead of the returned tuple (each boxed value costs the call): the clock's gap or
# jump and previous stamp, fault_check's predicted gyro and saturation flags (1.0 / 0.0)
POOL_OUT = POOL_MEM + MEM_SIZE
OUT_GAP, OUT_PREV, OUT_PX, OUT_PY, OUT_PZ, OUT_ACC_SAT, OUT_GYR_SAT = range(7)
POOL_SIZE = POOL_OUT + 7
# imu_input's outcome
IN_BACKWARD = -1  # the clock dropped the stamp (at or before the previous one); nothing else ran
IN_FUSED = 0  # clock model, fault check and sample_step all ran
IN_FAULT = 1  # clock model and fault check ran; the check found a saturated axis, a gyro
# outlier or an open clipped stretch (the caller finishes the monitor's work in Python)
IN_CLEAN = 2  # clock model and fault check ran, the sample is clean, sample_step's
# preconditions on the time failed (the caller takes the general path from there)


@numba.njit(cache=True)
def imu_input(
    pool,
    clk_buf,
    clk_corr,
    x,
    P,
    acc,
    gyr,
    q,
    stamp,
    acc_run,
    att_t,
    filt_t,
    filt_start,
    last_t,
    offset_rad,
    xa_now,
    stance,
):
    """``OnlineEstimator.add_imu`` for a sample in shank-aligned IMU axes, in one call: the IMU
    clock model (:func:`clock_correct` on the pool's clock state, ``clk_buf``, ``clk_corr``),
    the fault monitor's check (:func:`fault_check` on the pool's previous sample) at the
    corrected time and, if the sample is clean (no saturated axis, no open clipped stretch:
    ``acc_run`` 0, the gyro test passed), :func:`sample_step` (the pool's workspace, stance
    and propagation memory, ``x``, ``P``) when its preconditions on the time hold: not before
    the attitude tracker's time ``att_t``, the filter's ``filt_t`` (1e-9 s tolerance) or its
    start ``filt_start``, after the previous sample's ``last_t``, finite. ``pool``: POOL_*
    layout, constants at POOL_IN (IN_* slots). The same kernels in the same order as the
    separate calls, so the same bits.

    Returns (outcome (IN_*), corrected time, the clock's code (see :func:`clock_correct`),
    :func:`fault_check`'s d2 (-1.0 if it did not run), :func:`sample_step`'s code and R (the
    tracker's R unchanged unless IN_FUSED)); the clock's gap or jump (s) and previous stamp
    and :func:`fault_check`'s px, py, pz, acc_sat, gyr_sat go to the pool (POOL_OUT + OUT_*,
    written on every call that gets that far)."""
    c = pool[POOL_IN : POOL_IN + IN_SIZE]
    t, code, gap, prev = clock_correct(
        pool[POOL_CLK : POOL_CLK + CLK_SIZE],
        clk_buf,
        clk_corr,
        stamp,
        c[IN_PERIOD],
        c[IN_GAP_PERIODS],
        int(c[IN_WINDOW]),
        c[IN_SMOOTH] != 0.0,
        int(c[IN_MIN_FIT]),
        c[IN_KEEP_TOL],
    )
    R = (pool[0], pool[1], pool[2], pool[3], pool[4], pool[5], pool[6], pool[7], pool[8])
    out = pool[POOL_OUT : POOL_OUT + 7]
    out[OUT_GAP], out[OUT_PREV] = gap, prev
    if code < 0:
        return IN_BACKWARD, t, code, -1.0, 0, R
    d2, px, py, pz, acc_sat, gyr_sat = fault_check(
        pool[POOL_FAULT : POOL_FAULT + FAULT_PREV_SIZE],
        t,
        acc,
        gyr,
        q,
        c[IN_ACC_LIM],
        c[IN_GYR_LIM],
        c[IN_TEST] != 0.0,
        c[IN_SIGMA2],
    )
    out[OUT_PX], out[OUT_PY], out[OUT_PZ] = px, py, pz
    out[OUT_ACC_SAT] = 1.0 if acc_sat else 0.0
    out[OUT_GYR_SAT] = 1.0 if gyr_sat else 0.0
    if acc_sat or gyr_sat or acc_run != 0 or d2 > c[IN_GYRO_D2]:
        return IN_FAULT, t, code, d2, 0, R
    dt = t - att_t
    dt_filter = t - filt_t
    if (
        not t > last_t
        or dt < 0.0
        or t < filt_start - 1e-9
        or dt_filter < -1e-9
        or not math.isfinite(t)
    ):
        return IN_CLEAN, t, code, d2, 0, R
    R, moved = sample_step(
        pool,
        x,
        P,
        pool[POOL_MEM : POOL_MEM + MEM_SIZE],
        pool[POOL_STANCE : POOL_STANCE + STANCE_PREV_SIZE],
        acc,
        gyr,
        q,
        t,
        dt,
        min(1.0, dt / c[IN_TIME_CONSTANT]),
        min(1.0, dt / c[IN_PITCH_TIME_CONSTANT]),
        offset_rad,
        dt_filter,
        xa_now,
        stance,
    )
    return IN_FUSED, t, code, d2, moved, R
