"""Innovation consistency in the health report: the filter's own y^T S^-1 y, per family,
against its usual self (vio_graph/health.py, InnovationTest)."""

from __future__ import annotations

import json
import math
from pathlib import Path

import numpy as np
import pytest
from typer.testing import CliRunner

from vio_graph.cli import app
from vio_graph.filter.eskf import SagittalEskf
from vio_graph.filter.gating import chi2_quantile_scipy
from vio_graph.health import (
    HealthLimits,
    HealthMonitor,
    binomial_tail,
    chi2_quantile_wh,
)
from vio_graph.types import Displacement2D

RATE_HZ = 30.0


def _stream(
    monitor: HealthMonitor,
    family: str,
    rng: np.random.Generator,
    claimed_over_true: float,
    usual: float = 1.0,
    seconds: float = 20.0,
) -> None:
    """2-dof innovations y ~ N(0, S_true) at 30 Hz; the filter claims S = S_true *
    ``claimed_over_true`` and, as its usual self, innovations ``usual`` times smaller in
    variance than it claims (a conservative filter: usual < 1)."""
    S_true = np.array([[4e-6, 1e-6], [1e-6, 2e-6]]) * usual
    S_claimed_inv = np.linalg.inv(S_true * claimed_over_true / usual)
    L = np.linalg.cholesky(S_true)
    for k in range(int(seconds * RATE_HZ)):
        y = L @ rng.standard_normal(2)
        monitor.add_innovations(k / RATE_HZ, family, [(float(y @ S_claimed_inv @ y), 2, True)])


def _limits(c: float = 1.0, phi: float = 1.0) -> HealthLimits:
    return HealthLimits(innovation_reference={"displacement": (c, phi)})


def test_wilson_hilferty_quantile_matches_the_exact_one() -> None:
    for dof in (1.0, 1.5, 2.0, 3.0, 7.3, 20.0, 60.0, 300.0):
        exact = chi2_quantile_scipy(0.99, dof)
        assert chi2_quantile_wh(0.99, dof) == pytest.approx(exact, rel=0.01 if dof >= 1 else 0.05)
    with pytest.raises(ValueError):
        chi2_quantile_wh(0.99, 0.0)


def test_binomial_tail() -> None:
    assert binomial_tail(0, 9, 0.01) == 1.0
    assert binomial_tail(1, 1, 0.3) == pytest.approx(0.3)
    assert binomial_tail(1, 9, 0.01) == pytest.approx(1 - 0.99**9)
    assert binomial_tail(2, 9, 0.01) == pytest.approx(1 - 0.99**9 - 9 * 0.01 * 0.99**8)
    assert binomial_tail(10, 9, 0.01) == 0.0


def test_honest_covariances_pass_and_three_times_too_small_ones_warn() -> None:
    """Right covariances: the mean NIS per dof is ~1, ~1 % of windows fail and the trial is
    flagged on few of 40 seeds (the trial-level test's 1 %); covariances 3x too small: NIS
    ~3 per dof, nearly every window fails, flagged on every seed with a warning naming the
    family."""
    flagged_honest = flagged_small = 0
    fail_honest = windows = 0
    for seed in range(40):
        rng = np.random.default_rng(seed)
        honest, small = HealthMonitor(_limits()), HealthMonitor(_limits())
        _stream(honest, "displacement", rng, 1.0)
        _stream(small, "displacement", rng, 1.0 / 3.0)
        h, s = honest.innovations["displacement"], small.innovations["displacement"]
        assert h.nis_sum / h.dof_sum == pytest.approx(1.0, abs=0.12)
        assert s.nis_sum / s.dof_sum == pytest.approx(3.0, abs=0.4)
        assert s.failing_share > 0.9
        fail_honest += h.n_failing
        windows += h.n_windows
        flagged_honest += int(h.inconsistent)
        flagged_small += int(s.inconsistent)
        rep = small.report()
        assert not rep["ok"] and not rep["innovations_consistent"]
        assert any("innovations" in w and "displacement" in w for w in rep["warnings"])
        assert honest.report()["innovations"]["displacement"]["windows"] == h.n_windows == 19
    assert fail_honest / windows < 0.03  # the window test's 1 %
    assert flagged_honest <= 2  # the trial test's 1 % of 40
    assert flagged_small == 40


def test_the_test_is_against_the_filters_usual_self() -> None:
    """A conservative filter (innovations 5x smaller than its S on the reference trials) is
    not flagged at its usual level when the reference says so, and is flagged when it gets
    3x worse than usual, though its NIS is still below 1."""
    usual = 0.2
    for seed in range(5):
        rng = np.random.default_rng(100 + seed)
        as_usual, worse = HealthMonitor(_limits(usual)), HealthMonitor(_limits(usual))
        _stream(as_usual, "displacement", rng, 1.0, usual=usual)
        _stream(worse, "displacement", rng, 1.0 / 3.0, usual=usual)
        a, w = as_usual.innovations["displacement"], worse.innovations["displacement"]
        assert a.nis_sum / a.dof_sum == pytest.approx(usual, rel=0.15)
        assert w.nis_sum / w.dof_sum < 1.0
        assert not a.inconsistent and as_usual.report()["ok"]
        assert w.inconsistent and not worse.report()["ok"]


def test_dispersion_widens_the_test() -> None:
    """Windows whose sums vary phi times more than a chi-square's (correlated updates:
    each value repeated phi times) fail at ~1 % with the reference dispersion phi, and far
    more often without it."""
    phi = 10
    fails_with = fails_without = n = 0
    for seed in range(20):
        rng = np.random.default_rng(200 + seed)
        with_phi, without = HealthMonitor(_limits(1.0, phi)), HealthMonitor(_limits(1.0, 1.0))
        for k in range(int(60 * RATE_HZ / phi)):
            d2 = float(rng.chisquare(2))
            for j in range(phi):
                t = (k * phi + j) / RATE_HZ
                for m in (with_phi, without):
                    m.add_innovations(t, "displacement", [(d2, 2, True)])
        fails_with += with_phi.innovations["displacement"].n_failing
        fails_without += without.innovations["displacement"].n_failing
        n += with_phi.innovations["displacement"].n_windows
    assert fails_with / n < 0.04
    assert fails_without / n > 0.15


def test_refused_updates_are_counted_not_summed_and_unknown_families_are_untested() -> None:
    m = HealthMonitor(_limits())
    m.add_innovations(0.0, "displacement", [(1.0, 2, True), (500.0, 2, False)])
    m.add_innovations(0.1, "bridge", [(3.0, 2, True)])
    rep = m.report()["innovations"]
    assert rep["displacement"]["updates"] == 2 and rep["displacement"]["refused"] == 1
    assert rep["displacement"]["nis_sum"] == 1.0 and rep["displacement"]["dof"] == 2
    assert rep["untested_updates"] == 1
    assert math.isnan(rep["displacement"]["window_dispersion"])  # no window closed yet


def test_the_filter_records_the_gates_statistic_of_each_update() -> None:
    """SagittalEskf.take_innovations gives, per update, the same y^T S^-1 y as the gate test
    (displacement_d2), its dimension and the outcome, and forgets them once taken."""
    f = SagittalEskf()
    f.initialise(0.0, (0.0, 0.0))
    f.clone_position(0.0)
    d = Displacement2D(0.0, 0.0, np.array([0.003, -0.002]), np.eye(2) * 1e-5)
    d2 = f.displacement_d2(d)
    assert d2 is not None and d2 > 0
    assert f.update_displacement(d)
    (got,) = f.take_innovations()
    assert got[0] == pytest.approx(d2, rel=1e-9) and got[1:] == (2, True)
    assert f.take_innovations() == []
    far = Displacement2D(0.0, 0.0, np.array([1.0, 1.0]), np.eye(2) * 1e-6)
    assert not f.update_displacement(far)
    (got,) = f.take_innovations()
    assert got[1:] == (2, False) and got[0] > f.gate_d2


def test_a_clean_trial_reports_every_family_and_no_innovation_warning(
    short_upstair: Path, tmp_path: Path
) -> None:
    """End to end on the 4 s upstair trial: the estimator files the filter's updates by
    family, each family's windows are tested, and a clean trial is consistent."""
    out = tmp_path / "res"
    args = ["run", str(short_upstair), "--out", str(out), "--mode", "filter", "--no-rerun"]
    res = CliRunner().invoke(app, [*args, "--no-plots"])
    assert res.exit_code == 0, res.output
    h = json.loads((out / "metrics.json").read_text())["health"]
    inn = h["innovations"]
    for family in ("displacement", "corner", "level", "stance"):
        assert inn[family]["updates"] > 0 and inn[family]["dof"] > 0, family
        assert not inn[family]["inconsistent"], (family, inn[family])
    assert inn["displacement"]["windows"] >= 2
    assert h["innovations_consistent"]
    assert "innovations are larger" not in res.output
