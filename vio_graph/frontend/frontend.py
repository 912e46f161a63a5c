"""The visual front end: one depth frame in, profile / terrain / corner / displacement out.

``VisualFrontend.process`` is paper Section II.A step by step: sagittal slice (eq. 1) rotated
into the ground frame (eq. 2), kNN smoothing, terrain classification, RANSAC corner features
(Fig. 2), and frame-to-frame ICP (eq. 3-4) seeded and gated by the IMU prediction (see
``vio_graph.frontend.tracker``). It keeps only the previous frame; it does no I/O.
"""

from __future__ import annotations

import time
from dataclasses import dataclass, field

import numpy as np
from numpy.typing import NDArray

from vio_graph.errors import FrontendError
from vio_graph.frontend.camera_fixed import CameraFixedFilter
from vio_graph.frontend.config import FrontendConfig
from vio_graph.frontend.corners import CornerFeature, extract_corner
from vio_graph.frontend.icp import IcpResult
from vio_graph.frontend.noise import DepthNoiseTracker, level_noise_sigma
from vio_graph.frontend.projection import (
    drop_mixed_pixels,
    sagittal_slice_from_depth,
    slice_pixel_mask,
)
from vio_graph.frontend.smoothing import smooth_profile
from vio_graph.frontend.terrain import (
    SeenObstacle,
    classify_against_stand,
    classify_terrain,
    points_seen_under,
    points_under_levels,
    recall_obstacle,
)
from vio_graph.frontend.tracker import CornerTracker
from vio_graph.frontend.veil import veil_drops
from vio_graph.types import CornerObservation, DepthFrame, Displacement2D, TerrainKind


@dataclass(frozen=True)
class FrontendResult:
    """Everything the front end found in one frame.

    ``profile_xz_m`` (N, 2): smoothed sagittal slice relative to the camera, ground axes, metres.
    ``displacement``: camera displacement since the previous frame, or None with
    ``rejection_reason``. ``observation``: the corner relative to the camera (track id kept for
    the same physical corner). ``icp``: the ICP run (matched points for visualisation).
    ``timings_ms``: "projection", "smoothing", "terrain", "corners", "icp", "total".
    ``n_camera_fixed``: slice pixels found to move with the camera
    (vio_graph/frontend/camera_fixed.py); dropped from the slice with
    ``camera_fixed.drop_pixels`` (the default), only counted otherwise.
    ``relocalised``: the displacement comes from the tracker's lost-track search (no IMU
    seed; ``TrackerConfig.relocalise_after_frames``).
    """

    timestamp_s: float
    profile_xz_m: NDArray[np.float64]
    terrain: TerrainKind
    corner: CornerFeature | None
    displacement: Displacement2D | None
    observation: CornerObservation | None
    rejection_reason: str | None
    icp: IcpResult | None
    timings_ms: dict[str, float] = field(default_factory=dict)
    n_camera_fixed: int = 0
    relocalised: bool = False


class VisualFrontend:
    """Section II.A of the paper as a stateful per-frame processor."""

    def __init__(self, config: FrontendConfig | None = None) -> None:
        self.config = FrontendConfig() if config is None else config
        self._rng = np.random.default_rng(self.config.seed)
        self._tracker = CornerTracker(
            self.config.tracker, self.config.icp, self.config.corners.edge_sigma_m
        )
        self._corner_terrains = {TerrainKind(k) for k in self.config.corner_terrains}
        self._camera_fixed: CameraFixedFilter | None = None
        if self.config.camera_fixed.enabled or self.config.camera_fixed.drop_pixels:
            pc = self.config.projection
            self._camera_fixed = CameraFixedFilter(
                self.config.camera_fixed.k_sigma,
                pc.speckle_rel_tol,
                pc.speckle_abs_tol_m,
                self.config.camera_fixed.min_pixels,
                self.config.camera_fixed.onset_drop_tols,
                self.config.camera_fixed.onset_share,
                self.config.camera_fixed.confirm_frames,
            )
        self._camera_fixed_frames = 0  # frames seen by the camera-fixed test (idle checks)
        # rule step 6 (terrain.recall_obstacle): the camera placed by the sum of the predicted
        # displacements, and the last obstacle seen with the floor beside it in that frame
        self._track_xz_m = np.zeros(2)
        self._seen_obstacle: SeenObstacle | None = None
        sc = self.config.smoothing
        self._noise: DepthNoiseTracker | None = None
        if sc.noise_cell_ratio is not None and sc.grid_cell_m > 0:
            self._noise = DepthNoiseTracker(
                sc.grid_cell_m,
                sc.noise_cell_ratio,
                sc.noise_max_cell_m,
                sc.noise_warmup_frames,
                sc.noise_window_frames,
                sc.noise_hysteresis,
            )

    @property
    def grid_cell_m(self) -> float:
        """The thinning cell the next frame uses, m (adaptive with ``noise_cell_ratio``)."""
        return self.config.smoothing.grid_cell_m if self._noise is None else self._noise.cell_m

    @property
    def depth_noise_m(self) -> float:
        """Depth noise measured on the recent profiles, m (nan when not measured)."""
        return float("nan") if self._noise is None else self._noise.sigma_m

    def reset(self) -> None:
        """Forget the previous frame (e.g. after a gap in the recording); the measured depth
        noise is kept (the camera did not change)."""
        self._tracker.reset()
        self._seen_obstacle = None  # placed with displacements across the gap: forget it
        if self._camera_fixed is not None:
            self._camera_fixed.reset()
            self._camera_fixed_frames = 0

    def process(
        self,
        frame: DepthFrame,
        K: NDArray[np.float64],
        R_ground_cam: NDArray[np.float64],
        predicted_delta_xz_m: NDArray[np.float64] | None = None,
        predicted_cov_m2: NDArray[np.float64] | None = None,
        ground_turn_rad: float = 0.0,
        stand_height_m: float | None = None,
    ) -> FrontendResult:
        """Process one depth frame.

        Args:
            frame: the depth image (H, W) and confidence.
            K: (3, 3) camera intrinsics, pixels.
            R_ground_cam: (3, 3) camera -> gravity-aligned ground frame, heading removed.
            predicted_delta_xz_m: (2,) IMU-predicted camera displacement since the previous
                frame, ground axes, metres; None = paper's association without IMU.
            predicted_cov_m2: (2, 2) covariance of the prediction, m^2.
            ground_turn_rad: the caller turned its ground frame by rot_y(``ground_turn_rad``)
                since the previous frame (a pitch correction, rad); the previous frame is
                re-expressed in the turned frame before ICP compares the two.
            stand_height_m: height of the surface the foot last stood on relative to the
                camera (ground axes), m; decides frames that show one level only (terrain
                rule step 5); None = the frame alone decides.
        """
        if np.shape(R_ground_cam) != (3, 3):
            raise FrontendError(f"R_ground_cam must be 3x3, got {np.shape(R_ground_cam)}")
        cfg = self.config
        t = [time.perf_counter()]
        # eq. 1-2: sagittal slice |x_C| < w, rotated into the ground frame (camera-relative)
        pc = cfg.projection
        confidence = frame.confidence
        n_fixed = 0
        if self._camera_fixed is not None:  # pixels that move with the camera are no terrain
            cf = cfg.camera_fixed
            check = (
                cf.drop_pixels
                or self._camera_fixed.holding
                or self._camera_fixed_frames % cf.idle_check_every_frames == 0
            )
            self._camera_fixed_frames += 1
            if check:
                fixed = self._camera_fixed_pixels(
                    frame, K, R_ground_cam, predicted_delta_xz_m, predicted_cov_m2, ground_turn_rad
                )
                n_fixed = int(np.count_nonzero(fixed))
                if n_fixed and cf.drop_pixels:
                    confidence = np.where(fixed, 0, confidence).astype(frame.confidence.dtype)
            else:
                self._camera_fixed.remember(
                    frame.depth_m, R_ground_cam, frame.timestamp_s, self._camera_fixed_sigma()
                )
        if pc.mixed_pixel_jump_m is not None:  # mixed pixels at depth edges, slice pixels only
            at = slice_pixel_mask(
                frame.depth_m,
                confidence,
                K,
                pc.half_width_m,
                pc.min_depth_m,
                pc.max_depth_m,
                pc.min_confidence,
            )
            confidence = drop_mixed_pixels(
                frame.depth_m,
                confidence,
                pc.mixed_pixel_jump_m,
                pc.mixed_pixel_abs_tol_m,
                pc.mixed_pixel_rel_tol,
                at,
                pc.mixed_pixel_radius_px,
            )
        speckle = None
        if pc.speckle_min_agree > 0:  # drop_speckles, evaluated at the slice's pixels only
            speckle = (pc.speckle_rel_tol, pc.speckle_abs_tol_m, pc.speckle_min_agree)
        points_xz = sagittal_slice_from_depth(
            frame.depth_m,
            confidence,
            K,
            R_ground_cam,
            pc.half_width_m,
            pc.min_depth_m,
            pc.max_depth_m,
            pc.min_confidence,
            speckle,
        )
        veil_xz = None
        if pc.veil_window_px is not None:  # mixed pixels along the rays through depth edges
            sigma_m = pc.veil_sigma_floor_m
            if self._noise is not None and np.isfinite(self._noise.sigma_m):
                sigma_m = max(sigma_m, self._noise.sigma_m)
            veil = veil_drops(
                points_xz,
                sigma_m,
                pc.veil_window_px / float(K[1, 1]),
                pc.veil_max_incidence_deg,
                pc.veil_k_sigma,
                pc.veil_ray_tol_px / float(K[1, 1]),
            )
            if veil.any():
                veil_xz = points_xz[veil]
                points_xz = points_xz[~veil]
        t.append(time.perf_counter())
        # kNN smoothing (after grid thinning)
        sc = cfg.smoothing
        cell_m = self.grid_cell_m
        profile = smooth_profile(points_xz, sc.k_neighbours, cell_m, sc.min_points)
        t.append(time.perf_counter())
        # terrain class (replaces the paper's CNN)
        # the frame's own class decides whether a corner is looked for: the stand surface
        # (rule step 5) says which way the terrain goes, it adds no edge to this frame
        frame_terrain, levels = classify_terrain(profile, cfg.terrain)
        # the walking surface only: returns beneath a level or another surface of this
        # frame (open risers)
        under = points_under_levels(profile, levels, cfg.terrain)
        seen_under = points_seen_under(profile, levels, cfg.terrain)
        walk = profile
        if under.any() or seen_under.any():
            walk = profile[~(under | seen_under)]
            frame_terrain, levels = classify_terrain(walk, cfg.terrain)
            # the points seen under a surface that is no level leave the class only, unless
            # under_sight_profile: they are static returns, which ICP uses as well
            profile = walk if cfg.terrain.under_sight_profile else profile[~under]
        if self._noise is not None:  # the next frame's thinning cell
            sigma = level_noise_sigma(  # robust_sigma(level_residuals(...)) in one call
                points_xz,
                [(lv.height_m, lv.x_min_m, lv.x_max_m) for lv in levels],
                cfg.terrain.level_band_m,
                max_range_m=sc.noise_max_range_m,
            )
            self._noise.update(sigma)
        terrain = frame_terrain
        if stand_height_m is not None:
            terrain = classify_against_stand(
                walk, frame_terrain, levels, stand_height_m, cfg.terrain
            )
        if cfg.terrain.obstacle_memory:
            if predicted_delta_xz_m is None:  # no displacement to place this frame by
                self._seen_obstacle = None
            else:
                self._track_xz_m = self._track_xz_m + np.asarray(predicted_delta_xz_m, float)
            stand_z = None if stand_height_m is None else stand_height_m + self._track_xz_m[1]
            terrain, self._seen_obstacle = recall_obstacle(
                terrain,
                levels,
                self._track_xz_m,
                self._seen_obstacle,
                cfg.terrain,
                stand_z,
                frame_terrain,
            )
        t.append(time.perf_counter())
        # Fig. 2: RANSAC lines, feature points at the higher line's edge (stairs / obstacles)
        corner = None
        if frame_terrain in self._corner_terrains:
            # the veil lies on the ray through the edge: it places the face below a nosing
            # seen from above (the corner's points below the tread end), though it is no
            # static surface for the levels and ICP
            seen = profile
            if veil_xz is not None and pc.veil_corners:
                seen = np.vstack([profile, veil_xz])
            corner = extract_corner(seen, self._rng, cfg.corners, frame_terrain)
        t.append(time.perf_counter())
        # eq. 3-4: ICP against the previous frame, seeded and gated by the IMU prediction
        tracked = self._tracker.update(
            frame.timestamp_s,
            profile,
            corner,
            predicted_delta_xz_m,
            predicted_cov_m2,
            ground_turn_rad,
        )
        t.append(time.perf_counter())
        names = ("projection", "smoothing", "terrain", "corners", "icp")
        timings = {n: (b - a) * 1e3 for n, a, b in zip(names, t[:-1], t[1:], strict=True)}
        timings["total"] = (t[-1] - t[0]) * 1e3
        return FrontendResult(
            timestamp_s=frame.timestamp_s,
            profile_xz_m=profile,
            terrain=terrain,
            corner=corner,
            displacement=tracked.displacement,
            observation=tracked.observation,
            rejection_reason=tracked.reason,
            icp=tracked.icp,
            timings_ms=timings,
            n_camera_fixed=n_fixed,
            relocalised=tracked.relocalised,
        )

    def _camera_fixed_sigma(self) -> float:
        """Depth noise sd of one pixel for the camera-fixed test, m: the larger of the floor
        and the noise measured on level surfaces."""
        sigma = self.config.camera_fixed.depth_sigma_floor_m
        if np.isfinite(self.depth_noise_m):
            sigma = max(sigma, self.depth_noise_m)
        return float(sigma)

    def _camera_fixed_pixels(
        self,
        frame: DepthFrame,
        K: NDArray[np.float64],
        R_ground_cam: NDArray[np.float64],
        predicted_delta_xz_m: NDArray[np.float64] | None,
        predicted_cov_m2: NDArray[np.float64] | None,
        ground_turn_rad: float,
    ) -> NDArray[np.bool_]:
        """(H, W) slice pixels that move with the camera (camera_fixed.py); all False on the
        first frame and without an IMU prediction."""
        assert self._camera_fixed is not None
        pc, cf = self.config.projection, self.config.camera_fixed
        depth = np.asarray(frame.depth_m)
        K = np.asarray(K, dtype=float)

        def candidates() -> NDArray[np.bool_]:  # computed only when the test runs
            return slice_pixel_mask(
                depth,
                frame.confidence,
                K,
                pc.half_width_m,
                pc.min_depth_m,
                pc.max_depth_m,
                pc.min_confidence,
            )

        sigma = self._camera_fixed_sigma()
        return self._camera_fixed.update(
            depth,
            candidates,
            K,
            R_ground_cam,
            predicted_delta_xz_m,
            predicted_cov_m2,
            sigma,
            cf.rot_sigma_rad,
            ground_turn_rad,
            frame.timestamp_s,
            cf.stamp_sigma_s,
        )
