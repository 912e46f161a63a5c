"""A per-frame column kept as one float64 buffer grown by doubling.

The replay keeps a few numbers per frame for the outputs (frame times, pitch angles, the
filter's position covariance, every estimator's camera path). As Python lists of floats or of
small arrays they cost ~30 bytes per float or ~130 bytes per (2,) array, object headers
included; here 8 bytes per number, in a handful of large blocks instead of one object per
frame. It reads like the list it replaces: ``len``, truthiness, ``store[k]`` (a Python float
for scalar rows, a copy of the row otherwise), slices and ``np.asarray(store)`` (a copy of the
filled rows, shape (N, *row_shape)).
"""

from __future__ import annotations

from collections.abc import Iterator
from typing import Any

import numpy as np
from numpy.typing import ArrayLike, NDArray

_MIN_CAPACITY = 64


class GrowableArray:
    """Rows of a fixed shape (``()`` for numbers) appended one at a time."""

    def __init__(self, row_shape: tuple[int, ...] = ()) -> None:
        self.row_shape = tuple(row_shape)
        self._buf: NDArray[np.float64] = np.empty((0, *self.row_shape))
        self._n = 0

    def append(self, row: ArrayLike) -> None:
        if self._n == self._buf.shape[0]:
            grown = np.empty((max(_MIN_CAPACITY, 2 * self._n), *self.row_shape))
            grown[: self._n] = self._buf[: self._n]
            self._buf = grown
        self._buf[self._n] = row  # a row of another shape raises here, as it should
        self._n += 1

    def __len__(self) -> int:
        return self._n

    def __getitem__(self, k: Any) -> Any:
        if isinstance(k, slice):
            return self._buf[: self._n][k].copy()
        k = int(k)
        if not -self._n <= k < self._n:
            raise IndexError(f"row {k} of {self._n}")
        row = self._buf[k % self._n]
        return float(row) if not self.row_shape else row.copy()

    def __iter__(self) -> Iterator[Any]:
        return (self[k] for k in range(self._n))

    def __array__(self, dtype: Any = None, copy: bool | None = None) -> NDArray[Any]:
        out = self._buf[: self._n].copy()
        return out if dtype is None else out.astype(dtype, copy=False)

    def view(self) -> NDArray[np.float64]:
        """The filled rows without a copy (valid until the next append)."""
        return self._buf[: self._n]
