"""The 2D (sagittal x-z) terrain map built from keyframe profiles (paper Sec. II.D).

The paper adds "the 2D point clouds of the key frames ... to the local map". Each keyframe
brings its smoothed sagittal profile ``profile_xz_m`` (N, 2) *relative to the camera centre*
in world axes (the output of eq. 1-2 plus smoothing) and the keyframe's camera position
``camera_xz_m`` (2,) in the world x-z plane. World points are

    points_world_xz_m = camera_xz_m + profile_xz_m.

The map keeps the raw relative profiles and the latest pose of every keyframe, so that the
smoother can refine poses after the fact (:meth:`TerrainMap2D.update_poses`) and the merged
map is rebuilt from the new poses. Merging is a square grid in x-z (default 5 mm cells): each
occupied cell becomes one map point at the mean of its raw points, with the raw point count
as its weight. Cells seen by fewer than ``min_keyframes_per_cell`` distinct keyframes are
dropped: a spurious point of a single frame never reaches the map.

Pure module: no file I/O.
"""

from __future__ import annotations

from collections.abc import Iterable, Iterator, Mapping, Sequence
from dataclasses import dataclass

import numpy as np
from numpy.typing import ArrayLike, NDArray

from vio_graph.errors import MappingError
from vio_graph.growable import GrowableArray
from vio_graph.mapping.config import MapConfig


@dataclass(frozen=True)
class KeyframeProfile:
    """One keyframe as the map stores it.

    ``camera_xz_m``: (2,) camera position in the world x-z plane, metres.
    ``profile_xz_m``: (N, 2) profile points minus the camera position, world axes, metres.
    """

    timestamp_s: float
    camera_xz_m: NDArray[np.float64]
    profile_xz_m: NDArray[np.float64]

    def world_points_xz_m(self) -> NDArray[np.float64]:
        """(N, 2) profile placed in the world: camera_xz_m + profile_xz_m."""
        return self.camera_xz_m[None, :] + self.profile_xz_m


@dataclass(frozen=True)
class MapCells:
    """The merged map: one row per kept grid cell, sorted by cell (x, then z).

    ``points_xz_m``: (M, 2) mean of the raw points in the cell, world frame, metres.
    ``point_counts``: (M,) raw points merged into the cell.
    ``keyframe_counts``: (M,) distinct keyframes that put a point in the cell.
    ``cell_size_m``: grid cell edge length, metres.
    """

    points_xz_m: NDArray[np.float64]
    point_counts: NDArray[np.int64]
    keyframe_counts: NDArray[np.int64]
    cell_size_m: float

    def __len__(self) -> int:
        return int(self.points_xz_m.shape[0])


def _as_xz(value: ArrayLike, name: str) -> NDArray[np.float64]:
    arr = np.asarray(value, dtype=np.float64)
    if arr.shape != (2,) or not np.all(np.isfinite(arr)):
        raise MappingError(f"{name} must be a finite (2,) array, got shape {arr.shape}")
    return arr.copy()


def _as_profile(value: ArrayLike, copy: bool = True) -> NDArray[np.float64]:
    arr = np.asarray(value, dtype=np.float64)
    if arr.size == 0:
        return np.zeros((0, 2))
    if arr.ndim != 2 or arr.shape[1] != 2:
        raise MappingError(f"profile_xz_m must have shape (N, 2), got {arr.shape}")
    finite = np.all(np.isfinite(arr), axis=1)
    if not copy and finite.all():
        return arr
    return arr[finite]  # boolean indexing copies


def merge_points(
    points_xz_m: NDArray[np.float64],
    keyframe_index: NDArray[np.int64],
    config: MapConfig,
) -> MapCells:
    """Grid-merge world points (pure function).

    Args:
        points_xz_m: (P, 2) world points, metres.
        keyframe_index: (P,) integer id of the keyframe each point comes from.
        config: cell size and the per-cell support thresholds.

    Returns:
        The kept cells (mean position, raw point count, distinct keyframe count).
    """
    points_xz_m = np.asarray(points_xz_m, dtype=np.float64).reshape(-1, 2)
    keyframe_index = np.asarray(keyframe_index, dtype=np.int64).reshape(-1)
    if points_xz_m.shape[0] != keyframe_index.shape[0]:
        raise MappingError("points_xz_m and keyframe_index differ in length")
    if points_xz_m.shape[0] == 0:
        return MapCells(
            np.zeros((0, 2)), np.zeros(0, np.int64), np.zeros(0, np.int64), config.cell_size_m
        )
    # 1. integer cell of every point, folded into one int64 key ordered by (x cell, z cell)
    cell_ij = np.floor(points_xz_m / config.cell_size_m).astype(np.int64)
    cell_ij -= cell_ij.min(axis=0)
    n_z = int(cell_ij[:, 1].max()) + 1
    key = cell_ij[:, 0] * n_z + cell_ij[:, 1]
    cell_keys, cell_of_point = np.unique(key, return_inverse=True)
    n_cells = cell_keys.shape[0]
    # 2. per-cell sums and counts
    point_counts = np.bincount(cell_of_point, minlength=n_cells)
    sum_x = np.bincount(cell_of_point, weights=points_xz_m[:, 0], minlength=n_cells)
    sum_z = np.bincount(cell_of_point, weights=points_xz_m[:, 1], minlength=n_cells)
    # 3. distinct keyframes per cell: unique (cell, keyframe) pairs
    kf_dense = np.unique(keyframe_index, return_inverse=True)[1]
    n_kf = int(kf_dense.max()) + 1
    pairs = np.unique(cell_of_point.astype(np.int64) * n_kf + kf_dense)
    keyframe_counts = np.bincount(pairs // n_kf, minlength=n_cells)
    # 4. drop weakly supported cells (outliers)
    keep = (keyframe_counts >= config.min_keyframes_per_cell) & (
        point_counts >= config.min_points_per_cell
    )
    means = np.stack([sum_x[keep], sum_z[keep]], axis=1) / point_counts[keep, None]
    return MapCells(
        points_xz_m=means,
        point_counts=point_counts[keep].astype(np.int64),
        keyframe_counts=keyframe_counts[keep].astype(np.int64),
        cell_size_m=config.cell_size_m,
    )


#: points of consecutive keyframes handled as one batch by merge_keyframes (about 16 MiB of
#: working arrays; a 10-minute trial's ~3.8 million points in ~15 batches)
_KEY_BATCH = 1 << 18


def _sorted_distinct(values: NDArray[np.int64]) -> NDArray[np.int64]:
    """``np.unique(values)`` (sorted distinct integers) by a sort: numpy 2's hash-based
    ``np.unique`` took ~0.1 s per 4e5 keys here, the sort ~0.02 s. A stable sort (the same
    sorted integers): merge_keyframes passes the sorted keys so far followed by a batch's,
    and points of consecutive keyframes, which come in long ascending runs that numpy's
    stable sort merges instead of sorting afresh (the sorts of a 10-minute trial's map
    0.54 -> 0.12 s)."""
    v = np.sort(values, kind="stable")
    if v.size:
        v = v[np.concatenate(([True], v[1:] != v[:-1]))]
    return v


def _world_batches(
    keyframes: Sequence[KeyframeProfile], max_points: int | None = None
) -> Iterator[tuple[NDArray[np.float64], NDArray[np.int64], int]]:
    """The keyframes' world points (P, 2), consecutive non-empty keyframes at a time (about
    ``max_points`` points a batch; None: :data:`_KEY_BATCH`), with each point's keyframe
    number within the batch (P,) and the batch's keyframe count. The points are
    ``camera_xz_m + profile_xz_m`` of each keyframe in order
    (:meth:`KeyframeProfile.world_points_xz_m`, the same additions)."""
    limit = _KEY_BATCH if max_points is None else max_points
    group: list[KeyframeProfile] = []
    n = 0
    for kf in keyframes:
        if kf.profile_xz_m.shape[0]:
            group.append(kf)
            n += kf.profile_xz_m.shape[0]
        if group and (n >= limit or kf is keyframes[-1]):
            sizes = np.array([g.profile_xz_m.shape[0] for g in group], dtype=np.int64)
            cams = np.repeat(np.array([g.camera_xz_m for g in group]), sizes, axis=0)
            cams += np.concatenate([g.profile_xz_m for g in group])
            yield cams, np.repeat(np.arange(len(group), dtype=np.int64), sizes), len(group)
            group, n = [], 0


def merge_keyframes(keyframes: Sequence[KeyframeProfile], config: MapConfig) -> MapCells:
    """:func:`merge_points` of the keyframes' world points, bit for bit, in memory that grows
    with the map's cells, not with its raw points.

    ``merge_points`` on the concatenated points of a 10-minute trial (~3.8 million points,
    ~200,000 cells) holds the points, their cells, keys, the sort and the (cell, keyframe)
    pairs side by side, ~100 bytes a point; one key and one cell index per point across the
    passes still took ~47 bytes a point (~180 MiB), the batch run's peak. Here the points go
    through in batches of consecutive keyframes (:func:`_world_batches`, ~2.6e5 points): the
    sorted distinct cell keys are gathered batch by batch (a sort), a batch's points
    are then placed in their cells by ``np.searchsorted`` (the cell index ``np.unique``'s
    inverse gives), and the per-cell counts and sums are accumulated with ``np.add.at`` in
    the order of the points, i.e. the same additions in the same order as one
    ``np.bincount`` over all of them; the distinct keyframes per cell are counted from the
    distinct (cell, keyframe) pairs of each batch (a keyframe lies in one batch). So every
    output is the same. (Keyframe by keyframe, the ~30 numpy calls per keyframe made the
    merge of a 10-minute trial's 12,000 keyframes cost ~1.3 s of CPU.)"""
    cell = config.cell_size_m
    keyframes = list(keyframes)
    n_points = sum(kf.profile_xz_m.shape[0] for kf in keyframes)
    if n_points == 0:
        return MapCells(np.zeros((0, 2)), np.zeros(0, np.int64), np.zeros(0, np.int64), cell)
    # 1. extent of the integer cells (for the key layout of merge_points)
    lo = np.full(2, np.iinfo(np.int64).max, dtype=np.int64)
    hi_z = np.iinfo(np.int64).min
    for world, _, _ in _world_batches(keyframes):
        ij = np.floor(world / cell).astype(np.int64)
        lo = np.minimum(lo, ij.min(axis=0))
        hi_z = max(hi_z, int(ij[:, 1].max()))
    n_z = hi_z - int(lo[1]) + 1

    def keys_of(world_xz: NDArray[np.float64]) -> NDArray[np.int64]:
        """One key per point, ordered by (x cell, z cell), as in merge_points."""
        ij = np.floor(world_xz / cell).astype(np.int64)
        ij -= lo
        return ij[:, 0] * n_z + ij[:, 1]

    # 2. the sorted distinct keys (np.unique's cell_keys), merged a batch of points at a time
    cell_keys = np.zeros(0, dtype=np.int64)
    for world, _, _ in _world_batches(keyframes):
        cell_keys = _sorted_distinct(np.concatenate([cell_keys, keys_of(world)]))
    n_cells = cell_keys.shape[0]
    # 3. per-cell counts and sums in point order; distinct keyframes from distinct pairs
    point_counts = np.zeros(n_cells, dtype=np.int64)
    sum_x = np.zeros(n_cells)
    sum_z = np.zeros(n_cells)
    keyframe_counts = np.zeros(n_cells, dtype=np.int64)
    for world, kf_in_batch, n_kf in _world_batches(keyframes):
        idx = np.searchsorted(cell_keys, keys_of(world))
        point_counts += np.bincount(idx, minlength=n_cells)
        np.add.at(sum_x, idx, world[:, 0])
        np.add.at(sum_z, idx, world[:, 1])
        pairs = _sorted_distinct(idx * n_kf + kf_in_batch)
        keyframe_counts += np.bincount(pairs // n_kf, minlength=n_cells)
    keep = (keyframe_counts >= config.min_keyframes_per_cell) & (
        point_counts >= config.min_points_per_cell
    )
    means = np.stack([sum_x[keep], sum_z[keep]], axis=1) / point_counts[keep, None]
    return MapCells(
        points_xz_m=means,
        point_counts=point_counts[keep].astype(np.int64),
        keyframe_counts=keyframe_counts[keep].astype(np.int64),
        cell_size_m=cell,
    )


class TerrainMap2D:
    """Accumulates keyframe profiles into a thinned 2D terrain map.

    Usage::

        terrain_map = TerrainMap2D(MapConfig())
        terrain_map.add_keyframe(t_s, camera_xz_m, profile_xz_m)   # per keyframe
        terrain_map.update_poses(smoother.keyframe_estimates())   # after refinement
        terrain_map.points_xz_m                                     # (M, 2) world, metres

    The merged cells are recomputed lazily after any change.
    """

    def __init__(self, config: MapConfig | None = None) -> None:
        self.config = config if config is not None else MapConfig()
        self._keyframes: list[KeyframeProfile] = []
        self._cells: MapCells | None = None
        # sorted timestamps cache, grown in place while keyframes come in time order (a
        # replay: O(N) in all, where np.append per keyframe copied every earlier stamp)
        self._times: GrowableArray | None = None

    # -- building --------------------------------------------------------------------------
    def add_keyframe(
        self,
        timestamp_s: float,
        camera_xz_m: ArrayLike,
        profile_xz_m: ArrayLike,
        copy: bool = True,
    ) -> None:
        """Add one keyframe (camera position (2,) world, profile (N, 2) relative to camera).

        Non-finite profile rows are dropped. A keyframe with the timestamp of a stored one
        replaces it. With ``max_keyframes`` set, the oldest keyframes are forgotten. With
        ``copy=False`` a finite float64 (N, 2) profile is stored as given, not copied (the
        caller promises not to change it: a run's map shares the replay's profiles).
        """
        keyframe = KeyframeProfile(
            timestamp_s=float(timestamp_s),
            camera_xz_m=_as_xz(camera_xz_m, "camera_xz_m"),
            profile_xz_m=_as_profile(profile_xz_m, copy),
        )
        existing = self._find(keyframe.timestamp_s)
        times = self._times  # sorted timestamps, valid after _find; kept valid when cheap
        if existing is not None:
            self._keyframes[existing] = keyframe
            times = None
        else:
            last = self._keyframes[-1].timestamp_s if self._keyframes else -np.inf
            self._keyframes.append(keyframe)
            if last <= keyframe.timestamp_s:  # in time order (a replay): no sort needed
                if times is not None and len(times) == len(self._keyframes) - 1:
                    times.append(keyframe.timestamp_s)
            else:
                self._keyframes.sort(key=lambda kf: kf.timestamp_s)
                times = None
        if self.config.max_keyframes is not None:
            drop = max(0, len(self._keyframes) - self.config.max_keyframes)
            if drop:
                del self._keyframes[:drop]
                times = None
        self._cells = None
        self._times = times

    def update_poses(
        self,
        keyframe_poses: Mapping[float, ArrayLike] | Iterable[tuple[float, ArrayLike]],
    ) -> int:
        """Move stored keyframes to refined camera positions and invalidate the merged map.

        Args:
            keyframe_poses: ``{timestamp_s: camera_xz_m}`` or an iterable of tuples whose
                first two entries are ``(timestamp_s, camera_xz_m (2,))`` — e.g. the
                smoother's ``keyframe_estimates()`` (extra entries such as a covariance are
                ignored). Timestamps match within ``timestamp_match_tol_s``.

        Returns:
            How many stored keyframes were moved; unknown timestamps are ignored.
        """
        items = keyframe_poses.items() if isinstance(keyframe_poses, Mapping) else keyframe_poses
        moved = 0
        for entry in items:
            timestamp_s, camera_xz_m = entry[0], entry[1]
            i = self._find(float(timestamp_s))
            if i is None:
                continue
            old = self._keyframes[i]
            self._keyframes[i] = KeyframeProfile(
                old.timestamp_s, _as_xz(camera_xz_m, "camera_xz_m"), old.profile_xz_m
            )
            moved += 1
        if moved:
            self._cells = None
        return moved

    def clear(self) -> None:
        """Forget every keyframe."""
        self._keyframes = []
        self._cells = None
        self._times = None

    def _find(self, timestamp_s: float) -> int | None:
        """Index of the stored keyframe at ``timestamp_s`` (keyframes are kept sorted)."""
        if not self._keyframes:
            return None
        if self._times is None or len(self._times) != len(self._keyframes):
            self._times = GrowableArray()
            for kf in self._keyframes:
                self._times.append(kf.timestamp_s)
        times = self._times.view()
        j = int(np.searchsorted(times, timestamp_s))
        for i in (j - 1, j):
            if 0 <= i < times.shape[0]:
                if abs(times[i] - timestamp_s) <= self.config.timestamp_match_tol_s:
                    return i
        return None

    # -- reading ---------------------------------------------------------------------------
    def __len__(self) -> int:
        return len(self._keyframes)

    @property
    def keyframes(self) -> tuple[KeyframeProfile, ...]:
        """Stored keyframes, oldest first."""
        return tuple(self._keyframes)

    def raw_points_xz_m(self) -> tuple[NDArray[np.float64], NDArray[np.int64]]:
        """All stored profile points placed in the world: ((P, 2) metres, (P,) keyframe no.)."""
        if not self._keyframes:
            return np.zeros((0, 2)), np.zeros(0, np.int64)
        points = np.concatenate([kf.world_points_xz_m() for kf in self._keyframes], axis=0)
        sizes = [kf.profile_xz_m.shape[0] for kf in self._keyframes]
        index = np.repeat(np.arange(len(self._keyframes), dtype=np.int64), sizes)
        return points, index

    @property
    def cells(self) -> MapCells:
        """The merged, thinned map (recomputed after any change)."""
        if self._cells is None:
            self._cells = merge_keyframes(self._keyframes, self.config)
        return self._cells

    @property
    def points_xz_m(self) -> NDArray[np.float64]:
        """(M, 2) merged map points in the world x-z plane, metres (a copy)."""
        return self.cells.points_xz_m.copy()

    @property
    def point_counts(self) -> NDArray[np.int64]:
        """(M,) raw points behind each map point (use as weights)."""
        return self.cells.point_counts.copy()
