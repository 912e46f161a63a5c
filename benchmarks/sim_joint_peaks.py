"""Joint-angle peaks of the simulated gait against published values (docs/simulator.md).

For each scenario and seed: the peak knee and hip flexion and the ankle range (deg) over the
steady strides (tread to tread over two risers on stairs, every stride on level ground; a
stride whose landing lies past the motion's end is left out), the same over the whole
motion, from the leg motion itself (no recording). The steady-stride rule is the one of
tests/test_sim.py::test_joint_angle_peaks_near_published_values.

Usage::

    python benchmarks/sim_joint_peaks.py [--seeds 1 3] [--swing joint_space|via_points]
"""

from __future__ import annotations

import argparse

import numpy as np

from vio_graph.sim import load_scenario
from vio_graph.sim.gait import simulate_gait
from vio_graph.sim.terrain import build_terrain

SCENARIOS = ("upstair", "downstair", "level", "prosthesis_upstair", "obstacle")


def steady_mask(m, name: str) -> np.ndarray:
    """Samples of steady strides (see the module docstring)."""
    mask = np.zeros(m.t_s.size, dtype=bool)
    for s in m.strides:
        dz = s.next_toe_xz_m[1] - s.toe_xz_m[1]
        steady = s.arrive_kind == s.swing_kind and (name == "level" or abs(dz) > 0.2)
        if steady and s.t_next_s <= m.t_s[-1]:
            mask |= (m.t_s >= s.t_contact_s) & (m.t_s < s.t_next_s)
    return mask


def peaks(name: str, seed: int, swing: str | None) -> dict[str, float]:
    cfg = load_scenario(name)
    if swing is not None:
        cfg = cfg.model_copy(update={"gait": cfg.gait.model_copy(update={"swing_model": swing})})
    terrain = build_terrain(cfg.terrain)
    m = simulate_gait(terrain, cfg.gait, cfg.rig, cfg.duration_s, np.random.default_rng(seed))
    knee, hip, ankle = (np.degrees(a) for a in (m.knee_rad, m.thigh_pitch_rad, m.ankle_rad))
    mask = steady_mask(m, name)
    out = {"steady_share": float(mask.mean())}
    for key, sel in (("steady", mask), ("all", np.ones_like(mask))):
        if not sel.any():
            continue
        out[f"{key}_knee"] = float(knee[sel].max())
        out[f"{key}_hip"] = float(hip[sel].max())
        out[f"{key}_ankle_min"] = float(ankle[sel].min())
        out[f"{key}_ankle_max"] = float(ankle[sel].max())
    return out


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--seeds", type=int, nargs="+", default=[1, 3])
    ap.add_argument("--swing", choices=["joint_space", "via_points"], default=None)
    args = ap.parse_args()
    cols = ("steady knee", "steady hip", "steady ankle", "whole knee", "whole hip", "whole ankle")
    print("| scenario | seed | " + " | ".join(cols) + " |")
    print("|---|---|---|---|---|---|---|---|")
    for name in SCENARIOS:
        for seed in args.seeds:
            p = peaks(name, seed, args.swing)
            cells = []
            for key in ("steady", "all"):
                if f"{key}_knee" not in p:
                    cells += ["-", "-", "-"]
                    continue
                cells += [
                    f"{p[f'{key}_knee']:.0f}",
                    f"{p[f'{key}_hip']:.0f}",
                    f"{p[f'{key}_ankle_min']:.0f}..{p[f'{key}_ankle_max']:.0f}",
                ]
            print(f"| {name} | {seed} | " + " | ".join(cells) + " |")


if __name__ == "__main__":
    main()
