"""2D terrain map from keyframe profiles, step / obstacle geometry, and their export.

``local_map`` and ``steps`` are pure; ``export`` is the only module here that writes files.
"""

from vio_graph.mapping.config import MapConfig, MappingConfig, StepConfig
from vio_graph.mapping.local_map import KeyframeProfile, MapCells, TerrainMap2D, merge_points
from vio_graph.mapping.steps import (
    LevelSegment,
    ObstacleGeometry,
    RiserSegment,
    StepGeometry,
    TerrainGeometry,
    estimate_terrain_geometry,
    find_levels,
)

__all__ = [
    "KeyframeProfile",
    "LevelSegment",
    "MapCells",
    "MapConfig",
    "MappingConfig",
    "ObstacleGeometry",
    "RiserSegment",
    "StepConfig",
    "StepGeometry",
    "TerrainGeometry",
    "TerrainMap2D",
    "estimate_terrain_geometry",
    "find_levels",
    "merge_points",
]
