"""Chi-square gates of 2D measurements (displacements, landmarks, stance tests, health)."""

from __future__ import annotations

import numpy as np


def chi2_2dof_quantile(probability: float) -> float:
    """Quantile of the chi-square distribution with 2 degrees of freedom (closed form:
    -2 ln(1 - p)), e.g. 13.82 for p = 0.999."""
    return float(-2.0 * np.log1p(-probability))


def chi2_quantile(probability: float, dof: int) -> float:
    """Quantile of the chi-square distribution with ``dof`` degrees of freedom (1, 3, ...)."""
    from scipy.special import gammaincinv

    return float(2.0 * gammaincinv(0.5 * dof, probability))
