"""What a run shows in rerun: the static scene, each frame, the final paths and the map.

:class:`RunView` turns the run's data into calls on a visualizer
(:class:`vio_graph.viz.rerun_logger.Visualizer`, or the NullVisualizer that logs nothing);
the entity layout is documented in vio_graph/viz/rerun_logger.py.
"""

from __future__ import annotations

from collections.abc import Mapping

import numpy as np
from numpy.typing import NDArray

from vio_graph.config import OutputConfig
from vio_graph.estimator import RigGeometry
from vio_graph.frontend.projection import depth_to_points_cam
from vio_graph.protocol import FrameRecord
from vio_graph.recording.reader import Recording
from vio_graph.recording.streams import GroundTruth
from vio_graph.types import DepthFrame, EstimateStatus
from vio_graph.viz.rerun_logger import NullVisualizer


def cloud_world(
    frame: DepthFrame,
    K: NDArray[np.float64],
    R_world_cam: NDArray[np.float64],
    cam_xyz: NDArray[np.float64],
    stride: int,
) -> NDArray[np.float64]:
    """The frame's valid points in the world frame, every ``stride``-th pixel (for viewing):
    the front end's back-projection on the subsampled image with its scaled intrinsics."""
    K_sub = np.array(K, dtype=float)
    K_sub[:2] /= stride
    pts = depth_to_points_cam(
        frame.depth_m[::stride, ::stride], frame.confidence[::stride, ::stride], K_sub
    )
    return pts @ R_world_cam.T + cam_xyz


def true_leg(gt: GroundTruth, t_s: float | NDArray[np.float64]) -> NDArray[np.float64]:
    """The true knee, ankle, heel, toe and ankle again (the leg drawn as one strip), m: (5, 2)
    at one time, (N, 5, 2) at N times (s)."""
    knee, ankle, heel, toe = (
        gt.trajectories[b].xz_at(t_s) for b in ("knee", "ankle", "heel", "toe")
    )
    return np.stack([knee, ankle, heel, toe, ankle], axis=-2)


class RunView:
    """The rerun view of one run (``viz``: a Visualizer or NullVisualizer)."""

    def __init__(
        self,
        viz,
        rig: RigGeometry,
        groundtruth: GroundTruth | None,
        output: OutputConfig,
        depth_unit_m: float | None = None,
    ) -> None:
        """``depth_unit_m``: the recording's depth unit (m, ``camera.depth_unit_m``), with
        which the depth images go to rerun as the recorded integers (see
        :meth:`vio_graph.viz.rerun_logger.Visualizer.log_camera`); None: float32 metres."""
        self.viz = viz
        self.depth_unit_m = depth_unit_m
        self.rig = rig
        self.gt = groundtruth
        self.output = output
        #: False for the NullVisualizer itself (``--no-rerun``): nothing is logged, so the
        #: per-frame view (clouds, true leg, stacks; ~0.3 ms a frame) is not computed at all
        self.active = type(viz) is not NullVisualizer
        #: (frame stamps (N,) s, true leg (N, 5, 2) m) from :meth:`scene`, or None
        self._true_legs: tuple[NDArray[np.float64], NDArray[np.float64]] | None = None

    def scene(self, rec: Recording) -> None:
        """The static scene: the true terrain (mesh and profile) and true paths; and the true
        leg at every frame stamp, interpolated at once for :meth:`frame`."""
        if not self.active:
            return
        if self.gt is not None:
            t_s = np.asarray(rec.frame_timestamps_s, dtype=float)
            self._true_legs = (t_s, true_leg(self.gt, t_s))
        prof = np.asarray(rec.metadata.terrain.profile_xz_m, dtype=float)
        if prof.size == 0:
            return
        from vio_graph.viz.scene import extrude_profile

        verts, tris = extrude_profile(prof, width_m=1.0)
        self.viz.log_terrain(verts, tris, prof)
        if self.gt is not None:
            for body in ("camera", "toe", "knee"):
                self.viz.log_path(f"gt/{body}", self.gt.trajectories[body].xz_m)

    def frame(self, i: int, frame: DepthFrame, record: FrameRecord) -> None:
        """One depth frame: camera pose and depth image, cloud, slice, corner features, ICP
        matches, the leg (estimated and true), the clearance line (foot to nearest terrain
        point) and the status / toe-error / clearance time series."""
        if not self.active:
            return
        viz, est, res = self.viz, record.estimate, record.frontend
        viz.set_time(est.timestamp_s)
        cam_xyz = np.array([est.camera_xz_m[0], 0.0, est.camera_xz_m[1]])
        R_world_cam = record.R_world_imu @ self.rig.R_imu_cam
        viz.log_camera(
            cam_xyz,
            R_world_cam,
            self.rig.K,
            frame.depth_m.shape[1],
            frame.depth_m.shape[0],
            frame.depth_m,
            self.depth_unit_m,
        )
        if i % self.output.cloud_every_n_frames == 0:
            viz.log_cloud(
                cloud_world(frame, self.rig.K, R_world_cam, cam_xyz, self.output.cloud_pixel_stride)
            )
        viz.log_sagittal("slice", est.camera_xz_m + res.profile_xz_m, 0.002, (250, 200, 0))
        if res.corner is not None:
            viz.log_sagittal(
                "features", est.camera_xz_m + res.corner.feature_points_xz_m, 0.005, (255, 40, 40)
            )
        if res.icp is not None and res.icp.target_points_xz_m.size:
            viz.log_segments(
                "icp",
                est.camera_xz_m + res.icp.matched_source_xz_m,
                est.camera_xz_m + res.icp.target_points_xz_m,
            )
        viz.log_leg(
            "est",
            np.vstack([est.knee_xz_m, est.ankle_xz_m, est.heel_xz_m, est.toe_xz_m, est.ankle_xz_m]),
        )
        viz.log_scalar("status/fused", float(est.status is EstimateStatus.FUSED))
        sf = est.safety
        if sf is not None and np.all(np.isfinite(sf.toe_line_xz_m)):
            # the clearance: a line from the closest foot point to the closest terrain point
            viz.log_segments(
                "clearance",
                sf.toe_line_xz_m[:1],
                sf.toe_line_xz_m[1:],
                (255, 0, 160) if sf.near_trip_warning else (0, 200, 120),
            )
            viz.log_scalar("clearance_cm/estimate", 100 * sf.clearance_m)
            viz.log_scalar("clearance_cm/sigma", 100 * sf.clearance_sigma_m)
        if sf is not None and np.isfinite(sf.predicted_min_clearance_m):
            viz.log_scalar("clearance_cm/predicted_min", 100 * sf.predicted_min_clearance_m)
        if self.gt is not None:
            leg = self._true_leg(i, est.timestamp_s)
            viz.log_leg("gt", leg)
            toe_err = est.toe_xz_m - leg[3]
            viz.log_scalar("error_cm/toe_x", 100 * toe_err[0])
            viz.log_scalar("error_cm/toe_z", 100 * toe_err[1])

    def _true_leg(self, i: int, t_s: float) -> NDArray[np.float64]:
        """The true knee, ankle, heel, toe, ankle (5, 2), m, at ``t_s``: row ``i`` of the table
        :meth:`scene` made if frame ``i``'s stamp is ``t_s`` (the same floats: ``np.interp``
        works element by element), else interpolated here (~45 us a frame)."""
        table = self._true_legs
        if table is not None and i < table[0].shape[0] and table[0][i] == t_s:
            return table[1][i]
        assert self.gt is not None
        return true_leg(self.gt, t_s)

    def paths(self, paths: Mapping[str, Mapping[str, NDArray[np.float64]]]) -> None:
        """Every mode's final camera and toe paths (the filter's under ``est/``)."""
        for mode, bodies in paths.items():
            name = "est" if mode == "filter" else mode
            self.viz.log_path(f"{name}/camera", bodies["camera"])
            self.viz.log_path(f"{name}/toe", bodies["toe"])

    def map_points(self, points_xz_m: NDArray[np.float64]) -> None:
        self.viz.log_sagittal("map", points_xz_m, 0.003, (90, 90, 255))
