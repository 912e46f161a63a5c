"""What moves the filter's x: the level-surface tilts and the visual displacements against
the truth, and what the filter gives when either is replaced by the truth.

Replays each simulated recording through :class:`vio_graph.estimator.OnlineEstimator` (the
event order of ``vio-graph run``, filter mode) and, at every frame whose slice yields a level
surface tilt (``frontend/level.py``), compares the measured tilt with the tilt the slice
really has: the pitch error of the attitude the slice was rotated with, from
``groundtruth/imu_state.csv`` (:func:`residual_tilt_rad`). Reports per recording:

- the tilt error (measured minus true): mean (bias) and rms in degrees, and the rms of the
  error over the sigma the pitch aiding uses (the fit's sigma and
  ``level_aiding.measurement_floor_deg`` in quadrature; consistent tilts give ~1), overall and
  by the number of level lines in the slice;
- the displacements' x error (measured minus the true camera motion between the two frame
  times) against the x error of the IMU prediction that seeded the ICP (``pred_delta``, the
  same two times): the least-squares slope of the one on the other over the displacements
  whose x sigma is below 5 cm (0 = the displacement is independent of the seed, as the filter
  assumes; 1 = it repeats the seed's error; a correlation, not a sensitivity: the mocap
  noise of the reference motion enters both errors, and ``benchmarks/eval_icp_seed.py``
  measures the sensitivity), and the displacements' summed x error against
  the summed true x motion (a scale error, %);
- the filter's camera and toe ATE (cm, x / z, anchored at the first frame as in
  ``metrics.json``).

``--oracle-displacement-x`` gives every visual displacement the true camera x motion
(its z and covariance as measured), which does the same for the displacements.

``--oracle`` replaces every tilt the pitch aiding fuses by the true one plus
``--oracle-bias-deg`` plus ``--oracle-scale`` x its stated sigma x N(0, 1) (the level heights
are left as measured), which separates what the tilts' bias and scatter cost the filter from
everything else. A diagnostic, not a mode of the pipeline.

Usage::

    python benchmarks/eval_filter_x.py recordings/upstair_1 [REC ...] [--oracle]
        [--oracle-scale 1.0] [--oracle-bias-deg 0.0] [--oracle-displacement-x]
        [--config CONFIG.yaml]
"""

from __future__ import annotations

import argparse
import dataclasses
import math
from pathlib import Path
from typing import Any

import _common  # noqa: F401, I001 - before numpy: pins the thread pools numpy reads on import
import numpy as np
from numpy.typing import NDArray
from scipy.spatial.transform import Rotation, Slerp

from vio_graph.config import PipelineConfig, load_config
from vio_graph.estimator import OnlineEstimator, RigGeometry
from vio_graph.frontend.level import SurfaceTilt
from vio_graph.geometry import remove_yaw
from vio_graph.recording.reader import Recording
from vio_graph.replay import frames_due


def residual_tilt_rad(R_est_world_imu: NDArray, R_true_world_imu: NDArray) -> float:
    """The tilt (rad, ``SurfaceTilt`` convention: positive = level surfaces rise with x) that a
    slice rotated into the ground frame with the estimated attitude shows: with
    R_est = rot_y(d) R_true (heading removed from both) a level line appears turned by
    rot_y(d), i.e. with slope -tan(d), so the tilt is -d."""
    d = Rotation.from_matrix(
        remove_yaw(R_est_world_imu) @ remove_yaw(R_true_world_imu).T
    ).as_rotvec()[1]
    return -float(d)


def _true_attitude(rec: Recording):
    """t -> true R_world_imu (``groundtruth/imu_state.csv``, slerp between samples)."""
    st = rec.groundtruth.imu_state
    if st is None:
        raise SystemExit(f"{rec.root}: needs groundtruth/imu_state.csv (a simulated recording)")
    slerp = Slerp(st.timestamp_s, Rotation.from_quat(st.quat_wxyz[:, [1, 2, 3, 0]]))
    t_lo, t_hi = float(st.timestamp_s[0]), float(st.timestamp_s[-1])
    return lambda t: slerp([min(max(t, t_lo), t_hi)]).as_matrix()[0]


class TiltProbe(OnlineEstimator):
    """The online estimator, noting each level tilt with the true one (optionally fusing an
    oracle tilt instead)."""

    def __init__(self, config, rig, p0, truth, oracle: tuple[float, float] | None, seed: int):
        super().__init__(config, rig, p0)
        self._truth = truth
        self._oracle = oracle
        self._oracle_rng = np.random.default_rng(seed)
        self.tilts: list[tuple[float, float, float, float, int]] = []
        self._true_tilt = 0.0  # the current frame's true tilt (rad), set before fusing it
        # (t0, t1, x of the IMU prediction seeding ICP) of every front-end call with one
        self.seeds: dict[float, tuple[float, float]] = {}
        process = self.frontend.process

        def noting_seed(frame, K, R, pred=None, pred_cov=None, *args):
            if pred is not None and self._prev_frame is not None:
                self.seeds[frame.timestamp_s] = (self._prev_frame[0], float(pred[0]))
            return process(frame, K, R, pred, pred_cov, *args)

        self.frontend.process = noting_seed  # this instance only

    def _level_aiding(self, t: float, profile_xz_m: NDArray[np.float64]) -> float:
        # the attitude this frame's slice was rotated with (the offset is unchanged since)
        self._true_tilt = residual_tilt_rad(self.R_world_imu(t), self._truth(t))
        step = super()._level_aiding(t, profile_xz_m)
        st = self.surface_tilt
        if st is not None:
            self.tilts.append((t, st.tilt_rad, st.sigma_rad, self._true_tilt, st.n_lines))
        return step

    def _tilt_to_fuse(self, t: float, tilt: SurfaceTilt) -> tuple[float, float]:
        if self._oracle is None:
            return super()._tilt_to_fuse(t, tilt)
        # the fused tilt replaced: the truth with the given bias and noise scale
        scale, bias_rad = self._oracle
        noise = scale * tilt.sigma_rad * self._oracle_rng.standard_normal()
        return self._true_tilt + bias_rad + noise, tilt.sigma_rad


def _ate_cm(t: NDArray, est_xz: NDArray, traj) -> tuple[float, float]:
    ref = np.stack([np.interp(t, traj.timestamp_s, traj.position_m[:, i]) for i in (0, 2)], axis=1)
    err = est_xz - ref
    err -= err[0]
    rmse = np.sqrt(np.mean(err**2, axis=0)) * 100.0
    return float(rmse[0]), float(rmse[1])


def evaluate(
    path: Path,
    config: PipelineConfig,
    oracle: tuple[float, float] | None,
    seed: int = 0,
    oracle_displacement_x: bool = False,
) -> dict[str, Any]:
    """Tilt statistics and the filter's ATE of one recording."""
    rec = Recording.open(path)
    rig = RigGeometry.from_metadata(rec.metadata)
    cam = rec.groundtruth.trajectories["camera"]
    t0 = float(rec.frame_timestamps_s[0])
    p0 = np.array([np.interp(t0, cam.timestamp_s, cam.position_m[:, i]) for i in (0, 2)])
    est = TiltProbe(config, rig, p0, _true_attitude(rec), oracle, seed)
    rows = []

    def true_x(result):  # the front end's result with the displacement's x from the truth
        d = result.displacement
        if d is None:
            return result
        x0, x1 = np.interp([d.t0_s, d.t1_s], cam.timestamp_s, cam.position_m[:, 0])
        delta = np.array([x1 - x0, d.delta_xz_m[1]])
        return dataclasses.replace(result, displacement=dataclasses.replace(d, delta_xz_m=delta))

    transform = true_x if oracle_displacement_x else None
    disp = []
    for i in frames_due(rec, est):
        e, res = est.add_frame(rec.frame(i), None, transform)
        rows.append((e.timestamp_s, *e.camera_xz_m, *e.toe_xz_m))
        d, seed = res.displacement, est.seeds.get(e.timestamp_s)
        if d is not None and seed is not None and abs(seed[0] - d.t0_s) < 1e-9:
            x0, x1 = np.interp([d.t0_s, d.t1_s], cam.timestamp_s, cam.position_m[:, 0])
            disp.append((d.delta_xz_m[0] - (x1 - x0), seed[1] - (x1 - x0), x1 - x0, d.cov_m2[0, 0]))
    r = np.array(rows)
    T = np.array(est.tilts)
    floor = math.radians(config.filter.level_aiding.measurement_floor_deg)
    err = T[:, 1] - T[:, 3]
    norm = err / np.sqrt(T[:, 2] ** 2 + floor**2)
    by_lines = {}
    for n in sorted(set(T[:, 4].astype(int).tolist())):
        m = T[:, 4] == n
        by_lines[n] = {
            "n": int(m.sum()),
            "mean_deg": math.degrees(float(err[m].mean())),
            "rms_deg": math.degrees(float(np.sqrt(np.mean(err[m] ** 2)))),
            "rms_norm": float(np.sqrt(np.mean(norm[m] ** 2))),
        }
    D = np.array(disp)
    keep = D[:, 3] < 0.05**2
    e_d, e_s = D[keep, 0], D[keep, 1]
    return {
        "recording": path.name,
        "n_displacements_x": int(keep.sum()),
        "seed_slope": float(e_d @ e_s / (e_s @ e_s)),
        "displacement_x_scale_pct": float(100.0 * e_d.sum() / D[keep, 2].sum()),
        "n_tilts": int(T.shape[0]),
        "tilt_mean_deg": math.degrees(float(err.mean())),
        "tilt_rms_deg": math.degrees(float(np.sqrt(np.mean(err**2)))),
        "tilt_rms_norm": float(np.sqrt(np.mean(norm**2))),
        "by_lines": by_lines,
        "camera_ate_cm": _ate_cm(r[:, 0], r[:, 1:3], cam),
        "toe_ate_cm": _ate_cm(r[:, 0], r[:, 3:5], rec.groundtruth.trajectories["toe"]),
    }


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("recordings", nargs="+", type=Path)
    ap.add_argument("--config", type=Path, default=None)
    ap.add_argument("--oracle", action="store_true", help="fuse true tilts (see module doc)")
    ap.add_argument("--oracle-scale", type=float, default=1.0)
    ap.add_argument("--oracle-bias-deg", type=float, default=0.0)
    ap.add_argument(
        "--oracle-displacement-x", action="store_true", help="true x in every displacement"
    )
    ap.add_argument("--seed", type=int, default=0, help="seed of the oracle's noise")
    args = ap.parse_args()
    config = load_config(args.config)
    oracle = (args.oracle_scale, math.radians(args.oracle_bias_deg)) if args.oracle else None
    print(
        "| recording | tilts | error mean / rms (deg) | rms / sigma | 1 line: mean / rms (deg), "
        "rms / sigma | displacements with x: n, slope on seed, x scale error | "
        "filter camera x / z (cm) | filter toe x / z (cm) |"
    )
    print("|---|---|---|---|---|---|---|---|")
    for path in args.recordings:
        res = evaluate(path, config, oracle, args.seed, args.oracle_displacement_x)
        one = res["by_lines"].get(1)
        one_s = (
            "-"
            if one is None
            else f"{one['mean_deg']:+.2f} / {one['rms_deg']:.2f}, {one['rms_norm']:.2f}"
        )
        cx, cz = res["camera_ate_cm"]
        tx, tz = res["toe_ate_cm"]
        print(
            f"| {res['recording']} | {res['n_tilts']} | {res['tilt_mean_deg']:+.2f} / "
            f"{res['tilt_rms_deg']:.2f} | {res['tilt_rms_norm']:.2f} | {one_s} | "
            f"{res['n_displacements_x']}, {res['seed_slope']:.2f}, "
            f"{res['displacement_x_scale_pct']:+.1f} % | "
            f"{cx:.2f} / {cz:.2f} | {tx:.2f} / {tz:.2f} |",
            flush=True,
        )


if __name__ == "__main__":
    main()
