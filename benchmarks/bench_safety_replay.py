"""CPU time of the safety replay metrics.json makes of the batch path
(vio_graph/evaluation/safety.py ``replay_safety``: the safety monitor over every frame of the
batch graph's legs, with the keyframe profiles turned to the batch's attitude and placed at
its camera positions), and of the
same monitor with every output (what the online pass computes on the filter's path).

The recording is replayed once in ``--mode batch`` (no outputs) to collect the monitor's
inputs, pickled to ``--cache`` (reused when present: a 600 s trial takes a minute or two);
then each replay runs ``--repeats`` times in this process, CPU seconds by
``time.process_time``, after a 200-frame warm-up (the numba kernels' load). The compiled
kernels are on, as the run turns them on for a long recording. ``rows`` is a hash of the
replay's per-frame outputs (the SafetyLog rows), to compare trees.

    python benchmarks/bench_safety_replay.py REC --cache results/safety_replay_600s.pkl
"""

from __future__ import annotations

import argparse
import hashlib
import pickle
import statistics
import time
from pathlib import Path

import _common  # noqa: F401  (threads pinned to 1)
import numpy as np

from vio_graph.config import load_config
from vio_graph.evaluation.safety import replay_safety
from vio_graph.frontend.icp import use_compiled_by_default
from vio_graph.safety.online import SafetyLog, SafetyMonitor


def _inputs(rec: str, cache: Path) -> dict:
    if cache.exists():
        with cache.open("rb") as f:
            return pickle.load(f)  # noqa: S301 (our own cache)
    from vio_graph.pipeline import leg_trajectories
    from vio_graph.recording.reader import Recording
    from vio_graph.replay import Replay
    from vio_graph.viz.rerun_logger import NullVisualizer

    cfg = load_config(None)
    replay = Replay(Recording.open(rec), cfg, {"batch"}, NullVisualizer())
    lg = replay.run()
    use_enc = cfg.kinematics.shank_pitch_source == "encoders"
    paths = {m: leg_trajectories(replay.rig, xz, lg, use_enc, m) for m, xz in lg.camera_xz.items()}
    d = {
        "t_s": np.asarray(lg.t_s, dtype=float),
        "cov": np.asarray(lg.cov_position_m2),
        "stance": list(lg.in_stance),
        "profiles": dict(lg.profiles),
        # metrics.json's batch replay places the profiles at the batch's own attitude
        "profiles_batch": dict(lg.profiles_of("batch")),
        "paths": paths,
    }
    cache.parent.mkdir(parents=True, exist_ok=True)
    with cache.open("wb") as f:
        pickle.dump(d, f, protocol=5)
    return d


def _full_replay(cfg, d: dict, path: dict, n: int) -> SafetyLog:
    """The monitor with every output over the first ``n`` frames of ``path``."""
    mon, out = SafetyMonitor(cfg), SafetyLog()
    for k in range(n):
        out.append(
            mon.update(
                float(d["t_s"][k]),
                path["camera"][k],
                d["cov"][k],
                path["heel"][k],
                path["toe"][k],
                bool(d["stance"][k]),
                d["profiles"].get(k),
            )  # fmt: skip
        )
    return out


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("recording")
    ap.add_argument("--cache", type=Path, required=True, help="pickle of the replay's inputs")
    ap.add_argument("--repeats", type=int, default=3)
    args = ap.parse_args()
    use_compiled_by_default(True)
    cfg = load_config(None).safety
    d = _inputs(args.recording, args.cache)
    n = len(d["t_s"])
    runs = {
        "metrics replay (batch path)": lambda m: replay_safety(
            cfg,
            d["t_s"][:m],
            d["paths"]["batch"],
            d["cov"],
            d["stance"],
            d.get("profiles_batch", d["profiles"]),
        ),
        "every output (filter path)": lambda m: _full_replay(cfg, d, d["paths"]["filter"], m),
    }
    for name, run in runs.items():
        run(min(n, 200))  # warm-up
        times, digest = [], ""
        for _ in range(args.repeats):
            t0 = time.process_time()
            out = run(n)
            times.append(time.process_time() - t0)
            digest = hashlib.sha1(out._rows.view().tobytes()).hexdigest()[:12]
        print(
            f"{name}: {n} frames, CPU s median {statistics.median(times):.3f} "
            f"(runs {', '.join(f'{t:.3f}' for t in times)}), rows {digest}"
        )


if __name__ == "__main__":
    main()
