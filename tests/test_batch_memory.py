"""The batch smoother's memory-lean solve (Cholesky with a QR fallback) gives the QR answer,
and the memory helpers of a run change no result (docs/performance-log.md, Batch memory)."""

from __future__ import annotations

from types import SimpleNamespace

import gtsam
import numpy as np
import pytest

import vio_graph.smoother.batch as batch_mod
from vio_graph.memory import return_free_heap
from vio_graph.recording.reader import Recording
from vio_graph.safety.config import SafetyConfig
from vio_graph.safety.online import SafetyLog, SafetyMonitor
from vio_graph.smoother.batch import BatchSmoother, every_step_first_try
from vio_graph.smoother.config import SmootherConfig
from vio_graph.smoother.synthetic import feed, make_swinging_shank_trial


def _solved(factorization: str, **trial) -> BatchSmoother:
    s = BatchSmoother(SmootherConfig(batch_factorization=factorization), np.eye(4))
    feed(
        make_swinging_shank_trial(
            duration_s=4.0,
            seed=3,
            displacement_sigma_m=0.002,
            observation_sigma_m=0.003,
            accel_bias_mps2=(0.05, 0.0, -0.03),
            **trial,
        ),
        s,
    )
    s.solve()
    return s


def _poses(s: BatchSmoother) -> tuple[np.ndarray, np.ndarray]:
    est = s.keyframe_estimates(with_covariance=False)
    return np.array([e.camera_xz_m for e in est]), np.array([e.R_world_imu for e in est])


@pytest.mark.parametrize("outliers", [(), (40,)])
def test_cholesky_batch_gives_the_qr_keyframes(outliers):
    """Noisy displacements, corners, an accelerometer bias, and (second case) a one-step-off
    displacement the robust kernel down-weights: the Cholesky solve ends on the QR solve's
    keyframes to rounding (< 1e-9 m, < 1e-9 rad), with no fallback."""
    qr = _solved("QR", outlier_frames=outliers)
    ch = _solved("CHOLESKY", outlier_frames=outliers)
    assert ch.qr_fallbacks == 0
    assert ch.solve_iterations == qr.solve_iterations
    (xq, rq), (xc, rc) = _poses(qr), _poses(ch)
    assert len(xq) > 30
    assert np.max(np.abs(xc - xq)) < 1e-9
    assert np.max(np.abs(rc - rq)) < 1e-9
    # (the two differ in the last bits: ~1e-15 m here, so the bound above is a real check)
    assert qr.graph.error(qr.solve()) == pytest.approx(ch.graph.error(ch.solve()), rel=1e-9)


def test_a_retried_step_falls_back_to_the_qr_answer(monkeypatch):
    """When the Cholesky run retried a step, the solve is done again with QR and its answer
    is QR's bit for bit (reported as batch_qr_fallbacks)."""
    qr = _solved("QR")
    monkeypatch.setattr(batch_mod, "every_step_first_try", lambda opt, params: False)
    ch = _solved("CHOLESKY")
    assert ch.qr_fallbacks == 1
    assert ch.report().metrics["batch_qr_fallbacks"] == 1
    (xq, rq), (xc, rc) = _poses(qr), _poses(ch)
    assert np.array_equal(xq, xc) and np.array_equal(rq, rc)


def test_no_fallback_without_cholesky_or_when_switched_off(monkeypatch):
    monkeypatch.setattr(batch_mod, "every_step_first_try", lambda opt, params: False)
    assert _solved("QR").qr_fallbacks == 0
    s = BatchSmoother(SmootherConfig(batch_qr_fallback=False), np.eye(4))
    feed(make_swinging_shank_trial(duration_s=2.0, seed=1), s)
    s.solve()
    assert s.qr_fallbacks == 0


def test_every_step_first_try_reads_the_lambda_trace():
    """lambda_initial 1e-5, factor 10: 4 iterations without a retry end at 1e-9; one retry
    (x10, and one accepted step fewer) leaves 1e-7; a run that gave up ends higher still."""
    params = gtsam.LevenbergMarquardtParams()
    run = lambda n, lam: SimpleNamespace(iterations=lambda: n, lambda_=lambda: lam)  # noqa: E731
    lam = 1e-5
    for _ in range(4):
        lam /= 10.0
    assert every_step_first_try(run(4, lam), params)
    assert not every_step_first_try(run(4, lam * 100.0), params)
    assert not every_step_first_try(run(4, lam * 10.0), params)
    assert every_step_first_try(run(0, 1e-5), params)
    params.setUseFixedLambdaFactor(False)  # lambda then follows the gain ratio: no trace
    assert not every_step_first_try(run(4, lam), params)


def test_every_step_first_try_on_a_real_lm_run():
    """A well-posed problem converges without a retry, and the lambda trace says so."""
    from gtsam.symbol_shorthand import X

    graph = gtsam.NonlinearFactorGraph()
    graph.add(gtsam.PriorFactorPose3(X(0), gtsam.Pose3(), gtsam.noiseModel.Isotropic.Sigma(6, 1)))
    values = gtsam.Values()
    values.insert(X(0), gtsam.Pose3(gtsam.Rot3.Rz(0.3), np.array([1.0, 2.0, 3.0])))
    params = gtsam.LevenbergMarquardtParams()
    opt = gtsam.LevenbergMarquardtOptimizer(graph, values, params)
    opt.optimize()
    assert opt.iterations() >= 1 and every_step_first_try(opt, params)
    assert opt.error() < 1e-12


def test_batch_safety_replay_is_kept_as_rows(tmp_path):
    """replay_safety keeps one row a frame (SafetyLog) holding exactly what the monitor
    returned: every field of every frame of a replay of the monitor on a short path. The
    replay's monitor skips the predicted clearance (the metrics never score it), so the
    reference is a monitor built the same way, and that field is NaN in every row."""
    from vio_graph.evaluation.safety import replay_safety

    rng = np.random.default_rng(4)
    n = 60
    t = np.arange(n) / 30.0
    cam = np.c_[0.02 * np.arange(n), 0.3 + 0.01 * np.sin(np.arange(n) / 5.0)]
    path = {"camera": cam, "heel": cam - [0.05, 0.45], "toe": cam - [-0.15, 0.47]}
    cov = [np.eye(2) * 1e-6] * n
    stance = [bool(k % 20 < 8) for k in range(n)]
    xs = np.linspace(0.1, 0.8, 200)
    profiles = {
        k: np.c_[xs, -0.4 + 0.17 * (xs + 0.02 * k > 0.5) + 1e-4 * rng.standard_normal(200)]
        for k in range(0, n, 3)
    }
    cfg = SafetyConfig()
    out = replay_safety(cfg, t, path, cov, stance, profiles)
    assert isinstance(out, SafetyLog) and len(out) == n
    mon = SafetyMonitor(cfg, predict_clearance=False)
    ref = [
        mon.update(
            float(t[k]), cam[k], cov[k], path["heel"][k], path["toe"][k], stance[k], profiles.get(k)
        )
        for k in range(n)
    ]
    assert any(r is not None for r in ref)
    for a, b in zip(out, ref, strict=True):
        assert (a is None) == (b is None)
        if b is None:
            continue
        for name, v in vars(b).items():
            w = getattr(a, name)
            assert np.array_equal(np.asarray(w), np.asarray(v), equal_nan=True), name
        assert np.isnan(a.predicted_min_clearance_m)


def test_memory_helpers_change_nothing_read(tmp_path):
    """Handing back the depth maps' pages and the heap's free pages leaves every frame and
    every live array as it was."""
    rec = Recording.open("data/sample")
    rec.release_frame_pages()  # before any frame: a no-op
    before = [rec.frame(i).depth_m.copy() for i in (0, 5, 17)]
    keep = np.arange(1_000_000, dtype=float)
    rec.release_frame_pages()
    assert isinstance(return_free_heap(), bool)
    after = [rec.frame(i).depth_m for i in (0, 5, 17)]
    assert all(np.array_equal(a, b) for a, b in zip(before, after, strict=True))
    assert keep[-1] == 999_999.0 and keep.sum() == 999_999 * 1_000_000 / 2
