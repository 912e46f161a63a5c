"""Write a recording folder (format version 1), atomically.

Everything is written into a hidden temporary folder beside the target, which is renamed onto
the target only when complete: an interrupted write leaves no half-written recording.
"""

from __future__ import annotations

import os
import shutil
import tempfile
from collections.abc import Callable, Iterable
from pathlib import Path

import numpy as np
import yaml

from vio_graph.errors import OutputError, RecordingError
from vio_graph.recording import layout
from vio_graph.recording.metadata import RecordingMetadata
from vio_graph.recording.reader import RELEASE_EVERY_FRAMES, release_pages
from vio_graph.recording.streams import ContactTable, GroundTruth, ImuTable, JointTable
from vio_graph.recording.tum import format_tum


def _write_csv(path: Path, columns: tuple[str, ...], data: np.ndarray, fmt: str) -> None:
    data = np.asarray(data, dtype=float)
    if data.ndim != 2 or data.shape[1] != len(columns):
        raise RecordingError(path, f"expected {len(columns)} columns, got shape {data.shape}")
    if not np.all(np.isfinite(data)):
        raise RecordingError(path, "refusing to write NaN or inf")
    np.savetxt(path, data, delimiter=",", header=",".join(columns), comments="", fmt=fmt)


def write_recording(
    out_dir: Path,
    metadata: RecordingMetadata,
    imu: ImuTable,
    joints: JointTable,
    groundtruth: GroundTruth | None,
    frame_timestamps_s: np.ndarray,
    depth_frames: Iterable[tuple[np.ndarray, np.ndarray]],
    progress: Callable[[int], None] | None = None,
    overwrite: bool = False,
    contact: ContactTable | None = None,
) -> Path:
    """Write one recording.

    Args:
        out_dir: target folder; must not exist unless ``overwrite``.
        frame_timestamps_s: (N,) depth frame timestamps.
        depth_frames: N pairs (depth_m float32 (H, W) with 0 = invalid, confidence uint8 (H, W)),
            possibly a generator; depth is stored as uint16 in ``camera.depth_unit_m`` units.
        progress: called with the number of frames written so far.
        contact: optional foot-contact channel (``metadata.contact`` must describe it).
    """
    out_dir = Path(out_dir)
    if out_dir.exists() and not overwrite:
        raise OutputError(f"{out_dir}: already exists (pass overwrite=True to replace it)")
    out_dir.parent.mkdir(parents=True, exist_ok=True)
    tmp = Path(tempfile.mkdtemp(prefix=f".{out_dir.name}.", suffix=".partial", dir=out_dir.parent))
    try:
        if (contact is None) != (metadata.contact is None):
            raise OutputError(
                f"{out_dir}: a contact channel needs both the table and the "
                "metadata 'contact' section"
            )
        _write_into(
            tmp, metadata, imu, joints, groundtruth, frame_timestamps_s, depth_frames, progress
        )
        if contact is not None:
            _write_csv(
                tmp / layout.CONTACT_FILE,
                layout.CONTACT_COLUMNS,
                np.column_stack([contact.timestamp_s, contact.force_n]),
                fmt="%.9g",
            )
        if out_dir.exists():
            shutil.rmtree(out_dir)
        os.replace(tmp, out_dir)
    finally:
        if tmp.exists():
            shutil.rmtree(tmp, ignore_errors=True)
    return out_dir


def _write_into(
    root: Path,
    metadata: RecordingMetadata,
    imu: ImuTable,
    joints: JointTable,
    groundtruth: GroundTruth | None,
    frame_timestamps_s: np.ndarray,
    depth_frames: Iterable[tuple[np.ndarray, np.ndarray]],
    progress: Callable[[int], None] | None,
) -> None:
    (root / layout.DEPTH_DIR).mkdir()
    meta_dict = metadata.model_dump(mode="json")
    if meta_dict.get("contact") is None:  # optional section: absent, so older readers still read
        meta_dict.pop("contact", None)
    (root / layout.METADATA_FILE).write_text(
        yaml.safe_dump(meta_dict, sort_keys=False, default_flow_style=None), encoding="utf-8"
    )
    _write_csv(
        root / layout.IMU_FILE,
        layout.IMU_COLUMNS,
        np.column_stack([imu.timestamp_s, imu.accel_mps2, imu.gyro_radps, imu.quat_wxyz]),
        fmt="%.9g",
    )
    _write_csv(
        root / layout.JOINTS_FILE,
        layout.JOINT_COLUMNS,
        np.column_stack(
            [joints.timestamp_s, joints.thigh_pitch_rad, joints.knee_rad, joints.ankle_rad]
        ),
        fmt="%.9g",
    )
    ts = np.asarray(frame_timestamps_s, dtype=float)
    n = ts.shape[0]
    _write_csv(
        root / layout.DEPTH_TIMESTAMPS_FILE,
        layout.DEPTH_TIMESTAMP_COLUMNS,
        np.column_stack([np.arange(n), ts]),
        fmt="%.9g",
    )
    cam = metadata.camera
    shape = (n, cam.height_px, cam.width_px)
    depth_mm = np.lib.format.open_memmap(root / layout.DEPTH_MM_FILE, "w+", np.uint16, shape)
    conf = np.lib.format.open_memmap(root / layout.CONFIDENCE_FILE, "w+", np.uint8, shape)
    count = 0
    max_units = np.iinfo(np.uint16).max
    for i, (depth_m, confidence) in enumerate(depth_frames):
        if i >= n:
            raise RecordingError(root / layout.DEPTH_MM_FILE, f"more frames than timestamps ({n})")
        d = np.asarray(depth_m, dtype=np.float32)
        if d.shape != shape[1:]:
            raise RecordingError(root / layout.DEPTH_MM_FILE, f"frame {i} has shape {d.shape}")
        units = np.where(np.isfinite(d) & (d > 0), np.rint(d / cam.depth_unit_m), 0)
        depth_mm[i] = np.clip(units, 0, max_units).astype(np.uint16)
        conf[i] = np.where(depth_mm[i] > 0, np.asarray(confidence, dtype=np.uint8), 0)
        count = i + 1
        if count % RELEASE_EVERY_FRAMES == 0:  # written pages to disk and out of our memory
            for arr in (depth_mm, conf):
                arr.flush()
                release_pages(arr)
        if progress is not None:
            progress(count)
    if count != n:
        raise RecordingError(root / layout.DEPTH_MM_FILE, f"got {count} frames for {n} timestamps")
    depth_mm.flush()
    conf.flush()
    del depth_mm, conf
    if groundtruth is not None:
        _write_groundtruth(root, groundtruth)


def _write_groundtruth(root: Path, gt: GroundTruth) -> None:
    (root / layout.GT_DIR).mkdir()
    for body, traj in gt.trajectories.items():
        (root / layout.gt_trajectory_file(body)).write_text(format_tum(traj), encoding="utf-8")
    if gt.imu_state is not None:
        s = gt.imu_state
        _write_csv(
            root / layout.GT_IMU_STATE_FILE,
            layout.GT_IMU_STATE_COLUMNS,
            np.column_stack(
                [
                    s.timestamp_s,
                    s.position_m,
                    s.velocity_mps,
                    s.quat_wxyz,
                    s.accel_bias_mps2,
                    s.gyro_bias_radps,
                ]
            ),
            fmt="%.9g",
        )
    if gt.frame_edge_visible is not None:
        vis = np.asarray(gt.frame_edge_visible)
        ts = np.loadtxt(root / layout.DEPTH_TIMESTAMPS_FILE, delimiter=",", skiprows=1, ndmin=2)
        if vis.shape[0] != ts.shape[0]:
            raise RecordingError(
                root / layout.GT_FRAMES_FILE,
                f"{vis.shape[0]} visibility flags for {ts.shape[0]} frames",
            )
        _write_csv(
            root / layout.GT_FRAMES_FILE,
            layout.GT_FRAME_COLUMNS,
            np.column_stack([ts[:, 0], ts[:, 1], vis]),
            fmt="%.9g",
        )
