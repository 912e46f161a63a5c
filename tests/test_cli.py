"""The ``vio-graph`` command line: exit codes, one-line errors, refusals, interrupts.

Most tests call the console-script entry point ``vio_graph.cli.main`` in-process (fast); two run
the installed ``vio-graph`` in a subprocess: a bad recording (no traceback) and a ``run`` that
receives SIGTERM (exit 143, complete files only, a note of what was completed).
"""

from __future__ import annotations

import hashlib
import json
import os
import signal
import subprocess
import sys
import time
from pathlib import Path

import pytest
import yaml

from tests.conftest import tiny_metadata, tiny_streams
from vio_graph.cli import main
from vio_graph.io_utils import remove_temporaries
from vio_graph.recording import Recording, write_recording
from vio_graph.recording.tum import read_tum

VIO_GRAPH = Path(sys.executable).with_name("vio-graph")


def _cli(
    args: list[str], capsys: pytest.CaptureFixture[str], monkeypatch: pytest.MonkeyPatch
) -> tuple[int, str, str]:
    """Run the entry point in-process: (exit code, stdout, stderr)."""
    monkeypatch.setattr(sys, "argv", ["vio-graph", *args])
    previous = signal.getsignal(signal.SIGTERM)
    code = 0
    try:
        main()
    except SystemExit as exc:
        code = exc.code if isinstance(exc.code, int) else 1
    finally:
        signal.signal(signal.SIGTERM, previous)  # main() installs its own handler
    out, err = capsys.readouterr()
    return code, out, err


def _checksums(folder: Path) -> dict[str, str]:
    return {
        str(p.relative_to(folder)): hashlib.sha256(p.read_bytes()).hexdigest()
        for p in sorted(folder.rglob("*"))
        if p.is_file()
    }


def _temporaries(folder: Path) -> list[Path]:
    return [
        p
        for p in folder.rglob("*")
        if p.name.startswith(".") or p.name.endswith((".partial", ".tmp"))
    ]


# --------------------------------------------------------------------------- info
def test_info_good(tiny_recording: Path, capsys, monkeypatch) -> None:
    code, out, err = _cli(["info", str(tiny_recording)], capsys, monkeypatch)
    assert code == 0, err
    assert "(format v1, valid)" in out and "30 at 30.00 Hz, 16 x 12 px" in out
    assert "Traceback" not in out + err


def test_info_json_keys(tiny_recording: Path, capsys, monkeypatch) -> None:
    code, out, _ = _cli(["info", str(tiny_recording), "--json"], capsys, monkeypatch)
    assert code == 0
    s = json.loads(out)
    for key in ("duration_s", "frames", "frame_rate_hz", "imu_rate_hz", "gt_rate_hz", "image_size"):
        assert key in s, key
    # the tiny recording: 1 s, 30 frames of 16 x 12 px at 30 Hz, IMU 100 Hz, ground truth 120 Hz
    assert s["frames"] == 30 and s["image_size"] == [16, 12]
    assert s["frame_rate_hz"] == pytest.approx(30.0, abs=0.01)
    assert s["imu_rate_hz"] == pytest.approx(100.0, abs=0.01)
    assert s["gt_rate_hz"] == pytest.approx(120.0, abs=0.01)
    assert s["duration_s"] == pytest.approx(0.99, abs=0.01)  # last IMU sample at 0.99 s


def _nan_in_imu(root: Path) -> None:
    lines = (root / "imu.csv").read_text().splitlines()
    cells = lines[5].split(",")
    cells[2] = "nan"
    lines[5] = ",".join(cells)
    (root / "imu.csv").write_text("\n".join(lines) + "\n")


def _version(root: Path) -> None:
    d = yaml.safe_load((root / "metadata.yaml").read_text())
    d["format_version"] = 7
    (root / "metadata.yaml").write_text(yaml.safe_dump(d))


BAD = {
    "missing imu": (lambda r: (r / "imu.csv").unlink(), "imu.csv", "missing"),
    "nan": (_nan_in_imu, "imu.csv", "NaN"),
    "version": (_version, "metadata.yaml", "unknown format version"),
    "truncated npy": (
        lambda r: (r / "depth/depth_mm.npy").write_bytes(
            (r / "depth/depth_mm.npy").read_bytes()[:300]
        ),
        "depth_mm.npy",
        "truncated",
    ),
}


@pytest.mark.parametrize("case", list(BAD))
def test_info_bad_recording_one_line(tiny_recording: Path, capsys, monkeypatch, case: str) -> None:
    mutate, fname, words = BAD[case]
    mutate(tiny_recording)
    code, out, err = _cli(["info", str(tiny_recording)], capsys, monkeypatch)
    assert code == 1
    assert out == ""
    lines = err.strip().splitlines()
    assert len(lines) == 1, err
    assert lines[0].startswith("error: ") and fname in lines[0] and words in lines[0], err
    assert "Traceback" not in err


def test_info_missing_folder(tmp_path: Path, capsys, monkeypatch) -> None:
    code, _, err = _cli(["info", str(tmp_path / "nope")], capsys, monkeypatch)
    assert code == 1 and "recording folder not found" in err and "nope" in err


def test_installed_script_bad_recording_no_traceback(tiny_recording: Path) -> None:
    (tiny_recording / "joints.csv").write_text("timestamp_s,thigh_pitch_rad,knee_rad,ankle_rad\n")
    r = subprocess.run(
        [str(VIO_GRAPH), "info", str(tiny_recording)], capture_output=True, text=True, timeout=120
    )
    assert r.returncode == 1
    assert "Traceback" not in r.stderr + r.stdout
    errors = [line for line in r.stderr.splitlines() if line.startswith("error:")]
    assert len(errors) == 1 and "joints.csv" in errors[0] and "no data rows" in errors[0]


# --------------------------------------------------------------------------- refusals
def test_simulate_refuses_existing_out(tmp_path: Path, capsys, monkeypatch) -> None:
    out = tmp_path / "rec"
    out.mkdir()
    (out / "keep.txt").write_text("mine")
    code, _, err = _cli(["simulate", "--scenario", "level", "--out", str(out)], capsys, monkeypatch)
    assert code == 1 and "already exists" in err and "--overwrite" in err
    assert [p.name for p in out.iterdir()] == ["keep.txt"]


def test_simulate_names_the_scenario_and_the_field_when_the_terrain_is_too_short(
    tmp_path: Path, capsys, monkeypatch
) -> None:
    scenario = tmp_path / "long_level.yaml"
    scenario.write_text("name: long_level\nduration_s: 20.0\nterrain: {kind: level}\n")
    out = tmp_path / "rec"
    code, _, err = _cli(
        ["simulate", "--scenario", str(scenario), "--out", str(out)], capsys, monkeypatch
    )
    assert code == 1 and str(scenario) in err and "terrain too short" in err
    assert "terrain.exit_length_m" in err and "m per extra second" in err
    assert not out.exists()  # nothing half-written


def test_run_refuses_nonempty_results(
    tiny_recording: Path, tmp_path: Path, capsys, monkeypatch
) -> None:
    out = tmp_path / "results"
    out.mkdir()
    (out / "old.json").write_text("{}")
    code, _, err = _cli(["run", str(tiny_recording), "--out", str(out)], capsys, monkeypatch)
    assert code == 1 and "not empty" in err and "--overwrite" in err
    assert [p.name for p in out.iterdir()] == ["old.json"]


@pytest.mark.parametrize("mode", ["bogus", "filter,nonsense", ","])
def test_run_bad_mode(tiny_recording: Path, tmp_path: Path, capsys, monkeypatch, mode: str) -> None:
    out = tmp_path / "results"
    code, _, err = _cli(
        ["run", str(tiny_recording), "--out", str(out), "--mode", mode], capsys, monkeypatch
    )
    assert code == 1 and "--mode" in err and "Traceback" not in err
    assert not out.exists()  # refused before anything was written


def test_usage_errors_exit_2_without_traceback(capsys, monkeypatch) -> None:
    for args in (["info"], ["info", ".", "--bogus"], ["frobnicate"], []):
        code, _, err = _cli(args, capsys, monkeypatch)
        assert code == 2, (args, err)
        assert "Traceback" not in err


def test_help_exits_0(capsys, monkeypatch) -> None:
    code, out, _ = _cli(["info", "--help"], capsys, monkeypatch)
    assert code == 0 and "Validate a recording" in out


# --------------------------------------------------------------------------- outputs
def _two_second_recording(root: Path) -> Path:
    meta = tiny_metadata().model_copy(update={"duration_s": 2.0})
    imu, joints, gt, t_frames, frames = tiny_streams(meta, duration_s=2.0)
    return write_recording(root, meta, imu, joints, gt, t_frames, iter(frames))


def test_run_interrupted_in_process(tmp_path: Path, monkeypatch) -> None:
    """A KeyboardInterrupt while the outputs are written: complete files only, the rerun
    stream's temporary deleted, and RunInterrupted lists exactly the completed files."""
    from vio_graph import pipeline
    from vio_graph.config import load_config

    rec = _two_second_recording(tmp_path / "rec")
    before = _checksums(rec)
    real_write = pipeline.write_frames_csv

    def write_then_interrupt(path: Path, lg) -> Path:
        real_write(path, lg)
        (path.parent / ".frames.csv.abcd1234.tmp").write_text("half")  # a stale temporary
        raise KeyboardInterrupt

    monkeypatch.setattr(pipeline, "write_frames_csv", write_then_interrupt)
    out = tmp_path / "out"
    with pytest.raises(pipeline.RunInterrupted) as exc:
        pipeline.run_recording(rec, out, load_config(), progress=False, visualize=True)
    assert exc.value.signum == signal.SIGINT
    completed = sorted(str(p.relative_to(out)) for p in exc.value.completed)
    written = sorted(str(p.relative_to(out)) for p in out.rglob("*") if p.is_file())
    assert "config.yaml" in completed and "trajectories/filter_toe.tum" in completed
    assert written == sorted([*completed, "frames.csv"])  # renamed into place, then interrupted
    assert _temporaries(out) == []
    assert not (out / "run.rrd").exists()
    assert _checksums(rec) == before


def test_run_complete_leaves_input_untouched(tmp_path: Path, capsys, monkeypatch) -> None:
    rec = _two_second_recording(tmp_path / "rec")
    before = _checksums(rec)
    mtimes = {p: p.stat().st_mtime_ns for p in rec.rglob("*")}
    out = tmp_path / "out"
    code, out_text, err = _cli(
        ["run", str(rec), "--out", str(out), "--no-rerun"], capsys, monkeypatch
    )
    assert code == 0, err
    assert _checksums(rec) == before
    assert {p: p.stat().st_mtime_ns for p in rec.rglob("*")} == mtimes
    assert _temporaries(out) == []
    metrics = json.loads((out / "metrics.json").read_text())
    assert metrics["frames"] == 60
    mode = (out / "metrics.json").stat().st_mode & 0o777
    assert mode & 0o044 == 0o044 & ~_umask()  # not mkstemp's 0600: readable like any output


def test_run_no_plots_writes_the_same_results_without_figures(
    tmp_path: Path, capsys, monkeypatch
) -> None:
    """--no-plots leaves out plots/ and map/map.png; trajectories and the map's files are the
    same bytes as with the figures (frames.csv holds timings, so it is not compared)."""
    rec = _two_second_recording(tmp_path / "rec")
    runs = {}
    for name, extra in (("plots", []), ("no_plots", ["--no-plots"])):
        out = tmp_path / name
        args = ["run", str(rec), "--out", str(out), "--no-rerun", *extra]
        code, _, err = _cli(args, capsys, monkeypatch)
        assert code == 0, err
        runs[name] = {
            str(p.relative_to(out)): p.read_bytes() for p in out.rglob("*") if p.is_file()
        }
    with_plots, without = runs["plots"], runs["no_plots"]
    pngs = {k for k in with_plots if k.endswith(".png")}
    assert "plots/overview.png" in pngs and "map/map.png" in pngs
    assert not any(k.endswith(".png") for k in without)
    assert set(without) == set(with_plots) - pngs
    for k in without:
        if k.endswith((".tum", ".ply", ".pcd")) or k.startswith("map/steps."):
            assert without[k] == with_plots[k], k


def _umask() -> int:
    mask = os.umask(0)
    os.umask(mask)
    return mask


def test_remove_temporaries_only_touches_temporary_names(tmp_path: Path) -> None:
    keep = [".gitignore", "notes.txt", ".hidden.txt", "map.ply"]
    drop = [".metrics.json.k2j3h4g5.tmp", ".map.ply.ab_cd123.ply", ".run.rrd.partial"]
    for name in keep + drop:
        (tmp_path / "sub").mkdir(exist_ok=True)
        (tmp_path / "sub" / name).write_text("x")
    removed = remove_temporaries(tmp_path)
    assert sorted(p.name for p in removed) == sorted(drop)
    assert sorted(p.name for p in (tmp_path / "sub").iterdir()) == sorted(keep)


# --------------------------------------------------------------------------- SIGTERM
@pytest.fixture(scope="module")
def level_recording(tmp_path_factory: pytest.TempPathFactory) -> Path:
    """A short simulated level-walking trial (2 s, 60 frames at 224 x 172)."""
    from vio_graph.sim import load_scenario, simulate

    config = load_scenario("level").model_copy(update={"duration_s": 2.0})
    return simulate(config, 1, tmp_path_factory.mktemp("level") / "rec")


@pytest.mark.slow
def test_sigterm_during_run(level_recording: Path, tmp_path: Path) -> None:
    before = _checksums(level_recording)
    out = tmp_path / "results"
    env = {**os.environ, "PYTHONUNBUFFERED": "1"}
    proc = subprocess.Popen(
        [str(VIO_GRAPH), "run", str(level_recording), "--out", str(out)],
        stdout=subprocess.PIPE,
        stderr=subprocess.PIPE,
        text=True,
        env=env,
    )
    try:
        deadline = time.monotonic() + 120
        while not (out / "config.yaml").exists():  # the first output: the replay starts now
            assert proc.poll() is None, proc.communicate()
            assert time.monotonic() < deadline, "run did not start"
            time.sleep(0.02)
        time.sleep(0.3)
        proc.send_signal(signal.SIGTERM)
        stdout, stderr = proc.communicate(timeout=120)
    finally:
        if proc.poll() is None:
            proc.kill()
    assert proc.returncode == 143, stderr
    assert "Traceback" not in stderr + stdout
    assert "interrupted by SIGTERM" in stderr
    note = next(line for line in stderr.splitlines() if line.startswith("completed outputs"))
    listed = note.split(": ", 1)[1].split(", ")
    assert "config.yaml" in listed
    # only complete files: every file was renamed into place whole; no temporaries remain
    assert _temporaries(out) == []
    files = sorted(str(p.relative_to(out)) for p in out.rglob("*") if p.is_file())
    assert set(listed) <= set(files)
    for name in files:
        p = out / name
        if p.suffix == ".tum":
            assert len(read_tum(p)) > 0
        elif p.suffix == ".json":
            json.loads(p.read_text())
        elif p.suffix == ".yaml":
            assert isinstance(yaml.safe_load(p.read_text()), dict)
    assert "metrics.json" not in files  # written last: the run did not finish
    assert _checksums(level_recording) == before
    Recording.open(level_recording)  # still valid
