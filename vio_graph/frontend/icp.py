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
- Optional, off by default (``robust_kernel``, ``surface_radius_m``): after the trimmed ICP
  converges, reweighted iterations over every pair (Huber / Cauchy weights of the residual),
  measured against the nearest source point or against the source surface around each
  target point (soft correspondences). They make the answer continuous in the seed T0, which
  the trimmed nearest-neighbour ICP is not (docs/generalisation.md, "A seed-continuous ICP
  tried"). The pairs, RMS and covariance are then those the trimmed ICP keeps at the answer.

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

import math
import os
from dataclasses import dataclass
from typing import TYPE_CHECKING

import numpy as np
from numpy.typing import NDArray

from vio_graph.errors import FrontendError
from vio_graph.frontend.config import IcpConfig

if TYPE_CHECKING:  # scipy is imported where a KD-tree is built (numpy paths only)
    from scipy.spatial import cKDTree


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
    nb = nb.reshape(idx.size, k).T  # (k, M): one row per neighbour rank, contiguous gathers
    x = source[:, 0][nb]
    z = source[:, 1][nb]
    add = np.add.reduce  # the sum inside np.mean, without its Python overhead
    dx = x - add(x, axis=0) / k
    dz = z - add(z, axis=0) / k
    sxx = add(dx * dx, axis=0) / k
    szz = add(dz * dz, axis=0) / k
    sxz = add(dx * dz, axis=0) / k
    # direction of largest spread (tangent) has angle 0.5 * atan2(2 sxz, sxx - szz)
    theta = 0.5 * np.arctan2(2.0 * sxz, sxx - szz)
    normals = np.empty((theta.size, 2))
    normals[:, 0] = -np.sin(theta)
    normals[:, 1] = np.cos(theta)
    return normals


_Vec2 = tuple[float, float]


def _eig_sym2(a: float, b: float, c: float) -> tuple[_Vec2, tuple[_Vec2, _Vec2]]:
    """Eigen-decomposition of the symmetric 2x2 matrix [[a, b], [b, c]] in plain floats (what
    ``np.linalg.eigh`` returns, up to rounding and eigenvector signs, at a fraction of its call
    overhead): eigenvalues ascending and their unit eigenvectors."""
    half_trace = 0.5 * (a + c)
    radius = math.hypot(0.5 * (a - c), b)
    theta = 0.5 * math.atan2(2.0 * b, a - c)  # direction of the larger eigenvalue
    cos_t, sin_t = math.cos(theta), math.sin(theta)
    return (half_trace - radius, half_trace + radius), ((-sin_t, cos_t), (cos_t, sin_t))


class _NearestSource:
    """Nearest source point of every target point moved back by T: the same distances and
    matched coordinates as ``tree.query(target - T, k=1, distance_upper_bound=max_distance_m)``,
    cheaper over the ICP iterations, where T moves by millimetres.

    A k-nearest query at a translation T_c stores ``n_candidates`` candidates per target point
    and a radius r that no other source point is closer than (the last candidate's distance,
    or the search bound). At T, with shift s = |T - T_c|, every other source point is at least
    r - s away, so the nearest candidate is THE nearest source point when its distance is
    below r - s (and "nothing within max_distance_m" holds when r - s >= max_distance_m).
    Rows where that does not hold trigger a new k-nearest query at T. Distances are computed
    exactly as the KD-tree computes them (bit-identical). Two candidates at exactly the same
    distance are resolved by the KD-tree itself (a k = 1 query of those rows), unless they are
    the same point twice (kNN smoothing produces exact duplicates): any of those gives the same
    coordinates, distance and normal.
    """

    def __init__(
        self,
        src: NDArray[np.float64],
        tree: cKDTree,
        tgt: NDArray[np.float64],
        max_distance_m: float,
        n_candidates: int = 8,
        margin_m: float = 0.02,
    ) -> None:
        self._tree, self._tgt = tree, tgt
        self._n_src = src.shape[0]
        self._k = min(n_candidates, self._n_src)
        self._max = max_distance_m
        self._max2 = max_distance_m * max_distance_m
        self._bound = max_distance_m + margin_m
        self._sx = np.append(src[:, 0], np.inf)  # index n_src = "no neighbour" (the tree's)
        self._sz = np.append(src[:, 1], np.inf)
        self._cols = np.arange(tgt.shape[0])
        self._T_c = (math.nan, math.nan)
        self.candidates = np.zeros((0, tgt.shape[0]), dtype=np.intp)

    def _query_candidates(self, q: NDArray[np.float64], T: NDArray[np.float64]) -> None:
        d, c = self._tree.query(q, k=self._k, distance_upper_bound=self._bound)
        d, c = d.reshape(q.shape[0], -1), c.reshape(q.shape[0], -1)
        self.candidates = np.ascontiguousarray(c.T)  # (k, Nt): rows are candidate ranks
        self.candidate_dist = np.ascontiguousarray(d.T)
        cx, cz = self._sx[self.candidates], self._sz[self.candidates]
        # a point listed twice (exact duplicates sit at adjacent ranks) is hidden behind its
        # first listing: the same coordinates, distance and normal
        again = (cx[1:] == cx[:-1]) & (cz[1:] == cz[:-1])
        cx[1:][again] = np.inf
        cz[1:][again] = np.inf
        self._cx, self._cz = cx, cz
        self._radius = np.minimum(d[:, -1], self._bound)
        if self._k == self._n_src:  # rows that hold every source point: no other point
            self._radius[np.isfinite(d[:, -1])] = np.inf
        self._T_c = (float(T[0]), float(T[1]))

    def query(self, T: NDArray[np.float64]) -> tuple[NDArray[np.float64], NDArray[np.intp]]:
        """Distances (inf: none within max_distance_m) and source indices (n_src: none)."""
        q = self._tgt - T
        qx, qz = q[:, 0], q[:, 1]
        for attempt in range(2):
            shift = math.hypot(T[0] - self._T_c[0], T[1] - self._T_c[1])  # nan before any
            if attempt == 0 and not shift < 1.0:
                self._query_candidates(q, T)
                continue
            d2 = qx - self._cx
            d2 *= d2
            dz = qz - self._cz
            dz *= dz
            d2 += dz  # (k, Nt): (x - x')^2 + (z - z')^2, the KD-tree's arithmetic
            flat = d2.argmin(axis=0) * self._cols.size + self._cols
            best2 = d2.ravel()[flat]
            best = np.sqrt(best2)
            # lower bound of the distance of any non-candidate point, with a rounding margin;
            # rows without a neighbour need it >= max_distance_m (conservatively: >)
            clear = self._radius - (shift * (1.0 + 1e-9) + 1e-12)
            exact = np.minimum(best, self._max) < clear
            if attempt == 0 and not exact.all():
                self._query_candidates(q, T)
                continue
            break
        found = best2 < self._max2
        tie = np.count_nonzero(d2 == best2, axis=0) > 1  # two distinct points, same distance
        j = np.where(found, self.candidates.ravel()[flat], self._n_src)
        dist = np.where(found, best, np.inf)
        redo = np.flatnonzero((tie & found) | ~exact)
        if redo.size:
            dist[redo], j[redo] = self._tree.query(q[redo], k=1, distance_upper_bound=self._max)
        return dist, j


class SourceNormals:
    """The compiled ICP's source normals, kept from one :func:`icp_translation_2d` call to the
    next on the same source points (e.g. the tracker's restart check: ICP again on the same
    source and target from another seed). A normal is the PCA of a source point's
    ``normal_neighbours`` nearest source points, a function of the source and that count
    alone, so a normal computed by an earlier call is the one a later call would compute, bit
    for bit. The cache holds a copy of the source it belongs to and starts afresh when a call
    brings other points or another neighbour count. The numpy path ignores it."""

    def __init__(self) -> None:
        self._src: NDArray[np.float64] | None = None
        self._k = -1
        self.normals = np.empty((0, 2))
        self.have = np.zeros(0, dtype=bool)

    def arrays(
        self, src: NDArray[np.float64], k: int
    ) -> tuple[NDArray[np.float64], NDArray[np.bool_]]:
        """(normals (Ns, 2), have (Ns,)) for ``src`` (contiguous float (Ns, 2)) and ``k``
        neighbours: the ones kept if they belong to these points and ``k``, else fresh."""
        if self._k != k or self._src is None or not np.array_equal(self._src, src):
            self._src, self._k = src.copy(), k
            self.normals = np.full(src.shape, np.nan)
            self.have = np.zeros(src.shape[0], dtype=bool)
        return self.normals, self.have


def icp_translation_2d(
    source_xz_m: NDArray[np.float64],
    target_xz_m: NDArray[np.float64],
    initial_translation_xz_m: NDArray[np.float64] | None = None,
    config: IcpConfig | None = None,
    source_tree: cKDTree | None = None,
    source_normals: SourceNormals | None = None,
) -> IcpResult:
    """Translation T (eq. 3-4) such that ``target ~= T + source``.

    Args:
        source_xz_m: (Ns, 2) source points P_s, metres.
        target_xz_m: (Nt, 2) target points P_t, metres.
        initial_translation_xz_m: (2,) T0 (default zero), metres.
        source_tree: optional prebuilt KD-tree of ``source_xz_m`` (numpy path only).
        source_normals: optional :class:`SourceNormals` shared by calls on the same source
            (compiled path only): normals an earlier call computed are not computed again.

    Returns:
        IcpResult. ``n_correspondences`` is 0 (and ``rms_m`` inf) when no pair is within
        ``max_correspondence_m``; the translation is then T0.

    The iterations run compiled (``compiled``, numba) when numba is installed; otherwise,
    and on the rare exact distance ties the kernel hands back, the numpy path
    :func:`icp_translation_2d_reference` runs (the same answer to rounding; tests compare them).
    The surface stage (``surface_radius_m``) always runs on the numpy path.
    """
    kernels = compiled_kernels()
    if kernels is None or config is not None and config.surface_radius_m is not None:
        return icp_translation_2d_reference(
            source_xz_m, target_xz_m, initial_translation_xz_m, config, source_tree
        )
    cfg, src, tgt, T0 = _icp_inputs(source_xz_m, target_xz_m, initial_translation_xz_m, config)
    if source_normals is None:
        normals0, have0 = np.full(src.shape, np.nan), np.zeros(src.shape[0], dtype=bool)
    else:
        normals0, have0 = source_normals.arrays(src, cfg.normal_neighbours)
    tx, tz, iterations, converged, keep, j, normals, status = kernels.icp_loop(
        src,
        tgt,
        float(T0[0]),
        float(T0[1]),
        cfg.max_iterations,
        cfg.convergence_m,
        cfg.max_correspondence_m,
        cfg.trim_fraction,
        cfg.normal_neighbours,
        cfg.metric != "point_to_point",
        cfg.degenerate_ratio,
        normals0,
        have0,
        True,
        kernels.ROBUST_KERNELS[cfg.robust_kernel],
        cfg.robust_scale,
        cfg.sigma_floor_m,
    )
    if status != 0:  # an exact tie: let the KD-tree decide, as the numpy path does
        return icp_translation_2d_reference(src, tgt, T0, cfg, source_tree)
    T = np.array([tx, tz])
    if keep.size == 0:
        return _no_correspondence(T, iterations, cfg)
    # the pairs, residuals and RMS of the numpy path below, in one compiled call
    pairs_t, pairs_s, residual, pair_normals, rms = kernels.icp_pairs(
        src, tgt, tx, tz, keep, j, normals
    )
    cov = _covariance(pair_normals, residual, cfg)
    return IcpResult(T, cov, iterations, converged, rms, int(keep.size), pairs_t, pairs_s)


_KERNELS: list = []  # [module or None] once imported
_MODES: dict[str | bytes | None, str] = {}  # VIO_GRAPH_COMPILED's value -> "off", "auto", ...
_AUTO = [False]  # what "auto" (VIO_GRAPH_COMPILED unset) means now; see use_compiled_by_default

#: VIO_GRAPH_COMPILED: "1" compiled kernels whenever numba is installed, "0" never (the numpy
#: paths; same answers), unset or "auto": when the run asked for them
#: (:func:`use_compiled_by_default`, e.g. the replay of a long recording). A process pays
#: ~0.5 s for numba's import and ~0.5-1 s to load the cached kernels (the first run on a
#: machine compiles them: ~10-20 s), which a short trial does not win back.
COMPILED_ENV = "VIO_GRAPH_COMPILED"

#: recordings with at least this many depth frames replay with the compiled kernels under
#: "auto" (15 s at 30 fps). Measured on the 2-core EPYC (`vio-graph run --no-rerun
#: --no-plots`, numba's cache warm, CPU seconds of the process, the two interleaved): a 30 s
#: trial (900 frames) takes 37 % less with the kernels in filter mode and 41 % less with
#: ``--mode all`` (three safety monitors, two smoothers' step means), the 105-frame sample
#: recording +20 % (filter) and -4 % (all); so they pay off from ~200 frames in filter mode,
#: ~100 with every mode. The threshold keeps the 10 s trials of the paper's experiments
#: (300 frames) and the sample on the numpy paths, whose answers the compiled ones match to
#: ~1e-12 m, not bit for bit.
AUTO_COMPILED_MIN_FRAMES = 450


def use_compiled_by_default(enabled: bool = True) -> None:
    """Whether "auto" (``VIO_GRAPH_COMPILED`` unset) uses the compiled kernels from now on."""
    _AUTO[0] = bool(enabled)


def _compiled_env_raw() -> str | bytes | None:
    """``VIO_GRAPH_COMPILED``'s value as the environment holds it (None when unset).
    ``os.environ.get`` costs ~1.5-3 us a call (the key encoded, the value decoded, the
    Mapping machinery), ~30 us a frame at the dozen calls the front end makes; CPython's
    ``os.environ`` keeps the encoded variables in a dict (``_data``, updated by every
    assignment or deletion through ``os.environ``, as ``monkeypatch.setenv`` makes them),
    which one lookup reads. Anything else: ``os.environ.get``."""
    env = os.environ
    data = getattr(env, "_data", None)
    if _ENV_KEY and isinstance(data, dict):
        return data.get(_ENV_KEY[0])
    return env.get(COMPILED_ENV)


def _env_key() -> list:
    """[the encoded key of ``VIO_GRAPH_COMPILED`` in ``os.environ._data``], or [] when the
    mapping does not have that layout."""
    encode = getattr(os.environ, "encodekey", None)
    data = getattr(os.environ, "_data", None)
    if encode is None or not isinstance(data, dict):
        return []
    try:
        key = encode(COMPILED_ENV)
    except Exception:  # pragma: no cover - an unusual platform: os.environ.get
        return []
    # the layout check: the value found through the dict is the one os.environ.get finds
    raw = data.get(key)
    value = os.environ.get(COMPILED_ENV)
    decoded = raw.decode() if isinstance(raw, bytes) else raw
    return [key] if decoded == value else []


_ENV_KEY = _env_key()


def compiled_kernels():
    """The numba kernels module (``vio_graph.frontend.compiled``), or None: without numba,
    with ``VIO_GRAPH_COMPILED=0``, or under "auto" until :func:`use_compiled_by_default`.
    Imported on first use, so a run that does not use it pays nothing."""
    raw = _compiled_env_raw()  # called a dozen times a frame: the parse cached
    mode = _MODES.get(raw)
    if mode is None:
        text = raw.decode() if isinstance(raw, bytes) else raw
        mode = "auto" if text is None else text.strip().lower()
        mode = "off" if mode in ("0", "false", "no", "off") else mode
        _MODES[raw] = mode
    if mode == "off" or (mode == "auto" and not _AUTO[0]):
        return None
    if not _KERNELS:
        try:
            from vio_graph.frontend import compiled as module
        except ImportError:  # numba not installed: the numpy path
            _KERNELS.append(None)
        else:
            _KERNELS.append(module)
    return _KERNELS[0]


def _check_point_sets(src: NDArray[np.float64], tgt: NDArray[np.float64]) -> None:
    if src.ndim != 2 or src.shape[1] != 2 or tgt.ndim != 2 or tgt.shape[1] != 2:
        raise FrontendError(f"ICP needs (N, 2) point sets, got {src.shape} and {tgt.shape}")
    if src.shape[0] == 0 or tgt.shape[0] == 0:
        raise FrontendError("ICP needs non-empty source and target point sets")


def _icp_inputs(
    source_xz_m: NDArray[np.float64],
    target_xz_m: NDArray[np.float64],
    initial_translation_xz_m: NDArray[np.float64] | None,
    config: IcpConfig | None,
) -> tuple[IcpConfig, NDArray[np.float64], NDArray[np.float64], NDArray[np.float64]]:
    """(config, source, target, initial translation) as both ICP paths take them: float,
    contiguous (N, 2) point sets checked, the translation a fresh (2,) array (zeros if none)."""
    cfg = IcpConfig() if config is None else config
    src = np.ascontiguousarray(source_xz_m, dtype=float)
    tgt = np.ascontiguousarray(target_xz_m, dtype=float)
    _check_point_sets(src, tgt)
    T0 = (
        np.zeros(2)
        if initial_translation_xz_m is None
        else np.array(initial_translation_xz_m, dtype=float)
    )
    return cfg, src, tgt, T0


def _no_correspondence(T: NDArray[np.float64], iterations: int, cfg: IcpConfig) -> IcpResult:
    return IcpResult(
        T,
        np.eye(2) * cfg.max_variance_m2,
        iterations,
        False,
        float("inf"),
        0,
        np.empty((0, 2)),
        np.empty((0, 2)),
    )


def icp_translation_2d_reference(
    source_xz_m: NDArray[np.float64],
    target_xz_m: NDArray[np.float64],
    initial_translation_xz_m: NDArray[np.float64] | None = None,
    config: IcpConfig | None = None,
    source_tree: cKDTree | None = None,
) -> IcpResult:
    """numpy path of :func:`icp_translation_2d` (KD-tree queries; the tested reference)."""
    cfg, src, tgt, T = _icp_inputs(source_xz_m, target_xz_m, initial_translation_xz_m, config)
    from scipy.spatial import cKDTree

    tree = cKDTree(src) if source_tree is None else source_tree
    normals = _NormalCache(src, tree, cfg.normal_neighbours)
    nearest = _NearestSource(src, tree, tgt, cfg.max_correspondence_m)
    point_to_line = cfg.metric != "point_to_point"
    robust = cfg.robust_kernel != "none"
    converged = False
    keep = np.zeros(0, dtype=np.intp)
    j = np.zeros(0, dtype=np.intp)
    iterations = 0
    stage = _TRIMMED  # then, with a robust kernel, _ROBUST and a _FINAL query at the answer
    tgt_normals: NDArray[np.float64] | None = None
    stage_iterations = 0
    while True:
        if stage != _FINAL:
            iterations += 1
            stage_iterations += 1
        # eq. 3: nearest source point of T + P_s for every target point
        dist, j = nearest.query(T)
        if iterations == 1 and point_to_line:  # the points later iterations may match, at once
            d = nearest.candidate_dist
            margin_m = _PREFETCH_M if cfg.normal_neighbours <= 8 else _PREFETCH_WIDE_K_M
            likely = (d <= d[0] + margin_m) & (d < cfg.max_correspondence_m)
            normals.prefetch(nearest.candidates[likely])
        keep = np.flatnonzero(dist < np.inf)
        if keep.size == 0:
            break
        if stage != _ROBUST and cfg.trim_fraction > 0 and keep.size >= 4:
            n_keep = max(3, math.ceil((1.0 - cfg.trim_fraction) * keep.size))
            keep = keep[np.argsort(dist[keep])[:n_keep]]
        if stage == _FINAL:  # the pairs of the answer, as the trimmed ICP would keep them
            break
        residual = tgt[keep] - T - src[j[keep]]
        if stage == _ROBUST and cfg.surface_radius_m is not None:
            if tgt_normals is None:  # the target's own normals: fixed, whatever T
                k = min(cfg.normal_neighbours, tgt.shape[0])
                tgt_normals = _source_normals(tgt, cKDTree(tgt), np.arange(tgt.shape[0]), k)
            dT = _surface_step(src, tgt - T, tree, normals, cfg, tgt_normals)
        elif stage == _ROBUST:
            n = normals.get(j[keep]) if point_to_line else None
            dT = _robust_step(n, residual, cfg)
        elif not point_to_line:
            # eq. 4: translation step = mean residual of the pairs
            dT = residual.mean(axis=0)
        else:
            # point-to-line: solve (sum n n^T) dT = sum n (n . r); needs the source normals
            dT = _point_to_line_step(normals.get(j[keep]), residual, cfg.degenerate_ratio)
        T = T + dT
        converged = math.hypot(dT[0], dT[1]) <= cfg.convergence_m
        if converged or stage_iterations >= cfg.max_iterations:
            if not robust:
                break
            stage = _ROBUST if stage == _TRIMMED else _FINAL
            stage_iterations = 0
    if keep.size == 0:
        return _no_correspondence(T, iterations, cfg)
    pairs_t, pairs_s = tgt[keep], src[j[keep]]
    residual = pairs_t - T - pairs_s
    rms = float(np.sqrt((residual**2).sum(axis=1).mean()))
    cov = _covariance(normals.get(j[keep]), residual, cfg)
    return IcpResult(T, cov, iterations, converged, rms, int(keep.size), pairs_t, pairs_s)


_TRIMMED, _ROBUST, _FINAL = 0, 1, 2  # stages of the ICP iterations (reference path)


def robust_weights(
    r: NDArray[np.float64], kernel: str, scale: float, sigma_floor_m: float
) -> NDArray[np.float64]:
    """IRLS weights of residuals ``r`` (m): the ``kernel``'s (``"cauchy"``: 1 / (1 + (r/c)^2),
    ``"huber"``: min(1, c / |r|)) with c = ``scale`` x sigma, sigma = 1.4826 x median |r|
    floored at ``sigma_floor_m``. Smooth in r (Huber: continuous), so the reweighted
    minimiser moves continuously with the pairs."""
    a = np.abs(r)
    c = scale * max(1.4826 * float(np.median(a)), sigma_floor_m)
    if kernel == "cauchy":
        u = a / c
        return 1.0 / (1.0 + u * u)
    if kernel == "huber":
        return np.where(a <= c, 1.0, c / np.maximum(a, c))
    raise FrontendError(f"unknown robust kernel {kernel!r}")


def _robust_step(
    n: NDArray[np.float64] | None, residual: NDArray[np.float64], cfg: IcpConfig
) -> NDArray[np.float64]:
    """One IRLS step over all pairs: the weighted point-to-line step (``n`` the source normals)
    or, with ``n`` None, the weighted mean residual (point-to-point, weights of the distance)."""
    if n is None:
        w = robust_weights(
            np.hypot(residual[:, 0], residual[:, 1]),
            cfg.robust_kernel,
            cfg.robust_scale,
            cfg.sigma_floor_m,
        )
        return (w[:, None] * residual).sum(axis=0) / w.sum()
    nx, nz = n[:, 0], n[:, 1]
    r_n = nx * residual[:, 0] + nz * residual[:, 1]
    w = robust_weights(r_n, cfg.robust_kernel, cfg.robust_scale, cfg.sigma_floor_m)
    return _weighted_point_to_line_step(w, nx, nz, r_n, cfg.degenerate_ratio)


def _weighted_point_to_line_step(
    w: NDArray[np.float64],
    nx: NDArray[np.float64],
    nz: NDArray[np.float64],
    r_n: NDArray[np.float64],
    degenerate_ratio: float,
) -> NDArray[np.float64]:
    """dT (m) solving (sum w n n^T) dT = sum w n r_n in the non-degenerate eigen-directions
    (weights ``w``, unit normals (``nx``, ``nz``), residuals along them ``r_n``)."""
    wx, wz = w * nx, w * nz
    (w0, w1), (v0, v1) = _eig_sym2(float(wx @ nx), float(wx @ nz), float(wz @ nz))
    gx, gz = float(wx @ r_n), float(wz @ r_n)
    floor = max(degenerate_ratio * w1, 1e-9)  # degenerate directions: no step
    dx = dz = 0.0
    for w_, (vx, vz) in ((w0, v0), (w1, v1)):
        if w_ > floor:
            step = (vx * gx + vz * gz) / w_
            dx += vx * step
            dz += vz * step
    return np.array([dx, dz])


def surface_residuals(
    src: NDArray[np.float64],
    q: NDArray[np.float64],
    tree: cKDTree,
    normals: _NormalCache,
    radius_m: float,
    q_normals: NDArray[np.float64] | None = None,
) -> tuple[NDArray[np.float64], NDArray[np.float64], NDArray[np.float64]]:
    """Residuals of points ``q`` (N, 2) to the source surface around them: (r (N,), unit
    normals (N, 2), support (N,)). Source points s_i within ``radius_m`` of q weigh
    phi_i = (1 - |q - s_i|^2 / radius^2)^2; the normal is the principal direction of
    sum phi_i n_i n_i^T (n_i the source normals), r = n . (q - c) with c the phi-weighted
    centroid, support = sum phi_i (0: nothing within the radius, r = 0). Every term is
    continuous in q: points enter and leave the neighbourhood with weight 0.

    ``q_normals`` (N, 2): the points' own normals (fixed, whatever T). Each phi_i is then
    multiplied by (n_i . m)^8 (1 for parallel normals, 0.06 at 45 deg, 0 at 90 deg), so a
    riser point next to a nosing is measured against the riser, not a blend of riser and
    tread (which rounds the corner and biases T)."""
    lists = tree.query_ball_point(q, radius_m, return_sorted=True)
    lens = np.fromiter((len(x) for x in lists), dtype=np.intp, count=len(lists))
    n_q = q.shape[0]
    if lens.sum() == 0:
        return np.zeros(n_q), np.zeros((n_q, 2)), np.zeros(n_q)
    idx = np.concatenate([np.asarray(x, dtype=np.intp) for x in lists if len(x)])
    row = np.repeat(np.arange(n_q), lens)
    d = q[row] - src[idx]
    u = 1.0 - (d[:, 0] ** 2 + d[:, 1] ** 2) / radius_m**2
    phi = np.where(u > 0.0, u * u, 0.0)
    nrm = normals.get(idx)
    if q_normals is not None:
        cos2 = (nrm[:, 0] * q_normals[row, 0] + nrm[:, 1] * q_normals[row, 1]) ** 2
        phi = phi * cos2**4

    def total(v: NDArray[np.float64]) -> NDArray[np.float64]:
        return np.bincount(row, weights=v, minlength=n_q).astype(float)

    support = total(phi)
    a = total(phi * nrm[:, 0] * nrm[:, 0])
    b = total(phi * nrm[:, 0] * nrm[:, 1])
    c = total(phi * nrm[:, 1] * nrm[:, 1])
    theta = 0.5 * np.arctan2(2.0 * b, a - c)  # the larger eigenvalue's direction
    n = np.column_stack([np.cos(theta), np.sin(theta)])
    has = support > 0.0
    cx = total(phi * src[idx, 0])
    cz = total(phi * src[idx, 1])
    safe = np.where(has, support, 1.0)
    r = np.where(has, n[:, 0] * (q[:, 0] - cx / safe) + n[:, 1] * (q[:, 1] - cz / safe), 0.0)
    return r, n, support


def _surface_step(
    src: NDArray[np.float64],
    q: NDArray[np.float64],
    tree: cKDTree,
    normals: _NormalCache,
    cfg: IcpConfig,
    q_normals: NDArray[np.float64] | None = None,
) -> NDArray[np.float64]:
    """One reweighted point-to-surface step: (sum a w n n^T) dT = sum a w n r over the target
    points, a = support / (1 + support) (fades out at the neighbourhood's edge), w the robust
    kernel's weight of r (scale from the points with support)."""
    assert cfg.surface_radius_m is not None
    r, n, support = surface_residuals(src, q, tree, normals, cfg.surface_radius_m, q_normals)
    has = support > 0.0
    if not has.any():
        return np.zeros(2)
    r, n, support = r[has], n[has], support[has]
    w = robust_weights(r, cfg.robust_kernel, cfg.robust_scale, cfg.sigma_floor_m)
    w = w * support / (1.0 + support)
    return _weighted_point_to_line_step(w, n[:, 0], n[:, 1], r, cfg.degenerate_ratio)


def _point_to_line_step(
    n: NDArray[np.float64], residual: NDArray[np.float64], degenerate_ratio: float
) -> NDArray[np.float64]:
    """dT solving (sum n n^T) dT = sum n (n . r) in the non-degenerate eigen-directions (unit
    weights: 1.0 * x is x, so the same floats as without them)."""
    nx, nz = n[:, 0], n[:, 1]
    r_n = nx * residual[:, 0] + nz * residual[:, 1]
    return _weighted_point_to_line_step(np.ones_like(nx), nx, nz, r_n, degenerate_ratio)


#: normals are computed up front for the candidates this close (m) to each target's nearest at
#: T0 (later iterations mostly match those); the rest on demand. Narrower when a normal costs
#: more (many neighbours): measured on the simulated trials, 5 mm / 1 mm is the faster choice.
_PREFETCH_M = 0.005
_PREFETCH_WIDE_K_M = 0.001


class _NormalCache:
    """Source normals computed on demand (only for matched points) and kept."""

    def __init__(self, src: NDArray[np.float64], tree: cKDTree, k: int) -> None:
        self._src, self._tree, self._k = src, tree, k
        self._normals = np.empty(src.shape)
        self._have = np.zeros(src.shape[0], dtype=bool)

    def prefetch(self, idx: NDArray[np.intp]) -> None:
        """Compute the normals of source points ``idx`` now, in one KD-tree query (entries
        >= the number of source points, the tree's "no neighbour", are skipped)."""
        idx = np.unique(idx)
        idx = idx[idx < self._have.size]
        self.get(idx)

    def get(self, idx: NDArray[np.intp]) -> NDArray[np.float64]:
        missing = idx[~self._have[idx]]
        if missing.size:
            self._normals[missing] = _source_normals(self._src, self._tree, missing, self._k)
            self._have[missing] = True
        return self._normals[idx]


def _covariance(
    normals: NDArray[np.float64], residual: NDArray[np.float64], cfg: IcpConfig
) -> NDArray[np.float64]:
    """Point-to-line covariance of T (module docstring), eigenvalues capped."""
    nx, nz = normals[:, 0], normals[:, 1]
    r_n = nx * residual[:, 0] + nz * residual[:, 1]
    sigma2 = max(float(r_n @ r_n) / r_n.size, cfg.sigma_floor_m**2)
    (w0, w1), (v0, v1) = _eig_sym2(float(nx @ nx), float(nx @ nz), float(nz @ nz))
    floor = max(cfg.degenerate_ratio * w1, 1e-9)
    # sum_k var_k v_k v_k^T on Python floats: the same products and sums, in the same order,
    # as adding the two outer products to a zero array (one array at the end)
    xx = xz = zz = 0.0
    for w, (vx, vz) in ((w0, v0), (w1, v1)):
        var = min(sigma2 * cfg.cov_inflation / max(w, 1e-12), cfg.max_variance_m2)
        if cfg.metric == "point_to_line" and w <= floor:
            var = cfg.max_variance_m2
        xx += var * (vx * vx)
        xz += var * (vx * vz)
        zz += var * (vz * vz)
    return np.array([[xx, xz], [xz, zz]])
