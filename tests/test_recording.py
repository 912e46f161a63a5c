"""Recording format: round trips, laziness, and malformed input naming file and field."""

from __future__ import annotations

import shutil
from pathlib import Path

import numpy as np
import pytest
import yaml

from tests.conftest import tiny_metadata, tiny_streams
from vio_graph.errors import OutputError, RecordingError
from vio_graph.recording import Recording, write_recording
from vio_graph.recording.tum import read_tum, write_tum


def test_round_trip(tiny_recording: Path) -> None:
    meta = tiny_metadata()
    imu, joints, gt, t_frames, frames = tiny_streams(meta)
    rec = Recording.open(tiny_recording)
    assert rec.metadata == meta
    np.testing.assert_allclose(rec.imu.accel_mps2, imu.accel_mps2, rtol=1e-8, atol=1e-9)
    np.testing.assert_allclose(rec.imu.quat_wxyz, imu.quat_wxyz, atol=1e-8)
    np.testing.assert_allclose(rec.joints.knee_rad, joints.knee_rad)
    np.testing.assert_allclose(rec.frame_timestamps_s, t_frames)
    assert rec.num_frames == len(frames)
    for k in (0, 5, len(frames) - 1):
        f = rec.frame(k)
        assert f.depth_m.dtype == np.float32
        np.testing.assert_allclose(f.depth_m[f.depth_m > 0], frames[k][0][f.depth_m > 0], atol=5e-4)
    assert rec.frame(0).depth_m[0, 0] == 0 and rec.frame(0).confidence[0, 0] == 0
    for body, traj in gt.trajectories.items():
        np.testing.assert_allclose(
            rec.groundtruth.trajectories[body].position_m, traj.position_m, atol=1e-6
        )
    np.testing.assert_array_equal(rec.groundtruth.frame_edge_visible, gt.frame_edge_visible)


def test_frame_equals_the_straightforward_conversion(tiny_recording: Path) -> None:
    """frame() (one float32 multiply, counts from the valid mask) gives what converting the
    stored frame step by step gives: uint16 -> float32, times the unit, confidence 0 where
    the depth is not positive; with zero-depth pixels in the frame."""
    rec = Recording.open(tiny_recording)
    depth, scale, conf = rec._depth
    assert depth.dtype == np.uint16
    n_zero = 0
    for k in range(rec.num_frames):
        f = rec.frame(k)
        want = np.array(depth[k]).astype(np.float32) * np.float32(scale)
        want_conf = np.array(conf[k])
        want_conf[want <= 0] = 0
        n_zero += int(np.count_nonzero(want == 0))
        assert f.depth_m.dtype == np.float32 and f.confidence.dtype == np.uint8
        assert np.array_equal(f.depth_m, want) and np.array_equal(f.confidence, want_conf)
    assert n_zero > 0  # invalid pixels were zeroed in the confidence


@pytest.mark.parametrize(
    ("scale", "min_range_m", "max_range_m"),
    [
        (0.001, 0.1, 2.4),
        (1e-4, 0.2, 4.0),
        (1e-3 / 3, 0.1, 5.0),
        (2.5e-4, 0.0, 1.0),
        # exact depths (k / 1024 m) on thresholds a hair off a float32: compared in float64,
        # 3686 / 1024 m would be beyond the far one and 51 / 1024 m not below the near one
        (2.0**-10, 2.0 * (51 * 2.0**-10 + 1e-9), (3686 * 2.0**-10 - 1e-8) / 1.5),
    ],
)
def test_compiled_conversion_equals_the_numpy_path(
    tiny_recording: Path,
    monkeypatch: pytest.MonkeyPatch,
    scale: float,
    min_range_m: float,
    max_range_m: float,
) -> None:
    """The reader's one-pass compiled conversion of a uint16 frame (recording/compiled.py,
    on with the compiled paths) against its numpy path: the same float32 depths bit for bit,
    the same valid mask and count, and the same unit-check errors, on frames whose units land
    on, just above and just below the far and near thresholds (compared in float32 as numpy
    compares a float32 array with a Python float), zero pixels, and frames that fail a check."""
    pytest.importorskip("numba")
    from vio_graph.frontend.icp import COMPILED_ENV

    rec = Recording.open(tiny_recording)
    cam = rec.metadata.camera.model_copy(
        update={"min_range_m": min_range_m, "max_range_m": max_range_m}
    )
    rec.__dict__["metadata"] = rec.metadata.model_copy(update={"camera": cam})
    rng = np.random.default_rng(3)
    edges = [0.0]
    for t in (1.5 * max_range_m, 0.5 * min_range_m):
        u = int(round(float(np.float32(t)) / float(np.float32(scale))))
        edges += [float(v) for v in range(max(u - 3, 0), min(u + 4, 65536))]
    frames = []
    for k in range(60):
        kind = k % 4
        if kind == 0:  # a usual frame: mostly in range, some edge values and zeros
            f = rng.integers(0, 65536, size=(12, 16)).astype(float)
            f[rng.random(f.shape) < 0.5] = int(1.0 / scale)
        elif kind == 1:  # edge values only
            f = rng.choice(edges, size=(12, 16))
        elif kind == 2:  # mostly beyond the far threshold (fails a check), or empty
            f = np.full((12, 16), 65535.0 if k % 8 == 2 else 0.0)
        else:  # mostly below the near threshold
            f = rng.choice(edges[: len(edges) // 2 + 1], size=(12, 16))
            f[0, :3] = 65535.0
        frames.append(f)
    depth = np.stack(frames).astype(np.uint16)

    def convert(mode: str, k: int):
        monkeypatch.setenv(COMPILED_ENV, mode)
        try:
            return rec._convert(k, depth, scale, np.array(depth[k]) if k % 2 else None)
        except RecordingError as exc:
            return str(exc)

    n_errors = 0
    for k in range(depth.shape[0]):
        ref, fast = convert("0", k), convert("1", k)
        if isinstance(ref, str):
            n_errors += 1
            assert fast == ref
            continue
        assert not isinstance(fast, str)
        assert fast[0].dtype == np.float32 and fast[0].tobytes() == ref[0].tobytes()
        assert np.array_equal(fast[1], ref[1]) and fast[2] == ref[2]
    assert n_errors > 0  # the checks' errors were compared too


def test_frames_are_memory_mapped(tiny_recording: Path) -> None:
    rec = Recording.open(tiny_recording)
    depth, _, conf = rec._depth
    assert isinstance(depth, np.memmap) and isinstance(conf, np.memmap)


def test_summary(tiny_recording: Path) -> None:
    s = Recording.open(tiny_recording).summary()
    assert s["frames"] == 30 and s["image_size"] == [16, 12]
    assert abs(s["frame_rate_hz"] - 30) < 0.1 and abs(s["imu_rate_hz"] - 100) < 0.1
    assert abs(s["gt_rate_hz"] - 120) < 0.1
    assert s["terrain"]["kind"] == "stair_up"


def test_writer_refuses_existing_folder(tiny_recording: Path) -> None:
    meta = tiny_metadata()
    imu, joints, gt, t_frames, frames = tiny_streams(meta)
    with pytest.raises(OutputError):
        write_recording(tiny_recording, meta, imu, joints, gt, t_frames, iter(frames))


def test_writer_leaves_nothing_on_failure(tmp_path: Path) -> None:
    meta = tiny_metadata()
    imu, joints, gt, t_frames, frames = tiny_streams(meta)
    with pytest.raises(RecordingError):
        write_recording(tmp_path / "rec", meta, imu, joints, gt, t_frames, iter(frames[:-1]))
    assert list(tmp_path.iterdir()) == []


def test_tum_round_trip(tmp_path: Path) -> None:
    meta = tiny_metadata()
    _, _, gt, _, _ = tiny_streams(meta)
    traj = gt.trajectories["toe"]
    write_tum(tmp_path / "toe.tum", traj)
    back = read_tum(tmp_path / "toe.tum")
    np.testing.assert_allclose(back.position_m, traj.position_m, atol=1e-6)
    np.testing.assert_allclose(back.timestamp_s, traj.timestamp_s, atol=1e-9)


# --------------------------------------------------------------------------- malformed input
def _copy(src: Path, tmp_path: Path) -> Path:
    dst = tmp_path / "bad"
    shutil.copytree(src, dst)
    return dst


def _edit_csv(path: Path, fn) -> None:
    lines = path.read_text().splitlines()
    path.write_text("\n".join(fn(lines)) + "\n")


def _set_meta(root: Path, fn) -> None:
    p = root / "metadata.yaml"
    d = yaml.safe_load(p.read_text())
    fn(d)
    p.write_text(yaml.safe_dump(d))


CASES = {
    "missing imu": (lambda r: (r / "imu.csv").unlink(), "imu.csv", "missing"),
    "missing metadata": (lambda r: (r / "metadata.yaml").unlink(), "metadata.yaml", "missing"),
    "nan in imu": (
        lambda r: _edit_csv(
            r / "imu.csv",
            lambda ls: ls[:3] + [ls[3].replace(ls[3].split(",")[2], "nan", 1)] + ls[4:],
        ),
        "imu.csv",
        "NaN",
    ),
    "imu backwards": (
        lambda r: _edit_csv(r / "imu.csv", lambda ls: [ls[0], ls[2], ls[1]] + ls[3:]),
        "imu.csv",
        "backwards",
    ),
    "imu duplicate": (
        lambda r: _edit_csv(r / "imu.csv", lambda ls: ls[:2] + [ls[1]] + ls[2:]),
        "imu.csv",
        "duplicated",
    ),
    "imu header": (
        lambda r: _edit_csv(r / "imu.csv", lambda ls: ["t,a,b"] + ls[1:]),
        "imu.csv",
        "missing columns",
    ),
    "imu truncated row": (
        lambda r: _edit_csv(r / "imu.csv", lambda ls: ls[:-1] + [ls[-1][:10]]),
        "imu.csv",
        "malformed",
    ),
    "version": (
        lambda r: _set_meta(r, lambda d: d.update(format_version=99)),
        "metadata.yaml",
        "unknown format version",
    ),
    "meta field": (
        lambda r: _set_meta(r, lambda d: d["camera"].pop("fx_px")),
        "metadata.yaml",
        "camera.fx_px",
    ),
    "rate mismatch": (
        lambda r: _set_meta(r, lambda d: d["imu"].update(rate_hz=200.0)),
        "imu.csv",
        "does not match",
    ),
    "depth unit": (
        lambda r: _set_meta(r, lambda d: d["camera"].update(depth_unit_m=1.0)),
        "depth_mm.npy",
        "wrong depth unit",
    ),
    "truncated npy": (
        lambda r: (r / "depth/depth_mm.npy").write_bytes(
            (r / "depth/depth_mm.npy").read_bytes()[:500]
        ),
        "depth_mm.npy",
        "truncated",
    ),
    "wrong dtype": (
        lambda r: np.save(r / "depth/confidence.npy", np.zeros((30, 12, 16), np.float64)),
        "confidence.npy",
        "dtype",
    ),
    "wrong shape": (
        lambda r: np.save(r / "depth/confidence.npy", np.zeros((29, 12, 16), np.uint8)),
        "confidence.npy",
        "shape",
    ),
    "gt missing body": (lambda r: (r / "groundtruth/toe.tum").unlink(), "toe.tum", "missing"),
    "accel in g": (
        lambda r: _edit_csv(
            r / "imu.csv",
            lambda ls: (
                [ls[0]]
                + [
                    ",".join(
                        [
                            v if i not in (1, 2, 3) else str(float(v) / 9.81)
                            for i, v in enumerate(x.split(","))
                        ]
                    )
                    for x in ls[1:]
                ]
            ),
        ),
        "imu.csv",
        "g units",
    ),
    "joints in degrees": (
        lambda r: _edit_csv(
            r / "joints.csv",
            lambda ls: (
                [ls[0]]
                + [
                    ",".join(
                        [
                            v if i == 0 else str(float(v) * 57.3 * 20)
                            for i, v in enumerate(x.split(","))
                        ]
                    )
                    for x in ls[1:]
                ]
            ),
        ),
        "joints.csv",
        "degrees",
    ),
}


@pytest.mark.parametrize("name", list(CASES))
def test_malformed_recording_names_file(tiny_recording: Path, tmp_path: Path, name: str) -> None:
    mutate, fname, words = CASES[name]
    bad = _copy(tiny_recording, tmp_path)
    mutate(bad)
    with pytest.raises(RecordingError) as exc:
        Recording.open(bad)
    assert fname in str(exc.value) and words in str(exc.value), str(exc.value)


def test_symlink_escape_rejected(tiny_recording: Path, tmp_path: Path) -> None:
    bad = _copy(tiny_recording, tmp_path)
    outside = tmp_path / "outside.csv"
    shutil.copy(bad / "joints.csv", outside)
    (bad / "joints.csv").unlink()
    (bad / "joints.csv").symlink_to(outside)
    with pytest.raises(RecordingError, match="outside the recording"):
        Recording.open(bad)


def test_reader_never_modifies_input(tiny_recording: Path) -> None:
    before = {p: p.stat().st_mtime_ns for p in tiny_recording.rglob("*") if p.is_file()}
    rec = Recording.open(tiny_recording)
    n = sum(1 for _ in rec.frames())
    assert n == rec.num_frames
    after = {p: p.stat().st_mtime_ns for p in tiny_recording.rglob("*") if p.is_file()}
    assert before == after


def test_reader_median_equals_numpy_median() -> None:
    """The reader's median (np.partition, no numpy.ma import) gives np.median's value."""
    from vio_graph.recording.reader import _median

    rng = np.random.default_rng(3)
    for n in (1, 2, 3, 4, 7, 100, 101, 1000):
        for scale in (1e-3, 1.0, 1e6):
            x = rng.normal(size=n) * scale
            assert _median(x) == np.median(x)
    assert np.isnan(_median(np.array([1.0, np.nan, 2.0])))
    assert np.isnan(_median(np.array([])))


def test_frames_read_from_the_files_equal_the_memory_maps(
    tiny_recording: Path, tmp_path: Path
) -> None:
    """frame() reads a frame's bytes from the files with os.preadv (_RowReader: no page
    faults on the maps, nothing to hand back): the same frames bit for bit as reading through
    the memory maps (the path without preadv), for uint16 and float32 depth files (NaN
    pixels included), negative indices, IndexError past either end; a copy of the readers
    in another process opens the files again; a file shrunk after opening is reported."""
    import pickle

    from vio_graph.recording import layout

    f32 = tmp_path / "f32"
    shutil.copytree(tiny_recording, f32)
    counts = np.load(f32 / layout.DEPTH_MM_FILE)
    metres = counts.astype(np.float32) * np.float32(tiny_metadata().camera.depth_unit_m)
    metres[0, 0, :3] = np.nan
    np.save(f32 / layout.DEPTH_M_FILE, metres)
    (f32 / layout.DEPTH_MM_FILE).unlink()
    for root in (tiny_recording, f32):
        rec = Recording.open(root)
        assert rec._row_readers is not None
        plain = Recording.open(root)
        plain.__dict__["_row_readers"] = None  # read through the maps
        n = rec.num_frames
        for k in [*range(n), -1, -n]:
            a, b = rec.frame(k), plain.frame(k)
            assert a.index == b.index == k and a.timestamp_s == b.timestamp_s
            assert a.depth_m.dtype == b.depth_m.dtype and a.depth_m.tobytes() == b.depth_m.tobytes()
            assert a.confidence.tobytes() == b.confidence.tobytes()
            assert a.depth_m.flags.writeable and a.confidence.flags.owndata
        for k in (n, -n - 1):
            with pytest.raises(IndexError):
                rec.frame(k)
        copies = pickle.loads(pickle.dumps(rec._row_readers))
        for copy, reader in zip(copies, rec._row_readers, strict=True):
            assert copy.fd != reader.fd and copy.read(3).tobytes() == reader.read(3).tobytes()
    rec = Recording.open(f32)
    reader = rec._row_readers[0]
    with open(f32 / layout.DEPTH_M_FILE, "r+b") as f:
        f.truncate(reader.offset + 2 * reader.row_bytes)
    assert rec.frame(1).depth_m.shape == counts.shape[1:]
    with pytest.raises(RecordingError, match="frame 2 cannot be read"):
        rec.frame(2)
