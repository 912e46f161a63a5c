"""Sagittal-plane error-state Kalman filter, SP-ESKF (paper Section II.C, eq. 5-8).

Nominal state x = (p, v, a_b, g), each a 2D vector in the ground x-z plane (a_b in the IMU
x-z axes); error state dx = (dp, dv, da_b, dg), dimension 8. ``p`` is the CAMERA optical
centre, because the ICP displacements the filter fuses are camera displacements.

Per IMU sample (:meth:`SagittalEskf.propagate`):
  1. R in SO(2) maps IMU (x, z) to ground (x, z); it is the pitch of the vendor orientation
     with the heading removed (eq. 5, docs/conventions.md).
  2. optional lever-arm transfer of the specific force from the IMU to the camera centre.
  3. nominal propagation, eq. 6; error-state / covariance propagation, eq. 7.
Per displacement (:meth:`SagittalEskf.update_displacement`): Kalman correction eq. 8, error
injection into the nominal state and reset (the reset Jacobian is the identity here because
every error is additive).

Two measurement models (``FilterConfig.measurement_model``):

* ``position_pseudo`` -- the paper's eq. 8 with H = [I 0 0 0]: the ICP displacement delta
  between t0 and t1 becomes a position measurement z = p_hat(t0) + delta of p(t1), with
  noise V = cov(delta). Weakness: p_hat(t0) is itself the filter's estimate, strongly
  correlated with the state, but is treated as exact. The filter therefore believes it
  observes absolute position with ICP-level noise, its position covariance collapses to
  ~cov(delta) and it over-trusts every new displacement.
* ``stochastic_cloning`` -- the state is augmented with a copy p_c of the position at t0
  (Roumeliotis & Burdick, ICRA 2002); the displacement is the proper relative measurement
  z = p(t1) - p_c with H = [I 0 0 0 -I]. The clone carries its cross-covariance with the
  current state, so the innovation covariance is the (small) uncertainty of the IMU-predicted
  displacement plus cov(delta), and absolute-position uncertainty grows as it should.

Measured on the same synthetic data (tests/test_filter.py, ``nees_and_rmse``: 10 s of a
swinging shank walking forward, IMU noise 0.0118 m/s^2, accelerometer bias (0.05, -0.03)
m/s^2, white ICP displacement noise 3 mm per axis per frame, noise floor 0; 6 seeds):

=====================  ===================  ============================
model                  position RMSE (cm)   final-position NEES (2 dof)
=====================  ===================  ============================
position_pseudo        34.1                 6.3e5 (overconfident)
stochastic_cloning     4.7                  1.9 (consistent, expect 2)
ICP-only odometry      4.9                  --
=====================  ===================  ============================

The pseudo-measurement feeds the filter's own estimate back as an "absolute" measurement;
the spurious velocity corrections this causes integrate into drift. Inflating V (x10..x1000)
does not fix it (RMSE 0.30-0.76 m). With white per-frame ICP noise the absolute error of any
estimator is bounded below by the accumulated displacement noise, so cloning is only
marginally better than ICP alone there; its gains are consistency, gating and bridging gaps.

Landmarks (:meth:`SagittalEskf.update_landmark`): static 2D points augmented to the state
after the clone, SLAM-style, rather than fixed with an inflated noise: the landmark added at
first sight, L = p(t) + r, carries dp + dt dv + e with e the observation noise, so it is
correlated with the state, and later observations z = L - p(t) are relative measurements
that cannot shrink the position covariance below what it was at first sight (a fixed
landmark with noise "observation + own covariance", re-used every frame, would count that
uncertainty as independent each time and become overconfident). The estimator uses them for
tracked terrain corners and for the ankle during stance (vio_graph/estimator.py); the caller
marginalises a landmark (:meth:`drop_landmark`) when it is no longer needed (corners: a few
seconds after their last sight, at most 8; the ankle: when the stance ends), so the state
stays at 8 + 2 (clone) + 2 per landmark kept.

Measurement times need not coincide with IMU samples: p(t) is taken as
p + v dt + a dt^2 / 2 with dt = t - t_state and a the last ground-frame acceleration (H gains
a dt * I block on dv), exact for constant acceleration over the few ms between the last IMU
sample and the depth frame.
"""

from __future__ import annotations

import dataclasses
import math
from collections import deque
from dataclasses import dataclass
from statistics import NormalDist
from typing import NamedTuple

import numpy as np
from numpy.typing import ArrayLike, NDArray

from vio_graph.errors import EstimationError
from vio_graph.filter.config import FilterConfig
from vio_graph.filter.fast_imu import imu_kernels, sagittal_pitch
from vio_graph.filter.gating import chi2_2dof_quantile, mahalanobis2_2d
from vio_graph.filter.imu_faults import railed_axis
from vio_graph.filter.lever_arm import angular_acceleration, lever_arm_terms
from vio_graph.geometry import matrix_from_quat_wxyz, pitch_of, remove_yaw, rot_y_xz
from vio_graph.types import Displacement2D, EstimateStatus, ImuSample, LandmarkKey

#: error-state dimension of the paper's filter: (dp, dv, da_b, dg), each 2D
ERROR_STATE_DIM = 8
_CLONE_TOL_S = 1e-3  # a displacement's t0 must match the clone time to 1 ms
_CLONE = "clone"  # key of the stochastic clone among the augmented blocks (else LandmarkKey)
#: key of the slice's tilt error while one frame's level surfaces are fused (never propagated)
_TILT = "tilt"
#: key of the velocity clone across a saturated stretch (leg-chain bridge, relative form)
_VCLONE = "velocity_clone"
_NOT_LANDMARKS = (_CLONE, _TILT, _VCLONE)
_I2 = np.eye(2)
_ZERO22 = np.zeros((2, 2))  # a new clone's own noise (none)
#: variance (m^2) of a height landmark's x: a copy of the camera x that nothing observes
_FREE_X_VAR_M2 = 1.0


#: updates :attr:`SagittalEskf.innovations` keeps between two reads
_INNOVATIONS_KEPT = 10_000


@dataclass(frozen=True)
class FilterState:
    """Snapshot of an estimator (the filter or a baseline); arrays are copies.

    ``p_xz_m`` camera position (2,), ``v_xz_mps`` velocity (2,), ``accel_bias_xz_mps2`` a_b in
    IMU x-z axes (2,), ``gravity_xz_mps2`` g (2,), ``P`` the 8x8 error-state covariance
    (order dp, dv, da_b, dg; a clone block, if any, is not included).
    """

    timestamp_s: float
    p_xz_m: NDArray[np.float64]
    v_xz_mps: NDArray[np.float64]
    accel_bias_xz_mps2: NDArray[np.float64]
    gravity_xz_mps2: NDArray[np.float64]
    P: NDArray[np.float64]
    status: EstimateStatus
    n_imu: int = 0
    n_accepted: int = 0  # displacements (and position measurements) fused
    n_rejected: int = 0  # displacements that failed the chi-square gate
    n_landmark_accepted: int = 0  # landmark (corner, stance anchor) observations fused
    n_landmark_rejected: int = 0  # landmark observations that failed the gate
    n_stale: int = 0  # could not be related to the state (times too far apart)
    n_fallback: int = 0  # cloning mode only: no clone at t0, used the paper's pseudo-measurement

    @property
    def cov_position_m2(self) -> NDArray[np.float64]:
        """2x2 covariance of the position (m^2)."""
        return self.P[:2, :2].copy()


def sagittal_rotation(quat_wxyz: ArrayLike) -> NDArray[np.float64]:
    """SO(2) rotation R of eq. 5: IMU (x, z) -> ground (x, z), from R_world_imu.

    The heading is removed first (``geometry.remove_yaw``); R is rot_y(pitch) restricted to
    the x-z plane, [[cos, sin], [-sin, cos]], with pitch = ``geometry.pitch_of``.
    ``remove_yaw`` uses the ZYX decomposition, which for |pitch| > 90 deg returns the
    equivalent (yaw + pi, roll + pi) solution and would flip the pitch; such a result is
    recognised by its lateral axis pointing to world -y and turned back by pi about z, so a
    shank rotating through the vertical keeps a continuous pitch.
    """
    R_w_i = remove_yaw(matrix_from_quat_wxyz(quat_wxyz))
    if R_w_i[1, 1] < 0.0:  # body y (lateral) points to world -y: the flipped ZYX solution
        R_w_i = np.diag([-1.0, -1.0, 1.0]) @ R_w_i
    return rot_y_xz(float(pitch_of(R_w_i)))


def _f64(a: ArrayLike) -> NDArray[np.float64]:
    """``a`` as a float64 array (itself if it is one)."""
    return np.asarray(a, dtype=np.float64)


class _ImuMemo(NamedTuple):
    """What propagation needs from the previous IMU sample."""

    timestamp_s: float
    rc: float  # sagittal rotation R = [[rc, rs], [-rs, rc]]
    rs: float
    fx: float  # specific force at the camera (x, z), m/s^2, no tangential term
    fz: float
    gyro_radps: tuple[float, float, float]

    @property
    def R(self) -> NDArray[np.float64]:
        return np.array([[self.rc, self.rs], [-self.rs, self.rc]])


class SagittalEskf:
    """The paper's SP-ESKF, estimating the camera position in the sagittal plane.

    Args:
        config: filter parameters.
        imu_T_cam: 4x4 transform camera -> IMU; its translation r (m, IMU frame) is the lever
            arm used when ``config.lever_arm_compensation`` is on. ``None`` means r = 0.

    Usage: :meth:`initialise`, then :meth:`propagate` on every IMU sample and
    :meth:`update_displacement` whenever the front end yields a displacement; :attr:`state`
    at any time. Without displacements the filter keeps propagating (status IMU_ONLY).
    """

    def __init__(self, config: FilterConfig | None = None, imu_T_cam: ArrayLike | None = None):
        self.config = config if config is not None else FilterConfig()
        if imu_T_cam is None:
            self._r_imu_cam_m = np.zeros(3)
        else:
            T = np.asarray(imu_T_cam, dtype=float)
            if T.shape != (4, 4) or not np.all(np.isfinite(T)):
                raise EstimationError(f"imu_T_cam must be a finite 4x4 matrix, got {T.shape}")
            self._r_imu_cam_m = T[:3, 3].copy()
        self._r_xyz = tuple(self._r_imu_cam_m.tolist())
        self._Fx = np.eye(ERROR_STATE_DIM)  # propagate() rewrites the F_1 / F_2 entries
        p = self.config.gate_probability
        self._gate_d2 = chi2_2dof_quantile(p) if p is not None else np.inf
        # 1 dof: chi2_1(q) = (Phi^-1((1 + q) / 2))^2
        self._gate_d2_1dof = (
            float(NormalDist().inv_cdf(0.5 * (1.0 + p))) ** 2 if p is not None else np.inf
        )
        self._initialised = False
        self._t_s = 0.0
        self._x = np.zeros(ERROR_STATE_DIM)  # nominal (p, v, a_b, g)
        #: sum of the velocity corrections (m/s, x-z) the measurements made so far: what they
        #: said the IMU got wrong (read by imu_faults.SaturationScaleLearner)
        self.velocity_corrections_mps = np.zeros(2)
        self._P = np.zeros((ERROR_STATE_DIM, ERROR_STATE_DIM))
        # augmented static 2D blocks after the 8 core errors: the clone (key "clone") and
        # landmarks (LandmarkKey), in the order of ``_aug_keys``
        self._aug_keys: list[LandmarkKey | str] = []
        # (d, state time, clone time, state size, clone index, H, V) of the last
        # _displacement_setup, for update_displacement(d) on the same state
        self._setup_memo: tuple | None = None
        # (x, z) as two Python floats: the injection adds to them without an array per block
        self._aug_xz: dict[LandmarkKey | str, tuple[float, float]] = {}
        self._clone_t_s = 0.0
        self._prev: _ImuMemo | None = None
        # last ground-frame acceleration (m/s^2), for p(t); propagate() stores a tuple
        self._accel_w_mps2: NDArray[np.float64] | tuple[float, float] = np.zeros(2)
        # (t s, camera x-z m: an array, or a list of its floats on the compiled path)
        self._history: deque[tuple[float, NDArray[np.float64] | list[float]]] = deque()
        self._last_accept_s = -np.inf
        self._n_imu = self._n_acc = self._n_rej = self._n_stale = self._n_fallback = 0
        self._n_lm_acc = self._n_lm_rej = 0
        #: (y^T S^-1 y, dof, accepted) of every gated or fused update since the caller last
        #: took them (:meth:`take_innovations`): read by the health report's consistency
        #: test (vio_graph/health.py), never by the filter; the latest _INNOVATIONS_KEPT
        #: only, so a filter nobody reads stays bounded
        self.innovations: deque[tuple[float, int, bool]] = deque(maxlen=_INNOVATIONS_KEPT)
        self._prev_xa = 0.0  # extra accel sigma of the previous IMU sample (m/s^2)
        # the previous sample's saturation covariance on its clipped axes (body x-z, 2x2) and
        # pitch (rad), when imu_faults.saturation_axis_distrust applies it (None otherwise)
        self._prev_xc: tuple[NDArray[np.float64], float] | None = None
        # with imu_faults.saturation_axis_distrust_single: the railed axis (unit 3-vector) of
        # the current clipped stretch while it railed only that one, False once it railed
        # another or two, None outside a stretch
        self._stretch_axis: NDArray[np.float64] | bool | None = None
        # compiled propagation (filter/compiled_imu.py): the previous sample's memory in one
        # array instead of _prev / _prev_xa / _accel_w_mps2
        self._kernels = imu_kernels()
        self._mem = None if self._kernels is None else self._kernels.new_memory()
        # its last ground-frame acceleration, a view (what _accel_w_mps2 is when compiled)
        self._mem_aw = None
        if self._kernels is not None and self._mem is not None:
            self._mem_aw = self._mem[self._kernels.MEM_AW : self._kernels.MEM_AW + 2]
        # compiled measurement updates (filter/compiled_update.py), with the propagation
        self._update_kernels = None
        if self._kernels is not None:
            from vio_graph.filter import compiled_update

            self._update_kernels = compiled_update

    # ------------------------------------------------------------------ set-up
    def initialise(
        self,
        timestamp_s: float,
        p_xz: ArrayLike,
        v_xz: ArrayLike = (0.0, 0.0),
        accel_bias_xz: ArrayLike = (0.0, 0.0),
        gravity_xz: ArrayLike | None = None,
        P0: ArrayLike | None = None,
    ) -> None:
        """Set the nominal state at ``timestamp_s`` (s) and the error covariance.

        ``p_xz`` camera position (m), ``v_xz`` velocity (m/s), ``accel_bias_xz`` a_b (m/s^2,
        IMU x-z), ``gravity_xz`` g (m/s^2, default from the config), ``P0`` 8x8 covariance
        (default: diagonal from the config's initial sigmas).
        """
        c = self.config
        g = c.gravity_xz_mps2 if gravity_xz is None else gravity_xz
        x = np.concatenate([_vec2(p_xz), _vec2(v_xz), _vec2(accel_bias_xz), _vec2(g)])
        if P0 is None:
            sig = np.repeat(
                [
                    c.init_position_sigma_m,
                    c.init_velocity_sigma_mps,
                    c.init_accel_bias_sigma_mps2,
                    c.init_gravity_sigma_mps2,
                ],
                2,
            )
            P = np.diag(sig**2)
        else:
            P = np.array(P0, dtype=float)
            if P.shape != (ERROR_STATE_DIM, ERROR_STATE_DIM) or not np.all(np.isfinite(P)):
                raise EstimationError(f"P0 must be a finite 8x8 matrix, got {P.shape}")
        self._t_s = float(timestamp_s)
        self._x = x
        self._P = 0.5 * (P + P.T)
        self._aug_keys, self._aug_xz = [], {}
        self._setup_memo = None
        self._prev = None
        self._accel_w_mps2 = np.zeros(2)
        k = self._kernels
        if self._mem is not None and k is not None:
            self._mem[: k.MEM_PREV_XA] = 0.0  # no previous sample
            self._mem[k.MEM_AW :] = 0.0
        self._history = deque([(self._t_s, x[:2].copy())])
        self._last_accept_s = -np.inf
        self._initialised = True
        if self.config.measurement_model == "stochastic_cloning":
            self._set_clone(self._t_s)  # the first displacement starts here

    # ------------------------------------------------------------- propagation
    def propagate(self, imu: ImuSample) -> None:
        """Propagate nominal state (eq. 6) and covariance (eq. 7) to ``imu.timestamp_s``
        (:meth:`_propagate`, plus the saturation covariance of :meth:`_axis_distrust_split`)."""
        imu, now = self._axis_distrust_split(imu)
        t_before = self._t_s
        self._propagate(imu)
        self._axis_distrust_add(now, self._t_s - t_before)

    def _axis_distrust_split(
        self, imu: ImuSample
    ) -> tuple[ImuSample, tuple[NDArray[np.float64], float] | None]:
        """With ``imu_faults.saturation_axis_distrust``, a saturated sample's extra
        accelerometer variance goes on its clipped axes only (``accel_extra_cov_m2ps4``, the
        sample's axes; its x-z block here): the sample without its isotropic extra sigma and
        (that 2x2 block, its pitch). Otherwise the sample as it is and None."""
        xc = imu.accel_extra_cov_m2ps4
        fi = self.config.imu_faults
        if xc is None:
            self._stretch_axis = None
            return imu, None
        single = False
        if fi.saturation_axis_distrust_single and not imu.accel_held:
            # the stretch so far railed this one axis only (None: two, or another)
            axis = railed_axis(xc)
            prev = self._stretch_axis
            if prev is False or (
                axis is not None
                and isinstance(prev, np.ndarray)
                and abs(float(axis @ prev)) < 1.0 - 1e-9
            ):
                axis = None
            self._stretch_axis = False if axis is None else axis
            single = axis is not None
        if not (
            fi.saturation_axis_distrust or single or (imu.accel_held and fi.repaired_axis_distrust)
        ):
            return imu, None
        c = np.asarray(xc, dtype=float)[np.ix_([0, 2], [0, 2])]
        pitch = sagittal_pitch(imu.quat_wxyz)
        return dataclasses.replace(imu, accel_extra_sigma_mps2=0.0), (c, pitch)

    def _axis_distrust_add(self, now: tuple[NDArray[np.float64], float] | None, dt: float) -> None:
        """Add the clipped axes' velocity variance of this step (dt s): the step leans on
        this sample and, with the trapezoid, on the previous one (as the isotropic extra
        sigma does), so the larger of their body covariances per axis, rotated to the ground
        by their mean attitude (R_bar of eq. 7)."""
        prev, self._prev_xc = self._prev_xc, now
        if dt <= 0.0 or (now is None and prev is None):
            return
        lean = [x for x in (now, prev if self.config.integration == "trapezoid" else None) if x]
        if not lean:
            return
        C = np.maximum.reduce([x[0] for x in lean])
        rc = float(np.mean([math.cos(x[1]) for x in lean]))
        rs = float(np.mean([math.sin(x[1]) for x in lean]))
        R = np.array([[rc, rs], [-rs, rc]])  # body x-z -> ground, as in _propagate
        self._P[2:4, 2:4] += (R @ C @ R.T) * dt**2

    def _propagate(self, imu: ImuSample) -> None:
        """Propagate nominal state (eq. 6) and covariance (eq. 7) to ``imu.timestamp_s``.

        dt is the time since the previous IMU sample (or since :meth:`initialise`).
        Raises EstimationError if not initialised or if time runs backwards.

        Scalar arithmetic for the 2D vectors and a preallocated F_x (the numpy version,
        :meth:`propagate_reference`, spends ~100 us a sample on small-array overhead); the
        covariance product is the same F_x P F_x^T. Equal to the reference to rounding
        (tests/test_fast_imu.py).
        """
        if not self._initialised:
            raise EstimationError("propagate() called before initialise()")
        t = float(imu.timestamp_s)
        dt = t - self._t_s
        if dt < -1e-9 or not math.isfinite(t):
            raise EstimationError(
                f"IMU sample at {t:.6f} s is older than the state at {self._t_s:.6f} s"
            )
        if self._mem is not None:
            self._propagate_compiled(imu, t, dt)
            return
        ax, ay, az = np.asarray(imu.accel_mps2, dtype=float).tolist()
        gx, gy, gz = np.asarray(imu.gyro_radps, dtype=float).tolist()
        if not all(map(math.isfinite, (ax, ay, az, gx, gy, gz))):
            raise EstimationError(f"IMU sample at {t:.6f} s holds NaN or inf")
        pitch = sagittal_pitch(imu.quat_wxyz)
        rc, rs = math.cos(pitch), math.sin(pitch)  # R = [[rc, rs], [-rs, rc]]

        # 1. specific force at the camera centre (lever arm r, IMU frame)
        tx = tz = 0.0
        if self.config.lever_arm_compensation:
            prev = self._prev
            if prev is not None and t > prev.timestamp_s:
                h = t - prev.timestamp_s
                pgx, pgy, pgz = prev.gyro_radps
                alx, aly, alz = (gx - pgx) / h, (gy - pgy) / h, (gz - pgz) / h
            else:
                alx = aly = alz = 0.0
            rx, ry, rz = self._r_xyz
            # w x (w x r), alpha x r (geometry.cross3's products, in its order)
            cx, cy, cz = gy * rz - gz * ry, gz * rx - gx * rz, gx * ry - gy * rx
            ax += gy * cz - gz * cy
            az += gx * cy - gy * cx
            tx, tz = aly * rz - alz * ry, alx * ry - aly * rx
        fx, fz = ax, az

        # 2. ground-frame acceleration over [t - dt, t] (eq. 6: R (a_m - a_b) + g)
        x = self._x
        abx, abz, gwx, gwz = x[4:8].tolist()
        p = self._prev
        if self.config.integration == "trapezoid" and p is not None:
            b00, b01 = 0.5 * (p.rc + rc), 0.5 * (p.rs + rs)  # R_bar = [[b00, b01], [-b01, b00]]
            awx = 0.5 * ((p.rc * p.fx + p.rs * p.fz) + (rc * fx + rs * fz))
            awz = 0.5 * ((-p.rs * p.fx + p.rc * p.fz) + (-rs * fx + rc * fz))
        else:
            b00, b01 = rc, rs
            awx, awz = rc * fx + rs * fz, -rs * fx + rc * fz
        ux, uz = tx - abx, tz - abz
        awx = awx + (b00 * ux + b01 * uz) + gwx
        awz = awz + (-b01 * ux + b00 * uz) + gwz
        self._prev = _ImuMemo(t, rc, rs, fx, fz, (gx, gy, gz))
        self._accel_w_mps2 = (awx, awz)  # a tuple: read once a frame, written every sample
        self._n_imu += 1
        if dt <= 0.0:
            return

        # 3. nominal state, eq. 6
        px, pz, vx, vz = x[0:4].tolist()
        dt2 = dt**2
        x[0] = px + vx * dt + 0.5 * awx * dt2
        x[1] = pz + vz * dt + 0.5 * awz * dt2
        x[2] = vx + awx * dt
        x[3] = vz + awz * dt

        # 4. error state covariance, eq. 7: P <- F_x P F_x^T + F_i Q F_i^T; the augmented
        # blocks (clone, landmarks) are static, so F = diag(F_x, I) over the whole P (one
        # contiguous product instead of three sliced ones; the identity part is exact)
        P = self._P
        Fx = self._Fx
        if Fx.shape != P.shape:
            Fx = self._Fx = np.eye(P.shape[0])
        Fx[0, 2] = Fx[1, 3] = Fx[2, 6] = Fx[3, 7] = dt  # F_1
        Fx[2, 4], Fx[2, 5] = -b00 * dt, -b01 * dt  # F_2 = -R_bar dt
        Fx[3, 4], Fx[3, 5] = b01 * dt, -b00 * dt
        c = self.config
        var_v = (c.accel_noise_sigma_mps2 * dt) ** 2
        # distrusted samples (saturated / repaired, filter/imu_faults.py): the step leans on
        # this sample and, with the trapezoid, on the previous one
        xa_now = float(imu.accel_extra_sigma_mps2)
        xa = max(xa_now, self._prev_xa)
        self._prev_xa = xa_now
        if xa > 0.0:
            var_v += (xa * dt) ** 2
        if c.attitude_sigma_rad > 0:
            var_v += (math.sqrt(fx * fx + fz * fz) * c.attitude_sigma_rad * dt) ** 2
        var_ab = c.accel_bias_rw_mps2_per_sqrt_s**2 * dt
        P = self._P = Fx @ P @ Fx.T
        P[2, 2] += var_v
        P[3, 3] += var_v
        P[4, 4] += var_ab
        P[5, 5] += var_ab
        self._t_s = t
        self._remember(t, x[0:2])

    def _propagate_compiled(self, imu: ImuSample, t: float, dt: float) -> None:
        """The rest of :meth:`propagate` in one compiled call (filter/compiled_imu.py)."""
        c = self.config
        k, mem = self._kernels, self._mem
        assert k is not None and mem is not None
        moved = k.eskf_propagate(
            self._x,
            self._P,
            mem,
            t,
            dt,
            _f64(imu.accel_mps2),
            _f64(imu.gyro_radps),
            _f64(imu.quat_wxyz),
            self._r_imu_cam_m,
            c.lever_arm_compensation,
            c.integration == "trapezoid",
            c.accel_noise_sigma_mps2,
            float(imu.accel_extra_sigma_mps2),
            c.attitude_sigma_rad,
            c.accel_bias_rw_mps2_per_sqrt_s**2,
        )
        if moved < 0:
            raise EstimationError(f"IMU sample at {t:.6f} s holds NaN or inf")
        self._accel_w_mps2 = mem[k.MEM_AW : k.MEM_AW + 2]  # a view: updated in place
        self._n_imu += 1
        if moved:
            self._t_s = t
            self._remember(t, self._x[0:2])

    def compiled_propagation_constants(self, ws: NDArray[np.float64]) -> bool:
        """Write the constant inputs of the compiled propagation into the workspace ``ws`` of
        ``compiled_imu.sample_step`` (lever arm, switches, noise); False (nothing written)
        without the compiled kernels."""
        k = self._kernels
        if self._mem is None or k is None:
            return False
        c = self.config
        ws[k.WS_LEVER] = float(c.lever_arm_compensation)
        ws[k.WS_TRAPEZOID] = float(c.integration == "trapezoid")
        ws[k.WS_ACCEL_SIGMA] = c.accel_noise_sigma_mps2
        ws[k.WS_ATT_SIGMA] = c.attitude_sigma_rad
        ws[k.WS_VAR_AB_RATE] = c.accel_bias_rw_mps2_per_sqrt_s**2
        ws[k.WS_R_CAM : k.WS_R_CAM + 3] = self._r_imu_cam_m
        return True

    def adopt_memory(self, mem: NDArray[np.float64]) -> None:
        """Keep the compiled propagation's memory of the previous sample in ``mem`` (same
        size and values: a view of a caller's larger state array) from now on."""
        k = self._kernels
        assert k is not None and self._mem is not None and mem.shape == self._mem.shape
        old_aw = self._mem_aw
        self._mem = mem
        self._mem_aw = mem[k.MEM_AW : k.MEM_AW + 2]
        if self._accel_w_mps2 is old_aw:
            self._accel_w_mps2 = self._mem_aw

    def propagated_compiled(self, t: float, moved: int) -> None:
        """The bookkeeping of :meth:`_propagate_compiled` after a caller ran the kernel on
        ``_x``, ``_P`` and ``_mem`` itself (``compiled_imu.sample_step``; the caller checked
        :meth:`propagate`'s preconditions)."""
        if moved < 0:
            raise EstimationError(f"IMU sample at {t:.6f} s holds NaN or inf")
        assert self._mem_aw is not None
        self._accel_w_mps2 = self._mem_aw
        self._n_imu += 1
        if moved:
            self._t_s = t
            # _remember(t, p), written out (one call less a sample); the position as a
            # tuple of its floats (the history's readers take either, same values)
            h = self._history
            while h and h[-1][0] >= t:
                h.pop()
            h.append((t, self._x[0:2].tolist()))
            t_old = t - self.config.history_s
            while h[0][0] < t_old:
                h.popleft()

    def propagate_reference(self, imu: ImuSample) -> None:
        """The numpy reference of :meth:`propagate` (same state to rounding; the tests run
        both), with the same saturation covariance (:meth:`_axis_distrust_split`)."""
        imu, now = self._axis_distrust_split(imu)
        t_before = self._t_s
        self._propagate_reference(imu)
        self._axis_distrust_add(now, self._t_s - t_before)

    def _propagate_reference(self, imu: ImuSample) -> None:
        """The numpy reference of :meth:`_propagate`.

        Propagate nominal state (eq. 6) and covariance (eq. 7) to ``imu.timestamp_s``.

        dt is the time since the previous IMU sample (or since :meth:`initialise`).
        Raises EstimationError if not initialised or if time runs backwards.
        """
        if not self._initialised:
            raise EstimationError("propagate() called before initialise()")
        t = float(imu.timestamp_s)
        dt = t - self._t_s
        if dt < -1e-9 or not np.isfinite(t):
            raise EstimationError(
                f"IMU sample at {t:.6f} s is older than the state at {self._t_s:.6f} s"
            )
        accel = np.asarray(imu.accel_mps2, dtype=float)
        gyro = np.asarray(imu.gyro_radps, dtype=float)
        if not (np.all(np.isfinite(accel)) and np.all(np.isfinite(gyro))):
            raise EstimationError(f"IMU sample at {t:.6f} s holds NaN or inf")
        R = sagittal_rotation(imu.quat_wxyz)

        # 1. specific force at the camera centre (lever arm r, IMU frame)
        f3 = accel.copy()
        tangential = np.zeros(3)
        if self.config.lever_arm_compensation:
            prev = self._prev
            alpha = angular_acceleration(
                t,
                gyro,
                None if prev is None else prev.timestamp_s,
                None if prev is None else np.array(prev.gyro_radps),
            )
            centripetal, tangential = lever_arm_terms(gyro, alpha, self._r_imu_cam_m)
            f3 += centripetal
        f_xz = f3[[0, 2]]
        tangential_xz = tangential[[0, 2]]  # alpha x r

        # 2. ground-frame acceleration over [t - dt, t] (eq. 6: R (a_m - a_b) + g)
        ab, g = self._x[4:6], self._x[6:8]
        if self.config.integration == "trapezoid" and self._prev is not None:
            R_prev, f_prev = self._prev.R, np.array([self._prev.fx, self._prev.fz])
            R_bar = 0.5 * (R_prev + R)
            a_w = 0.5 * (R_prev @ f_prev + R @ f_xz)
        else:
            R_bar = R
            a_w = R @ f_xz
        a_w = a_w + R_bar @ (tangential_xz - ab) + g
        self._prev = _ImuMemo(
            t, float(R[0, 0]), float(R[0, 1]), float(f_xz[0]), float(f_xz[1]), tuple(gyro.tolist())
        )
        self._accel_w_mps2 = a_w
        self._n_imu += 1
        if dt <= 0.0:
            return

        # 3. nominal state, eq. 6
        p, v = self._x[0:2], self._x[2:4]
        self._x[0:2] = p + v * dt + 0.5 * a_w * dt**2
        self._x[2:4] = v + a_w * dt

        # 4. error state covariance, eq. 7: P <- F_x P F_x^T + F_i Q F_i^T
        Fx = np.eye(ERROR_STATE_DIM)
        Fx[0:2, 2:4] = _I2 * dt  # F_1
        Fx[2:4, 4:6] = -R_bar * dt  # F_2
        Fx[2:4, 6:8] = _I2 * dt  # F_1
        c = self.config
        var_v = (c.accel_noise_sigma_mps2 * dt) ** 2
        # distrusted samples (saturated / repaired, filter/imu_faults.py): the step leans on
        # this sample and, with the trapezoid, on the previous one
        xa = max(float(imu.accel_extra_sigma_mps2), self._prev_xa)
        self._prev_xa = float(imu.accel_extra_sigma_mps2)
        if xa > 0.0:
            var_v += (xa * dt) ** 2
        if c.attitude_sigma_rad > 0:
            var_v += float(np.linalg.norm(f_xz) * c.attitude_sigma_rad * dt) ** 2
        var_ab = c.accel_bias_rw_mps2_per_sqrt_s**2 * dt
        n = ERROR_STATE_DIM
        P = self._P
        P[:n, :n] = Fx @ P[:n, :n] @ Fx.T
        if P.shape[0] > n:  # clone block: cross terms move with F_x, the clone is static
            P[:n, n:] = Fx @ P[:n, n:]
            P[n:, :n] = P[:n, n:].T
        P[2:4, 2:4] += var_v * _I2
        P[4:6, 4:6] += var_ab * _I2
        self._t_s = t
        self._remember(t, self._x[0:2])

    # ------------------------------------------------------------- corrections
    def update_displacement(self, d: Displacement2D) -> bool:
        """Fuse a camera displacement from ``d.t0_s`` to ``d.t1_s`` (eq. 8).

        Returns True if accepted, False if rejected by the chi-square gate or as stale
        (counted in :attr:`state`). ``d.t1_s`` should be within ``max_time_mismatch_s`` of the
        last propagated IMU sample.
        """
        self._require_init()
        delta = _vec2(d.delta_xz_m)
        # H and V as the gate test of this displacement built them on this state (the same
        # arrays: the time, the clone and the state's size unchanged since), else built here
        memo, self._setup_memo = self._setup_memo, None
        if memo is not None and not (
            memo[0] is d
            and memo[1] == self._t_s
            and memo[2] == self._clone_t_s
            and memo[3] == self._P.shape[0]
            and _CLONE in self._aug_xz
            and memo[4] == self._aug_index(_CLONE)
        ):
            memo = None
        if memo is None:
            V = _measurement_v(
                d.cov_m2,
                self.config.measurement_cov_inflation,
                self.config.measurement_noise_floor_m,
            )
        else:
            V = memo[6]
        t1, t0 = float(d.t1_s), float(d.t0_s)
        tol = self.config.max_time_mismatch_s
        if abs(t1 - self._t_s) > tol or t1 < t0:
            self._n_stale += 1
            return False
        dt1 = t1 - self._t_s
        p_t1 = self._position_ahead_xz(dt1)

        cloning = self.config.measurement_model == "stochastic_cloning"
        if cloning and _CLONE in self._aug_xz and abs(self._clone_t_s - t0) <= _CLONE_TOL_S:
            # relative measurement z = p(t1) - p_c, H = [I dt*I 0 0 -I]
            H = (
                _clone_h(self._P.shape[0], dt1, self._aug_index(_CLONE))
                if memo is None
                else memo[5]
            )
            # delta - (p(t1) - clone) per axis on floats (the array expression's values)
            (d0, d1), (c0, c1) = delta.tolist(), self._aug_xz[_CLONE]
            innovation = np.array([d0 - (p_t1[0] - c0), d1 - (p_t1[1] - c1)])
        else:
            # (the memo exists only for a relative measurement on the current clone)
            assert memo is None
            # the paper: z = p_hat(t0) + delta is a position measurement, H = [I 0 0 0]
            p_t0 = self._position_at(t0)
            if p_t0 is None:
                self._n_stale += 1
                if cloning:
                    self._set_clone(t1)
                return False
            if cloning:
                self._n_fallback += 1
            H = np.zeros((2, self._P.shape[0]))
            H[:, 0:2] = _I2
            H[:, 2:4] = dt1 * _I2
            innovation = p_t0 + delta - np.array(p_t1)
        accepted = self._correct(innovation, H, V)
        if accepted:
            self._last_accept_s = t1
            self._record_correction(t1)
        if cloning:
            self._set_clone(t1)
        return accepted

    def clone_position(self, timestamp_s: float) -> None:
        """Stochastic cloning: remember p(``timestamp_s``) as the start of the next displacement.

        :meth:`update_displacement` clones at every t1 by itself; call this at depth frames
        that yielded no displacement, so that the next displacement (starting there) can be
        fused as a relative measurement. No-op in ``position_pseudo`` mode.
        """
        self._require_init()
        if self.config.measurement_model == "stochastic_cloning":
            self._set_clone(float(timestamp_s))

    def take_innovations(self) -> list[tuple[float, int, bool]]:
        """The (y^T S^-1 y, dof, accepted) of the updates since the last call, oldest first
        (and forget them): a read-out for the health report, no effect on the estimate."""
        out = list(self.innovations)
        self.innovations.clear()
        return out

    @property
    def n_gate_refusals(self) -> int:
        """Displacements refused by the chi-square gate so far."""
        return self._n_rej

    def inflate_velocity(self, sigma_mps: float, since_s: float = 0.0) -> None:
        """Add ``sigma_mps``^2 to the velocity variance (both axes): the filter no longer
        trusts its velocity, so the next measurements can correct it.

        ``since_s`` (s) > 0: the distrusted velocity error dv is taken as constant over the
        last ``since_s`` seconds, so the position carries since_s * dv and the clone
        (since_s - its age) * dv: the covariance grows by sigma^2 g g^T with g = (since_s,
        1, clone lever) per axis, which keeps the position-velocity correlation that lets a
        later velocity measurement correct the position it built up."""
        self._require_init()
        s2 = float(sigma_mps) ** 2
        since = max(float(since_s), 0.0)
        if since <= 0.0:
            self._P[2:4, 2:4] += s2 * _I2
            return
        n = self._P.shape[0]
        G = np.zeros((n, 2))
        G[0:2] = since * _I2
        G[2:4] = _I2
        if _CLONE in self._aug_xz:
            i = self._aug_index(_CLONE)
            G[i : i + 2] = max(since - (self._t_s - self._clone_t_s), 0.0) * _I2
        self._P += s2 * (G @ G.T)

    def _displacement_setup(self, d: Displacement2D) -> tuple[NDArray, NDArray, NDArray] | None:
        """The state's part of the gate test of displacement ``d``: (H, the measurement noise
        V, the predicted relative position in m), or None if ``d`` is not a relative
        measurement on the current clone."""
        self._require_init()
        t1, t0 = float(d.t1_s), float(d.t0_s)
        if (
            self.config.measurement_model != "stochastic_cloning"
            or _CLONE not in self._aug_xz
            or abs(self._clone_t_s - t0) > _CLONE_TOL_S
            or abs(t1 - self._t_s) > self.config.max_time_mismatch_s
        ):
            return None
        dt1 = t1 - self._t_s
        i = self._aug_index(_CLONE)
        H = _clone_h(self._P.shape[0], dt1, i)
        # p(t1) - clone per axis on floats (the array subtraction's values)
        (p0, p1), (c0, c1) = self._position_ahead_xz(dt1), self._aug_xz[_CLONE]
        predicted = np.array([p0 - c0, p1 - c1])
        V = _measurement_v(
            d.cov_m2, self.config.measurement_cov_inflation, self.config.measurement_noise_floor_m
        )
        # for update_displacement(d) on the same state (the frame's gate tests come first)
        self._setup_memo = (d, self._t_s, self._clone_t_s, self._P.shape[0], i, H, V)
        return H, V, predicted

    def displacement_d2(
        self,
        d: Displacement2D,
        extra_pv_cov: NDArray | None = None,
        delta_xz_m: ArrayLike | None = None,
    ) -> float | None:
        """Mahalanobis distance^2 the gate would see for displacement ``d`` (no update), with
        ``extra_pv_cov`` (4x4, on dp, dv) added to the state covariance first and
        ``delta_xz_m`` (m), if given, in place of ``d.delta_xz_m``. None if ``d`` is not a
        relative measurement on the current clone (nothing to test). The innovation
        covariance's 2x2 inverse in closed form (as :meth:`_correct`); the LAPACK solve of
        :meth:`displacement_d2_reference` agrees to rounding."""
        setup = self._displacement_setup(d)
        if setup is None:
            return None
        H, V, predicted = setup
        y = _vec2(d.delta_xz_m if delta_xz_m is None else delta_xz_m) - predicted
        P = self._P
        if extra_pv_cov is not None:
            P = P.copy()
            P[:4, :4] += np.asarray(extra_pv_cov, dtype=float)
        if self._update_kernels is not None:
            d2 = self._update_kernels.gate_d2(P, H, V, y)
            if math.isnan(d2):
                raise EstimationError("singular innovation covariance")
            return d2
        return mahalanobis2_2d(H @ P @ H.T + V, y)

    def displacement_d2_pair(
        self, d: Displacement2D, other_delta_xz_m: ArrayLike
    ) -> tuple[float, float] | None:
        """(``displacement_d2(d)``, ``displacement_d2(d, delta_xz_m=other_delta_xz_m)``) with
        the state's part (H, V, the predicted relative position) built once: the same two
        floats. None when ``d`` is not a relative measurement on the current clone."""
        setup = self._displacement_setup(d)
        if setup is None:
            return None
        H, V, predicted = setup
        y = _vec2(d.delta_xz_m) - predicted
        y_other = _vec2(other_delta_xz_m) - predicted
        P = self._P
        if self._update_kernels is not None:  # H P and S once for both (the same floats)
            d2, d2_other = self._update_kernels.gate_d2_pair(P, H, V, y, y_other)
            if math.isnan(d2) or math.isnan(d2_other):
                raise EstimationError("singular innovation covariance")
            return d2, d2_other
        S = H @ P @ H.T + V
        return mahalanobis2_2d(S, y), mahalanobis2_2d(S, y_other)

    def displacement_d2_pair_reference(
        self, d: Displacement2D, other_delta_xz_m: ArrayLike
    ) -> tuple[float, float] | None:
        """numpy reference of :meth:`displacement_d2_pair`: two
        :meth:`displacement_d2_reference` calls."""
        d2 = self.displacement_d2_reference(d)
        d2_other = self.displacement_d2_reference(d, delta_xz_m=other_delta_xz_m)
        if d2 is None or d2_other is None:
            return None
        return d2, d2_other

    def displacement_d2_reference(
        self,
        d: Displacement2D,
        extra_pv_cov: NDArray | None = None,
        delta_xz_m: ArrayLike | None = None,
    ) -> float | None:
        """numpy reference of :meth:`displacement_d2` (a LAPACK solve)."""
        if delta_xz_m is not None:
            d = Displacement2D(d.t0_s, d.t1_s, np.asarray(delta_xz_m, dtype=float), d.cov_m2)
        self._require_init()
        t1, t0 = float(d.t1_s), float(d.t0_s)
        if (
            self.config.measurement_model != "stochastic_cloning"
            or _CLONE not in self._aug_xz
            or abs(self._clone_t_s - t0) > _CLONE_TOL_S
            or abs(t1 - self._t_s) > self.config.max_time_mismatch_s
        ):
            return None
        dt1 = t1 - self._t_s
        H = _clone_h(self._P.shape[0], dt1, self._aug_index(_CLONE))
        y = _vec2(d.delta_xz_m) - (self._position_ahead(dt1) - np.array(self._aug_xz[_CLONE]))
        P = self._P.copy()
        if extra_pv_cov is not None:
            P[:4, :4] += np.asarray(extra_pv_cov, dtype=float)
        V = _measurement_v(
            d.cov_m2, self.config.measurement_cov_inflation, self.config.measurement_noise_floor_m
        )
        S = H @ P @ H.T + V
        return float(y @ np.linalg.solve(0.5 * (S + S.T), y))

    def inflate_position_velocity(self, cov_pv: NDArray) -> None:
        """Add ``cov_pv`` (4x4, on dp, dv) to the covariance: the IMU was wrong since the clone
        by that much (filter/imu_faults.velocity_fault_cov)."""
        self._require_init()
        self._P[:4, :4] += np.asarray(cov_pv, dtype=float)
        self._P = 0.5 * (self._P + self._P.T)

    @property
    def gate_d2(self) -> float:
        """Chi-square threshold of the displacement gate (inf if disabled)."""
        return self._gate_d2

    # --------------------------------------------------------------- landmarks
    def update_landmark(
        self,
        key: LandmarkKey,
        rel_xz: ArrayLike,
        cov: ArrayLike,
        timestamp_s: float | None = None,
        gate: bool = True,
    ) -> bool:
        """Fuse an observation of a static point (landmark) relative to the camera.

        ``rel_xz`` (m) is landmark minus camera at ``timestamp_s`` (ground axes), ``cov`` (m^2)
        its covariance, ``key`` its id (``LandmarkKey("corner", track_id)`` or
        ``LandmarkKey("ankle", stance_id)``; any hashable other than "clone" works). The
        landmark is part of the state (SLAM-style augmentation, like the clone): the first
        observation of a key adds L = p(t) + rel with error dp + dt dv + e, e ~ cov, so L
        carries the position uncertainty of that moment and its correlation with the state;
        every later observation is the relative measurement z = L - p(t), H = [-I -dt*I 0 0 .. I
        ..], gated like the displacements. While a landmark stays in view the position error
        therefore cannot grow beyond what it was when the landmark was first seen (plus
        observation noise). Returns True if the observation was fused (False: first sight, gated
        out, or stale). ``gate=False`` skips the chi-square gate (for observations whose
        association cannot be wrong, e.g. the stance ankle, where a drifted velocity must not
        lock the anchor out).
        """
        timing = self._measurement_time(timestamp_s)
        if timing is None:
            return False
        t, dt = timing
        rel = _vec2(rel_xz)
        V = _cov2(cov)
        if key not in self._aug_xz:
            self._augment(key, self._position_ahead(dt) + rel, dt, V)
            return False
        i = self._aug_index(key)
        H = _landmark_h(self._P.shape[0], dt, i)
        # rel - (L - p(t)) per axis on floats (the array expression's values)
        (r0, r1), (a0, a1) = rel.tolist(), self._aug_xz[key]
        p0, p1 = self._position_ahead_xz(dt)
        innovation = np.array([r0 - (a0 - p0), r1 - (a1 - p1)])
        accepted = self._correct(innovation, H, V, gate, landmark=True)
        if accepted:
            self._last_accept_s = max(self._last_accept_s, t)
            self._record_correction(t)
        return accepted

    def update_height_landmark(
        self,
        key: LandmarkKey,
        rel_z_m: float,
        var_m2: float,
        timestamp_s: float | None = None,
    ) -> bool:
        """Fuse the height of a static level surface (tread, landing, floor) relative to the
        camera: ``rel_z_m`` = surface z - camera z at ``timestamp_s`` (m, ground z), variance
        ``var_m2`` (m^2). Like :meth:`update_landmark` but z only: the first observation of
        ``key`` augments the state with the surface's height (the block's x is a free copy
        of the camera x, never observed), later ones are the scalar relative measurement
        z = L_z - p_z(t), gated at the displacement gate's probability with 1 dof. A surface
        stays in view for many frames and over several steps, and several are in view at once,
        so one is still seen when the next appears: the camera height is handed from surface
        to surface by co-observation instead of through the displacements. Returns True if fused.
        """
        timing = self._measurement_time(timestamp_s)
        if timing is None:
            return False
        t, dt = timing
        var = float(var_m2)
        if not (math.isfinite(rel_z_m) and math.isfinite(var) and var > 0.0):
            raise EstimationError("height landmark needs a finite height and variance > 0")
        if key not in self._aug_xz:
            value = self._position_ahead(dt) + np.array([0.0, float(rel_z_m)])
            self._augment(key, value, dt, np.diag([_FREE_X_VAR_M2, var]))
            return False
        i = self._aug_index(key)
        H = np.zeros((1, self._P.shape[0]))
        H[0, 1] = -1.0
        H[0, 3] = -dt
        H[0, i + 1] = 1.0
        predicted = self._aug_xz[key][1] - self._position_ahead(dt)[1]
        innovation = np.array([float(rel_z_m) - predicted])
        accepted = self._correct(innovation, H, np.array([[var]]), True, landmark=True, dof=1)
        if accepted:
            self._last_accept_s = max(self._last_accept_s, t)
            self._record_correction(t)
        return accepted

    def update_height_landmarks(
        self,
        keys: list[LandmarkKey],
        rel_z_m: list[float],
        var_m2: list[float],
        lever_m: list[float],
        tilt_var_rad2: float,
        timestamp_s: float | None = None,
    ) -> list[bool]:
        """Fuse the level surfaces of one slice together: :meth:`update_height_landmark` per
        surface, with the error the surfaces share. Each height was levelled by the slice's
        common tilt, so a tilt error tau (variance ``tilt_var_rad2``, rad^2) moves surface j's
        height by ``lever_m[j]`` x tau (its mean x from the camera, m) - the same tau for every
        surface of the slice. Fused one by one as independent heights (``var_m2`` holding the
        tilt term), a far surface and a near one would each count that error as new
        information. Here tau is a state for the length of the frame: augmented with its
        prior (independent of the rest), each surface is the scalar measurement
        rel_z_j = L_j - p_z(t) + lever_j tau + n_j (n_j ~ ``var_m2[j]``, the surface's own noise),
        gated alone (1 dof) as before; a first sight augments L_j = p_z(t) + rel_z_j -
        lever_j tau, correlated with tau; tau is marginalised after the last surface. Exact
        for the joint Gaussian (the same as one update with the covariance diag(var) +
        tilt_var lever lever^T for the surfaces that pass their gates). Returns per surface
        whether it was fused (False: first sight, gated out, or stale)."""
        n = len(keys)
        if not (len(rel_z_m) == len(var_m2) == len(lever_m) == n):
            raise EstimationError("height landmarks: keys, heights, variances, levers differ")
        timing = self._measurement_time(timestamp_s)
        if timing is None:
            return [False] * n
        t, dt = timing
        tilt_var = float(tilt_var_rad2)
        if not (math.isfinite(tilt_var) and tilt_var >= 0.0):
            raise EstimationError("the tilt variance must be finite and >= 0")
        for z, v, lv in zip(rel_z_m, var_m2, lever_m, strict=True):
            if not (math.isfinite(z) and math.isfinite(v) and v > 0.0 and math.isfinite(lv)):
                raise EstimationError("height landmark needs a finite height and variance > 0")
        # tau: a block (tau, unused) with no correlation to the state
        m = self._P.shape[0]
        P = np.zeros((m + 2, m + 2))
        P[:m, :m] = self._P
        P[m, m] = tilt_var
        P[m + 1, m + 1] = _FREE_X_VAR_M2
        self._P = P
        self._aug_keys.append(_TILT)
        self._aug_xz[_TILT] = (0.0, 0.0)
        out = []
        try:
            for key, z, v, lv in zip(keys, rel_z_m, var_m2, lever_m, strict=True):
                it = self._aug_index(_TILT)
                tau = float(self._aug_xz[_TILT][0])
                if key not in self._aug_xz:
                    size = self._P.shape[0]
                    J = np.zeros((2, size))
                    J[0, 0], J[0, 2] = 1.0, dt
                    J[1, 1], J[1, 3], J[1, it] = 1.0, dt, -float(lv)
                    value = self._position_ahead(dt) + np.array([0.0, float(z) - float(lv) * tau])
                    self._augment_rows(key, value, J, np.diag([_FREE_X_VAR_M2, float(v)]))
                    out.append(False)
                    continue
                i = self._aug_index(key)
                H = np.zeros((1, self._P.shape[0]))
                H[0, 1] = -1.0
                H[0, 3] = -dt
                H[0, i + 1] = 1.0
                H[0, it] = float(lv)
                predicted = self._aug_xz[key][1] - self._position_ahead(dt)[1] + float(lv) * tau
                innovation = np.array([float(z) - predicted])
                ok = self._correct(innovation, H, np.array([[float(v)]]), True, True, dof=1)
                if ok:
                    self._last_accept_s = max(self._last_accept_s, t)
                    self._record_correction(t)
                out.append(ok)
        finally:
            self._marginalise(_TILT)
        return out

    def update_velocity(
        self,
        v_xz_mps: ArrayLike,
        cov: ArrayLike,
        timestamp_s: float | None = None,
        gate: bool = True,
    ) -> bool:
        """Fuse a direct observation of the camera velocity (m/s, ground axes) at
        ``timestamp_s`` with covariance ``cov`` ((m/s)^2), e.g. the still ankle in stance seen
        through the turning shank (v_cam = -pitch rate x lever). The velocity there is
        v + a dt (H = [0 I 0 ..]). Unlike the stance anchor, which needs two frames of one
        stance, this informs the velocity from the first stance frame on: a fast gait's
        foot-flat lasts only a few frames. Returns True if fused (False: gated out or stale).
        """
        timing = self._measurement_time(timestamp_s)
        if timing is None:
            return False
        t, dt = timing
        H = np.zeros((2, self._P.shape[0]))
        H[:, 2:4] = _I2
        predicted = self._x[2:4] + dt * np.asarray(self._accel_w_mps2)
        innovation = _vec2(v_xz_mps) - predicted
        accepted = self._correct(innovation, H, _cov2(cov), gate, landmark=True)
        if accepted:
            self._record_correction(t)
        return accepted

    def clone_velocity(self) -> None:
        """Augment the state with a copy of the current velocity (m/s), replacing any previous
        one: the start of a velocity change that :meth:`update_velocity_change` observes. The
        copy is static (propagation leaves it) and shares the velocity's error, so its
        correlation with the position and the rest is kept."""
        self._require_init()
        self._marginalise(_VCLONE)
        J = np.zeros((2, self._P.shape[0]))
        J[:, 2:4] = _I2
        self._augment_rows(_VCLONE, self._x[2:4], J, _ZERO22)

    @property
    def has_velocity_clone(self) -> bool:
        """True while a velocity copy (:meth:`clone_velocity`) is in the state."""
        return _VCLONE in self._aug_xz

    def drop_velocity_clone(self) -> None:
        """Marginalise the velocity copy out of the state (no-op without one)."""
        self._marginalise(_VCLONE)

    def update_velocity_change(
        self, dv_xz_mps: ArrayLike, cov: ArrayLike, gate: bool = True
    ) -> bool:
        """Fuse an observation of the velocity change (m/s, ground x-z) from the copy of
        :meth:`clone_velocity` to now, covariance ``cov`` ((m/s)^2): z = v - v_clone,
        H = [0 I 0 .. -I]. Unlike an observation of the velocity itself built from the
        filter's own velocity at the copy's time, it does not count that velocity's error
        as new information, so the position-velocity correlation the error carries stays for
        the next absolute measurement. The copy is dropped afterwards. Returns True if fused;
        False if gated out or there is no copy."""
        self._require_init()
        if _VCLONE not in self._aug_xz:
            return False
        i = self._aug_index(_VCLONE)
        H = np.zeros((2, self._P.shape[0]))
        H[:, 2:4] = _I2
        H[:, i : i + 2] = -_I2
        innovation = _vec2(dv_xz_mps) - (self._x[2:4] - self._aug_xz[_VCLONE])
        accepted = self._correct(innovation, H, _cov2(cov), gate, landmark=True)
        if accepted:
            self._record_correction(self._t_s)
        self._marginalise(_VCLONE)
        return accepted

    def _measurement_time(self, timestamp_s: float | None) -> tuple[float, float] | None:
        """(t, t - t_state) of a measurement at ``timestamp_s`` (None: now), or None (counted
        as stale) if it is further than ``max_time_mismatch_s`` from the state."""
        self._require_init()
        t = self._t_s if timestamp_s is None else float(timestamp_s)
        dt = t - self._t_s
        if abs(dt) > self.config.max_time_mismatch_s:
            self._n_stale += 1
            return None
        return t, dt

    def drop_landmark(self, key: LandmarkKey) -> None:
        """Forget landmark ``key`` (marginalise it out of the state); no-op if unknown."""
        if key in _NOT_LANDMARKS:
            raise EstimationError(f"{key!r} is not a landmark")
        self._marginalise(key)

    @property
    def landmark_keys(self) -> tuple[LandmarkKey, ...]:
        """Keys of the landmarks currently in the state."""
        return tuple(k for k in self._aug_keys if k not in _NOT_LANDMARKS)  # type: ignore[misc]

    def landmark_keys_of_kind(self, kind: str) -> list[LandmarkKey]:
        """Keys of the landmarks of ``kind`` ("corner", "ankle", "level") in the state, in
        its order (:attr:`landmark_keys` filtered, without building the whole tuple)."""
        return [k for k in self._aug_keys if isinstance(k, LandmarkKey) and k.kind == kind]

    def has_landmark(self, key: LandmarkKey) -> bool:
        """True if landmark ``key`` is in the state (``key in landmark_keys``, one lookup)."""
        return key in self._aug_xz and key not in _NOT_LANDMARKS

    def landmark_xz(self, key: LandmarkKey) -> NDArray[np.float64]:
        """Current estimate (m) of landmark ``key``."""
        if key in _NOT_LANDMARKS or key not in self._aug_xz:
            raise EstimationError(f"unknown landmark {key!r}")
        return np.array(self._aug_xz[key])

    def landmark_z(self, key: LandmarkKey) -> float:
        """Current height estimate (m) of landmark ``key``: ``landmark_xz(key)[1]`` as a
        float, without the array."""
        if key in _NOT_LANDMARKS or key not in self._aug_xz:
            raise EstimationError(f"unknown landmark {key!r}")
        return self._aug_xz[key][1]

    # ------------------------------------------------------------------- state
    def position_velocity(self) -> tuple[float, NDArray[np.float64], NDArray[np.float64]]:
        """(time s, camera position m, velocity m/s) of the current estimate: the same values
        as :attr:`state`'s, without its snapshot of the covariance and the counters."""
        return self._t_s, self._x[0:2].copy(), self._x[2:4].copy()

    @property
    def status(self) -> EstimateStatus:
        """:attr:`state`'s status without the snapshot: FUSED while a measurement was accepted
        within ``fused_timeout_s``, else IMU_ONLY (INITIALISING before :meth:`initialise`)."""
        if not self._initialised:
            return EstimateStatus.INITIALISING
        if self._t_s - self._last_accept_s <= self.config.fused_timeout_s:
            return EstimateStatus.FUSED
        return EstimateStatus.IMU_ONLY

    def cov_position_m2(self) -> NDArray[np.float64]:
        """2x2 covariance of the position (m^2), a copy: :attr:`state`'s without the snapshot."""
        return self._P[:2, :2].copy()

    def cov_velocity_m2ps2(self) -> NDArray[np.float64]:
        """2x2 covariance of the velocity ((m/s)^2), a copy."""
        return self._P[2:4, 2:4].copy()

    def variance(self, i: int) -> float:
        """Variance of error-state component ``i`` (0-7: dp, dv, da_b, dg; x then z)."""
        if not 0 <= i < ERROR_STATE_DIM:
            raise EstimationError(f"error-state index {i} outside 0..{ERROR_STATE_DIM - 1}")
        return float(self._P[i, i])

    @property
    def state(self) -> FilterState:
        """Frozen snapshot of the current estimate."""
        n = ERROR_STATE_DIM
        return FilterState(
            timestamp_s=self._t_s,
            p_xz_m=self._x[0:2].copy(),
            v_xz_mps=self._x[2:4].copy(),
            accel_bias_xz_mps2=self._x[4:6].copy(),
            gravity_xz_mps2=self._x[6:8].copy(),
            P=self._P[:n, :n].copy(),
            status=self.status,
            n_imu=self._n_imu,
            n_accepted=self._n_acc,
            n_rejected=self._n_rej,
            n_landmark_accepted=self._n_lm_acc,
            n_landmark_rejected=self._n_lm_rej,
            n_stale=self._n_stale,
            n_fallback=self._n_fallback,
        )

    # ----------------------------------------------------------------- helpers
    def _correct(
        self,
        innovation: NDArray,
        H: NDArray,
        V: NDArray,
        gate: bool = True,
        landmark: bool = False,
        dof: int = 2,
    ) -> bool:
        """Gate, Kalman gain, injection and reset (eq. 8). Returns False if gated out.
        ``landmark`` says which counters the outcome goes to; ``dof`` is the measurement's
        dimension for the gate (2, or 1 for a height).

        Every measurement here is 1- or 2-dimensional, so S is inverted in closed form and
        the covariance update is P - K H P, which equals the Joseph form of
        :meth:`_correct_reference` (K = P H^T S^-1 makes its K S K^T and cross terms cancel);
        the two differ by rounding only (tests/test_filter_fastpaths.py). This replaces two
        LAPACK solves and four n x n products (n = 8 + 2 per clone / landmark) by small ones:
        numpy's per-call overhead, not the flops, is what a 2-row update costs."""
        m = H.shape[0]
        if m > 2:
            return self._correct_reference(innovation, H, V, gate, landmark, dof)
        if self._update_kernels is not None:
            return self._correct_compiled(innovation, H, V, gate, landmark, dof)
        P = self._P
        HP = H @ P
        S = HP @ H.T + V
        if m == 2:
            s00, s11 = float(S[0, 0]), float(S[1, 1])
            s01 = 0.5 * (float(S[0, 1]) + float(S[1, 0]))
            det = s00 * s11 - s01 * s01
            if det == 0.0 or not math.isfinite(det):
                raise EstimationError("singular innovation covariance")
            y0, y1 = float(innovation[0]), float(innovation[1])
            # S^-1 = [[s11, -s01], [-s01, s00]] / det
            u0, u1 = (s11 * y0 - s01 * y1) / det, (s00 * y1 - s01 * y0) / det
            d2 = y0 * u0 + y1 * u1
            S_inv = np.array([[s11 / det, -s01 / det], [-s01 / det, s00 / det]])
        else:
            s00 = float(S[0, 0])
            if s00 == 0.0 or not math.isfinite(s00):
                raise EstimationError("singular innovation covariance")
            y0 = float(innovation[0])
            d2 = y0 * y0 / s00
            S_inv = np.array([[1.0 / s00]])
        gate_d2 = self._gate_d2 if dof == 2 else self._gate_d2_1dof
        if gate and d2 > gate_d2:
            return self._counted(False, landmark, d2, m)
        K = (S_inv @ HP).T  # P H^T S^-1 (P, S symmetric)
        dx = K @ innovation
        P = P - K @ HP
        self._P = 0.5 * (P + P.T)
        self._inject(dx)
        return self._counted(True, landmark, d2, m)

    def _correct_compiled(
        self,
        innovation: NDArray,
        H: NDArray,
        V: NDArray,
        gate: bool,
        landmark: bool,
        dof: int,
    ) -> bool:
        """:meth:`_correct` in one compiled call (``compiled_update.correct``: the same
        formulas, products summed in index order; equal to rounding)."""
        k = self._update_kernels
        assert k is not None
        gate_d2 = self._gate_d2 if dof == 2 else self._gate_d2_1dof
        status, d2, P, dx = k.correct(
            self._P,
            np.ascontiguousarray(H, dtype=float),
            np.ascontiguousarray(V, dtype=float),
            np.ascontiguousarray(innovation, dtype=float),
            bool(gate),
            float(gate_d2),
        )
        if status == k.SINGULAR:
            raise EstimationError("singular innovation covariance")
        m = H.shape[0]
        if status == k.GATED:
            return self._counted(False, landmark, float(d2), m)
        self._P = P
        self._inject(dx)
        return self._counted(True, landmark, float(d2), m)

    def _counted(self, accepted: bool, landmark: bool, d2: float, m: int) -> bool:
        """Count an update's outcome (landmark or displacement counters) and note its
        normalised innovation squared ``d2`` with ``m`` degrees of freedom in
        :attr:`innovations`; returns ``accepted``."""
        self.innovations.append((d2, m, accepted))
        if landmark:
            if accepted:
                self._n_lm_acc += 1
            else:
                self._n_lm_rej += 1
        elif accepted:
            self._n_acc += 1
        else:
            self._n_rej += 1
        return accepted

    def _inject(self, dx: NDArray[np.float64]) -> None:
        """Add the error state ``dx`` to the nominal state and the augmented blocks; all
        errors are additive, so the reset dx <- 0 leaves P unchanged (reset Jacobian G = I)."""
        n = ERROR_STATE_DIM
        self._x = self._x + dx[:n]
        self.velocity_corrections_mps = self.velocity_corrections_mps + dx[2:4]
        aug = self._aug_xz
        d = dx.tolist()  # (the same float additions as on arrays, one conversion)
        for j, key in enumerate(self._aug_keys):
            i = n + 2 * j
            a0, a1 = aug[key]
            aug[key] = (a0 + d[i], a1 + d[i + 1])

    def _correct_reference(
        self,
        innovation: NDArray,
        H: NDArray,
        V: NDArray,
        gate: bool = True,
        landmark: bool = False,
        dof: int = 2,
    ) -> bool:
        """numpy reference of :meth:`_correct` (LAPACK solves, the Joseph form); any number
        of measurement rows."""
        P = self._P
        S = H @ P @ H.T + V
        S = 0.5 * (S + S.T)
        try:
            S_inv_y = np.linalg.solve(S, innovation)
        except np.linalg.LinAlgError as exc:
            raise EstimationError(f"singular innovation covariance: {exc}") from None
        gate_d2 = self._gate_d2 if dof == 2 else self._gate_d2_1dof
        d2 = float(innovation @ S_inv_y)
        m = H.shape[0]
        if gate and d2 > gate_d2:
            return self._counted(False, landmark, d2, m)
        K = np.linalg.solve(S, H @ P).T  # K = P H^T S^-1 (S, P symmetric)
        dx = K @ innovation
        # Joseph form of P <- (I - K H) P: same value, stays symmetric positive definite
        IKH = np.eye(P.shape[0]) - K @ H
        self._P = IKH @ P @ IKH.T + K @ V @ K.T
        self._P = 0.5 * (self._P + self._P.T)
        # inject the error state into the nominal state; all errors are additive, so the
        # reset dx <- 0 leaves P unchanged (reset Jacobian G = I)
        n = ERROR_STATE_DIM
        self._x = self._x + dx[:n]
        self.velocity_corrections_mps = self.velocity_corrections_mps + dx[2:4]
        for j, key in enumerate(self._aug_keys):
            i = n + 2 * j
            a0, a1 = self._aug_xz[key]
            self._aug_xz[key] = (a0 + float(dx[i]), a1 + float(dx[i + 1]))
        return self._counted(True, landmark, d2, m)

    def _set_clone(self, t_s: float) -> None:
        """Augment the state with p(t_s) = p + v (t_s - t), replacing any previous clone."""
        k = self._update_kernels
        if k is not None:  # compiled: the removal and the augmentation in one call
            i = self._aug_index(_CLONE) if _CLONE in self._aug_xz else -1
            dt = t_s - self._t_s
            self._P = k.recloned(self._P, i, float(dt), _ZERO22)
            if i >= 0:
                self._aug_keys.remove(_CLONE)
            self._aug_keys.append(_CLONE)
            self._aug_xz.pop(_CLONE, None)  # (re-inserted last, as the removal and append)
            self._aug_xz[_CLONE] = self._position_ahead_xz(dt)
            self._clone_t_s = t_s
            return
        self._marginalise(_CLONE)
        dt = t_s - self._t_s
        self._augment(_CLONE, self._position_ahead(dt), dt, _ZERO22)
        self._clone_t_s = t_s

    def _aug_index(self, key: LandmarkKey | str) -> int:
        """First row of the augmented block ``key`` in P."""
        return ERROR_STATE_DIM + 2 * self._aug_keys.index(key)

    def _marginalise(self, key: LandmarkKey | str) -> None:
        """Drop the augmented block ``key`` (if present): delete its rows and columns of P."""
        if key not in self._aug_xz:
            return
        i = self._aug_index(key)
        if self._update_kernels is not None:
            self._P = self._update_kernels.without_block(self._P, i)
        else:
            # rows and columns 0:i and i+2: copied (take: the np.ix_ gather's values and C
            # order without its index-grid overhead)
            keep = np.concatenate((np.arange(i), np.arange(i + 2, self._P.shape[0])))
            self._P = self._P.take(keep, 0).take(keep, 1)
        self._aug_keys.remove(key)
        del self._aug_xz[key]

    def _augment(
        self,
        key: LandmarkKey | str,
        value_xz: NDArray[np.float64],
        dt_s: float,
        extra_cov: NDArray,
    ) -> None:
        """Append a static block x_new = p(t + dt) + e with error dp + dt dv + e, e ~ extra_cov
        independent of the state (the block's cross-covariance follows from J P J^T)."""
        # J P J^T block by block, J = [[I], [I dt*I 0 ..]]: the old P, its new rows
        # A = P[0:2] + dt P[2:4] (and their transpose), and the new block A J_b^T + extra
        if self._update_kernels is not None:  # the same operations in one compiled call
            self._P = self._update_kernels.augmented(
                self._P, float(dt_s), np.asarray(extra_cov, dtype=float)
            )
            self._aug_keys.append(key)
            self._aug_xz[key] = _pair(value_xz)
            return
        P = self._P
        P = 0.5 * (P + P.T)  # (propagation leaves it symmetric only to rounding)
        m = P.shape[0]
        A = P[0:2] + dt_s * P[2:4]
        Q = np.empty((m + 2, m + 2))
        Q[:m, :m] = P
        Q[m:, :m] = A
        Q[:m, m:] = A.T
        B = A[:, 0:2] + dt_s * A[:, 2:4] + extra_cov
        Q[m:, m:] = 0.5 * (B + B.T)
        self._P = Q
        self._aug_keys.append(key)
        self._aug_xz[key] = _pair(value_xz)

    def _augment_rows(
        self,
        key: LandmarkKey | str,
        value_xz: NDArray[np.float64],
        J: NDArray[np.float64],
        extra_cov: NDArray,
    ) -> None:
        """Append a static block whose error is J dx + e (J: 2 x n over the current error
        state, e ~ extra_cov independent of it): rows J P, block J P J^T + extra."""
        P = self._P
        P = 0.5 * (P + P.T)
        m = P.shape[0]
        A = J @ P
        Q = np.empty((m + 2, m + 2))
        Q[:m, :m] = P
        Q[m:, :m] = A
        Q[:m, m:] = A.T
        B = A @ J.T + extra_cov
        Q[m:, m:] = 0.5 * (B + B.T)
        self._P = Q
        self._aug_keys.append(key)
        self._aug_xz[key] = _pair(value_xz)

    def _augment_reference(
        self,
        key: LandmarkKey | str,
        value_xz: NDArray[np.float64],
        dt_s: float,
        extra_cov: NDArray,
    ) -> None:
        """numpy reference of :meth:`_augment` (the full J P J^T)."""
        m = self._P.shape[0]
        J = np.zeros((m + 2, m))
        J[:m, :m] = np.eye(m)
        J[m:, 0:2] = _I2
        J[m:, 2:4] = dt_s * _I2
        P = J @ self._P @ J.T
        P[m:, m:] += extra_cov
        self._P = 0.5 * (P + P.T)
        self._aug_keys.append(key)
        self._aug_xz[key] = _pair(value_xz)

    def _position_ahead(self, dt_s: float) -> NDArray[np.float64]:
        """p(t + dt) = p + v dt + a dt^2 / 2 with the last ground-frame acceleration a (the
        Jacobian keeps only the I and dt*I blocks: the a-term is second order in dt)."""
        return np.array(self._position_ahead_xz(dt_s))

    def _position_ahead_xz(self, dt_s: float) -> tuple[float, float]:
        """:meth:`_position_ahead` as two Python floats (the same values)."""
        # on Python floats (a frame asks ~10 times): the same products and sums per axis as
        # ``x[0:2] + dt * x[2:4] + (0.5 dt^2) a`` on arrays, without five small-array calls
        x0, x1, v0, v1 = self._x[:4].tolist()
        a0, a1 = self._accel_w_mps2
        h = 0.5 * dt_s**2
        return x0 + dt_s * v0 + h * float(a0), x1 + dt_s * v1 + h * float(a1)

    def _remember(self, t_s: float, p_xz: NDArray, owned: bool = False) -> None:
        """Append (t_s, p) to the history, dropping entries at or after t_s (keeps it sorted).
        ``owned``: ``p_xz`` is a new array no one else holds (kept as is, not copied)."""
        history = self._history
        while history and history[-1][0] >= t_s:
            history.pop()
        history.append((t_s, p_xz if owned else p_xz.copy()))
        oldest = t_s - self.config.history_s
        while history and history[0][0] < oldest:
            history.popleft()

    def _record_correction(self, t_s: float) -> None:
        """Replace history entries from ``t_s`` on with the corrected estimate."""
        self._remember(t_s, self._position_ahead(t_s - self._t_s), owned=True)
        if self._t_s > t_s:
            self._remember(self._t_s, self._x[0:2])

    def _position_at(self, t_s: float) -> NDArray[np.float64] | None:
        """The filter's past position estimate at ``t_s`` (linear interpolation) or None."""
        if not self._history:
            return None
        times = np.array([h[0] for h in self._history])
        xz = np.array([h[1] for h in self._history])
        tol = self.config.max_time_mismatch_s
        if t_s < times[0] - tol or t_s > times[-1] + tol:
            return None
        return np.array([np.interp(t_s, times, xz[:, 0]), np.interp(t_s, times, xz[:, 1])])

    def _require_init(self) -> None:
        if not self._initialised:
            raise EstimationError("the filter is not initialised; call initialise() first")


def _pair(v: ArrayLike) -> tuple[float, float]:
    """An (x, z) value as two Python floats (an augmented block's nominal value)."""
    a = np.asarray(v, dtype=float).reshape(-1)
    return float(a[0]), float(a[1])


def _vec2(v: ArrayLike) -> NDArray[np.float64]:
    """A finite (x, z) vector as a new float array (the finiteness test on Python floats:
    np.all(np.isfinite(.)) costs more than the rest of a small update)."""
    a = np.array(v, dtype=float).reshape(-1)
    if a.shape != (2,) or not (math.isfinite(a[0]) and math.isfinite(a[1])):
        raise EstimationError(f"expected a finite (x, z) vector, got {np.asarray(v)!r}")
    return a


def _cov2_floats(c: ArrayLike) -> tuple[float, float, float, float]:
    """A finite 2x2 covariance, symmetrised, as its (00, 01, 10, 11) entries: the same
    0.5 (a_ij + a_ji) per entry as :func:`_cov2`, on Python floats."""
    a = np.asarray(c, dtype=float)
    if a.shape != (2, 2):
        raise EstimationError(f"expected a finite 2x2 covariance, got shape {a.shape}")
    (a00, a01), (a10, a11) = a.tolist()
    if not (
        math.isfinite(a00) and math.isfinite(a01) and math.isfinite(a10) and math.isfinite(a11)
    ):
        raise EstimationError(f"expected a finite 2x2 covariance, got shape {a.shape}")
    return 0.5 * (a00 + a00), 0.5 * (a01 + a10), 0.5 * (a10 + a01), 0.5 * (a11 + a11)


def _cov2(c: ArrayLike) -> NDArray[np.float64]:
    """A finite 2x2 covariance, symmetrised (new array)."""
    s00, s01, s10, s11 = _cov2_floats(c)
    return np.array([[s00, s01], [s10, s11]])


def _measurement_v(c: ArrayLike, inflation: float, floor_m: float) -> NDArray[np.float64]:
    """A displacement's measurement noise ``inflation * _cov2(c) + floor_m**2 * I`` (2x2),
    entry by entry on Python floats: the same products and sums as on arrays (the off-diagonal
    floor term is floor^2 * 0.0, added as numpy adds it)."""
    s00, s01, s10, s11 = _cov2_floats(c)
    f2 = floor_m**2
    z = f2 * 0.0
    return np.array(
        [
            [inflation * s00 + f2, inflation * s01 + z],
            [inflation * s10 + z, inflation * s11 + f2],
        ]
    )


def _landmark_h(n: int, dt: float, i: int) -> NDArray[np.float64]:
    """A landmark observation's H (2 x n): [-I, -dt I, 0.., I at columns i, i + 1, 0..],
    entry by entry the values of ``H[:, 0:2] = -I; H[:, 2:4] = -dt I; H[:, i:i+2] = I`` on
    zeros (with the signed zeros -0.0 and -dt * 0.0 the array products leave)."""
    H = np.zeros((2, n))
    row0, row1 = H[0], H[1]
    row0[0] = -1.0
    row1[1] = -1.0
    row0[1] = -0.0
    row1[0] = -0.0
    ndt = -dt
    row0[2] = ndt
    row1[3] = ndt
    z = ndt * 0.0
    row0[3] = z
    row1[2] = z
    row0[i] = 1.0
    row1[i + 1] = 1.0
    row0[i + 1] = 0.0
    row1[i] = 0.0
    return H


def _clone_h(n: int, dt1: float, i: int) -> NDArray[np.float64]:
    """The relative displacement's H (2 x n): [I, dt1 I, 0.., -I at columns i, i + 1, 0..],
    entry by entry the values of ``H[:, 0:2] = I; H[:, 2:4] = dt1 I; H[:, i:i+2] = -I`` on
    zeros (with the signed zeros dt1 * 0.0 and -0.0 the array products leave)."""
    H = np.zeros((2, n))
    row0, row1 = H[0], H[1]
    row0[0] = 1.0
    row1[1] = 1.0
    row0[2] = dt1
    row1[3] = dt1
    z = dt1 * 0.0
    row0[3] = z
    row1[2] = z
    row0[i] = -1.0
    row1[i + 1] = -1.0
    row0[i + 1] = -0.0
    row1[i] = -0.0
    return H
