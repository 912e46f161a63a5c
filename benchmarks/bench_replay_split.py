"""Where a replay's CPU goes per frame: the online estimator, the recording reader, and the
replay's own work (the event loop, the baselines beside the filter, the per-frame log).

``vio-graph run REC --mode filter`` spends most of its per-frame time in
``vio_graph.replay.Replay.run``; this splits that call three ways with ``time.process_time``
wrappers (~1 us a call, ~14,000 calls on a 60 s trial: ~0.01 ms a frame, on both sides alike;
``--detail`` splits the estimator and the replay's own work further, with ~30 more wrapped
calls a frame, exclusive times: a stage's time less that of the stages called in it):

* estimator: ``OnlineEstimator.process_frame``, ``add_imu`` and ``add_joints`` (the online
  path: front end, fusion, safety, IMU propagation);
* reader: ``Recording.frame`` (depth and confidence of one frame from disk);
* replay: the rest of ``Replay.run`` -- the event loop, the IMU-only and ICP-only baselines
  (vio_graph/filter/baselines.py), the filter's track and ``FrameLog.add``.

One process per tree and round (the default configuration, ``--mode filter``, no
visualizer); with ``--base REV`` that revision and the working tree alternate ``--rounds``
times, and medians over the rounds are printed. Each process first replays data/sample once
untimed with ``VIO_GRAPH_COMPILED=1`` (so a tree's first numba compile is not timed) and then
the recording under the default "auto" (compiled from 450 frames on).

    python benchmarks/bench_replay_split.py --recording REC [--base REV] [--rounds 3] [--detail]

REC: e.g. the 60 s trial of ``python benchmarks/bench_scale.py``
(results/scale/recordings/upstair_long_60s).
"""

from __future__ import annotations

import argparse
import tempfile
from pathlib import Path

import _common  # noqa: I001 - before numpy: pins the thread pools numpy reads on import
import numpy as np

_CHILD = r"""
import json, os, sys, time
tree, rec_path, detail = sys.argv[1], sys.argv[2], sys.argv[3] == "1"
sys.path[:0] = [tree, os.path.join(tree, "benchmarks")]
import _common  # noqa
import vio_graph
assert os.path.realpath(vio_graph.__file__).startswith(os.path.realpath(tree))
import vio_graph.estimator as E
import vio_graph.recording.reader as RD
import vio_graph.replay as RP
from vio_graph.config import load_config
from vio_graph.recording.reader import Recording
from vio_graph.replay import Replay
from vio_graph.viz.rerun_logger import NullVisualizer

def replay(path):
    rec = Recording.open(path)
    rp = Replay(rec, load_config(None), {"filter"}, NullVisualizer())
    t = time.process_time()
    rp.run()
    return rec.num_frames, time.process_time() - t

os.environ["VIO_GRAPH_COMPILED"] = "1"
replay(os.path.join(tree, "data", "sample"))  # untimed: loads (or compiles) the kernels
del os.environ["VIO_GRAPH_COMPILED"]
T = {"reader": 0.0}
inner = []  # exclusive times: a wrapped call's time less that of the wrapped calls in it

def wrap(obj, name, label):
    f = getattr(obj, name, None)
    if f is None:
        return  # (renamed or moved in this tree)
    def w(*a, **k):
        t = time.process_time()
        inner.append(0.0)
        try:
            return f(*a, **k)
        finally:
            dt = time.process_time() - t
            T[label] = T.get(label, 0.0) + dt - inner.pop()
            if inner:
                inner[-1] += dt
    setattr(obj, name, w)

wrap(E.OnlineEstimator, "process_frame", "estimator: rest" if detail else "estimator")
for n in ("add_imu", "add_joints"):
    wrap(E.OnlineEstimator, n, "estimator: IMU input" if detail else "estimator")
wrap(RD.Recording, "frame", "reader")
if detail:
    import vio_graph.filter.baselines as BL
    import vio_graph.filter.eskf as ES
    import vio_graph.frontend.frontend as FE
    import vio_graph.health as HE
    import vio_graph.protocol as PR
    import vio_graph.safety.online as SO
    wrap(FE.VisualFrontend, "process", "estimator: front end")
    wrap(SO.SafetyMonitor, "update", "estimator: safety outputs")
    for n in ("_fuse_landmarks", "_level_aiding", "_update_time_offset", "_test_frame_stamps",
              "_note_innovations", "_arbitrate_imu", "_recover_if_locked_out"):
        wrap(E.OnlineEstimator, n, "estimator: fusion")
    wrap(ES.SagittalEskf, "update_displacement", "estimator: fusion")
    wrap(HE.HealthMonitor, "add_frame", "estimator: fusion")
    for n in ("leg_points", "leg_angles", "_note_stand_surface"):
        wrap(E.OnlineEstimator, n, "estimator: kinematics")
    wrap(RP.FrameLog, "add", "replay: FrameLog.add")
    for cls in (BL.IcpOdometry, BL.ImuDeadReckoning, PR.FilterTrack):
        for n in ("add_frame", "add_imu"):
            wrap(cls, n, "replay: baselines and filter track")
n, run_s = replay(rec_path)
T["replay"] = run_s - sum(v for k, v in T.items() if not k.startswith("replay"))
if detail:
    T["estimator"] = sum(v for k, v in T.items() if k.startswith("estimator:"))
    own = sum(v for k, v in T.items() if k.startswith("replay:"))
    T["replay: rest (event loop, view)"] = T["replay"] - own
print("RESULT" + json.dumps({"frames": n, "run_s": run_s, **T}))
"""

PARTS = ("estimator", "reader", "replay")


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--recording", required=True, type=Path)
    ap.add_argument("--base", help="git revision to compare against (alternated)")
    ap.add_argument("--rounds", type=int, default=3)
    ap.add_argument(
        "--detail",
        action="store_true",
        help="split the estimator (front end, fusion, safety, kinematics, IMU input) and the "
        "replay's own work (FrameLog, baselines) further (~30 more wrapped calls a frame)",
    )
    args = ap.parse_args()
    rec = str(args.recording.resolve())
    new = Path(__file__).resolve().parent.parent
    with tempfile.TemporaryDirectory() as tmp:
        trees = {"new": new}
        if args.base:
            trees = {"base": _common.extract_revision(args.base, Path(tmp)), "new": new}
        res: dict[str, list[dict]] = {name: [] for name in trees}
        for r in range(args.rounds):
            for name, tree in trees.items():
                d = _common.run_in_tree(_CHILD, tree, rec, "1" if args.detail else "0")
                res[name].append(d)
                split = ", ".join(f"{p} {1e3 * d.get(p, 0.0) / d['frames']:.3f}" for p in PARTS)
                print(f"round {r} {name}: Replay.run {d['run_s']:.2f} s; ms/frame: {split}")
    for name, runs in res.items():
        parts = [p for p in runs[0] if p not in ("frames", "run_s")]
        med = {
            p: float(np.median([1e3 * d.get(p, 0.0) / d["frames"] for d in runs])) for p in parts
        }
        run_s = float(np.median([d["run_s"] for d in runs]))
        ms = float(np.median([1e3 * d["run_s"] / d["frames"] for d in runs]))
        print(f"{name} (median of {len(runs)}): Replay.run {run_s:.2f} s, {ms:.3f} ms/frame CPU")
        for p in sorted(parts):
            print(f"  {p:40s} {med[p]:.3f} ms/frame")


if __name__ == "__main__":
    main()
