"""The safety monitor's own prediction errors, measured online (no look-ahead, no I/O).

Each swing-template prediction (the heel and toe at the horizon's instants t + h_i) is kept
until its last instant has passed; when a frame arrives, every kept instant between the
previous frame and this one is compared with the estimated foot there (linear between the
two frames). The error of an instant is the larger of the heel's and the toe's position
errors (m). Errors are summed per horizon step and per swing (the swing in which the
prediction was made); the rms per step is over the current swing and the last ``swings``
ones. The monitor uses it to test only the steps its prediction has been accurate at
(docs/method.md section 8, "Near-trip warning")."""

from __future__ import annotations

import math

import numpy as np
from numpy.typing import NDArray


class PredictionErrors:
    """Online rms of the foot prediction's error per horizon step (m).

    ``h_s``: the horizon's instants (H + 1,), s after the prediction (h_s[0] = 0, the
    current pose); ``swings``: completed swings kept besides the current one."""

    def __init__(self, h_s: NDArray[np.float64], swings: int) -> None:
        self._h = np.asarray(h_s, dtype=float)
        self._slots = swings + 1
        n = len(self._h)
        self._sums = np.zeros((self._slots, n))  # squared errors per swing slot and step
        self._counts = np.zeros((self._slots, n))
        self._swing = -1  # id of the current swing (slot: id % slots); -1 before the first
        # kept predictions: time (s), poses (H + 1, 4: heel x, z, toe x, z), swing id
        self._t: list[float] = []
        self._poses: list[NDArray[np.float64]] = []
        self._ids: list[int] = []
        self._last: tuple[float, NDArray[np.float64]] | None = None  # previous frame

    def start_swing(self) -> None:
        """A new swing: its slot replaces the oldest swing's."""
        self._swing += 1
        k = self._swing % self._slots
        self._sums[k] = 0.0
        self._counts[k] = 0.0

    def predict(self, t_s: float, poses: NDArray[np.float64]) -> None:
        """Keep the prediction made at ``t_s``: heel and toe (H + 1, 4) at t_s + h_s."""
        if self._swing < 0:
            return
        self._t.append(t_s)
        self._poses.append(np.asarray(poses, dtype=float))
        self._ids.append(self._swing)

    def observe(self, t_s: float, foot: NDArray[np.float64]) -> None:
        """The estimated heel and toe (4,) at ``t_s``: the kept instants since the previous
        frame are scored; predictions whose last instant has passed are dropped."""
        foot = np.asarray(foot, dtype=float)
        if not np.all(np.isfinite(foot)):
            return  # (the next finite frame interpolates from the last finite one)
        last, self._last = self._last, (t_s, foot)
        if last is None or not t_s > last[0] or not self._t:
            return
        t0, f0 = last
        keep = []
        for j, (tp, poses, sid) in enumerate(zip(self._t, self._poses, self._ids, strict=True)):
            inst = tp + self._h
            sel = (inst > t0) & (inst <= t_s)
            if sel.any() and sid > self._swing - self._slots:
                w = (inst[sel] - t0) / (t_s - t0)
                actual = f0[None] + w[:, None] * (foot - f0)[None]
                d = poses[sel] - actual
                e2 = np.maximum(d[:, 0] ** 2 + d[:, 1] ** 2, d[:, 2] ** 2 + d[:, 3] ** 2)
                k = sid % self._slots
                self._sums[k, sel] += e2
                self._counts[k, sel] += 1.0
            if inst[-1] > t_s:
                keep.append(j)
        if len(keep) < len(self._t):
            self._t = [self._t[j] for j in keep]
            self._poses = [self._poses[j] for j in keep]
            self._ids = [self._ids[j] for j in keep]

    def rms(self) -> NDArray[np.float64]:
        """rms error per horizon step (H + 1,), m; NaN at a step not yet measured."""
        n = self._counts.sum(axis=0)
        with np.errstate(invalid="ignore", divide="ignore"):
            return np.where(n > 0, np.sqrt(self._sums.sum(axis=0) / np.maximum(n, 1.0)), np.nan)

    def trusted_steps(self, max_error_m: float) -> int:
        """The last horizon step m such that every step up to m has a measured rms error of
        at most ``max_error_m`` or none measured yet (0: only the current pose)."""
        m = 0
        for i, e in enumerate(self.rms().tolist()):
            if i == 0:
                continue
            if math.isfinite(e) and e > max_error_m:
                break
            m = i
        return m
