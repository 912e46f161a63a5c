"""The fixed-lag smoother's iSAM2 settings.

Factorisation: the setting reaches GTSAM, Cholesky gives the QR answer to well below a
millimetre, and a Cholesky update that finds the system indeterminate is redone in QR
(``smoother.fixed_lag_qr_fallback``) instead of ending the smoother. Marginalisation in
batches (``smoother.marginalization_slack_s``): the window holds between lag and lag + slack,
our mirror of it agrees with GTSAM's, and the estimates stay those of the plain window."""

from __future__ import annotations

import gtsam
import numpy as np
import pytest
from pydantic import ValidationError

from vio_graph.errors import EstimationError
from vio_graph.smoother.config import SmootherConfig
from vio_graph.smoother.sliding_window import SlidingWindowSmoother, isam2_params
from vio_graph.smoother.synthetic import feed, make_swinging_shank_trial

INDETERMINANT = "An indeterminant linear system was detected while working near variable x7"


def _xz(s: SlidingWindowSmoother) -> np.ndarray:
    return np.array([e.camera_xz_m for e in s.keyframe_estimates(with_covariance=False)])


class _FailingOnce:
    """Stands in for GTSAM's smoother: the ``at``-th update raises the Cholesky failure,
    before (``taken=False``) or after (``taken=True``) the real smoother took it in."""

    def __init__(
        self,
        inner: gtsam.IncrementalFixedLagSmoother,
        at: int,
        taken: bool,
        message: str = INDETERMINANT,
    ) -> None:
        self.inner, self.at, self.taken, self.calls = inner, at, taken, 0
        self.message = message

    def update(self, *args):
        self.calls += 1
        if self.calls == self.at:
            if self.taken:
                self.inner.update(*args)
            raise RuntimeError(self.message)
        return self.inner.update(*args)

    def __getattr__(self, name):
        return getattr(self.inner, name)


@pytest.fixture(scope="module")
def trial():
    return make_swinging_shank_trial(4.0, displacement_sigma_m=0.002, seed=3)


def test_factorization_setting_reaches_isam2_and_is_validated():
    for f in ("QR", "CHOLESKY"):
        cfg = SmootherConfig(fixed_lag_factorization=f, relinearize_threshold=0.07)
        s = SlidingWindowSmoother(cfg, np.eye(4))
        p = s._smoother.params()
        assert p.getFactorization() == f
        assert p.relinearizeSkip == 1
        assert isam2_params(cfg, "QR").getFactorization() == "QR"
    with pytest.raises(ValidationError):
        SmootherConfig(fixed_lag_factorization="LDL")
    with pytest.raises(ValidationError):
        SmootherConfig(fixed_lag_qr_fallback="maybe")


def test_cholesky_gives_the_qr_estimates(trial):
    out = {}
    for f in ("QR", "CHOLESKY"):
        s = SlidingWindowSmoother(SmootherConfig(fixed_lag_factorization=f), trial.imu_T_cam)
        feed(trial, s)
        out[f] = _xz(s)
        assert s.qr_fallback_at_s is None
    assert np.abs(out["CHOLESKY"] - out["QR"]).max() < 1e-5  # m


@pytest.mark.parametrize(
    ("taken", "message"),
    [(False, INDETERMINANT), (True, INDETERMINANT), (False, "")],
    ids=["before", "after", "empty-message"],
)
def test_failed_cholesky_update_is_redone_in_qr(trial, taken, message):
    """An indeterminate system, before or after GTSAM took the update in, and a failure with
    an empty message (GTSAM 4.3 raised one on a descent's window of displacements alone):
    the window is rebuilt in QR and the run goes on."""
    cfg = SmootherConfig(fixed_lag_factorization="CHOLESKY")
    ref = SlidingWindowSmoother(cfg, trial.imu_T_cam)
    feed(trial, ref)
    s = SlidingWindowSmoother(cfg, trial.imu_T_cam)
    at = 25  # keyframe 24: the window (2 s at 10 Hz) is full and keyframes leave it
    s._smoother = _FailingOnce(s._smoother, at, taken, message)
    feed(trial, s)
    kf_t = [e.timestamp_s for e in s.keyframe_estimates(with_covariance=False)]
    assert s.qr_fallback_at_s == pytest.approx(kf_t[at - 1])
    assert isinstance(s._smoother, gtsam.IncrementalFixedLagSmoother)
    assert s._smoother.params().getFactorization() == "QR"
    assert s.live_keys() == s.smoother_keys()
    assert len(s.update_times_ms) == len(kf_t)
    # the rebuilt window solves the same problem (one batch step from the linearisation
    # point instead of the incremental one): the same keyframes to well below a millimetre
    assert np.abs(_xz(s) - _xz(ref)).max() < 1e-3
    assert s.report().metrics["smoother_qr_fallback_at_s"] == s.qr_fallback_at_s


def test_without_fallback_or_for_other_errors_the_update_fails(trial):
    cfg = SmootherConfig(fixed_lag_factorization="CHOLESKY", fixed_lag_qr_fallback=False)
    s = SlidingWindowSmoother(cfg, trial.imu_T_cam)
    s._smoother = _FailingOnce(s._smoother, 5, False)
    with pytest.raises(EstimationError, match="indeterminant"):
        feed(trial, s)
    s = SlidingWindowSmoother(SmootherConfig(fixed_lag_factorization="QR"), trial.imu_T_cam)
    s._smoother = _FailingOnce(s._smoother, 5, False)
    with pytest.raises(EstimationError, match="indeterminant"):
        feed(trial, s)


def test_tail_equals_tells_whether_a_graph_ends_with_another():
    from vio_graph.smoother.sliding_window import _tail_equals

    noise = gtsam.noiseModel.Isotropic.Sigma(3, 1.0)
    a = gtsam.PriorFactorVector(1, np.zeros(3), noise)
    b = gtsam.PriorFactorVector(2, np.ones(3), noise)
    g, tail = gtsam.NonlinearFactorGraph(), gtsam.NonlinearFactorGraph()
    g.add(a)
    g.add(b)
    tail.add(gtsam.PriorFactorVector(2, np.ones(3), noise))
    assert _tail_equals(g, tail)
    tail.add(a)
    assert not _tail_equals(g, tail)
    tail.add(b)
    assert not _tail_equals(g, tail)  # longer than the graph


def test_marginalization_in_batches_keeps_the_window_between_lag_and_lag_plus_slack(trial):
    slack = 0.3
    out = {}
    for sl in (0.0, slack):
        cfg = SmootherConfig(window_s=1.0, marginalization_slack_s=sl)
        s = SlidingWindowSmoother(cfg, trial.imu_T_cam)
        lag = s.lag_s
        spans, leaving_updates = [], 0
        consume = s._consume

        def checked(u, s=s, consume=consume, spans=spans):
            nonlocal leaving_updates
            before = s.live_keys()
            consume(u)
            live = s.live_keys()
            assert live == s.smoother_keys()
            leaving_updates += bool(before - live)
            times = list(s._live.values())
            spans.append(max(times) - min(times))

        s._consume = checked
        feed(trial, s)
        out[sl] = _xz(s)
        spans = np.asarray(spans)
        assert spans.max() <= lag + sl + 1e-9
        if sl == 0.0:
            n_plain = leaving_updates
            assert spans[-10:].max() <= lag
        else:
            # full windows reach past the lag; keys leave in batches, in fewer updates
            assert spans.max() > lag
            assert leaving_updates < 0.5 * n_plain
    assert np.abs(out[slack] - out[0.0]).max() < 2e-3  # m
