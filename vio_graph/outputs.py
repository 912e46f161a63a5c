"""The files and summaries of one run: TUM trajectories, frames.csv, and the metrics.json
blocks that describe the replay (front end, filter, latency). Every file is written
atomically (temporary name, then rename)."""

from __future__ import annotations

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
    from vio_graph.replay import FrameLog, Replay


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
    from vio_graph.safety.online import CSV_COLUMNS, csv_values

    rows = [
        "frame,timestamp_s,status,terrain,displacement,rejection,keyframe,frontend_ms,"
        "stance," + ",".join(CSV_COLUMNS)
    ]
    fe_ms = lg.timings_ms.column("frontend_total")
    for k, t in enumerate(lg.t_s):
        safety = lg.safety[k] if k < len(lg.safety) else None
        rows.append(
            f"{k},{t:.6f},{lg.status[k]},{lg.terrain[k]},{int(lg.displacement_ok[k])},"
            f"{lg.rejection[k].replace(',', ';')},{int(lg.is_keyframe[k])},"
            f"{fe_ms[k]:.4f},{int(lg.in_stance[k])}," + ",".join(csv_values(safety))
        )
    atomic_write_text(path, "\n".join(rows) + "\n")
    return path


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
        },
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
