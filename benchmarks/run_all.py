"""Run every benchmark and regenerate docs/performance.md.

Each benchmark runs in its own process with the BLAS / OpenMP pools pinned to one thread and
writes benchmarks/results/<name>.json (gitignored); this script then renders the tables of all
of them, the machine and the date into docs/performance.md. About 3-5 minutes on 2 cores (the
first run also simulates the upstair trial into the system temp folder, ~20 s). The scaling
table's recordings are simulated once into results/scale/recordings and reused (the 600 s one
takes ~5 min of CPU to simulate; its online and batch runs ~15 min more).

    python benchmarks/run_all.py [--quick] [--no-doc] [--scale-durations 10 60 600]
"""

from __future__ import annotations

import argparse
import json
import os
import subprocess
import sys
import time
from typing import Any

import _common  # noqa: I001 - first: pins thread pools before numpy is imported
import bench_end_to_end
import bench_frontend
import bench_scale
import bench_simulator
import bench_smoother

# frontend first: it simulates the recording
BENCHMARKS = ("frontend", "smoother", "simulator", "scale")
#: run after those, each with its own section when its results exist
EXTRA_BENCHMARKS = ("end_to_end",)
DOC = _common.BENCH_DIR.parent / "docs" / "performance.md"
COMMAND = "python benchmarks/run_all.py"
#: trial lengths of the scaling table; with 600 s (18,000 frames):
#: ``--scale-durations 10 60 600`` (its recording simulated once, then reused)
SCALE_DURATIONS_S = ("10", "60")


def run_benchmark(
    name: str, quick: bool, scale_durations: tuple[str, ...] = SCALE_DURATIONS_S
) -> float:
    """Run benchmarks/bench_<name>.py in a fresh single-threaded process; wall time (s)."""
    args = [sys.executable, str(_common.BENCH_DIR / f"bench_{name}.py")]
    if quick:
        args += {
            "frontend": ["--quick"],
            "smoother": ["--quick"],
            "simulator": ["--runs", "1"],
            "scale": ["--durations", "10"],
            "end_to_end": ["--repeats", "1"],
        }[name]
    elif name == "scale":
        args += ["--durations", *scale_durations]
    env = dict(os.environ, **{v: "1" for v in _common.THREAD_VARIABLES})
    t0 = time.perf_counter()
    subprocess.run(args, check=True, env=env, stdout=subprocess.DEVNULL)
    return time.perf_counter() - t0


def summary(fe: dict[str, Any], sm: dict[str, Any], sim: dict[str, Any], sc: dict[str, Any]) -> str:
    f = _common.fmt
    ours, best = fe["ours_ms"], fe["ours_best_of_repeats_ms"]
    o3d = fe["open3d"]["imu"]["ms"]
    paper_total = fe["paper_ms"]["frontend"] + fe["paper_ms"]["fusion"]
    default_w = [x for x in sm["replay"]["fixed_lag"] if x["window_s"] == 2.0]
    sm_row = default_w[0] if default_w else sm["replay"]["fixed_lag"][0]
    batch60 = [b for b in sm["batch"] if b["trial_s"] == 60.0]
    imu = fe.get("imu_us_per_sample")
    kiss = fe.get("kiss_icp")
    rows = [
        *(
            [
                [
                    "IMU propagation per sample (clock, fault monitor, attitude, SP-ESKF, "
                    "stance detector; compiled)",
                    f"{f(imu['fast']['median'], 1)} / {f(imu['fast']['p95'], 1)} us",
                    f"target <= 20 us; numpy reference {f(imu['reference']['median'], 1)} us "
                    f"(fast / reference = {f(imu['ratio_median'], 3)})"
                    + (
                        f"; Python closed forms (short recordings) "
                        f"{f(imu['scalar']['median'], 1)} us"
                        if "scalar" in imu
                        else ""
                    ),
                ]
            ]
            if imu
            else []
        ),
        [
            "front end + fusion per frame (simulated upstair)",
            f"{f(ours['frontend_plus_fusion']['median'])} / "
            f"{f(ours['frontend_plus_fusion']['p95'])} ms",
            f"target <= 1 ms; paper {paper_total:.1f} ms ({fe['paper_ms']['frontend']} + "
            f"{fe['paper_ms']['fusion']})",
        ],
        [
            f"front end + fusion, per frame best of {fe['repeats']} replays",
            f"{f(best['frontend_plus_fusion']['median'])} / "
            f"{f(best['frontend_plus_fusion']['p95'])} ms",
            "less sensitive to other processes (see below)",
        ],
        [
            "safety outputs per frame (toe clearance, prediction, placement)",
            f"{f(ours['safety']['median'], 3)} / {f(ours['safety']['p95'], 3)} ms",
            "target <= 0.2 ms"
            + (
                f"; numpy reference {f(fe['reference_ms']['safety']['median'], 3)} ms"
                if "reference_ms" in fe
                else ""
            ),
        ],
        [
            "per frame incl. kinematics and IMU propagation",
            f"{f(ours['per_frame_total']['median'])} / {f(ours['per_frame_total']['p95'])} ms",
            "30 fps budget: 33 ms",
        ],
        [
            "open3d 3D point-to-point ICP, full clouds, IMU init (direct ICP)",
            f"{f(o3d['median'], 1)} / {f(o3d['p95'], 1)} ms",
            f"paper ~{fe['paper_ms']['direct_icp']:.0f} ms; ours / open3d = "
            f"{f(fe['ratios']['ours_frontend_plus_fusion_over_open3d_imu'], 3)}",
        ],
        *(
            [
                [
                    "KISS-ICP odometry, small-scene configuration, per frame",
                    f"{f(kiss['ms']['median'], 1)} / {f(kiss['ms']['p95'], 1)} ms",
                    f"displacement error {f(kiss['err_mm']['median'], 1)} mm median (ours "
                    f"{f(fe['ours_displacement']['err_mm']['median'], 1)}); ours / KISS-ICP = "
                    f"{f(fe['ratios']['ours_frontend_plus_fusion_over_kiss_icp'], 3)}",
                ]
            ]
            if kiss
            else []
        ),
        [
            f"fixed-lag smoother per keyframe, {sm_row['window_s']:g} s window (replay)",
            f"{f(sm_row['update_plus_build_ms']['median'])} / "
            f"{f(sm_row['update_plus_build_ms']['p95'])} ms",
            f"target <= 1 ms; update {f(sm_row['update_ms']['median'])} + factor building "
            f"{f(sm_row['build_ms']['median'])} ms"
            + (
                f" (numpy step means: {f(leg['build_ms']['median'])} ms)"
                if (leg := sm["replay"].get("numpy_sampler"))
                else ""
            ),
        ],
    ]
    if "imu_input_us_per_sample" in sm_row:
        rows.insert(
            1 if imu else 0,
            [
                "IMU sample into the smoother's preintegration buffer",
                f"{f(sm_row['imu_input_us_per_sample']['median'], 1)} / "
                f"{f(sm_row['imu_input_us_per_sample']['p95'], 1)} us",
                "target <= 20 us (samples that complete no keyframe)",
            ],
        )
    if sm["replay"]["batch"]:
        b = sm["replay"]["batch"]
        rows.append(
            [
                f"batch smoother, {b['trial_s']:.0f} s trial (replay)",
                f"{f(b['solve_s'])} s",
                f"{b['keyframes']} keyframes",
            ]
        )
    if batch60:
        rows.append(
            [
                "batch smoother, 60 s synthetic trial",
                f"{f(batch60[0]['solve_s'])} s",
                f"+ {f(batch60[0]['build_s'])} s graph building",
            ]
        )
    rows.append(
        [
            f"simulate a {sim['duration_s']:.0f} s upstair trial",
            f"{f(sim['simulate_median_s'], 1)} s",
            f"median of {sim['runs']}; {f(sim['render_ms_per_frame'], 1)} ms per frame render",
        ]
    )
    for row in sc["rows"]:
        on = row["online"]
        rows.append(
            [
                f"`vio-graph run REC --out OUT --mode filter --no-rerun`, "
                f"{row['duration_s']:g} s trial",
                f"{f(on['wall_s'], 1)} s wall, {f(on['cpu_s'], 1)} s CPU",
                f"peak RSS {f(on['peak_rss_mib'], 0)} MiB; see Scale",
            ]
        )
    return _common.md_table(["what", "median / p95", "reference"], rows)


def render(
    walls_s: dict[str, float], quick: bool, scale_durations: tuple[str, ...] = SCALE_DURATIONS_S
) -> str:
    fe, sm, sim, sc = (_common.read_result(n) for n in BENCHMARKS)
    m = fe["machine"]
    loads = ", ".join(
        f"{n} {r['machine']['load_average_1_5_15min'][0]}"
        for n, r in zip(BENCHMARKS, (fe, sm, sim, sc), strict=True)
    )
    lines = [
        "# Performance",
        "",
        f"Generated by `benchmarks/run_all.py` on {m['date_utc']}"
        + (" (--quick: fewer repeats, numbers less reliable)" if quick else "")
        + ". "
        "Do not edit by hand; rerun instead. Each speed-up measured against the commit "
        "before it, one change at a time: [performance-log.md](performance-log.md).",
        "",
        "Reproduce (from the repository root, about 10-15 minutes"
        + (
            ", plus ~20 minutes for the 600 s trial and ~5 more the first time, when it is "
            "simulated into results/scale/recordings"
            if "600" in scale_durations
            else ""
        )
        + "):",
        "",
        "```bash",
        COMMAND
        + (" --quick" if quick else "")
        + (
            " --scale-durations " + " ".join(scale_durations)
            if scale_durations != SCALE_DURATIONS_S
            else ""
        ),
        "```",
        "",
        f"Machine: {m['cpu_model']}, {m['logical_cores']} logical cores "
        f"({m['usable_cores']} usable), {m['platform']}; Python {m['python']}, numpy "
        f"{m['numpy']}, scipy {m['scipy']}; vio_graph at `{m['source_revision']}`"
        + (
            " (`+dirty`: the working tree had uncommitted changes in vio_graph/ or configs/)"
            if "+dirty" in m["source_revision"]
            else ""
        )
        + ". Every benchmark runs single-threaded "
        "(OMP / OpenBLAS / MKL threads = 1). Load average (1 min) when each benchmark "
        f"finished: {loads}. The machine is shared, so medians and p95 are reported, "
        "comparisons are ratios measured in the same run, and a load above the core count "
        "inflates every number (the p95 most).",
        "",
        *(
            [
                f"**Measured on an overloaded machine** (load average up to {max_load:.0f} on "
                f"{m['logical_cores']} cores): the process held a core a fraction of the time, "
                "so wall-clock figures (per-stage medians included) are inflated several-fold "
                "and even CPU times rise (shared caches); trust the ratios measured in the same "
                "run and the CPU time per frame of the whole replay loop, and rerun on a quiet "
                "machine for absolute numbers.",
                "",
            ]
            if (
                max_load := max(
                    r["machine"]["load_average_1_5_15min"][0] for r in (fe, sm, sim, sc)
                )
            )
            > 2 * (m["logical_cores"] or 1)
            else []
        ),
        "## Summary",
        "",
        summary(fe, sm, sim, sc),
        "",
        "## Front end, fusion and kinematics per frame",
        "",
        bench_frontend.markdown(fe),
        "",
        "## Smoother",
        "",
        bench_smoother.markdown(sm),
        "",
        "## Simulator",
        "",
        bench_simulator.markdown(sim),
        "",
        "## Scale",
        "",
        bench_scale.markdown(sc),
        "",
        *(
            [
                "The 600 s (18,000 frames) row: `python benchmarks/run_all.py --scale-durations "
                "10 60 600` (the recording is simulated once into results/scale/recordings, "
                "~5 min of CPU, and reused; its two runs take ~15 min more).",
                "",
            ]
            if not any(row["duration_s"] >= 600 for row in sc["rows"])
            else []
        ),
    ]
    if (_common.RESULTS_DIR / "end_to_end.json").exists():
        lines += [
            "## End to end",
            "",
            bench_end_to_end.markdown(_common.read_result("end_to_end")),
            "",
        ]
    if walls_s:
        lines += [
            "## Benchmark wall times",
            "",
            _common.md_table(
                ["benchmark", "wall s"],
                [[f"`benchmarks/bench_{n}.py`", f"{w:.0f}"] for n, w in walls_s.items()],
            ),
            "",
        ]
    return "\n".join(lines)


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--quick", action="store_true", help="smoke run (fewer repeats)")
    ap.add_argument("--no-doc", action="store_true", help="only write benchmarks/results/")
    ap.add_argument(
        "--render-only",
        action="store_true",
        help="regenerate the doc from existing results (wall times unknown)",
    )
    ap.add_argument(
        "--scale-durations",
        nargs="+",
        default=list(SCALE_DURATIONS_S),
        help="trial lengths (s) of the scaling table; 600 adds ~20 min (reused recording)",
    )
    args = ap.parse_args()
    walls: dict[str, float] = {}
    walls_file = _common.RESULTS_DIR / "run_all_wall_s.json"
    if args.render_only:
        walls = json.loads(walls_file.read_text()) if walls_file.exists() else {}
    else:
        for name in (*BENCHMARKS, *EXTRA_BENCHMARKS):
            walls[name] = run_benchmark(name, args.quick, tuple(args.scale_durations))
            print(f"{name}: {walls[name]:.0f} s", flush=True)  # noqa: T201 - script output
        walls_file.write_text(json.dumps(walls) + "\n")
    if not args.no_doc:
        DOC.write_text(render(walls, args.quick, tuple(args.scale_durations)))
        print(f"wrote {DOC}")  # noqa: T201 - script output


if __name__ == "__main__":
    main()
