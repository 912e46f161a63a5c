"""IMU samples the estimator should not trust: saturation, outliers, vision arbitration.

Three mechanisms, none of them a fixed threshold on the raw signal (a causal median spike
filter was tried and removed: heel-strike transients of the true specific force look like
spikes to any such threshold):

* **Saturation** (:class:`ImuFaultMonitor`): an axis at or beyond ``saturation_margin`` of the
  range declared in the recording's metadata (``imu.accel_range_mps2``,
  ``imu.gyro_range_radps``) is clipped; its true value lies beyond the rail by an unknown
  amount, on the rail's side. With a half-normal prior of sigma s = ``saturation_sigma_range``
  x range on that excess, its conditional mean is s sqrt(2/pi) and its sigma
  s sqrt(1 - 2/pi): the clipped axis is moved beyond the rail by the mean (the clipped value
  alone loses the whole excess, always in the same direction, and the velocity drifts by
  metres per second over a heel strike), and the sample carries the sigma as an extra
  uncertainty, which the filter adds to its velocity process noise and the smoothers to the
  preintegration covariance, so the next visual displacements and the stance anchor correct
  what the prior gets wrong. The excesses of one clipped stretch are one pulse, so their
  errors add up, not average out: the k-th sample of a stretch carries sqrt(2k - 1) times
  the sigma (``saturation_correlated``), which makes the variance of a stretch of n samples
  n^2 times one sample's. (A bridge by the rigid-shank kinematics, knee force held from the
  last good sample plus the gyro's rotational terms, was tried: the knee's own deceleration
  dominates at heel strike and rises within a sample, so it bridged almost nothing; the
  leg chain with the hip's velocity held does bridge a stretch, filter/leg_bridge.py.) How far
  the signal went beyond the rail depends on the gait and the axis, so the scale per IMU axis
  is learnt from what the filter's measurements later say each stretch lost
  (:class:`SaturationScaleLearner`); the configured scale is its prior. The learnt scale
  sets the mean only: with ``saturation_sigma_prior_floor`` the sigma is that of the larger
  of the learnt and the configured scale, since past stretches' mean loss says little about
  how far the next one goes (a learnt x scale of 0.02 m/s^2 on the simulated descent made a
  stretch that lost 0.26 m/s look certain, and the stance's correction went to the position
  the wrong way).
* **Gyro outliers** (:class:`ImuFaultMonitor`): the IMU gives two views of the rotation, the
  gyro and the vendor orientation. Over one sample period the mean rate w_k from
  consecutive orientations predicts the gyro, g_k ~ 2 w_k - g_{k-1}; a chi-square test (3
  dof) on the residual flags a sample that disagrees and replaces it with that prediction
  (extra sigma = the test sigma). A heel strike turns the orientation as much as the gyro,
  so it passes. The sample is then taken as corrupt as a whole (a bus error or a shock hits
  the packet): its accelerometer is replaced by the last trusted one, with an extra sigma of
  ``held_accel_sigma_mps2``, and marked ``accel_held``: the smoothers, which see the next
  sample before they preintegrate, replace it by the interpolation between its trusted
  neighbours (vio_graph/smoother/graph.py; on the simulated gaits 3x closer to the true
  specific force than the held value). An accelerometer-only outlier is left to vision
  (below). The test's variance follows the sensor, not the MTi-1 at 100 Hz it was set on:
  (1) both noise sources of the residual, the gyro's white noise and the sample-to-sample
  change of the orientation's error, are white per sample, so the variance grows with the
  rate: ``gyro_ahrs_sigma_radps`` holds at 100 Hz and a recording at rate r (metadata
  ``imu.rate_hz``) is tested with sigma sqrt(r / 100 Hz); (2) that sigma is a floor under
  the variance the IMU's residuals actually show (a running mean of |r|^2 / 3 over
  ``gyro_ahrs_learn_time_s``, each statistic clipped at the gate): a consumer IMU's host-side
  orientation is several times noisier; (3) a repaired gyro is a prediction with the test's
  sigma and the next prediction is built on it, so after n repairs in a row the next test's
  variance is (1 + n) times the sigma^2. Without (1)-(3) one false alarm locked the test in
  (each repair's error fed the next prediction with its sign flipped): 60-90 % of the
  samples of a 200 Hz trial or a consumer IMU were repaired and the filter was off by metres
  (sweep imu_200hz, imu_consumer).
* **Accelerometer outliers** (:func:`velocity_fault_cov`, used by the estimator): vision
  arbitrates. When the filter's chi-square gate refuses a displacement, the hypothesis "one
  corrupted IMU sample in this interval" -- a velocity jump of sigma
  ``velocity_fault_sigma_mps`` at mid-interval, which moves the position by half the
  interval times the jump -- is tested with the same gate. If vision agrees with it, the
  filter's position/velocity covariance is widened by that jump and the displacement is
  fused; if not (a wrong association shifts a displacement by a whole stair step), the
  refusal stands.
"""

from __future__ import annotations

import dataclasses
import math
from types import ModuleType

import numpy as np
from numpy.typing import ArrayLike, NDArray

from vio_graph.filter.config import PAPER_IMU_RATE_HZ, ImuFaultConfig
from vio_graph.filter.fast_imu import (
    Mat3,
    as_f64,
    imu_kernels,
    mat3_rotvec,
    mat3_tmul,
    quat_matrix,
)
from vio_graph.filter.gating import chi2_quantile
from vio_graph.geometry import matrix_from_quat_wxyz
from vio_graph.types import ImuSample

_HALF_NORMAL_MEAN = float(np.sqrt(2.0 / np.pi))  # mean of |N(0, 1)|
_HALF_NORMAL_SD = float(np.sqrt(1.0 - 2.0 / np.pi))  # its standard deviation


def _as_mat3(R: NDArray[np.float64]) -> Mat3:
    """A (3, 3) array as a row-major tuple."""
    m0, m1, m2, m3, m4, m5, m6, m7, m8 = np.asarray(R, dtype=float).ravel().tolist()
    return (m0, m1, m2, m3, m4, m5, m6, m7, m8)


class ImuFaultMonitor:
    """Marks saturated samples and repairs gyro outliers, sample by sample (no look-ahead).

    Feed the samples in the IMU's own axes (before any mounting rotation), in time order.
    """

    def __init__(
        self,
        config: ImuFaultConfig,
        accel_range_mps2: float | None,
        gyro_range_radps: float | None,
        imu_rate_hz: float | None = None,
    ) -> None:
        self.config = config
        #: the gyro test's sigma at this IMU's rate (rad/s per axis; the configured one at
        #: 100 Hz or an unknown rate) and its variance for the next sample (grows along a run
        #: of repairs: module docstring)
        rate_scale = 1.0 if imu_rate_hz is None else math.sqrt(imu_rate_hz / PAPER_IMU_RATE_HZ)
        self.gyro_sigma_radps = config.gyro_ahrs_sigma_radps * rate_scale
        self._gyro_sigma = self.gyro_sigma_radps  # for the next sample
        self._gyro_sigma2 = self._gyro_sigma**2
        self._repair_run = 0  # repairs in a row up to the previous sample
        # the residual's variance per axis learnt from the samples that pass (rad^2/s^2),
        # starting at the configured one, and the weight of each sample (one nominal
        # period over the learning time constant; 0: not learnt)
        self._floor_var = self._gyro_sigma2
        self._learnt_var = self._floor_var
        self._above_floor = False
        learn_s = config.gyro_ahrs_learn_time_s
        period_s = 1.0 / (imu_rate_hz or PAPER_IMU_RATE_HZ)
        self._learn_rate = 0.0 if learn_s is None else min(1.0, period_s / learn_s)
        self._n_learnt = 1  # the configured variance counts as one sample
        self._consts: NDArray[np.float64] | None = None  # imu_input's constants, if it runs
        self._sigma2_slot = 0
        m = config.saturation_margin
        self._acc_lim = np.inf if accel_range_mps2 is None else m * float(accel_range_mps2)
        self._gyr_lim = np.inf if gyro_range_radps is None else m * float(gyro_range_radps)
        self._acc_sig = (
            0.0
            if accel_range_mps2 is None
            else (config.saturation_sigma_range * float(accel_range_mps2))
        )
        self._gyr_sig = (
            0.0
            if gyro_range_radps is None
            else (config.saturation_sigma_range * float(gyro_range_radps))
        )
        self._gyro_d2 = chi2_quantile(config.gyro_ahrs_probability, 3)
        self._prev: tuple[float, Mat3, tuple[float, float, float]] | None = None
        self._last_acc: tuple[float, ...] | None = None  # last trusted specific force
        self._prev_acc: tuple[float, ...] | None = None  # the trusted one before it
        #: the tangent's excess per clipped axis at the stretch's k-th sample is
        #: entry + slope k (m/s^2 beyond the rail, IMU axes; None: no cap for this stretch)
        self._tangent: tuple[NDArray[np.float64], NDArray[np.float64]] | None = None
        self._acc_run = 0  # consecutive samples with a saturated accelerometer axis
        #: scale (m/s^2) of the half-normal prior per IMU axis: the configured one until a
        #: SaturationScaleLearner has evidence (set_accel_scales)
        self.accel_scales_mps2 = np.full(3, self._acc_sig)
        #: the last sample's railed accelerometer axes (+1 / -1: the rail's side, 0: within
        #: range) and the velocity rate the prior put back on them (m/s^2, IMU axes)
        self.last_rail_sign = np.zeros(3)
        self.last_restored_mps2 = np.zeros(3)
        self.last_extra_cov = np.zeros((3, 3))
        self.last_capped = np.zeros(3, dtype=bool)
        self.n_accel_saturated = 0  #: samples with an accelerometer axis at the rail
        self.n_gyro_saturated = 0  #: samples with a gyro axis at the rail
        self.n_gyro_repaired = 0  #: gyro samples replaced by the orientation's rate
        self.max_gyro_d2 = 0.0  #: largest test statistic seen (diagnostics)
        self._kernels = imu_kernels()  # compiled process, or None
        # its previous sample: [has one, t, R_world_imu (9, row-major), gyro (3)]
        self._prev_arr = np.zeros(14)

    def _saturation_prior(
        self, accel_mps2: ArrayLike, acc_sat: bool, gyr_sat: bool, xa: float, xg: float
    ) -> tuple[NDArray[np.float64] | None, float, float]:
        """Count a clipped sample and apply the saturation prior: the accelerometer with the
        prior's mean put back on the railed axes (None if no axis is clipped) and the extra
        sigmas (the accelerometer's growing along a clipped stretch if
        ``saturation_correlated``). Shared by :meth:`process` and its reference."""
        self._acc_run = self._acc_run + 1 if acc_sat else 0
        acc = None
        if acc_sat:
            self.n_accel_saturated += 1
            a = np.asarray(accel_mps2, dtype=float)
            rail = np.abs(a) >= self._acc_lim
            scale = self._side_scales(a)
            cap = self._tangent_cap(a, rail)
            capped = np.zeros(3, dtype=bool)
            if cap is not None:
                # the half-normal's scale no larger than the tangent's excess (mean 0.8, sd
                # 0.6 of it: the bound lies beyond most of the prior's mass)
                capped = rail & (cap < scale)
                scale = np.where(capped, cap, scale)
            self.last_rail_sign = np.where(rail, np.sign(a), 0.0)
            self.last_restored_mps2 = self.last_rail_sign * scale * _HALF_NORMAL_MEAN
            #: the railed axes whose scale the tangent set (not the learnt one's)
            self.last_capped = capped
            acc = np.where(rail, a + np.sign(a) * scale * _HALF_NORMAL_MEAN, a)
            corr = np.sqrt(2.0 * self._acc_run - 1.0) if self.config.saturation_correlated else 1.0
            if self.config.saturation_sigma_prior_floor:
                scale = np.where(capped, scale, np.maximum(scale, self._acc_sig))
            sig_axes = np.where(rail, scale * _HALF_NORMAL_SD * corr, 0.0)
            xa = max(xa, float(np.max(sig_axes)))
            #: the prior's covariance on the clipped axes only (ImuSample.accel_extra_cov_m2ps4)
            self.last_extra_cov = np.diag(sig_axes**2)
        elif self.last_rail_sign.any():
            self.last_rail_sign = np.zeros(3)
            self.last_restored_mps2 = np.zeros(3)
        if gyr_sat:
            self.n_gyro_saturated += 1
            xg = max(xg, self._gyr_sig * _HALF_NORMAL_SD)
        return acc, xa, xg

    def _set_trusted(self, acc: tuple[float, ...]) -> None:
        """Remember a trusted specific force (and the one before it, for the tangent)."""
        self._prev_acc, self._last_acc = self._last_acc, acc

    def _tangent_cap(self, a: NDArray[np.float64], rail: NDArray[np.bool_]) -> NDArray | None:
        """With ``saturation_tangent_cap``: the largest excess (m/s^2, per IMU axis, inf
        where there is no bound) the clipped axes can have at this sample of the stretch.

        A clipped peak is concave near its top, so the tangent at the last trusted sample
        (its value plus the rise per sample since the one before, continued k samples)
        bounds it from above. The bound is set at the stretch's first sample, per railed
        axis, only where the tangent itself reaches the rail there (a signal that jumps
        past the rail, or fell into it, is not a concave peak: no bound)."""
        if not self.config.saturation_tangent_cap:
            return None
        k = self._acc_run
        if k == 1:
            self._tangent = None
            if self._last_acc is not None and self._prev_acc is not None:
                last = np.asarray(self._last_acc, dtype=float)
                prev = np.asarray(self._prev_acc, dtype=float)
                sgn = np.sign(a)
                rise = np.maximum(sgn * (last - prev), 0.0)  # towards the rail, per sample
                first = sgn * last + rise - np.abs(a)  # the tangent's excess at k = 1
                ok = rail & (first > 0.0)
                if ok.any():
                    self._tangent = (np.where(ok, first - rise, np.inf), np.where(ok, rise, 0.0))
        if self._tangent is None:
            return None
        base, rise = self._tangent
        return np.maximum(base + rise * k, 0.0)

    def _side_scales(self, accel_mps2: NDArray[np.float64]) -> NDArray[np.float64]:
        """The prior's scale per IMU axis for this sample: :attr:`accel_scales_mps2` as is
        (3 scales), or, with one scale per axis and rail side (6: the positive rails' x, y,
        z, then the negative rails'), the one of the side each axis is on."""
        s = self.accel_scales_mps2
        if s.shape[0] == 3:
            return s
        return np.where(accel_mps2 >= 0.0, s[:3], s[3:])

    def _after_test(self, repaired: bool, d2: float = -1.0) -> None:
        """Learn the residual's spread from a tested sample (statistic ``d2`` >= 0 under
        this sample's variance; not right after a repair, whose error is in the
        prediction), count a run of repairs, and set the test's variance for the next
        sample: (1 + repairs in a row) times the larger of the configured sigma^2 and the
        learnt one (in imu_input's constants too when that kernel runs the test)."""
        run = self._repair_run + 1 if repaired else 0
        changed = run != self._repair_run
        if d2 >= 0.0 and self._repair_run == 0 and self._learn_rate > 0.0:
            # the mean of |r|^2 / 3 (the variance per axis), each sample's statistic clipped
            # at the gate (a spike counts as a gate-sized residual), the configured
            # variance its first sample, exponentially weighted once the learning time is full
            self._n_learnt += 1
            w = max(self._learn_rate, 1.0 / self._n_learnt)
            r2 = min(d2, self._gyro_d2) * self._gyro_sigma2
            self._learnt_var += w * (r2 / 3.0 - self._learnt_var)
            changed = changed or self._learnt_var > self._floor_var or self._above_floor
        if not changed:
            return
        self._repair_run = run
        self._above_floor = self._learnt_var > self._floor_var
        if self._above_floor:
            self._gyro_sigma2 = self._learnt_var * (1.0 + run)
            self._gyro_sigma = math.sqrt(self._gyro_sigma2)
        else:
            self._gyro_sigma = self.gyro_sigma_radps * math.sqrt(1.0 + run)
            self._gyro_sigma2 = self._gyro_sigma**2
        if self._consts is not None:
            self._consts[self._sigma2_slot] = self._gyro_sigma2

    def process(self, sample: ImuSample) -> ImuSample:
        """The sample with its extra sigmas set (and its gyro replaced if it failed the test).

        Scalar arithmetic on Python floats (a clean sample costs a few microseconds; the
        numpy arrays are only built when the sample changes)."""
        if not self.config.enabled:
            return sample
        if self._kernels is not None:
            return self._process_compiled(sample)
        acc_l = np.asarray(sample.accel_mps2, dtype=float).tolist()
        gx, gy, gz = gyr_l = np.asarray(sample.gyro_radps, dtype=float).tolist()
        xa, xg = sample.accel_extra_sigma_mps2, sample.gyro_extra_sigma_radps
        acc_sat = any(abs(v) >= self._acc_lim for v in acc_l)
        gyr_sat = any(abs(v) >= self._gyr_lim for v in gyr_l)
        # acc: built only if the sample changes (None until then)
        acc, xa, xg = self._saturation_prior(sample.accel_mps2, acc_sat, gyr_sat, xa, xg)
        t = float(sample.timestamp_s)
        R = quat_matrix(sample.quat_wxyz)  # row-major tuple (geometry.matrix_from_quat_wxyz)
        repaired: tuple[float, float, float] | None = None
        held = False  # accelerometer replaced by the last trusted one
        d2 = -1.0
        if self.config.gyro_ahrs_test and self._prev is not None and t > self._prev[0]:
            t0, R0, (g0x, g0y, g0z) = self._prev
            h = t - t0
            wx, wy, wz = self._relative_rotvec(R0, R)  # over h: the mean rate, IMU axes
            px, py, pz = 2.0 * (wx / h) - g0x, 2.0 * (wy / h) - g0y, 2.0 * (wz / h) - g0z
            rx, ry, rz = gx - px, gy - py, gz - pz
            sigma = self._gyro_sigma
            d2 = (rx * rx + ry * ry + rz * rz) / self._gyro_sigma2
            self.max_gyro_d2 = max(self.max_gyro_d2, d2) if not gyr_sat else self.max_gyro_d2
            if d2 > self._gyro_d2:
                self.n_gyro_repaired += 1
                repaired = (px, py, pz)
                xg = max(xg, sigma) if not gyr_sat else xg
                if self._last_acc is not None and not acc_sat:
                    # the packet is corrupt: hold the last trusted specific force
                    acc = np.array(self._last_acc)
                    xa = max(xa, self.config.held_accel_sigma_mps2)
                    held = True
        self._prev = (t, R, (gx, gy, gz) if repaired is None else repaired)
        self._after_test(repaired is not None, -1.0 if gyr_sat else d2)
        if repaired is None and not acc_sat:
            self._set_trusted(tuple(acc_l))
        if (
            repaired is None
            and acc is None
            and xa == sample.accel_extra_sigma_mps2
            and xg == sample.gyro_extra_sigma_radps
        ):
            return sample
        return dataclasses.replace(
            sample,
            accel_mps2=np.array(acc_l) if acc is None else acc,
            gyro_radps=np.array(gyr_l if repaired is None else repaired),
            accel_extra_sigma_mps2=xa,
            gyro_extra_sigma_radps=xg,
            accel_held=held or sample.accel_held,
            accel_extra_cov_m2ps4=self.last_extra_cov if acc_sat else sample.accel_extra_cov_m2ps4,
        )

    def _process_compiled(self, sample: ImuSample) -> ImuSample:
        """:meth:`process` with its arithmetic in one compiled call (filter/compiled_imu.py)."""
        acc = as_f64(sample.accel_mps2)
        gyr = as_f64(sample.gyro_radps)
        cfg = self.config
        assert self._kernels is not None
        d2, px, py, pz, acc_sat, gyr_sat = self._kernels.fault_check(
            self._prev_arr,
            float(sample.timestamp_s),
            acc,
            gyr,
            as_f64(sample.quat_wxyz),
            self._acc_lim,
            self._gyr_lim,
            cfg.gyro_ahrs_test,
            self._gyro_sigma2,
        )
        return self.finish_compiled(sample, acc, gyr, d2, px, py, pz, acc_sat, gyr_sat)

    def compiled_constants(self, c: NDArray[np.float64], k: ModuleType) -> bool:
        """Write the check's constants into ``c`` (``compiled_imu.IN_*`` slots of the module
        ``k``) for a caller that runs ``compiled_imu.fault_check`` itself on
        ``_prev_arr`` (``compiled_imu.imu_input``); False (nothing written) if the monitor is
        off or not compiled."""
        if not self.config.enabled or self._kernels is None:
            return False
        cfg = self.config
        c[k.IN_ACC_LIM], c[k.IN_GYR_LIM] = self._acc_lim, self._gyr_lim
        c[k.IN_TEST] = 1.0 if cfg.gyro_ahrs_test else 0.0
        c[k.IN_SIGMA2] = self._gyro_sigma2
        c[k.IN_GYRO_D2] = self._gyro_d2
        # the kernel reads the test's variance from c: _after_test keeps it current
        self._consts, self._sigma2_slot = c, k.IN_SIGMA2
        return True

    def clean_compiled(self, acc: NDArray[np.float64], d2: float) -> None:
        """:meth:`finish_compiled` for a sample the check found clean (no saturated axis,
        ``_acc_run`` 0, d2 at most the gate): only the bookkeeping, the sample stays as it is."""
        if d2 >= 0.0:
            self.max_gyro_d2 = max(self.max_gyro_d2, d2)
        if d2 >= 0.0 or self._repair_run:
            self._after_test(False, d2)
        self._set_trusted(tuple(acc.tolist()))

    def finish_compiled(
        self,
        sample: ImuSample,
        acc: NDArray[np.float64],
        gyr: NDArray[np.float64],
        d2: float,
        px: float,
        py: float,
        pz: float,
        acc_sat: bool,
        gyr_sat: bool,
    ) -> ImuSample:
        """:meth:`process`'s work after ``compiled_imu.fault_check`` ran on ``_prev_arr`` with
        the sample's time, its ``acc``, ``gyr`` (float64 arrays) and orientation, and returned
        (d2, px, py, pz, acc_sat, gyr_sat)."""
        xa, xg = sample.accel_extra_sigma_mps2, sample.gyro_extra_sigma_radps
        cfg = self.config
        prev = self._prev_arr
        new_acc = None
        if acc_sat or gyr_sat or self._acc_run:
            new_acc, xa, xg = self._saturation_prior(acc, acc_sat, gyr_sat, xa, xg)
        repaired = False
        held = False  # accelerometer replaced by the last trusted one
        if d2 >= 0.0:
            if not gyr_sat:
                self.max_gyro_d2 = max(self.max_gyro_d2, d2)
            if d2 > self._gyro_d2:
                self.n_gyro_repaired += 1
                repaired = True
                xg = max(xg, self._gyro_sigma) if not gyr_sat else xg
                if self._last_acc is not None and not acc_sat:
                    # the packet is corrupt: hold the last trusted specific force
                    new_acc = np.array(self._last_acc)
                    xa = max(xa, cfg.held_accel_sigma_mps2)
                    held = True
        if d2 >= 0.0 or self._repair_run:
            self._after_test(repaired, -1.0 if gyr_sat else d2)
        if repaired:
            prev[11], prev[12], prev[13] = px, py, pz
        elif not acc_sat:  # (fault_check stored the gyro)
            self._set_trusted(tuple(acc.tolist()))
        if (
            not repaired
            and new_acc is None
            and xa == sample.accel_extra_sigma_mps2
            and xg == sample.gyro_extra_sigma_radps
        ):
            return sample
        return dataclasses.replace(
            sample,
            accel_mps2=acc.copy() if new_acc is None else new_acc,
            gyro_radps=np.array([px, py, pz]) if repaired else gyr.copy(),
            accel_extra_sigma_mps2=xa,
            gyro_extra_sigma_radps=xg,
            accel_held=held or sample.accel_held,
            accel_extra_cov_m2ps4=self.last_extra_cov if acc_sat else sample.accel_extra_cov_m2ps4,
        )

    def process_reference(self, sample: ImuSample) -> ImuSample:
        """numpy reference of :meth:`process` (the tests compare the two)."""
        if not self.config.enabled:
            return sample
        acc = np.asarray(sample.accel_mps2, dtype=float)
        gyr = np.asarray(sample.gyro_radps, dtype=float)
        xa, xg = sample.accel_extra_sigma_mps2, sample.gyro_extra_sigma_radps
        acc_sat = bool(np.any(np.abs(acc) >= self._acc_lim))
        gyr_sat = bool(np.any(np.abs(gyr) >= self._gyr_lim))
        prior_acc, xa, xg = self._saturation_prior(acc, acc_sat, gyr_sat, xa, xg)
        acc = acc if prior_acc is None else prior_acc
        t = float(sample.timestamp_s)
        R = matrix_from_quat_wxyz(sample.quat_wxyz)
        repaired = gyr
        held = False  # accelerometer replaced by the last trusted one
        d2 = -1.0
        if self.config.gyro_ahrs_test and self._prev is not None and t > self._prev[0]:
            t0, R0, g0 = self._prev
            w = np.array(self._relative_rotvec_reference(R0, _as_mat3(R))) / (t - t0)
            pred = 2.0 * w - np.asarray(g0)
            r = gyr - pred
            sigma = self._gyro_sigma
            d2 = float(r @ r) / self._gyro_sigma2
            self.max_gyro_d2 = max(self.max_gyro_d2, d2) if not gyr_sat else self.max_gyro_d2
            if d2 > self._gyro_d2:
                self.n_gyro_repaired += 1
                repaired = pred
                xg = max(xg, sigma) if not gyr_sat else xg
                if self._last_acc is not None and not acc_sat:
                    acc = np.array(self._last_acc)
                    xa = max(xa, self.config.held_accel_sigma_mps2)
                    held = True
        gx, gy, gz = repaired.tolist()
        self._prev = (t, _as_mat3(R), (gx, gy, gz))
        self._after_test(repaired is not gyr, -1.0 if gyr_sat else d2)
        if repaired is gyr and not acc_sat:
            self._set_trusted(tuple(acc.tolist()))
        if (
            repaired is gyr
            and xa == sample.accel_extra_sigma_mps2
            and xg == sample.gyro_extra_sigma_radps
        ):
            return sample
        return dataclasses.replace(
            sample,
            accel_mps2=acc,
            gyro_radps=repaired,
            accel_extra_sigma_mps2=xa,
            gyro_extra_sigma_radps=xg,
            accel_held=held or sample.accel_held,
            accel_extra_cov_m2ps4=self.last_extra_cov if acc_sat else sample.accel_extra_cov_m2ps4,
        )

    @staticmethod
    def _relative_rotvec(R0: Mat3, R: Mat3) -> tuple[float, float, float]:
        """Rotation vector (rad) of R0^T R, scalar closed form (fast_imu); equals
        :meth:`_relative_rotvec_reference` to rounding (tests/test_fast_imu.py)."""
        return mat3_rotvec(mat3_tmul(R0, R))

    @staticmethod
    def _relative_rotvec_reference(R0: Mat3, R: Mat3) -> tuple[float, float, float]:
        """numpy / scipy reference of :meth:`_relative_rotvec`."""
        from scipy.spatial.transform import Rotation

        R_rel = np.reshape(R0, (3, 3)).T @ np.reshape(R, (3, 3))
        wx, wy, wz = Rotation.from_matrix(R_rel).as_rotvec().tolist()
        return wx, wy, wz

    @property
    def n_distrusted(self) -> int:
        """Samples marked so far: saturated (either sensor) or repaired."""
        return self.n_accel_saturated + self.n_gyro_saturated + self.n_gyro_repaired

    def report(self) -> dict[str, int]:
        return {
            "accel_saturated_samples": self.n_accel_saturated,
            "gyro_saturated_samples": self.n_gyro_saturated,
            "gyro_repaired_samples": self.n_gyro_repaired,
        }


def railed_axis(extra_cov_m2ps4: ArrayLike) -> NDArray[np.float64] | None:
    """The unit axis (3-vector, the covariance's axes) of a saturated sample's covariance on
    its railed axes (``ImuSample.accel_extra_cov_m2ps4``) if it rails exactly one axis, else
    None. Rank one is tested to rounding (the monitor puts exact zeros on the axes within
    range; a mount rotation adds rounding only), not against a tuned tolerance."""
    C = np.asarray(extra_cov_m2ps4, dtype=float).reshape(3, 3)
    w, V = np.linalg.eigh(0.5 * (C + C.T))
    if not w[2] > 0.0 or w[1] > 1e-9 * w[2]:
        return None
    return np.asarray(V[:, 2], dtype=float)


def velocity_fault_cov(sigma_mps: float, interval_s: float) -> NDArray[np.float64]:
    """4x4 covariance on (dp, dv) of a velocity jump of sigma ``sigma_mps`` at the middle of
    an interval of ``interval_s`` seconds ending now: dv = j, dp = (interval / 2) j."""
    J = np.vstack([0.5 * interval_s * np.eye(2), np.eye(2)])
    return sigma_mps**2 * (J @ J.T)


@dataclasses.dataclass
class _Episode:
    """Clipped stretches close together and the evidence window after them."""

    U: NDArray[np.float64]  # (2, 3 or 6) world x-z velocity per unit of each scale
    restored_mps: NDArray[np.float64]  # (2,) velocity the prior put back (world x-z)
    corrections0_mps: NDArray[np.float64]  # the filter's correction sum at the start
    var_before: float  # the filter's velocity variance (trace) before the first stretch
    in_stretch: bool = True
    end_s: float = 0.0  # when the last stretch ended
    var_peak: float = 0.0  # largest velocity variance since


class SaturationScaleLearner:
    """The half-normal scale of the clipped excess, per IMU axis, learnt from what the
    filter's measurements say each clipped stretch lost (empirical Bayes, online).

    How far the true specific force went beyond the rail depends on the gait and the mount:
    on the simulated stairs a push-off clips the shank's x axis at 2-3 times the range, a
    level-ground heel strike its z axis at a fraction of it, and one fixed scale over-corrects
    one and under-corrects the other. The estimator does not need to guess: after a clipped
    stretch, vision and the stance measure the velocity, and the sum of the filter's velocity
    corrections since the stretch is what the prior got wrong. Per stretch j (stretches that
    follow each other before the evidence is in are merged), the velocity it lost, in world
    x-z, is linear in the axis scales s: ``m_j = U_j s``, U_j summing c h R_k e_a sign over its
    clipped samples k and railed axes a (c = sqrt(2/pi), the half-normal mean; h the sample
    period; R_k the sagittal rotation). The measured loss is what the prior put back plus the
    corrections, ``m_j = restored_j + sum dv``. The evidence is taken when the measurements
    have removed ``1 - explained_fraction`` of the velocity variance the stretch added
    (weight: the filter's velocity covariance then), and dropped if that takes longer than
    ``window_s`` (nothing measured the velocity). The scales are the least-squares solution
    with the configured scale as a prior of its own size (sigma = s0): one well measured
    stretch outweighs it.
    """

    def __init__(
        self, s0_mps2: float, explained_fraction: float, window_s: float, per_side: bool = False
    ) -> None:
        self.s0 = float(s0_mps2)
        self.explained_fraction = float(explained_fraction)
        self.window_s = float(window_s)
        #: one scale per IMU axis and rail side (6: positive x, y, z, then negative x, y, z;
        #: ``imu_faults.saturation_learn_per_side``) instead of one per axis (3)
        self.per_side = bool(per_side)
        n = 6 if self.per_side else 3
        self._A = np.eye(n) / self.s0**2  # normal equations, prior included
        self._b = np.full(n, 1.0 / self.s0)
        self.scales_mps2 = np.full(n, self.s0)
        self._ep: _Episode | None = None
        self.n_evidence = 0  #: stretches (merged) whose evidence was used
        self.n_dropped = 0  #: stretches whose velocity was not measured within window_s

    @property
    def active(self) -> bool:
        """A clipped stretch or its evidence window is open (feed every sample then)."""
        return self._ep is not None

    def add_sample(
        self,
        t_s: float,
        h_s: float,
        rail_sign: NDArray[np.float64],
        restored_mps2: NDArray[np.float64],
        R_xz_imu: NDArray[np.float64],
        velocity_var: float,
        corrections_mps: NDArray[np.float64],
    ) -> bool:
        """One IMU sample at ``t_s``, ``h_s`` after the previous one: its railed axes (+1 /
        -1 / 0, IMU axes), the specific force the prior put back on them, the (2, 3) map from
        IMU axes to world x-z, and the filter's velocity variance (trace) and correction sum
        now. Returns True when the scales
        changed."""
        h = max(float(h_s), 0.0)
        ep = self._ep
        if rail_sign.any():
            if ep is None:
                ep = self._ep = _Episode(
                    np.zeros((2, self._A.shape[0])),
                    np.zeros(2),
                    corrections_mps.copy(),
                    velocity_var,
                )
            ep.in_stretch = True
            du = (_HALF_NORMAL_MEAN * h) * (R_xz_imu * rail_sign)
            if self.per_side:  # each railed axis's column on the side it is clipped at
                ep.U[:, :3] += du * (rail_sign > 0.0)
                ep.U[:, 3:] += du * (rail_sign < 0.0)
            else:
                ep.U += du
            ep.restored_mps += h * (R_xz_imu @ restored_mps2)
            return False
        if ep is None:
            return False
        if ep.in_stretch:  # the stretch just ended: the evidence window opens
            ep.in_stretch = False
            ep.end_s = t_s
            ep.var_peak = velocity_var
            return False
        ep.var_peak = max(ep.var_peak, velocity_var)
        added = ep.var_peak - ep.var_before
        if added > 0.0 and velocity_var - ep.var_before <= self.explained_fraction * added:
            self._ep = None
            m = ep.restored_mps + (corrections_mps - ep.corrections0_mps)
            W = 1.0 / max(velocity_var, 1e-12)  # the measured loss's remaining variance
            self._A += W * (ep.U.T @ ep.U)
            self._b += W * (ep.U.T @ m)
            s = np.linalg.solve(self._A, self._b)
            self.scales_mps2 = np.maximum(s, 1e-3 * self.s0)  # a scale, not a sign
            self.n_evidence += 1
            return True
        if t_s - ep.end_s > self.window_s:
            self._ep = None
            self.n_dropped += 1
        return False
