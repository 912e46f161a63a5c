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


def chi2_quantile(probability: float, dof: int) -> float:
    """Quantile of the chi-square distribution with ``dof`` degrees of freedom (1, 3, ...)."""
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
