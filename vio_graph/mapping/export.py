"""Files of the mapping subpackage: the 2D map as point clouds, the step geometry as JSON and
CSV, and a PNG plot. The only module of vio_graph.mapping that does I/O; every file is
written atomically (temporary name in the same folder, then rename).

Point clouds (``map.ply``, ``map.pcd``)
    The map points in the world frame as 3D points ``(x, 0, z)`` in metres (the sagittal
    plane is y = 0), written by open3d (binary PLY with double coordinates; binary PCD).

Step geometry JSON (``steps.json``)
    ``{"format": "vio_graph.terrain_geometry", "version": 1, "kind": <TerrainKind value>,
    "summary": {"n_steps", "n_obstacles", "mean_rise_m", "mean_tread_m"},
    "steps": [...], "obstacles": [...], "levels": [...], "risers": [...],
    "comparison": <compare_to_truth dict> | null}``. Each list entry holds the fields of
    the dataclass of the same name in ``vio_graph.mapping.steps`` (arrays as lists, metres);
    unknown values are ``null``.

Step geometry CSV (``steps.csv``)
    One row per step and per obstacle, comma separated, header line first, empty cell =
    unknown. Columns (units in the names, world frame, metres):

    ========================== ========================================================
    ``feature``                ``step`` or ``obstacle``
    ``index``                  step number along +x (obstacles counted separately)
    ``direction``              ``up`` / ``down`` for steps, empty for obstacles
    ``height_m``               step rise, or obstacle height above the ground
    ``height_std_m``           its standard error
    ``depth_m``                step tread (to the next nosing; empty for the last step),
                               or obstacle depth along x
    ``depth_std_m``            its standard error
    ``edge_x_m``, ``edge_z_m``  step nosing, or obstacle front top edge
    ``edge_x_std_m``, ``edge_z_std_m``  their standard errors
    ``back_edge_x_m``, ``back_edge_z_m``, ``back_edge_x_std_m``, ``back_edge_z_std_m``
                               obstacle back top edge (empty for steps)
    ``lower_z_m``, ``upper_z_m``  the two levels of a step; ground and top of an obstacle
    ``riser_observed``         1 if the step's riser was seen (nosing x from the riser),
                               0 if not, empty for obstacles
    ========================== ========================================================

Plot (``map.png``)
    Map points, detected levels (treads / floor) and risers, nosings and obstacle edges with
    their uncertainty, and optionally the true profile and edges; beside it the legend and a
    table of the first :data:`MAP_TABLE_ROWS` steps (the rest in ``steps.csv``). Drawn on an
    Agg canvas with a fixed layout; the camera path through at most
    ``vio_graph.viz.decimate.MAX_LINE_POINTS`` points.
"""

from __future__ import annotations

import csv
import io
import json
import math
from collections.abc import Sequence
from pathlib import Path
from typing import Any

import numpy as np
from numpy.typing import ArrayLike, NDArray

from vio_graph.errors import OutputError
from vio_graph.io_utils import atomic_path, atomic_write_text
from vio_graph.mapping.steps import (
    LevelSegment,
    ObstacleGeometry,
    RiserSegment,
    StepGeometry,
    TerrainGeometry,
)
from vio_graph.o3d import open3d
from vio_graph.recording.metadata import TerrainInfo
from vio_graph.types import TerrainKind

GEOMETRY_FORMAT = "vio_graph.terrain_geometry"
GEOMETRY_VERSION = 1
CSV_COLUMNS = (
    "feature",
    "index",
    "direction",
    "height_m",
    "height_std_m",
    "depth_m",
    "depth_std_m",
    "edge_x_m",
    "edge_z_m",
    "edge_x_std_m",
    "edge_z_std_m",
    "back_edge_x_m",
    "back_edge_z_m",
    "back_edge_x_std_m",
    "back_edge_z_std_m",
    "lower_z_m",
    "upper_z_m",
    "riser_observed",
)


# ---------------------------------------------------------------------------------------------
# point clouds
def _points_3d(points_xz_m: ArrayLike) -> NDArray[np.float64]:
    pts = np.asarray(points_xz_m, dtype=np.float64).reshape(-1, 2)
    return np.column_stack([pts[:, 0], np.zeros(pts.shape[0]), pts[:, 1]])


def write_point_cloud(path: Path, points_xz_m: ArrayLike) -> Path:
    """Write (M, 2) map points as a PLY or PCD file (chosen by the suffix), y = 0.

    Binary little-endian x, y, z (PLY doubles, PCD float32), the layouts open3d writes and
    reads back (:func:`read_point_cloud_xz`), written with numpy: importing open3d costs ~1 s
    a run.

    Raises:
        OutputError: unknown suffix.
    """
    path = Path(path)
    if path.suffix.lower() not in (".ply", ".pcd"):
        raise OutputError(f"{path}: point cloud suffix must be .ply or .pcd")
    pts = np.ascontiguousarray(_points_3d(points_xz_m), dtype="<f8")
    n = pts.shape[0]
    if path.suffix.lower() == ".ply":
        header = (
            "ply\nformat binary_little_endian 1.0\ncomment vio_graph map, x-z plane\n"
            f"element vertex {n}\nproperty double x\nproperty double y\n"
            "property double z\nend_header\n"
        )
    else:  # float32, as open3d writes (and reads) PCD
        pts = pts.astype("<f4")
        header = (
            "# .PCD v0.7 - Point Cloud Data file format\nVERSION 0.7\nFIELDS x y z\n"
            f"SIZE 4 4 4\nTYPE F F F\nCOUNT 1 1 1\nWIDTH {n}\nHEIGHT 1\n"
            f"VIEWPOINT 0 0 0 1 0 0 0\nPOINTS {n}\nDATA binary\n"
        )
    with atomic_path(path, suffix=path.suffix) as tmp:
        Path(tmp).write_bytes(header.encode("ascii") + pts.tobytes())
    return path


def read_point_cloud_xz(path: Path) -> NDArray[np.float64]:
    """Read a PLY/PCD written by :func:`write_point_cloud`: (M, 2) x-z points, metres.

    Raises:
        OutputError: the file is missing, unreadable, or its points are not in y = 0.
    """
    path = Path(path)
    if not path.is_file():
        raise OutputError(f"{path}: no such file")
    cloud = open3d().io.read_point_cloud(str(path))
    pts = np.asarray(cloud.points, dtype=np.float64)
    if pts.size and np.max(np.abs(pts[:, 1])) > 1e-6:
        raise OutputError(f"{path}: points are not in the sagittal plane y = 0")
    return pts[:, [0, 2]].copy()


# ---------------------------------------------------------------------------------------------
# JSON
def _clean(value: Any) -> Any:
    """JSON-ready copy: arrays to lists, numpy scalars to Python, non-finite floats to None."""
    if isinstance(value, dict):
        return {str(k): _clean(v) for k, v in value.items()}
    if isinstance(value, (list, tuple)):
        return [_clean(v) for v in value]
    if isinstance(value, np.ndarray):
        return _clean(value.tolist())
    if isinstance(value, np.generic):
        return _clean(value.item())
    if isinstance(value, TerrainKind):
        return value.value
    if isinstance(value, float) and not math.isfinite(value):
        return None
    return value


def _fields(obj: Any) -> dict[str, Any]:
    return {name: getattr(obj, name) for name in obj.__dataclass_fields__}


def geometry_to_dict(
    geometry: TerrainGeometry, comparison: dict[str, Any] | None = None
) -> dict[str, Any]:
    """The JSON document of ``steps.json`` (schema in the module docstring)."""
    return _clean(
        {
            "format": GEOMETRY_FORMAT,
            "version": GEOMETRY_VERSION,
            "kind": geometry.kind.value,
            "summary": {
                "n_steps": len(geometry.steps),
                "n_obstacles": len(geometry.obstacles),
                "mean_rise_m": geometry.mean_rise_m,
                "mean_tread_m": geometry.mean_tread_m,
            },
            "steps": [_fields(s) for s in geometry.steps],
            "obstacles": [_fields(o) for o in geometry.obstacles],
            "levels": [_fields(lv) for lv in geometry.levels],
            "risers": [_fields(r) for r in geometry.risers],
            "comparison": comparison,
        }
    )


def _arr(value: Any) -> NDArray[np.float64]:
    return np.asarray(value, dtype=np.float64)


def geometry_from_dict(doc: dict[str, Any]) -> TerrainGeometry:
    """Inverse of :func:`geometry_to_dict`.

    Raises:
        OutputError: not a vio_graph terrain-geometry document or a field is missing.
    """
    if doc.get("format") != GEOMETRY_FORMAT or doc.get("version") != GEOMETRY_VERSION:
        raise OutputError(f"not a {GEOMETRY_FORMAT} v{GEOMETRY_VERSION} document")
    try:
        steps = tuple(
            StepGeometry(
                **{
                    **s,
                    "nosing_xz_m": _arr(s["nosing_xz_m"]),
                    "nosing_std_xz_m": _arr(s["nosing_std_xz_m"]),
                }
            )
            for s in doc["steps"]
        )
        obstacles = tuple(
            ObstacleGeometry(
                **{
                    **o,
                    **{
                        k: _arr(o[k])
                        for k in (
                            "front_edge_xz_m",
                            "back_edge_xz_m",
                            "front_edge_std_xz_m",
                            "back_edge_std_xz_m",
                        )
                    },
                }
            )
            for o in doc["obstacles"]
        )
        levels = tuple(LevelSegment(**lv) for lv in doc["levels"])
        risers = tuple(RiserSegment(**r) for r in doc["risers"])
        kind = TerrainKind(doc["kind"])
    except (KeyError, TypeError, ValueError) as exc:
        raise OutputError(f"malformed terrain-geometry document: {exc}") from exc
    return TerrainGeometry(kind, steps, obstacles, levels, risers)


def write_geometry_json(
    path: Path, geometry: TerrainGeometry, comparison: dict[str, Any] | None = None
) -> Path:
    """Write ``steps.json`` (schema in the module docstring), optionally with the
    :func:`vio_graph.evaluation.map_accuracy.compare_to_truth` result."""
    doc = geometry_to_dict(geometry, comparison)
    atomic_write_text(Path(path), json.dumps(doc, indent=2, allow_nan=False) + "\n")
    return Path(path)


def read_geometry_json(path: Path) -> TerrainGeometry:
    """Read a ``steps.json`` written by :func:`write_geometry_json`.

    Raises:
        OutputError: missing file, invalid JSON or not a terrain-geometry document.
    """
    path = Path(path)
    try:
        doc = json.loads(path.read_text(encoding="utf-8"))
    except (OSError, json.JSONDecodeError) as exc:
        raise OutputError(f"{path}: cannot read terrain geometry JSON: {exc}") from exc
    try:
        return geometry_from_dict(doc)
    except OutputError as exc:
        raise OutputError(f"{path}: {exc}") from exc


# ---------------------------------------------------------------------------------------------
# CSV
def _num(value: float | None) -> str:
    return "" if value is None or not math.isfinite(float(value)) else repr(float(value))


def geometry_csv_rows(geometry: TerrainGeometry) -> list[dict[str, str]]:
    """Rows of ``steps.csv`` as strings keyed by :data:`CSV_COLUMNS`."""
    rows: list[dict[str, str]] = []
    for s in geometry.steps:
        rows.append(
            {
                "feature": "step",
                "index": str(s.index),
                "direction": s.direction,
                "height_m": _num(s.rise_m),
                "height_std_m": _num(s.rise_std_m),
                "depth_m": _num(s.tread_m),
                "depth_std_m": _num(s.tread_std_m),
                "edge_x_m": _num(s.nosing_xz_m[0]),
                "edge_z_m": _num(s.nosing_xz_m[1]),
                "edge_x_std_m": _num(s.nosing_std_xz_m[0]),
                "edge_z_std_m": _num(s.nosing_std_xz_m[1]),
                "back_edge_x_m": "",
                "back_edge_z_m": "",
                "back_edge_x_std_m": "",
                "back_edge_z_std_m": "",
                "lower_z_m": _num(s.lower_z_m),
                "upper_z_m": _num(s.upper_z_m),
                "riser_observed": "1" if s.riser_observed else "0",
            }
        )
    for i, o in enumerate(geometry.obstacles):
        rows.append(
            {
                "feature": "obstacle",
                "index": str(i),
                "direction": "",
                "height_m": _num(o.height_m),
                "height_std_m": _num(o.height_std_m),
                "depth_m": _num(o.depth_m),
                "depth_std_m": _num(o.depth_std_m),
                "edge_x_m": _num(o.front_edge_xz_m[0]),
                "edge_z_m": _num(o.front_edge_xz_m[1]),
                "edge_x_std_m": _num(o.front_edge_std_xz_m[0]),
                "edge_z_std_m": _num(o.front_edge_std_xz_m[1]),
                "back_edge_x_m": _num(o.back_edge_xz_m[0]),
                "back_edge_z_m": _num(o.back_edge_xz_m[1]),
                "back_edge_x_std_m": _num(o.back_edge_std_xz_m[0]),
                "back_edge_z_std_m": _num(o.back_edge_std_xz_m[1]),
                "lower_z_m": _num(o.ground_z_m),
                "upper_z_m": _num(o.top_z_m),
                "riser_observed": "",
            }
        )
    return rows


def write_geometry_csv(path: Path, geometry: TerrainGeometry) -> Path:
    """Write ``steps.csv`` (columns in the module docstring)."""
    buffer = io.StringIO()
    writer = csv.DictWriter(buffer, fieldnames=CSV_COLUMNS, lineterminator="\n")
    writer.writeheader()
    writer.writerows(geometry_csv_rows(geometry))
    atomic_write_text(Path(path), buffer.getvalue())
    return Path(path)


def read_geometry_csv(path: Path) -> tuple[tuple[StepGeometry, ...], tuple[ObstacleGeometry, ...]]:
    """Read the steps and obstacles of a ``steps.csv`` written by :func:`write_geometry_csv`.

    Raises:
        OutputError: missing file, wrong header or a malformed row (the message names the
            line).
    """
    path = Path(path)
    try:
        text = path.read_text(encoding="utf-8")
    except OSError as exc:
        raise OutputError(f"{path}: cannot read: {exc}") from exc
    reader = csv.DictReader(io.StringIO(text))
    if tuple(reader.fieldnames or ()) != CSV_COLUMNS:
        raise OutputError(f"{path}: header must be {','.join(CSV_COLUMNS)}")

    def f(row: dict[str, str], key: str) -> float | None:
        return float(row[key]) if row[key] != "" else None

    def xz(row: dict[str, str], kx: str, kz: str) -> NDArray[np.float64]:
        return np.array([float(row[kx]), float(row[kz])])

    steps: list[StepGeometry] = []
    obstacles: list[ObstacleGeometry] = []
    for line, row in enumerate(reader, start=2):
        try:
            if row["feature"] == "step":
                if row["direction"] not in ("up", "down"):
                    raise ValueError(f"direction {row['direction']!r}")
                steps.append(
                    StepGeometry(
                        index=int(row["index"]),
                        direction=row["direction"],  # type: ignore[arg-type]
                        rise_m=float(row["height_m"]),
                        rise_std_m=float(row["height_std_m"]),
                        tread_m=f(row, "depth_m"),
                        tread_std_m=f(row, "depth_std_m"),
                        nosing_xz_m=xz(row, "edge_x_m", "edge_z_m"),
                        nosing_std_xz_m=xz(row, "edge_x_std_m", "edge_z_std_m"),
                        lower_z_m=float(row["lower_z_m"]),
                        upper_z_m=float(row["upper_z_m"]),
                        riser_observed=row["riser_observed"] == "1",
                    )
                )
            elif row["feature"] == "obstacle":
                obstacles.append(
                    ObstacleGeometry(
                        height_m=float(row["height_m"]),
                        height_std_m=float(row["height_std_m"]),
                        depth_m=float(row["depth_m"]),
                        depth_std_m=float(row["depth_std_m"]),
                        front_edge_xz_m=xz(row, "edge_x_m", "edge_z_m"),
                        back_edge_xz_m=xz(row, "back_edge_x_m", "back_edge_z_m"),
                        front_edge_std_xz_m=xz(row, "edge_x_std_m", "edge_z_std_m"),
                        back_edge_std_xz_m=xz(row, "back_edge_x_std_m", "back_edge_z_std_m"),
                        ground_z_m=float(row["lower_z_m"]),
                        top_z_m=float(row["upper_z_m"]),
                    )
                )
            else:
                raise ValueError(f"feature {row['feature']!r}")
        except (TypeError, ValueError) as exc:
            raise OutputError(f"{path}: line {line}: {exc}") from exc
    return tuple(steps), tuple(obstacles)


# ---------------------------------------------------------------------------------------------
# plot
def _geometry_points(geometry: TerrainGeometry) -> NDArray[np.float64]:
    pts = [[lv.x_start_edge_m, lv.z_m] for lv in geometry.levels]
    pts += [[lv.x_end_edge_m, lv.z_m] for lv in geometry.levels]
    pts += [list(s.nosing_xz_m) for s in geometry.steps]
    pts += [list(e) for o in geometry.obstacles for e in (o.front_edge_xz_m, o.back_edge_xz_m)]
    return np.asarray(pts, dtype=np.float64).reshape(-1, 2)


def _step_table_rows(geometry: TerrainGeometry) -> list[list[str]]:
    rows = []
    for k, s in enumerate(geometry.steps, start=1):
        tread = "-" if s.tread_m is None else f"{1000 * s.tread_m:.1f}"
        rows.append(
            [
                str(k),
                s.direction,
                f"{1000 * s.rise_m:.1f}",
                tread,
                f"{s.nosing_xz_m[0]:.2f}, {s.nosing_xz_m[1]:.2f}",
            ]
        )
    for k, o in enumerate(geometry.obstacles, start=1):
        rows.append(
            [
                f"O{k}",
                "block",
                f"{1000 * o.height_m:.1f}",
                f"{1000 * o.depth_m:.1f}",
                f"{o.front_edge_xz_m[0]:.2f}, {o.front_edge_xz_m[1]:.2f}",
            ]
        )
    return rows


def step_table_text(rows: list[list[str]], headers: list[str], max_rows: int) -> str:
    """``rows`` (cells as strings) under ``headers`` as fixed-width text, columns right-aligned
    to their widest cell, a rule under the header; the first ``max_rows`` rows, then a line
    saying how many more are in ``steps.csv``."""
    shown = rows[:max_rows]
    widths = [max(len(c) for c in col) for col in zip(headers, *shown, strict=False)]

    def line(cells: list[str]) -> str:
        return "  ".join(c.rjust(w) for c, w in zip(cells, widths, strict=True))

    lines = [line(headers), "-" * len(line(headers)), *(line(r) for r in shown)]
    if len(rows) > len(shown):
        lines.append(f"... {len(rows) - len(shown)} more in steps.csv")
    return "\n".join(lines)


def write_map_png(
    path: Path,
    points_xz_m: ArrayLike,
    geometry: TerrainGeometry | None = None,
    terrain_info: TerrainInfo | None = None,
    camera_xz_m: ArrayLike | None = None,
    title: str | None = None,
) -> Path:
    """Write :func:`map_figure` as a PNG (atomically)."""
    from vio_graph.viz.plots import save_png

    fig = map_figure(points_xz_m, geometry, terrain_info, camera_xz_m, title)
    with atomic_path(Path(path), suffix=".png") as tmp:
        save_png(fig, tmp)
    return Path(path)


#: step rows in the table beside the map: as many as fit above the legend
MAP_TABLE_ROWS = 14


def map_figure(
    points_xz_m: ArrayLike,
    geometry: TerrainGeometry | None = None,
    terrain_info: TerrainInfo | None = None,
    camera_xz_m: ArrayLike | None = None,
    title: str | None = None,
) -> Any:
    """The map (x forward, z up, equal axes, zoomed to the mapped part) with the detected
    levels, risers, nosings and obstacle edges (error bars = 3 sigma), optionally the true
    profile and edges of ``terrain_info`` and the keyframe camera positions (K, 2); nosings
    are numbered and their rise / tread listed in a table beside the plot. A matplotlib
    Figure (Agg canvas)."""
    from vio_graph.viz.decimate import plot_indices
    from vio_graph.viz.plots import new_figure, zoom_limits

    pts = np.asarray(points_xz_m, dtype=np.float64).reshape(-1, 2)
    cams = (
        np.asarray(camera_xz_m, dtype=np.float64).reshape(-1, 2)
        if camera_xz_m is not None
        else np.zeros((0, 2))
    )
    rows = _step_table_rows(geometry) if geometry is not None else []
    fig = new_figure(figsize=(12, 5.0), dpi=110)
    if rows:
        gs = fig.add_gridspec(
            1, 2, width_ratios=[2.6, 1], left=0.06, right=0.98, wspace=0.08, bottom=0.1, top=0.92
        )
        ax = fig.add_subplot(gs[0, 0])
        side = fig.add_subplot(gs[0, 1])
        side.axis("off")
    else:
        ax = fig.add_subplot(1, 1, 1)
        side = None
    ax.scatter(pts[:, 0], pts[:, 1], s=1.5, c="0.55", label=f"map ({pts.shape[0]} points)")
    if terrain_info is not None and terrain_info.profile_xz_m:
        true_profile = np.asarray(terrain_info.profile_xz_m)
        ax.plot(true_profile[:, 0], true_profile[:, 1], "k--", lw=0.8, label="true profile")
    if terrain_info is not None and terrain_info.edges_xz_m:
        true_edges = np.asarray(terrain_info.edges_xz_m)
        ax.plot(true_edges[:, 0], true_edges[:, 1], "kx", ms=8, label="true edges")
    if cams.size:
        shown_cams = cams[plot_indices(cams)]
        ax.plot(
            shown_cams[:, 0],
            shown_cams[:, 1],
            "-",
            color="tab:purple",
            lw=1,
            label="camera (keyframes)",
        )
    if geometry is not None:
        _draw_geometry(ax, geometry)
        ax.set_title(title or f"terrain map: {geometry.kind.value}", y=1.0)
    elif title:
        ax.set_title(title, y=1.0)
    # zoom to what was mapped (and the camera that mapped it), not the whole true profile
    limits = zoom_limits(
        [pts, cams] + ([_geometry_points(geometry)] if geometry else []), margin_m=0.15
    )
    if limits is not None:
        ax.set_xlim(*limits[0])
        ax.set_ylim(*limits[1])
        ax.set_aspect("equal", adjustable="box")
    else:
        ax.set_aspect("equal", adjustable="datalim")
    ax.set_xlabel("x forward [m]")
    ax.set_ylabel("z up [m]")
    ax.grid(True, lw=0.3)
    if side is None:
        ax.legend(loc="best", fontsize=7)
        return fig
    handles, labels = ax.get_legend_handles_labels()
    side.legend(handles, labels, loc="lower left", fontsize=8, frameon=False)
    # the table as one monospaced text block (one text artist instead of one per cell)
    headers = (
        ["#", "kind", "rise/height mm", "tread/depth mm", "edge x, z m"]
        if geometry is not None and geometry.obstacles
        else ["#", "kind", "rise mm", "tread mm", "nosing x, z m"]
    )
    side.text(
        0.0,
        1.0,
        step_table_text(rows, headers, MAP_TABLE_ROWS),
        family="monospace",
        fontsize=8,
        va="top",
        linespacing=1.35,
        transform=side.transAxes,
    )
    return fig


#: steps numbered on the map figure; a longer trial (a 10-minute one maps ~800 steps) numbers
#: every k-th step only, so the labels stay legible and the figure cheap
MAX_NUMBERED_STEPS = 60


def _segments(x: list[tuple[float, float]], z: list[tuple[float, float]]) -> tuple[Any, Any]:
    """Many two-point segments as one NaN-separated polyline (one artist, not one each)."""
    nan = np.full((len(x), 1), np.nan)
    xs = np.hstack([np.asarray(x, float).reshape(-1, 2), nan]).ravel()
    zs = np.hstack([np.asarray(z, float).reshape(-1, 2), nan]).ravel()
    return xs, zs


def _draw_geometry(ax: Any, geometry: TerrainGeometry) -> None:
    if geometry.levels:
        xs, zs = _segments(
            [(lv.x_start_edge_m, lv.x_end_edge_m) for lv in geometry.levels],
            [(lv.z_m, lv.z_m) for lv in geometry.levels],
        )
        ax.plot(xs, zs, "-", color="tab:blue", lw=2.5, alpha=0.8, label="levels (treads, floor)")
    if geometry.risers:
        xs, zs = _segments(
            [(r.x_m, r.x_m) for r in geometry.risers],
            [(r.z_bottom_m, r.z_top_m) for r in geometry.risers],
        )
        ax.plot(xs, zs, "-", color="tab:green", lw=2.5, alpha=0.8, label="risers")
    if geometry.steps:  # one errorbar artist for every nosing
        nosing = np.array([s.nosing_xz_m for s in geometry.steps], dtype=float)
        sigma3 = 3 * np.array([s.nosing_std_xz_m for s in geometry.steps], dtype=float)
        ax.errorbar(
            nosing[:, 0],
            nosing[:, 1],
            xerr=sigma3[:, 0],
            yerr=sigma3[:, 1],
            fmt="o",
            color="tab:red",
            ms=5,
            label="nosings (3 sigma), numbered as in the table",
        )
    every = -(-len(geometry.steps) // MAX_NUMBERED_STEPS) if geometry.steps else 1
    for i, s in enumerate(geometry.steps):
        if i % every:
            continue
        # the step number only, up and to the left of the nosing (above the riser, clear of
        # the tread): short labels do not collide, the numbers are in the table
        ax.annotate(
            str(i + 1),
            s.nosing_xz_m,
            textcoords="offset points",
            xytext=(-9, 6),
            ha="right",
            fontsize=8,
            color="tab:red",
            fontweight="bold",
        )
    for i, o in enumerate(geometry.obstacles):
        edges = np.array([o.front_edge_xz_m, o.back_edge_xz_m])
        ax.plot(
            edges[:, 0],
            edges[:, 1],
            "s",
            color="tab:orange",
            ms=6,
            label="obstacle edges" if i == 0 else None,
        )
        ax.annotate(
            f"O{i + 1}",
            edges.mean(axis=0),
            textcoords="offset points",
            xytext=(0, 10),
            ha="center",
            fontsize=8,
            color="tab:orange",
            fontweight="bold",
        )


# ---------------------------------------------------------------------------------------------
# everything at once
def export_map(
    out_dir: Path,
    points_xz_m: ArrayLike,
    geometry: TerrainGeometry,
    terrain_info: TerrainInfo | None = None,
    comparison: dict[str, Any] | None = None,
    camera_xz_m: ArrayLike | None = None,
    formats: Sequence[str] = ("ply", "pcd", "json", "csv", "png"),
) -> dict[str, Path]:
    """Write ``map.ply``, ``map.pcd``, ``steps.json``, ``steps.csv`` and ``map.png`` (those
    listed in ``formats``) into ``out_dir``; return {format: path}."""
    out_dir = Path(out_dir)
    unknown = set(formats) - {"ply", "pcd", "json", "csv", "png"}
    if unknown:
        raise OutputError(f"unknown export formats: {sorted(unknown)}")
    written: dict[str, Path] = {}
    if "ply" in formats:
        written["ply"] = write_point_cloud(out_dir / "map.ply", points_xz_m)
    if "pcd" in formats:
        written["pcd"] = write_point_cloud(out_dir / "map.pcd", points_xz_m)
    if "json" in formats:
        written["json"] = write_geometry_json(out_dir / "steps.json", geometry, comparison)
    if "csv" in formats:
        written["csv"] = write_geometry_csv(out_dir / "steps.csv", geometry)
    if "png" in formats:
        written["png"] = write_map_png(
            out_dir / "map.png", points_xz_m, geometry, terrain_info, camera_xz_m
        )
    return written
