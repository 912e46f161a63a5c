"""ROS bag import: synthetic ROS 1 .bag and ROS 2 .mcap bags round-trip into recordings."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest
import yaml
from rosbags.rosbag1 import Writer as Writer1
from rosbags.rosbag2 import StoragePlugin
from rosbags.rosbag2 import Writer as Writer2
from rosbags.typesys import Stores, get_typestore

from vio_graph.errors import BagImportError, ConfigError
from vio_graph.recording import Recording
from vio_graph.recording.rosbag_import import BagTopics, import_bag, load_rig

REPO = Path(__file__).resolve().parents[1]
RIG_EXAMPLE = REPO / "configs" / "rig_example.yaml"
T0_NS = 1_700_000_000_123_456_789  # bag clock (ROS time) of the first sample
W, H = 16, 12
N_FRAMES, FRAME_DT_NS = 10, 100_000_000  # 10 Hz
N_IMU, IMU_DT_NS = 100, 10_000_000  # 100 Hz, 1 s
FX, FY, CX, CY = 14.0, 15.0, 7.5, 5.5


def _depth_m(i: int) -> np.ndarray:
    """Frame i: a ramp 0.5..0.9 m shifted by i cm, one NaN and one 0 pixel (invalid)."""
    d = (0.5 + 0.4 * np.linspace(0, 1, W * H).reshape(H, W) + 0.01 * i).astype(np.float32)
    d[0, 0], d[1, 1] = np.nan, 0.0
    return d


def _imu_rows() -> np.ndarray:
    """(N, 10): acc xyz, gyr xyz, q wxyz (unit) with distinct values per sample."""
    k = np.arange(N_IMU)
    pitch = 0.1 * np.sin(k / 10)
    acc = np.column_stack([0.3 * np.cos(k / 7), 0.01 * k, 9.81 + 0.2 * np.sin(k / 5)])
    gyr = np.column_stack([0.001 * k, np.cos(k / 9), -0.002 * k])
    q = np.column_stack([np.cos(pitch / 2), 0 * k, np.sin(pitch / 2), 0 * k])
    return np.column_stack([acc, gyr, q])


def _joint_rows() -> np.ndarray:
    k = np.arange(N_IMU)
    return np.column_stack([0.3 * np.sin(k / 20), 0.5 + 0.2 * np.cos(k / 15), -0.1 * np.sin(k / 8)])


def _contact_force_n() -> np.ndarray:
    """Load-cell force per IMU tick, N: stance ~700 N, swing ~10 N."""
    k = np.arange(N_IMU)
    return 355.0 + 345.0 * np.sin(k / 8)


def _switch_closed() -> np.ndarray:
    return (np.arange(N_IMU) // 20) % 2 == 0


def _write_bag(
    path: Path,
    ros2: bool,
    skip: tuple[str, ...] = (),
    encoding: str = "32FC1",
    storage: StoragePlugin = StoragePlugin.MCAP,
    contact: str | None = None,
) -> Path:
    """A synthetic bag: depth, camera_info, IMU and joint states on the default topics;
    ``contact`` adds a foot-contact topic ``/contact`` of that type (std_msgs/msg/Float64 as
    -force / 2, std_msgs/msg/Bool, geometry_msgs/msg/WrenchStamped with force.z = force),
    sampled at the IMU rate; header-less types are timed by their receive time."""
    ts = get_typestore(Stores.ROS2_HUMBLE if ros2 else Stores.ROS1_NOETIC)
    T = ts.types
    topics = BagTopics()

    def header(t_ns: int):
        stamp = T["builtin_interfaces/msg/Time"](sec=t_ns // 10**9, nanosec=t_ns % 10**9)
        if ros2:
            return T["std_msgs/msg/Header"](stamp=stamp, frame_id="pico_flexx_optical_frame")
        return T["std_msgs/msg/Header"](seq=0, stamp=stamp, frame_id="pico_flexx_optical_frame")

    msgs: list[tuple[str, str, int, object]] = []  # topic, type, receive time, message
    for i in range(N_FRAMES):
        t = T0_NS + i * FRAME_DT_NS
        d = _depth_m(i)
        data = (np.nan_to_num(d) * 1000).astype("<u2") if encoding == "16UC1" else d.astype("<f4")
        img = T["sensor_msgs/msg/Image"](
            header=header(t),
            height=H,
            width=W,
            encoding=encoding,
            is_bigendian=0,
            step=W * data.itemsize,
            data=np.frombuffer(data.tobytes(), np.uint8),
        )
        msgs.append((topics.depth, "sensor_msgs/msg/Image", t + 2_000_000, img))
        roi = T["sensor_msgs/msg/RegionOfInterest"](
            x_offset=0, y_offset=0, height=0, width=0, do_rectify=False
        )
        k = np.array([FX, 0, CX, 0, FY, CY, 0, 0, 1], dtype=float)
        p = np.array([FX, 0, CX, 0, 0, FY, CY, 0, 0, 0, 1, 0], dtype=float)
        fields = dict(
            header=header(t),
            height=H,
            width=W,
            distortion_model="plumb_bob",
            binning_x=0,
            binning_y=0,
            roi=roi,
        )
        if ros2:
            fields.update(d=np.zeros(5), k=k, r=np.eye(3).ravel(), p=p)
        else:
            fields.update(D=np.zeros(5), K=k, R=np.eye(3).ravel(), P=p)
        msgs.append(
            (
                topics.camera_info,
                "sensor_msgs/msg/CameraInfo",
                t + 2_000_000,
                T["sensor_msgs/msg/CameraInfo"](**fields),
            )
        )
    vec = T["geometry_msgs/msg/Vector3"]
    for i, r in enumerate(_imu_rows()):
        t = T0_NS + i * IMU_DT_NS
        imu = T["sensor_msgs/msg/Imu"](
            header=header(t),
            orientation=T["geometry_msgs/msg/Quaternion"](x=r[7], y=r[8], z=r[9], w=r[6]),
            orientation_covariance=np.zeros(9),
            angular_velocity=vec(x=r[3], y=r[4], z=r[5]),
            angular_velocity_covariance=np.zeros(9),
            linear_acceleration=vec(x=r[0], y=r[1], z=r[2]),
            linear_acceleration_covariance=np.zeros(9),
        )
        msgs.append((topics.imu, "sensor_msgs/msg/Imu", t + 1_000_000, imu))
    for i, r in enumerate(_joint_rows()):
        t = T0_NS + i * IMU_DT_NS + 3_000_000
        js = T["sensor_msgs/msg/JointState"](
            header=header(t),
            name=["ankle", "knee", "thigh_pitch", "hip_yaw"],
            position=np.array([r[2], r[1], r[0], 9.0]),
            velocity=np.zeros(4),
            effort=np.zeros(4),
        )
        msgs.append((topics.joints, "sensor_msgs/msg/JointState", t + 1_000_000, js))
    for i, (f, closed) in enumerate(zip(_contact_force_n(), _switch_closed(), strict=True)):
        t = T0_NS + i * IMU_DT_NS + 1_000_000  # receive time (= stamp of a WrenchStamped)
        if contact == "std_msgs/msg/Float64":
            msg = T[contact](data=-0.5 * f)
        elif contact == "std_msgs/msg/Bool":
            msg = T[contact](data=bool(closed))
        elif contact == "geometry_msgs/msg/WrenchStamped":
            w = T["geometry_msgs/msg/Wrench"](
                force=vec(x=3.0, y=-2.0, z=f), torque=vec(x=0.0, y=0.0, z=0.0)
            )
            msg = T[contact](header=header(t), wrench=w)
            t += 1_000_000  # received 1 ms after its stamp
        else:
            break
        msgs.append(("/contact", contact, t, msg))
    msgs = [m for m in msgs if m[0] not in skip]
    msgs.sort(key=lambda m: m[2])

    if ros2:
        writer = Writer2(path, version=9, storage_plugin=storage)
        serialize = ts.serialize_cdr
    else:
        writer = Writer1(path)
        serialize = ts.serialize_ros1
    with writer:
        conns = {}
        for topic, msgtype, t, msg in msgs:
            if topic not in conns:
                conns[topic] = writer.add_connection(topic, msgtype, typestore=ts)
            writer.write(conns[topic], t, serialize(msg, msgtype))
    return path


@pytest.fixture(scope="module")
def rig_10hz(tmp_path_factory: pytest.TempPathFactory) -> Path:
    """The example rig file with a 10 Hz camera (the synthetic bags' depth rate)."""
    raw = yaml.safe_load(RIG_EXAMPLE.read_text())
    raw["camera"]["frame_rate_hz"] = 10.0
    path = tmp_path_factory.mktemp("rig") / "rig.yaml"
    path.write_text(yaml.safe_dump(raw))
    return path


@pytest.fixture(scope="module")
def ros1_bag(tmp_path_factory: pytest.TempPathFactory) -> Path:
    return _write_bag(tmp_path_factory.mktemp("bag1") / "trial.bag", ros2=False)


@pytest.fixture(scope="module")
def ros2_bag(tmp_path_factory: pytest.TempPathFactory) -> Path:
    return _write_bag(tmp_path_factory.mktemp("bag2") / "trial_mcap", ros2=True)


def _check_round_trip(rec: Recording) -> None:
    # shared span: 3 ms (first joint sample) .. 0.9 s (last depth frame), widened by half a
    # frame period (50 ms): all frames; IMU 0 .. 0.95 s and joints 0.003 .. 0.943 s, each plus
    # one sample after the span
    assert rec.num_frames == N_FRAMES
    np.testing.assert_allclose(rec.frame_timestamps_s, np.arange(N_FRAMES) * 0.1, atol=1e-9)
    for i in (0, 5, 9):
        f = rec.frame(i)
        want = np.nan_to_num(_depth_m(i))
        assert f.depth_m[0, 0] == 0 and f.depth_m[1, 1] == 0
        assert np.max(np.abs(f.depth_m - want)) <= 0.0005 + 1e-6  # uint16 mm: within 1 mm
        assert np.all((f.confidence == 255) == (want > 0))
    cam = rec.metadata.camera
    assert (cam.width_px, cam.height_px, cam.fx_px, cam.fy_px, cam.cx_px, cam.cy_px) == (
        W,
        H,
        FX,
        FY,
        CX,
        CY,
    )
    n_imu = 97
    rows = _imu_rows()[:n_imu]
    imu = rec.imu
    np.testing.assert_allclose(imu.timestamp_s, np.arange(n_imu) * 0.01, atol=1e-9)
    np.testing.assert_allclose(imu.accel_mps2, rows[:, 0:3], atol=1e-6, rtol=0)
    np.testing.assert_allclose(imu.gyro_radps, rows[:, 3:6], atol=1e-6, rtol=0)
    np.testing.assert_allclose(imu.quat_wxyz, rows[:, 6:10], atol=1e-6, rtol=0)
    j = rec.joints  # stamped 3 ms after the IMU, JointState order ankle, knee, thigh, hip_yaw
    n_joint = 96
    np.testing.assert_allclose(j.timestamp_s, np.arange(n_joint) * 0.01 + 0.003, atol=1e-9)
    np.testing.assert_allclose(
        np.column_stack([j.thigh_pitch_rad, j.knee_rad, j.ankle_rad]),
        _joint_rows()[:n_joint],
        atol=1e-6,
        rtol=0,
    )
    prov = rec.metadata.provenance
    assert prov.source == "device"
    assert prov.config["time_origin_ns"] == T0_NS
    assert rec.metadata.duration_s == pytest.approx(0.96)


def test_ros1_bag_round_trip(ros1_bag: Path, rig_10hz: Path, tmp_path: Path) -> None:
    out = import_bag(ros1_bag, rig_10hz, tmp_path / "rec")
    _check_round_trip(Recording.open(out))


def test_ros2_mcap_round_trip(ros2_bag: Path, rig_10hz: Path, tmp_path: Path) -> None:
    frames: list[int] = []
    out = import_bag(ros2_bag, rig_10hz, tmp_path / "rec", progress=frames.append)
    _check_round_trip(Recording.open(out))
    assert frames[-1] == N_FRAMES
    # a bare .mcap file (no metadata.yaml beside it) reads the same
    mcap = next(ros2_bag.glob("*.mcap"))
    _check_round_trip(Recording.open(import_bag(mcap, rig_10hz, tmp_path / "rec_file")))


def test_ros2_db3_folder(tmp_path: Path, rig_10hz: Path) -> None:
    bag = _write_bag(tmp_path / "trial_db3", ros2=True, storage=StoragePlugin.SQLITE3)
    assert list(bag.glob("*.db3"))
    _check_round_trip(Recording.open(import_bag(bag, rig_10hz, tmp_path / "rec")))


def test_receive_time_option(ros1_bag: Path, rig_10hz: Path, tmp_path: Path) -> None:
    rec = Recording.open(import_bag(ros1_bag, rig_10hz, tmp_path / "rec", use_receive_time=True))
    # depth received 2 ms after its stamp, IMU 1 ms after: origin is the first IMU receive time
    assert rec.metadata.provenance.config["time_origin_ns"] == T0_NS + 1_000_000
    np.testing.assert_allclose(rec.frame_timestamps_s, np.arange(N_FRAMES) * 0.1 + 0.001, atol=1e-9)


def test_16uc1_millimetre_depth(tmp_path: Path, rig_10hz: Path) -> None:
    bag = _write_bag(tmp_path / "mm.bag", ros2=False, encoding="16UC1")
    rec = Recording.open(import_bag(bag, rig_10hz, tmp_path / "rec"))
    assert np.max(np.abs(rec.frame(3).depth_m - np.nan_to_num(_depth_m(3)))) <= 0.001 + 1e-6


def test_missing_imu_topic_names_bag_and_lists_topics(tmp_path: Path, rig_10hz: Path) -> None:
    bag = _write_bag(tmp_path / "noimu.bag", ros2=False, skip=("/imu/data",))
    with pytest.raises(BagImportError) as err:
        import_bag(bag, rig_10hz, tmp_path / "rec")
    msg = str(err.value)
    assert str(bag) in msg and "/imu/data" in msg
    assert "/pico_flexx/image_depth (sensor_msgs/msg/Image)" in msg
    assert "/joint_states (sensor_msgs/msg/JointState)" in msg
    assert not (tmp_path / "rec").exists()


def test_other_topic_name_and_wrong_encoding(tmp_path: Path, rig_10hz: Path) -> None:
    bag = _write_bag(tmp_path / "enc.bag", ros2=False, encoding="rgb8")
    with pytest.raises(BagImportError, match="encoding 'rgb8' not supported"):
        import_bag(bag, rig_10hz, tmp_path / "rec")
    with pytest.raises(BagImportError, match="/camera/depth"):
        import_bag(bag, rig_10hz, tmp_path / "rec", topics=BagTopics(depth="/camera/depth"))


def test_rate_mismatch_and_bad_joint_names(tmp_path: Path, ros1_bag: Path) -> None:
    raw = yaml.safe_load(RIG_EXAMPLE.read_text())  # camera declared at 30 Hz, bag has 10 Hz
    rig = tmp_path / "rig30.yaml"
    rig.write_text(yaml.safe_dump(raw))
    with pytest.raises(BagImportError, match=r"10.00 Hz.*camera.frame_rate_hz = 30 Hz"):
        import_bag(ros1_bag, rig, tmp_path / "rec")
    raw["camera"]["frame_rate_hz"] = 10.0
    raw["joints"]["knee"]["name"] = "knee_joint"
    rig.write_text(yaml.safe_dump(raw))
    with pytest.raises(BagImportError, match=r"without joints \['knee_joint'\]"):
        import_bag(ros1_bag, rig, tmp_path / "rec")


def test_empty_bag(tmp_path: Path, rig_10hz: Path) -> None:
    ts = get_typestore(Stores.ROS1_NOETIC)
    bag = tmp_path / "empty.bag"
    with Writer1(bag) as w:
        w.add_connection("/imu/data", "sensor_msgs/msg/Imu", typestore=ts)
    with pytest.raises(BagImportError, match="empty"):
        import_bag(bag, rig_10hz, tmp_path / "rec")
    with pytest.raises(BagImportError, match="not found"):
        import_bag(tmp_path / "nope.bag", rig_10hz, tmp_path / "rec")


def test_rig_file_errors_name_file_and_field(tmp_path: Path) -> None:
    assert load_rig(RIG_EXAMPLE).camera.has_intrinsics is False
    raw = yaml.safe_load(RIG_EXAMPLE.read_text())
    raw["leg"]["shank_length_m"] = -0.4
    bad = tmp_path / "bad.yaml"
    bad.write_text(yaml.safe_dump(raw))
    with pytest.raises(ConfigError, match=r"bad.yaml \[leg.shank_length_m\]"):
        load_rig(bad)
    raw = yaml.safe_load(RIG_EXAMPLE.read_text())
    raw["camera"]["fx_px"] = 200.0  # only one of the four intrinsics
    bad.write_text(yaml.safe_dump(raw))
    with pytest.raises(ConfigError, match=r"bad.yaml \[camera\].*all of fx_px"):
        load_rig(bad)


def test_cli_import_bag(ros1_bag: Path, rig_10hz: Path, tmp_path: Path) -> None:
    from typer.testing import CliRunner

    from vio_graph.cli import app

    out = tmp_path / "rec"
    res = CliRunner().invoke(
        app, ["import-bag", str(ros1_bag), "--rig", str(rig_10hz), "--out", str(out)]
    )
    assert res.exit_code == 0, res.output
    assert Recording.open(out).num_frames == N_FRAMES
    res = CliRunner().invoke(
        app,
        [
            "import-bag",
            str(ros1_bag),
            "--rig",
            str(rig_10hz),
            "--out",
            str(tmp_path / "rec2"),
            "--imu-topic",
            "/xsens/imu",
        ],
    )
    assert isinstance(res.exception, BagImportError) and "/xsens/imu" in str(res.exception)


# ------------------------------------------------------------------ foot contact


def _rig_with_contact(rig_10hz: Path, tmp_path: Path, **contact) -> Path:
    raw = yaml.safe_load(rig_10hz.read_text())
    raw["contact"] = contact
    path = tmp_path / "rig_contact.yaml"
    path.write_text(yaml.safe_dump(raw))
    return path


@pytest.mark.parametrize(
    ("ros2", "msgtype", "mapping"),
    [
        (
            False,
            "std_msgs/msg/Float64",
            dict(
                kind="load_cell", msgtype="std_msgs/Float64", threshold_n=100.0, scale=2.0, sign=-1
            ),
        ),
        (True, "geometry_msgs/msg/WrenchStamped", dict(kind="load_cell", threshold_n=100.0)),
        (False, "std_msgs/msg/Bool", dict(kind="switch", msgtype="std_msgs/Bool")),
    ],
)
def test_contact_topic_becomes_contact_csv(
    tmp_path: Path, rig_10hz: Path, ros2: bool, msgtype: str, mapping: dict
) -> None:
    bag = _write_bag(tmp_path / ("c_mcap" if ros2 else "c.bag"), ros2=ros2, contact=msgtype)
    rig = _rig_with_contact(rig_10hz, tmp_path, topic="/contact", **mapping)
    rec = Recording.open(import_bag(bag, rig, tmp_path / "rec"))
    _check_round_trip(rec)  # the other streams are unchanged by the contact topic
    c = rec.contact
    assert c is not None and rec.metadata.contact is not None
    # received (or stamped) 1 ms after each IMU tick; the shared span ends 50 ms after the last
    # depth frame (0.95 s): samples 0 .. 94 plus one after
    n = 96
    np.testing.assert_allclose(c.timestamp_s, np.arange(n) * 0.01 + 0.001, atol=1e-9)
    if mapping["kind"] == "switch":
        assert rec.metadata.contact.kind == "switch" and rec.metadata.contact.threshold_n == 0.5
        assert np.array_equal(c.force_n, _switch_closed()[:n].astype(float))
        assert np.array_equal(c.loaded, _switch_closed()[:n])
    else:
        assert rec.metadata.contact.kind == "load_cell"
        assert rec.metadata.contact.threshold_n == 100.0
        np.testing.assert_allclose(c.force_n, _contact_force_n()[:n], rtol=1e-8, atol=1e-6)
        assert np.array_equal(c.loaded, _contact_force_n()[:n] >= 100.0)
    assert rec.metadata.provenance.config["topics"]["contact"] == "/contact"


def test_contact_topic_missing_or_mismatched_names_it(
    tmp_path: Path, rig_10hz: Path, ros1_bag: Path
) -> None:
    rig = _rig_with_contact(
        rig_10hz, tmp_path, topic="/prosthesis/load_cell", kind="load_cell", threshold_n=80.0
    )
    with pytest.raises(BagImportError) as err:
        import_bag(ros1_bag, rig, tmp_path / "rec")
    msg = str(err.value)
    assert "/prosthesis/load_cell" in msg and "contact" in msg and str(ros1_bag) in msg
    assert "/imu/data (sensor_msgs/msg/Imu)" in msg  # lists what the bag has
    assert not (tmp_path / "rec").exists()
    # the rig's msgtype must match the bag's
    bag = _write_bag(tmp_path / "b.bag", ros2=False, contact="std_msgs/msg/Bool")
    rig = _rig_with_contact(
        rig_10hz, tmp_path, topic="/contact", kind="switch", msgtype="std_msgs/Float32"
    )
    with pytest.raises(BagImportError, match=r"/contact.*std_msgs/msg/Bool.*std_msgs/Float32"):
        import_bag(bag, rig, tmp_path / "rec")
    # a Bool is a switch, not a load cell
    rig = _rig_with_contact(
        rig_10hz, tmp_path, topic="/contact", kind="load_cell", threshold_n=50.0
    )
    with pytest.raises(BagImportError, match="contact.kind = load_cell"):
        import_bag(bag, rig, tmp_path / "rec")
    # a numeric switch topic that is not 0 / 1
    bag = _write_bag(tmp_path / "f.bag", ros2=False, contact="std_msgs/msg/Float64")
    rig = _rig_with_contact(rig_10hz, tmp_path, topic="/contact", kind="switch")
    with pytest.raises(BagImportError, match="switch must read 0 or 1"):
        import_bag(bag, rig, tmp_path / "rec")


def test_rig_contact_section_is_validated(tmp_path: Path, rig_10hz: Path) -> None:
    rig = _rig_with_contact(rig_10hz, tmp_path, topic="/lc", kind="load_cell")
    with pytest.raises(ConfigError, match=r"\[contact\].*threshold_n"):
        load_rig(rig)
    rig = _rig_with_contact(
        rig_10hz, tmp_path, topic="/lc", kind="switch", msgtype="std_msgs/String"
    )
    with pytest.raises(ConfigError, match=r"\[contact\].*not supported"):
        load_rig(rig)
    rig = _rig_with_contact(
        rig_10hz,
        tmp_path,
        topic="/lc",
        kind="load_cell",
        threshold_n=80.0,
        msgtype="geometry_msgs/WrenchStamped",
    )
    assert load_rig(rig).contact.threshold == 80.0
