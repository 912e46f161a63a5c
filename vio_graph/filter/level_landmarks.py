"""Height landmarks of the filter: which remembered level surface a measured one is, and when
to forget one.

The level aiding finds the near-horizontal lines of every slice (frontend/level.py): treads,
landings, the floor, obstacle tops. Each is a static surface at one height, so its height
relative to the camera is a z-only landmark observation (SagittalEskf.update_height_landmark).
Surfaces carry no track id: a measured line whose height (filter camera z + observed height)
lies within ``reidentify_m`` of a remembered height landmark, and clearly nearer to it than to
any landmark of another height, is that landmark; otherwise it is a new one. Two different
surfaces at the same height are the same landmark, which is right for a z-only landmark. A
height landmark unseen for ``memory_s`` leaves the filter state, and so do the oldest beyond
``max_landmarks``.

With ``one_per_surface`` (FilterConfig.level_one_landmark_per_surface) no new landmark is made
within ``reidentify_m`` of a remembered one or of one made from the same slice: such a line is
that surface again (a floor the line fit split into near and far pieces, whose heights differ
by their own few-millimetre errors) or ambiguous, and is skipped. Without it the pieces become
landmarks a few millimetres apart, all "the same surface" to the association, and the camera
height can step from one to the next when the displacements push it past their midpoint
(docs/generalisation.md, joint-space swing).
"""

from __future__ import annotations

from vio_graph.filter.eskf import SagittalEskf
from vio_graph.filter.landmark_memory import LandmarkMemory
from vio_graph.types import LandmarkKey


class LevelLandmarks(LandmarkMemory):
    """Association of measured level surfaces to height landmarks, and their last sight (s)."""

    kind = "level"

    def __init__(
        self,
        reidentify_m: float,
        memory_s: float,
        max_landmarks: int,
        one_per_surface: bool = False,
    ) -> None:
        super().__init__(memory_s, max_landmarks)
        self.reidentify_m = reidentify_m
        self.one_per_surface = one_per_surface
        self._next_id = 0

    def key(
        self,
        height_m: float,
        eskf: SagittalEskf,
        taken: set[LandmarkKey],
        made: dict[LandmarkKey, float] | None = None,
    ) -> LandmarkKey | None:
        """Landmark key of a level surface at world height ``height_m`` (m): the nearest
        height landmark of ``eskf`` if it is within ``reidentify_m`` and no landmark of another
        surface (more than ``reidentify_m`` from it) is within twice that distance; else a new
        key. None if that nearest landmark is in ``taken`` (already matched in this frame:
        one surface the line fit split in two, observed once). ``made`` holds the heights (m)
        of the keys this slice already made (first sights, not yet in ``eskf``); with
        ``one_per_surface`` a height within ``reidentify_m`` of one of them or of a remembered
        landmark gives None instead of a new key, and a new key is added to ``made``."""
        known = self.keys(eskf)
        if known:
            heights = {k: eskf.landmark_z(k) for k in known}
            best = min(known, key=lambda k: abs(heights[k] - height_m))
            d0 = abs(heights[best] - height_m)
            if d0 < self.reidentify_m:
                rivals = [
                    abs(h - height_m)
                    for k, h in heights.items()
                    if abs(h - heights[best]) > self.reidentify_m
                ]
                if all(d > 2 * d0 for d in rivals):
                    return None if best in taken else best
                if self.one_per_surface:
                    return None  # near a remembered surface but ambiguous: no duplicate
        if self.one_per_surface and made is not None:
            if any(abs(h - height_m) < self.reidentify_m for h in made.values()):
                return None  # the same surface as a line of this slice (a split fit)
        self._next_id += 1
        key = LandmarkKey("level", self._next_id)
        if made is not None:
            made[key] = height_m
        return key

    def forget(self, t_s: float, current: set[LandmarkKey], eskf: SagittalEskf) -> None:
        """Marginalise from ``eskf`` the height landmarks unseen for ``memory_s`` at ``t_s``
        (s), and the oldest beyond ``max_landmarks`` (never one in ``current``)."""
        self._forget(t_s, current, eskf)
