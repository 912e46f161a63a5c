"""Finding and reading YAML config files (shared by the pipeline and the simulator configs)."""

from __future__ import annotations

from pathlib import Path
from typing import Any, TypeVar

import yaml
from pydantic import BaseModel, ValidationError

import vio_graph
from vio_graph.errors import ConfigError

ModelT = TypeVar("ModelT", bound=BaseModel)


def configs_dir() -> Path:
    """The repository's ``configs/`` folder (beside the package)."""
    return Path(vio_graph.__file__).resolve().parents[1] / "configs"


def resolve_config_path(name_or_path: str | Path) -> Path:
    """A bare name means ``configs/NAME.yaml``; anything with a suffix or a slash is a path."""
    text = str(name_or_path)
    is_path = text.endswith((".yaml", ".yml")) or "/" in text or "\\" in text
    return Path(text) if is_path else configs_dir() / f"{text}.yaml"


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
