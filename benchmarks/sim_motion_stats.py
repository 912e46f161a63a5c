"""How violent is a recording's motion? Camera speed and IMU specific force, per recording.

A check of the simulator against what a shank-worn rig sees on real stairs (a few g of
specific force in swing, impacts aside; a point near the knee no faster than the foot, 4-5
m/s at most): for each recording, from ``groundtruth/camera.tum`` (speed by central
differences of the positions, m/s) and ``imu.csv`` (norm of the specific force, m/s^2):
the peak camera speed and when, the share of ground-truth samples above 3 m/s, the specific
force's p99 and peak (in g) and the shares of IMU samples above 4 g and 8 g.

Usage::

    python benchmarks/sim_motion_stats.py recordings/upstair_s1 recordings/downstair_s1

Needs ground truth (a simulated recording); prints a markdown table.
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

import numpy as np

from vio_graph.errors import VioGraphError
from vio_graph.geometry import GRAVITY_MPS2
from vio_graph.recording import Recording

SPEED_LIMIT_MPS = 3.0
FORCE_LIMITS_G = (4.0, 8.0)


def motion_stats(rec_dir: Path) -> dict[str, float]:
    """The figures of one recording (see the module docstring)."""
    rec = Recording.open(rec_dir)
    if rec.groundtruth is None or "camera" not in rec.groundtruth.trajectories:
        raise VioGraphError(f"{rec_dir}: no groundtruth/camera.tum (not a simulated recording?)")
    cam = rec.groundtruth.trajectories["camera"]
    t = np.asarray(cam.timestamp_s, dtype=float)
    xz = np.asarray(cam.xz_m, dtype=float)
    speed = np.hypot(np.gradient(xz[:, 0], t), np.gradient(xz[:, 1], t))
    force_g = np.linalg.norm(np.asarray(rec.imu.accel_mps2, dtype=float), axis=1) / GRAVITY_MPS2
    i = int(np.argmax(speed))
    out = {
        "peak_speed_mps": float(speed[i]),
        "peak_speed_at_s": float(t[i]),
        "share_above_speed": float(np.mean(speed > SPEED_LIMIT_MPS)),
        "force_p99_g": float(np.percentile(force_g, 99)),
        "force_peak_g": float(force_g.max()),
    }
    for g in FORCE_LIMITS_G:
        out[f"share_above_{g:g}g"] = float(np.mean(force_g > g))
    return out


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("recordings", nargs="+", type=Path)
    args = ap.parse_args(argv)
    print(
        f"| recording | peak camera speed (m/s, at s) | > {SPEED_LIMIT_MPS:g} m/s | "
        "specific force p99 / peak (g) | " + " | ".join(f"> {g:g} g" for g in FORCE_LIMITS_G) + " |"
    )
    print("|---|---|---|---|" + "---|" * len(FORCE_LIMITS_G))
    for rec in args.recordings:
        try:
            m = motion_stats(rec)
        except VioGraphError as exc:
            print(f"error: {exc}", file=sys.stderr)
            return 1
        shares = " | ".join(f"{100 * m[f'share_above_{g:g}g']:.1f} %" for g in FORCE_LIMITS_G)
        print(
            f"| {rec.name} | {m['peak_speed_mps']:.1f} ({m['peak_speed_at_s']:.2f}) | "
            f"{100 * m['share_above_speed']:.1f} % | {m['force_p99_g']:.1f} / "
            f"{m['force_peak_g']:.1f} | {shares} |"
        )
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
