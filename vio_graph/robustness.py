"""Fault sweep: toe ATE of filter, smoother and batch against fault severity.

Each case is a set of simulator faults (``vio_graph.sim`` ``faults`` section: camera blackout,
dropped frames, spurious depth points, an occluding foot, IMU spikes and saturation, a
camera-IMU time offset, clock jitter) and/or a front-end failure injected in the replay
(``PipelineConfig.inject``: wrong corner associations). ``vio-graph robustness`` simulates every
case for the chosen seeds (same seeds as the clean case, so the walk is identical), runs every
mode and writes a table, a plot and ``robustness.json``.

Recovery after a blackout: the time from the end of the blackout until the filter's toe error
comes back within 1.5x its clean-run error (median over the clean run) and stays there for
0.2 s.
"""

from __future__ import annotations

from collections.abc import Callable, Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np

from vio_graph.config import PipelineConfig
from vio_graph.evaluation.tables import report_header
from vio_graph.experiments import _map, _run_one
from vio_graph.io_utils import (
    atomic_path,
    atomic_write_json,
    atomic_write_text,
    write_generated_doc,
)

MODES = ("filter", "smoother", "batch")


@dataclass(frozen=True)
class FaultCase:
    name: str
    severity: str
    sim_faults: dict[str, Any]
    inject: dict[str, Any]


BLACKOUT_START_S = 4.0

FAULT_CASES: tuple[FaultCase, ...] = (
    FaultCase("clean", "-", {}, {}),
    FaultCase(
        "camera blackout",
        "1 s",
        {"camera_blackout_start_s": BLACKOUT_START_S, "camera_blackout_duration_s": 1.0},
        {},
    ),
    FaultCase(
        "camera blackout",
        "2 s",
        {"camera_blackout_start_s": BLACKOUT_START_S, "camera_blackout_duration_s": 2.0},
        {},
    ),
    FaultCase("dropped frames", "20 %", {"dropped_frame_probability": 0.2}, {}),
    FaultCase("wrong corner associations", "10 %", {}, {"wrong_association_rate": 0.1}),
    FaultCase("wrong corner associations", "25 %", {}, {"wrong_association_rate": 0.25}),
    FaultCase("spurious depth points", "5 %", {"spurious_point_fraction": 0.05}, {}),
    FaultCase(
        "occluding foot in view", "1 s", {"occluder_start_s": 3.0, "occluder_duration_s": 1.0}, {}
    ),
    FaultCase("IMU spikes", "2 Hz", {"imu_spike_rate_hz": 2.0}, {}),
    FaultCase("IMU accel saturation", "4 g", {"imu_accel_saturation_mps2": 39.2}, {}),
    FaultCase("camera-IMU time offset", "10 ms", {"camera_time_offset_s": 0.01}, {}),
    FaultCase("clock jitter", "2 ms", {"clock_jitter_s": 0.002}, {}),
)

#: an unflagged knock: 60 m/s^2 on two accelerometer axes for 0.1 s at 2 s (a 6 m/s velocity
#: error per axis inside the sensor's range; vio_graph/sim/config.FaultsConfig.imu_knock_*)
KNOCK_CASE = FaultCase("IMU knock", "0.1 s x 60 m/s^2", {"imu_knock_start_s": 2.0}, {})

#: the IMU and clock faults of issue 11 (``vio-graph robustness --cases imu``): spikes, a knock,
#: saturation (4 g, and 3 g: the simulator's joint-space swing reaches 3-4.7 g at its peaks, so
#: 4 g clips nothing on three of the four paper scenarios and 3 g clips 2-4 % of their samples),
#: camera-IMU offsets over -30..+30 ms and clock jitter
IMU_CASES: tuple[FaultCase, ...] = (
    FAULT_CASES[0],
    *(c for c in FAULT_CASES if c.name in ("IMU spikes", "IMU accel saturation")),
    FaultCase("IMU accel saturation", "3 g", {"imu_accel_saturation_mps2": 29.4}, {}),
    KNOCK_CASE,
    FaultCase("camera-IMU time offset", "-30 ms", {"camera_time_offset_s": -0.03}, {}),
    *(c for c in FAULT_CASES if c.name in ("camera-IMU time offset", "clock jitter")),
    FaultCase("camera-IMU time offset", "30 ms", {"camera_time_offset_s": 0.03}, {}),
)

#: the camera-IMU offset rows of IMU_CASES with their clean reference
#: (``vio-graph robustness --cases offsets``)
OFFSET_CASES: tuple[FaultCase, ...] = tuple(
    c for c in IMU_CASES if c.name in ("clean", "camera-IMU time offset")
)

#: the accelerometer saturation rows of IMU_CASES (4 g, 3 g) with their clean reference
#: (``vio-graph robustness --cases saturation``)
SATURATION_CASES: tuple[FaultCase, ...] = tuple(
    c for c in IMU_CASES if c.name in ("clean", "IMU accel saturation")
)


#: the IMU spike row of IMU_CASES with its clean reference (``vio-graph robustness --cases
#: spikes``)
SPIKE_CASES: tuple[FaultCase, ...] = tuple(
    c for c in IMU_CASES if c.name in ("clean", "IMU spikes")
)


#: the knock row of IMU_CASES with its clean reference (``vio-graph robustness --cases knock``)
KNOCK_CASES: tuple[FaultCase, ...] = (FAULT_CASES[0], KNOCK_CASE)


#: the occluding-foot row with its clean reference (``vio-graph robustness --cases occluder``)
OCCLUDER_CASES: tuple[FaultCase, ...] = tuple(
    c for c in FAULT_CASES if c.name in ("clean", "occluding foot in view")
)


def _slug(case: FaultCase) -> str:
    text = f"{case.name}_{case.severity}".lower()
    return "".join(c if c.isalnum() else "_" for c in text).strip("_")


def _simulate_case(args: tuple[str, dict[str, Any], int, Path]) -> Path:
    from vio_graph.sim import load_scenario
    from vio_graph.sim.cache import simulate_cached

    scenario, faults, seed, out = args
    cfg = load_scenario(scenario)
    if faults:
        cfg = cfg.model_copy(update={"faults": cfg.faults.model_copy(update=faults)})
    return simulate_cached(cfg, seed, out)


def run_sweep(
    out_dir: Path,
    scenario: str,
    seeds: Sequence[int],
    config: PipelineConfig,
    cases: Sequence[FaultCase] = FAULT_CASES,
    jobs: int = 1,
    progress: Callable[[int], None] | None = None,
) -> dict[str, Any]:
    """Simulate and run every (case, seed); return per-case mean toe ATE and recovery times."""
    out_dir = Path(out_dir)
    sims = [
        (scenario, c.sim_faults, s, out_dir / "recordings" / f"{_slug(c)}_s{s}")
        for c in cases
        for s in seeds
    ]
    _map(_simulate_case, sims, jobs, None)
    items = []
    for c in cases:
        cfg = config.model_copy(update={"inject": config.inject.model_copy(update=c.inject)})
        for s in seeds:
            rec = out_dir / "recordings" / f"{_slug(c)}_s{s}"
            items.append((rec, out_dir / "runs" / f"{_slug(c)}_s{s}", cfg.model_dump_json(), MODES))
    metrics = _map(_run_one, items, jobs, progress)
    results: dict[str, Any] = {"scenario": scenario, "seeds": list(seeds), "cases": []}
    clean_err = {}
    k = 0
    for c in cases:
        rows = metrics[k : k + len(seeds)]
        runs = items[k : k + len(seeds)]
        k += len(seeds)
        entry: dict[str, Any] = {
            "name": c.name,
            "severity": c.severity,
            "faults": c.sim_faults,
            "inject": c.inject,
        }
        for mode in MODES:
            vals = np.array(
                [[m["ate_cm"][mode]["toe"]["x"], m["ate_cm"][mode]["toe"]["z"]] for m in rows]
            )
            entry[mode] = {"x": float(vals[:, 0].mean()), "z": float(vals[:, 1].mean())}
        entry["filter_rejected_chi2"] = int(sum(m["filter"]["rejected_chi2"] for m in rows))
        if all("time_offset" in m for m in rows):  # the online camera-IMU offset, per seed
            entry["time_offset_ms"] = [1e3 * m["time_offset"]["estimate_s"] for m in rows]
            entry["time_offset_sigma_ms"] = [1e3 * m["time_offset"]["sigma_s"] for m in rows]
            # seeds whose replay was re-run with the offset applied from the start
            entry["time_offset_reruns"] = sum("rerun" in m["time_offset"] for m in rows)
        if c.name == "clean":
            for rec, res, _, _ in runs:
                clean_err[rec.name.split("_s")[-1]] = _toe_error(rec, res)
        if "camera_blackout_duration_s" in c.sim_faults:
            rec_times = []
            for (rec, res, _, _), seed in zip(runs, seeds, strict=True):
                t, e = _toe_error(rec, res)
                base = clean_err.get(str(seed))
                level = 1.5 * float(np.median(base[1])) if base is not None else np.nan
                end = BLACKOUT_START_S + c.sim_faults["camera_blackout_duration_s"]
                rec_times.append(_recovery_time(t, e, end, level))
            entry["recovery_s"] = float(np.nanmean(rec_times))
        results["cases"].append(entry)
    clean = results["cases"][0]
    for entry in results["cases"]:
        for mode in MODES:
            for ax in ("x", "z"):
                entry[mode][f"{ax}_ratio"] = entry[mode][ax] / max(clean[mode][ax], 1e-9)
    return results


def _toe_error(rec: Path, res: Path) -> tuple[np.ndarray, np.ndarray]:
    """Filter toe error norm (m) per frame, after anchoring the first pose (paper's ATE)."""
    from vio_graph.evaluation.association import associate
    from vio_graph.evaluation.metrics import ate_per_axis
    from vio_graph.recording.tum import read_tum

    pair = associate(
        read_tum(res / "trajectories" / "filter_toe.tum"),
        read_tum(rec / "groundtruth" / "toe.tum"),
        max_diff_s=0.02,
    )
    ate = ate_per_axis(pair.est, pair.ref, anchor="first")
    return ate.timestamp_s, np.linalg.norm(ate.errors_xyz_m, axis=1)


def _recovery_time(
    t: np.ndarray, err: np.ndarray, t_end: float, level: float, hold_s: float = 0.2
) -> float:
    after = t >= t_end
    ok = err <= level
    for i in np.flatnonzero(after):
        j = (t >= t[i]) & (t <= t[i] + hold_s)
        if np.all(ok[j]):
            return float(t[i] - t_end)
    return float("nan")


def markdown(results: dict[str, Any], command: str) -> str:
    lines = [
        *report_header("Robustness: toe ATE against sensor faults", command),
        f"Scenario `{results['scenario']}`, seeds {results['seeds']} (the same walks with and "
        "without each fault). Toe ATE in cm (paper's definition, mean over seeds) and, in "
        "brackets, the ratio to the clean run. `chi2 rej.` counts displacements the filter's "
        "gate refused (all seeds). Recovery: seconds after a blackout ends until the filter's "
        "toe error is back within 1.5x its clean-run median and stays there for 0.2 s.",
        "",
        "| fault | severity | filter x | filter z | smoother x | smoother z | batch x | "
        "batch z | chi2 rej. | recovery (s) | td est. (ms) |",
        "|---|---|---|---|---|---|---|---|---|---|---|",
    ]
    for e in results["cases"]:
        cells = []
        for mode in MODES:
            for ax in ("x", "z"):
                cells.append(f"{e[mode][ax]:.2f} ({e[mode][f'{ax}_ratio']:.2f}x)")
        rec = f"{e['recovery_s']:.2f}" if "recovery_s" in e else "—"
        lines.append(
            f"| {e['name']} | {e['severity']} | "
            + " | ".join(cells)
            + f" | {e['filter_rejected_chi2']} | {rec} | {_td_cell(e)} |"
        )
    lines += ["", "![fault sweep](figures/robustness.png)", ""]
    return "\n".join(lines)


def _td_cell(entry: dict[str, Any]) -> str:
    """Online camera-IMU offset per seed, ms (estimate +- 1 sigma)."""
    if "time_offset_ms" not in entry:
        return "—"
    return ", ".join(
        f"{v:.1f}±{s:.1f}"
        for v, s in zip(entry["time_offset_ms"], entry["time_offset_sigma_ms"], strict=True)
    )


def plot(results: dict[str, Any], path: Path) -> Path:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    cases = results["cases"]
    labels = [f"{c['name']}\n{c['severity']}" for c in cases]
    fig, axes = plt.subplots(1, 2, figsize=(14, 5), constrained_layout=True, sharey=True)
    width = 0.27
    for ax, axis in zip(axes, ("x", "z"), strict=True):
        for k, (mode, color) in enumerate(
            (("filter", "tab:orange"), ("smoother", "tab:blue"), ("batch", "tab:purple"))
        ):
            vals = [c[mode][axis] for c in cases]
            ax.bar(np.arange(len(cases)) + (k - 1) * width, vals, width, color=color, label=mode)
        ax.set_xticks(np.arange(len(cases)), labels, rotation=60, ha="right", fontsize=7)
        ax.set_title(f"toe ATE {axis} (cm)")
        ax.axhline(5.0, color="k", lw=0.8, ls="--")
        ax.legend(fontsize=8)
    with atomic_path(Path(path), suffix=".png") as tmp:
        fig.savefig(tmp, dpi=85)
    plt.close(fig)
    return Path(path)


def write_outputs(
    results: dict[str, Any], out_dir: Path, command: str, doc_path: Path | None
) -> dict[str, Path]:
    out_dir = Path(out_dir)
    written = {
        "json": out_dir / "robustness.json",
        "markdown": out_dir / "robustness.md",
        "figure": plot(results, out_dir / "figures" / "robustness.png"),
    }
    atomic_write_json(written["json"], results)
    md = markdown(results, command)
    atomic_write_text(written["markdown"], md)
    if doc_path is not None:
        write_generated_doc(Path(doc_path), md)
        plot(results, Path(doc_path).parent / "figures" / "robustness.png")
        written["doc"] = Path(doc_path)
    return written
