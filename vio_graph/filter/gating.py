"""Chi-square gates of 2D measurements (displacements, landmarks, stance tests, health)."""

from __future__ import annotations

import math

import numpy as np
from numpy.typing import NDArray

from vio_graph.errors import EstimationError


def chi2_2dof_quantile(probability: float) -> float:
    """Quantile of the chi-square distribution with 2 degrees of freedom (closed form:
    -2 ln(1 - p)), e.g. 13.82 for p = 0.999."""
    return float(-2.0 * np.log1p(-probability))


#: chi-square quantiles of the usual gate probabilities, (probability, dof) -> the value
#: scipy's ``2 * gammaincinv(dof / 2, probability)`` gives, stored exactly (``float.hex``):
#: with the default configuration a run then needs no scipy.special, whose import is
#: ~0.3 s of CPU a process (tests/test_gating_table.py compares every entry with scipy)
KNOWN_CHI2_QUANTILES: dict[tuple[float, int], float] = {
    key: float.fromhex(value)
    for key, value in {
        (0.95, 1): "0x1.ebb4ec31e7ef5p+1",
        (0.95, 2): "0x1.7f7427b73e38ep+2",
        (0.95, 3): "0x1.f4248080e68edp+2",
        (0.99, 1): "0x1.a8a2255a6e924p+2",
        (0.99, 2): "0x1.26bb1bbb55514p+3",
        (0.99, 3): "0x1.6b0925f3ee5a7p+3",
        (0.999, 1): "0x1.5a7b6c0cc8b77p+3",
        (0.999, 2): "0x1.ba18a998fffa0p+3",
        (0.999, 3): "0x1.044280e2bdaadp+4",
        (0.9999, 1): "0x1.e45fe3a3b14d1p+3",
        (0.9999, 2): "0x1.26bb1bbb55553p+4",
        (0.9999, 3): "0x1.51b8600a509e9p+4",
        (0.99999, 1): "0x1.382ec7bfdbafbp+4",
        (0.99999, 2): "0x1.7069e2aa2b45dp+4",
        (0.99999, 3): "0x1.9e6d91242d5dbp+4",
        (0.999999, 1): "0x1.7ed99bac43b90p+4",
        (0.999999, 2): "0x1.ba18a998fc064p+4",
        (0.999999, 3): "0x1.eaa339720b014p+4",
    }.items()
}


def chi2_quantile(probability: float, dof: int) -> float:
    """Quantile of the chi-square distribution with ``dof`` degrees of freedom (1, 3, ...):
    from :data:`KNOWN_CHI2_QUANTILES` when listed there, else computed with scipy."""
    known = KNOWN_CHI2_QUANTILES.get((float(probability), int(dof)))
    if known is not None:
        return known
    return chi2_quantile_scipy(probability, dof)


def chi2_quantile_scipy(probability: float, dof: int) -> float:
    """:func:`chi2_quantile` computed (scipy.special.gammaincinv), the reference of the table."""
    from scipy.special import gammaincinv

    return float(2.0 * gammaincinv(0.5 * dof, probability))


def mahalanobis2_2d(S: NDArray[np.float64], y: NDArray[np.float64]) -> float:
    """y^T S^-1 y for a 2x2 covariance ``S`` (symmetrised) and a 2-vector ``y``, with the
    inverse in closed form: equal to ``y @ np.linalg.solve(S, y)`` to rounding, without a
    LAPACK call's overhead (a few us, more than the arithmetic). Raises EstimationError if
    ``S`` is singular or not finite."""
    s00, s11 = float(S[0, 0]), float(S[1, 1])
    s01 = 0.5 * (float(S[0, 1]) + float(S[1, 0]))
    det = s00 * s11 - s01 * s01
    if det == 0.0 or not math.isfinite(det):
        raise EstimationError("singular innovation covariance")
    y0, y1 = float(y[0]), float(y[1])
    return (y0 * (s11 * y0 - s01 * y1) + y1 * (s00 * y1 - s01 * y0)) / det
