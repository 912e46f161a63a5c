"""Visual front end (paper Section II.A): sagittal slice, smoothing, terrain class, RANSAC
corner features, IMU-seeded and gated frame-to-frame ICP."""

from vio_graph.frontend.config import FrontendConfig
from vio_graph.frontend.corners import CornerFeature, extract_corner
from vio_graph.frontend.frontend import FrontendResult, VisualFrontend
from vio_graph.frontend.icp import IcpResult, icp_translation_2d
from vio_graph.frontend.projection import (
    depth_to_points_cam,
    sagittal_slice,
    sagittal_slice_from_depth,
)
from vio_graph.frontend.smoothing import smooth_profile
from vio_graph.frontend.terrain import ConfusionTable, classify_terrain, confusion_table
from vio_graph.frontend.tracker import CornerTracker, TrackerOutput

__all__ = [
    "ConfusionTable",
    "CornerFeature",
    "CornerTracker",
    "FrontendConfig",
    "FrontendResult",
    "IcpResult",
    "TrackerOutput",
    "VisualFrontend",
    "classify_terrain",
    "confusion_table",
    "depth_to_points_cam",
    "extract_corner",
    "icp_translation_2d",
    "sagittal_slice",
    "sagittal_slice_from_depth",
    "smooth_profile",
]
