"""Sensor fault injection (vio_graph.sim.config.FaultsConfig; all faults off by default).

Pure functions of their inputs and a generator:
- camera blackout: every pixel invalid (depth 0, confidence 0) inside a time window;
- dropped frames: frames missing from the recording (their timestamps are skipped);
- depth corruption: a fraction of spurious valid pixels, and a foot-like blob (an elliptic
  dome close to the lens) occluding part of the view inside a time window;
- IMU spikes (one sample, one random axis, random sign) and saturation at a lower range;
- a constant camera-IMU time offset and white clock jitter on the recorded timestamps.
"""

from __future__ import annotations

import numpy as np
from numpy.typing import NDArray

from vio_graph.sim.config import CameraConfig, FaultsConfig

_JITTER_CLIP_PERIODS = 0.4  # keeps jittered timestamps strictly increasing


def in_window(t_s: NDArray | float, start_s: float | None, duration_s: float) -> NDArray:
    """True where ``start_s <= t < start_s + duration_s`` (all False when start is None)."""
    t = np.asarray(t_s, dtype=float)
    if start_s is None or duration_s <= 0:
        return np.zeros(t.shape, dtype=bool)
    return (t >= start_s) & (t < start_s + duration_s)


def has_depth_faults(cfg: FaultsConfig) -> bool:
    """True if any fault changes the pixels of a rendered frame."""
    return (
        (cfg.camera_blackout_start_s is not None and cfg.camera_blackout_duration_s > 0)
        or cfg.spurious_point_fraction > 0
        or (cfg.occluder_start_s is not None and cfg.occluder_duration_s > 0)
    )


def kept_frames(n_frames: int, cfg: FaultsConfig, rng: np.random.Generator) -> NDArray:
    """Indices (K,) of the frames that reach the recording (Bernoulli drops, first kept)."""
    if cfg.dropped_frame_probability <= 0:
        return np.arange(n_frames)
    keep = rng.random(n_frames) >= cfg.dropped_frame_probability
    keep[0] = True
    return np.flatnonzero(keep)


def stamp_times(
    true_s: NDArray,
    offset_s: float,
    jitter_s: float,
    period_s: float,
    rng: np.random.Generator,
) -> NDArray[np.float64]:
    """Recorded timestamps: true time + constant offset + white jitter (clipped at
    0.4 periods so the stamps stay strictly increasing)."""
    t = np.asarray(true_s, dtype=float) + offset_s
    if jitter_s > 0:
        lim = _JITTER_CLIP_PERIODS * period_s
        t = t + np.clip(rng.normal(0.0, jitter_s, t.shape), -lim, lim)
    return t


def corrupt_depth(
    depth_m: NDArray[np.float32],
    confidence: NDArray[np.uint8],
    t_true_s: float,
    cfg: FaultsConfig,
    camera: CameraConfig,
    rng: np.random.Generator,
) -> tuple[NDArray[np.float32], NDArray[np.uint8]]:
    """Depth faults of one frame captured at ``t_true_s``; returns new arrays."""
    depth = np.array(depth_m, dtype=np.float32, copy=True)
    conf = np.array(confidence, dtype=np.uint8, copy=True)
    h, w = depth.shape
    if cfg.occluder_start_s is not None and in_window(
        t_true_s, cfg.occluder_start_s, cfg.occluder_duration_s
    ):
        v, u = np.mgrid[0:h, 0:w]
        cu, cv = cfg.occluder_center_uv_frac[0] * w, cfg.occluder_center_uv_frac[1] * h
        au, av = cfg.occluder_size_frac[0] * w, cfg.occluder_size_frac[1] * h
        r2 = ((u - cu) / au) ** 2 + ((v - cv) / av) ** 2
        blob = r2 < 1.0
        # a rounded surface (shoe) bulging towards the lens, 4 cm deeper at its rim
        z_blob = cfg.occluder_depth_m + 0.04 * r2 + rng.normal(0, 0.002, r2.shape)
        depth = np.where(blob, z_blob, depth).astype(np.float32)
        conf = np.where(blob, 200, conf).astype(np.uint8)
    if cfg.spurious_point_fraction > 0:
        k = int(round(cfg.spurious_point_fraction * depth.size))
        idx = rng.choice(depth.size, size=k, replace=False)
        depth.flat[idx] = rng.uniform(camera.min_range_m, camera.max_range_m, k)
        conf.flat[idx] = rng.integers(1, 256, k)
    if cfg.camera_blackout_start_s is not None and in_window(
        t_true_s, cfg.camera_blackout_start_s, cfg.camera_blackout_duration_s
    ):
        depth[:] = 0.0
        conf[:] = 0
    return depth, conf


def corrupt_imu(
    accel_mps2: NDArray,
    gyro_radps: NDArray,
    rate_hz: float,
    cfg: FaultsConfig,
    rng: np.random.Generator,
) -> tuple[NDArray[np.float64], NDArray[np.float64], NDArray[np.int64]]:
    """IMU spikes, a knock, then saturation; returns new accel (N, 3), gyro (N, 3) and the
    spike sample indices (each spike hits one random axis of both sensors, random signs).
    Sample i is taken at i / ``rate_hz`` seconds (the knock's window)."""
    accel = np.array(accel_mps2, dtype=float, copy=True)
    gyro = np.array(gyro_radps, dtype=float, copy=True)
    n = accel.shape[0]
    spikes = np.zeros(0, dtype=np.int64)
    if cfg.imu_spike_rate_hz > 0:
        spikes = np.flatnonzero(rng.random(n) < min(cfg.imu_spike_rate_hz / rate_hz, 1.0))
        k = spikes.size
        ax_a, ax_g = rng.integers(0, 3, k), rng.integers(0, 3, k)
        accel[spikes, ax_a] += rng.choice([-1.0, 1.0], k) * cfg.imu_spike_accel_mps2
        gyro[spikes, ax_g] += rng.choice([-1.0, 1.0], k) * cfg.imu_spike_gyro_radps
    if cfg.imu_knock_start_s is not None and cfg.imu_knock_duration_s > 0:
        i0 = int(round(cfg.imu_knock_start_s * rate_hz))
        i1 = i0 + int(round(cfg.imu_knock_duration_s * rate_hz))
        accel[i0:i1, 0] += cfg.imu_knock_accel_mps2
        accel[i0:i1, 2] -= cfg.imu_knock_accel_mps2
    if cfg.imu_accel_saturation_mps2 is not None:
        lim = cfg.imu_accel_saturation_mps2
        accel = np.clip(accel, -lim, lim)
    if cfg.imu_gyro_saturation_radps is not None:
        lim = cfg.imu_gyro_saturation_radps
        gyro = np.clip(gyro, -lim, lim)
    return accel, gyro, spikes


def summary(cfg: FaultsConfig, n_dropped: int, n_spikes: int) -> str:
    """One line naming the active faults (for metadata.provenance.notes); '' if none."""
    parts = []
    if cfg.camera_blackout_start_s is not None and cfg.camera_blackout_duration_s > 0:
        parts.append(
            f"camera blackout {cfg.camera_blackout_start_s:g} s + "
            f"{cfg.camera_blackout_duration_s:g} s"
        )
    if cfg.dropped_frame_probability > 0:
        parts.append(f"{n_dropped} frames dropped (p={cfg.dropped_frame_probability:g})")
    if cfg.spurious_point_fraction > 0:
        parts.append(f"spurious points {cfg.spurious_point_fraction:g}")
    if cfg.occluder_start_s is not None and cfg.occluder_duration_s > 0:
        parts.append(f"occluder {cfg.occluder_start_s:g} s + {cfg.occluder_duration_s:g} s")
    if cfg.imu_spike_rate_hz > 0:
        parts.append(f"{n_spikes} IMU spikes")
    if cfg.imu_knock_start_s is not None and cfg.imu_knock_duration_s > 0:
        parts.append(
            f"IMU knock {cfg.imu_knock_start_s:g} s + {cfg.imu_knock_duration_s:g} s at "
            f"{cfg.imu_knock_accel_mps2:g} m/s^2"
        )
    if cfg.imu_accel_saturation_mps2 is not None or cfg.imu_gyro_saturation_radps is not None:
        parts.append(
            f"IMU saturation accel {cfg.imu_accel_saturation_mps2} m/s^2, gyro "
            f"{cfg.imu_gyro_saturation_radps} rad/s"
        )
    if cfg.camera_time_offset_s != 0:
        parts.append(f"camera time offset {cfg.camera_time_offset_s:g} s")
    if cfg.clock_jitter_s > 0:
        parts.append(f"clock jitter {cfg.clock_jitter_s:g} s")
    return ("faults: " + "; ".join(parts)) if parts else ""
