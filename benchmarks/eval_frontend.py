"""Front-end accuracy against ground truth: every ICP displacement vs the true camera motion.

Replays each recording through :class:`vio_graph.estimator.OnlineEstimator` (the same event
order as ``vio-graph run``) and compares every displacement the front end passes to the filter
with the ground-truth camera displacement between the same two frame times
(``groundtruth/camera.tum`` interpolated linearly at t0 and t1). Reports per recording and
pooled:

- availability: fraction of frames with a displacement, overall and among the frames whose
  ``groundtruth/frames.csv`` says a terrain edge is visible;
- error (measured - true) median / p95 of |e| and mean (bias) in x and z, and the NEES
  e^T C^-1 e of the front end's covariance C (2 dof: a consistent C gives mean 2);
- error and availability per true camera speed bin;
- rejection reasons (numbers stripped) and the filter's chi-square accept / reject counts;
- terrain confusion over frames (truth = the recording's terrain kind when an edge is visible,
  ``no_edge`` otherwise).

``--attitude gt`` feeds the front end the ground-truth camera attitude instead of the IMU's,
which separates attitude errors from ICP errors.

Usage::

    python benchmarks/eval_frontend.py data/recordings/upstair_1 [REC ...] \\
        --out results/eval_frontend [--attitude imu|gt] [--config CONFIG.yaml]

Writes ``OUT/eval_frontend.json`` and ``OUT/eval_frontend.md``.
"""

from __future__ import annotations

import argparse
import json
import re
from collections import Counter
from pathlib import Path
from typing import Any

import numpy as np
from numpy.typing import NDArray
from scipy.spatial.transform import Rotation, Slerp

from vio_graph.config import PipelineConfig, load_config
from vio_graph.estimator import OnlineEstimator, RigGeometry
from vio_graph.geometry import remove_yaw
from vio_graph.recording.reader import Recording
from vio_graph.replay import frames_due

SPEED_BINS_MPS = (0.0, 0.25, 0.5, 1.0, 1.5, 2.0, 3.0, np.inf)


def _interp_xz(t_ref: NDArray, xyz: NDArray, t: float) -> NDArray[np.float64]:
    return np.array([np.interp(t, t_ref, xyz[:, 0]), np.interp(t, t_ref, xyz[:, 2])])


def _gt_attitude(rec: Recording, rig: RigGeometry):
    """Function t -> R_ground_cam from the true IMU orientation (``groundtruth/imu_state.csv``,
    noiseless in simulated recordings; the mocap camera orientation carries marker noise),
    interpolated to the frame time, heading removed exactly as the estimator does."""
    st = rec.groundtruth.imu_state
    if st is None:
        raise SystemExit(f"{rec.root}: --attitude gt needs groundtruth/imu_state.csv")
    q = st.quat_wxyz
    slerp = Slerp(st.timestamp_s, Rotation.from_quat(q[:, [1, 2, 3, 0]]))
    R_imu_cam = rig.R_imu_cam

    def at(t: float) -> NDArray[np.float64]:
        R_world_imu = slerp([t]).as_matrix()[0]
        return remove_yaw(R_world_imu) @ R_imu_cam

    return at


def replay(rec: Recording, config: PipelineConfig, attitude: str) -> dict[str, Any]:
    """Run the online estimator over ``rec``; per-frame rows of what the front end produced."""
    gt = rec.groundtruth
    cam = gt.trajectories["camera"]
    rig = RigGeometry.from_metadata(rec.metadata)
    t_frames = rec.frame_timestamps_s
    p0 = _interp_xz(cam.timestamp_s, cam.position_m, float(t_frames[0]))
    est = OnlineEstimator(config, rig, p0)
    gt_att = _gt_attitude(rec, rig) if attitude == "gt" else None
    rows: list[dict[str, Any]] = []
    for i in frames_due(rec, est):
        frame = rec.frame(i)
        override = None if gt_att is None else gt_att(frame.timestamp_s)
        e, res = est.add_frame(frame, override)
        row: dict[str, Any] = {
            "t": frame.timestamp_s,
            "frame": i,
            "terrain": res.terrain.value,
            "reason": res.rejection_reason or "",
            "ms": res.timings_ms.get("total", np.nan),
            "est_xz": e.camera_xz_m,
            "disp": None,
        }
        d = res.displacement
        if d is not None:
            true = _interp_xz(cam.timestamp_s, cam.position_m, d.t1_s) - _interp_xz(
                cam.timestamp_s, cam.position_m, d.t0_s
            )
            row["disp"] = (d.t0_s, d.t1_s, np.asarray(d.delta_xz_m), np.asarray(d.cov_m2), true)
        rows.append(row)
    fs = est.filter.state
    return {
        "rows": rows,
        "filter": {"accepted": fs.n_accepted, "rejected_chi2": fs.n_rejected, "stale": fs.n_stale},
    }


def _true_speed(rec: Recording, t: NDArray[np.float64]) -> NDArray[np.float64]:
    cam = rec.groundtruth.trajectories["camera"]
    dt = 1.0 / 60.0
    a = np.stack([_interp_xz(cam.timestamp_s, cam.position_m, float(x - dt)) for x in t])
    b = np.stack([_interp_xz(cam.timestamp_s, cam.position_m, float(x + dt)) for x in t])
    return np.linalg.norm(b - a, axis=1) / (2 * dt)


def _err_stats(err: NDArray[np.float64]) -> dict[str, Any]:
    if err.shape[0] == 0:
        return {"n": 0}
    a = np.abs(err) * 1e3
    return {
        "n": int(err.shape[0]),
        "median_abs_mm": {"x": float(np.median(a[:, 0])), "z": float(np.median(a[:, 1]))},
        "p95_abs_mm": {
            "x": float(np.percentile(a[:, 0], 95)),
            "z": float(np.percentile(a[:, 1], 95)),
        },
        "mean_mm": {"x": float(err[:, 0].mean() * 1e3), "z": float(err[:, 1].mean() * 1e3)},
    }


def summarise(rec: Recording, out: dict[str, Any]) -> dict[str, Any]:
    rows = out["rows"]
    n = len(rows)
    t = np.array([r["t"] for r in rows])
    vis_all = rec.groundtruth.frame_edge_visible
    frames = np.array([r["frame"] for r in rows])
    visible = vis_all[frames].astype(bool) if vis_all is not None else np.ones(n, bool)
    has = np.array([r["disp"] is not None for r in rows])
    speed = _true_speed(rec, t)
    with_d = [r for r in rows if r["disp"] is not None]
    err = np.array([r["disp"][2] - r["disp"][4] for r in with_d]).reshape(-1, 2)
    nees = np.array(
        [float(e @ np.linalg.solve(r["disp"][3], e)) for e, r in zip(err, with_d, strict=True)]
    )
    d_speed = speed[has]
    by_speed = []
    for lo, hi in zip(SPEED_BINS_MPS[:-1], SPEED_BINS_MPS[1:], strict=True):
        in_bin = (speed >= lo) & (speed < hi)
        if not in_bin.any():
            continue
        sel = (d_speed >= lo) & (d_speed < hi)
        by_speed.append(
            {
                "speed_mps": [lo, None if np.isinf(hi) else hi],
                "frames": int(in_bin.sum()),
                "frames_visible": int((in_bin & visible).sum()),
                "availability_visible": float(has[in_bin & visible].mean())
                if (in_bin & visible).any()
                else float("nan"),
                **_err_stats(err[sel]),
            }
        )
    reasons = Counter(re.sub(r"\s*\([^)]*\)", "", r["reason"]) for r in rows if r["reason"])
    truth_kind = rec.metadata.terrain.kind or "unknown"
    confusion: dict[str, Counter] = {}
    for r, v in zip(rows, visible, strict=False):
        confusion.setdefault(truth_kind if v else "no_edge", Counter())[r["terrain"]] += 1
    # ICP-only progress: sum of accepted displacements vs the true sum over the same intervals
    sum_meas = np.array([r["disp"][2] for r in with_d]).sum(axis=0) if with_d else np.zeros(2)
    sum_true = np.array([r["disp"][4] for r in with_d]).sum(axis=0) if with_d else np.zeros(2)
    cam = rec.groundtruth.trajectories["camera"]
    total_true = _interp_xz(cam.timestamp_s, cam.position_m, float(t[-1])) - _interp_xz(
        cam.timestamp_s, cam.position_m, float(t[0])
    )
    est_xz = np.stack([r["est_xz"] for r in rows])
    gt_xz = np.stack([_interp_xz(cam.timestamp_s, cam.position_m, float(x)) for x in t])
    cam_err = est_xz - gt_xz - (est_xz[0] - gt_xz[0])
    return {
        "recording": Path(rec.root).name,
        "scenario": rec.metadata.provenance.scenario,
        "seed": rec.metadata.provenance.seed,
        "frames": n,
        "availability": float(has.mean()) if n else 0.0,
        "availability_visible": float(has[visible].mean()) if visible.any() else float("nan"),
        "visible_fraction": float(visible.mean()) if n else 0.0,
        "error": _err_stats(err),
        "nees": {
            "mean": float(nees.mean()) if nees.size else float("nan"),
            "median": float(np.median(nees)) if nees.size else float("nan"),
            "p95": float(np.percentile(nees, 95)) if nees.size else float("nan"),
            "max_abs_err_mm": float(np.abs(err).max() * 1e3) if nees.size else float("nan"),
            "frac_above_13.8": float((nees > 13.8).mean()) if nees.size else float("nan"),
        },
        "error_by_speed": by_speed,
        "rejections": dict(reasons.most_common()),
        "filter": out["filter"],
        "terrain_confusion": {k: dict(v) for k, v in confusion.items()},
        "displacement_sum_m": {
            "measured": sum_meas.tolist(),
            "true_same_intervals": sum_true.tolist(),
            "true_whole_trial": total_true.tolist(),
        },
        "filter_camera_rmse_cm": {
            "x": float(np.sqrt(np.mean(cam_err[:, 0] ** 2)) * 100),
            "z": float(np.sqrt(np.mean(cam_err[:, 1] ** 2)) * 100),
        },
        "frontend_ms": {
            "median": float(np.nanmedian([r["ms"] for r in rows])),
            "p95": float(np.nanpercentile([r["ms"] for r in rows], 95)),
        },
        "_err": err,
        "_nees": nees,
    }


def _markdown(results: list[dict[str, Any]], attitude: str) -> str:
    L = [f"# Front-end displacement accuracy (attitude: {attitude})", ""]
    L += [
        "| recording | avail | avail (edge visible) | err x med/p95/mean mm | "
        "err z med/p95/mean mm | NEES mean/p95 | filter acc/rej | cam RMSE x/z cm | fe ms |",
        "|---|---|---|---|---|---|---|---|---|",
    ]
    for r in results:
        e = r["error"]
        if e["n"]:
            ex, ez = (
                f"{e['median_abs_mm'][a]:.1f}/{e['p95_abs_mm'][a]:.1f}/{e['mean_mm'][a]:+.1f}"
                for a in ("x", "z")
            )
        else:
            ex = ez = "-"
        f = r["filter"]
        c = r["filter_camera_rmse_cm"]
        L.append(
            f"| {r['scenario']} s{r['seed']} | {r['availability']:.2f} | "
            f"{r['availability_visible']:.2f} | {ex} | {ez} | {r['nees']['mean']:.1f}/"
            f"{r['nees']['p95']:.1f} | "
            f"{f['accepted']}/{f['rejected_chi2']} | {c['x']:.1f}/{c['z']:.1f} | "
            f"{r['frontend_ms']['median']:.1f} |"
        )
    for r in results:
        L += [
            "",
            f"## {r['scenario']} seed {r['seed']}",
            "",
            "| true speed m/s | frames (visible) | avail visible | n | |e| x med/p95 mm | "
            "|e| z med/p95 mm | mean x/z mm |",
            "|---|---|---|---|---|---|---|",
        ]
        for b in r["error_by_speed"]:
            lo, hi = b["speed_mps"]
            rng = f"{lo:.2f}-{'inf' if hi is None else f'{hi:.2f}'}"
            if b["n"]:
                L.append(
                    f"| {rng} | {b['frames']} ({b['frames_visible']}) | "
                    f"{b['availability_visible']:.2f} | {b['n']} | "
                    f"{b['median_abs_mm']['x']:.1f}/{b['p95_abs_mm']['x']:.1f} | "
                    f"{b['median_abs_mm']['z']:.1f}/{b['p95_abs_mm']['z']:.1f} | "
                    f"{b['mean_mm']['x']:+.1f}/{b['mean_mm']['z']:+.1f} |"
                )
            else:
                L.append(
                    f"| {rng} | {b['frames']} ({b['frames_visible']}) | "
                    f"{b['availability_visible']:.2f} | 0 | - | - | - |"
                )
        L += [
            "",
            "Rejections: " + ", ".join(f"{k}: {v}" for k, v in r["rejections"].items()),
            "",
            "Terrain confusion (rows truth, columns predicted): "
            + "; ".join(f"{k} -> {v}" for k, v in r["terrain_confusion"].items()),
            "",
            f"Displacement sums (m): {r['displacement_sum_m']}",
        ]
    return "\n".join(L) + "\n"


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("recordings", nargs="+", type=Path)
    ap.add_argument("--out", type=Path, required=True, help="output folder")
    ap.add_argument("--attitude", choices=("imu", "gt"), default="imu")
    ap.add_argument("--config", type=Path, default=None, help="pipeline config YAML")
    args = ap.parse_args()
    config = load_config(args.config) if args.config else PipelineConfig()
    results = []
    for path in args.recordings:
        rec = Recording.open(path)
        results.append(summarise(rec, replay(rec, config, args.attitude)))
    pooled_err = np.vstack([r.pop("_err") for r in results])
    pooled_nees = np.concatenate([r.pop("_nees") for r in results])
    report = {
        "attitude": args.attitude,
        "recordings": results,
        "pooled_error": _err_stats(pooled_err),
        "pooled_nees": {
            "n": int(pooled_nees.size),
            "mean": float(pooled_nees.mean()) if pooled_nees.size else None,
            "p95": float(np.percentile(pooled_nees, 95)) if pooled_nees.size else None,
        },
    }
    args.out.mkdir(parents=True, exist_ok=True)
    (args.out / "eval_frontend.json").write_text(json.dumps(report, indent=1))
    md = _markdown(results, args.attitude)
    pn = report["pooled_nees"]
    if pn["n"]:
        md += f"\nPooled NEES over {pn['n']} displacements: mean {pn['mean']:.2f}, "
        md += f"p95 {pn['p95']:.2f} (consistent, 2 dof: 2 and 6.0)\n"
    (args.out / "eval_frontend.md").write_text(md)
    print(md)


if __name__ == "__main__":
    main()
