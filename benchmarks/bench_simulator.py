"""Benchmark: time simulate() of a 10 s upstair trial to a temp dir (median of 3 runs).

Writes benchmarks/results/simulator.json (threads pinned to 1 by ``_common``) and prints a
markdown table.
Run: python benchmarks/bench_simulator.py [--runs N]
"""

from __future__ import annotations

import argparse
import statistics
import tempfile
import time
from pathlib import Path

import _common  # noqa: I001 - first: pins thread pools before numpy is imported
import numpy as np

from vio_graph.sim import load_scenario, simulate, simulate_trial


def run(runs: int = 3) -> dict:
    config = load_scenario("upstair").model_copy(update={"duration_s": 10.0})
    times_s = []
    for run in range(runs):
        with tempfile.TemporaryDirectory() as tmp:
            t0 = time.perf_counter()
            simulate(config, seed=run + 1, out_dir=Path(tmp) / "rec")
            times_s.append(time.perf_counter() - t0)
    t0 = time.perf_counter()
    trial = simulate_trial(config, seed=1)
    t_trial = time.perf_counter() - t0
    t0, c0 = time.perf_counter(), time.process_time()
    valid = [int((trial.render_frame(i)[0] > 0).sum()) for i in range(trial.n_frames)]
    t_render = (time.perf_counter() - t0) / trial.n_frames
    c_render = (time.process_time() - c0) / trial.n_frames
    # the open3d (Embree) ray cast alone, one ray per pixel centre at the same poses
    cam = trial.camera
    v, u = np.mgrid[0 : cam.cfg.height_px, 0 : cam.cfg.width_px].astype(float)
    c0 = time.process_time()
    for i in range(trial.n_frames):
        cam.cast(trial.camera_position_m[i], trial.R_world_cam[i], u, v)
    c_cast = (time.process_time() - c0) / trial.n_frames
    result = {
        "scenario": "upstair",
        "duration_s": config.duration_s,
        "frames": trial.n_frames,
        "runs": runs,
        "simulate_median_s": statistics.median(times_s),
        "simulate_all_s": times_s,
        "simulate_trial_in_memory_s": t_trial,
        "render_ms_per_frame": 1e3 * t_render,
        "render_cpu_ms_per_frame": 1e3 * c_render,
        "ray_cast_cpu_ms_per_frame": 1e3 * c_cast,
        "mean_valid_pixels_per_frame": float(np.mean(valid)),
        "edge_visible_fraction": float(trial.groundtruth.frame_edge_visible.mean()),
    }
    return result


def markdown(r: dict) -> str:
    return "\n".join(
        [
            "| metric | value |",
            "|---|---|",
            f"| simulate() 10 s upstair, median of {r['runs']} | {r['simulate_median_s']:.1f} s |",
            f"| in-memory simulate_trial (no frames) | {r['simulate_trial_in_memory_s']:.2f} s |",
            f"| render one 224x172 frame | {r['render_ms_per_frame']:.1f} ms |",
            *(
                [
                    f"| render one frame, CPU time | {r['render_cpu_ms_per_frame']:.1f} ms |",
                    "| of which the ray cast (`TofCamera.cast`: open3d / Embree), CPU time "
                    f"| {r['ray_cast_cpu_ms_per_frame']:.1f} ms |",
                ]
                if "render_cpu_ms_per_frame" in r
                else []
            ),
            f"| mean valid pixels / frame | {r['mean_valid_pixels_per_frame']:.0f} of 38528 |",
            f"| frames seeing a stair edge | {100 * r['edge_visible_fraction']:.0f} % |",
        ]
    )


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--runs", type=int, default=3, help="simulate() runs (median reported)")
    result = run(ap.parse_args().runs)
    _common.write_result("simulator", result)
    print(markdown(result))  # noqa: T201 - benchmark script output


if __name__ == "__main__":
    main()
