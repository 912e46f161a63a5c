"""Strips of the height map a nosing hid from the camera (safety.gap_floor_check,
clearance.gap_terrain): known answers of the strip terrain and of the monitor's clearance of a
foot standing on, or swinging towards, such a strip."""

from __future__ import annotations

import numpy as np
import pytest

from vio_graph.safety.clearance import HeightProfile, gap_terrain
from vio_graph.safety.config import SafetyConfig
from vio_graph.safety.online import SafetyMonitor


def _prof(cols: list[tuple[float, float, float]]) -> HeightProfile:
    lo, hi, z = (np.array(v, dtype=float) for v in zip(*cols, strict=True))
    return HeightProfile(lo, hi, z, np.full(len(lo), 0.003))


def test_gap_terrain_floors_and_risers_of_bridged_strips() -> None:
    # floor to 0.40, a rising strip to 0.48, a tread at 0.15 to 0.80, a dropping strip to
    # 0.86, a lower tread at 0.05 to 1.0, then a 20 cm gap (not bridged) and a last bin
    prof = _prof([(0.0, 0.40, 0.0), (0.48, 0.80, 0.15), (0.86, 1.0, 0.05), (1.20, 1.3, 0.05)])
    bins = np.array([10, 11, 12, 13])
    floors, f_bins, risers, r_bins = gap_terrain(prof, bins, 0.15, riser_from_x_m=0.43)
    np.testing.assert_allclose(floors.x_lo_m, [0.40, 0.80])
    np.testing.assert_allclose(floors.x_hi_m, [0.48, 0.86])
    np.testing.assert_allclose(floors.z_m, [0.0, 0.05])  # the lower neighbour's height
    np.testing.assert_array_equal(f_bins, [10, 12])
    # the rising strip's riser beyond the foot (x >= 0.43), at the higher neighbour's height;
    # the dropping strip has none
    np.testing.assert_allclose(risers.x_lo_m, [0.43])
    np.testing.assert_allclose(risers.x_hi_m, [0.48])
    np.testing.assert_allclose(risers.z_m, [0.15])
    np.testing.assert_array_equal(r_bins, [11])
    # a foot past the strip leaves no room for its riser; no bridging: nothing
    assert len(gap_terrain(prof, bins, 0.15, riser_from_x_m=0.5)[2]) == 0
    assert len(gap_terrain(prof, bins, 0.05)[0]) == 0


# floor to the riser at x = 0.5 (0.15 m high), tread to the next riser at 0.78
STEP = [(-1.0, 0.0), (0.5, 0.0), (0.5, 0.15), (0.78, 0.15), (0.78, 0.30), (2.0, 0.30)]


def _monitor(check: bool, stance_contact: bool = False) -> SafetyMonitor:
    """A monitor whose map saw STEP except the last 10 cm of the floor before the riser
    (the strip the nosing above hides), from three keyframes. ``stance_contact`` off by
    default here: the tests look at what the map says under a foot, not at the report of
    a standing foot as a contact."""
    mon = SafetyMonitor(
        SafetyConfig(
            bin_m=0.005, min_keyframes=2, gap_floor_check=check, stance_contact=stance_contact
        )
    )
    prof = HeightProfile.from_polyline(STEP)
    xs = np.linspace(-0.2, 1.6, 400)
    xs = xs[(xs < 0.40) | (xs >= 0.5)]
    z = prof.z_m[np.clip(np.searchsorted(prof.x_hi_m, xs), 0, len(prof) - 1)]
    cam = np.array([0.0, 0.5])
    rng = np.random.default_rng(0)
    for k in range(3):
        pts = np.stack([xs, z + rng.normal(0, 0.0005, xs.size)], 1) - cam
        mon.update(0.01 * k, cam, np.eye(2) * 1e-6, [-0.5, 0.2], [-0.25, 0.2], False, pts)
    return mon


@pytest.mark.parametrize("check", [True, False])
def test_foot_standing_on_the_hidden_strip(check: bool) -> None:
    """Heel raised over the mapped floor, toe on the floor in the hidden strip: the true
    clearance is 0. Without the strip's floor the nearest terrain is the last mapped bin,
    1.5 cm from the foot line."""
    s = _monitor(check).update(1.0, [0.0, 0.5], np.eye(2) * 1e-6, [0.25, 0.05], [0.47, 0.0], True)
    if check:
        assert s.clearance_m == pytest.approx(0.0, abs=0.002)
    else:
        assert s.clearance_m == pytest.approx(0.0155, abs=0.002)
    # reported as a contact (the default), the standing foot is 0 with the outline's sigma
    mon = _monitor(check, stance_contact=True)
    s = mon.update(1.0, [0.0, 0.5], np.eye(2) * 1e-6, [0.25, 0.05], [0.47, 0.0], True)
    assert s.clearance_m == 0.0 and s.clearance_sigma_m <= SafetyConfig().foot_sigma_m


def test_foot_swinging_towards_a_hidden_riser_is_not_known() -> None:
    """Toe 6 cm above the floor, 2 cm before the strip: the mapped bins say 6 cm, but the riser
    hidden in the strip could stand 2 cm ahead of the toe: NaN (with the check), 6 cm without."""
    foot = ([0.15, 0.08], [0.38, 0.06])
    on = _monitor(True).update(1.0, [0.0, 0.5], np.eye(2) * 1e-6, *foot, False)
    off = _monitor(False).update(1.0, [0.0, 0.5], np.eye(2) * 1e-6, *foot, False)
    assert off.clearance_m == pytest.approx(0.06, abs=0.002)
    assert np.isnan(on.clearance_m) and np.isnan(on.clearance_sigma_m)
    # far from the strip (toe 20 cm before it) the riser cannot be nearer: known, unchanged
    far = ([-0.05, 0.08], [0.18, 0.06])
    a = _monitor(True).update(1.0, [0.0, 0.5], np.eye(2) * 1e-6, *far, False)
    b = _monitor(False).update(1.0, [0.0, 0.5], np.eye(2) * 1e-6, *far, False)
    assert a.clearance_m == b.clearance_m == pytest.approx(0.06, abs=0.002)
