"""The ``vio-graph`` command line (typer). Thin: parse, call the library, report.

Known errors (:class:`vio_graph.errors.VioGraphError`) become one line on stderr and exit code 1.
"""

from __future__ import annotations

import json
import logging
import math
import signal
import sys
from collections.abc import Sequence
from pathlib import Path
from typing import TYPE_CHECKING, Annotated

import typer

from vio_graph.errors import VioGraphError
from vio_graph.interrupts import on_sigterm

if TYPE_CHECKING:
    from vio_graph.config import PipelineConfig

app = typer.Typer(
    add_completion=False,
    # plain click help: typer's rich formatting costs ~0.3 s of imports on every --help
    rich_markup_mode=None,
    no_args_is_help=True,
    help="Sagittal-plane visual-inertial motion estimation for prostheses on stairs and obstacles.",
)
log = logging.getLogger("vio_graph")


def _setup_logging(verbose: bool) -> None:
    logging.basicConfig(
        level=logging.DEBUG if verbose else logging.INFO,
        format="%(levelname)s %(name)s: %(message)s",
        stream=sys.stderr,
    )


@app.callback()
def _main(
    verbose: Annotated[bool, typer.Option("--verbose", "-v", help="Debug logging.")] = False,
) -> None:
    _setup_logging(verbose)


@app.command()
def info(
    recording: Annotated[Path, typer.Argument(help="Recording folder.")],
    as_json: Annotated[bool, typer.Option("--json", help="Print one JSON object.")] = False,
) -> None:
    """Validate a recording and summarise it.

    Example: vio-graph info data/recordings/upstair_s1 --json
    """
    from vio_graph.recording import Recording

    summary = Recording.open(recording).summary()
    if as_json:
        typer.echo(json.dumps(summary))
        return
    typer.echo(f"recording      {summary['path']}  (format v{summary['format_version']}, valid)")
    typer.echo(f"duration       {summary['duration_s']:.2f} s")
    typer.echo(
        f"depth frames   {summary['frames']} at {summary['frame_rate_hz']:.2f} Hz, "
        f"{summary['image_size'][0]} x {summary['image_size'][1]} px"
    )
    typer.echo(
        f"IMU            {summary['imu_samples']} samples at {summary['imu_rate_hz']:.2f} Hz"
    )
    typer.echo(f"joint angles   {summary['joint_samples']} at {summary['joint_rate_hz']:.2f} Hz")
    if summary["gt_rate_hz"]:
        typer.echo(
            f"ground truth   {', '.join(summary['gt_bodies'])} at {summary['gt_rate_hz']:.2f} Hz"
        )
    else:
        typer.echo("ground truth   none")
    if "edge_visible_fraction" in summary:
        typer.echo(f"edge visible   {100 * summary['edge_visible_fraction']:.1f} % of frames")
    terrain = ", ".join(f"{k}={v}" for k, v in summary["terrain"].items())
    typer.echo(f"rig / terrain  {summary['rig']} / {terrain}")
    p = summary["provenance"]
    typer.echo(
        f"provenance     {p['source']} scenario={p['scenario']} seed={p['seed']} {p['software']}"
    )


@app.command()
def simulate(
    scenario: Annotated[str, typer.Option(help="Scenario name in configs/ or a YAML path.")],
    out: Annotated[Path, typer.Option(help="Output recording folder.")],
    seed: Annotated[int, typer.Option(help="Random seed (same seed, same recording).")] = 1,
    overwrite: Annotated[bool, typer.Option(help="Replace an existing folder.")] = False,
) -> None:
    """Simulate a trial with ground truth into a recording folder.

    Example: vio-graph simulate --scenario upstair --seed 1 --out data/recordings/upstair_s1
    """
    if out.exists() and not overwrite:  # before the (slow) simulator imports
        raise VioGraphError(f"{out}: already exists (use --overwrite to replace it)")
    from vio_graph.errors import SimulationError
    from vio_graph.sim import load_scenario
    from vio_graph.sim import simulate as run_simulation
    from vio_graph.viz.progress import progress_bar

    config = load_scenario(scenario)
    try:
        with progress_bar(
            total=None, desc=f"simulating {scenario} seed {seed}", unit="frame"
        ) as bar:
            path = run_simulation(config, seed, out, progress=bar.update_to, overwrite=overwrite)
    except SimulationError as exc:  # the scenario asks for what the simulator cannot make
        raise VioGraphError(f"{scenario}: {exc}") from exc
    typer.echo(f"wrote {path}")


def _print_ate_table(metrics: dict) -> None:
    """Toe and camera ATE (cm) per mode, the paper's definition."""
    ate = metrics.get("ate_cm")
    if not ate:
        typer.echo("no ground truth: no ATE")
        return
    from vio_graph.evaluation.run_metrics import ate_key

    key = ate_key(metrics)
    typer.echo(
        f"ATE (cm, first pose anchored{', obstacle-visible frames' if key != 'ate_cm' else ''}):"
    )
    typer.echo(f"  {'mode':<10} {'toe x':>7} {'toe z':>7} {'camera x':>9} {'camera z':>9}")
    for mode, bodies in metrics[key].items():
        toe, cam = bodies["toe"], bodies["camera"]
        typer.echo(f"  {mode:<10} {toe['x']:7.2f} {toe['z']:7.2f} {cam['x']:9.2f} {cam['z']:9.2f}")
    lat = metrics.get("latency_ms", {})
    if "frontend" in lat:
        typer.echo(
            f"front end per frame: median {lat['frontend']['median']:.2f} ms, "
            f"p95 {lat['frontend']['p95']:.2f} ms"
        )
    m = metrics.get("map", {})
    if m.get("rise_error_mm") is not None:
        typer.echo(
            f"map ({m['source_mode']} poses): rise error {m['rise_error_mm']:.1f} mm, "
            f"tread error {m.get('tread_error_mm') or float('nan'):.1f} mm"
        )
    for mode, c in metrics.get("clearance", {}).items():  # safety outputs (docs/outputs.md)
        nt = c["near_trip"]
        pl = metrics["placement"][mode]["error_mm"]["median"]
        w1 = c.get("within_1sigma", float("nan"))
        sigma = f", within 1 sigma {w1:.2f}" if math.isfinite(w1) else ""
        cs = c.get("pose_consistency_scale", {}).get("last", float("nan"))
        sigma += f" (pose consistency scale {cs:.2f})" if math.isfinite(cs) else ""
        trips = (
            f"near-trips {nt['events']}, warnings {nt['warnings']}, recall {nt['recall']:.2f}, "
            f"min lead {nt['min_lead_ms']:.0f} ms"
            if nt["events"]
            else f"no near-trip (true clearance < 2 cm), near-trip warnings {nt['warnings']}"
        )
        place = f"; placement error median {pl:.1f} mm" if math.isfinite(pl) else ""
        typer.echo(
            f"toe clearance ({mode}): error median {c['error_mm']['median']:.1f} mm, p95 "
            f"{c['error_mm']['p95']:.1f} mm{sigma}; {trips}{place}"
        )


def _print_health(metrics: dict) -> None:
    """One line of health figures, then one warning line per likely cause (if any)."""
    h = metrics.get("health")
    if not h:
        return
    typer.echo(
        f"health: {100 * h['displacements_rejected_share']:.0f} % of visual displacements "
        f"refused, stance on {100 * h['stance_share']:.0f} % of frames, fused path off visual "
        f"odometry in {100 * h['fused_vs_visual']['departure_share']:.0f} % of "
        f"{h['fused_vs_visual']['window_s']:g} s windows"
    )
    for line in h["warnings"]:
        typer.secho(line, fg=typer.colors.YELLOW, err=True)
    for line in fault_lines(metrics):
        typer.secho(line, fg=typer.colors.YELLOW, err=True)


def fault_lines(metrics: dict) -> list[str]:
    """Summary lines for IMU faults, the camera-IMU offset and timestamp jumps (empty when
    there is nothing to say)."""
    lines = []
    f = metrics.get("imu_faults", {})
    n_sat = f.get("accel_saturated_samples", 0) + f.get("gyro_saturated_samples", 0)
    if n_sat or f.get("gyro_repaired_samples", 0) or f.get("vision_kept_against_imu", 0):
        lines.append(
            f"IMU: {f.get('accel_saturated_samples', 0)} accelerometer and "
            f"{f.get('gyro_saturated_samples', 0)} gyro samples saturated, "
            f"{f.get('gyro_repaired_samples', 0)} gyro samples replaced by the orientation "
            f"rate, {f.get('vision_kept_against_imu', 0)} displacements kept against the IMU"
        )
    td = metrics.get("time_offset", {})
    if td.get("applied_s", 0.0) != 0.0:
        lines.append(
            f"camera-IMU time offset {1e3 * td['estimate_s']:.1f} ms "
            f"(1-sigma {1e3 * td['sigma_s']:.1f} ms), applied to the fusion"
        )
    if "rerun" in td:
        r = td["rerun"]
        lines.append(
            f"the first {r['frames']} frames were re-run with the offset applied from the "
            "start; the online output for them was the first pass's (metrics.json "
            "'time_offset' 'rerun')"
        )
    if "final_rerun" in td:
        r = td["final_rerun"]
        held = (
            f"the offset held at its final estimate, {1e3 * r['applied_s']:.1f} ms"
            if r["applied_s"] != 0.0
            else "the stamps as recorded (the later tilts refuted the offset applied)"
        )
        lines.append(
            f"every frame was run once more with {held}; the written trajectories are that "
            "pass's (metrics.json 'time_offset' 'final_rerun')"
        )
    for name, rep in metrics.get("timestamps", {}).items():
        if rep.get("gaps") or rep.get("backwards"):
            lines.append(
                f"{name} timestamps: {rep['gaps']} gaps ({rep['gap_total_s']:.3f} s "
                f"in total), {rep['backwards']} stamps at or before the previous one "
                "(dropped); see metrics.json 'timestamps'"
            )
    return lines


def _parse_modes(mode: str) -> tuple[str, ...]:
    from vio_graph.pipeline import MODES, PEER_MODES

    if mode == "all":
        return MODES
    modes = tuple(m.strip() for m in mode.split(",") if m.strip())
    bad = [m for m in modes if m not in MODES + PEER_MODES]
    if bad or not modes:
        raise VioGraphError(
            f"--mode: unknown {bad or mode!r}; use filter, smoother, batch or all "
            "(and the baseline gtsam_legged)"
        )
    return modes


@app.command()
def run(
    recording: Annotated[Path, typer.Argument(help="Recording folder.")],
    out: Annotated[Path, typer.Option(help="Results folder.")],
    mode: Annotated[
        str, typer.Option(help="filter | smoother | batch | all (comma list ok).")
    ] = "filter",
    config: Annotated[
        Path | None, typer.Option(help="Pipeline config YAML (default configs/default.yaml).")
    ] = None,
    overwrite: Annotated[
        bool, typer.Option(help="Write into an existing, non-empty folder.")
    ] = False,
    no_rerun: Annotated[bool, typer.Option("--no-rerun", help="Skip the .rrd recording.")] = False,
    no_plots: Annotated[
        bool,
        typer.Option("--no-plots", help="Skip the PNG figures (plots/, map/map.png)."),
    ] = False,
) -> None:
    """Estimate the knee/ankle/heel/toe motion of one recording and write results.

    Writes trajectories/*.tum (evo), metrics.json, frames.csv, plots/, map/, run.rrd and
    config.yaml. Example: vio-graph run data/sample --out results/sample --mode all
    """
    from vio_graph.memory import collection_paused_for_start_up

    # no garbage collection while the modules, the configuration and the kernels load (the
    # replay's start ends the pause), nor over them at exit (vio_graph/memory.py): ~0.5 s of
    # CPU less a 30 s run
    with collection_paused_for_start_up():
        from vio_graph.config import load_config
        from vio_graph.pipeline import run_recording

        cfg = load_config(config)
        if no_plots:  # output.plots: false, as a config file could say
            cfg = cfg.model_copy(update={"output": cfg.output.model_copy(update={"plots": False})})
        result = run_recording(
            recording,
            out,
            cfg,
            modes=_parse_modes(mode),
            overwrite=overwrite,
            visualize=not no_rerun,
        )
    _print_ate_table(result.metrics)
    _print_health(result.metrics)
    typer.echo(f"results in {result.out_dir}")


@app.command()
def demo(
    out: Annotated[Path, typer.Option(help="Folder for the demo recording and results.")] = Path(
        "results/demo"
    ),
    scenario: Annotated[str, typer.Option(help="Scenario to simulate.")] = "upstair",
    seed: Annotated[int, typer.Option(help="Simulation seed.")] = 1,
    mode: Annotated[str, typer.Option(help="filter | smoother | batch | all.")] = "all",
) -> None:
    """Simulate the default upstair trial (embedded default data), run the estimator on it and
    print the error table. Re-running reuses the simulated recording if the simulator's code
    is the same (vio_graph/sim/cache.py)."""
    from vio_graph.config import load_config
    from vio_graph.pipeline import run_recording
    from vio_graph.sim import load_scenario, simulate
    from vio_graph.sim.cache import recording_is_current
    from vio_graph.viz.progress import progress_bar

    rec_dir = out / f"recording_{scenario}_s{seed}"
    config = load_scenario(scenario)
    if not recording_is_current(rec_dir, config, seed):  # (re)simulate: none, or another sim
        with progress_bar(
            total=None, desc=f"simulating {scenario} seed {seed}", unit="frame"
        ) as bar:
            simulate(config, seed, rec_dir, progress=bar.update_to, overwrite=True)
    typer.echo(f"recording   {rec_dir}")
    res_dir = out / "results"
    result = run_recording(
        rec_dir, res_dir, load_config(), modes=_parse_modes(mode), overwrite=True
    )
    _print_ate_table(result.metrics)
    _print_health(result.metrics)
    typer.echo(f"results     {res_dir}")
    typer.echo(f"rerun view  {res_dir / 'run.rrd'}   (open with: rerun {res_dir / 'run.rrd'})")
    typer.echo(f"overview    {res_dir / 'plots' / 'overview.png'}")
    typer.echo(f"map         {res_dir / 'map'}")


_SCHEDULER_HELP = (
    "Run the trials on Dask: 'local' (a LocalCluster of --jobs workers) or an existing "
    "scheduler's address, e.g. tcp://10.0.0.5:8786 (docs/scaling.md). Default: this machine's "
    "process pool."
)


def _evaluate_sweep(
    out: Path,
    seeds: int,
    conditions: list[str] | None,
    mode: str,
    cfg,
    jobs: int,
    doc: Path | None,
    scheduler: str | None = None,
) -> None:
    from vio_graph.sweep import (
        SWEEP_CONDITIONS,
        SWEEP_SEED_BASE,
        condition_by_name,
        run_sweep,
        write_sweep_report,
    )
    from vio_graph.viz.progress import progress_bar

    try:
        names = (
            [condition_by_name(c).name for c in conditions]
            if conditions
            else [c.name for c in SWEEP_CONDITIONS]
        )
    except KeyError as exc:
        raise typer.BadParameter(str(exc.args[0])) from None
    seed_list = list(range(SWEEP_SEED_BASE, SWEEP_SEED_BASE + seeds))
    with progress_bar(len(names) * len(seed_list), "sweep", "trial") as bar:
        results = run_sweep(
            out,
            cfg,
            seed_list,
            names,
            _parse_modes(mode),
            jobs,
            progress=bar.update_to,
            scheduler=scheduler,
        )
    command = "vio-graph evaluate " + " ".join(sys.argv[2:])
    written = write_sweep_report(results, out, command, len(seed_list), doc)
    failed = [r for r in results if "error" in r]
    for r in failed:
        typer.secho(
            f"{r['condition']} seed {r['seed']} failed: {r['error']}", fg=typer.colors.RED, err=True
        )
    for path in written.values():
        typer.echo(f"wrote {path}")


@app.command()
def evaluate(
    out: Annotated[Path, typer.Option(help="Folder for recordings, runs and the report.")] = Path(
        "results/evaluate"
    ),
    seeds: Annotated[int, typer.Option(help="Seeds 1..N per experiment.")] = 5,
    scenario: Annotated[
        list[str] | None, typer.Option(help="Experiments (default: the paper's four).")
    ] = None,
    mode: Annotated[str, typer.Option(help="Modes to run.")] = "all",
    config: Annotated[Path | None, typer.Option(help="Pipeline config YAML.")] = None,
    jobs: Annotated[int, typer.Option(help="Parallel processes.")] = 1,
    doc: Annotated[
        Path | None, typer.Option(help="Also write the report here (e.g. docs/results.md).")
    ] = None,
    ablation: Annotated[
        bool,
        typer.Option(
            help="Also run the smoother ablation (seeds 1-2) and the filter "
            "ablation (all seeds, filter only)."
        ),
    ] = False,
    sweep: Annotated[
        bool,
        typer.Option(
            help="Run the generalisation sweep instead (vio_graph/sweep.py): "
            "every condition x --seeds seeds from 1000, default config; "
            "writes generalisation.md."
        ),
    ] = False,
    condition: Annotated[
        list[str] | None, typer.Option(help="--sweep: only these conditions (repeatable).")
    ] = None,
    scheduler: Annotated[str | None, typer.Option(help=_SCHEDULER_HELP)] = None,
) -> None:
    """The paper's experiments x seeds on simulated trials: simulate (cached), run every mode,
    write summary.json, results.md and the Fig. 5-style plot. With --sweep: the
    generalisation sweep over gaits, stairs, mounts, frame rates, ToF artefacts and lengths.

    Examples: vio-graph evaluate --seeds 5 --jobs 2 --doc docs/results.md;
    vio-graph evaluate --sweep --seeds 3 --jobs 2 --out results/sweep --doc docs/generalisation.md
    """
    from vio_graph.config import load_config

    if sweep:
        _evaluate_sweep(out, seeds, condition, mode, load_config(config), jobs, doc, scheduler)
        return
    from vio_graph.experiments import PAPER_EXPERIMENTS, simulate_trials
    from vio_graph.viz.progress import progress_bar

    scenarios = scenario or list(PAPER_EXPERIMENTS)
    cfg = load_config(config)
    seed_list = list(range(1, seeds + 1))
    n = len(scenarios) * len(seed_list)
    with progress_bar(n, "simulating", "trial") as bar:
        recs = simulate_trials(
            out, scenarios, seed_list, jobs=jobs, progress=bar.update_to, scheduler=scheduler
        )
    command = (
        "vio-graph evaluate " + " ".join(sys.argv[2:])
        if len(sys.argv) > 2
        else "vio-graph evaluate"
    )
    written = _estimate_and_report(recs, out, cfg, mode, jobs, scheduler, command, doc)
    if ablation:
        from vio_graph.experiments import (
            ABLATION_VARIANTS,
            ablation_markdown,
            run_ablation,
            run_filter_ablation,
        )
        from vio_graph.io_utils import atomic_write_text

        sub = [r for r in recs if r[1] in (1, 2)]
        with progress_bar(len(ABLATION_VARIANTS), "ablation", "variant") as bar:
            table = run_ablation(
                sub, out, cfg, jobs=jobs, progress=bar.update_to, scheduler=scheduler
            )
        ftable = run_filter_ablation(recs, out, cfg, jobs=jobs, scheduler=scheduler)
        md = (
            ablation_markdown(ftable, "Filter ablation, all seeds", ("filter",))
            + "\n"
            + ablation_markdown(table, "Smoother ablation, seeds 1-2")
        )
        for path in [written["markdown"]] + ([written["doc"]] if "doc" in written else []):
            text = path.read_text()
            atomic_write_text(
                path, text.replace("![toe trajectories]", md + "\n![toe trajectories]")
            )
        typer.echo(md)
    typer.echo(written["markdown"].read_text().split("## Smoother vs filter")[0])
    for k, p in written.items():
        typer.echo(f"{k:9} {p}")


def _estimate_and_report(
    recs: Sequence[tuple[str, int | None, Path]],
    out: Path,
    cfg: PipelineConfig,
    mode: str,
    jobs: int,
    scheduler: str | None,
    command: str,
    doc: Path | None,
) -> dict[str, Path]:
    """Run every mode on (scenario, seed, recording) triples under a progress bar and write
    the results report (evaluate and compare)."""
    from vio_graph.experiments import run_trials, write_report
    from vio_graph.viz.progress import progress_bar

    with progress_bar(len(recs), "estimating", "trial") as bar:
        runs = run_trials(
            recs,
            out,
            cfg,
            modes=_parse_modes(mode),
            jobs=jobs,
            progress=bar.update_to,
            scheduler=scheduler,
        )
    return write_report(runs, out, command, cfg, doc)


@app.command()
def compare(
    recordings: Annotated[list[Path], typer.Argument(help="Recording folders.")],
    out: Annotated[Path, typer.Option(help="Folder for runs and the report.")],
    mode: Annotated[str, typer.Option(help="Modes to run.")] = "all",
    config: Annotated[Path | None, typer.Option(help="Pipeline config YAML.")] = None,
    jobs: Annotated[int, typer.Option(help="Parallel processes.")] = 1,
    doc: Annotated[Path | None, typer.Option(help="Also write the report here.")] = None,
    scheduler: Annotated[str | None, typer.Option(help=_SCHEDULER_HELP)] = None,
) -> None:
    """Filter vs smoother vs batch on existing recordings, grouped by their scenario.

    Example: vio-graph compare data/recordings/upstair_s* data/recordings/downstair_s* --out
    results/cmp
    """
    from vio_graph.config import load_config
    from vio_graph.recording import Recording

    cfg = load_config(config)
    recs = []
    for r in recordings:
        meta = Recording.open(r).metadata
        recs.append((meta.provenance.scenario or meta.terrain.kind, meta.provenance.seed, Path(r)))
    command = "vio-graph compare " + " ".join(sys.argv[2:])
    written = _estimate_and_report(recs, out, cfg, mode, jobs, scheduler, command, doc)
    typer.echo(written["markdown"].read_text().split("## Smoother vs filter")[0])
    for k, p in written.items():
        typer.echo(f"{k:9} {p}")


@app.command()
def batch(
    recordings: Annotated[list[Path], typer.Argument(help="Recording folders.")],
    out: Annotated[Path, typer.Option(help="Study folder: runs/, summary.csv/.md/.png.")],
    mode: Annotated[str, typer.Option(help="filter | smoother | batch | all (comma list ok).")] = (
        "all"
    ),
    config: Annotated[Path | None, typer.Option(help="Base pipeline config YAML.")] = None,
    set_: Annotated[
        list[str] | None,
        typer.Option(
            "--set",
            help="Grid over a config field, FIELD=V1,V2 (repeatable; the "
            "grid is every combination), e.g. --set smoother.window_s=1,2.",
        ),
    ] = None,
    scheduler: Annotated[
        str | None,
        typer.Option(
            help="Dask scheduler address (tcp://HOST:PORT); 'local' (default) starts a "
            "LocalCluster here; 'serial' runs every task in this process."
        ),
    ] = None,
    workers: Annotated[
        int | None, typer.Option(help="LocalCluster worker processes (default: CPU count).")
    ] = None,
    resume: Annotated[
        bool, typer.Option(help="Skip tasks whose outputs are complete (same config).")
    ] = False,
    overwrite: Annotated[
        bool, typer.Option(help="Run every task again into an existing study folder.")
    ] = False,
) -> None:
    """Many trials at once: one Dask task per recording x mode x config, failures isolated,
    one summary (summary.csv, summary.md, summary.png) in --out.

    Example: vio-graph batch data/sample data/recordings/up1 --out results/study
    --mode filter,smoother --set smoother.window_s=1,2 --workers 2
    """
    from vio_graph.config import load_config
    from vio_graph.studies.batch import make_tasks, run_batch, write_summary
    from vio_graph.studies.grid import expand_grid
    from vio_graph.viz.progress import progress_bar

    missing = [str(r) for r in recordings if not r.is_dir()]
    if missing:
        raise VioGraphError(f"not a recording folder: {', '.join(missing)}")
    if (out / "runs").exists() and not (resume or overwrite):
        raise VioGraphError(
            f"{out}: a study is already there (use --resume to finish it or "
            "--overwrite to run it again)"
        )
    grid = expand_grid(load_config(config), set_)
    modes = _parse_modes(mode)
    tasks = make_tasks(recordings, modes, grid, out)
    typer.echo(
        f"{len(tasks)} tasks: {len(recordings)} recording(s) x {len(modes)} mode(s) x "
        f"{len(grid)} config(s)",
        err=True,
    )
    with progress_bar(len(tasks), "batch", "task") as bar:
        rows = run_batch(tasks, out, scheduler, workers, resume, progress=bar.update_to)
    command = "vio-graph batch " + " ".join(sys.argv[2:])
    written = write_summary(rows, out, command.strip())
    failed = [r for r in rows if r["status"] != "ok"]
    for r in failed:
        typer.secho(
            f"failed {r['config']}/{r['trial']}/{r['mode']}: {r['error']}",
            fg=typer.colors.RED,
            err=True,
        )
    for k, p in written.items():
        typer.echo(f"{k:9} {p}")
    if failed:
        raise VioGraphError(
            f"{len(failed)} of {len(rows)} tasks failed (listed in {written['markdown']})"
        )


@app.command("map")
def map_command(
    recording: Annotated[Path, typer.Argument(help="Recording folder.")],
    out: Annotated[Path, typer.Option(help="Output folder for the map.")],
    mode: Annotated[
        str, typer.Option(help="Poses to build the map from: filter | smoother | batch.")
    ] = "batch",
    config: Annotated[Path | None, typer.Option(help="Pipeline config YAML.")] = None,
    overwrite: Annotated[
        bool, typer.Option(help="Write into an existing, non-empty folder.")
    ] = False,
) -> None:
    """Build the 2D stair map from refined keyframes and export it: map.ply, map.pcd (open3d),
    steps.json, steps.csv (rise, tread, nosing per step) and map.png.

    Example: vio-graph map data/recordings/upstair_s1 --out results/upstair_s1_map
    """
    from vio_graph.config import load_config
    from vio_graph.pipeline import run_recording

    modes = _parse_modes(mode)
    result = run_recording(
        recording, out, load_config(config), modes=modes, overwrite=overwrite, visualize=False
    )
    m = result.metrics.get("map", {})
    typer.echo(
        f"map from {m.get('source_mode')} poses: {m.get('points', 0)} points, "
        f"{m.get('n_steps_estimated')} steps"
    )
    if m.get("rise_error_mm") is not None:
        typer.echo(
            f"rise error {m['rise_error_mm']:.1f} mm, tread error "
            f"{m.get('tread_error_mm') or float('nan'):.1f} mm (vs the recording's truth)"
        )
    typer.echo(f"map files in {out / 'map'}")


def _report_interrupt(exc: BaseException) -> int:
    """Say what an interrupted command finished; return the exit code (128 + signal)."""
    signum = getattr(exc, "signum", signal.SIGINT)
    typer.echo(f"interrupted by {signal.Signals(signum).name}", err=True)
    completed = getattr(exc, "completed", None)
    out_dir = getattr(exc, "out_dir", None)
    if completed is not None and out_dir is not None:
        names = sorted(str(p.relative_to(out_dir)) for p in completed)
        typer.echo(
            f"completed outputs in {out_dir} ({len(names)}, each file whole; the rest "
            f"was not written): {', '.join(names) if names else 'none'}",
            err=True,
        )
    else:
        typer.echo("no partial output was left behind", err=True)
    return 128 + int(signum)


@app.command()
def robustness(
    out: Annotated[Path, typer.Option(help="Folder for recordings, runs and the report.")] = Path(
        "results/robustness"
    ),
    scenario: Annotated[str, typer.Option(help="Scenario to perturb.")] = "upstair",
    seeds: Annotated[int, typer.Option(help="Seeds 1..N.")] = 2,
    config: Annotated[Path | None, typer.Option(help="Pipeline config YAML.")] = None,
    jobs: Annotated[int, typer.Option(help="Parallel processes.")] = 1,
    doc: Annotated[
        Path | None, typer.Option(help="Also write the report here (e.g. docs/robustness.md).")
    ] = None,
    cases: Annotated[
        str,
        typer.Option(
            help="'all' faults, or 'imu': clean, IMU spikes / saturation, "
            "camera-IMU offsets -30..30 ms, clock jitter; or 'offsets': clean and the "
            "camera-IMU offsets only; or 'saturation': clean and the 4 g accelerometer "
            "saturation only; or 'spikes': clean and the 2 Hz IMU spikes only; or 'knock': "
            "clean and the 0.1 s IMU knock only; or 'occluder': clean and the occluding foot "
            "only."
        ),
    ] = "all",
) -> None:
    """Fault sweep: toe ATE of filter, smoother and batch for camera blackouts, dropped frames,
    wrong corner associations, depth corruption, IMU spikes/saturation, time offset and jitter.

    Example: vio-graph robustness --seeds 2 --jobs 2 --doc docs/robustness.md
    """
    from vio_graph.config import load_config
    from vio_graph.robustness import (
        FAULT_CASES,
        IMU_CASES,
        KNOCK_CASES,
        OCCLUDER_CASES,
        OFFSET_CASES,
        SATURATION_CASES,
        SPIKE_CASES,
        run_sweep,
        write_outputs,
    )
    from vio_graph.viz.progress import progress_bar

    case_sets = {
        "all": FAULT_CASES,
        "imu": IMU_CASES,
        "offsets": OFFSET_CASES,
        "saturation": SATURATION_CASES,
        "spikes": SPIKE_CASES,
        "knock": KNOCK_CASES,
        "occluder": OCCLUDER_CASES,
    }
    if cases not in case_sets:
        raise VioGraphError(
            f"--cases: unknown {cases!r}; use all, imu, offsets, saturation, spikes, knock or "
            "occluder"
        )
    case_list = case_sets[cases]
    cfg = load_config(config)
    seed_list = list(range(1, seeds + 1))
    with progress_bar(len(case_list) * len(seed_list), "fault sweep", "run") as bar:
        results = run_sweep(
            out, scenario, seed_list, cfg, case_list, jobs=jobs, progress=bar.update_to
        )
    command = "vio-graph robustness " + " ".join(sys.argv[2:])
    written = write_outputs(results, out, command.strip(), doc)
    typer.echo(written["markdown"].read_text())


@app.command("import-bag")
def import_bag_command(
    bag: Annotated[Path, typer.Argument(help="ROS 1 .bag, ROS 2 bag folder, or .mcap/.db3 file.")],
    rig: Annotated[Path, typer.Option(help="Rig YAML (see configs/rig_example.yaml).")],
    out: Annotated[Path, typer.Option(help="Output recording folder.")],
    depth_topic: Annotated[
        str, typer.Option(help="sensor_msgs/Image, 32FC1 m or 16UC1 mm.")
    ] = "/pico_flexx/image_depth",
    camera_info_topic: Annotated[
        str, typer.Option(help="sensor_msgs/CameraInfo.")
    ] = "/pico_flexx/camera_info",
    imu_topic: Annotated[str, typer.Option(help="sensor_msgs/Imu.")] = "/imu/data",
    joints_topic: Annotated[str, typer.Option(help="sensor_msgs/JointState.")] = "/joint_states",
    receive_time: Annotated[
        bool,
        typer.Option("--receive-time", help="Use the bag's receive time instead of header.stamp."),
    ] = False,
    groundtruth_dir: Annotated[
        Path | None,
        typer.Option(help="Folder with camera/knee/ankle/heel/toe.tum on the bag clock."),
    ] = None,
    overwrite: Annotated[bool, typer.Option(help="Replace an existing folder.")] = False,
) -> None:
    """Convert a ROS bag (pico flexx depth, Xsens IMU, joint states) into a recording.

    Example: vio-graph import-bag trial.bag --rig configs/rig_example.yaml
    --out data/recordings/trial1
    """
    if out.exists() and not overwrite:
        raise VioGraphError(f"{out}: already exists (use --overwrite to replace it)")
    from vio_graph.recording.rosbag_import import BagTopics, import_bag
    from vio_graph.viz.progress import progress_bar

    topics = BagTopics(
        depth=depth_topic, camera_info=camera_info_topic, imu=imu_topic, joints=joints_topic
    )
    with progress_bar(total=None, desc=f"importing {bag.name}", unit="frame") as bar:
        path = import_bag(
            bag,
            rig,
            out,
            topics=topics,
            use_receive_time=receive_time,
            groundtruth_dir=groundtruth_dir,
            progress=bar.update_to,
            overwrite=overwrite,
        )
    typer.echo(f"wrote {path}")


def main() -> None:
    """Console-script entry point: known errors -> one line and exit code 1; SIGINT/SIGTERM
    -> cleanup, a note of the completed outputs, exit code 130/143."""
    signal.signal(signal.SIGTERM, on_sigterm)
    from vio_graph.memory import freeze_at_exit

    freeze_at_exit()  # this process is ours: its shutdown need not collect (memory.py)
    # invoke the click command directly: typer's own main turns KeyboardInterrupt into a bare
    # exit code 130, losing which signal it was and what the interrupted command completed
    command = typer.main.get_command(app)
    try:
        with command.make_context("vio-graph", sys.argv[1:]) as ctx:
            command.invoke(ctx)
    except VioGraphError as exc:
        typer.echo(f"error: {exc}", err=True)
        sys.exit(1)
    except KeyboardInterrupt as exc:
        sys.exit(_report_interrupt(exc))
    except BrokenPipeError:  # output piped into e.g. `head`, which closed early
        import os

        os.dup2(os.open(os.devnull, os.O_WRONLY), sys.stdout.fileno())
        sys.exit(1)
    except typer.Exit as exc:  # --help, typer.Exit
        sys.exit(exc.exit_code)
    except typer.Abort:
        typer.echo("aborted", err=True)
        sys.exit(130)
    except typer.TyperException as exc:  # (typer's own click) usage errors: message, exit 2
        show = getattr(exc, "show", None)
        if show is not None:
            show()
        else:
            typer.echo(f"error: {exc.format_message()}", err=True)
        sys.exit(exc.exit_code)


if __name__ == "__main__":
    main()
