"""Parameter grids over pipeline config fields: ``--set filter.x=1,2 --set smoother.window_s=1,2``.

Each ``--set`` names a field by its dotted path in :class:`~vio_graph.config.PipelineConfig`
(checked against the pydantic models: an unknown section or field is an error naming the
fields that exist) and gives one or more comma-separated values (each read as YAML: ``1.5``,
``true``, ``imu``). The grid is the Cartesian product of the ``--set`` options, in the order
given; every point is merged into the base config and validated (a bad value is an error
naming the field and the pydantic message).
"""

from __future__ import annotations

import itertools
import re
import typing
from dataclasses import dataclass
from typing import Any

import yaml
from pydantic import BaseModel, ValidationError

from vio_graph.config import PipelineConfig
from vio_graph.errors import VioGraphError


@dataclass(frozen=True)
class GridPoint:
    """One config of a grid: its folder-safe ``tag``, the values set, the validated config."""

    tag: str
    params: dict[str, Any]
    config: PipelineConfig


def _model_in(annotation: Any) -> type[BaseModel] | None:
    """The pydantic model a field holds (also inside ``X | None``), else None."""
    if isinstance(annotation, type) and issubclass(annotation, BaseModel):
        return annotation
    for arg in typing.get_args(annotation):
        if isinstance(arg, type) and issubclass(arg, BaseModel):
            return arg
    return None


def check_field_path(path: str, model: type[BaseModel] = PipelineConfig) -> None:
    """Raise VioGraphError unless ``path`` (``section.field[.sub]``) is a field of ``model``."""
    parts = path.split(".")
    if not all(parts):
        raise VioGraphError(f"--set {path}: empty field name")
    current: type[BaseModel] | None = model
    walked = []
    for k, name in enumerate(parts):
        if current is None:
            raise VioGraphError(
                f"--set {path}: {'.'.join(walked)} is a value, not a section (no field "
                f"{name!r} below it)"
            )
        fields = current.model_fields
        if name not in fields:
            where = ".".join(walked) or "the pipeline config"
            raise VioGraphError(
                f"--set {path}: {where} has no field {name!r}; fields: {', '.join(fields)}"
            )
        walked.append(name)
        sub = _model_in(fields[name].annotation)
        if k == len(parts) - 1 and sub is not None:
            raise VioGraphError(
                f"--set {path}: {path} is a section; name one of its fields: "
                f"{', '.join(sub.model_fields)}"
            )
        current = sub


def parse_set(option: str) -> tuple[str, list[Any]]:
    """``"filter.x=1,2"`` -> ``("filter.x", [1, 2])`` (field checked, values read as YAML)."""
    if "=" not in option:
        raise VioGraphError(
            f"--set {option}: expected FIELD=VALUE[,VALUE...], e.g. --set smoother.window_s=1,2"
        )
    path, _, raw = option.partition("=")
    path = path.strip()
    check_field_path(path)
    texts = [v.strip() for v in raw.split(",")]
    if not raw.strip() or not all(texts):
        raise VioGraphError(f"--set {option}: empty value")
    try:
        values = [yaml.safe_load(v) for v in texts]
    except yaml.YAMLError as exc:
        raise VioGraphError(f"--set {option}: cannot read a value ({exc})") from None
    if len(set(map(repr, values))) != len(values):
        raise VioGraphError(f"--set {option}: a value is repeated")
    return path, values


def _set_in(data: dict[str, Any], path: str, value: Any) -> None:
    parts = path.split(".")
    for name in parts[:-1]:
        data = data[name]
    data[parts[-1]] = value


def _slug(text: str) -> str:
    return re.sub(r"[^A-Za-z0-9._-]+", "-", text).strip("-")


def expand_grid(base: PipelineConfig, options: list[str] | None) -> list[GridPoint]:
    """Every combination of the ``--set`` options merged into ``base``; no options -> one
    point tagged ``base``."""
    axes = [parse_set(o) for o in options or []]
    paths = [p for p, _ in axes]
    if len(set(paths)) != len(paths):
        raise VioGraphError(f"--set: a field is set twice ({', '.join(paths)})")
    if not axes:
        return [GridPoint("base", {}, base)]
    points = []
    for combo in itertools.product(*(values for _, values in axes)):
        data = base.model_dump(mode="json")
        params = dict(zip(paths, combo, strict=True))
        for path, value in params.items():
            _set_in(data, path, value)
        try:
            cfg = PipelineConfig.model_validate(data)
        except ValidationError as exc:
            err = exc.errors()[0]
            where = ".".join(str(x) for x in err["loc"])
            raise VioGraphError(
                f"--set {', '.join(f'{k}={v}' for k, v in params.items())}: {where}: {err['msg']}"
            ) from None
        tag = "__".join(_slug(f"{k}-{v}") for k, v in params.items())
        points.append(GridPoint(tag, params, cfg))
    return points
