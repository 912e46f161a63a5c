"""The offline filter-vs-smoother consistency figures (vio_graph/health.py,
smoothed_vs_filtered, filter_sigma_summary): known answers on synthetic paths."""

from __future__ import annotations

import numpy as np
import pytest

from vio_graph.health import (
    HealthLimits,
    disagreement_warning,
    filter_sigma_summary,
    smoothed_vs_filtered,
)


def _paths(n: int = 200, sigma_x_m: float = 0.01, sigma_z_m: float = 0.005):
    t = np.linspace(0.0, 2.0, n)
    filt = np.stack([0.5 * t, 0.1 * np.sin(t)], axis=1)
    cov = np.zeros((n, 2, 2))
    cov[:, 0, 0] = sigma_x_m**2
    cov[:, 1, 1] = sigma_z_m**2
    return t, filt, cov


def test_a_constant_offset_after_the_start_is_tested_against_the_filter_variance() -> None:
    t, filt, cov = _paths()
    other = filt.copy()
    other[100:, 0] += 0.04  # 4 cm = 4 filter sigmas in x from frame 100 on: d^2 = 16
    other[:, 1] += 0.3  # a constant z offset is removed by anchoring at the first pose
    rep = smoothed_vs_filtered(t, filt, cov, other)
    assert rep["chi2_limit"] == pytest.approx(10.8276, abs=1e-3)  # chi-square 1 dof, 0.999
    assert rep["x"]["max_d2"] == pytest.approx(16.0)
    assert rep["x"]["max_d2_at_s"] == pytest.approx(t[100])
    assert rep["x"]["difference_at_max_cm"] == pytest.approx(4.0)
    assert rep["x"]["beyond_share"] == pytest.approx(0.5)
    assert rep["x"]["rms_difference_cm"] == pytest.approx(4.0 * np.sqrt(0.5))
    assert rep["z"]["max_d2"] == pytest.approx(0.0, abs=1e-20)
    assert not rep["consistent"]


def test_a_difference_within_the_filter_sigma_passes() -> None:
    t, filt, cov = _paths(sigma_x_m=0.03)
    other = filt.copy()
    other[100:, 0] += 0.04  # the same 4 cm against a 3 cm sigma: d^2 = 1.78
    rep = smoothed_vs_filtered(t, filt, cov, other)
    assert rep["x"]["max_d2"] == pytest.approx((4.0 / 3.0) ** 2)
    assert rep["x"]["beyond_share"] == 0.0
    assert rep["consistent"]


def test_frames_without_a_variance_are_left_out() -> None:
    t, filt, cov = _paths()
    other = filt.copy()
    other[150:, 0] += 0.05
    cov[150:, 0, 0] = 0.0  # no variance where they differ: nothing to test
    other[120, 1] = np.nan
    rep = smoothed_vs_filtered(t, filt, cov, other)
    assert rep["x"]["frames"] == 150
    assert rep["x"]["max_d2"] == 0.0
    assert rep["z"]["frames"] == 199
    assert rep["consistent"]


def test_filter_sigma_summary_is_the_square_root_of_the_variances() -> None:
    _, _, cov = _paths()
    cov[-1, 0, 0] = 0.02**2
    rep = filter_sigma_summary(cov)
    assert rep["x"]["median_cm"] == pytest.approx(1.0)
    assert rep["x"]["last_cm"] == pytest.approx(2.0)
    assert rep["z"]["p95_cm"] == pytest.approx(0.5)


def test_a_large_lasting_disagreement_warns_and_names_the_axis() -> None:
    t, filt, cov = _paths(sigma_z_m=0.002)
    other = filt.copy()
    other[:, 1] += np.linspace(0.0, 0.025, len(t))  # the smoother's z walks 2.5 cm away
    rep = smoothed_vs_filtered(t, filt, cov, other)
    warning = disagreement_warning("smoother", rep)
    assert warning is not None and "height (z)" in warning and "forward (x)" not in warning
    assert "up to 2.5 cm" in warning and "health.smoother_vs_filter" in warning


def test_a_large_rms_difference_warns_even_within_the_filter_sigma() -> None:
    t, filt, cov = _paths(sigma_x_m=0.04)  # a filter that claims 4 cm in x
    other = filt.copy()
    other[:, 0] += np.linspace(0.0, 0.05, len(t))  # 2.9 cm RMS apart, under 1.25 sigma
    rep = smoothed_vs_filtered(t, filt, cov, other)
    assert rep["x"]["beyond_share"] == 0.0 and rep["x"]["rms_difference_cm"] > 2.0
    warning = disagreement_warning("batch", rep)
    assert warning is not None and "forward (x)" in warning
    other = filt.copy()
    other[:, 0] += np.linspace(0.0, 0.03, len(t))  # 1.7 cm RMS: no warning
    assert disagreement_warning("batch", smoothed_vs_filtered(t, filt, cov, other)) is None


def test_a_small_or_brief_disagreement_does_not_warn() -> None:
    t, filt, cov = _paths(sigma_z_m=0.001)
    small = filt.copy()
    small[100:, 1] += 0.015  # beyond a 1 mm sigma on half the frames, but 1.5 cm apart
    rep = smoothed_vs_filtered(t, filt, cov, small)
    assert rep["z"]["beyond_share"] == pytest.approx(0.5)
    assert disagreement_warning("batch", rep) is None
    brief = filt.copy()
    brief[190:195, 1] += 0.05  # 5 cm apart, on 2.5 % of the frames
    rep = smoothed_vs_filtered(t, filt, cov, brief)
    assert disagreement_warning("batch", rep) is None
    assert disagreement_warning("batch", rep, HealthLimits(max_disagreement_share=0.02))
