"""The ``vio-graph`` command line (typer). Thin: parse, call the library, report.

Known errors (:class:`vio_graph.errors.VioGraphError`) become one line on stderr and exit code 1.
"""

from __future__ import annotations

import json
import logging
import sys
from pathlib import Path
from typing import Annotated

import typer

from vio_graph.errors import VioGraphError

app = typer.Typer(
    add_completion=False,
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
def _main(verbose: Annotated[bool, typer.Option("--verbose", "-v", help="Debug logging.")] = False) -> None:
    _setup_logging(verbose)


@app.command()
def info(
    recording: Annotated[Path, typer.Argument(help="Recording folder.")],
    as_json: Annotated[bool, typer.Option("--json", help="Print one JSON object.")] = False,
) -> None:
    """Validate a recording and summarise it.

    Example: vio-graph info runs/upstair_s1 --json
    """
    from vio_graph.recording import Recording

    summary = Recording.open(recording).summary()
    if as_json:
        typer.echo(json.dumps(summary))
        return
    typer.echo(f"recording      {summary['path']}  (format v{summary['format_version']}, valid)")
    typer.echo(f"duration       {summary['duration_s']:.2f} s")
    typer.echo(f"depth frames   {summary['frames']} at {summary['frame_rate_hz']:.2f} Hz, "
               f"{summary['image_size'][0]} x {summary['image_size'][1]} px")
    typer.echo(f"IMU            {summary['imu_samples']} samples at {summary['imu_rate_hz']:.2f} Hz")
    typer.echo(f"joint angles   {summary['joint_samples']} at {summary['joint_rate_hz']:.2f} Hz")
    if summary["gt_rate_hz"]:
        typer.echo(f"ground truth   {', '.join(summary['gt_bodies'])} at "
                   f"{summary['gt_rate_hz']:.2f} Hz")
    else:
        typer.echo("ground truth   none")
    if "edge_visible_fraction" in summary:
        typer.echo(f"edge visible   {100 * summary['edge_visible_fraction']:.1f} % of frames")
    terrain = ", ".join(f"{k}={v}" for k, v in summary["terrain"].items())
    typer.echo(f"rig / terrain  {summary['rig']} / {terrain}")
    p = summary["provenance"]
    typer.echo(f"provenance     {p['source']} scenario={p['scenario']} seed={p['seed']} {p['software']}")


@app.command()
def simulate(
    scenario: Annotated[str, typer.Option(help="Scenario name in configs/ or a YAML path.")],
    out: Annotated[Path, typer.Option(help="Output recording folder.")],
    seed: Annotated[int, typer.Option(help="Random seed (same seed, same recording).")] = 1,
    overwrite: Annotated[bool, typer.Option(help="Replace an existing folder.")] = False,
) -> None:
    """Simulate a trial with ground truth into a recording folder.

    Example: vio-graph simulate --scenario upstair --seed 1 --out runs/upstair_s1
    """
    from vio_graph.sim import load_scenario, simulate as run_simulation
    from vio_graph.viz.progress import progress_bar

    if out.exists() and not overwrite:
        raise VioGraphError(f"{out}: already exists (use --overwrite to replace it)")
    config = load_scenario(scenario)
    with progress_bar(total=None, desc=f"simulating {scenario} seed {seed}", unit="frame") as bar:
        path = run_simulation(config, seed, out, progress=bar.update_to)
    typer.echo(f"wrote {path}")


def main() -> None:
    """Console-script entry point: known errors -> one line and exit code 1."""
    try:
        app(standalone_mode=False)
    except VioGraphError as exc:
        typer.echo(f"error: {exc}", err=True)
        sys.exit(1)
    except KeyboardInterrupt:
        typer.echo("interrupted", err=True)
        sys.exit(130)
    except Exception as exc:  # click's own usage errors
        import click

        if isinstance(exc, click.exceptions.ClickException):
            exc.show()
            sys.exit(exc.exit_code)
        if isinstance(exc, click.exceptions.Exit):
            sys.exit(exc.exit_code)
        if isinstance(exc, click.exceptions.Abort):
            typer.echo("aborted", err=True)
            sys.exit(130)
        raise


if __name__ == "__main__":
    main()
