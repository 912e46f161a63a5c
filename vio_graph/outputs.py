"""The files and summaries of one run: TUM trajectories, frames.csv, and the metrics.json
blocks that describe the replay (front end, filter, latency). Every file is written
atomically (temporary name, then rename)."""

from __future__ import annotations

import math
from collections.abc import Mapping
from pathlib import Path
from typing import TYPE_CHECKING, Any

import numpy as np
from numpy.typing import NDArray

from vio_graph.evaluation.latency import stats_ms
from vio_graph.io_utils import atomic_write_text
from vio_graph.recording.streams import Trajectory
from vio_graph.recording.tum import write_tum

if TYPE_CHECKING:
    from vio_graph.estimator import OnlineEstimator
    from vio_graph.replay import FrameLog, Replay
    from vio_graph.safety.online import SafetyLog


def write_trajectories(
    out: Path, t_s: NDArray[np.float64], paths: Mapping[str, Mapping[str, NDArray[np.float64]]]
) -> list[Path]:
    """``trajectories/<mode>_<body>.tum`` (evo-readable) for every mode and body."""
    files = []
    for mode, bodies in paths.items():
        for body, xz in bodies.items():
            p = out / "trajectories" / f"{mode}_{body}.tum"
            p.parent.mkdir(exist_ok=True)
            write_tum(p, Trajectory.from_xz(t_s, xz))
            files.append(p)
    return files


def write_frames_csv(path: Path, lg: FrameLog) -> Path:
    """One row per frame: time, status, terrain, displacement, rejection reason, keyframe,
    front-end time (ms), stance, then the safety outputs (vio_graph/safety/online.CSV_COLUMNS,
    empty cells where unknown; docs/outputs.md)."""
    from vio_graph.safety.online import CSV_COLUMNS

    rows = [
        "frame,timestamp_s,status,terrain,displacement,rejection,keyframe,frontend_ms,"
        "stance," + ",".join(CSV_COLUMNS)
    ]
    fe_ms = lg.timings_ms.column("frontend_total").tolist()
    times = np.asarray(lg.t_s, dtype=float).tolist()
    safety = _safety_cells(lg.safety, len(times))
    for k, t in enumerate(times):
        rows.append(
            f"{k},{t:.6f},{lg.status[k]},{lg.terrain[k]},{int(lg.displacement_ok[k])},"
            f"{lg.rejection[k].replace(',', ';')},{int(lg.is_keyframe[k])},"
            f"{fe_ms[k]:.4f},{int(lg.in_stance[k])}," + safety[k]
        )
    atomic_write_text(path, "\n".join(rows) + "\n")
    return path


#: frames.csv safety columns taken from SafetyEstimate.placement (its entries in order)
_PLACEMENT_COLUMNS = ("heel_to_nosing_m", "toe_to_nosing_m", "heel_to_back_m", "toe_to_back_m")
#: frames.csv safety columns written as integers (the bool and int fields)
_INTEGER_COLUMNS = ("near_trip_warning", "steps_seen", "landing")


def _safety_cells(log: SafetyLog | list, n: int) -> list[str]:
    """Per frame (``n``), the frames.csv safety cells joined by commas: the text
    ``safety.online.csv_values`` gives for that frame's SafetyEstimate (or None beyond the
    log), made column by column from the log's float64 rows instead of rebuilding one
    object a frame."""
    from vio_graph.safety.online import CSV_COLUMNS, SafetyLog, csv_values

    if not isinstance(log, SafetyLog):
        return [",".join(csv_values(log[k] if k < len(log) else None)) for k in range(n)]
    m = min(len(log), n)
    placement = log.column("placement")[:m]
    columns = []
    for name in CSV_COLUMNS:
        if name in _PLACEMENT_COLUMNS:
            values = placement[:, _PLACEMENT_COLUMNS.index(name)].tolist()
        else:
            values = log.column(name)[:m].tolist()
        if name in _INTEGER_COLUMNS:  # finite wherever the frame has an estimate
            columns.append([str(int(v)) if math.isfinite(v) else "" for v in values])
        else:
            columns.append([f"{v:.5f}" if math.isfinite(v) else "" for v in values])
    # a frame without an estimate: NaN in every column, the landing flag included
    present = np.isfinite(log.column("landing")[:m]).tolist()
    empty = ",".join([""] * len(CSV_COLUMNS))
    rows = zip(*columns, strict=True)
    cells = [",".join(row) if ok else empty for row, ok in zip(rows, present, strict=True)]
    return cells + [empty] * (n - m)


def count(values: list[str]) -> dict[str, int]:
    """How often each value occurs, by value."""
    keys, counts = np.unique(np.asarray(values, dtype=str), return_counts=True)
    return {str(k): int(c) for k, c in zip(keys, counts, strict=True)}


def frontend_summary(lg: FrameLog) -> dict[str, Any]:
    """Share of frames with a displacement, rejection reasons, terrain classes, statuses,
    keyframes."""
    return {
        "displacement_fraction": float(np.mean(lg.displacement_ok)) if lg.t_s else 0.0,
        "rejections": count(lg.rejection),
        "terrain_counts": count(lg.terrain),
        "status_counts": count(lg.status),
        "keyframes": int(np.sum(lg.is_keyframe)),
    }


def filter_summary(replay: Replay) -> dict[str, Any]:
    """The online filter's measurement counts and the level-aiding state at the end."""
    online = replay.online
    fs = online.filter.state
    return {
        "accepted": fs.n_accepted,
        "rejected_chi2": fs.n_rejected,
        "stale": fs.n_stale,
        "injected_wrong_associations": replay.injected_wrong_associations,
        "level_aiding": {
            "accepted": online.pitch_offset.n_accepted,
            "rejected": online.pitch_offset.n_rejected,
            "final_offset_deg": float(np.degrees(online.pitch_offset.offset_rad)),
            "bend_test": bend_test_summary(online),
        },
        "vendor_pitch": vendor_pitch_summary(online),
    }


def bend_test_summary(online: OnlineEstimator) -> dict[str, Any] | None:
    """The level surfaces' bend test (``filter.level_aiding.bend_test``): frames with both a
    level tilt and a face lean, frames whose tilt was held back as bent, and the last
    weighted mean disagreement (deg); None when the test is off."""
    test = online.bend_test
    if test is None:
        return None
    mean = test.mean_rad()
    return {
        "pairs": test.n_pairs,
        "bent_frames": test.n_bent_frames,
        "resets": test.n_resets,
        "mean_disagreement_deg": None if mean is None else float(np.degrees(mean)),
    }


def vendor_pitch_summary(online: OnlineEstimator) -> dict[str, Any]:
    """The vendor orientation's pitch sigma the attitude's pull is weighed with
    (``filter.attitude.vendor_pitch_sigma_deg``): the configured one, or the online estimate
    at the end (``auto``; None before any disagreement was taken); the pitch pull's time
    constant at the end (s)."""
    configured = online.config.filter.attitude.vendor_pitch_sigma_deg
    est = online.vendor_pitch_variance
    sigma = est.sigma_deg if est is not None else configured
    return {
        "mode": "off" if configured is None else "auto" if est is not None else "fixed",
        "sigma_deg": None if sigma is None else float(sigma),
        "disagreements": 0 if est is None else est.n,
        "final_pitch_time_constant_s": float(online.attitude.pitch_time_constant_s),
    }


def latency_summary(lg: FrameLog, estimator_latency_ms: Mapping[str, Any]) -> dict[str, Any]:
    """Per-frame stage latencies (ms: median, p95, mean, n) plus the estimators' own
    (``estimator_latency_ms``, e.g. the smoother's per-keyframe update)."""

    def col(name: str) -> list[float]:
        return lg.timings_ms.column(name).tolist()

    fe = col("frontend_total")
    fusion, kin, imu = col("fusion"), col("kinematics"), col("imu_propagation")
    total = np.asarray(fe) + np.asarray(fusion) + np.asarray(kin) + np.asarray(imu)
    out: dict[str, Any] = {
        "frontend": stats_ms(fe),
        "fusion": stats_ms(fusion),
        "kinematics": stats_ms(kin),
        "imu_propagation_per_frame": stats_ms(imu),
        "per_frame_total": stats_ms(total),
        "safety": stats_ms(col("safety")),
    }
    for stage in ("projection", "smoothing", "terrain", "corners", "icp"):
        out[f"frontend_{stage}"] = stats_ms(col(f"frontend_{stage}"))
    out.update(estimator_latency_ms)
    return out
