"""Static types: mypy (with the pydantic plugin) is clean on the packages listed in
pyproject.toml's [tool.mypy] ``files`` (frontend, filter, smoother, geometry, types, the
estimator protocol, the online estimator, the replay and the run's pipeline). Runs as part
of the test suite, so the README's test command is the CI check."""

from __future__ import annotations

import subprocess
import sys
import tempfile
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]


def _mypy(*paths: str) -> subprocess.CompletedProcess[str]:
    """mypy with the project's configuration and a cache reused between runs; no paths =
    the configured ``files``."""
    cache = Path(tempfile.gettempdir()) / "vio_graph_mypy_cache"
    return subprocess.run(
        [
            sys.executable,
            "-m",
            "mypy",
            "--config-file",
            str(ROOT / "pyproject.toml"),
            "--cache-dir",
            str(cache),
            *paths,
        ],
        cwd=ROOT,
        capture_output=True,
        text=True,
        timeout=600,
    )


def test_mypy_is_clean_on_the_core_packages() -> None:
    out = _mypy()
    assert "No module named mypy" not in out.stderr, "install the test extra: .[test]"
    assert out.returncode == 0, out.stdout + out.stderr
    assert "Success: no issues found" in out.stdout


def test_mypy_reports_a_type_error(tmp_path: Path) -> None:
    """The check can fail: the same configuration flags a wrong argument type."""
    bad = tmp_path / "bad.py"
    bad.write_text("from vio_graph.geometry import rot_y\n\nrot_y('half a turn')\n")
    out = _mypy(str(bad))
    assert out.returncode == 1, out.stdout + out.stderr
    assert "bad.py:3: error" in out.stdout
