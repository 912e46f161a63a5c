"""The filter's repair of a corrupt IMU packet from the sample after it.

When the fault monitor (filter/imu_faults.py) finds a packet whose gyro disagrees with the
vendor orientation, it can only use the past: the gyro becomes the orientation's prediction
and the accelerometer the last trusted value (``ImuSample.accel_held``). On the simulated
gaits both are poor stand-ins: the predicted gyro is 0.4-1.3 rad/s off per axis (5-13 mrad of
attitude over one sample, which the complementary attitude tracker keeps for about its 1 s
time constant, tilting every slice and the strapdown's gravity), and the held specific force
is up to 29 m/s^2 off at heel strike (0.29 m/s of velocity). The next sample is a measurement
of the same motion 10 ms later: the linear interpolation between the trusted samples either
side is 3-5x closer for the accelerometer (what the smoothers already use,
``smoother.held_accel_interpolation``) and 0.07 rad/s RMS in pitch for the gyro.

:class:`NextSampleRepair` holds such a packet back (the filter, the attitude tracker and the
stance detector do not see it yet) until the next sample arrives; if that one is a
measurement it replaces the packet's accelerometer and gyro by the interpolation, then both
are released in order. The filter therefore runs one IMU sample (10 ms) late only over a
repaired packet; a depth frame in that gap is extrapolated from the sample before it, as any
frame is from the latest one. Two corrupt packets in a row, or a saturated neighbour, release
the held packet as the monitor left it (the latency never exceeds one sample). Samples the
monitor did not touch pass straight through, so a clean recording is fused bit for bit as
without it.
"""

from __future__ import annotations

import dataclasses

import numpy as np
from numpy.typing import ArrayLike, NDArray

from vio_graph.filter.gating import chi2_quantile
from vio_graph.types import ImuSample


def keep_consistent_axes(
    measured: ArrayLike | None, stand_in: ArrayLike, sigma: float, probability: float
) -> NDArray[np.float64]:
    """Per axis, the measured value where it agrees with the stand-in (the interpolation
    between the packet's measured neighbours) within the ``probability`` quantile of a 1-dof
    chi-square with sigma ``sigma``, else the stand-in. A spike on one axis (a bit error, a
    shock on one channel) then costs that axis only, while a heel strike's true transient on
    the others, which the interpolation misses by a few m/s^2, stays measured. None: the
    stand-in throughout."""
    s = np.array(stand_in, dtype=float)
    if measured is None:
        return s
    m = np.asarray(measured, dtype=float)
    ok = (m - s) ** 2 <= chi2_quantile(probability, 1) * sigma**2
    return np.where(ok, m, s)


def interpolated_axes_cov(
    kept: ArrayLike, measured: ArrayLike, variance: float
) -> NDArray[np.float64] | None:
    """The extra covariance (3x3, diagonal, ``variance``'s unit) of a repaired packet whose
    axes :func:`keep_consistent_axes` settled: ``variance`` on the axes it interpolated, 0 on
    the ones it kept as measured (they are measurements).

    None (the caller keeps ``variance`` on every axis) when it kept every axis: the packet
    is corrupt (its gyro failed the monitor's test), but the test found no accelerometer
    axis to blame. At a heel strike the interpolation itself misses the true force by up to
    ~20 m/s^2, so a 30 m/s^2 spike of the other sign passes the per-axis test (upstair seed
    2 at 3.76 s: x measured 30 m/s^2 low, 11 from the interpolation against a 16 m/s^2
    bound). Not finding the corrupt axis there is no evidence that the axes are clean."""
    kept_all = np.asarray(kept) == np.asarray(measured)
    if np.all(kept_all):
        return None
    return np.diag(np.where(kept_all, 0.0, variance))


def _measured(sample: ImuSample) -> bool:
    """True if the fault monitor left the sample as measured (no extra sigma, not held)."""
    return (
        not sample.accel_held
        and sample.accel_extra_sigma_mps2 == 0.0
        and sample.gyro_extra_sigma_radps == 0.0
    )


class NextSampleRepair:
    """Holds a packet the fault monitor repaired until the next sample (module docstring).

    Feed every sample, in time order and in one set of axes, to :meth:`push`; it returns the
    samples ready for the filter (0, 1 or 2).
    """

    def __init__(
        self,
        interpolated_accel_sigma_mps2: float,
        gyro_sigma_radps: float | None = None,
        axis_probability: float | None = None,
        axis_distrust: bool = False,
    ) -> None:
        self.accel_sigma_mps2 = float(interpolated_accel_sigma_mps2)
        #: per-axis test of the packet's measurement against the interpolation
        #: (:func:`keep_consistent_axes`); None = the whole packet interpolated
        self.gyro_sigma_radps = gyro_sigma_radps
        self.axis_probability = axis_probability
        #: with the per-axis test: the extra accelerometer variance on the interpolated axes
        #: only (``ImuSample.accel_extra_cov_m2ps4``), the kept axes being measurements
        self.axis_distrust = axis_distrust
        self.n_axes_kept = 0  #: axes (accelerometer and gyro) of repaired packets left measured
        self._prev: ImuSample | None = None  # the latest released sample, if measured
        self._pending: ImuSample | None = None  # a repaired packet waiting for its successor
        self.n_repaired = 0  #: packets replaced by the interpolation

    @property
    def pending(self) -> ImuSample | None:
        """The packet held back, if any."""
        return self._pending

    def push(self, sample: ImuSample) -> list[ImuSample]:
        """The samples the filter may take now, in time order."""
        out: list[ImuSample] = []
        if self._pending is not None:
            held, self._pending = self._pending, None
            if self._prev is not None and _measured(sample):
                held = self.interpolate(self._prev, held, sample)
                self.n_repaired += 1
            out.append(held)
            self._prev = None
        if sample.accel_held and self._prev is not None:
            self._pending = sample
            return out
        out.append(sample)
        self._prev = sample if _measured(sample) else None
        return out

    def passed(self, sample: ImuSample) -> None:
        """:meth:`push` of a sample that goes straight through (nothing pending, the sample
        not held), for a caller that hands it to the filter itself."""
        self._prev = sample if _measured(sample) else None

    def interpolate(self, before: ImuSample, held: ImuSample, after: ImuSample) -> ImuSample:
        """``held`` with accelerometer and gyro linearly interpolated in time between its
        measured neighbours (with ``axis_probability``: only on the axes whose measurement
        disagrees with the interpolation, :func:`keep_consistent_axes`); the accelerometer
        carries ``accel_sigma_mps2`` as its extra sigma (still marked ``accel_held``), the
        gyro keeps the monitor's."""
        t0, t1 = before.timestamp_s, after.timestamp_s
        w = (held.timestamp_s - t0) / (t1 - t0)
        acc = (1.0 - w) * np.asarray(before.accel_mps2, float) + w * np.asarray(
            after.accel_mps2, float
        )
        gyr = (1.0 - w) * np.asarray(before.gyro_radps, float) + w * np.asarray(
            after.gyro_radps, float
        )
        p, sg = self.axis_probability, self.gyro_sigma_radps
        cov = held.accel_extra_cov_m2ps4
        if p is not None and sg is not None and held.measured_accel_mps2 is not None:
            ma, mg = held.measured_accel_mps2, held.measured_gyro_radps
            acc = keep_consistent_axes(ma, acc, self.accel_sigma_mps2, p)
            gyr = keep_consistent_axes(mg, gyr, sg, p)
            self.n_axes_kept += int(np.sum(acc == ma) + np.sum(gyr == mg))
            if self.axis_distrust and cov is None:
                cov = interpolated_axes_cov(acc, ma, self.accel_sigma_mps2**2)
        return dataclasses.replace(
            held,
            accel_mps2=acc,
            gyro_radps=gyr,
            accel_extra_sigma_mps2=self.accel_sigma_mps2,
            accel_extra_cov_m2ps4=cov,
        )
