"""Configuration of the foot-to-terrain safety outputs (section ``safety`` of PipelineConfig).

Every length is in metres, every time in seconds; see docs/method.md ("Foot-to-terrain
safety outputs") for the definitions.
"""

from __future__ import annotations

from typing import Literal

from pydantic import BaseModel, ConfigDict, Field, model_validator


class SafetyConfig(BaseModel):
    """Toe clearance, foot placement and terrain-ahead outputs of the online estimator."""

    model_config = ConfigDict(extra="forbid", frozen=True)

    enabled: bool = Field(default=True, description="compute the safety outputs per frame")
    bin_m: float = Field(
        default=0.005,
        gt=0,
        le=0.05,
        description="x bin width of the online height map built from keyframe profiles, m",
    )
    map_statistic: Literal["median", "mean"] = Field(
        default="median",
        description="a map bin's height over the keyframes that saw it: median (robust to "
        "the ToF mixed pixels between a nosing and the tread below) or mean (before 2026-12)",
    )
    min_keyframes: int = Field(
        default=4, ge=1, description="a map bin is used once this many keyframes saw it"
    )
    agreement_keyframes: int = Field(
        default=2,
        ge=1,
        description="a map bin is used before min_keyframes views once this many keyframes "
        "saw it and their heights agree (spread <= agreement_sigmas x sqrt(2) x map_sigma_m): "
        "a surface seen twice at one height is terrain, the ToF mixed pixels scatter from view "
        "to view and still need min_keyframes views; >= min_keyframes: off (before 2026-12-03)",
    )
    view_ceilings: bool = Field(
        default=True,
        description="a keyframe's height in a map bin counts only if its view reached the "
        "bin's highest kept height (less the 1 cm top band): a view that passed under a "
        "nosing overhang, or whose field of view ends below the top of a riser, is no "
        "evidence against the higher surface others saw there; False: every view counts "
        "(before 2026-12-03, fourth session)",
    )
    contact_map: bool = Field(
        default=True,
        description="a foot in stance is a measurement of the terrain: the map's bins under "
        "its sole are lowered to the sole (+ contact_sigmas x the foot-to-map sigma) when "
        "above it by less than edge_min_rise_m (mixed pixels of a hidden strip, not a step "
        "the foot estimate overlaps); off: the map is the camera's alone (before 2026-12-03)",
    )
    non_penetration: bool = Field(
        default=True,
        description="the reported clearance is the most probable one given that a foot is "
        "never inside the terrain: an estimate below 0 (the foot outline inside the mapped "
        "terrain, a pose or map error) is reported as 0, with the sigma of the Gaussian "
        "truncated at 0 (safety/clearance.py, non_penetrating; non_penetration_sigma); "
        "False: the signed distance "
        "as computed (before 2026-12-03, eighth session)",
    )
    non_penetration_sigma: Literal["truncated", "contact", "tread_contact"] = Field(
        default="tread_contact",
        description="the sigma of a clearance non_penetration clamps to 0: 'truncated', the "
        "truncated Gaussian's alone; 'contact', at most the foot outline's foot_sigma_m (a "
        "clamped foot is reported in contact, and under a standing foot the map is capped "
        "to the sole, contact_map, so the map's own sigma does not enter); 'tread_contact', "
        "that bound only when the way out of the terrain is vertical (the sole inside a "
        "tread); a foot inside a riser's face (the foot-to-terrain line more horizontal "
        "than vertical: the pose's x error, no sole rests there) keeps the truncated "
        "Gaussian's ('contact' before 2026-12-04)",
    )
    stance_contact: bool = Field(
        default=True,
        description="a foot the estimator holds in stance (its stance anchor, the flag the "
        "contact map also uses) is reported in contact: clearance 0 with at most the foot "
        "outline's sigma foot_sigma_m, whatever gap the map leaves under it (a map a few mm "
        "below the sole; the contact map only lowers bins); empty clearances stay empty; "
        "off: the map's distance under a standing foot (before 2026-12-04)",
    )
    contact_sigmas: float = Field(
        default=2.0,
        gt=0,
        description="the contact margin above the sole in sigmas of the sole-to-map height "
        "difference, sqrt(foot_sigma_m^2 + map_sigma_m^2) (count)",
    )
    agreement_sigmas: float = Field(
        default=3.0,
        gt=0,
        description="the agreement test's width in map_sigma_m of a height difference "
        "between two views (count)",
    )
    sole_thickness_m: float = Field(
        default=0.0,
        ge=0,
        le=0.05,
        description="sole below the heel-toe line; 0 when the rig's heel and toe points are "
        "the sole's contact points (the simulator's and the sample rig's), m",
    )
    horizon_s: float = Field(
        default=0.3,
        ge=0.05,
        le=0.5,
        description="prediction horizon of the minimum clearance (issue: 100-300 ms), s",
    )
    horizon_steps: int = Field(
        default=20,
        ge=1,
        le=50,
        description="foot poses evaluated over the horizon (count): 15 ms apart over 0.3 s, "
        "the swinging toe (up to 3 m/s past a nosing) 4.5 cm from pose to pose; 10 before "
        "2026-12-05 (9 cm: the template's closest approach to a nosing fell between poses)",
    )
    motion_model: Literal["swing_template", "constant_velocity"] = Field(
        default="swing_template",
        description="prediction of the foot over the horizon: the displacement the heel and "
        "toe made at the same time since lift-off in the user's previous swings "
        "(swing_template; constant velocity until one swing has been seen, and in stance), "
        "or the toe's velocity held constant",
    )
    template_swings: int = Field(
        default=3, ge=1, le=20, description="previous swings the template's median is over (count)"
    )
    template_match: Literal["off", "templates", "constant_velocity"] = Field(
        default="templates",
        description="a template joins this swing's prediction only if its heel and toe "
        "displacements since lift-off agreed with this swing's so far (rms over the swing's "
        "frames of the larger distance at most near_trip_m): the first step onto a flight "
        "(one step) is no template of a two-step swing. When none agrees: 'templates', "
        "every template (the error check decides; the default); 'constant_velocity', the "
        "fallback used before any swing was seen (false warnings doubled on ascent); 'off': "
        "every template always (before 2026-12-05). docs/method.md section 8, 'Near-trips "
        "on the joint-space swing'",
    )
    swing_speed_mps: float = Field(
        default=0.3,
        gt=0,
        description="lift-off: the toe moves faster than this without a stance anchor; "
        "landing: slower than a third of it, m/s",
    )
    template_swing_s: tuple[float, float] = Field(
        default=(0.2, 1.5),
        description="a swing of this duration range joins the template; "
        "a longer one is abandoned, s",
    )
    window_m: float = Field(
        default=0.3,
        gt=0,
        description="terrain within this x distance of the foot is "
        "searched for the nearest point, m",
    )
    toe_pass_m: float = Field(
        default=0.05,
        ge=0,
        description="the next edge ahead is the first with x beyond the "
        "toe minus this (an edge the toe is crossing still counts), m",
    )
    min_coverage: float = Field(
        default=0.5,
        ge=0,
        le=1,
        description="the clearance is reported (else NaN) when the "
        "terrain under at least this share of the foot's x span has been mapped",
    )
    unseen_terrain_check: bool = Field(
        default=True,
        description="the clearance is reported (else NaN) only when every x within "
        "window_m of the foot that the map has not seen is horizontally at least as far "
        "from the foot as the clearance the mapped terrain gives (unseen terrain could be "
        "that close: the mapped bins alone would overstate the clearance); off: the mapped "
        "bins alone decide",
    )
    gap_floor_check: bool = Field(
        default=True,
        description="the strips between mapped bins that the map bridges (at most "
        "edge_max_gap_m wide: what a nosing hid from the camera) hold terrain between the "
        "heights seen either side (clearance.gap_terrain): the clearance is at most the "
        "foot's distance to a floor at the lower height, and it is not known (NaN) when the "
        "riser a rising strip holds could be nearer than that by more than its sigma; off: "
        "a strip is empty space, and a foot over it is reported as high as the bins beside "
        "it are far",
    )
    edge_min_rise_m: float = Field(
        default=0.04, gt=0, description="a height change of at least this is a riser/edge, m"
    )
    edge_max_gap_m: float = Field(
        default=0.15,
        gt=0,
        description="unseen x gaps up to this are bridged when looking "
        "for an edge (a descending riser is hidden under its nosing), m",
    )
    tread_tolerance_m: float = Field(
        default=0.015,
        gt=0,
        description="bins within this height of the landing height "
        "belong to the tread the foot lands on, m",
    )
    near_trip_m: float = Field(
        default=0.02, gt=0, description="a swing clearance below this is a near-trip, m"
    )
    warning_sigma: float = Field(
        default=1.0,
        ge=0,
        description="warn when the predicted clearance of the foot poses that could be a "
        "near-trip (SafetyEstimate.near_trip_clearance_m) minus this many sigma of the next "
        "edge falls below near_trip_m (count of sigma)",
    )
    warning_min_forward_speed_mps: float = Field(
        default=0.5,
        ge=0,
        description="a near-trip needs the toe to move forward faster than "
        "this and at least as fast as it descends (excludes the landing, where the clearance "
        "goes to zero by design), m/s",
    )
    warning_error_check: bool = Field(
        default=True,
        description="the warning tests the swing template's predicted poses only up to the "
        "horizon step at which the monitor's own measured prediction error (rms over the "
        "current swing's earlier predictions of the larger of the heel's and toe's errors, "
        "checked at t + h against the estimated foot) is at most near_trip_m: a prediction "
        "wrong by more than the margin it tests cannot resolve a near-trip (steps not yet "
        "measured count as accurate); off: every pose over horizon_s (before 2026-12-03)",
    )
    warning_template_spread: bool = Field(
        default=False,
        description="with warning_error_check: a horizon step not yet measured in this swing "
        "counts as accurate only if the templates the prediction is the median of agree there "
        "(rms distance from the median at most near_trip_m); off: every such step counts as "
        "accurate",
    )
    map_sigma_m: float = Field(
        default=0.003, ge=0, description="1-sigma floor of a map bin's height, m"
    )
    relative_pose_scale: float = Field(
        default=1.0,
        ge=0,
        le=1,
        description="weight of the filter's covariance growth "
        "|P_now - P_keyframes| in the clearance variance (1: the random-walk model as it is; "
        "lower it where the filter's covariance is known to be conservative)",
    )
    consistency_window_keyframes: int = Field(
        default=30,
        ge=0,
        description="the sigmas' pose and map terms are scaled by how the last this many "
        "keyframes' heights agreed with the map (their common offset against the filter's "
        "covariance growth, the per-bin rest against the bins' sigma; safety/consistency.py); "
        "0: not scaled (count)",
    )
    consistency_min_keyframes: int = Field(
        default=5,
        ge=1,
        description="keyframes tested against the map before the consistency scale "
        "leaves 1 (count)",
    )
    consistency_scale_range: tuple[float, float] = Field(
        default=(0.25, 4.0),
        description="the consistency scale is clipped to this range (lo <= 1 <= hi)",
    )
    pose_scale_on_x: bool = Field(
        default=False,
        description="the pose consistency scale also on the pose term's horizontal (x) part; "
        "off: only on its vertical part, which is what the keyframes' common height offset "
        "observes, the x part keeping the filter's own covariance growth (the xz covariance "
        "takes the scale once). On is the behaviour before 2026-12-03 (docs/method.md "
        "section 8, docs/results.md)",
    )
    foot_sigma_m: float = Field(
        default=0.001,
        ge=0,
        description="1-sigma of the foot outline relative to the terrain points, m: the "
        "shank pitch error common to the foot and the keyframe profiles (both rotated by the "
        "estimated attitude about the camera) cancels; left is the pitch change since the "
        "keyframes (filter.stance_pitch_sigma_rad 0.002 rad x 0.45 m camera-to-foot lever "
        "= 0.9 mm) and the ankle encoder (0.05 deg x 0.2 m = 0.2 mm). 4 mm before "
        "2026-12-02 (the heel / toe error relative to the camera alone, 1.4-2.4 mm per "
        "axis on the paper trials, did not cancel in that)",
    )

    @model_validator(mode="after")
    def _consistent(self) -> SafetyConfig:
        lo, hi = self.consistency_scale_range
        if not 0 < lo <= 1 <= hi:
            raise ValueError(
                f"safety.consistency_scale_range must satisfy 0 < lo <= 1 <= hi, "
                f"got {self.consistency_scale_range}"
            )
        if self.tread_tolerance_m >= self.edge_min_rise_m:
            raise ValueError(
                f"safety.tread_tolerance_m ({self.tread_tolerance_m} m) must be "
                f"below safety.edge_min_rise_m ({self.edge_min_rise_m} m)"
            )
        return self

    @property
    def agreement_tolerance_m(self) -> float:
        """Largest spread of a bin's keyframe heights that counts as agreement (m): two
        independent views of one surface, each with ``map_sigma_m``, differ by at most
        ``agreement_sigmas`` standard deviations of their difference."""
        return self.agreement_sigmas * 2.0**0.5 * self.map_sigma_m
