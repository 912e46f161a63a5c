"""Before / after of the per-IMU-sample path in one run: two source trees (a git revision and
the working tree) replayed alternately, each in its own process, with the existing benchmark
replays.

Per process: the compiled kernels loaded (``bench_frontend.compiled_startup_s``), one warm-up
replay, then ``--replays`` replays of the simulated upstair trial through
``bench_frontend.replay_once`` (CPU time, ``time.process_time``, of every
``OnlineEstimator.add_imu`` call) and one through ``bench_smoother._replay_smoother`` (2 s
window: CPU time of the smoother's ``add_imu`` on samples that complete no keyframe).
``VIO_GRAPH_COMPILED=1`` in both (the numba path, what long recordings run). The processes
alternate base, working tree, base, ... ``--rounds`` times, so machine load hits both alike;
medians pool all samples of all rounds.

    python benchmarks/ab_imu_sample.py --base e89c802 [--rounds 3] [--replays 2]
"""

from __future__ import annotations

import argparse
import tempfile
from pathlib import Path

import _common  # noqa: I001 - before numpy: pins the thread pools numpy reads on import
import numpy as np

_CHILD = r"""
import json, os, sys
tree, replays = sys.argv[1], int(sys.argv[2])
sys.path[:0] = [tree, os.path.join(tree, "benchmarks")]
os.environ["VIO_GRAPH_COMPILED"] = "1"
import _common  # noqa
import bench_frontend as bf
import bench_smoother as bs
import vio_graph
assert os.path.realpath(vio_graph.__file__).startswith(os.path.realpath(tree))
from vio_graph.recording.reader import Recording
rec = Recording.open(bf.ensure_recording(None))
frames = [rec.frame(i) for i in range(rec.num_frames)]
bf.compiled_startup_s()
timed = bf._TimedIcp(bf.tracker_module.icp_translation_2d)
bf.tracker_module.icp_translation_2d = timed
bf.replay_once(rec, frames, timed)  # warm-up
imu = []
for _ in range(replays):
    imu += bf.replay_once(rec, frames, timed)["imu_cpu_us"]
sm = bs._replay_smoother(rec, 2.0, {"smoother"})
sm.pop("_replay")
print("RESULT" + json.dumps({"add_imu_us": imu, "smoother_us": sm["imu_input_us_per_sample"]}))
"""


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--base", required=True, help="git revision to compare against")
    ap.add_argument("--rounds", type=int, default=3)
    ap.add_argument("--replays", type=int, default=2, help="timed replays per process")
    args = ap.parse_args()
    new = Path(__file__).resolve().parent.parent
    with tempfile.TemporaryDirectory() as tmp:
        base = _common.extract_revision(args.base, Path(tmp))
        res: dict[str, dict[str, list]] = {
            name: {"add_imu_us": [], "smoother_us": []} for name in ("base", "new")
        }
        for r in range(args.rounds):
            for name, tree in (("base", base), ("new", new)):
                d = _common.run_in_tree(_CHILD, tree, str(args.replays))
                res[name]["add_imu_us"] += d["add_imu_us"]
                res[name]["smoother_us"].append(d["smoother_us"]["median"])
                print(
                    f"round {r} {name}: add_imu median {np.median(d['add_imu_us']):.1f} us, "
                    f"smoother add_imu median {d['smoother_us']['median']:.1f} us",
                    flush=True,
                )
    st = {k: _common.stats_ms(v["add_imu_us"]) for k, v in res.items()}
    for name in ("base", "new"):
        print(
            f"{name}: OnlineEstimator.add_imu CPU us median {st[name]['median']:.1f}, "
            f"p95 {st[name]['p95']:.1f} (n = {st[name]['n']}); smoother add_imu median per "
            f"process {', '.join(f'{v:.1f}' for v in res[name]['smoother_us'])} us"
        )
    print(f"ratio new / base (add_imu median): {st['new']['median'] / st['base']['median']:.3f}")


if __name__ == "__main__":
    main()
