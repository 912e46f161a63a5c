"""Rerun recording (``.rrd``) of a trial, and a null logger with the same interface.

The pipeline logs through :class:`Visualizer`; with visualisation off it gets a
:class:`NullVisualizer`, so there are no ``if visualize:`` branches in the loop. Sagittal (x, z)
data is shown in 3D at y = 0. Entity layout:

- ``world/terrain``            terrain mesh (static) and true profile
- ``world/camera``             estimated camera pose (a time series)
- ``world/camera/image``       pinhole (static); ``world/camera/image/depth`` the depth image,
                               which the viewer back-projects through the pinhole (the
                               recorded uint16 counts with meter = 1 / depth unit, see
                               :meth:`Visualizer.log_camera`)
- ``world/cloud``              depth cloud in the world frame (subsampled)
- ``world/slice``              sagittal slice (ground frame, placed at the estimate)
- ``world/features``           corner feature points; ``world/icp`` ICP matches
- ``world/est/<body>``, ``world/gt/<body>``   estimated and true paths (camera, knee, toe, ...)
- ``world/leg/est``, ``world/leg/gt``         leg links knee-ankle-heel-toe
- ``world/map``                 2D map points and step edges
- ``plots/...``                 scalar time series (errors, status)

Nothing is logged one frame at a time. The time series (the camera pose and the ``plots/``
scalars) are collected during the run and sent with ``rr.send_columns`` when the recording is
closed, one call per entity. The per-frame entities (depth image, cloud, slice, features, ICP
matches, clearance line, leg links, map) are collected as rows (time, instances, radius,
colour) and sent the same way every :data:`FLUSH_ROWS` rows and at close, so memory stays
bounded on long trials and an entity costs one archetype construction per batch instead of
one per frame. The rows are the ones ``rr.log`` would have written (same components, one
radius and one colour per row), without rerun's ``log_time`` wall-clock timeline.

What is logged how often (vio_graph/viz/run_view.py): depth image, slice, features, ICP
matches, leg links and scalars every frame; the 3D cloud every
``output.cloud_every_n_frames``-th frame (default 3) at every ``output.cloud_pixel_stride``-th
pixel (default 3): the viewer back-projects the full depth image through the pinhole anyway,
the cloud is the world-frame overlay.
"""

from __future__ import annotations

from collections import defaultdict
from pathlib import Path

import numpy as np
from numpy.typing import NDArray

_COLORS = {
    "est": (230, 120, 20),
    "gt": (40, 160, 60),
    "filter": (230, 120, 20),
    "smoother": (40, 110, 220),
    "batch": (150, 60, 200),
    "imu_only": (150, 150, 150),
    "icp_only": (200, 60, 60),
}


def _xz_to_xyz(xz: NDArray[np.float64]) -> NDArray[np.float64]:
    """Sagittal points (N, 2) or one (2,), metres, as (N, 3) at y = 0."""
    xz = np.asarray(xz, dtype=float).reshape(-1, 2)
    xyz = np.zeros((xz.shape[0], 3))
    xyz[:, 0::2] = xz
    return xyz


def _depth_image(
    depth_m: NDArray[np.floating], unit_m: float | None
) -> tuple[NDArray[np.float32] | NDArray[np.uint16], float]:
    """(image, meter) to send for a depth image in metres: uint16 counts of ``unit_m`` with
    meter = 1 / unit_m if ``depth_m`` is exactly such counts as the recording reader makes
    them (float32 count x float32 unit), else a float32 copy with meter = 1. Always a new
    array: the caller's frame buffer may be reused before the rows are sent."""
    d = np.asarray(depth_m)
    if unit_m is not None and unit_m > 0 and d.dtype == np.float32 and d.size:
        counts = np.rint(d * np.float32(1.0 / unit_m))
        if 0.0 <= counts.min() and counts.max() <= np.iinfo(np.uint16).max:
            u16 = counts.astype(np.uint16)
            if np.array_equal(u16.astype(np.float32) * np.float32(unit_m), d):
                return u16, 1.0 / unit_m
    return np.array(d, dtype=np.float32), 1.0


class NullVisualizer:
    """Does nothing; same interface as :class:`Visualizer`."""

    def set_time(self, timestamp_s: float) -> None: ...
    def log_terrain(self, vertices_m, triangles, profile_xz_m) -> None: ...
    def log_camera(
        self, position_m, R_world_cam, K, width_px, height_px, depth_m=None, depth_unit_m=None
    ) -> None: ...
    def log_cloud(self, points_world_m) -> None: ...
    def log_sagittal(self, name, points_xz_m, radius_m: float = 0.004, color=None) -> None: ...
    def log_segments(self, name, starts_xz_m, ends_xz_m, color=None) -> None: ...
    def log_leg(self, name, points_xz_m) -> None: ...
    def log_path(self, name, xz_m, static: bool = True) -> None: ...
    def log_scalar(self, name, value: float) -> None: ...
    def close(self) -> None: ...
    def abort(self) -> None: ...


#: rows of a per-frame entity collected before they are sent (5 s at 30 frames/s; about 11.6 MB
#: of uint16 depth images at 224 x 172 pixels, 2.9 MB at data/sample's 112 x 86)
FLUSH_ROWS = 150


class _Rows:
    """The rows of one per-frame entity not yet sent: per row the time stamp (s), the
    instances (points (n, 3), strips (k, m, 3), metres, or a depth image (h, w)), one radius
    (m; for a depth image its ``meter``, units per metre) and one RGB colour."""

    def __init__(self, kind: str) -> None:
        self.kind = kind  # "points" | "strips" | "depth"
        self.times_s: list[float] = []
        self.data: list[NDArray[np.floating]] = []
        self.radii: list[float] = []
        self.colors: list[tuple[int, int, int]] = []

    def add(self, t_s: float, data, radius_m: float = 0.0, color=(0, 0, 0)) -> int:
        self.times_s.append(t_s)
        self.data.append(data)
        self.radii.append(radius_m)
        self.colors.append(color)
        return len(self.times_s)


class Visualizer(NullVisualizer):
    """Writes a rerun ``.rrd`` file (no viewer needed)."""

    def __init__(self, rrd_path: Path, application_id: str = "vio_graph") -> None:
        import rerun as rr

        self._rr = rr
        self.path = Path(rrd_path)
        self.path.parent.mkdir(parents=True, exist_ok=True)
        self._rec = rr.RecordingStream(application_id)
        # written under a temporary name and renamed by close(): never a half-written .rrd
        self._tmp_path = self.path.with_name(f".{self.path.name}.partial")
        self._rec.save(str(self._tmp_path))
        self._rec.log("world", rr.ViewCoordinates.RIGHT_HAND_Z_UP, static=True)
        self._t_s = 0.0
        self._pinhole_logged = False
        # time series sent as columns by close(): entity -> (times s, values)
        self._scalars: dict[str, tuple[list[float], list[float]]] = defaultdict(lambda: ([], []))
        self._camera: tuple[list[float], list[NDArray[np.float64]], list[NDArray[np.float64]]] = (
            [],
            [],
            [],
        )
        # per-frame entities, sent as columns every FLUSH_ROWS rows and by close()
        self._rows: dict[str, _Rows] = {}

    def set_time(self, timestamp_s: float) -> None:
        self._t_s = float(timestamp_s)

    def _add(self, entity: str, kind: str, data, radius_m: float = 0.0, color=(0, 0, 0)) -> None:
        rows = self._rows.get(entity)
        if rows is None:
            rows = self._rows[entity] = _Rows(kind)
        if rows.add(self._t_s, data, radius_m, tuple(color)) >= FLUSH_ROWS:
            self._flush(entity)

    def log_terrain(self, vertices_m, triangles, profile_xz_m) -> None:
        rr = self._rr
        if vertices_m is not None and len(vertices_m):
            self._rec.log(
                "world/terrain/mesh",
                rr.Mesh3D(
                    vertex_positions=np.asarray(vertices_m, dtype=np.float32),
                    triangle_indices=np.asarray(triangles, dtype=np.uint32),
                    albedo_factor=[0.75, 0.75, 0.78, 0.6],
                ),
                static=True,
            )
        if profile_xz_m is not None and len(profile_xz_m):
            self._rec.log(
                "world/terrain/profile",
                rr.LineStrips3D([_xz_to_xyz(profile_xz_m)], colors=[(60, 60, 60)]),
                static=True,
            )

    def log_camera(
        self, position_m, R_world_cam, K, width_px, height_px, depth_m=None, depth_unit_m=None
    ) -> None:
        """The camera pose, the pinhole (once) and the depth image ``depth_m`` (metres, 0 =
        invalid). ``depth_unit_m``: the recording's depth unit (m) if its depth is stored as
        integers of it (uint16 millimetres from the ToF camera): the image is then sent as
        those integers with ``meter`` = 1 / unit, which the viewer reads as the same metres,
        at half the bytes of float32 to encode and store. Sent as float32 metres if the
        image is not exactly such integers (checked: converted back with the reader's
        formula, float32 integers times float32 unit, it must give ``depth_m`` bit for bit)."""
        rr = self._rr
        times, translations, rotations = self._camera
        times.append(self._t_s)
        translations.append(np.asarray(position_m, dtype=float))
        rotations.append(np.asarray(R_world_cam, dtype=float))
        if not self._pinhole_logged:  # one sensor: the same intrinsics for every frame
            self._rec.log(
                "world/camera/image",
                rr.Pinhole(
                    image_from_camera=np.asarray(K, dtype=float),
                    width=width_px,
                    height=height_px,
                    image_plane_distance=0.1,
                ),
                static=True,
            )
            self._pinhole_logged = True
        if depth_m is not None:
            depth, meter = _depth_image(depth_m, depth_unit_m)
            self._add("world/camera/image/depth", "depth", depth, meter)

    def log_cloud(self, points_world_m) -> None:
        pts = np.asarray(points_world_m, dtype=np.float32).reshape(-1, 3)
        self._add("world/cloud", "points", pts, 0.002, (120, 140, 200))

    def log_sagittal(self, name, points_xz_m, radius_m: float = 0.004, color=None) -> None:
        self._add(
            f"world/{name}", "points", _xz_to_xyz(points_xz_m), radius_m, color or (250, 200, 0)
        )

    def log_segments(self, name, starts_xz_m, ends_xz_m, color=None) -> None:
        strips = np.stack([_xz_to_xyz(starts_xz_m), _xz_to_xyz(ends_xz_m)], axis=1)
        self._add(f"world/{name}", "strips", strips, 0.001, color or (255, 0, 255))

    def log_leg(self, name, points_xz_m) -> None:
        color = _COLORS["gt"] if name.endswith("gt") else _COLORS["est"]
        self._add(f"world/leg/{name}", "strips", _xz_to_xyz(points_xz_m)[None], 0.006, color)

    def log_path(self, name, xz_m, static: bool = True) -> None:
        kind = name.split("/")[0]
        if not static:
            self._rec.set_time("time", duration=self._t_s)
        self._rec.log(
            f"world/{name}",
            self._rr.LineStrips3D(
                [_xz_to_xyz(xz_m)], colors=[_COLORS.get(kind, (0, 0, 0))], radii=0.0015
            ),
            static=static,
        )

    def log_scalar(self, name, value: float) -> None:
        times, values = self._scalars[f"plots/{name}"]
        times.append(self._t_s)
        values.append(float(value))

    def _time_column(self, times_s: list[float]):
        """A ``time`` column with the nanoseconds ``set_time`` gives the same seconds (rounded,
        where a float array would be truncated)."""
        ns = np.array([round(1e9 * t) for t in times_s], dtype=np.int64)
        return self._rr.TimeColumn("time", duration=ns.astype("timedelta64[ns]"))

    def _flush(self, entity: str) -> None:
        """Send the collected rows of one per-frame entity with one ``send_columns`` call:
        the instances partitioned by row, one radius and one colour per row."""
        rr, rows = self._rr, self._rows.pop(entity, None)
        if rows is None or not rows.times_s:
            return
        n = len(rows.times_s)
        if rows.kind == "depth":
            dtypes = {np.dtype(np.float32): rr.ChannelDatatype.F32}
            dtypes[np.dtype(np.uint16)] = rr.ChannelDatatype.U16
            fmt = [
                rr.components.ImageFormat(
                    width=d.shape[1], height=d.shape[0], channel_datatype=dtypes[d.dtype]
                )
                for d in rows.data
            ]
            columns = rr.DepthImage.columns(
                buffer=[d.reshape(-1).view(np.uint8) for d in rows.data],
                format=fmt,
                meter=np.asarray(rows.radii, dtype=np.float32),
            )
        else:
            archetype = rr.Points3D if rows.kind == "points" else rr.LineStrips3D
            lengths = [len(d) for d in rows.data]
            if rows.kind == "points":
                instances = archetype.columns(
                    positions=np.concatenate(rows.data).astype(np.float32).reshape(-1, 3)
                )
            elif len({d.shape[1] for d in rows.data}) == 1:  # equal-length strips: one array
                instances = archetype.columns(
                    strips=np.concatenate(rows.data)
                    .astype(np.float32)
                    .reshape(-1, *rows.data[0].shape[1:])
                )
            else:
                instances = archetype.columns(strips=[s for d in rows.data for s in d])
            columns = [
                *instances.partition(lengths),
                *archetype.columns(
                    radii=np.asarray(rows.radii, dtype=np.float32),
                    colors=np.asarray(rows.colors, dtype=np.uint8).reshape(n, 3),
                ),
            ]
        rr.send_columns(
            entity,
            indexes=[self._time_column(rows.times_s)],
            columns=columns,
            recording=self._rec,
        )

    def _send_time_series(self) -> None:
        """The collected time series, one ``send_columns`` call per entity."""
        rr = self._rr
        for entity in list(self._rows):
            self._flush(entity)
        times, translations, rotations = self._camera
        if times:
            rr.send_columns(
                "world/camera",
                indexes=[self._time_column(times)],
                columns=rr.Transform3D.columns(
                    translation=np.asarray(translations), mat3x3=np.asarray(rotations)
                ),
                recording=self._rec,
            )
        for entity, (t, v) in self._scalars.items():
            rr.send_columns(
                entity,
                indexes=[self._time_column(t)],
                columns=rr.Scalars.columns(scalars=np.asarray(v)),
                recording=self._rec,
            )

    def close(self) -> None:
        import os

        self._send_time_series()
        self._rec.flush()
        self._rec.disconnect()
        os.replace(self._tmp_path, self.path)

    def abort(self) -> None:
        """Stop recording and delete the unfinished file (an interrupted or failed run)."""
        try:
            self._rec.disconnect()
        finally:
            self._tmp_path.unlink(missing_ok=True)
