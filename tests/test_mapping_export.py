"""Round trips of the mapping exports (PLY, PCD, JSON, CSV) and the PNG plot."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest

from tests.test_mapping_synth import camera_track, observe, obstacle_profile, stair_profile
from vio_graph.errors import OutputError
from vio_graph.evaluation.map_accuracy import compare_to_truth
from vio_graph.mapping.export import (
    CSV_COLUMNS,
    export_map,
    read_geometry_csv,
    read_geometry_json,
    read_point_cloud_xz,
    write_geometry_csv,
    write_geometry_json,
    write_point_cloud,
)
from vio_graph.mapping.local_map import TerrainMap2D
from vio_graph.mapping.steps import TerrainGeometry, estimate_terrain_geometry
from vio_graph.recording.metadata import TerrainInfo


def _scene(terrain: TerrainInfo, x_end_m: float) -> tuple[TerrainMap2D, TerrainGeometry]:
    cams = camera_track(terrain, -0.3, x_end_m, step_m=0.02)
    profiles = observe(terrain, cams, 0.0025, np.random.default_rng(0))
    terrain_map = TerrainMap2D()
    for i, (cam, prof) in enumerate(zip(cams, profiles, strict=True)):
        terrain_map.add_keyframe(0.1 * i, cam, prof)
    geometry = estimate_terrain_geometry(terrain_map.points_xz_m, terrain_map.point_counts)
    return terrain_map, geometry


@pytest.fixture(scope="module")
def stair_scene() -> tuple[TerrainInfo, TerrainMap2D, TerrainGeometry]:
    terrain = stair_profile(0.147, 0.28, 5, up=False)
    return (terrain, *_scene(terrain, 1.8))


@pytest.fixture(scope="module")
def obstacle_scene() -> tuple[TerrainInfo, TerrainMap2D, TerrainGeometry]:
    terrain = obstacle_profile(0.14, 0.13)
    return (terrain, *_scene(terrain, 1.0))


@pytest.mark.parametrize("suffix", [".ply", ".pcd"])
def test_point_cloud_round_trip(tmp_path: Path, stair_scene, suffix: str) -> None:
    _, terrain_map, _ = stair_scene
    points = terrain_map.points_xz_m
    path = write_point_cloud(tmp_path / f"map{suffix}", points)
    back = read_point_cloud_xz(path)
    assert back.shape == points.shape
    np.testing.assert_allclose(back, points, atol=1e-6, rtol=0)
    assert [p.name for p in tmp_path.iterdir()] == [f"map{suffix}"]  # no temp files left


def test_point_cloud_errors(tmp_path: Path) -> None:
    with pytest.raises(OutputError):
        write_point_cloud(tmp_path / "map.xyz", np.zeros((3, 2)))
    with pytest.raises(OutputError):
        read_point_cloud_xz(tmp_path / "missing.ply")
    off_plane = tmp_path / "off.ply"
    from vio_graph.o3d import open3d

    o3d = open3d()
    cloud = o3d.geometry.PointCloud()
    cloud.points = o3d.utility.Vector3dVector(np.array([[0.0, 0.2, 0.0], [1.0, 0.0, 1.0]]))
    o3d.io.write_point_cloud(str(off_plane), cloud)
    with pytest.raises(OutputError, match="y = 0"):
        read_point_cloud_xz(off_plane)


def _assert_same_features(a: TerrainGeometry, steps, obstacles) -> None:
    assert len(a.steps) == len(steps) and len(a.obstacles) == len(obstacles)
    for s, t in zip(a.steps, steps, strict=True):
        assert (s.index, s.direction, s.riser_observed, s.tread_m) == (
            t.index,
            t.direction,
            t.riser_observed,
            t.tread_m,
        )
        assert (s.rise_m, s.rise_std_m, s.lower_z_m, s.upper_z_m, s.tread_std_m) == (
            t.rise_m,
            t.rise_std_m,
            t.lower_z_m,
            t.upper_z_m,
            t.tread_std_m,
        )
        np.testing.assert_array_equal(s.nosing_xz_m, t.nosing_xz_m)
        np.testing.assert_array_equal(s.nosing_std_xz_m, t.nosing_std_xz_m)
    for o, p in zip(a.obstacles, obstacles, strict=True):
        for name in o.__dataclass_fields__:
            np.testing.assert_array_equal(getattr(o, name), getattr(p, name))


@pytest.mark.parametrize("scene", ["stair_scene", "obstacle_scene"])
def test_json_round_trip(tmp_path: Path, scene: str, request: pytest.FixtureRequest) -> None:
    terrain, _, geometry = request.getfixturevalue(scene)
    comparison = compare_to_truth(geometry, terrain)
    path = write_geometry_json(tmp_path / "steps.json", geometry, comparison)
    doc = json.loads(path.read_text())
    assert doc["kind"] == terrain.kind
    assert doc["comparison"]["kind_correct"] is True
    assert doc["summary"]["n_steps"] == len(geometry.steps)
    back = read_geometry_json(path)
    assert back.kind is geometry.kind
    _assert_same_features(back, geometry.steps, geometry.obstacles)
    assert back.levels == geometry.levels and back.risers == geometry.risers


@pytest.mark.parametrize("scene", ["stair_scene", "obstacle_scene"])
def test_csv_round_trip(tmp_path: Path, scene: str, request: pytest.FixtureRequest) -> None:
    _, _, geometry = request.getfixturevalue(scene)
    path = write_geometry_csv(tmp_path / "steps.csv", geometry)
    lines = path.read_text().splitlines()
    assert lines[0] == ",".join(CSV_COLUMNS)
    assert len(lines) == 1 + len(geometry.steps) + len(geometry.obstacles)
    steps, obstacles = read_geometry_csv(path)
    _assert_same_features(geometry, steps, obstacles)


def test_malformed_files_raise_output_error(tmp_path: Path) -> None:
    bad_json = tmp_path / "bad.json"
    bad_json.write_text("{not json")
    with pytest.raises(OutputError):
        read_geometry_json(bad_json)
    bad_json.write_text(json.dumps({"format": "something else", "version": 1}))
    with pytest.raises(OutputError, match="not a"):
        read_geometry_json(bad_json)
    bad_csv = tmp_path / "bad.csv"
    bad_csv.write_text("a,b\n1,2\n")
    with pytest.raises(OutputError, match="header"):
        read_geometry_csv(bad_csv)
    row = ["step", "0", "sideways"] + ["1.0"] * (len(CSV_COLUMNS) - 4) + ["1"]
    bad_csv.write_text(",".join(CSV_COLUMNS) + "\n" + ",".join(row) + "\n")
    with pytest.raises(OutputError, match="line 2"):
        read_geometry_csv(bad_csv)


def test_export_map_writes_every_file(tmp_path: Path, stair_scene) -> None:
    terrain, terrain_map, geometry = stair_scene
    cams = np.array([kf.camera_xz_m for kf in terrain_map.keyframes])
    written = export_map(
        tmp_path / "out", terrain_map.points_xz_m, geometry, terrain, camera_xz_m=cams
    )
    assert sorted(written) == ["csv", "json", "pcd", "ply", "png"]
    png = written["png"].read_bytes()
    assert png[:8] == b"\x89PNG\r\n\x1a\n" and len(png) > 10_000
    assert sorted(p.name for p in (tmp_path / "out").iterdir()) == [
        "map.pcd",
        "map.ply",
        "map.png",
        "steps.csv",
        "steps.json",
    ]
    with pytest.raises(OutputError):
        export_map(tmp_path, terrain_map.points_xz_m, geometry, formats=("ply", "las"))


def test_map_png_is_the_default_encodings_pixels(tmp_path: Path, stair_scene) -> None:
    """The map figure is written at zlib level PNG_COMPRESS_LEVEL (save_png) instead of
    matplotlib's default: decoded, the same pixels and the same text chunks (Software) as
    the figure saved the default way; only the compression differs."""
    from PIL import Image

    from vio_graph.mapping.export import map_figure
    from vio_graph.viz.plots import PNG_COMPRESS_LEVEL

    terrain, terrain_map, geometry = stair_scene
    cams = np.array([kf.camera_xz_m for kf in terrain_map.keyframes])
    written = export_map(
        tmp_path / "out", terrain_map.points_xz_m, geometry, terrain, camera_xz_m=cams
    )
    default = tmp_path / "default.png"
    map_figure(terrain_map.points_xz_m, geometry, terrain, cams).savefig(default, format="png")
    assert PNG_COMPRESS_LEVEL != 6  # (Pillow's default: the test would compare nothing)
    assert written["png"].read_bytes() != default.read_bytes()
    with Image.open(written["png"]) as ours, Image.open(default) as theirs:
        assert ours.size == theirs.size and ours.mode == theirs.mode
        assert ours.text == theirs.text
        np.testing.assert_array_equal(np.asarray(ours), np.asarray(theirs))
