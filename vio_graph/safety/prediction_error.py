"""The safety monitor's own prediction errors in the current swing, measured online (no
look-ahead, no I/O).

Each swing-template prediction of the swing (the heel and toe at the horizon's instants
t + h_i) is kept until its last instant has passed; when a frame arrives, every kept instant
between the previous frame and this one is compared with the estimated foot there (linear
between the two frames). The error of an instant is the larger of the heel's and the toe's
position errors (m); the rms per horizon step is over the swing's predictions so far. The
monitor uses it to test only the steps its prediction has been accurate at in this swing
(docs/method.md section 8, "The warning checks its own prediction")."""

from __future__ import annotations

import math
from types import ModuleType

import numpy as np
from numpy.typing import NDArray


class PredictionErrors:
    """Online rms of the foot prediction's error per horizon step in the current swing (m).

    ``h_s``: the horizon's instants (H + 1,), s after the prediction (h_s[0] = 0, the
    current pose); ``capacity``: predictions kept at first (grows when needed); ``kernels``:
    the compiled module (vio_graph/safety/compiled.py, ``observe_errors``: :meth:`observe`'s
    scoring in one call, the same floats) or None (numpy)."""

    def __init__(
        self, h_s: NDArray[np.float64], capacity: int = 16, kernels: ModuleType | None = None
    ) -> None:
        self._kernels = kernels
        self._h = np.asarray(h_s, dtype=float)
        n = len(self._h)
        self._sums = np.zeros(n)  # squared errors per step, this swing
        self._counts = np.zeros(n)
        self._in_swing = False
        # kept predictions, one row each (free rows: time NaN): the time they were made (s)
        # and the poses (H + 1, 4: heel x, z, toe x, z)
        self._t = np.full(capacity, np.nan)
        self._poses = np.zeros((capacity, n, 4))
        self._kept = 0  # rows in use
        self._last: tuple[float, tuple[float, ...]] | None = None  # previous finite frame
        self._trusted: dict[float, int] = {}  # trusted_steps by bound, until the next error

    def start_swing(self) -> None:
        """A new swing: the last one's predictions and errors are dropped."""
        self._in_swing = True
        self._sums[:] = 0.0
        self._counts[:] = 0.0
        self._t[:] = np.nan
        self._kept = 0
        self._trusted.clear()

    def predict(self, t_s: float, poses: NDArray[np.float64]) -> None:
        """Keep the prediction made at ``t_s``: heel and toe (H + 1, 4) at t_s + h_s."""
        if not self._in_swing:
            return
        if self._kept == len(self._t):  # (more frames per horizon than rows: twice the rows)
            c = len(self._t)
            self._t = np.concatenate([self._t, np.full(c, np.nan)])
            self._poses = np.concatenate([self._poses, np.zeros_like(self._poses)])
        j = int(np.flatnonzero(np.isnan(self._t))[0])
        self._t[j] = t_s
        self._poses[j] = poses
        self._kept += 1

    def observe(self, t_s: float, foot: tuple[float, float, float, float]) -> None:
        """The estimated heel and toe (x, z, x, z) at ``t_s``: the kept instants since the
        previous frame are scored; predictions whose last instant has passed are dropped."""
        if not math.isfinite(sum(foot)):
            return  # (the next finite frame interpolates from the last finite one)
        last, self._last = self._last, (t_s, foot)
        if last is None or not t_s > last[0] or self._kept == 0:
            return
        if self._kernels is not None:
            scored, dropped = self._kernels.observe_errors(
                self._t, self._h, self._poses, last[0], np.array(last[1]), t_s,
                np.array(foot), self._sums, self._counts,
            )  # fmt: skip
            if scored:
                self._trusted.clear()
            self._kept -= int(dropped)
            return
        t0, f0 = last[0], np.array(last[1])
        f1 = np.array(foot)
        inst = self._t[:, None] + self._h[None]  # (rows, H + 1); NaN rows compare False
        rows, steps = np.nonzero((inst > t0) & (inst <= t_s))
        if rows.size:
            w = (inst[rows, steps] - t0) / (t_s - t0)
            d = self._poses[rows, steps] - (f0[None] + w[:, None] * (f1 - f0)[None])
            e2 = np.maximum(d[:, 0] ** 2 + d[:, 1] ** 2, d[:, 2] ** 2 + d[:, 3] ** 2)
            n = len(self._h)
            self._sums += np.bincount(steps, e2, minlength=n)
            self._counts += np.bincount(steps, minlength=n)
            self._trusted.clear()
        done = inst[:, -1] <= t_s  # (NaN rows: False)
        if done.any():
            self._t[done] = np.nan
            self._kept -= int(done.sum())

    def rms(self) -> NDArray[np.float64]:
        """rms error per horizon step (H + 1,), m; NaN at a step not yet measured."""
        with np.errstate(invalid="ignore", divide="ignore"):
            return np.sqrt(self._sums / self._counts)  # (0 / 0: NaN)

    def measured(self) -> NDArray[np.bool_]:
        """Per horizon step (H + 1,): whether an error has been measured in this swing."""
        return self._counts > 0

    def trusted_steps(self, max_error_m: float) -> int:
        """The last horizon step m such that every step up to m has a measured rms error of
        at most ``max_error_m`` or none measured yet (0: only the current pose)."""
        m = self._trusted.get(max_error_m)
        if m is None:
            if self._kernels is not None:  # (the compiled path: on Python floats)
                m = _trusted_steps(self._sums.tolist(), self._counts.tolist(), max_error_m)
            else:
                bad = self.rms() > max_error_m  # (NaN: not measured, not bad)
                bad[0] = False  # the current pose is the estimate itself
                m = int(np.argmax(bad)) - 1 if bad.any() else len(self._h) - 1
            self._trusted[max_error_m] = m
        return m


def _trusted_steps(sums: list[float], counts: list[float], max_error_m: float) -> int:
    """:meth:`PredictionErrors.trusted_steps` on the sums and counts as Python floats, without
    numpy's per-call cost on 11 values: the same IEEE division and square root per step
    (0 / 0 is NaN, not bad; a positive sum over no count is +inf, bad), the same answer
    (tests/test_safety_prediction_error.py)."""
    for i in range(1, len(sums)):
        s, c = sums[i], counts[i]
        if c == 0.0:
            bad = s > 0.0 and math.inf > max_error_m
        else:
            q = s / c
            bad = q >= 0.0 and math.sqrt(q) > max_error_m  # (NaN and negative: NaN, not bad)
        if bad:
            return i - 1
    return len(sums) - 1
