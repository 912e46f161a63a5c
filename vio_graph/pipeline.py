"""One run, as a table of contents: load the recording, estimate, evaluate, map, write.

``run_recording`` replays the streams through every estimator (vio_graph/replay.py: the
online filter, the baselines and the smoothers behind one protocol, vio_graph/protocol.py),
derives every mode's leg trajectories by forward kinematics, evaluates them against ground
truth (vio_graph/evaluation/), builds the map from the best available keyframe poses
(vio_graph/mapping/run_map.py) and writes the results folder (vio_graph/outputs.py, the
rerun view from vio_graph/viz/run_view.py), every file atomically.
"""

from __future__ import annotations

import signal
import time
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np
from numpy.typing import NDArray

import vio_graph
from vio_graph.config import PipelineConfig, dump_config
from vio_graph.errors import OutputError
from vio_graph.estimator import RigGeometry
from vio_graph.evaluation.diagnostics import (
    displacement_nees,
    position_nees,
    stance_scores,
    true_stance,
)
from vio_graph.evaluation.run_metrics import (
    evaluate_paths,
    shank_pitch_error_deg,
    terrain_accuracy,
)
from vio_graph.health import disagreement_warning, filter_sigma_summary, smoothed_vs_filtered
from vio_graph.io_utils import atomic_write_json, atomic_write_text, remove_temporaries
from vio_graph.mapping.run_map import build_run_map
from vio_graph.memory import start_up_done
from vio_graph.outputs import (
    filter_summary,
    frontend_summary,
    latency_summary,
    write_frames_csv,
    write_trajectories,
)
from vio_graph.recording.reader import Recording
from vio_graph.replay import MODES, PEER_MODES, FrameLog, Replay

#: map files of a run (map/); the PNG figure only with ``output.plots``
MAP_FORMATS = ("ply", "pcd", "json", "csv", "png")

__all__ = [
    "MODES",
    "PEER_MODES",
    "RunInterrupted",
    "RunResult",
    "leg_trajectories",
    "run_recording",
]


@dataclass
class RunResult:
    out_dir: Path
    metrics: dict[str, Any]
    files: list[Path]


class RunInterrupted(KeyboardInterrupt):
    """A run stopped by SIGINT/SIGTERM (a KeyboardInterrupt carrying ``signum``) after its
    cleanup: ``completed`` lists the output files that were fully written (every file is
    written under a temporary name and renamed, and the temporaries are removed), so the
    results folder holds complete files only."""

    def __init__(self, out_dir: Path, completed: list[Path], signum: int) -> None:
        super().__init__(f"interrupted; {len(completed)} outputs completed in {out_dir}")
        self.out_dir = out_dir
        self.completed = completed
        self.signum = signum


def leg_trajectories(
    rig: RigGeometry,
    camera_xz: NDArray[np.float64],
    lg: FrameLog,
    use_encoders: bool,
    mode: str | None = None,
) -> dict[str, NDArray[np.float64]]:
    """Knee, ankle, heel and toe (N, 2) for a camera path, by forward kinematics (Fig. 3).

    The shank pitch from the IMU is the mode's own (``lg.shank_pitch_by_mode``: a keyframe
    smoother's refined attitude) if it has one, else the filter's (``lg.shank_pitch_imu``)."""
    pitch = lg.shank_pitch_by_mode.get(mode) if mode is not None else None
    pts = rig.leg_points(
        camera_xz,
        np.asarray(lg.shank_pitch_imu if pitch is None else pitch),
        np.asarray(lg.shank_pitch_chain),
        np.asarray(lg.ankle_rad),
        use_encoders,
    )
    return {
        "camera": camera_xz,
        "knee": pts.knee_xz_m,
        "ankle": pts.ankle_xz_m,
        "heel": pts.heel_xz_m,
        "toe": pts.toe_xz_m,
    }


def run_recording(
    recording: Path | str,
    out_dir: Path | str,
    config: PipelineConfig,
    modes: tuple[str, ...] = ("filter",),
    overwrite: bool = False,
    visualize: bool = True,
    progress: bool = True,
) -> RunResult:
    """Run the estimator(s) on one recording and write the results folder.

    Writes (each file atomically): ``config.yaml``, ``trajectories/<mode>_<body>.tum``,
    ``frames.csv``, ``metrics.json``, ``plots/*.png``, ``map/*`` and ``run.rrd``.
    """
    from vio_graph.viz.rerun_logger import NullVisualizer, Visualizer

    out = Path(out_dir)
    if out.exists() and any(out.iterdir()) and not overwrite:
        raise OutputError(f"{out}: results folder exists and is not empty (use --overwrite)")
    rec = Recording.open(recording)
    bad = set(modes) - set(MODES) - set(PEER_MODES)
    if bad:
        raise OutputError(f"unknown modes {sorted(bad)}; choose from {MODES + PEER_MODES}")
    out.mkdir(parents=True, exist_ok=True)
    files: list[Path] = []
    viz = NullVisualizer()
    try:
        atomic_write_text(out / "config.yaml", dump_config(config))
        files.append(out / "config.yaml")
        if visualize and config.output.rerun:
            viz = Visualizer(out / "run.rrd")
        return _run_into(out, rec, recording, config, modes, progress, viz, files)
    except BaseException as exc:  # errors, SIGINT, or SIGTERM turned into KeyboardInterrupt
        viz.abort()  # no half-written run.rrd
        remove_temporaries(out)
        if isinstance(exc, KeyboardInterrupt):
            signum = getattr(exc, "signum", signal.SIGINT)
            raise RunInterrupted(out, [f for f in files if f.is_file()], signum) from exc
        raise


def _run_into(
    out: Path,
    rec: Recording,
    recording: Path | str,
    config: PipelineConfig,
    modes: tuple[str, ...],
    progress: bool,
    viz,
    files: list[Path],
) -> RunResult:
    """The body of :func:`run_recording`; appends every completed output file to ``files``."""
    from vio_graph.viz.progress import progress_bar
    from vio_graph.viz.rerun_logger import Visualizer

    # estimate: every estimator through the recording, then every mode's leg points
    replay = Replay(rec, config, set(modes), viz)
    replay.view.scene(rec)
    start_up_done()  # (the garbage collector's start-up pause, if any, ends: memory.py)
    t_start = time.perf_counter()
    with progress_bar(
        rec.num_frames, f"estimating {Path(recording).name}", "frame", enabled=progress
    ) as bar:
        lg = replay.run(progress=bar.update_to)
    wall_s = time.perf_counter() - t_start
    t_s = np.asarray(lg.t_s)
    camera = lg.camera_xz
    use_enc = config.kinematics.shank_pitch_source == "encoders"
    paths = {m: leg_trajectories(replay.rig, xz, lg, use_enc, m) for m, xz in camera.items()}
    files += write_trajectories(out, t_s, paths)
    files.append(write_frames_csv(out / "frames.csv", lg))

    # evaluate
    metrics = _evaluate(rec, config, replay, lg, paths, wall_s)
    safety_truth = None
    if rec.groundtruth is not None and config.safety.enabled:
        from vio_graph.evaluation.safety import safety_metrics

        block, safety_truth = safety_metrics(
            config.safety, rec.groundtruth, rec.metadata.terrain, lg, paths
        )
        metrics.update(block)

    # map, from the best refined keyframe poses available (position and attitude: the
    # profiles at that mode's own pitch, FrameLog.profiles_of)
    map_mode = "batch" if "batch" in camera else "smoother" if "smoother" in camera else "filter"
    run_map = build_run_map(
        t_s, lg.profiles_of(map_mode), camera[map_mode], config.mapping, rec.metadata.terrain
    )
    metrics["map"] = {"source_mode": map_mode, **run_map.metrics}

    # write
    if run_map.geometry is not None:
        from vio_graph.mapping.export import export_map

        written = export_map(
            out / "map",
            run_map.points_xz_m,
            run_map.geometry,
            rec.metadata.terrain,
            run_map.comparison,
            camera_xz_m=camera[map_mode],
            formats=MAP_FORMATS if config.output.plots else MAP_FORMATS[:-1],  # png last
        )
        replay.view.map_points(run_map.points_xz_m)
        files += list(written.values())
    if config.output.plots:
        from vio_graph.viz.plots import plot_run_overview

        files.append(plot_run_overview(out / "plots" / "overview.png", rec, t_s, paths, metrics))
        if config.safety.enabled and lg.safety:
            from vio_graph.viz.plots import plot_clearance

            files.append(
                plot_clearance(out / "plots" / "clearance.png", t_s, lg.safety, safety_truth)
            )
    replay.view.paths(paths)
    viz.close()
    if isinstance(viz, Visualizer):
        files.append(out / "run.rrd")
    atomic_write_json(out / "metrics.json", metrics)
    files.append(out / "metrics.json")
    return RunResult(out_dir=out, metrics=metrics, files=files)


def _evaluate(
    rec: Recording,
    config: PipelineConfig,
    replay: Replay,
    lg: FrameLog,
    paths: dict[str, dict[str, NDArray[np.float64]]],
    wall_s: float,
) -> dict[str, Any]:
    """metrics.json without the map: what was run, accuracy against ground truth (if any),
    latency, the estimators' reports and failures, front end, filter, health, stance."""
    t_s = np.asarray(lg.t_s)
    use_enc = config.kinematics.shank_pitch_source == "encoders"
    metrics: dict[str, Any] = {
        "recording": str(rec.root),
        "scenario": rec.metadata.provenance.scenario,
        "seed": rec.metadata.provenance.seed,
        "terrain": rec.metadata.terrain.kind,
        "rig": rec.metadata.leg.rig,
        "modes": sorted(paths),
        "software": f"vio_graph {vio_graph.__version__}",
        "frames": len(lg.t_s),
        "wall_time_s": wall_s,
    }
    gt = rec.groundtruth
    if gt is not None:
        visible = None
        if gt.frame_edge_visible is not None:
            visible = gt.frame_edge_visible[: len(t_s)].astype(bool)
        metrics.update(evaluate_paths(gt, t_s, paths, visible))
        metrics["shank_pitch_error_deg"] = shank_pitch_error_deg(
            gt, t_s, np.asarray(lg.shank_pitch_chain if use_enc else lg.shank_pitch_imu)
        )
        if lg.shank_pitch_by_mode:  # the smoothers' own pitch (smoother.leg_attitude)
            metrics["shank_pitch_error_deg_by_mode"] = {
                m: shank_pitch_error_deg(gt, t_s, p) for m, p in lg.shank_pitch_by_mode.items()
            }
    reports = [e.report() for e in replay.estimators.values()]
    metrics["latency_ms"] = latency_summary(
        lg, {k: v for r in reports for k, v in r.latency_ms.items()}
    )
    metrics["smoother_failures"] = replay.failed
    for r in reports:
        metrics.update(r.metrics)
    metrics["frontend"] = frontend_summary(lg)
    metrics["filter"] = filter_summary(replay)
    metrics["health"] = replay.online.health_report()
    _add_estimate_consistency(metrics["health"], lg)
    metrics.update(replay.online.fault_report())  # imu_faults, time_offset, timestamps
    if replay.imu_retimed is not None and "imu" in metrics["timestamps"]:
        # the stamps the online clock model saw were already on the offline line
        metrics["timestamps"]["imu"]["offline_line"] = replay.imu_retimed
    if replay.rerun is not None:
        metrics["time_offset"]["rerun"] = rerun_report(replay, gt)
    if replay.final_rerun is not None:  # td held at its final estimate over a last pass
        metrics["time_offset"]["final_rerun"] = dict(replay.final_rerun)
    if gt is not None:
        metrics["terrain_classification"] = terrain_accuracy(
            rec.metadata.terrain.kind, lg.terrain, gt.frame_edge_visible
        )
        metrics["stance_detection"] = stance_scores(
            np.asarray(lg.in_stance, bool), true_stance(gt.trajectories["ankle"], t_s)
        )
        metrics["frontend"]["displacement_nees"] = displacement_nees(
            lg.displacements, gt.trajectories["camera"], config.filter.measurement_noise_floor_m
        )
        if "filter" in lg.camera_xz and len(lg.cov_position_m2) == len(t_s):
            metrics["filter"]["position_nees"] = position_nees(
                lg.camera_xz["filter"],
                np.asarray(lg.cov_position_m2),
                gt.trajectories["camera"].xz_at(t_s),
            )
    return metrics


def _add_estimate_consistency(health: dict[str, Any], lg: FrameLog) -> None:
    """Health figures from the whole run (no ground truth): the filter's own position
    sigma, and each smoother's path tested against the filter's covariance
    (vio_graph/health.py, smoothed_vs_filtered). No estimate is changed; a smoother whose
    path and the filter's disagree beyond that covariance by a size that matters adds a
    warning and clears ``health.ok`` (health.disagreement_warning)."""
    cov = np.asarray(lg.cov_position_m2, dtype=float)
    t_s = np.asarray(lg.t_s, dtype=float)
    if "filter" not in lg.camera_xz or len(cov) != len(t_s) or not len(t_s):
        return
    health["filter_sigma"] = filter_sigma_summary(cov)
    for mode in ("smoother", "batch"):
        if mode in lg.camera_xz and len(lg.camera_xz[mode]) == len(t_s):
            health[f"{mode}_vs_filter"] = smoothed_vs_filtered(
                t_s, lg.camera_xz["filter"], cov, lg.camera_xz[mode]
            )
            warning = disagreement_warning(mode, health[f"{mode}_vs_filter"])
            if warning is not None:
                health.setdefault("warnings", []).append(warning)
                health["ok"] = False


def rerun_report(replay: Replay, gt) -> dict[str, Any]:
    """The retroactive re-run (vio_graph/replay.py): frames re-run, the last one's stamp
    (s), the offset applied and its sigma (s), and, with ground truth, the filter's camera
    error (cm RMS, x and z) over those frames as the first pass gave it online and as
    written after the re-run."""
    rep: dict[str, Any] = dict(replay.rerun or {})
    first = replay.first_pass_xz
    if gt is not None and first is not None and len(first):
        n = len(first)
        t_s = np.asarray(replay.log.t_s[:n])
        true = np.array([gt.trajectories["camera"].xz_at(t) for t in t_s])
        for name, xz in (("first_pass", first), ("rerun", replay.log.camera_xz["filter"][:n])):
            rms = 100.0 * np.sqrt(np.mean((np.asarray(xz) - true) ** 2, axis=0))
            rep[f"{name}_filter_camera_rmse_cm"] = {"x": float(rms[0]), "z": float(rms[1])}
    return rep
