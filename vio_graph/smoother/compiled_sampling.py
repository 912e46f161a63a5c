"""Compiled step means for GTSAM's preintegration (numba): ``imu_sampling.common_frame_samples``
(the default sampler) in one call, without numpy's per-call overhead on the ~10 samples of a
keyframe interval (~0.4 ms a keyframe in numpy, tens of microseconds here).

The same algorithm written out element by element: knots, curvature-corrected step means
(``np.interp``'s rule for the knot values), step rotations by Rodrigues' formula, the specific
force averaged in the frame of the interval's start and handed back in each step's frame. The
3x3 products are summed in plain order where numpy's matmul / einsum may use other orders or
fused multiply-adds, so the last bits can differ; ``imu_sampling.common_frame_samples`` stays
the tested reference (tests/test_smoother.py: 1e-12 on the steps, 1e-9 m on a replay).

Selected with the other compiled kernels (``filter.fast_imu.imu_kernels``); imported only
then.
"""

from __future__ import annotations

import math

import numba
import numpy as np

from vio_graph.compiled_sums import add_reduce


@numba.njit(cache=True)
def _interp(x, xp, fp, col):
    """``np.interp(x, xp, fp[:, col])`` for one x (held outside xp, exact at a sample)."""
    n = xp.size
    if x > xp[n - 1]:
        return fp[n - 1, col]
    if x < xp[0]:
        return fp[0, col]
    if x == xp[n - 1]:
        return fp[n - 1, col]
    j = np.searchsorted(xp, x, side="right") - 1
    if xp[j] == x:
        return fp[j, col]
    slope = (fp[j + 1, col] - fp[j, col]) / (xp[j + 1] - xp[j])
    v = slope * (x - xp[j]) + fp[j, col]
    if math.isnan(v):
        v = slope * (x - xp[j + 1]) + fp[j + 1, col]
        if math.isnan(v) and fp[j, col] == fp[j + 1, col]:
            v = fp[j, col]
    return v


@numba.njit(cache=True)
def _second_derivative(t, y):
    """``imu_sampling._second_derivative``: central differences, ends copied."""
    n = t.size
    ypp = np.zeros_like(y)
    if n < 3:
        return ypp
    for i in range(1, n - 1):
        h0 = t[i] - t[i - 1]
        h1 = t[i + 1] - t[i]
        for c in range(3):
            ypp[i, c] = (
                2.0 * ((y[i + 1, c] - y[i, c]) / h1 - (y[i, c] - y[i - 1, c]) / h0) / (h0 + h1)
            )
    for c in range(3):
        ypp[0, c] = ypp[1, c]
        ypp[n - 1, c] = ypp[n - 2, c]
    return ypp


@numba.njit(cache=True)
def _step_means(t, y, knots, curv, dt):
    """``imu_sampling._quadratic_step_means``' step means of y (N, 3) over the knots."""
    ypp = _second_derivative(t, y)
    nk = knots.size
    yk = np.empty((nk, 3))
    ppk = np.empty((nk, 3))
    for k in range(nk):
        for c in range(3):
            ppk[k, c] = _interp(knots[k], t, ypp, c)
            yk[k, c] = _interp(knots[k], t, y, c) + curv[k] * ppk[k, c]
    out = np.empty((nk - 1, 3))
    for k in range(nk - 1):
        w = dt[k] ** 2 / 12.0
        for c in range(3):
            out[k, c] = 0.5 * (yk[k + 1, c] + yk[k, c]) - w * 0.5 * (ppk[k + 1, c] + ppk[k, c])
    return out


@numba.njit(cache=True)
def _so3_exp(wx, wy, wz, R):
    """``imu_sampling.so3_exp`` of one rotation vector (rad) into R (3, 3)."""
    theta = math.sqrt(wx * wx + wy * wy + wz * wz)
    if theta < 1e-8:
        a, b = 1.0, 0.5
    else:
        a = math.sin(theta) / theta
        b = (1.0 - math.cos(theta)) / theta**2
    # K = [w]x; K @ K = w w^T - |w|^2 I
    R[0, 0] = 1.0 + b * (-wz * wz - wy * wy)
    R[0, 1] = -a * wz + b * (wy * wx)
    R[0, 2] = a * wy + b * (wz * wx)
    R[1, 0] = a * wz + b * (wx * wy)
    R[1, 1] = 1.0 + b * (-wz * wz - wx * wx)
    R[1, 2] = -a * wx + b * (wz * wy)
    R[2, 0] = -a * wy + b * (wx * wz)
    R[2, 1] = a * wx + b * (wy * wz)
    R[2, 2] = 1.0 + b * (-wy * wy - wx * wx)


@numba.njit(cache=True)
def common_frame_steps(t, a, g, t0, t1, tol, substeps=1):
    """``imu_sampling.common_frame_samples(t, a, g, t0, t1, substeps)`` (tol =
    ``TIME_TOL_S``): the step accelerations (K, 3, each in its step-start frame), gyro
    means (K, 3) and step lengths (K,)."""
    n = t.size
    m = 0
    for i in range(n):
        if t[i] > t0 + tol and t[i] < t1 - tol:
            m += 1
    knots = np.empty(m + 2)
    knots[0] = t0
    j = 1
    for i in range(n):
        if t[i] > t0 + tol and t[i] < t1 - tol:
            knots[j] = t[i]
            j += 1
    knots[m + 1] = t1
    if substeps > 1:
        coarse = knots
        knots = np.empty((m + 1) * substeps + 1)
        for k in range(m + 1):
            step = coarse[k + 1] - coarse[k]
            for q in range(substeps):
                knots[k * substeps + q] = coarse[k] + step * (q / substeps)
        knots[(m + 1) * substeps] = t1
    nk = knots.size
    ns = nk - 1
    curv = np.zeros(nk)
    for k in range(nk):
        x = knots[k]
        if x > t[0] and x < t[n - 1]:
            lo = min(max(np.searchsorted(t, x, side="right") - 1, 0), n - 1)
            hi = min(lo + 1, n - 1)
            curv[k] = 0.5 * (x - t[lo]) * (x - t[hi])
    dt = np.empty(ns)
    for k in range(ns):
        dt[k] = knots[k + 1] - knots[k]

    g_mid = _step_means(t, g, knots, curv, dt)
    # rotations at the knots (interval start = I), from the steps GTSAM integrates
    R_knot = np.empty((nk, 3, 3))
    R_knot[0] = np.eye(3)
    S = np.empty((3, 3))
    for k in range(ns):
        _so3_exp(g_mid[k, 0] * dt[k], g_mid[k, 1] * dt[k], g_mid[k, 2] * dt[k], S)
        for r in range(3):
            for c in range(3):
                R_knot[k + 1, r, c] = (
                    R_knot[k, r, 0] * S[0, c]
                    + R_knot[k, r, 1] * S[1, c]
                    + R_knot[k, r, 2] * S[2, c]
                )
    # specific force of every sample in the interval-start frame
    F = np.empty((n, 3))
    Rt = np.empty((3, 3))
    for i in range(n):
        k = min(max(np.searchsorted(knots, t[i], side="right") - 1, 0), ns - 1)
        h = t[i] - knots[k]
        _so3_exp(g_mid[k, 0] * h, g_mid[k, 1] * h, g_mid[k, 2] * h, S)
        for r in range(3):
            for c in range(3):
                Rt[r, c] = (
                    R_knot[k, r, 0] * S[0, c]
                    + R_knot[k, r, 1] * S[1, c]
                    + R_knot[k, r, 2] * S[2, c]
                )
        for r in range(3):
            F[i, r] = Rt[r, 0] * a[i, 0] + Rt[r, 1] * a[i, 1] + Rt[r, 2] * a[i, 2]
    F_mean = _step_means(t, F, knots, curv, dt)
    a_in = np.empty((ns, 3))
    for k in range(ns):
        for c in range(3):
            a_in[k, c] = (
                R_knot[k, 0, c] * F_mean[k, 0]
                + R_knot[k, 1, c] * F_mean[k, 1]
                + R_knot[k, 2, c] * F_mean[k, 2]
            )
    return a_in, g_mid, dt


@numba.njit(cache=True)
def discretization_var(t, a, t0, t1, tol):
    """``imu_sampling.discretization_velocity_var(t, a, t0, t1)`` (tol = ``TIME_TOL_S``): the
    same fourth differences and window periods, element by element in numpy's order, and
    their squares summed as ``np.sum`` sums them (numpy's pairwise order over the touching
    windows' rows, C order), so the same float."""
    n = t.size
    if n < 5:
        return 0.0
    sq = np.empty(3 * (n - 4))
    m = 0
    for j in range(n - 4):
        if t[j + 4] > t0 - tol and t[j] < t1 + tol:
            h = (t[j + 4] - t[j]) / 4.0
            for c in range(3):
                d4 = (
                    a[j, c]
                    - 4.0 * a[j + 1, c]
                    + 6.0 * a[j + 2, c]
                    - 4.0 * a[j + 3, c]
                    + a[j + 4, c]
                )
                v = h * d4
                sq[m] = v * v
                m += 1
    return add_reduce(sq[:m])
