"""The front end's fast paths give the results of the straightforward formulations they replace
(KD-tree query per ICP iteration, np.linalg.eigh, (N, k, 2) means, np.median, ...)."""

from __future__ import annotations

import numpy as np
import pytest
from scipy.spatial import cKDTree

from vio_graph.frontend import icp as icp_module
from vio_graph.frontend.config import IcpConfig
from vio_graph.frontend.icp import icp_translation_2d
from vio_graph.frontend.smoothing import grid_thin, knn_smooth


@pytest.fixture(autouse=True)
def _compiled_on(monkeypatch: pytest.MonkeyPatch) -> None:
    """The compiled kernels on (VIO_GRAPH_COMPILED=1) unless a test says otherwise."""
    monkeypatch.setenv(icp_module.COMPILED_ENV, "1")


def _stairs(rng: np.random.Generator, n: int = 400, noise_m: float = 0.002) -> np.ndarray:
    """Noisy two-step stair profile (treads and risers), metres."""
    s = rng.uniform(0.0, 1.0, n)
    x = np.where(s < 0.3, s, np.where(s < 0.45, 0.3, np.where(s < 0.75, s - 0.15, 0.6)))
    z = np.where(s < 0.3, 0.0, np.where(s < 0.45, s - 0.3, np.where(s < 0.75, 0.15, s - 0.6)))
    return np.column_stack([x, z]) + rng.normal(0, noise_m, (n, 2))


def _smoothed(rng: np.random.Generator) -> np.ndarray:
    """A profile as the front end makes it: thinned, kNN-smoothed (with exact duplicates)."""
    return knn_smooth(grid_thin(_stairs(rng, 3000), 0.005), 5)


@pytest.mark.parametrize("k", [2, 5, 9, 15])
def test_knn_smooth_equals_the_mean_over_the_neighbours(k: int) -> None:
    pts = _stairs(np.random.default_rng(k), 500)
    _, idx = cKDTree(pts).query(pts, k=k)
    assert np.array_equal(knn_smooth(pts, k), pts[idx].mean(axis=1))


def test_compiled_smoothing_equals_the_numpy_path() -> None:
    """grid_thin and knn_smooth compiled (numba) against their numpy references: the same
    centroids and means bit for bit, the sparse (sorted) grid path included; an exact tie at
    the k-th neighbour goes back to the numpy path."""
    from vio_graph.frontend import smoothing

    kernels = icp_module.compiled_kernels()
    assert kernels is not None
    rng = np.random.default_rng(31)
    for case in range(30):
        pts = _stairs(rng, int(rng.integers(1, 3000)))
        if case % 5 == 0:
            pts = np.vstack([pts, [[4000.0, -3000.0]]])  # 1e12 cells: the sorted path
        cell = [0.005, 0.01, 0.0021][case % 3]
        thin = smoothing.grid_thin(pts, cell)
        assert np.array_equal(thin, smoothing.grid_thin_reference(pts, cell))
        for k in (2, 5, 9):
            ref = smoothing.knn_smooth_reference(thin, k)
            assert np.array_equal(smoothing.knn_smooth(thin, k), ref)
    grid = np.array([[x, z] for x in range(6) for z in range(3)], dtype=float)  # ties everywhere
    assert kernels.knn_smooth(grid, 2)[1] != 0
    assert np.array_equal(smoothing.knn_smooth(grid, 2), smoothing.knn_smooth_reference(grid, 2))


def _check_nearest(src: np.ndarray, tgt: np.ndarray, translations: list[np.ndarray]) -> None:
    tree = cKDTree(src)
    nearest = icp_module._NearestSource(src, tree, tgt, 0.08)
    for T in translations:
        dist, j = nearest.query(T)
        d_ref, j_ref = tree.query(tgt - T, k=1, distance_upper_bound=0.08)
        assert np.array_equal(dist, d_ref)
        found = np.isfinite(d_ref)
        assert np.array_equal(j[~found], j_ref[~found])  # n_src: no neighbour
        # the same point; among exact duplicates any index is the same point
        assert np.array_equal(src[j[found]], src[j_ref[found]])


def test_nearest_source_equals_the_kdtree_query_over_icp_like_steps() -> None:
    rng = np.random.default_rng(3)
    for _ in range(10):
        src = _smoothed(rng)
        assert np.unique(src, axis=0).shape[0] < src.shape[0]  # has exact duplicates
        tgt = src[rng.choice(src.shape[0], 60, replace=False)] + rng.normal(0, 0.01, (60, 2))
        T = rng.normal(0, 0.02, 2)
        steps = [T]
        for _ in range(8):  # converging steps, then a jump and a far translation
            T = T + rng.normal(0, 0.003, 2)
            steps.append(T)
        steps += [T + np.array([0.05, -0.04]), T + np.array([2.0, 0.0]), T]
        _check_nearest(src, tgt, steps)


def test_nearest_source_resolves_exact_ties_like_the_kdtree() -> None:
    # a lattice: many targets are exactly equidistant from two different source points
    g = np.arange(0.0, 0.2, 0.01)
    src = np.array([[x, z] for x in g for z in g])
    tgt = src[::7] + 0.005
    _check_nearest(src, tgt, [np.zeros(2), np.array([0.005, 0.0]), np.array([0.0, 0.005])])
    _check_nearest(src[:5], tgt, [np.zeros(2), np.array([0.1, 0.1])])  # fewer than 8 points


def test_eig_sym2_matches_eigh() -> None:
    rng = np.random.default_rng(5)
    cases = [rng.normal(size=(30, 2)) for _ in range(50)]
    cases += [np.column_stack([np.full(20, 1e-4), np.ones(20)]), np.eye(2), np.zeros((3, 2))]
    for n in cases:
        A = n.T @ n
        (w0, w1), (v0, v1) = icp_module._eig_sym2(A[0, 0], A[0, 1], A[1, 1])
        w, V = np.linalg.eigh(A)
        scale = max(w[-1], 1e-300)
        assert abs(w0 - w[0]) <= 1e-12 * scale and abs(w1 - w[1]) <= 1e-12 * scale
        V2 = np.column_stack([v0, v1])
        assert np.allclose(V2 @ np.diag([w0, w1]) @ V2.T, A, atol=1e-12 * scale)
        assert np.allclose(V2.T @ V2, np.eye(2), atol=1e-14)


def _reference_icp(src, tgt, T0, cfg: IcpConfig):
    """The straightforward ICP (KD-tree query and eigh every iteration, normals as (M, k, 2))."""
    tree = cKDTree(src)
    T = np.array(T0, float)

    def normals(idx):
        _, nb = tree.query(src[idx], k=min(cfg.normal_neighbours, src.shape[0]))
        p = src[nb]
        d = p - p.mean(axis=1, keepdims=True)
        th = 0.5 * np.arctan2(
            2.0 * (d[..., 0] * d[..., 1]).mean(axis=1),
            (d[..., 0] ** 2).mean(axis=1) - (d[..., 1] ** 2).mean(axis=1),
        )
        return np.column_stack([-np.sin(th), np.cos(th)])

    it = 0
    while it < cfg.max_iterations:
        it += 1
        dist, j = tree.query(tgt - T, k=1, distance_upper_bound=cfg.max_correspondence_m)
        keep = np.flatnonzero(np.isfinite(dist))
        n_keep = max(3, int(np.ceil((1.0 - cfg.trim_fraction) * keep.size)))
        keep = keep[np.argsort(dist[keep])[:n_keep]]
        r = tgt[keep] - T - src[j[keep]]
        n = normals(j[keep])
        w, V = np.linalg.eigh(n.T @ n)
        ok = w > max(cfg.degenerate_ratio * w[-1], 1e-9)
        b = V.T @ (n.T @ (n * r).sum(axis=1))
        dT = V[:, ok] @ (b[ok] / w[ok])
        T = T + dT
        if np.linalg.norm(dT) <= cfg.convergence_m:
            break
    r = tgt[keep] - T - src[j[keep]]
    n = normals(j[keep])
    sigma2 = max(float(((r * n).sum(axis=1) ** 2).mean()), cfg.sigma_floor_m**2)
    w, V = np.linalg.eigh(n.T @ n)
    var = np.minimum(sigma2 * cfg.cov_inflation / np.maximum(w, 1e-12), cfg.max_variance_m2)
    var[w <= max(cfg.degenerate_ratio * w[-1], 1e-9)] = cfg.max_variance_m2
    return T, (V * var) @ V.T, it, keep.size


@pytest.mark.parametrize("normal_neighbours", [6, 15])
def test_icp_equals_the_straightforward_implementation(normal_neighbours: int) -> None:
    cfg = IcpConfig(normal_neighbours=normal_neighbours)
    rng = np.random.default_rng(normal_neighbours)
    for case in range(12):
        src = _smoothed(rng)
        true_T = rng.normal(0, 0.03, 2)
        # noise per point: an exact translated copy ties many pair distances, and the trimming
        # of tied distances then depends on the last bits of T
        box = (src[:, 0] > 0.2) & (src[:, 0] < 0.45)
        if case % 3 == 0:  # a flat tread only: the degenerate direction
            box = (src[:, 0] > 0.35) & (src[:, 0] < 0.55) & (src[:, 1] > 0.1)
        tgt = src[box] + true_T + rng.normal(0, 0.002, (int(box.sum()), 2))
        T0 = true_T + rng.normal(0, 0.005, 2)
        res = icp_translation_2d(src, tgt, T0, cfg)
        T, cov, iterations, n_pairs = _reference_icp(src, tgt, T0, cfg)
        assert np.allclose(res.translation_xz_m, T, rtol=0, atol=1e-12)
        assert np.allclose(res.cov_m2, cov, rtol=1e-9, atol=1e-15)
        assert (res.iterations, res.n_correspondences) == (iterations, n_pairs)


def test_compiled_icp_equals_the_numpy_path() -> None:
    """The numba iterations (compiled) against icp_translation_2d_reference: both metrics,
    with and without trimming, with a robust (reweighted) finish, wide normals, coarse grids
    full of exact ties (the kernel hands those back to the numpy path) and targets out of
    range."""
    kernels = icp_module.compiled_kernels()
    assert kernels is not None  # numba is a dependency: the compiled path is the one tested
    rng = np.random.default_rng(21)
    statuses = []
    configs = [
        IcpConfig(),
        IcpConfig(metric="point_to_point"),
        IcpConfig(trim_fraction=0.0, normal_neighbours=15),
        IcpConfig(max_correspondence_m=0.03, normal_neighbours=3),
        IcpConfig(robust_kernel="cauchy"),
        IcpConfig(robust_kernel="huber", metric="point_to_point"),
        IcpConfig(robust_kernel="cauchy", trim_fraction=0.0, normal_neighbours=15),
        IcpConfig(robust_kernel="huber", surface_radius_m=0.012),  # numpy path either way
    ]
    for case in range(80):
        cfg = configs[case % len(configs)]
        src = _smoothed(rng)
        if case % 5 == 4:  # a coarse grid: exact duplicates and exactly tied distances
            src = np.round(src, 2)
        box = (src[:, 0] > rng.uniform(-0.1, 0.4)) & (src[:, 0] < rng.uniform(0.3, 0.7))
        true_T = rng.normal(0, 0.03, 2)
        tgt = src[box] + true_T + rng.normal(0, 0.002, (int(box.sum()), 2))
        if case % 5 == 4:
            tgt = np.round(tgt, 2)
        if case == 7:
            tgt = tgt + 1.0  # nothing within range
        if tgt.shape[0] == 0:
            continue
        T0 = true_T + rng.normal(0, 0.005, 2)
        statuses.append(
            kernels.icp_loop(
                src, np.ascontiguousarray(tgt), T0[0], T0[1], cfg.max_iterations,
                cfg.convergence_m, cfg.max_correspondence_m, cfg.trim_fraction,
                cfg.normal_neighbours, cfg.metric != "point_to_point", cfg.degenerate_ratio,
                *_fresh_normals(src), True, kernels.ROBUST_KERNELS[cfg.robust_kernel],
                cfg.robust_scale, cfg.sigma_floor_m,
            )[-1]
        )  # fmt: skip
        got = icp_translation_2d(src, tgt, T0, cfg)
        ref = icp_module.icp_translation_2d_reference(src, tgt, T0, cfg)
        np.testing.assert_allclose(got.translation_xz_m, ref.translation_xz_m, rtol=0, atol=1e-9)
        np.testing.assert_allclose(got.cov_m2, ref.cov_m2, rtol=1e-9, atol=1e-15)
        assert (got.iterations, got.converged, got.n_correspondences) == (
            ref.iterations,
            ref.converged,
            ref.n_correspondences,
        )
        assert got.rms_m == pytest.approx(ref.rms_m, rel=1e-9)
        if got.n_correspondences:
            assert np.array_equal(got.target_points_xz_m, ref.target_points_xz_m) or np.allclose(
                np.sort(got.target_points_xz_m, axis=0), np.sort(ref.target_points_xz_m, axis=0)
            )
        if case == 7:
            assert got.n_correspondences == 0 and np.array_equal(got.translation_xz_m, T0)
    assert statuses.count(0) >= 50  # mostly compiled,
    assert any(s != 0 for s in statuses)  # and the ties did go back to the numpy path


def _fresh_normals(src: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """The source normals an ICP kernel call starts from when none are known yet."""
    return np.full(src.shape, np.nan), np.zeros(src.shape[0], dtype=bool)


def test_icp_keeping_clear_matches_is_searching_every_time_bit_for_bit() -> None:
    """The ICP kernel does not search again for a target point whose last match is still
    clearly its nearest (``keep_clear_matches``): every output (T, iterations, kept pairs,
    matches, normals, status) is what searching every time gives, bit for bit, on profiles
    as the front end makes them (duplicates from the smoothing), coarse grids with exact ties,
    seeds far off (many iterations), both metrics and the fallback's settings."""
    kernels = icp_module.compiled_kernels()
    assert kernels is not None
    rng = np.random.default_rng(77)
    iterations = []
    for case in range(40):
        src = _smoothed(rng)
        if case % 5 == 4:
            src = np.round(src, 2)
        box = (src[:, 0] > rng.uniform(-0.1, 0.4)) & (src[:, 0] < rng.uniform(0.3, 0.7))
        true_T = rng.normal(0, 0.03, 2)
        tgt = src[box] + true_T + rng.normal(0, [0.0005, 0.002, 0.004][case % 3], (box.sum(), 2))
        if case % 5 == 4:
            tgt = np.round(tgt, 2)
        if tgt.shape[0] == 0:
            continue
        tgt = np.ascontiguousarray(tgt)
        T0 = true_T + rng.normal(0, [0.002, 0.008, 0.015][case % 3], 2)
        k, corr = ((6, 0.05), (15, 0.03))[case % 2]
        args = (src, tgt, T0[0], T0[1], 20, 1e-6, corr, 0.1, k, case % 7 != 6, 0.05)
        fast = kernels.icp_loop(*args, *_fresh_normals(src))
        slow = kernels.icp_loop(*args, *_fresh_normals(src), False)
        assert fast[:4] == slow[:4] and fast[-1] == slow[-1], case
        for a, b in zip(fast[4:7], slow[4:7], strict=True):
            assert np.array_equal(a, b, equal_nan=True), case
        iterations.append(fast[2])
    assert max(iterations) >= 8  # long runs of small steps, where matches are kept


def test_compiled_icp_hands_an_exact_tie_back() -> None:
    """Two distinct source points exactly as near to a target point: which one the KD-tree
    picks is its own business, so the kernel must not decide."""
    kernels = icp_module.compiled_kernels()
    assert kernels is not None
    src = np.array([[-0.25, 0.0], [0.25, 0.0], [0.0, 1.0], [1.0, 1.0]])
    tgt = np.array([[0.0, 0.0], [0.0, 1.0], [1.0, 1.0], [1.0, 0.0]])
    cfg = IcpConfig(max_correspondence_m=0.5, trim_fraction=0.0)
    out = kernels.icp_loop(
        src, tgt, 0.0, 0.0, 20, 1e-6, 0.5, 0.0, 3, True, cfg.degenerate_ratio, *_fresh_normals(src)
    )
    assert out[-1] != 0
    got = icp_translation_2d(src, tgt, None, cfg)
    ref = icp_module.icp_translation_2d_reference(src, tgt, None, cfg)
    assert np.array_equal(got.translation_xz_m, ref.translation_xz_m)


def _same_result(a: icp_module.IcpResult, b: icp_module.IcpResult) -> bool:
    counts_a = (a.iterations, a.converged, a.n_correspondences, a.rms_m)
    counts_b = (b.iterations, b.converged, b.n_correspondences, b.rms_m)
    return (
        counts_a == counts_b
        and np.array_equal(a.translation_xz_m, b.translation_xz_m)
        and np.array_equal(a.cov_m2, b.cov_m2)
        and np.array_equal(a.target_points_xz_m, b.target_points_xz_m)
        and np.array_equal(a.matched_source_xz_m, b.matched_source_xz_m)
    )


def test_shared_source_normals_give_the_same_icp_bit_for_bit() -> None:
    """ICP calls that share a SourceNormals (the tracker's restart check: the same source and
    target from a second seed) give what each call gives alone, bit for bit: a normal is the
    source's own. The cache starts afresh for other points (also the same array changed in
    place) or another neighbour count, and the second call does compute fewer normals."""
    rng = np.random.default_rng(23)
    cfg = IcpConfig(normal_neighbours=15, max_correspondence_m=0.03)
    reused = 0
    for case in range(16):
        src = _smoothed(rng)
        if case % 4 == 3:  # coarse: exact duplicates and ties (the numpy path may answer)
            src = np.round(src, 2)
        box = (src[:, 0] > rng.uniform(-0.1, 0.3)) & (src[:, 0] < rng.uniform(0.35, 0.7))
        true_T = rng.normal(0, 0.03, 2)
        tgt = src[box] + true_T + rng.normal(0, 0.002, (int(box.sum()), 2))
        if tgt.shape[0] == 0:
            continue
        shared = icp_module.SourceNormals()
        seeds = [true_T + rng.normal(0, 0.005, 2) for _ in range(3)]
        for k, T0 in enumerate(seeds):
            have_before = int(shared.have.sum()) if k else 0
            got = icp_translation_2d(src, tgt, T0, cfg, None, shared)
            alone = icp_translation_2d(src, tgt, T0, cfg)
            assert _same_result(got, alone), (case, k)
            reused += have_before
        other = IcpConfig(normal_neighbours=6, max_correspondence_m=0.03)
        got = icp_translation_2d(src, tgt, seeds[0], other, None, shared)
        assert _same_result(got, icp_translation_2d(src, tgt, seeds[0], other))
        moved = src.copy()
        moved[::7] += 0.004  # other points in an array the cache has seen
        shared.arrays(moved, 6)
        moved[::5] -= 0.003  # ... and the same array changed in place
        got = icp_translation_2d(moved, tgt, seeds[1], other, None, shared)
        assert _same_result(got, icp_translation_2d(moved, tgt, seeds[1], other))
    assert reused > 0  # later calls started from normals already known


def _scan_order_neighbours(src: np.ndarray, rank: np.ndarray, i: int, kk: int) -> list[int]:
    """The kk nearest source points of point i in the order a scan outwards in x from it keeps
    them (by distance, then |dx|, left before right, outwards on each side), brute force."""
    px, pz = src[i]
    pos = rank[i]

    def key(m: int) -> tuple:
        dx, dz = src[m, 0] - px, src[m, 1] - pz
        left = rank[m] < pos
        return (dx * dx + dz * dz, abs(px - src[m, 0]), not left, -rank[m] if left else rank[m])

    return sorted(range(src.shape[0]), key=key)[:kk]


def test_grid_neighbour_search_equals_the_x_scan_order() -> None:
    """The ICP kernel's bucket-grid searches (compiled._nearest, compiled._normal) pick the
    points, ties and neighbour order of a scan of the x-sorted source (what the kernel did
    before the grid, and the order its sums depend on): the nearest point within reach (the
    first in x order among equally near ones), and a normal's k nearest in scan order."""
    kernels = icp_module.compiled_kernels()
    assert kernels is not None
    rng = np.random.default_rng(41)
    for case in range(12):
        src = _smoothed(rng)[: int(rng.integers(5, 400))]
        if case % 3 == 2:  # coarse: exact duplicates and equal distances
            src = np.round(src, 2)
        src = np.ascontiguousarray(src)
        rank = np.empty(src.shape[0], np.int64)
        rank[np.argsort(src[:, 0], kind="mergesort")] = np.arange(src.shape[0])
        grid = kernels._grid(src, 0.01)
        reach = 0.03 * (1.0 + 1e-9) + 1e-12
        for q in src[rng.integers(0, src.shape[0], 30)] + rng.normal(0, 0.01, (30, 2)):
            best2, bi, tie, second2 = kernels._nearest(src, grid, rank, q[0], q[1], reach, 0.03**2)
            d2 = (q[0] - src[:, 0]) ** 2 + (q[1] - src[:, 1]) ** 2
            near = np.abs(src - q).max(axis=1) <= reach
            if not near.any():
                assert bi == src.shape[0] and best2 == np.inf
                continue
            assert best2 == d2[near].min()
            # the second-nearest of the points searched (cells around the box: at least the
            # box's points), the kept one's twins included
            others = np.delete(d2, bi)
            assert (
                others.min()
                <= second2
                <= np.delete(d2, bi)[np.delete(near, bi)].min(initial=np.inf)
            )
            at = np.flatnonzero(near & (d2 == best2))
            assert bi == at[np.argmin(rank[at])]
            distinct = np.abs(src[at] - src[bi]).max(axis=1) > 1e-12
            assert tie == (bool(distinct.any()) and best2 < 0.03**2)
        for k in (3, 6, 15):
            kk = min(k + 1, src.shape[0])
            best_d, best_i = np.empty(kk), np.empty(kk, np.int64)
            for i in rng.integers(0, src.shape[0], 20):
                kernels._normal(src, grid, rank, int(i), k, best_d, best_i)
                assert list(best_i) == _scan_order_neighbours(src, rank, int(i), kk)


def test_compiled_icp_pairs_are_numpys_bit_for_bit() -> None:
    """compiled.icp_pairs (the kept pairs, residuals, normals and RMS of one ICP) gives the
    floats of the numpy formulation it replaced in icp_translation_2d, RMS included (numpy's
    pairwise mean), so the covariance from them is the same too."""
    kernels = icp_module.compiled_kernels()
    assert kernels is not None
    cfg = IcpConfig()
    rng = np.random.default_rng(8)
    for n_tgt in (1, 7, 60, 300):  # below, at and beyond numpy's 8-wide and 128 blocks
        src = _smoothed(rng)
        tgt = src[rng.integers(0, src.shape[0], n_tgt)] + 0.004
        tgt = np.ascontiguousarray(tgt + rng.normal(0, 0.001, tgt.shape))  # no exact ties
        tx, tz, _, _, keep, j, normals, status = kernels.icp_loop(
            src, tgt, 0.004, 0.004, 20, 1e-6, 0.03, 0.1, 15, True, cfg.degenerate_ratio,
            *_fresh_normals(src),
        )  # fmt: skip
        assert status == 0 and keep.size > 0
        pairs_t, pairs_s, residual, pair_normals, rms = kernels.icp_pairs(
            src, tgt, tx, tz, keep, j, normals
        )
        T = np.array([tx, tz])
        assert np.array_equal(pairs_t, tgt[keep]) and np.array_equal(pairs_s, src[j[keep]])
        assert np.array_equal(residual, tgt[keep] - T - src[j[keep]])
        assert np.array_equal(pair_normals, normals[j[keep]])
        assert rms == float(np.sqrt((residual**2).sum(axis=1).mean()))
        ref_cov = icp_module._covariance(normals[j[keep]], tgt[keep] - T - src[j[keep]], cfg)
        assert np.array_equal(icp_module._covariance(pair_normals, residual, cfg), ref_cov)


def test_nearest_source_on_small_and_sparse_sets() -> None:
    rng = np.random.default_rng(11)
    for _ in range(100):
        n_src = int(rng.integers(1, 30))
        src = np.round(rng.uniform(0, 0.3, (n_src, 2)), 2)  # coarse grid: duplicates and ties
        tgt = np.round(rng.uniform(-0.05, 0.35, (int(rng.integers(1, 40)), 2)), 2)
        T = np.round(rng.normal(0, 0.05, 2), 3)
        steps = [T + np.round(rng.normal(0, s, 2), 3) for s in (0.0, 0.005, 0.02, 0.1, 0.005)]
        _check_nearest(src, tgt, steps)


def test_sagittal_slice_tables_equal_the_per_pixel_tests() -> None:
    from vio_graph.frontend import projection

    K = np.array([[210.6, 0.0, 111.5], [0.0, 212.9, 85.5], [0.0, 0.0, 1.0]])
    rng = np.random.default_rng(2)
    values = np.array([0, 0.1, 0.1000001, 4.0, 3.9999998, np.nan, np.inf, -1.0, 0.25])
    cols = np.arange(224)
    for trial in range(40):
        dtype = np.float32 if trial % 4 else np.float64
        depth = rng.choice(values, size=(172, 224)).astype(dtype)
        depth = np.where(rng.random(depth.shape) < 0.5, rng.uniform(0, 5, depth.shape), depth)
        depth = depth.astype(dtype)
        # pixels exactly at the lateral boundary |x_C| = half_width of their column
        half_width = float(rng.choice([0.05, 0.03]))
        ax = np.abs((cols - K[0, 2]) / K[0, 0])
        depth[rng.integers(0, 172, 224), cols] = (half_width / np.maximum(ax, 1e-3)).astype(dtype)
        conf = rng.integers(0, 3, depth.shape).astype(np.uint8)
        R = np.linalg.qr(rng.normal(size=(3, 3)))[0]
        args = (
            half_width,
            float(rng.choice([0.0, 0.1, 0.25])),
            float(rng.choice([4.0, 1.5, np.inf])),
            int(rng.integers(1, 3)),
        )
        fast = projection.sagittal_slice_from_depth(depth, conf, K, R, *args)
        reference = projection._sagittal_slice_reference(depth, conf, K, R, *args)
        assert fast.shape[0] > 0
        assert np.array_equal(fast, reference)
        # the per-pixel mask (the camera-fixed test's candidates) holds exactly those pixels
        mask = projection.slice_pixel_mask(depth, conf, K, *args)
        assert int(np.count_nonzero(mask)) == fast.shape[0]
        # the per-column intervals give the mask of the per-pixel tests written out
        assert np.array_equal(mask, projection.slice_pixel_mask_reference(depth, conf, K, *args))
        full = projection.sagittal_slice(
            projection.depth_to_points_cam(depth, conf, K, args[1], args[2], args[3]), R, half_width
        )
        assert np.allclose(fast, full, rtol=0, atol=1e-12)


def _reference_find_levels(pts: np.ndarray, config) -> list:
    """find_levels with numpy medians, np.split runs and array searchsorted (the original)."""
    from vio_graph.frontend.terrain import Level, _robust_extent

    band = config.level_band_m
    order = np.argsort(pts[:, 1])
    z, x = pts[order, 1], pts[order, 0]
    alive = np.ones(z.size, dtype=bool)
    levels = []
    for _ in range(config.max_levels):
        za, xa = z[alive], x[alive]
        if za.size < config.min_level_points:
            break
        counts = np.searchsorted(za, za + band, "right") - np.searchsorted(za, za - band, "left")
        found, tried = False, []
        for i in np.argsort(-counts, kind="stable"):
            if counts[i] < config.min_level_points or len(tried) >= 3:
                break
            if any(abs(za[i] - h) <= band for h in tried):
                continue
            tried.append(float(za[i]))
            lo, hi = np.searchsorted(za, [za[i] - band, za[i] + band], "left")
            height = float(np.median(za[lo:hi]))
            lo, hi = np.searchsorted(za, [height - band, height + band], "left")
            xs = np.sort(xa[lo:hi])
            for r in np.split(xs, np.flatnonzero(np.diff(xs) > config.level_gap_m) + 1):
                if r.size < config.min_level_points:
                    continue
                x_lo, x_med, x_hi = _robust_extent(r)
                if x_hi - x_lo >= config.min_level_length_m:
                    levels.append(Level(height, x_lo, x_hi, x_med, int(r.size)))
                    found = True
            if found:
                alive[np.flatnonzero(alive)[lo:hi]] = False
                break
        if not found:
            break
    return sorted(levels, key=lambda lv: lv.x_median_m)


def test_find_levels_equals_the_numpy_formulation() -> None:
    """The compiled levels (the fixture turns the kernels on) and the numpy path both equal
    the original formulation, bit for bit."""
    from vio_graph.frontend.config import TerrainConfig
    from vio_graph.frontend.terrain import find_levels, find_levels_reference

    assert icp_module.compiled_kernels() is not None

    rng = np.random.default_rng(4)
    configs = [TerrainConfig(), TerrainConfig(min_level_points=3, level_gap_m=0.02)]
    n_levels = 0
    for _ in range(150):
        n = int(rng.integers(5, 400))
        heights = rng.choice([0.0, 0.147, 0.294, -0.147], n)
        pts = np.column_stack([rng.uniform(0, 1, n), heights + rng.normal(0, 0.006, n)])
        if rng.random() < 0.3:
            pts = np.round(pts, 3)  # ties in z and x
        for cfg in configs:
            levels = find_levels(pts, cfg)
            assert levels == _reference_find_levels(pts, cfg)
            assert find_levels_reference(pts, cfg) == levels
            n_levels += len(levels)
    assert n_levels > 300


def test_compiled_level_ransac_equals_the_numpy_path() -> None:
    """The level-surface RANSAC's hypotheses scored compiled and in numpy: the same inlier
    mask, the same random draws consumed, None in the same cases (steep or too short)."""
    from vio_graph.frontend import level

    assert icp_module.compiled_kernels() is not None
    rng = np.random.default_rng(41)
    n_none = n_masks = 0
    for case in range(200):
        n = int(rng.integers(5, 400))
        x = np.sort(rng.uniform(-0.5, 1.0, n))
        z = np.where(x > 0.3, 0.15, 0.0) + rng.normal(0, 0.002, n) + 0.02 * x * (case % 3)
        if case % 5 == 0:
            x, z = np.round(x, 2), np.round(z, 3)  # ties between hypotheses' counts
        if case % 9 == 0:
            z = 2.0 * x  # every line too steep
        if case % 11 == 0:
            x = np.full(n, 0.2) + rng.normal(0, 0.005, n)  # no pair 3 cm apart
        ra, rb = np.random.default_rng(case), np.random.default_rng(case)
        got = level._best_line(x, z, 0.0875, 0.004, ra)
        ref = level._best_line_reference(x, z, 0.0875, 0.004, rb)
        assert (got is None) == (ref is None)
        if ref is None:
            n_none += 1
        else:
            assert np.array_equal(got, ref)
            n_masks += 1
        assert ra.integers(0, 1 << 30) == rb.integers(0, 1 << 30)
    assert n_none > 10 and n_masks > 100


def test_compiled_paths_can_be_switched_off(monkeypatch: pytest.MonkeyPatch) -> None:
    """VIO_GRAPH_COMPILED=0: the numpy paths run (no kernels), with the same answers."""
    src = _smoothed(np.random.default_rng(51))
    tgt = src[(src[:, 0] > 0.2) & (src[:, 0] < 0.45)] + 0.01
    on = icp_translation_2d(src, tgt, np.array([0.012, 0.008]))
    monkeypatch.setattr(icp_module, "_KERNELS", [])
    monkeypatch.setenv(icp_module.COMPILED_ENV, "0")
    assert icp_module.compiled_kernels() is None
    off = icp_translation_2d(src, tgt, np.array([0.012, 0.008]))
    np.testing.assert_allclose(on.translation_xz_m, off.translation_xz_m, rtol=0, atol=1e-9)
    monkeypatch.setattr(icp_module, "_KERNELS", [])
    monkeypatch.setenv(icp_module.COMPILED_ENV, "1")
    assert icp_module.compiled_kernels() is not None
    # unset ("auto"): off until a run asks (the replay of a long recording does)
    monkeypatch.delenv(icp_module.COMPILED_ENV)
    monkeypatch.setattr(icp_module, "_AUTO", [False])
    assert icp_module.compiled_kernels() is None
    icp_module.use_compiled_by_default()
    assert icp_module.compiled_kernels() is not None


def test_compiled_switch_follows_every_change_of_the_environment(
    monkeypatch: pytest.MonkeyPatch,
) -> None:
    """compiled_kernels caches the parse of VIO_GRAPH_COMPILED per value, not the value: every
    change made through os.environ is seen at the next call, and each spelling gives its
    mode ("0" / "false" / "no" / "off" in any case and padding: off; unset: auto, off until
    use_compiled_by_default)."""
    monkeypatch.setattr(icp_module, "_AUTO", [False])
    import os

    def mode_of(text: str | None) -> str:
        m = "auto" if text is None else text.strip().lower()
        return "off" if m in ("0", "false", "no", "off") else m

    for value in ("0", "1", " OFF ", "False", "no", "auto", "yes", "", "\u00e9t\u00e9", None, "1"):
        if value is None:
            monkeypatch.delenv(icp_module.COMPILED_ENV, raising=False)
        else:
            monkeypatch.setenv(icp_module.COMPILED_ENV, value)
        expect_off = mode_of(os.environ.get(icp_module.COMPILED_ENV)) in ("off", "auto")
        assert (icp_module.compiled_kernels() is None) == expect_off


@pytest.mark.parametrize("compiled", ["1", "0"])
def test_speckle_test_at_the_slice_pixels_equals_the_whole_image_filter(
    compiled: str, monkeypatch: pytest.MonkeyPatch
) -> None:
    """sagittal_slice_from_depth(..., speckle=...) evaluates drop_speckles only where the slice
    keeps a pixel (numpy on their bounding box, or the compiled kernel for float32 depth): the
    same points as the whole-image filter followed by the slice, on noisy stair-like images
    (spurious returns, dropout, NaN, float32 and float64 depth)."""
    from vio_graph.frontend import projection

    monkeypatch.setenv(icp_module.COMPILED_ENV, compiled)
    assert (icp_module.compiled_kernels() is not None) == (compiled == "1")

    K = np.array([[210.6, 0.0, 111.5], [0.0, 212.9, 85.5], [0.0, 0.0, 1.0]])
    rng = np.random.default_rng(5)
    rows = np.arange(172, dtype=np.float32)[:, None]
    n_dropped = 0
    for trial in range(24):
        dtype = np.float32 if trial % 3 else np.float64
        depth = 0.4 + (172 - rows) * 0.006 + np.zeros((1, 224), dtype=np.float32)
        depth[: int(rng.integers(40, 120))] += 0.15  # a riser
        spurious = rng.random(depth.shape) < 0.05
        depth[spurious] = rng.uniform(0.05, 4.0, int(spurious.sum()))
        depth[rng.random(depth.shape) < 0.01] = np.nan
        depth = depth.astype(dtype)
        conf = np.where(rng.random(depth.shape) < 0.1, 0, 200).astype(np.uint8)
        R = np.linalg.qr(rng.normal(size=(3, 3)))[0]
        speckle = (0.03, 0.01, int(rng.integers(1, 4)))
        args = (0.05, float(rng.choice([0.0, 0.1])), float(rng.choice([4.0, 1.5])), 1)
        fast = projection.sagittal_slice_from_depth(depth, conf, K, R, *args, speckle)
        filtered = projection.drop_speckles(depth, conf, *speckle)
        reference = projection._sagittal_slice_reference(depth, filtered, K, R, *args)
        unfiltered = projection._sagittal_slice_reference(depth, conf, K, R, *args)
        assert reference.shape[0] > 100
        assert np.array_equal(fast, reference)
        n_dropped += unfiltered.shape[0] - reference.shape[0]
    assert n_dropped > 100  # the filter did drop slice points


def test_level_tilt_means_are_np_mean_bit_for_bit(monkeypatch: pytest.MonkeyPatch) -> None:
    """measure_surface_tilt's means and extents taken without numpy's dispatch
    (level._mean, level._ptp) give the same SurfaceTilt, every float equal, as np.mean and
    np.ptp, on stair-like profiles with 1-4 level lines (the numpy path)."""
    from vio_graph.frontend import level

    monkeypatch.setenv(icp_module.COMPILED_ENV, "0")
    rng = np.random.default_rng(8)
    profiles = []
    for case in range(60):
        n_steps = int(rng.integers(1, 5))
        x = np.sort(rng.uniform(-0.3, 0.3 * n_steps, int(rng.integers(60, 400))))
        z = 0.15 * np.floor(x / 0.3) + rng.normal(0, 0.002, x.size) + 0.01 * x * (case % 3)
        profiles.append(np.column_stack([x, z]))
    fast = [
        level.measure_surface_tilt(p, np.random.default_rng(k), end_trim_m=0.01)
        for k, p in enumerate(profiles)
    ]
    monkeypatch.setattr(level, "_mean", lambda a: float(np.mean(a)))
    monkeypatch.setattr(level, "_ptp", lambda a: float(np.ptp(a)))
    ref = [
        level.measure_surface_tilt(p, np.random.default_rng(k), end_trim_m=0.01)
        for k, p in enumerate(profiles)
    ]
    assert sum(t is not None and t.n_lines >= 2 for t in fast) > 20
    assert fast == ref  # dataclass equality: every float the same


def test_compiled_corner_lines_equal_the_numpy_path() -> None:
    """The corners' horizontal-line RANSAC and largest run compiled and in numpy: the same
    height, the same inlier mask, the same draws consumed, None in the same cases (no
    candidate, every hypothesis excluded); the same run."""
    from vio_graph.frontend import corners

    assert icp_module.compiled_kernels() is not None
    rng = np.random.default_rng(43)
    n_none = n_lines = 0
    for case in range(200):
        pts = _stairs(rng, int(rng.integers(1, 300)), noise_m=0.003)
        if case % 5 == 0:
            pts = np.round(pts, 2)  # ties between the hypotheses' counts and in the runs
        cand = None if case % 3 == 0 else rng.uniform(size=pts.shape[0]) < 0.7
        if case % 13 == 0:
            cand = np.zeros(pts.shape[0], bool)  # no candidate at all
        exclude = () if case % 2 else (0.0, 0.15)
        separation = 0.5 if case % 7 == 0 else 0.02  # 0.5: every hypothesis excluded
        ra, rb = np.random.default_rng(case), np.random.default_rng(case)
        got = corners.ransac_horizontal_line(pts, 0.01, 20, ra, exclude, separation, cand)
        ref = corners.ransac_horizontal_line_reference(pts, 0.01, 20, rb, exclude, separation, cand)
        assert (got is None) == (ref is None)
        if ref is None:
            n_none += 1
        else:
            assert got is not None
            assert got.height_m == ref.height_m
            assert np.array_equal(got.inliers, ref.inliers)
            n_lines += 1
            gap = 0.005 * (case % 4)
            x = pts[ref.inliers, 0]
            assert np.array_equal(
                corners._largest_run(x, gap), corners._largest_run_reference(x, gap)
            )
        assert ra.integers(0, 1 << 30) == rb.integers(0, 1 << 30)
    assert n_none > 20 and n_lines > 100


def test_face_percentiles_and_medians_are_numpys_bit_for_bit() -> None:
    """find_faces' percentile (linear) and median on sorted values equal np.percentile and
    np.median exactly, for every size (odd, even, 1) and with ties."""
    from vio_graph.frontend.terrain import _median_sorted, _percentile_sorted

    rng = np.random.default_rng(47)
    for n in [*range(1, 40), 97, 128, 301]:
        for _ in range(5):
            v = rng.normal(0.1, 0.05, n)
            if n % 3 == 0:
                v = np.round(v, 2)
            s = np.sort(v).tolist()
            for q in (5, 50, 95):
                assert _percentile_sorted(s, q) == np.percentile(v, q)
            assert _median_sorted(s, 0, n) == np.median(v)


def _level_profiles(rng: np.random.Generator, n_cases: int) -> list[np.ndarray]:
    """Stair-like profiles with 1-4 treads, tilted, some too steep or rounded to a grid."""
    out = []
    for case in range(n_cases):
        n_steps = int(rng.integers(1, 5))
        x = np.sort(rng.uniform(-0.3, 0.3 * n_steps, int(rng.integers(20, 600))))
        z = 0.15 * np.floor(x / 0.3) + rng.normal(0, 0.002, x.size) + 0.01 * x * (case % 3)
        if case % 7 == 0:
            z = 2.0 * x  # every line too steep
        if case % 5 == 0:
            x, z = np.round(x, 3), np.round(z, 3)  # ties between the hypotheses' counts
        out.append(np.column_stack([x, z]))
    return out


def test_compiled_surface_tilt_equals_the_numpy_path() -> None:
    """measure_surface_tilt in one compiled call (compiled.surface_tilt, the random draws
    taken by numba's Generator.integers from the caller's generator) and its numpy path: the
    same lines (count, points, extents bit for bit), the tilt, sigmas and heights to rounding
    (the dot products are summed in another order than BLAS's), None in the same cases, the
    same draws consumed."""
    from vio_graph.frontend import level

    assert icp_module.compiled_kernels() is not None
    rng = np.random.default_rng(8)
    n_none = n_multi = 0
    for k, p in enumerate(_level_profiles(rng, 300)):
        trim = 0.01 * (k % 2)
        ra, rb = np.random.default_rng(k), np.random.default_rng(k)
        got = level.measure_surface_tilt(p, ra, end_trim_m=trim)
        ref = level._surface_tilt_numpy(p, rb, np.radians(5.0), 0.004, 25, 0.12, 4, 5.0, trim)
        assert ra.integers(0, 1 << 30) == rb.integers(0, 1 << 30)
        assert (got is None) == (ref is None)
        if ref is None:
            n_none += 1
            continue
        assert got is not None
        assert (got.n_lines, got.n_inliers) == (ref.n_lines, ref.n_inliers)
        n_multi += got.n_lines >= 2
        np.testing.assert_allclose(
            [got.tilt_rad, got.sigma_rad, got.extent_m],
            [ref.tilt_rad, ref.sigma_rad, ref.extent_m],
            rtol=1e-12,
            atol=1e-15,
        )
        for a, b in zip(got.lines, ref.lines, strict=True):
            assert (a.x_min_m, a.x_max_m) == (b.x_min_m, b.x_max_m)
            np.testing.assert_allclose(
                [a.height_m, a.sigma_m, a.x_mid_m, a.noise_sigma_m],
                [b.height_m, b.sigma_m, b.x_mid_m, b.noise_sigma_m],
                rtol=1e-12,
                atol=1e-12,
            )
            assert a.noise_sigma_m > 0.0 and a.x_mid_m != 0.0  # the shared-tilt fields are set
    assert n_none > 30 and n_multi > 100


def test_compiled_pairwise_sum_is_np_add_reduce_bit_for_bit() -> None:
    """The compiled means of the level kernel and the clock line sum like np.add.reduce
    (pairwise, blocks of 128), every size up to a few blocks, so the same floats."""
    from vio_graph import compiled_sums

    rng = np.random.default_rng(9)
    for n in [*range(1, 300), 511, 1000, 4097]:
        a = rng.normal(size=n) * 10.0 ** rng.uniform(-3, 3, n)
        assert compiled_sums.pairwise_sum(a, 0, n) == np.add.reduce(a)
        assert compiled_sums.add_reduce(a) == np.add.reduce(a)
        assert compiled_sums.pairwise_sum(np.r_[1.0, a], 1, n) == np.add.reduce(a)


def test_compiled_corner_equals_the_numpy_path() -> None:
    """extract_corner in one compiled call (compiled.corner, the draws taken by numba's
    Generator.integers from the caller's generator) and its numpy path
    (extract_corner_reference): the same CornerFeature bit for bit, None in the same cases,
    the same draws consumed; every terrain class (near, far and median-decided ends), with
    and without the face requirement, on noisy and grid-rounded steps."""
    import dataclasses

    from vio_graph.frontend import corners
    from vio_graph.frontend.config import CornerConfig
    from vio_graph.types import TerrainKind

    assert icp_module.compiled_kernels() is not None
    rng = np.random.default_rng(3)
    kinds = list(TerrainKind)
    n_found = n_face = n_far = 0
    for case in range(400):
        n = int(rng.integers(10, 500))
        s = rng.uniform(0, 1, n)
        rise = rng.uniform(0.1, 0.2)
        x = np.where(s < 0.3, s, np.where(s < 0.45, 0.3, np.where(s < 0.75, s - 0.15, 0.6)))
        z = np.where(
            s < 0.3,
            0.0,
            np.where(s < 0.45, (s - 0.3) / 0.15 * rise, np.where(s < 0.75, rise, rise + s - 0.75)),
        )
        pts = np.column_stack([x + rng.uniform(-0.5, 0.5), z])
        pts += rng.normal(0, rng.choice([0.001, 0.003, 0.01]), (n, 2))
        if case % 6 == 0:
            pts = np.round(pts, 2)
        cfg = CornerConfig(
            near_edge_needs_face=bool(case % 2), face_band_m=[0.02, 0.04][case % 3 % 2]
        )
        terrain = kinds[case % len(kinds)]
        ra, rb = np.random.default_rng(case), np.random.default_rng(case)
        got = corners.extract_corner(pts, ra, cfg, terrain)
        ref = None
        if pts.shape[0] >= 2 * cfg.min_line_inliers:
            ref = corners.extract_corner_reference(pts, rb, cfg, terrain)
        assert ra.integers(0, 1 << 30) == rb.integers(0, 1 << 30)
        assert (got is None) == (ref is None)
        if ref is None:
            continue
        assert got is not None
        for f in dataclasses.fields(ref):
            assert np.array_equal(getattr(got, f.name), getattr(ref, f.name)), f.name
        n_found += 1
        n_face += ref.has_face
        n_far += ref.side == "far"
    assert n_found > 250 and n_face > 100 and n_far > 40


def test_compiled_level_band_counts_and_order_equal_numpys() -> None:
    """find_levels' compiled band counts (two pointers) and their order (counting sort) equal
    the searchsorted counts and the stable argsort of the numpy reference, ties included."""
    from vio_graph.frontend import compiled

    rng = np.random.default_rng(13)
    for case in range(500):
        za = np.sort(rng.normal(0.0, 0.1, int(rng.integers(1, 400))))
        if case % 3 == 0:
            za = np.round(za, 2)  # runs of equal heights and keys on the values
        band = [0.005, 0.01, 0.0][case % 3]
        want = np.searchsorted(za, za + band, "right") - np.searchsorted(za, za - band, "left")
        counts = compiled._band_counts(za, band)
        assert np.array_equal(counts, want)
        assert np.array_equal(compiled._descending_stable(counts), np.argsort(-want, kind="stable"))


def test_rng_handle_draws_what_the_generator_draws() -> None:
    """compiled.rng_ref: the kernels' handle on a Generator draws the same integers as the
    Generator itself and advances the same state (the Generator's next draw in Python is the
    one it would have made after the kernel's), and one handle is kept per Generator."""
    kernels = icp_module.compiled_kernels()
    assert kernels is not None
    x = np.linspace(0.0, 1.0, 200)
    z = np.where(x < 0.5, 0.0, 0.15) + np.random.default_rng(0).normal(0, 0.001, 200)
    args = (400, 0.09, 0.004, 25, 0.12, 4, 0.0, 5.0)
    a, b = np.random.default_rng(7), np.random.default_rng(7)
    via_handle = kernels.surface_tilt(x, z, kernels.rng_ref(a), *args)
    direct = kernels.surface_tilt(x, z, b, *args)
    assert via_handle[0] == direct[0] == 0
    assert np.array_equal(via_handle[4], direct[4]) and via_handle[1] == direct[1]
    assert np.array_equal(a.integers(0, 10**9, 5), b.integers(0, 10**9, 5))
    assert kernels.rng_ref(a) is kernels.rng_ref(a)


def _blas_matmul_is_forward_fma() -> bool:
    """Whether numpy's (N, 3) @ (3, 2) here sums as a product then two fused multiply-adds
    in index order (OpenBLAS on Haswell and later), checked exactly with fractions."""
    from fractions import Fraction

    rng = np.random.default_rng(0)
    p = rng.normal(size=(64, 3))
    R = rng.normal(size=(2, 3))
    got = p @ R.T

    def fma(a: float, b: float, c: float) -> float:
        return float(Fraction(a) * Fraction(b) + Fraction(c))

    want = [[fma(a[2], r[2], fma(a[1], r[1], a[0] * r[0])) for r in R] for a in p]
    return bool(np.array_equal(got, np.array(want)))


def test_compiled_slice_equals_the_numpy_path_at_every_agreement_count() -> None:
    """The compiled slice (the pixel tests, the speckle test stopping once ``min_agree``
    neighbours agree, back-projection and eq. 2 in one pass) against the numpy path on the
    same tables, for every ``min_agree`` of 0..8, with neighbours exactly at the tolerance and
    the column band reaching the image borders: the same pixels, and the same floats where
    numpy's matrix product sums as the kernel does (else within 1e-12 m)."""
    from vio_graph.frontend import projection

    kernels = icp_module.compiled_kernels()
    assert kernels is not None
    exact = _blas_matmul_is_forward_fma()
    K = np.array([[210.6, 0.0, 111.5], [0.0, 212.9, 85.5], [0.0, 0.0, 1.0]])
    rng = np.random.default_rng(8)
    for trial in range(27):
        min_agree = trial % 9
        rows = np.arange(172, dtype=np.float32)[:, None]
        depth = (0.3 + 0.0002 * rows + np.zeros((1, 224))).astype(np.float32)
        # neighbours at exactly abs_tol + rel_tol * d of each other along rows
        step = np.float32(0.01) + np.float32(0.03) * depth[:, :1]
        depth[:, 1::2] = depth[:, :1] + step
        depth[:, ::2] = depth[:, :1]
        noisy = rng.random(depth.shape) < 0.1
        depth[noisy] = rng.uniform(0.05, 4.0, int(noisy.sum())).astype(np.float32)
        depth[rng.random(depth.shape) < 0.02] = np.nan
        conf = np.where(rng.random(depth.shape) < 0.1, 0, 200).astype(np.uint8)
        half_width = float(rng.choice([0.05, 0.5]))  # 0.5: the band reaches the borders
        tables = projection._slice_tables(
            K.tobytes(), depth.shape, depth.dtype, half_width, 0.1, 4.0
        )
        c0, c1, lower, upper, x_grid, y_grid = tables
        R_xz = np.linalg.qr(rng.normal(size=(3, 3)))[0][[0, 2], :]
        speckle = (np.float32(0.03), np.float32(0.01), min_agree)
        fast = kernels.slice_xz(
            depth, conf, c0, c1, lower, upper, 1, *speckle, x_grid[0], y_grid[:, 0], R_xz
        )
        cam = projection._slice_cam_points_numpy(
            depth, conf, c0, c1, lower, upper, 1, speckle if min_agree else None, x_grid, y_grid
        )
        ref = cam @ R_xz.T
        assert ref.shape[0] > 20
        assert fast.shape == ref.shape
        if exact:
            assert np.array_equal(fast, ref)
        else:
            assert np.allclose(fast, ref, rtol=0, atol=1e-12)


def test_compiled_slice_row_pair_shortcut_at_the_tolerance() -> None:
    """The compiled slice's shortcut for a need of two (both row neighbours present and
    agreeing) against the numpy path where the row neighbours lie a float32 step inside or
    outside the tolerance, are invalid or off the image, for needs of 1-3: the same pixels
    (a shortcut that accepted a neighbour beyond the tolerance, or one that is not present,
    would keep pixels the numpy path drops)."""
    from vio_graph.frontend import projection

    kernels = icp_module.compiled_kernels()
    assert kernels is not None
    K = np.array([[210.6, 0.0, 111.5], [0.0, 212.9, 85.5], [0.0, 0.0, 1.0]])
    rng = np.random.default_rng(21)
    n_kept = {}
    for min_agree in (1, 2, 3, 2, 2):
        rows = np.arange(172, dtype=np.float32)[:, None]
        depth = (0.3 + 0.002 * rows + np.zeros((1, 224))).astype(np.float32)
        step = np.float32(0.01) + np.float32(0.03) * depth[:, :1]
        depth[:, 1::2] = depth[:, :1] + step  # the odd columns at the tolerance of the even
        # a float32 step or two up or down on a third of the pixels: either side of it
        nudge = rng.integers(-2, 3, depth.shape) * (rng.random(depth.shape) < 0.33)
        for k in (-2, -1, 1, 2):
            at = nudge == k
            toward = np.float32(np.inf) if k > 0 else np.float32(-np.inf)
            for _ in range(abs(k)):
                depth[at] = np.nextafter(depth[at], toward)
        depth[rng.random(depth.shape) < 0.03] = np.nan
        conf = np.where(rng.random(depth.shape) < 0.05, 0, 200).astype(np.uint8)
        tables = projection._slice_tables(K.tobytes(), depth.shape, depth.dtype, 0.5, 0.1, 4.0)
        c0, c1, lower, upper, x_grid, y_grid = tables
        R_xz = np.eye(3)[[0, 2], :]
        speckle = (np.float32(0.03), np.float32(0.01), min_agree)
        fast = kernels.slice_xz(
            depth, conf, c0, c1, lower, upper, 1, *speckle, x_grid[0], y_grid[:, 0], R_xz
        )
        cam = projection._slice_cam_points_numpy(
            depth, conf, c0, c1, lower, upper, 1, speckle, x_grid, y_grid
        )
        assert fast.shape == (cam.shape[0], 2)
        assert np.array_equal(fast, cam @ R_xz.T)
        n_kept[min_agree] = cam.shape[0]
    # the nudges decide pixels: fewer kept with a larger need, and not all dropped
    assert 0 < n_kept[3] < n_kept[2] < n_kept[1] < 172 * 224


def test_compiled_seen_under_equals_the_numpy_mask() -> None:
    """surface.seen_under_mask compiled (``compiled.seen_under``: sorted prefix, blocks
    skipped by a bound, the count stopped at the threshold) against its numpy form: the same
    mask on open-riser scenes (points that are seen under), random clouds with ties on a
    grid, NaNs and points behind the camera, for several margins, drops and counts."""
    from vio_graph.surface import seen_under_mask

    kernels = icp_module.compiled_kernels()
    assert kernels is not None
    front = np.column_stack([np.full(7, 0.7), np.linspace(-0.18, -0.15, 7)])
    tread = np.column_stack([np.linspace(0.4, 0.69, 30), np.full(30, -0.3)])
    floor = np.column_stack([np.linspace(1.0, 1.6, 60), np.full(60, -0.45)])
    rng = np.random.default_rng(12)
    n_seen = 0
    for case in range(200):
        n = int(rng.integers(0, 300))
        pts = np.column_stack([rng.uniform(-0.1, 2.0, n), rng.uniform(-0.8, 0.4, n)])
        if case % 2 == 0:  # an open-riser scene with noise, some points seen under
            scene = np.vstack([front, tread, floor])
            pts = np.vstack([pts[: n // 8], scene + rng.normal(0, 0.003, scene.shape)])
        if case % 5 == 0:
            pts = np.round(pts, 2)  # ties in x and on the line of sight
        if case % 7 == 0 and pts.shape[0]:
            pts[rng.integers(0, pts.shape[0]), int(rng.integers(0, 2))] = np.nan
        for margin, drop, count in ((0.05, 0.04, 3), (0.0, 0.0, 1), (0.2, 0.1, 5), (0.05, 0.04, 0)):
            ref = seen_under_mask(pts, margin, drop, count)
            fast = kernels.seen_under(
                np.ascontiguousarray(pts[:, 0]),
                np.ascontiguousarray(pts[:, 1]),
                margin,
                drop,
                count,
            )
            assert np.array_equal(fast, ref)
            n_seen += int(ref.sum())
    assert n_seen > 1000


def test_compiled_seen_under_with_the_floor_beyond_a_slab_equals_the_numpy_masks() -> None:
    """``compiled.seen_under_floor`` (the front end's ``points_seen_under`` in one call)
    against ``seen_under_mask | floor_beyond_slab_mask``: the same mask on an open-riser
    flight whose floor runs on under a tread (points found beyond the slab), random levels
    over random clouds, NaNs, no levels, for several margins, drops, bands and counts."""
    from vio_graph.surface import floor_beyond_slab_mask, seen_under_mask

    kernels = icp_module.compiled_kernels()
    assert kernels is not None
    tread = np.column_stack([np.linspace(0.4, 0.69, 30), np.full(30, -0.3)])
    floor = np.column_stack([np.linspace(0.05, 1.6, 160), np.full(160, -0.45)])
    rng = np.random.default_rng(21)
    n_beyond = 0
    for case in range(200):
        n = int(rng.integers(0, 200))
        pts = np.column_stack([rng.uniform(-0.1, 2.0, n), rng.uniform(-0.8, 0.4, n)])
        if case % 2 == 0:  # a tread over the floor, which runs on beyond it
            scene = np.vstack([tread, floor])
            pts = np.vstack([pts[: n // 8], scene + rng.normal(0, 0.003, scene.shape)])
            z = [-0.3, -0.45]
            lo, hi = [0.4, 0.05], [0.69, 1.6]
        else:
            n_lv = int(rng.integers(0, 4))
            z = rng.uniform(-0.6, 0.2, n_lv).tolist()
            lo = rng.uniform(-0.1, 1.0, n_lv).tolist()
            hi = (np.asarray(lo) + rng.uniform(0.0, 1.2, n_lv)).tolist()
        if case % 5 == 0:
            pts = np.round(pts, 2)  # ties at the bands' and extents' edges
        if case % 7 == 0 and pts.shape[0]:
            pts[rng.integers(0, pts.shape[0]), int(rng.integers(0, 2))] = np.nan
        for margin, drop, count, min_pts in (
            (0.05, 0.04, 3, 10),
            (0.0, 0.0, 1, 0),
            (0.2, 0.1, 5, 30),
        ):
            ref = seen_under_mask(pts, margin, drop, count)
            beyond = floor_beyond_slab_mask(pts, z, lo, hi, margin, drop, drop, min_pts)
            ref = ref | beyond
            fast = kernels.seen_under_floor(
                np.ascontiguousarray(pts[:, 0]),
                np.ascontiguousarray(pts[:, 1]),
                margin,
                drop,
                count,
                np.array(z, dtype=float),
                np.array(lo, dtype=float),
                np.array(hi, dtype=float),
                drop,
                min_pts,
            )
            assert np.array_equal(fast, ref)
            n_beyond += int(beyond.sum())
    assert n_beyond > 1000


def test_compiled_depth_noise_equals_the_numpy_path() -> None:
    """level_residuals and robust_sigma with the kernels on (``compiled.level_bands``,
    ``compiled.median_abs_deviation``) against their numpy references: the same
    residuals and sigma bit for bit, with points exactly on the range circle and on a band's
    edges, ties, NaNs, no level, overlapping bands, and even and odd counts."""
    from vio_graph.frontend import noise

    assert icp_module.compiled_kernels() is not None
    rng = np.random.default_rng(5)
    for case in range(150):
        n = int(rng.integers(0, 1500))
        pts = np.column_stack([rng.uniform(-0.2, 1.0, n), rng.uniform(-0.6, 0.2, n)])
        if case % 4 == 0:
            pts = np.round(pts, 2)  # on the bands' edges
        if case % 9 == 0 and n:
            pts[0, 1] = np.nan
        ang = rng.uniform(-1.5, 0.2, 40)
        pts = np.vstack([pts, 0.6 * np.column_stack([np.cos(ang), np.sin(ang)])])
        heights = rng.uniform(-0.6, 0.2, int(rng.integers(0, 5)))
        levels = [
            (h, lo, lo + rng.uniform(0.05, 0.6))
            for h, lo in zip(heights, rng.uniform(-0.2, 0.8, heights.size), strict=True)
        ]
        for max_range in (0.6, np.inf):
            for band in (0.02, 0.0):
                fast = noise.level_residuals(pts, levels, band, min_points=5, max_range_m=max_range)
                ref = noise.level_residuals_reference(pts, levels, band, 5, max_range)
                assert np.array_equal(fast, ref, equal_nan=True)
    sizes = 0
    for case in range(400):
        r = rng.normal(0.0, 0.003, int(rng.integers(0, 80)))
        if case % 3 == 0:
            r = np.round(r, 3)  # ties, zero deviations
        if case % 5 == 0 and r.size:
            r[: r.size // 2] = r[0]
        if case % 17 == 0 and r.size:
            r[0] = np.nan
        fast, ref = noise.robust_sigma(r), noise.robust_sigma_reference(r)
        assert fast == ref or (np.isnan(fast) and np.isnan(ref))
        sizes += r.size % 2
    assert 0 < sizes < 400  # odd and even counts


def test_compiled_level_noise_sigma_equals_the_numpy_path() -> None:
    """level_noise_sigma in one compiled call (``compiled.level_noise``: bands, line fits,
    MAD) against robust_sigma_reference(level_residuals_reference(...)): the same float bit
    for bit, with band edges, ties, NaNs, infinities, no level, levels below the point
    count, overlapping bands and a replay-sized band of thousands of points."""
    from vio_graph.frontend import noise

    assert icp_module.compiled_kernels() is not None
    rng = np.random.default_rng(23)
    n_finite = 0
    for case in range(200):
        n = int(rng.integers(0, 9000 if case % 10 == 0 else 1500))
        pts = np.column_stack([rng.uniform(-0.2, 1.0, n), rng.uniform(-0.6, 0.2, n)])
        heights = rng.uniform(-0.6, 0.2, int(rng.integers(0, 5)))
        if case % 3 == 0 and n:  # dense bands about a tilted line
            heights = np.append(heights, -0.3)
            pts[: n // 2, 1] = -0.3 + 0.02 * pts[: n // 2, 0] + rng.normal(0, 0.003, n // 2)
        if case % 4 == 0:
            pts = np.round(pts, 2)  # on the bands' edges, ties
        if case % 9 == 0 and n:
            pts[0, 1] = np.nan
        if case % 13 == 0 and n:
            pts[-1] = (0.5, np.inf)
        levels = [
            (h, lo, lo + rng.uniform(0.05, 1.2))
            for h, lo in zip(heights, rng.uniform(-0.2, 0.8, heights.size), strict=True)
        ]
        for max_range in (0.6, np.inf):
            for band in (0.02, 0.0):
                for min_points in (5, 20):
                    args = (pts, levels, band, min_points, max_range)
                    fast = noise.level_noise_sigma(*args)
                    ref = noise.level_noise_sigma_reference(*args)
                    assert fast == ref or (np.isnan(fast) and np.isnan(ref)), (case, fast, ref)
                    n_finite += int(np.isfinite(ref))
    assert n_finite > 500


def test_compiled_robust_sigma_by_selection_equals_the_numpy_medians() -> None:
    """robust_sigma's kernel (``compiled.median_abs_deviation``: both medians by selection,
    no sort) against
    ``np.median(np.abs(r - np.median(r)))`` on residual sets of 1 to thousands of values (a
    replay's size), odd and even, with many ties, signed zeros, a constant run, one-sided
    sets, infinities and NaNs (the numpy path then): the same float bit for bit."""
    from vio_graph.frontend import noise

    kernels = icp_module.compiled_kernels()
    assert kernels is not None
    rng = np.random.default_rng(12)
    n_kernel = 0
    for case in range(120):
        r = rng.normal(0.0, 0.003, int(rng.integers(1, 7000 if case % 2 else 12)))
        if case % 7 == 6:
            r = np.abs(r) ** 3  # most deviations on one side
        if case % 3 == 0:
            r = np.round(r, 4)  # many ties
        if case % 4 == 1:
            r[rng.random(r.size) < 0.3] = -0.0
            r[rng.random(r.size) < 0.3] = 0.0
        if case % 5 == 2:
            r[: r.size // 2] = r[-1]
        if case % 11 == 3:
            r[int(rng.integers(0, r.size))] = (np.inf, -np.inf, np.nan)[case % 3]
        fast, ref = noise.robust_sigma(r), noise.robust_sigma_reference(r)
        assert fast == ref or (np.isnan(fast) and np.isnan(ref))
        assert np.signbit(fast) == np.signbit(ref)
        if np.isfinite(r).all():
            n_kernel += 1
            mad, ok = kernels.median_abs_deviation(r)
            assert ok
            assert mad == np.median(np.abs(r - np.median(r)))
            assert not np.signbit(mad)
    assert 100 < n_kernel < 120


def test_compiled_under_levels_equals_the_numpy_mask() -> None:
    """surface.under_levels_mask compiled (``compiled.under_levels``, point by point) against
    its numpy form: the same mask for random levels (overlapping, nested, shorter than the
    margins) over open-riser scenes and random clouds with ties, NaNs and points behind the
    camera, with and without the line-of-sight rule."""
    from vio_graph.surface import under_levels_mask

    kernels = icp_module.compiled_kernels()
    assert kernels is not None
    rng = np.random.default_rng(21)
    n_under = 0
    for case in range(300):
        n = int(rng.integers(0, 400))
        pts = np.column_stack([rng.uniform(-0.1, 2.0, n), rng.uniform(-0.8, 0.2, n)])
        if case % 3 == 0:
            pts = np.round(pts, 2)  # on the levels' ends and heights
        if case % 7 == 0 and n:
            pts[rng.integers(0, n), int(rng.integers(0, 2))] = np.nan
        n_levels = int(rng.integers(0, 5))
        z = np.round(rng.uniform(-0.8, 0.2, n_levels), 2)
        lo = np.round(rng.uniform(-0.1, 1.5, n_levels), 2)
        hi = lo + np.round(rng.uniform(0.0, 0.8, n_levels), 2)
        for margin, drop, band, sight in ((0.05, 0.04, 0.04, 0.01), (0.0, 0.0, 0.0, 0.0)):
            for use_sight in (True, False):
                ref = under_levels_mask(
                    pts, z, lo, hi, margin, drop, band, sight if use_sight else None
                )
                fast = kernels.under_levels(
                    np.ascontiguousarray(pts[:, 0]),
                    np.ascontiguousarray(pts[:, 1]),
                    z,
                    lo,
                    hi,
                    margin,
                    drop,
                    band,
                    sight,
                    use_sight,
                )
                assert np.array_equal(fast, ref)
                n_under += int(ref.sum())
    assert n_under > 1000


def _camera_fixed_scene(rng: np.random.Generator, case: int):
    """Two depth frames of a stair (a camera-fixed blob in most), their camera -> ground
    rotations and the true ground displacement; NaN and zero pixels sprinkled in."""
    from vio_graph.frontend.synthetic import (
        camera_rotation,
        pico_flexx_K,
        render_depth,
        stair_polyline,
    )

    K = pico_flexx_K()
    poly = stair_polyline("stair_up", start_x_m=0.5)
    p0 = np.array([0.0, 0.45]) + rng.normal(0.0, 0.02, 2)
    step = rng.normal(0.0, [0.03, 0.01]) if case % 4 else np.zeros(2)  # some: standing
    pitches = 0.6 + rng.normal(0.0, 0.05), 0.6 + rng.normal(0.0, 0.05)
    frames = []
    for p, pitch in ((p0, pitches[0]), (p0 + step, pitches[1])):
        R = camera_rotation(pitch, rng.normal(0.0, 0.02))
        depth, conf = render_depth(poly, p, R, K, noise_m=0.002, rng=rng)
        h, w = depth.shape
        if case % 3:  # the near-lens blob at the same pixels in both frames
            v, u = np.mgrid[0:h, 0:w]
            r2 = ((u - 0.5 * w) / (0.45 * w)) ** 2 + ((v - 0.8 * h) / (0.3 * h)) ** 2
            z = 0.25 + 0.04 * r2 + rng.normal(0.0, 0.002, r2.shape)
            depth = np.where(r2 < 1.0, z, depth).astype(np.float32)
        depth[rng.random(depth.shape) < 0.01] = np.nan
        depth[rng.random(depth.shape) < 0.01] = 0.0
        frames.append((depth, conf, R))
    return K, frames, step


def test_compiled_camera_fixed_mask_equals_the_numpy_path() -> None:
    """camera_fixed_mask compiled (one pass, ``compiled.camera_fixed``) against its numpy
    reference over swings, stance, wrong predictions, turns that move points out of the
    view or behind the camera, held masks and float64 depth: the same mask, the same
    unchanged pixels and the same view-test counts, bit for bit (the reference's matrix
    product summed as this BLAS sums it; else the masks may differ at a rounding tie)."""
    from vio_graph.frontend import camera_fixed as cf

    assert icp_module.compiled_kernels() is not None
    exact = _blas_matmul_is_forward_fma()
    rng = np.random.default_rng(12)
    n_found = n_view = 0
    for case in range(40):
        K, ((d0, c0, R0), (d1, c1, R1)), step = _camera_fixed_scene(rng, case)
        delta = step + (rng.normal(0.0, 0.03, 2) if case % 5 == 0 else 0.0)  # wrong IMU
        R1u = R1
        if case % 7 == 0:  # a large turn: points leave the view / go behind the camera
            R1u = camera_rotation_any(rng) @ R1
        motion = cf.motion_from_ground(R0, R1u, delta, np.eye(2) * 0.002**2, 0.005, 0.01)
        if case % 6 == 0:
            d0, d1 = d0.astype(np.float64), d1.astype(np.float64)
        cand = (c1 > 0) & (rng.random(c1.shape) < 0.9)
        held = None if case % 2 else rng.random(cand.shape) < 0.3
        sigma = float(rng.choice([0.002, 0.003, 0.01]))
        got, want = {}, {}
        for fn, res in ((cf.camera_fixed_mask, got), (cf.camera_fixed_mask_reference, want)):
            same = np.zeros(cand.shape, dtype=bool)
            stats: dict = {}
            mask = fn(d0, d1, cand, K, motion, sigma, 3.0, held, same, stats)
            res.update(mask=mask, same=same, stats=stats)
        assert np.array_equal(got["same"], want["same"])
        assert got["stats"] == want["stats"]
        if exact:
            assert np.array_equal(got["mask"], want["mask"])
        else:  # a rounding tie at a threshold at most
            assert np.count_nonzero(got["mask"] != want["mask"]) <= 2
        n_found += bool(want["mask"].any())
        n_view += bool(want["stats"])
    assert n_found >= 10 and n_view >= 15  # the cases reach the camera-fixed decision


def camera_rotation_any(rng: np.random.Generator) -> np.ndarray:
    """A random rotation of up to ~90 degrees."""
    from scipy.spatial.transform import Rotation

    return Rotation.from_rotvec(rng.normal(0.0, 0.8, 3)).as_matrix()


def test_means_without_the_wrapper_are_ndarray_mean_bit_for_bit() -> None:
    """noise._line_residuals and extract_corner take their means as np.add.reduce / count
    instead of ndarray.mean (its Python wrapper, ~2.5 us a call): the same floats, bit for
    bit, at every size (numpy sums in pairs from 8 values on, in blocks of 128), strided
    columns and values of mixed magnitude included."""
    from vio_graph.frontend.noise import _line_residuals

    def reference(xs: np.ndarray, zs: np.ndarray) -> np.ndarray:
        xc = xs - xs.mean()
        zc = zs - zs.mean()
        sxx = float(xc @ xc)
        slope = float(xc @ zc) / sxx if sxx > 0 else 0.0
        return zc - slope * xc

    rng = np.random.default_rng(7)
    for n in [1, 2, 3, 7, 8, 9, 15, 16, 17, 127, 128, 129, 255, 256, 300, 1000, 4097]:
        for scale in (1e-3, 1.0, 1e6):
            pts = rng.normal(size=(n, 2)) * scale + rng.normal(size=2) * 10.0
            pts[::3] *= 1e-9  # mixed magnitudes: the order of the additions matters
            xs, zs = np.ascontiguousarray(pts[:, 0]), np.ascontiguousarray(pts[:, 1])
            assert np.array_equal(_line_residuals(xs, zs), reference(xs, zs))
            ours = np.add.reduce(pts, axis=0) / pts.shape[0]
            assert ours.tobytes() == pts.mean(axis=0).tobytes()


def test_compiled_source_crop_equals_the_numpy_crop() -> None:
    """The tracker's ICP source crop (``compiled.source_crop``) against its numpy form: the
    same points in the same order, with profile points exactly on the grown box's edges,
    NaNs in the target or the profile, and one-point targets."""
    from vio_graph.frontend.tracker import _source_crop_reference

    kernels = icp_module.compiled_kernels()
    assert kernels is not None
    rng = np.random.default_rng(21)
    n_inside = 0
    for case in range(300):
        prof = np.round(rng.uniform(-0.2, 1.2, (int(rng.integers(0, 300)), 2)), 2)
        tgt = np.round(rng.uniform(0.0, 1.0, (int(rng.integers(1, 60)), 2)), 2)
        T0 = np.round(rng.normal(0.0, 0.02, 2), 2)
        grow = float(rng.choice([0.0, 0.01, 0.05]))
        if case % 13 == 0 and prof.shape[0]:
            prof[0, int(case % 2)] = np.nan
        if case % 17 == 0:
            tgt[-1, int(case % 2)] = np.nan
        got = kernels.source_crop(prof, tgt, float(T0[0]), float(T0[1]), grow)
        want = _source_crop_reference(prof, tgt, T0, grow)
        assert got.shape == want.shape
        assert np.array_equal(got, want, equal_nan=True)
        n_inside += want.shape[0]
    assert n_inside > 1000


def test_compiled_switch_follows_the_environment(monkeypatch: pytest.MonkeyPatch) -> None:
    """compiled_kernels reads VIO_GRAPH_COMPILED through os.environ's own dict (one lookup):
    every change made through os.environ is seen at the next call, as os.environ.get sees
    it (on, off, unset = "auto", off by default until use_compiled_by_default)."""
    assert icp_module.compiled_kernels() is not None  # the fixture's "1"
    monkeypatch.setenv(icp_module.COMPILED_ENV, "0")
    assert icp_module._compiled_env_raw() in ("0", b"0")
    assert icp_module.compiled_kernels() is None
    monkeypatch.setenv(icp_module.COMPILED_ENV, " On ")
    assert icp_module.compiled_kernels() is not None
    monkeypatch.delenv(icp_module.COMPILED_ENV)
    assert icp_module._compiled_env_raw() is None
    monkeypatch.setattr(icp_module, "_AUTO", [False])
    assert icp_module.compiled_kernels() is None
    monkeypatch.setattr(icp_module, "_AUTO", [True])
    assert icp_module.compiled_kernels() is not None
