"""2D translation-only ICP (paper Section II.A.3, eq. 3-4).

With the slice rotated into the ground frame (eq. 2) the camera motion between frames is a pure
translation T in the x-z plane, and ``P_target ~= T + P_source``.

- Eq. 3: each target point P_i is matched to the nearest source point of ``T + P_s``
  (a KD-tree of the source, queried at ``P_i - T``).
- Eq. 4: the least-squares translation step for point-to-point pairs is the mean residual,
  ``dT = mean(P_i - (T + P'_i))``; ``T <- T + dT``. Stop when |dT| <= ``convergence_m``
  (paper: 1e-6) or after ``max_iterations`` (paper: 20).
- Metric: ``metric="point_to_point"`` is eq. 4 exactly. The default ``"point_to_line"``
  replaces the mean residual by the translation that minimises the residuals along the source
  normals, ``(sum n n^T) dT = sum n (n . r)``. With noisy points, point-to-point ICP stops
  where nearest-neighbour pairs stop changing and keeps part of the error of T0 along the
  tread (about half of a 4 mm IMU prediction error in the front-end test); point-to-line lets
  the riser points pull x all the way.
- Robustness (not in the paper): pairs farther than ``max_correspondence_m`` are ignored and,
  optionally, the worst ``trim_fraction`` of the rest (trimmed ICP).

Covariance (not in the paper). Point-to-point residuals cannot tell a well-constrained corner
from a flat tread that can slide along itself, so the covariance uses the point-to-line model
at the converged solution: for every kept pair the source's local normal n_i (PCA of its
``normal_neighbours`` nearest source points) gives the information sum_i n_i n_i^T / sigma^2,
with sigma^2 the mean squared point-to-line residual (floored at ``sigma_floor_m``^2).
Neighbouring points are correlated after kNN smoothing, so the covariance is inflated by
``cov_inflation`` (about the smoothing k). Unobservable directions (a flat tread along x) are
capped at ``max_variance_m2`` instead of infinity.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from numpy.typing import NDArray
from scipy.spatial import cKDTree

from vio_graph.errors import FrontendError
from vio_graph.frontend.config import IcpConfig


@dataclass(frozen=True)
class IcpResult:
    """Result of :func:`icp_translation_2d`.

    ``translation_xz_m`` (2,): T with target ~= T + source. ``cov_m2`` (2, 2): its covariance.
    ``target_points_xz_m`` (K, 2) and ``matched_source_xz_m`` (K, 2): the kept pairs at the
    last iteration (source points untransformed), for visualisation.
    """

    translation_xz_m: NDArray[np.float64]
    cov_m2: NDArray[np.float64]
    iterations: int
    converged: bool
    rms_m: float
    n_correspondences: int
    target_points_xz_m: NDArray[np.float64]
    matched_source_xz_m: NDArray[np.float64]


def _source_normals(
    source: NDArray[np.float64], tree: cKDTree, idx: NDArray[np.intp], k: int
) -> NDArray[np.float64]:
    """Unit normals (M, 2) of the source curve at source points ``idx`` (PCA of k neighbours)."""
    k = min(k, source.shape[0])
    _, nb = tree.query(source[idx], k=k)
    nb_pts = source[nb]  # (M, k, 2)
    d = nb_pts - nb_pts.mean(axis=1, keepdims=True)
    sxx = (d[..., 0] ** 2).mean(axis=1)
    szz = (d[..., 1] ** 2).mean(axis=1)
    sxz = (d[..., 0] * d[..., 1]).mean(axis=1)
    # direction of largest spread (tangent) has angle 0.5 * atan2(2 sxz, sxx - szz)
    theta = 0.5 * np.arctan2(2.0 * sxz, sxx - szz)
    return np.column_stack([-np.sin(theta), np.cos(theta)])


def icp_translation_2d(
    source_xz_m: NDArray[np.float64],
    target_xz_m: NDArray[np.float64],
    initial_translation_xz_m: NDArray[np.float64] | None = None,
    config: IcpConfig | None = None,
    source_tree: cKDTree | None = None,
) -> IcpResult:
    """Translation T (eq. 3-4) such that ``target ~= T + source``.

    Args:
        source_xz_m: (Ns, 2) source points P_s, metres.
        target_xz_m: (Nt, 2) target points P_t, metres.
        initial_translation_xz_m: (2,) T0 (default zero), metres.
        source_tree: optional prebuilt KD-tree of ``source_xz_m``.

    Returns:
        IcpResult. ``n_correspondences`` is 0 (and ``rms_m`` inf) when no pair is within
        ``max_correspondence_m``; the translation is then T0.
    """
    cfg = IcpConfig() if config is None else config
    src = np.asarray(source_xz_m, dtype=float)
    tgt = np.asarray(target_xz_m, dtype=float)
    if src.ndim != 2 or src.shape[1] != 2 or tgt.ndim != 2 or tgt.shape[1] != 2:
        raise FrontendError(f"ICP needs (N, 2) point sets, got {src.shape} and {tgt.shape}")
    if src.shape[0] == 0 or tgt.shape[0] == 0:
        raise FrontendError("ICP needs non-empty source and target point sets")
    T = np.zeros(2) if initial_translation_xz_m is None else np.array(
        initial_translation_xz_m, dtype=float
    )
    tree = cKDTree(src) if source_tree is None else source_tree
    normals = _NormalCache(src, tree, cfg.normal_neighbours)
    converged = False
    keep = np.zeros(0, dtype=np.intp)
    j = np.zeros(0, dtype=np.intp)
    iterations = 0
    for iterations in range(1, cfg.max_iterations + 1):
        # eq. 3: nearest source point of T + P_s for every target point
        dist, j = tree.query(tgt - T, k=1, distance_upper_bound=cfg.max_correspondence_m)
        keep = np.flatnonzero(np.isfinite(dist))
        if keep.size == 0:
            break
        if cfg.trim_fraction > 0 and keep.size >= 4:
            n_keep = max(3, int(np.ceil((1.0 - cfg.trim_fraction) * keep.size)))
            keep = keep[np.argsort(dist[keep])[:n_keep]]
        residual = tgt[keep] - T - src[j[keep]]
        if cfg.metric == "point_to_point":
            # eq. 4: translation step = mean residual of the pairs
            dT = residual.mean(axis=0)
        else:
            # point-to-line: solve (sum n n^T) dT = sum n (n . r); needs the source normals
            n = normals.get(j[keep])
            w, V = np.linalg.eigh(n.T @ n)
            ok = w > max(cfg.degenerate_ratio * w[-1], 1e-9)  # degenerate directions: no step
            b = V.T @ (n.T @ (n * residual).sum(axis=1))
            dT = V[:, ok] @ (b[ok] / w[ok])
        T = T + dT
        if np.linalg.norm(dT) <= cfg.convergence_m:
            converged = True
            break
    if keep.size == 0:
        return IcpResult(T, np.eye(2) * cfg.max_variance_m2, iterations, False, float("inf"), 0,
                         np.empty((0, 2)), np.empty((0, 2)))
    pairs_t, pairs_s = tgt[keep], src[j[keep]]
    residual = pairs_t - T - pairs_s
    rms = float(np.sqrt((residual**2).sum(axis=1).mean()))
    cov = _covariance(normals.get(j[keep]), residual, cfg)
    return IcpResult(T, cov, iterations, converged, rms, int(keep.size), pairs_t, pairs_s)


class _NormalCache:
    """Source normals computed on demand (only for matched points) and kept."""

    def __init__(self, src: NDArray[np.float64], tree: cKDTree, k: int) -> None:
        self._src, self._tree, self._k = src, tree, k
        self._normals = np.full(src.shape, np.nan)

    def get(self, idx: NDArray[np.intp]) -> NDArray[np.float64]:
        missing = np.unique(idx[np.isnan(self._normals[idx, 0])])
        if missing.size:
            self._normals[missing] = _source_normals(self._src, self._tree, missing, self._k)
        return self._normals[idx]


def _covariance(
    normals: NDArray[np.float64], residual: NDArray[np.float64], cfg: IcpConfig
) -> NDArray[np.float64]:
    """Point-to-line covariance of T (module docstring), eigenvalues capped."""
    r_n = (residual * normals).sum(axis=1)
    sigma2 = max(float((r_n**2).mean()), cfg.sigma_floor_m**2)
    info = normals.T @ normals  # sum n n^T, (2, 2)
    w, V = np.linalg.eigh(info)
    var = np.minimum(sigma2 * cfg.cov_inflation / np.maximum(w, 1e-12), cfg.max_variance_m2)
    if cfg.metric == "point_to_line":
        var[w <= max(cfg.degenerate_ratio * w[-1], 1e-9)] = cfg.max_variance_m2
    return (V * var) @ V.T
