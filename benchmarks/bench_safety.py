"""Per-frame latency of the foot-to-terrain safety outputs (``SafetyMonitor.update``,
vio_graph/safety/online.py), single thread, per configuration (today's, the constant-velocity
motion model, and the configuration before 2026-12) and per implementation: the compiled
kernels on the incremental map (what a long run and bench_frontend use), the same in numpy,
and the numpy reference whose map rebuilds its whole profile and edges at each keyframe (the
numpy default; tests/test_safety_incremental.py: all of them give the same outputs). The
compiled monitor runs each step of a frame in one kernel call (keyframe step, clearance and
next edge, prediction: ``fused``); "per-operation kernels" is the same monitor calling the
kernels of the single operations with Python between them, as before they were fused.
Target: 0.2 ms per frame.

The filter is replayed once on each recording to collect the monitor's inputs (camera,
covariance, heel, toe, stance, keyframe profiles); then only the monitor is run over those
frames ``--repeats`` times per implementation (interleaved), each ``update`` timed with
``time.process_time`` (CPU time: other processes on the core do not count). Statistics pool
all frames of all repeats; keyframe frames (which also add the profile to the map) are
reported separately. Threads: BLAS / OpenMP pinned to 1 (``_common``). The machine's load
average is written beside the numbers (benchmarks/results/safety.json): the machine this ran
on is shared, so the median is the figure to read.

    python benchmarks/bench_safety.py data/recordings/upstair_s1 data/recordings/downstair_s1
    python benchmarks/bench_safety.py data/recordings/upstair_s1 --compiled-only --repeats 10
"""

from __future__ import annotations

import argparse
import time
from pathlib import Path

import _common
import numpy as np

from vio_graph.config import load_config
from vio_graph.recording.reader import Recording
from vio_graph.safety.config import SafetyConfig
from vio_graph.safety.online import SafetyMonitor

PATHS = {  # label: SafetyMonitor arguments
    "compiled, incremental map": {"compiled": True},
    "compiled, per-operation kernels": {"compiled": True, "fused": False},
    "numpy, incremental map": {"incremental": True, "compiled": False},
    "numpy reference (map rebuilt per keyframe)": {"incremental": False},
}
TARGET_MS = 0.2
VARIANTS = {  # label: SafetyConfig overrides
    "default (swing template)": {},
    "default without the warning's prediction check": {"warning_error_check": False},
    "default without foot contact in the map": {"contact_map": False},
    "constant velocity": {"motion_model": "constant_velocity"},
    "before 2026-12 (mean map, 1 cm bins, constant velocity, 0.2 s)": {
        "motion_model": "constant_velocity",
        "horizon_s": 0.2,
        "map_statistic": "mean",
        "bin_m": 0.01,
        "min_keyframes": 2,
    },
}


def bench(path: Path, repeats: int, paths: dict[str, dict]) -> list[dict]:
    cfg = load_config(None)
    rec = Recording.open(path)
    lg, est = _common.filter_leg_run(rec, cfg)
    t = np.asarray(lg.t_s)
    kf = np.zeros(len(t), bool)
    kf[list(lg.profiles)] = True
    rows = []
    for label, over in VARIANTS.items():
        sc = SafetyConfig(**{**cfg.safety.model_dump(), **over})
        ms: dict[str, list[float]] = {p: [] for p in paths}
        for _ in range(repeats):
            for p, kw in paths.items():
                mon = SafetyMonitor(sc, **kw)
                for k in range(len(t)):
                    t0 = time.process_time_ns()
                    _common.monitor_update(mon, lg, est, k)
                    ms[p].append((time.process_time_ns() - t0) * 1e-6)
        for p in paths:
            a = np.asarray(ms[p]).reshape(repeats, -1)
            rows.append(
                {
                    "recording": path.name,
                    "variant": label,
                    "path": p,
                    "all": _common.stats_ms(a),
                    "keyframes": _common.stats_ms(a[:, kf]),
                    "other_frames": _common.stats_ms(a[:, ~kf]),
                }
            )
    return rows


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("recordings", nargs="+", type=Path, help="recording folders")
    ap.add_argument("--repeats", type=int, default=5, help="monitor replays per recording")
    ap.add_argument("--compiled-only", action="store_true", help="only the compiled paths")
    args = ap.parse_args()
    paths = {p: kw for p, kw in PATHS.items() if kw.get("compiled") or not args.compiled_only}
    rows = [r for p in args.recordings for r in bench(p, args.repeats, paths)]
    out = _common.write_result(
        "safety", {"repeats": args.repeats, "target_ms": TARGET_MS, "rows": rows}
    )
    table = [
        [
            r["recording"],
            r["variant"],
            r["path"],
            r["all"]["n"],
            _common.fmt(r["all"]["median"], 3),
            _common.fmt(r["all"]["p95"], 3),
            _common.fmt(r["keyframes"]["median"], 3),
            _common.fmt(r["other_frames"]["median"], 3),
        ]
        for r in rows
    ]
    print(
        _common.md_table(
            [
                "recording",
                "safety config",
                "implementation",
                "frames",
                "median ms",
                "p95 ms",
                "keyframes median ms",
                "other frames median ms",
            ],
            table,
        )
    )
    print(f"target: <= {TARGET_MS} ms per frame (CPU time, median)")
    print(f"load average (1, 5, 15 min): {_common.machine_info()['load_average_1_5_15min']}")
    print(f"wrote {out}")


if __name__ == "__main__":
    main()
