"""Paired A/B of fixed-lag smoother settings in one process: per keyframe CPU time of the
iSAM2 update (with its bookkeeping) and of the factor building, the settings alternated.

The smoother's input (every ``add_imu`` / ``add_frame`` / ``finish`` call of a replay through
``vio_graph.replay.Replay``, front end and filter as in ``vio-graph run``) is recorded once per
recording; each round then feeds that same stream to a fresh ``SlidingWindowSmoother`` per
setting, A, B, A, B, ..., so machine load hits both alike. Times are CPU time
(``time.process_time``), not wall time: on a shared machine a preempted update would
otherwise count another process's slice. Reported: medians (and means, p95) per setting,
pooled over rounds, the ratios B / A, the iSAM2 variables re-eliminated per update, and the
largest difference of the keyframe camera positions between A and B.

    python benchmarks/ab_fixed_lag.py --a fixed_lag_factorization=QR marginalization_slack_s=0
        [--b ...] [--recording REC ...] [--rounds 5]

``--a`` / ``--b`` take ``field=value`` items of ``SmootherConfig`` (values parsed as YAML);
``--a`` defaults to the configuration as it is.
"""

from __future__ import annotations

import argparse
import time
from pathlib import Path
from typing import Any

import _common  # noqa: I001 - first: pins thread pools before numpy is imported
import numpy as np
import yaml

from vio_graph.smoother.sliding_window import SlidingWindowSmoother

_CALLS = ("add_imu", "add_frame", "finish")


def capture(rec_dir: Path) -> tuple[list[tuple[str, tuple]], Any, np.ndarray]:
    """Replay ``rec_dir`` with the fixed-lag smoother; its input calls (the last smoother the
    replay made, after any retroactive re-run), its config and the IMU-camera transform."""
    from vio_graph.config import PipelineConfig
    from vio_graph.recording.reader import Recording
    from vio_graph.replay import Replay
    from vio_graph.viz.rerun_logger import NullVisualizer

    saved = {n: getattr(SlidingWindowSmoother, n) for n in (*_CALLS, "__init__")}
    made: list[SlidingWindowSmoother] = []

    def init(self, *a: Any, **k: Any) -> None:
        saved["__init__"](self, *a, **k)
        self._ab_calls = []
        made.append(self)

    def recorder(name: str):
        inner = saved[name]

        def call(self, *a: Any) -> Any:
            self._ab_calls.append((name, a))
            return inner(self, *a)

        return call

    SlidingWindowSmoother.__init__ = init
    for n in _CALLS:
        setattr(SlidingWindowSmoother, n, recorder(n))
    try:
        replay = Replay(Recording.open(rec_dir), PipelineConfig(), {"smoother"}, NullVisualizer())
        replay.run()
    finally:
        for n, f in saved.items():
            setattr(SlidingWindowSmoother, n, f)
    sm = made[-1]
    return sm._ab_calls, sm.config, replay.rig.shank_imu_T_cam


def feed(calls: list[tuple[str, tuple]], config: Any, imu_T_cam: np.ndarray) -> dict[str, Any]:
    """One smoother fed ``calls``; CPU ms per keyframe of the update and of the building."""
    upd: list[float] = []
    build: list[float] = []
    reelim: list[int] = []
    s = SlidingWindowSmoother(config, imu_T_cam)
    consume, complete = s._consume, s._builder._complete_pending

    def timed_consume(u: Any) -> None:
        c0 = time.process_time()
        consume(u)
        upd.append((time.process_time() - c0) * 1e3)
        reelim.append(s._smoother.getISAM2Result().getVariablesReeliminated())

    def timed_complete() -> Any:
        c0 = time.process_time()
        out = complete()
        build.append((time.process_time() - c0) * 1e3)
        return out

    s._consume = timed_consume  # type: ignore[method-assign]
    s._builder._complete_pending = timed_complete  # type: ignore[method-assign]
    for name, args in calls:
        getattr(s, name)(*args)
    xz = np.array([e.camera_xz_m for e in s.keyframe_estimates(with_covariance=False)])
    return {"update": upd, "build": build, "reelim": reelim, "xz": xz, "smoother": s}


def parse_items(items: list[str]) -> dict[str, Any]:
    out = {}
    for item in items:
        key, _, value = item.partition("=")
        out[key] = yaml.safe_load(value)
    return out


def run(recordings: list[Path], a: dict[str, Any], b: dict[str, Any], rounds: int) -> dict:
    rows = []
    for rec in recordings:
        calls, config, T = capture(rec)
        cfg = {"A": config.model_copy(update=a), "B": config.model_copy(update=b)}
        for k, c in cfg.items():  # validated like a config file
            cfg[k] = type(config).model_validate(c.model_dump())
        res: dict[str, dict[str, list]] = {
            k: {"update": [], "build": [], "reelim": []} for k in cfg
        }
        xz: dict[str, np.ndarray] = {}
        fallback: dict[str, Any] = {}
        for r in range(rounds):
            for k in ("A", "B") if r % 2 == 0 else ("B", "A"):
                out = feed(calls, cfg[k], T)
                for m in ("update", "build", "reelim"):
                    res[k][m] += out[m]
                xz[k] = out["xz"]
                fallback[k] = out["smoother"].qr_fallback_at_s
        row: dict[str, Any] = {"recording": _common.display_path(rec), "rounds": rounds}
        for k in ("A", "B"):
            upd, build = np.asarray(res[k]["update"]), np.asarray(res[k]["build"])
            n = min(upd.size, build.size)
            row[k] = {
                "update_ms": _common.stats_ms(upd),
                "build_ms": _common.stats_ms(build),
                "update_plus_build_ms": _common.stats_ms(upd[:n] + build[:n]),
                "reeliminated_mean": float(np.mean(res[k]["reelim"])),
                "qr_fallback_at_s": fallback[k],
            }
        for m in ("update_ms", "update_plus_build_ms"):
            row[f"ratio_{m}_median"] = row["B"][m]["median"] / row["A"][m]["median"]
            row[f"ratio_{m}_mean"] = row["B"][m]["mean"] / row["A"][m]["mean"]
        row["max_xz_difference_mm"] = float(np.nanmax(np.abs(xz["B"] - xz["A"]))) * 1e3
        rows.append(row)
        print_row(row)
    return {"a": a, "b": b, "rows": rows}


def print_row(row: dict[str, Any]) -> None:
    f = _common.fmt
    print(f"{row['recording']} ({row['rounds']} rounds)")  # noqa: T201
    for k in ("A", "B"):
        r = row[k]
        print(  # noqa: T201
            f"  {k}: update median {f(r['update_ms']['median'], 3)} ms (mean "
            f"{f(r['update_ms']['mean'], 3)}, p95 {f(r['update_ms']['p95'], 3)}), build median "
            f"{f(r['build_ms']['median'], 3)} ms, update + build median "
            f"{f(r['update_plus_build_ms']['median'], 3)} ms (mean "
            f"{f(r['update_plus_build_ms']['mean'], 3)}), re-eliminated "
            f"{r['reeliminated_mean']:.1f} per update, QR fallback {r['qr_fallback_at_s']}"
        )
    print(  # noqa: T201
        f"  B/A: update median {row['ratio_update_ms_median']:.3f} (mean "
        f"{row['ratio_update_ms_mean']:.3f}), update + build median "
        f"{row['ratio_update_plus_build_ms_median']:.3f} (mean "
        f"{row['ratio_update_plus_build_ms_mean']:.3f}); keyframes differ by at most "
        f"{row['max_xz_difference_mm']:.4f} mm"
    )


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--a", nargs="*", default=[], help="SmootherConfig items of A (field=value)")
    ap.add_argument("--b", nargs="*", default=[], help="SmootherConfig items of B (field=value)")
    ap.add_argument("--recording", type=Path, action="append", help="(repeatable)")
    ap.add_argument("--rounds", type=int, default=5)
    args = ap.parse_args()
    from bench_frontend import ensure_recording

    recs = args.recording or [ensure_recording(None)]
    result = run(recs, parse_items(args.a), parse_items(args.b), args.rounds)
    _common.write_result("ab_fixed_lag", result)


if __name__ == "__main__":
    main()
