"""Whole-profile ICP fallback (no corner) and degenerate directions in point-to-line ICP."""

from __future__ import annotations

import numpy as np
import pytest

from vio_graph.frontend import icp as icp_module
from vio_graph.frontend import tracker as tracker_module
from vio_graph.frontend.config import IcpConfig, TrackerConfig
from vio_graph.frontend.icp import icp_translation_2d
from vio_graph.frontend.smoothing import smooth_profile
from vio_graph.frontend.tracker import CornerTracker


def _floor(camera_xz: np.ndarray, seed: int) -> np.ndarray:
    """A flat floor at z = 0 seen from ``camera_xz``, points relative to the camera, 2 mm noise,
    the visible stretch moving with the camera (field-of-view ends, not terrain ends)."""
    rng = np.random.default_rng(seed)
    x = np.linspace(0.2, 1.0, 400) + camera_xz[0]
    pts = np.column_stack([x, rng.normal(0.0, 0.002, x.size)])
    return pts - camera_xz


def test_floor_icp_measures_z_and_leaves_x_at_the_prediction() -> None:
    c0, delta = np.array([0.0, 0.5]), np.array([0.05, 0.01])
    pred = delta + np.array([0.012, 0.004])  # IMU prediction 12 mm / 4 mm off
    tracker = CornerTracker()
    tracker.update(0.0, _floor(c0, 1), None)
    out = tracker.update(1 / 30, _floor(c0 + delta, 2), None, pred, np.eye(2) * 0.01**2)
    d = out.displacement
    assert d is not None, out.reason
    assert abs(d.delta_xz_m[1] - delta[1]) < 0.001  # z from the floor
    assert abs(d.delta_xz_m[0] - pred[0]) < 1e-4  # x unobservable: stays at the prediction
    assert d.cov_m2[0, 0] > 0.99 * IcpConfig().max_variance_m2  # ...and says so


def test_no_displacement_without_corner_in_paper_mode_or_without_prediction() -> None:
    c0, delta = np.array([0.0, 0.5]), np.array([0.05, 0.01])
    for cfg, pred in ((TrackerConfig(profile_fallback=False), delta), (TrackerConfig(), None)):
        tracker = CornerTracker(cfg)
        tracker.update(0.0, _floor(c0, 1), None)
        out = tracker.update(1 / 30, _floor(c0 + delta, 2), None, pred)
        assert out.displacement is None and out.reason == "no corner in this frame"


def test_empty_previous_profile_gives_no_displacement_instead_of_an_error() -> None:
    tracker = CornerTracker()
    tracker.update(0.0, np.empty((0, 2)), None)
    out = tracker.update(1 / 30, _floor(np.zeros(2), 1), None, np.zeros(2))
    assert out.displacement is None


def test_degenerate_direction_stays_at_the_initial_guess() -> None:
    """Point-to-line ICP on a floor: x is degenerate, so it stays at T0 with the capped
    variance while z is solved."""
    src = _floor(np.zeros(2), 3)
    tgt = _floor(np.array([0.03, 0.0]), 4)
    T0 = np.array([-0.02, 0.0])
    on = icp_translation_2d(src, tgt, T0, IcpConfig(normal_neighbours=15))
    assert abs(on.translation_xz_m[0] - T0[0]) < 1e-4
    assert on.cov_m2[0, 0] > 0.99 * IcpConfig().max_variance_m2
    assert abs(on.translation_xz_m[1]) < 0.001


def test_fallback_pairs_only_surface_the_previous_frame_saw() -> None:
    """A fast swing: the new frame sees 10 cm of floor beyond the previous frame's view. With
    ``fallback_overlap_margin_m`` the target points that, moved back by the seed, fall outside
    the previous extent shrunk by the margin take no part; with None they may pair with the
    previous profile's end."""
    c0, delta = np.array([0.0, 0.5]), np.array([0.10, 0.0])
    prev = _floor(c0, 1)
    prev_max_world = float((prev + c0)[:, 0].max())
    margin = 0.01
    used_max = {}
    for m in (margin, None):
        tracker = CornerTracker(TrackerConfig(fallback_overlap_margin_m=m))
        tracker.update(0.0, prev, None)
        out = tracker.update(1 / 30, _floor(c0 + delta, 2), None, delta, np.eye(2) * 0.01**2)
        assert out.displacement is not None, out.reason
        assert abs(out.displacement.delta_xz_m[1] - delta[1]) < 0.001
        used_max[m] = float(out.icp.target_points_xz_m[:, 0].max() + (c0 + delta)[0])
    assert used_max[margin] <= prev_max_world - margin + 1e-9
    assert used_max[None] > prev_max_world - margin


def _far_floor(camera_xz: np.ndarray, seed: int) -> np.ndarray:
    """16 cm of floor 1.5 m ahead and 1 m below the camera with 1 cm of depth noise: the
    short, noisy far tread of a descent, whose PCA normals tilt at random."""
    rng = np.random.default_rng(seed)
    x = np.linspace(1.50, 1.66, 60) + camera_xz[0]
    pts = np.column_stack([x, -1.0 + rng.normal(0.0, 0.01, x.size)])
    return pts - camera_xz


def test_a_result_that_follows_its_seed_does_not_claim_x() -> None:
    """Forty frame pairs of such a floor, IMU seed 7 mm off per axis (sigma 7 mm). The x of
    the profile ICP is the seed's plus noise; the point-to-line covariance reads the tilted
    normals as x information. With the restart check a result that moves with its seed gets
    that spread as covariance: x errors beyond 3 claimed sigmas 4 of 40 -> at most 1 (the
    straight-line test, which drops x from such a floor altogether, off)."""
    delta = np.array([-0.024, -0.045])
    beyond = {}
    for check in (True, False):
        z = []
        for seed in range(40):
            rng = np.random.default_rng(1000 + seed)
            pred = delta + rng.normal(0.0, 0.007, 2)
            cfg = TrackerConfig(fallback_restart_check=check, fallback_straight_ratio=None)
            tracker = CornerTracker(cfg)
            tracker.update(0.0, _far_floor(np.zeros(2), 2 * seed), None)
            out = tracker.update(
                1 / 30, _far_floor(delta, 2 * seed + 1), None, pred, np.eye(2) * 0.007**2
            )
            d = out.displacement
            assert d is not None, out.reason
            z.append((d.delta_xz_m[0] - delta[0]) / np.sqrt(d.cov_m2[0, 0]))
        beyond[check] = int(np.sum(np.abs(z) > 3.0))
    assert beyond[False] >= 3  # the overconfidence exists
    assert beyond[True] <= 1 < beyond[False]


def test_a_straight_noisy_floor_gives_no_x_and_keeps_z() -> None:
    """The same forty noisy far-floor pairs with the straight-line test (default): every
    displacement keeps the seed's x with the capped variance, z stays measured. Without it
    (restart check on) some claim x to a few mm."""
    delta = np.array([-0.024, -0.045])
    cap = IcpConfig().max_variance_m2
    sx_without = []
    for seed in range(40):
        rng = np.random.default_rng(1000 + seed)
        pred = delta + rng.normal(0.0, 0.007, 2)
        for ratio in (25.0, None):
            tracker = CornerTracker(TrackerConfig(fallback_straight_ratio=ratio))
            tracker.update(0.0, _far_floor(np.zeros(2), 2 * seed), None)
            out = tracker.update(
                1 / 30, _far_floor(delta, 2 * seed + 1), None, pred, np.eye(2) * 0.007**2
            )
            d = out.displacement
            assert d is not None, out.reason
            if ratio is None:
                sx_without.append(np.sqrt(d.cov_m2[0, 0]))
                continue
            # along the floor: the seed (up to the tilt of the normals' mean times z's move),
            assert abs(d.delta_xz_m[0] - pred[0]) < 0.02  # and a claim that says nothing
            assert d.cov_m2[0, 0] > 0.9 * cap  # sigma x > 0.95 m
            assert abs(d.delta_xz_m[1] - delta[1]) < 0.02  # z still from the floor:
            info = np.linalg.inv(d.cov_m2)  # its variance given x (the line's fitted tilt
            assert 1.0 / info[1, 1] < 0.01**2  # correlates z with the unknown x)
    assert min(sx_without) < 0.01  # the overconfidence the test removes


def _step(camera_xz: np.ndarray, seed: int) -> np.ndarray:
    """A floor at z = 0, an 18 cm riser at x = 1 m and the tread above, seen from
    ``camera_xz``: points relative to the camera, 2 mm noise."""
    rng = np.random.default_rng(seed)
    x0 = np.linspace(0.7, 1.0, 120)
    z_riser = np.linspace(0.0, 0.18, 72)
    x1 = np.linspace(1.0, 1.3, 120)
    pts = np.vstack(
        [
            np.column_stack([x0, np.zeros_like(x0)]),
            np.column_stack([np.full_like(z_riser, 1.0), z_riser]),
            np.column_stack([x1, np.full_like(x1, 0.18)]),
        ]
    )
    return pts + rng.normal(0.0, 0.002, pts.shape) - camera_xz


def test_a_profile_with_a_riser_keeps_its_x() -> None:
    """Floor, riser and tread (no corner given): the riser fixes x, the straight-line test
    leaves it alone, and the profile ICP recovers x from a seed 12 mm off to within 2 mm,
    claiming a few millimetres."""
    c0, delta = np.array([-0.2, 0.5]), np.array([0.04, 0.01])
    pred = delta + np.array([0.012, -0.004])
    tracker = CornerTracker(TrackerConfig(fallback_straight_ratio=25.0))
    tracker.update(0.0, _step(c0, 1), None)
    out = tracker.update(1 / 30, _step(c0 + delta, 2), None, pred, np.eye(2) * 0.01**2)
    d = out.displacement
    assert d is not None, out.reason
    assert abs(d.delta_xz_m[0] - delta[0]) < 0.002
    assert np.sqrt(d.cov_m2[0, 0]) < 0.005
    assert abs(d.delta_xz_m[1] - delta[1]) < 0.002


def test_the_restart_check_shares_the_source_normals_bit_for_bit(
    monkeypatch: pytest.MonkeyPatch,
) -> None:
    """The profile fallback's restart check runs ICP again on the same source with the first
    ICP's source normals (SourceNormals): its displacements and covariances are those of the
    restart check computing every normal afresh, bit for bit, on the noisy far floors above
    (where the check widens some claims) with the compiled kernels."""
    monkeypatch.setenv(icp_module.COMPILED_ENV, "1")
    delta = np.array([-0.024, -0.045])

    def outputs(check: bool = True) -> list[tuple[np.ndarray, np.ndarray]]:
        got = []
        for seed in range(12):
            rng = np.random.default_rng(1000 + seed)
            pred = delta + rng.normal(0.0, 0.007, 2)
            cfg = TrackerConfig(fallback_straight_ratio=None, fallback_restart_check=check)
            tracker = CornerTracker(cfg)
            tracker.update(0.0, _far_floor(np.zeros(2), 2 * seed), None)
            out = tracker.update(
                1 / 30, _far_floor(delta, 2 * seed + 1), None, pred, np.eye(2) * 0.007**2
            )
            assert out.displacement is not None, out.reason
            got.append((out.displacement.delta_xz_m, out.displacement.cov_m2))
        return got

    shared = outputs()
    unchecked = outputs(check=False)
    assert any(not np.array_equal(a[1], b[1]) for a, b in zip(shared, unchecked, strict=True))
    calls: list[object] = []
    real = tracker_module.icp_translation_2d

    def fresh(src, tgt, T0, cfg, tree, normals=None):  # type: ignore[no-untyped-def]
        calls.append(normals)
        return real(src, tgt, T0, cfg, tree)  # every normal computed again

    monkeypatch.setattr(tracker_module, "icp_translation_2d", fresh)
    alone = outputs()
    assert len(calls) == 2 * len(alone)  # ICP and the restart check's ICP on every pair
    assert all(isinstance(n, icp_module.SourceNormals) for n in calls)
    for (d1, c1), (d2, c2) in zip(shared, alone, strict=True):
        assert np.array_equal(d1, d2) and np.array_equal(c1, c2)


def test_the_restart_at_icp_reach_does_not_inherit_the_prediction_sigma() -> None:
    """The far floor of the test above with a prediction that claims 1 mm but is 7 mm off
    per axis (a filter too sure of its velocity). Moved by two prediction sigmas (2 mm), the
    restart cannot tell that the result follows its seed, and x errors beyond 3 claimed
    sigmas are common; moved by half ICP's correspondence distance
    (``fallback_restart_shift: reach``), the claim is the same whatever the prediction's
    sigma, and at most 1 of 40 lies beyond 3 sigmas."""
    delta = np.array([-0.024, -0.045])
    beyond = {}
    claims = {}
    for shift in ("prediction", "reach"):
        z = []
        for pred_sigma in (0.001, 0.007):
            for seed in range(40):
                rng = np.random.default_rng(1000 + seed)
                pred = delta + rng.normal(0.0, 0.007, 2)
                cfg = TrackerConfig(fallback_restart_shift=shift, fallback_straight_ratio=None)
                tracker = CornerTracker(cfg)
                tracker.update(0.0, _far_floor(np.zeros(2), 2 * seed), None)
                out = tracker.update(
                    1 / 30, _far_floor(delta, 2 * seed + 1), None, pred, np.eye(2) * pred_sigma**2
                )
                d = out.displacement
                assert d is not None, out.reason
                claims[(shift, pred_sigma, seed)] = d.cov_m2
                if pred_sigma == 0.001:
                    z.append((d.delta_xz_m[0] - delta[0]) / np.sqrt(d.cov_m2[0, 0]))
        beyond[shift] = int(np.sum(np.abs(z) > 3.0))
    assert beyond["prediction"] >= 3  # the claim shrinks with the prediction's sigma
    assert beyond["reach"] <= 1
    for seed in range(40):
        np.testing.assert_array_equal(
            claims[("reach", 0.001, seed)], claims[("reach", 0.007, seed)]
        )


def _ray_noise_floor(camera_height_m: float, rng: np.random.Generator) -> np.ndarray:
    """A level floor seen by a camera ``camera_height_m`` above it, 900 rays spread evenly in
    elevation (as pixel rows are) over 0.3-1.6 m, depth noise along each ray growing with
    range (2 mm + 4 mm/m^2 r^2, ToF-like), then the front end's 5 mm thinning and kNN
    smoothing. Points relative to the camera."""
    ang = rng.uniform(np.arctan2(camera_height_m, 1.6), np.arctan2(camera_height_m, 0.3), 900)
    r = camera_height_m / np.sin(ang)
    rays = np.column_stack([np.cos(ang), -np.sin(ang)])
    pts = (r + rng.normal(0.0, 0.002 + 0.004 * r**2))[:, None] * rays
    return smooth_profile(pts, 5, 0.005, 10)


def test_floor_heights_of_the_smoothed_profile_have_no_range_bias() -> None:
    """Noise along the rays, growing with range, does not make the thinned and smoothed floor
    read high or low with range: the mean height in each 20 cm band is the true one within
    0.3 mm (measured: +0.21 mm in the nearest band, where the view ends, 0.07 mm or less
    beyond; the smoothed points scatter 1.2-1.5 mm)."""
    rng = np.random.default_rng(5)
    prof = np.vstack([_ray_noise_floor(0.45, rng) for _ in range(40)])
    r = np.hypot(prof[:, 0], prof[:, 1])
    h = prof[:, 1] + 0.45
    for lo in np.arange(0.4, 1.4, 0.2):
        band = (r >= lo) & (r < lo + 0.2)
        assert band.sum() > 500
        assert abs(h[band].mean()) < 3e-4, (lo, h[band].mean())


def test_full_target_profile_icp_walks_less_in_z() -> None:
    """Level walking, 4 cm a frame with a known height wobble, the IMU seed exact: the
    per-frame z error of the profile ICP with the 1 cm thinned target (default) and with the
    whole profile registered (fallback_full_target). The whole profile cuts the sd (measured
    0.35 -> 0.26 mm), neither has a mean bias beyond 0.05 mm a frame (measured +0.015 and
    -0.011 mm, standard errors 0.026 and 0.020), and the full target claims the thinned
    target's z variance within a factor of two (its covariance is scaled by the point-count
    ratio, so twice the points do not claim twice the information)."""
    sd, mean, claim = {}, {}, {}
    for full in (False, True):
        errs, claims = [], []
        for seed in range(3):
            rng = np.random.default_rng(seed)
            tracker = CornerTracker(TrackerConfig(fallback_full_target=full))
            z = 0.45
            tracker.update(0.0, _ray_noise_floor(z, rng), None)
            for k in range(1, 61):
                dz = 0.004 * np.sin(k / 5.0)
                z += dz
                delta = np.array([0.04, dz])
                out = tracker.update(
                    k / 30, _ray_noise_floor(z, rng), None, delta, np.eye(2) * 0.01**2
                )
                d = out.displacement
                assert d is not None, out.reason
                assert abs(d.delta_xz_m[0] - delta[0]) < 1e-3  # x: the exact seed
                errs.append(d.delta_xz_m[1] - dz)
                claims.append(d.cov_m2[1, 1])
        e = np.array(errs)
        sd[full], mean[full] = float(e.std()), float(e.mean())
        claim[full] = float(np.mean(claims))
    assert 0.5 < claim[True] / claim[False] < 2.0
    assert sd[True] < 0.85 * sd[False]
    assert sd[True] < 0.3e-3
    assert abs(mean[True]) < 0.05e-3 and abs(mean[False]) < 0.05e-3
