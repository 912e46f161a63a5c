"""Configuration of the visual front end (paper Section II.A), one model per step.

Every threshold the front end uses lives here, with its unit in the name and its default in
code. Models are frozen pydantic v2 models that reject unknown keys, so a typo in a YAML file
is an error, not a silently ignored setting.
"""

from __future__ import annotations

from typing import Literal

from pydantic import BaseModel, ConfigDict, Field, model_validator

TerrainName = Literal["stair_up", "stair_down", "obstacle", "level", "unknown"]


class _Strict(BaseModel):
    model_config = ConfigDict(extra="forbid", frozen=True)


class ProjectionConfig(_Strict):
    """Sagittal slice (eq. 1) and rotation into the ground frame (eq. 2)."""

    half_width_m: float = Field(
        0.05, gt=0, description="keep points with |x_C| < half_width_m (lateral camera axis), m"
    )
    min_depth_m: float = Field(0.1, ge=0, description="ignore pixels closer than this, m")
    max_depth_m: float = Field(4.0, gt=0, description="ignore pixels farther than this, m")
    min_confidence: int = Field(
        1, ge=1, le=255, description="ignore pixels whose confidence is below this (0 = invalid)"
    )
    speckle_min_agree: int = Field(
        2,
        ge=0,
        le=8,
        description="drop a depth pixel unless at least this many of its 8 neighbours agree "
        "with it (speckle_rel_tol, speckle_abs_tol_m), or, with fewer valid neighbours, all of "
        "them but at least one; 0 = off. A random return agrees with one neighbour by chance "
        "about 1 time in 5 and with two about 1 in 40, while a surface pixel at a depth edge "
        "still has two along the edge. Upstair seeds 1-3, filter toe x/z cm, 5 % spurious "
        "pixels: off 9.55/2.24, 2: 0.93/1.13, 3 (without the dropout rule): 0.96/1.19; clean: "
        "off 0.62/1.01, 2: 0.61/1.06, 3: 0.87/0.87",
    )
    speckle_rel_tol: float = Field(
        0.03, ge=0, description="speckle test: neighbours agree within this share of the depth"
    )
    speckle_abs_tol_m: float = Field(
        0.01, ge=0, description="speckle test: plus this absolute tolerance, m"
    )
    mixed_pixel_jump_m: float | None = Field(
        None,
        gt=0,
        description="mixed-pixel test (projection.mixed_pixel_drops), evaluated at the slice's "
        "pixels: a pixel whose valid 3x3 neighbours span more than this depth jump, m, whose "
        "depth lies farther than mixed_pixel_abs_tol_m + mixed_pixel_rel_tol x depth from both "
        "the nearest and the farthest of them (window mixed_pixel_radius_px), and that is on no "
        "plane through its opposite 3x3 neighbours, straddles a depth edge (a nosing over the "
        "tread below) and is dropped; null = off",
    )
    mixed_pixel_abs_tol_m: float = Field(
        0.01,
        ge=0,
        description="mixed-pixel test: distance from either extreme, m (about 3-4 axial noise "
        "sd of a pixel at 1 m)",
    )
    mixed_pixel_rel_tol: float = Field(
        0.01, ge=0, description="mixed-pixel test: plus this share of the pixel's depth"
    )
    mixed_pixel_radius_px: int = Field(
        1,
        ge=1,
        le=4,
        description="mixed-pixel test: the near and far extremes are taken over the valid "
        "pixels of a (2 r + 1)^2 window. 2 reaches across the band the driver's flying-pixel "
        "filter invalidates at a jump, but also takes the nosing pixel (between the nearer "
        "upper tread and the lower one) for a mixed pixel: downstair s1000-1002 map nosing "
        "error 3.0-3.8 -> 7.8-9.1 mm, batch toe x 0.35-0.40 -> 0.76-1.13 cm",
    )
    veil_window_px: float | None = Field(
        None,
        gt=0,
        description="veil test (frontend.veil.veil_drops) on the raw slice points: a point "
        "that lies between a nearer and a farther return within this many pixels' angle "
        "(vertical focal length) of its own viewing ray, by more than a surface seen at "
        "veil_max_incidence_deg and the depth noise allow, is a mixed pixel at a depth edge "
        "and is dropped; the nearest return (a nosing) and the farthest (the tread behind it) "
        "are kept. null = off",
    )
    veil_corners: bool = Field(
        True,
        description="veil test: the corner extraction still sees the dropped points (they lie "
        "on the ray through the nosing and place the face below it); the levels, the noise "
        "measurement and ICP do not",
    )
    veil_ray_tol_px: float = Field(
        1.0,
        ge=0,
        description="veil test: uncertainty of a point's own ray, pixels (footprint and "
        "sample-position jitter), added to the angle between two points when the grazing "
        "allowance is computed",
    )
    veil_max_incidence_deg: float = Field(
        75.0,
        gt=0,
        lt=90,
        description="veil test: the steepest incidence at which the camera returns a surface, "
        "deg (the simulated pico flexx2 drops pixels beyond 75)",
    )
    veil_k_sigma: float = Field(
        3.0, ge=0, description="veil test: noise allowance in depth-noise sigmas (of two points)"
    )
    veil_sigma_floor_m: float = Field(
        0.003,
        gt=0,
        description="veil test: depth noise sd of one point, m: the larger of this and the "
        "noise the front end measures on level surfaces",
    )


class CameraFixedConfig(_Strict):
    """Pixels that move with the camera (an occluding foot close to the lens) leave the slice
    (vio_graph/frontend/camera_fixed.py): the previous frame saw the same depth at the same
    pixel, and the world-static hypothesis under the IMU-predicted camera motion is refused."""

    enabled: bool = Field(
        True,
        description="look for slice pixels that move with the camera and count them "
        "(FrontendResult.n_camera_fixed, metrics.json health.camera_fixed with a warning); "
        "with drop_pixels (the default) they also leave the slice",
    )
    drop_pixels: bool = Field(
        True,
        description="also drop those pixels from the slice (on by default since the "
        "occlusion-onset requirement, onset_drop_tols: a filter velocity knocked 0.6 m/s off "
        "with a tiny covariance, tests/test_filter_lockout.py, no longer makes the terrain "
        "read as moving with the camera). Upstair s1-2 with a 1 s occluding foot, filter toe "
        "17.6x / 15.1x the clean error off, 1.57x / 1.07x on; clean trials unchanged (no "
        "pixel removed). false = found and reported only (configs/camera_fixed_report_only.yaml)",
    )
    k_sigma: float = Field(
        3.0, gt=0, description="both hypotheses are tested at this many depth-noise sigmas"
    )
    depth_sigma_floor_m: float = Field(
        0.003,
        gt=0,
        description="depth noise sd of one pixel, m: the larger of this and the noise the "
        "front end measures on level surfaces",
    )
    rot_sigma_rad: float = Field(
        0.005, ge=0, description="sd of the IMU's rotation between two frames, rad"
    )
    stamp_sigma_s: float = Field(
        0.002,
        ge=0,
        description="sd of a frame stamp's jitter, s: the predicted motion between two frames "
        "is uncertain by sqrt(2) x this over the frame interval, as a share of itself (the "
        "robustness sweep's 2 ms clock jitter removed up to 249 terrain pixels on 5 frames "
        "of upstair s1 without it)",
    )
    min_pixels: int = Field(
        20,
        ge=1,
        description="a surface (pixels of unchanged depth between depth edges) needs at least "
        "this many pixels that pass the test to count as an object; fewer are chance passes "
        "of terrain pixels (clean upstair s1-2: at most 12 a frame, 1-3 in one surface; the "
        "1 s occluding foot: ~6700 in one surface)",
    )
    onset_drop_tols: float | None = Field(
        3.0,
        gt=0,
        description="occlusion onset (camera_fixed.OnsetTracker): a surface leaves the slice "
        "only if at least onset_share of its pixels have kept their depth since it dropped "
        "by more than this many times the speckle test's agreement (3 % + 1 cm of the depth "
        "before) in one frame, or since they were first valid (the trial's first frame, a "
        "strap in view from the start). Evidence that does not come from the filter's "
        "velocity: terrain read as camera-fixed under a confidently wrong prediction has no "
        "onset. null = no such requirement",
    )
    onset_share: float = Field(
        0.5,
        gt=0,
        le=1,
        description="share of a surface's pixels that must have an occlusion onset",
    )
    confirm_frames: int = Field(
        1,
        ge=1,
        description="a pixel counts (and is removed) once it has been camera-fixed on this many "
        "consecutive tested frames. 2 drops the test's single-frame coincidences (held-out "
        "AV: terrain on two single frames under a 50 Hz IMU's prediction, then the same as "
        "report-only) but delays the object by a frame, which the occluder rows pay for "
        "(obstacle smoother x 0.97x -> 4.01x the clean error, batch 1.03x -> 3.52x): 1",
    )
    idle_check_every_frames: int = Field(
        3,
        ge=1,
        description="report-only mode (drop_pixels off): while no pixel is held as "
        "camera-fixed, test every this many frames (the others only remember their depth "
        "image); once a surface is found, every frame until it is gone. An occluding foot "
        "stays in view for 10-30 frames, so it is reported at most this many frames late, "
        "and a clean trial pays for the test on one frame in this many (~1.7 ms a frame "
        "at 224 x 172, numpy, on the 2-core machine). With drop_pixels: every frame",
    )


class SmoothingConfig(_Strict):
    """Grid thinning followed by kNN smoothing of the 2D profile (end of Section II.A.1)."""

    grid_cell_m: float = Field(
        0.005, ge=0, description="thinning cell size in x and z, m; 0 disables thinning"
    )
    k_neighbours: int = Field(
        5, ge=1, description="each point is replaced by the mean of its k nearest neighbours"
    )
    min_points: int = Field(
        10, ge=1, description="profiles with fewer points (after thinning) are not smoothed"
    )
    noise_cell_ratio: float | None = Field(
        2.0,
        gt=0,
        description="adaptive thinning cell: the cell is this many times the depth noise "
        "measured on the recording's own profiles (vertical scatter of the raw points about "
        "line fits of the levels, vio_graph.frontend.noise), never below grid_cell_m nor above "
        "noise_max_cell_m; None = grid_cell_m always",
    )
    noise_max_range_m: float = Field(
        0.6,
        gt=0,
        description="adaptive thinning cell: the noise is measured on points nearer than this "
        "to the camera (where the corners are tracked; ToF noise grows with range), m",
    )
    noise_max_cell_m: float = Field(
        0.015, gt=0, description="adaptive thinning cell: upper bound, m"
    )
    noise_warmup_frames: int = Field(
        30,
        ge=1,
        description="adaptive thinning cell: frames with a noise value before the cell may change",
    )
    noise_window_frames: int = Field(
        60, ge=1, description="adaptive thinning cell: median over this many recent frame values"
    )
    noise_hysteresis: float = Field(
        0.6,
        ge=0,
        description="adaptive thinning cell: the cell changes only when the asked cell differs "
        "from it by more than this share",
    )


class TerrainConfig(_Strict):
    """Geometric terrain classifier on the smoothed profile (replaces the paper's CNN)."""

    level_band_m: float = Field(
        0.02, gt=0, description="half-height of the band that collects a horizontal level, m"
    )
    min_level_length_m: float = Field(
        0.05, gt=0, description="a level must span at least this much in x (robust extent), m"
    )
    min_level_points: int = Field(8, ge=1, description="a level must hold at least this many")
    level_gap_m: float = Field(
        0.06, gt=0, description="a level band is split into separate levels at x gaps above this, m"
    )
    max_levels: int = Field(5, ge=1, description="at most this many levels are extracted")
    min_step_m: float = Field(
        0.04, gt=0, description="height differences below this are the same level, m"
    )
    max_step_m: float = Field(
        0.30, gt=0, description="a height difference above this is not a step (wall/drop), m"
    )
    obstacle_max_depth_m: float = Field(
        0.20,
        gt=0,
        description="a single raised level shorter than this (in x) is an obstacle top, m",
    )
    max_unexplained_fraction: float = Field(
        0.35,
        ge=0,
        le=1,
        description="profiles with more points outside every level are UNKNOWN",
    )
    min_points: int = Field(20, ge=1, description="fewer profile points than this -> UNKNOWN")
    use_faces: bool = Field(
        True,
        description="when the levels alone give LEVEL or UNKNOWN, let vertical segments (risers, "
        "obstacle faces) decide; False = levels only",
    )
    face_gap_m: float = Field(
        0.02, gt=0, description="points outside the levels are grouped at x gaps above this, m"
    )
    face_max_width_m: float = Field(
        0.03, gt=0, description="a face is the points within half this of its group's median x, m"
    )
    face_context_m: float = Field(
        0.06, gt=0, description="surface points this close before / after a face orient it, m"
    )
    min_face_points: int = Field(5, ge=2, description="a face needs at least this many points")
    stand_level: bool = Field(
        True,
        description="a frame that shows only one level height (LEVEL) is compared with the "
        "surface the instrumented foot last stood on (the estimator's heel / toe at stance): "
        "at least min_step_m lower -> STAIR_DOWN, higher -> STAIR_UP (or "
        "OBSTACLE by the short raised level rule); False = the frame alone decides",
    )
    obstacle_far_side: bool = Field(
        True,
        description="with stand_level: a frame whose levels only go down, the nearest at least "
        "min_step_m above the surface the foot last stood on and the farthest back at that "
        "surface's height (within min_step_m), is OBSTACLE (the far side of a raised top "
        "dropping back to the floor), not STAIR_DOWN; the reported class only (corners use "
        "the frame's own class)",
    )
    obstacle_memory: bool = Field(
        True,
        description="remember the last obstacle seen with the floor on both sides (its top's "
        "height and x extent and the floor's height, placed with the predicted camera "
        "displacements): a later frame whose levels are that top (overlapping it in x) and "
        "that floor is OBSTACLE, whatever of the far side it shows; the reported class only",
    )
    under_level_margin_m: float | None = Field(
        0.05,
        gt=0,
        description="points beneath a level of the same frame (at least min_step_m below it "
        "and more than this inside its robust x extent on both sides, or seen along a line of "
        "sight that passed under it, or on a lower level it overlaps by more than this; "
        "vio_graph/surface.py) are not the walking surface: the floor seen under open-riser "
        "treads or through gaps. They are dropped from the frame's profile (terrain, corners, "
        "ICP, keyframes) when any occur, m; None: keep every point",
    )
    under_sight_min_points: int | None = Field(
        3,
        ge=1,
        description="a point is also beneath the walking surface when at least this many "
        "profile points more than under_level_margin_m nearer in x lie min_step_m or more "
        "above its line of sight (seen through a gap under a surface that is no level of the "
        "frame, e.g. under the front of an open-riser tread whose top is out of view; "
        "vio_graph.surface.seen_under_mask), and so is the floor beyond a level that it runs "
        "under and lies in front of (floor_beyond_slab_mask); they leave the terrain class "
        "(and, with under_sight_profile, the profile); None: levels only",
    )
    under_sight_profile: bool = Field(
        False,
        description="the points under_sight_min_points finds also leave the profile the "
        "corners, ICP, keyframes and map see (open_risers, 3 seeds: toe clearance p95 9.7 -> "
        "6.1 mm, but smoother / batch toe x 0.40 / 0.38 -> 0.50 / 0.58 cm and seed 1000's map "
        "lost a step); False: the terrain class only (clearance 9.7, toe x 0.40 / 0.38 cm)",
    )


class CornerConfig(_Strict):
    """RANSAC corner extraction (paper Fig. 2)."""

    inlier_distance_m: float = Field(
        0.02, gt=0, description="paper's d: inlier distance to a horizontal line, m"
    )
    window_m: float = Field(
        0.05, gt=0, description="paper's w: half-size of the square feature window at the edge, m"
    )
    n_hypotheses: int = Field(64, ge=1, description="RANSAC hypotheses per line")
    min_line_inliers: int = Field(10, ge=2, description="a line needs at least this many inliers")
    min_line_separation_m: float = Field(
        0.04, gt=0, description="the second line must be at least this far from the first, m"
    )
    min_line_length_m: float = Field(
        0.03,
        gt=0,
        description="a horizontal line whose main run spans less than this in x is a band "
        "across a vertical face, not a surface; RANSAC is run again without its points, m",
    )
    max_gap_m: float = Field(
        0.04,
        gt=0,
        description="inliers of the higher line are split into runs at x gaps larger than this; "
        "the run with most points is the surface whose end is the edge, m",
    )
    min_feature_points: int = Field(6, ge=3, description="fewer feature points -> no corner")
    face_top_margin_m: float = Field(
        0.008,
        ge=0,
        description="face (riser / nosing block) candidates start this far below the tread "
        "line: the corner itself is rounded by the kNN smoothing, m",
    )
    max_nosing_gap_m: float = Field(
        0.09,
        gt=0,
        description="the face may lie up to this far in front of the tread end (a band of "
        "tread behind the nosing missing, 3-6 cm on a pico flexx2, plus the smoothing), m",
    )
    near_edge_needs_face: bool = Field(
        False,
        description="True: a near-end corner (stairs up, obstacle front) is only given when a "
        "face line below the tread supports it. False: without a face the edge is the end of "
        "the tread run (has_face False) and the tracker widens its x uncertainty "
        "(TrackerConfig.faceless_edge_x_sigma_m); such corners still fix z, and dropping them "
        "raised the toe z ATE on simulated ascents (upstair s2 1.18 -> 1.46 cm)",
    )
    face_band_m: float = Field(
        0.025,
        gt=0,
        description="face candidates are taken down to this far below the tread line (down to "
        "window_m if too few): an overhanging nosing block is 2-4 cm tall, and below it the "
        "riser lies farther back, m",
    )
    face_cluster_m: float = Field(
        0.006,
        gt=0,
        description="face candidates are split into vertical lines at x steps larger than this, m",
    )
    min_face_points: int = Field(
        3, ge=1, description="a face line needs at least this many points (5 mm grid: 1.5 cm)"
    )
    edge_sigma_m: float = Field(
        0.01, gt=0, description="1-sigma of the edge point estimate for CornerObservation, m"
    )


class IcpConfig(_Strict):
    """2D translation-only ICP (eq. 3-4)."""

    metric: Literal["point_to_point", "point_to_line"] = Field(
        "point_to_line",
        description="'point_to_point' = eq. 4 (mean residual); 'point_to_line' uses normals",
    )
    max_iterations: int = Field(20, ge=1, description="paper: 20")
    convergence_m: float = Field(1e-6, gt=0, description="paper: stop when |dT| <= 1e-6 m")
    max_correspondence_m: float = Field(
        0.08, gt=0, description="correspondences farther than this are ignored, m"
    )
    trim_fraction: float = Field(
        0.1, ge=0, lt=1, description="drop this fraction of the worst correspondences per step"
    )
    normal_neighbours: int = Field(
        6, ge=3, description="source neighbours used to estimate the local normal (covariance)"
    )
    surface_radius_m: float | None = Field(
        None,
        gt=0,
        description="with a robust_kernel: the reweighted stage measures each target point's "
        "residual to the source surface around it (the source points within this radius, "
        "weighted (1 - d^2/r^2)^2, their normals averaged as n n^T) instead of to its "
        "nearest source point, so no pair switches partner and the objective is smooth in T; "
        "None = nearest source point",
    )
    robust_kernel: Literal["none", "cauchy", "huber"] = Field(
        "none",
        description="'none' = the trimmed ICP alone; 'cauchy' / 'huber' = after it converges, "
        "iteratively reweighted least squares over every pair within max_correspondence_m, "
        "each weighted by the kernel of its point-to-line residual (point-to-point: its "
        "distance), so the answer moves continuously with the seed instead of jumping when a "
        "pair crosses the trimming cut",
    )
    robust_scale: float = Field(
        2.385,
        gt=0,
        description="kernel width in residual sigmas (Cauchy 2.385 / Huber 1.345 = 95 % "
        "efficiency on Gaussian residuals); sigma = 1.4826 x the median absolute residual "
        "of the pairs at the current T, at least sigma_floor_m",
    )
    sigma_floor_m: float = Field(
        0.003, gt=0, description="lower bound of the point-to-line residual sigma, m"
    )
    cov_inflation: float = Field(
        5.0,
        ge=1,
        description="variance inflation for correlated (kNN-smoothed) residuals; ~ k_neighbours",
    )
    max_variance_m2: float = Field(
        1.0, gt=0, description="cap of the covariance eigenvalues (unobservable directions), m^2"
    )
    degenerate_ratio: float = Field(
        0.05,
        ge=0,
        lt=1,
        description="point-to-line: directions whose information (sum n n^T) is below this "
        "fraction of the strongest are degenerate (a floor along x): ICP does not move T along "
        "them (it stays at T0) and their variance is max_variance_m2; 0 disables",
    )


class TrackerConfig(_Strict):
    """Frame-to-frame association and gating (Section II.A.3 plus the IMU-seeded gate)."""

    icp_target: Literal["profile", "features"] = Field(
        "profile",
        description="'features' = paper (previous feature points); 'profile' = the previous "
        "smoothed profile, which also works when the tracked corner changes",
    )
    source_margin_m: float = Field(
        0.05,
        ge=0,
        description="ICP source = previous profile within the target's box (moved by T0) grown "
        "by max_correspondence_m + this margin, m",
    )
    same_corner_gate_m: float = Field(
        0.10,
        gt=0,
        description="paper's preset threshold: feature means (after compensating the motion) "
        "closer than this belong to the same physical corner, m",
    )
    gate_chi2: float = Field(
        13.8, gt=0, description="Mahalanobis^2 gate of ICP vs IMU prediction (2 dof, 99.9 %)"
    )
    gate_sigma_floor_m: float = Field(
        0.01, ge=0, description="added in quadrature to the gate covariance, m"
    )
    default_prediction_sigma_m: float = Field(
        0.03, gt=0, description="prediction 1-sigma per axis when no covariance is given, m"
    )
    max_rms_m: float = Field(0.01, gt=0, description="reject ICP results with larger RMS, m")
    min_correspondences: int = Field(6, ge=1, description="reject ICP with fewer inliers")
    max_frame_gap_s: float = Field(
        0.2, gt=0, description="no displacement across larger gaps between frames, s"
    )
    profile_fallback: bool = Field(
        True,
        description="frames without a corner: ICP of the whole profile (treads, risers, floor) "
        "against the previous profile, seeded and gated by the IMU prediction (needs one); "
        "False = paper (no displacement without a corner)",
    )
    fallback_normal_neighbours: int = Field(
        15,
        ge=3,
        description="profile fallback: neighbours for the source normals. After 5 mm grid "
        "thinning a noisy floor is a band 2-3 cells thick; with 6 neighbours many floor normals "
        "come out horizontal and fake x information (obstacle s1: displacement NEES 56 -> 6)",
    )
    fallback_grid_m: float = Field(
        0.01, ge=0, description="profile fallback: the target profile is thinned to this grid, m"
    )
    fallback_full_target: bool = Field(
        False,
        description="profile fallback: register every point of the smoothed profile instead "
        "of its fallback_grid_m thinning, and scale the covariance by the ratio of the two "
        "point counts (the claim of the thinned target). Level s1-6 either swing, exact "
        "attitude and seed (benchmarks/eval_floor_icp.py): z error sd 0.65-0.74 -> 0.38-0.48 "
        "mm a frame, summed z over 10 s RMS 9.9 -> 6.2 mm. Off: with it the smoothers lose x "
        "on level walking (docs/generalisation.md, 'The far floor does not read high')",
    )
    fallback_max_correspondence_m: float | None = Field(
        0.03,
        gt=0,
        description="profile fallback: correspondence distance (m) of the whole-profile ICP. "
        "In a fast swing part of the new profile is surface the previous frame never saw; "
        "within the corner ICP's 8 cm those points still pair with an end of the previous "
        "profile and pull the result towards zero motion (more than the 10 % trimming can "
        "drop). Measured on a simulated 40 s ascent, seed 1, ground-truth attitude: summed "
        "displacement z -3.0 % -> -0.8 %, availability 0.93 -> 1.00. None = the ICP's own",
    )
    fallback_overlap_margin_m: float | None = Field(
        0.01,
        ge=0,
        description="profile fallback: keep only target points that, moved back by the IMU "
        "seed, fall inside the previous profile's x extent shrunk by this margin (m): surface "
        "the previous frame never saw has no counterpart. None = keep all",
    )
    corner_overlap_check: bool = Field(
        True,
        description="a corner the previous frame did not hold (a nosing entering the view): "
        "its window is registered only with the points that, moved back by the IMU seed, fall "
        "inside the previous profile (fallback_overlap_margin_m), and with the profile "
        "fallback if fewer than min_correspondences do. Unchecked, the unseen part slides "
        "onto the surface next to it: on the 2-minute ascent (sweep long_2min, seed 1000, "
        "first 22 s) such displacements were 15-49 mm off in z, all downwards, while claiming "
        "4-11 mm, and carried most of the filter's z drift. False = register the whole window",
    )
    edge_x_without_face: bool = Field(
        True,
        description="corner windows without face points below the edge (stair descent: the "
        "risers face away) constrain x only through the smoothed end of the tread, which biases "
        "ICP; take x from the edge-point difference instead. False = ICP x as is",
    )
    edge_x_sigma_m: float = Field(
        0.006,
        gt=0,
        description="1-sigma of one edge point's x for edge_x_without_face, m. Set on "
        "simulated descent (seeds 1-3): 4 mm -> 6 mm took the displacement NEES from 3.7-3.9 "
        "to 3.3-3.6 and the filter toe x ATE from 3.58/3.20/1.42 to 3.39/2.80/1.40 cm (the far "
        "end of a tread jumps with the occlusion); the remaining excess NEES is elsewhere",
    )
    min_face_points: int = Field(
        3, ge=1, description="a corner window has a face if this many points lie below the edge"
    )
    faceless_edge_x_sigma_m: float = Field(
        0.03,
        gt=0,
        description="x 1-sigma of a near-end corner observation without a face line below it "
        "(the end of the tread: a missing band behind the nosing moves it by 2-6 cm), m",
    )
    corner_check: bool = Field(
        True,
        description="reject corner ICP that disagrees with the difference of the two nosings "
        "when both were placed from their face lines (ICP locked on the borders of a missing "
        "band); False = no check",
    )
    corner_check_sigma_m: float = Field(
        0.003,
        gt=0,
        description="1-sigma of one nosing position placed from its face line, per axis, for "
        "corner_check (synthetic noisy stairs with 0-6 cm bands: median 1 mm, p90 2-3 mm), m",
    )
    fallback_straight_ratio: float | None = Field(
        None,
        gt=0,
        description="off (None) by default: on the generalisation sweep it improved the "
        "smoothers' x on level ground but worsened the online foot placement on descents; 25 is "
        "the measured value (docs/method.md section 1). Profile fallback: if the matched points "
        "of both frames lie on one straight "
        "line (mean squared distance to their total-least-squares line below this many times "
        "half the mean squared pair residual along its normal), a translation along the line "
        "is unobservable: along the covariance's least-informed direction the displacement "
        "keeps the seed, with variance max_variance_m2. PCA normals of a noisy flat floor "
        "tilt at random and otherwise read as x information (obstacle s1: a level floor "
        "claiming 1.7 mm in x, 1 cm off). Level frames of upstair / downstair / obstacle s1: "
        "median 4.2-5.9, p95 7.4-13.4; frames with a riser 240 and up. None = trust the "
        "point-to-line covariance",
    )
    fallback_restart_check: bool = Field(
        True,
        description="profile fallback: run ICP a second time from the seed moved by two "
        "prediction sigmas along the least-known direction of the result; a result that "
        "follows the seed by more than its covariance allows (corner_inflate_chi2) gets the "
        "difference added to its covariance. False = the covariance as ICP claims it",
    )
    fallback_restart_shift: Literal["prediction", "reach"] = Field(
        "prediction",
        description="profile fallback, fallback_restart_check: how far the second ICP's seed "
        "is moved. 'prediction': two prediction sigmas along the least-known direction, at "
        "most half the correspondence distance. 'reach': half the correspondence distance "
        "always, so that whether the profile determines the answer is tested at ICP's own "
        "capture range and the displacement's covariance does not shrink with the filter's "
        "(a level floor's slide, which the profile does not see, then reads as that range "
        "whatever the prediction's sigma). Changes clean runs; measured on the paper "
        "scenarios only (docs/robustness.md, 'one railed axis'): clean toe x obstacle filter "
        "1.29 -> 0.79 cm, the others within 0.05; not yet on the generalisation sweep",
    )
    corner_inflate_chi2: float = Field(
        5.99,
        gt=0,
        description="corner_check: above this Mahalanobis^2 (2 dof, 95 %) and below gate_chi2 "
        "the ICP covariance is inflated by the disagreement with the nosing difference",
    )
    relocalise_after_frames: int | None = Field(
        0,
        ge=0,
        description="lost-track search: when the IMU-seeded registration has produced no "
        "displacement for this many frames in a row and fails again (0: at its first "
        "failure), the whole profile is registered against the previous one WITHOUT the IMU "
        "seed (a grid search around vision's own constant-velocity prediction, then ICP from "
        "its best candidates); the result skips the front end's prediction gate and goes to "
        "the filter (filter.relocalised_max_accel_mps2). An IMU prediction that diverged (a "
        "knock, a saturated accelerometer) otherwise seeds ICP metres off on every later "
        "frame, and vision never returns. The search gives nothing when it is ambiguous (two "
        "solutions with the same support that disagree beyond their covariances; the IMU's "
        "prediction counts as one), or registers less than relocalise_min_share of the "
        "profile. None: off (configs/relocalise_off.yaml). On the 123 clean trials of the "
        "generalisation sweep it gave an answer on one (camera 8 cm, 0 deg, seed 1002: filter "
        "toe x 0.70 -> 0.58 cm) and left the rest identical; an unflagged 0.1 s knock goes "
        "from metres to millimetres (docs/robustness.md, 'An IMU knock')",
    )
    relocalise_check_frames: int = Field(
        5,
        ge=0,
        description="lost-track search: after a searched displacement, the seeded ones of up "
        "to this many frames are checked against the search too (the IMU that was wrong may "
        "still be): the search's result replaces a seeded one it disagrees with or measures "
        "more than; the checks end at the first seeded result that passes",
    )
    relocalise_max_speed_mps: float = Field(
        4.0,
        gt=0,
        description="lost-track search radius: the fastest camera speed searched for, m/s "
        "(a shank-mounted camera peaks near 3 m/s in swing)",
    )
    relocalise_max_accel_mps2: float = Field(
        50.0,
        gt=0,
        description="lost-track search after a visual displacement: the grid is centred on "
        "vision's constant-velocity prediction and spans what this acceleration (m/s^2) "
        "changes over the frame interval (0.5 a dt^2: 2.8 cm at 30 fps, 11 cm at 15 fps), so a "
        "stair's period stays out of reach; a shank peaks near 5 g",
    )
    relocalise_grid_m: float = Field(
        0.02, gt=0, description="lost-track search: spacing of the coarse translation grid, m"
    )
    relocalise_inlier_m: float = Field(
        0.01,
        gt=0,
        description="lost-track search: a target point supports a translation if a previous "
        "profile point lies within this distance of it, m",
    )
    relocalise_min_share: float = Field(
        0.5,
        gt=0,
        le=1,
        description="lost-track search: the answer must register at least this share of the "
        "frame's (thinned) profile within relocalise_inlier_m of the previous profile; a "
        "registration of a minority of the profile is a partial overlap whose translation "
        "the rest of the profile does not confirm (fast 15 fps swing frames: 20-30 % and "
        "centimetres off; after a knock: 90-100 %)",
    )
    relocalise_support_ratio: float = Field(
        0.8,
        gt=0,
        le=1,
        description="lost-track search: a second solution with at least this share of the "
        "best one's support, farther than their covariances allow (gate_chi2), makes the "
        "search ambiguous; the IMU-seeded prediction is one of the candidates, so a search "
        "answer is used only where the prediction's translation has clearly less support",
    )


class FrontendConfig(_Strict):
    """Everything the visual front end needs; defaults reproduce the paper where it is explicit."""

    projection: ProjectionConfig = ProjectionConfig()
    camera_fixed: CameraFixedConfig = CameraFixedConfig()
    smoothing: SmoothingConfig = SmoothingConfig()
    terrain: TerrainConfig = TerrainConfig()
    corners: CornerConfig = CornerConfig()
    icp: IcpConfig = IcpConfig()
    tracker: TrackerConfig = TrackerConfig()
    corner_terrains: tuple[TerrainName, ...] = Field(
        ("stair_up", "stair_down", "obstacle"),
        description="terrain classes on which corners are extracted (paper: stairs, obstacle)",
    )
    seed: int = Field(0, description="seed of the RANSAC random generator")

    @model_validator(mode="after")
    def _check_ranges(self) -> FrontendConfig:
        if self.projection.max_depth_m <= self.projection.min_depth_m:
            raise ValueError("projection.max_depth_m must exceed projection.min_depth_m")
        return self
