"""GTSAM keyframe smoother (fixed-lag and batch) over IMU, ICP displacements and corner tracks.

See :mod:`vio_graph.smoother.graph` for the graph (nodes, factors, noise, priors).
"""

from vio_graph.smoother.batch import BatchSmoother
from vio_graph.smoother.config import FactorFamilies, SmootherConfig
from vio_graph.smoother.interface import KeyframeEstimate
from vio_graph.smoother.sliding_window import SlidingWindowSmoother

__all__ = [
    "BatchSmoother",
    "FactorFamilies",
    "KeyframeEstimate",
    "SlidingWindowSmoother",
    "SmootherConfig",
]
