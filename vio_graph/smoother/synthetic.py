"""Synthetic swinging-shank trials for testing and benchmarking the smoother (pure numpy).

The IMU pitches sinusoidally (about +y, up to ~3 rad/s) while moving forward with a vertical
bob; the camera sits at a lever arm ``imu_T_cam``. IMU samples are exact (specific force and
gyro from the analytic trajectory, optional constant biases); displacements are exact camera
motions plus white noise (and optional bias / outliers / gaps); corner observations are stair
nosings at fixed world points minus the camera position plus noise. The "filter estimate" is
dead reckoning of the displacements (velocity from the truth plus noise), a deliberately poor
initial guess.
"""

from __future__ import annotations

from collections.abc import Iterator, Sequence
from dataclasses import dataclass

import numpy as np
from numpy.typing import NDArray

from vio_graph.geometry import GRAVITY_MPS2, make_transform, quat_wxyz_from_matrix, rot_y, rot_z
from vio_graph.types import (
    CornerObservation,
    Displacement2D,
    EstimateStatus,
    FrameEstimate,
    ImuSample,
)

#: camera optical z along IMU +x, camera x along IMU -y, camera y along IMU -z
R_IMU_CAM = np.array([[0.0, 0.0, 1.0], [-1.0, 0.0, 0.0], [0.0, -1.0, 0.0]])
IMU_P_CAM_M = np.array([0.05, 0.0, 0.08])


@dataclass(frozen=True)
class SyntheticTrial:
    """A generated trial: inputs of the smoother plus the ground truth.

    Arrays are per depth frame (N frames) unless said otherwise.
    """

    imu: list[ImuSample]
    frame_times_s: NDArray[np.float64]  # (N,)
    camera_xz_true_m: NDArray[np.float64]  # (N, 2)
    displacements: list[Displacement2D | None]  # (N,), frame n-1 -> n
    observations: list[list[CornerObservation]]  # (N,)
    is_keyframe: NDArray[np.bool_]  # (N,)
    filter_estimates: list[FrameEstimate]  # (N,)
    imu_T_cam: NDArray[np.float64]  # (4, 4)
    corners_xz_m: NDArray[np.float64]  # (K, 2)

    @property
    def filter_xz_m(self) -> NDArray[np.float64]:
        """(N, 2) filter camera positions."""
        return np.array([e.camera_xz_m for e in self.filter_estimates])


def _trajectory(t: NDArray[np.float64]) -> dict[str, NDArray[np.float64]]:
    """Analytic IMU trajectory: pitch (rad), rate, position (N,3), velocity, acceleration."""
    w = 2.0 * np.pi * 1.0  # 1 Hz gait
    A = 0.5  # rad -> peak rate ~3.1 rad/s
    v_fwd, a1, a2, h = 0.8, 0.1, 0.03, 0.5
    pitch = A * np.sin(w * t)
    rate = A * w * np.cos(w * t)
    z0 = np.zeros_like(t)
    pos = np.stack([v_fwd * t + a1 * np.sin(w * t), z0, h + a2 * np.cos(2 * w * t)], -1)
    vel = np.stack([v_fwd + a1 * w * np.cos(w * t), z0, -2 * w * a2 * np.sin(2 * w * t)], -1)
    acc = np.stack([-a1 * w**2 * np.sin(w * t), z0, -4 * w**2 * a2 * np.cos(2 * w * t)], -1)
    return {"pitch": pitch, "rate": rate, "pos": pos, "vel": vel, "acc": acc}


def make_swinging_shank_trial(
    duration_s: float = 10.0,
    *,
    imu_rate_hz: float = 100.0,
    frame_rate_hz: float = 30.0,
    keyframe_every: int = 3,
    displacement_sigma_m: float = 0.0,
    displacement_bias_mps: tuple[float, float] = (0.0, 0.0),
    observation_sigma_m: float = 0.0,
    accel_bias_mps2: tuple[float, float, float] = (0.0, 0.0, 0.0),
    gyro_bias_radps: tuple[float, float, float] = (0.0, 0.0, 0.0),
    heading_rad: float = 0.0,
    gap_s: tuple[float, float] | None = None,
    outlier_frames: Sequence[int] = (),
    outlier_xz_m: tuple[float, float] = (0.28, 0.147),
    corners: bool = True,
    filter_velocity_sigma_mps: float = 0.02,
    filter_drift_mps: tuple[float, float] = (0.0, 0.0),
    seed: int = 0,
) -> SyntheticTrial:
    """Generate a trial (see module docstring).

    Args:
        displacement_bias_mps: constant velocity bias added to every displacement (x, z).
        gap_s: (t0, t1): frames with t0 <= t < t1 have no displacement and no observation
            (the displacement into the first frame after the gap is dropped too).
        outlier_frames: frame indices whose displacement is off by ``outlier_xz_m`` (a corner
            associated with the next stair step).
        heading_rad: vendor AHRS heading (the smoother must remove it).
        filter_drift_mps: constant velocity (x, z, m/s) added to the "filter" positions, the
            initial guesses: a filter that drifts over a long trial.
    """
    rng = np.random.default_rng(seed)
    imu_T_cam = make_transform(R_IMU_CAM, IMU_P_CAM_M)

    # --- IMU ---
    t_imu = np.arange(0.0, duration_s + 0.05, 1.0 / imu_rate_hz)
    tr = _trajectory(t_imu)
    R = rot_y(tr["pitch"])  # (M, 3, 3) R_world_imu
    g_world = np.array([0.0, 0.0, -GRAVITY_MPS2])
    f_body = np.einsum("nji,nj->ni", R, tr["acc"] - g_world) + np.asarray(accel_bias_mps2)
    gyro = np.stack([np.zeros_like(t_imu), tr["rate"], np.zeros_like(t_imu)], -1)
    gyro = gyro + np.asarray(gyro_bias_radps)
    q = quat_wxyz_from_matrix(rot_z(heading_rad) @ R)
    imu = [
        ImuSample(float(t_imu[k]), f_body[k].copy(), gyro[k].copy(), q[k].copy())
        for k in range(t_imu.size)
    ]

    # --- camera truth at frame times ---
    t_f = np.arange(0.0, duration_s + 1e-9, 1.0 / frame_rate_hz)
    trf = _trajectory(t_f)
    Rf = rot_y(trf["pitch"])
    cam = trf["pos"] + Rf @ IMU_P_CAM_M
    omega = np.stack([np.zeros_like(t_f), trf["rate"], np.zeros_like(t_f)], -1)
    cam_vel = trf["vel"] + np.einsum("nij,nj->ni", Rf, np.cross(omega, IMU_P_CAM_M))
    cam_xz, cam_vel_xz = cam[:, [0, 2]], cam_vel[:, [0, 2]]
    n = t_f.size
    in_gap = np.zeros(n, bool)
    if gap_s is not None:
        in_gap = (t_f >= gap_s[0]) & (t_f < gap_s[1])

    # --- displacements (frame n-1 -> n) ---
    dt_f = np.diff(t_f)
    d_true = np.diff(cam_xz, axis=0)
    noise = rng.normal(0.0, displacement_sigma_m, d_true.shape) if displacement_sigma_m else 0.0
    d_meas = d_true + noise + np.outer(dt_f, displacement_bias_mps)
    for k in outlier_frames:
        d_meas[k - 1] += np.asarray(outlier_xz_m)
    cov_d = np.eye(2) * max(displacement_sigma_m, 1e-3) ** 2
    disps: list[Displacement2D | None] = [None]
    for k in range(1, n):
        if in_gap[k] or in_gap[k - 1]:
            disps.append(None)
        else:
            disps.append(Displacement2D(float(t_f[k - 1]), float(t_f[k]), d_meas[k - 1], cov_d))

    # --- corners: stair nosings ahead of the start, at least 40, enough for the whole trial ---
    n_corners = max(40, int(np.ceil((cam_xz[-1, 0] + 1.2) / 0.28)))
    corner_xz = np.array([[1.2 + 0.28 * k, 0.147 * (k + 1)] for k in range(n_corners)])
    obs: list[list[CornerObservation]] = []
    cov_o = np.eye(2) * max(observation_sigma_m, 1e-3) ** 2
    for k in range(n):
        rel = corner_xz - cam_xz[k]
        vis = (
            np.flatnonzero((rel[:, 0] > 0.3) & (rel[:, 0] < 1.2))
            if corners
            else np.zeros(0, dtype=int)
        )
        frame_obs = []
        if not in_gap[k]:
            for j in vis:
                o = rel[j] + (rng.normal(0.0, observation_sigma_m, 2) if observation_sigma_m else 0)
                frame_obs.append(CornerObservation(float(t_f[k]), int(j), o, cov_o))
        obs.append(frame_obs)

    # --- "filter" = displacement dead reckoning (true velocity through gaps) ---
    est = np.empty_like(cam_xz)
    est[0] = cam_xz[0]
    for k in range(1, n):
        step = d_meas[k - 1] if disps[k] is not None else cam_vel_xz[k] * dt_f[k - 1]
        est[k] = est[k - 1] + step
    est += np.outer(t_f - t_f[0], filter_drift_mps)
    vel_est = cam_vel_xz + rng.normal(0.0, filter_velocity_sigma_mps, cam_vel_xz.shape)
    zero2 = np.zeros(2)
    filt = [
        FrameEstimate(
            timestamp_s=float(t_f[k]),
            status=EstimateStatus.FUSED,
            camera_xz_m=est[k].copy(),
            velocity_xz_mps=vel_est[k].copy(),
            cov_position_m2=np.eye(2) * 1e-4,
            knee_xz_m=zero2,
            ankle_xz_m=zero2,
            heel_xz_m=zero2,
            toe_xz_m=zero2,
        )
        for k in range(n)
    ]
    kf = np.zeros(n, bool)
    kf[::keyframe_every] = True
    return SyntheticTrial(imu, t_f, cam_xz, disps, obs, kf, filt, imu_T_cam, corner_xz)


def replay_events(trial: SyntheticTrial) -> Iterator[tuple[str, int]]:
    """Time-ordered events ("imu", k) / ("frame", n); an IMU sample at a frame's time first."""
    t_imu = np.array([s.timestamp_s for s in trial.imu])
    k = 0
    for n, t in enumerate(trial.frame_times_s):
        while k < t_imu.size and t_imu[k] <= t + 1e-9:
            yield "imu", k
            k += 1
        yield "frame", n
    while k < t_imu.size:
        yield "imu", k
        k += 1


def feed(trial: SyntheticTrial, smoother: object, use_filter_guess: bool = True) -> None:
    """Drive any smoother with the shared ingestion interface through a whole trial."""
    for kind, i in replay_events(trial):
        if kind == "imu":
            smoother.feed_imu(trial.imu[i])  # type: ignore[attr-defined]
        else:
            smoother.feed_frame(  # type: ignore[attr-defined]
                float(trial.frame_times_s[i]),
                bool(trial.is_keyframe[i]),
                trial.filter_estimates[i] if use_filter_guess or i == 0 else None,
                trial.displacements[i],
                trial.observations[i],
            )
    smoother.flush()  # type: ignore[attr-defined]
