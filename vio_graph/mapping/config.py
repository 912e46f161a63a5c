"""Configuration of the 2D terrain map and the step-geometry extraction (pydantic v2).

Defaults live in code; every field carries its unit in its name and its description.
"""

from __future__ import annotations

from pydantic import BaseModel, ConfigDict, Field, model_validator


class _Frozen(BaseModel):
    model_config = ConfigDict(extra="forbid", frozen=True)


class MapConfig(_Frozen):
    """How keyframe profiles are merged into the 2D (x-z) terrain map."""

    cell_size_m: float = Field(
        default=0.005, gt=0, description="edge length of the square x-z grid cells, metres"
    )
    min_keyframes_per_cell: int = Field(
        default=2,
        ge=1,
        description="cells seen by fewer distinct keyframes are dropped as outliers (count)",
    )
    min_points_per_cell: int = Field(
        default=1, ge=1, description="cells holding fewer raw points are dropped (count)"
    )
    max_keyframes: int | None = Field(
        default=None,
        ge=1,
        description="keep only the newest keyframes (by timestamp); None keeps all (count)",
    )
    timestamp_match_tol_s: float = Field(
        default=1e-6,
        ge=0,
        description="two keyframe timestamps closer than this are the same keyframe, seconds",
    )


class StepConfig(_Frozen):
    """Segmentation of the map into horizontal levels (treads, floor, landing, obstacle top)
    and vertical faces (risers, obstacle sides), and the step geometry derived from them."""

    level_tolerance_m: float = Field(
        default=0.01,
        gt=0,
        description="half-height of the z window whose points belong to one horizontal level, m",
    )
    min_level_length_m: float = Field(
        default=0.04, gt=0, description="shortest x extent of a horizontal segment, metres"
    )
    min_level_cells: int = Field(
        default=6, ge=2, description="fewest map cells that make a horizontal segment (count)"
    )
    min_level_contrast: float = Field(
        default=2.0,
        ge=1.0,
        description="a level holds at least this many times the weight of the windows just "
        "above and below its z spread over its x range (ratio)",
    )
    max_gap_m: float = Field(
        default=0.03,
        gt=0,
        description="an x gap wider than this splits one level into two segments, metres",
    )
    min_rise_m: float = Field(
        default=0.03,
        gt=0,
        description="levels closer in height than this are merged, not a step, metres",
    )
    under_level_margin_m: float | None = Field(
        default=0.05,
        gt=0,
        description="map points beneath a level (at least min_rise_m + level_tolerance_m "
        "below it and more than this inside its x extent on both sides: the floor seen under "
        "open-riser treads, a wall under a landing) are not the walking surface; when any "
        "occur they are dropped and the levels found again, metres; None: keep every point",
    )
    under_junctions: bool = Field(
        default=True,
        description="with under_level_margin_m: also drop map points at least min_rise_m + "
        "level_tolerance_m below both of two abutting levels (the next starts within "
        "max_gap_m of the end of the other) within under_level_margin_m of their junction, "
        "the strips the beneath-a-level rule leaves out (the floor seen through the open "
        "riser between two treads)",
    )
    riser_margin_m: float = Field(
        default=0.015,
        ge=0,
        description="riser points within this height of either level are ignored (rounded "
        "corners), metres",
    )
    riser_x_window_m: float = Field(
        default=0.03,
        gt=0,
        description="riser points are searched within this x distance of the level ends, m",
    )
    min_riser_cells: int = Field(
        default=4, ge=2, description="fewest cells for a riser x fit to be used (count)"
    )
    column_width_m: float = Field(
        default=0.005,
        gt=0,
        description="x column width of the edge estimate; use the map's cell size (or a "
        "multiple), metres",
    )
    edge_blur_m: float = Field(
        default=0.015,
        gt=0,
        description="length at a level's end (from its outermost cell) that holds the "
        "noise-blurred edge in the 50 % edge estimate, metres",
    )
    edge_reference_m: float = Field(
        default=0.08,
        gt=0,
        description="length inside the level, before the blurred end, whose weight per "
        "metre is the 100 % reference of the 50 % edge estimate, metres",
    )
    max_obstacle_depth_m: float = Field(
        default=0.6,
        gt=0,
        description="a raised plateau with lower ground on both sides and at most this depth "
        "is an obstacle, metres",
    )
    max_levels: int | None = Field(
        default=None,
        ge=1,
        description="at most this many level searches (count); None: search until no z window "
        "holds min_level_cells cells. A cap must exceed the number of treads in the map: a "
        "cap of 40 silently dropped most treads of a 150-step trial, so that neighbouring "
        "detected levels were several steps apart",
    )

    @model_validator(mode="after")
    def _check(self) -> StepConfig:
        if self.min_rise_m <= self.level_tolerance_m:
            raise ValueError("min_rise_m must exceed level_tolerance_m")
        return self


class MappingConfig(_Frozen):
    """The mapping section: the map and the step extraction."""

    map: MapConfig = Field(default_factory=MapConfig, description="2D map accumulation")
    steps: StepConfig = Field(default_factory=StepConfig, description="step geometry")
