"""Lint: ruff check (rules in pyproject.toml [tool.ruff]) is clean and ruff format changes
nothing, on the package, the tests and the benchmarks. Runs as part of the test suite, so the
README's test command is the CI check."""

from __future__ import annotations

import subprocess
import sys
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
TREES = ["vio_graph", "tests", "benchmarks"]


def _ruff(*args: str) -> subprocess.CompletedProcess[str]:
    return subprocess.run(
        [sys.executable, "-m", "ruff", *args], cwd=ROOT, capture_output=True, text=True, timeout=300
    )


def test_ruff_check_is_clean() -> None:
    out = _ruff("check", "--no-cache", *TREES)
    assert "No module named ruff" not in out.stderr, "install the test extra: .[test]"
    assert out.returncode == 0, out.stdout + out.stderr


def test_ruff_reports_a_lint_error(tmp_path: Path) -> None:
    """The check can fail: an unused import in a file under the same configuration."""
    bad = tmp_path / "bad.py"
    bad.write_text("import os\n")
    out = _ruff("check", "--no-cache", "--config", str(ROOT / "pyproject.toml"), str(bad))
    assert out.returncode == 1 and "F401" in out.stdout, out.stdout + out.stderr


def test_ruff_format_leaves_the_tree_unchanged() -> None:
    out = _ruff("format", "--check", "--no-cache", *TREES)
    assert out.returncode == 0, out.stdout + out.stderr
