"""Read and validate a recording folder (format version 1).

Opening a recording validates every small stream completely (metadata, IMU, joints, depth
timestamps, ground truth) and the depth arrays' headers; depth frames themselves are memory
mapped and converted one at a time, so a long trial never has to fit in memory. Every problem
raises :class:`vio_graph.errors.RecordingError` naming the file and, where there is one, the field.
Loading is safe: ``yaml.safe_load``, ``numpy.load(allow_pickle=False)``, fixed file names that
must resolve inside the recording folder.
"""

from __future__ import annotations

import os
from collections.abc import Iterator
from functools import cached_property
from pathlib import Path

import numpy as np
import yaml
from pydantic import ValidationError

from vio_graph.errors import RecordingError
from vio_graph.recording import layout
from vio_graph.recording.metadata import RecordingMetadata
from vio_graph.recording.streams import (
    GROUNDTRUTH_BODIES,
    GroundTruth,
    ImuStateTable,
    ImuTable,
    JointTable,
)
from vio_graph.recording.tum import read_tum
from vio_graph.types import DepthFrame

GRAVITY_MPS2 = 9.81
RATE_TOLERANCE = 0.2  # relative difference allowed between declared and measured rates


class Recording:
    """A validated recording. Use :meth:`open`."""

    def __init__(self, root: Path) -> None:
        self.root = Path(root)

    # ------------------------------------------------------------------ opening
    @classmethod
    def open(cls, path: str | os.PathLike[str]) -> Recording:
        root = Path(path)
        if not root.exists():
            raise RecordingError(root, "recording folder not found")
        if not root.is_dir():
            raise RecordingError(root, "not a folder (a recording is a folder)")
        rec = cls(root)
        rec._validate()
        return rec

    def _file(self, rel: str, required: bool = True) -> Path | None:
        p = self.root / rel
        if p.is_symlink() or p.exists():
            resolved = p.resolve()
            if not resolved.is_relative_to(self.root.resolve()):
                raise RecordingError(p, "points outside the recording folder")
            if not p.is_file():
                raise RecordingError(p, "is not a regular file")
            return p
        if required:
            raise RecordingError(p, "required file is missing")
        return None

    def _validate(self) -> None:
        _ = self.metadata
        _ = self.imu
        _ = self.joints
        _ = self.frame_timestamps_s
        self._check_depth_arrays()
        _ = self.groundtruth

    # ------------------------------------------------------------------ metadata
    @cached_property
    def metadata(self) -> RecordingMetadata:
        path = self._file(layout.METADATA_FILE)
        try:
            raw = yaml.safe_load(path.read_text(encoding="utf-8"))
        except (yaml.YAMLError, UnicodeDecodeError) as exc:
            raise RecordingError(path, f"not valid YAML ({exc.__class__.__name__})") from None
        if not isinstance(raw, dict):
            raise RecordingError(path, "top level must be a mapping")
        try:
            return RecordingMetadata.model_validate(raw)
        except ValidationError as exc:
            err = exc.errors()[0]
            field = ".".join(str(x) for x in err["loc"])
            more = f" (and {len(exc.errors()) - 1} more problems)" if len(exc.errors()) > 1 else ""
            raise RecordingError(path, err["msg"] + more, field=field or None) from None

    # ------------------------------------------------------------------ CSV streams
    def _read_csv(self, rel: str, columns: tuple[str, ...], required: bool = True):
        path = self._file(rel, required)
        if path is None:
            return None
        try:
            with path.open(encoding="utf-8") as fh:
                header = fh.readline().strip()
        except UnicodeDecodeError:
            raise RecordingError(path, "not a UTF-8 text file") from None
        found = tuple(h.strip() for h in header.split(","))
        if found != columns:
            missing = [c for c in columns if c not in found]
            problem = f"missing columns {missing}" if missing else f"unexpected header {found}"
            raise RecordingError(path, problem + f"; expected {','.join(columns)}", field="header")
        try:
            data = np.loadtxt(path, delimiter=",", skiprows=1, ndmin=2, dtype=float)
        except ValueError as exc:
            raise RecordingError(path, f"malformed row ({exc})") from None
        if data.size == 0:
            raise RecordingError(path, "no data rows")
        if data.shape[1] != len(columns):
            raise RecordingError(path, f"rows have {data.shape[1]} values, expected {len(columns)}")
        bad = ~np.isfinite(data)
        if bad.any():
            row, col = np.argwhere(bad)[0]
            raise RecordingError(path, f"NaN or inf in row {row + 2}", field=columns[col])
        _check_timestamps(path, data[:, 0])
        return data

    @cached_property
    def imu(self) -> ImuTable:
        path = self.root / layout.IMU_FILE
        d = self._read_csv(layout.IMU_FILE, layout.IMU_COLUMNS)
        imu = ImuTable(d[:, 0], d[:, 1:4], d[:, 4:7], d[:, 7:11])
        meta = self.metadata.imu
        _check_rate(path, imu.timestamp_s, meta.rate_hz, "imu.rate_hz")
        qn = np.linalg.norm(imu.quat_wxyz, axis=1)
        if np.any(np.abs(qn - 1.0) > 1e-3):
            raise RecordingError(path, f"quaternion not unit length (row {np.argmax(np.abs(qn - 1)) + 2})",
                                 field="q_w..q_z")
        acc_norm = np.median(np.linalg.norm(imu.accel_mps2, axis=1))
        if not 0.5 * GRAVITY_MPS2 < acc_norm < 2.0 * GRAVITY_MPS2:
            hint = " (looks like g units, expected m/s^2)" if 0.5 < acc_norm < 2.0 else ""
            raise RecordingError(path, f"median accelerometer norm {acc_norm:.3g} is not near "
                                 f"gravity{hint}", field="acc_*_mps2")
        if np.max(np.abs(imu.accel_mps2)) > 1.01 * meta.accel_range_mps2:
            raise RecordingError(path, "accelerometer beyond the declared range", field="acc_*_mps2")
        if np.max(np.abs(imu.gyro_radps)) > 1.01 * meta.gyro_range_radps:
            raise RecordingError(path, "gyroscope beyond the declared range (degrees instead of "
                                 "radians?)", field="gyr_*_radps")
        return imu

    @cached_property
    def joints(self) -> JointTable:
        path = self.root / layout.JOINTS_FILE
        d = self._read_csv(layout.JOINTS_FILE, layout.JOINT_COLUMNS)
        _check_rate(path, d[:, 0], self.metadata.joint_rate_hz, "joint_rate_hz")
        if np.max(np.abs(d[:, 1:])) > np.pi:
            col = layout.JOINT_COLUMNS[1 + int(np.argmax(np.max(np.abs(d[:, 1:]), axis=0)))]
            raise RecordingError(path, "joint angle beyond +-pi rad (degrees instead of radians?)",
                                 field=col)
        return JointTable(d[:, 0], d[:, 1], d[:, 2], d[:, 3])

    @cached_property
    def frame_timestamps_s(self) -> np.ndarray:
        path = self.root / layout.DEPTH_TIMESTAMPS_FILE
        d = self._read_csv(layout.DEPTH_TIMESTAMPS_FILE, layout.DEPTH_TIMESTAMP_COLUMNS)
        if not np.array_equal(d[:, 0], np.arange(d.shape[0])):
            raise RecordingError(path, "frame column must count 0, 1, 2, ...", field="frame")
        _check_rate(path, d[:, 1], self.metadata.camera.frame_rate_hz, "camera.frame_rate_hz")
        return d[:, 1].copy()

    # ------------------------------------------------------------------ depth
    @cached_property
    def _depth(self) -> tuple[np.ndarray, float, np.ndarray]:
        """(depth array memmap, metres per unit, confidence memmap)."""
        cam = self.metadata.camera
        mm = self._file(layout.DEPTH_MM_FILE, required=False)
        m = self._file(layout.DEPTH_M_FILE, required=False)
        if mm is None and m is None:
            raise RecordingError(self.root / layout.DEPTH_MM_FILE,
                                 f"required file is missing (or {layout.DEPTH_M_FILE})")
        path, dtype, scale = (mm, np.uint16, cam.depth_unit_m) if mm else (m, np.float32, 1.0)
        depth = _load_npy(path)
        conf_path = self._file(layout.CONFIDENCE_FILE)
        conf = _load_npy(conf_path)
        n = self.frame_timestamps_s.shape[0]
        for p, arr, dt in ((path, depth, dtype), (conf_path, conf, np.uint8)):
            if arr.dtype != dt:
                raise RecordingError(p, f"dtype {arr.dtype}, expected {np.dtype(dt)}")
            if arr.shape != (n, cam.height_px, cam.width_px):
                raise RecordingError(p, f"shape {arr.shape}, expected (frames={n}, "
                                     f"height={cam.height_px}, width={cam.width_px})")
        return depth, scale, conf

    def _check_depth_arrays(self) -> None:
        depth, scale, _ = self._depth
        n = depth.shape[0]
        if n == 0:
            raise RecordingError(self.root / layout.DEPTH_MM_FILE, "recording has no depth frames")
        for i in sorted({0, n // 2, n - 1}):
            self._convert(i, depth, scale)

    def _convert(self, i: int, depth: np.ndarray, scale: float) -> np.ndarray:
        path = self.root / (layout.DEPTH_MM_FILE if depth.dtype == np.uint16 else layout.DEPTH_M_FILE)
        raw = np.asarray(depth[i])
        if raw.dtype == np.float32:
            if np.isinf(raw).any() or (raw < 0).any():
                raise RecordingError(path, f"frame {i} has inf or negative depth")
            d = np.nan_to_num(raw, nan=0.0)
        else:
            d = raw.astype(np.float32) * np.float32(scale)
        cam = self.metadata.camera
        valid = d > 0
        if valid.any():
            too_far = np.mean(d[valid] > 1.5 * cam.max_range_m)
            if too_far > 0.5:
                raise RecordingError(path, f"frame {i}: most depths exceed 1.5x the camera's max "
                                     f"range {cam.max_range_m} m (wrong depth unit?)",
                                     field="camera.depth_unit_m")
        return d

    @property
    def num_frames(self) -> int:
        return int(self.frame_timestamps_s.shape[0])

    def frame(self, i: int) -> DepthFrame:
        """Depth frame ``i`` (float32 metres, 0 = invalid), read lazily from disk."""
        depth, scale, conf = self._depth
        d = self._convert(i, depth, scale)
        c = np.array(conf[i])
        c[d <= 0] = 0
        return DepthFrame(index=i, timestamp_s=float(self.frame_timestamps_s[i]), depth_m=d,
                          confidence=c)

    def frames(self, start: int = 0, stop: int | None = None) -> Iterator[DepthFrame]:
        for i in range(start, self.num_frames if stop is None else min(stop, self.num_frames)):
            yield self.frame(i)

    # ------------------------------------------------------------------ ground truth
    @cached_property
    def groundtruth(self) -> GroundTruth | None:
        """Ground truth if the recording has a groundtruth/ folder, else None."""
        if not (self.root / layout.GT_DIR).is_dir():
            return None
        trajs = {}
        for body in GROUNDTRUTH_BODIES:
            path = self._file(layout.gt_trajectory_file(body), required=True)
            trajs[body] = read_tum(path)
            if self.metadata.groundtruth_rate_hz:
                _check_rate(path, trajs[body].timestamp_s, self.metadata.groundtruth_rate_hz,
                            "groundtruth_rate_hz")
        state = None
        d = self._read_csv(layout.GT_IMU_STATE_FILE, layout.GT_IMU_STATE_COLUMNS, required=False)
        if d is not None:
            state = ImuStateTable(d[:, 0], d[:, 1:4], d[:, 4:7], d[:, 7:11], d[:, 11:14],
                                  d[:, 14:17])
        vis = None
        f = self._read_csv(layout.GT_FRAMES_FILE, layout.GT_FRAME_COLUMNS, required=False)
        if f is not None:
            if f.shape[0] != self.num_frames:
                raise RecordingError(self.root / layout.GT_FRAMES_FILE,
                                     f"{f.shape[0]} rows for {self.num_frames} depth frames")
            vis = f[:, 2].astype(np.int8)
        return GroundTruth(trajectories=trajs, imu_state=state, frame_edge_visible=vis)

    # ------------------------------------------------------------------ summary
    def summary(self) -> dict:
        """A JSON-ready summary (what ``vio-graph info --json`` prints)."""
        meta = self.metadata
        ft = self.frame_timestamps_s
        gt = self.groundtruth
        t0 = min(ft[0], self.imu.timestamp_s[0])
        t1 = max(ft[-1], self.imu.timestamp_s[-1])
        out = {
            "path": str(self.root),
            "format_version": meta.format_version,
            "duration_s": round(float(t1 - t0), 4),
            "frames": self.num_frames,
            "frame_rate_hz": round(_rate(ft), 3),
            "imu_samples": len(self.imu),
            "imu_rate_hz": round(_rate(self.imu.timestamp_s), 3),
            "joint_samples": len(self.joints),
            "joint_rate_hz": round(_rate(self.joints.timestamp_s), 3),
            "gt_rate_hz": round(_rate(gt.trajectories["camera"].timestamp_s), 3) if gt else None,
            "gt_bodies": sorted(gt.trajectories) if gt else [],
            "image_size": [meta.camera.width_px, meta.camera.height_px],
            "rig": meta.leg.rig,
            "terrain": {"kind": meta.terrain.kind, **meta.terrain.params},
            "provenance": {"source": meta.provenance.source, "scenario": meta.provenance.scenario,
                           "seed": meta.provenance.seed, "software": meta.provenance.software},
        }
        if gt is not None and gt.frame_edge_visible is not None:
            out["edge_visible_fraction"] = round(float(np.mean(gt.frame_edge_visible)), 4)
        return out


def _rate(t: np.ndarray) -> float:
    return float(1.0 / np.median(np.diff(t))) if t.shape[0] > 1 else 0.0


def _check_timestamps(path: Path, t: np.ndarray) -> None:
    dt = np.diff(t)
    if np.any(dt == 0):
        raise RecordingError(path, f"duplicated timestamp at row {int(np.argmax(dt == 0)) + 3}",
                             field="timestamp_s")
    if np.any(dt < 0):
        raise RecordingError(path, f"timestamps go backwards at row {int(np.argmax(dt < 0)) + 3}",
                             field="timestamp_s")


def _check_rate(path: Path, t: np.ndarray, declared_hz: float, field: str) -> None:
    if t.shape[0] < 3:
        raise RecordingError(path, f"only {t.shape[0]} samples", field="timestamp_s")
    measured = _rate(t)
    if abs(measured - declared_hz) > RATE_TOLERANCE * declared_hz:
        raise RecordingError(path, f"measured rate {measured:.2f} Hz does not match the declared "
                             f"{declared_hz:g} Hz in metadata.yaml", field=field)


def _load_npy(path: Path) -> np.ndarray:
    try:
        return np.load(path, mmap_mode="r", allow_pickle=False)
    except (ValueError, OSError, EOFError) as exc:
        raise RecordingError(path, f"not a readable .npy array (truncated or corrupt: {exc})") from None
