"""The SP-ESKF's closed-form update (2x2 inverse, P - K H P, block-wise augmentation) gives
the results of the numpy reference it replaced (LAPACK solves, Joseph form, J P J^T): same
accept / refuse decisions, the same state and covariance to rounding, over random sequences
of every measurement kind; the closed-form gate distance equals the LAPACK one."""

from __future__ import annotations

import numpy as np
import pytest

from vio_graph.errors import EstimationError
from vio_graph.filter import FilterConfig, SagittalEskf
from vio_graph.filter.gating import mahalanobis2_2d
from vio_graph.geometry import GRAVITY_MPS2
from vio_graph.types import Displacement2D, ImuSample, LandmarkKey

UPRIGHT = np.array([1.0, 0.0, 0.0, 0.0])


def _imu(t: float, rng: np.random.Generator) -> ImuSample:
    """An upright IMU with a little random acceleration and pitch rate."""
    acc = np.array([rng.normal(0, 0.5), 0.0, GRAVITY_MPS2 + rng.normal(0, 0.5)])
    return ImuSample(t, acc, np.array([0.0, rng.normal(0, 0.3), 0.0]), UPRIGHT)


def _run(seed: int, reference: bool) -> tuple[SagittalEskf, list[bool]]:
    """1 s at 100 Hz with a frame every 3 samples: a displacement (sometimes an outlier, so
    the gate refuses), corner landmarks, height landmarks, a velocity, drops."""
    rng = np.random.default_rng(seed)
    f = SagittalEskf(FilterConfig())
    if reference:  # the numpy reference paths on this instance only
        f._correct = f._correct_reference  # type: ignore[method-assign]
        f.displacement_d2 = f.displacement_d2_reference  # type: ignore[method-assign]
        f._augment = f._augment_reference  # type: ignore[method-assign]
    f.initialise(0.0, (0.0, 0.0))
    outcomes: list[bool] = []
    t_prev = 0.0
    for k in range(1, 101):
        t = k / 100.0
        f.propagate(_imu(t, rng))
        if k % 3:
            continue
        delta = rng.normal(0, 0.01, 2) + (0.3 if rng.uniform() < 0.15 else 0.0)
        d = Displacement2D(t_prev, t, delta, np.diag(rng.uniform(1e-6, 1e-5, 2)))
        d2 = f.displacement_d2(d)
        d2_moved = f.displacement_d2(d, np.eye(4) * 1e-4, delta + 0.01)
        outcomes.append(bool(d2 is not None and d2_moved is not None))
        outcomes.append(f.update_displacement(d))
        t_prev = t
        for c in range(int(rng.integers(1, 4))):
            key = LandmarkKey("corner", c)
            rel = np.array([0.5 + 0.1 * c, -0.3]) - f.state.p_xz_m + rng.normal(0, 0.003, 2)
            outcomes.append(f.update_landmark(key, rel, np.eye(2) * 1e-5, t))
        h = LandmarkKey("level", k % 2)
        rel_z = -0.4 - f.state.p_xz_m[1] + rng.normal(0, 0.002)
        outcomes.append(f.update_height_landmark(h, float(rel_z), 4e-6, t))
        outcomes.append(f.update_velocity(f.state.v_xz_mps + 0.01, np.eye(2) * 1e-3, t))
        if k % 15 == 0:
            f.drop_landmark(LandmarkKey("corner", 2))
    return f, outcomes


@pytest.mark.parametrize("seed", [0, 1, 2, 3])
def test_closed_form_update_equals_the_reference(seed: int) -> None:
    fast, out_fast = _run(seed, reference=False)
    ref, out_ref = _run(seed, reference=True)
    assert out_fast == out_ref
    assert False in out_ref and True in out_ref  # the gate refused some, accepted others
    assert fast._aug_keys == ref._aug_keys
    np.testing.assert_allclose(fast._x, ref._x, rtol=0, atol=1e-12)
    np.testing.assert_allclose(fast._P, ref._P, rtol=0, atol=1e-15)
    for key in ref._aug_keys:
        np.testing.assert_allclose(fast._aug_xz[key], ref._aug_xz[key], rtol=0, atol=1e-12)


@pytest.mark.parametrize("seed", [0, 1, 2, 3])
def test_compiled_update_equals_the_reference(seed: int, monkeypatch: pytest.MonkeyPatch) -> None:
    """The updates and gate distances compiled (filter/compiled_update.py, with the compiled
    propagation: VIO_GRAPH_COMPILED=1) against the numpy references (LAPACK, Joseph form):
    the same accept / refuse decisions, the same state and covariance to rounding."""
    from vio_graph.frontend import icp as icp_module

    monkeypatch.setenv(icp_module.COMPILED_ENV, "1")
    fast, out_fast = _run(seed, reference=False)
    assert fast._update_kernels is not None
    monkeypatch.setenv(icp_module.COMPILED_ENV, "0")
    ref, out_ref = _run(seed, reference=True)
    assert ref._update_kernels is None
    assert out_fast == out_ref
    assert False in out_ref and True in out_ref
    assert fast._aug_keys == ref._aug_keys
    np.testing.assert_allclose(fast._x, ref._x, rtol=0, atol=1e-12)
    np.testing.assert_allclose(fast._P, ref._P, rtol=0, atol=1e-15)
    for key in ref._aug_keys:
        np.testing.assert_allclose(fast._aug_xz[key], ref._aug_xz[key], rtol=0, atol=1e-12)


def test_compiled_gate_distance_and_singular_covariance(monkeypatch: pytest.MonkeyPatch) -> None:
    """The compiled gate distance equals the LAPACK one; a singular innovation covariance
    raises in the compiled update as in the numpy one."""
    from vio_graph.frontend import icp as icp_module

    monkeypatch.setenv(icp_module.COMPILED_ENV, "1")
    f, _ = _run(5, reference=False)
    assert f._update_kernels is not None
    t = f.state.timestamp_s
    f.clone_position(t - 0.02)
    rng = np.random.default_rng(7)
    for _ in range(20):
        d = Displacement2D(t - 0.02, t, rng.normal(0, 0.02, 2), np.diag(rng.uniform(1e-6, 1e-4, 2)))
        extra = None if rng.uniform() < 0.5 else np.diag(rng.uniform(0, 1e-3, 4))
        moved = None if rng.uniform() < 0.5 else rng.normal(0, 0.02, 2)
        got = f.displacement_d2(d, extra, moved)
        want = f.displacement_d2_reference(d, extra, moved)
        assert got is not None and want is not None
        assert got == pytest.approx(want, rel=1e-10)
    n = f._P.shape[0]
    H = np.zeros((2, n))  # observes nothing: S = V = 0
    with pytest.raises(EstimationError, match="singular"):
        f._correct(np.ones(2), H, np.zeros((2, 2)))
    with pytest.raises(EstimationError, match="singular"):
        f._correct(np.ones(1), H[:1], np.zeros((1, 1)), dof=1)


def test_gate_distance_equals_the_reference() -> None:
    f, _ = _run(5, reference=False)
    t = f.state.timestamp_s
    f.clone_position(t - 0.02)
    rng = np.random.default_rng(7)
    for _ in range(20):
        d = Displacement2D(t - 0.02, t, rng.normal(0, 0.02, 2), np.diag(rng.uniform(1e-6, 1e-4, 2)))
        extra = None if rng.uniform() < 0.5 else np.diag(rng.uniform(0, 1e-3, 4))
        moved = None if rng.uniform() < 0.5 else rng.normal(0, 0.02, 2)
        got = f.displacement_d2(d, extra, moved)
        want = f.displacement_d2_reference(d, extra, moved)
        assert got is not None and want is not None
        assert got == pytest.approx(want, rel=1e-10)


@pytest.mark.parametrize("compiled", ["0", "1"])
def test_gate_distance_pair_is_two_gate_distances(
    compiled: str, monkeypatch: pytest.MonkeyPatch
) -> None:
    """displacement_d2_pair (the frame-stamp test's two hypotheses) gives the floats of two
    displacement_d2 calls, with and without the compiled updates, and the reference's to
    rounding; None where displacement_d2 says None."""
    from vio_graph.frontend import icp as icp_module

    monkeypatch.setenv(icp_module.COMPILED_ENV, compiled)
    f, _ = _run(6, reference=False)
    assert (f._update_kernels is not None) == (compiled == "1")
    t = f.state.timestamp_s
    f.clone_position(t - 0.02)
    rng = np.random.default_rng(9)
    for _ in range(20):
        d = Displacement2D(t - 0.02, t, rng.normal(0, 0.02, 2), np.diag(rng.uniform(1e-6, 1e-4, 2)))
        moved = rng.normal(0, 0.02, 2)
        pair = f.displacement_d2_pair(d, moved)
        assert pair == (f.displacement_d2(d), f.displacement_d2(d, delta_xz_m=moved))
        ref = f.displacement_d2_pair_reference(d, moved)
        assert ref is not None and pair == pytest.approx(ref, rel=1e-10)
    stale = Displacement2D(t - 0.5, t, np.zeros(2), np.eye(2) * 1e-6)  # not on the clone
    assert f.displacement_d2_pair(stale, np.zeros(2)) is None
    assert f.displacement_d2(stale) is None


def test_non_finite_measurements_are_refused() -> None:
    f = SagittalEskf()
    f.initialise(0.0, (0.0, 0.0))
    with pytest.raises(EstimationError, match="finite"):
        f.update_landmark(LandmarkKey("corner", 0), (np.nan, 0.0), np.eye(2))
    with pytest.raises(EstimationError, match="finite"):
        f.update_landmark(LandmarkKey("corner", 0), (0.0, 0.0), np.diag([np.inf, 1.0]))


def test_closed_form_mahalanobis_equals_the_solve() -> None:
    rng = np.random.default_rng(3)
    for _ in range(200):
        A = rng.normal(0, 1, (2, 2))
        S = A @ A.T + np.eye(2) * 10.0 ** rng.uniform(-8, 0)
        y = rng.normal(0, 1, 2)
        assert mahalanobis2_2d(S, y) == pytest.approx(float(y @ np.linalg.solve(S, y)), rel=1e-9)
    with pytest.raises(EstimationError, match="singular"):
        mahalanobis2_2d(np.ones((2, 2)), np.ones(2))


def test_gyro_interpolation_equals_np_interp() -> None:
    """AttitudeTracker.gyro_at (np.interp written out) equals the numpy form bit for bit:
    between samples, on their stamps, before the history and after the latest sample."""
    from vio_graph.filter.attitude import AttitudeTracker

    rng = np.random.default_rng(11)
    tracker = AttitudeTracker()
    stamps = np.cumsum(rng.uniform(0.008, 0.012, 40))
    for t in stamps:
        tracker.add(
            ImuSample(float(t), np.array([0.0, 0.0, GRAVITY_MPS2]), rng.normal(0, 1, 3), UPRIGHT)
        )
        kept = np.array([r[0] for r in tracker._recent])
        queries = [*kept, *rng.uniform(kept[0] - 0.02, kept[-1] + 0.02, 20)]
        for q in queries:
            assert np.array_equal(tracker.gyro_at(float(q)), tracker.gyro_at_reference(float(q)))


def test_state_accessors_equal_the_snapshot() -> None:
    """status, cov_position_m2, cov_velocity_m2ps2 and variance read what :attr:`state`
    copies, without the snapshot."""
    f = SagittalEskf()
    assert f.status == f.state.status
    f, _ = _run(2, reference=False)
    state = f.state
    assert f.status == state.status
    assert np.array_equal(f.cov_position_m2(), state.cov_position_m2)
    assert np.array_equal(f.cov_velocity_m2ps2(), state.P[2:4, 2:4])
    assert [f.variance(i) for i in range(8)] == np.diag(state.P).tolist()
    with pytest.raises(EstimationError, match="index"):
        f.variance(8)


def test_compiled_augment_and_marginalise_equal_the_numpy_blocks() -> None:
    """The compiled augmentation covariance and block removal (filter/compiled_update.py)
    equal _augment's block-wise numpy formulation and _marginalise's take, bit for bit."""
    from vio_graph.filter import compiled_update

    rng = np.random.default_rng(17)
    for _ in range(300):
        m = 8 + 2 * int(rng.integers(0, 8))
        A = rng.normal(size=(m, m))
        P = A @ A.T + 1e-9 * rng.normal(size=(m, m))  # symmetric to rounding only
        dt = float(rng.uniform(-0.01, 0.01))
        extra = rng.normal(size=(2, 2)) * 1e-4
        Ps = 0.5 * (P + P.T)
        rows = Ps[0:2] + dt * Ps[2:4]
        want = np.empty((m + 2, m + 2))
        want[:m, :m], want[m:, :m], want[:m, m:] = Ps, rows, rows.T
        B = rows[:, 0:2] + dt * rows[:, 2:4] + extra
        want[m:, m:] = 0.5 * (B + B.T)
        assert np.array_equal(compiled_update.augmented(P, dt, extra), want)
        i = 8 + 2 * int(rng.integers(0, (m - 8) // 2)) if m > 8 else 0
        keep = np.concatenate((np.arange(i), np.arange(i + 2, m)))
        assert np.array_equal(compiled_update.without_block(P, i), P.take(keep, 0).take(keep, 1))
        # the clone replaced in one call: the removal, then the augmentation, bit for bit
        want = compiled_update.augmented(compiled_update.without_block(P, i), dt, extra)
        assert np.array_equal(compiled_update.recloned(P, i, dt, extra), want)
        want = compiled_update.augmented(P, dt, extra)  # no old clone (i < 0)
        assert np.array_equal(compiled_update.recloned(P, -1, dt, extra), want)


@pytest.mark.parametrize("compiled", ["0", "1"])
def test_displacement_update_after_its_gate_tests_is_the_same(
    compiled: str, monkeypatch: pytest.MonkeyPatch
) -> None:
    """update_displacement reuses H and V that the frame's gate tests (displacement_d2,
    displacement_d2_pair) built for the same displacement on the same state: the filter ends
    in the same state, bit for bit, as one whose updates come without the tests (also when
    the covariance was widened in between, and when the tests were for another
    displacement)."""
    from vio_graph.frontend import icp as icp_module

    monkeypatch.setenv(icp_module.COMPILED_ENV, compiled)

    def run(tests: bool) -> SagittalEskf:
        rng = np.random.default_rng(12)
        f = SagittalEskf(FilterConfig())
        f.initialise(0.0, (0.0, 0.0))
        t_prev = 0.0
        for k in range(1, 151):
            t = k / 100.0
            f.propagate(_imu(t, rng))
            if k % 3:
                continue
            delta = rng.normal(0, 0.01, 2) + (0.3 if rng.uniform() < 0.15 else 0.0)
            d = Displacement2D(t_prev, t, delta, np.diag(rng.uniform(1e-6, 1e-5, 2)))
            other = Displacement2D(t_prev, t, delta + 0.01, np.diag([2e-6, 3e-6]))
            mode = int(rng.integers(0, 4))
            if tests:
                if mode == 0:
                    f.displacement_d2_pair(d, delta + 0.005)
                elif mode == 1:
                    f.displacement_d2(d)
                    f.inflate_position_velocity(np.eye(4) * 1e-5)
                elif mode == 2:
                    f.displacement_d2(other)
            elif mode == 1:
                f.inflate_position_velocity(np.eye(4) * 1e-5)
            f.update_displacement(d)
            f.update_landmark(LandmarkKey("corner", k % 4), [0.4, -0.3], np.eye(2) * 1e-5, t)
            t_prev = t
        return f

    a, b = run(tests=True), run(tests=False)
    assert (a._update_kernels is not None) == (compiled == "1")
    assert a._n_acc == b._n_acc and a._n_rej == b._n_rej and a._n_acc > 20
    assert a._aug_keys == b._aug_keys and a._aug_xz == b._aug_xz
    assert np.array_equal(a._x, b._x) and np.array_equal(a._P, b._P)


def test_position_ahead_is_the_array_formula_bit_for_bit() -> None:
    """_position_ahead on Python floats: p + dt v + (dt^2 / 2) a as the array expression it
    replaced computes it, whether the acceleration is an array, a tuple or a view."""
    f = SagittalEskf(FilterConfig())
    f.initialise(0.0, (0.1, 0.2))
    rng = np.random.default_rng(4)
    for accel in (np.array([0.3, -9.1]), (0.3, -9.1), np.arange(4.0)[1:3]):
        f._accel_w_mps2 = accel
        for _ in range(200):
            f._x[:4] = rng.normal(0, 1, 4)
            dt = float(rng.normal(0, 0.01))
            want = f._x[0:2] + dt * f._x[2:4] + 0.5 * dt**2 * np.asarray(accel)
            assert np.array_equal(f._position_ahead(dt), want)


def test_stand_height_median_equals_numpy_median() -> None:
    """The stand surface's running median (estimator._median_finite, on Python floats)
    against np.median: the same float bit for bit on odd and even counts, ties, signed
    zeros and values that round when halved."""
    from vio_graph.estimator import _median_finite

    rng = np.random.default_rng(3)
    for case in range(500):
        values = rng.normal(-0.3, 0.05, int(rng.integers(1, 60)))
        if case % 3 == 0:
            values = np.round(values, 3)  # ties
        if case % 7 == 0:
            values[: values.size // 2] = -0.0 if case % 2 else 0.0
        if case % 11 == 0:
            values = np.nextafter(values, np.inf)  # odd last bits: halving the sum rounds
        got = _median_finite(values.tolist())
        want = float(np.median(values))
        assert np.float64(got).tobytes() == np.float64(want).tobytes()


def test_displacement_h_and_noise_are_the_array_formulas_bit_for_bit() -> None:
    """The displacement's and a landmark's H, V and the symmetrised covariance built on
    Python floats (eskf._clone_h, _landmark_h, _measurement_v, _cov2) are the arrays the
    numpy expressions they replaced give, signed zeros included."""
    from vio_graph.filter.eskf import _I2, _clone_h, _cov2, _landmark_h, _measurement_v

    rng = np.random.default_rng(11)
    for _ in range(300):
        n = 8 + 2 * int(rng.integers(1, 6))
        i = 8 + 2 * int(rng.integers(0, (n - 8) // 2))
        dt1 = float(rng.normal(0, 0.005))
        want_h = np.zeros((2, n))
        want_h[:, 0:2] = _I2
        want_h[:, 2:4] = dt1 * _I2
        want_h[:, i : i + 2] = -_I2
        got_h = _clone_h(n, dt1, i)
        assert np.array_equal(got_h, want_h)
        assert np.array_equal(np.signbit(got_h), np.signbit(want_h))
        want_h = np.zeros((2, n))
        want_h[:, 0:2] = -_I2
        want_h[:, 2:4] = -dt1 * _I2
        want_h[:, i : i + 2] = _I2
        got_h = _landmark_h(n, dt1, i)
        assert np.array_equal(got_h, want_h)
        assert np.array_equal(np.signbit(got_h), np.signbit(want_h))
        c = rng.normal(0, 1e-3, (2, 2))
        inflation, floor = float(rng.uniform(0.5, 3.0)), float(rng.uniform(0.0, 0.01))
        want_c = 0.5 * (c + c.T)
        assert np.array_equal(_cov2(c), want_c)
        want_v = inflation * want_c + floor**2 * _I2
        got_v = _measurement_v(c, inflation, floor)
        assert np.array_equal(got_v, want_v)
        assert np.array_equal(np.signbit(got_v), np.signbit(want_v))
    with pytest.raises(EstimationError):
        _cov2(np.array([[1.0, np.nan], [0.0, 1.0]]))
    with pytest.raises(EstimationError):
        _cov2(np.eye(3))
