"""Read and validate a recording folder (format version 1).

Opening a recording validates every small stream completely (metadata, IMU, joints, depth
timestamps, ground truth) and the depth arrays' headers; depth frames themselves are memory
mapped and converted one at a time, so a long trial never has to fit in memory. Every problem
raises :class:`vio_graph.errors.RecordingError` naming the file and, where there is one, the field.
Loading is safe: YAML through the safe loader only (``yaml.safe_load`` semantics, libyaml's
``CSafeLoader`` when available), ``numpy.load(allow_pickle=False)``, fixed file names that must
resolve inside the recording folder; ``metadata.yaml`` cannot name files (unknown keys are
refused). No other exception type escapes :meth:`Recording.open`: the fuzz tests
(tests/test_fuzz_recording.py) check that on thousands of mutated recordings.
"""

from __future__ import annotations

import math
import mmap
import operator
import os
import tokenize
import warnings
import weakref
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
    ContactTable,
    GroundTruth,
    ImuStateTable,
    ImuTable,
    JointTable,
)
from vio_graph.recording.tum import read_tum
from vio_graph.types import DepthFrame

GRAVITY_MPS2 = 9.81
RATE_TOLERANCE = 0.2  # relative difference allowed between declared and measured rates
DURATION_TOLERANCE = 0.2  # relative difference allowed between duration_s and a stream's span
RELEASE_EVERY_FRAMES = 256  # frames read between hand-backs of the depth maps' pages
START_TOLERANCE_S = 0.5  # plus DURATION_TOLERANCE * duration_s: allowed offset of stream starts
_YAML_LOADER = getattr(yaml, "CSafeLoader", yaml.SafeLoader)  # safe either way; C is 7x faster


class Recording:
    """A validated recording. Use :meth:`open`."""

    def __init__(self, root: Path) -> None:
        self.root = Path(root)
        self._frames_read = 0

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

    @cached_property
    def _root_resolved(self) -> Path:
        try:
            return self.root.resolve(strict=True)
        except (OSError, RuntimeError) as exc:
            raise RecordingError(self.root, f"cannot be opened ({_describe(exc)})") from None

    def _file(self, rel: str, required: bool = True) -> Path | None:
        p = self.root / rel
        try:
            if p.is_symlink() or p.exists():
                resolved = p.resolve(strict=True)
                if not resolved.is_relative_to(self._root_resolved):
                    raise RecordingError(p, "points outside the recording folder")
                if not p.is_file():
                    raise RecordingError(p, "is not a regular file")
                return p
        except (OSError, RuntimeError) as exc:  # dangling link, symlink loop, permissions
            raise RecordingError(p, f"cannot be opened ({_describe(exc)})") from None
        if required:
            raise RecordingError(p, "required file is missing")
        return None

    def _validate(self) -> None:
        _ = self.metadata
        _ = self.imu
        _ = self.joints
        _ = self.contact
        _ = self.frame_timestamps_s
        self._check_depth_arrays()
        _ = self.groundtruth
        self._check_time_spans()

    def _check_time_spans(self) -> None:
        """Every stream covers the declared ``duration_s`` (a truncated stream, or a stream on
        another clock or in other time units, is refused)."""
        duration = self.metadata.duration_s
        streams = [
            (layout.IMU_FILE, self.imu.timestamp_s),
            (layout.JOINTS_FILE, self.joints.timestamp_s),
            (layout.DEPTH_TIMESTAMPS_FILE, self.frame_timestamps_s),
        ]
        if self.contact is not None:
            streams.append((layout.CONTACT_FILE, self.contact.timestamp_s))
        if self.groundtruth is not None:
            streams += [
                (layout.gt_trajectory_file(b), t.timestamp_s)
                for b, t in self.groundtruth.trajectories.items()
            ]
        t0_imu = self.imu.timestamp_s[0]
        slack = DURATION_TOLERANCE * duration
        for rel, t in streams:
            span = float(t[-1] - t[0])
            period = _median(np.diff(t))
            if abs(span - duration) > slack + 2 * period:
                raise RecordingError(
                    self.root / rel,
                    f"covers {span:.3g} s but metadata.yaml "
                    f"declares duration_s {duration:g} s (truncated file or "
                    "wrong time unit?)",
                    field="timestamp_s",
                )
            if abs(float(t[0] - t0_imu)) > slack + START_TOLERANCE_S:
                raise RecordingError(
                    self.root / rel,
                    f"starts at {t[0]:.6g} s, {t[0] - t0_imu:.3g}"
                    f" s away from imu.csv (streams on different clocks?)",
                    field="timestamp_s",
                )

    # ------------------------------------------------------------------ metadata
    @cached_property
    def metadata(self) -> RecordingMetadata:
        path = self._file(layout.METADATA_FILE)
        try:
            raw = yaml.load(path.read_bytes().decode("utf-8"), Loader=_YAML_LOADER)  # noqa: S506
        except (yaml.YAMLError, UnicodeDecodeError, RecursionError) as exc:
            raise RecordingError(path, f"not valid YAML ({exc.__class__.__name__})") from None
        except OSError as exc:
            raise RecordingError(path, f"cannot be read ({_describe(exc)})") from None
        if not isinstance(raw, dict):
            raise RecordingError(path, "top level must be a mapping")
        bad = _yaml_tree_problem(raw)
        if bad is not None:
            raise RecordingError(path, bad[1], field=_printable(bad[0])[:80])
        try:
            with np.errstate(all="ignore"):  # huge numbers overflow in the transform checks
                return RecordingMetadata.model_validate(raw)
        except ValidationError as exc:
            err = exc.errors()[0]
            field = _printable(".".join(str(x) for x in err["loc"]))[:80]
            more = f" (and {len(exc.errors()) - 1} more problems)" if len(exc.errors()) > 1 else ""
            msg = " ".join(str(err["msg"]).split())  # one line
            raise RecordingError(path, msg + more, field=field or None) from None

    # ------------------------------------------------------------------ CSV streams
    def _read_csv(self, rel: str, columns: tuple[str, ...], required: bool = True):
        """(rows, columns) float array of a CSV stream; the ``timestamp_s`` column must
        increase strictly."""
        path = self._file(rel, required)
        if path is None:
            return None
        try:
            text = path.read_bytes().decode("utf-8-sig")  # tolerate a spreadsheet's BOM
        except UnicodeDecodeError:
            raise RecordingError(path, "not a UTF-8 text file") from None
        except OSError as exc:
            raise RecordingError(path, f"cannot be read ({_describe(exc)})") from None
        if "\0" in text:
            raise RecordingError(path, "contains NUL bytes (binary data or a corrupt file)")
        lines = text.splitlines()
        header = lines[0].strip() if lines else ""
        found = tuple(h.strip() for h in header.split(","))
        if found != columns:
            missing = [c for c in columns if c not in found]
            problem = f"missing columns {missing}" if missing else f"unexpected header {found}"
            raise RecordingError(path, problem + f"; expected {','.join(columns)}", field="header")
        try:
            with warnings.catch_warnings():
                warnings.simplefilter("ignore")  # "input contained no data": reported below
                data = np.loadtxt(lines[1:], delimiter=",", ndmin=2, dtype=float, comments=None)
        except ValueError as exc:
            raise RecordingError(path, f"malformed row ({_describe(exc)})") from None
        if data.size == 0:
            raise RecordingError(path, "no data rows")
        if data.shape[1] != len(columns):
            raise RecordingError(path, f"rows have {data.shape[1]} values, expected {len(columns)}")
        bad = ~np.isfinite(data)
        if bad.any():
            row, col = np.argwhere(bad)[0]
            raise RecordingError(path, f"NaN or inf in row {row + 2}", field=columns[col])
        _check_timestamps(path, data[:, columns.index("timestamp_s")])
        return data

    @cached_property
    def imu(self) -> ImuTable:
        path = self.root / layout.IMU_FILE
        d = self._read_csv(layout.IMU_FILE, layout.IMU_COLUMNS)
        imu = ImuTable(d[:, 0], d[:, 1:4], d[:, 4:7], d[:, 7:11])
        meta = self.metadata.imu
        _check_rate(path, imu.timestamp_s, meta.rate_hz, "imu.rate_hz")
        _check_unit_quaternions(path, imu.quat_wxyz)
        with np.errstate(over="ignore"):
            acc_norm = _median(np.linalg.norm(imu.accel_mps2, axis=1))
        # units check only (g or mg instead of m/s^2): a fast gait puts the shank median
        # near 2 g (cadence 1.5x in the simulator), so the upper bound is 3 g
        if not 0.5 * GRAVITY_MPS2 < acc_norm < 3.0 * GRAVITY_MPS2:
            hint = " (looks like g units, expected m/s^2)" if 0.5 < acc_norm < 2.0 else ""
            raise RecordingError(
                path,
                f"median accelerometer norm {acc_norm:.3g} is not near gravity{hint}",
                field="acc_*_mps2",
            )
        if np.max(np.abs(imu.accel_mps2)) > 1.01 * meta.accel_range_mps2:
            raise RecordingError(
                path, "accelerometer beyond the declared range", field="acc_*_mps2"
            )
        if np.max(np.abs(imu.gyro_radps)) > 1.01 * meta.gyro_range_radps:
            raise RecordingError(
                path,
                "gyroscope beyond the declared range (degrees instead of radians?)",
                field="gyr_*_radps",
            )
        return imu

    @cached_property
    def joints(self) -> JointTable:
        path = self.root / layout.JOINTS_FILE
        d = self._read_csv(layout.JOINTS_FILE, layout.JOINT_COLUMNS)
        _check_rate(path, d[:, 0], self.metadata.joint_rate_hz, "joint_rate_hz")
        if np.max(np.abs(d[:, 1:])) > np.pi:
            col = layout.JOINT_COLUMNS[1 + int(np.argmax(np.max(np.abs(d[:, 1:]), axis=0)))]
            raise RecordingError(
                path, "joint angle beyond +-pi rad (degrees instead of radians?)", field=col
            )
        return JointTable(d[:, 0], d[:, 1], d[:, 2], d[:, 3])

    @cached_property
    def contact(self) -> ContactTable | None:
        """The optional foot-contact channel; None without ``contact.csv``."""
        path = self.root / layout.CONTACT_FILE
        d = self._read_csv(layout.CONTACT_FILE, layout.CONTACT_COLUMNS, required=False)
        model = self.metadata.contact
        if d is None:
            if model is not None:
                raise RecordingError(
                    path, "metadata.yaml declares a contact channel but the file is missing"
                )
            return None
        if model is None:
            raise RecordingError(
                path,
                "contact.csv is present but metadata.yaml has no "
                "'contact' section (kind, threshold_n)",
                field="contact",
            )
        if model.kind == "switch" and not np.all(np.isin(d[:, 1], (0.0, 1.0))):
            raise RecordingError(path, "a switch channel must hold 0 or 1", field="force_n")
        return ContactTable(d[:, 0], d[:, 1], d[:, 1] >= model.threshold_n)

    @cached_property
    def frame_timestamps_s(self) -> np.ndarray:
        path = self.root / layout.DEPTH_TIMESTAMPS_FILE
        d = self._read_csv(layout.DEPTH_TIMESTAMPS_FILE, layout.DEPTH_TIMESTAMP_COLUMNS)
        if not np.array_equal(d[:, 0], np.arange(d.shape[0])):
            raise RecordingError(path, "frame column must count 0, 1, 2, ...", field="frame")
        if d.shape[0] == 0:
            raise RecordingError(path, "recording has no depth frames")
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
            raise RecordingError(
                self.root / layout.DEPTH_MM_FILE,
                f"required file is missing (or {layout.DEPTH_M_FILE})",
            )
        path, dtype, scale = (mm, np.uint16, cam.depth_unit_m) if mm else (m, np.float32, 1.0)
        depth = _load_npy(path)
        conf_path = self._file(layout.CONFIDENCE_FILE)
        if conf_path is None:  # pragma: no cover - _file raises for required files
            raise RecordingError(self.root / layout.CONFIDENCE_FILE, "required file is missing")
        conf = _load_npy(conf_path)
        n = self.frame_timestamps_s.shape[0]
        for p, arr, dt in ((path, depth, dtype), (conf_path, conf, np.uint8)):
            if arr.dtype != dt:
                raise RecordingError(p, f"dtype {arr.dtype}, expected {np.dtype(dt)}")
            if arr.shape != (n, cam.height_px, cam.width_px):
                raise RecordingError(
                    p,
                    f"shape {arr.shape}, expected (frames={n}, "
                    f"height={cam.height_px}, width={cam.width_px})",
                )
        return depth, scale, conf

    @cached_property
    def _row_readers(self) -> tuple[_RowReader, _RowReader] | None:
        """Readers of one frame of the depth and confidence files (:class:`_RowReader`),
        opened once, or None where the frames are read through the memory maps (no
        ``os.preadv``, or a map whose frames are not contiguous in the file)."""
        depth, _, conf = self._depth
        if not _RowReader.can_read(depth) or not _RowReader.can_read(conf):
            return None
        conf_path = self.root / layout.CONFIDENCE_FILE
        return _RowReader(depth, self._depth_path(depth)), _RowReader(conf, conf_path)

    def _check_depth_arrays(self) -> None:
        """Convert the first, middle and last frames (catches unit mistakes and corrupt data
        without reading the whole array) and refuse a recording whose sampled frames are all
        empty (no valid pixel)."""
        depth, scale, _ = self._depth
        n = depth.shape[0]
        if n == 0:
            raise RecordingError(self._depth_path(depth), "recording has no depth frames")
        sampled = sorted({0, n // 2, n - 1})
        if not any(self._convert(i, depth, scale)[2] for i in sampled):
            raise RecordingError(
                self._depth_path(depth),
                f"frames {sampled} have no valid depth pixel (empty frames)",
            )

    def _depth_path(self, depth: np.ndarray) -> Path:
        return self.root / (
            layout.DEPTH_MM_FILE if depth.dtype == np.uint16 else layout.DEPTH_M_FILE
        )

    def _convert(
        self, i: int, depth: np.ndarray, scale: float, row: np.ndarray | None = None
    ) -> tuple[np.ndarray, np.ndarray, int]:
        """Frame ``i``'s depth in metres (float32, 0 = invalid, never NaN: the file holds
        uint16 or float32, checked on opening, and NaN becomes 0), its valid mask (d > 0) and
        their count, after the unit checks. ``row``: the stored frame ``depth[i]`` already
        read into a new array (:class:`_RowReader`), else it is read from ``depth``."""
        cam = self.metadata.camera
        kernels = _compiled_kernels() if depth.dtype == np.uint16 else None
        counts = None
        try:
            if depth.dtype == np.float32:
                raw = np.array(depth[i]) if row is None else row
            elif kernels is not None:  # the numpy lines below in one compiled pass
                src = np.asarray(depth[i] if row is None else row)
                d = np.empty(src.shape, np.float32)
                valid = np.empty(src.shape, np.bool_)
                counts = kernels.depth_from_units(
                    src,
                    np.float32(scale),
                    np.float32(1.5 * cam.max_range_m),  # float32, as numpy compares d with it
                    np.float32(0.5 * cam.min_range_m),
                    d,
                    valid,
                )
            else:  # the integer unit scaled in float32, in one pass (= astype, then multiply)
                src = depth[i] if row is None else row
                d = np.multiply(src, np.float32(scale), dtype=np.float32, casting="unsafe")
        except (OSError, ValueError) as exc:  # the file changed or shrank after opening
            raise RecordingError(
                self._depth_path(depth), f"frame {i} cannot be read ({_describe(exc)})"
            ) from None
        if depth.dtype == np.float32:
            if np.isinf(raw).any() or (raw < 0).any():
                raise RecordingError(
                    self._depth_path(depth), f"frame {i} has inf or negative depth"
                )
            d = np.nan_to_num(raw, nan=0.0)
        # shares of the valid pixels (d > 0) beyond the range checks, counted without copying
        # the valid pixels out (copying them out was most of the cost of reading a frame)
        if counts is None:
            valid = d > 0
            n_valid = int(np.count_nonzero(valid))
        else:
            n_valid = counts[0]
        if n_valid:
            n_far = np.count_nonzero(d > 1.5 * cam.max_range_m) if counts is None else counts[1]
            too_far = n_far / n_valid
            if too_far > 0.5:
                raise RecordingError(
                    self._depth_path(depth),
                    f"frame {i}: most depths exceed 1.5x the camera's max "
                    f"range {cam.max_range_m} m (wrong depth unit?)",
                    field="camera.depth_unit_m",
                )
            near_m = 0.5 * cam.min_range_m
            # valid & (d < near_m), counted as all d < near_m less the invalid pixels (d <= 0,
            # no NaN), which are all nearer than a positive near_m
            if near_m <= 0:
                n_near = 0
            else:
                n_below = int(np.count_nonzero(d < near_m)) if counts is None else counts[2]
                n_near = n_below - (d.size - n_valid)
            too_near = n_near / n_valid
            if too_near > 0.5:
                raise RecordingError(
                    self._depth_path(depth),
                    f"frame {i}: most depths are below half the camera's "
                    f"min range {cam.min_range_m} m (wrong depth unit?)",
                    field="camera.depth_unit_m",
                )
        return d, valid, n_valid

    @property
    def num_frames(self) -> int:
        return int(self.frame_timestamps_s.shape[0])

    def frame(self, i: int) -> DepthFrame:
        """Depth frame ``i`` (float32 metres, 0 = invalid), read lazily from disk.

        Where the system has ``os.preadv`` (Linux, the BSDs, macOS) the frame's bytes are
        read from the files into new arrays (:class:`_RowReader`), the same bytes as the
        memory maps hold, without touching the maps: the process's resident memory stays
        flat over a long trial (a 10-minute recording maps ~2 GB) and a frame costs no page
        faults (~0.02 ms less a frame). Elsewhere the frame is read through the maps, whose
        pages are handed back every ``RELEASE_EVERY_FRAMES`` frames
        (``madvise(MADV_DONTNEED)``): they stay in the page cache, but no longer count in the
        process's resident memory."""
        depth, scale, conf = self._depth
        rows = self._row_readers
        if rows is None:
            d, valid, n_valid = self._convert(i, depth, scale)
            c = np.array(conf[i])
            self._frames_read += 1
            if self._frames_read % RELEASE_EVERY_FRAMES == 0:
                release_pages(depth)
                release_pages(conf)
        else:
            k = operator.index(i)  # numpy's row indexing: from the end if negative
            n = depth.shape[0]
            if not -n <= k < n:
                raise IndexError(f"index {k} is out of bounds for axis 0 with size {n}")
            k %= n
            d, valid, n_valid = self._convert(k, depth, scale, rows[0].read(k))
            c = rows[1].read(k)
        if n_valid < d.size:  # c[~valid] = 0 (d <= 0; d holds no NaN), as one product:
            np.multiply(c, valid, out=c)  # c * 1 = c, c * 0 = 0 (no mask array built)
        return DepthFrame(
            index=i, timestamp_s=float(self.frame_timestamps_s[i]), depth_m=d, confidence=c
        )

    def release_frame_pages(self) -> None:
        """Hand back the resident pages of the depth and confidence maps now (as
        :meth:`frame` does every ``RELEASE_EVERY_FRAMES`` frames); a replay calls it once it
        has read its last frame, so that the up to ``RELEASE_EVERY_FRAMES`` frames read since
        the last hand-back do not stay resident through the rest of the run. A no-op if no
        frame was read."""
        if "_depth" not in self.__dict__:  # (the cached maps were never opened)
            return
        depth, _, conf = self._depth
        release_pages(depth)
        release_pages(conf)

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
            try:
                with warnings.catch_warnings():
                    warnings.simplefilter("ignore")  # numpy's "no data": read_tum reports it
                    trajs[body] = read_tum(path)
            except OSError as exc:
                raise RecordingError(path, f"cannot be read ({_describe(exc)})") from None
            if self.metadata.groundtruth_rate_hz:
                _check_rate(
                    path,
                    trajs[body].timestamp_s,
                    self.metadata.groundtruth_rate_hz,
                    "groundtruth_rate_hz",
                )
            elif len(trajs[body]) < 2:
                raise RecordingError(path, f"only {len(trajs[body])} poses", field="timestamp")
        state = None
        d = self._read_csv(layout.GT_IMU_STATE_FILE, layout.GT_IMU_STATE_COLUMNS, required=False)
        if d is not None:
            _check_unit_quaternions(self.root / layout.GT_IMU_STATE_FILE, d[:, 7:11])
            state = ImuStateTable(
                d[:, 0], d[:, 1:4], d[:, 4:7], d[:, 7:11], d[:, 11:14], d[:, 14:17]
            )
        vis = None
        f = self._read_csv(layout.GT_FRAMES_FILE, layout.GT_FRAME_COLUMNS, required=False)
        if f is not None:
            path = self.root / layout.GT_FRAMES_FILE
            if f.shape[0] != self.num_frames:
                raise RecordingError(path, f"{f.shape[0]} rows for {self.num_frames} depth frames")
            if not np.array_equal(f[:, 0], np.arange(f.shape[0])):
                raise RecordingError(path, "frame column must count 0, 1, 2, ...", field="frame")
            if not np.allclose(f[:, 1], self.frame_timestamps_s, rtol=0.0, atol=1e-6):
                raise RecordingError(
                    path, "timestamps differ from depth/timestamps.csv", field="timestamp_s"
                )
            if not np.all((f[:, 2] == 0) | (f[:, 2] == 1)):
                raise RecordingError(path, "values must be 0 or 1", field="edge_visible")
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
            "provenance": {
                "source": meta.provenance.source,
                "scenario": meta.provenance.scenario,
                "seed": meta.provenance.seed,
                "software": meta.provenance.software,
            },
        }
        if gt is not None and gt.frame_edge_visible is not None:
            out["edge_visible_fraction"] = round(float(np.mean(gt.frame_edge_visible)), 4)
        return out


def _compiled_kernels():
    """vio_graph/recording/compiled.py when the compiled paths are on (numba installed and
    :func:`vio_graph.frontend.icp.compiled_kernels` says so: ``VIO_GRAPH_COMPILED``, or "auto"
    as a replay of a long recording sets it), else None (the numpy path)."""
    from vio_graph.frontend.icp import compiled_kernels

    if compiled_kernels() is None:
        return None
    from vio_graph.recording import compiled

    return compiled


def _rate(t: np.ndarray) -> float:
    return float(1.0 / _median(np.diff(t))) if t.shape[0] > 1 else 0.0


def _median(values: np.ndarray) -> float:
    """``np.median`` of a 1-D array, the same value, without ``np.median``'s import of
    ``numpy.ma`` (~50 ms of ``vio-graph info``); NaN if any value is NaN, as there."""
    v = np.asarray(values, dtype=float).reshape(-1)
    n = v.shape[0]
    if n == 0 or np.isnan(v).any():
        return float("nan")
    half = n // 2
    if n % 2:
        return float(np.partition(v, half)[half])
    part = np.partition(v, (half - 1, half))
    return float((part[half - 1] + part[half]) / 2.0)


def _check_timestamps(path: Path, t: np.ndarray) -> None:
    dt = np.diff(t)
    if np.any(dt == 0):
        raise RecordingError(
            path, f"duplicated timestamp at row {int(np.argmax(dt == 0)) + 3}", field="timestamp_s"
        )
    if np.any(dt < 0):
        raise RecordingError(
            path,
            f"timestamps go backwards at row {int(np.argmax(dt < 0)) + 3}",
            field="timestamp_s",
        )


def _check_rate(path: Path, t: np.ndarray, declared_hz: float, field: str) -> None:
    if t.shape[0] < 3:
        raise RecordingError(path, f"only {t.shape[0]} samples", field="timestamp_s")
    measured = _rate(t)
    if abs(measured - declared_hz) > RATE_TOLERANCE * declared_hz:
        raise RecordingError(
            path,
            f"measured rate {measured:.2f} Hz does not match the declared "
            f"{declared_hz:g} Hz in metadata.yaml",
            field=field,
        )


def _check_unit_quaternions(path: Path, quat_wxyz: np.ndarray) -> None:
    err = np.abs(np.linalg.norm(quat_wxyz, axis=1) - 1.0)
    if np.any(err > 1e-3):
        raise RecordingError(
            path, f"quaternion not unit length (row {int(np.argmax(err)) + 2})", field="q_w..q_z"
        )


# What numpy raises on a corrupt .npy: bad magic/version/header values (ValueError), short
# files (EOFError, OSError from mmap), and header text its tokenizer cannot parse.
_NPY_ERRORS = (
    ValueError,
    OSError,
    EOFError,
    SyntaxError,
    TypeError,
    KeyError,
    OverflowError,
    MemoryError,
    tokenize.TokenError,
)


class _RowReader:
    """Reads row ``i`` (one frame) of a C-ordered ``.npy`` memory map from its file into a
    new array with one ``os.preadv``: the same bytes as ``np.array(memmap[i])``, without
    faulting the map's pages in (so nothing to hand back) and with a fresh, writable array.
    The file is opened once, when the reader is made (right after the map, so the same
    file), and closed when the reader is collected."""

    def __init__(self, mm: np.memmap, path: Path) -> None:
        self._open(Path(str(mm.filename)), path, mm.dtype, mm.shape[1:], int(mm.offset))

    def _open(
        self, file: Path, path: Path, dtype: np.dtype, shape: tuple[int, ...], offset: int
    ) -> None:
        # file: the mapped file's absolute name; path: its name in the recording (errors)
        self.file, self.path, self.dtype, self.shape, self.offset = file, path, dtype, shape, offset
        self.row_bytes = int(dtype.itemsize * math.prod(shape))
        self.fd = os.open(file, os.O_RDONLY | getattr(os, "O_CLOEXEC", 0))
        weakref.finalize(self, os.close, self.fd)

    def __reduce__(self):  # a copy in another process opens the file again
        args = (self.file, self.path, self.dtype, self.shape, self.offset)
        return (_RowReader._reopened, args)

    @staticmethod
    def _reopened(
        file: Path, path: Path, dtype: np.dtype, shape: tuple[int, ...], offset: int
    ) -> _RowReader:
        reader = _RowReader.__new__(_RowReader)
        reader._open(file, path, dtype, shape, offset)
        return reader

    @staticmethod
    def can_read(arr: np.ndarray) -> bool:
        return (
            hasattr(os, "preadv")
            and isinstance(arr, np.memmap)
            and arr.filename is not None
            and arr.ndim >= 2
            and arr.flags.c_contiguous
        )

    def read(self, i: int) -> np.ndarray:
        """Row ``i`` as a new array; a RecordingError naming the file if it cannot be read
        whole (changed or shrunk since opening)."""
        out = np.empty(self.shape, self.dtype)
        try:
            n = os.preadv(self.fd, [out], self.offset + i * self.row_bytes)
        except OSError as exc:
            raise RecordingError(
                self.path, f"frame {i} cannot be read ({_describe(exc)})"
            ) from None
        if n != self.row_bytes:
            raise RecordingError(
                self.path, f"frame {i} cannot be read (file shorter than when opened)"
            )
        return out


def release_pages(arr: np.ndarray) -> None:
    """Drop the resident pages of a read-only memory map (re-read from the page cache on the
    next access); a no-op for arrays that are not memory maps or platforms without madvise."""
    mm = getattr(arr, "_mmap", None)
    advice = getattr(mmap, "MADV_DONTNEED", None)
    if mm is None or advice is None or not hasattr(mm, "madvise"):
        return
    try:
        mm.madvise(advice)
    except (OSError, ValueError):  # closed map or refused advice: memory is then not flat
        pass


def _load_npy(path: Path) -> np.ndarray:
    try:
        arr = np.load(path, mmap_mode="r", allow_pickle=False)
    except _NPY_ERRORS as exc:
        raise RecordingError(
            path, f"not a readable .npy array (truncated or corrupt: {_describe(exc)})"
        ) from None
    if not isinstance(arr, np.ndarray):  # np.load opens a zip (.npz) whatever the name
        if hasattr(arr, "close"):
            arr.close()
        raise RecordingError(path, f"not a .npy array (found {type(arr).__name__})")
    return arr


def _printable(text: str) -> str:
    """``text`` with control characters escaped (YAML keys can hold newlines)."""
    return "".join(c if c.isprintable() else repr(c)[1:-1] for c in text)


def _describe(exc: BaseException) -> str:
    """An exception as one short line (messages from numpy or the OS can span lines)."""
    text = " ".join(str(exc).split()) or exc.__class__.__name__
    return text if len(text) <= 200 else text[:197] + "..."


_MAX_YAML_DEPTH = 32  # metadata.yaml nests 4 levels; deeper is garbage or an alias cycle


def _yaml_tree_problem(node: object, where: str = "", depth: int = 0) -> tuple[str, str] | None:
    """(field, problem) for the first NaN/inf number, or for nesting deeper than any metadata
    (which includes self-referencing YAML aliases, ``a: &x [*x]``), else None."""
    if isinstance(node, float) and not math.isfinite(node):
        return where or "(top level)", "NaN or inf is not allowed"
    if isinstance(node, dict):
        items = list(node.items())
    elif isinstance(node, list):
        items = list(enumerate(node))
    else:
        return None
    if depth >= _MAX_YAML_DEPTH:
        return where or "(top level)", "nested too deeply (recursive alias?)"
    for k, v in items:
        found = _yaml_tree_problem(v, f"{where}.{k}" if where else str(k), depth + 1)
        if found is not None:
            return found
    return None
