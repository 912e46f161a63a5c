"""Time association of an estimated trajectory with ground truth (like evo's core/sync.py).

The ground truth (motion capture, 120 Hz) is denser than the estimate (30 fps), so instead of
snapping to the nearest ground-truth pose it is interpolated linearly (positions) and by
slerp (orientations) at the estimate's timestamps. An estimate is kept only where ground
truth exists on both sides within ``max_diff_s``, so mocap gaps (marker occlusions) are not
bridged by interpolation.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from numpy.typing import NDArray

from vio_graph.errors import EvaluationError
from vio_graph.recording.streams import Trajectory


@dataclass(frozen=True)
class AssociatedTrajectories:
    """An estimate and ground truth at the same ``timestamp_s`` (N,).

    ``est`` holds the kept estimate poses, ``ref`` the ground truth interpolated there;
    ``est_indices`` (N,) are the kept rows of the original estimate.
    """

    est: Trajectory
    ref: Trajectory
    est_indices: NDArray[np.int64]
    max_diff_s: float
    offset_s: float


def associate(
    traj_est: Trajectory,
    traj_ref: Trajectory,
    max_diff_s: float = 0.01,
    offset_s: float = 0.0,
) -> AssociatedTrajectories:
    """Interpolate ``traj_ref`` at the timestamps of ``traj_est``.

    Args:
        traj_est: estimated trajectory (N timestamps, strictly increasing).
        traj_ref: ground truth (M timestamps, strictly increasing), usually denser.
        max_diff_s: largest gap (s) between an estimate timestamp and the ground-truth samples
            on either side of it.
        offset_s: added to the estimate's timestamps before matching (estimate clock ->
            ground-truth clock); the returned trajectories keep the estimate's clock.

    Raises:
        EvaluationError: a trajectory is empty / unordered, or no timestamp matches.
    """
    t_est = np.asarray(traj_est.timestamp_s, dtype=float)
    t_ref = np.asarray(traj_ref.timestamp_s, dtype=float)
    for name, t in (("estimate", t_est), ("ground truth", t_ref)):
        if t.size == 0:
            raise EvaluationError(f"the {name} trajectory is empty")
        if np.any(np.diff(t) <= 0):
            raise EvaluationError(f"the {name} timestamps are not strictly increasing")
    if max_diff_s < 0:
        raise EvaluationError(f"max_diff_s must be >= 0, got {max_diff_s}")
    tq = t_est + offset_s
    # right neighbour index (first ref time >= tq) and left neighbour
    hi = np.clip(np.searchsorted(t_ref, tq, side="left"), 0, t_ref.size - 1)
    lo = np.clip(hi - 1, 0, t_ref.size - 1)
    exact = np.isclose(t_ref[hi], tq, rtol=0.0, atol=1e-9)
    lo = np.where(exact, hi, lo)
    inside = (tq >= t_ref[0] - 1e-9) & (tq <= t_ref[-1] + 1e-9)
    close = (np.abs(tq - t_ref[lo]) <= max_diff_s) & (np.abs(t_ref[hi] - tq) <= max_diff_s)
    keep = np.flatnonzero(inside & close)
    if keep.size == 0:
        raise EvaluationError(
            f"found no matching timestamps between the estimate ({t_est[0]:.3f}..{t_est[-1]:.3f}"
            f" s) and the ground truth ({t_ref[0]:.3f}..{t_ref[-1]:.3f} s) with max. time diff "
            f"{max_diff_s} s and time offset {offset_s} s"
        )
    lo, hi, tq_k = lo[keep], hi[keep], tq[keep]
    span = t_ref[hi] - t_ref[lo]
    w = np.divide(tq_k - t_ref[lo], span, out=np.zeros_like(tq_k), where=span > 0)
    pos = (1.0 - w)[:, None] * traj_ref.position_m[lo] + w[:, None] * traj_ref.position_m[hi]
    quat = slerp_wxyz(traj_ref.quat_wxyz[lo], traj_ref.quat_wxyz[hi], w)
    est = Trajectory(
        t_est[keep].copy(), traj_est.position_m[keep].copy(), traj_est.quat_wxyz[keep].copy()
    )
    ref = Trajectory(t_est[keep].copy(), pos, quat)
    return AssociatedTrajectories(
        est, ref, keep.astype(np.int64), float(max_diff_s), float(offset_s)
    )


def slerp_wxyz(
    q0: NDArray[np.float64], q1: NDArray[np.float64], w: NDArray[np.float64]
) -> NDArray[np.float64]:
    """Spherical linear interpolation of unit quaternions (N, 4) [w, x, y, z] at w (N,) in [0, 1].

    Takes the shorter arc; falls back to normalised linear interpolation for nearly equal
    quaternions.
    """
    q0 = np.asarray(q0, dtype=float)
    q1 = np.asarray(q1, dtype=float).copy()
    w = np.asarray(w, dtype=float)[:, None]
    dot = np.sum(q0 * q1, axis=1, keepdims=True)
    q1 = np.where(dot < 0, -q1, q1)
    dot = np.abs(dot).clip(max=1.0)
    theta = np.arccos(dot)
    sin_t = np.sin(theta)
    small = sin_t < 1e-9
    safe = np.where(small, 1.0, sin_t)
    a = np.where(small, 1.0 - w, np.sin((1.0 - w) * theta) / safe)
    b = np.where(small, w, np.sin(w * theta) / safe)
    q = a * q0 + b * q1
    return q / np.linalg.norm(q, axis=1, keepdims=True)
