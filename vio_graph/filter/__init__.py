"""SP-ESKF (paper eq. 5-8) and the baselines sharing its interface."""

from vio_graph.filter.baselines import IcpOdometry, ImuDeadReckoning
from vio_graph.filter.config import FilterConfig
from vio_graph.filter.eskf import FilterState, SagittalEskf, sagittal_rotation

__all__ = [
    "FilterConfig",
    "FilterState",
    "IcpOdometry",
    "ImuDeadReckoning",
    "SagittalEskf",
    "sagittal_rotation",
]
