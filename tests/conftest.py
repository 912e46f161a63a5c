"""Shared fixtures: a tiny hand-made recording (independent of the simulator), and the safety
monitor's per-frame inputs on data/sample."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

from vio_graph.geometry import make_transform, quat_wxyz_from_matrix, rot_y
from vio_graph.recording.metadata import (
    FORMAT_VERSION,
    CameraModel,
    Extrinsics,
    ImuModel,
    LegGeometry,
    Provenance,
    RecordingMetadata,
    TerrainInfo,
)
from vio_graph.recording.streams import GroundTruth, ImuTable, JointTable, Trajectory
from vio_graph.recording.writer import write_recording


def tiny_metadata(
    width: int = 16, height: int = 12, frame_rate_hz: float = 30.0
) -> RecordingMetadata:
    R_s_c = np.array([[0.0, 0.0, 1.0], [-1.0, 0.0, 0.0], [0.0, -1.0, 0.0]])
    return RecordingMetadata(
        format_version=FORMAT_VERSION,
        duration_s=1.0,
        camera=CameraModel(
            width_px=width,
            height_px=height,
            fx_px=15.0,
            fy_px=15.0,
            cx_px=width / 2,
            cy_px=height / 2,
            depth_unit_m=0.001,
            min_range_m=0.1,
            max_range_m=2.4,
            frame_rate_hz=frame_rate_hz,
        ),
        imu=ImuModel(
            rate_hz=100.0,
            accel_noise_density_mps2_per_sqrt_hz=1.18e-3,
            gyro_noise_density_radps_per_sqrt_hz=1.22e-4,
            accel_bias_random_walk_mps3_per_sqrt_hz=1e-4,
            gyro_bias_random_walk_radps2_per_sqrt_hz=1e-5,
            orientation_rms_rad=0.017,
            accel_range_mps2=156.9,
            gyro_range_radps=34.9,
        ),
        joint_rate_hz=100.0,
        groundtruth_rate_hz=120.0,
        extrinsics=Extrinsics(
            imu_T_cam=make_transform(np.eye(3) @ R_s_c, [0.02, 0, 0]).tolist(),
            knee_T_cam=make_transform(R_s_c, [0.06, 0, -0.1]).tolist(),
        ),
        leg=LegGeometry(
            rig="able_bodied",
            thigh_length_m=0.43,
            shank_length_m=0.43,
            heel_in_foot_xz_m=(-0.05, -0.07),
            toe_in_foot_xz_m=(0.2, -0.07),
        ),
        terrain=TerrainInfo(
            kind="stair_up",
            params={"rise_m": 0.147, "tread_m": 0.28},
            profile_xz_m=[(0.0, 0.0), (0.5, 0.0), (0.5, 0.147), (0.78, 0.147)],
            edges_xz_m=[(0.5, 0.147)],
        ),
        provenance=Provenance(source="device", notes="hand-made test recording"),
    )


def tiny_streams(meta: RecordingMetadata, duration_s: float = 1.0, seed: int = 0):
    rng = np.random.default_rng(seed)
    t_imu = np.arange(0.0, duration_s, 1.0 / meta.imu.rate_hz)
    n = t_imu.size
    pitch = 0.2 * np.sin(2 * np.pi * t_imu)
    R = rot_y(pitch)
    accel = np.einsum("nji,j->ni", R, np.array([0.0, 0.0, 9.81])) + rng.normal(0, 0.01, (n, 3))
    imu = ImuTable(t_imu, accel, rng.normal(0, 0.01, (n, 3)), quat_wxyz_from_matrix(R))
    joints = JointTable(t_imu.copy(), 0.1 * np.ones(n), 0.3 * np.ones(n), -0.05 * np.ones(n))
    t_frames = np.arange(0.0, duration_s, 1.0 / meta.camera.frame_rate_hz)
    h, w = meta.camera.height_px, meta.camera.width_px
    frames = [
        (np.full((h, w), 0.5 + 0.01 * k, np.float32), np.full((h, w), 200, np.uint8))
        for k in range(t_frames.size)
    ]
    frames[0][0][0, 0] = 0.0  # one invalid pixel
    t_gt = np.arange(0.0, duration_s, 1.0 / 120.0)
    trajs = {
        body: Trajectory.from_xz(t_gt, np.column_stack([0.3 * t_gt + k, 0.1 * t_gt]))
        for k, body in enumerate(("camera", "knee", "ankle", "heel", "toe"))
    }
    gt = GroundTruth(trajectories=trajs, frame_edge_visible=np.ones(t_frames.size, np.int8))
    return imu, joints, gt, t_frames, frames


@pytest.fixture
def tiny_recording(tmp_path: Path) -> Path:
    meta = tiny_metadata()
    imu, joints, gt, t_frames, frames = tiny_streams(meta)
    return write_recording(tmp_path / "rec", meta, imu, joints, gt, t_frames, iter(frames))


@pytest.fixture(scope="session")
def short_upstair(tmp_path_factory: pytest.TempPathFactory) -> Path:
    """A 4 s simulated upstair trial (seed 3), shared by the end-to-end tests."""
    from vio_graph.sim import load_scenario, simulate

    cfg = load_scenario("upstair").model_copy(update={"duration_s": 4.0})
    return simulate(cfg, seed=3, out_dir=tmp_path_factory.mktemp("rec") / "up")


@pytest.fixture(scope="session")
def sample_frames() -> list[tuple]:
    """The monitor's per-frame inputs on data/sample, as the online estimator gives them
    (filter camera and covariance, heel and toe by kinematics, stance, keyframe profiles)."""
    from vio_graph.config import load_config
    from vio_graph.pipeline import leg_trajectories
    from vio_graph.recording.reader import Recording
    from vio_graph.replay import Replay
    from vio_graph.viz.rerun_logger import NullVisualizer

    cfg = load_config(None)
    replay = Replay(
        Recording.open(Path(__file__).resolve().parents[1] / "data" / "sample"),
        cfg,
        {"filter"},
        NullVisualizer(),
    )
    lg = replay.run()
    use_enc = cfg.kinematics.shank_pitch_source == "encoders"
    legs = leg_trajectories(replay.rig, lg.camera_xz["filter"], lg, use_enc)
    return [
        (
            float(lg.t_s[k]),
            legs["camera"][k],
            lg.cov_position_m2[k],
            legs["heel"][k],
            legs["toe"][k],
            bool(lg.in_stance[k]),
            lg.profiles.get(k),
        )
        for k in range(len(lg.t_s))
    ]
