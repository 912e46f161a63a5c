"""Before / after of the per-frame front end and fusion in one run: two source trees (a git
revision and the working tree) replayed alternately, each in its own process.

Per process: the compiled kernels loaded (``bench_frontend.compiled_startup_s``), one warm-up
replay, then ``--replays`` replays of the simulated upstair trial through
``bench_frontend.replay_once`` with ``VIO_GRAPH_COMPILED=1`` (the numba paths, what long
recordings run): the estimator's stage times per frame (wall clock), the CPU time of every
``VisualFrontend.process`` call (``frontend_cpu``: the whole front end, the camera-fixed
test included) and of every ``OnlineEstimator.add_frame`` call. The processes alternate
base, working tree, base, ... ``--rounds`` times, so machine load hits both alike; medians
and p95 pool all frames of all replays of all rounds.

With ``--clock cpu`` the stage clocks (``time.perf_counter`` in vio_graph/estimator.py and
in vio_graph/frontend/frontend.py, whose per-stage times the estimator passes on) are replaced
in the child by ``time.process_time``, so every stage time (the front end's, fusion, safety,
kinematics) is CPU time: other processes on the machine's cores do not count. That is the
comparison to make on a shared machine. (Before 2026-12-03 evening only the estimator's clock
was replaced: the front end's stage rows were wall-clock time even with ``--clock cpu``.)

    python benchmarks/ab_frontend.py --base f239660~1 [--rounds 3] [--replays 2] [--clock cpu]
"""

from __future__ import annotations

import argparse
import tempfile
from pathlib import Path

import _common  # noqa: I001 - before numpy: pins the thread pools numpy reads on import
import numpy as np

STAGES = (
    "frontend_projection",
    "frontend_smoothing",
    "frontend_terrain",
    "frontend_corners",
    "frontend_icp",
    "frontend_total",
    "fusion",
    "frontend_plus_fusion",
    "safety",
    "kinematics",
)

_CHILD = r"""
import json, os, sys, time
tree, replays, clock = sys.argv[1], int(sys.argv[2]), sys.argv[3]
sys.path[:0] = [tree, os.path.join(tree, "benchmarks")]
os.environ["VIO_GRAPH_COMPILED"] = "1"
import _common  # noqa
import bench_frontend as bf
import vio_graph
import vio_graph.estimator as estimator_module
assert os.path.realpath(vio_graph.__file__).startswith(os.path.realpath(tree))
if clock == "cpu":
    class _CpuClock:  # the stage clocks of the estimator and the front end, in CPU time
        perf_counter = staticmethod(time.process_time)
    import vio_graph.frontend.frontend as frontend_module
    estimator_module.time = _CpuClock
    frontend_module.time = _CpuClock
from vio_graph.recording.reader import Recording
rec = Recording.open(bf.ensure_recording(None))
frames = [rec.frame(i) for i in range(rec.num_frames)]
bf.compiled_startup_s()
timed = bf._TimedIcp(bf.tracker_module.icp_translation_2d)
bf.tracker_module.icp_translation_2d = timed
from vio_graph.frontend.frontend import VisualFrontend
fe_cpu = []
process = VisualFrontend.process
def timed_process(self, *args, **kwargs):  # CPU time of the whole front end per frame
    c0 = time.process_time_ns()
    out = process(self, *args, **kwargs)
    fe_cpu.append((time.process_time_ns() - c0) * 1e-6)
    return out
VisualFrontend.process = timed_process
bf.replay_once(rec, frames, timed)  # warm-up
rows, cpu = [], []
fe_cpu.clear()
for _ in range(replays):
    run = bf.replay_once(rec, frames, timed)
    rows += run["timings"]
    cpu += run["frame_cpu_ms"]
print("RESULT" + json.dumps({"rows": rows, "add_frame_cpu_ms": cpu, "frontend_cpu_ms": fe_cpu}))
"""


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--base", required=True, help="git revision to compare against")
    ap.add_argument("--rounds", type=int, default=3)
    ap.add_argument("--replays", type=int, default=2, help="timed replays per process")
    ap.add_argument(
        "--clock", choices=("wall", "cpu"), default="wall", help="the stage times' clock"
    )
    args = ap.parse_args()
    new = Path(__file__).resolve().parent.parent
    pooled: dict[str, dict[str, list[float]]] = {
        name: {s: [] for s in (*STAGES, "frontend_cpu", "add_frame_cpu")}
        for name in ("base", "new")
    }
    with tempfile.TemporaryDirectory() as tmp:
        base = _common.extract_revision(args.base, Path(tmp))
        for r in range(args.rounds):
            for name, tree in (("base", base), ("new", new)):
                d = _common.run_in_tree(_CHILD, tree, str(args.replays), args.clock)
                for s in STAGES:
                    pooled[name][s] += [row.get(s, 0.0) for row in d["rows"]]
                pooled[name]["add_frame_cpu"] += d["add_frame_cpu_ms"]
                pooled[name]["frontend_cpu"] += d["frontend_cpu_ms"]
                ff = np.median([row["frontend_plus_fusion"] for row in d["rows"]])
                print(f"round {r} {name}: front end + fusion median {ff:.3f} ms", flush=True)
    print("| ms per frame | base median | base p95 | new median | new p95 | ratio of medians |")
    print("|---|---|---|---|---|---|")
    for s in (*STAGES, "frontend_cpu", "add_frame_cpu"):
        b, n = _common.stats_ms(pooled["base"][s]), _common.stats_ms(pooled["new"][s])
        print(
            f"| {s} | {b['median']:.3f} | {b['p95']:.3f} | {n['median']:.3f} | "
            f"{n['p95']:.3f} | {n['median'] / b['median']:.3f} |"
        )
    info = _common.machine_info()
    print(
        f"clock: {args.clock}; frames per side: {len(pooled['base']['fusion'])}; "
        f"load average (1, 5, 15 min): {info['load_average_1_5_15min']}"
    )


if __name__ == "__main__":
    main()
