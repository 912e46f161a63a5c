"""Peak shank IMU motion of the generalisation sweep's conditions, against the simulator's
plausibility bound (vio_graph.sim.plausibility).

For each sweep condition (vio_graph/sweep.py) and seed, from the simulated leg motion itself
(no recording, no sensor noise or clipping; analytic at the 1 kHz gait samples over the
trial): the peak and p99 of the specific force's norm at the IMU point (g), the time of the
peak, the IMU point's peak speed (m/s) and the instrumented leg's swing kinds. The gait is
simulated without the plausibility check, so conditions above the bound are listed, flagged,
instead of raising. ``--step-on-depth-m`` overrides ``gait.obstacle_step_on_depth_m`` (e.g.
0.6 to step over the 25 x 50 cm platform, as before the rule existed); ``--obstacle H D``
the obstacle's height and depth (m) of obstacle conditions.

Usage::

    python benchmarks/sim_shank_peaks.py --condition obstacle_25x50 --seeds 1000 1001 1002
    python benchmarks/sim_shank_peaks.py --seeds 1000          # every condition, ~1 min
    python benchmarks/sim_shank_peaks.py --condition obstacle_25x50 --obstacle 0.14 0.38 \
        --step-on-depth-m 0.6 --seeds 1000 1002

Prints a markdown table.
"""

from __future__ import annotations

import argparse

import numpy as np

from vio_graph.sim.gait import simulate_gait
from vio_graph.sim.plausibility import MAX_SHANK_SPECIFIC_FORCE_G, shank_specific_force_g
from vio_graph.sim.terrain import build_terrain
from vio_graph.sim.trial import _rng, rig_transforms
from vio_graph.sweep import SWEEP_CONDITIONS, condition_by_name, condition_scenario


def shank_peaks(
    name: str,
    seed: int,
    step_on_depth_m: float | None = None,
    obstacle_m: tuple[float, float] | None = None,
) -> dict:
    """The figures of one sweep condition and seed (see the module docstring)."""
    cfg = condition_scenario(condition_by_name(name))
    if obstacle_m is not None and cfg.terrain.kind == "obstacle":
        size = {"obstacle_height_m": obstacle_m[0], "obstacle_depth_m": obstacle_m[1]}
        cfg = cfg.model_copy(update={"terrain": cfg.terrain.model_copy(update=size)})
    if step_on_depth_m is not None:
        gait = cfg.gait.model_copy(update={"obstacle_step_on_depth_m": step_on_depth_m})
        cfg = cfg.model_copy(update={"gait": gait})
    terrain = build_terrain(cfg.terrain, _rng(seed, "terrain"))
    m = simulate_gait(terrain, cfg.gait, cfg.rig, cfg.duration_s, _rng(seed, "gait"))
    _, _, imu_xz = rig_transforms(cfg.rig)
    t, force_g = shank_specific_force_g(m, imu_xz, cfg.duration_s)
    v = m.shank_point(t, imu_xz, 1)
    kinds = [s.swing_kind for s in m.strides if s.t_toe_off_s < cfg.duration_s]
    return {
        "peak_g": float(force_g.max()),
        "t_peak_s": float(t[int(np.argmax(force_g))]),
        "p99_g": float(np.percentile(force_g, 99)),
        "speed_peak_mps": float(np.hypot(v[:, 0], v[:, 1]).max()),
        "swings": [k for i, k in enumerate(kinds) if i == 0 or k != kinds[i - 1]],
    }


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--condition", action="append", help="sweep condition (repeatable)")
    ap.add_argument("--seeds", type=int, nargs="+", default=[1000])
    ap.add_argument("--step-on-depth-m", type=float, default=None)
    ap.add_argument("--obstacle", type=float, nargs=2, metavar=("H", "D"), default=None)
    args = ap.parse_args(argv)
    names = args.condition or [c.name for c in SWEEP_CONDITIONS]
    print(
        "| condition | seed | specific force peak (g) | at (s) | p99 (g) | IMU speed peak (m/s) "
        "| swings | bound |"
    )
    print("|---|---|---|---|---|---|---|---|")
    for name in names:
        for seed in args.seeds:
            s = shank_peaks(name, seed, args.step_on_depth_m, args.obstacle)
            ok = "ok" if s["peak_g"] <= MAX_SHANK_SPECIFIC_FORCE_G else "**over**"
            print(
                f"| {name} | {seed} | {s['peak_g']:.1f} | {s['t_peak_s']:.2f} "
                f"| {s['p99_g']:.2f} | {s['speed_peak_mps']:.2f} | {' '.join(s['swings'])} "
                f"| {ok} |"
            )
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
