"""The front end's displacements with everything else exact: how much does the ICP's z walk?

Simulates a scenario in memory and feeds :class:`vio_graph.frontend.frontend.VisualFrontend`
every depth frame with the simulator's exact camera attitude (``R_world_cam``, the true
ground frame) and, as the IMU seed, the true displacement since the previous frame (sigma
1 cm). What is left is the front end's own error: per frame the measured minus the true
displacement. Reports, per trial, the number of displacements, the mean and sd of the z
error (um), the lag-1 correlation of consecutive z errors (-0.5 if each frame's noise
cancelled in the next pair, 0 for a random walk), and the summed x and z errors (mm).

``--camera-noise off`` renders without any ToF noise (``camera.noise: false``), which
separates what the noise does from what the geometry does.

Usage::

    python benchmarks/eval_floor_icp.py --scenario level --seeds 1 2 3 [--duration 10] \\
        [--swing joint_space] [--camera-noise off] [--config CONFIG.yaml]
"""

from __future__ import annotations

import argparse

import _common  # noqa: F401, I001 - before numpy: pins the thread pools numpy reads on import
import numpy as np

from vio_graph.config import load_config
from vio_graph.frontend.frontend import VisualFrontend
from vio_graph.sim.config import load_scenario
from vio_graph.sim.trial import simulate_trial
from vio_graph.types import DepthFrame


def trial_errors(trial, frontend: VisualFrontend) -> np.ndarray:
    """(N, 2) measured minus true displacement (m) of every displacement the front end gives."""
    cam = trial.camera
    K = np.array([[cam.fx, 0.0, cam.cx], [0.0, cam.fy, cam.cy], [0.0, 0.0, 1.0]])
    unit = trial.config.camera.depth_unit_m
    errors = []
    for i in range(trial.n_frames):
        depth, conf = trial.render_frame(i)
        depth = (np.rint(depth / unit) * unit).astype(np.float32)  # as the recording stores it
        conf = np.where(depth > 0, conf, 0).astype(np.uint8)
        pos = trial.camera_position_m
        true = None if i == 0 else (pos[i] - pos[i - 1])[[0, 2]]
        res = frontend.process(
            DepthFrame(i, float(trial.frame_true_time_s[i]), depth, conf),
            K,
            trial.R_world_cam[i],
            true,
            None if true is None else np.eye(2) * 0.01**2,
        )
        if res.displacement is not None and true is not None:
            errors.append(res.displacement.delta_xz_m - true)
    return np.array(errors).reshape(-1, 2)


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--scenario", default="level", help="scenario name or YAML")
    ap.add_argument("--seeds", type=int, nargs="+", default=[1, 2, 3])
    ap.add_argument("--duration", type=float, default=10.0, help="trial duration, s")
    ap.add_argument("--swing", choices=["via_points", "joint_space"], default=None)
    ap.add_argument("--camera-noise", choices=["on", "off"], default="on")
    ap.add_argument("--config", default=None, help="pipeline config YAML (its frontend part)")
    args = ap.parse_args()
    scenario = load_scenario(args.scenario)
    update: dict = {"duration_s": args.duration}
    if args.swing is not None:
        update["gait"] = scenario.gait.model_copy(update={"swing_model": args.swing})
    if args.camera_noise == "off":
        update["camera"] = scenario.camera.model_copy(update={"noise": False})
    scenario = scenario.model_copy(update=update)
    fe_cfg = load_config(args.config).frontend if args.config else None
    print("| seed | n | z mean um | z sd um | lag-1 corr z | sum x mm | sum z mm |")
    print("|---|---|---|---|---|---|---|")
    for seed in args.seeds:
        e = trial_errors(simulate_trial(scenario, seed), VisualFrontend(fe_cfg))
        z = e[:, 1]
        lag1 = float(np.corrcoef(z[:-1], z[1:])[0, 1]) if z.size > 2 else float("nan")
        print(
            f"| {seed} | {z.size} | {1e6 * z.mean():+.1f} | {1e6 * z.std():.0f} | {lag1:+.2f} "
            f"| {1e3 * e[:, 0].sum():+.1f} | {1e3 * z.sum():+.1f} |"
        )


if __name__ == "__main__":
    main()
