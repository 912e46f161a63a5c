"""Latency summaries (ms) for metrics.json."""

from __future__ import annotations

import numpy as np
from numpy.typing import ArrayLike


def stats_ms(values: ArrayLike) -> dict[str, float]:
    """Median, p95, mean and count of durations in ms (NaN statistics and n = 0 if empty)."""
    v = np.asarray(values, dtype=float)
    if v.size == 0:
        return {"median": float("nan"), "p95": float("nan"), "mean": float("nan"), "n": 0}
    return {
        "median": float(np.median(v)),
        "p95": float(np.percentile(v, 95)),
        "mean": float(np.mean(v)),
        "n": int(v.size),
    }
