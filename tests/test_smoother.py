"""Tests of vio_graph.smoother on synthetic swinging-shank trials with known ground truth."""

from __future__ import annotations

import gtsam
import numpy as np
import pytest
from pydantic import ValidationError

from vio_graph.errors import EstimationError
from vio_graph.geometry import GRAVITY_MPS2, pitch_of, rot_y
from vio_graph.smoother.batch import BatchSmoother
from vio_graph.smoother.config import FactorFamilies, SmootherConfig
from vio_graph.smoother.graph import (
    B,
    KeyframeGraphBuilder,
    L,
    V,
    X,
    camera_xz_cov_from_pose_cov,
    robust_noise,
)
from vio_graph.smoother.imu_sampling import (
    common_frame_samples,
    discretization_velocity_var,
    make_preintegration_params,
    midpoint_samples,
    so3_exp,
)
from vio_graph.smoother.sliding_window import SlidingWindowSmoother
from vio_graph.smoother.synthetic import (
    IMU_P_CAM_M,
    SyntheticTrial,
    _trajectory,
    feed,
    make_swinging_shank_trial,
)
from vio_graph.types import CornerObservation, ImuSample, StanceObservation


def keyframe_errors_m(trial: SyntheticTrial, smoother) -> tuple[np.ndarray, np.ndarray]:
    """Per-keyframe camera position error (m) and keyframe times (s)."""
    est = smoother.keyframe_estimates(with_covariance=False)
    idx = np.flatnonzero(trial.is_keyframe)
    assert [e.timestamp_s for e in est] == pytest.approx(list(trial.frame_times_s[idx]))
    xz = np.array([e.camera_xz_m for e in est])
    return np.linalg.norm(xz - trial.camera_xz_true_m[idx], axis=1), trial.frame_times_s[idx]


def rms(e: np.ndarray) -> float:
    return float(np.sqrt(np.mean(e**2)))


# ---------------------------------------------------------------------------------------------
# building blocks
# ---------------------------------------------------------------------------------------------
def test_config_lag_rule_and_strictness():
    cfg = SmootherConfig(window_s=2.0, keyframe_period_s=0.1)
    assert cfg.smoother_lag_s() == pytest.approx(2.05)
    assert SmootherConfig(window_s=0.5).smoother_lag_s() == pytest.approx(0.55)
    with pytest.raises(ValidationError):
        SmootherConfig(window_size=3)  # extra field
    with pytest.raises(ValidationError):
        SmootherConfig(robust_kernel="tukey")
    with pytest.raises(ValidationError):
        cfg.window_s = 1.0  # frozen


def test_so3_exp_matches_gtsam():
    w = np.array([[0.3, -0.2, 1.1], [0.0, 0.0, 0.0], [1e-10, 0.0, 0.0]])
    R = so3_exp(w)
    for k in range(3):
        np.testing.assert_allclose(R[k], gtsam.Rot3.Expmap(w[k]).matrix(), atol=1e-12)


def test_midpoint_samples_exact_for_quadratic_signal():
    t = np.arange(0.0, 0.5, 0.01)
    y = np.stack([1.0 + 2.0 * t, 3.0 * t**2, -t], -1)
    a_mid, g_mid, dt = midpoint_samples(t, y, y, 0.105, 0.337)
    assert dt.sum() == pytest.approx(0.337 - 0.105)
    knots = np.concatenate([[0.105], np.cumsum(dt) + 0.105])
    # exact step means of the quadratic signal
    mean = np.stack(
        [
            1.0 + (knots[1:] + knots[:-1]),
            (knots[1:] ** 3 - knots[:-1] ** 3) / dt,
            -0.5 * (knots[1:] + knots[:-1]),
        ],
        -1,
    )
    np.testing.assert_allclose(g_mid, mean, atol=1e-10)
    # the averaged specific force is rotated by half the step rotation
    expected = np.einsum("nij,nj->ni", so3_exp(0.5 * g_mid * dt[:, None]), mean)
    np.testing.assert_allclose(a_mid, expected, atol=1e-10)
    with pytest.raises(EstimationError):
        midpoint_samples(t, y, y, 0.3, 0.3)


def test_preintegration_matches_analytic_shank_motion():
    """GTSAM preintegration fed by midpoint samples vs the analytic trajectory over 0.3 s."""
    t = np.arange(0.0, 2.0, 0.01)
    tr = _trajectory(t)
    R = rot_y(tr["pitch"])
    f = np.einsum("nji,nj->ni", R, tr["acc"] - np.array([0.0, 0.0, -GRAVITY_MPS2]))
    gyro = np.stack([0 * t, tr["rate"], 0 * t], -1)
    t0, t1 = 0.4, 0.7  # peak rate ~3.1 rad/s at t = 0.5
    pim = gtsam.PreintegratedCombinedMeasurements(make_preintegration_params(SmootherConfig()))
    for a, g, dt in zip(*midpoint_samples(t, f, gyro, t0, t1), strict=True):
        pim.integrateMeasurement(a, g, dt)
    k0, k1 = 40, 70
    nav0 = gtsam.NavState(gtsam.Pose3(gtsam.Rot3(R[k0]), tr["pos"][k0]), tr["vel"][k0])
    nav1 = pim.predict(nav0, gtsam.imuBias.ConstantBias())
    assert np.linalg.norm(nav1.pose().translation() - tr["pos"][k1]) < 5e-5  # 0.05 mm
    assert np.linalg.norm(nav1.velocity() - tr["vel"][k1]) < 5e-4
    ang = np.linalg.norm(gtsam.Rot3.Logmap(gtsam.Rot3(R[k1]).between(nav1.pose().rotation())))
    assert ang < 2e-5  # rad


def test_camera_covariance_from_pose_covariance_matches_sampling():
    rng = np.random.default_rng(0)
    R = rot_y(0.4)
    pose = gtsam.Pose3(gtsam.Rot3(R), np.array([1.0, 0.0, 0.5]))
    A = rng.normal(size=(6, 6)) * np.r_[[0.02] * 3, [0.01] * 3]
    cov6 = A @ A.T
    xi = rng.multivariate_normal(np.zeros(6), cov6, size=20000)
    c0 = pose.transformFrom(IMU_P_CAM_M)
    cams = np.array([pose.retract(x).transformFrom(IMU_P_CAM_M) - c0 for x in xi[:4000]])
    emp = np.cov(cams[:, [0, 2]].T)
    pred = camera_xz_cov_from_pose_cov(R, cov6, IMU_P_CAM_M)
    np.testing.assert_allclose(pred, emp, rtol=0.1, atol=2e-6)


def test_builder_chains_displacements_and_breaks_on_gaps():
    tr = make_swinging_shank_trial(1.0)
    b = KeyframeGraphBuilder(SmootherConfig(), tr.imu_T_cam)
    n_between = []
    from vio_graph.smoother.synthetic import replay_events

    drop = 5  # frame 5's displacement missing: keyframes 3 -> 6 get no displacement factor
    for kind, i in replay_events(tr):
        if kind == "imu":
            ups = b.add_imu(tr.imu[i])
        else:
            d = None if i == drop else tr.displacements[i]
            kf = bool(tr.is_keyframe[i])
            ups = b.add_frame(tr.frame_times_s[i], kf, tr.filter_estimates[i], d, None)
        for u in ups:
            chars = [[gtsam.Symbol(k).chr() for k in ks] for ks in u.factor_keys]
            n_between.append(sum(1 for c in chars if c == [ord("x"), ord("x")]))
    # keyframe 0 has none, keyframe 2 (frames 3..6) lost its chain, all others have one
    assert n_between[0] == 0 and n_between[2] == 0
    assert all(n == 1 for k, n in enumerate(n_between) if k not in (0, 2))


def test_builder_keeps_corners_and_stance_anchors_apart():
    """A corner and a stance anchor with the same number are two landmarks; the stance keeps
    its landmark over its frames and gets no corner sigma (types, not id ranges, tell them
    apart)."""
    tr = make_swinging_shank_trial(0.5)
    cfg = SmootherConfig(corner_landmark_sigma_m=0.05)
    b = KeyframeGraphBuilder(cfg, tr.imu_T_cam)
    from vio_graph.smoother.synthetic import replay_events

    cov = np.eye(2) * 1e-4
    landmark_factors = []  # per keyframe: (landmark key, 2x2 translation covariance) per factor
    for kind, i in replay_events(tr):
        if kind == "imu":
            ups = b.add_imu(tr.imu[i])
        else:
            t, kf = float(tr.frame_times_s[i]), bool(tr.is_keyframe[i])
            obs = [
                CornerObservation(t, 0, np.array([0.5, -0.3]), cov),
                StanceObservation(t, 0, np.array([-0.1, -0.4]), cov),
            ]
            ups = b.add_frame(t, kf, tr.filter_estimates[i], tr.displacements[i], obs)
        for u in ups:
            kf_factors = []
            for n, ks in enumerate(u.factor_keys):
                if [gtsam.Symbol(k).chr() for k in ks] == [ord("x"), ord("l")]:
                    noise = u.factors.at(n).noiseModel().noise()
                    kf_factors.append((ks[1], np.asarray(noise.covariance())[3:, 3:]))
            landmark_factors.append(kf_factors)
    assert len(landmark_factors) > 2
    for kf_factors in landmark_factors:
        (corner_key, corner_cov), (anchor_key, anchor_cov) = kf_factors
        assert (corner_key, anchor_key) == (L(0), L(1))
        assert corner_cov[0, 0] == pytest.approx(1e-4 + 0.05**2)
        assert anchor_cov[0, 0] == pytest.approx(1e-4)


def test_ingestion_errors():
    tr = make_swinging_shank_trial(0.5)
    s = SlidingWindowSmoother(SmootherConfig(), tr.imu_T_cam)
    s.feed_imu(tr.imu[0])
    with pytest.raises(EstimationError):
        s.feed_imu(tr.imu[0])  # timestamps must increase
    with pytest.raises(EstimationError):
        s.feed_frame(0.0, True, None, None, None)  # first keyframe needs an initial guess
    with pytest.raises(EstimationError):
        SlidingWindowSmoother(SmootherConfig(), np.eye(3))


# ---------------------------------------------------------------------------------------------
# whole-graph behaviour
# ---------------------------------------------------------------------------------------------
@pytest.mark.parametrize("cls", [SlidingWindowSmoother, BatchSmoother])
def test_noiseless_trial_recovers_ground_truth(cls):
    # vendor heading of 0.4 rad must be removed; the filter guess is off by a few cm
    tr = make_swinging_shank_trial(4.0, heading_rad=0.4, filter_velocity_sigma_mps=0.05)
    rng = np.random.default_rng(5)
    bad = [
        type(e)(**{**e.__dict__, "camera_xz_m": e.camera_xz_m + rng.normal(0, 0.02, 2)})
        for e in tr.filter_estimates
    ]
    bad[0] = tr.filter_estimates[0]
    tr = SyntheticTrial(**{**tr.__dict__, "filter_estimates": bad})
    s = cls(SmootherConfig(window_s=1.0), tr.imu_T_cam)
    feed(tr, s)
    err, _ = keyframe_errors_m(tr, s)
    assert err.max() < 1e-3  # sub-millimetre
    # per-frame output on the frames' own timestamps
    traj = s.frame_trajectory(tr.frame_times_s, tr.filter_xz_m)
    assert traj.shape == (tr.frame_times_s.size, 2)
    kf = np.flatnonzero(tr.is_keyframe)
    np.testing.assert_allclose(traj[kf], tr.camera_xz_true_m[kf], atol=1e-3)
    cov = s.keyframe_estimates()[-1].cov_m2
    assert cov.shape == (2, 2) and np.all(np.linalg.eigvalsh(cov) > 0)


@pytest.mark.parametrize("use_filter_guess", [True, False])
def test_imu_only_gap_is_bridged_with_bounded_error(use_filter_guess):
    """1 s without displacements and corners, unknown accelerometer bias of 0.05 m/s^2.

    Left uncorrected that bias alone would add 25 mm over the gap; the graph estimates it
    from the displacements around the gap. Without filter guesses the new keyframes are
    initialised by IMU prediction from the previous keyframe.
    """
    bias = np.array([0.05, 0.0, -0.05])
    kw = dict(displacement_sigma_m=0.001, accel_bias_mps2=tuple(bias), corners=False, seed=1)
    tr = make_swinging_shank_trial(4.0, gap_s=(2.0, 3.0), **kw)
    s = SlidingWindowSmoother(SmootherConfig(window_s=2.0), tr.imu_T_cam)
    feed(tr, s, use_filter_guess=use_filter_guess)
    err, t = keyframe_errors_m(tr, s)
    before = err[t < 2.0][-1]
    in_gap = (t >= 2.0) & (t <= 3.0)
    assert before < 0.005
    assert err[in_gap].max() - before < 0.008  # < 8 mm extra through a 1 s blind gap
    b_est = s.latest_state()[2].accelerometer()
    assert np.abs(b_est - bias).max() < 0.02


def test_old_keyframes_leave_the_window_but_keep_their_estimates():
    tr = make_swinging_shank_trial(3.0, displacement_sigma_m=0.002, seed=4)
    cfg = SmootherConfig(
        window_s=0.5,
        keyframe_period_s=0.1,
        marginal_covariance="when_newest",
        marginalization_slack_s=0.0,  # (every update marginalises: the window is exact)
    )
    s = SlidingWindowSmoother(cfg, tr.imu_T_cam)
    feed(tr, s)
    live = s.live_keys()
    assert live == s.smoother_keys()  # our mirror agrees with GTSAM's own window
    n_kf = int(tr.is_keyframe.sum())
    live_x = sorted(gtsam.Symbol(k).index() for k in live if gtsam.Symbol(k).chr() == ord("x"))
    # lag 0.55 s at 10 Hz keyframes: the newest 6 keyframes stay
    assert live_x == list(range(n_kf - 6, n_kf))
    assert X(0) not in live and V(0) not in live
    assert L(0) not in live  # the first stair nosing left the view at ~1 s
    assert any(gtsam.Symbol(k).chr() == ord("l") for k in live)  # corners still in view
    est = s.keyframe_estimates()
    assert len(est) == n_kf
    err, _ = keyframe_errors_m(tr, s)
    assert err.max() < 0.02
    assert all(np.isfinite(e.cov_m2).all() for e in est)
    # estimates of marginalised keyframes are frozen: more data does not change them
    first = est[0].camera_xz_m.copy()
    s.feed_imu(ImuSample(10.0, tr.imu[-1].accel_mps2, tr.imu[-1].gyro_radps, tr.imu[-1].quat_wxyz))
    np.testing.assert_array_equal(s.keyframe_estimates()[0].camera_xz_m, first)
    assert len(s.update_times_ms) == n_kf


def test_marginal_covariance_modes_change_only_the_frozen_covariances():
    """at_exit / when_newest / none: the same estimates bit for bit; none leaves NaN on the
    keyframes that left the window (live ones still get theirs on request); the filtering
    marginal (when_newest) is wider than the smoothed one just before exit (at_exit)."""
    tr = make_swinging_shank_trial(3.0, displacement_sigma_m=0.002, seed=4)
    out = {}
    for mode in ("at_exit", "when_newest", "none"):
        cfg = SmootherConfig(window_s=0.5, marginal_covariance=mode, marginalization_slack_s=0.0)
        s = SlidingWindowSmoother(cfg, tr.imu_T_cam)
        feed(tr, s)
        live_x = {gtsam.Symbol(k).index() for k in s.live_keys() if k >> 56 == ord("x")}
        out[mode] = s.keyframe_estimates()
    n = len(out["none"])
    frozen = [i for i in range(n) if i not in live_x]
    assert len(frozen) > 20 and len(live_x) == 6
    for mode in ("at_exit", "when_newest"):
        for a, b in zip(out[mode], out["none"], strict=True):
            np.testing.assert_array_equal(a.camera_xz_m, b.camera_xz_m)
            np.testing.assert_array_equal(a.R_world_imu, b.R_world_imu)
        assert all(np.all(np.linalg.eigvalsh(e.cov_m2) > 0) for e in out[mode])
    assert all(np.isnan(out["none"][i].cov_m2).all() for i in frozen)
    for i in live_x:  # live keyframes: the current marginal whatever the mode
        np.testing.assert_array_equal(out["none"][i].cov_m2, out["at_exit"][i].cov_m2)
    ratio = [
        np.trace(out["when_newest"][i].cov_m2) / np.trace(out["at_exit"][i].cov_m2) for i in frozen
    ]
    assert np.median(ratio) > 1.0


@pytest.mark.parametrize("cls", [SlidingWindowSmoother, BatchSmoother])
def test_one_step_off_displacement_is_downweighted(cls):
    """A displacement off by a stair step (0.28 m, 0.147 m) barely moves the robust solution."""
    kw = dict(displacement_sigma_m=0.002, corners=False, seed=2)
    clean = make_swinging_shank_trial(3.0, **kw)
    bad = make_swinging_shank_trial(3.0, outlier_frames=[40], **kw)

    def run(trial, kernel):
        s = cls(SmootherConfig(robust_kernel=kernel), trial.imu_T_cam)
        feed(trial, s)
        return np.array([e.camera_xz_m for e in s.keyframe_estimates(with_covariance=False)])

    ref = run(clean, "huber")
    dev_huber = np.abs(run(bad, "huber") - ref).max()
    dev_cauchy = np.abs(run(bad, "cauchy") - ref).max()
    dev_l2 = np.abs(run(bad, "none") - ref).max()
    assert dev_huber < 0.02 and dev_cauchy < 0.02
    assert dev_l2 > 0.1  # the plain least-squares solution is dragged by the outlier
    assert dev_l2 > 10 * dev_huber


@pytest.mark.parametrize("cls", [SlidingWindowSmoother, BatchSmoother])
def test_landmarks_bound_drift_of_biased_displacements(cls):
    tr = make_swinging_shank_trial(
        10.0,
        displacement_sigma_m=0.003,
        observation_sigma_m=0.005,
        displacement_bias_mps=(0.02, 0.01),
        seed=3,
    )
    res = {}
    for lm in (True, False):
        s = cls(SmootherConfig(factors=FactorFamilies(landmarks=lm)), tr.imu_T_cam)
        feed(tr, s)
        res[lm] = rms(keyframe_errors_m(tr, s)[0])
    assert res[True] < 0.02  # corners in view all along: ~1 cm
    assert res[True] < 0.2 * res[False]


def test_batch_fixed_lag_variant_agrees_with_incremental():
    tr = make_swinging_shank_trial(3.0, displacement_sigma_m=0.002, seed=4)
    out = {}
    for batch_solver in (True, False):
        # (the same window in both: the batch solver marginalises at every update)
        cfg = SmootherConfig(
            window_s=0.5, fixed_lag_batch_solver=batch_solver, marginalization_slack_s=0.0
        )
        s = SlidingWindowSmoother(cfg, tr.imu_T_cam)
        feed(tr, s)
        assert s.live_keys() == s.smoother_keys()
        out[batch_solver] = s.keyframe_estimates()
    xz_b = np.array([e.camera_xz_m for e in out[True]])
    xz_i = np.array([e.camera_xz_m for e in out[False]])
    np.testing.assert_allclose(xz_b, xz_i, atol=2e-3)
    assert np.isnan(out[True][-1].cov_m2).all()  # no marginals from BatchFixedLagSmoother


def test_held_samples_cover_interval_and_hold_values() -> None:
    from vio_graph.smoother.imu_sampling import held_samples

    t = np.arange(0.0, 0.5, 0.01)
    a = np.column_stack([t, 2 * t, np.full_like(t, 9.81)])
    g = np.column_stack([np.zeros_like(t), 3 * t, np.zeros_like(t)])
    a_s, g_s, dt = held_samples(t, a, g, 0.105, 0.3)
    assert abs(dt.sum() - 0.195) < 1e-12
    np.testing.assert_allclose(a_s[0], a[10])  # the step starting at 0.105 holds the 0.10 sample
    np.testing.assert_allclose(g_s[1], g[11])


def test_batch_counts_downweighted_outliers() -> None:
    """The batch smoother reports the robust factors it down-weights: a one-step-off
    displacement is among them and is the worst-fitting factor of the run, well above the
    worst of the same run without it."""
    from vio_graph.smoother.batch import BatchSmoother
    from vio_graph.smoother.config import SmootherConfig
    from vio_graph.smoother.synthetic import feed, make_swinging_shank_trial

    clean = BatchSmoother(SmootherConfig(), np.eye(4))
    feed(make_swinging_shank_trial(duration_s=3.0, seed=1), clean)
    bad = BatchSmoother(SmootherConfig(), np.eye(4))
    feed(make_swinging_shank_trial(duration_s=3.0, seed=1, outlier_frames=(40,)), bad)
    c, b = clean.robust_outliers(), bad.robust_outliers()
    assert c["robust_factors"] > 10
    assert b["downweighted"] >= c["downweighted"]
    assert b["max_whitened_error"] > 1.5 * c["max_whitened_error"]


def test_downweighted_counts_in_one_pass_are_the_two_passes_bit_for_bit() -> None:
    """BatchSmoother.robust_outliers counts the IMU and the other robust factors in one pass
    over the graph (count_downweighted_both); the answers are count_downweighted's, called
    once per kind, exactly: counts, and the largest whitened error to the bit, at thresholds
    where some factors of each kind are down-weighted and some are not."""
    from vio_graph.smoother.batch import count_downweighted, count_downweighted_both
    from vio_graph.smoother.synthetic import feed, make_swinging_shank_trial

    bad = BatchSmoother(SmootherConfig(), np.eye(4))
    feed(make_swinging_shank_trial(duration_s=3.0, seed=1, outlier_frames=(40, 61)), bad)
    result = bad.solve()
    graph = bad.graph
    ref = count_downweighted(graph, result, 1.0)
    ref_imu = count_downweighted(graph, result, 1.0, imu=True)
    # thresholds inside each kind's spread of errors: both branches of the test are taken
    thresholds = [(0.0, 0.0), (1.0, 1.0), (1e9, 1e9)]
    thresholds.append((0.5 * ref["max_whitened_error"], 0.5 * ref_imu["max_whitened_error"]))
    for thr, thr_imu in thresholds:
        want = count_downweighted(graph, result, thr)
        want_imu = count_downweighted(graph, result, thr_imu, imu=True)
        got, got_imu = count_downweighted_both(graph, result, thr, thr_imu)
        assert got == want and got_imu == want_imu
        assert type(got["max_whitened_error"]) is float
    mid, mid_imu = count_downweighted_both(
        graph, result, 0.5 * ref["max_whitened_error"], 0.5 * ref_imu["max_whitened_error"]
    )
    assert 0 < mid["downweighted"] < mid["robust_factors"]
    assert ref_imu["robust_factors"] > 0 and 0 < mid_imu["downweighted"]
    out = bad.robust_outliers()
    cfg = SmootherConfig()
    want = count_downweighted(graph, result, cfg.robust_threshold)
    want_imu = count_downweighted(graph, result, cfg.imu_robust_threshold, imu=True)
    assert out == {**want, **{f"imu_{k}": v for k, v in want_imu.items()}}


def test_discretization_variance_zero_for_cubic_and_sized_by_a_kink() -> None:
    t = np.arange(0.0, 0.3, 0.01)
    cubic = np.stack([1.0 + 2 * t - 3 * t**2 + 4 * t**3] * 3, axis=-1)
    assert discretization_velocity_var(t, cubic, 0.1, 0.2) == pytest.approx(0.0, abs=1e-20)
    # a step of 1 m/s^2 at one sample: fourth differences 1, -4, 6, -4, 1 in the five
    # windows that contain it, all touching [0.1, 0.2]; one axis only
    a = np.zeros((t.size, 3))
    a[15, 0] = 1.0
    expected = 0.01**2 * (1 + 16 + 36 + 16 + 1)
    assert discretization_velocity_var(t, a, 0.1, 0.2) == pytest.approx(expected)
    # windows wholly after the interval do not count
    assert discretization_velocity_var(t, a, 0.0, 0.1) == pytest.approx(0.0)


def test_discretization_term_inflates_only_the_imu_noise() -> None:
    cfg = SmootherConfig()
    base = make_preintegration_params(cfg)
    p = make_preintegration_params(cfg, extra_velocity_var_m2ps2=1e-4, duration_s=0.1)
    acc0 = cfg.accel_noise_density_mps2_per_sqrt_hz**2
    assert np.diag(p.getAccelerometerCovariance()) == pytest.approx([acc0 + 1e-3] * 3)
    assert np.allclose(p.getGyroscopeCovariance(), base.getGyroscopeCovariance())


def test_imu_factor_noise_is_fixed_when_built() -> None:
    """The builder reuses one parameters object across keyframe intervals (set_white_noise):
    that is exact only because a CombinedImuFactor takes its noise model from the finished
    preintegration. Changing the parameters afterwards leaves the factor's noise as built,
    and a later interval integrated with the reused object equals one with fresh ones."""
    from vio_graph.smoother.imu_sampling import set_white_noise

    cfg = SmootherConfig()
    acc, gyr, dt = np.array([0.3, -0.2, 9.9]), np.array([0.1, 2.5, -0.3]), 0.01

    def factor(params: gtsam.PreintegrationCombinedParams) -> gtsam.CombinedImuFactor:
        pim = gtsam.PreintegratedCombinedMeasurements(params, gtsam.imuBias.ConstantBias())
        for _ in range(10):
            pim.integrateMeasurement(acc, gyr, dt)
        return gtsam.CombinedImuFactor(X(0), V(0), X(1), V(1), B(0), B(1), pim)

    shared = make_preintegration_params(cfg, 1e-4, 0.1)
    first = factor(shared)
    cov_first = first.noiseModel().covariance().copy()
    set_white_noise(shared, cfg, 5e-2, 0.1, 1e-3)  # the next interval, much noisier
    np.testing.assert_array_equal(first.noiseModel().covariance(), cov_first)
    second = factor(shared)
    fresh = factor(make_preintegration_params(cfg, 5e-2, 0.1, 1e-3))
    np.testing.assert_array_equal(second.noiseModel().covariance(), fresh.noiseModel().covariance())
    assert second.noiseModel().covariance()[6, 6] > 10 * cov_first[6, 6]  # velocity block


def test_builder_maps_measurements_with_the_given_attitude() -> None:
    """A frame attitude passed by the caller (the filter's) is the keyframe's rotation, not the
    IMU stream's AHRS."""
    tr = make_swinging_shank_trial(0.5)
    b = KeyframeGraphBuilder(SmootherConfig(), tr.imu_T_cam)
    from vio_graph.smoother.synthetic import replay_events

    R_given = rot_y(0.3)
    rots = []
    for kind, i in replay_events(tr):
        if kind == "imu":
            ups = b.add_imu(tr.imu[i])
        else:
            ups = b.add_frame(
                tr.frame_times_s[i],
                bool(tr.is_keyframe[i]),
                tr.filter_estimates[i],
                tr.displacements[i],
                None,
                R_given,
            )
        rots += [u.values.atPose3(X(u.index)).rotation().matrix() for u in ups]
    assert len(rots) >= 2
    assert all(np.allclose(R, R_given, atol=1e-9) for R in rots)


def test_common_frame_preintegration_is_exact_for_gravity_on_a_spinning_shank() -> None:
    """Gravity seen by an IMU turning at 8 rad/s (swing): the world-frame velocity change over
    0.1 s is exactly g dt. The moving-frame midpoint rule falls short by (omega dt)^2/24 per
    step (a downward drift); the common-frame rule does not."""
    from vio_graph.smoother.imu_sampling import common_frame_samples, midpoint_samples, so3_exp

    w = np.array([0.0, 8.0, 0.0])
    t = np.arange(0.0, 0.2, 0.01)
    g_world = np.array([0.0, 0.0, 9.81])
    f = np.stack([so3_exp(-w * ti) @ g_world for ti in t])  # specific force of a still body
    gyro = np.tile(w, (t.size, 1))
    true_dv = so3_exp(-w * 0.05) @ g_world * 0.1  # in the frame at t0 = 0.05 s

    def integrate(fn) -> np.ndarray:
        a, gm, dt = fn(t, f, gyro, 0.05, 0.15)
        R, dv = np.eye(3), np.zeros(3)
        for k in range(dt.size):  # GTSAM's order: start-of-step rotation, then rotate
            dv += R @ a[k] * dt[k]
            R = R @ so3_exp(gm[k] * dt[k])
        return dv

    assert np.linalg.norm(integrate(common_frame_samples) - true_dv) < 1e-9
    short = np.linalg.norm(integrate(midpoint_samples) - true_dv)
    assert 1e-4 < short < 1e-3  # 0.26 mm/s: (0.08)^2 / 24 * 9.81 * 0.1


def test_chained_displacements_add_the_per_frame_floor() -> None:
    """Two frame-to-frame displacements chain into one: deltas add, covariances add, and
    each frame contributes frame_displacement_sigma_m^2 per axis."""
    from vio_graph.types import Displacement2D

    cfg = SmootherConfig(frame_displacement_sigma_m=0.002)
    b = KeyframeGraphBuilder(cfg, np.eye(4))
    c = np.diag([1e-6, 4e-6])
    b._chain_displacement(Displacement2D(0.0, 0.1, np.array([0.01, 0.02]), c))
    b._chain_displacement(Displacement2D(0.1, 0.2, np.array([0.03, -0.01]), c))
    t0, t1, delta, cov = b._chain
    assert (t0, t1) == (0.0, 0.2)
    np.testing.assert_allclose(delta, [0.04, 0.01])
    np.testing.assert_allclose(cov, 2 * c + 2 * np.eye(2) * 0.002**2)


# ---------------------------------------------------------------------------------------------
# long trials
# ---------------------------------------------------------------------------------------------
@pytest.mark.parametrize("cls", [SlidingWindowSmoother, BatchSmoother])
def test_long_trial_does_not_follow_a_drifting_filter(cls):
    """60 s (~600 keyframes, ~170 stair nosings passed) with a filter that drifts by 5 mm/s
    in x and -2 mm/s in z (30 cm / 12 cm at the end). The filter only supplies initial
    guesses: the refined keyframes keep only the random walk of the relative factors
    (~1 cm RMS over the trial here), not the filter's drift. A weak
    absolute position prior at each initial guess (sigma 1 m, the former default) adds up
    over the keyframes: hundreds of such priors outweigh the relative factors at long
    wavelengths, and the estimate follows the filter's drift."""
    tr = make_swinging_shank_trial(
        60.0,
        displacement_sigma_m=0.002,
        observation_sigma_m=0.003,
        filter_drift_mps=(0.005, -0.002),
        seed=7,
    )
    drift_at_end = np.linalg.norm(tr.filter_xz_m[-1] - tr.camera_xz_true_m[-1])
    assert drift_at_end > 0.3
    err = {}
    for weak in (False, True):
        cfg = SmootherConfig(factors=FactorFamilies(weak_position=weak), weak_position_sigma_m=1.0)
        s = cls(cfg, tr.imu_T_cam)
        feed(tr, s)
        e, t = keyframe_errors_m(tr, s)
        err[weak] = e[t > 50.0]
        if not weak:
            assert rms(e) < 0.015 and e.max() < 0.025
    assert SmootherConfig().factors.weak_position is False  # the default
    # the old prior drags the end towards the filter (measured: 8.6-9.1 vs 1.1-1.4 cm)
    assert rms(err[True]) > 4 * rms(err[False])


def test_stance_velocity_bounds_a_blind_stretch() -> None:
    """2.5 s without displacements or corners and an accelerometer bias: the velocity a still
    point implies (here the camera's instantaneous centre of rotation, as the ankle, with a
    5 cm/s sigma) holds the keyframe velocities, and so the path, through the stretch; the
    factor takes the IMU velocity from the gyro and the lever IMU -> camera -> still point
    (a wrong lever sign or frame would make it worse, not better)."""
    bias = (0.1, 0.0, -0.1)
    kw = dict(displacement_sigma_m=0.001, accel_bias_mps2=bias, corners=False, seed=2)
    tr = make_swinging_shank_trial(4.0, gap_s=(1.5, 4.0), **kw)
    t_f = tr.frame_times_s
    v_cam = np.gradient(tr.camera_xz_true_m, t_f, axis=0)
    # the still point: the camera's instantaneous centre of rotation (pitch rate about world
    # y): v_cam = -omega x r  <=>  r = (v_z, -v_x) / rate; only where it is within 1 m
    t_imu = np.array([s.timestamp_s for s in tr.imu])
    rate = np.interp(t_f, t_imu, [s.gyro_radps[1] for s in tr.imu])
    cov = np.eye(2) * 1e-4
    obs = [
        [
            StanceObservation(
                float(t_f[n]),
                n,
                np.array([v_cam[n, 1], -v_cam[n, 0]]) / rate[n],
                cov,
                camera_velocity_xz_mps=v_cam[n],
                velocity_cov=np.eye(2) * 0.05**2,
            )
        ]
        if 1.5 <= t_f[n] <= 4.0 and np.hypot(*v_cam[n]) < abs(rate[n])
        else []
        for n in range(t_f.size)
    ]
    errs = {}
    for on in (False, True):
        fam = FactorFamilies(stance_anchors=False, stance_velocity=on)
        s = SlidingWindowSmoother(SmootherConfig(window_s=2.0, factors=fam), tr.imu_T_cam)
        trial = SyntheticTrial(**{**tr.__dict__, "observations": obs})
        feed(trial, s, use_filter_guess=False)
        err, t = keyframe_errors_m(tr, s)
        errs[on] = err[t >= 1.5].max()
    assert errs[True] < 0.5 * errs[False], errs
    assert errs[True] < 0.02, errs


def test_stance_velocity_uses_the_gyro_at_the_keyframe_time() -> None:
    """The shank's pitch rate ramps at 20 rad/s^2 (stance at 1.5x cadence) and the keyframe
    falls 7 ms after a 100 Hz gyro sample. The IMU velocity prior is that of a still ankle
    with the gyro interpolated to the keyframe time, -omega(t) x (ankle - imu), for the whole
    lever; the filter's camera velocity, built with the latest (stale) gyro sample, is only
    the flag that the filter fused it. Mixing the two (the former model) is off by 0.06 m/s
    here."""
    T = np.eye(4)
    T[:3, 3] = [0.02, 0.0, 0.05]  # camera in IMU axes, m
    b = KeyframeGraphBuilder(SmootherConfig(), T)
    q = np.array([1.0, 0.0, 0.0, 0.0])
    rate = lambda t: 1.0 + 20.0 * t  # noqa: E731 (rad/s about y)
    for k in range(12):
        t = 0.01 * k
        gyro = np.array([0.0, rate(t), 0.0])
        b.add_imu(ImuSample(t, np.array([0.0, 0.0, GRAVITY_MPS2]), gyro, q))
    t_kf = 0.107
    ankle_rel = np.array([0.05, -0.40])  # ankle - camera, m
    stale = -np.cross([0.0, rate(0.10), 0.0], [ankle_rel[0], 0.0, ankle_rel[1]])[[0, 2]]
    ob = StanceObservation(
        t_kf,
        0,
        ankle_rel,
        np.eye(2) * 1e-6,
        camera_velocity_xz_mps=stale,
        velocity_cov=np.eye(2) * 0.05**2,
    )
    est = make_swinging_shank_trial(0.2).filter_estimates[0]
    assert b.add_frame(0.05, True, est, None, None, np.eye(3))  # first keyframe, no stance
    ups = b.add_frame(t_kf, True, est, None, ob, np.eye(3))
    assert len(ups) == 1 and ups[0].index == 1
    g = ups[0].factors
    priors = [
        g.at(k).prior()
        for k in range(g.size())
        if isinstance(g.at(k), gtsam.PriorFactorVector)
        and g.at(k).keys()[0] == V(1)
        and np.linalg.norm(g.at(k).prior()) > 0
    ]
    assert len(priors) == 1
    imu_to_ankle = T[:3, 3] + np.array([ankle_rel[0], 0.0, ankle_rel[1]])
    expected = -np.cross([0.0, rate(t_kf), 0.0], imu_to_ankle)
    np.testing.assert_allclose(priors[0], expected, atol=1e-9)
    former = np.r_[stale[0], 0.0, stale[1]] - np.cross([0.0, rate(t_kf), 0.0], T[:3, 3])
    assert np.linalg.norm(former - expected) > 0.05


@pytest.mark.parametrize("cls", [BatchSmoother, SlidingWindowSmoother])
def test_smoothed_pitch_corrects_the_filters_attitude_errors(cls) -> None:
    """The leg kinematics of a smoothed mode use the smoother's refined attitude
    (``shank_pitch_path``): the frames' attitude (the filter's, the keyframes' prior) is the
    true one turned by a known pitch error (0.5 deg rms white per frame, 1.5 deg at the first
    frame, the toe ATE's anchor); the exact gyro ties the keyframes together and the
    accelerometer shows gravity, so the refined pitch is far closer to the truth."""
    tr = make_swinging_shank_trial(4.0, displacement_sigma_m=0.0005, seed=3)
    rng = np.random.default_rng(5)
    err = np.radians(rng.normal(0.0, 0.5, tr.frame_times_s.size))
    err[0] = np.radians(1.5)
    true_pitch = np.asarray(_trajectory(tr.frame_times_s)["pitch"])
    from vio_graph.smoother.synthetic import replay_events

    sm = cls(SmootherConfig(), tr.imu_T_cam)
    for kind, i in replay_events(tr):
        if kind == "imu":
            sm.feed_imu(tr.imu[i])
        else:
            sm.feed_frame(
                float(tr.frame_times_s[i]),
                bool(tr.is_keyframe[i]),
                tr.filter_estimates[i],
                tr.displacements[i],
                tr.observations[i],
                rot_y(true_pitch[i] + err[i]),
            )
    sm.flush()
    if isinstance(sm, BatchSmoother):
        sm.solve()
    filter_pitch = true_pitch + err
    kf = tr.is_keyframe
    smoothed = sm.shank_pitch_path(tr.frame_times_s, filter_pitch, pitch_of)
    before = np.degrees(filter_pitch - true_pitch)[kf]
    after = np.degrees(smoothed - true_pitch)[kf]
    assert rms(before) == pytest.approx(0.53, abs=0.05)  # the premise: the filter's error
    # measured: batch 0.16 deg rms, first keyframe -0.24; fixed-lag 0.25, -0.85 (its first
    # keyframes leave the window after 2-2.2 s, and the first pose's prior is the tighter one)
    assert rms(after) < 0.55 * rms(before)
    # the anchor frame: 1.5 deg in the filter's attitude. The fixed-lag smoother keeps the
    # value read as the keyframe leaves the window; in this trial the window's estimate of
    # it moves between -0.26 deg at 2.0 s (the exit of an exact 2 s window) and -0.85 deg at
    # 2.2 s (the exit with smoother.marginalization_slack_s = 0.2, the default)
    assert abs(after[0]) < (0.5 if isinstance(sm, BatchSmoother) else 1.0)
    with pytest.raises(EstimationError, match="filter pitches"):
        sm.shank_pitch_path(tr.frame_times_s, filter_pitch[:-1], pitch_of)


def _jittered_shank_imu(n: int, seed: int) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """n samples at 100 Hz with 2 ms jitter: a shank swinging at up to ~7 rad/s, gravity and
    heel-strike-like spikes in the specific force."""
    rng = np.random.default_rng(seed)
    t = 0.01 * np.arange(n) + rng.uniform(-0.002, 0.002, n)
    g = np.column_stack([0.3 * np.sin(3 * t), 7.0 * np.cos(6 * t), 0.2 * np.sin(9 * t)])
    a = np.column_stack([2.0 * np.sin(5 * t), 0.1 * t, 9.81 + 3.0 * np.cos(7 * t)])
    a[rng.integers(0, n, 3)] += rng.normal(0.0, 20.0, (3, 3))
    return t, a, g


def test_compiled_step_means_equal_the_numpy_sampler() -> None:
    """smoother/compiled_sampling.py against imu_sampling.common_frame_samples: intervals
    between samples, on samples, beyond the last sample, and one sample only."""
    pytest.importorskip("numba")
    from vio_graph.smoother.compiled_sampling import common_frame_steps
    from vio_graph.smoother.imu_sampling import TIME_TOL_S, common_frame_samples

    t, a, g = _jittered_shank_imu(40, seed=5)
    cases = [(t[3] + 0.004, t[14] - 0.003), (t[2], t[12]), (t[30], t[-1] + 0.02)]
    cases += [(t[5] - 0.001, t[5] + 0.002)]
    for (t0, t1), substeps in zip(cases * 2, [1] * len(cases) + [3] * len(cases), strict=True):
        ref = common_frame_samples(t, a, g, t0, t1, substeps)
        got = common_frame_steps(t, a, g, t0, t1, TIME_TOL_S, substeps)
        for r, c in zip(ref, got, strict=True):
            assert r.shape == c.shape
            np.testing.assert_allclose(c, r, rtol=1e-12, atol=1e-12)
    one = (t[:1], a[:1], g[:1], t[0] - 0.01, t[0] + 0.01)
    for r, c in zip(common_frame_samples(*one), common_frame_steps(*one, TIME_TOL_S), strict=True):
        np.testing.assert_allclose(c, r, rtol=1e-12, atol=1e-12)


def test_compiled_discretization_var_is_the_numpy_float() -> None:
    """compiled_sampling.discretization_var against imu_sampling.discretization_velocity_var:
    the same float (same differences, numpy's summation order), for intervals inside, at
    the ends of and beyond the samples, too few samples, and an interval no window touches;
    and it is not trivially zero."""
    pytest.importorskip("numba")
    from vio_graph.smoother.compiled_sampling import discretization_var
    from vio_graph.smoother.imu_sampling import TIME_TOL_S, discretization_velocity_var

    t, a, _ = _jittered_shank_imu(60, seed=11)
    cases = [(t[3] + 0.004, t[14] - 0.003), (t[0], t[-1]), (t[50], t[-1] + 0.02)]
    cases += [(t[5] - 0.001, t[5] + 0.002), (t[-1] + 1.0, t[-1] + 2.0), (t[0] - 1.0, t[0])]
    values = []
    for t0, t1 in cases:
        ref = discretization_velocity_var(t, a, t0, t1)
        got = discretization_var(t, a, t0, t1, TIME_TOL_S)
        assert got == ref, (t0, t1)  # bit for bit
        values.append(ref)
    assert values[1] > values[0] > 0.0 and values[4] == 0.0
    for n in range(5):  # fewer than five samples: no window
        assert discretization_var(t[:n], a[:n], t[0], t[-1], TIME_TOL_S) == 0.0


def test_compiled_preintegration_gives_the_same_smoother_answer(
    short_upstair, monkeypatch: pytest.MonkeyPatch
) -> None:
    """A replay's fixed-lag and batch keyframes with the compiled step means (and the
    compiled IMU path, VIO_GRAPH_COMPILED=1) equal the numpy path's to 1e-9 m."""
    pytest.importorskip("numba")
    from vio_graph.config import PipelineConfig
    from vio_graph.recording import Recording
    from vio_graph.replay import Replay
    from vio_graph.viz.rerun_logger import NullVisualizer

    rec = Recording.open(short_upstair)

    def keyframes(compiled: str) -> dict[str, np.ndarray]:
        monkeypatch.setenv("VIO_GRAPH_COMPILED", compiled)
        base = PipelineConfig()  # frozen keyframes' covariances compared too
        sm_cfg = base.smoother.model_copy(update={"marginal_covariance": "when_newest"})
        rp = Replay(
            rec,
            base.model_copy(update={"smoother": sm_cfg}),
            {"smoother", "batch"},
            NullVisualizer(),
        )
        rp.run()
        out = {}
        for name in ("smoother", "batch"):
            est = rp.estimators[name].keyframe_estimates()
            out[name] = np.array([e.camera_xz_m for e in est])
            out[name + " cov"] = np.array([e.cov_m2 for e in est])
        return out

    ref, got = keyframes("0"), keyframes("1")
    assert ref["smoother"].shape[0] > 20
    for name in ref:
        if name.endswith("cov"):
            np.testing.assert_allclose(got[name], ref[name], rtol=1e-6, atol=1e-15, err_msg=name)
        else:
            np.testing.assert_allclose(got[name], ref[name], rtol=0, atol=1e-9, err_msg=name)


@pytest.mark.parametrize("cls", [BatchSmoother, SlidingWindowSmoother])
def test_first_velocity_prior_is_as_uncertain_as_the_filter_says(cls) -> None:
    """A trial starting mid-stride (1.7 m/s): the filter starts at the first frame with v = 0
    and 0.5 m/s of sigma, and a corrupt IMU packet 50 ms in carries extra sigma (the chain of
    IMU factors from the first keyframe to the later ones is loosened, as by a spike the
    monitor repaired). With the filter's covariance in the first velocity prior the
    displacements place the first keyframes; with 0.1 m/s alone the prior's wrong mean pulls
    the first motion short by 1-2 cm, and the first-pose-anchored path keeps that offset."""
    import dataclasses

    tr = make_swinging_shank_trial(1.0, displacement_sigma_m=0.001, corners=False, seed=2)
    f0 = tr.filter_estimates[0]
    assert np.linalg.norm(f0.velocity_xz_mps) > 1.5
    tr.filter_estimates[0] = dataclasses.replace(
        f0, velocity_xz_mps=np.zeros(2), cov_velocity_m2ps2=np.eye(2) * 0.5**2
    )
    tr.imu[5] = dataclasses.replace(tr.imu[5], accel_extra_sigma_mps2=5.0)
    err = {}
    for on in (True, False):
        s = cls(
            SmootherConfig(first_velocity_filter_cov=on, first_velocity_test=False), tr.imu_T_cam
        )
        feed(tr, s)
        xz = np.array([e.camera_xz_m for e in s.keyframe_estimates(with_covariance=False)])
        idx = np.flatnonzero(tr.is_keyframe)
        e = xz - tr.camera_xz_true_m[idx]
        err[on] = np.max(np.abs(e - e[0]))
    assert err[True] < 0.006
    assert err[False] > 0.008 and err[False] > 1.5 * err[True]


@pytest.mark.parametrize("cls", [BatchSmoother, SlidingWindowSmoother])
def test_a_robust_kernel_lets_the_imu_chain_outvote_a_wrong_first_velocity(cls) -> None:
    """The trial of the test above (1.7 m/s at the start, the filter's guess v = 0, a corrupt
    packet 50 ms in), the prior kept at 0.1 m/s but under a Huber kernel
    (``first_velocity_kernel``): 17 sigma off, it pulls with a constant force instead of a
    growing one, and the displacements place the first keyframes as with the filter's
    covariance; without the kernel the first motion comes out short."""
    import dataclasses

    tr = make_swinging_shank_trial(1.0, displacement_sigma_m=0.001, corners=False, seed=2)
    f0 = tr.filter_estimates[0]
    tr.filter_estimates[0] = dataclasses.replace(
        f0, velocity_xz_mps=np.zeros(2), cov_velocity_m2ps2=np.eye(2) * 0.5**2
    )
    tr.imu[5] = dataclasses.replace(tr.imu[5], accel_extra_sigma_mps2=5.0)
    err = {}
    for kernel in ("huber", "none"):
        s = cls(
            SmootherConfig(first_velocity_kernel=kernel, first_velocity_test=False), tr.imu_T_cam
        )
        feed(tr, s)
        xz = np.array([e.camera_xz_m for e in s.keyframe_estimates(with_covariance=False)])
        idx = np.flatnonzero(tr.is_keyframe)
        e = xz - tr.camera_xz_true_m[idx]
        err[kernel] = np.max(np.abs(e - e[0]))
    assert err["huber"] < 0.006
    assert err["none"] > 1.5 * err["huber"]


def _start_mid_stride_trial(v0_guess_wrong: bool, corrupt_packet: str | None):
    """The trial of the two tests above: 1.7 m/s at the start, the filter's start guess v = 0
    with 0.5 m/s of sigma (or, ``v0_guess_wrong`` False, its true velocity), and a packet
    50 ms in that the fault monitor repaired (``corrupt_packet`` 'repaired': held, extra
    sigma) or only distrusted ('saturated': extra sigma, the saturation prior's mark)."""
    import dataclasses

    tr = make_swinging_shank_trial(1.0, displacement_sigma_m=0.001, corners=False, seed=2)
    f0 = tr.filter_estimates[0]
    v0 = np.zeros(2) if v0_guess_wrong else f0.velocity_xz_mps
    tr.filter_estimates[0] = dataclasses.replace(
        f0, velocity_xz_mps=v0, cov_velocity_m2ps2=np.eye(2) * 0.5**2
    )
    if corrupt_packet is not None:
        held = corrupt_packet == "repaired"
        tr.imu[5] = dataclasses.replace(tr.imu[5], accel_extra_sigma_mps2=5.0, accel_held=held)
    return tr


def _first_pose_anchored_error(tr, s) -> np.ndarray:
    xz = np.array([e.camera_xz_m for e in s.keyframe_estimates(with_covariance=False)])
    e = xz - tr.camera_xz_true_m[np.flatnonzero(tr.is_keyframe)]
    return e - e[0]


@pytest.mark.parametrize("cls", [BatchSmoother, SlidingWindowSmoother])
def test_a_repaired_packet_near_the_start_puts_the_first_velocity_prior_to_the_test(cls) -> None:
    """``first_velocity_test`` (default): the repaired packet 50 ms in loosens the IMU
    chain, so the first velocity prior is tested at the estimate; 17 sigma off, it fails and
    is given the filter's covariance, and the displacements place the first keyframes (the
    answer of ``first_velocity_filter_cov``); without the test the first motion comes out
    short by more than 8 mm."""
    tr = _start_mid_stride_trial(v0_guess_wrong=True, corrupt_packet="repaired")
    s_on = cls(SmootherConfig(), tr.imu_T_cam)
    feed(tr, s_on)
    s_off = cls(SmootherConfig(first_velocity_test=False), tr.imu_T_cam)
    feed(tr, s_off)
    e_on = np.max(np.abs(_first_pose_anchored_error(tr, s_on)))
    e_off = np.max(np.abs(_first_pose_anchored_error(tr, s_off)))
    s_on.keyframe_estimates(with_covariance=False)  # (the batch solves here)
    assert s_on.first_velocity_relaxed and not s_off.first_velocity_relaxed
    assert e_on < 0.006
    assert e_off > 0.008 and e_off > 1.5 * e_on


@pytest.mark.parametrize("cls", [BatchSmoother, SlidingWindowSmoother])
@pytest.mark.parametrize(
    ("v0_guess_wrong", "corrupt_packet"),
    [(True, None), (True, "saturated"), (False, "repaired")],
    ids=["clean", "saturated", "right_v0"],
)
def test_the_first_velocity_test_leaves_a_chain_without_repairs_or_a_right_prior_alone(
    cls, v0_guess_wrong: bool, corrupt_packet: str | None
) -> None:
    """No repaired packet (a clean trial, or a saturated sample, with the same wrong start
    guess): the test is never run and the answer is bit for bit the one without it. A
    repaired packet but a start guess that is right: the prior passes its test and stays as
    built."""
    tr = _start_mid_stride_trial(v0_guess_wrong, corrupt_packet)
    out = {}
    for on in (True, False):
        s = cls(SmootherConfig(first_velocity_test=on), tr.imu_T_cam)
        feed(tr, s)
        out[on] = _first_pose_anchored_error(tr, s)
        assert not s.first_velocity_relaxed
    np.testing.assert_array_equal(out[True], out[False])


# ---------------------------------------------------------------------------------------------
# the gyro's discretisation term (imu_sampling.discretization_rotation_var)
# ---------------------------------------------------------------------------------------------
def _step_mean_rotation_error(t, gyro_y, t0, t1, integral) -> float:
    """Pitch (rad) the common-frame step means integrate over [t0, t1] minus ``integral``."""
    from vio_graph.smoother.imu_sampling import common_frame_samples

    g = np.zeros((t.size, 3))
    g[:, 1] = gyro_y
    a = np.tile([0.0, 0.0, GRAVITY_MPS2], (t.size, 1))
    _, g_mid, dt = common_frame_samples(t, a, g, t0, t1)
    return float(g_mid[:, 1] @ dt - integral)


def test_gyro_discretization_gain_is_the_quartic_step_error() -> None:
    """Known answer: the curvature-corrected step mean of a quartic rate misses its integral
    over one sample step by exactly (11/720) h D4, the config's default gain."""
    from vio_graph.smoother.config import GYRO_DISCRETIZATION_GAIN

    assert SmootherConfig().gyro_discretization_gain == GYRO_DISCRETIZATION_GAIN == 11 / 720
    for h, c, k in [(0.02, 3.0e3, 0), (0.01, -5.0e4, 3), (0.005, 1.0e5, 7)]:
        t = h * np.arange(-6, 12)
        t0, t1 = t[6 + k], t[7 + k]
        err = _step_mean_rotation_error(t, c * t**4, t0, t1, c * (t1**5 - t0**5) / 5)
        d4 = 24.0 * c * h**4  # the fourth difference of c t^4
        assert abs(err) == pytest.approx(GYRO_DISCRETIZATION_GAIN * h * abs(d4), rel=1e-6)


def test_gyro_discretization_variance_against_monte_carlo_kinks() -> None:
    """Monte Carlo: a heel strike as a jump of the angular acceleration (rate c (t - tau)+,
    c ~ N(0, 1) rad/s^2, tau uniform around a 0.1 s interval sampled at 50 Hz). The mean
    squared rotation error of the step means is 1.5x the mean variance the term predicts
    (each window counted as independent while a kink's windows add coherently), and the
    prediction is exactly zero where no sample sees the kink's curvature (a linear rate)."""
    from vio_graph.smoother.config import GYRO_DISCRETIZATION_GAIN as GAIN
    from vio_graph.smoother.imu_sampling import discretization_rotation_var

    rng = np.random.default_rng(0)
    h = 0.02
    t = h * np.arange(-10, 16)
    t0, t1 = 0.0, 5 * h
    sq_err, pred = [], []
    for _ in range(2000):
        tau, c = rng.uniform(t0 - 3 * h, t1 + 3 * h), rng.normal()
        rate = c * np.maximum(t - tau, 0.0)
        ramp = 0.5 * c * (max(t1 - tau, 0.0) ** 2 - max(t0 - tau, 0.0) ** 2)
        sq_err.append(_step_mean_rotation_error(t, rate, t0, t1, ramp) ** 2)
        g = np.zeros((t.size, 3))
        g[:, 1] = rate
        pred.append(GAIN**2 * discretization_rotation_var(t, g, t0, t1))
    ratio = np.mean(sq_err) / np.mean(pred)
    assert 1.3 < ratio < 1.8
    lin = np.zeros((t.size, 3))
    lin[:, 1] = 2.0 + 30.0 * t
    assert discretization_rotation_var(t, lin, t0, t1) == pytest.approx(0.0, abs=1e-24)


def test_gyro_discretization_term_enters_the_rotation_covariance() -> None:
    """The builder adds gain^2 x discretization_rotation_var to the IMU factor's rotation
    covariance (GTSAM's preintegrated rotation block, small rotations: exactly the added
    white-noise variance x duration), and the velocity block is not touched by it."""
    from vio_graph.smoother.imu_sampling import discretization_rotation_var

    t, a, g = _jittered_shank_imu(30, seed=4)
    g[12, 1] += 3.0  # a rate spike: large fourth differences in the interval

    def preint(gain: float):
        b = KeyframeGraphBuilder(SmootherConfig(gyro_discretization_gain=gain), np.eye(4))
        for k in range(t.size):
            b.add_imu(ImuSample(float(t[k]), a[k], g[k], np.array([1.0, 0.0, 0.0, 0.0])))
        b._last_kf_time_s = float(t[8])
        return b._preintegrate(float(t[18])).preintMeasCov()

    gain = 11 / 720
    with_term, without = preint(gain), preint(0.0)
    expected = gain**2 * discretization_rotation_var(t, g, float(t[8]), float(t[18]))
    assert expected > 50 * SmootherConfig().gyro_noise_density_radps_per_sqrt_hz ** 2 * 0.1
    added = np.diag(with_term[:3, :3] - without[:3, :3])
    np.testing.assert_allclose(added, expected, rtol=0.05)
    vel_w, vel_wo = np.diag(with_term[3:9, 3:9]), np.diag(without[3:9, 3:9])
    assert np.all(vel_w >= vel_wo) and np.all(vel_w < 1.01 * vel_wo)
    np.testing.assert_array_equal(with_term[9:, 9:], without[9:, 9:])


def _z_biased_trial_without_corners():
    """A 10 s swinging-shank trial whose displacements drift 1 cm/s in z, no corner in view
    (the height-landmark tests add the level observations)."""
    return make_swinging_shank_trial(
        10.0,
        displacement_sigma_m=0.002,
        displacement_bias_mps=(0.0, 0.01),
        corners=False,
        seed=5,
    )


@pytest.mark.parametrize("cls", [SlidingWindowSmoother, BatchSmoother])
def test_height_landmarks_bound_z_drift_and_leave_x_alone(cls) -> None:
    """A floor seen from every keyframe (a z-only landmark, LevelObservation) holds the
    camera height against displacements biased in z; with no corner in view it must not
    pull x (only its z row is weighted)."""
    from dataclasses import replace

    from vio_graph.types import LevelObservation

    tr = _z_biased_trial_without_corners()
    rng = np.random.default_rng(11)
    floor_z_m = -0.40
    levels = [
        [
            LevelObservation(
                float(t), 1, floor_z_m - float(xz[1]) + float(rng.normal(0.0, 0.002)), 0.002**2
            )
        ]
        for t, xz in zip(tr.frame_times_s, tr.camera_xz_true_m, strict=True)
    ]
    with_levels = replace(tr, observations=levels)
    idx = np.flatnonzero(tr.is_keyframe)
    err = {}
    for name, trial in (("without", tr), ("with", with_levels)):
        cfg = SmootherConfig(factors=FactorFamilies(height_landmarks=True))
        s = cls(cfg, trial.imu_T_cam)
        feed(trial, s)
        xz = np.array([e.camera_xz_m for e in s.keyframe_estimates(with_covariance=False)])
        err[name] = xz - trial.camera_xz_true_m[idx]
    z_without, z_with = rms(err["without"][:, 1]), rms(err["with"][:, 1])
    assert z_without > 0.02  # 1 cm/s of z bias over 10 s
    # (the batch keeps every biased displacement: a compromise, ~5 mm; the window ~1.5 mm)
    assert z_with < 0.01 and z_with < 0.2 * z_without
    # x: a height says nothing about x; only the IMU's x-z coupling moves it (a few mm)
    assert rms(err["with"][:, 0]) < rms(err["without"][:, 0]) + 0.003


def test_shipped_height_landmark_config_keeps_one_floor_the_filter_split() -> None:
    """configs/smoother_height_landmarks.yaml (height landmarks, the graph's association) on
    the 10 s trial whose displacements drift 1 cm/s in z, a floor at z = -0.40 m seen from
    every frame but handed under two filter ids in turn (the filter's split of one floor,
    docs/generalisation.md): the graph makes one floor landmark, within 1 cm of the floor's
    height (the biased displacements pull the whole path and the floor with it by a few mm),
    and the camera height stays within 1 cm rms; without the floor it drifts by centimetres.
    The filter's ids would have made two floors."""
    from dataclasses import replace
    from pathlib import Path

    from vio_graph.config import load_config
    from vio_graph.types import LandmarkKey, LevelObservation

    path = Path(__file__).resolve().parents[1] / "configs" / "smoother_height_landmarks.yaml"
    shipped = load_config(path).smoother
    assert shipped.factors.height_landmarks
    assert shipped.factors.height_landmark_association == "graph"
    tr = _z_biased_trial_without_corners()
    rng = np.random.default_rng(11)
    floor_z_m = -0.40
    levels = [
        [
            LevelObservation(
                float(t), 7 + k % 2, floor_z_m - float(xz[1]) + rng.normal(0, 2e-3), 4e-6
            )
        ]
        for k, (t, xz) in enumerate(zip(tr.frame_times_s, tr.camera_xz_true_m, strict=True))
    ]
    idx = np.flatnonzero(tr.is_keyframe)
    z_err = {}
    for name, trial in (("floor", replace(tr, observations=levels)), ("no floor", tr)):
        s = BatchSmoother(shipped, trial.imu_T_cam)
        feed(trial, s)
        xz = np.array([e.camera_xz_m for e in s.keyframe_estimates(with_covariance=False)])
        z_err[name] = xz[:, 1] - tr.camera_xz_true_m[idx, 1]
        if name == "floor":
            nodes = [k for k in s._builder._landmark_of if k.kind == "level"]
            assert nodes == [LandmarkKey("level", 0)]  # one floor, one landmark
            assert s._result is not None
            floor = s._result.atPose3(s._builder._landmark_of[nodes[0]]).translation()[2]
            assert floor == pytest.approx(floor_z_m, abs=0.01)
    assert rms(z_err["no floor"]) > 0.02
    assert rms(z_err["floor"]) < 0.01
    by_filter = BatchSmoother(
        SmootherConfig(factors=FactorFamilies(height_landmarks=True)), tr.imu_T_cam
    )
    feed(replace(tr, observations=levels), by_filter)
    assert sorted(k.id for k in by_filter._builder._landmark_of if k.kind == "level") == [7, 8]


def test_frame_record_hands_level_observations_only_when_asked() -> None:
    from vio_graph.protocol import FrameRecord
    from vio_graph.types import LevelObservation

    lv = (LevelObservation(1.0, 3, -0.4, 4e-6), LevelObservation(1.0, 4, -0.25, 1e-6))
    corner = CornerObservation(1.0, 0, np.array([0.5, -0.3]), np.eye(2) * 1e-6)
    rec = FrameRecord(
        estimate=None,  # type: ignore[arg-type]  (not read by observations())
        frontend=None,  # type: ignore[arg-type]
        displacement=None,
        corner=corner,
        stance=None,
        R_world_imu=np.eye(3),
        shank_pitch_imu_rad=0.0,
        shank_pitch_chain_rad=0.0,
        ankle_rad=0.0,
        in_stance=False,
        levels=lv,
    )
    assert rec.observations() == [corner, lv[1]]  # the better-measured surface only
    assert rec.observations(levels=False) == [corner]


@pytest.mark.parametrize("cls", [SlidingWindowSmoother, BatchSmoother])
def test_graph_association_refuses_a_surface_the_filter_misassociated(cls) -> None:
    """For 1 s of a 10 s trial the camera sees a tread 15 cm above the floor, and the
    filter hands it with the floor's id (a wrong association). With the filter's ids the
    graphs pull the camera towards it; associated by the graph's own height
    (``height_landmark_association`` 'graph'), the tread is a landmark of its own and the
    height stays within 1 mm of the trial with every surface associated right."""
    from dataclasses import replace

    from vio_graph.types import LevelObservation

    tr = _z_biased_trial_without_corners()
    floor_z_m, tread_z_m = -0.40, -0.25

    def levels(wrong: bool) -> list[list[LevelObservation]]:
        rng = np.random.default_rng(11)  # the same noise in every case
        out = []
        for t, xz in zip(tr.frame_times_s, tr.camera_xz_true_m, strict=True):
            on_tread = 4.0 <= t < 5.0
            z = tread_z_m if on_tread else floor_z_m
            rel = z - float(xz[1]) + float(rng.normal(0.0, 0.002))
            level_id = 1 if (wrong or not on_tread) else 2
            out.append([LevelObservation(float(t), level_id, rel, 0.002**2)])
        return out

    idx = np.flatnonzero(tr.is_keyframe)

    def z_rms(association: str, wrong: bool) -> float:
        cfg = SmootherConfig(
            factors=FactorFamilies(height_landmarks=True, height_landmark_association=association)
        )
        s = cls(cfg, tr.imu_T_cam)
        feed(replace(tr, observations=levels(wrong)), s)
        xz = np.array([e.camera_xz_m for e in s.keyframe_estimates(with_covariance=False)])
        return rms(xz[:, 1] - tr.camera_xz_true_m[idx, 1])

    right = z_rms("filter", wrong=False)
    assert right < 0.005
    # the wrong id pulls: window 0.9 -> 5.8 mm, batch 3.7 -> 42 mm
    assert z_rms("filter", wrong=True) > right + 0.004
    assert z_rms("graph", wrong=True) < right + 0.001


def test_graph_level_association_gate() -> None:
    """The graph's association: nearest landmark within the gate and clearly nearest, else a
    new one; the smoother's estimates move the landmarks; an unknown kernel is refused."""
    from vio_graph.smoother.graph import _GraphLevel
    from vio_graph.types import LandmarkKey

    cfg = SmootherConfig(
        factors=FactorFamilies(height_landmarks=True, height_landmark_association="graph")
    )
    b = KeyframeGraphBuilder(cfg, np.eye(4))
    a = b._graph_level_key(-0.40)
    assert a == LandmarkKey("level", 0)
    b._graph_levels[1] = _GraphLevel(a, -0.40)
    assert b._graph_level_key(-0.42) == a  # 2 cm: the same floor
    assert b._graph_level_key(-0.36) == LandmarkKey("level", 1)  # 4 cm: beyond the gate
    assert b._graph_levels[1].z_m == -0.42  # it follows the surface
    b._graph_levels[2] = _GraphLevel(LandmarkKey("level", 1), -0.37)
    assert b._graph_level_key(-0.395) == LandmarkKey("level", 2)  # not clearly nearest
    b.set_level_heights({1: -0.30})
    assert b._graph_levels[1].z_m == -0.30
    with pytest.raises(ValidationError):
        SmootherConfig(height_landmark_kernel="tukey")
    kernel = SmootherConfig(height_landmark_kernel="geman_mcclure")
    noise = robust_noise(kernel, gtsam.noiseModel.Isotropic.Sigma(1, 0.002), "geman_mcclure", 3.0)
    assert isinstance(noise, gtsam.noiseModel.Robust)


@pytest.mark.parametrize("rate_hz", [50.0, 100.0])
def test_substeps_cut_the_first_moment_error_n_squared_fold(rate_hz: float) -> None:
    """A specific force rising linearly, a(t) = a0 + j t, no rotation: the step means are
    exact, so the preintegrated velocity is too, but GTSAM's v dt + a dt^2 / 2 per step
    overshoots the position by j h^3 / 12 per step of length h, j T h^2 / 12 over T; with n
    sub-steps (SmootherConfig.preintegration_substeps) by j T h^2 / (12 n^2)."""
    h = 1.0 / rate_hz
    t = h * np.arange(40)
    a0, j = np.array([1.0, 0.0, -2.0]), np.array([30.0, 0.0, 80.0])  # m/s^2, m/s^3
    a = a0 + j * t[:, None]
    g = np.zeros_like(a)
    t0, t1 = t[5], t[15]
    T = t1 - t0
    cfg = SmootherConfig()
    for n in (1, 2, 4):
        a_m, g_m, dt = common_frame_samples(t, a, g, t0, t1, n)
        assert dt.size == 10 * n
        assert np.isclose(dt.sum(), T)
        pim = gtsam.PreintegratedCombinedMeasurements(
            make_preintegration_params(cfg), gtsam.imuBias.ConstantBias()
        )
        for k in range(dt.size):
            pim.integrateMeasurement(a_m[k], g_m[k], float(dt[k]))
        a_t0 = a0 + j * t0
        exact_p = a_t0 * T**2 / 2 + j * T**3 / 6
        exact_v = a_t0 * T + j * T**2 / 2
        np.testing.assert_allclose(pim.deltaVij(), exact_v, atol=1e-9)
        np.testing.assert_allclose(
            pim.deltaPij() - exact_p, j * T * h**2 / (12 * n**2), rtol=1e-6, atol=1e-12
        )


def test_substeps_must_be_positive() -> None:
    t, a, g = _jittered_shank_imu(20, seed=2)
    with pytest.raises(EstimationError):
        common_frame_samples(t, a, g, t[3], t[9], 0)
    with pytest.raises(ValidationError):
        SmootherConfig(preintegration_substeps=0)
