"""The clearance given that a foot is never inside the terrain (safety/clearance.py,
``non_penetrating``; config ``safety.non_penetration``): known answers for the truncated
Gaussian, and the monitor's output with and without it."""

from __future__ import annotations

import math

import numpy as np
import pytest

from vio_graph.safety.clearance import ONE_SIGMA_MASS, HeightProfile, non_penetrating
from vio_graph.safety.config import SafetyConfig
from vio_graph.safety.online import SafetyMonitor

# stair descent: the upper tread at 0.30 m ends at x = 0.5, the lower one at 0.15 m
DOWN = [(-1.0, 0.30), (0.5, 0.30), (0.5, 0.15), (2.0, 0.15)]


def test_a_clearance_outside_the_terrain_is_unchanged() -> None:
    assert non_penetrating(0.012, 0.004) == (0.012, 0.004)
    assert non_penetrating(0.0, 0.004) == (0.0, 0.004)
    c, s = non_penetrating(float("nan"), 0.004)
    assert math.isnan(c) and s == 0.004
    assert non_penetrating(-0.01, 0.0) == (0.0, 0.0)  # no sigma: only the clamp


@pytest.mark.parametrize("a", [1e-9, 0.5, 1.0, 2.0, 4.0, 8.0])
def test_the_sigma_holds_one_sigma_of_the_truncated_gaussian(a: float) -> None:
    """A foot a sigmas inside the terrain: the clearance is 0 and [0, sigma] holds 68.3 % of
    N(c, s^2) truncated at 0, checked by integrating the density numerically."""
    s = 0.005
    c = -a * s
    c_out, q = non_penetrating(c, s)
    assert c_out == 0.0
    x = np.linspace(0.0, q, 20001)
    dens = np.exp(-0.5 * ((x - c) / s) ** 2) / (s * math.sqrt(2 * math.pi))
    inside = float(np.sum((dens[1:] + dens[:-1]) * np.diff(x)) / 2)
    above_zero = 0.5 * math.erfc(a / math.sqrt(2.0))  # Q(a), without cancellation
    assert inside / above_zero == pytest.approx(ONE_SIGMA_MASS, abs=2e-4)
    assert q <= s * (1 + 1e-6)


def test_sigma_is_continuous_at_contact_and_shrinks_with_the_penetration() -> None:
    s = 0.004
    assert non_penetrating(-1e-12, s)[1] == pytest.approx(s, rel=1e-6)  # c = 0: s itself
    qs = [non_penetrating(-a * s, s)[1] for a in (0.5, 1.0, 2.0, 4.0, 8.0, 16.0)]
    assert all(q1 > q2 > 0 for q1, q2 in zip(qs, qs[1:], strict=False))
    # far inside, the truncated Gaussian's tail is exponential: q -> ln(1 / 0.317) s^2 / |c|
    a = 16.0
    assert non_penetrating(-a * s, s)[1] == pytest.approx(
        -math.log(1 - ONE_SIGMA_MASS) * s / a, rel=0.01
    )


def test_montecarlo_share_within_the_sigma() -> None:
    """Draws of the true clearance from N(c, s^2), kept where >= 0 (the foot outside): the
    share within [0, sigma] of the reported 0 is 0.683."""
    rng = np.random.default_rng(3)
    c, s = -0.006, 0.004
    draws = rng.normal(c, s, 2_000_000)
    draws = draws[draws >= 0]
    _, q = non_penetrating(c, s)
    assert np.mean(draws <= q) == pytest.approx(ONE_SIGMA_MASS, abs=0.01)


def _map_down(mon: SafetyMonitor, n: int = 6) -> None:
    rng = np.random.default_rng(0)
    xs = np.linspace(-0.2, 1.6, 400)
    prof = HeightProfile.from_polyline(DOWN)
    z = np.array([prof.z_m[np.clip(np.searchsorted(prof.x_hi_m, x), 0, len(prof) - 1)] for x in xs])
    cam = np.array([0.0, 0.8])
    for k in range(n):
        pts = np.stack([xs, z + rng.normal(0, 0.0005, xs.size)], 1) - cam
        mon.update(0.01 * k, cam, np.eye(2) * 1e-6, [-0.5, 0.5], [-0.25, 0.5], False, pts)


@pytest.mark.parametrize("compiled", [False, True])
def test_monitor_reports_a_heel_inside_the_riser_as_contact(compiled: bool) -> None:
    """A foot on the lower tread with its heel estimated 2 cm into the riser behind it (the
    descent's x drift): the signed distance is -2 cm; with non_penetration the clearance is
    0 and the sigma that of the truncated Gaussian; without it, as before."""
    P_now = np.diag([3.6e-5, 1e-5])  # x sigma 6 mm since the keyframes
    out = {}
    for on, mode in ((False, "contact"), (True, "truncated"), (True, "contact")):
        cfg = SafetyConfig(
            non_penetration=on, non_penetration_sigma=mode, foot_sigma_m=0.001, stance_contact=False
        )  # (the foot stands: without stance_contact, to see the clamp alone)
        mon = SafetyMonitor(cfg, compiled=compiled)
        _map_down(mon)
        out[on, mode] = mon.update(1.0, [0.3, 0.8], P_now, [0.48, 0.15], [0.73, 0.15], True)
    raw, trunc, now = out[False, "contact"], out[True, "truncated"], out[True, "contact"]
    assert raw.clearance_m == pytest.approx(-0.02, abs=0.003)  # 5 mm bins
    assert 0.004 < raw.clearance_sigma_m < 0.008
    assert trunc.clearance_m == now.clearance_m == 0.0
    q = non_penetrating(raw.clearance_m, raw.clearance_sigma_m)[1]
    assert trunc.clearance_sigma_m == pytest.approx(q, rel=1e-9)
    # ~3.3 sigma inside: the truncated Gaussian's 1-sigma is ~0.3 s (1.8-1.9 mm here)
    assert 0.25 * raw.clearance_sigma_m < q < 0.35 * raw.clearance_sigma_m
    assert now.clearance_sigma_m == pytest.approx(0.001)  # a contact's: the foot outline's
    # everything else is the same estimate
    np.testing.assert_equal(now.nosing_clearance_m, raw.nosing_clearance_m)
    np.testing.assert_array_equal(now.toe_line_xz_m, raw.toe_line_xz_m)
    # a foot above the tread: identical with and without
    for on in (False, True):
        mon = SafetyMonitor(SafetyConfig(non_penetration=on), compiled=compiled)
        _map_down(mon)
        out[on] = mon.update(1.0, [0.3, 0.8], P_now, [0.55, 0.19], [0.80, 0.19], False)
    assert out[True].clearance_m == out[False].clearance_m == pytest.approx(0.04, abs=0.003)
    assert out[True].clearance_sigma_m == out[False].clearance_sigma_m


def test_contact_sigma_bounds_only_a_clamped_clearance() -> None:
    s = 0.004
    assert non_penetrating(-1e-12, s, 0.001) == (0.0, 0.001)  # q = s = 4 mm > 1 mm
    assert non_penetrating(-0.05, s, 0.001)[1] == pytest.approx(non_penetrating(-0.05, s)[1])
    assert non_penetrating(-0.05, s)[1] < 0.001  # 12.5 sigma in: q < the contact's
    assert non_penetrating(0.002, s, 0.001) == (0.002, s)  # not clamped: unchanged


@pytest.mark.parametrize("compiled", [False, True])
def test_a_standing_foot_over_a_map_below_its_sole_is_reported_in_contact(compiled: bool) -> None:
    """The map reads the lower tread 4 mm below the truth (the sole stands at 0.154 m on a
    tread mapped at 0.15 m): with the foot in stance the clearance is a contact, 0 with the
    foot outline's sigma (safety.stance_contact); without it, the map's 4 mm gap with the
    pose and map sigma. The same foot in swing is unchanged either way, and a standing foot
    over unmapped terrain stays unknown."""
    P_now = np.diag([3.6e-5, 1e-5])
    heel, toe = [0.70, 0.154], [0.95, 0.154]
    out = {}
    for on in (False, True):
        for stance in (False, True):
            mon = SafetyMonitor(SafetyConfig(stance_contact=on), compiled=compiled)
            _map_down(mon)
            out[on, stance] = mon.update(1.0, [0.5, 0.8], P_now, heel, toe, stance)
    gap = out[False, True]
    assert gap.clearance_m == pytest.approx(0.004, abs=1e-3)
    assert gap.clearance_sigma_m > 0.002  # the relative pose (3.2 mm in z) and the map
    now = out[True, True]
    assert now.clearance_m == 0.0
    assert now.clearance_sigma_m == pytest.approx(0.001)  # foot_sigma_m, a contact's
    np.testing.assert_array_equal(now.toe_line_xz_m, gap.toe_line_xz_m)
    assert now.predicted_min_clearance_m == gap.predicted_min_clearance_m
    for on in (False, True):  # swing: the map's distance as it was
        assert out[on, False].clearance_m == gap.clearance_m
        assert out[on, False].clearance_sigma_m == gap.clearance_sigma_m
    # standing where nothing was mapped: no clearance, in contact or not
    mon = SafetyMonitor(SafetyConfig(stance_contact=True), compiled=compiled)
    _map_down(mon)
    far = mon.update(1.0, [3.5, 0.8], P_now, [3.2, 0.15], [3.45, 0.15], True)
    assert math.isnan(far.clearance_m)


def test_score_splits_contact_frames_from_gaussian_ones() -> None:
    """metrics.json ``clearance.filter``: the shares within 1 / 2 sigma over all frames and
    split into the frames reported in contact (clearance exactly 0, the sigma a contact's
    bound) and the others (Gaussian estimates): counted by hand."""
    from vio_graph.evaluation.safety import score_mode
    from vio_graph.safety.online import SafetyEstimate

    nan = float("nan")
    # 100 Gaussian frames (sigma 4 mm; |error| 0.5 / 1.5 / 2.5 sigma on 70 / 25 / 5 frames)
    # and 50 contact frames (sigma 1 mm; the truth 0.5 mm inside on 30, 2.5 mm on 20)
    z = np.r_[np.full(70, 0.5), np.full(25, 1.5), np.full(5, 2.5)]
    true = np.r_[np.full(100, 0.05), np.full(30, -0.0005), np.full(20, -0.0025)]
    est = np.r_[0.05 + z * 0.004 * np.where(np.arange(100) % 2, 1, -1), np.zeros(50)]
    sig = np.r_[np.full(100, 0.004), np.full(50, 0.001)]
    rest = dict.fromkeys(
        ("nosing_clearance_m", "nosing_sigma_m", "predicted_min_clearance_m", "edge_distance_m")
        + ("predicted_min_nosing_clearance_m", "edge_distance_sigma_m", "mean_rise_m"),
        nan,
    )
    rest |= {"mean_tread_m": nan, "steps_seen": 0, "near_trip_warning": False, "landing": False}
    ests = [
        SafetyEstimate(
            clearance_m=c,
            clearance_sigma_m=s,
            toe_line_xz_m=np.zeros((2, 2)),
            placement=np.full(4, nan),
            **rest,
        )
        for c, s in zip(est, sig, strict=True)
    ]
    n = len(ests)
    truth = {
        "clearance_m": true,
        "nosing_clearance_m": np.full(n, nan),
        "placement": np.full((n, 4), nan),
        "t_dense_s": np.arange(n) * 0.03,
        "near_trip": np.zeros(n, bool),
        "nosing_dense_m": np.full(n, nan),
    }
    block, _ = score_mode(ests, truth, np.arange(n) * 0.03, True)
    assert block["within_1sigma"] == pytest.approx((70 + 30) / 150)
    assert block["within_2sigma"] == pytest.approx((95 + 30) / 150)
    assert block["contact"]["share"] == pytest.approx(50 / 150)
    assert block["contact"]["within_1sigma"] == pytest.approx(0.6)
    assert block["contact"]["within_2sigma"] == pytest.approx(0.6)
    assert block["not_contact"]["within_1sigma"] == pytest.approx(0.70)
    assert block["not_contact"]["within_2sigma"] == pytest.approx(0.95)


@pytest.mark.parametrize("compiled", [False, True])
def test_the_contact_bound_is_for_a_sole_in_a_tread_not_a_foot_in_a_riser(compiled: bool) -> None:
    """safety.non_penetration_sigma 'tread_contact' (default): a swinging foot estimated 2 cm
    into the riser behind it (a horizontal way out: the pose's x error) keeps the truncated
    Gaussian's sigma, while a foot 3 mm into the tread below it (a vertical way out) is a
    contact with the foot outline's; 'contact' bounds both."""
    P_now = np.diag([3.6e-5, 1e-5])
    riser = ([0.48, 0.15], [0.73, 0.15])  # heel 2 cm inside the upper step's column
    tread = ([0.60, 0.147], [0.85, 0.147])  # 3 mm below the lower tread
    out = {}
    for mode in ("contact", "tread_contact", "truncated"):
        for name, (heel, toe) in (("riser", riser), ("tread", tread)):
            cfg = SafetyConfig(non_penetration_sigma=mode, foot_sigma_m=0.001)
            mon = SafetyMonitor(cfg, compiled=compiled)
            _map_down(mon)
            out[mode, name] = mon.update(1.0, [0.3, 0.8], P_now, heel, toe, False)
    for name in ("riser", "tread"):
        assert out["tread_contact", name].clearance_m == 0.0
    q = out["truncated", "riser"].clearance_sigma_m
    assert q > 0.0015  # ~0.3 of the raw sigma (4-8 mm), above the contact's 1 mm
    assert out["tread_contact", "riser"].clearance_sigma_m == q
    assert out["contact", "riser"].clearance_sigma_m == pytest.approx(0.001)
    assert out["truncated", "tread"].clearance_sigma_m > 0.0015  # the bound acts here
    assert out["tread_contact", "tread"].clearance_sigma_m == pytest.approx(0.001)
    assert out["contact", "tread"].clearance_sigma_m == pytest.approx(0.001)
