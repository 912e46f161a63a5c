"""Any IMU mounting: the same trial with the IMU axes rotated gives the same estimate.

A recording is re-written with its IMU re-mounted (accelerometer, gyro and vendor orientation
expressed in rotated axes, ``imu_T_cam`` changed to match); the physics is the same, so the
estimate must be too (issue: within 10 % of the shank-aligned mount's ATE).
"""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest

from vio_graph.config import PipelineConfig
from vio_graph.estimator import RigGeometry
from vio_graph.geometry import make_transform, matrix_from_quat_wxyz, quat_wxyz_from_matrix
from vio_graph.pipeline import run_recording
from vio_graph.recording import Recording
from vio_graph.recording.streams import ImuTable
from vio_graph.recording.writer import write_recording
from vio_graph.types import ImuSample


def _rot(axis: str, angle_rad: float) -> np.ndarray:
    c, s = np.cos(angle_rad), np.sin(angle_rad)
    return {
        "x": np.array([[1, 0, 0], [0, c, -s], [0, s, c]]),
        "y": np.array([[c, 0, s], [0, 1, 0], [-s, 0, c]]),
        "z": np.array([[c, -s, 0], [s, c, 0], [0, 0, 1]]),
    }[axis]


def remount_imu(src: Path, dst: Path, R_new_old: np.ndarray, declare: bool = True) -> Path:
    """Copy recording ``src`` to ``dst`` with the IMU axes turned: a vector v in the old IMU
    axes is R_new_old v in the new ones. ``declare=False`` keeps the old ``imu_T_cam`` in the
    metadata (a rig whose extrinsics do not match its mounting)."""
    rec = Recording.open(src)
    R = np.asarray(R_new_old, dtype=float)
    imu = rec.imu
    quat = np.array([quat_wxyz_from_matrix(matrix_from_quat_wxyz(q) @ R.T) for q in imu.quat_wxyz])
    new_imu = ImuTable(imu.timestamp_s, imu.accel_mps2 @ R.T, imu.gyro_radps @ R.T, quat)
    T = rec.metadata.extrinsics.imu_T_cam_matrix()
    new_T = make_transform(R @ T[:3, :3], R @ T[:3, 3])
    ext = rec.metadata.extrinsics.model_copy(update={"imu_T_cam": new_T.tolist()})
    meta = rec.metadata.model_copy(update={"extrinsics": ext}) if declare else rec.metadata
    frames = ((f.depth_m, f.confidence) for f in rec.frames())
    return write_recording(
        dst, meta, new_imu, rec.joints, rec.groundtruth, rec.frame_timestamps_s, frames
    )


def test_shank_axes_undo_any_mount() -> None:
    """A sample from a rotated mount, turned into shank axes, equals the aligned sample."""
    rng = np.random.default_rng(0)
    R_s_c = np.array([[0.0, 0.0, 1.0], [-1.0, 0.0, 0.0], [0.0, -1.0, 0.0]])
    knee_T_cam = make_transform(R_s_c, [0.07, 0.0, -0.05])
    imu_T_cam = make_transform(R_s_c, [0.02, 0.0, 0.01])  # shank-aligned IMU
    aligned = RigGeometry(np.eye(3), imu_T_cam, knee_T_cam, leg=None)
    assert aligned.imu_is_shank_aligned
    R_world_imu = _rot("y", 0.4) @ _rot("z", 1.0)
    s = ImuSample(0.5, rng.normal(size=3), rng.normal(size=3), quat_wxyz_from_matrix(R_world_imu))
    assert aligned.imu_in_shank_axes(s) is s  # bit for bit
    for R in (R_s_c.T, _rot("x", np.pi / 2), _rot("y", -np.pi / 2), _rot("x", np.pi)):
        mounted = RigGeometry(
            np.eye(3), make_transform(R @ imu_T_cam[:3, :3], R @ imu_T_cam[:3, 3]), knee_T_cam, None
        )
        assert not mounted.imu_is_shank_aligned
        raw = ImuSample(
            0.5, R @ s.accel_mps2, R @ s.gyro_radps, quat_wxyz_from_matrix(R_world_imu @ R.T)
        )
        back = mounted.imu_in_shank_axes(raw)
        np.testing.assert_allclose(back.accel_mps2, s.accel_mps2, atol=1e-12)
        np.testing.assert_allclose(back.gyro_radps, s.gyro_radps, atol=1e-12)
        np.testing.assert_allclose(matrix_from_quat_wxyz(back.quat_wxyz), R_world_imu, atol=1e-12)
        np.testing.assert_allclose(mounted.shank_imu_T_cam, imu_T_cam, atol=1e-12)


def _config() -> PipelineConfig:
    """Default pipeline, no plots, shank pitch from the IMU (so that the reported shank pitch
    error is the IMU attitude's, whatever the mount)."""
    base = PipelineConfig()
    return base.model_copy(
        update={
            "output": base.output.model_copy(update={"plots": False}),
            "kinematics": base.kinematics.model_copy(update={"shank_pitch_source": "imu"}),
        }
    )


@pytest.fixture(scope="module")
def aligned_ate(short_upstair: Path, tmp_path_factory: pytest.TempPathFactory) -> dict:
    out = tmp_path_factory.mktemp("mount") / "aligned"
    run_recording(
        short_upstair, out, _config(), modes=("filter", "smoother"), progress=False, visualize=False
    )
    return json.loads((out / "metrics.json").read_text())


MOUNTS = {
    "camera_axes": None,  # IMU axes = camera axes (imu_T_cam rotation = identity)
    "x90": _rot("x", np.pi / 2),
    "y90": _rot("y", np.pi / 2),
    "z90": _rot("z", np.pi / 2),
    "upside_down": _rot("x", np.pi),
}


@pytest.mark.slow
@pytest.mark.parametrize("mount", list(MOUNTS))
def test_any_mount_gives_the_aligned_estimate(
    mount: str, short_upstair: Path, aligned_ate: dict, tmp_path: Path
) -> None:
    R = MOUNTS[mount]
    if R is None:  # new IMU axes are the camera's: v_cam = R_imu_cam^T v_imu
        R = Recording.open(short_upstair).metadata.extrinsics.imu_T_cam_matrix()[:3, :3].T
    rec = remount_imu(short_upstair, tmp_path / "rec", R)
    modes = ("filter", "smoother") if mount in ("camera_axes", "upside_down") else ("filter",)
    out = tmp_path / "res"
    run_recording(rec, out, _config(), modes=modes, progress=False, visualize=False)
    m = json.loads((out / "metrics.json").read_text())
    for mode in modes:
        for axis in ("x", "z"):
            ref = aligned_ate["ate_cm"][mode]["toe"][axis]
            got = m["ate_cm"][mode]["toe"][axis]
            assert got <= 1.1 * ref + 0.05, (mode, axis, got, ref)
    # the shank pitch comes out right whatever the mount (it was 21 deg off with camera axes)
    assert m["shank_pitch_error_deg"]["rms"] < 1.0
