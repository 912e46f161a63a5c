"""A plain (non-editable) install works: the wheel carries the scenario and pipeline YAML files
and the installed package finds them from any working directory.

The slow test builds the wheel from this checkout, installs it with ``--no-deps --no-index`` into
a fresh venv made in tmp_path (dependencies come from the dev environment's site-packages through
a .pth line, which does not run the dev environment's editable-install hook, so the only
``vio_graph`` importable is the installed one), and runs the console script from tmp_path,
outside the repository.
"""

from __future__ import annotations

import os
import shutil
import subprocess
import sys
import sysconfig
import tomllib
import venv
from importlib import metadata
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]


def test_every_subpackage_is_listed() -> None:
    """pyproject lists the packages (vio_graph.configs has no folder to be found): a subpackage
    missing from the list would be missing from the wheel."""
    listed = set(
        tomllib.loads((ROOT / "pyproject.toml").read_text())["tool"]["setuptools"]["packages"]
    )
    inits = (ROOT / "vio_graph").rglob("__init__.py")
    on_disk = {".".join(p.parent.relative_to(ROOT).parts) for p in inits}
    missing = sorted(on_disk - listed)
    assert not missing, f"add {missing} to [tool.setuptools] packages in pyproject.toml"
    assert listed - on_disk == {"vio_graph.configs"}


def _can_build_without_isolation() -> bool:
    """setuptools>=77 and wheel in this interpreter (the ``test`` extra installs them): then the
    build needs no index at all."""
    try:
        major = int(metadata.version("setuptools").split(".")[0])
        metadata.version("wheel")
    except metadata.PackageNotFoundError:
        return False
    return major >= 77


def _run(cmd: list[str], cwd: Path, env: dict[str, str], timeout: float = 120) -> str:
    proc = subprocess.run(cmd, cwd=cwd, env=env, capture_output=True, text=True, timeout=timeout)
    assert proc.returncode == 0, (
        f"{' '.join(map(str, cmd))} exited {proc.returncode}\n{proc.stdout}\n{proc.stderr}"
    )
    return proc.stdout


@pytest.mark.slow
def test_wheel_install_finds_packaged_configs(tmp_path: Path) -> None:
    env = {
        k: v
        for k, v in os.environ.items()
        if k not in ("PYTHONPATH", "PYTHONHOME", "VIRTUAL_ENV", "PYTHONSTARTUP")
    }
    env["PIP_DISABLE_PIP_VERSION_CHECK"] = "1"

    # 1. the wheel, built from a copy of what the build reads (an in-tree build would leave
    #    build/ in the checkout, whose stale files later builds would pick up)
    src = tmp_path / "src"
    src.mkdir()
    for name in ("pyproject.toml", "README.md"):
        shutil.copy2(ROOT / name, src / name)
    for name in ("vio_graph", "configs"):
        shutil.copytree(
            ROOT / name, src / name, ignore=shutil.ignore_patterns("__pycache__", "*.pyc")
        )
    wheel_dir = tmp_path / "wheel"
    build = [
        sys.executable,
        "-m",
        "pip",
        "wheel",
        str(src),
        "--no-deps",
        "-q",
        "-w",
        str(wheel_dir),
    ]
    if _can_build_without_isolation():
        build += ["--no-build-isolation", "--no-index"]
    _run(build, tmp_path, env, timeout=180)
    (wheel,) = wheel_dir.glob("vio_graph-*.whl")

    # 2. a fresh venv, dependencies visible through a .pth line, the wheel installed offline
    env_dir = tmp_path / "venv"
    venv.EnvBuilder(with_pip=False).create(env_dir)
    python = env_dir / "bin" / "python"
    purelib = "import sysconfig; print(sysconfig.get_paths()['purelib'])"
    site = Path(_run([str(python), "-c", purelib], tmp_path, env).strip())
    dev_site = {sysconfig.get_paths()["purelib"], sysconfig.get_paths()["platlib"]}
    (site / "_dev_dependencies.pth").write_text("\n".join(sorted(dev_site)) + "\n")
    _run(
        [
            sys.executable,
            "-m",
            "pip",
            "--python",
            str(python),
            "install",
            "--no-deps",
            "--no-index",
            "-q",
            str(wheel),
        ],
        tmp_path,
        env,
    )

    # 3. from outside the repository, the console script as a user runs it (before the fix:
    #    "site-packages/configs/upstair.yaml: scenario file not found"); the demo reuses this
    #    recording (same seed) and reads the packaged default pipeline config
    work = tmp_path / "elsewhere"
    work.mkdir()
    script = env_dir / "bin" / "vio-graph"
    out = work / "demo"
    _run(
        [
            str(script),
            "simulate",
            "--scenario",
            "upstair",
            "--seed",
            "1",
            "--out",
            str(out / "recording_upstair_s1"),
        ],
        work,
        env,
    )
    demo = _run([str(script), "demo", "--mode", "filter", "--out", str(out)], work, env)
    assert "ATE" in demo and (out / "results").is_dir()

    # 4. what was found: the installed package's copies of every configs/*.yaml, byte for byte
    #    (load_config() falls back silently to the in-code defaults when default.yaml is absent,
    #    so the demo alone does not show it was found)
    check = f"""
import filecmp, pathlib, vio_graph
from vio_graph.config_files import config_dirs, configs_dir, resolve_config_path
pkg = pathlib.Path(vio_graph.__file__).resolve().parent
assert pkg.is_relative_to(pathlib.Path({str(site)!r}).resolve()), pkg
assert config_dirs() == [pkg / "configs"] and configs_dir() == pkg / "configs", config_dirs()
repo = pathlib.Path({str(ROOT / "configs")!r})
names = sorted(p.name for p in repo.glob("*.yaml"))
assert sorted(p.name for p in (pkg / "configs").glob("*.yaml")) == names
for name in names:
    path = resolve_config_path(name[:-5])
    assert path == pkg / "configs" / name and filecmp.cmp(path, repo / name, shallow=False), path
print("ok")
"""
    assert _run([str(python), "-c", check], work, env).strip() == "ok"
