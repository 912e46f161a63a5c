"""How much of its IMU seed does a visual displacement's x repeat? Measured, not regressed.

``benchmarks/eval_filter_x.py`` regresses each displacement's x error on the x error of the
IMU prediction that seeded its ICP ("seed slope"). A slope is not a sensitivity: anything
that moves both errors together (the reference they are both measured against, or the
filter's own state) shows up in it. This script measures the sensitivity itself. It replays
a recording through :class:`vio_graph.estimator.OnlineEstimator` (filter mode, the event
order of ``vio-graph run``) and, before every real tracker update, runs a deep copy of the
tracker on the same frame with the prediction's x moved by +-delta, and one copy seeded
with the true x motion. Per frame:

- ``J(delta) = (x(seed + delta) - x(seed - delta)) / (2 delta)``: 0 = the displacement does
  not depend on where ICP starts, 1 = it moves with the seed (the whole tracker runs: the
  seed also picks the ICP source crop, the overlap test, the gate and the fallbacks);
- the x error of the displacement seeded with the truth, and its slope on the real seed's
  error (what the seed slope would be if the seed had no effect at all).

Frames are grouped by the ICP that gave the displacement (corner window or whole-profile
fallback) and by stance (true camera speed below 0.15 m/s) / swing; only displacements whose
x sigma is below 5 cm count (as in eval_filter_x.py).

The simulated ground truth is motion capture with marker noise (``mocap.marker_noise_m``,
0.5 mm per axis on the camera cluster at 120 Hz), which enters the reference x motion of
both the seed and the displacement, with the same sign. ``--truth REC`` takes the camera
trajectory from another recording instead: the same scenario and seed simulated with
``mocap: {noise: false}`` in its YAML (every sensor stream is the same; only the
ground-truth files differ).

Usage::

    python benchmarks/eval_icp_seed.py recordings/D_s7041 [--truth recordings/D_s7041_nf]
        [--deltas-mm 1,3,10] [--config CONFIG.yaml]
"""

from __future__ import annotations

import argparse
import copy
from pathlib import Path
from typing import Any

import _common  # noqa: F401, I001 - before numpy: pins the thread pools numpy reads on import
import numpy as np

import vio_graph.frontend.tracker as tracker_module
from vio_graph.config import load_config
from vio_graph.estimator import OnlineEstimator, RigGeometry
from vio_graph.frontend.tracker import CornerTracker
from vio_graph.recording.reader import Recording
from vio_graph.replay import frames_due

_STANCE_MPS = 0.15
_X_INFORMATIVE_M2 = 0.05**2

#: id of each IcpResult the tracker made -> True if it ran with the corner window's config
#: (the replayed tracker's ``_icp_cfg``; the profile fallback has its own)
_ICP_KIND: dict[int, bool] = {}
_CORNER_CFG: list[Any] = [None]
_icp = tracker_module.icp_translation_2d


def _noting_icp(src, tgt, T0=None, cfg=None, *args, **kwargs):
    res = _icp(src, tgt, T0, cfg, *args, **kwargs)
    _ICP_KIND[id(res)] = cfg is _CORNER_CFG[0]
    return res


tracker_module.icp_translation_2d = _noting_icp  # this script's process only


def _replay(path: Path, config, deltas_m: list[float]) -> list[dict[str, Any]]:
    """One row per displacement of the replay (with a prediction): its x, x variance, the
    seed's x, the true x motion and the x of the perturbed and true-seeded copies (m)."""
    rec = Recording.open(path)
    rig = RigGeometry.from_metadata(rec.metadata)
    cam = rec.groundtruth.trajectories["camera"]
    t0 = float(rec.frame_timestamps_s[0])
    p0 = np.array([np.interp(t0, cam.timestamp_s, cam.position_m[:, i]) for i in (0, 2)])
    est = OnlineEstimator(config, rig, p0)
    tracker = est.frontend._tracker
    _CORNER_CFG[0] = tracker._icp_cfg
    real_update = tracker.update
    rows: list[dict[str, Any]] = []

    def true_dx(ta: float, tb: float) -> float:
        xa, xb = np.interp([ta, tb], cam.timestamp_s, cam.position_m[:, 0])
        return float(xb - xa)

    def probed_update(t, profile, corner, pred=None, pred_cov=None, turn=0.0):
        alt: dict[Any, float | None] = {}
        if pred is not None and tracker._prev is not None:
            pred = np.asarray(pred, float)
            runs = [(s * d, pred + [s * d, 0.0]) for d in deltas_m for s in (-1, 1)]
            runs.append(("true", np.array([true_dx(tracker._prev.timestamp_s, t), pred[1]])))
            for key, p in runs:
                twin = copy.deepcopy(tracker)
                o = CornerTracker.update(twin, t, profile, corner, p, pred_cov, turn)
                alt[key] = None if o.displacement is None else float(o.displacement.delta_xz_m[0])
        out = real_update(t, profile, corner, pred, pred_cov, turn)
        d = out.displacement
        if d is not None and pred is not None and out.icp is not None:
            rows.append(
                {
                    "x": float(d.delta_xz_m[0]),
                    "var_x": float(d.cov_m2[0, 0]),
                    "seed": float(pred[0]),
                    "alt": alt,
                    "corner": _ICP_KIND.get(id(out.icp), False),
                    "t0": d.t0_s,
                    "t1": d.t1_s,
                }
            )
        _ICP_KIND.clear()
        return out

    tracker.update = probed_update  # this instance only
    for i in frames_due(rec, est):
        est.add_frame(rec.frame(i))
    return rows


def summarise(rows: list[dict[str, Any]], truth: Path, deltas_m: list[float]) -> list[str]:
    """Markdown rows per frame group (see the module doc)."""
    cam = Recording.open(truth).groundtruth.trajectories["camera"]
    recs = []
    for r in rows:
        x0, x1 = np.interp([r["t0"], r["t1"]], cam.timestamp_s, cam.position_m[:, 0])
        true = float(x1 - x0)
        js = []
        for d in deltas_m:
            a, b = r["alt"].get(d), r["alt"].get(-d)
            js.append(np.nan if a is None or b is None else (a - b) / (2.0 * d))
        xt = r["alt"].get("true")
        recs.append(
            (
                r["x"] - true,
                r["seed"] - true,
                np.nan if xt is None else xt - true,
                r["var_x"],
                abs(true) / (r["t1"] - r["t0"]),
                float(r["corner"]),
                *js,
            )
        )
    R = np.array(recs, float).reshape(-1, 6 + len(deltas_m))
    informative = R[:, 3] < _X_INFORMATIVE_M2
    groups = {
        "all": informative,
        "corner ICP": informative & (R[:, 5] == 1),
        "profile ICP": informative & (R[:, 5] == 0),
        "stance": informative & (R[:, 4] < _STANCE_MPS),
        "swing": informative & (R[:, 4] >= _STANCE_MPS),
    }
    out = []
    for name, m in groups.items():
        if not m.any():
            continue
        e_d, e_s, e_t = R[m, 0], R[m, 1], R[m, 2]
        ok = np.isfinite(e_t)
        j_cells = []
        for k in range(len(deltas_m)):
            J = R[m, 6 + k]
            J = J[np.isfinite(J)]
            j_cells.append(f"{np.median(J):.2f} / {J.mean():.2f} / {np.mean(J > 0.5):.2f}")
        out.append(
            f"| {name} | {int(m.sum())} | {e_d @ e_s / (e_s @ e_s):.2f} | "
            f"{e_t[ok] @ e_s[ok] / (e_s[ok] @ e_s[ok]):.2f} | "
            + " | ".join(j_cells)
            + f" | {1e3 * np.sqrt(np.mean(e_s**2)):.1f} / {1e3 * np.sqrt(np.mean(e_d**2)):.1f} / "
            f"{1e3 * np.sqrt(np.mean(e_t[ok] ** 2)):.1f} |"
        )
    return out


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("recording", type=Path)
    ap.add_argument("--truth", type=Path, default=None, help="recording with noise-free truth")
    ap.add_argument("--deltas-mm", default="1,3,10")
    ap.add_argument("--config", type=Path, default=None)
    args = ap.parse_args()
    deltas = [1e-3 * float(v) for v in args.deltas_mm.split(",")]
    rows = _replay(args.recording, load_config(args.config), deltas)
    print(f"{args.recording.name} (truth: {(args.truth or args.recording).name})")
    head = " | ".join(f"J({1e3 * d:g} mm) median / mean / > 0.5" for d in deltas)
    print(
        f"| frames | n | seed slope | slope if seeded with the truth | {head} | "
        "rms x error (mm): seed / displacement / displacement seeded with the truth |"
    )
    print("|---" * (5 + len(deltas)) + "|")
    for line in summarise(rows, args.truth or args.recording, deltas):
        print(line)


if __name__ == "__main__":
    main()
