"""Benchmark: ``vio-graph run REC --mode all`` end to end on a 30 s trial, with and without the
outputs that only serve viewing (issue 10, item 1: <= 6 s wall on one core with ``.rrd``, plots
and map; <= 3 s with ``--no-rerun --no-plots``).

The recording is configs/upstair_long.yaml stretched to 30 s (as in bench_scale.py), simulated
once and cached under results/benchmarks/ (git-ignored). Two kinds of measurement:

* **whole runs**: ``vio-graph run REC --out OUT --mode all`` and the same with ``--no-rerun
  --no-plots``, each as its own process, the two interleaved ``--repeats`` times; wall and
  user + system CPU seconds of that process (``os.wait4``), medians;
* **per-stage split**: one more process per configuration runs the same command in-process
  with the stages wrapped (CPU seconds, ``time.process_time``, each stage without the stages
  nested in it): estimation (every estimator over the frames), rerun setup (importing rerun
  and its pyarrow / pandas, opening the .rrd), the rerun view (the per-frame view, sending
  it in columns, closing the file), evaluation (metrics and the safety replay), map
  building, map files (PLY, PCD, JSON, CSV), map PNG (the first figure: it pays the matplotlib
  import), plots (overview, clearance), trajectory and frames.csv files; ``startup and
  rest`` is the remainder of the process (interpreter, imports, CLI, config, opening the
  recording, metrics.json).

With ``--base REV`` the same commands also run on git revision REV (``git archive``d to a
temporary folder, run from there with it first on the import path), alternated with this
tree's in every repeat, and the table gives both sides and the ratio this tree / REV. REV's
first run compiles its numba cache (a minute or two of CPU): it runs once untimed first.

``--recording REC --mode M --flags=F``: the same on another recording (e.g. a 600 s trial of
bench_scale.py), in mode M, with the run flags F as the one configuration (no aim).

Writes benchmarks/results/end_to_end.json (with ``--base``, ``--recording`` or ``--flags``:
end_to_end_ab.json) and prints a markdown table.
Run: python benchmarks/bench_end_to_end.py [--repeats 3] [--base REV] [--recording REC]
"""

from __future__ import annotations

import argparse
import json
import os
import shutil
import statistics
import subprocess
import sys
import time
from collections.abc import Callable
from pathlib import Path
from typing import Any

import _common  # noqa: I001 - first: pins thread pools before numpy is imported
import numpy as np

DURATION_S = 30.0
ROOT = _common.BENCH_DIR.parent
CACHE = ROOT / "results" / "benchmarks"
#: the two configurations of item 1 and their aims (s wall on one core)
CONFIGS: dict[str, tuple[list[str], float]] = {
    "all outputs (.rrd, plots, map)": ([], 6.0),
    "--no-rerun --no-plots": (["--no-rerun", "--no-plots"], 3.0),
}
#: stage -> functions (module, qualified name) whose time counts as that stage
STAGES: dict[str, tuple[tuple[str, str], ...]] = {
    "estimation": (("vio_graph.replay", "Replay.run"),),
    "rerun setup (import rerun, open .rrd)": (
        ("vio_graph.viz.rerun_logger", "Visualizer.__init__"),
    ),
    "rerun view (per frame, sending)": (
        ("vio_graph.viz.rerun_logger", "Visualizer.close"),
        ("vio_graph.viz.run_view", "RunView.scene"),
        ("vio_graph.viz.run_view", "RunView.frame"),
        ("vio_graph.viz.run_view", "RunView.paths"),
        ("vio_graph.viz.run_view", "RunView.map_points"),
    ),
    "evaluation": (
        ("vio_graph.pipeline", "_evaluate"),
        ("vio_graph.evaluation.safety", "safety_metrics"),
    ),
    "map building": (("vio_graph.pipeline", "build_run_map"),),
    "map files (PLY, PCD, JSON, CSV)": (
        ("vio_graph.mapping.export", "write_point_cloud"),
        ("vio_graph.mapping.export", "write_geometry_json"),
        ("vio_graph.mapping.export", "write_geometry_csv"),
    ),
    "map PNG": (("vio_graph.mapping.export", "write_map_png"),),
    "plots (overview, clearance)": (
        ("vio_graph.viz.plots", "plot_run_overview"),
        ("vio_graph.viz.plots", "plot_clearance"),
    ),
    "trajectories, frames.csv": (
        ("vio_graph.pipeline", "write_trajectories"),
        ("vio_graph.pipeline", "write_frames_csv"),
    ),
}


def recording() -> Path:
    """The 30 s trial, simulated on first use (``vio-graph simulate``, seed 1)."""
    import bench_scale

    rec = CACHE / f"upstair_long_{DURATION_S:g}s"
    if not (rec / "metadata.yaml").exists():
        CACHE.mkdir(parents=True, exist_ok=True)
        scenario = bench_scale._scenario(DURATION_S, CACHE)
        cmd = [sys.executable, "-m", "vio_graph.cli", "simulate", "--scenario", str(scenario)]
        subprocess.run(cmd + ["--seed", "1", "--out", str(rec), "--overwrite"], check=True)
    return rec


_measure = _common.measure_process


def _run_args(rec: Path, out: Path, flags: list[str], mode: str = "all") -> list[str]:
    return ["run", str(rec), "--out", str(out), "--mode", mode, "--overwrite", *flags]


class StageClock:
    """Exclusive CPU seconds per stage: a wrapped call's time minus that of the wrapped calls
    inside it (the per-frame view runs inside the estimation loop)."""

    def __init__(self) -> None:
        self.cpu_s: dict[str, float] = {}
        self._children: list[float] = []

    def wrap(self, stage: str, fn: Callable[..., Any]) -> Callable[..., Any]:
        def timed(*args: Any, **kwargs: Any) -> Any:
            self._children.append(0.0)
            t0 = time.process_time()
            try:
                return fn(*args, **kwargs)
            finally:
                elapsed = time.process_time() - t0
                inner = self._children.pop()
                self.cpu_s[stage] = self.cpu_s.get(stage, 0.0) + elapsed - inner
                if self._children:
                    self._children[-1] += elapsed

        return timed


def _install(clock: StageClock) -> list[str]:
    """Wrap the functions of :data:`STAGES`; returns the ones not found (renamed or moved)."""
    import importlib

    missing = []
    for stage, targets in STAGES.items():
        for module_name, qualname in targets:
            owner: Any = importlib.import_module(module_name)
            *parents, name = qualname.split(".")
            for p in parents:
                owner = getattr(owner, p, None)
            fn = getattr(owner, name, None) if owner is not None else None
            if fn is None:
                missing.append(f"{module_name}.{qualname}")
                continue
            setattr(owner, name, clock.wrap(stage, fn))
    return missing


def stages_child(cli_args: list[str], result_file: Path) -> None:
    """In this process: run the CLI with the stages wrapped, write the split as JSON."""
    import vio_graph.cli

    clock = StageClock()
    missing = _install(clock)
    sys.argv = ["vio-graph", *cli_args]
    try:
        vio_graph.cli.main()
    except SystemExit as exc:
        if exc.code not in (0, None):
            raise
    total = time.process_time()  # the whole process so far: interpreter, imports, run
    split = dict(clock.cpu_s)
    split["startup and rest"] = total - sum(split.values())
    result_file.write_text(json.dumps({"cpu_s": split, "total_cpu_s": total, "missing": missing}))


def _stage_split(
    rec: Path, out: Path, flags: list[str], tree: Path | None = None, mode: str = "all"
) -> dict[str, Any]:
    result_file = out.with_suffix(".stages.json")
    env = dict(os.environ, **{v: "1" for v in _common.THREAD_VARIABLES})
    if tree is not None:  # the package of that tree (this script and _common from here)
        env["PYTHONPATH"] = str(tree)
    args = [sys.executable, str(Path(__file__).resolve()), "--stages-child", str(result_file)]
    subprocess.run(
        [*args, "--", *_run_args(rec, out, flags, mode)],
        check=True,
        env=env,
        cwd=tree,
        stdout=subprocess.DEVNULL,
    )
    split = json.loads(result_file.read_text())
    result_file.unlink()
    shutil.rmtree(out, ignore_errors=True)
    return split


def run(
    repeats: int = 3,
    base: str | None = None,
    rec_path: Path | None = None,
    mode: str = "all",
    flags: list[str] | None = None,
) -> dict[str, Any]:
    """The two configurations of :data:`CONFIGS` on the 30 s trial, or ``flags`` alone (one
    configuration, no aim) on the recording ``rec_path``, in ``mode``."""
    rec = (recording() if rec_path is None else Path(rec_path)).resolve()
    stamps = np.loadtxt(rec / "depth" / "timestamps.csv", delimiter=",", skiprows=1, ndmin=2)
    frames = stamps.shape[0]
    configs = CONFIGS if flags is None else {" ".join(flags) or "(no flags)": (flags, np.nan)}
    scenario = f"upstair_long stretched to {DURATION_S:g} s, seed 1"
    if rec_path is not None:
        scenario = _common.display_path(rec)
    info = {
        "scenario": scenario,
        "duration_s": DURATION_S if rec_path is None else float(np.ptp(stamps[:, 1])),
        "frames": frames,
        "mode": mode,
    }
    scratch = (_common.SCRATCH_DIR / "end_to_end").resolve()
    scratch.mkdir(parents=True, exist_ok=True)
    if base is None:
        return {**info, **_run_sides(rec, scratch, repeats, {"this tree": None}, configs, mode)}
    import tempfile

    with tempfile.TemporaryDirectory() as tmp:
        tree = _common.extract_revision(base, Path(tmp))
        cli = [sys.executable, "-m", "vio_graph.cli"]
        warm = _run_args(rec, scratch / "warm", ["--no-rerun", "--no-plots"], mode)
        _measure(cli + warm, tree)  # compiles REV's numba cache: not timed
        shutil.rmtree(scratch / "warm", ignore_errors=True)
        sides = {base: tree, "this tree": None}
        out = {**info, **_run_sides(rec, scratch, repeats, sides, configs, mode), "base": base}
    return out


def _run_sides(
    rec: Path,
    scratch: Path,
    repeats: int,
    sides: dict[str, Path | None],
    configs: dict[str, tuple[list[str], float]],
    mode: str,
) -> dict[str, Any]:
    """Every configuration on every side (a source tree, None: this one), alternated."""
    cli = [sys.executable, "-m", "vio_graph.cli"]
    runs: dict[tuple[str, str], list[dict[str, float]]] = {
        (name, side): [] for name in configs for side in sides
    }
    order = list(sides.items())
    for k in range(repeats):  # interleaved: a load change hits both configurations alike
        for name, (flags, _aim) in configs.items():
            for side, tree in order if k % 2 == 0 else order[::-1]:
                out = scratch / "out"
                runs[name, side].append(_measure(cli + _run_args(rec, out, flags, mode), tree))
                shutil.rmtree(out, ignore_errors=True)
    rows = []
    for name, (flags, aim) in configs.items():
        for side, tree in sides.items():
            r = runs[name, side]
            rows.append(
                {
                    "config": name,
                    "side": side,
                    "flags": flags,
                    "aim_wall_s": aim,
                    "wall_s": statistics.median(x["wall_s"] for x in r),
                    "cpu_s": statistics.median(x["cpu_s"] for x in r),
                    "runs": r,
                    "stages": _stage_split(rec, scratch / "out_stages", flags, tree, mode),
                }
            )
    return {"repeats": repeats, "rows": rows}


def markdown(r: dict[str, Any]) -> str:
    f = _common.fmt
    d = r["duration_s"]
    mode = r.get("mode", "all")
    sides = list(dict.fromkeys(row.get("side", "this tree") for row in r["rows"]))
    cpu_of = {(row["config"], row.get("side", "this tree")): row["cpu_s"] for row in r["rows"]}
    whole = [
        [
            f"`vio-graph run REC --out OUT --mode {mode} {' '.join(row['flags'])}`".replace(
                " `", "`"
            ),
            *([row.get("side", "this tree")] if len(sides) > 1 else []),
            f"{f(row['wall_s'], 1)} s",
            f"{f(row['cpu_s'], 1)} s",
            f"<= {row['aim_wall_s']:g} s" if np.isfinite(row["aim_wall_s"]) else "",
            f"{d / row['cpu_s']:.1f}x",
            *([f"{row['cpu_s'] / cpu_of[row['config'], sides[0]]:.3f}"] if len(sides) > 1 else []),
        ]
        for row in r["rows"]
    ]
    head = ["command", "wall", "CPU", "aim (wall)", "x real time"]
    if len(sides) > 1:
        head = [head[0], "tree", *head[1:], f"CPU / {sides[0]}"]
    names = list(dict.fromkeys(n for row in r["rows"] for n in row["stages"]["cpu_s"]))
    split = [
        [name] + [f(row["stages"]["cpu_s"].get(name, 0.0), 2) for row in r["rows"]]
        for name in names
    ]
    columns = [row["config"] + (f" ({row['side']})" if len(sides) > 1 else "") for row in r["rows"]]
    split.append(["total"] + [f(row["stages"]["total_cpu_s"], 2) for row in r["rows"]])
    missing = sorted({m for row in r["rows"] for m in row["stages"]["missing"]})
    return "\n".join(
        [
            f"A {d:.3g} s trial ({r['frames']} frames; {r['scenario']}), `--mode {mode}`; "
            f"each command its own single-threaded process, the commands "
            f"interleaved {r['repeats']} times, medians of wall and user + system CPU seconds "
            "(`os.wait4`). The aims (issue 10) are wall seconds on one core; on a shared "
            "machine the CPU seconds are the figure to compare. Real time factor on CPU "
            "time.",
            "",
            *([f"Base: `{r['base']}`; CPU ratios this tree / base.", ""] if "base" in r else []),
            _common.md_table(head, whole),
            "",
            "CPU seconds per stage (one more run of each command, stages wrapped in-process; "
            "a stage's time excludes the stages nested in it, `startup and rest` is the rest "
            "of the process: interpreter, imports, CLI, config, opening the recording, "
            "metrics.json):",
            "",
            _common.md_table(["stage", *columns], split),
            *(["", "Not measured (renamed or moved): " + ", ".join(missing)] if missing else []),
        ]
    )


def main() -> None:
    if len(sys.argv) > 2 and sys.argv[1] == "--stages-child":
        stages_child(sys.argv[4:], Path(sys.argv[2]))  # argv: --stages-child FILE -- ARGS
        return
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--repeats", type=int, default=3, help="runs of each command (median)")
    ap.add_argument("--base", help="git revision to compare with (alternated runs)")
    ap.add_argument("--recording", type=Path, help="another recording (default: the 30 s trial)")
    ap.add_argument("--mode", default="all", help="the run's --mode (default all)")
    ap.add_argument(
        "--flags",
        help="one configuration: these run flags (e.g. '--no-rerun'; '' for none) instead of "
        "the two of issue 10",
    )
    args = ap.parse_args()
    flags = None if args.flags is None else args.flags.split()
    r = run(args.repeats, args.base, args.recording, args.mode, flags)
    # (an A/B result apart: docs/performance.md reads end_to_end.json as this tree's figures)
    default = args.base is None and args.recording is None and flags is None and args.mode == "all"
    _common.write_result("end_to_end" if default else "end_to_end_ab", r)
    print(markdown(r))  # noqa: T201 - script output


if __name__ == "__main__":
    main()
