"""Finding and reading YAML config files (shared by the pipeline and the simulator configs)."""

from __future__ import annotations

import atexit
import shutil
import tempfile
from importlib import resources
from importlib.resources.abc import Traversable
from pathlib import Path
from typing import Any, TypeVar

import yaml
from pydantic import BaseModel, ValidationError

import vio_graph
from vio_graph.errors import ConfigError

ModelT = TypeVar("ModelT", bound=BaseModel)

#: Folder of the YAML files inside the installed package. The wheel build maps the repository's
#: top-level ``configs/`` here (``[tool.setuptools.package-dir]`` in pyproject.toml); git holds
#: only the top-level copy.
PACKAGED_CONFIGS = "configs"


def source_configs_dir() -> Path | None:
    """The repository's top-level ``configs/`` when running from a source checkout (an editable
    install or the tests), else None. A checkout is recognised by ``pyproject.toml`` beside the
    package, so an unrelated ``site-packages/configs`` is never picked up."""
    root = Path(vio_graph.__file__).resolve().parents[1]
    folder = root / "configs"
    return folder if (root / "pyproject.toml").is_file() and folder.is_dir() else None


def packaged_configs_dir() -> Path | None:
    """The copy of ``configs/`` shipped in the wheel (``vio_graph/configs``), or None."""
    folder = resources.files(vio_graph) / PACKAGED_CONFIGS
    if not folder.is_dir():
        return None
    if isinstance(folder, Path):
        return folder
    return _extracted(str(folder), folder)  # e.g. imported from a zip: the loaders need files


_EXTRACTED: dict[str, Path] = {}


def _extracted(key: str, folder: Traversable) -> Path:
    """The files of ``folder`` copied once per process (under ``key``) to a temporary folder."""
    if key not in _EXTRACTED:
        target = Path(tempfile.mkdtemp(prefix="vio_graph_configs_"))
        atexit.register(shutil.rmtree, target, ignore_errors=True)
        for item in folder.iterdir():
            if item.is_file():
                (target / item.name).write_bytes(item.read_bytes())
        _EXTRACTED[key] = target
    return _EXTRACTED[key]


def config_dirs() -> list[Path]:
    """Where bare config names are looked up, in order: the repository's ``configs/`` (so edits
    there take effect in a checkout), then the copy packaged in the wheel."""
    return [d for d in (source_configs_dir(), packaged_configs_dir()) if d is not None]


def configs_dir() -> Path:
    """The first folder of :func:`config_dirs`: the repository's ``configs/`` in a checkout, the
    packaged copy in an installed wheel (if neither exists, the packaged location, which then
    makes "not found" errors name where the file was expected)."""
    dirs = config_dirs()
    return dirs[0] if dirs else Path(vio_graph.__file__).resolve().parent / PACKAGED_CONFIGS


def resolve_config_path(name_or_path: str | Path) -> Path:
    """A bare name means ``NAME.yaml`` in the first of :func:`config_dirs` holding it; anything
    with a suffix or a slash is a path, used as given."""
    text = str(name_or_path)
    is_path = text.endswith((".yaml", ".yml")) or "/" in text or "\\" in text
    if is_path:
        return Path(text)
    for folder in config_dirs():
        candidate = folder / f"{text}.yaml"
        if candidate.is_file():
            return candidate
    # not found: a path in the primary folder, so the caller's "not found" error names it
    return configs_dir() / f"{text}.yaml"


def load_yaml_mapping(path: Path) -> dict[str, Any]:
    """Read a YAML mapping safely; errors name the file."""
    path = Path(path)
    if not path.is_file():
        raise ConfigError(f"{path}: config file not found")
    try:
        data = yaml.safe_load(path.read_text(encoding="utf-8")) or {}
    except (yaml.YAMLError, UnicodeDecodeError) as exc:
        raise ConfigError(f"{path}: not valid YAML ({exc})") from None
    if not isinstance(data, dict):
        raise ConfigError(f"{path}: top level must be a mapping")
    return data


def validate_model(model: type[ModelT], data: dict[str, Any], path: Path) -> ModelT:
    """Validate ``data`` against ``model``; the error names the file and every bad field."""
    try:
        return model.model_validate(data)
    except ValidationError as exc:
        problems = "; ".join(
            f"{'.'.join(str(p) for p in e['loc'])}: {e['msg']}" for e in exc.errors()
        )
        raise ConfigError(f"{path}: {problems}") from None
