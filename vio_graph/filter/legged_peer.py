"""A peer from outside the project: GTSAM 4.3's legged-robot invariant EKF
(``gtsam.LeggedInvariantEKF``, Hartley et al.'s contact-aided InEKF) driven like every other
estimator through the protocol (vio_graph/protocol.py). Mode ``gtsam_legged`` of
``vio-graph run`` (a baseline: never part of ``--mode all``).

What it is given, per the issue ("the same shank IMU, the same kinematic chain and our stance
detection"):

- every IMU sample in shank axes as measured (``ImuStep.shank``: gyro and specific force,
  3-D), zero-order hold between samples (as GTSAM's ``LeggedEstimatorExample.py``), gravity
  9.81 m/s^2 along world -z (``PreintegrationParams.MakeSharedU``);
- one foot, the ankle joint: a point fixed on the shank, so its position in the IMU frame is
  the rig's kinematic chain (``FrameRecord.estimate.ankle_xz_m`` minus the IMU position,
  turned into IMU axes with the attitude the chain was built with);
- a contact at every frame our stance detector anchored (``FrameRecord.in_stance``;
  touchdown at the first frame of each stance), none otherwise.

It sees no depth data (no displacement, no corners): it is leg odometry + IMU, the class of
estimator GTSAM ships for legged robots. Start: the first IMU sample, at the run's initial
camera position (like the IMU-only baseline), at rest, attitude from the sample's vendor
orientation with the heading removed. The camera position per frame is the estimated IMU pose
composed with ``shank_imu_T_cam`` (x-z kept; the lateral axis is ignored).

Parameters are GTSAM's example values except the accelerometer sigma (0.1 m/s^2/sqrt(Hz))
and the contact sigma (2 mm), chosen on the simulated upstair trial seed 1 among
{0.02, 0.1, 0.3} x {1, 2, 5, 20 mm} (camera RMSE x 28 -> 3.4 cm; GTSAM's example values
2e-2 and 2-3 cm suit a quadruped's feet, not one ankle in contact 25 % of the frames).
"""

from __future__ import annotations

import time
from typing import Any

import numpy as np
from numpy.typing import ArrayLike, NDArray

from vio_graph.errors import EstimationError
from vio_graph.filter.baselines import PathKeeper
from vio_graph.geometry import remove_yaw
from vio_graph.protocol import EstimatorReport, FrameRecord, ImuStep

GRAVITY_MPS2 = 9.81


def _quat_to_R(q_wxyz: ArrayLike) -> NDArray[np.float64]:
    w, x, y, z = (float(v) for v in np.asarray(q_wxyz, dtype=float) / np.linalg.norm(q_wxyz))
    return np.array(
        [
            [1 - 2 * (y * y + z * z), 2 * (x * y - w * z), 2 * (x * z + w * y)],
            [2 * (x * y + w * z), 1 - 2 * (x * x + z * z), 2 * (y * z - w * x)],
            [2 * (x * z - w * y), 2 * (y * z + w * x), 1 - 2 * (x * x + y * y)],
        ]
    )


def legged_params(
    gyro_sigma_radps: float = 1e-3,
    accel_sigma_mps2: float = 0.1,
    contact_sigma_m: float = 0.002,
):
    """``gtsam.LeggedEstimatorParams`` for the shank rig (continuous-time IMU noise densities
    as sigmas per sqrt(s) of the rig's sensor; GTSAM's example values elsewhere)."""
    import gtsam

    p = gtsam.LeggedEstimatorParams()
    pre = gtsam.PreintegrationParams.MakeSharedU(GRAVITY_MPS2)
    pre.setGyroscopeCovariance(np.eye(3) * gyro_sigma_radps**2)
    pre.setIntegrationCovariance(np.eye(3) * 1e-6)
    pre.setAccelerometerCovariance(np.eye(3) * accel_sigma_mps2**2)
    p.preintegrationParams = pre
    p.body_P_imu = gtsam.Pose3()
    p.footholdProcessSigma = 1e-4
    p.footholdInitSigma = 0.5
    p.contactCovariance = np.eye(3) * contact_sigma_m**2
    p.heightPriorSigma = 0.02
    p.useRobustContactNoise = False
    p.robustContactHuberK = 2.0
    p.imuBias = gtsam.imuBias.ConstantBias()
    p.biasAccRandomWalkSigma = 5e-3
    p.biasOmegaRandomWalkSigma = 1e-4
    p.useFullContactInitialization = False
    p.marginalizeLeavingFoot = True
    return p


class GtsamLeggedPeer(PathKeeper):
    """GTSAM's ``LeggedInvariantEKF`` on the shank IMU with the ankle as the one foot."""

    name = "gtsam_legged"

    def __init__(self, imu_T_cam: ArrayLike, initial_camera_xz_m: ArrayLike | None = None) -> None:
        T = np.asarray(imu_T_cam, dtype=float)
        if T.shape != (4, 4) or not np.all(np.isfinite(T)):
            raise EstimationError(f"imu_T_cam must be a finite 4x4 matrix, got {T.shape}")
        super().__init__(initial_camera_xz_m)  # self._p0, self._path
        self._t_cam = T[:3, 3].copy()  # camera in the IMU frame, m
        self._ekf: Any = None  # gtsam.LeggedInvariantEKF once the first IMU sample came
        self._t_s = float("nan")
        self._held: tuple[NDArray[np.float64], NDArray[np.float64]] | None = None
        self._was_contact = False
        self._ms: list[float] = []
        self._n_contacts = 0

    def _start(self, step: ImuStep) -> None:
        import gtsam

        s = step.shank
        R = remove_yaw(_quat_to_R(s.quat_wxyz))
        cam = np.array([self._p0[0], 0.0, self._p0[1]])
        p_imu = cam - R @ self._t_cam
        nav = gtsam.NavState(gtsam.Rot3(R), p_imu, np.zeros(3))
        P0 = np.zeros((12, 12))
        P0[:3, :3] = np.eye(3) * 1e-4  # attitude, rad^2
        P0[3:6, 3:6] = np.eye(3) * 1e-4  # velocity, (m/s)^2
        P0[6:9, 6:9] = np.eye(3) * 1e-6  # position, m^2
        P0[9:, 9:] = np.eye(3) * 0.25  # the foothold, m^2
        params = legged_params()
        self._ekf = gtsam.LeggedInvariantEKF(nav, np.zeros((3, 1)), P0, params, ["ankle"])

    def _predict_to(self, t_s: float) -> None:
        dt = t_s - self._t_s
        if self._held is not None and dt > 0:
            self._ekf.predict(self._held[0], self._held[1], dt)
            self._t_s = t_s

    def add_imu(self, step: ImuStep) -> None:
        s = step.shank
        t0 = time.perf_counter()
        if self._ekf is None:
            self._start(step)
            self._t_s = s.timestamp_s
        else:
            self._predict_to(s.timestamp_s)
        self._held = (np.asarray(s.gyro_radps, float), np.asarray(s.accel_mps2, float))
        self._ms.append((time.perf_counter() - t0) * 1e3)

    def add_frame(self, record: FrameRecord) -> None:
        import gtsam

        if self._ekf is None:
            raise EstimationError("gtsam_legged: a frame before the first IMU sample")
        t0 = time.perf_counter()
        self._predict_to(record.timestamp_s)
        contacts = []
        if record.in_stance:
            est = record.estimate
            R = np.asarray(record.R_world_imu, dtype=float)
            cam = np.array([est.camera_xz_m[0], 0.0, est.camera_xz_m[1]])
            ankle = np.array([est.ankle_xz_m[0], 0.0, est.ankle_xz_m[1]])
            # the ankle in IMU axes through the chain: fixed on the shank
            body = R.T @ (ankle - cam) + self._t_cam
            m = gtsam.ContactMeasurement()
            m.foot = 0
            m.bodyPoint = body
            m.touchdown = not self._was_contact
            contacts.append(m)
            self._n_contacts += 1
        self._was_contact = bool(record.in_stance)
        self._ekf.processContacts(contacts)
        e = self._ekf.estimate()
        p = np.asarray(e.x(0), dtype=float)
        Rm = np.asarray(e.rotation().matrix(), dtype=float)
        cam_w = p + Rm @ self._t_cam
        if not np.all(np.isfinite(cam_w)):
            raise EstimationError(f"gtsam_legged diverged at t={record.timestamp_s:.3f} s")
        self._path.append(np.array([cam_w[0], cam_w[2]]))
        self._ms[-1] += (time.perf_counter() - t0) * 1e3

    def report(self) -> EstimatorReport:
        ms = np.asarray(self._ms) if self._ms else np.zeros(1)
        return EstimatorReport(
            latency_ms={
                "gtsam_legged": {
                    "median": float(np.median(ms)),
                    "p95": float(np.percentile(ms, 95)),
                }
            },
            metrics={"gtsam_legged": {"contact_frames": self._n_contacts}},
        )
