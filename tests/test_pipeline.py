"""End to end: simulate a short upstair trial, run every mode, check outputs and accuracy."""

from __future__ import annotations

import json
import re
from pathlib import Path

import numpy as np
import pytest

from vio_graph.config import PipelineConfig
from vio_graph.pipeline import run_recording
from vio_graph.recording import Recording
from vio_graph.recording.tum import read_tum


@pytest.fixture(scope="module")
def run_all(short_upstair: Path, tmp_path_factory: pytest.TempPathFactory):
    out = tmp_path_factory.mktemp("res") / "run"
    return run_recording(
        short_upstair, out, PipelineConfig(), modes=("filter", "smoother", "batch"), progress=False
    )


def test_outputs_written(run_all) -> None:
    out = run_all.out_dir
    for mode in ("filter", "smoother", "batch", "imu_only", "icp_only"):
        for body in ("camera", "knee", "ankle", "heel", "toe"):
            traj = read_tum(out / "trajectories" / f"{mode}_{body}.tum")
            assert len(traj) > 50
    for name in (
        "metrics.json",
        "config.yaml",
        "frames.csv",
        "run.rrd",
        "plots/overview.png",
        "map/map.ply",
        "map/map.pcd",
        "map/steps.json",
        "map/steps.csv",
    ):
        assert (out / name).is_file(), name
    assert not list(out.rglob("*.partial")) and not list(out.rglob(".*.tmp"))


def test_metrics_schema_and_accuracy(run_all) -> None:
    m = json.loads((run_all.out_dir / "metrics.json").read_text())
    for mode in ("filter", "smoother", "batch", "imu_only", "icp_only"):
        for body in ("toe", "camera"):
            for axis in ("x", "z"):
                assert np.isfinite(m["ate_cm"][mode][body][axis])
    assert m["latency_ms"]["frontend"]["median"] > 0
    assert m["latency_ms"]["frontend"]["p95"] >= m["latency_ms"]["frontend"]["median"]
    assert m["latency_ms"]["smoother_update"]["n"] > 0
    # the fused estimates beat IMU dead reckoning; the smoothers stay within a few cm
    assert m["ate_cm"]["filter"]["toe"]["x"] < m["ate_cm"]["imu_only"]["toe"]["x"]
    # floors and treads were in view: the level-surface pitch correction was used
    la = m["filter"]["level_aiding"]
    assert la["accepted"] > 50 and abs(la["final_offset_deg"]) < 5.0
    # the level-aided shank pitch against the true knee-ankle segment (MTi-1 alone: ~1 deg)
    sp = m["shank_pitch_error_deg"]
    assert 0.0 < sp["rms"] < 0.6 and sp["max_abs"] >= sp["rms"]
    # the smoothed modes' legs use their own refined attitude (smoother.leg_attitude)
    by_mode = m["shank_pitch_error_deg_by_mode"]
    assert set(by_mode) == {"smoother", "batch"}
    for mode in ("smoother", "batch"):
        assert 0.0 < by_mode[mode]["rms"] < 0.6
    for mode in ("smoother", "batch"):
        assert m["ate_cm"][mode]["toe"]["x"] < 6.0 and m["ate_cm"][mode]["toe"]["z"] < 6.0
    assert m["map"]["rise_error_mm"] is not None and m["map"]["rise_error_mm"] < 15.0


def test_kinematics_match_ground_truth_joints(short_upstair: Path, run_all) -> None:
    """Knee/ankle/toe from the camera estimate keep the true leg geometry: their offsets from
    the estimated camera match the ground-truth offsets to within the encoder/IMU noise."""
    rec = Recording.open(short_upstair)
    gt = rec.groundtruth.trajectories
    out = run_all.out_dir / "trajectories"
    cam = read_tum(out / "batch_camera.tum")
    for body, tol_m in (("knee", 0.01), ("ankle", 0.02), ("toe", 0.03)):
        est = read_tum(out / f"batch_{body}.tum")
        rel_est = est.xz_m - cam.xz_m
        ref = np.column_stack(
            [
                np.interp(cam.timestamp_s, gt[b].timestamp_s, gt[b].position_m[:, k])
                for b, k in ((body, 0), (body, 2))
            ]
        )
        ref_cam = np.column_stack(
            [
                np.interp(cam.timestamp_s, gt["camera"].timestamp_s, gt["camera"].position_m[:, k])
                for k in (0, 2)
            ]
        )
        err = np.linalg.norm(rel_est - (ref - ref_cam), axis=1)
        assert np.median(err) < tol_m, (body, np.median(err))


def test_refuses_existing_results(short_upstair: Path, run_all) -> None:
    from vio_graph.errors import OutputError

    with pytest.raises(OutputError, match="exists"):
        run_recording(short_upstair, run_all.out_dir, PipelineConfig(), progress=False)


def test_input_recording_unchanged(short_upstair: Path, tmp_path: Path) -> None:
    import hashlib

    def digest() -> dict[str, str]:
        return {
            str(p): hashlib.sha256(p.read_bytes()).hexdigest()
            for p in sorted(short_upstair.rglob("*"))
            if p.is_file()
        }

    before = digest()
    run_recording(short_upstair, tmp_path / "r", PipelineConfig(), visualize=False, progress=False)
    assert digest() == before


def test_rerun_recording_verifies_and_has_the_scene(run_all) -> None:
    """The .rrd loads in rerun's own verifier and holds the entities the docs promise."""
    import subprocess
    import sys

    rerun_cli = Path(sys.executable).parent / "rerun"
    if not rerun_cli.exists():
        pytest.skip("rerun CLI not installed next to this interpreter")
    rrd = run_all.out_dir / "run.rrd"
    ok = subprocess.run(
        [str(rerun_cli), "rrd", "verify", str(rrd)], capture_output=True, text=True, timeout=120
    )
    assert ok.returncode == 0, ok.stderr
    dump = subprocess.run(
        [str(rerun_cli), "rrd", "print", str(rrd)], capture_output=True, text=True, timeout=120
    ).stdout
    for entity in (
        "/world/cloud",
        "/world/slice",
        "/world/features",
        "/world/icp",
        "/world/leg/est",
        "/world/leg/gt",
        "/world/terrain/mesh",
        "/world/map",
        "/world/gt/toe",
        "/world/est/toe",
        "/world/smoother/toe",
    ):
        assert entity in dump, entity
    # rows per entity and its component columns, summed over the chunks
    rows: dict[str, int] = {}
    columns: dict[str, str] = {}
    for m in re.finditer(r"with (\d+) rows .* - (\S+) - data columns: \[(.*)\]", dump):
        rows[m.group(2)] = rows.get(m.group(2), 0) + int(m.group(1))
        columns[m.group(2)] = m.group(3)
    n_frames = run_all.metrics["frames"]
    # the time series (sent as columns): one row per frame each
    for series in ("/plots/status/fused", "/plots/error_cm/toe_x", "/plots/error_cm/toe_z"):
        assert rows.get(series) == n_frames, (series, rows.get(series))
        assert "Scalars:scalars" in columns[series]
    assert rows.get("/world/camera") == n_frames
    assert "Transform3D:translation" in columns["/world/camera"]
    # every frame's depth image under the camera's (static) pinhole, so it is back-projected
    assert rows.get("/world/camera/image/depth") == n_frames
    assert "DepthImage:buffer" in columns["/world/camera/image/depth"]
    assert "Pinhole:image_from_camera" in columns["/world/camera/image"]


def test_recording_without_ground_truth(short_upstair: Path, tmp_path: Path) -> None:
    """A real trial has no motion capture: the run still writes trajectories and a map."""
    import shutil

    rec = tmp_path / "nogt"
    shutil.copytree(short_upstair, rec)
    shutil.rmtree(rec / "groundtruth")
    res = run_recording(rec, tmp_path / "r", PipelineConfig(), visualize=False, progress=False)
    assert "ate_cm" not in res.metrics
    assert read_tum(res.out_dir / "trajectories" / "filter_toe.tum").timestamp_s.size > 50
    assert (res.out_dir / "map" / "map.ply").is_file()
