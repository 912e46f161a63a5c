"""One simulated trial: terrain -> gait -> sensors -> recording (the only I/O is the writer)."""

from __future__ import annotations

import datetime as _dt
from collections.abc import Callable, Iterator
from dataclasses import dataclass
from pathlib import Path

import numpy as np
from numpy.typing import NDArray

from vio_graph.errors import TerrainTooShortError
from vio_graph.geometry import invert_transform, make_transform, rot_x, rot_y, rot_z
from vio_graph.recording.metadata import (
    FORMAT_VERSION,
    ContactModel,
    Extrinsics,
    ImuModel,
    LegGeometry,
    Provenance,
    RecordingMetadata,
    TerrainInfo,
)
from vio_graph.recording.streams import ContactTable, GroundTruth, ImuTable, JointTable
from vio_graph.sim import faults as _faults
from vio_graph.sim.cache import software_tag
from vio_graph.sim.config import RigConfig, ScenarioConfig
from vio_graph.sim.contact import simulate_contact
from vio_graph.sim.gait import LegMotion, simulate_gait
from vio_graph.sim.imu import ImuTruth, simulate_imu
from vio_graph.sim.joints import simulate_joints
from vio_graph.sim.mocap import camera_poses, simulate_mocap
from vio_graph.sim.plausibility import check_plausible_motion
from vio_graph.sim.terrain import Terrain, build_terrain
from vio_graph.sim.tof import TofCamera

# random streams by name; append only (the index seeds each stream)
_STREAMS = ("terrain", "gait", "imu", "joints", "mocap", "frames", "tof", "faults", "contact")


def R_shank_cam(pitch_down_deg: float) -> NDArray[np.float64]:
    """Camera (optical: x right, y down, z forward) in the shank frame, optical axis pitched
    ``pitch_down_deg`` below the shank's anterior x axis."""
    b = np.radians(pitch_down_deg)
    z_c = np.array([np.cos(b), 0.0, -np.sin(b)])
    x_c = np.array([0.0, -1.0, 0.0])
    y_c = np.cross(z_c, x_c)
    return np.stack([x_c, y_c, z_c], axis=1)


def R_shank_imu(rig: RigConfig) -> NDArray[np.float64]:
    """IMU axes in the shank frame: the base axes (``rig.imu_axes``: shank or camera) rotated
    by ``rig.imu_rotation_rpy_deg`` = Rz(yaw) Ry(pitch) Rx(roll)."""
    base = np.eye(3) if rig.imu_axes == "shank" else R_shank_cam(rig.camera_pitch_down_deg)
    if not any(rig.imu_rotation_rpy_deg):
        return base
    roll, pitch, yaw = np.radians(rig.imu_rotation_rpy_deg)
    return base @ rot_z(yaw) @ rot_y(pitch) @ rot_x(roll)


def rig_transforms(rig: RigConfig) -> tuple[NDArray, NDArray, NDArray]:
    """knee_T_cam, knee_T_imu (4x4) and the IMU point in the shank frame (x, z)."""
    R_s_c = R_shank_cam(rig.camera_pitch_down_deg)
    cam = np.array([rig.camera_in_shank_xz_m[0], 0.0, rig.camera_in_shank_xz_m[1]])
    knee_T_cam = make_transform(R_s_c, cam)
    imu_p = cam + R_s_c @ np.asarray(rig.imu_in_camera_xyz_m, dtype=float)
    imu_p[1] = 0.0  # the leg model is planar: keep the IMU in the sagittal plane
    knee_T_imu = make_transform(R_shank_imu(rig), imu_p)
    return knee_T_cam, knee_T_imu, imu_p[[0, 2]]


@dataclass(frozen=True)
class SimulatedTrial:
    """Everything about one simulated trial, in memory. Depth frames are rendered lazily."""

    config: ScenarioConfig
    seed: int
    terrain: Terrain
    motion: LegMotion
    camera: TofCamera
    metadata: RecordingMetadata
    imu: ImuTable
    imu_truth: ImuTruth
    joints: JointTable
    groundtruth: GroundTruth
    frame_timestamps_s: NDArray[np.float64]  # (F,) as recorded (offset / jitter faults)
    camera_position_m: NDArray[np.float64]  # (F, 3) true, at the true capture times
    R_world_cam: NDArray[np.float64]  # (F, 3, 3)
    camera_in_shank_xz_m: NDArray[np.float64]
    imu_in_shank_xz_m: NDArray[np.float64]
    frame_true_time_s: NDArray[np.float64]  # (F,) true capture times
    frame_source_index: NDArray[np.int64]  # (F,) index before dropped frames were removed
    imu_spike_index: NDArray[np.int64]  # IMU samples carrying an injected spike
    contact: ContactTable | None = None  # contact.csv (config.contact.kind != none)

    @property
    def n_frames(self) -> int:
        return int(self.frame_timestamps_s.size)

    def render_frame(self, i: int) -> tuple[NDArray[np.float32], NDArray[np.uint8]]:
        """Depth (H, W) float32 m (0 invalid) and confidence uint8 of frame i (deterministic)."""
        src = int(self.frame_source_index[i])
        rng = np.random.default_rng([self.seed, _STREAMS.index("tof"), src])
        depth, conf = self.camera.render(self.camera_position_m[i], self.R_world_cam[i], rng)
        fc = self.config.faults
        if _faults.has_depth_faults(fc):
            rng_f = np.random.default_rng([self.seed, _STREAMS.index("faults"), src])
            depth, conf = _faults.corrupt_depth(
                depth, conf, float(self.frame_true_time_s[i]), fc, self.config.camera, rng_f
            )
        return depth, conf

    def frames(self) -> Iterator[tuple[NDArray[np.float32], NDArray[np.uint8]]]:
        """Lazy generator over all frames (for write_recording)."""
        for i in range(self.n_frames):
            yield self.render_frame(i)


def _rng(seed: int, stream: str) -> np.random.Generator:
    return np.random.default_rng([seed, _STREAMS.index(stream)])


_LENGTH_STEP_M = 0.25  # search step for a terrain length that covers the trial
_LENGTH_SEARCH_M = 30.0  # give up suggesting a length beyond this much more terrain


def _terrain_and_gait(
    config: ScenarioConfig, seed: int, suggest: bool = True
) -> tuple[Terrain, LegMotion]:
    """The terrain and the leg's motion; when the terrain is too short, the error names the
    shortest length of the end field (0.25 m steps) with which this seed's walk covers the
    trial (the walk ends on whole strides drawn with jitter, so no formula gives it). A motion
    whose shank IMU specific force exceeds ``gait.max_shank_specific_force_g`` raises
    ImplausibleMotionError (``check_plausible_motion``)."""
    terrain = build_terrain(config.terrain, _rng(seed, "terrain"))
    try:
        motion = simulate_gait(
            terrain, config.gait, config.rig, config.duration_s, _rng(seed, "gait")
        )
    except TerrainTooShortError as err:
        if not suggest:
            raise
        now_m = float(getattr(config.terrain, err.field))
        for k in range(1, int(_LENGTH_SEARCH_M / _LENGTH_STEP_M) + 1):
            length_m = now_m + k * _LENGTH_STEP_M
            longer = config.model_copy(
                update={"terrain": config.terrain.model_copy(update={err.field: length_m})}
            )
            try:
                _terrain_and_gait(longer, seed, suggest=False)
            except TerrainTooShortError:
                continue
            raise TerrainTooShortError(
                f"{err}; with terrain.{err.field}: {length_m:.2f} (now {now_m:.2f}) this "
                f"trial simulates for seed {seed} (checked)",
                err.field,
            ) from None
        raise
    # refuse a motion no human shank makes (a foothold out of reach, a folded swing)
    bound_g = config.gait.max_shank_specific_force_g
    if bound_g is not None:
        _, _, imu_xz = rig_transforms(config.rig)
        check_plausible_motion(motion, imu_xz, config.duration_s, terrain, config.gait, bound_g)
    return terrain, motion


def simulate_trial(config: ScenarioConfig, seed: int) -> SimulatedTrial:
    """Simulate one trial in memory (frames are rendered on demand)."""
    terrain, motion = _terrain_and_gait(config, seed)
    knee_T_cam, knee_T_imu, imu_xz = rig_transforms(config.rig)
    cam_xz = np.asarray(config.rig.camera_in_shank_xz_m, dtype=float)
    R_s_c = knee_T_cam[:3, :3]
    imu, imu_state, truth = simulate_imu(
        motion,
        config.imu,
        config.duration_s,
        imu_xz,
        _rng(seed, "imu"),
        R_shank_imu=knee_T_imu[:3, :3],
    )
    joints = simulate_joints(motion, config.joints, imu.timestamp_s, _rng(seed, "joints"))
    fc = config.faults
    f_rng = _rng(seed, "faults")
    accel, gyro, spikes = _faults.corrupt_imu(
        imu.accel_mps2, imu.gyro_radps, config.imu.rate_hz, fc, f_rng
    )
    imu_stamp = _faults.stamp_times(
        imu.timestamp_s, 0.0, fc.clock_jitter_s, 1.0 / config.imu.rate_hz, f_rng
    )
    imu = ImuTable(imu_stamp, accel, gyro, imu.quat_wxyz)
    joints = JointTable(imu_stamp.copy(), joints.thigh_pitch_rad, joints.knee_rad, joints.ankle_rad)
    traj = simulate_mocap(
        motion, config.mocap, config.duration_s, cam_xz, R_s_c, _rng(seed, "mocap")
    )
    camera = TofCamera(config.camera, terrain)
    fr = _rng(seed, "frames")
    period = 1.0 / config.camera.frame_rate_hz
    nominal = np.arange(0.5 * period, config.duration_s - 1e-9, period)
    jitter = fr.normal(0, config.camera.timestamp_jitter_s, nominal.size)
    frame_t = nominal + np.clip(jitter, -0.4 * period, 0.4 * period)
    source = _faults.kept_frames(frame_t.size, fc, f_rng)
    frame_t = frame_t[source]
    frame_stamp = _faults.stamp_times(
        frame_t, fc.camera_time_offset_s, fc.clock_jitter_s, period, f_rng
    )
    cam_pos, R_w_c = camera_poses(motion, frame_t, cam_xz, R_s_c)
    edges = np.zeros((terrain.edges_xz_m.shape[0], 3))
    edges[:, 0], edges[:, 2] = terrain.edges_xz_m[:, 0], terrain.edges_xz_m[:, 1]
    visible = camera.edges_visible(cam_pos, R_w_c, edges).any(axis=1).astype(np.int8)
    gt = GroundTruth(trajectories=traj, imu_state=imu_state, frame_edge_visible=visible)
    notes = _faults.summary(fc, nominal.size - source.size, spikes.size)
    contact, contact_model = None, None
    if config.contact.kind != "none":
        contact, contact_model = simulate_contact(
            motion,
            config.contact,
            config.duration_s,
            _rng(seed, "contact"),
            pause_ramp_s=config.gait.pause_ramp_s,
        )
    metadata = _metadata(
        config, seed, terrain, motion, camera, knee_T_cam, knee_T_imu, notes, contact_model
    )
    return SimulatedTrial(
        config=config,
        seed=seed,
        terrain=terrain,
        motion=motion,
        camera=camera,
        metadata=metadata,
        imu=imu,
        imu_truth=truth,
        joints=joints,
        groundtruth=gt,
        frame_timestamps_s=frame_stamp,
        camera_position_m=cam_pos,
        R_world_cam=R_w_c,
        camera_in_shank_xz_m=cam_xz,
        imu_in_shank_xz_m=imu_xz,
        frame_true_time_s=frame_t,
        frame_source_index=source,
        imu_spike_index=spikes,
        contact=contact,
    )


def _metadata(
    config: ScenarioConfig,
    seed: int,
    terrain: Terrain,
    motion: LegMotion,
    camera: TofCamera,
    knee_T_cam: NDArray,
    knee_T_imu: NDArray,
    notes: str = "",
    contact: ContactModel | None = None,
) -> RecordingMetadata:
    ic = config.imu
    leg = motion.leg
    return RecordingMetadata(
        format_version=FORMAT_VERSION,
        duration_s=config.duration_s,
        camera=camera.camera_model(),
        imu=ImuModel(
            rate_hz=ic.rate_hz,
            accel_noise_density_mps2_per_sqrt_hz=ic.accel_noise_density,
            gyro_noise_density_radps_per_sqrt_hz=ic.gyro_noise_density,
            accel_bias_random_walk_mps3_per_sqrt_hz=ic.accel_bias_rw,
            gyro_bias_random_walk_radps2_per_sqrt_hz=ic.gyro_bias_rw,
            orientation_rms_rad=float(np.radians(ic.orientation_rms_deg)),
            # a saturation fault emulates an IMU with that lower range: declare it
            accel_range_mps2=min(
                ic.accel_range_mps2, config.faults.imu_accel_saturation_mps2 or np.inf
            ),
            gyro_range_radps=min(
                ic.gyro_range_radps, config.faults.imu_gyro_saturation_radps or np.inf
            ),
        ),
        joint_rate_hz=ic.rate_hz,
        groundtruth_rate_hz=config.mocap.rate_hz,
        extrinsics=Extrinsics(
            imu_T_cam=(invert_transform(knee_T_imu) @ knee_T_cam).tolist(),
            knee_T_cam=knee_T_cam.tolist(),
        ),
        leg=LegGeometry(
            rig=config.rig.rig,
            thigh_length_m=leg.thigh_length_m,
            shank_length_m=leg.shank_length_m,
            heel_in_foot_xz_m=leg.heel_in_foot_xz_m,
            toe_in_foot_xz_m=leg.toe_in_foot_xz_m,
        ),
        terrain=TerrainInfo(
            kind=terrain.kind,
            params=terrain.params,
            profile_xz_m=[tuple(p) for p in terrain.profile_xz_m.tolist()],
            edges_xz_m=[tuple(p) for p in terrain.edges_xz_m.tolist()],
        ),
        provenance=Provenance(
            source="simulator",
            scenario=config.name,
            seed=seed,
            # without a contact sensor the saved config is the same as before the section
            config=provenance_config(config),
            software=software_tag(),
            created_utc=_dt.datetime.now(_dt.UTC).strftime("%Y-%m-%dT%H:%M:%SZ"),
            notes=notes,
        ),
        contact=contact,
    )


#: fields added after recordings were published, by section: left out of the saved config at
#: their defaults, so a scenario that does not use them saves the same metadata as before
_LATER_FIELDS = {
    "terrain": (
        "rise_jitter_m",
        "tread_jitter_m",
        "first_rise_m",
        "last_rise_m",
        "open_risers",
    ),
    "gait": ("obstacle_step_on_depth_m", "max_shank_specific_force_g"),
    "faults": ("imu_knock_start_s", "imu_knock_duration_s", "imu_knock_accel_mps2"),
}


def provenance_config(config: ScenarioConfig) -> dict:
    """The scenario as saved in ``metadata.provenance.config`` (JSON-ready): the whole
    config, without the contact section when there is no contact sensor and without the
    later fields (``_LATER_FIELDS``) at their defaults."""
    exclude: dict = {}
    for section, names in _LATER_FIELDS.items():
        cfg = getattr(config, section)
        default = type(cfg)()
        later = {k for k in names if getattr(cfg, k) == getattr(default, k)}
        if later:
            exclude[section] = later
    if config.contact.kind == "none":
        exclude["contact"] = True
    return config.model_dump(mode="json", exclude=exclude or None)


def simulate(
    config: ScenarioConfig,
    seed: int,
    out_dir: Path,
    progress: Callable[[int], None] | None = None,
    overwrite: bool = False,
) -> Path:
    """Simulate a trial and write it as a recording folder; returns the folder."""
    from vio_graph.recording.writer import write_recording

    trial = simulate_trial(config, seed)
    return write_recording(
        Path(out_dir),
        trial.metadata,
        trial.imu,
        trial.joints,
        trial.groundtruth,
        trial.frame_timestamps_s,
        trial.frames(),
        progress=progress,
        overwrite=overwrite,
        contact=trial.contact,
    )
