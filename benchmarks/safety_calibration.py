"""Where the safety outputs' remaining misses come from (docs/results.md, "Foot-to-terrain
safety outputs"): the pose part of the clearance sigma against the pose part of the error,
and the cause of each false near-trip warning.

The filter is replayed once per recording; then the safety monitor (vio_graph/safety/online.py)
is re-run on its estimate (``replay_safety``):

- pose part: the monitor on the estimated camera with the true foot outline minus the monitor
  on the true camera with the true foot outline (the keyframe profiles placed at each), over
  the sigma of the estimated-camera run without the map floor and the foot term; its rms
  (1 when the filter's covariance growth describes its drift), with the rms error and sigma
  in mm;
- the foot outline's error relative to the camera (heel and toe, sd per axis), the range of
  the camera's z error and the filter's own z sigma at the end of the trial;
- false warnings: each warning run that is not a true positive (``near_trip_scores``) is
  re-tested with the estimated foot's actual poses over the next ``horizon_s`` in place of the
  motion model's (same candidate poses: forward, next edge, cleared first; same sigma):
  "motion model" if those poses would not have warned, else "clearance" (the foot did pass
  within 2 cm + 1 sigma of the mapped edge).

    python benchmarks/safety_calibration.py data/recordings/downstair_s1 [more ...]
"""

from __future__ import annotations

import argparse
from pathlib import Path

import _common  # pins BLAS threads before numpy
import numpy as np

from vio_graph.config import load_config
from vio_graph.evaluation.safety import _runs, replay_safety, true_safety
from vio_graph.recording.reader import Recording
from vio_graph.safety.clearance import edge_clearance_many
from vio_graph.safety.config import SafetyConfig
from vio_graph.safety.online import SafetyMonitor


def pose_part(lg, est, true, cfg: SafetyConfig) -> tuple[float, float, float]:
    """(rms error mm, rms sigma mm, rms of error / sigma) of the pose part."""
    sc = SafetyConfig(**{**cfg.model_dump(), "foot_sigma_m": 0.0, "map_sigma_m": 0.0})
    off = {b: true[b] - true["camera"] for b in ("heel", "toe")}
    res = {}
    for name, cam in (("true", true["camera"]), ("est", est["camera"])):
        path = {"camera": cam, "heel": cam + off["heel"], "toe": cam + off["toe"]}
        out = replay_safety(
            sc, np.asarray(lg.t_s), path, lg.cov_position_m2, lg.in_stance, lg.profiles
        )
        res[name] = (
            np.array([s.clearance_m for s in out]),
            np.array([s.clearance_sigma_m for s in out]),
        )
    e, sig = res["est"][0] - res["true"][0], res["est"][1]
    ok = np.isfinite(e) & np.isfinite(sig) & (sig > 0)
    rms = lambda a: float(np.sqrt(np.mean(a**2)))  # noqa: E731
    return rms(e[ok]) * 1e3, rms(sig[ok]) * 1e3, rms(e[ok] / sig[ok])


def oracle_risk(mon: SafetyMonitor, t, k: int, est, cfg: SafetyConfig) -> float:
    """The warning's tested clearance with the estimated foot's actual next poses (m)."""
    idx = np.r_[k, np.flatnonzero((t > t[k]) & (t <= t[k] + cfg.horizon_s))]
    edges = mon.edges
    if len(edges) == 0 or len(idx) < 3:
        return float("nan")
    hp, tp = est["heel"][idx], est["toe"][idx]
    vp = np.gradient(tp, t[idx], axis=0)
    fwd = (vp[:, 0] > cfg.warning_min_forward_speed_mps) & (vp[:, 1] > -vp[:, 0])
    nxt = np.searchsorted(edges.xz_m[:, 0], tp[:, 0] - cfg.toe_pass_m, side="right")
    best = float("nan")
    for i in np.unique(nxt[nxt < len(edges)]):
        dd = edge_clearance_many(hp, tp, edges.xz_m[i], cfg.sole_thickness_m)
        ok = fwd & (nxt == i) & np.logical_or.accumulate(dd >= cfg.near_trip_m)
        if ok.any() and not float(dd[ok].min()) >= best:
            best = float(dd[ok].min())
    return best


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("recordings", nargs="+", type=Path, help="simulated recording folders")
    args = ap.parse_args()
    cfg = load_config(None)
    sc = cfg.safety
    print(
        "| recording | foot outline error sd x / z (mm) | camera z error range (mm) "
        "| filter z sigma at the end (mm) | pose part: error rms (mm) | sigma rms (mm) "
        "| error / sigma rms | false warnings | of which motion model | of which clearance |"
    )
    print("|---|---|---|---|---|---|---|---|---|---|")
    for path in args.recordings:
        rec = Recording.open(path)
        if rec.groundtruth is None:
            raise SystemExit(f"{path}: no ground truth (a simulated recording is needed)")
        lg, est = _common.filter_leg_run(rec, cfg)
        t = np.asarray(lg.t_s)
        true = _common.true_leg_paths(rec, t)
        e_mm, s_mm, z = pose_part(lg, est, true, sc)
        truth = true_safety(rec.groundtruth, rec.metadata.terrain, t, np.zeros(len(t), bool), sc)
        if truth is None:
            raise SystemExit(f"{path}: no true terrain profile / heel / toe")
        td = truth["t_dense_s"]
        events = [(td[a], td[b]) for a, b in _runs(truth["near_trip"])]
        mon = SafetyMonitor(sc)
        warn, oracle_warns = [], []
        for k in range(len(t)):
            s = _common.monitor_update(mon, lg, est, k)
            warn.append(s.near_trip_warning)
            r = oracle_risk(mon, t, k, est, sc) if s.near_trip_warning else float("nan")
            sig = s.nosing_sigma_m if np.isfinite(s.nosing_sigma_m) else 0.0
            oracle_warns.append(
                bool(np.isfinite(r) and r - sc.warning_sigma * sig < sc.near_trip_m)
            )
        false = motion = 0
        for a, b in _runs(np.array(warn)):
            if any(t[a] <= e1 and t[b] >= e0 - 1.0 for e0, e1 in events):
                continue
            false += 1
            motion += not oracle_warns[a]
        rel = np.concatenate(
            [est[b] - est["camera"] - (true[b] - true["camera"]) for b in ("heel", "toe")]
        )
        cam_z = est["camera"][:, 1] - true["camera"][:, 1]
        print(
            f"| {_common.display_path(path)} | {np.std(rel[:, 0]) * 1e3:.1f} / "
            f"{np.std(rel[:, 1]) * 1e3:.1f} | {np.ptp(cam_z) * 1e3:.1f} | "
            f"{np.sqrt(lg.cov_position_m2[-1][1][1]) * 1e3:.1f} | {e_mm:.1f} | {s_mm:.1f} | "
            f"{z:.2f} | {false} | {motion} | {false - motion} |",
            flush=True,
        )


if __name__ == "__main__":
    main()
