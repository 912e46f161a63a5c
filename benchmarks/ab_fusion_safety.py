"""Before / after of the fusion and safety stages per frame, in CPU time: two source trees (a
git revision and the working tree) replayed alternately, each in its own process.

Per process: the compiled kernels loaded (``bench_frontend.compiled_startup_s``), one warm-up
replay, then ``--replays`` replays of the simulated upstair trial through
``bench_frontend.replay_once`` with ``VIO_GRAPH_COMPILED=1`` (the numba paths, what long
recordings and bench_frontend run). The estimator's stage clock (``time.perf_counter`` in
vio_graph/estimator.py) is replaced in the child by ``time.process_time``, so the stage times
(fusion: level-surface pitch and the SP-ESKF updates; safety: ``SafetyMonitor.update``;
kinematics) are CPU time: other processes on the machine's cores do not count. The processes
alternate base, working tree, base, ... ``--rounds`` times; medians and p95 pool all frames of
all replays of all rounds.

    python benchmarks/ab_fusion_safety.py --base 1b66439 [--rounds 4] [--replays 2]
"""

from __future__ import annotations

import argparse
import tempfile
from pathlib import Path

import _common  # noqa: I001 - before numpy: pins the thread pools numpy reads on import
import numpy as np

STAGES = ("fusion", "safety", "kinematics", "frontend_total")

_CHILD = r"""
import json, os, sys, time
tree, replays = sys.argv[1], int(sys.argv[2])
sys.path[:0] = [tree, os.path.join(tree, "benchmarks")]
os.environ["VIO_GRAPH_COMPILED"] = "1"
import _common  # noqa
import bench_frontend as bf
import vio_graph
import vio_graph.estimator as estimator_module
assert os.path.realpath(vio_graph.__file__).startswith(os.path.realpath(tree))


class _CpuClock:  # the estimator's stage clock, in CPU time
    perf_counter = staticmethod(time.process_time)


estimator_module.time = _CpuClock
from vio_graph.recording.reader import Recording
rec = Recording.open(bf.ensure_recording(None))
frames = [rec.frame(i) for i in range(rec.num_frames)]
bf.compiled_startup_s()
timed = bf._TimedIcp(bf.tracker_module.icp_translation_2d)
bf.tracker_module.icp_translation_2d = timed
bf.replay_once(rec, frames, timed)  # warm-up
rows, cpu = [], []
for _ in range(replays):
    run = bf.replay_once(rec, frames, timed)
    rows += run["timings"]
    cpu += run["frame_cpu_ms"]
print("RESULT" + json.dumps({"rows": rows, "add_frame_cpu_ms": cpu}))
"""


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--base", required=True, help="git revision to compare against")
    ap.add_argument("--rounds", type=int, default=4)
    ap.add_argument("--replays", type=int, default=2, help="timed replays per process")
    args = ap.parse_args()
    new = Path(__file__).resolve().parent.parent
    pooled: dict[str, dict[str, list[float]]] = {
        name: {s: [] for s in (*STAGES, "add_frame_cpu")} for name in ("base", "new")
    }
    with tempfile.TemporaryDirectory() as tmp:
        base = _common.extract_revision(args.base, Path(tmp))
        for r in range(args.rounds):
            for name, tree in (("base", base), ("new", new)):
                d = _common.run_in_tree(_CHILD, tree, str(args.replays))
                for s in STAGES:
                    pooled[name][s] += [row.get(s, 0.0) for row in d["rows"]]
                pooled[name]["add_frame_cpu"] += d["add_frame_cpu_ms"]
                med = {s: np.median([row.get(s, 0.0) for row in d["rows"]]) for s in STAGES[:2]}
                print(
                    f"round {r} {name}: fusion {med['fusion']:.3f} ms, "
                    f"safety {med['safety']:.3f} ms (CPU, median)",
                    flush=True,
                )
    print("| CPU ms per frame | base median | base p95 | new median | new p95 | ratio of medians |")
    print("|---|---|---|---|---|---|")
    for s in (*STAGES, "add_frame_cpu"):
        b, n = _common.stats_ms(pooled["base"][s]), _common.stats_ms(pooled["new"][s])
        print(
            f"| {s} | {b['median']:.3f} | {b['p95']:.3f} | {n['median']:.3f} | "
            f"{n['p95']:.3f} | {n['median'] / b['median']:.3f} |"
        )
    info = _common.machine_info()
    print(
        f"frames per side: {len(pooled['base']['fusion'])}; load average (1, 5, 15 min): "
        f"{info['load_average_1_5_15min']}"
    )


if __name__ == "__main__":
    main()
