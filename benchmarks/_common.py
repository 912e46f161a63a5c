"""Shared helpers of the benchmark scripts: single-thread setup, statistics, machine info,
JSON results and markdown tables.

Import this module BEFORE numpy (``import _common`` first in a script): it pins the BLAS /
OpenMP thread pools to one thread, because thread pools are only read when numpy, scipy or
open3d are first imported. Benchmarks only, never used by the library.
"""

from __future__ import annotations

import os
import tempfile

THREAD_VARIABLES = (
    "OMP_NUM_THREADS",
    "OPENBLAS_NUM_THREADS",
    "MKL_NUM_THREADS",
    "NUMEXPR_NUM_THREADS",
    "VECLIB_MAXIMUM_THREADS",
)
for _name in THREAD_VARIABLES:
    os.environ[_name] = "1"

import datetime  # noqa: E402
import json  # noqa: E402
import platform  # noqa: E402
from pathlib import Path  # noqa: E402
from typing import Any  # noqa: E402

import numpy as np  # noqa: E402

BENCH_DIR = Path(__file__).resolve().parent
RESULTS_DIR = BENCH_DIR / "results"
SCRATCH_DIR = Path(
    os.environ.get("VIO_GRAPH_BENCH_SCRATCH", Path(tempfile.gettempdir()) / "vio_graph_bench")
)


def display_path(path: Path | str) -> str:
    """A recording path as results JSON should show it: relative to the working directory
    when it lies below it, else only its folder name (no path of the machine it ran on)."""
    p = Path(path)
    try:
        return str(p.resolve().relative_to(Path.cwd().resolve()))
    except ValueError:
        return p.name


def stats_ms(values: Any) -> dict[str, float]:
    """Median, p95, mean, min and count of a list of durations (any unit; name says ms)."""
    v = np.asarray(values, dtype=float).reshape(-1)
    v = v[np.isfinite(v)]
    if v.size == 0:
        nan = float("nan")
        return {"median": nan, "p95": nan, "mean": nan, "min": nan, "n": 0}
    return {
        "median": float(np.median(v)),
        "p95": float(np.percentile(v, 95)),
        "mean": float(np.mean(v)),
        "min": float(np.min(v)),
        "n": int(v.size),
    }


def cpu_model() -> str:
    """CPU model name from /proc/cpuinfo (``platform.processor()`` elsewhere)."""
    try:
        for line in Path("/proc/cpuinfo").read_text().splitlines():
            if line.startswith("model name"):
                return line.split(":", 1)[1].strip()
    except OSError:
        pass
    return platform.processor() or platform.machine()


def source_revision() -> str:
    """Git commit of the checkout, with ``+dirty`` if vio_graph/ or configs/ have uncommitted
    changes (the benchmarks measure the working tree)."""
    import subprocess

    def git(*args: str) -> str:
        return subprocess.run(
            ["git", *args], cwd=BENCH_DIR, capture_output=True, text=True, check=False
        ).stdout.strip()

    rev = git("rev-parse", "--short", "HEAD") or "unknown"
    return rev + (
        "+dirty" if git("status", "--porcelain", "--", "../vio_graph", "../configs") else ""
    )


def machine_info() -> dict[str, Any]:
    """What the numbers were measured on."""
    try:
        usable = len(os.sched_getaffinity(0))
    except AttributeError:  # not Linux
        usable = os.cpu_count() or 0
    try:
        load = os.getloadavg()
    except OSError:
        load = (float("nan"),) * 3
    import scipy

    return {
        "cpu_model": cpu_model(),
        "logical_cores": os.cpu_count(),
        "usable_cores": usable,
        "load_average_1_5_15min": [round(x, 2) for x in load],
        "platform": platform.platform(),
        "python": platform.python_version(),
        "numpy": np.__version__,
        "scipy": scipy.__version__,
        "threads": {name: os.environ.get(name) for name in THREAD_VARIABLES},
        "source_revision": source_revision(),
        "date_utc": datetime.datetime.now(datetime.UTC).strftime("%Y-%m-%d %H:%M UTC"),
    }


def write_result(name: str, result: dict[str, Any]) -> Path:
    """Write ``benchmarks/results/<name>.json`` with the machine info under ``"machine"``."""
    RESULTS_DIR.mkdir(parents=True, exist_ok=True)
    path = RESULTS_DIR / f"{name}.json"
    payload = {"benchmark": name, "machine": machine_info(), **result}
    path.write_text(json.dumps(payload, indent=2) + "\n")
    return path


def read_result(name: str) -> dict[str, Any]:
    return json.loads((RESULTS_DIR / f"{name}.json").read_text())


def md_table(headers: list[str], rows: list[list[Any]]) -> str:
    """A markdown table; floats are printed as given (format them before)."""
    lines = ["| " + " | ".join(headers) + " |", "|" + "---|" * len(headers)]
    lines += ["| " + " | ".join(str(c) for c in row) + " |" for row in rows]
    return "\n".join(lines)


def fmt(x: float, digits: int = 2) -> str:
    """Fixed-point number, 'n/a' for NaN / None."""
    if x is None or not np.isfinite(x):
        return "n/a"
    return f"{x:.{digits}f}"


def filter_leg_run(rec: Any, cfg: Any) -> tuple[Any, dict[str, Any]]:
    """Replay a recording in filter mode; returns the replay log and the filter's camera,
    knee, ankle, heel and toe paths (x-z, metres) with the config's shank pitch source
    (the safety benchmarks' common input)."""
    from vio_graph.pipeline import leg_trajectories
    from vio_graph.replay import Replay
    from vio_graph.viz.rerun_logger import NullVisualizer

    replay = Replay(rec, cfg, {"filter"}, NullVisualizer())
    lg = replay.run()
    use_enc = cfg.kinematics.shank_pitch_source == "encoders"
    return lg, leg_trajectories(replay.rig, lg.camera_xz["filter"], lg, use_enc)


def monitor_update(mon: Any, lg: Any, est: dict[str, Any], k: int, in_stance: Any = None) -> Any:
    """Feed frame ``k`` of a :func:`filter_leg_run` to a ``SafetyMonitor`` as the online
    estimator does; ``in_stance`` replaces the log's stance flags when given (bool per
    frame). Returns the monitor's estimate."""
    stance = lg.in_stance if in_stance is None else in_stance
    return mon.update(
        float(lg.t_s[k]),
        est["camera"][k],
        lg.cov_position_m2[k],
        est["heel"][k],
        est["toe"][k],
        bool(stance[k]),
        lg.profiles.get(k),
    )


def true_leg_paths(rec: Any, t: Any) -> dict[str, Any]:
    """The simulator's true camera, heel and toe (x-z, metres) at the times ``t`` (s)."""
    gt = rec.groundtruth.trajectories
    return {b: gt[b].xz_at(t) for b in ("camera", "heel", "toe")}


#: run by a small Python process that starts and waits for the measured command: its argv
#: (JSON) and working directory; prints the child's wall, CPU, peak RSS and exit code (JSON)
_MEASURING_PARENT = """
import json, os, subprocess, sys, time
args, cwd = json.loads(sys.argv[1]), sys.argv[2] or None
t0 = time.perf_counter()
proc = subprocess.Popen(args, cwd=cwd, stdout=subprocess.DEVNULL, stderr=subprocess.PIPE)
err = proc.stderr.read()
_, status, usage = os.wait4(proc.pid, 0)
wall = time.perf_counter() - t0
sys.stderr.buffer.write(err[-4000:])
print(json.dumps({"wall_s": wall, "cpu_s": usage.ru_utime + usage.ru_stime,
                  "peak_rss_mib": usage.ru_maxrss / 1024.0,
                  "code": os.waitstatus_to_exitcode(status)}))
"""


def measure_process(args: list[str], tree: Path | None = None) -> dict[str, float]:
    """Run ``args`` as a single-threaded child process (BLAS / OpenMP threads = 1); its wall
    (s), user + system CPU (s) and peak resident memory (MiB), from ``os.wait4``. ``tree``:
    a source tree (:func:`extract_revision`) to run instead of this one, first on the import
    path and the working directory (``python -m`` puts the working directory first).

    The command is started by a small Python process, not by this one: Linux folds the
    high-water RSS of the process that execs into the new program's peak (and Python's
    subprocess execs from a vfork child sharing its parent's memory), so a command started
    from a long-lived benchmark process reported that process's memory as its own (``vio-graph
    --help`` at 119 MiB instead of 18). The small parent's own ~10 MiB is the floor left.

    Raises:
        RuntimeError: the process exited with a non-zero code (its stderr's end included).
    """
    import subprocess
    import sys

    env = dict(os.environ, **{v: "1" for v in THREAD_VARIABLES})
    if tree is not None:
        env["PYTHONPATH"] = str(tree)
    cwd = "" if tree is None else str(tree)
    runner = [sys.executable, "-c", _MEASURING_PARENT, json.dumps(list(args)), cwd]
    done = subprocess.run(runner, env=env, cwd=tree, capture_output=True, check=False)
    err = done.stderr.decode(errors="replace")
    lines = done.stdout.decode(errors="replace").strip().splitlines()
    if done.returncode != 0 or not lines:
        raise RuntimeError(f"measuring {' '.join(args)} failed:\n{err[-2000:]}")
    got = json.loads(lines[-1])
    if got["code"] != 0:
        raise RuntimeError(f"{' '.join(args)} failed ({got['code']}):\n{err[-2000:]}")
    return {"wall_s": got["wall_s"], "cpu_s": got["cpu_s"], "peak_rss_mib": got["peak_rss_mib"]}


def extract_revision(rev: str, out: Path) -> Path:
    """The source tree of git revision ``rev`` (``git archive``) unpacked below ``out``:
    the baseline side of the A/B benchmarks."""
    import subprocess
    import tarfile

    repo = Path(__file__).resolve().parent.parent
    tar = out / "base.tar"
    with tar.open("wb") as f:
        subprocess.run(["git", "-C", str(repo), "archive", rev], stdout=f, check=True)
    dest = out / "base"
    with tarfile.open(tar) as t:
        t.extractall(dest, filter="data")
    return dest


def run_in_tree(code: str, tree: Path, *args: str) -> dict:
    """Run the Python ``code`` in a fresh process with ``tree`` first on the import path
    and return the JSON object it prints on a line starting with ``RESULT``."""
    import subprocess
    import sys

    env = dict(os.environ, PYTHONPATH=str(tree))
    out = subprocess.run(
        [sys.executable, "-c", code, str(tree), *args],
        capture_output=True,
        text=True,
        env=env,
        cwd=tree,
    )
    lines = [x for x in out.stdout.splitlines() if x.startswith("RESULT")]
    if not lines:
        raise RuntimeError(f"replay in {tree} failed:\n{out.stderr[-3000:]}")
    return json.loads(lines[0][len("RESULT") :])
