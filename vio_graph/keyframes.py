"""Keyframe selection (paper Section II.D).

The paper takes frames whose displacement lies between 0.01 m and 0.05 m as keyframes. We read
that as: a frame becomes a keyframe once the camera has moved at least ``min_displacement_m``
since the last keyframe (so a standing subject does not flood the map and the smoother); a frame
whose displacement since the last keyframe already exceeds ``max_displacement_m`` is still taken
(skipping it would only widen the gap) but counted as ``over_max``; and a keyframe is forced
after ``max_interval_s`` so the smoother always has nodes to bridge blind periods.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from pydantic import BaseModel, ConfigDict, Field


class KeyframeConfig(BaseModel):
    model_config = ConfigDict(extra="forbid", frozen=True)

    min_displacement_m: float = Field(default=0.01, ge=0, description="paper: 0.01 m")
    max_displacement_m: float = Field(default=0.05, gt=0, description="paper: 0.05 m")
    max_interval_s: float = Field(default=0.25, gt=0, description="force a keyframe after this")


@dataclass
class KeyframeSelector:
    config: KeyframeConfig
    last_position_xz_m: np.ndarray | None = None
    last_timestamp_s: float | None = None
    count: int = 0
    over_max: int = 0

    def is_keyframe(self, timestamp_s: float, camera_xz_m: np.ndarray) -> bool:
        """Decide for one frame (call once per frame, in time order)."""
        if self.last_position_xz_m is None:
            take = True
        else:
            moved = float(np.linalg.norm(np.asarray(camera_xz_m) - self.last_position_xz_m))
            waited = timestamp_s - float(self.last_timestamp_s)
            take = moved >= self.config.min_displacement_m or waited >= self.config.max_interval_s
            if take and moved > self.config.max_displacement_m:
                self.over_max += 1
        if take:
            self.last_position_xz_m = np.array(camera_xz_m, dtype=float)
            self.last_timestamp_s = float(timestamp_s)
            self.count += 1
        return take
