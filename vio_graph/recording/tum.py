"""TUM trajectory files: ``timestamp tx ty tz qx qy qz qw`` per line (what evo reads)."""

from __future__ import annotations

import os
from pathlib import Path

import numpy as np

from vio_graph.errors import RecordingError
from vio_graph.io_utils import atomic_write_text
from vio_graph.recording.streams import Trajectory


def read_tum(path: str | os.PathLike[str]) -> Trajectory:
    """Read a TUM file; raises RecordingError naming the file on any malformation."""
    path = Path(path)
    if not path.is_file():
        raise RecordingError(path, "file not found")
    try:
        data = np.loadtxt(path, comments="#", ndmin=2, dtype=float)
    except ValueError as exc:
        raise RecordingError(path, f"not a TUM trajectory ({exc})") from None
    if data.size == 0:
        raise RecordingError(path, "empty trajectory")
    if data.shape[1] != 8:
        raise RecordingError(path, f"expected 8 columns, found {data.shape[1]}")
    if not np.all(np.isfinite(data)):
        raise RecordingError(path, "contains NaN or inf")
    t = data[:, 0]
    if np.any(np.diff(t) <= 0):
        raise RecordingError(path, "timestamps are not strictly increasing", field="timestamp")
    quat_wxyz = data[:, [7, 4, 5, 6]]
    norms = np.linalg.norm(quat_wxyz, axis=1)
    if np.any(np.abs(norms - 1.0) > 1e-3):
        raise RecordingError(path, "quaternions are not unit length", field="quaternion")
    return Trajectory(t.copy(), data[:, 1:4].copy(), quat_wxyz / norms[:, None])


def format_tum(traj: Trajectory) -> str:
    """TUM text for a trajectory (9 decimals on time, 6 on position and quaternion)."""
    q = traj.quat_wxyz
    rows = np.column_stack([traj.timestamp_s, traj.position_m, q[:, 1], q[:, 2], q[:, 3], q[:, 0]])
    # Python floats and one %-format per row: the same digits as formatting each numpy
    # scalar with an f-string (both round through the same double-to-string), ~4x faster.
    # A column that holds one value in every row (y = 0 and the identity orientation of the
    # sagittal paths, Trajectory.from_xz: 5 of the 8) is formatted once into the row's
    # format, the same text; "one value" by its bits, so -0.0 beside 0.0 or NaNs are not
    fields = ["%.9f"] + ["%.6f"] * 7
    varying = list(range(8))
    if rows.shape[0] > 1:
        bits = rows.view(np.int64)
        same = (bits == bits[0]).all(axis=0)
        varying = [0]  # (the time column always varies)
        for k in range(1, 8):
            if same[k]:
                fields[k] = fields[k] % float(rows[0, k])
            else:
                varying.append(k)
    line = " ".join(fields).__mod__
    lines = map(line, map(tuple, rows[:, varying].tolist()))
    return "# timestamp tx ty tz qx qy qz qw\n" + "\n".join(lines) + "\n"


def write_tum(path: str | os.PathLike[str], traj: Trajectory) -> None:
    """Write a TUM file atomically (temporary name, then rename)."""
    atomic_write_text(Path(path), format_tum(traj))
