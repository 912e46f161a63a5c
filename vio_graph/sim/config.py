"""Scenario configuration of the simulator (pydantic v2, defaults in code, YAML overrides).

Numbers and their sources are in docs/simulator.md.
"""

from __future__ import annotations

from pathlib import Path
from typing import Literal

from pydantic import BaseModel, ConfigDict, Field, field_validator

from vio_graph.config_files import load_yaml_mapping, resolve_config_path, validate_model
from vio_graph.errors import ConfigError


class _Section(BaseModel):
    model_config = ConfigDict(extra="forbid", frozen=True)


def _check_range(v: tuple[float, float] | None, lo_min: float) -> tuple[float, float] | None:
    """A (lo, hi) range with lo_min <= lo <= hi."""
    if v is not None and not (lo_min <= v[0] <= v[1]):
        raise ValueError(f"expected {lo_min} <= lo <= hi, got {tuple(v)}")
    return v


class TerrainConfig(_Section):
    """Sagittal terrain profile, extruded across ``width_m``. The first feature (first riser,
    first edge down, obstacle front face) is at x = ``approach_length_m``; the floor at the
    trial start is z = 0."""

    kind: Literal["stair_up", "stair_down", "obstacle", "level"] = Field(
        "stair_up", description="terrain class"
    )
    approach_length_m: float = Field(1.5, gt=0, description="level floor before the feature, m")
    stair_rise_m: float = Field(0.147, gt=0, description="riser height, m (paper III.A)")
    stair_tread_m: float = Field(0.28, gt=0, description="tread depth, m (paper III.A)")
    n_steps: int = Field(12, ge=1, description="number of risers")
    landing_length_m: float = Field(4.0, gt=0, description="level floor after the stairs, m")
    obstacle_height_m: float = Field(0.14, gt=0, description="obstacle height, m (paper III.A)")
    obstacle_depth_m: float = Field(0.13, gt=0, description="obstacle depth along x, m")
    exit_length_m: float = Field(13.0, gt=0, description="level floor after the obstacle, m")
    width_m: float = Field(1.2, gt=0, description="stair / walkway width, m")
    side_walls: bool = Field(True, description="add vertical walls at y = +-width/2")
    wall_height_m: float = Field(1.2, gt=0, description="wall height above the profile, m")
    nosing_overhang_m: float = Field(
        0.0,
        ge=0,
        le=0.05,
        description="stairs: horizontal protrusion of each tread's nosing past the riser "
        "below it, m (typical 0-0.03; building codes allow up to ~0.03-0.04). The nosing tip "
        "stays at the same place as without overhang; the riser is set back under it",
    )
    nosing_thickness_m: float = Field(
        0.03,
        gt=0,
        description="stairs with overhang: thickness of the protruding tread slab, m (its "
        "underside is visible to a camera below the nosing)",
    )
    n_flights: int = Field(
        1,
        ge=1,
        description="stairs: number of flights of n_steps risers each, joined by level landings",
    )
    flight_landing_m: float = Field(
        1.2,
        gt=0,
        description="stairs with n_flights > 1: level landing between flights, measured from "
        "the top (ascent) / last (descent) nosing of one flight to the first nosing of the "
        "next, m (must hold a foot: >= ~0.35 m)",
    )
    rise_jitter_m: float = Field(
        0.0,
        ge=0,
        le=0.05,
        description="stairs: each riser's height is stair_rise_m plus a deviation drawn "
        "uniformly in [-j, j] per riser from the trial's seed, m (building codes allow ~0.01 m "
        "between risers of a flight, old and outdoor stairs exceed it); 0: all rises equal",
    )
    tread_jitter_m: float = Field(
        0.0,
        ge=0,
        le=0.08,
        description="stairs: each tread's depth (nosing to nosing) is stair_tread_m plus a "
        "deviation drawn uniformly in [-j, j] per tread from the trial's seed, m; 0: all equal",
    )
    first_rise_m: float | None = Field(
        None,
        gt=0,
        description="stairs: height of the first riser of the stair (a raised or lowered "
        "floor finish), m; None: like the others",
    )
    last_rise_m: float | None = Field(
        None,
        gt=0,
        description="stairs: height of the last riser of the stair, m; None: like the others",
    )
    open_risers: bool = Field(
        False,
        description="stairs: no riser faces; each tread is a slab of nosing_thickness_m from "
        "its nosing to the next riser line, with the floor (ascent) or the lower floor "
        "(descent) continuing underneath, so depth rays pass under the nosings. The walking "
        "surface (metadata profile) is the same as with closed risers",
    )


class GaitConfig(_Section):
    """Gait of the instrumented leg. Times are stride (gait-cycle) times."""

    pattern: Literal["step_over_step", "step_to_step"] = Field(
        "step_over_step", description="stair pattern; step_to_step: one tread per cycle"
    )
    level_stride_time_s: float = Field(1.15, gt=0, description="level stride time, s")
    stair_stride_time_s: float = Field(1.35, gt=0, description="stair stride time, s [U]")
    stride_time_jitter: float = Field(0.05, ge=0, description="per-trial relative sd")
    level_stride_length_m: float = Field(1.25, gt=0, description="level stride length, m")
    stride_length_jitter: float = Field(0.05, ge=0, description="per-trial relative sd")
    step_jitter_m: float = Field(0.01, ge=0, description="per-foothold placement sd, m")
    stance_fraction_level: float = Field(0.61, gt=0.4, lt=0.8, description="Beaulieu 2008")
    stance_fraction_stair: float = Field(0.65, gt=0.4, lt=0.8, description="McFadyen 1988")
    step_to_step_pause_s: float = Field(0.5, ge=0, description="double-support pause, s")
    leading_leg: Literal["contralateral", "instrumented"] = Field(
        "contralateral",
        description="step_to_step: the leg that steps onto the next tread first; the other "
        "joins it on the same tread (contralateral: the instrumented leg trails)",
    )
    cadence_scale: float = Field(
        1.0,
        ge=0.25,
        le=2.0,
        description="multiplies the step frequency: every stride time (and the step_to_step "
        "movement time) is divided by it; 0.5 = twice the stride time (typical 0.5-1.5)",
    )
    pause_range_s: tuple[float, float] | None = Field(
        None,
        description="standing pause inserted once per stride with the instrumented foot flat "
        "(step_to_step: with both feet on the same tread), drawn uniformly in [lo, hi] s per "
        "stride; the motion decelerates into and accelerates out of it over pause_ramp_s; "
        "None: no pauses",
    )
    pause_ramp_s: float = Field(
        0.4, gt=0, description="deceleration / acceleration time around each pause, s"
    )
    pause_sway_deg: tuple[float, float] = Field(
        (1.0, 3.0),
        description="weight shift during a pause: amplitude range of the sagittal shank sway "
        "about the fixed ankle (foot flat), deg, drawn per pause",
    )
    pause_sway_hz: tuple[float, float] = Field(
        (0.3, 0.5), description="weight-shift sway frequency range, Hz, drawn per pause"
    )

    @field_validator("pause_range_s", "pause_sway_deg")
    @classmethod
    def _nonneg_range(cls, v):
        return _check_range(v, 0.0)

    @field_validator("pause_sway_hz")
    @classmethod
    def _positive_range(cls, v):
        return _check_range(v, 1e-6)

    start_distance_m: float = Field(
        0.45, gt=0, description="instrumented toe to the first feature at t = 0, m"
    )
    toe_clearance_level_m: float = Field(0.02, gt=0, description="Moosabhoy & Gard 2006")
    early_swing_toe_lift_m: float = Field(
        0.03, gt=0, description="level: toe height above the floor at 25 % of the swing, m"
    )
    toe_clearance_nosing_m: float = Field(0.045, gt=0, description="over stair nosings, m [U]")
    toe_clearance_obstacle_m: float = Field(0.12, gt=0, description="Patla & Rietdyk 1993 [U]")
    obstacle_step_on_depth_m: float = Field(
        0.30,
        gt=0,
        description="obstacles deeper than this (terrain.obstacle_depth_m) are stepped onto, "
        "not over: the instrumented leg steps up onto the top (an ascent swing), the other "
        "foot swings past to the floor beyond, then the instrumented leg steps down (a descent "
        "swing). Stepping over, the crossing step spans 0.18 m + depth + 0.20 m + a foot "
        "length from the trailing to the leading toe (0.95 m at 0.30 m depth, H = 1.75 m: 1.1 "
        "x thigh + shank); beyond that the simulated hip path cannot bring the leading foot "
        "down within the leg's reach (measured: 0.32-0.34 m for H = 1.55-1.75 m, "
        "docs/simulator.md)",
    )
    max_shank_specific_force_g: float | None = Field(
        20.0,
        gt=0,
        description="plausibility bound: a simulated motion whose specific force at the shank "
        "IMU exceeds this (g, 1 kHz, whole trial) is refused with an ImplausibleMotionError "
        "naming the stride and its terrain / gait parameters (vio_graph.sim.plausibility; the "
        "simulator gives 1.5-10 g with the joint-space swing, up to 14 g with the via-point "
        "stress swing); None: no check (stress tests that clip the accelerometer on purpose)",
    )
    stair_toe_margin_m: float = Field(0.03, ge=0, description="ascent: toe to next riser, m")
    stair_heel_margin_m: float = Field(0.03, ge=0, description="descent: heel to riser, m")
    heel_strike_pitch_deg: float = Field(15.0, ge=0, description="foot toe-up at heel strike")
    forefoot_landing_pitch_deg: float = Field(
        14.0, ge=0, description="foot toe-down at stair contact (Riener 2002)"
    )
    toe_off_pitch_deg: float = Field(50.0, gt=0, description="foot toe-down at toe-off, level")
    knee_contact_deg: dict[str, float] = Field(
        default_factory=lambda: {"level": 18.0, "ascent": 60.0, "descent": 18.0},
        description="knee flexion targets at foot contact, deg",
    )
    knee_midstance_deg: dict[str, float] = Field(
        default_factory=lambda: {"level": 20.0, "ascent": 35.0, "descent": 40.0},
        description="knee flexion targets at mid-stance (30 % of the stride), deg",
    )
    swing_ankle_deg: dict[str, float | None] = Field(
        default_factory=lambda: {
            "level": -10.0,
            "obstacle": -5.0,
            "ascent": -12.0,
            "descent": None,
        },
        description="ankle plantarflexion (+) held in mid-swing by swing kind, deg (stairs "
        "~10-16 dorsiflexion: McFadyen & Winter 1988); None: foot pitch from the key poses "
        "only (descent: blending towards the shank drives the heel into the nosing)",
    )
    swing_ankle_blend_fraction: float = Field(
        0.35,
        gt=0,
        le=0.5,
        description="fraction of the swing over which the foot pitch blends from the toe-off "
        "pose to shank + swing ankle (and back to the landing pose)",
    )
    hip_ahead_midstance_m: dict[str, float] = Field(
        default_factory=lambda: {"level": 0.05, "ascent": -0.06, "descent": 0.10},
        description="hip x minus stance-ankle x at mid-stance, m",
    )
    swing_model: Literal["via_points", "joint_space"] = Field(
        "joint_space",
        description="swing of the instrumented leg. joint_space (default): thigh and knee "
        "angles are C2 quintics from the toe-off state to the landing state through a peak "
        "knee flexion (swing_peak_knee_deg at swing_peak_knee_fraction of the swing), ankle by "
        "forward kinematics, raised by a C2 bump where the sole would miss the configured "
        "clearance (camera 2-3 m/s, specific force 2-5 g, as a shank on real stairs). "
        "via_points (the default before 2026-12-05, kept as a stress condition): the toe "
        "follows a spline through clearance via-points and the knee follows by inverse "
        "kinematics (fast ankle translation in early swing: camera 3.5-4.5 m/s, specific "
        "force p99 6-10 g, more violent than a real shank)",
    )
    swing_peak_knee_deg: dict[str, float] = Field(
        default_factory=lambda: {"level": 62.0, "ascent": 93.0, "descent": 89.0, "obstacle": 95.0},
        description="joint_space: peak swing knee flexion by swing kind, deg (level ~60-65: "
        "Winter 2009 [V]; ascent ~93, descent ~89: McFadyen & Winter 1988, Protopapadaki 2007 "
        "[V]; obstacle lead limb ~90-100: Chou & Draganich 1997 [U]); the clearance check may "
        "add flexion",
    )
    swing_peak_knee_fraction: dict[str, float] = Field(
        default_factory=lambda: {"level": 0.30, "ascent": 0.40, "descent": 0.35, "obstacle": 0.40},
        description="joint_space: time of the peak swing knee flexion as a fraction of the swing "
        "(level: peak at ~73 % of the cycle, toe-off at ~61 %: Winter 2009 [V]; stairs: peak at "
        "~75-80 %, toe-off at ~64 %: McFadyen & Winter 1988 [U])",
    )
    toe_off_roll_fraction: float = Field(
        1.5,
        ge=0.0,
        le=2.0,
        description="joint_space: foot pitch rate at toe-off as a fraction of its mean rate "
        "from heel-off to toe-off (the foot leaves the ground still rolling over the toe; "
        "via_points keeps a zero rate there)",
    )

    @field_validator("swing_peak_knee_fraction")
    @classmethod
    def _fractions_inside_swing(cls, v):
        for kind, f in v.items():
            if not 0.1 <= f <= 0.7:
                raise ValueError(f"swing_peak_knee_fraction[{kind}] = {f} is outside [0.1, 0.7]")
        return v


class RigConfig(_Section):
    """Instrumented leg and sensor mounting. Positions are (x, z) in the shank frame (origin
    at the knee joint centre, x anterior, z from ankle to knee)."""

    rig: Literal["able_bodied", "prosthesis"] = "able_bodied"
    body_height_m: float = Field(1.75, gt=0, description="subject height H, m (Winter 2009)")
    shank_length_m: float | None = Field(
        None, description="knee-ankle length, m; None: 0.246 H (able) or 0.42 (prosthesis pylon)"
    )
    heel_in_foot_xz_m: tuple[float, float] | None = Field(
        None, description="heel in the foot frame, m; None: anthropometric default"
    )
    toe_in_foot_xz_m: tuple[float, float] | None = Field(
        None, description="toe in the foot frame, m; None: anthropometric default"
    )
    camera_in_shank_xz_m: tuple[float, float] = Field(
        (0.07, -0.05),
        description="camera optical centre in the shank frame, m (just below the knee: from "
        "there the camera looks down on the next two treads; lower mounts see mostly risers)",
    )
    camera_pitch_down_deg: float = Field(
        20.0,
        description="optical axis below the shank x axis, deg (shallower loses the tread "
        "surfaces to grazing incidence, steeper sees one step only)",
    )
    imu_in_camera_xyz_m: tuple[float, float, float] = Field(
        (0.0, 0.02, -0.015), description="IMU point in the camera frame, m (fixed together)"
    )
    imu_axes: Literal["shank", "camera"] = Field(
        "shank",
        description="base orientation of the IMU axes: shank (x anterior, y lateral, z along "
        "the shank to the knee) or camera (the camera's optical axes: imu_T_cam rotation = "
        "identity); imu_rotation_rpy_deg is applied on top",
    )
    imu_rotation_rpy_deg: tuple[float, float, float] = Field(
        (0.0, 0.0, 0.0),
        description="roll, pitch, yaw of the IMU axes relative to the base axes (imu_axes), "
        "deg: R_base_imu = Rz(yaw) Ry(pitch) Rx(roll)",
    )


class CameraConfig(_Section):
    """pmd pico flexx2 ToF camera (Cai 2024, royale). Noise switches allow noiseless tests."""

    width_px: int = Field(224, gt=0)
    height_px: int = Field(172, gt=0)
    hfov_deg: float = Field(56.0, gt=0, lt=180, description="horizontal field of view, deg")
    vfov_deg: float = Field(44.0, gt=0, lt=180, description="vertical field of view, deg")
    min_range_m: float = Field(0.1, ge=0, description="Mode 5 near limit, m")
    max_range_m: float = Field(2.4, gt=0, description="Mode 5 far limit, m")
    frame_rate_hz: float = Field(30.0, gt=0, description="depth frame rate, Hz")
    depth_unit_m: float = Field(0.001, gt=0, description="stored depth unit, m")
    noise: bool = Field(True, description="master switch for all depth noise")
    axial_coeffs: tuple[float, float, float, float] = Field(
        (0.002362, -0.001041, 0.000753, 0.000185),
        description="a, b, c, d of sigma_z(z, theta) in m (Cai 2024, Mode 5 @30 fps)",
    )
    lateral_noise_px: float = Field(0.86, ge=0, description="sample-position jitter sd, px")
    mixed_pixel_probability: float = Field(0.6, ge=0, le=1, description="at depth jumps")
    mixed_pixel_jump_m: float = Field(0.04, gt=0, description="neighbour jump that mixes, m")
    flying_pixel_thresholds_m: tuple[float, float] = Field(
        (0.018, 0.14), description="royale flying-pixel threshold at <=1 m and >=4.5 m"
    )
    max_incidence_deg: float = Field(75.0, gt=0, le=90, description="grazing cut-off [U]")
    max_noise_m: float = Field(0.07, gt=0, description="royale: pixels noisier are invalid")
    timestamp_jitter_s: float = Field(0.001, ge=0, description="frame time jitter sd, s")
    edge_gap_m: tuple[float, float] | None = Field(
        None,
        description="missing band behind depth discontinuities (flying-pixel filter of the "
        "driver at stair nosings): per frame and per edge a band length is drawn uniformly in "
        "[lo, hi] m and the surface seen right behind each convex edge (the tread behind an "
        "ascending nosing, the lower tread past a descending one) is invalid over that length; "
        "real pico flexx2 stair profiles show 0.03-0.06 m; None: off",
    )

    depth_scale_error: float = Field(
        0.0,
        gt=-0.1,
        lt=0.1,
        description="systematic depth scale error (calibration, temperature): every depth is "
        "multiplied by 1 + this; the pico flexx2 specifies <= 1 % of distance; 0: off",
    )
    wiggling_amplitude_m: float = Field(
        0.0,
        ge=0,
        le=0.05,
        description="ToF 'wiggling' (harmonics of the modulation signal): depth error "
        "A sin(2 pi z / period + phase) left after calibration, m; a few mm typical; 0: off",
    )
    wiggling_period_m: float = Field(
        0.5,
        gt=0,
        description="depth period of the wiggling error, m (a quarter of the "
        "unambiguous range is typical)",
    )
    wiggling_phase_rad: float = Field(0.0, description="phase of the wiggling error, rad")
    multipath_bias_m: float = Field(
        0.0,
        ge=0,
        le=0.1,
        description="multipath interference in concave corners (tread meets riser): light "
        "bounced off one face returns via the other, so depths near the corner read long by "
        "up to this, m; decays as exp(-r / multipath_decay_m) with the distance r from the "
        "corner; real ToF: cm near corners; 0: off",
    )
    multipath_decay_m: float = Field(
        0.05, gt=0, description="decay length of the multipath depth error from the corner, m"
    )

    @field_validator("edge_gap_m")
    @classmethod
    def _gap_range(cls, v):
        return _check_range(v, 0.0)


class ImuConfig(_Section):
    """Xsens MTi-1 series (datasheet values; docs/simulator.md)."""

    rate_hz: float = Field(100.0, gt=0)
    noise: bool = Field(True, description="switch for all IMU errors")
    accel_noise_density: float = Field(1.18e-3, ge=0, description="m/s^2/sqrt(Hz)")
    gyro_noise_density: float = Field(1.22e-4, ge=0, description="rad/s/sqrt(Hz)")
    accel_bias_rw: float = Field(3e-5, ge=0, description="bias random walk, m/s^3/sqrt(Hz) [U]")
    gyro_bias_rw: float = Field(5e-6, ge=0, description="bias random walk, rad/s^2/sqrt(Hz) [U]")
    accel_turn_on_bias_mps2: float = Field(0.02, ge=0, description="turn-on bias sd [U]")
    gyro_turn_on_bias_radps: float = Field(0.002, ge=0, description="turn-on bias sd [U]")
    accel_range_mps2: float = Field(16 * 9.81, gt=0, description="+-16 g")
    gyro_range_radps: float = Field(34.9, gt=0, description="+-2000 deg/s")
    orientation_rms_deg: float = Field(1.0, ge=0, description="roll/pitch error RMS, deg")
    heading_rms_deg: float = Field(2.0, ge=0, description="heading error RMS, deg")
    orientation_error_tau_s: float = Field(2.0, gt=0, description="error correlation time [U]")
    random_heading_offset: bool = Field(True, description="VRU heading is arbitrary")


class JointSensorConfig(_Section):
    """Thigh IMU pitch and knee/ankle encoders at the IMU rate."""

    noise: bool = True
    thigh_pitch_error_deg: float = Field(1.0, ge=0, description="correlated error RMS, deg")
    thigh_error_tau_s: float = Field(1.0, gt=0, description="error correlation time, s")
    encoder_bits: int = Field(14, ge=1, description="quantisation (0.022 deg at 14 bit)")
    encoder_noise_deg: float = Field(0.05, ge=0, description="white noise sd, deg [U]")


class MocapConfig(_Section):
    """Motion capture (Raptor-12HS, 120 Hz)."""

    rate_hz: float = Field(120.0, gt=0)
    noise: bool = True
    marker_noise_m: float = Field(0.001, ge=0, description="per-marker sd, m (Merriaux 2017)")
    n_markers: int = Field(4, ge=3, description="markers per rigid-body cluster")
    cluster_radius_m: float = Field(0.05, gt=0, description="cluster size for orientation, m")


class FaultsConfig(_Section):
    """Sensor faults injected into the simulated data (all off by default; vio_graph.sim.faults).

    Times are trial times (s, true clock). Every field is saved in
    ``metadata.provenance.config["faults"]`` because the whole scenario config is.
    """

    camera_blackout_start_s: float | None = Field(
        None, ge=0, description="start of a camera blackout (all pixels invalid), s; None: off"
    )
    camera_blackout_duration_s: float = Field(0.0, ge=0, description="blackout length, s")
    dropped_frame_probability: float = Field(
        0.0,
        ge=0,
        lt=0.5,
        description="per-frame probability that a frame is missing from the recording "
        "(its timestamp is skipped)",
    )
    spurious_point_fraction: float = Field(
        0.0,
        ge=0,
        le=1,
        description="fraction of pixels per frame replaced by a spurious valid depth, uniform "
        "over the camera's range",
    )
    occluder_start_s: float | None = Field(
        None, ge=0, description="start of a foot-like blob occluding the view, s; None: off"
    )
    occluder_duration_s: float = Field(0.0, ge=0, description="occluder time window, s")
    occluder_center_uv_frac: tuple[float, float] = Field(
        (0.5, 0.8), description="blob centre as fractions of image width and height"
    )
    occluder_size_frac: tuple[float, float] = Field(
        (0.45, 0.3), description="blob semi-axes as fractions of image width and height"
    )
    occluder_depth_m: float = Field(
        0.25, gt=0, description="depth of the blob's nearest point (a foot close to the lens), m"
    )
    imu_spike_rate_hz: float = Field(
        0.0, ge=0, description="mean rate of IMU spikes (one sample, one random axis), 1/s"
    )
    imu_spike_accel_mps2: float = Field(30.0, ge=0, description="accel spike magnitude, m/s^2")
    imu_spike_gyro_radps: float = Field(5.0, ge=0, description="gyro spike magnitude, rad/s")
    imu_knock_start_s: float | None = Field(
        None,
        ge=0,
        description="start of an IMU knock, s (None: off): imu_knock_accel_mps2 added to the "
        "accelerometer's x and subtracted from its z for imu_knock_duration_s, a velocity "
        "error of accel x duration per axis inside the sensor's range, so nothing flags it",
    )
    imu_knock_duration_s: float = Field(0.1, ge=0, description="IMU knock length, s")
    imu_knock_accel_mps2: float = Field(
        60.0, ge=0, description="IMU knock acceleration on each of two axes, m/s^2"
    )
    imu_accel_saturation_mps2: float | None = Field(
        None, gt=0, description="clip the accelerometer at this lower range, m/s^2; None: off"
    )
    imu_gyro_saturation_radps: float | None = Field(
        None, gt=0, description="clip the gyroscope at this lower range, rad/s; None: off"
    )
    camera_time_offset_s: float = Field(
        0.0,
        description="constant camera-IMU clock offset: depth timestamps = true capture time + "
        "offset (IMU and mocap keep true time), s",
    )
    clock_jitter_s: float = Field(
        0.0,
        ge=0,
        description="sd of white timestamp error on depth frames and IMU/joint samples (the "
        "data stay at the true times), s; clipped at 0.4 sample periods",
    )


class ContactConfig(_Section):
    """Foot-contact sensor of the instrumented leg (vio_graph.sim.contact), written as
    ``contact.csv`` with the metadata ``contact`` section. Off by default (``kind: none``:
    no contact channel, the recording is the same as without this section)."""

    kind: Literal["none", "load_cell", "switch"] = Field(
        "none",
        description="none; load_cell: pylon axial force in N (e.g. the Open Source Leg's "
        "6-axis cell); switch: heel / foot switch, 1 closed, 0 open",
    )
    rate_hz: float = Field(100.0, gt=0, description="sample rate of contact.csv, Hz")
    body_mass_kg: float = Field(75.0, gt=0, description="subject mass (with the device), kg")
    grf_dip_fraction: float = Field(
        0.15,
        ge=0,
        lt=0.5,
        description="vertical force shape over the stance: humps of (1 + f) body weight after "
        "loading and before push-off, (1 - f) at mid-stance (walking: ~0.1-0.2)",
    )
    threshold_n: float = Field(
        80.0,
        gt=0,
        description="load_cell: the foot counts as loaded at or above this force, N (written "
        "to metadata contact.threshold_n; a switch always writes 0.5)",
    )
    load_cell_noise_sd_n: float = Field(3.0, ge=0, description="white noise sd, N [U]")
    load_cell_offset_sd_n: float = Field(
        5.0, ge=0, description="zero-offset (drift since taring) sd, drawn per trial, N [U]"
    )
    load_cell_filter_tau_s: float = Field(
        0.01, ge=0, description="first-order low-pass time constant of the amplifier, s [U]"
    )
    load_cell_delay_s: float = Field(
        0.005, ge=0, description="transport delay (ADC, bus, logging), s [U]"
    )
    switch_region: Literal["foot", "heel"] = Field(
        "foot",
        description="foot: switch under the whole sole (closed through the stance); heel: "
        "heel switch (closed from heel contact to heel-off; forefoot landings close it only at "
        "foot flat)",
    )
    switch_actuation_n: float = Field(
        30.0, gt=0, description="force under the switch that closes it, N [U]"
    )
    switch_delay_s: float = Field(0.01, ge=0, description="switch to logged sample delay, s [U]")
    switch_bounce_s: float = Field(
        0.008, ge=0, description="contact bounce window after each transition, s [U]"
    )
    switch_max_bounces: int = Field(
        3, ge=0, description="up to this many opposite pulses per transition (uniform 0..n)"
    )


class ScenarioConfig(_Section):
    """Everything the simulator needs for one trial (given a seed)."""

    name: str = Field("custom", description="scenario name recorded in provenance")
    duration_s: float = Field(10.0, gt=0, description="trial duration, s")
    terrain: TerrainConfig = TerrainConfig()
    gait: GaitConfig = GaitConfig()
    rig: RigConfig = RigConfig()
    camera: CameraConfig = CameraConfig()
    imu: ImuConfig = ImuConfig()
    joints: JointSensorConfig = JointSensorConfig()
    mocap: MocapConfig = MocapConfig()
    faults: FaultsConfig = FaultsConfig()
    contact: ContactConfig = ContactConfig()


def load_scenario(name_or_path: str | Path) -> ScenarioConfig:
    """Load a scenario: a bare name -> configs/NAME.yaml, otherwise a YAML path.

    The YAML holds overrides of the defaults in code; unknown keys raise ConfigError.
    """
    path = resolve_config_path(name_or_path)
    if not path.is_file():
        raise ConfigError(f"{path}: scenario file not found")
    data = load_yaml_mapping(path)
    data.setdefault("name", path.stem)
    return validate_model(ScenarioConfig, data, path)
