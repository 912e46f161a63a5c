"""Motion-capture ground truth at 120 Hz (Raptor-12HS): camera pose (optical frame), knee,
ankle, heel and toe, with ~1 mm per-marker noise (Merriaux et al. 2017)."""

from __future__ import annotations

import numpy as np
from numpy.typing import NDArray

from vio_graph.geometry import quat_wxyz_from_matrix, rot_x, rot_y, rot_z
from vio_graph.recording.streams import Trajectory
from vio_graph.sim.config import MocapConfig
from vio_graph.sim.gait import LegMotion, rot_xz


def _to3d(xz: NDArray) -> NDArray[np.float64]:
    out = np.zeros((xz.shape[0], 3))
    out[:, 0], out[:, 2] = xz[:, 0], xz[:, 1]
    return out


def camera_poses(
    motion: LegMotion, t_s: NDArray, camera_in_shank_xz_m: NDArray, R_shank_cam: NDArray
) -> tuple[NDArray[np.float64], NDArray[np.float64]]:
    """True camera position (N, 3) and R_world_cam (N, 3, 3) at times (N,)."""
    t = np.asarray(t_s, dtype=float)
    pos = _to3d(motion.shank_point(t, camera_in_shank_xz_m))
    R = rot_y(motion.shank_pitch(t)) @ R_shank_cam
    return pos, R


def simulate_mocap(
    motion: LegMotion,
    cfg: MocapConfig,
    duration_s: float,
    camera_in_shank_xz_m: NDArray,
    R_shank_cam: NDArray,
    rng: np.random.Generator,
) -> dict[str, Trajectory]:
    """Ground-truth trajectories by name (see recording.streams.GROUNDTRUTH_BODIES)."""
    dt = 1.0 / cfg.rate_hz
    t = np.arange(0.0, duration_s + 0.5 * dt, dt)
    n = t.size
    cam_pos, R_w_c = camera_poses(motion, t, camera_in_shank_xz_m, R_shank_cam)
    shank = motion.shank_pitch(t)
    foot = motion.foot_pitch(t)
    ankle = motion.ankle(t)
    L = motion.leg.shank_length_m
    knee = ankle + rot_xz(shank, np.array([0.0, L]))
    heel = ankle + rot_xz(foot, np.array(motion.leg.heel_in_foot_xz_m))
    toe = ankle + rot_xz(foot, np.array(motion.leg.toe_in_foot_xz_m))
    pts = {"knee": _to3d(knee), "ankle": _to3d(ankle), "heel": _to3d(heel), "toe": _to3d(toe)}
    rot = {"knee": rot_y(shank), "ankle": rot_y(shank), "heel": rot_y(foot), "toe": rot_y(foot)}
    if cfg.noise:
        s = cfg.marker_noise_m
        cam_pos = cam_pos + rng.normal(0, s / np.sqrt(cfg.n_markers), (n, 3))
        ang = rng.normal(0, s / (cfg.cluster_radius_m * np.sqrt(cfg.n_markers)), (n, 3))
        R_err = np.stack([rot_z(a[2]) @ rot_y(a[1]) @ rot_x(a[0]) for a in ang])
        R_w_c = R_err @ R_w_c
        pts = {k: v + rng.normal(0, s, (n, 3)) for k, v in pts.items()}
    out = {"camera": Trajectory(t, cam_pos, quat_wxyz_from_matrix(R_w_c))}
    for k, v in pts.items():
        out[k] = Trajectory(t.copy(), v, quat_wxyz_from_matrix(rot[k]))
    return out
