"""How violent are simulated swings? Camera point, knee, toe clearance, per swing model.

Computed from the simulated leg motion itself (no recording, no sensor noise or clipping):
for each scenario (``path[:seed[:cadence_scale]]``) and each ``gait.swing_model``, over the
trial's duration: the camera point's peak speed (m/s) and share of samples above 3 m/s, its
specific force (norm of acceleration minus gravity, analytic from the motion's splines) p99
and peak in g and share above 4 g, the peak knee angular rate (deg/s) and flexion (deg), the
lowest sole-terrain gap (mm, negative = penetration) and the toe's clearance above each
nosing / obstacle edge it passes over in swing (mm; per edge crossing, lowest first).

Usage::

    python benchmarks/sim_swing_stats.py configs/upstair.yaml configs/level.yaml:1:1.2

Prints a markdown table (one row per scenario and swing model).
"""

from __future__ import annotations

import argparse
from pathlib import Path

import numpy as np

from vio_graph.geometry import GRAVITY_MPS2
from vio_graph.sim.config import load_scenario
from vio_graph.sim.trial import _terrain_and_gait

SPEED_LIMIT_MPS = 3.0
FORCE_LIMIT_G = 4.0
MODELS = ("via_points", "joint_space")


def parse_spec(spec: str) -> tuple[str, int, float | None]:
    """``path[:seed[:cadence_scale]]`` -> (path, seed (1), cadence_scale (None: the file's))."""
    path, _, rest = spec.partition(":")
    parts = rest.split(":") if rest else []
    if len(parts) > 2:
        raise ValueError(f"{spec!r}: expected path[:seed[:cadence_scale]]")
    seed = int(parts[0]) if parts else 1
    cadence = float(parts[1]) if len(parts) == 2 else None
    return path, seed, cadence


def swing_stats(path: str | Path, seed: int, swing_model: str, cadence: float | None = None):
    """The figures of one scenario under one swing model (see the module docstring)."""
    cfg = load_scenario(path)
    upd: dict = {"swing_model": swing_model}
    if cadence is not None:
        upd["cadence_scale"] = cadence
    cfg = cfg.model_copy(update={"gait": cfg.gait.model_copy(update=upd)})
    terrain, m = _terrain_and_gait(cfg, seed)
    t = m.t_s[(m.t_s > 0.05) & (m.t_s < cfg.duration_s)]
    cam = np.asarray(cfg.rig.camera_in_shank_xz_m)
    v = m.shank_point(t, cam, 1)
    a = m.shank_point(t, cam, 2)
    speed = np.hypot(v[:, 0], v[:, 1])
    force_g = np.hypot(a[:, 0], a[:, 1] + GRAVITY_MPS2) / GRAVITY_MPS2
    keep = m.t_s < cfg.duration_s
    knee_rate = np.degrees(np.abs(np.gradient(m.knee_rad, m.t_s)))[keep]
    fr = np.linspace(0.0, 1.0, 15)
    sole = (
        m.heel_xz_m[:, None, :] * (1 - fr[None, :, None])
        + m.toe_xz_m[:, None, :] * fr[None, :, None]
    )
    gap = sole[..., 1] - terrain.height_at(sole[..., 0].ravel()).reshape(sole.shape[:2])
    swing = ~(m.stance_mask(m.t_s, "heel") | m.stance_mask(m.t_s, "toe")) & keep
    toe = m.toe_xz_m
    crossings = []
    for xe, ze in terrain.edges_xz_m:
        d = toe[:, 0] - xe
        k = np.flatnonzero((d[:-1] < 0) & (d[1:] >= 0) & swing[:-1] & swing[1:])
        crossings += [float(toe[i, 1] - ze) for i in k]
    return {
        "peak_speed_mps": float(speed.max()),
        "share_above_speed": float(np.mean(speed > SPEED_LIMIT_MPS)),
        "force_p99_g": float(np.percentile(force_g, 99)),
        "force_peak_g": float(force_g.max()),
        "share_above_force": float(np.mean(force_g > FORCE_LIMIT_G)),
        "knee_rate_peak_dps": float(knee_rate.max()),
        "knee_peak_deg": float(np.degrees(m.knee_rad[keep].max())),
        "sole_gap_min_m": float(gap[keep].min()),
        "edge_clearance_m": sorted(crossings),
    }


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("scenarios", nargs="+", help="path[:seed[:cadence_scale]]")
    args = ap.parse_args(argv)
    print(
        "| scenario | swing model | camera peak (m/s) | > 3 m/s | specific force p99 / peak (g) "
        "| > 4 g | knee rate peak (deg/s) | knee peak (deg) | sole gap min (mm) "
        "| toe over edges, lowest 3 (mm) |"
    )
    print("|---|---|---|---|---|---|---|---|---|---|")
    for spec in args.scenarios:
        path, seed, cadence = parse_spec(spec)
        for model in MODELS:
            s = swing_stats(path, seed, model, cadence)
            edges = " ".join(f"{1000 * c:.0f}" for c in s["edge_clearance_m"][:3]) or "-"
            print(
                f"| {Path(path).stem} s{seed}{f' x{cadence:g}' if cadence else ''} | {model} "
                f"| {s['peak_speed_mps']:.2f} | {100 * s['share_above_speed']:.1f} % "
                f"| {s['force_p99_g']:.1f} / {s['force_peak_g']:.1f} "
                f"| {100 * s['share_above_force']:.1f} % | {s['knee_rate_peak_dps']:.0f} "
                f"| {s['knee_peak_deg']:.0f} | {1000 * s['sole_gap_min_m']:.1f} | {edges} |"
            )
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
