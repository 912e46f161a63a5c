"""Corner landmarks of the filter: which landmark a corner track is, and when to forget one.

The front end gives every corner a track id that it keeps while it can follow the corner from
frame to frame. A track that ends and a new one that starts on the same physical corner (the
shank looks away and back) would make two landmarks of one corner; a new track whose corner
lands within ``reidentify_radius_m`` of a remembered corner landmark (and clearly nearer to it
than to any other) is therefore re-identified as that landmark. A corner landmark unseen for
``memory_s`` leaves the filter state, and so do the oldest beyond ``max_landmarks``.
"""

from __future__ import annotations

import numpy as np
from numpy.typing import NDArray

from vio_graph.filter.eskf import SagittalEskf
from vio_graph.filter.landmark_memory import LandmarkMemory
from vio_graph.types import CornerObservation, LandmarkKey


class CornerLandmarks(LandmarkMemory):
    """Track id -> landmark key, and the last sight (s) of every corner landmark."""

    kind = "corner"

    def __init__(
        self, reidentify_radius_m: float | None, memory_s: float, max_landmarks: int
    ) -> None:
        super().__init__(memory_s, max_landmarks)
        self.reidentify_radius_m = reidentify_radius_m
        self._alias: dict[int, LandmarkKey] = {}  # track id -> landmark key

    def key(
        self, obs: CornerObservation, camera_xz_m: NDArray[np.float64], eskf: SagittalEskf
    ) -> LandmarkKey:
        """Landmark key of a corner observation seen from ``camera_xz_m`` (world, m): its
        track's, or, for a new track, a remembered corner landmark of ``eskf`` it matches."""
        tid = obs.track_id
        if tid in self._alias:
            return self._alias[tid]
        key = LandmarkKey("corner", tid)
        radius = self.reidentify_radius_m
        if radius is not None:
            seen = camera_xz_m + np.asarray(obs.corner_rel_xz_m, float)
            known = self.keys(eskf)
            if known:
                d = np.array([np.linalg.norm(eskf.landmark_xz(k) - seen) for k in known])
                order = np.argsort(d)
                if d[order[0]] < radius and (d.size == 1 or d[order[1]] > 2 * d[order[0]]):
                    key = known[int(order[0])]
        self._alias[tid] = key
        return key

    def forget(self, t_s: float, current: LandmarkKey | None, eskf: SagittalEskf) -> None:
        """Marginalise from ``eskf`` the corner landmarks unseen for ``memory_s`` at ``t_s``
        (s), and the oldest beyond ``max_landmarks`` (never ``current``)."""
        self._forget(t_s, set() if current is None else {current}, eskf)
        # ended tracks whose landmark is gone are never looked up again (ids only increase)
        self._alias = {
            tid: k for tid, k in self._alias.items() if k == current or eskf.has_landmark(k)
        }
