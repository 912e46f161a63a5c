"""Self-diagnosis of the online estimate: is the estimator in trouble, and why?

A fused estimate can fail silently: a stance detector that flags swings pins the ankle, the
gate then refuses the correct visual displacements, and the position stops advancing while
every number still looks finite. :class:`HealthMonitor` watches three things, frame by frame,
with no look-ahead (pure algorithm, no I/O):

- the share of visual displacements the filter's chi-square gate refused;
- the share of frames anchored in stance;
- frames on which the front end found pixels that move with the camera (an occluding
  foot or strap, vio_graph/frontend/camera_fixed.py): reported, with a warning when they are
  found on two consecutive frames or more (a real object persists; a single frame's
  detection is the test's chance coincidence); ``frontend.camera_fixed.drop_pixels`` (on by
  default) removes it from the slice, without which it is taken for terrain;
- the departure of the fused path from visual odometry: over windows of ``window_s`` the
  filter's camera displacement is compared with the sum of the visual displacements over the
  same frames, as a chi-square test (2 dof) with the displacements' own covariances. A
  healthy filter fails it in ~0.1 % of windows (at p = 0.999); a pinned or diverged one in
  most;
- the consistency of the filter's own innovations, per measurement family (visual
  displacements, corner and level landmarks, stance anchor): the normalised innovation
  squared y^T S^-1 y of its accepted updates, summed over windows and tested as a scaled
  chi-square against the family's usual self (:class:`InnovationTest`). It needs no
  ground truth: an update whose innovation is larger than the filter's covariance predicts
  says that covariance (or the measurement's) is optimistic.

:meth:`HealthMonitor.report` returns the figures and at most one warning line per cause.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field
from statistics import NormalDist

import numpy as np
from numpy.typing import NDArray

from vio_graph.filter.gating import chi2_2dof_quantile
from vio_graph.types import Displacement2D

#: the 2x2 identity, never written (``_I2 * v`` is ``np.eye(2) * v``, a new array)
_I2 = np.eye(2)


@dataclass(frozen=True)
class HealthLimits:
    """When the monitor warns. Not fitted to a gait: shares and chi-square probabilities."""

    window_s: float = 1.0  #: length (s) of the fused-vs-visual comparison windows
    probability: float = 0.999  #: chi-square probability of one window's test
    floor_m: float = 0.002  #: sigma (m) per axis added to each frame's displacement
    max_rejected_share: float = 0.2  #: warn above this share of refused displacements
    max_departure_share: float = 0.1  #: warn above this share of windows failing the test
    max_stance_share: float = 0.8  #: stance on more frames than this is suspicious
    max_pitch_offset_deg: float = 3.0  #: level surfaces disagree with the IMU by more
    #: the level surfaces disagree with the IMU's gravity by more than this on their own: a
    #: mounting error, whatever the refusals say (a vendor orientation is ~1 deg off, and the
    #: correction stayed within 2.3 deg on every simulated trial with a correct mount)
    max_pitch_offset_alone_deg: float = 5.0
    #: one window this far off is a jump, whatever the share (chi-square p = 1 - 1e-6: a
    #: healthy filter reaches it once in a million windows)
    jump_probability: float = 1.0 - 1e-6
    #: a visual displacement whose x sigma (m) is at most this carries forward information
    x_informative_sigma_m: float = 0.01
    #: warn when nothing but the IMU carried x (no x-informative displacement, corner or
    #: stance anchor) for more than this share of the trial
    max_x_blind_share: float = 1.0 / 3.0
    #: warn when, over one such stretch that began with or holds IMU samples the fault
    #: monitor distrusted (saturated, repaired), the filter's own velocity sigma integrated
    #: over time (how far x may have drifted by its own account) exceeds this (m): the
    #: project's 2 cm accuracy aim. Clean stretches are left to the share above: there the
    #: sum is 1-8 cm on the simulated trials (conservative: their errors are 0.4-1.8 cm)
    max_blind_drift_sigma_m: float = 0.02
    #: innovation consistency (:class:`InnovationTest`): length (s) of its windows
    innovation_window_s: float = 1.0
    #: chi-square probability of one window's test (a window fails above it: 1 % of windows
    #: of a filter as consistent as on the reference trials)
    innovation_probability: float = 0.99
    #: warn when a family's count of failing windows is this improbable for windows that
    #: fail independently with 1 - innovation_probability each (binomial tail): one failing
    #: window never warns, two do in a trial of up to 15 windows, three up to 44
    innovation_trial_probability: float = 0.01
    #: the filter's usual self per measurement family: (mean normalised innovation squared
    #: per degree of freedom, dispersion of the window means against a chi-square's), pooled
    #: over the four paper scenarios, seeds 1-3 (docs/method.md, "Innovation consistency").
    #: Not 1: the front end's covariances carry floors (its displacement NEES is 4-5 before
    #: them), so an honest filter's NIS is well below 1; the test asks whether a run is
    #: worse than that, not whether NIS = 1.
    #: offline (:func:`disagreement_warning`): warn when a smoother's path and the filter's
    #: differ by more than the filter's covariance allows (chi-square, 99.9 %, per frame) on
    #: more than this share of frames (a consistent pair: at most 0.1 %)...
    max_disagreement_share: float = 0.05
    #: ...and by at least this much (m) somewhere; or, whatever the covariance, by this much
    #: RMS over the trial: two paths this far apart cannot both be within half of it (the
    #: triangle inequality), so one is off by at least half the project's 2 cm aim
    min_disagreement_m: float = 0.02
    innovation_reference: dict[str, tuple[float, float]] = field(
        hash=False,  # (a dict: HealthLimits stays hashable without it)
        default_factory=lambda: {
            "displacement": (0.14, 22.0),
            "corner": (0.052, 39.0),
            "level": (0.18, 14.0),
            "stance": (0.037, 13.0),
        },
    )


@dataclass
class _Window:
    t0_s: float
    p0_xz_m: NDArray[np.float64]
    sum_delta_xz_m: NDArray[np.float64] = field(default_factory=lambda: np.zeros(2))
    sum_cov_m2: NDArray[np.float64] = field(default_factory=lambda: np.zeros((2, 2)))


class HealthMonitor:
    """Per-frame bookkeeping of the estimator's consistency; see the module docstring."""

    def __init__(self, limits: HealthLimits | None = None) -> None:
        self.limits = limits or HealthLimits()
        self._gate_d2 = chi2_2dof_quantile(self.limits.probability)
        self._jump_d2 = chi2_2dof_quantile(self.limits.jump_probability)
        self.n_frames = 0
        self.n_displacements = 0  # frames with a visual displacement from the front end
        self.n_refused = 0  # ... that the filter's gate refused
        self.n_stance = 0  # frames anchored in stance
        self.n_windows = 0
        self.n_departures = 0
        self.max_departure_m = 0.0
        self.max_departure_d2 = 0.0  # largest Mahalanobis^2 of a window
        self.n_recoveries = 0  # gate lock-out recoveries of the filter (estimator sets it)
        # lost-track searches that found a displacement, and those the filter fused (the
        # estimator sets them; frontend TrackerConfig.relocalise_after_frames)
        self.n_relocalised = 0
        self.n_relocalised_fused = 0
        self.first_relocalised_s: float | None = None
        #: per-family consistency of the filter's own innovations (:class:`InnovationTest`)
        self.innovations = {
            f: InnovationTest(self.limits, f) for f in self.limits.innovation_reference
        }
        self.n_untested_innovations = 0  # updates of other families (the saturation bridge)
        self._prev: tuple[float, NDArray[np.float64]] | None = None  # (t, fused camera xz)
        self._window: _Window | None = None
        # forward (x) observability: runs of frames on which nothing but the IMU carried x
        self._x_blind_since: float | None = None
        self._t_first_s: float | None = None
        self.x_blind_s = 0.0  # summed length (s) of those runs
        self.max_x_blind_s = 0.0  # the longest run (s)
        # the filter's x velocity sigma integrated over a run (m): its own drift bound
        self._drift_sigma_m = 0.0
        self._prev_v_sigma: tuple[float, float] | None = None  # (t, x velocity sigma)
        self.max_drift_sigma_m = 0.0
        self.max_drift_at_s = 0.0  # end time (s) of the run with the largest one
        # the same over runs with distrusted IMU samples (the warning's figure)
        self._run_distrusted_from = 0  # distrusted-sample count when the run began
        self.max_distrusted_drift_sigma_m = 0.0
        self.max_distrusted_drift_at_s = 0.0
        self._n_distrusted = 0
        # pixels that moved with the camera (an occluder), removed by the front end
        self.n_camera_fixed_frames = 0
        self.max_camera_fixed_pixels = 0
        self.camera_fixed_first_s: float | None = None
        self.camera_fixed_last_s: float | None = None
        self._cf_run_start: float | None = None
        self.max_camera_fixed_run_s = 0.0
        self._cf_run_frames = 0
        #: frames in the longest run of consecutive frames with camera-fixed pixels
        self.max_camera_fixed_run_frames = 0

    def add_frame(
        self,
        t_s: float,
        fused_camera_xz_m: NDArray[np.float64],
        displacement: Displacement2D | None,
        accepted: bool,
        in_stance: bool,
        landmark_seen: bool = False,
        refused: bool | None = None,
        velocity_sigma_x_mps: float | None = None,
        distrusted_imu_samples: int = 0,
        camera_fixed_pixels: int = 0,
    ) -> None:
        """One depth frame: the fused camera position after the update, the front end's
        displacement (None: none), whether the filter accepted it, whether it was anchored,
        whether a corner landmark was observed, and whether the gate refused it (None: every
        displacement not accepted counts as refused; the estimator tells a gate refusal from
        a displacement it could not relate to its state, e.g. across a frame gap).
        ``velocity_sigma_x_mps``: the filter's 1-sigma of the forward velocity after the
        update (None: not tracked); ``distrusted_imu_samples``: how many IMU samples the
        fault monitor has distrusted so far (saturated, repaired); ``camera_fixed_pixels``:
        pixels the front end removed from this frame as moving with the camera."""
        p = np.asarray(fused_camera_xz_m, dtype=float)
        self._track_camera_fixed(float(t_s), int(camera_fixed_pixels))
        self.n_frames += 1
        self.n_stance += int(in_stance)
        if self._t_first_s is None:
            self._t_first_s = float(t_s)
        prev, self._prev = self._prev, (float(t_s), p.copy())
        x_seen = (
            in_stance
            or landmark_seen
            or (
                accepted
                and displacement is not None
                and float(displacement.cov_m2[0][0]) <= self.limits.x_informative_sigma_m**2
            )
        )
        self._track_x_blind(float(t_s), x_seen)
        self._track_drift(float(t_s), x_seen, velocity_sigma_x_mps, int(distrusted_imu_samples))
        if displacement is None:
            self._window = None  # the visual chain is broken
            return
        self.n_displacements += 1
        self.n_refused += int(not accepted if refused is None else refused)
        if prev is None or abs(displacement.t0_s - prev[0]) > 1e-6:
            self._window = None
            return
        w = self._window
        if w is None:
            w = self._window = _Window(prev[0], prev[1])
        w.sum_delta_xz_m = w.sum_delta_xz_m + np.asarray(displacement.delta_xz_m, dtype=float)
        w.sum_cov_m2 = (
            w.sum_cov_m2
            + np.asarray(displacement.cov_m2, dtype=float)
            + _I2 * self.limits.floor_m**2
        )
        if t_s - w.t0_s >= self.limits.window_s:
            r = (p - w.p0_xz_m) - w.sum_delta_xz_m
            d2 = float(r @ np.linalg.solve(w.sum_cov_m2, r))
            self.n_windows += 1
            self.n_departures += int(d2 > self._gate_d2)
            self.max_departure_m = max(self.max_departure_m, float(np.hypot(*r)))
            self.max_departure_d2 = max(self.max_departure_d2, d2)
            self._window = _Window(float(t_s), p.copy())

    def add_innovations(
        self, t_s: float, family: str, items: list[tuple[float, int, bool]]
    ) -> None:
        """The filter's updates of one measurement family at time ``t_s`` (s): (normalised
        innovation squared y^T S^-1 y, its degrees of freedom, accepted)."""
        test = self.innovations.get(family)
        if test is None:
            self.n_untested_innovations += len(items)
            return
        for d2, m, accepted in items:
            test.add(float(t_s), float(d2), int(m), bool(accepted))

    def _track_camera_fixed(self, t_s: float, n_pixels: int) -> None:
        if n_pixels <= 0:
            self._cf_run_start = None
            self._cf_run_frames = 0
            return
        self._cf_run_frames += 1
        self.max_camera_fixed_run_frames = max(
            self.max_camera_fixed_run_frames, self._cf_run_frames
        )
        self.n_camera_fixed_frames += 1
        self.max_camera_fixed_pixels = max(self.max_camera_fixed_pixels, n_pixels)
        if self.camera_fixed_first_s is None:
            self.camera_fixed_first_s = t_s
        self.camera_fixed_last_s = t_s
        if self._cf_run_start is None:
            self._cf_run_start = t_s
        self.max_camera_fixed_run_s = max(self.max_camera_fixed_run_s, t_s - self._cf_run_start)

    def _track_x_blind(self, t_s: float, x_seen: bool) -> None:
        if not x_seen:
            if self._x_blind_since is None:
                self._x_blind_since = t_s
            return
        if self._x_blind_since is not None:
            run = t_s - self._x_blind_since
            self.x_blind_s += run
            self.max_x_blind_s = max(self.max_x_blind_s, run)
            self._x_blind_since = None

    def _track_drift(
        self, t_s: float, x_seen: bool, v_sigma: float | None, n_distrusted: int
    ) -> None:
        """Integrate the x velocity sigma (trapezoid) over each run of x-blind frames (up to
        and including the frame that ends it), and note whether IMU samples were distrusted
        since the run began (in the frame interval that started it included)."""
        self._n_distrusted = n_distrusted
        prev, self._prev_v_sigma = (
            self._prev_v_sigma,
            (None if v_sigma is None else (t_s, float(v_sigma))),
        )
        if prev is not None and v_sigma is not None:
            self._drift_sigma_m += 0.5 * (prev[1] + float(v_sigma)) * (t_s - prev[0])
            if self._drift_sigma_m > self.max_drift_sigma_m:
                self.max_drift_sigma_m = self._drift_sigma_m
                self.max_drift_at_s = t_s
            distrusted = n_distrusted > self._run_distrusted_from
            if distrusted and self._drift_sigma_m > self.max_distrusted_drift_sigma_m:
                self.max_distrusted_drift_sigma_m = self._drift_sigma_m
                self.max_distrusted_drift_at_s = t_s
        if x_seen:
            self._drift_sigma_m = 0.0
            self._run_distrusted_from = n_distrusted

    def report(self, pitch_offset_deg: float = 0.0) -> dict:
        """Figures and warnings so far. ``pitch_offset_deg``: the level-surface correction
        of the IMU pitch (filter/attitude.PitchOffsetFilter), a hint for mounting errors."""
        lim = self.limits
        open_run = (  # a stretch still running at the latest frame
            self._prev[0] - self._x_blind_since
            if self._x_blind_since is not None and self._prev is not None
            else 0.0
        )
        longest_x_blind = max(self.max_x_blind_s, open_run)
        x_blind_s = self.x_blind_s + open_run
        rejected = _share(self.n_refused, self.n_displacements)
        departure = _share(self.n_departures, self.n_windows)
        stance = _share(self.n_stance, self.n_frames)
        warnings: list[str] = []
        jump = self.max_departure_d2 > self._jump_d2
        trouble = (
            rejected > lim.max_rejected_share
            or departure > lim.max_departure_share
            or jump
            or abs(pitch_offset_deg) > lim.max_pitch_offset_alone_deg
        )
        if trouble:
            what = (
                f"{100 * rejected:.0f} % of visual displacements were refused by the "
                f"filter's gate and the fused path left visual odometry in "
                f"{100 * departure:.0f} % of {lim.window_s:g} s windows (up to "
                f"{100 * self.max_departure_m:.1f} cm"
                + (f", {self.n_recoveries} gate lock-out recoveries" if self.n_recoveries else "")
                + ")"
            )
            if abs(pitch_offset_deg) > lim.max_pitch_offset_deg:
                cause = (
                    f"the IMU attitude disagrees with the level surfaces by "
                    f"{pitch_offset_deg:.1f} deg: check imu_T_cam / knee_T_cam (the IMU "
                    f"and camera mounting) in metadata.yaml"
                )
            elif stance > lim.max_stance_share:
                cause = (
                    f"the foot was anchored in stance on {100 * stance:.0f} % of frames: "
                    f"the stance detector may be flagging swings (slow gait?); try "
                    f"filter.stance_anchor: false"
                )
            else:
                cause = (
                    "vision and the IMU disagree: check the camera-IMU time offset, "
                    "imu_T_cam and the IMU noise settings"
                )
            warnings.append(
                f"WARNING: the fused estimate is inconsistent: {what}. Likely cause: {cause}."
            )
        duration_s = (
            0.0
            if self._prev is None or self._t_first_s is None
            else self._prev[0] - self._t_first_s
        )
        x_blind_share = x_blind_s / duration_s if duration_s > 0 else 0.0
        weak_x = x_blind_share > lim.max_x_blind_share and not trouble  # one cause at a time
        if weak_x:
            warnings.append(
                f"WARNING: the forward (x) position was carried by the IMU alone on "
                f"{100 * x_blind_share:.0f} % of the trial (longest {longest_x_blind:.1f} s): no "
                f"riser, corner or stance anchor constrained it, so x may have drifted by "
                f"centimetres without the filter's covariance showing it. Likely cause: level "
                f"floor with no edge in view (vision measures no forward motion there) and "
                f"few detected stances (fast walking), or a camera that sees no risers."
            )
        drift_m = self.max_distrusted_drift_sigma_m
        drift = drift_m > lim.max_blind_drift_sigma_m and not (trouble or weak_x)
        if drift:
            warnings.append(
                f"WARNING: by the filter's own covariance, its forward (x) position may have "
                f"drifted by {100 * drift_m:.1f} cm (1-sigma) up to "
                f"{self.max_distrusted_drift_at_s:.2f} s, where nothing but the IMU carried x. "
                f"Likely cause: IMU samples it could not trust ({self._n_distrusted} saturated "
                f"or repaired in the trial) followed by a stretch where vision measured no "
                f"forward motion (level floor, no edge in view); the smoothers correct it "
                f"once a stance or an edge follows."
            )
        if self.n_relocalised_fused:
            warnings.append(
                f"WARNING: the visual front end lost track and found it again by an unseeded "
                f"search on {self.n_relocalised_fused} frames (first at "
                f"{self.first_relocalised_s:.2f} s): the IMU prediction had moved farther from "
                f"the truth than ICP can reach from it. Likely cause: saturated or corrupted "
                f"IMU samples (a knock, a fast swing beyond the accelerometer's range) or a "
                f"long stretch without vision; the estimate around then is less certain."
            )
        bad = [t for t in self.innovations.values() if t.inconsistent]
        if bad:
            worst = max(bad, key=lambda t: (t.failing_share, t.max_window_ratio))
            what = "; ".join(
                f"{t.family} {100 * t.failing_share:.0f} % of {t.n_windows} windows (mean "
                f"NIS per dof {t.nis_sum / t.dof_sum:.2f}, {t.nis_sum / t.dof_sum / t.scale:.1f}x "
                f"its usual {t.scale:.2g})"
                for t in bad
            )
            warnings.append(
                f"WARNING: the filter's innovations are larger than its own covariance "
                f"predicts ({what} failed the {100 * (1 - lim.innovation_probability):g} % "
                f"chi-square test of {lim.innovation_window_s:g} s windows): its uncertainty "
                f"is optimistic and the estimate may be off by more than it claims. Likely "
                f"cause: {_INNOVATION_CAUSES.get(worst.family, 'unknown')}."
            )
        # an object fixed to the rig is found again on the next frame (once found, every
        # frame is tested); a detection that does not repeat is the test's own chance
        # coincidence (41-329 pixels on single frames of 2 of 108 clean sweep trials), counted
        # in the figures below but not warned about
        if self.max_camera_fixed_run_frames >= 2:
            warnings.append(
                f"WARNING: something moved with the camera (an occluding foot or strap close "
                f"to the lens?) on {self.n_camera_fixed_frames} frames between "
                f"{self.camera_fixed_first_s:.2f} s and {self.camera_fixed_last_s:.2f} s (up to "
                f"{self.max_camera_fixed_pixels} pixels, longest run "
                f"{self.max_camera_fixed_run_s:.2f} s): removed from the slice unless "
                f"frontend.camera_fixed.drop_pixels is off (then it was taken for terrain "
                f"there, and the estimate may have jumped)."
            )
        return {
            "frames": self.n_frames,
            "visual_displacements": self.n_displacements,
            "displacements_rejected_share": rejected,
            "stance_share": stance,
            "fused_vs_visual": {
                "windows": self.n_windows,
                "window_s": lim.window_s,
                "departure_share": departure,
                "max_departure_cm": 100.0 * self.max_departure_m,
                "max_mahalanobis2": self.max_departure_d2,
                "jump": jump,
            },
            "recoveries": self.n_recoveries,
            "relocalisations": {
                "found": self.n_relocalised,
                "fused": self.n_relocalised_fused,
                "first_s": self.first_relocalised_s,
            },
            "x_blind": {
                "total_s": x_blind_s,
                "share": x_blind_share,
                "longest_s": longest_x_blind,
                "warned": weak_x,
                "max_drift_sigma_cm": 100 * self.max_drift_sigma_m,
                "max_drift_at_s": self.max_drift_at_s,
                "max_drift_sigma_after_distrusted_imu_cm": 100 * drift_m,
                "drift_warned": drift,
            },
            "camera_fixed": {
                "frames": self.n_camera_fixed_frames,
                "max_pixels": self.max_camera_fixed_pixels,
                "first_s": self.camera_fixed_first_s,
                "last_s": self.camera_fixed_last_s,
                "longest_run_s": self.max_camera_fixed_run_s,
                "longest_run_frames": self.max_camera_fixed_run_frames,
            },
            "pitch_offset_deg": float(pitch_offset_deg),
            "innovations": {f: t.summary() for f, t in self.innovations.items()}
            | {"untested_updates": self.n_untested_innovations},
            "innovations_consistent": not bad,
            "ok": not (trouble or weak_x or drift or bad),
            "warnings": warnings,
        }


def input_fault_context(imu_faults: dict, stamp_test: dict | None) -> list[str]:
    """Faults the estimator itself found in this run's inputs that make its IMU prediction,
    and so its innovations, less reliable than its noise settings say: IMU samples at the
    declared range (clipped; ``imu_faults`` of :meth:`OnlineEstimator.fault_report`) and
    camera stamps the frame-stamp test replaced by the clock line (``stamp_test``). One
    phrase each, for the warning that follows an innovation inconsistency; empty when the
    inputs looked clean. No threshold of its own: these are the monitors' decisions."""
    out = []
    n_acc = int(imu_faults.get("accel_saturated_samples", 0))
    n_gyr = int(imu_faults.get("gyro_saturated_samples", 0))
    if n_acc or n_gyr:
        what = " and ".join(
            f"{n} {axis} sample{'s' if n != 1 else ''}"
            for n, axis in ((n_acc, "accelerometer"), (n_gyr, "gyroscope"))
            if n
        )
        out.append(
            f"{what} at the IMU's declared range (clipped: the prediction through them is "
            f"bridged, not measured; metrics.json imu_faults)"
        )
    if stamp_test and (stamp_test.get("stamps") == "clock line" or stamp_test.get("switches")):
        out.append(
            "camera stamps that scatter about the camera's clock line (the frame-stamp test "
            f"switched {int(stamp_test.get('switches', 0))} time(s); clock jitter: "
            "metrics.json timestamps.camera)"
        )
    return out


#: what a family's inconsistency most likely means (the warning's "likely cause")
_INNOVATION_CAUSES = {
    "displacement": (
        "the visual displacements scatter more than the front end's covariances say: depth "
        "noisier than its model (ToF noise, dark or shiny surfaces, sunlight), or the IMU "
        "prediction is off (camera-IMU time offset, imu_T_cam, IMU noise settings)"
    ),
    "corner": (
        "the stair-corner positions scatter more than their sigmas: noisy depth near the "
        "nosings, or corners re-identified on the wrong step (irregular stairs)"
    ),
    "level": (
        "the level surfaces' heights scatter more than their sigmas: depth noisier than the "
        "front end's model (ToF noise), or treads that are not level"
    ),
    "stance": (
        "the ankle anchor disagrees with the IMU-propagated position: the IMU is noisier "
        "than the filter's noise settings (a consumer-grade or low-rate IMU: check "
        "filter.accel_noise_sigma_mps2), a slipping foot, or a stance detector flagging parts "
        "of the swing or of a rolling foot (with filter.stance_contact propose or confirm, "
        "a loaded foot whose ankle still moves: try filter.stance_contact: off; else "
        "filter.stance_anchor: false)"
    ),
}


def binomial_tail(k: int, n: int, p: float) -> float:
    """P(X >= k) for X ~ Binomial(n, p) (1 for k <= 0)."""
    if k <= 0:
        return 1.0
    return float(sum(math.comb(n, j) * p**j * (1.0 - p) ** (n - j) for j in range(k, n + 1)))


def chi2_quantile_wh(probability: float, dof: float) -> float:
    """Quantile of the chi-square distribution with ``dof`` (> 0, not necessarily an
    integer) degrees of freedom, Wilson-Hilferty's cube-root normal approximation:
    dof (1 - 2 / (9 dof) + z sqrt(2 / (9 dof)))^3, z the normal quantile. Within 1 % of the
    exact value at p = 0.99 from dof = 1 on (4 % at 0.5, worse below: the test keeps
    dof >= 1; tests/test_health_innovations.py)."""
    if dof <= 0:
        raise ValueError(f"dof must be positive, got {dof}")
    z = NormalDist().inv_cdf(probability)
    a = 2.0 / (9.0 * dof)
    return float(dof * max(1.0 - a + z * math.sqrt(a), 0.0) ** 3)


class InnovationTest:
    """Consistency of one measurement family's innovations with the filter's covariance.

    Every update the filter makes has a normalised innovation squared d2 = y^T S^-1 y with
    m = dim(y) degrees of freedom; if the filter's covariance and the measurement's are
    honest, d2 is chi-square(m). Over windows of ``innovation_window_s`` the sum q of the
    accepted updates' d2 and the sum k of their m are compared with the family's usual self
    (``innovation_reference``: mean d2 per dof c, dispersion phi of the window means
    against a chi-square's, which covers heavy tails and updates correlated within a
    window): q / (c phi) against the chi-square quantile with k / phi dof at
    ``innovation_probability`` (a scaled chi-square matched to the reference's first two
    moments). Windows are consecutive, each closed by the first update at least
    ``innovation_window_s`` after its first one once it holds k >= phi (at least one
    effective degree of freedom); the last, open window is not tested. The family is
    inconsistent when its count of failing windows is improbable (binomial tail below
    ``innovation_trial_probability``) for windows failing at the test's own rate. Refused
    (gated) updates are counted but not summed: the gate truncates d2, and refusals have
    their own share in the report."""

    def __init__(self, limits: HealthLimits, family: str) -> None:
        self.limits = limits
        self.family = family
        c, phi = limits.innovation_reference[family]
        if c <= 0 or phi <= 0:
            raise ValueError(f"innovation reference of {family} must be positive, got {c}, {phi}")
        self.scale, self.dispersion = float(c), float(phi)
        self.n_accepted = self.n_refused = 0
        self.nis_sum = 0.0  # sum of d2 of accepted updates
        self.dof_sum = 0
        self.n_windows = self.n_failing = 0
        self.max_window_ratio = 0.0  # largest window mean d2 per dof / c
        self.dispersion_sum = 0.0  # sum over windows of (ratio - 1)^2 k / 2
        self._t0: float | None = None
        self._q = 0.0
        self._k = 0

    def add(self, t_s: float, d2: float, m: int, accepted: bool) -> None:
        """One update at ``t_s`` (s): its y^T S^-1 y, dimension and outcome."""
        if not accepted:
            self.n_refused += 1
            return
        if not math.isfinite(d2):
            return
        if (
            self._t0 is not None
            and t_s - self._t0 >= self.limits.innovation_window_s
            and self._k >= self.dispersion
        ):
            self._close()
        if self._t0 is None:
            self._t0 = t_s
        self.n_accepted += 1
        self.nis_sum += d2
        self.dof_sum += m
        self._q += d2
        self._k += m

    def _close(self) -> None:
        q, k = self._q, self._k
        self._t0, self._q, self._k = None, 0.0, 0
        if k == 0:
            return
        ratio = q / (self.scale * k)
        nu = k / self.dispersion
        self.n_windows += 1
        self.n_failing += int(
            q / (self.scale * self.dispersion)
            > chi2_quantile_wh(self.limits.innovation_probability, nu)
        )
        self.max_window_ratio = max(self.max_window_ratio, ratio)
        self.dispersion_sum += (ratio - 1.0) ** 2 * k / 2.0

    @property
    def failing_share(self) -> float:
        return _share(self.n_failing, self.n_windows)

    @property
    def trial_p_value(self) -> float:
        """Probability of at least :attr:`n_failing` failing windows out of :attr:`n_windows`
        if each failed independently at the test's rate (binomial tail)."""
        return binomial_tail(
            self.n_failing, self.n_windows, 1.0 - self.limits.innovation_probability
        )

    @property
    def inconsistent(self) -> bool:
        """Persistently worse than the family's usual self."""
        return self.trial_p_value < self.limits.innovation_trial_probability

    def summary(self) -> dict:
        """The figures of metrics.json ``health.innovations.<family>``."""
        return {
            "updates": self.n_accepted + self.n_refused,
            "refused": self.n_refused,
            "dof": self.dof_sum,
            "nis_sum": self.nis_sum,
            "mean_nis_per_dof": self.nis_sum / self.dof_sum if self.dof_sum else float("nan"),
            "reference_nis_per_dof": self.scale,
            "reference_dispersion": self.dispersion,
            "ratio_to_reference": (
                self.nis_sum / (self.dof_sum * self.scale) if self.dof_sum else float("nan")
            ),
            "windows": self.n_windows,
            "failing_windows": self.n_failing,
            "failing_share": self.failing_share,
            "trial_p_value": self.trial_p_value,
            "max_window_ratio": self.max_window_ratio,
            "window_dispersion": (
                self.dispersion_sum / self.n_windows if self.n_windows else float("nan")
            ),
            "inconsistent": self.inconsistent,
        }


def _share(part: int, whole: int) -> float:
    return float(part) / whole if whole else 0.0


def smoothed_vs_filtered(
    t_s: NDArray[np.float64],
    filter_xz_m: NDArray[np.float64],
    filter_cov_m2: NDArray[np.float64],
    other_xz_m: NDArray[np.float64],
    probability: float = 0.999,
) -> dict:
    """Offline consistency of a second estimate of the same path (a smoother's) with the
    filter's, per axis (x, z). Report only: nothing is changed.

    Both paths are anchored at their first pose (as the ATE). The difference of two
    estimates of one path has covariance P_f - P_s for a smoother that saw every
    measurement the filter did (Rauch-Tung-Striebel), which is at most the filter's own
    P_f. So d^2 = (x_s - x_f)^2 / P_f,xx is at most the difference's chi-square (1 dof),
    a conservative test: beyond its ``probability`` quantile one of the two estimates is
    further from the other than the filter's covariance allows, i.e. one of them is wrong
    (which, the test cannot say). ``t_s`` (N,) s, ``*_xz_m`` (N, 2) m, ``filter_cov_m2``
    (N, 2, 2) m^2; frames with a non-positive or non-finite variance or a non-finite
    position are left out. Returns per axis the frames tested, the share beyond the
    quantile, the largest d^2 with its time and difference (cm), and the largest and
    RMS difference (cm). The RMS difference needs no covariance: by the triangle
    inequality it is at most the sum of the two paths' RMS errors, so a difference
    above twice an accuracy aim means one of them misses it."""
    t = np.asarray(t_s, dtype=float)
    f = np.asarray(filter_xz_m, dtype=float).reshape(-1, 2)
    o = np.asarray(other_xz_m, dtype=float).reshape(-1, 2)
    var = np.asarray(filter_cov_m2, dtype=float).reshape(-1, 2, 2)[:, [0, 1], [0, 1]]
    diff = (o - o[:1]) - (f - f[:1]) if len(f) else np.zeros((0, 2))
    z = NormalDist().inv_cdf(0.5 * (1.0 + probability))
    limit = z * z  # the chi-square (1 dof) quantile, exact
    out: dict = {"probability": probability, "chi2_limit": limit}
    for j, axis in enumerate("xz"):
        ok = np.isfinite(diff[:, j]) & np.isfinite(var[:, j]) & (var[:, j] > 0)
        if not ok.any():
            out[axis] = {
                "frames": 0,
                "beyond_share": 0.0,
                "max_d2": 0.0,
                "max_d2_at_s": None,
                "difference_at_max_cm": 0.0,
                "max_difference_cm": 0.0,
                "rms_difference_cm": 0.0,
            }
            continue
        d2 = diff[ok, j] ** 2 / var[ok, j]
        k = int(np.argmax(d2))
        out[axis] = {
            "frames": int(ok.sum()),
            "beyond_share": float(np.mean(d2 > limit)),
            "max_d2": float(d2[k]),
            "max_d2_at_s": float(t[ok][k]),
            "difference_at_max_cm": float(100.0 * diff[ok, j][k]),
            "max_difference_cm": float(100.0 * np.max(np.abs(diff[ok, j]))),
            "rms_difference_cm": float(100.0 * np.sqrt(np.mean(diff[ok, j] ** 2))),
        }
    out["consistent"] = all(out[a]["max_d2"] <= limit for a in "xz")
    return out


def disagreement_warning(
    mode: str, consistency: dict, limits: HealthLimits | None = None
) -> str | None:
    """A warning when ``mode``'s path (a smoother's) and the filter's disagree, or None.

    ``consistency`` is :func:`smoothed_vs_filtered`'s report. The pair is in trouble on an
    axis when their RMS difference is at least ``min_disagreement_m`` (no covariance needed:
    one of the two is then off by at least half of it, RMS), or when more than
    ``max_disagreement_share`` of the frames are beyond the chi-square quantile (the
    difference is larger than the filter's covariance allows) *and* the paths are at least
    ``min_disagreement_m`` apart somewhere: one of them is off by more than it claims, by a
    size that matters. Which one, the test cannot say: the filter's own innovation
    warnings, if any, point at the filter."""
    lim = limits or HealthLimits()
    parts = []
    for axis, name in (("x", "forward (x)"), ("z", "height (z)")):
        a = consistency.get(axis) or {}
        share = float(a.get("beyond_share", 0.0))
        apart_cm = float(a.get("max_difference_cm", 0.0))
        rms_cm = float(a.get("rms_difference_cm", 0.0))
        size_cm = 100.0 * lim.min_disagreement_m
        if rms_cm >= size_cm or (share > lim.max_disagreement_share and apart_cm >= size_cm):
            parts.append(
                f"{name} by {rms_cm:.1f} cm RMS (up to {apart_cm:.1f} cm; beyond the filter's "
                f"covariance on {100.0 * share:.0f} % of frames)"
            )
    if not parts:
        return None
    return (
        f"WARNING: the {mode}'s path and the filter's disagree in "
        + " and in ".join(parts)
        + ": at least one of them is off by more than it claims (the test cannot say which; "
        "compare the two paths, and see any innovation warning above for the filter). "
        f"metrics.json health.{mode}_vs_filter."
    )


def filter_sigma_summary(filter_cov_m2: NDArray[np.float64]) -> dict:
    """The filter's own position sigma (cm) per axis: median, 95th percentile and last
    frame. Report only; it says how far the filter itself claims it may be off (a
    consistent filter with an x sigma of 1.8 cm is within 2 cm only about as often as
    a normal variable is within 1.1 sigma)."""
    var = np.asarray(filter_cov_m2, dtype=float).reshape(-1, 2, 2)[:, [0, 1], [0, 1]]
    out: dict = {}
    for j, axis in enumerate("xz"):
        v = var[np.isfinite(var[:, j]) & (var[:, j] >= 0), j]
        s = 100.0 * np.sqrt(v) if v.size else np.array([np.nan])
        out[axis] = {
            "median_cm": float(np.median(s)),
            "p95_cm": float(np.percentile(s, 95)),
            "last_cm": float(s[-1]),
        }
    return out
