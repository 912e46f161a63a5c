"""Foot-contact sensor of the instrumented leg: pylon load cell or heel / foot switch.

The truth is the gait model's stance of the instrumented foot (``Stride.t_contact_s`` ..
``Stride.t_toe_off_s``). Over each stance the foot carries a share of body weight
(:func:`load_share`): it rises over the initial double support after contact, falls over the
terminal double support before toe-off (the contralateral foot's contact to toe-off) and has
the two humps and mid-stance dip of the vertical ground reaction force in between. Standing
pauses (``LegMotion.holds_s``) share the weight equally between the feet.

The sensors (:func:`simulate_contact`) turn that load into the ``contact.csv`` channel:

- ``load_cell``: axial force in N = share x body weight, first-order low-pass + transport
  delay (the amplifier and its filter), a per-trial zero offset and white noise;
- ``switch``: 1 while the force under the switch (whole sole, or the heel only) is at or above
  its actuation force, shifted by the switch delay, with contact bounce (a few short opposite
  pulses) just after every transition.

Numbers and sources: docs/simulator.md ("Foot contact").
"""

from __future__ import annotations

import numpy as np
from numpy.typing import NDArray

from vio_graph.recording.metadata import ContactModel
from vio_graph.recording.streams import ContactTable
from vio_graph.sim.config import ContactConfig
from vio_graph.sim.gait import LegMotion

GRAVITY_MPS2 = 9.81
GRID_DT_S = 1e-3  # internal time grid of the sensor models (1 kHz)
SWITCH_THRESHOLD_N = 0.5  # a switch channel holds 0 / 1: loaded at or above 0.5
MIN_RAMP_FRACTION = 0.05  # weight-transfer ramps last at least this fraction of the stance
MAX_RAMP_FRACTION = 0.45  # ... and at most this (loading and unloading must not overlap)


def _smoothstep(x: NDArray) -> NDArray[np.float64]:
    """C1 ramp 0 -> 1 over x in [0, 1] (clipped outside)."""
    x = np.clip(x, 0.0, 1.0)
    return x * x * (3.0 - 2.0 * x)


def transfer_time_s(t_contact_s: float, t_toe_off_s: float, t_contra_contact_s: float) -> float:
    """Duration of the weight-transfer ramps of one stance, s: the terminal double support
    (contralateral contact to toe-off) when the contralateral foot lands inside the stance,
    else 15 % of the stance; clipped to 5-45 % of the stance."""
    stance = t_toe_off_s - t_contact_s
    if t_contact_s < t_contra_contact_s < t_toe_off_s:
        d = t_toe_off_s - t_contra_contact_s
    else:
        d = 0.15 * stance
    return float(np.clip(d, MIN_RAMP_FRACTION * stance, MAX_RAMP_FRACTION * stance))


def motion_time_s(motion: LegMotion, t_s: NDArray | float) -> NDArray[np.float64]:
    """Real time minus the standing pauses before it (constant through a pause), so that a
    pause does not stretch the weight-transfer ramps."""
    t = np.asarray(t_s, dtype=float)
    u = t.copy()
    for a, b in motion.holds_s:
        u = u - np.clip(t - a, 0.0, b - a)
    return u


def load_share(
    motion: LegMotion, t_s: NDArray, dip_fraction: float = 0.15, pause_ramp_s: float = 0.4
) -> NDArray[np.float64]:
    """Share of body weight (0 in swing, ~1 in single support) on the instrumented foot."""
    t = np.asarray(t_s, dtype=float)
    u = motion_time_s(motion, t)
    w = np.zeros(t.shape)
    stance = np.zeros(t.shape, dtype=bool)
    for s in motion.strides:
        m = (t >= s.t_contact_s) & (t <= s.t_toe_off_s)
        if not m.any():
            continue
        tc, to, tcc = (
            float(motion_time_s(motion, x))
            for x in (s.t_contact_s, s.t_toe_off_s, s.t_contra_contact_s)
        )
        d = transfer_time_s(tc, to, tcc)
        x = u[m]
        up = _smoothstep((x - tc) / d)
        down = _smoothstep((to - x) / d)
        # vertical ground reaction force: humps at 25 % and 75 % of the stance (loading
        # response, push-off), a dip at mid-stance; the ramps take it to zero at the ends
        shape = 1.0 - dip_fraction * np.cos(4.0 * np.pi * (x - tc) / (to - tc))
        w[m] = up * down * shape
        stance |= m
    if motion.holds_s:  # standing pause: both feet flat, weight shared equally
        h = np.zeros(t.shape)
        for a, b in motion.holds_s:
            into = _smoothstep((t - (a - pause_ramp_s)) / pause_ramp_s)
            out = _smoothstep(((b + pause_ramp_s) - t) / pause_ramp_s)
            h = np.maximum(h, np.minimum(into, out))
        h = np.where(stance, h, 0.0)
        w = (1.0 - h) * w + h * 0.5
    return w


def _first_order_lowpass(x: NDArray, dt_s: float, tau_s: float) -> NDArray[np.float64]:
    """y' = (x - y) / tau, exact for a piecewise-constant input, y(0) = x(0)."""
    if tau_s <= 0:
        return np.asarray(x, dtype=float).copy()
    from scipy.signal import lfilter

    a = 1.0 - np.exp(-dt_s / tau_s)
    y, _ = lfilter([a], [1.0, a - 1.0], x, zi=[(1.0 - a) * x[0]])
    return y


def _bounce(
    state: NDArray[np.bool_], cfg: ContactConfig, rng: np.random.Generator
) -> NDArray[np.bool_]:
    """Contact bounce: after each transition of ``state`` (1 kHz grid), up to
    ``switch_max_bounces`` short pulses back to the previous state within
    ``switch_bounce_s``."""
    out = state.copy()
    n_win = int(round(cfg.switch_bounce_s / GRID_DT_S))
    if n_win < 2 or cfg.switch_max_bounces == 0:
        return out
    for k in np.flatnonzero(state[1:] != state[:-1]) + 1:
        for _ in range(int(rng.integers(0, cfg.switch_max_bounces + 1))):
            start = k + int(rng.integers(0, n_win - 1))
            width = int(rng.integers(1, max(2, n_win // 3) + 1))
            stop = min(start + width, k + n_win, out.size)
            out[start:stop] = state[k - 1]
    return out


def simulate_contact(
    motion: LegMotion,
    cfg: ContactConfig,
    duration_s: float,
    rng: np.random.Generator,
    pause_ramp_s: float = 0.4,
) -> tuple[ContactTable, ContactModel]:
    """The contact channel of one trial (``cfg.kind`` must not be ``none``)."""
    if cfg.kind == "none":
        raise ValueError("simulate_contact needs contact.kind load_cell or switch")
    weight_n = cfg.body_mass_kg * GRAVITY_MPS2
    grid = np.arange(0.0, duration_s + 0.1, GRID_DT_S)
    force = weight_n * load_share(motion, grid, cfg.grf_dip_fraction, pause_ramp_s)
    period = 1.0 / cfg.rate_hz
    t = np.arange(0.0, duration_s + 0.5 * period, period)
    t = t[t <= duration_s + 1e-9]
    if cfg.kind == "load_cell":
        filtered = _first_order_lowpass(force, GRID_DT_S, cfg.load_cell_filter_tau_s)
        value = np.interp(t - cfg.load_cell_delay_s, grid, filtered)
        offset = rng.normal(0.0, cfg.load_cell_offset_sd_n)
        value = value + offset + rng.normal(0.0, cfg.load_cell_noise_sd_n, t.size)
        threshold = cfg.threshold_n
    else:
        if cfg.switch_region == "heel":
            force = force * motion.stance_mask(grid, "heel")
        closed = _bounce(force >= cfg.switch_actuation_n, cfg, rng)
        idx = np.floor((t - cfg.switch_delay_s) / GRID_DT_S + 1e-9).astype(np.int64)
        value = np.where(idx >= 0, closed[np.clip(idx, 0, grid.size - 1)], False).astype(float)
        threshold = SWITCH_THRESHOLD_N
    table = ContactTable(t, value, value >= threshold)
    return table, ContactModel(kind=cfg.kind, threshold_n=threshold)
