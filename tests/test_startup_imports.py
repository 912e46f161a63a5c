"""Start-up cost of the command line is paid only for what a command uses (issue 10): the
heavy libraries are imported where they are needed, never at module level of the command
line. Checked on ``sys.modules`` of a fresh interpreter (no timing asserts)."""

from __future__ import annotations

import json
import os
import subprocess
import sys
from pathlib import Path

import pytest

REPO = Path(__file__).resolve().parents[1]
HEAVY = (
    "gtsam",
    "numba",
    "llvmlite",
    "matplotlib",
    "rerun",
    "open3d",
    "scipy",
    "dask",
    "pandas",
    "numpy",
    "pydantic",
    "yaml",
)

# runs the command line in this interpreter, then prints which of HEAVY it imported
_PROBE = """
import contextlib, io, json, sys
heavy = set(json.loads(sys.argv[2]))
sys.argv = ["vio-graph"] + json.loads(sys.argv[1])
import vio_graph.cli
if sys.argv[1:]:
    with contextlib.redirect_stdout(io.StringIO()):
        try:
            vio_graph.cli.main()
        except SystemExit as exc:
            assert not exc.code, exc.code
print(json.dumps(sorted({m.split(".")[0] for m in sys.modules} & heavy)))
"""


def _imported(args: list[str]) -> set[str]:
    env = {k: v for k, v in os.environ.items() if k != "VIO_GRAPH_COMPILED"}
    env["PYTHONPATH"] = str(REPO) + os.pathsep + env.get("PYTHONPATH", "")
    out = subprocess.run(
        [sys.executable, "-c", _PROBE, json.dumps(args), json.dumps(HEAVY)],
        capture_output=True,
        text=True,
        cwd=REPO,
        env=env,
        timeout=600,
    )
    assert out.returncode == 0, out.stderr[-2000:]
    return set(json.loads(out.stdout.strip().splitlines()[-1]))


def test_importing_the_command_line_imports_no_heavy_library() -> None:
    # `vio-graph --help` needs typer only: not even numpy
    assert _imported([]) == set()
    assert _imported(["--help"]) == set()


def test_info_reads_the_recording_without_the_estimator_libraries() -> None:
    # metadata (pydantic, YAML) and the streams (numpy); no scipy, compiled kernels, plots
    assert _imported(["info", str(REPO / "data" / "sample")]) == {"numpy", "pydantic", "yaml"}


@pytest.mark.slow
def test_run_imports_only_what_its_mode_and_outputs_use(tmp_path: Path) -> None:
    sample = str(REPO / "data" / "sample")
    # the filter without rerun and figures: no GTSAM, no rerun, no matplotlib, no numba
    # (a short recording runs the numpy paths), no open3d (the map files are written directly)
    lean = _imported(
        ["run", sample, "--out", str(tmp_path / "a"), "--mode", "filter", "--no-rerun"]
        + ["--no-plots"]
    )
    assert lean == {"numpy", "pydantic", "yaml", "scipy"}
    # the .rrd brings rerun, figures matplotlib, the smoother GTSAM
    more = _imported(["run", sample, "--out", str(tmp_path / "b"), "--mode", "smoother"])
    assert {"matplotlib", "gtsam", "rerun"} <= more
    # figures alone: matplotlib, and nothing of the smoothers or rerun
    plots_only = _imported(["run", sample, "--out", str(tmp_path / "c"), "--no-rerun"])
    assert "matplotlib" in plots_only and not {"gtsam", "rerun", "numba"} & plots_only
