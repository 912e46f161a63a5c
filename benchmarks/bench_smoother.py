"""Benchmark of the GTSAM smoother, on synthetic trials and on a simulated recording replayed
through ``vio_graph.pipeline``.

- fixed-lag (synthetic): per-keyframe update time (median, p95) for windows of 0.5, 1, 2 and
  4 s on a 30 s swinging-shank trial (10 Hz keyframes, 5 mm displacement noise, corner
  landmarks while stairs are in view);
- batch (synthetic): solve time (and build time) for 10, 30 and 60 s trials;
- replay: the same windows and the batch solve on the simulated upstair trial (seed 1, 10 s)
  replayed by ``vio_graph.replay.Replay`` (front end, filter and smoother exactly as in
  ``vio-graph run``; no visualisation), keyframe times from the smoother itself.

Writes benchmarks/results/smoother.json (threads pinned to 1 by ``_common``).

    python benchmarks/bench_smoother.py [--quick] [--recording DIR]
"""

from __future__ import annotations

import argparse
import os
import time
from pathlib import Path
from typing import Any

import _common  # noqa: I001 - first: pins thread pools before numpy is imported
import numpy as np

# the compiled step means (smoother/compiled_sampling.py), what a long recording uses; the
# replay's 2 s window also runs once with the numpy sampler (``numpy_leg``)
os.environ.setdefault("VIO_GRAPH_COMPILED", "1")

from vio_graph.smoother.batch import BatchSmoother
from vio_graph.smoother.config import SmootherConfig
from vio_graph.smoother.sliding_window import SlidingWindowSmoother
from vio_graph.smoother.synthetic import SyntheticTrial, feed, make_swinging_shank_trial

WINDOWS_S = [0.5, 1.0, 2.0, 4.0]


def trial(duration_s: float) -> SyntheticTrial:
    return make_swinging_shank_trial(
        duration_s,
        displacement_sigma_m=0.005,
        observation_sigma_m=0.005,
        accel_bias_mps2=(0.02, 0.0, -0.01),
        seed=7,
    )


def keyframe_ate_m(tr: SyntheticTrial, smoother: object) -> float:
    est = smoother.keyframe_estimates(with_covariance=False)  # type: ignore[attr-defined]
    xz = np.array([e.camera_xz_m for e in est])
    idx = np.flatnonzero(tr.is_keyframe)
    return float(np.sqrt(np.mean(np.sum((xz - tr.camera_xz_true_m[idx]) ** 2, axis=1))))


def filter_ate_m(tr: SyntheticTrial) -> float:
    idx = np.flatnonzero(tr.is_keyframe)
    d = tr.filter_xz_m[idx] - tr.camera_xz_true_m[idx]
    return float(np.sqrt(np.mean(np.sum(d**2, axis=1))))


def bench_fixed_lag(duration_s: float, windows_s: list[float]) -> list[dict]:
    tr = trial(duration_s)
    rows = []
    for w in windows_s:
        s = SlidingWindowSmoother(SmootherConfig(window_s=w), tr.imu_T_cam)
        t0 = time.perf_counter()
        feed(tr, s)
        wall = time.perf_counter() - t0
        upd = np.asarray(s.update_times_ms)
        build = np.asarray(s.build_times_ms)
        rows.append(
            {
                "window_s": w,
                "trial_s": duration_s,
                "keyframes": int(upd.size),
                "update_ms_median": float(np.median(upd)),
                "update_ms_p95": float(np.percentile(upd, 95)),
                "build_ms_median": float(np.median(build)),
                "build_ms_p95": float(np.percentile(build, 95)),
                "total_wall_s": wall,
                "keyframe_ate_mm": 1e3 * keyframe_ate_m(tr, s),
                "filter_ate_mm": 1e3 * filter_ate_m(tr),
            }
        )
    return rows


def bench_batch(durations_s: list[float]) -> list[dict]:
    rows = []
    for d in durations_s:
        tr = trial(d)
        s = BatchSmoother(SmootherConfig(), tr.imu_T_cam)
        t0 = time.perf_counter()
        feed(tr, s)
        build = time.perf_counter() - t0
        s.solve()
        rows.append(
            {
                "trial_s": d,
                "keyframes": len(s.keyframe_estimates(with_covariance=False)),
                "factors": int(s.graph.nrFactors()),
                "build_s": build,
                "solve_s": s.solve_time_ms / 1e3,
                "iterations": s.solve_iterations,
                "keyframe_ate_mm": 1e3 * keyframe_ate_m(tr, s),
                "filter_ate_mm": 1e3 * filter_ate_m(tr),
            }
        )
    return rows


def markdown_synthetic(fixed: list[dict], batch: list[dict], meta: dict) -> str:
    lines = [
        f"Synthetic swinging shank. {meta['note']}",
        "",
        "Fixed-lag (IncrementalFixedLagSmoother, "
        f"{SmootherConfig().fixed_lag_factorization} factorisation), per keyframe:",
        "",
        "| window s | keyframes | update ms median | update ms p95 | build ms median "
        "| build ms p95 | ATE mm (smoother) | ATE mm (filter guess) |",
        "|---|---|---|---|---|---|---|---|",
    ]
    for r in fixed:
        lines.append(
            f"| {r['window_s']:.1f} | {r['keyframes']} | {r['update_ms_median']:.2f} "
            f"| {r['update_ms_p95']:.2f} | {r['build_ms_median']:.2f} | {r['build_ms_p95']:.2f} "
            f"| {r['keyframe_ate_mm']:.1f} | {r['filter_ate_mm']:.1f} |"
        )
    lines += [
        "",
        "Batch (Levenberg-Marquardt, multifrontal QR):",
        "",
        "| trial s | keyframes | factors | build s | solve s | LM iterations "
        "| ATE mm (smoother) | ATE mm (filter guess) |",
        "|---|---|---|---|---|---|---|---|",
    ]
    for r in batch:
        lines.append(
            f"| {r['trial_s']:.0f} | {r['keyframes']} | {r['factors']} | {r['build_s']:.2f} "
            f"| {r['solve_s']:.2f} | {r['iterations']} | {r['keyframe_ate_mm']:.1f} "
            f"| {r['filter_ate_mm']:.1f} |"
        )
    lines.append("")
    return "\n".join(lines)


def _timed_imu_input(sm: Any) -> list[float]:
    """Wrap the smoother's ``add_imu`` (the per-sample preintegration input): CPU time (us) of
    every call that completes no keyframe (those include the keyframe's factor building)."""
    out: list[float] = []
    inner = sm.add_imu

    def add_imu(step: Any) -> None:
        n = len(sm.build_times_ms)
        c0 = time.process_time_ns()
        inner(step)
        if len(sm.build_times_ms) == n:
            out.append((time.process_time_ns() - c0) * 1e-3)

    sm.add_imu = add_imu
    return out


def _replay_smoother(rec: Any, w: float, modes: set[str], compiled: bool = True) -> dict[str, Any]:
    """One replay with a fixed-lag window of ``w`` s; the smoother's per-keyframe times."""
    from vio_graph.config import PipelineConfig
    from vio_graph.filter import fast_imu
    from vio_graph.replay import Replay
    from vio_graph.viz.rerun_logger import NullVisualizer

    base = PipelineConfig()
    config = base.model_copy(update={"smoother": base.smoother.model_copy(update={"window_s": w})})
    fast_imu.USE_COMPILED[0] = compiled
    try:
        replay = Replay(rec, config, modes, NullVisualizer())
    finally:
        fast_imu.USE_COMPILED[0] = True
    sm = replay.estimators["smoother"]
    imu_us = _timed_imu_input(sm)
    t0 = time.perf_counter()
    replay.run()
    wall = time.perf_counter() - t0
    k = min(len(sm.update_times_ms), len(sm.build_times_ms))
    upd, build = np.asarray(sm.update_times_ms[:k]), np.asarray(sm.build_times_ms[:k])
    return {
        "window_s": w,
        "keyframes": k,
        "update_ms": _common.stats_ms(upd),
        "build_ms": _common.stats_ms(build),
        "update_plus_build_ms": _common.stats_ms(upd + build),
        "imu_input_us_per_sample": _common.stats_ms(imu_us),
        "replay_wall_s": wall,
        "_replay": replay,
    }


def bench_replay(recording: Path, windows_s: list[float]) -> dict[str, Any]:
    """The smoother inside the real replay loop, one replay per window (batch on the first);
    the 2 s window (or the first) again with the numpy step means, right after it."""
    from vio_graph.recording.reader import Recording

    rec = Recording.open(recording)
    rows, batch = [], {}
    numpy_leg: dict[str, Any] = {}
    leg_w = 2.0 if 2.0 in windows_s else windows_s[0]
    for n, w in enumerate(windows_s):
        modes = {"smoother", "batch"} if n == 0 else {"smoother"}
        row = _replay_smoother(rec, w, modes)
        replay = row.pop("_replay")
        rows.append(row)
        if w == leg_w:
            numpy_leg = _replay_smoother(rec, w, {"smoother"}, compiled=False)
            numpy_leg.pop("_replay")
        if "batch" in replay.estimators:
            b = replay.estimators["batch"]
            batch = {
                "trial_s": float(rec.frame_timestamps_s[-1] - rec.frame_timestamps_s[0]),
                "keyframes": len(b.keyframe_estimates(with_covariance=False)),
                "factors": int(b.graph.nrFactors()),
                "solve_s": b.solve_time_ms / 1e3,
                "iterations": b.solve_iterations,
            }
    return {
        "recording": _common.display_path(str(recording)),
        "frames": rec.num_frames,
        "fixed_lag": rows,
        # the same window with the numpy step means (imu_sampling.common_frame_samples) and the
        # Python per-sample path: what a short recording runs without VIO_GRAPH_COMPILED=1
        "numpy_sampler": numpy_leg,
        "batch": batch,
    }


def run(quick: bool = False, recording: Path | None = None) -> dict[str, Any]:
    fixed_trial = 10.0 if quick else 30.0
    batch_trials = [10.0] if quick else [10.0, 30.0, 60.0]
    fixed = bench_fixed_lag(fixed_trial, WINDOWS_S)
    batch = bench_batch(batch_trials)
    note = (
        "update = smoother update + bookkeeping (no marginal: marginal_covariance none); "
        "build = preintegration + factor construction. Corners exist only for x < 12.5 m "
        "(the first ~14 s), after that only relative measurements constrain the drift."
    )
    from bench_frontend import ensure_recording

    replay = bench_replay(ensure_recording(recording), WINDOWS_S[:1] if quick else WINDOWS_S)
    return {"meta": {"note": note}, "fixed_lag": fixed, "batch": batch, "replay": replay}


def markdown(r: dict[str, Any]) -> str:
    f = _common.fmt
    rp = r["replay"]
    rows = [
        [
            f(x["window_s"], 1),
            x["keyframes"],
            f(x["update_ms"]["median"]),
            f(x["update_ms"]["p95"]),
            f(x["build_ms"]["median"]),
            f(x["build_ms"]["p95"]),
            f(x["update_plus_build_ms"]["median"]),
            f(x["update_plus_build_ms"]["p95"]),
        ]
        for x in rp["fixed_lag"]
    ]
    b = rp["batch"]
    leg = rp.get("numpy_sampler")
    lines = [
        f"Replay of the simulated upstair trial ({rp['frames']} frames) through "
        "`vio_graph.replay.Replay` (the smoother as `vio-graph run` uses it), per keyframe:",
        "",
        _common.md_table(
            [
                "window s",
                "keyframes",
                "update ms median",
                "update ms p95",
                "build ms median",
                "build ms p95",
                "total ms median",
                "total ms p95",
            ],
            rows,
        ),
        "",
    ]
    if leg:
        same = [x for x in rp["fixed_lag"] if x["window_s"] == leg["window_s"]][0]
        lines += [
            f"Preintegration step means compiled with numba (smoother/compiled_sampling.py, "
            f"`VIO_GRAPH_COMPILED=1` as on long recordings) against the numpy sampler "
            f"(imu_sampling.common_frame_samples, the tested reference; short recordings), "
            f"{leg['window_s']:g} s window, consecutive replays:",
            "",
            _common.md_table(
                ["what", "compiled median", "compiled p95", "numpy median", "numpy p95"],
                [
                    [
                        f"{name}, {unit}",
                        f(same[key]["median"], nd),
                        f(same[key]["p95"], nd),
                        f(leg[key]["median"], nd),
                        f(leg[key]["p95"], nd),
                    ]
                    for name, key, unit, nd in (
                        ("factor building (incl. preintegration)", "build_ms", "ms", 2),
                        ("smoother update", "update_ms", "ms", 2),
                        ("update + building", "update_plus_build_ms", "ms", 2),
                        (
                            "IMU sample into the smoother (no keyframe completed)",
                            "imu_input_us_per_sample",
                            "us",
                            1,
                        ),
                    )
                ],
            ),
            "",
        ]
    if b:
        lines += [
            f"Batch solve on the same replay: {b['trial_s']:.0f} s trial, {b['keyframes']} "
            f"keyframes, {b['factors']} factors, {b['solve_s']:.2f} s "
            f"({b['iterations']} LM iterations).",
            "",
        ]
    lines.append(markdown_synthetic(r["fixed_lag"], r["batch"], r["meta"]))
    return "\n".join(lines)


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--quick", action="store_true", help="short trials (smoke run)")
    ap.add_argument(
        "--recording",
        type=Path,
        default=None,
        help="recording for the replay part (default: simulated upstair seed 1)",
    )
    args = ap.parse_args()
    result = run(args.quick, args.recording)
    _common.write_result("smoother", result)
    print(markdown(result))  # noqa: T201 - benchmark script output


if __name__ == "__main__":
    main()
