"""The level surfaces' heights against the truth: is a far tread read too high or too low?

Replays each simulated recording through :class:`vio_graph.estimator.OnlineEstimator` (the
event order of ``vio-graph run``, filter mode) and, for every level surface the front end
reports (``SurfaceTilt.lines``, frontend/level.py), compares its height relative to the
camera with the truth: the true tread height under the line's x extent (the terrain's
``profile_xz_m`` in metadata.yaml) minus the true camera height (``groundtruth/camera.tum``).

The error is split in two:

- *tilt*: the line's height is read at the camera after levelling the slice by the fitted
  common slope s; the slice's true tilt t (the pitch error of the attitude it was rotated
  with, ``groundtruth/imu_state.csv``) would give mean(z) - t x_mid, so (t - s) x_mid of the
  error is the slope fit's;
- *depth*: the rest, the height the line's points give when levelled with the true tilt.

Rows are grouped by range (x_mid, m) and by whether the line was the first sight of its
height landmark in the filter. Also reports the filter camera z error at the end (cm).

Usage::

    python benchmarks/eval_level_heights.py REC [REC ...] [--config CONFIG.yaml] [--csv OUT]
"""

from __future__ import annotations

import argparse
import math
from pathlib import Path
from typing import Any

import _common  # noqa: F401, I001 - before numpy: pins the thread pools numpy reads on import
import numpy as np
from eval_filter_x import _true_attitude, residual_tilt_rad
from numpy.typing import NDArray

from vio_graph.config import load_config
from vio_graph.estimator import OnlineEstimator, RigGeometry
from vio_graph.recording.reader import Recording
from vio_graph.replay import frames_due

#: range bins (m, x_mid of the line)
_BINS = (0.0, 0.4, 0.7, 1.0, 1.4, 3.0)


def _treads(profile_xz_m: NDArray) -> NDArray:
    """(n, 3) horizontal segments of a true profile polyline: x0, x1, z (m)."""
    p = np.asarray(profile_xz_m, float)
    out = []
    for a, b in zip(p[:-1], p[1:], strict=True):
        if abs(b[1] - a[1]) < 1e-9 and b[0] - a[0] > 1e-6:
            out.append((a[0], b[0], a[1]))
    return np.array(out)


def true_level(treads: NDArray, x_lo: float, x_hi: float) -> tuple[float, float]:
    """The height (m) of the horizontal segment that overlaps [x_lo, x_hi] most, and the
    share of the interval it covers."""
    ov = np.minimum(treads[:, 1], x_hi) - np.maximum(treads[:, 0], x_lo)
    k = int(np.argmax(ov))
    return float(treads[k, 2]), float(ov[k] / max(x_hi - x_lo, 1e-9))


class LevelProbe(OnlineEstimator):
    """The online estimator, noting each level line with the true tilt and whether the
    filter took it as a new height landmark."""

    def __init__(self, config, rig, p0, truth) -> None:
        super().__init__(config, rig, p0)
        self._truth = truth
        self.rows: list[tuple] = []
        self._true_tilt = 0.0
        key = self._levels.key

        def noting_key(height_m, eskf, taken):
            k = key(height_m, eskf, taken)
            self._keys.append((height_m, k, k is not None and not eskf.has_landmark(k)))
            return k

        self._levels.key = noting_key  # this instance only
        self._keys: list = []

    def _level_aiding(self, t: float, profile_xz_m: NDArray[np.float64], *args) -> float:
        self._true_tilt = residual_tilt_rad(self.R_world_imu(t), self._truth(t))
        return super()._level_aiding(t, profile_xz_m, *args)

    def _fuse_levels(self, t: float) -> None:
        self._keys = []
        camera_z = float(self._position_at(t)[0][1])
        super()._fuse_levels(t)
        st = self.surface_tilt
        if st is None:
            return
        by_h = {round(h, 12): (k, new) for h, k, new in self._keys}
        s = math.tan(st.tilt_rad)
        for ln in st.lines:
            k, new = by_h.get(round(camera_z + ln.height_m, 12), (None, False))
            used = k is not None
            self.rows.append(
                (t, ln.height_m, ln.sigma_m, ln.noise_sigma_m, ln.x_min_m, ln.x_max_m,
                 ln.x_mid_m, s, math.tan(self._true_tilt), int(used), int(new),
                 -1 if k is None else k.id, camera_z)
            )  # fmt: skip


def evaluate(path: Path, config) -> dict[str, Any]:
    rec = Recording.open(path)
    rig = RigGeometry.from_metadata(rec.metadata)
    cam = rec.groundtruth.trajectories["camera"]
    t0 = float(rec.frame_timestamps_s[0])
    p0 = np.array([np.interp(t0, cam.timestamp_s, cam.position_m[:, i]) for i in (0, 2)])
    est = LevelProbe(config, rig, p0, _true_attitude(rec))
    treads = _treads(rec.metadata.terrain.profile_xz_m)
    cam_err = []
    for i in frames_due(rec, est):
        e, _ = est.add_frame(rec.frame(i))
        tz = np.interp(e.timestamp_s, cam.timestamp_s, cam.position_m[:, 2])
        cam_err.append((e.timestamp_s, e.camera_xz_m[1] - tz))
    R = np.array(est.rows)
    t = R[:, 0]
    cx = np.interp(t, cam.timestamp_s, cam.position_m[:, 0])
    cz = np.interp(t, cam.timestamp_s, cam.position_m[:, 2])
    out = []
    for row, x, z in zip(R, cx, cz, strict=True):
        h_true, cover = true_level(treads, x + row[4], x + row[5])
        tilt_part = (row[8] - row[7]) * row[6]  # (t - s) x_mid
        err = row[1] - (h_true - z)
        inc = math.degrees(math.atan2(-row[1], row[6]))  # depression of the ray to x_mid
        out.append((*row, h_true - z, err, tilt_part, err - tilt_part, cover, inc))
    return {"rows": np.array(out), "cam_err": np.array(cam_err), "name": path.name}


#: columns of a result row
COLS = (
    "t_s height_m sigma_m noise_sigma_m x_min_m x_max_m x_mid_m slope true_slope used new "
    "key camera_z_est_m height_true_m err_m tilt_part_m depth_part_m cover depression_deg"
).split()


def summarise(name: str, A: NDArray, cam_err: NDArray) -> None:
    c = {n: i for i, n in enumerate(COLS)}
    ok = A[:, c["cover"]] > 0.8
    A = A[ok]
    print(f"## {name}: {A.shape[0]} lines; filter camera z error at end "
          f"{100 * cam_err[-1, 1]:+.2f} cm")  # fmt: skip
    print("| range m | sight | n | err mean mm | tilt part | depth part | rms mm | sigma med mm |")
    print("|---|---|---|---|---|---|---|---|")
    for lo, hi in zip(_BINS[:-1], _BINS[1:], strict=True):
        for label, m in (
            ("all used", A[:, c["used"]] == 1),
            ("first", A[:, c["new"]] == 1),
            ("unused", A[:, c["used"]] == 0),
        ):
            m = m & (A[:, c["x_mid_m"]] >= lo) & (A[:, c["x_mid_m"]] < hi)
            if m.sum() == 0:
                continue
            e = A[m, c["err_m"]] * 1e3
            print(
                f"| {lo:.1f}-{hi:.1f} | {label} | {int(m.sum())} | {e.mean():+.2f} | "
                f"{1e3 * A[m, c['tilt_part_m']].mean():+.2f} | "
                f"{1e3 * A[m, c['depth_part_m']].mean():+.2f} | "
                f"{np.sqrt(np.mean(e**2)):.2f} | {1e3 * np.median(A[m, c['sigma_m']]):.2f} |"
            )


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("recordings", nargs="+", type=Path)
    ap.add_argument("--config", type=Path, default=None)
    ap.add_argument("--csv", type=Path, default=None, help="folder for per-line rows")
    args = ap.parse_args()
    config = load_config(args.config)
    for path in args.recordings:
        res = evaluate(path, config)
        summarise(res["name"], res["rows"], res["cam_err"])
        if args.csv is not None:
            args.csv.mkdir(parents=True, exist_ok=True)
            np.savetxt(args.csv / f"{res['name']}.csv", res["rows"], delimiter=",",
                       header=",".join(COLS), comments="")  # fmt: skip
            np.savetxt(args.csv / f"{res['name']}_camz.csv", res["cam_err"], delimiter=",")


if __name__ == "__main__":
    main()
