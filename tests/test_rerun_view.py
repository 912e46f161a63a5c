"""The .rrd written in columns holds what one ``rr.log`` per frame would have written, and the
recording of data/sample has the documented entities with one row per frame."""

from __future__ import annotations

import math
from pathlib import Path
from typing import Any

import numpy as np
import pytest

rr = pytest.importorskip("rerun")
from rerun.chunk import RrdReader  # noqa: E402

from vio_graph.viz import rerun_logger  # noqa: E402
from vio_graph.viz.rerun_logger import Visualizer, _xz_to_xyz  # noqa: E402

ROOT = Path(__file__).resolve().parents[1]
IGNORED = ("rerun.controls.RowId", "log_time", "time")


def rrd_content(path: Path) -> dict[tuple[str, str], list[tuple[Any, Any]]]:
    """(entity, component) -> sorted (time, value) rows of a .rrd, whatever the chunking;
    the recording properties, row ids and rerun's wall-clock ``log_time`` left out."""
    out: dict[tuple[str, str], list[tuple[Any, Any]]] = {}
    for chunk in RrdReader(path).stream():
        if chunk.entity_path == "/__properties":
            continue
        batch = chunk.to_record_batch()
        cols = batch.to_pydict()
        times = cols.get("time", [None] * batch.num_rows)
        for name in batch.schema.names:
            if name not in IGNORED:
                rows = out.setdefault((chunk.entity_path, name), [])
                rows += list(zip(times, cols[name], strict=True))
    return {k: sorted(v, key=repr) for k, v in out.items()}


def rrd_rows(path: Path) -> dict[str, dict[str, Any]]:
    """Per entity: static rows, rows on the time line, component columns."""
    out: dict[str, dict[str, Any]] = {}
    for chunk in RrdReader(path).stream():
        e = out.setdefault(chunk.entity_path, {"static": 0, "rows": 0, "columns": set()})
        e["static" if chunk.is_static else "rows"] += chunk.num_rows
        e["columns"] |= set(chunk.to_record_batch().schema.names) - set(IGNORED)
    return out


def _frames(n: int = 11) -> list[dict[str, Any]]:
    rng = np.random.default_rng(7)
    return [
        {
            "t": 0.1 + i / 30.0,
            "depth": rng.uniform(0.2, 2.0, (6, 8)).astype(np.float32),
            "cloud": rng.normal(size=(int(rng.integers(0, 5)), 3)),
            "slice": rng.normal(size=(int(rng.integers(1, 6)), 2)),
            "icp": rng.normal(size=(int(rng.integers(0, 4)), 2, 2)),
            "leg": rng.normal(size=(5, 2)),
            "warn": bool(i % 4 == 0),
            "err": float(rng.normal()),
        }
        for i in range(n)
    ]


def _log_frames(viz: Visualizer, frames: list[dict[str, Any]]) -> None:
    K = np.array([[100.0, 0, 4], [0, 100.0, 3], [0, 0, 1]])
    viz.log_terrain(np.zeros((3, 3)), np.array([[0, 1, 2]]), np.array([[0.0, 0.0], [1.0, 0.1]]))
    for i, f in enumerate(frames):
        viz.set_time(f["t"])
        viz.log_camera(np.array([i, 0.0, 1.0]), np.eye(3), K, 8, 6, f["depth"])
        if i % 3 == 0:
            viz.log_cloud(f["cloud"])
        viz.log_sagittal("slice", f["slice"], 0.002, (250, 200, 0))
        viz.log_segments("icp", f["icp"][:, 0], f["icp"][:, 1])
        viz.log_segments(
            "clearance", f["leg"][:1], f["leg"][1:2], (255, 0, 160) if f["warn"] else None
        )
        viz.log_leg("est", f["leg"])
        viz.log_scalar("error_cm/toe_x", f["err"])
    viz.log_sagittal("map", frames[0]["slice"], 0.003, (90, 90, 255))
    viz.log_path("est/toe", frames[1]["slice"])
    viz.close()


def _reference(path: Path, frames: list[dict[str, Any]]) -> None:
    """The same frames through one ``rr.log`` per entity and frame (the way of the logger
    before it sent columns)."""
    rec = rr.RecordingStream("vio_graph")
    rec.save(str(path))
    rec.log("world", rr.ViewCoordinates.RIGHT_HAND_Z_UP, static=True)
    K = np.array([[100.0, 0, 4], [0, 100.0, 3], [0, 0, 1]])
    rec.log(
        "world/terrain/mesh",
        rr.Mesh3D(
            vertex_positions=np.zeros((3, 3), np.float32),
            triangle_indices=np.array([[0, 1, 2]], np.uint32),
            albedo_factor=[0.75, 0.75, 0.78, 0.6],
        ),
        static=True,
    )
    rec.log(
        "world/terrain/profile",
        rr.LineStrips3D([_xz_to_xyz(np.array([[0.0, 0.0], [1.0, 0.1]]))], colors=[(60, 60, 60)]),
        static=True,
    )
    rec.log(
        "world/camera/image",
        rr.Pinhole(image_from_camera=K, width=8, height=6, image_plane_distance=0.1),
        static=True,
    )

    def strips(name, a, b, color, radius=0.001):
        s = np.stack([_xz_to_xyz(a), _xz_to_xyz(b)], axis=1)
        rec.log(name, rr.LineStrips3D(s, colors=[color], radii=radius))

    for i, f in enumerate(frames):
        rec.set_time("time", duration=f["t"])
        rec.log("world/camera", rr.Transform3D(translation=[i, 0.0, 1.0], mat3x3=np.eye(3)))
        rec.log("world/camera/image/depth", rr.DepthImage(f["depth"], meter=1.0))
        if i % 3 == 0:
            pts = f["cloud"].astype(np.float32)
            rec.log("world/cloud", rr.Points3D(pts, radii=0.002, colors=[(120, 140, 200)]))
        rec.log(
            "world/slice",
            rr.Points3D(_xz_to_xyz(f["slice"]), radii=0.002, colors=[(250, 200, 0)]),
        )
        strips("world/icp", f["icp"][:, 0], f["icp"][:, 1], (255, 0, 255))
        color = (255, 0, 160) if f["warn"] else (255, 0, 255)
        strips("world/clearance", f["leg"][:1], f["leg"][1:2], color)
        rec.log(
            "world/leg/est",
            rr.LineStrips3D([_xz_to_xyz(f["leg"])], colors=[(230, 120, 20)], radii=0.006),
        )
        rec.log("plots/error_cm/toe_x", rr.Scalars(f["err"]))
    rec.log(
        "world/map",
        rr.Points3D(_xz_to_xyz(frames[0]["slice"]), radii=0.003, colors=[(90, 90, 255)]),
    )
    rec.log(
        "world/est/toe",
        rr.LineStrips3D([_xz_to_xyz(frames[1]["slice"])], colors=[(230, 120, 20)], radii=0.0015),
        static=True,
    )
    rec.flush()
    rec.disconnect()


def test_columns_hold_what_per_frame_logging_held(tmp_path: Path, monkeypatch) -> None:
    """Every entity, component and value of the per-frame ``rr.log`` reference, across several
    flushes (4 rows each) and with frames that have no ICP match or cloud point."""
    monkeypatch.setattr(rerun_logger, "FLUSH_ROWS", 4)
    frames = _frames()
    viz = Visualizer(tmp_path / "cols.rrd")
    _log_frames(viz, frames)
    _reference(tmp_path / "ref.rrd", frames)
    got, want = rrd_content(tmp_path / "cols.rrd"), rrd_content(tmp_path / "ref.rrd")
    assert sorted(got) == sorted(want)
    for key in want:
        assert got[key] == want[key], key
    assert not list(tmp_path.glob("*.partial"))


def test_sample_recording_entities_and_lengths(tmp_path: Path) -> None:
    """data/sample, filter mode: the entity paths of the docs, one row per frame for the time
    series, the camera, the depth image, slice, ICP and leg links; a cloud every third frame."""
    from vio_graph.config import PipelineConfig
    from vio_graph.pipeline import run_recording

    res = run_recording(ROOT / "data" / "sample", tmp_path / "r", PipelineConfig(), progress=False)
    n = res.metrics["frames"]
    rows = rrd_rows(res.out_dir / "run.rrd")
    expected = {
        "/__properties",
        "/world",
        "/world/terrain/mesh",
        "/world/terrain/profile",
        "/world/camera",
        "/world/camera/image",
        "/world/camera/image/depth",
        "/world/cloud",
        "/world/slice",
        "/world/features",
        "/world/icp",
        "/world/clearance",
        "/world/leg/est",
        "/world/leg/gt",
        "/world/map",
        *(f"/world/gt/{b}" for b in ("camera", "toe", "knee")),
        *(f"/world/{m}/{b}" for m in ("est", "imu_only", "icp_only") for b in ("camera", "toe")),
        "/plots/status/fused",
        "/plots/error_cm/toe_x",
        "/plots/error_cm/toe_z",
        "/plots/clearance_cm/estimate",
        "/plots/clearance_cm/sigma",
        "/plots/clearance_cm/predicted_min",
    }
    assert set(rows) == expected
    for entity in (
        "/plots/status/fused",
        "/plots/error_cm/toe_x",
        "/plots/error_cm/toe_z",
        "/world/camera",
        "/world/camera/image/depth",
        "/world/slice",
        "/world/leg/est",
        "/world/leg/gt",
    ):
        assert rows[entity]["rows"] == n, entity
    stride = PipelineConfig().output.cloud_every_n_frames
    assert rows["/world/cloud"]["rows"] == math.ceil(n / stride)
    assert 0 < rows["/world/icp"]["rows"] <= n
    assert rows["/world/camera/image/depth"]["columns"] >= {"DepthImage:buffer", "DepthImage:meter"}
    assert "Pinhole:image_from_camera" in rows["/world/camera/image"]["columns"]
    assert rows["/world/camera/image"]["static"] == 1 and rows["/world/est/toe"]["static"] == 1


def _depth_reference(path: Path, images: list[Any], meter: float) -> None:
    """The depth images through one ``rr.log`` each (rerun's own DepthImage conversion)."""
    rec = rr.RecordingStream("vio_graph")
    rec.save(str(path))
    for i, d in enumerate(images):
        rec.set_time("time", duration=0.1 + i / 30.0)
        rec.log("world/camera/image/depth", rr.DepthImage(d, meter=meter))
    rec.flush()
    rec.disconnect()


def _depth_rows(path: Path) -> list[tuple[Any, Any]]:
    content = rrd_content(path)
    return [
        (key[1], rows) for key, rows in sorted(content.items()) if key[0].endswith("image/depth")
    ]


def test_depth_sent_as_the_recorded_integers(tmp_path: Path, monkeypatch) -> None:
    """Depth images that are recorded millimetres (as the reader makes them: float32 count x
    float32 unit, 0 = invalid) go to rerun as those uint16 counts with meter 1000, what
    ``rr.DepthImage(counts, meter=1000)`` writes, across flushes; the viewer's metres (count /
    meter) are the estimator's to float32 rounding. Images that are not such counts (or
    without a unit) go as float32 metres with meter 1, as before."""
    monkeypatch.setattr(rerun_logger, "FLUSH_ROWS", 4)
    rng = np.random.default_rng(3)
    counts = [rng.integers(0, 2400, (6, 8)).astype(np.uint16) for _ in range(9)]
    counts[2][:] = 0  # an empty frame
    unit = 0.001
    depth_m = [c.astype(np.float32) * np.float32(unit) for c in counts]
    K = np.array([[100.0, 0, 4], [0, 100.0, 3], [0, 0, 1]])

    def log(path: Path, images: list[Any], unit_m: float | None) -> None:
        viz = Visualizer(path)
        for i, d in enumerate(images):
            viz.set_time(0.1 + i / 30.0)
            viz.log_camera(np.zeros(3), np.eye(3), K, 8, 6, d, unit_m)
        viz.close()

    log(tmp_path / "mm.rrd", depth_m, unit)
    _depth_reference(tmp_path / "mm_ref.rrd", counts, 1000.0)
    got = _depth_rows(tmp_path / "mm.rrd")
    assert got == _depth_rows(tmp_path / "mm_ref.rrd")
    meters = [m for name, rows in got if name.endswith("meter") for _, m in rows]
    assert len(meters) == len(counts) and set(np.ravel(meters).tolist()) == {1000.0}
    for c, d in zip(counts, depth_m, strict=True):
        np.testing.assert_allclose(c / np.float32(1000.0), d, rtol=2e-7, atol=0)

    floats = [rng.uniform(0.2, 2.0, (6, 8)).astype(np.float32) for _ in range(5)]
    for name, images, unit_m in (("f", floats, unit), ("none", depth_m, None)):
        log(tmp_path / f"{name}.rrd", images, unit_m)
        _depth_reference(tmp_path / f"{name}_ref.rrd", images, 1.0)
        assert _depth_rows(tmp_path / f"{name}.rrd") == _depth_rows(tmp_path / f"{name}_ref.rrd")


def test_depth_image_conversion_is_exact_or_declined() -> None:
    """``_depth_image``: counts only when they give back the float32 metres bit for bit (a
    value off the millimetre grid, a negative, a NaN or a count beyond uint16 declines); the
    float32 copy is never the caller's buffer."""
    from vio_graph.viz.rerun_logger import _depth_image

    d = np.array([[0, 1, 2047, 65535]], np.uint16).astype(np.float32) * np.float32(0.001)
    img, meter = _depth_image(d, 0.001)
    assert img.dtype == np.uint16 and meter == 1000.0
    assert img.tolist() == [[0, 1, 2047, 65535]]
    for bad in (d + np.float32(1e-4), -d, np.where(d > 1, np.nan, d), d * 2):
        img, meter = _depth_image(bad.astype(np.float32), 0.001)
        assert img.dtype == np.float32 and meter == 1.0 and img is not bad
        np.testing.assert_array_equal(img, bad)
    img, _ = _depth_image(d, None)
    assert img.dtype == np.float32 and img is not d


class _Calls:
    """A visualizer that accepts every call and does nothing (an active view's target)."""

    def __getattr__(self, name: str) -> Any:
        return lambda *args, **kwargs: None


def test_true_leg_at_the_frame_stamps_equals_the_per_frame_interpolation() -> None:
    """The view's true leg comes from one table interpolated at every frame stamp (scene);
    each row is the per-frame interpolation bit for bit, and a stamp that is not the frame's
    own is interpolated on its own."""
    from vio_graph.config import PipelineConfig
    from vio_graph.estimator import RigGeometry
    from vio_graph.recording.reader import Recording
    from vio_graph.viz.run_view import RunView, true_leg

    rec = Recording.open(ROOT / "data" / "sample")
    gt = rec.groundtruth
    assert gt is not None
    t = np.asarray(rec.frame_timestamps_s, dtype=float)
    between = np.concatenate([t[:-1] + np.diff(t) / 3, [t[0] - 1.0, t[-1] + 1.0]])
    for times in (t, between):
        table = true_leg(gt, times)
        assert table.shape == (times.size, 5, 2)
        for k, tk in enumerate(times):
            one = true_leg(gt, float(tk))
            assert np.array_equal(table[k].view(np.int64), one.view(np.int64))
            bodies = ("knee", "ankle", "heel", "toe", "ankle")
            assert np.array_equal(one, [gt.trajectories[b].xz_at(float(tk)) for b in bodies])
    view = RunView(_Calls(), RigGeometry.from_metadata(rec.metadata), gt, PipelineConfig().output)
    view.scene(rec)
    assert np.shares_memory(view._true_leg(3, float(t[3])), view._true_legs[1])
    off = float(t[3]) + 1e-3
    assert np.array_equal(view._true_leg(3, off), true_leg(gt, off))
    assert not np.array_equal(view._true_leg(3, off), view._true_leg(3, float(t[3])))
