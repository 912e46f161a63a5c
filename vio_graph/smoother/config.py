"""Configuration of the GTSAM smoother (fixed-lag and batch), the project's step beyond the paper.

IMU noise defaults come from the Xsens MTi-1 series datasheet (continuous-time densities):
accelerometer 120 ug/sqrt(Hz) = 1.18e-3 m/s^2/sqrt(Hz), gyroscope 0.007 deg/s/sqrt(Hz) =
1.22e-4 rad/s/sqrt(Hz). Bias random walks are set larger than the in-run stability so that the
bias can absorb slow drift and small lever-arm / attitude errors. Every field carries its unit
in its name or description.
"""

from __future__ import annotations

from typing import Literal

from pydantic import BaseModel, ConfigDict, Field

from vio_graph.geometry import GRAVITY_MPS2

#: Xsens MTi-1 accelerometer noise density, m/s^2/sqrt(Hz).
MTI1_ACCEL_NOISE_DENSITY_MPS2_PER_SQRT_HZ = 1.18e-3
#: Xsens MTi-1 gyroscope noise density, rad/s/sqrt(Hz).
MTI1_GYRO_NOISE_DENSITY_RADPS_PER_SQRT_HZ = 1.22e-4
#: Error of the curvature-corrected step mean (trapezoid minus dt^2/12 y'', y'' by central
#: differences) over one sample step of a quartic signal, in units of h * D4 (h the step, D4
#: the fourth difference): exactly 11/720 (tests/test_smoother.py checks it).
GYRO_DISCRETIZATION_GAIN = 11.0 / 720.0


class FactorFamilies(BaseModel):
    """Which factor families enter the graph (for the ablation study)."""

    model_config = ConfigDict(extra="forbid", frozen=True)

    imu: bool = Field(default=True, description="preintegrated CombinedImuFactor between keyframes")
    displacement: bool = Field(
        default=True, description="chained ICP displacements between keyframes (BetweenFactorPose3)"
    )
    landmarks: bool = Field(
        default=True, description="corner tracks as landmarks L(j) observed from keyframes"
    )
    stance_anchors: bool = Field(
        default=True,
        description="the planted ankle during each stance as a landmark seen through the leg "
        "(the filter's stance anchor, vio_graph/filter/stance.py)",
    )
    height_landmarks: bool = Field(
        default=False,
        description="the level surfaces of a keyframe's slice (treads, landings, floor) as "
        "z-only landmarks, associated by the filter's height landmarks "
        "(filter.level_landmarks): the floor's height is handed from keyframe to keyframe, "
        "as the filter's is (docs/method.md, 'Height landmarks in the smoothers'). Off: it "
        "ties the graphs to the filter's association, and where the filter fails the smoothers "
        "would fail with it (occluding foot, upstair seeds 1-2: batch toe z 0.51 -> 5.08 cm; "
        "height_landmark_association 'graph' removes that coupling); it also loses on "
        "descents (sweep sts_descent, two_flights_down; held-out Q), with either association: "
        "there the surfaces seen beyond ~0.4 m read 1.5-3 mm high and scatter more than "
        "their variance says (docs/method.md, section 4). That loss is in the toe, not the "
        "camera: with the 'graph' association sweep sts_descent seeds 1000-1001 camera z "
        "smoother / batch 0.28 / 0.28 -> 0.09 / 0.08 cm while toe z 0.33 / 0.29 -> 0.54 / "
        "0.50, the first frame's leg-chain error (-0.4 to -0.55 cm, the toe ATE's anchor) "
        "no longer offset by a drifting camera; the fixed-lag smoother's own loss on "
        "two_flights_down goes with fixed_lag_batch_solver (configs/"
        "smoother_height_landmarks.yaml; docs/generalisation.md, fifteenth session)",
    )
    height_landmark_association: Literal["filter", "graph"] = Field(
        default="filter",
        description="with height_landmarks: which surface is which landmark. 'filter': the "
        "filter's height landmark ids (LevelObservation.level_id; the filter re-identifies a "
        "surface by its own height, so where the filter's height fails the graphs inherit a "
        "wrong association). 'graph': the graph decides by its own height: the surface's "
        "world height (the keyframe's height as the graph last solved it, moved by the "
        "filter's motion since, plus the observed height) against each live height "
        "landmark's estimate, nearest within height_landmark_gate_m and clearly nearest "
        "(the next at least twice as far), else a new landmark. The fixed-lag smoother uses "
        "its latest solution; the batch solves once without the height factors, associates "
        "with that solution and solves again",
    )
    stance_velocity: bool = Field(
        default=True,
        description="a stance keyframe's IMU velocity from the still ankle (the filter's "
        "stance velocity observation, moved from the camera to the IMU with the gyro). Sweep "
        "seed 1002, smoother / batch toe x cm: IMU upside down 2.27 / 1.02 -> 0.46 / 0.44, IMU "
        "turned 90 deg 2.06 / 1.16 -> 0.62 / 0.62 (the smoother's x ran away on the final "
        "level landing, where the filter, with the velocity, did not)",
    )
    saturation_bridge: bool = Field(
        default=True,
        description="the first keyframe after a saturated accelerometer stretch gets the "
        "filter's leg-chain bridge velocity (filter/leg_bridge.py, moved from the camera to "
        "the IMU with the gyro) as a prior on its velocity; no effect without saturation",
    )
    saturation_bridge_relative: bool = Field(
        default=False,
        description="the bridge as the velocity change it measures: a factor between the "
        "velocities of the keyframes before and after the stretch (the chain's change across "
        "it, the filter's IMU propagation on either side, the chain's covariance: hip and "
        "encoder noise) instead of the prior, whose value and noise hold the filter's own "
        "velocity before the stretch. Off: 4 g seeds 1-3 smoother / batch toe x upstair "
        "0.53 / 0.57 -> 0.49 / 0.56, obstacle 0.77 / 0.80 -> 0.66 / 0.72, but "
        "prosthesis_upstair 0.79 / 0.93 -> 0.95 / 1.03 cm, where the chain misses the change "
        "by 0.1-0.8 m/s and the prior's larger noise weighed it down (docs/robustness.md, "
        "saturation). No effect without saturation_bridge or without saturation",
    )
    saturation_bridge_discretisation: bool = Field(
        default=True,
        description="the bridge's noise in the smoothers also holds the leg chain's own "
        "discretisation error at the stretch's two ends (the term the filter's "
        "filter.imu_faults.saturation_bridge_discretisation_sigma adds, off there; "
        "LegChainBridge.discretisation_cov): at 1.5x cadence the bridge missed by 0.37 and "
        "0.66 m/s at a stated 0.18 and 0.145 m/s and the prior held the velocity off over the "
        "blind landing. Off: held-out G seeds 7007-7014 smoother / batch toe x 1.49 / 1.41 "
        "-> 2.23 / 2.13 cm, sweep cadence_1.5 0.93 / 1.03 -> 0.94 / 0.90, 4 g saturation on "
        "the paper scenarios within 0.01 cm (docs/generalisation.md, G traced). The keyframe "
        "that carries the bridge may be a later one: the joints must cover the ends by two "
        "periods (at most 0.1 s). The filter is unchanged. No effect without "
        "saturation_bridge or without saturation",
    )
    attitude: bool = Field(default=True, description="vendor AHRS attitude prior per keyframe")
    planar: bool = Field(
        default=True, description="sagittal-plane priors: lateral position and velocity = 0"
    )
    weak_position: bool = Field(
        default=False,
        description="weak absolute position prior per keyframe at its initial guess (the "
        "filter's position), for conditioning. Off by default: both solvers factorise with "
        "QR and need no such prior, and the priors add up over a trial (N keyframes at "
        "sigma s act on the slow, trial-long error modes like one prior of sigma s/sqrt(N)), "
        "so the smoothed path followed the filter's drift: 2-minute upstair trial, camera x "
        "ATE fixed-lag 9.4 -> 2.8 cm, batch 12.1 -> 2.1 cm without it",
    )


class SmootherConfig(BaseModel):
    """Parameters of :mod:`vio_graph.smoother` (graph, fixed-lag and batch smoothers)."""

    model_config = ConfigDict(extra="forbid", frozen=True)

    # --- window ---
    window_s: float = Field(
        default=2.0,
        gt=0,
        description="fixed-lag window length (s); the smoother lag is set to n*dt + dt/2 with "
        "dt = keyframe_period_s so that the window does not alternate by one keyframe",
    )
    keyframe_period_s: float = Field(
        default=0.1, gt=0, description="nominal keyframe spacing (s), used only to set the lag"
    )
    marginalization_slack_s: float = Field(
        default=0.2,
        ge=0,
        description="fixed-lag smoother (the incremental one; fixed_lag_batch_solver "
        "marginalises at every update): keys leave the window in batches, once the oldest is "
        "older than lag + slack (s); the window then holds between lag and lag + slack. 0: "
        "every update marginalises what is older than the lag. An update that marginalises "
        "makes GTSAM's IncrementalFixedLagSmoother order the re-eliminated variables with "
        "only the leaving keys constrained (first), which lets the Bayes tree's root drift "
        "away from the newest keyframe (then every update re-eliminates the path from the "
        "newest keyframe to that root); updates that marginalise nothing keep iSAM2's own "
        "rule (the new keys last, at the root). 0 -> 0.2: update median -38 % upstair s1, "
        "-78 % downstair s1 (benchmarks/ab_fixed_lag.py); ATE change in docs/method.md",
    )

    # --- IMU (continuous-time densities, MTi-1 datasheet) ---
    gravity_mps2: float = Field(default=GRAVITY_MPS2, gt=0, description="gravity magnitude m/s^2")
    accel_noise_density_mps2_per_sqrt_hz: float = Field(
        default=MTI1_ACCEL_NOISE_DENSITY_MPS2_PER_SQRT_HZ,
        gt=0,
        description="accelerometer white-noise density (m/s^2/sqrt(Hz))",
    )
    gyro_noise_density_radps_per_sqrt_hz: float = Field(
        default=MTI1_GYRO_NOISE_DENSITY_RADPS_PER_SQRT_HZ,
        gt=0,
        description="gyroscope white-noise density (rad/s/sqrt(Hz))",
    )
    accel_bias_rw_mps3_per_sqrt_hz: float = Field(
        default=1e-3, gt=0, description="accelerometer bias random walk (m/s^3/sqrt(Hz))"
    )
    gyro_bias_rw_radps2_per_sqrt_hz: float = Field(
        default=1e-4, gt=0, description="gyroscope bias random walk (rad/s^2/sqrt(Hz))"
    )
    imu_discretization_gain: float = Field(
        default=0.02,
        ge=0,
        description="gain (dimensionless) on the sampled-signal model error added to each IMU "
        "factor's covariance (imu_sampling.discretization_velocity_var); 0 = datasheet noise only. "
        "0.02 makes the velocity error of preintegration from the true state consistent "
        "(mean normalised squared error 1.0, p95 3.0) on the four simulated experiments, "
        "preintegrating from the true state over every keyframe interval",
    )
    gyro_discretization_gain: float = Field(
        default=GYRO_DISCRETIZATION_GAIN,
        ge=0,
        description="gain (dimensionless) on the sampled gyro signal's model error added to each "
        "IMU factor's rotation covariance (imu_sampling.discretization_rotation_var, sum of "
        "(h D4)^2 over the gyro's fourth differences D4, h the sample period); 0 = datasheet "
        "noise only. Default 11/720: the curvature-corrected step mean of a quartic signal "
        "misses its integral over one step by exactly (11/720) h D4 (analytic, not fitted). "
        "On the simulated upstair gait the term is ~15x the MTi-1's white gyro noise over "
        "0.1 s around heel strikes at 50 Hz and negligible in smooth swing at 100 Hz",
    )
    integration_sigma_m: float = Field(
        default=1e-4, gt=0, description="preintegration position integration noise sigma (m)"
    )

    held_accel_interpolation: bool = Field(
        default=True,
        description="replace an accelerometer sample the fault monitor held over a corrupted "
        "packet (ImuSample.accel_held, vio_graph/filter/imu_faults.py) by the linear "
        "interpolation between its trusted neighbours once the next sample has arrived; "
        "False = preintegrate the held value",
    )
    held_gyro_interpolation: bool = Field(
        default=False,
        description="with held_accel_interpolation: also replace the gyro of that corrupted "
        "packet (which the fault monitor predicted from the vendor orientation, 0.4-0.6 rad/s "
        "RMS per axis off on the simulated gaits) by the interpolation between its "
        "neighbours (0.07 rad/s RMS in pitch); extra gyro sigma interpolated_gyro_sigma_radps",
    )
    held_keep_consistent_axes: bool = Field(
        default=True,
        description="with held_accel_interpolation: an axis of that corrupted packet whose "
        "measurement agrees with the interpolation between its neighbours (within the "
        "held_axis_probability quantile of a 1-dof chi-square, sigma "
        "interpolated_accel_sigma_mps2 / interpolated_gyro_sigma_radps) keeps the measurement "
        "(ImuSample.measured_accel_mps2 / measured_gyro_radps), the others get the "
        "interpolation (accelerometer) or the monitor's stand-in (gyro, unless "
        "held_gyro_interpolation); filter.imu_faults.keep_consistent_axes is the filter's",
    )
    held_axis_distrust: bool = Field(
        default=True,
        description="with held_keep_consistent_axes: the interpolated sample's extra "
        "accelerometer variance (interpolated_accel_sigma_mps2) on the axes that were "
        "interpolated only (ImuSample-style per-axis covariance, as saturation_axis_distrust "
        "for clipped axes); the kept axes are measurements. False: on every axis "
        "(docs/robustness.md, IMU spikes: the interpolated axes only)",
    )
    held_axis_probability: float = Field(
        default=0.999, gt=0, lt=1, description="probability of that per-axis test"
    )
    interpolated_gyro_sigma_radps: float = Field(
        default=0.3,
        gt=0,
        description="extra sigma (rad/s, per axis) of an interpolated gyro sample (the "
        "interpolation's 99th-percentile error in pitch on the simulated gaits: 0.34 rad/s)",
    )
    interpolated_accel_sigma_mps2: float = Field(
        default=5.0,
        gt=0,
        description="extra sigma (m/s^2, per axis) of an interpolated accelerometer sample: "
        "on the four simulated paper experiments (3 seeds, noise-free neighbours) the "
        "interpolation misses the true specific force by 1.2-1.8 m/s^2 RMS per axis, 5-7 at "
        "the 99th percentile (the held value: 4-5 RMS, 19-23 at the 99th)",
    )

    # --- displacement / landmark measurements ---
    preintegration: Literal["common_frame", "midpoint_curvature", "raw"] = Field(
        default="common_frame",
        description="'common_frame': curvature-corrected step means of the specific force "
        "taken in the interval-start frame (imu_sampling.common_frame_samples; exact for gravity); "
        "'midpoint_curvature': the same means in the moving IMU frame, turned by half a "
        "step (imu_sampling.midpoint_samples; gravity short by (omega dt)^2/24, upstair toe z "
        "0.70 vs 0.40 cm); 'raw': each IMU sample held over its step, as GTSAM's "
        "integrateMeasurement assumes (the ablation's baseline)",
    )
    preintegration_substeps: int = Field(
        default=1,
        ge=1,
        le=8,
        description="each step between IMU samples (and the keyframe times) is split into "
        "this many equal sub-steps, each with its own curvature-corrected mean "
        "(imu_sampling._imu_knots). GTSAM moves the position by v dt + a dt^2 / 2 with the "
        "step's mean a, which misses the first moment of a changing specific force by "
        "dt^2 / 12 times its change over the step; n sub-steps cut that n^2-fold. It "
        "matters at low IMU rates (docs/method.md section 4, 'Sub-steps')",
    )
    distrust_noise: Literal["per_step", "spread"] = Field(
        default="per_step",
        description="where the extra variance of distrusted IMU samples (saturated, repaired; "
        "vio_graph/filter/imu_faults.py) enters the preintegration: 'per_step' = in the steps "
        "those samples fall in, so the position uncertainty grows with the time since them, "
        "as a lost velocity pulse's error does; 'spread' = evenly over the keyframe interval "
        "as extra white noise (before 2026-12-02; upstair s1 4 g saturation batch toe x "
        "4.29 cm)",
    )
    saturation_axis_distrust: bool = Field(
        default=True,
        description="a saturated sample's extra accelerometer variance on its clipped axes "
        "only (ImuSample.accel_extra_cov_m2ps4): the other axes are measured, so the "
        "velocity a clipped stretch lost is unknown along one body axis, and what vision "
        "measures of it (z on a level floor) fixes its share on the blind axis (x). Off: on "
        "every axis. No effect without saturation",
    )
    height_landmark_kernel: Literal["default", "huber", "cauchy", "geman_mcclure", "none"] = Field(
        default="default",
        description="M-estimator on the height-landmark factors (factors.height_landmarks): "
        "'default' = robust_kernel / robust_threshold (as the displacements and corners); "
        "the others with height_landmark_kernel_threshold. A redescending kernel (cauchy, "
        "geman_mcclure) lets the other factors outvote a wrongly associated surface",
    )
    height_landmark_kernel_threshold: float = Field(
        default=3.0, gt=0, description="its threshold in whitened units (sigmas)"
    )
    height_landmark_heights: Literal["filter", "ray_fit"] = Field(
        default="filter",
        description="factors.height_landmarks: the heights handed to the smoothers. 'filter': "
        "the filter's own (filter.level_aiding.ray_fit decides how they are fitted). "
        "'ray_fit': each surface's height refitted with its errors along the camera rays "
        "(frontend/level.py, _ray_refit; far surfaces on a descent read 1.5-3 mm high with "
        "the vertical fit) for the smoothers only, the filter keeping its own heights "
        "(the level surfaces are then fitted on the numpy path: the filter's heights and "
        "tilt equal to rounding, not bit for bit). No effect without height_landmarks",
    )
    height_landmark_gate_m: float = Field(
        default=0.03,
        gt=0,
        description="factors.height_landmark_association 'graph': a surface within this "
        "height (m) of a live height landmark's estimate, and clearly nearest to it, is that "
        "landmark (the filter's level_reidentify_m, the same rule: level surfaces of "
        "different height are a rise apart, >= 0.10 m on the simulated stairs)",
    )
    robust_kernel: Literal["huber", "cauchy", "none"] = Field(
        default="huber", description="M-estimator on displacement and landmark factors"
    )
    robust_threshold: float = Field(
        default=1.345,
        gt=0,
        description="kernel threshold in whitened units (sigmas) of the whole factor residual",
    )
    imu_robust_kernel: Literal["huber", "cauchy", "none"] = Field(
        default="huber",
        description="M-estimator on the IMU factors of the batch smoother (a spike or a "
        "saturated interval the fault monitor did not catch); 'none' = Gaussian IMU factors. "
        "Not in the fixed-lag smoother: iSAM2 keeps a factor's first linearisation, so IMU "
        "factors down-weighted at the filter's initial guess stay down-weighted",
    )
    imu_robust_threshold: float = Field(
        default=6.1,
        gt=0,
        description="IMU kernel threshold in whitened units of the whole 15-dim residual "
        "(rotation, position, velocity, two biases): sqrt of the chi-square 15-dof quantile at "
        "p = 0.999, so a consistent factor is never down-weighted",
    )
    frame_displacement_sigma_m: float = Field(
        default=0.001,
        ge=0,
        description="sigma (m) added in quadrature per axis to each frame-to-frame ICP "
        "displacement before it is chained (the filter's measurement_noise_floor_m plays "
        "the same role: the front end's covariance is optimistic, NEES ~4-5). 10 seeds x 4 "
        "experiments, smoother toe x cm at 0 / 1 / 3 mm: upstair 0.71/0.62/0.49, obstacle "
        "0.74/0.76/1.04",
    )
    min_measurement_sigma_m: float = Field(
        default=1e-3,
        gt=0,
        description="floor on displacement / observation sigmas (m) per axis: avoids "
        "near-singular covariances from the front end",
    )
    corner_landmark_sigma_m: float = Field(
        default=0.0,
        ge=0,
        description="sigma (m) added in quadrature per axis to a corner observation's "
        "covariance (FilterConfig.corner_landmark_sigma_m for the filter, also 0). 0: measured "
        "on upstair x 5 seeds, 3 / 5 / 10 mm gave toe z ATE 0.66 / 0.67 / 0.70 cm vs 0.65 cm",
    )
    lateral_measurement_sigma_m: float = Field(
        default=1.0,
        gt=0,
        description="sigma (m) on the unobserved lateral (world y) axis of 2D measurements",
    )
    measurement_rotation_sigma_rad: float = Field(
        default=1.0,
        gt=0,
        description="sigma (rad) on the rotation part of BetweenFactorPose3 measurements: the "
        "rotation is only the AHRS value, so it is left almost free",
    )

    # --- attitude anchoring (vendor AHRS, heading removed) ---
    attitude_sigma_rad: float = Field(
        default=0.02,
        gt=0,
        description="sigma (rad) of the per-keyframe AHRS attitude prior; inflated over the "
        "datasheet (1 deg RMS dynamic) because AHRS errors are correlated in time",
    )

    # --- priors ---
    first_position_sigma_m: float = Field(
        default=1e-3, gt=0, description="prior sigma (m) on the first keyframe position"
    )
    first_velocity_sigma_mps: float = Field(
        default=0.1, gt=0, description="prior sigma (m/s) on the first keyframe velocity"
    )
    first_velocity_kernel: Literal["huber", "cauchy", "none"] = Field(
        default="none",
        description="robust kernel on the first keyframe's velocity prior (the filter's v = 0 "
        "at its start, 7-9 sigma off on a trial starting mid-stride): 'huber' lets the IMU "
        "chain and the displacements outvote it. Off: 2 Hz spikes seeds 1-3 downstair "
        "smoother / batch toe x 0.96 / 0.84 -> 0.75 / 0.64 cm, but obstacle 0.51 / 0.52 -> "
        "0.59 / 0.61 cm; clean trials within -8 .. +1 % (docs/method.md, IMU faults)",
    )
    first_velocity_kernel_threshold: float = Field(
        default=1.345, gt=0, description="its threshold (whitened; 95 % Gaussian efficiency)"
    )
    first_velocity_filter_cov: bool = Field(
        default=False,
        description="the first keyframe's velocity prior also carries the filter's velocity "
        "covariance at that frame (added to first_velocity_sigma_mps^2 in x-z): the filter "
        "starts at the first frame with v = 0 and 0.5 m/s of sigma, so on a trial starting "
        "mid-stride (0.7 m/s) the 0.1 m/s prior is a 7-sigma pull that only the IMU chain to "
        "the later keyframes holds off (a repaired IMU packet 60 ms in loosened it: downstair "
        "seed 2 with spikes, smoother toe x 0.96 -> 0.37 cm). Off: on the clean obstacle "
        "trials (seeds 1-3) it cost the batch smoother 0.27 -> 0.33 cm in x "
        "(docs/method.md, IMU faults and clocks)",
    )
    first_velocity_test: bool = Field(
        default=True,
        description="when a keyframe interval within the fixed-lag window of the first "
        "keyframe spans an IMU packet the fault monitor repaired (its extra sigma loosens the "
        "IMU chain that normally outvotes the filter's start guess v = 0), "
        "test the first keyframe's velocity prior at the estimate (chi-square, 3 dof) and, if "
        "it fails, give it the filter's velocity covariance (first_velocity_filter_cov's "
        "prior) and solve again. Never acts on a trial without repaired packets (clean, "
        "saturated, offset, jitter). 2 Hz spikes: docs/method.md, IMU faults and clocks",
    )
    first_velocity_test_probability: float = Field(
        default=0.999,
        gt=0,
        lt=1,
        description="quantile of the first velocity prior's chi-square test (3 dof)",
    )
    first_attitude_sigma_rad: float = Field(
        default=0.01, gt=0, description="prior sigma (rad) on the first keyframe attitude"
    )
    accel_bias_prior_sigma_mps2: float = Field(
        default=0.05, gt=0, description="prior sigma (m/s^2) on the first accelerometer bias"
    )
    gyro_bias_prior_sigma_radps: float = Field(
        default=5e-3, gt=0, description="prior sigma (rad/s) on the first gyroscope bias"
    )
    lateral_position_sigma_m: float = Field(
        default=1e-3, gt=0, description="sagittal-plane prior sigma (m) on IMU world y"
    )
    lateral_velocity_sigma_mps: float = Field(
        default=1e-3, gt=0, description="sagittal-plane prior sigma (m/s) on IMU world y velocity"
    )
    weak_position_sigma_m: float = Field(
        default=1.0,
        gt=0,
        description="weak absolute prior sigma (m) on each keyframe's x, z at the initial guess",
    )
    landmark_lateral_sigma_m: float = Field(
        default=1e-3, gt=0, description="prior sigma (m) on a landmark's world y (fixed at 0)"
    )
    landmark_rotation_sigma_rad: float = Field(
        default=1e-4, gt=0, description="prior sigma (rad) fixing the unused landmark rotation"
    )
    landmark_position_sigma_m: float = Field(
        default=10.0, gt=0, description="weak prior sigma (m) on a landmark's x, z"
    )

    # --- solver ---
    fixed_lag_factorization: Literal["QR", "CHOLESKY"] = Field(
        default="CHOLESKY",
        description="ISAM2 factorisation in the fixed-lag smoother. Cholesky factorises the "
        "normal equations (condition number squared), QR the Jacobian. Cholesky: update "
        "median -13 % (upstair s1) to -15 % (downstair s1), means -18 % / -39 %, with "
        "marginalization_slack_s 0.2 (benchmarks/ab_fixed_lag.py); the paper's 4 scenarios x "
        "3 seeds and 4 x 2 with 5 % spurious depth points gave the QR ATEs to 1e-3 cm with "
        "no failure. An earlier graph raised IndeterminantLinearSystem with Cholesky on a "
        "spurious-points trial: fixed_lag_qr_fallback answers that case",
    )
    fixed_lag_qr_fallback: bool = Field(
        default=True,
        description="with CHOLESKY: when an update fails (finds the system indeterminate, or "
        "any other GTSAM error), rebuild the "
        "window (its factors, marginals of the keyframes already gone, linearisation point "
        "and key times) in a QR smoother and continue in QR for the rest of the run "
        "(metrics.json: smoother_qr_fallback_at_s); off: the smoother stops there as any "
        "failed update does",
    )
    batch_factorization: Literal["QR", "CHOLESKY"] = Field(
        default="CHOLESKY",
        description="LM linear solver of the full batch. CHOLESKY (with batch_qr_fallback): "
        "half the solve's memory of QR (its Bayes trees hold the whole stacked Jacobian of "
        "every clique), 600 s trial +197 against +407 MiB, ~30 % less solve CPU, the same "
        "keyframes to 2e-11 m (docs/performance-log.md, Batch memory). QR: robust to the poor "
        "conditioning of long relative-only runs, it never squares the condition number; the "
        "fallback gives its answer wherever the Cholesky solve could have differed from it",
    )
    batch_qr_fallback: bool = Field(
        default=True,
        description="with batch_factorization CHOLESKY: if any LM step had to be retried "
        "(GTSAM's LM takes a failed Cholesky factorisation, an indefinite system, as a rejected "
        "step and raises lambda instead of raising an error), solve again with QR from the "
        "initial values and keep that answer (metrics.json batch_qr_fallbacks). With every step "
        "taken at its first lambda, the Cholesky and QR answers differ by rounding only",
    )
    marginal_covariance: Literal["at_exit", "when_newest", "none"] = Field(
        default="none",
        description="covariance kept for keyframes that leave the window: the smoothed marginal "
        "just before marginalisation (~3.5 ms per keyframe, far from the Bayes-tree root), the "
        "filtering marginal when the keyframe was newest (~0.2 ms median, ~0.6 ms mean on "
        "simulated stairs; conservative), or none (NaN; keyframes still in the window get "
        "theirs on request). Nothing in `vio-graph run` reads keyframe covariances, hence none "
        "by default; ask for one of the others when calling keyframe_estimates() yourself",
    )
    relinearize_threshold: float = Field(
        default=0.05,
        gt=0,
        description="ISAM2 relinearisation threshold (tangent units) of the fixed-lag smoother. "
        "0.01 -> 0.05: update + building CPU per keyframe -32 % on downstair s1 (the old value "
        "relinearised ~11 variables and re-eliminated ~130 of ~170 at every update), -17 % "
        "obstacle, -5 % upstair; smoother toe ATE over the paper's 4 scenarios x 3 seeds "
        "within +-0.1 cm per trial, means equal or lower except obstacle x over the whole "
        "trial (0.33 -> 0.41 cm; 0.36 -> 0.34 cm on the frames with the edge visible)",
    )
    batch_max_iterations: int = Field(default=50, gt=0, description="LM iterations (batch)")
    batch_relative_error_tol: float = Field(
        default=1e-6, gt=0, description="LM relative error decrease tolerance (batch)"
    )
    fixed_lag_batch_solver: bool = Field(
        default=False,
        description="use gtsam.BatchFixedLagSmoother (LM) instead of IncrementalFixedLagSmoother",
    )

    leg_attitude: Literal["smoothed", "filter"] = Field(
        default="smoothed",
        description="shank pitch of the smoothed modes' leg kinematics (knee, ankle, heel, toe "
        "from the camera): 'smoothed' = the smoother's own refined keyframe attitude (the "
        "filter's per-frame pitch plus the keyframe corrections, interpolated in time, like "
        "the camera path), 'filter' = the filter's causal level-aided attitude. The smoothed "
        "attitude uses later keyframes through the gyro and the gravity direction the "
        "accelerometer shows once vision fixes the motion: keyframe shank pitch error RMS "
        "0.28 / 0.26 / 0.30 -> 0.17 / 0.18 / 0.18 deg (batch, prosthesis_upstair seeds 1, 2, "
        "5), first keyframe (the toe ATE's anchor) 0.88 -> 0.27 deg on seed 1",
    )
    factors: FactorFamilies = Field(
        default_factory=FactorFamilies, description="factor families switched on"
    )

    def smoother_lag_s(self) -> float:
        """Lag handed to GTSAM: n * dt + dt / 2 with n = round(window / dt) (seconds)."""
        n = max(1, round(self.window_s / self.keyframe_period_s))
        return n * self.keyframe_period_s + 0.5 * self.keyframe_period_s
