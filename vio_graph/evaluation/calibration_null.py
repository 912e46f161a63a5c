"""How far a calibrated sigma's "share of frames within 1 / 2 sigma" scatters by chance.

The frames of one trial are not independent draws: the clearance error of frame k and frame
k + 1 share nearly all of their pose drift and map error, so a trial of 300 frames holds far
fewer than 300 independent looks at the sigma. The per-trial share within 1 sigma of even a
perfectly calibrated Gaussian error therefore scatters around 0.683 much more than the
binomial sd sqrt(0.683 x 0.317 / n) of independent frames.

The null model: the error is ``sigma_k * u_k`` with ``u`` a stationary zero-mean,
unit-variance Gaussian process over the frame index whose autocorrelation is that measured
on the trial's standardised error ``z = err / sigma`` (the frames without an estimate keep
their place in time, so a gap decorrelates as the process does). Since ``|err| <= k sigma``
is ``|u| <= k``, the sigma series cancels: the share's distribution depends on the number
and spacing of the frames and on the autocorrelation only. Many synthetic ``u`` series give
the null distribution of the shares; its 5-95 % interval tells whether an observed share is
a calibration fault or chance. Pooled over several trials (one scenario's seeds), the
trials are drawn independently and the share is taken over all their frames.

Two autocorrelation models (``acf_model``):

- ``empirical``: the sample autocorrelation of ``z`` (about its mean, over the pairs of
  frames both with an estimate), cut to zero from its first non-positive lag on and made a
  valid (positive semi-definite) correlation by clipping the Toeplitz matrix's negative
  eigenvalues;
- ``ar1``: ``rho ** lag`` with ``rho`` the lag-1 sample autocorrelation.

Both are estimated from the same short series, which biases them low (the trial mean is
removed): the interval is if anything too narrow, i.e. the verdict "fault" is the generous
one. Pure numpy; no I/O.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np
from numpy.typing import ArrayLike, NDArray

LEVELS = (1.0, 2.0)  # the shares scored: within 1 and 2 sigma
GAUSS_SHARE = (0.6826894921370859, 0.9544997361036416)  # P(|u| <= 1), P(|u| <= 2)
AIM_BANDS = ((0.61, 0.75), (0.86, 1.00))  # issue 12's "within 10 %" (docs/results.md)


def standardised_error(err_m: ArrayLike, sigma_m: ArrayLike) -> NDArray[np.float64]:
    """``err / sigma`` per frame, NaN where either is missing or the sigma is not positive
    (the frames the score of evaluation/safety.py leaves out)."""
    e = np.asarray(err_m, dtype=float)
    s = np.asarray(sigma_m, dtype=float)
    z = np.full(e.shape, np.nan)
    ok = np.isfinite(e) & np.isfinite(s) & (s > 0)
    z[ok] = e[ok] / s[ok]
    return z


def sample_autocorrelation(z: ArrayLike, max_lag: int | None = None) -> NDArray[np.float64]:
    """Autocorrelation of ``z`` at lags 0..max_lag (frames), NaN frames skipped: at lag L
    the mean of (z_k - m)(z_{k+L} - m) over the pairs with both finite, over the variance
    (m, variance over the finite frames). Lags with no pair are 0. ``acf[0] == 1``."""
    x = np.asarray(z, dtype=float)
    n = len(x)
    L = n - 1 if max_lag is None else min(int(max_lag), n - 1)
    ok = np.isfinite(x)
    if ok.sum() < 2:
        raise ValueError("autocorrelation needs at least 2 finite values")
    d = np.where(ok, x - x[ok].mean(), 0.0)
    var = float(np.mean(d[ok] ** 2))
    acf = np.zeros(L + 1)
    acf[0] = 1.0
    if var <= 0:
        return acf
    w = ok.astype(float)
    for lag in range(1, L + 1):
        pairs = float(np.dot(w[:-lag], w[lag:]))
        if pairs > 0:
            acf[lag] = float(np.dot(d[:-lag], d[lag:])) / pairs / var
    return acf


def truncated_acf(acf: ArrayLike) -> NDArray[np.float64]:
    """The autocorrelation cut to zero from its first non-positive lag on (the noisy tail
    of a short series' estimate)."""
    a = np.asarray(acf, dtype=float).copy()
    bad = np.flatnonzero(a[1:] <= 0)
    if bad.size:
        a[1 + bad[0] :] = 0.0
    return a


def ar1_acf(rho: float, n: int) -> NDArray[np.float64]:
    """``rho ** lag`` for lags 0..n-1 (an AR(1) process's autocorrelation)."""
    if not -1.0 < rho < 1.0:
        raise ValueError(f"AR(1) coefficient must be in (-1, 1), got {rho}")
    return rho ** np.arange(n, dtype=float)


def correlation_factor(acf: ArrayLike, n: int) -> NDArray[np.float64]:
    """A factor ``F`` (n, n) with ``F @ F.T`` the Toeplitz correlation matrix of ``acf``
    over n frames (lags past the given ones are 0), its negative eigenvalues clipped to 0
    and the diagonal renormalised to 1."""
    a = np.zeros(n)
    src = np.asarray(acf, dtype=float)[:n]
    a[: len(src)] = src
    idx = np.arange(n)
    R = a[np.abs(idx[:, None] - idx[None, :])]
    w, V = np.linalg.eigh(R)
    F = V * np.sqrt(np.clip(w, 0.0, None))
    norm = np.sqrt(np.sum(F * F, axis=1))
    return F / np.where(norm > 0, norm, 1.0)[:, None]


def within_shares(z: ArrayLike, levels: Sequence[float] = LEVELS) -> NDArray[np.float64]:
    """Share of the finite ``z`` with ``|z| <= level``, per level (along the last axis of a
    (..., n) array: one share per row)."""
    x = np.asarray(z, dtype=float)
    ok = np.isfinite(x)
    n = ok.sum(axis=-1)
    out = [np.sum(ok & (np.abs(np.where(ok, x, 0.0)) <= lv), axis=-1) / n for lv in levels]
    return np.stack(out, axis=-1)


def calibrated_draws(
    factor: NDArray[np.float64],
    mask: NDArray[np.bool_],
    n_draws: int,
    rng: np.random.Generator,
) -> NDArray[np.float64]:
    """``n_draws`` unit-variance Gaussian series with correlation ``factor @ factor.T``
    (n, n), NaN outside ``mask`` (the frames without an estimate), shape (n_draws, n)."""
    u = rng.standard_normal((n_draws, factor.shape[1])) @ factor.T
    u[:, ~np.asarray(mask, bool)] = np.nan
    return u


@dataclass(frozen=True)
class NullResult:
    """Observed and null shares of one trial or one pool of trials (per level of
    ``LEVELS``): ``observed``, ``interval`` (2 levels x (low, high) quantiles),
    ``p_band`` the null probability that both shares fall in ``AIM_BANDS`` (a perfectly
    calibrated sigma meets the aim this often), ``n_frames``, ``rho1`` (the lag-1
    autocorrelation; for a pool, the frame-weighted mean) and ``sd`` the null shares'
    standard deviation per level."""

    observed: NDArray[np.float64]
    interval: NDArray[np.float64]
    p_band: float
    n_frames: int
    rho1: float
    sd: NDArray[np.float64]

    def verdicts(self) -> list[str]:
        """Per level: 'chance' (inside the null interval), 'narrow' (below: sigma too
        small) or 'wide' (above: sigma too large)."""
        out = []
        for o, (lo, hi) in zip(self.observed, self.interval, strict=True):
            out.append("narrow" if o < lo else "wide" if o > hi else "chance")
        return out


def trial_factor(z: ArrayLike, acf_model: str = "empirical") -> tuple[NDArray, float]:
    """(correlation factor over the trial's frames, lag-1 autocorrelation) of the
    standardised error series ``z`` (NaN: no estimate)."""
    x = np.asarray(z, dtype=float)
    acf = sample_autocorrelation(x)
    rho = float(acf[1]) if len(acf) > 1 else 0.0
    if acf_model == "empirical":
        model = truncated_acf(acf)
    elif acf_model == "ar1":
        model = ar1_acf(min(max(rho, 0.0), 0.999), len(x))
    elif acf_model == "white":
        model = np.array([1.0])
    else:
        raise ValueError(f"unknown acf_model {acf_model!r} (empirical, ar1, white)")
    return correlation_factor(model, len(x)), rho


def null_test(
    zs: Sequence[ArrayLike],
    acf_model: str = "empirical",
    n_draws: int = 2000,
    quantiles: tuple[float, float] = (0.05, 0.95),
    seed: int = 0,
) -> NullResult:
    """The shares within 1 / 2 sigma of the standardised error series ``zs`` (one per
    trial; several: pooled over all their frames) against the null of a calibrated error
    with each trial's own autocorrelation (module docstring). Deterministic in ``seed``."""
    rng = np.random.default_rng(seed)
    counts = np.zeros((n_draws, len(LEVELS)))
    observed = np.zeros(len(LEVELS))
    n_tot, rho_w = 0, 0.0
    for z in zs:
        x = np.asarray(z, dtype=float)
        mask = np.isfinite(x)
        n = int(mask.sum())
        if n == 0:
            continue
        F, rho = trial_factor(x, acf_model)
        u = calibrated_draws(F, mask, n_draws, rng)
        counts += within_shares(u) * n
        observed += within_shares(x) * n
        n_tot += n
        rho_w += rho * n
    if n_tot == 0:
        raise ValueError("no frame with an error and a sigma")
    shares = counts / n_tot
    interval = np.quantile(shares, quantiles, axis=0).T  # (levels, 2)
    (a1, b1), (a2, b2) = AIM_BANDS
    in_band = (
        (shares[:, 0] >= a1) & (shares[:, 0] <= b1) & (shares[:, 1] >= a2) & (shares[:, 1] <= b2)
    )
    return NullResult(
        observed / n_tot,
        interval,
        float(in_band.mean()),
        n_tot,
        rho_w / n_tot,
        shares.std(axis=0),
    )


def binomial_interval(
    n: int, p: float, quantiles: tuple[float, float] = (0.05, 0.95)
) -> tuple[float, float]:
    """Quantiles of a binomial share (k / n, k ~ B(n, p)): the null of independent frames."""
    k = np.arange(n + 1)
    logpmf = (
        _log_factorial(n)
        - _log_factorial(k)
        - _log_factorial(n - k)
        + k * np.log(p)
        + (n - k) * np.log1p(-p)
    )
    cdf = np.cumsum(np.exp(logpmf - logpmf.max()))
    cdf /= cdf[-1]
    lo = int(np.searchsorted(cdf, quantiles[0]))
    hi = int(np.searchsorted(cdf, quantiles[1]))
    return lo / n, hi / n


def _log_factorial(k: ArrayLike) -> NDArray[np.float64]:
    from math import lgamma

    kk = np.atleast_1d(np.asarray(k))
    return np.array([lgamma(float(v) + 1.0) for v in kk]).reshape(np.shape(k))


__all__ = [
    "AIM_BANDS",
    "GAUSS_SHARE",
    "LEVELS",
    "NullResult",
    "ar1_acf",
    "binomial_interval",
    "calibrated_draws",
    "correlation_factor",
    "null_test",
    "sample_autocorrelation",
    "standardised_error",
    "trial_factor",
    "truncated_acf",
    "within_shares",
]
