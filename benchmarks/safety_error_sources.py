"""Where the toe-clearance error comes from, on one simulated recording (docs/results.md,
"Foot-to-terrain safety outputs").

The filter is replayed once (``vio_graph.replay.Replay``, mode ``filter``); then the safety
monitor (vio_graph/safety/online.py) is re-run on the same keyframe profiles with parts of the
estimate replaced by the simulator's truth, and each variant's clearance is compared with the
true clearance (the true foot against the true terrain):

- ``map only (filter attitude)``: true camera position and true heel / toe, the profiles as
  the filter made them (camera-relative in ground axes, i.e. turned by the filter's attitude
  at the keyframe): the map's own error plus the keyframes' attitude error (a profile turned
  by the pitch error about the true camera). Not the map's error: in the online map the
  attitude error comes with the position error the filter made with it, and the two partly
  cancel (downstair seed 1: p95 15 mm here, 8 mm online);
- ``map only``: the same with each keyframe profile turned by the pitch error (the true minus
  the filter's shank pitch, ``lg.shank_pitch_imu``), i.e. placed at the true keyframe pose:
  what is left is the map itself (depth noise, mixed pixels, binning, occlusion);
- ``+ foot outline``: the map of ``map only``, the estimated heel / toe relative to the
  estimated camera placed at the true camera (shank pitch, ankle, leg lengths);
- ``+ pose x only`` / ``+ pose z only``: the camera with only its x (z) error (the other
  coordinate true) and the true foot outline relative to it, the profiles at the true
  attitude as in ``map only``: the split of the position error between the axes;
- ``+ pose``: estimated camera, the true foot outline relative to it;
- ``online``: the estimate as it is (estimated camera and foot outline).

Timing (frame time stamps) is not a separate source here: the truth is interpolated at the
frame's time stamp, which is the time of the depth image the estimate uses.

Each variant is scored under the given safety configurations (``--variant NAME=JSON``, JSON
overrides of ``SafetyConfig``; by default today's configuration and the one before the map's
median / 5 mm / 4-keyframe change).

    python benchmarks/safety_error_sources.py data/recordings/downstair_s1
"""

from __future__ import annotations

import argparse
import json
from pathlib import Path

import _common  # pins BLAS threads before numpy
import numpy as np

from vio_graph.config import load_config
from vio_graph.evaluation.safety import replay_safety, true_safety
from vio_graph.recording.reader import Recording
from vio_graph.safety.config import SafetyConfig

BEFORE = {"map_statistic": "mean", "bin_m": 0.01, "min_keyframes": 2}


def _p95(e_mm: np.ndarray, mask: np.ndarray) -> str:
    return f"{np.percentile(e_mm[mask], 95):.1f}" if mask.any() else "—"


def _true_shank_pitch(rec: Recording, t: np.ndarray) -> np.ndarray:
    """The true knee - ankle segment's pitch (rad) at the times ``t`` (as
    ``shank_pitch_error_deg``: rot_y(pitch) (0, L) = (L sin, L cos))."""
    gt = rec.groundtruth.trajectories
    seg = gt["knee"].xz_at(t) - gt["ankle"].xz_at(t)
    return np.arctan2(seg[:, 0], seg[:, 1])


def _turn(profile_xz_m: np.ndarray, angle_rad: float) -> np.ndarray:
    """A camera-relative profile (N, 2, x-z) turned by rot_y(angle) about the camera."""
    c, s = np.cos(angle_rad), np.sin(angle_rad)
    p = np.asarray(profile_xz_m, dtype=float)
    return np.column_stack((c * p[:, 0] + s * p[:, 1], -s * p[:, 0] + c * p[:, 1]))


def keyframes_covering(
    x_m: float, camera_xz_m: dict[int, np.ndarray], profiles: dict[int, np.ndarray], bin_m: float
) -> list[int]:
    """The keyframes (frame indices, ascending) whose profile, placed at ``camera_xz_m[k]``,
    has a point within ``bin_m`` of ``x_m`` in x: the views a map bin there can hold."""
    return sorted(
        k
        for k, p in profiles.items()
        if k in camera_xz_m
        and np.any(np.abs(camera_xz_m[k][0] + np.asarray(p)[:, 0] - x_m) < bin_m)
    )


def mapped_by(lg, est, true, tc, cfg, frames: list[int]) -> None:
    """Per frame: the clearance's closest terrain point, the keyframes that covered its bin
    (the last 24, as a bin keeps) and their camera x error and range against the frame's."""
    from vio_graph.safety.online import SafetyMonitor

    t = np.asarray(lg.t_s)
    err = (est["camera"] - true["camera"]) * 1e3
    mon = SafetyMonitor(cfg.safety, predict_clearance=False)
    cams: dict[int, np.ndarray] = {}
    print(
        "| frame | clearance est / true (mm) | terrain point x, z (m) | views | frames "
        "| camera x error of the views: median (range), mm | now (mm) | range (m) |"
    )
    print("|---|---|---|---|---|---|---|---|")
    for k in range(len(t)):
        prof = lg.profiles.get(k)
        s = _common.monitor_update(mon, lg, est, k)
        if prof is not None:
            cams[k] = np.asarray(est["camera"][k])
        if k not in frames:
            continue
        q = s.toe_line_xz_m[1]
        seen = {j: lg.profiles[j] for j in cams}
        users = keyframes_covering(float(q[0]), cams, seen, cfg.safety.bin_m)[-24:]
        if not users:
            continue
        ux = err[users, 0]
        r = np.median([np.hypot(*(q - cams[j])) for j in users])
        print(
            f"| {k} | {s.clearance_m * 1e3:.1f} / {tc[k] * 1e3:.1f} | "
            f"{q[0]:.3f}, {q[1]:.3f} | {len(users)} | {users[0]}-{users[-1]} | "
            f"{np.median(ux):+.1f} ({ux.min():+.1f} to {ux.max():+.1f}) | {err[k, 0]:+.1f} | "
            f"{r:.2f} |"
        )


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("recording", type=Path, help="simulated recording folder")
    ap.add_argument("--config", default=None, help="pipeline config (default: default.yaml)")
    ap.add_argument(
        "--variant",
        action="append",
        default=[],
        help="NAME=JSON overrides of the safety config (repeatable)",
    )
    ap.add_argument(
        "--mapped-by",
        default="",
        help="comma-separated frames: print who mapped the terrain point nearest the foot "
        "(keyframes, their camera x error and range) instead of the table",
    )
    args = ap.parse_args()
    cfg = load_config(args.config)
    variants = {"today": {}, "before (mean, 1 cm bins, 2 keyframes)": BEFORE}
    for v in args.variant:
        name, _, js = v.partition("=")
        variants[name] = json.loads(js)
    rec = Recording.open(args.recording)
    if rec.groundtruth is None:
        raise SystemExit(f"{args.recording}: no ground truth (a simulated recording is needed)")
    lg, est = _common.filter_leg_run(rec, cfg)
    t = np.asarray(lg.t_s)
    true = _common.true_leg_paths(rec, t)
    landing = np.array([bool(s.landing) if s is not None else False for s in lg.safety])
    truth = true_safety(rec.groundtruth, rec.metadata.terrain, t, landing, cfg.safety)
    if truth is None:
        raise SystemExit(f"{args.recording}: no true terrain profile / heel / toe")
    tc = truth["clearance_m"]
    if args.mapped_by:
        mapped_by(lg, est, true, tc, cfg, [int(f) for f in args.mapped_by.split(",")])
        return
    oh, ot = est["heel"] - est["camera"], est["toe"] - est["camera"]
    th, tt = true["heel"] - true["camera"], true["toe"] - true["camera"]
    # the profiles at the true keyframe poses: turned by the attitude error about the camera
    pitch_err = _true_shank_pitch(rec, t) - np.asarray(lg.shank_pitch_imu)
    true_att = {k: _turn(p, pitch_err[k]) for k, p in lg.profiles.items()}
    # the camera with only its x (z) error, the other coordinate true
    cam_x = np.column_stack((est["camera"][:, 0], true["camera"][:, 1]))
    cam_z = np.column_stack((true["camera"][:, 0], est["camera"][:, 1]))
    cases = {
        "map only (filter attitude)": (true["camera"], true["heel"], true["toe"]),
        "map only": (true["camera"], true["heel"], true["toe"]),
        "+ foot outline": (true["camera"], true["camera"] + oh, true["camera"] + ot),
        "+ pose x only": (cam_x, cam_x + th, cam_x + tt),
        "+ pose z only": (cam_z, cam_z + th, cam_z + tt),
        "+ pose": (est["camera"], est["camera"] + th, est["camera"] + tt),
        "online": (est["camera"], est["heel"], est["toe"]),
    }
    stance = np.asarray(lg.in_stance, bool)
    print(f"{args.recording.name}: |estimated - true clearance| (mm) over the frames with both")
    print()
    print(
        "| safety config | case | frames | median | p95 | p95 stance | p95 swing "
        "| within 1 / 2 sigma |"
    )
    print("|---|---|---|---|---|---|---|---|")
    for vname, over in variants.items():
        sc = SafetyConfig(**{**cfg.safety.model_dump(), **over})
        for cname, (cam, heel, toe) in cases.items():
            path = {"camera": cam, "heel": heel, "toe": toe}
            true_pose = cname in ("map only", "+ foot outline", "+ pose x only", "+ pose z only")
            prof = true_att if true_pose else lg.profiles
            out = replay_safety(sc, t, path, lg.cov_position_m2, lg.in_stance, prof)
            c = np.array([s.clearance_m for s in out])
            sig = np.array([s.clearance_sigma_m for s in out])
            e = np.abs(c - tc) * 1e3
            ok = np.isfinite(e)
            if not ok.any():
                continue
            z = e[ok] / (sig[ok] * 1e3)
            print(
                f"| {vname} | {cname} | {ok.sum()} | {np.median(e[ok]):.1f} | "
                f"{np.percentile(e[ok], 95):.1f} | {_p95(e, ok & stance)} | "
                f"{_p95(e, ok & ~stance)} | "
                f"{np.mean(z <= 1):.2f} / {np.mean(z <= 2):.2f} |"
            )


if __name__ == "__main__":
    main()
