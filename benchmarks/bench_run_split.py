"""Where a whole ``vio-graph run`` spends its CPU besides the online estimator: start-up
(imports, configuration, opening the recording, building the estimators with the first
numba kernels), the replay's parts, the end-of-run stages, and the cyclic garbage
collector's own time.

One child process per tree and round runs the command line's entry point in-process with
``time.process_time`` wrappers around the parts (inclusive times, ~1 us a call) and a
``gc.callbacks`` hook timing every collection (that time is also inside the part that
triggered it); the rest of the process (interpreter, imports, the command line, exit) is
``other``. With ``--base REV`` that revision (``git
archive``; its first process compiles numba's cache, untimed) and this tree alternate
``--rounds`` times and the medians over the rounds are printed side by side.

    python benchmarks/bench_run_split.py --recording REC [--mode all] [--base REV] [--rounds 3]
        [--plots]

(``--base-tree DIR`` instead of ``--base``: a base tree already unpacked, whose numba cache
is then reused.)

REC: e.g. the 30 s or 60 s trial of ``python benchmarks/bench_scale.py``. The run writes
into a temporary folder with ``--no-rerun --no-plots``; with ``--plots``, ``--no-rerun``
only (the figures of a default run), and the figures get rows of their own: the overview and
clearance PNGs, and the map PNG, which is also inside the row of the map's files
(``export_map``: PLY, PCD, JSON, CSV and the PNG; a row of its own with or without
``--plots``).
"""

from __future__ import annotations

import argparse
import statistics
import tempfile
from pathlib import Path

import _common  # noqa: I001 - before numpy: pins the thread pools numpy reads on import

_CHILD = r"""
import functools, gc, json, os, sys, time
tree, rec, mode, out, plots = sys.argv[1:6]
sys.path.insert(0, tree)
T = {}
N = {}
def wrap(obj, name, label):
    f = getattr(obj, name, None)
    if f is None:
        return  # (renamed or moved in this tree)
    @functools.wraps(f)
    def w(*a, **k):
        t = time.process_time()
        try:
            return f(*a, **k)
        finally:
            T[label] = T.get(label, 0.0) + time.process_time() - t
            N[label] = N.get(label, 0) + 1
    setattr(obj, name, w)
start = {}
def on_gc(phase, info):
    if phase == "start":
        start["t"] = time.process_time()
    else:
        T["garbage collector"] = T.get("garbage collector", 0.0) + time.process_time() - start["t"]
        N["garbage collector"] = N.get("garbage collector", 0) + 1
gc.callbacks.append(on_gc)
import vio_graph
assert os.path.realpath(vio_graph.__file__).startswith(os.path.realpath(tree))
import vio_graph.cli as cli
import vio_graph.pipeline as PL
import vio_graph.replay as RP
import vio_graph.estimator as E
import vio_graph.recording.reader as RD
import vio_graph.evaluation.safety as ES
wrap(RD.Recording, "open", "start-up: open the recording")
wrap(RP.Replay, "__init__", "start-up: estimators and first kernels (Replay)")
wrap(RP.Replay, "run", "replay")
wrap(E.OnlineEstimator, "process_frame", "replay: online estimator, frames")
wrap(E.OnlineEstimator, "add_imu", "replay: online estimator, IMU")
wrap(RD.Recording, "frame", "replay: reading depth frames")
wrap(PL, "write_trajectories", "end: TUM files")
wrap(PL, "write_frames_csv", "end: frames.csv")
wrap(PL, "_evaluate", "end: metrics")
wrap(ES, "safety_metrics", "end: safety metrics (replays)")
wrap(PL, "build_run_map", "end: map")
import vio_graph.mapping.export as MX
wrap(MX, "export_map", "end: map files (PLY, PCD, JSON, CSV; PNG with --plots)")
if plots == "plots":
    import vio_graph.viz.plots as VP
    wrap(VP, "plot_run_overview", "end: overview PNG")
    wrap(VP, "plot_clearance", "end: clearance PNG")
    wrap(MX, "write_map_png", "(within the map files) map PNG")
guard = RP.Replay._guard
def by_estimator(self, e, t_s, fn, *a):
    t = time.process_time()
    try:
        return guard(self, e, t_s, fn, *a)
    finally:
        label = "replay: " + e.name + (" (finish)" if fn.__name__ == "finish" else "")
        T[label] = T.get(label, 0.0) + time.process_time() - t
RP.Replay._guard = by_estimator
sys.argv = ["vio-graph", "run", rec, "--out", out, "--mode", mode, "--no-rerun", "--overwrite"]
if plots != "plots":
    sys.argv.append("--no-plots")
import contextlib, io
with contextlib.redirect_stdout(io.StringIO()):
    try:
        cli.main()
    except SystemExit as exc:
        assert not exc.code, exc.code
t = os.times()
T["process"] = t.user + t.system
if "replay" in T:  # the event loop, the frame log, the view: the replay less its parts
    T["replay: rest"] = T.pop("replay") - sum(v for k, v in T.items() if k.startswith("replay:"))
parts = ("start-up:", "replay:", "end:")
T["other (interpreter, imports, CLI, exit)"] = T["process"] - sum(
    v for k, v in T.items() if k.startswith(parts)
)
print("RESULT" + json.dumps({"T": T, "N": N}))
"""


def _round(tree: Path, rec: Path, mode: str, tmp: Path, plots: bool = False) -> dict:
    flag = "plots" if plots else "no-plots"
    return _common.run_in_tree(_CHILD, tree, str(rec.resolve()), mode, str(tmp / "out"), flag)


def _table(rows: dict[str, list[dict]]) -> str:
    names = list(rows)
    labels: list[str] = []
    for runs in rows.values():
        for r in runs:
            labels += [k for k in r["T"] if k not in labels and k != "process"]
    order = sorted(labels, key=lambda k: (k.split(":")[0], k))
    med = {
        n: {k: statistics.median(r["T"].get(k, 0.0) for r in rows[n]) for k in labels}
        for n in names
    }
    proc = {n: statistics.median(r["T"]["process"] for r in rows[n]) for n in names}
    lines = [
        "| CPU s (median of rounds) | " + " | ".join(names) + " |",
        "|---" * (len(names) + 1) + "|",
    ]
    for k in order:
        cells = [f"{med[n][k]:.3f}" for n in names]
        lines.append(f"| {k} | " + " | ".join(cells) + " |")
    lines.append("| **process** | " + " | ".join(f"**{proc[n]:.3f}**" for n in names) + " |")
    return "\n".join(lines)


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--recording", required=True, type=Path)
    ap.add_argument("--mode", default="filter")
    ap.add_argument("--base", help="git revision to compare against (alternated)")
    ap.add_argument(
        "--base-tree", type=Path, help="instead of --base: a source tree already unpacked"
    )
    ap.add_argument("--rounds", type=int, default=3)
    ap.add_argument("--plots", action="store_true", help="draw the figures too (rows of their own)")
    args = ap.parse_args()
    here = _common.BENCH_DIR.parent
    with tempfile.TemporaryDirectory() as tmp_s:
        tmp = Path(tmp_s)
        trees = {"this tree": here}
        if args.base or args.base_tree:
            base = args.base_tree or _common.extract_revision(args.base, tmp)
            _round(base, args.recording, args.mode, tmp, args.plots)  # untimed: numba's cache
            trees = {args.base or "base": base, **trees}
        rows: dict[str, list[dict]] = {n: [] for n in trees}
        for k in range(args.rounds):
            for name, tree in trees.items():
                r = _round(tree, args.recording, args.mode, tmp, args.plots)
                rows[name].append(r)
                print(f"round {k} {name}: process {r['T']['process']:.2f} s CPU", flush=True)
    print(_table(rows))


if __name__ == "__main__":
    main()
