"""The replay loop: a recording in, estimates, metrics, map, plots and a rerun view out.

``run_recording`` is a table of contents: replay the streams in time order through the online
estimator (filter mode) and, beside it, the baselines and the smoothers; finish the smoothers;
derive every mode's leg trajectories by forward kinematics; evaluate against ground truth;
build the map from the best available keyframe poses; write everything atomically.
"""

from __future__ import annotations

import dataclasses
import logging
import signal
import time
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np
from numpy.typing import NDArray

import vio_graph
from vio_graph.config import PipelineConfig, dump_config
from vio_graph.errors import EstimationError, OutputError
from vio_graph.estimator import OnlineEstimator, RigGeometry
from vio_graph.evaluation.diagnostics import displacement_nees, stance_scores, true_stance
from vio_graph.evaluation.run_metrics import (
    evaluate_paths,
    shank_pitch_error_deg,
    terrain_accuracy,
)
from vio_graph.filter.baselines import IcpOdometry, ImuDeadReckoning
from vio_graph.frontend.projection import depth_to_points_cam
from vio_graph.io_utils import atomic_write_json, atomic_write_text, remove_temporaries
from vio_graph.mapping.local_map import TerrainMap2D
from vio_graph.recording.reader import Recording
from vio_graph.recording.streams import Trajectory
from vio_graph.recording.tum import write_tum
from vio_graph.types import Displacement2D, EstimateStatus, LandmarkObservation, TerrainKind

log = logging.getLogger(__name__)

MODES = ("filter", "smoother", "batch")
BASELINES = ("imu_only", "icp_only")


@dataclass
class FrameLog:
    """Per-frame quantities collected during the replay (lists, one entry per depth frame)."""

    t_s: list[float] = field(default_factory=list)
    camera_xz: dict[str, list[NDArray[np.float64]]] = field(default_factory=dict)
    shank_pitch_imu: list[float] = field(default_factory=list)
    shank_pitch_chain: list[float] = field(default_factory=list)
    ankle_rad: list[float] = field(default_factory=list)
    status: list[str] = field(default_factory=list)
    terrain: list[str] = field(default_factory=list)
    displacement_ok: list[bool] = field(default_factory=list)
    rejection: list[str] = field(default_factory=list)
    is_keyframe: list[bool] = field(default_factory=list)
    profiles: dict[int, NDArray[np.float64]] = field(default_factory=dict)  # keyframes only
    timings_ms: list[dict[str, float]] = field(default_factory=list)
    filter_rejected: int = 0
    in_stance: list[bool] = field(default_factory=list)  # stance anchor used at this frame
    displacements: list[Displacement2D] = field(default_factory=list)  # the front end's


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


def _stats_ms(values: list[float] | NDArray[np.float64]) -> dict[str, float]:
    v = np.asarray(values, dtype=float)
    if v.size == 0:
        return {"median": float("nan"), "p95": float("nan"), "mean": float("nan"), "n": 0}
    return {
        "median": float(np.median(v)),
        "p95": float(np.percentile(v, 95)),
        "mean": float(np.mean(v)),
        "n": int(v.size),
    }


def replay_order(rec: Recording) -> tuple[NDArray[np.int8], NDArray[np.int64]]:
    """Event order by time: (kind, index) with kind 0 = IMU, 1 = joints, 2 = depth frame,
    3 = contact sample (recordings with ``contact.csv``).

    On equal timestamps IMU comes first, then joints, then contact, then the frame (no
    look-ahead: a frame only sees sensor data stamped at or before it).
    """
    times = [rec.imu.timestamp_s, rec.joints.timestamp_s, rec.frame_timestamps_s]
    if rec.contact is not None:
        times.append(rec.contact.timestamp_s)
    kinds = np.concatenate([np.full(t.shape[0], k, np.int8) for k, t in enumerate(times)])
    idx = np.concatenate([np.arange(t.shape[0]) for t in times])
    priority = np.array([0, 1, 3, 2], np.int8)[kinds]  # contact before the frame
    order = np.lexsort((priority, np.concatenate(times)))
    return kinds[order], idx[order]


class Replay:
    """Drives the online estimator, the baselines and the smoothers through one recording."""

    def __init__(self, rec: Recording, config: PipelineConfig, modes: set[str], viz) -> None:
        self.rec = rec
        self.config = config
        self.modes = modes
        self.viz = viz
        self.rig = RigGeometry.from_metadata(rec.metadata)
        gt = rec.groundtruth
        p0 = None
        if gt is not None:  # place the estimate's origin at the true start (the paper's anchor)
            p0 = _interp_xz(gt.trajectories["camera"], rec.frame_timestamps_s[0])
        self.p0 = np.zeros(2) if p0 is None else p0
        self.online = OnlineEstimator(config, self.rig, p0)
        self.baselines = {
            "imu_only": ImuDeadReckoning(config.filter, self.rig.shank_imu_T_cam),
            "icp_only": IcpOdometry(),
        }
        self.smoothers: dict[str, Any] = {}
        if "smoother" in modes:
            from vio_graph.smoother.sliding_window import SlidingWindowSmoother

            self.smoothers["smoother"] = SlidingWindowSmoother(
                config.smoother, self.rig.shank_imu_T_cam)
        if "batch" in modes:
            from vio_graph.smoother.batch import BatchSmoother

            self.smoothers["batch"] = BatchSmoother(config.smoother, self.rig.shank_imu_T_cam)
        self.log = FrameLog(camera_xz={m: [] for m in ("filter", *BASELINES)})
        self._inject_rng = np.random.default_rng(config.inject.seed)
        self.injected_wrong_associations = 0
        self.batch_solve_s = float("nan")
        self.failed: dict[str, dict[str, Any]] = {}
        self.failed_smoothers: dict[str, Any] = {}

    def run(self, progress=None) -> FrameLog:
        rec, online, lg = self.rec, self.online, self.log
        kinds, idx = replay_order(rec)
        started = False
        waiting: list[int] = []  # frames whose capture time the IMU has not reached yet
        for kind, i in zip(kinds, idx, strict=True):
            if kind != 2 and waiting:
                self._release_frames(waiting, progress)
            if kind == 0:
                s = rec.imu.sample(int(i))
                if not online.add_imu(s):
                    continue  # stamp at or before the previous one: reported, not fused
                s = online.latest_imu_shank_axes  # the sample in shank axes, for the peers
                for b in self.baselines.values():
                    if not started:
                        b.initialise(s.timestamp_s, self.p0)
                    else:
                        b.propagate(s)
                s_level = online.latest_imu  # s with the level-surface pitch applied
                for name, sm in list(self.smoothers.items()):
                    self._guard(name, sm.add_imu, s_level)
                started = True
            elif kind == 1:
                online.add_joints(rec.joints.sample(int(i)))
            elif kind == 3:
                online.add_contact(rec.contact.sample(int(i)))
            else:
                if not started:
                    continue  # frames before the first IMU sample cannot be placed
                waiting.append(int(i))
                self._release_frames(waiting, progress)
        self._release_frames(waiting, progress, final=True)
        for name, sm in list(self.smoothers.items()):
            self._guard(name, sm.flush)
        if "batch" in self.smoothers:
            t0 = time.perf_counter()
            self._guard("batch", self.smoothers["batch"].solve)
            self.batch_solve_s = time.perf_counter() - t0
        return lg

    def _release_frames(self, waiting: list[int], progress, final: bool = False) -> None:
        """Process the waiting frames whose capture time on the IMU clock (stamp minus the
        camera-IMU offset, filter/time_offset.py) is at most one IMU period after the latest
        IMU sample (as without an offset); a negative offset (early camera stamps) holds a
        frame until the IMU has caught up."""
        online = self.online
        period = 1.0 / self.rec.metadata.imu.rate_hz
        while waiting:
            t_imu = online.latest_imu.timestamp_s
            t_cap = self.rec.frame_timestamps_s[waiting[0]] - online.time_offset.applied_s
            if not final and t_cap > t_imu + period:
                return
            i = waiting.pop(0)
            self._frame(i)
            if progress is not None:
                progress(i + 1)

    def _smoother_observations(self, res) -> list[LandmarkObservation]:
        """Landmark observations for the smoothers: the corner and, if enabled, the stance
        anchor (the planted ankle, a landmark seen through the leg)."""
        corner = self.online.corner_observation  # re-identified corners share a track id
        obs: list[LandmarkObservation] = [corner] if corner is not None else []
        stance = self.online.stance_observation
        if stance is not None and self.config.smoother.factors.stance_anchors:
            obs.append(stance)
        return obs

    def _guard(self, name: str, fn, *args) -> None:
        """Call a smoother; if it fails (e.g. GTSAM finds the system indeterminate), stop feeding
        it, keep its last good keyframes, and record the failure instead of killing the run
        (the filter's answer stands in for the frames after it)."""
        try:
            fn(*args)
        except EstimationError as exc:
            t = (
                args[0].timestamp_s
                if args and hasattr(args[0], "timestamp_s")
                else (args[0] if args and isinstance(args[0], float) else float("nan"))
            )
            log.warning("%s stopped at t=%.3f s: %s", name, t, str(exc).splitlines()[0])
            self.failed[name] = {"t_s": t, "error": str(exc).splitlines()[0]}
            self.failed_smoothers[name] = self.smoothers.pop(name)

    def _inject(self, res):
        """Shift a displacement by a whole stair step (config.inject), for robustness tests."""
        inj = self.config.inject
        if res.displacement is None or inj.wrong_association_rate <= 0:
            return res
        if self._inject_rng.random() >= inj.wrong_association_rate:
            return res
        sign = 1.0 if self._inject_rng.random() < 0.5 else -1.0
        d = res.displacement
        bad = dataclasses.replace(d, delta_xz_m=d.delta_xz_m + sign * np.asarray(inj.step_xz_m))
        self.injected_wrong_associations += 1
        return dataclasses.replace(res, displacement=bad)

    def _frame(self, i: int) -> None:
        frame = self.rec.frame(i)
        est, res = self.online.add_frame(frame, transform_result=self._inject)
        lg = self.log
        lg.t_s.append(est.timestamp_s)
        lg.camera_xz["filter"].append(est.camera_xz_m)
        for name, b in self.baselines.items():
            if res.displacement is not None:
                b.update_displacement(res.displacement)
            s = b.state
            lg.camera_xz[name].append(
                s.p_xz_m + s.v_xz_mps * (est.timestamp_s - s.timestamp_s)
                if name == "imu_only"
                else s.p_xz_m.copy()
            )
        # the attitude the displacement and observations were built with (level-aided)
        R_world_imu = self.online.R_world_imu(est.timestamp_s)
        for name, sm in list(self.smoothers.items()):
            self._guard(
                name,
                sm.add_frame,
                est.timestamp_s,
                est.is_keyframe,
                est,
                res.displacement,
                self._smoother_observations(res),
                R_world_imu,
            )
        imu_pitch, chain_pitch, ankle = self.online.leg_angles(R_world_imu)
        lg.shank_pitch_imu.append(imu_pitch)
        lg.shank_pitch_chain.append(chain_pitch)
        lg.ankle_rad.append(ankle)
        lg.status.append(est.status.value)
        lg.terrain.append(res.terrain.value)
        lg.displacement_ok.append(res.displacement is not None)
        if res.displacement is not None:
            lg.displacements.append(res.displacement)
        lg.in_stance.append(self.online.in_stance)
        lg.rejection.append(res.rejection_reason or "")
        lg.is_keyframe.append(est.is_keyframe)
        if est.is_keyframe:
            lg.profiles[len(lg.t_s) - 1] = res.profile_xz_m
        lg.timings_ms.append(est.timings_ms)
        self._visualise(i, frame, est, res, R_world_imu)

    def _visualise(self, i, frame, est, res, R_world_imu) -> None:
        viz, out_cfg = self.viz, self.config.output
        viz.set_time(est.timestamp_s)
        cam_xyz = np.array([est.camera_xz_m[0], 0.0, est.camera_xz_m[1]])
        R_world_cam = R_world_imu @ self.rig.R_imu_cam
        viz.log_camera(
            cam_xyz,
            R_world_cam,
            self.rig.K,
            frame.depth_m.shape[1],
            frame.depth_m.shape[0],
            frame.depth_m,
        )
        if i % out_cfg.cloud_every_n_frames == 0:
            viz.log_cloud(
                _cloud_world(frame, self.rig.K, R_world_cam, cam_xyz, out_cfg.cloud_pixel_stride)
            )
        viz.log_sagittal("slice", est.camera_xz_m + res.profile_xz_m, 0.002, (250, 200, 0))
        if res.corner is not None:
            viz.log_sagittal(
                "features", est.camera_xz_m + res.corner.feature_points_xz_m, 0.005, (255, 40, 40)
            )
        if res.icp is not None and res.icp.target_points_xz_m.size:
            viz.log_segments(
                "icp",
                est.camera_xz_m + res.icp.matched_source_xz_m,
                est.camera_xz_m + res.icp.target_points_xz_m,
            )
        viz.log_leg(
            "est",
            np.vstack([est.knee_xz_m, est.ankle_xz_m, est.heel_xz_m, est.toe_xz_m, est.ankle_xz_m]),
        )
        viz.log_scalar("status/fused", float(est.status is EstimateStatus.FUSED))
        gt = self.rec.groundtruth
        if gt is not None:
            pts = [
                _interp_xz(gt.trajectories[b], est.timestamp_s)
                for b in ("knee", "ankle", "heel", "toe", "ankle")
            ]
            viz.log_leg("gt", np.vstack(pts))
            toe_err = est.toe_xz_m - pts[3]
            viz.log_scalar("error_cm/toe_x", 100 * toe_err[0])
            viz.log_scalar("error_cm/toe_z", 100 * toe_err[1])


def _interp_xz(traj: Trajectory, t: float) -> NDArray[np.float64]:
    return np.array([np.interp(t, traj.timestamp_s, traj.position_m[:, k]) for k in (0, 2)])


def _cloud_world(frame, K, R_world_cam, cam_xyz, stride: int) -> NDArray[np.float64]:
    """The frame's valid points in the world frame, every ``stride``-th pixel (for viewing):
    the front end's back-projection on the subsampled image with its scaled intrinsics."""
    K_sub = np.array(K, dtype=float)
    K_sub[:2] /= stride
    pts = depth_to_points_cam(frame.depth_m[::stride, ::stride],
                              frame.confidence[::stride, ::stride], K_sub)
    return pts @ R_world_cam.T + cam_xyz


def leg_trajectories(
    rig: RigGeometry, camera_xz: NDArray[np.float64], lg: FrameLog, use_encoders: bool
) -> dict[str, NDArray[np.float64]]:
    """Knee, ankle, heel and toe (N, 2) for a camera path, by forward kinematics (Fig. 3)."""
    pts = rig.leg_points(camera_xz, np.asarray(lg.shank_pitch_imu),
                         np.asarray(lg.shank_pitch_chain), np.asarray(lg.ankle_rad), use_encoders)
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
    bad = set(modes) - set(MODES)
    if bad:
        raise OutputError(f"unknown modes {sorted(bad)}; choose from {MODES}")
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

    _log_static_scene(viz, rec)
    replay = Replay(rec, config, set(modes), viz)
    t_start = time.perf_counter()
    with progress_bar(
        rec.num_frames, f"estimating {Path(recording).name}", "frame", enabled=progress
    ) as bar:
        lg = replay.run(progress=bar.update_to)
    wall_s = time.perf_counter() - t_start
    t_s = np.asarray(lg.t_s)
    camera = {m: np.asarray(v) for m, v in lg.camera_xz.items()}
    filter_xz = camera["filter"]
    for name, sm in {**replay.smoothers, **replay.failed_smoothers}.items():
        try:  # a failed smoother still reports the keyframes it solved before failing
            camera[name] = np.asarray(sm.frame_trajectory(t_s, filter_xz))
        except EstimationError as exc:
            log.warning("%s has no usable estimate: %s", name, exc)
            camera[name] = filter_xz.copy()
    use_enc = config.kinematics.shank_pitch_source == "encoders"
    paths = {m: leg_trajectories(replay.rig, xz, lg, use_enc) for m, xz in camera.items()}

    # trajectories (TUM, evo-readable)
    for mode, bodies in paths.items():
        for body, xz in bodies.items():
            p = out / "trajectories" / f"{mode}_{body}.tum"
            p.parent.mkdir(exist_ok=True)
            write_tum(p, Trajectory.from_xz(t_s, xz))
            files.append(p)
    files.append(_write_frames_csv(out / "frames.csv", lg))

    metrics: dict[str, Any] = {
        "recording": str(rec.root),
        "scenario": rec.metadata.provenance.scenario,
        "seed": rec.metadata.provenance.seed,
        "terrain": rec.metadata.terrain.kind,
        "rig": rec.metadata.leg.rig,
        "modes": sorted(camera),
        "software": f"vio_graph {vio_graph.__version__}",
        "frames": len(lg.t_s),
        "wall_time_s": wall_s,
    }
    gt = rec.groundtruth
    visible = None
    if gt is not None:
        if gt.frame_edge_visible is not None:
            visible = gt.frame_edge_visible[: len(t_s)].astype(bool)
        metrics.update(evaluate_paths(gt, t_s, paths, visible))
        metrics["shank_pitch_error_deg"] = shank_pitch_error_deg(
            gt, t_s, np.asarray(lg.shank_pitch_chain if use_enc else lg.shank_pitch_imu))
    metrics["latency_ms"] = _latencies(lg, replay)
    metrics["smoother_failures"] = replay.failed
    if "batch" in replay.smoothers:  # measurements the robust kernels down-weighted
        try:
            metrics["batch_robust"] = replay.smoothers["batch"].robust_outliers()
        except EstimationError as exc:
            log.warning("batch robust statistics unavailable: %s", exc)
    metrics["frontend"] = {
        "displacement_fraction": float(np.mean(lg.displacement_ok)) if lg.t_s else 0.0,
        "rejections": _count(lg.rejection),
        "terrain_counts": _count(lg.terrain),
        "status_counts": _count(lg.status),
        "keyframes": int(np.sum(lg.is_keyframe)),
    }
    fs = replay.online.filter.state
    metrics["filter"] = {
        "accepted": fs.n_accepted,
        "rejected_chi2": fs.n_rejected,
        "stale": fs.n_stale,
        "injected_wrong_associations": replay.injected_wrong_associations,
        "level_aiding": {
            "accepted": replay.online.pitch_offset.n_accepted,
            "rejected": replay.online.pitch_offset.n_rejected,
            "final_offset_deg": float(np.degrees(replay.online.pitch_offset.offset_rad)),
        },
    }
    metrics["health"] = replay.online.health_report()
    metrics.update(replay.online.fault_report())  # imu_faults, time_offset, timestamps
    if gt is not None:
        metrics["terrain_classification"] = terrain_accuracy(
            rec.metadata.terrain.kind, lg.terrain, gt.frame_edge_visible)
        metrics["stance_detection"] = stance_scores(
            np.asarray(lg.in_stance, bool), true_stance(gt.trajectories["ankle"], t_s))
        metrics["frontend"]["displacement_nees"] = displacement_nees(
            lg.displacements, gt.trajectories["camera"], config.filter.measurement_noise_floor_m)

    # map from the best refined keyframe poses available
    map_mode = "batch" if "batch" in camera else "smoother" if "smoother" in camera else "filter"
    map_metrics, map_files = _build_and_export_map(
        rec, config, lg, camera[map_mode], out / "map", viz
    )
    metrics["map"] = {"source_mode": map_mode, **map_metrics}
    files += map_files
    if config.output.plots:
        from vio_graph.viz.plots import plot_run_overview

        files.append(plot_run_overview(out / "plots" / "overview.png", rec, t_s, paths, metrics))
    for mode, bodies in paths.items():
        viz.log_path(f"{'est' if mode == 'filter' else mode}/camera", bodies["camera"])
        viz.log_path(f"{'est' if mode == 'filter' else mode}/toe", bodies["toe"])
    viz.close()
    if isinstance(viz, Visualizer):
        files.append(out / "run.rrd")
    atomic_write_json(out / "metrics.json", metrics)
    files.append(out / "metrics.json")
    return RunResult(out_dir=out, metrics=metrics, files=files)


def _count(values: list[str]) -> dict[str, int]:
    keys, counts = np.unique(np.asarray(values, dtype=str), return_counts=True)
    return {str(k): int(c) for k, c in zip(keys, counts, strict=True)}


def _latencies(lg: FrameLog, replay: Replay) -> dict[str, Any]:
    def col(name: str) -> list[float]:
        return [t.get(name, np.nan) for t in lg.timings_ms]

    fe = col("frontend_total")
    fusion, kin, imu = col("fusion"), col("kinematics"), col("imu_propagation")
    total = np.asarray(fe) + np.asarray(fusion) + np.asarray(kin) + np.asarray(imu)
    out: dict[str, Any] = {
        "frontend": _stats_ms(fe),
        "fusion": _stats_ms(fusion),
        "kinematics": _stats_ms(kin),
        "imu_propagation_per_frame": _stats_ms(imu),
        "per_frame_total": _stats_ms(total),
    }
    for stage in ("projection", "smoothing", "terrain", "corners", "icp"):
        out[f"frontend_{stage}"] = _stats_ms(col(f"frontend_{stage}"))
    smoothers = {**replay.smoothers, **replay.failed_smoothers}
    if "smoother" in smoothers:
        sm = smoothers["smoother"]
        n = min(len(sm.update_times_ms), len(sm.build_times_ms))
        per_kf = np.asarray(sm.update_times_ms[:n]) + np.asarray(sm.build_times_ms[:n])
        out["smoother_update"] = _stats_ms(per_kf)
    if "batch" in smoothers:
        out["batch_solve_s"] = replay.batch_solve_s
    return out


def _write_frames_csv(path: Path, lg: FrameLog) -> Path:
    rows = ["frame,timestamp_s,status,terrain,displacement,rejection,keyframe,frontend_ms,"
            "stance"]
    for k, t in enumerate(lg.t_s):
        rows.append(
            f"{k},{t:.6f},{lg.status[k]},{lg.terrain[k]},{int(lg.displacement_ok[k])},"
            f"{lg.rejection[k].replace(',', ';')},{int(lg.is_keyframe[k])},"
            f"{lg.timings_ms[k].get('frontend_total', float('nan')):.4f},{int(lg.in_stance[k])}"
        )
    atomic_write_text(path, "\n".join(rows) + "\n")
    return path


def _log_static_scene(viz, rec: Recording) -> None:
    prof = np.asarray(rec.metadata.terrain.profile_xz_m, dtype=float)
    if prof.size == 0:
        return
    from vio_graph.viz.scene import extrude_profile

    verts, tris = extrude_profile(prof, width_m=1.0)
    viz.log_terrain(verts, tris, prof)
    gt = rec.groundtruth
    if gt is not None:
        for body in ("camera", "toe", "knee"):
            viz.log_path(f"gt/{body}", gt.trajectories[body].xz_m)


def _build_and_export_map(rec, config, lg: FrameLog, camera_xz, out_dir: Path, viz):
    from vio_graph.mapping.export import export_map
    from vio_graph.mapping.steps import compare_to_truth, estimate_terrain_geometry

    tmap = TerrainMap2D(config.mapping.map)
    for k, prof in lg.profiles.items():
        if prof.shape[0]:
            tmap.add_keyframe(lg.t_s[k], camera_xz[k], prof)
    pts = tmap.points_xz_m
    metrics: dict[str, Any] = {"keyframes": len(lg.profiles), "points": int(pts.shape[0])}
    if pts.shape[0] < 10:
        return metrics, []
    kind = TerrainKind(rec.metadata.terrain.kind) if rec.metadata.terrain.kind else None
    geometry = estimate_terrain_geometry(pts, tmap.point_counts, config.mapping.steps, kind)
    comparison = None
    if rec.metadata.terrain.profile_xz_m:
        comparison = compare_to_truth(geometry, rec.metadata.terrain)
        metrics.update(_flatten_comparison(comparison))
    written = export_map(
        out_dir, pts, geometry, rec.metadata.terrain, comparison, camera_xz_m=camera_xz
    )
    viz.log_sagittal("map", pts, 0.003, (90, 90, 255))
    metrics["detected_kind"] = (
        geometry.kind.value if hasattr(geometry.kind, "value") else str(geometry.kind)
    )
    return metrics, list(written.values())


def _flatten_comparison(cmp: dict[str, Any]) -> dict[str, Any]:
    """Headline map errors (mean absolute, mm) plus the full comparison."""
    out: dict[str, Any] = {
        "rise_error_mm": cmp.get("rise_mae_mm"),
        "tread_error_mm": cmp.get("tread_mae_mm"),
        "nosing_error_mm": cmp.get("nosing_mae_mm"),
        "n_steps_estimated": cmp.get("n_steps_estimated"),
        "n_steps_matched": cmp.get("n_steps_matched"),
    }
    obstacles = cmp.get("obstacles") or []
    if obstacles:
        out["obstacle_height_error_mm"] = obstacles[0].get("height_error_mm")
        out["obstacle_depth_error_mm"] = obstacles[0].get("depth_error_mm")
    out["comparison"] = cmp
    return out
