"""The stored chi-square quantiles (filter/gating.py KNOWN_CHI2_QUANTILES, which spare a run
the scipy.special import) are scipy's values, and chi2_quantile answers the same with and
without the table."""

from __future__ import annotations

import pytest

from vio_graph.filter.gating import (
    KNOWN_CHI2_QUANTILES,
    chi2_2dof_quantile,
    chi2_quantile,
    chi2_quantile_scipy,
)


@pytest.mark.parametrize("key", sorted(KNOWN_CHI2_QUANTILES))
def test_stored_quantile_is_scipys(key: tuple[float, int]) -> None:
    probability, dof = key
    # bit for bit with the scipy the table was written with; a later scipy may move the
    # last bits of gammaincinv, which the relative tolerance allows
    assert KNOWN_CHI2_QUANTILES[key] == pytest.approx(
        chi2_quantile_scipy(probability, dof), rel=1e-14, abs=0.0
    )
    assert chi2_quantile(probability, dof) == KNOWN_CHI2_QUANTILES[key]


def test_quantiles_outside_the_table_are_computed() -> None:
    assert (0.9995, 1) not in KNOWN_CHI2_QUANTILES
    assert chi2_quantile(0.9995, 1) == chi2_quantile_scipy(0.9995, 1)
    # a known answer: the 2-dof quantile has the closed form -2 ln(1 - p)
    assert chi2_quantile(0.9995, 2) == pytest.approx(chi2_2dof_quantile(0.9995), rel=1e-12)
    assert chi2_quantile(0.95, 1) == pytest.approx(1.959963984540054**2, rel=1e-12)


def test_integer_like_arguments_find_the_table() -> None:
    assert chi2_quantile(0.999, 3.0) == KNOWN_CHI2_QUANTILES[(0.999, 3)]  # type: ignore[arg-type]
