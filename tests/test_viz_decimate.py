"""Line decimation for the run figures keeps every extreme, every gap and the time order."""

from __future__ import annotations

import numpy as np
import pytest

from vio_graph.viz.decimate import plot_indices


def test_short_series_untouched() -> None:
    np.testing.assert_array_equal(plot_indices(np.arange(50.0), max_points=100), np.arange(50))


def test_long_series_bounded_sorted_and_keeps_ends() -> None:
    rng = np.random.default_rng(3)
    xz = np.cumsum(rng.normal(size=(20_000, 2)), axis=0)
    idx = plot_indices(xz, max_points=700)
    assert len(idx) <= 700
    assert np.all(np.diff(idx) > 0)
    assert idx[0] == 0 and idx[-1] == len(xz) - 1


def test_extremes_of_every_bucket_survive() -> None:
    """Narrow spikes (one sample wide) are what a stride would drop: all of them are kept, so
    the line reaches the same heights and depths."""
    t = np.linspace(0.0, 600.0, 18_000)
    z = np.sin(t)
    spikes = np.arange(500, 18_000, 1_000)
    z[spikes] += 10.0
    z[spikes + 3] -= 10.0
    idx = plot_indices(np.column_stack([t, z]), max_points=1_000)
    assert set(spikes) <= set(idx) and set(spikes + 3) <= set(idx)
    assert z[idx].max() == z.max() and z[idx].min() == z.min()


def test_gaps_still_break_the_line() -> None:
    v = np.sin(np.linspace(0.0, 50.0, 10_000))
    v[4_321] = np.nan
    idx = plot_indices(v, max_points=500)
    assert 4_321 in idx
    assert np.nanmax(v[idx]) == np.nanmax(v)


def test_bad_input() -> None:
    with pytest.raises(ValueError, match="shape"):
        plot_indices(np.zeros((4, 2, 2)))
    with pytest.raises(ValueError, match="max_points"):
        plot_indices(np.zeros((100, 3)), max_points=8)
