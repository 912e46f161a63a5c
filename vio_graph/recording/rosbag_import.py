"""Import a ROS bag (ROS 1 ``.bag``, ROS 2 ``.db3`` / ``.mcap`` folder or file) as a recording.

Reads with the pure-Python ``rosbags`` package, so no ROS installation is needed:

- depth: ``sensor_msgs/Image`` from the pico flexx driver (``32FC1`` metres, NaN or 0 invalid;
  ``16UC1`` millimetres is accepted too), streamed frame by frame into the writer;
- intrinsics: the first ``sensor_msgs/CameraInfo`` (or the rig file's, which take precedence);
- IMU: ``sensor_msgs/Imu`` (vendor orientation, angular velocity, linear acceleration), raw
  samples, no resampling;
- joints: ``sensor_msgs/JointState``, three named joints mapped by the rig file;
- foot contact (optional, named in the rig file's ``contact`` section): a load-cell force
  (``std_msgs/Float64`` / ``Float32``, or ``geometry_msgs/WrenchStamped`` force.z) or a
  heel / foot switch (``std_msgs/Bool``), written as ``contact.csv``.

Two passes over the bag: the first collects timestamps, the IMU and joint samples (small) and
checks topics, encodings, sizes and rates; the second streams the depth frames through a
generator into :func:`vio_graph.recording.write_recording`, so a bag's frames never all sit in
memory. Depth frames are cropped to the time span all streams share (widened by half a frame
period); IMU and joint samples to that span plus one sample on each side, so every frame time
lies between two samples. Times are put on a clock starting at the earliest kept sample
(``provenance.config.time_origin_ns`` keeps the bag-clock origin, integer ns).
"""

from __future__ import annotations

import datetime as _dt
import logging
from collections.abc import Callable, Iterator, Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any, Literal

import numpy as np
import yaml
from pydantic import BaseModel, ConfigDict, Field, ValidationError, model_validator

import vio_graph
from vio_graph.errors import BagImportError, ConfigError
from vio_graph.recording.metadata import (
    FORMAT_VERSION,
    CameraModel,
    ContactModel,
    Extrinsics,
    ImuModel,
    LegGeometry,
    Provenance,
    RecordingMetadata,
    TerrainInfo,
)
from vio_graph.recording.streams import (
    GROUNDTRUTH_BODIES,
    ContactTable,
    GroundTruth,
    ImuTable,
    JointTable,
)
from vio_graph.recording.tum import read_tum
from vio_graph.recording.writer import write_recording

log = logging.getLogger(__name__)

RATE_TOLERANCE = 0.2  # relative difference allowed between the rig's and the measured rates
QUAT_NORM_TOLERANCE = 1e-3  # as the reader's check
MSGTYPES = {
    "depth": "sensor_msgs/msg/Image",
    "camera_info": "sensor_msgs/msg/CameraInfo",
    "imu": "sensor_msgs/msg/Imu",
    "joints": "sensor_msgs/msg/JointState",
}
# foot-contact message types; the std_msgs ones have no header (timed by receive time)
CONTACT_MSGTYPES = (
    "std_msgs/msg/Float64",
    "std_msgs/msg/Float32",
    "std_msgs/msg/Bool",
    "geometry_msgs/msg/WrenchStamped",
)
SWITCH_THRESHOLD_N = 0.5  # a switch channel holds 0 / 1
# depth encodings: numpy little-endian dtype and metres per stored unit
DEPTH_ENCODINGS = {"32FC1": ("<f4", 1.0), "16UC1": ("<u2", 0.001), "mono16": ("<u2", 0.001)}


# ---------------------------------------------------------------------------- configuration
class _Strict(BaseModel):
    model_config = ConfigDict(extra="forbid", frozen=True)


class BagTopics(_Strict):
    """Topic names; the defaults are those of pico_flexx_driver, xsens_mti_driver and a
    ``joint_state_publisher``-style encoder node."""

    depth: str = Field("/pico_flexx/image_depth", description="sensor_msgs/Image, 32FC1 m")
    camera_info: str = Field("/pico_flexx/camera_info", description="sensor_msgs/CameraInfo")
    imu: str = Field("/imu/data", description="sensor_msgs/Imu")
    joints: str = Field("/joint_states", description="sensor_msgs/JointState")


class RigCamera(_Strict):
    """Depth camera facts a bag does not carry. Intrinsics given here override camera_info."""

    fx_px: float | None = Field(None, gt=0, description="focal length x, px (None: camera_info)")
    fy_px: float | None = Field(None, gt=0, description="focal length y, px (None: camera_info)")
    cx_px: float | None = Field(None, description="principal point x, px (None: camera_info)")
    cy_px: float | None = Field(None, description="principal point y, px (None: camera_info)")
    frame_rate_hz: float = Field(gt=0, description="nominal depth frame rate, Hz (checked)")
    min_range_m: float = Field(ge=0, description="nearest valid depth, m")
    max_range_m: float = Field(gt=0, description="farthest valid depth, m")
    depth_unit_m: float = Field(0.001, gt=0, description="metres per stored uint16 unit")
    model: str = Field("pmd CamBoard pico flexx", description="free text")

    @model_validator(mode="after")
    def _all_or_none(self) -> RigCamera:
        given = [v is not None for v in (self.fx_px, self.fy_px, self.cx_px, self.cy_px)]
        if any(given) and not all(given):
            raise ValueError("give all of fx_px, fy_px, cx_px, cy_px or none (camera_info)")
        return self

    @property
    def has_intrinsics(self) -> bool:
        return self.fx_px is not None


class JointSource(_Strict):
    """One joint of the JointState message: value_rad = sign * position + offset_rad."""

    name: str = Field(min_length=1, description="name in JointState.name")
    sign: Literal[1, -1] = Field(1, description="-1 if the encoder counts the other way")
    offset_rad: float = Field(0.0, description="added after the sign, rad")


class RigJoints(_Strict):
    rate_hz: float = Field(gt=0, description="nominal JointState rate, Hz (checked)")
    thigh_pitch: JointSource = Field(description="hip flexion, + knee ahead of the hip")
    knee: JointSource = Field(description="knee flexion, +")
    ankle: JointSource = Field(description="ankle plantarflexion, +")


def _full_msgtype(name: str) -> str:
    """``std_msgs/Float64`` -> ``std_msgs/msg/Float64`` (rosbags' spelling for ROS 1 and 2)."""
    parts = name.strip("/").split("/")
    return f"{parts[0]}/msg/{parts[1]}" if len(parts) == 2 else "/".join(parts)


class RigContact(_Strict):
    """Optional foot-contact topic: a load cell's force or a heel / foot switch.

    force_n = sign * scale * value + offset_n (value: ``data`` of a Float64 / Float32, the
    ``wrench.force.<wrench_axis>`` of a WrenchStamped); a Bool switch gives 1 (closed) / 0."""

    topic: str = Field(min_length=1, description="topic name in the bag")
    msgtype: str | None = Field(
        None,
        description="std_msgs/Float64, std_msgs/Float32, std_msgs/Bool or "
        "geometry_msgs/WrenchStamped (checked against the bag); None: the bag's type",
    )
    kind: Literal["load_cell", "switch"] = Field(
        description="load_cell: axial force in N; switch: 1 closed, 0 open"
    )
    threshold_n: float | None = Field(
        None,
        gt=0,
        description="load_cell: loaded at or above this force, N (required); switch: 0.5",
    )
    scale: float = Field(1.0, description="newtons per published unit (load_cell)")
    sign: Literal[1, -1] = Field(1, description="-1 if the cell reports compression negative")
    offset_n: float = Field(0.0, description="added after sign and scale, N (tare)")
    wrench_axis: Literal["x", "y", "z"] = Field(
        "z", description="WrenchStamped: the force component along the pylon axis"
    )
    rate_hz: float | None = Field(None, gt=0, description="nominal rate, Hz (checked if given)")

    @model_validator(mode="after")
    def _consistent(self) -> RigContact:
        if self.msgtype is not None and _full_msgtype(self.msgtype) not in CONTACT_MSGTYPES:
            raise ValueError(
                f"msgtype {self.msgtype!r} not supported (one of {', '.join(CONTACT_MSGTYPES)})"
            )
        if self.kind == "load_cell" and self.threshold_n is None:
            raise ValueError(
                "a load_cell needs threshold_n (the force at which the foot counts as loaded, N)"
            )
        if self.kind == "switch" and self.threshold_n not in (None, SWITCH_THRESHOLD_N):
            raise ValueError("a switch channel holds 0 / 1: leave threshold_n out (0.5)")
        if (
            self.kind == "load_cell"
            and self.msgtype is not None
            and _full_msgtype(self.msgtype) == "std_msgs/msg/Bool"
        ):
            raise ValueError("std_msgs/Bool carries a switch: set kind: switch")
        return self

    @property
    def threshold(self) -> float:
        return SWITCH_THRESHOLD_N if self.threshold_n is None else self.threshold_n


class RigConfig(_Strict):
    """The rig file (see configs/rig_example.yaml): what the bag does not say."""

    camera: RigCamera
    imu: ImuModel
    joints: RigJoints
    extrinsics: Extrinsics
    leg: LegGeometry
    terrain: TerrainInfo = TerrainInfo(kind="unknown")
    groundtruth_rate_hz: float | None = Field(None, gt=0, description="mocap rate, Hz")
    contact: RigContact | None = Field(None, description="optional foot-contact topic")
    notes: str = ""


def load_rig(path: str | Path) -> RigConfig:
    """Read and validate a rig YAML file; errors name the file and the field."""
    path = Path(path)
    try:
        raw = yaml.safe_load(path.read_text(encoding="utf-8"))
    except OSError as exc:
        raise ConfigError(f"{path}: cannot be read ({exc.strerror or exc})") from None
    except yaml.YAMLError as exc:
        raise ConfigError(f"{path}: not valid YAML ({exc.__class__.__name__})") from None
    if not isinstance(raw, dict):
        raise ConfigError(f"{path}: top level must be a mapping")
    try:
        return RigConfig.model_validate(raw)
    except ValidationError as exc:
        err = exc.errors()[0]
        field = ".".join(str(x) for x in err["loc"]) or "(top level)"
        more = f" (and {len(exc.errors()) - 1} more problems)" if len(exc.errors()) > 1 else ""
        raise ConfigError(f"{path} [{field}]: {' '.join(str(err['msg']).split())}{more}") from None


# ---------------------------------------------------------------------------- decoding
def stamp_ns(msg: Any) -> int:
    """header.stamp of a message, integer nanoseconds."""
    return int(msg.header.stamp.sec) * 1_000_000_000 + int(msg.header.stamp.nanosec)


def decode_depth_image(msg: Any) -> np.ndarray:
    """float32 (H, W) depth in metres, 0 = invalid, from a sensor_msgs/Image.

    Raises ValueError for an unsupported encoding or a short buffer (the caller names the bag).
    """
    if msg.encoding not in DEPTH_ENCODINGS:
        raise ValueError(
            f"encoding {msg.encoding!r} not supported (expected one of {sorted(DEPTH_ENCODINGS)})"
        )
    dtype_le, scale = DEPTH_ENCODINGS[msg.encoding]
    dtype = np.dtype(dtype_le).newbyteorder(">" if msg.is_bigendian else "<")
    h, w, step = int(msg.height), int(msg.width), int(msg.step)
    row_bytes = w * dtype.itemsize
    data = np.asarray(msg.data, dtype=np.uint8)
    if step < row_bytes or data.size < step * h:
        raise ValueError(
            f"{data.size} bytes with step {step} do not hold a {w}x{h} {msg.encoding} image"
        )
    rows = data[: step * h].reshape(h, step)[:, :row_bytes]
    values = np.ascontiguousarray(rows).view(dtype).reshape(h, w)
    depth_m = values.astype(np.float32) * np.float32(scale)
    depth_m[~np.isfinite(depth_m) | (depth_m < 0)] = 0.0
    return depth_m


@dataclass(frozen=True)
class _Scan:
    """What the first pass learns: times (bag clock, ns), small streams, image facts."""

    depth_ns: np.ndarray  # (M,) every depth message, bag order
    depth_size_wh: tuple[int, int]
    camera_info: Any | None
    imu_ns: np.ndarray
    imu_rows: np.ndarray  # (N, 10): acc xyz, gyr xyz, q wxyz
    joint_ns: np.ndarray
    joint_rows: np.ndarray  # (K, 3): thigh, knee, ankle (rad, sign/offset applied)
    contact_ns: np.ndarray  # (C,) empty without a contact topic
    contact_rows: np.ndarray  # (C, 1): force_n (sign, scale, offset applied; switch 0 / 1)


def _open_reader(bag: Path):  # noqa: ANN202 - rosbags imported lazily
    from rosbags.highlevel import AnyReader
    from rosbags.typesys import Stores, get_typestore

    try:
        reader = AnyReader([bag], default_typestore=get_typestore(Stores.ROS2_HUMBLE))
        reader.open()
    except FileNotFoundError:
        raise BagImportError(bag, "bag not found") from None
    except Exception as exc:  # rosbags raises its own error classes per format
        raise BagImportError(bag, f"cannot be read as a ROS bag ({exc})") from None
    return reader


def _connections(reader: Any, bag: Path, topic: str, kind: str, required: bool) -> list:
    topics = reader.topics
    if topic not in topics:
        if not required:
            return []
        have = ", ".join(f"{t} ({i.msgtype})" for t, i in sorted(topics.items())) or "none"
        raise BagImportError(bag, f"{kind} topic not in the bag; the bag has: {have}", field=topic)
    info = topics[topic]
    if info.msgtype != MSGTYPES[kind]:
        raise BagImportError(
            bag, f"{kind} topic has type {info.msgtype}, expected {MSGTYPES[kind]}", field=topic
        )
    if info.msgcount == 0 and required:
        raise BagImportError(bag, f"no messages on the {kind} topic", field=topic)
    return list(info.connections)


def _time_ns(msg: Any, receive_ns: int, use_receive_time: bool) -> int:
    return receive_ns if use_receive_time or not hasattr(msg, "header") else stamp_ns(msg)


def _contact_connections(reader: Any, bag: Path, rc: RigContact) -> list:
    """Connections of the rig's contact topic, checked: present, a supported type (the rig's
    msgtype if given), a type that fits the kind, not empty."""
    topics = reader.topics
    if rc.topic not in topics:
        have = ", ".join(f"{t} ({i.msgtype})" for t, i in sorted(topics.items())) or "none"
        raise BagImportError(
            bag,
            f"contact topic (rig file contact.topic) not in the bag; the bag has: {have}",
            field=rc.topic,
        )
    info = topics[rc.topic]
    if rc.msgtype is not None and info.msgtype != _full_msgtype(rc.msgtype):
        raise BagImportError(
            bag,
            f"contact topic has type {info.msgtype}, the rig file says "
            f"contact.msgtype = {rc.msgtype}",
            field=rc.topic,
        )
    if info.msgtype not in CONTACT_MSGTYPES:
        raise BagImportError(
            bag,
            f"contact topic has type {info.msgtype}, expected one of {', '.join(CONTACT_MSGTYPES)}",
            field=rc.topic,
        )
    if info.msgtype == "std_msgs/msg/Bool" and rc.kind != "switch":
        raise BagImportError(
            bag,
            "contact topic is std_msgs/Bool (a switch) but the rig file "
            f"says contact.kind = {rc.kind}",
            field=rc.topic,
        )
    if info.msgcount == 0:
        raise BagImportError(bag, "no messages on the contact topic", field=rc.topic)
    return list(info.connections)


def _contact_value(msg: Any, rc: RigContact) -> float:
    """force_n of one contact message (see RigContact)."""
    if isinstance(getattr(msg, "data", None), (bool, np.bool_)):
        return 1.0 if msg.data else 0.0
    raw = getattr(msg.wrench.force, rc.wrench_axis) if hasattr(msg, "wrench") else msg.data
    return rc.sign * rc.scale * float(raw) + rc.offset_n


def _scan(bag: Path, topics: BagTopics, rig: RigConfig, use_receive_time: bool) -> _Scan:
    reader = _open_reader(bag)
    try:
        if reader.message_count == 0:
            raise BagImportError(bag, "the bag is empty (no messages)")
        conns = {
            "depth": _connections(reader, bag, topics.depth, "depth", True),
            "camera_info": _connections(
                reader, bag, topics.camera_info, "camera_info", not rig.camera.has_intrinsics
            ),
            "imu": _connections(reader, bag, topics.imu, "imu", True),
            "joints": _connections(reader, bag, topics.joints, "joints", True),
        }
        if rig.contact is not None:
            conns["contact"] = _contact_connections(reader, bag, rig.contact)
        kind_of = {c.id: kind for kind, cs in conns.items() for c in cs}
        wanted = [c for cs in conns.values() for c in cs]
        depth_ns, imu_ns, imu_rows, joint_ns, joint_rows = [], [], [], [], []
        contact_ns: list[int] = []
        contact_rows: list[float] = []
        size_wh: tuple[int, int] | None = None
        camera_info = None
        joint_index: dict[tuple[str, ...], list[int]] = {}
        sources = (rig.joints.thigh_pitch, rig.joints.knee, rig.joints.ankle)
        for conn, receive_ns, raw in reader.messages(connections=wanted):
            kind = kind_of[conn.id]
            msg = reader.deserialize(raw, conn.msgtype)
            t_ns = _time_ns(msg, receive_ns, use_receive_time)
            if kind == "depth":
                if msg.encoding not in DEPTH_ENCODINGS:
                    raise BagImportError(
                        bag,
                        f"depth encoding {msg.encoding!r} not supported "
                        f"(expected one of {sorted(DEPTH_ENCODINGS)})",
                        field=conn.topic,
                    )
                wh = (int(msg.width), int(msg.height))
                if size_wh is None:
                    size_wh = wh
                elif wh != size_wh:
                    raise BagImportError(
                        bag,
                        f"depth frame {len(depth_ns)} is {wh[0]}x{wh[1]} "
                        f"px, earlier frames {size_wh[0]}x{size_wh[1]} px",
                        field=conn.topic,
                    )
                depth_ns.append(t_ns)
            elif kind == "camera_info":
                camera_info = camera_info if camera_info is not None else msg
            elif kind == "imu":
                o, g, a = msg.orientation, msg.angular_velocity, msg.linear_acceleration
                imu_ns.append(t_ns)
                imu_rows.append((a.x, a.y, a.z, g.x, g.y, g.z, o.w, o.x, o.y, o.z))
            elif kind == "contact":
                assert rig.contact is not None
                contact_ns.append(t_ns)
                contact_rows.append(_contact_value(msg, rig.contact))
            else:
                names = tuple(msg.name)
                if names not in joint_index:
                    missing = [s.name for s in sources if s.name not in names]
                    if missing:
                        raise BagImportError(
                            bag,
                            f"JointState without joints {missing}; it "
                            f"names {list(names)} (set joints.*.name in the "
                            "rig file)",
                            field=conn.topic,
                        )
                    joint_index[names] = [names.index(s.name) for s in sources]
                pos = np.asarray(msg.position, dtype=float)
                idx = joint_index[names]
                if pos.shape[0] <= max(idx):
                    raise BagImportError(
                        bag,
                        f"JointState with {pos.shape[0]} positions for {len(names)} names",
                        field=conn.topic,
                    )
                joint_ns.append(t_ns)
                joint_rows.append(
                    [s.sign * pos[i] + s.offset_rad for s, i in zip(sources, idx, strict=True)]
                )
    except BagImportError:
        raise
    except Exception as exc:  # corrupt chunks, undecodable messages
        raise BagImportError(bag, f"cannot be read ({exc.__class__.__name__}: {exc})") from None
    finally:
        reader.close()
    assert size_wh is not None  # the depth topic has messages
    return _Scan(
        depth_ns=np.asarray(depth_ns, dtype=np.int64),
        depth_size_wh=size_wh,
        camera_info=camera_info,
        imu_ns=np.asarray(imu_ns, dtype=np.int64),
        imu_rows=np.asarray(imu_rows, dtype=float).reshape(-1, 10),
        joint_ns=np.asarray(joint_ns, dtype=np.int64),
        joint_rows=np.asarray(joint_rows, dtype=float).reshape(-1, 3),
        contact_ns=np.asarray(contact_ns, dtype=np.int64),
        contact_rows=np.asarray(contact_rows, dtype=float).reshape(-1, 1),
    )


# ---------------------------------------------------------------------------- checks
def _sorted_unique(t_ns: np.ndarray, rows: np.ndarray) -> tuple[np.ndarray, np.ndarray, int]:
    """Samples sorted by time with repeated timestamps dropped (first kept); count dropped."""
    order = np.argsort(t_ns, kind="stable")
    t, r = t_ns[order], rows[order]
    keep = np.concatenate([[True], np.diff(t) > 0])
    return t[keep], r[keep], int((~keep).sum())


def _bracketing(t_ns: np.ndarray, start_ns: int, end_ns: int) -> slice:
    """Samples inside [start, end] plus one on each side, so that every depth frame time can be
    interpolated between two samples (``t_ns`` sorted)."""
    first = max(int(np.searchsorted(t_ns, start_ns, side="left")) - 1, 0)
    stop = min(int(np.searchsorted(t_ns, end_ns, side="right")) + 1, t_ns.shape[0])
    return slice(first, stop)


def _increasing_mask(t_ns: np.ndarray) -> np.ndarray:
    """Keep a depth frame only if it is later than every frame kept before it (bag order)."""
    keep = np.zeros(t_ns.shape[0], dtype=bool)
    last = np.iinfo(np.int64).min
    for i, t in enumerate(t_ns):
        if t > last:
            keep[i], last = True, t
    return keep


def _check_rate(bag: Path, topic: str, t_ns: np.ndarray, declared_hz: float, field: str) -> float:
    if t_ns.shape[0] < 3:
        raise BagImportError(
            bag, f"only {t_ns.shape[0]} samples in the shared time span", field=topic
        )
    measured = 1e9 / float(np.median(np.diff(t_ns)))
    if abs(measured - declared_hz) > RATE_TOLERANCE * declared_hz:
        raise BagImportError(
            bag,
            f"measured rate {measured:.2f} Hz, the rig file declares {field} = {declared_hz:g} Hz",
            field=topic,
        )
    return measured


def _field(msg: Any, ros1_name: str, ros2_name: str) -> Any:
    """A field spelled differently in ROS 1 and ROS 2 message definitions (CameraInfo K / k)."""
    return getattr(msg, ros1_name) if hasattr(msg, ros1_name) else getattr(msg, ros2_name)


def _camera_model(
    bag: Path, topics: BagTopics, rig: RigConfig, scan: _Scan
) -> tuple[CameraModel, str]:
    """Camera model and a note on its source (and on lens distortion the format cannot hold)."""
    w, h = scan.depth_size_wh
    cam = rig.camera
    note = ""
    if cam.has_intrinsics:
        fx, fy, cx, cy = cam.fx_px, cam.fy_px, cam.cx_px, cam.cy_px
        note = "intrinsics from the rig file"
    else:
        info = scan.camera_info
        if info is None:
            raise BagImportError(
                bag,
                "no camera_info message and no intrinsics in the rig file",
                field=topics.camera_info,
            )
        if (int(info.width), int(info.height)) != (w, h):
            raise BagImportError(
                bag,
                f"camera_info is {info.width}x{info.height} px but depth frames are {w}x{h} px",
                field=topics.camera_info,
            )
        k = np.asarray(_field(info, "K", "k"), dtype=float)
        fx, fy, cx, cy = k[0], k[4], k[2], k[5]
        if not (fx > 0 and fy > 0):
            raise BagImportError(
                bag, f"camera_info K has fx={fx}, fy={fy}", field=topics.camera_info
            )
        note = "intrinsics from camera_info"
        d = np.asarray(_field(info, "D", "d"), dtype=float)
        if d.size and np.any(d != 0):
            log.warning("%s: camera_info has distortion %s; stored as a pinhole model", bag, d)
            note += f" (distortion {np.round(d, 6).tolist()} not applied: pinhole model)"
    model = CameraModel(
        width_px=w,
        height_px=h,
        fx_px=float(fx),
        fy_px=float(fy),
        cx_px=float(cx),
        cy_px=float(cy),
        depth_unit_m=cam.depth_unit_m,
        min_range_m=cam.min_range_m,
        max_range_m=cam.max_range_m,
        frame_rate_hz=cam.frame_rate_hz,
        model=cam.model,
    )
    return model, note


def _load_groundtruth(gt_dir: Path, t0_ns: int) -> GroundTruth:
    """TUM files camera/knee/ankle/heel/toe.tum, timestamps on the bag clock (s)."""
    trajs = {}
    for body in GROUNDTRUTH_BODIES:
        path = gt_dir / f"{body}.tum"
        if not path.is_file():
            raise BagImportError(path, f"ground truth needs {', '.join(GROUNDTRUTH_BODIES)} .tum")
        traj = read_tum(path)
        rel = traj.timestamp_s - t0_ns * 1e-9
        trajs[body] = type(traj)(rel, traj.position_m, traj.quat_wxyz)
    return GroundTruth(trajectories=trajs)


# ---------------------------------------------------------------------------- import
def _depth_frames(
    bag: Path, topic: str, keep: np.ndarray, scanned_ns: np.ndarray, use_receive_time: bool
) -> Iterator[tuple[np.ndarray, np.ndarray]]:
    """Second pass: the kept depth frames, one at a time (metres, confidence 255 if valid)."""
    reader = _open_reader(bag)
    try:
        conns = list(reader.topics[topic].connections)
        for i, (conn, receive_ns, raw) in enumerate(reader.messages(connections=conns)):
            if i < keep.shape[0] and keep[i]:
                msg = reader.deserialize(raw, conn.msgtype)
                if _time_ns(msg, receive_ns, use_receive_time) != scanned_ns[i]:
                    raise BagImportError(
                        bag,
                        f"depth message {i} changed between the two "
                        "passes (bag modified while importing?)",
                        field=topic,
                    )
                try:
                    depth_m = decode_depth_image(msg)
                except ValueError as exc:
                    raise BagImportError(bag, f"depth message {i}: {exc}", field=topic) from None
                yield depth_m, np.where(depth_m > 0, 255, 0).astype(np.uint8)
    finally:
        reader.close()


def import_bag(
    bag_path: str | Path,
    rig_yaml: str | Path,
    out_dir: str | Path,
    topics: BagTopics | None = None,
    use_receive_time: bool = False,
    groundtruth_dir: str | Path | None = None,
    progress: Callable[[int], None] | None = None,
    overwrite: bool = False,
) -> Path:
    """Convert one bag into a recording folder; returns ``out_dir``.

    Args:
        bag_path: ROS 1 ``.bag``, ROS 2 bag folder (``.db3`` or ``.mcap`` inside) or a bare
            ``.mcap`` / ``.db3`` file.
        rig_yaml: rig file (configs/rig_example.yaml documents every field).
        topics: topic names (defaults: :class:`BagTopics`).
        use_receive_time: time samples by the bag's receive time instead of header.stamp.
        groundtruth_dir: optional folder with camera/knee/ankle/heel/toe.tum on the bag clock.
        progress: called with the number of depth frames written so far.
    """
    bag, topics = Path(bag_path), topics or BagTopics()
    rig = load_rig(rig_yaml)
    scan = _scan(bag, topics, rig, use_receive_time)

    # the time span all streams share (depth, IMU, joints and contact if any), widened by half
    # a depth frame period so that streams starting a few ms apart do not cost a frame
    rc = rig.contact
    streams = [scan.depth_ns, scan.imu_ns, scan.joint_ns] + ([scan.contact_ns] if rc else [])
    start_ns = max(int(t.min()) for t in streams)
    end_ns = min(int(t.max()) for t in streams)
    if end_ns <= start_ns:
        raise BagImportError(
            bag,
            "depth, IMU, joint"
            + (" and contact" if rc else "")
            + " streams do not overlap in time",
        )
    slack_ns = int(0.5e9 / rig.camera.frame_rate_hz)
    start_ns, end_ns = start_ns - slack_ns, end_ns + slack_ns
    imu_ns, imu_rows, imu_dups = _sorted_unique(scan.imu_ns, scan.imu_rows)
    joint_ns, joint_rows, joint_dups = _sorted_unique(scan.joint_ns, scan.joint_rows)
    in_span = lambda t: (t >= start_ns) & (t <= end_ns)  # noqa: E731
    imu_sel, joint_sel = (
        _bracketing(imu_ns, start_ns, end_ns),
        _bracketing(joint_ns, start_ns, end_ns),
    )
    imu_ns, imu_rows = imu_ns[imu_sel], imu_rows[imu_sel]
    joint_ns, joint_rows = joint_ns[joint_sel], joint_rows[joint_sel]
    contact_ns, contact_rows, contact_dups = scan.contact_ns, scan.contact_rows, 0
    if rc is not None:
        contact_ns, contact_rows, contact_dups = _sorted_unique(contact_ns, contact_rows)
        contact_sel = _bracketing(contact_ns, start_ns, end_ns)
        contact_ns, contact_rows = contact_ns[contact_sel], contact_rows[contact_sel]
    keep = _increasing_mask(scan.depth_ns) & in_span(scan.depth_ns)
    depth_ns = scan.depth_ns[keep]

    _check_rate(bag, topics.depth, depth_ns, rig.camera.frame_rate_hz, "camera.frame_rate_hz")
    _check_rate(bag, topics.imu, imu_ns, rig.imu.rate_hz, "imu.rate_hz")
    _check_rate(bag, topics.joints, joint_ns, rig.joints.rate_hz, "joints.rate_hz")
    contact, contact_model = None, None
    if rc is not None:
        if rc.rate_hz is not None:
            _check_rate(bag, rc.topic, contact_ns, rc.rate_hz, "contact.rate_hz")
        force = contact_rows[:, 0]
        if rc.kind == "switch" and not np.all(np.isin(force, (0.0, 1.0))):
            bad = force[~np.isin(force, (0.0, 1.0))][0]
            raise BagImportError(
                bag,
                f"a switch must read 0 or 1 after sign and scale, got "
                f"{bad:g} (use std_msgs/Bool, or kind: load_cell)",
                field=rc.topic,
            )
        if not np.all(np.isfinite(force)):
            raise BagImportError(bag, "contact force is NaN or inf", field=rc.topic)
        contact_model = ContactModel(kind=rc.kind, threshold_n=rc.threshold)
    q_norm = np.linalg.norm(imu_rows[:, 6:10], axis=1)
    if np.any(np.abs(q_norm - 1.0) > QUAT_NORM_TOLERANCE):
        row = int(np.argmax(np.abs(q_norm - 1.0)))
        raise BagImportError(
            bag,
            f"IMU orientation not a unit quaternion (sample {row}, norm "
            f"{q_norm[row]:.4g}); the recording needs the vendor orientation",
            field=topics.imu,
        )

    camera, camera_note = _camera_model(bag, topics, rig, scan)
    kept = [depth_ns, imu_ns, joint_ns] + ([contact_ns] if rc else [])
    t0_ns = min(int(t[0]) for t in kept)  # earliest kept sample
    t1_ns = max(int(t[-1]) for t in kept)
    rel = lambda t: (t - t0_ns).astype(float) * 1e-9  # noqa: E731
    dropped = {
        "imu_repeated_stamps": imu_dups,
        "joint_repeated_stamps": joint_dups,
        "depth_out_of_order_or_repeated": int((~_increasing_mask(scan.depth_ns)).sum()),
        "depth_outside_shared_span": int((~in_span(scan.depth_ns)).sum()),
    }
    if rc is not None:
        dropped["contact_repeated_stamps"] = contact_dups
    metadata = RecordingMetadata(
        format_version=FORMAT_VERSION,
        duration_s=(t1_ns - t0_ns) * 1e-9,
        camera=camera,
        imu=rig.imu,
        joint_rate_hz=rig.joints.rate_hz,
        groundtruth_rate_hz=rig.groundtruth_rate_hz if groundtruth_dir else None,
        extrinsics=rig.extrinsics,
        leg=rig.leg,
        terrain=rig.terrain,
        provenance=Provenance(
            source="device",
            config={
                "bag": str(bag),
                "rig_file": str(rig_yaml),
                "topics": topics.model_dump() | ({"contact": rc.topic} if rc else {}),
                "time_source": "receive" if use_receive_time else "header.stamp",
                "time_origin_ns": t0_ns,
                "dropped": dropped,
            },
            software=f"vio_graph {vio_graph.__version__} rosbag_import",
            created_utc=_dt.datetime.now(_dt.UTC).strftime("%Y-%m-%dT%H:%M:%SZ"),
            notes="; ".join(x for x in (rig.notes, camera_note) if x),
        ),
        contact=contact_model,
    )
    imu = ImuTable(rel(imu_ns), imu_rows[:, 0:3], imu_rows[:, 3:6], imu_rows[:, 6:10])
    joints = JointTable(rel(joint_ns), joint_rows[:, 0], joint_rows[:, 1], joint_rows[:, 2])
    if contact_model is not None:
        force = contact_rows[:, 0]
        contact = ContactTable(rel(contact_ns), force, force >= contact_model.threshold_n)
    gt = _load_groundtruth(Path(groundtruth_dir), t0_ns) if groundtruth_dir else None
    log.info(
        "%s: %d depth frames, %d IMU, %d joint samples over %.2f s; dropped %s",
        bag,
        depth_ns.shape[0],
        len(imu),
        len(joints),
        metadata.duration_s,
        dropped,
    )
    return write_recording(
        Path(out_dir),
        metadata,
        imu,
        joints,
        gt,
        rel(depth_ns),
        _depth_frames(bag, topics.depth, keep, scan.depth_ns, use_receive_time),
        progress=progress,
        overwrite=overwrite,
        contact=contact,
    )


__all__: Sequence[str] = [
    "BagTopics",
    "RigConfig",
    "RigContact",
    "decode_depth_image",
    "import_bag",
    "load_rig",
]
