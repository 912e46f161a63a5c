"""Benchmark: how a run scales with the trial length (10 s, 60 s, 600 s by default).

Per trial length, three stages, each as its own process (the numbers are that process's own
accounting from ``os.wait4``: wall, user + system CPU, peak resident memory):

* ``simulate``: ``vio-graph simulate`` of the long stair scenario (configs/upstair_long.yaml,
  step over step, 14 flights per 120 s), stretched to the length with flights added;
* ``online``: ``vio-graph run REC --mode filter --no-rerun`` (the online filter and the two
  baselines, trajectories, metrics, plots and map);
* ``batch``: ``vio-graph run REC --mode batch --no-rerun`` (the same plus the GTSAM batch
  smoother over the whole trial); its ``batch_solve_s`` from metrics.json is reported too.

Recordings are cached in the benchmark scratch folder (``VIO_GRAPH_BENCH_SCRATCH``, default
the system temp folder); a 600 s recording is ~2.1 GB of depth and confidence.
Writes benchmarks/results/scale.json and prints a markdown table.
Run: python benchmarks/bench_scale.py [--durations 10 60 600]
"""

from __future__ import annotations

import argparse
import json
import math
import os
import shutil
import subprocess
import sys
import time
from pathlib import Path

import _common  # noqa: I001 - first: pins thread pools before numpy is imported

FLIGHTS_PER_S = 14 / 120.0  # configs/upstair_long.yaml: 14 flights in 120 s


def _measure(args: list[str]) -> dict:
    """Run ``args`` as a child process; its wall (s), CPU (s) and peak RSS (MiB)."""
    env = dict(os.environ, **{v: "1" for v in _common.THREAD_VARIABLES})
    t0 = time.perf_counter()
    proc = subprocess.Popen(args, env=env, stdout=subprocess.DEVNULL, stderr=subprocess.PIPE)
    _, status, usage = os.wait4(proc.pid, 0)
    wall = time.perf_counter() - t0
    err = proc.stderr.read().decode(errors="replace") if proc.stderr else ""
    proc.returncode = os.waitstatus_to_exitcode(status)
    if proc.returncode != 0:
        raise RuntimeError(f"{' '.join(args)} failed ({proc.returncode}):\n{err[-2000:]}")
    return {
        "wall_s": wall,
        "cpu_s": usage.ru_utime + usage.ru_stime,
        "peak_rss_mib": usage.ru_maxrss / 1024.0,
    }


def _scenario(duration_s: float, folder: Path) -> Path:
    """configs/upstair_long.yaml stretched to ``duration_s`` (enough flights for it)."""
    from vio_graph.sim import load_scenario

    cfg = load_scenario("upstair_long")
    n_flights = max(1, math.ceil(duration_s * FLIGHTS_PER_S) + 1)
    data = cfg.model_dump(mode="json")
    data["name"] = f"upstair_long_{duration_s:g}s"
    data["duration_s"] = float(duration_s)
    data["terrain"]["n_flights"] = n_flights
    path = folder / f"{data['name']}.yaml"  # written as JSON, which is YAML
    path.write_text(json.dumps(data))
    return path


def run(durations_s: list[float]) -> dict:
    cli = [sys.executable, "-m", "vio_graph.cli"]
    scratch = _common.SCRATCH_DIR / "scale"
    scratch.mkdir(parents=True, exist_ok=True)
    rows = []
    for d in durations_s:
        rec = scratch / f"upstair_long_{d:g}s"
        row: dict = {"duration_s": d}
        sim_file = scratch / f"upstair_long_{d:g}s.simulate.json"
        if not (rec / "metadata.yaml").exists() or not sim_file.exists():
            scen = _scenario(d, scratch)
            row["simulate"] = _measure(
                cli
                + [
                    "simulate",
                    "--scenario",
                    str(scen),
                    "--seed",
                    "1",
                    "--out",
                    str(rec),
                    "--overwrite",
                ]
            )
            sim_file.write_text(json.dumps(row["simulate"]))
        else:  # the recording is cached: the figures of the run that simulated it
            row["simulate"] = {**json.loads(sim_file.read_text()), "cached": True}
        frames = sum(1 for _ in (rec / "depth" / "timestamps.csv").open()) - 1
        row["frames"] = frames
        for stage, mode in (("online", "filter"), ("batch", "batch")):
            out = scratch / f"out_{d:g}s_{stage}"
            row[stage] = _measure(
                cli
                + ["run", str(rec), "--out", str(out), "--mode", mode, "--no-rerun", "--overwrite"]
            )
            metrics = json.loads((out / "metrics.json").read_text())
            if stage == "batch":
                row["batch_solve_s"] = _find(metrics, "batch_solve_s")
            shutil.rmtree(out, ignore_errors=True)
        rows.append(row)
        print(json.dumps(row), flush=True)  # noqa: T201 - progress of a long benchmark
    return {"scenario": "upstair_long (stretched)", "rows": rows}


def _find(obj, key: str):
    """First value of ``key`` anywhere in a nested JSON object (None if absent)."""
    if isinstance(obj, dict):
        if key in obj:
            return obj[key]
        obj = list(obj.values())
    if isinstance(obj, list):
        for v in obj:
            found = _find(v, key)
            if found is not None:
                return found
    return None


def markdown(r: dict) -> str:
    f = _common.fmt
    rows = []
    for row in r["rows"]:
        for stage in ("simulate", "online", "batch"):
            m = row.get(stage)
            if m is None:
                continue
            extra = "measured when the recording was simulated" if m.get("cached") else ""
            if stage == "online":
                extra = f"{row['duration_s'] / m['cpu_s']:.1f}x real time on CPU time"
            if stage == "batch" and row.get("batch_solve_s") is not None:
                extra = f"batch solve {f(row['batch_solve_s'])} s"
            rows.append(
                [
                    f"{row['duration_s']:g} s ({row['frames']} frames)",
                    stage,
                    f(m["wall_s"], 1),
                    f(m["cpu_s"], 1),
                    f(m["peak_rss_mib"], 0),
                    extra,
                ]
            )
    return "\n".join(
        [
            "Stages as separate processes (`vio-graph simulate --scenario S --seed 1 --out REC`; "
            "online = `vio-graph run REC --out OUT --mode filter --no-rerun`; batch = "
            "`vio-graph run REC --out OUT --mode batch --no-rerun`, which includes the online "
            "pass), each with trajectories, metrics, plots and map written. Wall and CPU "
            "seconds and peak resident memory of that process (`os.wait4`); single thread. "
            "Scenario: "
            "configs/upstair_long.yaml stretched to the trial length.",
            "",
            _common.md_table(["trial", "stage", "wall s", "CPU s", "peak RSS MiB", "note"], rows),
        ]
    )


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument(
        "--durations", type=float, nargs="+", default=[10.0, 60.0, 600.0], help="trial lengths, s"
    )
    args = ap.parse_args()
    r = run(args.durations)
    _common.write_result("scale", r)
    print(markdown(r))  # noqa: T201 - script output


if __name__ == "__main__":
    main()
