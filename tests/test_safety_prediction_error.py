"""The near-trip warning discounts a prediction the monitor has measured to be wrong
(vio_graph/safety/prediction_error.py, SafetyConfig.warning_error_check): known errors are
measured exactly, a swing unlike its template does not warn from the template's wrong path,
and the compiled and numpy monitors agree."""

from __future__ import annotations

import numpy as np
import pytest

from vio_graph.safety.clearance import HeightProfile
from vio_graph.safety.config import SafetyConfig
from vio_graph.safety.online import SafetyMonitor
from vio_graph.safety.prediction_error import PredictionErrors

# flat floor, then a 5 cm step up at x 0.95 m (an edge at (0.95, 0.05))
STEP_UP = [(-1.0, 0.0), (0.95, 0.0), (0.95, 0.05), (2.0, 0.05)]
DT = 1 / 30


def test_known_prediction_errors_are_measured_exactly() -> None:
    """A prediction that the foot stands still while it moves at 0.1 m/s in x is wrong by
    0.1 m/s x h at each horizon step; the steps up to 2 cm of error are trusted."""
    h = np.linspace(0.0, 0.3, 11)  # steps of 30 ms
    pe = PredictionErrors(h, capacity=4)  # (grows: 10 predictions kept at once)
    pe.start_swing()
    foot0 = np.array([0.0, 0.0, 0.25, 0.0])
    for k in range(25):
        t = k * DT
        foot = foot0 + np.array([0.1, 0.0, 0.1, 0.0]) * t
        pe.observe(t, tuple(foot.tolist()))
        pe.predict(t, np.repeat(foot[None], len(h), 0))  # "the foot stays where it is"
    rms = pe.rms()
    assert np.isnan(rms[0])  # the current pose is never scored
    np.testing.assert_allclose(rms[1:], 0.1 * h[1:], rtol=1e-9)
    assert pe.trusted_steps(0.02) == 6  # 0.1 m/s x 0.18 s = 1.8 mm ... 0.21 s: 2.1 cm
    pe.start_swing()  # a new swing: nothing measured yet, every step trusted
    assert np.all(np.isnan(pe.rms())) and pe.trusted_steps(0.02) == 10


def _keyframes(mon: SafetyMonitor, rng: np.random.Generator) -> None:
    xs = np.linspace(-0.2, 1.6, 400)
    prof = HeightProfile.from_polyline(STEP_UP)
    z = np.array([prof.z_m[np.clip(np.searchsorted(prof.x_hi_m, x), 0, len(prof) - 1)] for x in xs])
    cam = np.array([0.0, 0.5])
    for k in range(3):
        pts = np.stack([xs, z + rng.normal(0, 0.0005, xs.size)], 1) - cam
        mon.update(0.01 * k, cam, np.eye(2) * 1e-6, [-0.5, 0.2], [-0.25, 0.2], False, pts)


def _toe(s: float, x0: float, rise_m: float, up_m: float) -> np.ndarray:
    """Toe of a 0.5 s, 0.6 m swing at fraction s: forward (smooth), rising ``rise_m`` and
    back, ending ``up_m`` higher."""
    p = 10 * s**3 - 15 * s**4 + 6 * s**5
    return np.array([x0 + 0.6 * p, rise_m * np.sin(np.pi * s) + up_m * p])


def _two_swings(cfg: SafetyConfig, compiled: bool) -> list:
    """A shuffling swing on the floor (toe 1 cm up: the template), then a swing that steps
    onto the 5 cm step with the toe 15 cm up; the second swing's estimates."""
    mon = SafetyMonitor(cfg, compiled=compiled)
    _keyframes(mon, np.random.default_rng(4))
    t, out = 10.0, []
    for i, (x0, rise, up) in enumerate([(0.0, 0.01, 0.0), (0.6, 0.15, 0.05)]):
        for _ in range(6):  # stance
            toe = _toe(0.0, x0, rise, up)
            mon.update(t, [0, 0.5], np.eye(2) * 1e-6, toe - [0.25, 0], toe, True)
            t += DT
        for tau in np.arange(DT, 0.5 + DT / 2, DT):
            toe = _toe(min(tau / 0.5, 1.0), x0, rise, up)
            s = mon.update(t, [0, 0.5], np.eye(2) * 1e-6, toe - [0.25, 0], toe, False)
            if i == 1:
                out.append(s)
            t += DT
    return out


def test_a_swing_unlike_its_template_is_discounted() -> None:
    """The shuffle's template predicts the high step's toe running into the riser (a
    predicted penetration: the unchecked monitor warns on the swing's first two frames);
    the real toe passes 13 cm above the edge. The check measures the template's error on
    this swing from its second frame on and stops testing the steps it got wrong: only the
    lift-off frame, with nothing measured yet, warns."""
    unchecked = _two_swings(SafetyConfig(min_keyframes=2, warning_error_check=False), False)
    assert unchecked[0].predicted_min_nosing_clearance_m < 0
    assert [s.near_trip_warning for s in unchecked[:3]] == [True, True, False]
    checked = _two_swings(SafetyConfig(min_keyframes=2), False)
    assert checked[0].near_trip_warning  # lift-off: no error measured in this swing yet
    assert not any(s.near_trip_warning for s in checked[1:])
    # only the steps it measured right are tested: the first 15 ms (of 20 steps over 0.3 s)
    # for a few frames, far from the riser, then none (NaN)
    tested = np.array([s.near_trip_clearance_m for s in checked[1:]])
    assert not np.any(tested < 0.1) and np.isnan(tested[-1])
    # what the warning does not test is no other output: the predictions stay as they were
    for a, b in zip(unchecked, checked, strict=True):
        assert a.predicted_min_nosing_clearance_m == b.predicted_min_nosing_clearance_m or (
            np.isnan(a.predicted_min_nosing_clearance_m)
            and np.isnan(b.predicted_min_nosing_clearance_m)
        )
        assert a.clearance_m == b.clearance_m or np.isnan(a.clearance_m + b.clearance_m)


def test_compiled_monitor_discounts_as_the_numpy_one() -> None:
    """The discounted warning's clearance is the same, within 1e-9 m, with the compiled
    kernels as in numpy, frame by frame."""
    pytest.importorskip("numba")
    cfg = SafetyConfig(min_keyframes=2)
    ref, comp = _two_swings(cfg, False), _two_swings(cfg, True)
    a = np.array([s.near_trip_clearance_m for s in ref])
    b = np.array([s.near_trip_clearance_m for s in comp])
    np.testing.assert_array_equal(np.isnan(a), np.isnan(b))
    np.testing.assert_allclose(b[np.isfinite(b)], a[np.isfinite(a)], rtol=0, atol=1e-9)
    assert [s.near_trip_warning for s in ref] == [s.near_trip_warning for s in comp]


def test_compiled_scoring_equals_the_numpy_scoring() -> None:
    """``observe`` through the compiled kernel (``observe_errors``) leaves the same sums,
    counts, kept rows and trusted steps as numpy, to the bit, over swings of noisy
    predictions with frames at jittered times (some instants between frames, some rows
    dropped, the rows growing past their capacity)."""
    compiled = pytest.importorskip("vio_graph.safety.compiled")
    rng = np.random.default_rng(3)
    h = np.linspace(0.0, 0.3, 11)
    ref, comp = PredictionErrors(h, capacity=2), PredictionErrors(h, 2, kernels=compiled)
    t, n_scored, steps_seen = 0.0, 0, set()
    for _swing in range(4):
        for pe in (ref, comp):
            pe.start_swing()
        for _ in range(30):
            t += DT * rng.uniform(0.3, 1.7)
            foot = tuple(rng.normal(0.0, 0.1, 4).tolist())
            poses = np.asarray(foot)[None] + rng.normal(0.0, 0.02, (len(h), 4))
            for pe in (ref, comp):
                pe.observe(t, foot)
                pe.predict(t, poses)
            np.testing.assert_array_equal(comp._sums, ref._sums)
            np.testing.assert_array_equal(comp._counts, ref._counts)
            np.testing.assert_array_equal(comp._t, ref._t)
            assert comp._kept == ref._kept
            for bound in (0.01, 0.03, 0.1, 0.13, 0.16, 0.2, 0.3):  # (compiled: Python floats)
                m = comp.trusted_steps(bound)
                assert m == ref.trusted_steps(bound)
                steps_seen.add(m)
        n_scored += int(ref._counts.sum())
    assert n_scored > 100 and len(ref._t) > 2  # instants were scored; the rows grew
    assert len(steps_seen) >= 5  # (first untrusted steps all over the horizon)


def _swings(cfg: SafetyConfig, compiled: bool, swings: list[tuple[float, float, float]]) -> list:
    """:func:`_two_swings` with the swings (lift-off toe x, rise, end height) given; the
    last swing's estimates."""
    mon = SafetyMonitor(cfg, compiled=compiled)
    _keyframes(mon, np.random.default_rng(4))
    t, out = 10.0, []
    for i, (x0, rise, up) in enumerate(swings):
        for _ in range(6):  # stance
            toe = _toe(0.0, x0, rise, up)
            mon.update(t, [0, 0.5], np.eye(2) * 1e-6, toe - [0.25, 0], toe, True)
            t += DT
        for tau in np.arange(DT, 0.5 + DT / 2, DT):
            toe = _toe(min(tau / 0.5, 1.0), x0, rise, up)
            s = mon.update(t, [0, 0.5], np.eye(2) * 1e-6, toe - [0.25, 0], toe, False)
            if i == len(swings) - 1:
                out.append(s)
            t += DT
    return out


@pytest.mark.parametrize("compiled", [False, True])
def test_lift_off_is_not_warned_from_disagreeing_templates(compiled: bool) -> None:
    """Two shuffles and a high step as templates: at the high step's lift-off their median
    (a shuffle) runs the toe into the riser, and with nothing measured yet the check lets it
    warn; with ``warning_template_spread`` the steps where the templates disagree by more
    than near_trip_m are not tested (the shuffles and the high step part by up to 14 cm).
    From the next frame on ``template_match`` keeps the high step alone, 12.7 cm clear."""
    if compiled:
        pytest.importorskip("numba")
    swings = [(-0.6, 0.01, 0.0), (-0.6, 0.01, 0.0), (-0.6, 0.15, 0.05), (0.6, 0.15, 0.05)]
    off = _swings(SafetyConfig(min_keyframes=2), compiled, swings)
    on = _swings(SafetyConfig(min_keyframes=2, warning_template_spread=True), compiled, swings)
    assert off[0].predicted_min_nosing_clearance_m < 0 and off[0].near_trip_warning
    assert not any(s.near_trip_warning for s in on)
    assert on[0].near_trip_clearance_m > 0.1
    for a, b in zip(off[1:], on[1:], strict=True):  # later frames: measured, the same
        assert a.near_trip_warning == b.near_trip_warning
    assert abs(on[1].near_trip_clearance_m - 0.127) < 0.001
