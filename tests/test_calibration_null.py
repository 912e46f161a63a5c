"""The null distribution of the within-1/2-sigma shares (evaluation/calibration_null.py)
against known answers: white noise gives the binomial interval, a strongly autocorrelated
series a much wider one, a sigma half the error's scale is flagged narrow."""

from __future__ import annotations

import numpy as np
import pytest

from vio_graph.evaluation.calibration_null import (
    GAUSS_SHARE,
    ar1_acf,
    binomial_interval,
    correlation_factor,
    null_test,
    sample_autocorrelation,
    standardised_error,
    truncated_acf,
    within_shares,
)


def _ar1(n: int, rho: float, rng: np.random.Generator) -> np.ndarray:
    x = np.empty(n)
    x[0] = rng.standard_normal()
    e = rng.standard_normal(n) * np.sqrt(1 - rho**2)
    for k in range(1, n):
        x[k] = rho * x[k - 1] + e[k]
    return x


def test_white_noise_null_is_the_binomial_interval() -> None:
    n = 300
    z = np.random.default_rng(1).standard_normal(n)
    res = null_test([z], acf_model="white", n_draws=4000, seed=2)
    for level, p in enumerate(GAUSS_SHARE):
        lo, hi = binomial_interval(n, p)
        assert res.interval[level, 0] == pytest.approx(lo, abs=0.012)
        assert res.interval[level, 1] == pytest.approx(hi, abs=0.012)
    # the binomial 5-95 % interval of 300 independent frames: 0.683 +- 1.645 x 0.0269
    lo, hi = binomial_interval(n, GAUSS_SHARE[0])
    assert lo == pytest.approx(0.683 - 0.0442, abs=0.005)
    assert hi == pytest.approx(0.683 + 0.0442, abs=0.005)


def test_empirical_acf_of_white_noise_gives_about_the_binomial_interval() -> None:
    n = 300
    z = np.random.default_rng(3).standard_normal(n)
    res = null_test([z], acf_model="empirical", n_draws=3000, seed=4)
    lo, hi = binomial_interval(n, GAUSS_SHARE[0])
    width = res.interval[0, 1] - res.interval[0, 0]
    assert width == pytest.approx(hi - lo, rel=0.25)
    assert abs(res.rho1) < 0.15


def test_strong_autocorrelation_widens_the_interval() -> None:
    n, rho = 300, 0.95
    z = _ar1(n, rho, np.random.default_rng(5))
    res = null_test([z], acf_model="ar1", n_draws=3000, seed=6)
    lo, hi = binomial_interval(n, GAUSS_SHARE[0])
    width = res.interval[0, 1] - res.interval[0, 0]
    # effective sample size n (1 - rho) / (1 + rho) ~ 8 frames instead of 300
    assert width > 3.0 * (hi - lo)
    assert res.interval[0, 0] < GAUSS_SHARE[0] < res.interval[0, 1]
    assert res.rho1 == pytest.approx(rho, abs=0.06)
    # a perfectly calibrated sigma then meets the 10 % band far from always
    assert res.p_band < 0.6


def test_ar1_null_matches_direct_ar1_simulation() -> None:
    """The factor's draws have the shares of AR(1) series simulated by recursion."""
    n, rho, m = 200, 0.9, 1500
    rng = np.random.default_rng(7)
    direct = np.array([within_shares(_ar1(n, rho, rng)) for _ in range(m)])
    z = _ar1(n, rho, np.random.default_rng(8))
    F = correlation_factor(ar1_acf(rho, n), n)
    u = np.random.default_rng(9).standard_normal((m, n)) @ F.T
    via = within_shares(u)
    for level in range(2):
        q_direct = np.quantile(direct[:, level], [0.05, 0.95])
        q_via = np.quantile(via[:, level], [0.05, 0.95])
        assert q_via == pytest.approx(q_direct, abs=0.03)
    assert z.shape == (n,)


def test_sample_autocorrelation_recovers_ar1_and_skips_gaps() -> None:
    z = _ar1(20000, 0.8, np.random.default_rng(10))
    acf = sample_autocorrelation(z, max_lag=3)
    assert acf[0] == 1.0
    assert acf[1:] == pytest.approx([0.8, 0.64, 0.512], abs=0.03)
    z_gaps = z.copy()
    z_gaps[::7] = np.nan  # frames without an estimate keep their place in time
    assert sample_autocorrelation(z_gaps, max_lag=3)[1:] == pytest.approx(acf[1:], abs=0.03)


def test_truncated_acf_and_factor() -> None:
    a = truncated_acf([1.0, 0.5, 0.2, -0.1, 0.3])
    assert a.tolist() == [1.0, 0.5, 0.2, 0.0, 0.0]
    F = correlation_factor(a, 6)
    R = F @ F.T
    assert np.diag(R) == pytest.approx(np.ones(6))
    assert R[0, 1] == pytest.approx(0.5, abs=0.02)
    assert R[0, 4] == pytest.approx(0.0, abs=0.02)


def test_sigma_cancels_and_a_narrow_sigma_is_flagged() -> None:
    rng = np.random.default_rng(11)
    n = 400
    u = rng.standard_normal(n)
    sigma = rng.uniform(0.001, 0.02, n)
    err = sigma * u
    err[:30] = np.nan  # no estimate yet
    z = standardised_error(err, sigma)
    assert np.isnan(z[:30]).all()
    assert z[30:] == pytest.approx(u[30:])
    calibrated = null_test([z], acf_model="white", n_draws=2000, seed=12)
    assert calibrated.verdicts() == ["chance", "chance"]
    narrow = null_test([standardised_error(err, sigma / 2)], acf_model="white", seed=12)
    assert narrow.verdicts() == ["narrow", "narrow"]
    wide = null_test([standardised_error(err, sigma * 2)], acf_model="white", seed=12)
    assert wide.verdicts() == ["wide", "wide"]


def test_pooling_independent_trials_narrows_the_interval() -> None:
    rng = np.random.default_rng(13)
    zs = [_ar1(300, 0.95, rng) for _ in range(5)]
    one = null_test(zs[:1], acf_model="ar1", n_draws=2000, seed=14)
    pooled = null_test(zs, acf_model="ar1", n_draws=2000, seed=14)
    w1 = one.interval[0, 1] - one.interval[0, 0]
    w5 = pooled.interval[0, 1] - pooled.interval[0, 0]
    assert w5 == pytest.approx(w1 / np.sqrt(5), rel=0.35)
    assert pooled.n_frames == 1500
