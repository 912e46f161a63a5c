"""The consistency scale of the clearance sigma (vio_graph/safety/consistency.py)."""

from __future__ import annotations

import numpy as np
import pytest
from pydantic import ValidationError

from vio_graph.safety.clearance import HeightProfile
from vio_graph.safety.config import SafetyConfig
from vio_graph.safety.consistency import (
    ChiSquareScale,
    ChiSquareScaleReference,
    MapConsistency,
    keyframe_bin_tops,
    median_selected,
    psd_abs_zz,
)
from vio_graph.safety.online import OnlineHeightMap, SafetyMonitor, _psd_abs


@pytest.mark.parametrize("true_scale", [0.5, 1.0, 3.0])
def test_scale_recovers_the_ratio_of_innovation_to_predicted_sigma(true_scale: float) -> None:
    """Innovations drawn with true_scale times the predicted sigma, a few with gross
    errors (mixed pixels): the median-based scale returns true_scale within 10 %."""
    rng = np.random.default_rng(3)
    c = ChiSquareScale(window=30)
    for _ in range(30):
        v = rng.uniform(1e-6, 2e-5, 80)  # predicted variances, m^2
        r = rng.normal(0.0, true_scale * np.sqrt(v))
        r[:4] = 0.05  # 5 % outliers of 5 cm
        c.observe(r, v)
    assert c.scale == pytest.approx(true_scale, rel=0.1)


def test_scale_stays_one_until_enough_keyframes_and_is_clipped() -> None:
    c = ChiSquareScale(window=10, min_keyframes=3, scale_range=(0.5, 2.0))
    for _ in range(2):
        c.observe(np.full(50, 0.1), np.full(50, 1e-6))  # 100 sigma
    assert c.scale == 1.0
    c.observe(np.full(50, 0.1), np.full(50, 1e-6))
    assert c.scale == 2.0
    off = ChiSquareScale(window=0)
    off.observe(np.full(50, 0.1), np.full(50, 1e-6))
    assert off.scale == 1.0
    with pytest.raises(ValueError, match="differ in shape"):
        c.observe(np.zeros(3), np.ones(2))
    with pytest.raises(ValueError, match="scale_range"):
        ChiSquareScale(window=5, scale_range=(1.5, 2.0))
    with pytest.raises(ValidationError, match="consistency_scale_range"):
        SafetyConfig(consistency_scale_range=(0.5, 0.9))


def test_vectorised_psd_abs_matches_the_closed_form() -> None:
    rng = np.random.default_rng(0)
    for _ in range(200):
        a, b, c = rng.normal(0, 1e-5, 3)
        M = np.array([[a, b], [b, c]])
        ref = _psd_abs(M)[1][1]
        assert psd_abs_zz(np.array([[a, b, c]]))[0] == pytest.approx(ref, rel=1e-9, abs=1e-20)


def test_keyframe_tops_are_the_map_heights() -> None:
    """One keyframe into an empty map: the map's bins and heights are the tops."""
    rng = np.random.default_rng(2)
    xs = np.linspace(0.1, 0.9, 300)
    pts = np.stack([xs, np.where(xs < 0.5, 0.0, 0.15) + rng.normal(0, 1e-3, xs.size)], 1)
    cam = np.array([0.03, 0.5])
    m = OnlineHeightMap(0.005, 1)
    m.add_keyframe(cam, pts - cam, np.eye(2) * 1e-6)
    prof = m.profile(0.0)
    bins, top = keyframe_bin_tops(cam, pts - cam, 0.005, m.top_band_m)
    np.testing.assert_array_equal(bins, np.rint(prof.x_lo_m / 0.005).astype(int))
    np.testing.assert_allclose(top, prof.z_m, atol=1e-12)


def _drifting_walk(true_scale: float, window: int, seed: int) -> tuple[float, list[float]]:
    """A camera walking over a flat floor while its z estimate drifts as a random walk whose
    increments are ``true_scale`` times the filter's covariance growth; a foot 5 cm above
    the floor, placed with the same drift. Returns (the final pose consistency scale, the
    clearance errors over their sigma)."""
    from vio_graph.safety.online import SafetyMonitor

    rng = np.random.default_rng(seed)
    # the map ends 5 cm past the toe here: the unseen-terrain check would leave most of these
    # clearances unknown, and this test is about the consistency scale alone
    cfg = SafetyConfig(
        consistency_window_keyframes=window,
        map_sigma_m=0.0005,
        foot_sigma_m=0.0,
        unseen_terrain_check=False,
    )
    mon = SafetyMonitor(cfg)
    q = 0.0008**2  # filter z variance growth per keyframe, m^2
    drift, z = 0.0, []
    for k in range(90):
        cam_true = np.array([0.015 * k, 0.5])
        drift += rng.normal(0.0, true_scale * np.sqrt(q))
        cam = cam_true + [0.0, drift]
        P = np.diag([1e-6, 1e-6 + q * k])
        xs = cam_true[0] + np.linspace(0.2, 0.5, 150)
        pts = np.stack([xs, rng.normal(0.0, 0.0005, xs.size)], 1) - cam_true
        mon.update(0.1 * k, cam, P, [0.0, 0.0], [0.1, 0.0], False, pts)
        # the foot 5 cm over bins the camera saw 0-17 keyframes ago, placed with the drift
        heel = np.array([cam_true[0] + 0.25, 0.05 + drift])
        s = mon.update(0.1 * k + 0.05, cam, P, heel, heel + [0.2, 0.0], False)
        if k >= 40 and np.isfinite(s.clearance_m):
            z.append((s.clearance_m - 0.05) / s.clearance_sigma_m)
    return mon.consistency.pose_scale, z


def test_drift_the_filter_understates_is_found_and_the_sigma_covers_it() -> None:
    """Known answer: the filter's z covariance grows 3x (in sigma) slower than its drift.
    The keyframes' heights of the same bins disagree by that drift: the pose scale goes well
    above 1 (the estimator says it is in trouble) and the clearance's 1-sigma band covers
    ~68 % of the frames (0.43 without). With a consistent filter the scale stays near or
    below 1 and the band ~68 %. (The scale reads about 2 for the drift's 3, and 0.7 for 1: a
    profile's offset mixes bins mapped at different times, and the map term holds part of
    the drift; the coverage is what the scale is for.)"""

    def pooled(true_scale: float, window: int, seeds: range) -> tuple[float, np.ndarray]:
        runs = [_drifting_walk(true_scale, window, seed) for seed in seeds]
        return float(np.median([s for s, _ in runs])), np.abs(np.concatenate([z for _, z in runs]))

    scale, z_on = pooled(3.0, 30, range(8))
    _, z_off = pooled(3.0, 0, range(8))
    assert 1.5 <= scale <= 3.5
    assert np.mean(z_off <= 1) < 0.5
    assert 0.58 <= np.mean(z_on <= 1) <= 0.80
    assert np.mean(z_on <= 2) >= 0.86
    scale, z_on = pooled(1.0, 30, range(8))
    assert 0.4 <= scale <= 1.3
    assert 0.58 <= np.mean(z_on <= 1) <= 0.80
    assert np.mean(z_on <= 2) >= 0.86


def test_empty_map_and_keyframe_leave_the_scale_alone() -> None:
    c = MapConsistency(window=5, min_keyframes=1)
    empty = HeightProfile(np.zeros(0), np.zeros(0), np.zeros(0), np.zeros(0))
    no_cov = np.zeros((1, 3))
    c.observe_keyframe(
        [0, 0.5], np.zeros((0, 2)), np.eye(2), empty, lambda k: no_cov, 0.005, 0.01, 1
    )
    assert c.pose_scale == 1.0 and c.map_scale == 1.0


def test_pose_and_map_scales_from_keyframes_against_a_known_map() -> None:
    """A mapped floor (bins of 5 mm at z = 0, sigma 3 mm); each keyframe sees it shifted by
    a drift of 2x the filter's predicted 2 mm (common to all bins) plus 1 mm of per-bin
    noise: the pose scale reads ~2, the map scale ~1/3 (the 3 mm sigma is 3x the scatter)."""
    rng = np.random.default_rng(5)
    n_bins, bin_m = 120, 0.005
    x_lo = np.arange(n_bins) * bin_m
    mapped = HeightProfile(x_lo, x_lo + bin_m, np.zeros(n_bins), np.full(n_bins, 0.003))
    P_bin = np.diag([1e-6, 1e-6])
    P_now = P_bin + np.diag([0.0, 0.002**2])
    c = MapConsistency(window=60)
    cam = np.array([0.0, 0.5])
    P_bin_rows = np.array([[P_bin[0, 0], P_bin[0, 1], P_bin[1, 1]]])

    def rows(k: np.ndarray) -> np.ndarray:
        return np.repeat(P_bin_rows, len(k), axis=0)

    for _ in range(60):
        drift = rng.normal(0.0, 2 * 0.002)
        z = drift + rng.normal(0.0, 0.001, n_bins)
        pts = np.stack([x_lo + bin_m / 2, z], 1) - cam
        c.observe_keyframe(cam, pts, P_now, mapped, rows, bin_m, 0.01, 1.0)
    assert c.pose_scale == pytest.approx(2.0, rel=0.25)
    assert c.map_scale == pytest.approx(1 / 3, rel=0.15)


def test_bin_cov_rows_match_bin_cov() -> None:
    rng = np.random.default_rng(4)
    m = OnlineHeightMap(0.005, 2)
    for i in range(4):
        A = rng.normal(0, 1e-3, (2, 2))
        xs = np.linspace(0.1 + 0.02 * i, 0.6, 120)
        m.add_keyframe([0.0, 0.5], np.stack([xs, np.zeros_like(xs)], 1) - [0.0, 0.5], A @ A.T)
    prof = m.profile(0.003)
    k = np.arange(len(prof))
    rows = m.bin_cov_rows(k)
    ref = np.array([m.bin_cov(int(i)) for i in k])
    np.testing.assert_allclose(rows, np.stack([ref[:, 0, 0], ref[:, 0, 1], ref[:, 1, 1]], 1))


def test_median_by_selection_is_numpys_median() -> None:
    """Odd and even sizes, repeated values, infinities and NaN: the same float, bit for bit."""
    rng = np.random.default_rng(5)
    for n in [1, 2, 3, 4, 7, 10, 301, 1000]:
        for _ in range(20):
            a = rng.normal(0.0, 1.0, n) ** 3
            a[rng.random(n) < 0.3] = a[0]  # ties
            if n > 3 and rng.random() < 0.3:
                a[rng.integers(n)] = rng.choice([np.inf, -np.inf, np.nan])
            got, want = median_selected(a.copy()), float(np.median(a))
            assert (np.isnan(got) and np.isnan(want)) or got == want, (n, got, want)
    assert np.isnan(median_selected(np.zeros(0)))


@pytest.mark.parametrize("window", [1, 3, 30])
def test_sorted_window_scale_equals_the_reference(window: int) -> None:
    """Keyframes of random sizes (some empty or all invalid, many repeated values) through
    the sorted window and through the reference's median of the concatenated window: the
    same scale after every keyframe, bit for bit."""
    rng = np.random.default_rng(window)
    a = ChiSquareScale(window, min_keyframes=2, scale_range=(0.1, 10.0))
    b = ChiSquareScaleReference(window, min_keyframes=2, scale_range=(0.1, 10.0))
    for k in range(200):
        n = int(rng.integers(0, 60))
        r = rng.normal(0.0, 1e-3, n).round(5)  # rounding: repeated normalised squares
        v = np.full(n, 1e-6)
        v[rng.random(n) < 0.1] = rng.choice([0.0, np.nan, -1.0])  # dropped values
        a.observe(r, v)
        b.observe(r, v)
        assert a.scale == b.scale, k


def test_consistency_equals_the_reference_over_a_replay(sample_frames) -> None:
    """data/sample through the safety monitor with the reference map: at every keyframe
    the default consistency test (sorted window, medians by selection) gives the pose and
    map scales of the reference one, bit for bit."""
    cfg = SafetyConfig()
    mon = SafetyMonitor(cfg, incremental=False)
    fast = MapConsistency(
        cfg.consistency_window_keyframes,
        cfg.consistency_min_keyframes,
        cfg.consistency_scale_range,
    )
    observe = mon.consistency.observe_keyframe
    seen: list[tuple[float, float, float, float]] = []

    def both(*args, **kw) -> None:  # the reference as the monitor runs it, the default beside
        observe(*args, **kw)
        fast.observe_keyframe(*args, **kw)
        c = mon.consistency
        seen.append((c.pose_scale, fast.pose_scale, c.map_scale, fast.map_scale))

    mon.consistency.observe_keyframe = both  # type: ignore[method-assign]
    for f in sample_frames:
        mon.update(*f)
    assert len(seen) > 20
    assert any(p != 1.0 for p, *_ in seen)  # the scales left 1
    for k, (p_ref, p, m_ref, m) in enumerate(seen):
        assert (p, m) == (p_ref, m_ref), k


def _kernels():
    pytest.importorskip("numba")
    from vio_graph.safety import compiled

    return compiled


@pytest.mark.parametrize("window", [1, 3, 30])
def test_compiled_window_merge_equals_the_numpy_merge(window: int) -> None:
    """The sorted window merged by the compiled kernel (one pass: the oldest keyframe's
    values out, the new ones in) holds the numpy merge's values and gives its scale after
    every keyframe, bit for bit, on keyframes of random sizes with many repeated values."""
    K = _kernels()
    rng = np.random.default_rng(10 + window)
    a = ChiSquareScale(window, min_keyframes=2, scale_range=(0.1, 10.0))
    b = ChiSquareScale(window, min_keyframes=2, scale_range=(0.1, 10.0), kernels=K)
    ref = ChiSquareScaleReference(window, min_keyframes=2, scale_range=(0.1, 10.0))
    for k in range(200):
        n = int(rng.integers(0, 60))
        r = rng.normal(0.0, 1e-3, n).round(5)  # rounding: repeated normalised squares
        v = np.full(n, 1e-6)
        v[rng.random(n) < 0.1] = rng.choice([0.0, np.nan, -1.0])  # dropped values
        for c in (a, b, ref):
            c.observe(r, v)
        np.testing.assert_array_equal(b._sorted, a._sorted, err_msg=str(k))
        assert a.scale == b.scale == ref.scale, k
    assert a.scale != 1.0 or window < 2  # (a window of 1 never reaches min_keyframes)


def _random_keyframe(rng: np.random.Generator, x0: float) -> np.ndarray:
    """A noisy stair profile (N, 2) relative to a camera at (x0, 0.5): mixed pixels, a few
    NaN points, heights rounded to 0.1 mm (ties)."""
    x = np.sort(rng.uniform(x0 - 0.3, x0 + 0.9, 300))
    z = 0.15 * np.floor(x / 0.28) + rng.normal(0, 0.002, x.size).round(4)
    z[rng.random(x.size) < 0.02] -= 0.1  # mixed pixels
    rel = np.stack([x - x0, z - 0.5], 1)
    rel[rng.random(x.size) < 0.01] = np.nan
    return rel


def test_compiled_keyframe_test_equals_the_numpy_test_on_random_stairs() -> None:
    """Keyframes walking over noisy stairs with growing covariances: the compiled
    consistency test (one kernel per keyframe, the compiled windows) gives the numpy test's
    pose and map scales after every keyframe, bit for bit."""
    from vio_graph.safety.height_map import IncrementalHeightMap

    K = _kernels()
    cfg = SafetyConfig()
    rng = np.random.default_rng(4)
    m = IncrementalHeightMap(cfg.bin_m, cfg.min_keyframes)
    args = (cfg.consistency_window_keyframes, 2, (0.1, 10.0))
    ref, comp = MapConsistency(*args), MapConsistency(*args, kernels=K)
    n_scaled = 0
    for k, x0 in enumerate(np.arange(-0.5, 3.0, 0.02)):
        P = np.array([[1e-6 + 4e-7 * k, 2e-7 * k], [2e-7 * k, 1e-6 + 3e-7 * k]])
        cam = np.array([x0 + rng.normal(0, 0.003), 0.5 + rng.normal(0, 0.003)])
        rel = _random_keyframe(rng, float(x0))
        fin = rel[np.all(np.isfinite(rel), axis=1)]
        seen = m.window(float(fin[:, 0].min() + cam[0]), float(fin[:, 0].max() + cam[0]), 0.003)
        ref.observe_keyframe(
            cam,
            rel,
            P,
            seen.profile,
            lambda j, bins=seen.bins: m.bin_cov_rows_at(bins[j]),
            cfg.bin_m,
            m.top_band_m,
            cfg.relative_pose_scale,
        )
        tops = K.keyframe_tops(rel, float(cam[0]), float(cam[1]), cfg.bin_m, m.top_band_m)
        comp.observe_bin_tops(
            tops, seen.profile, seen.bins, *m.bin_cov_sums(), P, cfg.bin_m, cfg.relative_pose_scale
        )
        assert (comp.pose_scale, comp.map_scale) == (ref.pose_scale, ref.map_scale), k
        n_scaled += comp.pose_scale != 1.0 and comp.map_scale != 1.0
        m.add_keyframe(cam, rel, P)
    assert n_scaled > 50  # the scales left 1 on most keyframes


def test_compiled_consistency_equals_the_reference_over_a_replay(sample_frames) -> None:
    """data/sample through the compiled monitor (keyframe step fused in one kernel,
    ``keyframe_step``): at every keyframe its consistency test gives the pose and map scales
    of the reference test run beside it on the same map, bit for bit."""
    K = _kernels()
    cfg = SafetyConfig()
    mon = SafetyMonitor(cfg, compiled=True)
    assert mon.consistency._kernels is K
    ref = MapConsistency(
        cfg.consistency_window_keyframes,
        cfg.consistency_min_keyframes,
        cfg.consistency_scale_range,
        reference=True,
    )
    seen: list[tuple[float, float, float, float]] = []
    for f in sample_frames:
        _, cam, P, _, _, _, prof = f
        w = None if prof is None else mon._keyframe_window(cam, prof)
        if w is not None:  # the reference test on the map before the keyframe joins it
            rows = mon.map.bin_cov_rows_at(w.bins)
            rel = np.asarray(prof, dtype=float).reshape(-1, 2)
            tops = K.keyframe_tops(rel, *map(float, cam), cfg.bin_m, mon.map.top_band_m)
            ref.observe_keyframe(
                None, None, P, w.profile, lambda k, rows=rows: rows[k], cfg.bin_m, 0.0,
                cfg.relative_pose_scale, tops,
            )  # fmt: skip
        mon.update(*f)  # (the compiled keyframe step: test, merges and map in one call)
        if w is not None:
            c = mon.consistency
            seen.append((ref.pose_scale, c.pose_scale, ref.map_scale, c.map_scale))
    assert len(seen) > 20
    assert any(p != 1.0 for p, *_ in seen)
    for k, (p_ref, p, m_ref, m) in enumerate(seen):
        assert (p, m) == (p_ref, m_ref), k
    with pytest.raises(ValueError, match="compiled"):
        MapConsistency(5, reference=True, kernels=K)
    with pytest.raises(ValueError, match="compiled kernels"):
        MapConsistency(5).observe_bin_tops(*([None] * 9))


@pytest.mark.parametrize("compiled", [False, True])
def test_pose_scale_acts_on_the_vertical_part_only(compiled: bool) -> None:
    """Known answer: the pose consistency scale comes from the keyframes' common *height*
    offset, so it multiplies the pose term's vertical part; the horizontal part keeps the
    filter's own covariance growth (``pose_scale_on_x: false``, the default). A foot 1 cm
    before a riser (horizontal normal) has the sigma sqrt(dP_xx) whatever the scale; over
    the tread (vertical normal) the scale acts as before. ``pose_scale_on_x: true`` is the
    old behaviour: the scale on both."""
    if compiled and _kernels() is None:
        pytest.skip("numba not available")
    xs = np.arange(0.0, 0.6, 0.001)
    zs = np.where(xs < 0.3025, 0.0, 0.15)  # the riser face at the bin edge x = 0.300
    cam = np.array([0.0, 0.5])
    profile = np.stack([xs, zs], 1) - cam
    P_kf = np.diag([1e-6, 1e-6])
    P_now = P_kf + np.diag([4e-6, 9e-6])  # growth since the keyframes: 2 mm x, 3 mm z
    sp = 2.0  # the pose scale the keyframes are taken to have read
    for on_x in (False, True):
        cfg = SafetyConfig(foot_sigma_m=0.0, map_sigma_m=0.001, pose_scale_on_x=on_x)
        mon = SafetyMonitor(cfg, compiled=compiled)
        for k in range(6):
            mon.update(0.1 * k, cam, P_kf, [0.05, 0.05], [0.25, 0.05], False, profile)
        mon.consistency.pose._scale = sp
        mon.consistency.map._scale = 1.0
        riser = mon.update(1.0, cam, P_now, [0.10, 0.05], [0.29, 0.05], False)
        tread = mon.update(1.1, cam, P_now, [0.02, 0.05], [0.22, 0.05], False)
        assert riser.clearance_m == pytest.approx(0.01, abs=1e-9)
        assert tread.clearance_m == pytest.approx(0.05, abs=1e-9)
        x_weight = sp if on_x else 1.0
        assert riser.clearance_sigma_m == pytest.approx(x_weight * 0.002, rel=1e-9)
        assert tread.clearance_sigma_m == pytest.approx(np.hypot(sp * 0.003, 0.001), rel=1e-9)
