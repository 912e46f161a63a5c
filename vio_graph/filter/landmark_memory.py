"""Last sight of the filter's landmarks of one kind, and when to forget them.

Shared by the corner landmarks (filter/corner_landmarks.py) and the height landmarks
(filter/level_landmarks.py): a landmark unseen for ``memory_s`` leaves the filter state, and
so do the oldest beyond ``max_landmarks``, never one observed in the current frame.
"""

from __future__ import annotations

from collections.abc import Set

from vio_graph.filter.eskf import SagittalEskf
from vio_graph.types import LandmarkKey


class LandmarkMemory:
    """The last sight (s) of every landmark of kind ``kind`` in a filter state."""

    kind: str = ""

    def __init__(self, memory_s: float, max_landmarks: int) -> None:
        self.memory_s = memory_s
        self.max_landmarks = max_landmarks
        self._seen: dict[LandmarkKey, float] = {}  # landmark key -> last seen, s

    @classmethod
    def keys(cls, eskf: SagittalEskf) -> list[LandmarkKey]:
        """The landmarks of this kind in the filter state, in its order."""
        return eskf.landmark_keys_of_kind(cls.kind)

    def saw(self, key: LandmarkKey, t_s: float) -> None:
        """The landmark ``key`` was observed at ``t_s`` (s)."""
        self._seen[key] = t_s

    def _forget(self, t_s: float, current: Set[LandmarkKey], eskf: SagittalEskf) -> None:
        """Marginalise from ``eskf`` the landmarks of this kind unseen for ``memory_s`` at
        ``t_s`` (s), and the oldest beyond ``max_landmarks`` (never one in ``current``); the
        last sights kept are those of the landmarks still in the state or in ``current``."""
        alive = []
        for k in self.keys(eskf):
            if k not in current and t_s - self._seen.get(k, t_s) > self.memory_s:
                eskf.drop_landmark(k)
            else:
                alive.append(k)
        # the state's order is kept by the drops, so ``alive`` is keys(eskf) now
        if len(alive) > self.max_landmarks:  # (else nothing to drop: no sort needed)
            kept_kind = sorted(alive, key=lambda k: self._seen.get(k, t_s))
            for k in kept_kind[: len(kept_kind) - self.max_landmarks]:
                if k not in current:
                    eskf.drop_landmark(k)
        self._seen = {k: v for k, v in self._seen.items() if k in current or eskf.has_landmark(k)}
