"""Trajectory error metrics: the paper's ATE per axis, aligned APE and RPE.

All functions take trajectories that are already associated (same timestamps, see
:func:`vio_graph.evaluation.association.associate`) and return frozen result objects holding
the statistics, the per-sample errors and the alignment that was used. Nothing is mutated.
Errors are ``estimate - reference`` in metres, world frame (x forward, z up).
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Literal

import numpy as np
from numpy.typing import ArrayLike, NDArray

from vio_graph.errors import EvaluationError
from vio_graph.geometry import make_transform, matrix_from_quat_wxyz
from vio_graph.recording.streams import Trajectory

M_TO_CM = 100.0


@dataclass(frozen=True)
class ErrorStats:
    """Statistics of non-negative error magnitudes (m), as evo reports them."""

    rmse: float
    mean: float
    median: float
    std: float
    min: float
    max: float
    sse: float
    n: int

    @classmethod
    def of(cls, err_m: ArrayLike) -> ErrorStats:
        """Statistics of the magnitudes ``err_m`` (N,)."""
        e = np.abs(np.asarray(err_m, dtype=float))
        if e.size == 0:
            raise EvaluationError("no samples to compute statistics over")
        return cls(
            rmse=float(np.sqrt(np.mean(e**2))),
            mean=float(np.mean(e)),
            median=float(np.median(e)),
            std=float(np.std(e)),
            min=float(np.min(e)),
            max=float(np.max(e)),
            sse=float(np.sum(e**2)),
            n=int(e.size),
        )


@dataclass(frozen=True)
class AteResult:
    """The paper's absolute trajectory error (Section III.B).

    ``errors_xyz_m`` (N, 3) signed per-sample errors at ``timestamp_s`` (N,) -- only the samples
    inside the mask; ``translation_m`` (3,) the offset added to the estimate.
    """

    timestamp_s: NDArray[np.float64]
    errors_xyz_m: NDArray[np.float64]
    translation_m: NDArray[np.float64]
    anchor: str
    rmse_x_m: float
    rmse_z_m: float
    rmse_total_m: float  # over the 3D error norm (= x-z norm for sagittal trajectories)
    stats: ErrorStats  # of the 3D error norms

    @property
    def rmse_x_cm(self) -> float:
        return self.rmse_x_m * M_TO_CM

    @property
    def rmse_z_cm(self) -> float:
        return self.rmse_z_m * M_TO_CM

    @property
    def rmse_total_cm(self) -> float:
        return self.rmse_total_m * M_TO_CM


@dataclass(frozen=True)
class Alignment:
    """A similarity transform applied to the estimate: p' = scale * R p + t."""

    kind: str
    rotation: NDArray[np.float64]  # (3, 3)
    translation_m: NDArray[np.float64]  # (3,)
    scale: float = 1.0

    def matrix(self) -> NDArray[np.float64]:
        """4x4 homogeneous matrix [[s R, t], [0, 1]]."""
        return make_transform(self.scale * self.rotation, self.translation_m)

    def apply(self, position_m: NDArray[np.float64]) -> NDArray[np.float64]:
        """Transform positions (N, 3); returns a new array."""
        return self.scale * position_m @ self.rotation.T + self.translation_m


@dataclass(frozen=True)
class ApeResult:
    """Absolute position error after an alignment (evo's APE, translation part)."""

    timestamp_s: NDArray[np.float64]
    errors_xyz_m: NDArray[np.float64]  # (N, 3) signed, inside the mask
    alignment: Alignment
    stats: ErrorStats  # of the error norms
    rmse_x_m: float
    rmse_z_m: float


@dataclass(frozen=True)
class RpeResult:
    """Relative position error over a time delta: e = (p_est[j] - p_est[i]) - (p_ref[j] -
    p_ref[i]) for pairs with t_j - t_i ~= ``delta_s``."""

    delta_s: float
    pairs: NDArray[np.int64]  # (K, 2) indices (i, j)
    errors_xyz_m: NDArray[np.float64]  # (K, 3)
    stats: ErrorStats
    rmse_x_m: float
    rmse_z_m: float


def ate_per_axis(
    traj_est: Trajectory,
    traj_ref: Trajectory,
    anchor: Literal["first", "mean", "none"] = "first",
    mask: ArrayLike | None = None,
) -> AteResult:
    """The paper's ATE: anchor the estimate to the ground truth, then RMSE per axis (m).

    ``anchor="first"`` translates the estimate so that its first position equals the ground
    truth's first position (no rotation, no scale) -- what the paper does and what evo's
    ``align_origin`` does when the first orientations are equal. ``"mean"`` removes the mean
    offset instead (the least-squares translation), ``"none"`` compares raw positions.
    The anchor always uses the first sample, even if ``mask`` excludes it; ``mask`` (N,) bool
    selects the samples that enter the errors (e.g. the obstacle's visible periods).
    """
    est_p, ref_p = _check_pair(traj_est, traj_ref)
    keep = _mask(mask, est_p.shape[0])
    if anchor == "first":
        t = ref_p[0] - est_p[0]
    elif anchor == "mean":
        t = np.mean(ref_p[keep] - est_p[keep], axis=0)
    elif anchor == "none":
        t = np.zeros(3)
    else:
        raise EvaluationError(f"unknown anchor {anchor!r}; use 'first', 'mean' or 'none'")
    err = (est_p + t - ref_p)[keep]
    norms = np.linalg.norm(err, axis=1)
    stats = ErrorStats.of(norms)
    return AteResult(
        timestamp_s=np.asarray(traj_est.timestamp_s, dtype=float)[keep].copy(),
        errors_xyz_m=err,
        translation_m=t,
        anchor=anchor,
        rmse_x_m=_rmse(err[:, 0]),
        rmse_z_m=_rmse(err[:, 2]),
        rmse_total_m=stats.rmse,
        stats=stats,
    )


def umeyama_alignment(
    x: ArrayLike, y: ArrayLike, with_scale: bool = False
) -> tuple[NDArray[np.float64], NDArray[np.float64], float]:
    """Least-squares similarity (R, t, c) minimising sum ||y_i - (c R x_i + t)||^2.

    Umeyama, "Least-squares estimation of transformation parameters between two point
    patterns", IEEE PAMI 13(4), 1991. ``x``, ``y``: (m, n) points as columns (m = dimension).
    Returns R (m, m), t (m,), c (1.0 unless ``with_scale``).
    """
    x = np.asarray(x, dtype=float)
    y = np.asarray(y, dtype=float)
    if x.shape != y.shape or x.ndim != 2:
        raise EvaluationError(f"point sets must have equal (m, n) shapes, got {x.shape} {y.shape}")
    m, n = x.shape
    mean_x, mean_y = x.mean(axis=1), y.mean(axis=1)  # eq. 34, 35
    xc, yc = x - mean_x[:, None], y - mean_y[:, None]
    sigma_x2 = np.sum(xc**2) / n  # eq. 36
    cov_xy = yc @ xc.T / n  # eq. 38
    u, d, vt = np.linalg.svd(cov_xy)  # SVD, text between eq. 38 and 39
    if np.count_nonzero(d > np.finfo(float).eps) < m - 1:
        raise EvaluationError("degenerate point set: Umeyama alignment is not possible")
    s = np.eye(m)  # eq. 39 / 43: reflection guard
    if np.linalg.det(u) * np.linalg.det(vt) < 0.0:
        s[m - 1, m - 1] = -1.0
    R = u @ s @ vt  # eq. 40
    c = float(np.trace(np.diag(d) @ s) / sigma_x2) if with_scale else 1.0  # eq. 42
    t = mean_y - c * R @ mean_x  # eq. 41
    return R, t, c


def align(
    traj_est: Trajectory,
    traj_ref: Trajectory,
    kind: Literal["none", "origin", "translation", "se2", "se3", "sim3"],
    mask: ArrayLike | None = None,
) -> Alignment:
    """The transform that aligns ``traj_est`` to ``traj_ref``.

    - ``origin``: world_T_ref0 * inv(world_T_est0), the full first-pose alignment of evo's
      ``align_origin`` (rotation from the first orientations, then translation);
    - ``translation``: least-squares translation (mean offset);
    - ``se2``: Umeyama rotation about y + translation in the x-z plane (sagittal);
    - ``se3`` / ``sim3``: Umeyama in 3D, without / with scale.
    Least-squares alignments use only the samples in ``mask``.
    """
    est_p, ref_p = _check_pair(traj_est, traj_ref)
    keep = _mask(mask, est_p.shape[0])
    if kind == "none":
        return Alignment(kind, np.eye(3), np.zeros(3))
    if kind == "origin":
        R_ref0 = matrix_from_quat_wxyz(traj_ref.quat_wxyz[0])
        R_est0 = matrix_from_quat_wxyz(traj_est.quat_wxyz[0])
        R = R_ref0 @ R_est0.T
        return Alignment(kind, R, ref_p[0] - R @ est_p[0])
    if kind == "translation":
        return Alignment(kind, np.eye(3), np.mean(ref_p[keep] - est_p[keep], axis=0))
    if kind == "se2":
        R2, t2, _ = umeyama_alignment(est_p[keep][:, [0, 2]].T, ref_p[keep][:, [0, 2]].T)
        R = np.eye(3)
        R[np.ix_([0, 2], [0, 2])] = R2
        t = np.array([t2[0], np.mean(ref_p[keep, 1] - est_p[keep, 1]), t2[1]])
        return Alignment(kind, R, t)
    if kind in ("se3", "sim3"):
        R, t, c = umeyama_alignment(est_p[keep].T, ref_p[keep].T, with_scale=kind == "sim3")
        return Alignment(kind, R, t, c)
    raise EvaluationError(f"unknown alignment {kind!r}")


def ape(
    traj_est: Trajectory,
    traj_ref: Trajectory,
    alignment: Literal["none", "origin", "translation", "se2", "se3", "sim3"] = "se3",
    mask: ArrayLike | None = None,
) -> ApeResult:
    """Absolute position error after :func:`align` (evo's APE with PoseRelation.translation_part).

    ``mask`` (N,) bool selects the samples used for the alignment and the statistics.
    """
    est_p, ref_p = _check_pair(traj_est, traj_ref)
    keep = _mask(mask, est_p.shape[0])
    al = align(traj_est, traj_ref, alignment, keep)
    err = (al.apply(est_p) - ref_p)[keep]
    return ApeResult(
        timestamp_s=np.asarray(traj_est.timestamp_s, dtype=float)[keep].copy(),
        errors_xyz_m=err,
        alignment=al,
        stats=ErrorStats.of(np.linalg.norm(err, axis=1)),
        rmse_x_m=_rmse(err[:, 0]),
        rmse_z_m=_rmse(err[:, 2]),
    )


def rpe(
    traj_est: Trajectory,
    traj_ref: Trajectory,
    delta_s: float,
    tolerance_s: float | None = None,
    all_pairs: bool = True,
) -> RpeResult:
    """Relative position error over ``delta_s`` seconds (e.g. 0.1 s or 1 s).

    For each i, j is the sample whose time is closest to t_i + delta_s; pairs further than
    ``tolerance_s`` (default: half the median sampling interval) from that time are dropped.
    ``all_pairs=False`` uses non-overlapping pairs only (i, j, then j, ...), like evo.
    Orientation is not used: the error is the difference of the displacement vectors.
    """
    est_p, ref_p = _check_pair(traj_est, traj_ref)
    t = np.asarray(traj_est.timestamp_s, dtype=float)
    if delta_s <= 0:
        raise EvaluationError(f"delta_s must be > 0, got {delta_s}")
    if t.size < 2:
        raise EvaluationError("RPE needs at least two poses")
    tol = 0.5 * float(np.median(np.diff(t))) if tolerance_s is None else float(tolerance_s)
    target = t + delta_s
    j = np.clip(np.searchsorted(t, target), 1, t.size - 1)
    j = np.where(np.abs(t[j - 1] - target) < np.abs(t[j] - target), j - 1, j)
    ok = (np.abs(t[j] - target) <= tol) & (j > np.arange(t.size))
    i = np.flatnonzero(ok)
    j = j[ok]
    if not all_pairs and i.size:
        chain, nxt = [], {int(a): int(b) for a, b in zip(i, j, strict=True)}
        k = int(i[0])
        while k in nxt:  # follows the chain i -> j -> ...; length <= N, not a point loop
            chain.append((k, nxt[k]))
            k = nxt[k]
        pairs = np.array(chain, dtype=np.int64).reshape(-1, 2)
    else:
        pairs = np.column_stack([i, j]).astype(np.int64)
    if pairs.shape[0] == 0:
        raise EvaluationError(f"no pose pairs {delta_s} s apart (tolerance {tol} s)")
    a, b = pairs[:, 0], pairs[:, 1]
    err = (est_p[b] - est_p[a]) - (ref_p[b] - ref_p[a])
    return RpeResult(
        delta_s=float(delta_s),
        pairs=pairs,
        errors_xyz_m=err,
        stats=ErrorStats.of(np.linalg.norm(err, axis=1)),
        rmse_x_m=_rmse(err[:, 0]),
        rmse_z_m=_rmse(err[:, 2]),
    )


def _rmse(e: NDArray[np.float64]) -> float:
    return float(np.sqrt(np.mean(np.square(e))))


def _check_pair(
    traj_est: Trajectory, traj_ref: Trajectory
) -> tuple[NDArray[np.float64], NDArray[np.float64]]:
    est_p = np.asarray(traj_est.position_m, dtype=float)
    ref_p = np.asarray(traj_ref.position_m, dtype=float)
    if est_p.shape != ref_p.shape or est_p.ndim != 2 or est_p.shape[1] != 3:
        raise EvaluationError(
            f"trajectories are not associated: shapes {est_p.shape} and {ref_p.shape}; "
            "call evaluation.association.associate() first"
        )
    if est_p.shape[0] == 0:
        raise EvaluationError("empty trajectories")
    if not np.allclose(traj_est.timestamp_s, traj_ref.timestamp_s, rtol=0.0, atol=1e-6):
        raise EvaluationError("trajectories have different timestamps; associate them first")
    return est_p, ref_p


def _mask(mask: ArrayLike | None, n: int) -> NDArray[np.bool_]:
    if mask is None:
        return np.ones(n, dtype=bool)
    m = np.asarray(mask, dtype=bool)
    if m.shape != (n,):
        raise EvaluationError(f"mask must have shape ({n},), got {m.shape}")
    if not m.any():
        raise EvaluationError("mask selects no samples")
    return m
