"""Compiled ICP iterations (numba): the loop of :func:`vio_graph.frontend.icp.icp_translation_2d`
in one call, without numpy's per-call overhead on a few hundred points.

Same algorithm and arithmetic as the numpy path (``icp._icp_numpy``, the tested reference):

- nearest source point of each target point moved back by T (eq. 3), squared distances as
  the KD-tree computes them, ``(x - x')^2 + (z - z')^2``; a pair counts when that is below
  ``max_correspondence_m^2``. The source is bucketed once per call in a grid of 1 cm cells
  (``_grid``); a query looks only at the cells within reach: 5 mm in the first iteration
  (the whole correspondence distance if no point is surely that near), after it the distance
  of the point the same target matched in the previous iteration (T moves by millimetres,
  so a few cells). Among equally near points the one
  first in x order is kept, as the earlier scan of the x-sorted source did, so the pairs are
  the same bit for bit;
- the trimmed ICP, the point-to-line step and its eigen-decomposition, and the source normals
  (PCA of the ``normal_neighbours`` nearest source points, found in growing squares of grid
  cells and summed over the neighbours in distance order like ``icp._source_normals``; equal
  distances in the order of an outward scan in x, ``_before``).

Where the two could pick different points -- two distinct source points at exactly the same
distance from a target point, a distinct point tied with the k-th neighbour of a normal, or
two distinct pairs tied at the trimming cut -- the kernel stops and says so (status > 0), and
the caller runs the numpy path instead. Points within ``_SAME_M`` of each other count as one
(kNN smoothing leaves near duplicates a rounding step apart). Otherwise the answers agree to
rounding (tests/test_frontend_fastpaths.py, 1e-9 m).

numba is imported only here, and only when the first ICP runs (``cache=True``: compiled once
per machine, then loaded from ``__pycache__``).
"""

from __future__ import annotations

import math
from typing import Any

import numba
import numpy as np
from llvmlite import ir as llvm_ir
from numba.core import cgutils
from numba.core import types as nb_types
from numba.core.extending import intrinsic, overload_method
from numba.experimental import structref

from vio_graph.compiled_sums import pairwise_sum

_OK = 0
_TIE = 1  # a distinct source point as near as the matched one
_TIE_TRIM = 2  # distinct pairs at the same distance across the trimming cut
_TIE_NORMAL = 3  # a distinct point as near as a normal's k-th neighbour
#: points closer than this (m, per axis) count as the same point: kNN smoothing leaves near
#: duplicates one rounding step apart, and either gives the same answer to ~1e-18 m
_SAME_M = 1e-12


# ------------------------------------------------------------------ random generator handle


@structref.register
class _RngRefType(nb_types.StructRef):
    """numba type of :class:`RngRef`."""

    def preprocess_fields(self, fields):
        return tuple((name, nb_types.unliteral(typ)) for name, typ in fields)


class RngRef(structref.StructRefProxy):
    """A numpy Generator as the kernels see it, unboxed once. Passing the Generator itself
    costs every call ~25-45 us (numba types it in Python and unboxes its bit generator through
    three ``ctypes.cast`` calls); this handle costs a few us. It draws from the same bit
    generator state as the Generator (``integers`` forwards to it), so the draws and the
    Generator's later ones are the same as with the Generator passed directly."""


structref.define_proxy(RngRef, _RngRefType, ["rng"])


@overload_method(_RngRefType, "integers")
def _rng_ref_integers(self, low, high, size):  # pragma: no cover - compiled
    def impl(self, low, high, size):
        return self.rng.integers(low, high, size)

    return impl


@numba.njit(cache=True)
def _new_rng_ref(rng):  # pragma: no cover - compiled
    return RngRef(rng)


_RNG_REFS: list = []  # (Generator, its RngRef), the latest few


def rng_ref(rng: np.random.Generator) -> RngRef:
    """The :class:`RngRef` of ``rng`` (made on first use, kept for the latest 8 generators;
    each holds its Generator alive)."""
    for g, ref in _RNG_REFS:
        if g is rng:
            return ref
    ref = _new_rng_ref(rng)
    _RNG_REFS.append((rng, ref))
    del _RNG_REFS[:-8]
    return ref


@numba.njit(cache=True)
def _same(ax, az, bx, bz):  # pragma: no cover - compiled
    return abs(ax - bx) <= _SAME_M and abs(az - bz) <= _SAME_M


@numba.njit(cache=True)
def _eig_sym2(a, b, c):  # pragma: no cover - compiled
    half_trace = 0.5 * (a + c)
    radius = math.hypot(0.5 * (a - c), b)
    theta = 0.5 * math.atan2(2.0 * b, a - c)
    cos_t, sin_t = math.cos(theta), math.sin(theta)
    return half_trace - radius, half_trace + radius, -sin_t, cos_t, cos_t, sin_t


#: cell of the ICP source's bucket grid (m): a few smoothed profile points (~2 mm apart) per
#: cell, so a query looks at tens of points instead of the whole x window (a riser holds
#: every point at the same x)
_GRID_CELL_M = 0.01
#: first ICP iteration: each target's nearest source point is searched within this reach (m)
#: first, and within the whole correspondence distance only if none is surely that near
_FIRST_REACH_M = 0.005


@numba.njit(cache=True)
def _grid(pts, cell):  # pragma: no cover - compiled
    """Bucket grid of ``pts``: cell (ix, iz) = floor((p - origin) / cell), cells numbered
    ix * nz + iz, and the points of cell c at ``items[start[c]:start[c + 1]]`` (input order).
    The cell grows (doubles) until the grid has at most 4 N + 1024 cells. Returns
    (x0, z0, cell, nx, nz, start, items)."""
    n = pts.shape[0]
    x0 = pts[0, 0]
    x1 = x0
    z0 = pts[0, 1]
    z1 = z0
    for i in range(1, n):
        x0 = min(x0, pts[i, 0])
        x1 = max(x1, pts[i, 0])
        z0 = min(z0, pts[i, 1])
        z1 = max(z1, pts[i, 1])
    while True:
        nx = int((x1 - x0) / cell) + 1
        nz = int((z1 - z0) / cell) + 1
        if nx * nz <= 4 * n + 1024:
            break
        cell *= 2.0
    cid = np.empty(n, np.int64)
    start = np.zeros(nx * nz + 1, np.int64)
    for i in range(n):
        ix = min(int((pts[i, 0] - x0) / cell), nx - 1)
        iz = min(int((pts[i, 1] - z0) / cell), nz - 1)
        cid[i] = ix * nz + iz
        start[cid[i] + 1] += 1
    for c in range(nx * nz):
        start[c + 1] += start[c]
    fill = start[:-1].copy()
    items = np.empty(n, np.int64)
    for i in range(n):
        items[fill[cid[i]]] = i
        fill[cid[i]] += 1
    return x0, z0, cell, nx, nz, start, items


@numba.njit(cache=True)
def _cell_range(q, origin, cell, n_cells, reach):  # pragma: no cover - compiled
    """Cells [lo, hi] (clipped; lo > hi when none) holding every point within ``reach`` of
    coordinate ``q`` along one axis."""
    a = (q - reach - origin) / cell
    b = (q + reach - origin) / cell
    if not (b >= 0.0 and a < n_cells):  # also NaN
        return 1, 0
    lo = int(math.floor(a)) if a > 0.0 else 0
    hi = int(math.floor(b)) if b < n_cells else n_cells - 1
    return lo, min(hi, n_cells - 1)


@numba.njit(cache=True)
def _nearest(src, grid, rank, qx, qz, window, max2):  # pragma: no cover - compiled
    """Nearest source point of (qx, qz) among those within ``window`` per axis: (squared
    distance, index (n_src: none), tie, second). Squared distances as the KD-tree computes
    them; among points at the same distance the one first in x order (``rank``), as a scan of
    the x-sorted source would keep; ``tie`` when a distinct point (not within ``_SAME_M``) is
    as near as the kept one and within ``max2``; ``second`` the least squared distance of the
    other points searched (inf if none; a point at the kept one's distance counts)."""
    x0, z0, cell, nx, nz, start, items = grid
    ns = src.shape[0]
    ilo, ihi = _cell_range(qx, x0, cell, nx, window)
    klo, khi = _cell_range(qz, z0, cell, nz, window)
    best2 = np.inf
    second2 = np.inf
    bi = ns
    n_equal = 0
    if klo > khi:
        return best2, bi, False, second2
    for ix in range(ilo, ihi + 1):  # the cells klo..khi of a column are contiguous
        for s in range(start[ix * nz + klo], start[ix * nz + khi + 1]):
            m = items[s]
            dx = qx - src[m, 0]
            dz = qz - src[m, 1]
            d2 = dx * dx + dz * dz
            if d2 < best2:
                second2 = best2
                best2 = d2
                bi = m
                n_equal = 0
            elif d2 == best2:
                second2 = d2
                n_equal += 1
                if rank[m] < rank[bi]:
                    bi = m
            elif d2 < second2:
                second2 = d2
    tie = False
    if n_equal > 0 and best2 < max2:
        for ix in range(ilo, ihi + 1):
            for s in range(start[ix * nz + klo], start[ix * nz + khi + 1]):
                m = items[s]
                dx = qx - src[m, 0]
                dz = qz - src[m, 1]
                if (
                    m != bi
                    and dx * dx + dz * dz == best2
                    and not _same(src[m, 0], src[m, 1], src[bi, 0], src[bi, 1])
                ):
                    tie = True
    return best2, bi, tie, second2


@numba.njit(cache=True, inline="always")
def _before(d2, m, e2, e, px, pos, src, rank):  # pragma: no cover - compiled
    """True if point m at squared distance d2 comes before point e at e2 in the order of a
    scan outwards in x from sorted position ``pos`` (x ``px``) that keeps the nearest in
    arrival order (the scan the kernels used before the grid, and the order their sums keep):
    by distance, then by |x - px|, left before right, and outwards in x order on each side."""
    if d2 != e2:
        return d2 < e2
    am = abs(px - src[m, 0])
    ae = abs(px - src[e, 0])
    if am != ae:
        return am < ae
    rm, re = rank[m], rank[e]
    left_m, left_e = rm < pos, re < pos
    if left_m != left_e:
        return left_m
    return rm > re if left_m else rm < re


@numba.njit(cache=True, inline="always")
def _knn(src, grid, rank, i, kk, best_d, best_i):  # pragma: no cover - compiled
    """The kk nearest source points of source point i (itself included) into ``best_d`` /
    ``best_i`` (squared distances, indices), the same points in the same order as a scan
    outwards in x that keeps the nearest (``_before``), searched in growing squares of grid
    cells."""
    x0, z0, cell, nx, nz, start, items = grid
    px, pz = src[i, 0], src[i, 1]
    pos = rank[i]
    best_d[:kk] = np.inf
    best_i[:kk] = -1
    cx = min(int((px - x0) / cell), nx - 1)
    cz = min(int((pz - z0) / cell), nz - 1)
    margin = 1e-9 * cell + 1e-12  # cell assignment rounding
    r = 0
    while True:
        for ix in range(max(cx - r, 0), min(cx + r, nx - 1) + 1):
            edge = ix == cx - r or ix == cx + r
            for iz in range(max(cz - r, 0), min(cz + r, nz - 1) + 1):
                if not (edge or iz == cz - r or iz == cz + r):
                    continue  # inside: visited with a smaller square
                c = ix * nz + iz
                for s in range(start[c], start[c + 1]):
                    m = items[s]
                    dx = src[m, 0] - px
                    dz = src[m, 1] - pz
                    d2 = dx * dx + dz * dz
                    last = best_i[kk - 1]
                    if last >= 0 and not _before(d2, m, best_d[kk - 1], last, px, pos, src, rank):
                        continue
                    q = kk - 1
                    while q > 0 and (
                        best_i[q - 1] < 0
                        or _before(d2, m, best_d[q - 1], best_i[q - 1], px, pos, src, rank)
                    ):
                        best_d[q] = best_d[q - 1]
                        best_i[q] = best_i[q - 1]
                        q -= 1
                    best_d[q] = d2
                    best_i[q] = m
        # distance from (px, pz) to the nearest point outside the square searched so far
        out = np.inf
        if cx - r > 0:
            out = min(out, px - (x0 + (cx - r) * cell))
        if cx + r < nx - 1:
            out = min(out, x0 + (cx + r + 1) * cell - px)
        if cz - r > 0:
            out = min(out, pz - (z0 + (cz - r) * cell))
        if cz + r < nz - 1:
            out = min(out, z0 + (cz + r + 1) * cell - pz)
        if out == np.inf:
            break  # the whole grid searched
        out -= margin
        if best_i[kk - 1] >= 0 and out > 0.0 and out * out > best_d[kk - 1]:
            break
        r += 1


@numba.njit(cache=True)
def _tie_at_kth(src, grid, i, best_d, best_i, k):  # pragma: no cover - compiled
    """True if a point distinct from the k nearest of point i (``best_i[:k]``, from
    :func:`_knn`) lies at the k-th distance: the KD-tree of the numpy path may pick it."""
    x0, z0, cell, nx, nz, start, items = grid
    px, pz = src[i, 0], src[i, 1]
    dk = best_d[k - 1]
    reach = math.sqrt(dk) + 1e-9 * cell + 1e-12
    ilo, ihi = _cell_range(px, x0, cell, nx, reach)
    klo, khi = _cell_range(pz, z0, cell, nz, reach)
    for ix in range(ilo, ihi + 1):
        for s in range(start[ix * nz + klo], start[ix * nz + khi + 1]):
            m = items[s]
            dx = src[m, 0] - px
            dz = src[m, 1] - pz
            if dx * dx + dz * dz != dk:
                continue
            inside = False
            same = False
            for t in range(k):
                b = best_i[t]
                if b == m:
                    inside = True
                elif best_d[t] == dk and _same(src[b, 0], src[b, 1], src[m, 0], src[m, 1]):
                    same = True
            if not inside and not same:
                return True
    return False


@numba.njit(cache=True)
def _normal(src, grid, rank, i, k, best_d, best_i):  # pragma: no cover - compiled
    """Unit normal at source point i from its k nearest source points (itself included),
    the same neighbours in the same order as the x scan (:func:`_knn`); returns (nx, nz,
    tie). ``best_d`` / ``best_i``: scratch of length min(k + 1, n)."""
    n = src.shape[0]
    kk = min(k + 1, n)  # one more than needed: a tie at the k-th place is detected
    kn = min(k, n)
    _knn(src, grid, rank, i, kk, best_d, best_i)
    # a point distinct from the k kept ones at the k-th distance (only if the (k+1)-th is)
    tie = kk > kn and best_d[kn] == best_d[kn - 1] and _tie_at_kth(src, grid, i, best_d, best_i, kn)
    sx = 0.0
    sz = 0.0
    for r in range(kn):
        sx += src[best_i[r], 0]
        sz += src[best_i[r], 1]
    mx = sx / kn
    mz = sz / kn
    sxx = 0.0
    szz = 0.0
    sxz = 0.0
    for r in range(kn):
        dx = src[best_i[r], 0] - mx
        dz = src[best_i[r], 1] - mz
        sxx += dx * dx
        szz += dz * dz
        sxz += dx * dz
    sxx /= kn
    szz /= kn
    sxz /= kn
    theta = 0.5 * math.atan2(2.0 * sxz, sxx - szz)
    return -math.sin(theta), math.cos(theta), tie


@numba.njit(cache=True)
def _fill_normal(src, grid, rank, k, normals, have, m, best_d, best_i):  # pragma: no cover
    """Compute source point m's normal into ``normals`` once (``have`` marks it); True if a
    distance tie makes it ambiguous (the caller hands the case to the numpy path)."""
    if have[m]:
        return False
    nx, nz, tie = _normal(src, grid, rank, m, k, best_d, best_i)
    if tie:
        return True
    normals[m, 0] = nx
    normals[m, 1] = nz
    have[m] = True
    return False


@numba.njit(cache=True)
def icp_loop(
    src,
    tgt,
    t0x,
    t0z,
    max_iterations,
    convergence_m,
    max_correspondence_m,
    trim_fraction,
    normal_neighbours,
    point_to_line,
    degenerate_ratio,
    normals,
    have,
    keep_clear_matches=True,
    robust_kernel=0,
    robust_scale=2.385,
    sigma_floor_m=0.003,
):  # pragma: no cover - compiled
    """The ICP iterations. Returns (Tx, Tz, iterations, converged, keep, j, normals, status):
    ``keep`` the kept target indices of the last iteration (in the numpy path's order), ``j``
    (Nt,) matched source index per target (n_src: none), ``normals`` (Ns, 2) source normals
    (NaN where not computed), status 0 = fine, else a tie (``_TIE*``: run the numpy path).

    ``normals`` (Ns, 2) and ``have`` (Ns,) bool are the source normals known so far, filled in
    place (a normal is a function of the source points and ``normal_neighbours`` alone, so
    another ICP on the same source with the same ``normal_neighbours`` may pass them again:
    :class:`vio_graph.frontend.icp.SourceNormals`); fresh: NaN and False.

    ``keep_clear_matches``: a target point whose last match is still clearly its nearest
    source point is not searched again. Each search also gives a lower bound of the distance
    of every other source point (the second-nearest searched, or the search box's half-width
    for those not searched); when T moves by s, no other point comes more than s nearer, so
    a match nearer than that bound less s (with margins far above rounding) is what the search
    would return: the same point, the same squared distance (computed alike), no tie. False
    searches every time (the tests compare the two bit for bit).

    ``robust_kernel`` (0 none, ``_CAUCHY``, ``_HUBER``): after the trimmed iterations converge
    (or reach ``max_iterations``), up to ``max_iterations`` reweighted ones over every pair
    (weights ``_robust_weight`` of the point-to-line residual, or of the distance), then one
    more search at the answer for the trimmed pairs ``keep`` (the numpy path's stages)."""
    ns = src.shape[0]
    nt = tgt.shape[0]
    order = np.argsort(src[:, 0], kind="mergesort")
    rank = np.empty(ns, np.int64)  # position of each source point in the x order
    for r in range(ns):
        rank[order[r]] = r
    grid = _grid(src, max(_GRID_CELL_M, max_correspondence_m / 8.0))
    kk = min(normal_neighbours + 1, ns)
    best_d = np.empty(kk)  # scratch of the normals' neighbour search
    best_i = np.empty(kk, np.int64)
    max2 = max_correspondence_m * max_correspondence_m
    j = np.full(nt, ns, np.int64)
    dist = np.full(nt, np.inf)
    # per target point: no source point but j[i] is nearer than this (m) at the T of its
    # last search, less the moves of T since (keep_clear_matches)
    clear = np.zeros(nt)
    keep = np.zeros(0, np.int64)
    tx, tz = t0x, t0z
    px, pz = tx, tz  # T of the previous iteration
    converged = False
    iterations = 0
    stage = 0  # 0 trimmed, 1 reweighted (robust_kernel), 2 the final search at the answer
    stage_iterations = 0
    weights = np.empty(nt)
    window = max_correspondence_m * (1.0 + 1e-9) + 1e-12  # |x - x'| beyond: out of range
    while True:
        if stage != 2:
            iterations += 1
            stage_iterations += 1
        moved = math.hypot(tx - px, tz - pz) * (1.0 + 1e-9) + 1e-12
        px, pz = tx, tz
        # eq. 3: nearest source point of every target point moved back by T
        n_found = 0
        for i in range(nt):
            qx = tgt[i, 0] - tx
            qz = tgt[i, 1] - tz
            # T moves by millimetres between iterations: the point matched last time bounds
            # the search (every point at least as near lies within its distance per axis)
            reach = min(_FIRST_REACH_M, window)
            m = j[i]
            clear[i] -= moved
            if m < ns:
                dx = qx - src[m, 0]
                dz = qz - src[m, 1]
                d2 = dx * dx + dz * dz
                if d2 < max2:
                    d = math.sqrt(d2)
                    if keep_clear_matches and d * (1.0 + 1e-9) + 1e-12 < clear[i]:
                        # still clearly the nearest: what the search below would return
                        dist[i] = d
                        n_found += 1
                        continue
                    reach = d * (1.0 + 1e-9) + 1e-12
            box = reach
            best2, bi, tie, second2 = _nearest(src, grid, rank, qx, qz, reach, max2)
            if reach < window and not best2 * (1.0 + 1e-9) + 1e-24 < reach * reach:
                # nothing surely this near within the reach: the whole window
                box = window
                best2, bi, tie, second2 = _nearest(src, grid, rank, qx, qz, window, max2)
            # other points: the second-nearest searched, or outside the box searched
            clear[i] = min(math.sqrt(second2), box) * (1.0 - 1e-9) - 1e-12
            if best2 < max2:
                if tie:
                    return tx, tz, iterations, converged, keep, j, normals, _TIE
                j[i] = bi
                dist[i] = math.sqrt(best2)
                n_found += 1
            else:
                j[i] = ns
                dist[i] = np.inf
        if n_found == 0:
            keep = np.zeros(0, np.int64)
            break
        keep = np.empty(n_found, np.int64)
        c = 0
        for i in range(nt):
            if dist[i] < np.inf:
                keep[c] = i
                c += 1
        if stage != 1 and trim_fraction > 0 and n_found >= 4:
            n_keep = max(3, math.ceil((1.0 - trim_fraction) * n_found))
            dk = dist[keep]
            srt = np.argsort(dk, kind="mergesort")
            if n_keep < n_found and dk[srt[n_keep - 1]] == dk[srt[n_keep]]:
                # equal distances across the cut: which pairs stay must not depend on the sort,
                # so every pair at that distance must be the same pair (duplicates)
                a = keep[srt[n_keep - 1]]
                for c in range(n_found):
                    b = keep[c]
                    if dist[b] == dk[srt[n_keep]] and not (
                        _same(tgt[a, 0], tgt[a, 1], tgt[b, 0], tgt[b, 1])
                        and _same(src[j[a], 0], src[j[a], 1], src[j[b], 0], src[j[b], 1])
                    ):
                        return tx, tz, iterations, converged, keep, j, normals, _TIE_TRIM
            keep = keep[srt[:n_keep]]
        if stage == 2:
            break
        nk = keep.size
        if stage == 1:
            dtx, dtz, status = _robust_step(
                src,
                tgt,
                grid,
                rank,
                normal_neighbours,
                normals,
                have,
                best_d,
                best_i,
                keep,
                j,
                tx,
                tz,
                point_to_line,
                degenerate_ratio,
                robust_kernel,
                robust_scale,
                sigma_floor_m,
                weights,
            )
            if status != _OK:
                return tx, tz, iterations, converged, keep, j, normals, status
        elif not point_to_line:
            # eq. 4: the mean residual
            rx = 0.0
            rz = 0.0
            for c in range(nk):
                i = keep[c]
                rx += (tgt[i, 0] - tx) - src[j[i], 0]
                rz += (tgt[i, 1] - tz) - src[j[i], 1]
            dtx = rx / nk
            dtz = rz / nk
        else:
            a = 0.0
            b = 0.0
            cc = 0.0
            gx = 0.0
            gz = 0.0
            for c in range(nk):
                i = keep[c]
                m = j[i]
                if _fill_normal(
                    src, grid, rank, normal_neighbours, normals, have, m, best_d, best_i
                ):
                    return tx, tz, iterations, converged, keep, j, normals, _TIE_NORMAL
                nx = normals[m, 0]
                nz = normals[m, 1]
                rx = (tgt[i, 0] - tx) - src[m, 0]
                rz = (tgt[i, 1] - tz) - src[m, 1]
                r_n = nx * rx + nz * rz
                a += nx * nx
                b += nx * nz
                cc += nz * nz
                gx += nx * r_n
                gz += nz * r_n
            w0, w1, v0x, v0z, v1x, v1z = _eig_sym2(a, b, cc)
            floor = max(degenerate_ratio * w1, 1e-9)
            dtx = 0.0
            dtz = 0.0
            if w0 > floor:
                step = (v0x * gx + v0z * gz) / w0
                dtx += v0x * step
                dtz += v0z * step
            if w1 > floor:
                step = (v1x * gx + v1z * gz) / w1
                dtx += v1x * step
                dtz += v1z * step
        tx = tx + dtx
        tz = tz + dtz
        converged = math.hypot(dtx, dtz) <= convergence_m
        if converged or stage_iterations >= max_iterations:
            if robust_kernel == 0:
                break
            stage = 1 if stage == 0 else 2
            stage_iterations = 0
    # the normals the covariance needs (the numpy path computes them for the kept pairs)
    for c in range(keep.size):
        m = j[keep[c]]
        if _fill_normal(src, grid, rank, normal_neighbours, normals, have, m, best_d, best_i):
            return tx, tz, iterations, converged, keep, j, normals, _TIE_NORMAL
    return tx, tz, iterations, converged, keep, j, normals, _OK


_CAUCHY = 1  # robust_kernel codes of icp_loop ("cauchy", "huber" in IcpConfig)
_HUBER = 2
ROBUST_KERNELS = {"none": 0, "cauchy": _CAUCHY, "huber": _HUBER}


@numba.njit(cache=True)
def _robust_weight(a, c, kernel):  # pragma: no cover - compiled
    """IRLS weight of an absolute residual ``a`` for the kernel width ``c`` (as
    ``icp.robust_weights``)."""
    if kernel == _CAUCHY:
        u = a / c
        return 1.0 / (1.0 + u * u)
    return 1.0 if a <= c else c / max(a, c)


@numba.njit(cache=True)
def _robust_step(
    src,
    tgt,
    grid,
    rank,
    normal_neighbours,
    normals,
    have,
    best_d,
    best_i,
    keep,
    j,
    tx,
    tz,
    point_to_line,
    degenerate_ratio,
    kernel,
    scale,
    sigma_floor_m,
    weights,
):  # pragma: no cover - compiled
    """One reweighted step over the pairs ``keep`` (as ``icp._robust_step``): (dTx, dTz,
    status). ``weights`` (>= keep.size,) is scratch; it holds the residuals, then weights."""
    nk = keep.size
    for c in range(nk):
        i = keep[c]
        m = j[i]
        rx = (tgt[i, 0] - tx) - src[m, 0]
        rz = (tgt[i, 1] - tz) - src[m, 1]
        if point_to_line:
            if _fill_normal(src, grid, rank, normal_neighbours, normals, have, m, best_d, best_i):
                return 0.0, 0.0, _TIE_NORMAL
            weights[c] = abs(normals[m, 0] * rx + normals[m, 1] * rz)
        else:
            weights[c] = math.hypot(rx, rz)
    width = scale * max(1.4826 * np.median(weights[:nk]), sigma_floor_m)
    for c in range(nk):
        weights[c] = _robust_weight(weights[c], width, kernel)
    if not point_to_line:
        sw = 0.0
        sx = 0.0
        sz = 0.0
        for c in range(nk):
            i = keep[c]
            w = weights[c]
            sw += w
            sx += w * ((tgt[i, 0] - tx) - src[j[i], 0])
            sz += w * ((tgt[i, 1] - tz) - src[j[i], 1])
        return sx / sw, sz / sw, _OK
    a = 0.0
    b = 0.0
    cc = 0.0
    gx = 0.0
    gz = 0.0
    for c in range(nk):
        i = keep[c]
        m = j[i]
        w = weights[c]
        nx = normals[m, 0]
        nz = normals[m, 1]
        r_n = nx * ((tgt[i, 0] - tx) - src[m, 0]) + nz * ((tgt[i, 1] - tz) - src[m, 1])
        a += w * nx * nx
        b += w * nx * nz
        cc += w * nz * nz
        gx += w * nx * r_n
        gz += w * nz * r_n
    w0, w1, v0x, v0z, v1x, v1z = _eig_sym2(a, b, cc)
    floor = max(degenerate_ratio * w1, 1e-9)
    dtx = 0.0
    dtz = 0.0
    if w0 > floor:
        step = (v0x * gx + v0z * gz) / w0
        dtx += v0x * step
        dtz += v0z * step
    if w1 > floor:
        step = (v1x * gx + v1z * gz) / w1
        dtx += v1x * step
        dtz += v1z * step
    return dtx, dtz, _OK


@numba.njit(cache=True)
def icp_pairs(src, tgt, tx, tz, keep, j, normals):  # pragma: no cover - compiled
    """What :func:`vio_graph.frontend.icp.icp_translation_2d` makes of ``icp_loop``'s kept
    pairs, in one call: (target points ``tgt[keep]``, matched source points
    ``src[j[keep]]``, residuals ``tgt - T - src``, their source normals, RMS). The same
    floats as numpy's: residuals (t - T) - s, the RMS ``sqrt(mean(rx^2 + rz^2))`` with the
    mean as np.add.reduce's pairwise sum over n."""
    n = keep.size
    pairs_t = np.empty((n, 2))
    pairs_s = np.empty((n, 2))
    residual = np.empty((n, 2))
    nrm = np.empty((n, 2))
    sq = np.empty(n)
    for c in range(n):
        i = keep[c]
        m = j[i]
        pairs_t[c, 0] = tgt[i, 0]
        pairs_t[c, 1] = tgt[i, 1]
        pairs_s[c, 0] = src[m, 0]
        pairs_s[c, 1] = src[m, 1]
        rx = (tgt[i, 0] - tx) - src[m, 0]
        rz = (tgt[i, 1] - tz) - src[m, 1]
        residual[c, 0] = rx
        residual[c, 1] = rz
        nrm[c, 0] = normals[m, 0]
        nrm[c, 1] = normals[m, 1]
        sq[c] = rx * rx + rz * rz
    rms = math.sqrt(pairwise_sum(sq, 0, n) / n)
    return pairs_t, pairs_s, residual, nrm, rms


@numba.njit(cache=True)
def source_crop(prof, tgt, t0x, t0z, grow):  # pragma: no cover - compiled
    """``tracker.CornerTracker._source``'s crop on the profile: the points of ``prof`` (N, 2)
    inside the bounding box of ``tgt`` moved back by T0 (``tgt - T0``), grown by ``grow``
    on every side, in input order. The same comparisons against the same bounds as the
    numpy form (the box's extremes as np.min / np.max find them: NaN if a coordinate is NaN,
    which no point passes)."""
    nt = tgt.shape[0]
    x_lo = np.inf
    x_hi = -np.inf
    z_lo = np.inf
    z_hi = -np.inf
    nan_x = False
    nan_z = False
    for i in range(nt):
        mx = tgt[i, 0] - t0x
        mz = tgt[i, 1] - t0z
        if math.isnan(mx):
            nan_x = True
        else:
            x_lo = min(x_lo, mx)
            x_hi = max(x_hi, mx)
        if math.isnan(mz):
            nan_z = True
        else:
            z_lo = min(z_lo, mz)
            z_hi = max(z_hi, mz)
    n = prof.shape[0]
    out = np.empty((n, 2))
    if nan_x or nan_z:
        return out[:0]
    a = x_lo - grow
    b = x_hi + grow
    c = z_lo - grow
    d = z_hi + grow
    m = 0
    for k in range(n):
        px = prof[k, 0]
        pz = prof[k, 1]
        out[m, 0] = px
        out[m, 1] = pz
        m += (px >= a) & (px <= b) & (pz >= c) & (pz <= d)
    return out[:m].copy()


# ----------------------------------------------------------------------------- smoothing


@numba.njit(cache=True)
def grid_thin(pts, cell_m, max_dense_cells):  # pragma: no cover - compiled
    """``smoothing.grid_thin_reference`` (N > 0, cell_m > 0): centroids of the occupied cells
    in ascending cell key, each cell summed in input order (as np.bincount does)."""
    n = pts.shape[0]
    ix = np.empty(n, np.int64)
    iz = np.empty(n, np.int64)
    # the points read through a flat view of the (contiguous) array: the same divisions,
    # but LLVM vectorises this loop, which it did not with pts[i, 0] / pts[i, 1] (~2.5x
    # faster on a slice of ~8,500 points)
    flat = pts.reshape(-1)
    for i in range(n):
        ix[i] = np.int64(math.floor(flat[2 * i] / cell_m))
        iz[i] = np.int64(math.floor(flat[2 * i + 1] / cell_m))
    x_min = ix[0]
    x_max = ix[0]
    z_min = iz[0]
    z_max = iz[0]
    for i in range(n):  # the extent in one pass
        x_min = min(x_min, ix[i])
        x_max = max(x_max, ix[i])
        z_min = min(z_min, iz[i])
        z_max = max(z_max, iz[i])
    n_z = z_max - z_min + 1
    n_cells = (x_max - x_min + 1) * n_z
    key = np.empty(n, np.int64)
    for i in range(n):
        key[i] = (ix[i] - x_min) * n_z + (iz[i] - z_min)
    if n_cells > max_dense_cells:  # sparse over a huge extent: sort the keys instead
        order = np.argsort(key, kind="mergesort")  # stable: input order within a cell
        out = np.empty((n, 2))
        m = -1
        prev = -1
        count = 0
        sx = 0.0
        sz = 0.0
        for r in range(n):
            i = order[r]
            if key[i] != prev:
                if m >= 0:
                    out[m, 0] = sx / count
                    out[m, 1] = sz / count
                m += 1
                prev = key[i]
                count = 0
                sx = 0.0
                sz = 0.0
            count += 1
            sx += pts[i, 0]
            sz += pts[i, 1]
        out[m, 0] = sx / count
        out[m, 1] = sz / count
        return out[: m + 1].copy()
    # dense keys: number the occupied cells in ascending key, then sum in input order
    number = np.zeros(n_cells, np.int64)
    for i in range(n):
        number[key[i]] = 1
    m = 0
    for c in range(n_cells):  # without a branch on the occupancy (~15 % faster in all)
        occupied = number[c]
        number[c] = m
        m += occupied
    sums = np.zeros((m, 2))
    counts = np.zeros(m, np.int64)
    for i in range(n):
        c = number[key[i]]
        sums[c, 0] += pts[i, 0]
        sums[c, 1] += pts[i, 1]
        counts[c] += 1
    for c in range(m):
        sums[c, 0] /= counts[c]
        sums[c, 1] /= counts[c]
    return sums


@numba.njit(cache=True)
def knn_smooth(pts, k):  # pragma: no cover - compiled
    """``smoothing.knn_smooth_reference`` (2 <= k <= N): every point replaced by the mean of
    its k nearest points (itself included), summed in distance order (the order of the x
    scan, :func:`_knn` on a grid of the points). Returns (out, status): status 1 when a
    distinct point ties with a k-th neighbour (the KD-tree's pick decides: run the numpy
    path)."""
    n = pts.shape[0]
    order = np.argsort(pts[:, 0], kind="mergesort")
    rank = np.empty(n, np.int64)
    for r in range(n):
        rank[order[r]] = r
    grid = _grid(pts, _GRID_CELL_M)
    out = np.empty((n, 2))
    kk = min(k + 1, n)
    best_d = np.empty(kk)
    best_i = np.empty(kk, np.int64)
    for i in range(n):
        _knn(pts, grid, rank, i, kk, best_d, best_i)
        if kk > k and best_d[k] == best_d[k - 1] and _tie_at_kth(pts, grid, i, best_d, best_i, k):
            return out, _TIE
        sx = pts[best_i[0], 0]
        sz = pts[best_i[0], 1]
        for t in range(1, k):
            sx = sx + pts[best_i[t], 0]
            sz = sz + pts[best_i[t], 1]
        out[i, 0] = sx / k
        out[i, 1] = sz / k
    return out, _OK


# ----------------------------------------------------------------------------- level surfaces


@numba.njit(cache=True)
def best_line(x, z, i, j, max_slope, inlier_m):  # pragma: no cover - compiled
    """``level._best_line_reference`` after its random draws ``i``, ``j``: the hypothesis
    through points i[h], j[h] (near-horizontal, > 3 cm apart in x) with the most points
    within ``inlier_m`` vertically, the first of equals. Returns (i[h], slope), or (-1, 0.0)
    when no hypothesis qualifies."""
    n = x.shape[0]
    best_count = -1
    best_a = -1
    best_s = 0.0
    for h in range(i.shape[0]):
        a = i[h]
        b = j[h]
        dx = x[b] - x[a]
        if not abs(dx) > 0.03:
            continue
        s = (z[b] - z[a]) / dx
        if not abs(s) <= max_slope:
            continue
        c = 0
        for k in range(n):
            if abs(z[k] - z[a] - s * (x[k] - x[a])) < inlier_m:
                c += 1
        if c > best_count:
            best_count = c
            best_a = a
            best_s = s
    return best_a, best_s


@numba.njit(cache=True)
def _mean_of(a):  # pragma: no cover - compiled
    """level._mean: the pairwise sum over the length, the same float."""
    return pairwise_sum(a, 0, a.shape[0]) / a.shape[0]


@numba.njit(cache=True)
def _dot(a, b):  # pragma: no cover - compiled
    """a @ b summed in order (BLAS may sum in another order: equal to rounding)."""
    s = 0.0
    for k in range(a.shape[0]):
        s += a[k] * b[k]
    return s


@numba.njit(cache=True)
def _refine_line(x, z, mask, inlier_m):  # pragma: no cover - compiled
    """``level._refine``: the least-squares line on the ``mask`` points, inliers reselected."""
    n_in = 0
    for k in range(mask.shape[0]):
        if mask[k]:
            n_in += 1
    if n_in < 3:
        return mask
    xm = x[mask]
    zm = z[mask]
    x0 = _mean_of(xm)
    z0 = _mean_of(zm)
    xc = xm - x0
    s = _dot(xc, zm - z0) / max(_dot(xc, xc), 1e-12)
    return np.abs(z - z0 - s * (x - x0)) < inlier_m


@numba.njit(cache=True)
def surface_tilt(
    x,
    z,
    rng,
    n_hypotheses,
    max_slope,
    inlier_m,
    min_points,
    min_extent_m,
    max_lines,
    end_trim_m,
    correlated_points,
):  # pragma: no cover - compiled
    """``level.measure_surface_tilt_reference`` after its input checks, in one call: the same
    random draws from ``rng`` (numba's Generator.integers: numpy's algorithm on the same bit
    generator), the same line searches (``best_line``, ``_refine_line``), the same means
    (pairwise sums); the dot products summed in order (equal to BLAS's to rounding).

    Returns (status, tilt slope s, sigma of the slope, points used, lines) with lines (L, 6):
    height, sigma, x min, x max, mean x, own noise sigma (``LevelLine``'s fields); status
    0 = a tilt, 1 = no line or the shared slope too steep (None)."""
    n = x.shape[0]
    remaining = np.ones(n, np.bool_)
    starts = np.zeros(max_lines + 1, np.int64)
    chosen = np.empty(n, np.int64)  # the lines' point indices, one after the other
    n_lines = 0
    for _ in range(max_lines):
        idx = np.flatnonzero(remaining)
        m = idx.size
        if m < min_points:
            break
        xi = x[idx]
        zi = z[idx]
        i = rng.integers(0, m, n_hypotheses)
        j = rng.integers(0, m, n_hypotheses)
        a, s = best_line(xi, zi, i, j, max_slope, inlier_m)
        if a < 0:
            break
        mask = np.abs(zi - zi[a] - s * (xi - xi[a])) < inlier_m
        mask = _refine_line(xi, zi, mask, inlier_m)
        sel = idx[mask]
        if sel.size < min_points:
            break
        xs = x[sel]
        if xs.max() - xs.min() < min_extent_m:
            break
        remaining[sel] = False
        if end_trim_m > 0.0:
            lo = xs.min() + end_trim_m
            hi = xs.max() - end_trim_m
            sel = sel[(xs > lo) & (xs < hi)]
            if sel.size < 3:
                continue
        b = starts[n_lines]
        chosen[b : b + sel.size] = sel
        n_lines += 1
        starts[n_lines] = b + sel.size
    lines = np.empty((n_lines, 6))
    if n_lines == 0:
        return 1, 0.0, 0.0, 0, lines
    variances = np.empty(n_lines)
    szx = 0.0
    info = 0.0
    for q in range(n_lines):
        sel = chosen[starts[q] : starts[q + 1]]
        xs = x[sel]
        zs = z[sel]
        xc = xs - _mean_of(xs)
        zc = zs - _mean_of(zs)
        Sxx = _dot(xc, xc)
        Szx = _dot(xc, zc)
        s_k = Szx / max(Sxx, 1e-12)
        r = zc - s_k * xc
        var_k = max(pairwise_sum(r * r, 0, r.size) / max(1, xs.shape[0] - 2), 1e-8)
        variances[q] = var_k
        szx += Szx / var_k
        info += Sxx / var_k
    if not info > 0.0:  # every trimmed line's points share one x: no slope to measure
        return 1, 0.0, 0.0, 0, lines
    s = szx / info
    if abs(s) > max_slope:
        return 1, 0.0, 0.0, 0, lines
    sigma_slope = math.sqrt(correlated_points / info)
    for q in range(n_lines):
        sel = chosen[starts[q] : starts[q + 1]]
        xs = x[sel]
        zs = z[sel]
        x_mid = _mean_of(xs)
        var_own = correlated_points * variances[q] / xs.shape[0]
        var_h = var_own + (x_mid * sigma_slope) ** 2
        lines[q, 0] = _mean_of(zs - s * xs)
        lines[q, 1] = math.sqrt(var_h)
        lines[q, 2] = xs.min()
        lines[q, 3] = xs.max()
        lines[q, 4] = x_mid
        lines[q, 5] = math.sqrt(var_own)
    return 0, s, sigma_slope, starts[n_lines], lines


# ----------------------------------------------------------------------------- corner lines


@numba.njit(cache=True)
def horizontal_line(z_all, mask, draws, exclude, min_sep, d):  # pragma: no cover - compiled
    """``corners.ransac_horizontal_line_reference`` after its random draws (``draws``:
    indices into the sorted heights of the ``mask`` points): the hypotheses not within
    ``min_sep`` of an ``exclude`` height, the first with the most heights within ``d``, its
    inliers' median height. Returns (height, inlier mask), or (nan, empty) when every
    hypothesis is excluded. Comparisons and one (a + b) / 2 only: the same floats."""
    z = np.sort(z_all[mask])
    n = z.size
    best_count = -1
    best = 0.0
    for q in range(draws.size):
        h = z[draws[q]]
        excluded = False
        for e in range(exclude.size):
            if not abs(h - exclude[e]) >= min_sep:
                excluded = True
                break
        if excluded:
            continue
        c = np.searchsorted(z, h + d, side="right") - np.searchsorted(z, h - d)
        if c > best_count:
            best_count = c
            best = h
    if best_count < 0:
        return np.nan, np.zeros(0, np.bool_)
    lo = 0  # the inliers |z - best| <= d: one run of the sorted heights
    while lo < n and not abs(z[lo] - best) <= d:
        lo += 1
    hi = lo
    while hi < n and abs(z[hi] - best) <= d:
        hi += 1
    k = hi - lo
    mid = lo + k // 2
    height = z[mid] if k % 2 else (z[mid - 1] + z[mid]) / 2
    inliers = np.empty(z_all.size, np.bool_)
    for i in range(z_all.size):
        inliers[i] = mask[i] and abs(z_all[i] - height) <= d
    return height, inliers


@numba.njit(cache=True)
def largest_run(x, max_gap_m):  # pragma: no cover - compiled
    """``corners._largest_run_reference``: the sorted x values of the run (no gap above
    ``max_gap_m``) with the most points, the first of equals."""
    xs = np.sort(x)
    n = xs.size
    best_lo = 0
    best_hi = 0
    start = 0
    for end in range(1, n + 1):
        if end < n and not xs[end] - xs[end - 1] > max_gap_m:
            continue
        if end - start > best_hi - best_lo:
            best_lo = start
            best_hi = end
        start = end
    return xs[best_lo:best_hi]


@numba.njit(cache=True)
def _median_sorted(v):  # pragma: no cover - compiled
    """corners._median_of_sorted: the middle value, or (a + b) / 2 of the middle two."""
    n = v.size
    return v[n // 2] if n % 2 else (v[n // 2 - 1] + v[n // 2]) / 2


@numba.njit(cache=True)
def _surface_line(x, z, mask, rng, excl, n_hyp, d, min_sep, min_inliers, max_gap, min_length):
    # pragma: no cover - compiled
    """``corners._surface_line`` with the compiled line and run (``mask``: the candidates,
    consumed). Returns (height, inliers, status): status 0 a line, 1 a line with too few
    inliers (the caller's None), 2 None."""
    n = x.size
    for _ in range(3):
        n_cand = 0
        for k in range(n):
            if mask[k]:
                n_cand += 1
        if n_cand == 0:
            return 0.0, mask, 2
        draws = rng.integers(0, n_cand, n_hyp)
        height, inliers = horizontal_line(z, mask, draws, excl, min_sep, d)
        if inliers.shape[0] != n:
            return 0.0, mask, 2
        n_in = 0
        for k in range(n):
            if inliers[k]:
                n_in += 1
        if n_in < min_inliers:
            return height, inliers, 1
        run = largest_run(x[inliers], max_gap)
        if run[-1] - run[0] >= min_length:
            return height, inliers, 0
        mask = mask & ~inliers
    return 0.0, mask, 2


@numba.njit(cache=True)
def _face_x(x, z, x_end, h, d, window, max_nosing_gap, top_margin, face_band, cluster, min_pts):
    # pragma: no cover - compiled
    """``corners._face_line_x``: x of the supported face line below the tread end, or nan."""
    ahead = x_end - x
    depth = h - z
    near = (ahead <= max_nosing_gap) & (ahead >= -d) & (depth >= top_margin)
    cand = near & (depth <= face_band)
    if np.count_nonzero(cand) < min_pts:
        cand = near & (depth <= window)
        if np.count_nonzero(cand) < min_pts:
            return np.nan
    a = np.sort(ahead[cand])[::-1]  # foremost first
    lo = 0
    for hi in range(1, a.size + 1):
        if hi < a.size and not -(a[hi] - a[hi - 1]) > cluster:
            continue
        if hi - lo >= min_pts:
            return x_end - _median_sorted(a[lo:hi][::-1])
        lo = hi
    return np.nan


@numba.njit(cache=True)
def corner(
    x,
    z,
    rng,
    side_code,
    n_hyp,
    d,
    window,
    min_sep,
    min_inliers,
    max_gap,
    min_length,
    max_nosing_gap,
    top_margin,
    face_band,
    cluster,
    min_face_pts,
    needs_face,
    min_features,
):  # pragma: no cover - compiled
    """``corners.extract_corner_reference`` after its input checks, in one call: the same
    draws from ``rng`` (numba's Generator.integers: numpy's algorithm on the same bit
    generator), comparisons, medians and one (a + b) / 2 only, so the same floats.
    ``side_code``: 0 the near end, 1 the far end, 2 the side of the lower line's median x.

    Returns (status, edge x, edge z, upper height, lower height, upper inliers, lower
    inliers, near side, has face, feature window mask); status 0 a corner, else None."""
    n = x.size
    none = np.zeros(0, np.bool_)
    all_pts = np.ones(n, np.bool_)
    no_excl = np.empty(0)
    h1, in1, st = _surface_line(
        x, z, all_pts, rng, no_excl, n_hyp, d, min_sep, min_inliers, max_gap, min_length
    )
    if st != 0:
        return 1, 0.0, 0.0, 0.0, 0.0, 0, 0, True, False, none
    excl = np.empty(1)
    excl[0] = h1
    h2, in2, st = _surface_line(
        x, z, ~in1, rng, excl, n_hyp, d, min_sep, min_inliers, max_gap, min_length
    )
    if st != 0:
        return 1, 0.0, 0.0, 0.0, 0.0, 0, 0, True, False, none
    if h1 > h2:
        hu, inu, hl, inl = h1, in1, h2, in2
    else:
        hu, inu, hl, inl = h2, in2, h1, in1
    upper_x = x[inu]
    if side_code == 0:
        near_side = True
    elif side_code == 1:
        near_side = False
    else:
        near_side = _median_sorted(np.sort(x[inl])) < _median_sorted(np.sort(upper_x))
    run = largest_run(upper_x, max_gap)
    ex = run[0] if near_side else run[-1]
    ez = hu
    face = np.nan
    if near_side:
        face = _face_x(
            x, z, ex, ez, d, window, max_nosing_gap, top_margin, face_band, cluster, min_face_pts
        )
        if math.isnan(face) and needs_face:
            return 1, 0.0, 0.0, 0.0, 0.0, 0, 0, True, False, none
    has_face = not math.isnan(face)
    if has_face:
        ex = face
        tread = inu & (x - face > top_margin)
        if np.count_nonzero(tread) >= min_face_pts:
            ez = _median_sorted(np.sort(z[tread]))
    elif not near_side:
        below = (np.abs(x - ex) <= d) & (z < ez - d) & (z >= ez - window)
        if np.count_nonzero(below) >= 3:
            ex = _median_sorted(np.sort(x[below]))
    dx = x - ex
    band = max(0.0, run[0] - ex) if has_face else 0.0
    in_window = (dx >= -window) & (dx <= window + band) & (np.abs(z - ez) <= window)
    if np.count_nonzero(in_window) < min_features:
        return 1, 0.0, 0.0, 0.0, 0.0, 0, 0, True, False, none
    n_up = np.count_nonzero(inu)
    n_lo = np.count_nonzero(inl)
    return 0, ex, ez, hu, hl, n_up, n_lo, near_side, has_face, in_window


# ----------------------------------------------------------------------------- walking surface

#: points per block of the x-sorted profile in :func:`seen_under`'s bound test
_SEEN_BLOCK = 16


@numba.njit(cache=True)
def seen_under(x, z, margin, drop, min_occluders):  # pragma: no cover - compiled
    """``vio_graph.surface.seen_under_mask`` (its numpy form is the reference): True for a
    point P (x > 1e-6) when at least ``min_occluders`` points Q with ``xq < xp - margin`` lie
    above P's line of sight, ``zq > zp / xp * xq + drop``, the same comparisons of the same
    floats. The points ahead are sorted by x once, so the Q of a P are a prefix; the count
    stops at ``min_occluders``. The prefix is scanned in blocks of ``_SEEN_BLOCK`` sorted
    points, and a block whose highest z is at most the lower of the line's rounded heights at
    the block's two x ends (rounded products and sums are monotone, so no Q inside can pass
    the test) is skipped without looking at its points."""
    n = x.shape[0]
    under = np.zeros(n, np.bool_)
    m = 0
    for i in range(n):
        if x[i] > 1e-6:
            m += 1
    if m <= min_occluders:
        return under
    idx = np.empty(m, np.int64)
    k = 0
    for i in range(n):
        if x[i] > 1e-6:
            idx[k] = i
            k += 1
    order = idx[np.argsort(x[idx])]
    xs = x[order]
    zs = z[order]
    nb = (m + _SEEN_BLOCK - 1) // _SEEN_BLOCK
    top = np.full(nb, -np.inf)  # highest z per block (NaN never passes the test: left out)
    for q in range(m):
        b = q // _SEEN_BLOCK
        if zs[q] > top[b]:
            top[b] = zs[q]
    for a in range(m):
        xp = xs[a]
        lim = xp - margin
        s = zs[a] / xp
        cnt = 0
        q = 0
        while q < m and xs[q] < lim and cnt < min_occluders:
            end = min(q + _SEEN_BLOCK, m)
            b = q // _SEEN_BLOCK
            last = end - 1
            if not xs[last] < lim:
                last = q  # the block's x end inside the prefix: bound from its first point
                while last + 1 < end and xs[last + 1] < lim:
                    last += 1
            if top[b] <= min(s * xs[q], s * xs[last]) + drop:
                q = last + 1
                continue
            for j in range(q, last + 1):
                if zs[j] > s * xs[j] + drop:
                    cnt += 1
                    if cnt >= min_occluders:
                        break
            q = last + 1
        if cnt >= min_occluders:
            under[order[a]] = True
    return under


@numba.njit(cache=True)
def seen_under_floor(
    x, z, margin, drop, min_occluders, lz, lo, hi, band, min_points
):  # pragma: no cover - compiled
    """:func:`seen_under` or-ed with ``vio_graph.surface.floor_beyond_slab_mask`` (its numpy
    form is the reference) in one call: the front end's ``points_seen_under`` without the
    small numpy calls of the slab test per frame. Levels (``lz``, ``lo``, ``hi``) as in the
    reference; the same comparisons of the same floats, so the same mask bit for bit."""
    under = seen_under(x, z, margin, drop, min_occluders)
    n_lv = lz.shape[0]
    n = x.shape[0]
    beneath = np.zeros(0, np.bool_)
    for a in range(n_lv):
        for b in range(n_lv):
            # the slab test of ``surface._lower_overlapping``: b at least drop under a and
            # overlapping it in x by more than margin
            if b == a or not lz[b] < lz[a] - drop:
                continue
            if not min(hi[a], hi[b]) - max(lo[a], lo[b]) > margin:
                continue
            if beneath.shape[0] == 0:  # ``surface._beneath_levels``, once, when a slab exists
                beneath = np.zeros(n, np.bool_)
                for i in range(n):
                    for c in range(n_lv):
                        if x[i] > lo[c] + margin and x[i] < hi[c] - margin and z[i] < lz[c] - drop:
                            beneath[i] = True
                            break
            cnt = 0
            for i in range(n):
                if abs(z[i] - lz[b]) <= band and x[i] < lo[a] and not beneath[i]:
                    cnt += 1
            if cnt >= min_points:
                lim = hi[a] + margin
                for i in range(n):
                    if abs(z[i] - lz[b]) <= band and x[i] > lim:
                        under[i] = True
    return under


@numba.njit(cache=True)
def under_levels(x, pz, z, lo, hi, margin, drop, band, sight_margin, use_sight):  # pragma: no cover
    """``vio_graph.surface.under_levels_mask`` (its numpy form is the reference) point by
    point: the same comparisons of the same floats (the slope ``pz / x`` of a point ahead,
    ``min(x, s_hi)`` as ``np.minimum`` takes it for a point ahead, whose x is not NaN), so the
    same mask. ``use_sight``: ``sight_margin`` given."""
    n = x.shape[0]
    n_levels = z.shape[0]
    under = np.zeros(n, np.bool_)
    # the lower levels B each level A overlaps by more than margin (the third rule)
    pairs = np.zeros((n_levels, n_levels), np.bool_)
    for a in range(n_levels):
        for b in range(n_levels):
            overlap = min(hi[a], hi[b]) - max(lo[a], lo[b])
            pairs[a, b] = b != a and z[b] < z[a] - drop and overlap > margin
    for i in range(n):
        xi = x[i]
        zi = pz[i]
        ahead = xi > 1e-6
        slope = zi / xi if ahead else 0.0
        hit = False
        for a in range(n_levels):
            za = z[a] - drop
            a_lo = lo[a] + margin
            a_hi = hi[a] - margin
            if a_hi > a_lo and xi > a_lo and xi < a_hi and zi < za:
                hit = True
                break
            if use_sight and ahead and hi[a] - lo[a] > 2 * sight_margin:
                s_lo = lo[a] + sight_margin
                s_hi = hi[a] - sight_margin
                x_eval = min(xi, s_hi)
                if xi > lo[a] + margin and x_eval > s_lo and slope * x_eval < za:
                    hit = True
                    break
            if zi < za and xi >= lo[a] and xi <= hi[a]:
                for b in range(n_levels):
                    if pairs[a, b] and abs(zi - z[b]) <= band:
                        hit = True
                        break
                if hit:
                    break
        under[i] = hit
    return under


# ----------------------------------------------------------------------------- depth noise


@numba.njit(cache=True)
def level_bands(x, z, max_range, check_range, heights, lo, hi, band):  # pragma: no cover
    """The points of each level's band as ``noise.level_residuals_reference`` selects them:
    with ``check_range``, only points with ``hypot(x, z) < max_range`` (decided on
    ``x * x + z * z`` against ``max_range**2`` when that is more than 1e-12 relative away, else
    by libm's ``hypot`` as numpy calls it: the same points); then per level ``|z - height| <=
    band`` and ``lo <= x <= hi``. Returns (L, M) x and z of each level's points in input order
    and the (L,) counts.

    Without branches on the tests (every point is written at the next free place, which
    advances when it passes): the slice's points come in pixel order, where band and range
    membership alternate unpredictably, and the mispredicted branches were most of the time
    (~49 -> ~31 us on a frame's ~8,500 points). The same points in the same order."""
    n = x.shape[0]
    xk = np.empty(n)
    zk = np.empty(n)
    m = 0
    r2 = max_range * max_range
    r2_in = r2 * (1.0 - 1e-12)
    r2_out = r2 * (1.0 + 1e-12)
    for i in range(n):
        xi = x[i]
        zi = z[i]
        xk[m] = xi
        zk[m] = zi
        if check_range:
            d2 = xi * xi + zi * zi
            inside = d2 < r2_in
            if d2 >= r2_in and not d2 > r2_out:  # within 1e-12 of the range (rare): hypot
                inside = math.hypot(xi, zi) < max_range
            m += inside
        else:
            m += 1
    n_levels = heights.shape[0]
    bx = np.empty((n_levels, m))
    bz = np.empty((n_levels, m))
    counts = np.zeros(n_levels, np.int64)
    for lv in range(n_levels):
        h = heights[lv]
        x_lo = lo[lv]
        x_hi = hi[lv]
        c = 0
        for k in range(m):  # c <= k: the write stays inside the row
            xi = xk[k]
            zi = zk[k]
            bx[lv, c] = xi
            bz[lv, c] = zi
            c += (abs(zi - h) <= band) & (xi >= x_lo) & (xi <= x_hi)
        counts[lv] = c
    return bx, bz, counts


_SIGN64 = np.uint64(1) << np.uint64(63)


#: the radix selection's digits: sign and exponent first (12 bits), then the mantissa 12
#: bits at a time (the last digit overlaps bits the candidates then share)
_RADIX_SHIFTS = np.array([52, 40, 28, 16, 4, 0], np.uint64)
_RADIX_MASK = np.uint64(4095)


@numba.njit(cache=True)
def _rank_key(keys, work, k, hist, ready):  # pragma: no cover - compiled
    """The rank-``k`` (0-based) value of ``keys`` (uint64) by radix selection: a histogram of
    the next 12 bits of the candidates, the bucket that holds rank k kept, 6 passes at most
    over a shrinking set (``work`` a scratch array of the same size; ``keys`` unchanged).
    Branch-light, where a quickselect on ~5,500 random floats mispredicts half its
    comparisons (~3x slower); the pass that keeps the bucket's keys writes every key and
    advances on a match (a branch on the match missed often when the bucket held a large
    share). The first digit is the sign and the exponent, so a frame's residuals (a few
    binades about zero) leave a few hundred candidates after one pass, where 8-bit digits
    (sign and 7 exponent bits first) kept about half of them for the next two passes (both
    medians of a frame's ~5,600 residuals ~53 -> ~30 us). The histogram is cleared in the
    pass that keeps the bucket, at the candidates' own digits (a pass costs its candidates,
    not the 4,096 bins). ``hist`` (4,096 int64): zeros, or with ``ready`` the first digit's
    histogram of ``keys`` (counted as the keys were made); all zeros again on return."""
    n = keys.shape[0]
    src = keys
    m = n
    for p in range(_RADIX_SHIFTS.shape[0]):
        sh = _RADIX_SHIFTS[p]
        if p > 0 or not ready:
            for i in range(m):
                hist[(src[i] >> sh) & _RADIX_MASK] += 1
        d = 0
        while k >= hist[d]:
            k -= hist[d]
            d += 1
        if hist[d] == m:
            hist[d] = 0  # every candidate shares these bits
            continue
        ud = np.uint64(d)
        c = 0
        for i in range(m):  # every key written, kept when in the bucket: no branch to miss
            v = src[i]
            dg = (v >> sh) & _RADIX_MASK
            hist[dg] = 0
            work[c] = v
            c += dg == ud
        src = work
        m = c
        if m == 1:
            break
    return src[0]


@numba.njit(cache=True)
def _middle_key(keys, work, h, even, hist, ready):  # pragma: no cover - compiled
    """(rank h - 1 key if ``even`` else the rank-h key, rank-h key) of ``keys``: the rank
    h - 1 one is the rank-h key when fewer than h keys lie below it, else the largest below
    it (one pass). ``hist``, ``ready``: as :func:`_rank_key`'s."""
    hi = _rank_key(keys, work, h, hist, ready)
    if not even:
        return hi, hi
    below = 0
    lo = np.uint64(0)
    for i in range(keys.shape[0]):  # a count and a maximum, without branches
        v = keys[i]
        lt = v < hi
        below += lt
        lo = max(lo, v if lt else np.uint64(0))
    return (hi if below < h else lo), hi


@numba.njit(cache=True)
def _key_float(v):  # pragma: no cover - compiled
    """The float64 of a :func:`_float_keys` key."""
    b = v ^ _SIGN64 if v >> np.uint64(63) else ~v
    return np.array([b], np.uint64).view(np.float64)[0]


@numba.njit(cache=True)
def _float_keys(x, keys, hist):  # pragma: no cover - compiled
    """uint64 keys in the order of the floats ``x`` (finite; -0.0 just below +0.0): the bits,
    with the sign bit set for a positive value and all bits flipped for a negative one; the
    first radix digit of each counted in ``hist`` (zeros before: :func:`_rank_key`'s first
    pass, done here)."""
    u = x.view(np.uint64)
    for i in range(x.shape[0]):
        b = u[i]
        key = ~b if b >> np.uint64(63) else b | _SIGN64
        keys[i] = key
        hist[key >> _RADIX_SHIFTS[0]] += 1


@numba.njit(cache=True)
def _median_of_keys(x, keys, work, hist):  # pragma: no cover - compiled
    """Median of the finite floats ``x`` (at least one): the middle value, or the two middle
    ones as ``(a + b) / 2`` (numpy's mean of two), each found exactly by radix selection
    (``hist``: 4,096 zeros, zeros again on return)."""
    n = x.shape[0]
    _float_keys(x, keys, hist)
    lo, hi = _middle_key(keys, work, n // 2, n % 2 == 0, hist, True)
    a, b = _key_float(lo), _key_float(hi)
    return b if n % 2 == 1 else (a + b) / 2


@numba.njit(cache=True)
def median_abs_deviation(r):  # pragma: no cover - compiled
    """``np.median(np.abs(r - np.median(r)))`` of ``r`` (1-D, contiguous, at least one value)
    without sorting: both medians by radix selection (:func:`_median_of_keys`, a few passes
    over the values, where numpy's sort took ~130 us on a frame's ~5,500 residuals). Returns
    (mad, ok); ok False (nothing computed) when a value is not finite: the caller runs the
    numpy path. An order statistic is the same value however it is found; only the sign of
    a zero median may differ from the sort's pick (-0.0 ranks below +0.0 here), which leaves
    every deviation ``|r - med|`` the same. So the same float bit for bit."""
    n = r.shape[0]
    for i in range(n):
        if not math.isfinite(r[i]):
            return np.nan, False
    keys = np.empty(n, np.uint64)
    work = np.empty(n, np.uint64)
    hist = np.zeros(4096, np.int64)
    med = _median_of_keys(r, keys, work, hist)
    dev = np.empty(n)
    for i in range(n):
        dev[i] = abs(r[i] - med)
    return _median_of_keys(dev, keys, work, hist), True


@numba.njit(cache=True)
def level_noise(pts, max_range, check_range, levels, band, min_count):  # pragma: no cover
    """``noise.level_noise_sigma``'s compiled pass: the bands of :func:`level_bands` of the
    (N, 2) points (``levels`` (L, 3): height, x_min, x_max; both C-contiguous: a strided
    argument costs numba's dispatcher ~6 us to type), a least-squares line through each band of at
    least ``min_count`` points as ``noise._line_residuals`` fits it (the means by numpy's
    pairwise sum, the two dot products by BLAS ``ddot`` as numpy's ``@`` calls it), the
    residuals pooled in level order and their median absolute deviation
    (:func:`median_abs_deviation`). Returns (residuals, mad, ok): mad nan without residuals,
    ok False when a residual is not finite (the caller then runs numpy on the residuals).
    One call in place of the bands, one numpy fit per level and the MAD (~50 us of numpy's
    per-call overhead a frame); the same floats."""
    bx, bz, counts = level_bands(
        pts[:, 0],
        pts[:, 1],
        max_range,
        check_range,
        np.ascontiguousarray(levels[:, 0]),
        np.ascontiguousarray(levels[:, 1]),
        np.ascontiguousarray(levels[:, 2]),
        band,
    )
    total = 0
    for k in range(counts.shape[0]):
        if counts[k] >= min_count:
            total += counts[k]
    res = np.empty(total)
    m = 0
    for k in range(counts.shape[0]):
        n = counts[k]
        if n < min_count:
            continue
        xs = bx[k]
        zs = bz[k]
        mx = pairwise_sum(xs, 0, n) / n
        mz = pairwise_sum(zs, 0, n) / n
        xc = np.empty(n)
        zc = np.empty(n)
        for i in range(n):
            xc[i] = xs[i] - mx
            zc[i] = zs[i] - mz
        sxx = np.dot(xc, xc)
        slope = np.dot(xc, zc) / sxx if sxx > 0 else 0.0
        for i in range(n):
            res[m + i] = zc[i] - slope * xc[i]
        m += n
    if m == 0:
        return res, np.nan, True
    mad, ok = median_abs_deviation(res)
    return res, mad, ok


# ----------------------------------------------------------------------------- terrain levels


@numba.njit(cache=True)
def _band_counts(za, band):  # pragma: no cover - compiled
    """np.searchsorted(za, za + band, "right") - np.searchsorted(za, za - band, "left") on
    sorted ``za`` with two pointers that only move forward (the keys rise with i): the same
    comparisons against the same keys, O(n) instead of O(n log n)."""
    m = za.size
    counts = np.empty(m, np.int64)
    lo = 0
    hi = 0
    for i in range(m):
        key_lo = za[i] - band
        key_hi = za[i] + band
        while lo < m and za[lo] < key_lo:
            lo += 1
        while hi < m and not za[hi] > key_hi:
            hi += 1
        counts[i] = hi - lo
    return counts


@numba.njit(cache=True)
def _descending_stable(counts):  # pragma: no cover - compiled
    """np.argsort(-counts, kind="stable") for counts in 0..n: a counting sort (largest count
    first, equal counts in index order), O(n)."""
    m = counts.size
    top = 0
    for i in range(m):
        top = max(top, counts[i])
    start = np.zeros(top + 2, np.int64)  # start[top - c]: first slot of count c
    for i in range(m):
        start[top - counts[i] + 1] += 1
    for c in range(1, top + 2):
        start[c] += start[c - 1]
    order = np.empty(m, np.int64)
    for i in range(m):
        k = top - counts[i]
        order[start[k]] = i
        start[k] += 1
    return order


@numba.njit(cache=True)
def find_levels(z, x, band, max_levels, min_points, gap_m, min_length_m):  # pragma: no cover
    """``terrain.find_levels_reference`` on the profile sorted by height (``z`` ascending, ``x``
    in the same order): the same bands in the same order (a stable sort of the counts), the
    same medians and nearest-rank extents, so the same levels bit for bit (no sums: only
    comparisons, one (a + b) / 2 and index arithmetic). Returns (L, 5) rows (height, x lo,
    x hi, x median, points) in the order found."""
    n = z.shape[0]
    alive = np.ones(n, np.bool_)
    out = np.empty((n // max(min_points, 1) + 1, 5))
    n_out = 0
    tried = np.empty(3)
    for _ in range(max_levels):
        idx_alive = np.flatnonzero(alive)
        m = idx_alive.size
        if m < min_points:
            break
        za = z[idx_alive]  # still sorted by z
        xa = x[idx_alive]
        counts = _band_counts(za, band)
        order = _descending_stable(counts)
        found = False
        n_tried = 0
        for q in range(m):
            i = order[q]
            if counts[i] < min_points or n_tried >= 3:
                break
            zi = za[i]
            near = False
            for h in range(n_tried):
                if abs(zi - tried[h]) <= band:
                    near = True
                    break
            if near:
                continue
            tried[n_tried] = zi
            n_tried += 1
            a = np.searchsorted(za, zi - band)
            b = np.searchsorted(za, zi + band)
            mid = a + (b - a) // 2
            height = za[mid] if (b - a) % 2 else (za[mid - 1] + za[mid]) / 2
            lo = np.searchsorted(za, height - band)
            hi = np.searchsorted(za, height + band)
            xs = np.sort(xa[lo:hi])
            size = xs.size
            start = 0
            for end in range(1, size + 1):  # runs of x split at gaps above gap_m
                if end < size and not xs[end] - xs[end - 1] > gap_m:
                    continue
                if end - start >= min_points:
                    last = end - start - 1
                    x_lo = xs[start + int(0.05 * last)]
                    x_med = xs[start + last // 2]
                    x_hi = xs[start + int(np.ceil(0.95 * last))]
                    if x_hi - x_lo >= min_length_m:
                        out[n_out, 0] = height
                        out[n_out, 1] = x_lo
                        out[n_out, 2] = x_hi
                        out[n_out, 3] = x_med
                        out[n_out, 4] = end - start
                        n_out += 1
                        found = True
                start = end
            if found:
                alive[idx_alive[lo:hi]] = False
                break
        if not found:
            break
    return out[:n_out]


@numba.njit(cache=True)
def find_levels_xz(pts, band, max_levels, min_points, gap_m, min_length_m):  # pragma: no cover
    """:func:`find_levels` of the (N, 2) profile ``pts`` (C-contiguous), sorted by height
    here (a stable sort): one call in place of numpy's argsort and two gathers. Points of
    equal height may come in another order than numpy's (unstable) argsort puts them, which
    changes no level: a band takes all points of a height or none, its x values are sorted,
    and a height's count and first rank are the same whatever the order among equals."""
    order = np.argsort(pts[:, 1], kind="mergesort")
    n = order.shape[0]
    z = np.empty(n)
    x = np.empty(n)
    for i in range(n):
        z[i] = pts[order[i], 1]
        x[i] = pts[order[i], 0]
    return find_levels(z, x, band, max_levels, min_points, gap_m, min_length_m)


# ----------------------------------------------------------------------------- depth slice


@numba.njit(cache=True)
def _present(depth, conf, r, c):  # pragma: no cover - compiled
    """drop_speckles' validity of pixel (r, c): confidence > 0, finite depth > 0."""
    d = depth[r, c]
    return conf[r, c] > 0 and math.isfinite(d) and d > 0


@intrinsic
def _fma_intrinsic(typingctx, a, b, c):  # pragma: no cover - compiled
    """a * b + c rounded once (LLVM's ``llvm.fma.f64``, exact on any target)."""
    sig = nb_types.float64(nb_types.float64, nb_types.float64, nb_types.float64)

    def codegen(context, builder, signature, args):
        d = llvm_ir.DoubleType()
        fn = cgutils.get_or_insert_function(
            builder.module, llvm_ir.FunctionType(d, [d, d, d]), "llvm.fma.f64"
        )
        return builder.call(fn, args)

    return sig, codegen


#: a * b + c rounded once, callable from compiled code (typed as Any: mypy would read the
#: intrinsic's typing signature as its call signature)
_fma: Any = _fma_intrinsic


@numba.njit(cache=True)
def slice_xz(
    depth, conf, c0, c1, lower, upper, min_conf, rel_tol, abs_tol, min_agree, x_per_m, y_per_m, R_xz
):  # pragma: no cover - compiled
    """``projection.sagittal_slice_from_depth``'s compiled pass: the pixels of columns c0:c1
    with depth in [lower, upper[column]] (float32 bounds) and confidence >= ``min_conf``,
    with ``min_agree`` > 0 also passing ``projection.drop_speckles``' test (float32
    ``rel_tol`` / ``abs_tol``, the same float32 operations as numpy's), back-projected
    (z = depth as float64, x = z x_per_m[column - c0], y = z y_per_m[row]) and rotated by
    ``R_xz`` (2, 3): the (M, 2) slice in row-major pixel order. ``x_per_m`` (c1 - c0,) and
    ``y_per_m`` (H,) are one row and one column of the numpy path's (H, c1 - c0) grids (the
    same values): the two grids (~0.6 MB) did not stay in the cache beside the image, and
    reading them cost more than the rest of the pass (~80 -> ~40 us a frame without the
    speckle test).

    The speckle test stops counting neighbours once ``min_agree`` of them agree (its need is
    at most that, so the decision is known then); with ``min_agree`` 2 (the default) the two
    row neighbours are tested inline first, the loop's first two steps without its table
    lookups and bounds tests (~10 % of the pass on a 60 s trial's frames). The rotation is
    summed as the BLAS kernel numpy's ``points @ R_xz.T`` calls here does (OpenBLAS,
    Haswell and later): a product, then two fused multiply-adds, so the same floats on this
    BLAS, and within an ulp on another."""
    h, w = depth.shape
    nb = c1 - c0
    out = np.empty((h * nb, 2))
    r00, r01, r02 = R_xz[0, 0], R_xz[0, 1], R_xz[0, 2]
    r10, r11, r12 = R_xz[1, 0], R_xz[1, 1], R_xz[1, 2]
    m = 0
    for r in range(h):
        y_m = y_per_m[r]
        drow = depth[r]  # one row's views: no 2-D index arithmetic per pixel (~10 % of the pass)
        crow = conf[r]
        for j in range(nb):
            c = c0 + j
            d = drow[c]
            if not (d <= upper[j] and d >= lower and crow[c] >= min_conf):
                continue
            if min_agree > 0 and crow[c] > 0 and math.isfinite(d) and d > 0:  # _present
                tol = abs_tol + rel_tol * d
                # the usual case first: with a need of two, both row neighbours present and
                # agreeing decide it (the loop below visits them first and stops there)
                row_pair = False
                if min_agree == 2 and c >= 1 and c + 1 < w:
                    dl = drow[c - 1]
                    dr = drow[c + 1]
                    row_pair = (
                        crow[c - 1] > 0
                        and math.isfinite(dl)
                        and dl > 0
                        and abs(dl - d) <= tol
                        and crow[c + 1] > 0
                        and math.isfinite(dr)
                        and dr > 0
                        and abs(dr - d) <= tol
                    )
                if not row_pair:
                    n_valid = 0
                    agree = 0
                    for k in range(8):  # the row's neighbours first, then the column's
                        rr = r + _NB_DY[k]
                        cc = c + _NB_DX[k]
                        if rr < 0 or rr >= h or cc < 0 or cc >= w:
                            continue
                        if _present(depth, conf, rr, cc):
                            n_valid += 1
                            if abs(depth[rr, cc] - d) <= tol:
                                agree += 1
                                if agree >= min_agree:
                                    break
                    if agree < min(max(n_valid, 1), min_agree):
                        continue
            z = np.float64(d)
            x = z * x_per_m[j]
            y = z * y_m
            out[m, 0] = _fma(z, r02, _fma(y, r01, x * r00))
            out[m, 1] = _fma(z, r12, _fma(y, r11, x * r10))
            m += 1
    return out[:m]


_NB_DY = np.array([0, 0, -1, 1, -1, -1, 1, 1])
_NB_DX = np.array([-1, 1, 0, 0, -1, 1, -1, 1])


# ----------------------------------------------------------------------- camera-fixed pixels


@numba.njit(cache=True)
def _prev_depth(dp, v, u):  # pragma: no cover - compiled
    """The previous depth at pixel (v, u) as ``camera_fixed._world_test``'s padded image holds
    it: float64, inf where it is invalid (not finite or not positive) and outside the image.
    Looked up per pixel instead of building the padded (H + 4, W + 4) image: the same values
    for the few thousand lookups of a test, without a pass over the whole image."""
    h, w = dp.shape
    if v < 0 or v >= h or u < 0 or u >= w:
        return np.inf
    d = np.float64(dp[v, u])
    if math.isfinite(d) and d > 0:
        return d
    return np.inf


@numba.njit(cache=True, error_model="numpy")
def _project_prev(
    rr, cc, zz, fx, fy, cx, cy, R, t, s_world, rot_sigma, k_sigma, zp_o, uf_o, vf_o, tol_o
):  # pragma: no cover - compiled
    """The arithmetic of ``camera_fixed._world_test`` for a batch of pixels (rows ``rr``,
    columns ``cc`` as floats, depths ``zz``): the depth ``zp_o`` in the previous camera, the
    rounded pixel ``uf_o``, ``vf_o`` it projects to and the tolerance ``tol_o``. One loop
    without branches, which LLVM vectorises (divisions, fused multiply-adds, square roots and
    roundings several pixels per instruction; each element rounded as the scalar operation
    rounds it, so the same floats); ``error_model="numpy"``: a division by a zero ``zp``
    gives inf / NaN instead of raising (such a pixel is not seen: ``zp > 1e-3`` fails). Same
    operations in the same order as numpy's; ``Q @ R.T`` summed as the BLAS kernel numpy
    calls sums it (OpenBLAS, Haswell and later: a product, then two fused multiply-adds);
    the other sums round each operation as numpy does (numba contracts none into a fused
    multiply-add without fastmath)."""
    r00, r01, r02 = R[0, 0], R[0, 1], R[0, 2]
    r10, r11, r12 = R[1, 0], R[1, 1], R[1, 2]
    r20, r21, r22 = R[2, 0], R[2, 1], R[2, 2]
    t0, t1, t2 = t[0], t[1], t[2]
    for i in range(zz.shape[0]):
        z = zz[i]
        q0 = z * (cc[i] - cx) / fx
        q1 = z * (rr[i] - cy) / fy
        x = _fma(z, r02, _fma(q1, r01, q0 * r00)) + t0
        y = _fma(z, r12, _fma(q1, r11, q0 * r10)) + t1
        zp = _fma(z, r22, _fma(q1, r21, q0 * r20)) + t2
        zp_o[i] = zp
        uf_o[i] = np.rint(fx * x / zp + cx)
        vf_o[i] = np.rint(fy * y / zp + cy)
        qn = math.sqrt(q0 * q0 + q1 * q1) * rot_sigma
        tol_o[i] = k_sigma * math.sqrt(s_world + qn * qn)


@numba.njit(cache=True)
def _hidden_one(dp, dc, vi, ui, z, tol, fx, fy, cx, cy, R, t):  # pragma: no cover - compiled
    """``camera_fixed._hidden`` for one refused point: moved into the previous frame at
    pixel (vi, ui) with depth ``z``, is it hidden there behind a nearer surface that nothing
    shows to move with the camera? Every valid neighbour nearer than ``z - tol``, and the one
    closest to ``z`` (first in raster order on ties), moved back into the current frame
    (``dc``) by the inverse motion, not seen there on valid depth further than ``tol`` from
    where it should be. The same operations in the same order as the numpy path."""
    lim = z - tol
    kbest = np.inf
    vb = 0.0
    dvb = 0
    dub = 0
    found = False
    for dv in range(-1, 2):
        for du in range(-1, 2):
            v = _prev_depth(dp, vi + dv, ui + du)
            if not math.isfinite(v):
                continue
            if not v < lim:
                return False  # a surface at or behind the point was seen: not hidden
            a = abs(v - z)
            if not found or a < kbest:
                kbest = a
                vb = v
                dvb = dv
                dub = du
                found = True
    if not found:
        return False
    # the occluder refutes the occlusion only if fixed to the lens itself: the same depth at
    # the same pixel in the current frame
    if not abs(_prev_depth(dc, vi + dvb, ui + dub) - vb) <= tol:
        return True
    u0 = np.float64(ui + dub)
    v0 = np.float64(vi + dvb)
    d0 = vb * (u0 - cx) / fx - t[0]
    d1 = vb * (v0 - cy) / fy - t[1]
    d2 = vb - t[2]
    x = R[0, 0] * d0 + R[1, 0] * d1 + R[2, 0] * d2
    y = R[0, 1] * d0 + R[1, 1] * d1 + R[2, 1] * d2
    zc = R[0, 2] * d0 + R[1, 2] * d1 + R[2, 2] * d2
    if not zc > 1e-3:
        return True  # behind the current camera: out of view, the occlusion unrefuted
    h, w = dc.shape
    uc = np.rint(fx * x / zc + cx)
    vc = np.rint(fy * y / zc + cy)
    if not (uc >= -1.0 and uc <= w and vc >= -1.0 and vc <= h):
        return True  # out of view
    uci, vci = np.int64(uc), np.int64(vc)
    best = np.inf
    for dv in range(-1, 2):
        for du in range(-1, 2):
            best = min(best, abs(_prev_depth(dc, vci + dv, uci + du) - zc))
    # refuted only by valid current depth that disagrees (no valid pixel: unrefuted)
    return not (math.isfinite(best) and best > tol)


@numba.njit(cache=True)
def _world_batch(
    dp, dc, rr, cc, zz, fx, fy, cx, cy, R, t, s_world, rot_sigma, k_sigma
):  # pragma: no cover - compiled
    """``camera_fixed._world_test`` at a batch of pixels: (seen, consistent) per pixel, the
    arithmetic by :func:`_project_prev`, then the lookups; a refused point hidden behind a
    world-static surface (:func:`_hidden_one`, the current depth ``dc``) is not seen.
    ``consistent`` is False when not seen (every use of it is and-ed with ``seen``)."""
    h, w = dp.shape
    n = zz.shape[0]
    zp = np.empty(n)
    uf = np.empty(n)
    vf = np.empty(n)
    tol = np.empty(n)
    _project_prev(rr, cc, zz, fx, fy, cx, cy, R, t, s_world, rot_sigma, k_sigma, zp, uf, vf, tol)
    seen = np.zeros(n, np.bool_)
    world = np.zeros(n, np.bool_)
    for i in range(n):
        z = zp[i]
        if not z > 1e-3:
            continue
        u = uf[i]
        v = vf[i]
        # further out than a pixel: not seen (NaN and overflow too, which numpy's cast to
        # int64 turns into the most negative integer)
        if not (u >= -1.0 and u <= w and v >= -1.0 and v <= h):
            continue
        ui, vi = np.int64(u), np.int64(v)
        if abs(_prev_depth(dp, vi, ui) - z) <= tol[i]:
            # the centre pixel within the tolerance: the least of the 9 differences is too
            # (and finite), so seen and consistent without the other 8 lookups
            seen[i] = True
            world[i] = True
            continue
        # the least of the 9 differences (in a tree: the same value as numpy's running
        # minimum, no NaN can occur while zp is finite, and a shorter chain of dependent
        # operations); image rows vi - 1 .. vi + 1, columns ui - 1 .. ui + 1
        a0 = min(abs(_prev_depth(dp, vi - 1, ui - 1) - z), abs(_prev_depth(dp, vi - 1, ui) - z))
        a1 = min(abs(_prev_depth(dp, vi - 1, ui + 1) - z), abs(_prev_depth(dp, vi, ui - 1) - z))
        a2 = min(abs(_prev_depth(dp, vi, ui) - z), abs(_prev_depth(dp, vi, ui + 1) - z))
        a3 = min(abs(_prev_depth(dp, vi + 1, ui - 1) - z), abs(_prev_depth(dp, vi + 1, ui) - z))
        best = min(min(min(a0, a1), min(a2, a3)), abs(_prev_depth(dp, vi + 1, ui + 1) - z))
        if not math.isfinite(best):
            continue
        world[i] = best <= tol[i]
        seen[i] = world[i] or not _hidden_one(dp, dc, vi, ui, z, tol[i], fx, fy, cx, cy, R, t)
    return seen, world


@numba.njit(cache=True)
def camera_fixed(
    dp,
    dc,
    cand,
    fx,
    fy,
    cx,
    cy,
    R,
    t,
    s_world,
    rot_sigma,
    k_sigma,
    tol_fixed,
    held,
    use_held,
    view_step,
    view_share,
    out,
    same_out,
):  # pragma: no cover - compiled
    """``camera_fixed.camera_fixed_mask_reference`` compiled: ``out`` (H, W, all False on
    entry) receives the camera-fixed candidates, ``same_out`` the tested pixels whose depth
    is unchanged. ``tol_fixed`` = k sqrt(2) sd, ``s_world`` = 2 sd^2 + var_t (both as numpy
    computes them). Returns (view test run, n_confirm, n_refute, n_changed)."""
    h, w = dc.shape
    tested = np.empty(h * w, np.int64)  # flat indices of the unchanged candidates
    n_same = 0
    for r in range(h):
        for c in range(w):
            if not cand[r, c]:
                continue
            zc = np.float64(dc[r, c])
            zprev = np.float64(dp[r, c])
            if not (math.isfinite(zprev) and zprev > 0 and math.isfinite(zc) and zc > 0):
                continue
            if not abs(zc - zprev) <= tol_fixed:
                continue
            same_out[r, c] = True
            if use_held and held[r, c]:
                out[r, c] = True
            tested[n_same] = r * w + c
            n_same += 1
    if n_same == 0:
        return False, 0, 0, 0
    rr = np.empty(n_same)
    cc = np.empty(n_same)
    zz = np.empty(n_same)
    for i in range(n_same):
        r, c = tested[i] // w, tested[i] % w
        rr[i] = r
        cc[i] = c
        zz[i] = np.float64(dc[r, c])
    seen, world = _world_batch(
        dp, dc, rr, cc, zz, fx, fy, cx, cy, R, t, s_world, rot_sigma, k_sigma
    )
    n_fixed = 0  # the refused ones go to the front of ``tested``
    for i in range(n_same):
        if seen[i] and not world[i]:
            tested[n_fixed] = tested[i]
            n_fixed += 1
    if n_fixed == 0:
        return False, 0, 0, 0
    # the view test: every view_step-th pixel in both directions
    n_grid = ((h + view_step - 1) // view_step) * ((w + view_step - 1) // view_step)
    vr = np.empty(n_grid)
    vc = np.empty(n_grid)
    vz = np.empty(n_grid)
    unchanged = np.empty(n_grid, np.bool_)
    m = 0
    for r in range(0, h, view_step):
        for c in range(0, w, view_step):
            zprev = np.float64(dp[r, c])
            zc = np.float64(dc[r, c])
            if not (math.isfinite(zprev) and zprev > 0 and zc > 0):
                continue
            vr[m] = r
            vc[m] = c
            vz[m] = zc
            unchanged[m] = abs(zc - zprev) <= tol_fixed
            m += 1
    seen, world = _world_batch(
        dp, dc, vr[:m], vc[:m], vz[:m], fx, fy, cx, cy, R, t, s_world, rot_sigma, k_sigma
    )
    n_confirm = 0
    n_refute = 0
    n_changed = 0
    n_seen = 0
    for k in range(m):
        if not seen[k]:
            continue
        n_seen += 1
        if unchanged[k]:
            if not world[k]:
                n_refute += 1
        else:
            n_changed += 1
            if world[k]:
                n_confirm += 1
    if n_confirm >= n_refute or n_confirm >= view_share * n_seen:
        for i in range(n_fixed):
            out[tested[i] // w, tested[i] % w] = True
    return True, n_confirm, n_refute, n_changed


@numba.njit(cache=True)
def label4(img):  # pragma: no cover - compiled
    """``scipy.ndimage.label`` of a 2-D bool image with its default structure (4 neighbours):
    the components numbered 1, 2, ... in the raster order of their first pixel, as scipy
    numbers them, 0 outside. Returns (labels (H, W) int32, number of components)."""
    h, w = img.shape
    labels = np.zeros((h, w), np.int32)
    stack = np.empty(h * w, np.int64)  # every pixel is pushed once, when it is labelled
    n = 0
    for r in range(h):
        for c in range(w):
            if not img[r, c] or labels[r, c] != 0:
                continue
            n += 1
            labels[r, c] = n
            stack[0] = r * w + c
            top = 1
            while top > 0:
                top -= 1
                p = stack[top]
                pr = p // w
                pc = p - pr * w
                if pr > 0 and img[pr - 1, pc] and labels[pr - 1, pc] == 0:
                    labels[pr - 1, pc] = n
                    stack[top] = p - w
                    top += 1
                if pr < h - 1 and img[pr + 1, pc] and labels[pr + 1, pc] == 0:
                    labels[pr + 1, pc] = n
                    stack[top] = p + w
                    top += 1
                if pc > 0 and img[pr, pc - 1] and labels[pr, pc - 1] == 0:
                    labels[pr, pc - 1] = n
                    stack[top] = p - 1
                    top += 1
                if pc < w - 1 and img[pr, pc + 1] and labels[pr, pc + 1] == 0:
                    labels[pr, pc + 1] = n
                    stack[top] = p + 1
                    top += 1
    return labels, n


@numba.njit(cache=True)
def onset_update(
    depth, last, onset, drop_tols, rel_tol, abs_tol, keep_tol, same_tol
):  # pragma: no cover - compiled
    """``camera_fixed.OnsetTracker._update_reference`` compiled, in place: per pixel of the
    (H, W) ``depth`` (0 / non-finite = invalid), the last valid depth ``last`` (float64, nan
    = never valid) and the onset status ``onset`` (bool), the same tests on the same
    float64 values. Returns the counts of the reference: the pixels that got an onset in
    this image (a drop or a first valid depth), and those with an onset whose depth is
    within ``same_tol`` of the last valid one.

    Written without branches (every pixel's status and last depth stored, the unchanged
    value where the depth is invalid; the counts summed per row as 0 / 1): selects instead
    of jumps, ~1.9x faster than the branching loop on the 172 x 224 images of a 60 s
    trial, with the same status, depths and counts (a NaN last depth fails every
    comparison, as it did in the branches)."""
    h, w = depth.shape
    n_fresh = np.int64(0)
    n_same = np.int64(0)
    for r in range(h):
        row_fresh = np.int64(0)
        row_same = np.int64(0)
        for c in range(w):
            d = np.float64(depth[r, c])
            valid = (d > 0.0) & (d < np.inf)  # finite and positive (NaN fails both)
            m = last[r, c]
            change = d - m
            fresh = (m != m) | (change < -drop_tols * (rel_tol * m + abs_tol))
            o = onset[r, c]
            status = fresh | (o & (abs(change) <= keep_tol))
            onset[r, c] = status if valid else o
            last[r, c] = d if valid else m
            row_fresh += np.int64(valid & fresh)
            row_same += np.int64(valid & status & (abs(change) <= same_tol))
        n_fresh += row_fresh
        n_same += row_same
    return n_fresh, n_same
