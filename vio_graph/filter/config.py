"""Configuration of the SP-ESKF (paper Section II.C, eq. 5-8).

Defaults come from the Xsens MTi-1 series datasheet (accelerometer noise density
120 ug/sqrt(Hz) = 1.18e-3 m/s^2/sqrt(Hz); in-run bias stability 0.03 mg) and from the
paper's setup (IMU at 100 Hz, depth camera at 30 fps). Every field carries its unit in its
name or description.
"""

from __future__ import annotations

import math
from typing import Literal

from pydantic import BaseModel, ConfigDict, Field, field_validator

from vio_graph.geometry import GRAVITY_MPS2

#: Xsens MTi-1 accelerometer noise density, m/s^2/sqrt(Hz) (datasheet: 120 ug/sqrt(Hz)).
MTI1_ACCEL_NOISE_DENSITY_MPS2_PER_SQRT_HZ = 1.18e-3
#: IMU output rate used in the paper, Hz.
PAPER_IMU_RATE_HZ = 100.0
#: per-sample accelerometer white-noise sigma of the MTi-1 at 100 Hz (the paper's sigma_a), m/s^2
MTI1_ACCEL_SIGMA_MPS2 = MTI1_ACCEL_NOISE_DENSITY_MPS2_PER_SQRT_HZ * math.sqrt(PAPER_IMU_RATE_HZ)


class AttitudeConfig(BaseModel):
    """Where the slice rotation of eq. 2 comes from (module docstring)."""

    model_config = ConfigDict(extra="forbid", frozen=True)

    source: Literal["vendor", "vendor_extrapolated", "complementary"] = Field(
        default="complementary",
        description="'vendor' = the paper (latest vendor orientation); 'vendor_extrapolated' "
        "= rotated on by the gyro to the frame time; 'complementary' = gyro-integrated, "
        "pulled towards the vendor orientation, extrapolated to the frame time",
    )
    time_constant_s: float = Field(
        default=1.0,
        gt=0,
        description="complementary filter: time constant (s) of the pull towards the vendor "
        "orientation",
    )
    vendor_pitch_sigma_deg: float | Literal["auto"] | None = Field(
        default=None,
        description="complementary filter with the level-surface pitch aiding on: the vendor "
        "orientation's pitch error sigma (deg, MTi-1 ~1 deg RMS dynamic), or 'auto' to "
        "estimate it online from the vendor's disagreement with the level-aided pitch "
        "(VendorPitchVariance, over vendor_sigma_memory_s). The pull towards the vendor about "
        "the pitch axis is then weighed against the level-aided pitch offset's own variance "
        "(not below level_aiding.measurement_floor_deg^2, the tilt error shared by frames): its "
        "time constant becomes time_constant_s x (var_offset + var_vendor) / var_offset (12 s "
        "at the 0.3 deg floor and 1 deg vendor), so while level surfaces hold the pitch to a "
        "fraction of a degree the vendor's correlated error is not imported at its own pace, "
        "and when they are lost (the offset's variance grows) the pull returns to "
        "time_constant_s. Roll and heading, which no level surface observes, keep "
        "time_constant_s (the pull bounds the gyro bias's drift there). None = the fixed "
        "time_constant_s on every axis",
    )
    vendor_sigma_memory_s: float = Field(
        default=30.0,
        gt=0,
        description="vendor_pitch_sigma_deg 'auto': time (s) over which the disagreements are "
        "forgotten (exponential weights); many times the vendor error's correlation time "
        "(~2 s) so that the variance is averaged over several of its swings",
    )

    @field_validator("vendor_pitch_sigma_deg")
    @classmethod
    def _positive_sigma(cls, v: float | str | None) -> float | str | None:
        if isinstance(v, float) and not 0.0 < v < math.inf:
            raise ValueError(f"vendor_pitch_sigma_deg must be > 0 and finite or 'auto', got {v}")
        return v


class LevelAidingConfig(BaseModel):
    """Pitch aiding from level surfaces (frontend/level.py, filter/attitude.PitchOffsetFilter).

    Floors, treads and obstacle tops are horizontal; their tilt in the ground-frame slice is
    the pitch error of the attitude. Defaults: the vendor error drifts ~1 deg RMS with a
    correlation time of ~2 s (MTi-1 datasheet), a line fit over >= 12 cm of
    floor has a slope error of ~0.1 deg.
    """

    model_config = ConfigDict(extra="forbid", frozen=True)

    enabled: bool = Field(default=True, description="False = the IMU attitude as is (the paper)")
    max_tilt_deg: float = Field(
        default=5.0, gt=0, le=20, description="only lines within this angle of horizontal (deg)"
    )
    inlier_m: float = Field(default=0.004, gt=0, description="line inlier distance (m)")
    min_points: int = Field(default=25, ge=3, description="inliers a line needs")
    min_extent_m: float = Field(default=0.12, gt=0, description="x extent a line needs (m)")
    max_lines: int = Field(default=4, ge=1, description="most level lines used per frame")
    end_trim_m: float = Field(
        default=0.025,
        ge=0,
        description="points within this x distance (m) of either end of a level line are left "
        "out of the slope fit: the kNN smoothing rounds the corners at both ends of a tread "
        "the same way on every tread (about k grid cells, 2-3 cm), which biases the tilt",
    )
    correlated_points: float = Field(
        default=5.0,
        ge=1,
        description="slope variance multiplier: kNN smoothing (k = 5) correlates neighbouring "
        "profile points",
    )
    ray_fit: Literal["off", "heights", "all"] = Field(
        default="off",
        description="fit the level lines with their errors along the camera rays "
        "(frontend/level.py, _ray_refit) instead of vertical least squares, whose slope leans "
        "towards the rays on a surface seen at a slant (far treads of a descent read high): "
        "'heights' refits the surfaces' heights only (the tilt the pitch aiding fuses stays "
        "the vertical fit's), 'all' the tilt too",
    )
    bend_test: bool = Field(
        default=True,
        description="compare the level surfaces' tilt with the vertical faces' lean in each "
        "slice (filter/attitude.SurfaceBendTest): a pitch error turns both alike, depth "
        "errors that bend the surfaces (multipath in the tread-riser corners, wiggling) tilt "
        "them in opposite senses; while they disagree beyond bend_sigmas the tilts are shrunk "
        "towards the IMU's pitch by the disagreement (bend_vendor_sigma_deg) and not given to "
        "the time-offset estimator. False = fuse every tilt as measured",
    )
    bend_memory_s: float = Field(
        default=1.0, gt=0, description="memory (s) of the bend test's weighted mean"
    )
    bend_sigmas: float = Field(
        default=3.0,
        gt=0,
        description="the bend test flags the surfaces when the mean disagreement is this many "
        "standard errors from 0",
    )
    bend_vendor_sigma_deg: float = Field(
        default=1.0,
        gt=0,
        description="pitch error (deg, 1-sigma) of the IMU's own attitude that bent surfaces' "
        "tilts are weighed against (the MTi-1's dynamic roll/pitch accuracy, 1 deg RMS by "
        "its datasheet): their tilt is shrunk by sigma^2 / (sigma^2 + (disagreement / 2)^2)",
    )
    face_min_extent_m: float = Field(
        default=0.06, gt=0, description="height (m) a vertical face needs for the bend test"
    )
    face_min_points: int = Field(
        default=12, ge=3, description="profile points a vertical face needs for the bend test"
    )
    initial_sigma_deg: float = Field(
        default=3.0, gt=0, description="sigma (deg) of the offset before any measurement"
    )
    drift_deg_per_sqrt_s: float = Field(
        default=0.5, ge=0, description="random-walk sigma (deg/sqrt(s)) of the offset"
    )
    measurement_floor_deg: float = Field(
        default=0.3,
        ge=0,
        description="sigma (deg) added in quadrature to each tilt measurement (what the line "
        "fit does not see: smoothing at the line ends, mixed pixels)",
    )
    gate_sigmas: float = Field(
        default=4.0, gt=0, description="refuse a tilt further than this many sigmas"
    )


class ImuFaultConfig(BaseModel):
    """Saturated and corrupted IMU samples (vio_graph/filter/imu_faults.py)."""

    model_config = ConfigDict(extra="forbid", frozen=True)

    enabled: bool = Field(default=True, description="False = every IMU sample trusted as is")
    saturation_margin: float = Field(
        default=0.99,
        gt=0,
        le=1,
        description="an axis at or beyond this fraction of the declared range (metadata "
        "imu.accel_range_mps2 / gyro_range_radps) counts as saturated",
    )
    saturation_sigma_range: float = Field(
        default=0.5,
        gt=0,
        description="sigma of the half-normal prior on the unknown part of a saturated axis, "
        "in units of the range (the axis is moved beyond the rail by its mean, 0.8 sigma). "
        "0.5: on the four simulated paper experiments clipped at 4 g (seeds 1-4, 169 clipped "
        "stretches) the true excess averages 5-27 m/s^2 per clipped sample (0.1-0.7 x range; "
        "upstair heel strike the most, up to 2.4 x range); with 0.5 (chosen on seeds 1-3) the "
        "velocity a stretch loses is matched on average on seed 4 (mean error -0.03 m/s, "
        "RMS 0.45 m/s; sigma 1.0: +0.50 and 0.67 m/s)",
    )
    saturation_correlated: bool = Field(
        default=True,
        description="the excesses of consecutive saturated samples are one pulse, not "
        "independent: the k-th sample of a stretch carries sqrt(2k - 1) times the prior's "
        "sigma, so that the velocity variance a stretch of n samples adds is n^2 (fully "
        "correlated), not n, times one sample's. False: every sample the prior's sigma",
    )
    saturation_axis_distrust: bool = Field(
        default=False,
        description="the filter adds a saturated sample's extra accelerometer variance on "
        "its clipped axes only (ImuSample.accel_extra_cov_m2ps4, rotated to the ground by the "
        "sample's pitch): the other axes are measured. False: the largest clipped axis's "
        "sigma on both ground axes. No effect without saturation. Off: 4 g saturation seeds "
        "1-3 filter toe x obstacle 3.52 -> 1.51, upstair 1.75 -> 1.43 cm, but downstair 1.84 "
        "-> 1.94, prosthesis_upstair 1.32 -> 1.48, and the smoothers, which take the front "
        "end's displacements, the bridge and the learnt scales from the filter, lose (smoother "
        "toe x obstacle 0.61 -> 1.19, upstair 0.51 -> 0.72 cm): docs/robustness.md",
    )
    saturation_axis_distrust_single: bool = Field(
        default=False,
        description="saturation_axis_distrust for the samples of a clipped stretch that has "
        "so far railed one accelerometer axis only (a heel strike's z): the loss then lies "
        "along that axis turned to the ground, and the frames' measured direction (a level "
        "floor's z) fixes its share on the other ground axis. Samples of a stretch that "
        "rails two axes keep the isotropic variance. No effect without saturation. Off: 4 g "
        "seeds 1-3 filter toe x obstacle 4.09 -> 1.40, upstair 1.67 -> 1.43 cm, downstair and "
        "prosthesis_upstair within 0.04, but smoother toe x obstacle 0.57 -> 1.17, upstair "
        "0.53 -> 0.62 cm (through the profile ICP's restart check, "
        "frontend.tracker.fallback_restart_shift): docs/robustness.md",
    )
    saturation_sigma_prior_floor: bool = Field(
        default=True,
        description="the learnt scale (saturation_learn_scale) moves the prior's mean only: "
        "the sigma a clipped sample carries is that of the larger of the learnt and the "
        "configured scale. The learner measures the mean loss of past stretches, not the "
        "spread of the next one's: downstair 4 g learns an x scale of 0.02 m/s^2 from "
        "stretches that lost little, after which a clipped x stretch added no velocity "
        "variance and its 0.26 m/s loss, found at the stance, was taken as an old velocity "
        "error and moved the position 6.4 cm the wrong way. 4 g seeds 1-5 filter / smoother / "
        "batch toe x cm: downstair 2.64 / 1.46 / 1.27 -> 1.48 / 1.19 / 1.02, obstacle 4.00 / "
        "0.73 / 0.82 -> 3.48 / 0.91 / 0.92, upstair and prosthesis_upstair within 0.05; "
        "nothing changes without a clipped sample (docs/robustness.md)",
    )
    saturation_learn_scale: bool = Field(
        default=True,
        description="learn the half-normal scale per IMU axis from what the filter's "
        "measurements say each clipped stretch lost (imu_faults.SaturationScaleLearner); "
        "saturation_sigma_range x range is its prior. False: the configured scale throughout",
    )
    saturation_tangent_cap: bool = Field(
        default=True,
        description="cap the half-normal's scale of a clipped axis at the tangent's excess: "
        "the last trusted sample's value plus its rise per sample since the one before, "
        "continued to the k-th clipped sample, minus the rail. A peak is concave near its "
        "top, so its tangent bounds it from above; set per stretch where the tangent reaches "
        "the rail at the first clipped sample (a jump past the rail: no cap). The capped "
        "samples keep the capped sigma (no floor) and leave the learnt scale alone. 3 g "
        "saturation, filter / smoother / batch toe x cm, seeds 1-3: downstair (diagnosed on "
        "seed 1) 2.13 / 1.53 / 1.60 -> 1.10 / 0.98 / 0.91, upstair 1.64 / 0.39 / 0.42 -> "
        "1.26 / 0.38 / 0.40, obstacle 2.00 / 0.99 / 0.94 -> 1.85 / 0.92 / 0.84; seeds "
        "1000-1002: downstair 2.19 / 1.41 / 1.25 -> 1.58 / 0.86 / 0.78, upstair 1.40 / 0.38 / "
        "0.40 -> 1.26 / 0.43 / 0.45, obstacle unchanged; 4 g and clean trials within 0.02 "
        "(docs/method.md, 'The tangent bounds a clipped peak')",
    )
    saturation_learn_per_side: bool = Field(
        default=False,
        description="learn one scale per IMU axis and rail side (the positive and the "
        "negative rail of each axis apart) instead of one per axis: the two rails of an axis "
        "are clipped by different gait events (on the simulated 3 g stairs the shank's x "
        "rail at the swing's forward peak is exceeded by 7-13 m/s^2 per clipped sample, at "
        "its backward peak by 2-6), and one scale over-restores the one and under-restores "
        "the other. Only with saturation_learn_scale; each side starts from the configured "
        "scale",
    )
    saturation_explained_fraction: float = Field(
        default=0.1,
        gt=0,
        lt=1,
        description="a stretch's evidence is taken when the filter's velocity variance is "
        "back within this fraction of what the stretch added (its loss measured to about "
        "sqrt(0.1) = 0.3 of the prior's sigma)",
    )
    saturation_evidence_window_s: float = Field(
        default=1.0,
        gt=0,
        description="evidence not in this long after a stretch is dropped (nothing measured "
        "the velocity); longer than a swing (0.4-0.6 s) so the next stance counts",
    )
    saturation_bridge: bool = Field(
        default=True,
        description="after a saturated accelerometer stretch, observe the camera velocity "
        "through the leg chain with the hip's velocity held across the stretch "
        "(filter/leg_bridge.py; needs the joints stream: thigh pitch and knee encoder)",
    )
    saturation_bridge_hip_accel_mps2: float = Field(
        default=5.0,
        gt=0,
        description="sigma of the hip's acceleration across a clipped stretch (from the "
        "last trusted sample before it to the first after it): the bridge's sigma per axis "
        "grows by it times that window. Simulated 4 g, seeds 1-3, the chain's velocity "
        "change misses the camera's by 0.08-0.21 m/s RMS per axis on upstair and obstacle "
        "(1.4-4.2 m/s^2 RMS divided by the 30-90 ms window) and 0.12-0.41 on "
        "prosthesis_upstair (2.3-5.5 m/s^2). Toe x mean of 3 seeds, 3 -> 5 m/s^2, filter / "
        "smoother / batch: upstair 1.81 / 0.81 / 0.83 -> 1.75 / 0.66 / 0.67, obstacle "
        "3.31 / 2.47 / 2.66 -> 3.52 / 1.23 / 2.50, prosthesis_upstair 1.55 / 1.23 / 1.21 -> "
        "1.31 / 0.88 / 0.79",
    )
    saturation_bridge_rate_sigma_mps: float = Field(
        default=0.1,
        ge=0,
        description="sigma per axis (m/s) of the chain's velocity from the encoders' "
        "central differences (0.05 deg encoder noise over 20 ms through 0.4 m: 0.03 m/s, "
        "and the interpolation between joint samples)",
    )
    saturation_bridge_discretisation_sigma: bool = Field(
        default=False,
        description="add to the bridge's noise the chain velocity's own discretisation "
        "error at each end of the stretch, estimated from the joints (half the norm of the "
        "second difference of the chain's central-difference velocity over the neighbouring "
        "joint periods; filter/leg_bridge.py chain_velocity_discretisation_xz): a push-off "
        "the joints' rate does not resolve gets the sigma of its miss. The observation "
        "waits one joint period longer. Off: the sweep's cadence_1.5 (16 g clip, the chain "
        "0.4-0.6 m/s short at a 0.14-0.18 sigma) gains, filter toe x 2.16 -> 1.46 cm, but "
        "4 g saturation loses, toe x filter / smoother / batch upstair seeds 1-5 1.55 / "
        "0.83 / 0.85 -> 1.76 / 0.94 / 0.95, prosthesis_upstair seeds 1-3 1.47 / 0.79 / 0.93 "
        "-> 1.86 / 1.41 / 1.50 (docs/robustness.md)",
    )
    saturation_bridge_fourth_order: bool = Field(
        default=False,
        description="the chain velocity at the stretch's ends by the five-point (fourth-"
        "order) derivative of the joints, D - D''/6, instead of their central difference "
        "D; with saturation_bridge_discretisation_sigma its sigma is a third of the second "
        "difference (what is left of an acceleration step) instead of half. Off: with "
        "both on, 4 g upstair seeds 1-3 filter toe x 1.67 -> 1.21 cm but smoother / batch "
        "0.53 / 0.57 -> 0.68 / 0.69 and obstacle 2.79 / 0.77 / 0.80 -> 2.97 / 0.93 / 0.91 "
        "(docs/robustness.md)",
    )
    saturation_bridge_gate: bool = Field(
        default=True,
        description="chi-square gate the bridge's observation (the filter's gate "
        "probability): vision, the saturation prior and the chain arbitrate",
    )
    saturation_bridge_relative: bool = Field(
        default=True,
        description="fuse the bridge as what it measures, the velocity change across the "
        "stretch, against a copy of the filter's velocity at the stretch's start (stochastic "
        "cloning; filter/eskf.py update_velocity_change) instead of as a velocity whose "
        "covariance includes the filter's own at the start: the filter's velocity error from "
        "before the stretch is not counted again as new information, and keeps its "
        "correlation with the position for the next stance or frame",
    )
    gyro_ahrs_test: bool = Field(
        default=True,
        description="test each gyro sample against the rate of the vendor orientation (two "
        "outputs of the IMU); an inconsistent sample is replaced by the rate the orientation "
        "implies",
    )
    gyro_ahrs_sigma_radps: float = Field(
        default=0.5,
        gt=0,
        description="sigma (rad/s, per axis) of the test residual g_k - (2 w_k - g_{k-1}), w_k "
        "the mean rate from consecutive vendor orientations, at an IMU rate of 100 Hz: their "
        "error drift (MTi-1: 1-2 deg RMS, correlated over seconds) and the gyro noise. Both "
        "are white per sample, so at the recording's rate r (metadata imu.rate_hz) the test "
        "uses sigma sqrt(r / 100 Hz); the floor under the learnt sigma "
        "(gyro_ahrs_learn_time_s)",
    )
    gyro_ahrs_learn_time_s: float | None = Field(
        default=5.0,
        gt=0,
        description="the test's variance follows what this IMU's two outputs show: an "
        "exponentially weighted mean (time constant in s) of the squared residual per axis "
        "over the samples that pass; the test uses the larger of it and the (rate-scaled) "
        "gyro_ahrs_sigma_radps^2. An IMU whose orientation output is noisier than the MTi-1's "
        "(a consumer MEMS with a host-side fusion: 2 deg roll/pitch, 5 deg heading) otherwise "
        "fails the test on a third of its samples. None: the configured sigma only",
    )
    gyro_ahrs_probability: float = Field(
        default=0.999999,
        gt=0,
        lt=1,
        description="chi-square (3 dof) probability of the gyro test",
    )
    held_accel_sigma_mps2: float = Field(
        default=10.0,
        gt=0,
        description="a sample whose gyro failed the test is corrupted as a whole (a bus error "
        "or a shock hits the packet): its accelerometer is replaced by the previous trusted "
        "one with this extra sigma (m/s^2; gait changes the specific force by a few m/s^2 per "
        "10 ms, up to tens at heel strike)",
    )
    vision_arbitration: bool = Field(
        default=False,
        description="when the gate refuses a displacement, test the hypothesis 'the IMU was "
        "wrong in this interval' (a velocity jump of velocity_fault_sigma_mps at mid-interval); "
        "if vision then agrees, the filter's velocity and position are widened by it and the "
        "displacement is fused. Off by default: on clean trials it also kept the few "
        "displacements the gate rightly refuses (obstacle s1 filter toe x 2.12 -> 6.03 cm, "
        "downstair s2 3.47 -> 4.94 cm) and under 2 ms of clock jitter the ones that frame-time "
        "errors had spoiled",
    )
    velocity_fault_sigma_mps: float = Field(
        default=0.4,
        gt=0,
        description="sigma (m/s) of the velocity jump one corrupted IMU sample can cause "
        "(a 30 m/s^2 spike at 100 Hz: 0.3 m/s); a wrong corner association (a stair step in "
        "one frame, ~5 m/s over 33 ms) stays far outside it",
    )
    repair_from_next_sample: bool = Field(
        default=True,
        description="hold a packet the gyro test repaired back from the filter, the attitude "
        "tracker and the stance detector until the next sample arrives, and replace its held "
        "accelerometer and predicted gyro by the interpolation between its measured neighbours "
        "(filter/imu_repair.py; the filter runs one sample late over such a packet only). "
        "False = the filter fuses the monitor's stand-ins at once",
    )
    interpolated_accel_sigma_mps2: float = Field(
        default=5.0,
        gt=0,
        description="extra sigma (m/s^2, per axis) of an accelerometer sample the filter "
        "interpolated (repair_from_next_sample): the smoothers' value "
        "(smoother.interpolated_accel_sigma_mps2, the interpolation's error on the simulated "
        "gaits: 1.2-1.8 m/s^2 RMS, 5-7 at the 99th percentile)",
    )
    keep_consistent_axes: bool = Field(
        default=True,
        description="with repair_from_next_sample: an axis of the repaired packet (accelerometer "
        "or gyro) whose measured value agrees with the interpolation between its neighbours "
        "(within the consistent_axis_probability quantile of a 1-dof chi-square, sigma "
        "interpolated_accel_sigma_mps2 / gyro_ahrs_sigma_radps) keeps its measurement; only the "
        "axes that disagree are interpolated (filter/imu_repair.py keep_consistent_axes). "
        "False = the whole packet is interpolated",
    )
    repaired_axis_distrust: bool = Field(
        default=False,
        description="with keep_consistent_axes: the interpolated packet's extra accelerometer "
        "variance (interpolated_accel_sigma_mps2) on its interpolated axes only "
        "(ImuSample.accel_extra_cov_m2ps4, as smoother.held_axis_distrust does); the kept "
        "axes are measurements; a packet whose test kept every accelerometer axis keeps the "
        "variance on all of them (imu_repair.interpolated_axes_cov: the spike was not "
        "placed). Off by default: 2 Hz spikes seeds 1-3 filter toe x downstair 1.27 -> 0.84 "
        "cm, obstacle 1.76 -> 1.13, upstair 0.48 -> 0.47, but the smoothers, which take the "
        "filter's ICP seeds, downstair x 0.55 -> 0.73 cm and batch 0.43 -> 0.65 (seed 3: the "
        "front end's seed sensitivity at 1.3 s; docs/robustness.md, IMU spikes: the filter's "
        "twin traced)",
    )
    consistent_axis_probability: float = Field(
        default=0.999,
        gt=0,
        lt=1,
        description="probability of the per-axis test of keep_consistent_axes (0.999: 3.3 "
        "sigma, 16 m/s^2 and 1.6 rad/s; a 30 m/s^2 / 5 rad/s spike fails it)",
    )


class TimeOffsetConfig(BaseModel):
    """Online camera-IMU time offset and timestamp clock models (filter/time_offset.py)."""

    model_config = ConfigDict(extra="forbid", frozen=True)

    estimate: bool = Field(
        default=True,
        description="estimate the camera-IMU offset td (frame stamp = IMU-clock time + td) "
        "from the level-surface tilt against the shank pitch rate",
    )
    initial_sigma_s: float = Field(default=0.05, gt=0, description="prior sigma of td (s)")
    drift_s_per_sqrt_s: float = Field(
        default=1e-5, ge=0, description="random-walk sigma of td (s/sqrt(s))"
    )
    apply_sigmas: float = Field(
        default=3.0,
        ge=0,
        description="td is applied to the fusion once it is this many sigmas from 0 (a "
        "synchronised rig keeps its stamps untouched); the sigma is scaled by the tilts' "
        "consistency and nothing is applied before 10 tilts were accepted "
        "(TimeOffsetEstimator.consistency_scale)",
    )
    gate_probability: float = Field(
        default=0.999, gt=0, lt=1, description="chi-square (1 dof) gate of a tilt measurement"
    )
    rerun_window_s: float = Field(
        default=2.0,
        ge=0,
        description="retroactive re-run (vio_graph/replay.py): once td is applied within this "
        "many seconds of the first frame, the replay restarts every estimator from the first "
        "frame with the frames re-stamped by td from the start, so what was fused with the "
        "wrong offset does not stay in the state; 0: never",
    )
    rerun_sigma_s: float | None = Field(
        default=0.0015,
        gt=0,
        description="the re-run waits until td's sigma is at most this (s), or until the next "
        "frame would leave rerun_window_s; None: re-run as soon as td is applied",
    )
    rerun_final: bool = Field(
        default=True,
        description="replaying a recording (vio_graph/replay.py) on which td was estimated "
        "and applied: once every frame has been seen, every estimator runs once more from "
        "the first event with td held at its final estimate (0 if that is no longer "
        "apply_sigmas scaled sigmas from zero) and not re-estimated; the written "
        "trajectories are that pass's. The early re-run (rerun_window_s) starts with td "
        "known to rerun_sigma_s, 1-3 ms off, and the first seconds keep that error; the "
        "final estimate is within 0.4 ms. Costs one more pass, only where td was applied; "
        "false: the early re-run's answer is written",
    )
    imu_clock_model: bool = Field(
        default=True,
        description="replace IMU stamps by a clock model fitted to them (nominal rate, "
        "recursive line fit): removes timestamp jitter, keeps clock drift",
    )
    camera_clock_model: bool | Literal["auto"] = Field(
        default="auto",
        description="smooth the depth-frame stamps with a clock model: true = always; false = "
        "never (a camera whose capture instants jitter, like the simulator's clean camera at "
        "1 ms, has correct stamps the model would move); 'auto' = vision decides, frame by "
        "frame, with a sequential likelihood-ratio test of the displacements under both "
        "(time_offset.FrameStampTest); gaps are reported either way",
    )
    stamp_ambiguity_cov: bool = Field(
        default=False,
        description="with camera_clock_model 'auto': until the frame-stamp test has decided, "
        "each fused displacement's covariance holds the shift u of its IMU prediction under "
        "the other choice of frame times, weighted by the test's posterior probability of "
        "that choice (p u u^T; FrameStampTest.ambiguity_cov): displacements of a fast swing "
        "fused on jittered stamps the test does not yet distrust carry the doubt. Off: 2 ms "
        "clock jitter, filter toe x / z, paper scenarios seeds 1-3 mean 0.73 / 0.58 -> "
        "0.77 / 0.60 cm, a 10 x 40 cm obstacle seeds 9007, 9011-9015 mean 6.41 / 8.15 -> "
        "6.60 / 9.68 cm. Off by default: on the clean obstacle seed 3 the p = 0.5 of the "
        "undecided test widens correct stamps' displacements in the fast swing, filter z "
        "0.34 -> 0.39 cm, z NEES 0.82 -> 1.26 (docs/generalisation.md, second held-out set)",
    )
    stamp_test_tilts: bool = Field(
        default=False,
        description="with camera_clock_model 'auto': the level surfaces' tilt of each frame "
        "is evidence for the frame-stamp test too. The slice is rotated with the attitude "
        "at the frame's time, so the other choice of time (clock line or stamp, delta "
        "apart) turns the measured tilt by the shank pitch rate times delta; the tilt's "
        "innovation in the time-offset filter (pitch error and offset accounted for) is "
        "tested under both, capped at the level aiding's gate "
        "(FrameStampTest.add_tilt). A displacement sees a time error only through the "
        "velocity change over a frame; the tilt sees it through the rotation rate, so the "
        "test gathers evidence about twice as fast. Off: 2 ms clock jitter, filter toe x / z, "
        "joint-space seeds 1-3, obstacle 2.35 / 2.00 -> 0.95 / 0.37 cm (the height slip of "
        "seed 2 gone), prosthesis upstair 0.58 / 0.39 -> 0.47 / 0.40, upstair and downstair "
        "within 0.03; clean and camera-IMU offset trials unchanged to the bit. Off by "
        "default: on held-out jittered trials obstacle seed 4 x 0.69 -> 1.32 and downstair "
        "seed 4 x 1.38 -> 1.86 cm (obstacle seed 5 1.84 -> 0.82), and the 1.5x aim is still "
        "missed (docs/robustness.md, 'The frame-stamp test also reads the level surfaces' "
        "tilt')",
    )
    clock_window: int = Field(
        default=200, ge=10, description="samples the clock-model line fit remembers"
    )
    landmark_time_sigma: bool = Field(
        default=False,
        description="a height or corner landmark measured on a frame carries the frame "
        "time's uncertainty: its covariance grows by v v^T sigma_t^2 (v the filter's camera "
        "velocity at the frame), sigma_t^2 the mean square of the frame stamps' distances to "
        "the camera clock line (ClockModel.scatter_var_s2) when the line times are used (the "
        "line removes the transport part of the scatter, not a capture jitter, which is "
        "bounded by it), that times the frame-stamp test's probability of the line when the "
        "stamps are used; 0 for stamps on their line. A landmark relates the camera's "
        "position at the frame time to a fixed point, so a time error e moves it by v e "
        "without the cancellation consecutive displacements have, and a level surface first "
        "seen in a fast swing keeps that error (estimator._landmark_time_cov). Off: 2 ms "
        "clock jitter, filter toe z on held-out seeds 4-10, prosthesis upstair / upstair / "
        "obstacle 0.41 / 0.74 / 0.43 -> 0.36 / 0.68 / 0.41 cm (downstair 0.77 -> 0.78, x "
        "unchanged), prosthesis upstair seed 3 1.09 -> 0.80, but on seeds 1-3 upstair z "
        "0.47 -> 0.52 and obstacle x 1.32 -> 1.52 cm, prosthesis upstair 4 g saturation "
        "filter x 1.47 -> 1.78 cm; clean rows within 0.01 cm "
        "(docs/robustness.md, 'Clock jitter in the filter')",
    )
    frame_time_rotation_sigma: bool = Field(
        default=False,
        description="a frame's attitude is taken at its time, so a time error e turns its "
        "slice by omega e (omega the gyro rate at the frame, rad/s), which moves a point at "
        "(x, z) from the camera by about omega e (z, -x): the displacement's covariance "
        "grows by the rotation variance omega^2 sigma_t^2 times p p^T for the centroid p of "
        "both its frames' profiles, a corner's by the same at its position, the level "
        "surfaces' shared tilt and the pitch aiding's tilt by omega^2 sigma_t^2; sigma_t^2 "
        "as for landmark_time_sigma. Off: 2 ms clock jitter, filter toe x / z, joint-space "
        "obstacle seeds 1-3 2.35 / 2.00 -> 0.82 / 0.37 cm (a 5 cm height slip on seed 2 "
        "gone), but clean upstair / downstair x 0.59 / 0.76 -> 0.80 / 0.91 cm: the undecided "
        "frame-stamp test's first second widens exact stamps (docs/robustness.md, 'Frame "
        "time as a slice rotation'). "
        "estimator._frame_time_terms",
    )
    camera_clock_rate_prior_ppm: float | None = Field(
        default=None,
        ge=0,
        description="prior sd (ppm) of the camera clock's rate about the nominal frame rate in "
        "the online frame clock line (time_offset.ClockModel._fit_rate_prior): the slope is "
        "drawn to the nominal period by the stamps' scatter over this prior, so a few seconds "
        "of jittered stamps do not tilt the line; stamps without scatter still fit any drift. "
        "None (default): the slope is fitted freely. 100 ppm halves the line's error under 2 "
        "ms stamp jitter (0.47 -> 0.24 ms rms, 12 recordings) and prosthesis upstair seed 3's "
        "filter toe z (1.09 -> 0.69 cm), but on seeds 4-10 of the four paper scenarios the "
        "filter is unchanged within seed noise (z 0.59 -> 0.59, x 1.15 -> 1.16 cm), so off "
        "(docs/robustness.md, 'Clock jitter in the filter'; configs/camera_rate_prior.yaml)",
    )
    imu_clock_offline_half_window: int = Field(
        default=1000,
        ge=0,
        description="replaying a recording (vio_graph/replay.py), IMU stamps that scatter "
        "about their clock line (jitter) reach the smoothers (fixed-lag and batch) at a "
        "line fitted over this many samples on either side of each (the fixed-lag "
        "smoother's looking ahead by its lag only) "
        "(time_offset.centred_clock_line; 1000 = 10 s at 100 Hz, over which a crystal's "
        "rate is constant); the filter keeps the online one-sided clock model; stamps on "
        "their line are left bit for bit; 0: off",
    )
    gap_periods: float = Field(
        default=1.9,
        gt=1,
        description="a stamp more than this many nominal periods after the previous one is a "
        "gap (reported; the clock model restarts after it). Below it consecutive samples count "
        "as one period apart, so the stamp jitter must stay below (gap_periods - 1) periods "
        "(the simulator clips its jitter at 0.4 periods); a single missing sample is a gap",
    )


class FilterConfig(BaseModel):
    """Parameters of :class:`vio_graph.filter.eskf.SagittalEskf`.

    Noise model (paper eq. 5 and the Q of eq. 7):

    - ``accel_noise_sigma_mps2`` is the per-sample sigma sigma_a of the acceleration error;
      Q puts sigma_a^2 dt^2 on the velocity error per IMU step (Sola 2017, eq. 262). The
      paper's value is the sensor's white noise, noise density * sqrt(rate) = 1.18e-3 *
      sqrt(100) = 0.0118 m/s^2 (``MTI1_ACCEL_SIGMA_MPS2``). On the simulated trials that makes
      the filter's velocity ~10x overconfident: the vendor attitude error (~1 deg, a 0.17
      m/s^2 gravity leak that the IMU-frame bias cannot follow while the shank rotates),
      lever-arm and 2D-model errors are not in Q, so the velocity lags the ICP displacements
      by 0.2-0.3 m/s (7-8 mm per frame at 30 fps), the gate then rejects good displacements
      and every swing without vision loses centimetres. The default 0.5 m/s^2 covers that
      model error (filter camera RMSE, upstair s2: 117 -> 8 cm in x with the same
      displacements; ``benchmarks/eval_frontend.py``).
    - ``accel_bias_rw_mps2_per_sqrt_s`` is sigma_ab of the bias random walk; Q puts
      sigma_ab^2 dt on the bias error per step. The MTi-1 in-run bias stability (0.03 mg =
      2.9e-4 m/s^2) suggests ~1e-4; the default is larger (1e-3) so that the filter can follow
      the slow, temperature-driven drift and the residual lever-arm / attitude errors that a
      2D bias absorbs on a swinging shank.
    """

    model_config = ConfigDict(extra="forbid", frozen=True)

    # --- IMU noise (eq. 5, Q of eq. 7) ---
    accel_noise_sigma_mps2: float = Field(
        default=0.5,
        gt=0,
        description="per-sample acceleration error sigma (m/s^2) at the IMU rate: sensor noise "
        "(MTi-1: 0.0118, MTI1_ACCEL_SIGMA_MPS2 = the paper's Q) plus the model error of the "
        "sagittal strapdown (vendor attitude ~1 deg -> 0.17 m/s^2 gravity leak, lever arm, "
        "2D bias); with the datasheet value the velocity is overconfident and lags",
    )
    accel_bias_rw_mps2_per_sqrt_s: float = Field(
        default=1e-3, ge=0, description="accelerometer bias random walk sigma (m/s^2/sqrt(s))"
    )
    attitude_sigma_rad: float = Field(
        default=0.0,
        ge=0,
        description=(
            "vendor pitch error (rad, MTi-1: 1 deg RMS dynamic). If > 0 it is added to the "
            "velocity process noise as (|f| sigma dt)^2; 0 reproduces the paper's Q"
        ),
    )

    # --- initial state and covariance (sigmas of the error state) ---
    gravity_xz_mps2: tuple[float, float] = Field(
        default=(0.0, -GRAVITY_MPS2), description="initial gravity in the ground x-z plane (m/s^2)"
    )
    start_at_first_frame: bool = Field(
        default=True,
        description="initialise the filter at the first depth frame instead of the first IMU "
        "sample (False). A trial that starts mid-stride has the camera moving by then; "
        "started earlier with v = 0, the first displacement corrects the velocity and with "
        "it, retroactively, where the first frame was, after that frame's position has been "
        "output (0.5-0.7 cm on obstacle seed 1), and the first-pose-anchored ATE carries that "
        "offset through the trial. Seeds 1-3, filter toe x/z cm, False -> True: obstacle "
        "(edge-visible frames) 1.32/0.34 -> 0.62/0.33, downstair 2.46/0.71 -> 1.03/0.80, "
        "upstair 0.61/1.06 -> 0.58/0.96, prosthesis_upstair 1.24/1.33 -> 0.99/1.11; sweep "
        "seeds 1000-1002: reference 0.77/0.88 -> 0.60/0.81, slow step-to-step 2.13/0.88 -> "
        "2.74/0.96 (its first frames are now closer to the truth, camera x at frame 1 off by "
        "0.1 instead of 0.7 cm; the early offset had cancelled a later lag)",
    )
    init_position_sigma_m: float = Field(default=1e-3, gt=0, description="initial sigma of p (m)")
    init_velocity_sigma_mps: float = Field(
        default=0.5, gt=0, description="initial sigma of v (m/s); trials may start mid-stride"
    )
    init_accel_bias_sigma_mps2: float = Field(
        default=0.1, gt=0, description="initial sigma of the accelerometer bias a_b (m/s^2)"
    )
    init_gravity_sigma_mps2: float = Field(
        default=1e-3,
        gt=0,
        description="initial sigma of g (m/s^2); small: g and a_b are nearly inseparable",
    )

    # --- measurement model (eq. 8) ---
    measurement_model: Literal["position_pseudo", "stochastic_cloning"] = Field(
        default="stochastic_cloning",
        description=(
            "'position_pseudo': the paper's z = p_hat(t0) + delta with H = [I 0 0 0] "
            "(ignores the correlation between p_hat(t0) and the state); "
            "'stochastic_cloning': the state is augmented with p(t0) and the displacement is "
            "a relative measurement z = p(t1) - p(t0) (Roumeliotis & Burdick 2002)"
        ),
    )
    measurement_noise_floor_m: float = Field(
        default=2e-3,
        ge=0,
        description="sigma (m) added in quadrature to each axis of a displacement covariance",
    )
    measurement_cov_inflation: float = Field(
        default=1.0, gt=0, description="factor (-) multiplying the displacement covariance"
    )
    gate_probability: float | None = Field(
        default=0.999,
        gt=0,
        lt=1,
        description="chi-square (2 dof) gate probability on the innovation; None disables",
    )
    max_time_mismatch_s: float = Field(
        default=0.05,
        gt=0,
        description=(
            "largest gap (s) between a displacement's t0/t1 and the filter's state/clone/"
            "history times; beyond it the displacement is rejected as stale"
        ),
    )
    lockout_refusals: int | None = Field(
        default=3,
        ge=1,
        description="this many displacements refused by the gate in a row widen the velocity "
        "covariance to init_velocity_sigma_mps (gate lock-out recovery; at gate_probability "
        "0.999 three chance refusals in a row happen once in 1e9). The front end's refusals of "
        "ICP against the same IMU prediction count too. None = never",
    )
    lockout_since_last_fix: bool = Field(
        default=False,
        description="the lock-out recovery takes the distrusted velocity error as constant "
        "since the last fused displacement and widens the position (and the clone) by its "
        "integral with the matching correlation (SagittalEskf.inflate_velocity since_s), so "
        "a later velocity measurement corrects the position too. False: velocity only. Off by "
        "default: with time_offset.stamp_ambiguity_cov it takes the held-out trial O (16 g "
        "clip, 2 ms clock jitter) from filter toe 11.4 / 16.6 to 7.7 / 3.9 cm, but alone it "
        "also widens the position on false lock-outs (2 ms jitter, obstacle seed 3 filter toe "
        "x 1.61 -> 4.63 cm; docs/generalisation.md, second held-out set)",
    )
    relocalised_max_accel_mps2: float = Field(
        default=60.0,
        gt=0,
        description="a displacement of the front end's lost-track search "
        "(frontend.tracker.relocalise_after_frames) that the gate refuses is taken, with the "
        "velocity variance widened to cover the disagreement, only if vision agrees with "
        "itself: its velocity and the previous frame's visual displacement's differ by at "
        "most this acceleration (m/s^2) times the time between them. A shank peaks near 5 g "
        "(simulated joint-space swing 2-5 g); a displacement from a corrupted frame rarely "
        "continues the previous one, and is then left to the gate",
    )
    history_s: float = Field(
        default=2.0, gt=0, description="how long (s) past position estimates are kept for t0"
    )

    # --- IMU handling ---
    integration: Literal["zoh", "trapezoid"] = Field(
        default="trapezoid",
        description=(
            "'zoh': eq. 6 with the current sample held over dt (the paper); 'trapezoid': the "
            "mean of the previous and current ground-frame accelerations"
        ),
    )
    strapdown_attitude: Literal["vendor", "tracked"] = Field(
        default="tracked",
        description=(
            "attitude the strapdown rotates the specific force with: 'vendor' = each sample's "
            "vendor orientation with the level-surface pitch offset; 'tracked' = the attitude "
            "tracker's (attitude.source, e.g. gyro-integrated complementary) with the offset"
        ),
    )
    lever_arm_compensation: bool = Field(
        default=True,
        description=(
            "transfer the IMU specific force to the camera centre with the gyro: "
            "f_cam = f_imu + alpha x r + omega x (omega x r), r = camera in IMU frame (m)"
        ),
    )
    attitude: AttitudeConfig = Field(
        default=AttitudeConfig(), description="slice rotation of eq. 2 (filter/attitude.py)"
    )
    level_aiding: LevelAidingConfig = Field(
        default=LevelAidingConfig(),
        description="pitch correction from level surfaces in the slice (frontend/level.py)",
    )
    imu_faults: ImuFaultConfig = Field(
        default=ImuFaultConfig(), description="saturated / corrupted IMU samples"
    )
    time_offset: TimeOffsetConfig = Field(
        default=TimeOffsetConfig(), description="camera-IMU time offset and clock models"
    )
    fused_timeout_s: float = Field(
        default=0.1,
        gt=0,
        description="status stays FUSED this long (s) after the last accepted displacement",
    )

    # --- landmarks (SagittalEskf.update_landmark; vio_graph/estimator.py) ---
    corner_landmarks: bool = Field(
        default=True,
        description=(
            "fuse the front end's corner observations (corner minus camera, one track id per "
            "physical corner) as landmarks in the state: the first sight of a track adds the "
            "corner with the current position uncertainty, later sights are relative "
            "measurements; see corner_memory_s and corner_reidentify_radius_m for when it "
            "leaves the state and when a new track is the same corner. False = the paper "
            "(displacements only)"
        ),
    )
    corner_landmark_sigma_m: float = Field(
        default=0.0,
        ge=0,
        description="sigma (m) added in quadrature per axis to a corner observation covariance. "
        "0: the front end's corner covariance alone (frontend.corners.edge_sigma_m, 1 cm, "
        "already ~9x the corners' measured error), as in the smoothers; a misplaced corner "
        "is the gate's to refuse. The earlier 0.01 (1.4 cm in all) let the visual "
        "displacements' random walk carry x on long trials (docs/method.md section 2)",
    )
    corner_reidentify_radius_m: float | None = Field(
        default=0.08,
        gt=0,
        description="a new corner track whose observed position (filter camera + corner) lies "
        "within this distance (m) of a remembered corner landmark, and clearly nearest to it "
        "(the next one at least twice as far), is that landmark seen again: the swinging "
        "shank looks at one nosing, then another, then back, and the front end gives every "
        "reappearance a new track. Stair corners are >= 0.31 m apart (tread 0.28, rise "
        "0.147). None = every track is a new landmark",
    )
    corner_memory_s: float = Field(
        default=3.0,
        gt=0,
        description="a corner landmark not seen for this long (s) is marginalised",
    )
    max_corner_landmarks: int = Field(
        default=8, ge=1, description="most corner landmarks kept in the state (oldest go)"
    )
    level_landmarks: bool = Field(
        default=True,
        description=(
            "fuse the heights of the level surfaces the level aiding finds in the slice "
            "(treads, landings, floor, obstacle tops; frontend/level.py) as height landmarks "
            "(SagittalEskf.update_height_landmark): z only, so any static level surface is "
            "one, and several are in view at once for many frames, so the camera height is "
            "handed from surface to surface by co-observation. The corner landmarks cannot do "
            "that (one corner a frame: a new nosing is placed where the displacements and the "
            "stance anchor put the camera, and their sub-millimetre per-step biases add up: "
            "filter toe z 6.7 cm on the 2-minute ascent). Needs level_aiding. False = none"
        ),
    )
    level_shared_tilt: bool = Field(
        default=True,
        description=(
            "the level surfaces of one slice are fused together with the tilt error they "
            "share (SagittalEskf.update_height_landmarks): each surface's height was levelled "
            "by the slice's common tilt, so its error has a part lever x tau with the same "
            "tau for all of them, of the tilt's variance: the fit's slope sigma plus "
            "level_aiding.measurement_floor_deg in quadrature, the sigma the pitch aiding "
            "gives the same tilt. False = each surface alone with the fit's slope sigma at "
            "its distance in its own variance (before 2026-12-03: a floor 1-1.5 m ahead came "
            "out 8 mm rms off against a claimed 2 mm on descent)"
        ),
    )
    level_reidentify_m: float = Field(
        default=0.03,
        gt=0,
        description="a level surface whose height (filter camera z + observed height, m) is "
        "within this distance of a remembered height landmark, and clearly nearest to it (the "
        "next at least twice as far), is that landmark; else a new one. Level surfaces of "
        "different height are a rise apart (>= 0.10 m on the simulated stairs)",
    )
    level_memory_s: float = Field(
        default=3.0,
        gt=0,
        description="a height landmark not seen for this long (s) leaves the state",
    )
    max_level_landmarks: int = Field(
        default=6, ge=1, description="most height landmarks kept in the state (oldest go)"
    )
    level_one_landmark_per_surface: bool = Field(
        default=False,
        description="make no new height landmark within level_reidentify_m of a remembered "
        "one or of one made from the same slice (skip that line): one surface, one landmark. "
        "Off: a floor split into near and far lines a few mm apart becomes several landmarks "
        "the camera height can step between. On: level s1-5, filter toe z 0.34 / 0.51 -> "
        "0.29 / 0.29 cm (via-point / joint-space swing), stairs unchanged, but the smoothers "
        "on level via-point trials z +0.06 cm and the filter's z covariance conservative "
        "(NEES 0.08); off until the sweep's clearance calibration is re-measured with it "
        "(filter/level_landmarks.py, docs/generalisation.md)",
    )
    stance_anchor: bool = Field(
        default=True,
        description=(
            "while the instrumented foot is in stance (filter/stance.py), the ankle position "
            "fixed at stance onset is a landmark seen from the camera through the leg "
            "kinematics: ankle - camera = R_shank (ankle_in_shank - camera_in_shank)"
        ),
    )
    stance_contact: Literal["off", "propose", "confirm"] = Field(
        default="off",
        description="role of a foot-contact channel (contact.csv) in proposing a stance. "
        "off: none, the acceleration detector proposes (a load cell or switch says the foot "
        "carries weight, which it also does while it rolls over the heel after contact and "
        "over the toe before toe-off, when the ankle moves; the anchor needs a still ankle). "
        "propose: a loaded foot is a stance candidate (vision and the foot's rotation then "
        "test it). confirm: a candidate needs both the loaded foot and the quiet ankle "
        "(the contact rules out a slow swing that looks quiet). Measured on nine trials with "
        "a channel (docs/method.md section 2): off best on six",
    )
    stance_accel_threshold_mps2: float = Field(
        default=2.0,
        gt=0,
        description="stance if the ankle acceleration (gravity removed, from the shank IMU "
        "with the lever arm to the ankle) stays below this (m/s^2) over the window. Simulated "
        "gaits: stance median 0.26, swing 10th percentile 5-6 m/s^2; 1.0 missed short level "
        "stances (upstair s4 x 14.5 -> 12.6 cm with 2.0)",
    )
    stance_speed_threshold_mps: float | None = Field(
        default=None,
        gt=0,
        description="if set: stance also needs the filter's ankle speed (camera velocity + "
        "pitch rate x lever) below this (m/s). Off by default: on level ground the filter "
        "velocity has drifted by the first stance (level s1: never detected with 0.3 m/s), "
        "while the acceleration window alone separates stance (median 0.26 m/s^2) from swing "
        "(10th percentile 6 m/s^2) on the simulated gaits",
    )
    stance_window_s: float = Field(
        default=0.1, gt=0, description="length (s) of the acceleration window of the detector"
    )
    stance_pitch_sigma_rad: float = Field(
        default=0.002,
        ge=0,
        description="error (rad) of the CHANGE of shank pitch since stance onset; times the "
        "camera-ankle distance it is the sigma of the ankle-from-camera observation. The "
        "constant part of the vendor pitch error (~1 deg) is in the anchor too and cancels; "
        "what remains over a 0.3 s stance is gyro-integration error (~0.1 deg). Measured "
        "(slip, pitch) sigmas on downstair s1/s4, filter toe x cm: (5 mm, 1 deg) 7.8/10.0; "
        "(2 mm, 0.01) 6.2/6.6; (1 mm, 0.005) 5.5/4.7; (0.5 mm, 0.002) 4.9/4.0",
    )
    stance_gate: bool = Field(
        default=True,
        description="chi-square gate each ankle observation (gate_probability). A refused "
        "observation is arbitrated by vision: if this frame's displacement confirmed the "
        "still ankle (stance_test), the anchor is taken anyway (on level ground the anchor is "
        "the only x information and the velocity drifts in every swing: level s1 toe x 4.4 "
        "cm this way, 556 cm if a refusal simply ended the stance); without visual evidence "
        "the stance ends (slow step-to-step s1 with every frame proposed as stance: toe x/z "
        "9.8/3.6 cm this way, 50/27 cm ungated)",
    )
    stance_test: bool = Field(
        default=True,
        description="test every proposed stance frame against vision "
        "(filter/stance.StanceConsistencyTest): the camera displacement must be what the "
        "shank turning about a still ankle explains, frame to frame and summed since onset. "
        "False = trust the acceleration detector alone (a slow swing then pins the ankle)",
    )
    stance_foot_test: bool = Field(
        default=True,
        description="test every proposed stance frame against the foot's rotation "
        "(filter/stance.FootRotationTest; needs the ankle angle of joints.csv): the foot "
        "pitch (shank pitch + ankle angle) must not change since onset by more than the "
        "anchor's ankle sigma allows, since a foot turning about its heel or toe moves the "
        "ankle. Mechanism, not a fitted threshold: the test uses stance_pitch_sigma_rad, "
        "stance_slip_sigma_m and stance_test_probability. A slow loading response (foot "
        "flattening at ~1 rad/s, ankle moving 8-10 cm/s with accelerations under the "
        "detector's threshold) otherwise passes as stance and the anchor holds the camera "
        "back by the ankle's travel (sweep sts_slow_30fps seed 1000: 2.2 cm in the first "
        "0.3 s, kept for the whole trial). Sweep seeds 1000-1002, filter toe x cm, off -> "
        "on: sts_slow_30fps 2.74 -> 1.12, sts_slow_15fps 2.20 -> 2.04; paper scenarios seeds "
        "1-5 identical except prosthesis_upstair 0.97 -> 1.05. False = no foot test",
    )
    stance_test_weighted_chain: bool = Field(
        default=False,
        description="the since-onset stance consistency test weighs each visual displacement "
        "by its inverse covariance (an estimate of the ankle's mean motion per frame) instead "
        "of summing the displacements: an x-blind displacement (ICP sigma ~1 m, only treads "
        "in view) then no longer blinds the chain's x for the rest of the stance "
        "(filter/stance.StanceConsistencyTest). Identical to the sum when the links' "
        "covariances are equal",
    )
    stance_override_needs_power: bool = Field(
        default=True,
        description="the vision override of a refused stance anchor (stance_gate) needs "
        "vision to have been able to see the disagreement: the chain of displacements since "
        "onset must reject a still ankle had the ankle moved by the anchor's innovation "
        "(StanceConsistencyTest.resolves, same chi-square probability). A displacement whose "
        "x is unobservable (ICP x sigma ~1 m, only treads in view) passes the stance test "
        "vacuously along x and would otherwise force an anchor the filter refuses by ~10 cm "
        "(upstair_step_to_step_slow seed 12, t = 15.615 s: camera x -11.1 cm in one update); "
        "without that power the refusal stands and the stance ends",
    )
    stance_test_probability: float = Field(
        default=0.999,
        gt=0,
        lt=1,
        description="chi-square (2 dof) probability of the stance consistency test",
    )
    stance_velocity_sigma_mps: float | None = Field(
        default=0.05,
        gt=0,
        description="if set: every anchored stance frame also observes the camera velocity "
        "of a still ankle (v_cam = -pitch rate x lever, ground axes) with this sigma (m/s) per "
        "axis, gated (never forced, unlike the anchor). The anchor needs two frames of one stance "
        "before it says anything; at 1.5x cadence foot-flat lasts 0.15 s and the detector "
        "passes 1-2 frames of it, so a velocity error (e.g. from an accelerometer clipped at a "
        "push-off) ran on across a level landing: sweep cadence_1.5 seeds 1000-1002, filter "
        "toe x 10.3/3.0/7.2 -> 2.4/3.6/5.4 cm. None = off",
    )
    stance_attitude_reanchor: bool = Field(
        default=True,
        description="end a stance anchor and start a new one at this frame when the "
        "level-surface pitch offset (level_aiding) has turned since the anchor's onset by "
        "more than the anchor's own sigma allows over the camera-ankle lever (turn x lever > "
        "sqrt(lever sigma^2 + slip sigma^2)): the anchor holds the ankle seen through the "
        "onset's attitude, and the turned lever would drag the camera by turn x lever "
        "(camera 8 cm below the knee, 0.36 m lever: 1 deg -> 6 mm). Sweep camera_8cm_0deg "
        "seeds 1000-1002 filter toe x 1.39/3.32/1.43 -> 1.23/1.86/1.51 cm. False = keep the "
        "anchor",
    )
    stance_slip_sigma_m: float = Field(
        default=0.0005,
        ge=0,
        description="sigma (m) per axis for ankle motion during detected stance (roll-over, "
        "soft contact), added to each ankle observation. 0.5 mm fits the simulator, whose "
        "ankle is rigidly still in foot-flat; re-measure on the rig (mocap ankle marker)",
    )
