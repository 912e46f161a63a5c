"""Studies on many trials (vio_graph/studies): the Dask engine against a real scheduler and two
real workers started as subprocesses on 127.0.0.1, the serial reference, --resume, grids.

Three short simulated trials (1.2 s upstair at 112 x 86 px, seeds 1-3) keep the whole file
well under a minute on a 2-core machine.
"""

from __future__ import annotations

import json
import os
import signal
import socket
import subprocess
import sys
import threading
import time
from pathlib import Path

import pytest

from vio_graph.config import PipelineConfig
from vio_graph.errors import VioGraphError
from vio_graph.studies.batch import (
    make_tasks,
    read_summary_csv,
    run_batch,
    trial_names,
    write_summary,
)
from vio_graph.studies.grid import check_field_path, expand_grid, parse_set

ROOT = Path(__file__).resolve().parents[1]
DASK = Path(sys.executable).with_name("dask")
#: no plots: the tasks stay short; the numbers do not depend on them
FAST = PipelineConfig().model_copy(
    update={"output": PipelineConfig().output.model_copy(update={"plots": False, "rerun": False})}
)
MODES = ("filter", "smoother")


def _upstair_trials(
    tmp_path_factory: pytest.TempPathFactory, folder: str, prefix: str, duration_s: float, seeds
) -> list[Path]:
    """Simulated upstair trials of ``duration_s`` (s) at 112 x 86 px, one per seed."""
    from vio_graph.sim import load_scenario, simulate

    base = load_scenario("upstair")
    cfg = base.model_copy(
        update={
            "duration_s": duration_s,
            "camera": base.camera.model_copy(update={"width_px": 112, "height_px": 86}),
        }
    )
    root = tmp_path_factory.mktemp(folder)
    return [simulate(cfg, seed=s, out_dir=root / f"{prefix}_s{s}") for s in seeds]


@pytest.fixture(scope="module")
def trials(tmp_path_factory: pytest.TempPathFactory) -> list[Path]:
    return _upstair_trials(tmp_path_factory, "trials", "up", 1.2, (1, 2, 3))


@pytest.fixture(scope="module")
def corrupt(tmp_path_factory: pytest.TempPathFactory) -> Path:
    rec = tmp_path_factory.mktemp("bad") / "corrupt_s9"
    rec.mkdir()
    (rec / "metadata.yaml").write_text("- not a mapping\n")
    return rec


@pytest.fixture(scope="module")
def serial(trials: list[Path], tmp_path_factory: pytest.TempPathFactory):
    """The reference: every task in this process, one after the other."""
    out = tmp_path_factory.mktemp("serial")
    tasks = make_tasks(trials, MODES, expand_grid(FAST, None), out)
    rows = run_batch(tasks, out, scheduler="serial")
    write_summary(rows, out, "serial")
    return out, rows


def _free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


class _Cluster:
    """`dask scheduler` + two `dask worker` subprocesses (no nanny: a killed worker stays dead)."""

    def __init__(self, n_workers: int = 2) -> None:
        port = _free_port()
        self.address = f"tcp://127.0.0.1:{port}"
        env = {
            **os.environ,
            "PYTHONPATH": str(ROOT) + os.pathsep + os.environ.get("PYTHONPATH", ""),
        }
        common = dict(
            env=env, stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL, start_new_session=True
        )
        self.scheduler = subprocess.Popen(
            [str(DASK), "scheduler", "--host", "127.0.0.1", "--port", str(port), "--no-dashboard"],
            **common,
        )
        self.workers = {
            f"w{k}": subprocess.Popen(
                [
                    str(DASK),
                    "worker",
                    self.address,
                    "--name",
                    f"w{k}",
                    "--nthreads",
                    "1",
                    "--no-nanny",
                    "--host",
                    "127.0.0.1",
                    "--no-dashboard",
                    "--memory-limit",
                    "0",
                ],
                **common,
            )
            for k in range(n_workers)
        }
        from distributed import Client

        deadline = time.monotonic() + 60
        while True:
            try:
                self.client = Client(self.address, timeout="5s")
                break
            except OSError:
                if time.monotonic() > deadline:
                    raise
                time.sleep(0.2)
        self.client.wait_for_workers(n_workers, timeout=60)
        # import the pipeline on every worker before timing-sensitive work starts
        self.client.run(lambda: __import__("vio_graph.pipeline").__name__)

    def worker_process(self, address: str) -> subprocess.Popen:
        name = self.client.scheduler_info()["workers"][address]["name"]
        return self.workers[name]

    def close(self) -> None:
        self.client.close()
        for p in [*self.workers.values(), self.scheduler]:
            if p.poll() is None:
                p.terminate()
        for p in [*self.workers.values(), self.scheduler]:
            try:
                p.wait(timeout=10)
            except subprocess.TimeoutExpired:
                p.kill()
                p.wait()


@pytest.fixture(scope="module")
def cluster():
    """One scheduler + two workers for the module (the kill test, last, leaves one)."""
    c = _Cluster(2)
    try:
        yield c
    finally:
        c.close()


def _ate(study: Path, row: dict) -> dict:
    m = json.loads((study / row["results"] / "metrics.json").read_text())
    return m["ate_cm"][row["mode"]]


# --------------------------------------------------------------------------- the cluster
def test_cluster_results_equal_serial_and_corrupt_fails_alone(
    cluster: _Cluster, trials, corrupt, serial, tmp_path: Path
) -> None:
    ref_dir, ref_rows = serial
    out = tmp_path / "study"
    tasks = make_tasks([*trials, corrupt], MODES, expand_grid(FAST, None), out)
    rows = run_batch(tasks, out, scheduler=cluster.address)
    write_summary(rows, out, "cluster")
    ok = [r for r in rows if r["status"] == "ok"]
    bad = [r for r in rows if r["status"] != "ok"]
    assert len(ok) == 6 and {r["trial"] for r in bad} == {"corrupt_s9"} and len(bad) == 2
    assert all("metadata.yaml" in r["error"] and "mapping" in r["error"] for r in bad)
    # the same numbers as the serial run, to the last bit, and the same summary lines
    for r, ref in zip(ok, ref_rows, strict=True):
        assert (r["trial"], r["mode"]) == (ref["trial"], ref["mode"])
        assert _ate(out, r) == _ate(ref_dir, ref)
    ref_csv = read_summary_csv(ref_dir / "summary.csv")
    csv_rows = read_summary_csv(out / "summary.csv")
    assert [r for r in csv_rows if r["status"] == "ok"] == ref_csv
    failed = [r for r in csv_rows if r["status"] == "failed"]
    assert len(failed) == 2 and all(r["error"].startswith("RecordingError") for r in failed)
    md = (out / "summary.md").read_text()
    assert "2 failed" in md and "corrupt_s9/filter: RecordingError" in md
    assert (out / "summary.png").stat().st_size > 10_000
    # sensible accuracy on these 1.2 s trials (ground truth in the recordings)
    assert all(0.0 < float(r["toe_x_cm"]) < 5.0 for r in csv_rows if r["status"] == "ok")


def test_compare_layer_on_the_cluster_equals_its_process_path(
    cluster: _Cluster, trials, corrupt, tmp_path: Path
) -> None:
    """`evaluate` / `compare` (experiments.run_trials) through --scheduler: the same metrics
    as the default path; a failure is one error naming the task, after the rest ran."""
    from vio_graph.experiments import run_trials

    recs = [("upstair", k + 1, p) for k, p in enumerate(trials[:2])]
    default = run_trials(recs, tmp_path / "a", FAST, modes=("filter",))
    dask = run_trials(recs, tmp_path / "b", FAST, modes=("filter",), scheduler=cluster.address)
    for a, b in zip(default, dask, strict=True):
        assert a.metrics["ate_cm"] == b.metrics["ate_cm"]
    with pytest.raises(VioGraphError, match=r"1 of 2 tasks failed.*corrupt_s9.*RecordingError"):
        run_trials(
            [*recs[:1], ("upstair", 9, corrupt)],
            tmp_path / "c",
            FAST,
            modes=("filter",),
            scheduler=cluster.address,
        )


@pytest.fixture(scope="module")
def long_trials(tmp_path_factory: pytest.TempPathFactory) -> list[Path]:
    """Two 5 s trials: tasks long enough (about a second each) for the kill to land in one;
    with the 1.2 s trials a batch could finish between two polls of the scheduler."""
    return _upstair_trials(tmp_path_factory, "long_trials", "up_long", 5.0, (1, 2))


def test_killed_worker_loses_no_trial(cluster: _Cluster, long_trials, tmp_path: Path) -> None:
    ref_dir = tmp_path / "ref"
    ref_tasks = make_tasks(long_trials, ("filter",), expand_grid(FAST, None), ref_dir)
    ref_rows = run_batch(ref_tasks, ref_dir, scheduler="serial")
    out = tmp_path / "study"
    tasks = make_tasks(long_trials, ("filter",), expand_grid(FAST, None), out)
    result: dict[str, list] = {}
    runner = threading.Thread(
        target=lambda: result.setdefault("rows", run_batch(tasks, out, cluster.address))
    )
    runner.start()
    victim = None
    deadline = time.monotonic() + 60
    while victim is None and time.monotonic() < deadline:
        busy = {addr: keys for addr, keys in cluster.client.processing().items() if keys}
        if busy:  # a worker is running a task: kill it mid-run
            victim = cluster.worker_process(next(iter(busy)))
            victim.send_signal(signal.SIGKILL)
        else:
            time.sleep(0.005)
    runner.join(timeout=120)
    assert victim is not None and victim.wait(timeout=10) == -signal.SIGKILL
    assert not runner.is_alive()
    rows = result["rows"]
    assert [r["status"] for r in rows] == ["ok"] * len(tasks)
    assert len(cluster.client.scheduler_info()["workers"]) == 1
    for r, ref in zip(rows, ref_rows, strict=True):
        assert _ate(out, r) == _ate(ref_dir, ref)


# --------------------------------------------------------------------------- resume
def test_resume_skips_complete_tasks(trials, serial, tmp_path: Path) -> None:
    ref_dir, ref_rows = serial
    out = tmp_path / "study"
    tasks = make_tasks(trials[:1], MODES, expand_grid(FAST, None), out)
    run_batch(tasks, out, scheduler="serial")
    kept = Path(tasks[0].out_dir) / "metrics.json"
    redo = Path(tasks[1].out_dir) / "metrics.json"
    stamp = kept.stat().st_mtime_ns
    redo.unlink()  # as if the run had been cut before this task finished
    rows = run_batch(tasks, out, scheduler="serial", resume=True)
    assert kept.stat().st_mtime_ns == stamp  # skipped
    assert redo.is_file()  # run again
    assert [r["status"] for r in rows] == ["ok", "ok"]
    for r, ref in zip(rows, ref_rows[:2], strict=True):
        assert _ate(out, r) == _ate(ref_dir, ref)
    # a different config is not "complete": the grid point's folder is new anyway, but the
    # same folder with another config.yaml must be run again
    other = FAST.model_copy(update={"smoother": FAST.smoother.model_copy(update={"window_s": 1.0})})
    changed = make_tasks(trials[:1], MODES, [expand_grid(other, None)[0]], out)
    from vio_graph.studies.batch import task_complete

    assert task_complete(changed[0]) is None and task_complete(tasks[0]) is not None


# --------------------------------------------------------------------------- grids
def test_grid_expands_and_validates() -> None:
    points = expand_grid(FAST, ["smoother.window_s=1,2", "filter.stance_anchor=true,false"])
    assert [p.tag for p in points] == [
        "smoother.window_s-1__filter.stance_anchor-True",
        "smoother.window_s-1__filter.stance_anchor-False",
        "smoother.window_s-2__filter.stance_anchor-True",
        "smoother.window_s-2__filter.stance_anchor-False",
    ]
    assert [(p.config.smoother.window_s, p.config.filter.stance_anchor) for p in points] == [
        (1.0, True),
        (1.0, False),
        (2.0, True),
        (2.0, False),
    ]
    assert points[0].config.output.plots is False  # the rest of the base config is kept
    assert expand_grid(FAST, None)[0].tag == "base"


@pytest.mark.parametrize(
    "option, message",
    [
        ("filter.nosuch=1", "filter has no field 'nosuch'"),
        ("nosuch.x=1", "the pipeline config has no field 'nosuch'"),
        ("filter=1", "filter is a section"),
        ("smoother.window_s", "expected FIELD=VALUE"),
        ("smoother.window_s=", "empty value"),
        ("smoother.window_s=1,1", "repeated"),
    ],
)
def test_bad_set_options(option: str, message: str) -> None:
    with pytest.raises(VioGraphError, match=message):
        expand_grid(FAST, [option])


def test_bad_grid_value_names_the_field() -> None:
    with pytest.raises(VioGraphError, match=r"smoother.window_s=abc: smoother.window_s"):
        expand_grid(FAST, ["smoother.window_s=abc"])
    with pytest.raises(VioGraphError, match="set twice"):
        expand_grid(FAST, ["smoother.window_s=1", "smoother.window_s=2"])
    assert parse_set("kinematics.shank_pitch_source=imu,encoders")[1] == ["imu", "encoders"]
    check_field_path("smoother.factors.landmarks")  # nested sections


def test_trial_names_disambiguate(tmp_path: Path) -> None:
    a, b = tmp_path / "s1" / "trial1", tmp_path / "s2" / "trial1"
    assert trial_names([a, b]) == ["s1__trial1", "s2__trial1"]
    assert trial_names([a, tmp_path / "x"]) == ["trial1", "x"]
    with pytest.raises(VioGraphError, match="given twice"):
        trial_names([a, a])


def test_cli_batch_serial_and_bad_set(trials, tmp_path: Path, capsys, monkeypatch) -> None:
    from tests.test_cli import _cli

    code, _, err = _cli(
        ["batch", str(trials[0]), "--out", str(tmp_path / "s"), "--set", "filter.nosuch=1"],
        capsys,
        monkeypatch,
    )
    assert code == 1 and "filter has no field 'nosuch'" in err and "Traceback" not in err
    cfg = tmp_path / "fast.yaml"
    from vio_graph.config import dump_config

    cfg.write_text(dump_config(FAST))
    args = [
        "batch",
        str(trials[0]),
        "--out",
        str(tmp_path / "s"),
        "--mode",
        "filter",
        "--config",
        str(cfg),
        "--scheduler",
        "serial",
    ]
    code, out, err = _cli(args, capsys, monkeypatch)
    assert code == 0, err
    assert (tmp_path / "s" / "summary.csv").is_file() and "summary.md" in out
    code, _, err = _cli(args, capsys, monkeypatch)  # the study is there: refused
    assert code == 1 and "--resume" in err
    code, _, err = _cli([*args, "--resume"], capsys, monkeypatch)
    assert code == 0, err
