"""The map of one run: keyframe profiles placed at the refined camera positions, merged into
a 2D terrain map, the step / obstacle geometry fitted to it and, with the true terrain in the
metadata, compared with it. Pure (the run writes the files with mapping/export.py)."""

from __future__ import annotations

from collections.abc import Mapping, Sequence
from dataclasses import dataclass, field
from typing import Any

import numpy as np
from numpy.typing import NDArray

from vio_graph.evaluation.map_accuracy import compare_to_truth
from vio_graph.mapping.config import MappingConfig
from vio_graph.mapping.local_map import TerrainMap2D
from vio_graph.mapping.steps import TerrainGeometry, estimate_terrain_geometry
from vio_graph.recording.metadata import TerrainInfo
from vio_graph.types import TerrainKind


@dataclass
class RunMap:
    """``points_xz_m`` (N, 2) merged map points, m; ``geometry`` (None below 10 points);
    ``comparison`` with the true terrain (None without it); ``metrics`` for metrics.json."""

    points_xz_m: NDArray[np.float64]
    geometry: TerrainGeometry | None = None
    comparison: dict[str, Any] | None = None
    metrics: dict[str, Any] = field(default_factory=dict)


def build_run_map(
    frame_times_s: Sequence[float] | NDArray[np.float64],
    profiles: Mapping[int, NDArray[np.float64]],
    camera_xz_m: NDArray[np.float64],
    config: MappingConfig,
    terrain: TerrainInfo,
) -> RunMap:
    """Map from the keyframe ``profiles`` (frame index -> slice (M, 2), camera-relative, m)
    placed at ``camera_xz_m`` (N, 2) of the frames at ``frame_times_s`` (s)."""
    tmap = TerrainMap2D(config.map)
    for k, prof in profiles.items():
        if prof.shape[0]:
            tmap.add_keyframe(frame_times_s[k], camera_xz_m[k], prof, copy=False)
    pts = tmap.points_xz_m
    metrics: dict[str, Any] = {"keyframes": len(profiles), "points": int(pts.shape[0])}
    if pts.shape[0] < 10:
        return RunMap(pts, metrics=metrics)
    kind = TerrainKind(terrain.kind) if terrain.kind else None
    geometry = estimate_terrain_geometry(pts, tmap.point_counts, config.steps, kind)
    comparison = None
    if terrain.profile_xz_m:
        comparison = compare_to_truth(geometry, terrain)
        metrics.update(_flatten_comparison(comparison))
    metrics["detected_kind"] = (
        geometry.kind.value if hasattr(geometry.kind, "value") else str(geometry.kind)
    )
    return RunMap(pts, geometry, comparison, metrics)


def _flatten_comparison(cmp: dict[str, Any]) -> dict[str, Any]:
    """Headline map errors (mean absolute, mm) plus the full comparison."""
    out: dict[str, Any] = {
        "rise_error_mm": cmp.get("rise_mae_mm"),
        "tread_error_mm": cmp.get("tread_mae_mm"),
        "nosing_error_mm": cmp.get("nosing_mae_mm"),
        "n_steps_estimated": cmp.get("n_steps_estimated"),
        "n_steps_matched": cmp.get("n_steps_matched"),
    }
    obstacles = cmp.get("obstacles") or []
    if obstacles:
        out["obstacle_height_error_mm"] = obstacles[0].get("height_error_mm")
        out["obstacle_depth_error_mm"] = obstacles[0].get("depth_error_mm")
    out["comparison"] = cmp
    return out
