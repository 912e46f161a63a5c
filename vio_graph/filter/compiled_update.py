"""Compiled SP-ESKF measurement updates (numba): ``SagittalEskf._correct`` and the gate
statistic of ``SagittalEskf.displacement_d2`` in one machine-code call each.

An update is 1- or 2-dimensional on a state of 8 + 2 per clone / landmark errors; the
arithmetic is a few thousand flops, and the numpy formulation (``_correct``: H P, H P H^T, the
2x2 inverse in closed form, K, P - K H P, the symmetrisation; about a dozen small-array
calls) spends ~40 us per update on per-call overhead. Here the same formulas run as loops:
the closed-form 2x2 inverse, the gate, K = P H^T S^-1, P - K H P symmetrised. The matrix
products sum in index order instead of BLAS's, so the results equal the numpy path's to
rounding (tests/test_filter_fastpaths.py: the updates to 1e-12 relative, a whole replay to
1e-9 m).

Which path runs is decided with the rest of the compiled filter (``fast_imu.imu_kernels``,
``VIO_GRAPH_COMPILED``).
"""

from __future__ import annotations

import math

import numba
import numpy as np

#: correct()'s status
ACCEPTED = 0
GATED = 1
SINGULAR = 2


@numba.njit(cache=True)
def _hp(H, P):  # pragma: no cover - compiled
    """H P (m x n), skipping the zero entries of H (most of its n columns)."""
    m, n = H.shape
    out = np.zeros((m, n))
    for r in range(m):
        for k in range(n):
            h = H[r, k]
            if h != 0.0:
                for c in range(n):
                    out[r, c] += h * P[k, c]
    return out


@numba.njit(cache=True)
def _innovation_cov(H, HP, V):  # pragma: no cover - compiled
    """S = (H P) H^T + V (m x m)."""
    m, n = H.shape
    S = np.empty((m, m))
    for r in range(m):
        for q in range(m):
            s = 0.0
            for k in range(n):
                h = H[q, k]
                if h != 0.0:
                    s += HP[r, k] * h
            S[r, q] = s + V[r, q]
    return S


@numba.njit(cache=True)
def _inverse_and_d2(S, y):  # pragma: no cover - compiled
    """(S^-1 as in ``SagittalEskf._correct``'s closed form, y^T S^-1 y, ok) for m = 1 or 2;
    ok False when S is singular or not finite."""
    m = S.shape[0]
    S_inv = np.empty((m, m))
    if m == 2:
        s00, s11 = S[0, 0], S[1, 1]
        s01 = 0.5 * (S[0, 1] + S[1, 0])
        det = s00 * s11 - s01 * s01
        if det == 0.0 or not math.isfinite(det):
            return S_inv, 0.0, False
        y0, y1 = y[0], y[1]
        u0, u1 = (s11 * y0 - s01 * y1) / det, (s00 * y1 - s01 * y0) / det
        S_inv[0, 0] = s11 / det
        S_inv[0, 1] = -s01 / det
        S_inv[1, 0] = -s01 / det
        S_inv[1, 1] = s00 / det
        return S_inv, y0 * u0 + y1 * u1, True
    s00 = S[0, 0]
    if s00 == 0.0 or not math.isfinite(s00):
        return S_inv, 0.0, False
    S_inv[0, 0] = 1.0 / s00
    return S_inv, y[0] * y[0] / s00, True


@numba.njit(cache=True)
def correct(P, H, V, y, gate, gate_d2):  # pragma: no cover - compiled
    """``SagittalEskf._correct``'s arithmetic for m = 1 or 2 measurement rows.

    Returns (status, d2, P_new, dx): status ACCEPTED (P_new = P - K H P symmetrised, dx = K y
    the error state to inject), GATED (``gate`` and d2 > ``gate_d2``; P_new, dx unset) or
    SINGULAR (S singular or not finite)."""
    m, n = H.shape
    HP = _hp(H, P)
    S = _innovation_cov(H, HP, V)
    S_inv, d2, ok = _inverse_and_d2(S, y)
    if not ok:
        return SINGULAR, d2, P, np.zeros(n)
    if gate and d2 > gate_d2:
        return GATED, d2, P, np.zeros(n)
    # K = (S^-1 H P)^T (n x m)
    K = np.zeros((n, m))
    for c in range(n):
        for r in range(m):
            s = 0.0
            for q in range(m):
                s += S_inv[r, q] * HP[q, c]
            K[c, r] = s
    dx = np.zeros(n)
    for c in range(n):
        s = 0.0
        for r in range(m):
            s += K[c, r] * y[r]
        dx[c] = s
    Q = np.empty((n, n))
    for a in range(n):
        for b in range(n):
            s = 0.0
            for r in range(m):
                s += K[a, r] * HP[r, b]
            Q[a, b] = P[a, b] - s
    out = np.empty((n, n))
    for a in range(n):
        for b in range(n):
            out[a, b] = 0.5 * (Q[a, b] + Q[b, a])
    return ACCEPTED, d2, out, dx


@numba.njit(cache=True)
def _gate_terms(P, H, V):  # pragma: no cover - compiled
    """The innovation covariance S = H P H^T + V of a 2-row H as (s00, s01, s11, det), s01
    the mean of its two off-diagonal entries."""
    HP = _hp(H, P)
    S = _innovation_cov(H, HP, V)
    s00, s11 = S[0, 0], S[1, 1]
    s01 = 0.5 * (S[0, 1] + S[1, 0])
    return s00, s01, s11, s00 * s11 - s01 * s01


@numba.njit(cache=True)
def _gate_quadratic(y, s00, s01, s11, det):  # pragma: no cover - compiled
    """y^T S^-1 y from :func:`_gate_terms`' values, in closed form."""
    y0, y1 = y[0], y[1]
    return (y0 * (s11 * y0 - s01 * y1) + y1 * (s00 * y1 - s01 * y0)) / det


@numba.njit(cache=True)
def gate_d2(P, H, V, y):  # pragma: no cover - compiled
    """y^T (H P H^T + V)^-1 y for a 2-row H (``gating.mahalanobis2_2d``'s closed form), or
    nan when the innovation covariance is singular or not finite."""
    s00, s01, s11, det = _gate_terms(P, H, V)
    if det == 0.0 or not math.isfinite(det):
        return np.nan
    return _gate_quadratic(y, s00, s01, s11, det)


@numba.njit(cache=True)
def gate_d2_pair(P, H, V, y, y_other):  # pragma: no cover - compiled
    """(:func:`gate_d2` of ``y``, of ``y_other``) with H P and S built once: the same two
    floats as two calls."""
    s00, s01, s11, det = _gate_terms(P, H, V)
    if det == 0.0 or not math.isfinite(det):
        return np.nan, np.nan
    return _gate_quadratic(y, s00, s01, s11, det), _gate_quadratic(y_other, s00, s01, s11, det)


@numba.njit(cache=True)
def without_block(P, i):  # pragma: no cover - compiled
    """P without rows and columns i, i + 1 (``SagittalEskf._marginalise``'s take): a copy,
    the same values."""
    n = P.shape[0]
    out = np.empty((n - 2, n - 2))
    for a in range(n - 2):
        ra = a if a < i else a + 2
        for b in range(n - 2):
            out[a, b] = P[ra, b if b < i else b + 2]
    return out


@numba.njit(cache=True)
def augmented(P, dt_s, extra_cov):  # pragma: no cover - compiled
    """``SagittalEskf._augment``'s covariance: P symmetrised, then the new block's rows
    A = P[0:2] + dt P[2:4] and its own block B = A[:, 0:2] + dt A[:, 2:4] + extra,
    symmetrised; element by element the same operations as the numpy path, so the same
    floats."""
    m = P.shape[0]
    Q = np.empty((m + 2, m + 2))
    for a in range(m):
        for b in range(m):
            Q[a, b] = 0.5 * (P[a, b] + P[b, a])
    for r in range(2):
        for c in range(m):
            v = Q[r, c] + dt_s * Q[2 + r, c]
            Q[m + r, c] = v
            Q[c, m + r] = v
    B = np.empty((2, 2))
    for r in range(2):
        for c in range(2):
            B[r, c] = Q[m + r, c] + dt_s * Q[m + r, 2 + c] + extra_cov[r, c]
    for r in range(2):
        for c in range(2):
            Q[m + r, m + c] = 0.5 * (B[r, c] + B[c, r])
    return Q


@numba.njit(cache=True)
def recloned(P, i, dt_s, extra_cov):  # pragma: no cover - compiled
    """``SagittalEskf._set_clone``'s covariance in one call: the old clone's rows and
    columns i, i + 1 removed (:func:`without_block`; i < 0: no old clone), then the new
    clone appended (:func:`augmented`): the same two functions, so the same floats."""
    if i >= 0:
        P = without_block(P, i)
    return augmented(P, dt_s, extra_cov)
