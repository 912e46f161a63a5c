"""GTSAM keyframe smoother (fixed-lag and batch) over IMU, ICP displacements and corner tracks.

See :mod:`vio_graph.smoother.graph` for the graph (nodes, factors, noise, priors).

The names below are loaded on first use (PEP 562), so importing the configuration
(``vio_graph.smoother.config``) does not import GTSAM: a filter-only run never pays for it.
"""

from __future__ import annotations

import importlib
from typing import TYPE_CHECKING, Any

if TYPE_CHECKING:
    from vio_graph.smoother.batch import BatchSmoother
    from vio_graph.smoother.config import FactorFamilies, SmootherConfig
    from vio_graph.smoother.interface import KeyframeEstimate
    from vio_graph.smoother.sliding_window import SlidingWindowSmoother

_LAZY = {
    "BatchSmoother": "vio_graph.smoother.batch",
    "FactorFamilies": "vio_graph.smoother.config",
    "KeyframeEstimate": "vio_graph.smoother.interface",
    "SlidingWindowSmoother": "vio_graph.smoother.sliding_window",
    "SmootherConfig": "vio_graph.smoother.config",
}

__all__ = [
    "BatchSmoother",
    "FactorFamilies",
    "KeyframeEstimate",
    "SlidingWindowSmoother",
    "SmootherConfig",
]


def __getattr__(name: str) -> Any:
    module = _LAZY.get(name)
    if module is None:
        raise AttributeError(f"module {__name__!r} has no attribute {name!r}")
    value = getattr(importlib.import_module(module), name)
    globals()[name] = value
    return value
