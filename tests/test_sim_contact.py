"""Simulated foot-contact sensor (contact.csv): load cell and heel / foot switch against the
gait model's true stance (Stride.t_contact_s .. t_toe_off_s). Short trials, small images."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

from vio_graph.errors import ConfigError
from vio_graph.recording import Recording
from vio_graph.sim import load_scenario, simulate_trial
from vio_graph.sim.config import ScenarioConfig
from vio_graph.sim.trial import simulate

DURATION_S = 6.0
WEIGHT_N = 75.0 * 9.81  # default body_mass_kg


def _with_contact(cfg: ScenarioConfig, duration_s: float = DURATION_S, **contact):
    return cfg.model_copy(
        update={"duration_s": duration_s, "contact": cfg.contact.model_copy(update=contact)}
    )


def _stances(trial, end_s: float) -> list[tuple[float, float]]:
    """True stances (contact, toe-off) that lie inside [0, end_s]."""
    return [(s.t_contact_s, s.t_toe_off_s) for s in trial.motion.strides if s.t_toe_off_s < end_s]


def _runs(t: np.ndarray, on: np.ndarray) -> list[tuple[float, float]]:
    """Closed / loaded runs as (first on sample time, first off sample time)."""
    x = np.concatenate([[0], on.astype(np.int8), [0]])
    starts, stops = np.flatnonzero(np.diff(x) == 1), np.flatnonzero(np.diff(x) == -1)
    tt = np.concatenate([t, [np.inf]])
    return [(float(tt[a]), float(tt[b])) for a, b in zip(starts, stops, strict=True)]


@pytest.fixture(scope="module")
def upstair() -> ScenarioConfig:
    return load_scenario("upstair")


def test_default_has_no_contact_and_other_streams_do_not_change(upstair) -> None:
    off = simulate_trial(_with_contact(upstair), 1)
    assert off.contact is None and off.metadata.contact is None
    assert "contact" not in off.metadata.provenance.config  # saved config as before
    on = simulate_trial(_with_contact(upstair, kind="load_cell"), 1)
    assert (
        on.contact is not None and on.metadata.provenance.config["contact"]["kind"] == "load_cell"
    )
    # the sensor draws from its own random stream: every other stream is identical
    for a, b in (
        (off.imu.accel_mps2, on.imu.accel_mps2),
        (off.imu.quat_wxyz, on.imu.quat_wxyz),
        (off.joints.knee_rad, on.joints.knee_rad),
        (off.frame_timestamps_s, on.frame_timestamps_s),
        (
            off.groundtruth.trajectories["toe"].position_m,
            on.groundtruth.trajectories["toe"].position_m,
        ),
    ):
        assert np.array_equal(a, b)


def test_config_rejects_unknown_contact_kind(tmp_path: Path) -> None:
    bad = tmp_path / "bad.yaml"
    bad.write_text("duration_s: 2.0\ncontact: {kind: pressure_mat}\n")
    with pytest.raises(ConfigError, match="contact.kind"):
        load_scenario(bad)


def test_switch_closed_exactly_during_true_stance_within_delay(upstair) -> None:
    delay_s, rate_hz = 0.01, 200.0
    trial = simulate_trial(
        _with_contact(
            upstair, kind="switch", switch_bounce_s=0.0, switch_delay_s=delay_s, rate_hz=rate_hz
        ),
        3,
    )
    c = trial.contact
    assert trial.metadata.contact.kind == "switch" and trial.metadata.contact.threshold_n == 0.5
    assert set(np.unique(c.force_n)) == {0.0, 1.0}
    assert np.array_equal(c.loaded, c.force_n == 1.0)
    stances = _stances(trial, DURATION_S - 0.1)
    assert len(stances) >= 4
    runs = _runs(c.timestamp_s, c.loaded)
    # one closed run per stance (the last run may be cut by the trial end)
    assert len(runs[: len(stances)]) == len(stances)
    period = 1.0 / rate_hz
    for (tc, to), (close, open_) in zip(stances, runs, strict=False):
        # closes once the force passes the 30 N actuation (< 60 ms into the weight transfer)
        # plus the delay; opens when it drops below it again, before toe-off plus the delay
        assert tc + delay_s <= close <= tc + delay_s + 0.06 + period
        assert to + delay_s - 0.06 <= open_ <= to + delay_s + period
    # open through every swing
    swing = np.zeros(c.timestamp_s.size, dtype=bool)
    for (_, to), (tc_next, _) in zip(stances, stances[1:], strict=False):
        swing |= (c.timestamp_s > to + delay_s + period) & (c.timestamp_s < tc_next + delay_s)
    assert swing.sum() > 100 and not c.loaded[swing].any()


def test_switch_bounce_only_right_after_transitions(upstair) -> None:
    bounce_s = 0.008
    kw = dict(kind="switch", rate_hz=1000.0, switch_delay_s=0.0)
    clean = simulate_trial(_with_contact(upstair, switch_bounce_s=0.0, **kw), 3).contact
    noisy = simulate_trial(
        _with_contact(upstair, switch_bounce_s=bounce_s, switch_max_bounces=3, **kw), 3
    ).contact
    assert np.array_equal(clean.timestamp_s, noisy.timestamp_s)
    differ = clean.loaded != noisy.loaded
    assert differ.any()  # some bounce happened
    edges = clean.timestamp_s[np.flatnonzero(np.diff(clean.loaded.astype(np.int8))) + 1]
    t_diff = clean.timestamp_s[differ]
    since_edge = t_diff - edges[np.searchsorted(edges, t_diff, side="right") - 1]
    assert since_edge.max() < bounce_s + 1e-9


def test_heel_switch_closes_at_foot_flat_after_forefoot_landing(upstair) -> None:
    trial = simulate_trial(
        _with_contact(
            upstair,
            kind="switch",
            switch_region="heel",
            switch_bounce_s=0.0,
            switch_delay_s=0.0,
            rate_hz=500.0,
        ),
        3,
    )
    c = trial.contact
    toe_landings = [
        s for s in trial.motion.strides if s.landing == "toe" and s.t_toe_off_s < DURATION_S - 0.1
    ]
    assert len(toe_landings) >= 3  # stair ascent: forefoot landings
    for s in toe_landings:
        stance = (c.timestamp_s >= s.t_contact_s) & (c.timestamp_s <= s.t_toe_off_s)
        closed_t = c.timestamp_s[stance & c.loaded]
        assert closed_t.size > 0
        assert closed_t.min() >= s.t_flat_s - 1e-9  # forefoot loading: heel still in the air
        assert closed_t.max() <= s.t_heel_off_s + 1e-9  # heel-off opens it


def test_load_cell_tracks_body_weight_during_true_stance(upstair) -> None:
    trial = simulate_trial(_with_contact(upstair, kind="load_cell"), 2)
    c, meta = trial.contact, trial.metadata.contact
    assert meta.kind == "load_cell" and meta.threshold_n == 80.0
    assert np.array_equal(c.loaded, c.force_n >= 80.0)
    assert c.timestamp_s[0] == 0.0 and np.allclose(np.diff(c.timestamp_s), 0.01)
    stances = _stances(trial, DURATION_S - 0.1)
    assert len(stances) >= 4
    ramp_s, lag_s = 0.1, 0.05  # weight transfer to the threshold; filter + delay (~15 ms)
    in_stance = np.zeros(c.timestamp_s.size, dtype=bool)
    for tc, to in stances:
        m = (c.timestamp_s >= tc) & (c.timestamp_s <= to)
        in_stance |= (c.timestamp_s >= tc) & (c.timestamp_s <= to + lag_s)
        core = (c.timestamp_s >= tc + ramp_s) & (c.timestamp_s <= to - ramp_s)
        assert c.loaded[core].all()  # loaded through the stance except the ramps
        # first loaded sample within the ramp after contact
        first = c.timestamp_s[m & c.loaded].min()
        assert tc < first <= tc + ramp_s
        # vertical force: humps above body weight, a dip below it at mid-stance
        assert 1.0 * WEIGHT_N < c.force_n[m].max() < 1.3 * WEIGHT_N
        mid = np.abs(c.timestamp_s - 0.5 * (tc + to)) < 0.02
        assert 0.7 * WEIGHT_N < c.force_n[mid].mean() < 0.95 * WEIGHT_N
    # swing: unloaded, the force is offset + noise around 0 N
    swing = ~in_stance & (c.timestamp_s < stances[-1][1])
    assert swing.sum() > 50
    assert not c.loaded[swing].any()
    assert np.abs(c.force_n[swing]).max() < 40.0


def test_load_cell_shares_weight_during_standing_pauses() -> None:
    cfg = load_scenario("upstair_step_to_step_slow")
    trial = simulate_trial(
        _with_contact(
            cfg,
            duration_s=10.0,
            kind="load_cell",
            load_cell_noise_sd_n=0.0,
            load_cell_offset_sd_n=0.0,
        ),
        1,
    )
    holds = [h for h in trial.motion.holds_s if h[1] < 10.0]
    assert holds
    c = trial.contact
    for a, b in holds:
        m = (c.timestamp_s > a + 0.1) & (c.timestamp_s < b)
        assert m.sum() > 100
        np.testing.assert_allclose(c.force_n[m], 0.5 * WEIGHT_N, rtol=0.02)


def test_simulated_contact_round_trips_through_the_recording(upstair, tmp_path: Path) -> None:
    cfg = _with_contact(upstair, duration_s=1.5, kind="switch")
    cfg = cfg.model_copy(
        update={"camera": cfg.camera.model_copy(update={"width_px": 32, "height_px": 24})}
    )
    out = simulate(cfg, 4, tmp_path / "rec")
    rec = Recording.open(out)
    want = simulate_trial(cfg, 4).contact
    assert rec.metadata.contact is not None and rec.metadata.contact.kind == "switch"
    assert rec.contact is not None
    np.testing.assert_allclose(rec.contact.timestamp_s, want.timestamp_s, atol=1e-9)
    assert np.array_equal(rec.contact.force_n, want.force_n)
    assert np.array_equal(rec.contact.loaded, want.loaded)
