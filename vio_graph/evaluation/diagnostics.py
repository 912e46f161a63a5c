"""Evaluation of the estimator's internal decisions against ground truth.

Pure functions on arrays (no I/O): stance detection against the true ankle motion, and the
consistency (NEES) of the visual displacements the front end produced and of the filter's own
position covariance.
"""

from __future__ import annotations

import numpy as np
from numpy.typing import NDArray

from vio_graph.filter.gating import chi2_2dof_quantile
from vio_graph.recording.streams import Trajectory
from vio_graph.types import Displacement2D

#: the true ankle counts as still when it moves less than this speed (m/s) over
#: ``STILL_WINDOW_S``: mocap marker noise (~1 mm) gives ~1 cm/s over 0.1 s.
STILL_SPEED_MPS = 0.05
STILL_WINDOW_S = 0.1


def true_stance(ankle: Trajectory, t_s: NDArray[np.float64]) -> NDArray[np.bool_]:
    """True where the ground-truth ankle is still (speed over ``STILL_WINDOW_S`` below
    ``STILL_SPEED_MPS``) at the times ``t_s`` (s)."""
    t = np.asarray(t_s, dtype=float)
    half = STILL_WINDOW_S / 2
    d = ankle.xz_at(t + half) - ankle.xz_at(t - half)
    return np.hypot(d[:, 0], d[:, 1]) / STILL_WINDOW_S < STILL_SPEED_MPS


def stance_scores(flagged: NDArray[np.bool_], truth: NDArray[np.bool_]) -> dict[str, float]:
    """Precision and recall of per-frame stance flags against the truth (NaN if undefined)."""
    f = np.asarray(flagged, dtype=bool)
    g = np.asarray(truth, dtype=bool)
    tp = float(np.sum(f & g))
    return {
        "precision": tp / f.sum() if f.sum() else float("nan"),
        "recall": tp / g.sum() if g.sum() else float("nan"),
        "flagged_share": float(f.mean()) if f.size else float("nan"),
        "true_share": float(g.mean()) if g.size else float("nan"),
    }


def displacement_nees(
    displacements: list[Displacement2D], camera: Trajectory, floor_m: float = 0.0
) -> dict[str, float]:
    """Normalised estimation error squared of visual displacements against the true camera
    displacement over the same interval: e^T (C + floor^2 I)^-1 e, 2 dof. A consistent
    front end has mean ~2 and ~95 % of values below 5.99; the error is in cm too."""
    if not displacements:
        nan = float("nan")
        return {"n": 0, "mean": nan, "p95": nan, "within_95": nan, "error_p95_cm": nan}
    t0 = np.array([d.t0_s for d in displacements])
    t1 = np.array([d.t1_s for d in displacements])
    true = camera.xz_at(t1) - camera.xz_at(t0)
    est = np.array([d.delta_xz_m for d in displacements], dtype=float)
    err = est - true
    cov = np.array([d.cov_m2 for d in displacements], dtype=float) + np.eye(2) * floor_m**2
    nees = np.einsum("ni,ni->n", err, np.linalg.solve(cov, err[..., None])[..., 0])
    return {
        "n": int(nees.size),
        "mean": float(np.mean(nees)),
        "p95": float(np.percentile(nees, 95)),
        "within_95": float(np.mean(nees < chi2_2dof_quantile(0.95))),
        "error_p95_cm": float(100 * np.percentile(np.hypot(err[:, 0], err[:, 1]), 95)),
    }


def position_nees(
    est_xz_m: NDArray[np.float64],
    cov_m2: NDArray[np.float64],
    true_xz_m: NDArray[np.float64],
) -> dict[str, dict[str, float]]:
    """Consistency of the filter's position covariance per axis (x, z): the error (both
    paths anchored at their first pose, as the ATE) squared over the filter's variance, per
    frame. A consistent filter has a mean of 1 and 0.68 / 0.95 of the frames within 1 / 2
    sigma; above 1 it is overconfident. ``est_xz_m``, ``true_xz_m`` (N, 2) m, ``cov_m2``
    (N, 2, 2) m^2; frames with a zero variance are left out."""
    est = np.asarray(est_xz_m, dtype=float)
    true = np.asarray(true_xz_m, dtype=float)
    var = np.asarray(cov_m2, dtype=float).reshape(-1, 2, 2)[:, [0, 1], [0, 1]]
    err = (est - est[:1]) - (true - true[:1])
    out = {}
    for j, axis in enumerate("xz"):
        ok = var[:, j] > 0
        nees = err[ok, j] ** 2 / var[ok, j]
        if nees.size == 0:
            nan = float("nan")
            out[axis] = {"n": 0, "mean": nan, "within_1sigma": nan, "within_2sigma": nan}
            continue
        out[axis] = {
            "n": int(nees.size),
            "mean": float(np.mean(nees)),
            "within_1sigma": float(np.mean(nees <= 1.0)),
            "within_2sigma": float(np.mean(nees <= 4.0)),
        }
    return out
