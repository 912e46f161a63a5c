"""Frame-to-frame corner association and displacement (paper Section II.A.3, made robust).

Sign convention: the profile is relative to the camera, so a fixed terrain corner appears at
``corner - c_k`` in frame k. ICP (eq. 3-4) with the previous frame as source and the current
feature points as target gives ``T = -(c_k - c_{k-1})``; the camera displacement is ``-T``.

Paper mode (no IMU prediction, ``predicted_delta_xz_m=None``): two consecutive corners are the
same if their feature means differ by less than ``same_corner_gate_m``; ICP then starts from the
mean difference. On stairs this is fragile: the terrain is periodic (tread 0.28 m, rise
0.147 m) and during swing the shank moves 5-12 cm per frame at 30 fps (twice that at 15 fps).
Any gate wide enough to follow the corner at those speeds also accepts the NEXT nosing when the
tracked one leaves the view, and the displacement is then off by a whole step.

IMU-seeded mode (the default whenever the caller passes a prediction):

1. ICP starts from the IMU-predicted displacement, ``T0 = -predicted_delta``, so it converges to
   the local minimum of the correct period.
2. The source is the previous frame's whole smoothed profile (``icp_target="profile"``), not
   only its feature points; the current corner's points then find their counterparts even when
   the previous frame picked a different corner (``"features"`` reproduces the paper).
3. Gate: the ICP displacement must agree with the prediction,
   ``v^T (P_pred + C_icp + s^2 I)^-1 v <= gate_chi2`` with ``v = -T - predicted_delta``,
   ``s = gate_sigma_floor_m`` (default 13.8 = chi^2(2) at 99.9 %). A result one step off
   (>= 0.28 m) is far outside any IMU prediction covariance over one frame.
4. ICP quality: at least ``min_correspondences`` pairs and RMS <= ``max_rms_m``.
5. Track id: the current corner is the previous one if, moved back by the accepted T (or by
   T0 when ICP is rejected), its feature mean lies within ``same_corner_gate_m`` of the
   previous mean; otherwise it gets a new id.
6. No face below the edge (``edge_x_without_face``): on stair descent the risers face away, so
   the window holds only the end of a tread whose smoothing-rounded end biases ICP in x by
   centimetres per frame (downstair s1: -46 mm mean x error, with a 3 mm claimed sigma). When
   neither this nor the previous corner of the same track has a face, x comes from the edge
   points, ``-(edge_k - edge_{k-1})`` with variance ``2 edge_x_sigma_m^2``, z from ICP.
6b. Nosing check (``corner_check``): when this and the previous corner are the same track and
   both nosings were placed from a face line (``CornerFeature.has_face``), the difference of
   the two nosings is an independent displacement. Between two frames a band of missing tread
   behind the nosing moves with the camera, and ICP can lock onto the band's borders; such a
   result disagrees with the nosing difference v (Mahalanobis^2 above ``gate_chi2`` with
   ``C_icp + 2 corner_check_sigma_m^2 I``: rejected; above ``corner_inflate_chi2``: accepted
   with ``C_icp + v v^T``, so the covariance it claims covers the disagreement it shows).
7. No corner at all (``profile_fallback``, needs a prediction): the whole profile, thinned to
   ``fallback_grid_m``, is registered against the previous profile from the IMU seed and gated
   the same way. Floors give z, risers x, and the degenerate direction of a floor (x) is
   neither moved nor trusted (``IcpConfig.degenerate_ratio``). The stair periodicity (0.28 m)
   is far outside the prediction's uncertainty over one frame, so the seed picks the period.
   On the simulated trials this raised the displacement availability from 0.62 to 0.90
   (upstair s1) and 0.08 to 0.9 (obstacle s1, mostly level floor). ``False`` = the paper.
   Only surface the previous frame saw takes part (``fallback_overlap_margin_m``): in a fast
   swing the far end of the new profile is new terrain, which would pair with the end of the
   previous profile and pull the result towards zero motion.
   A floor can still look informative in x: the PCA normals of a noisy flat profile tilt at
   random and the point-to-line covariance reads them as x information. When the matched
   points of both frames lie on one straight line (``fallback_straight_ratio``) the slide
   along that line is dropped: the seed's component, with ``max_variance_m2``.
8. Corner ICP rejected (quality, gate or nosing check): the whole-profile ICP of step 7 is
   tried before giving up, and the corner observation is kept. In fast swings the 10 cm
   window can lose its counterpart while the profile still registers; without this, a frame
   classified as stairs measured less than the same frame classified level.
"""

from __future__ import annotations

import dataclasses
import math
from dataclasses import dataclass
from typing import TYPE_CHECKING, NamedTuple

import numpy as np
from numpy.typing import NDArray

from vio_graph.frontend.config import IcpConfig, TrackerConfig
from vio_graph.frontend.corners import CornerFeature
from vio_graph.frontend.icp import (
    IcpResult,
    SourceNormals,
    compiled_kernels,
    icp_translation_2d,
)
from vio_graph.frontend.smoothing import grid_thin
from vio_graph.geometry import rot_y_xz
from vio_graph.types import CornerObservation, Displacement2D

if TYPE_CHECKING:  # scipy is imported where a KD-tree is built (numpy paths only)
    from scipy.spatial import cKDTree


def _mahalanobis2(v: NDArray[np.float64], cov: NDArray[np.float64], floor_m2: float) -> float:
    """v^T (cov + floor I)^-1 v for a 2-vector, written out (np.linalg.solve's value up to
    rounding, without its call overhead)."""
    a, b, c = float(cov[0, 0]) + floor_m2, float(cov[0, 1]), float(cov[1, 1]) + floor_m2
    b2 = float(cov[1, 0])
    x, z = float(v[0]), float(v[1])
    det = a * c - b * b2
    if det == 0.0:
        return float(v @ np.linalg.solve(cov + np.eye(2) * floor_m2, v))  # raises LinAlgError
    return (x * (c * x - b * z) + z * (a * z - b2 * x)) / det


@dataclass(frozen=True)
class TrackerOutput:
    """Association result of one frame.

    ``displacement``: camera displacement since the previous frame (or None, see ``reason``).
    ``observation``: the current corner relative to the camera (None without a corner).
    ``icp``: the ICP run (None if ICP was not run). ``mahalanobis2``: gate statistic (nan when
    no prediction was given). ``relocalised``: the displacement comes from the lost-track
    search (no IMU seed, no prediction gate; ``TrackerConfig.relocalise_after_frames``).
    """

    displacement: Displacement2D | None
    observation: CornerObservation | None
    icp: IcpResult | None
    reason: str | None
    track_id: int | None
    same_corner: bool
    mahalanobis2: float = float("nan")
    relocalised: bool = False


@dataclass(frozen=True)
class _Frame:
    timestamp_s: float
    profile_xz_m: NDArray[np.float64]
    corner: CornerFeature | None
    track_id: int | None


class _Search(NamedTuple):
    """A lost-track search's answer: the displacement and its ICP run, with what the
    comparison with a seeded result needs: the answer's support (target points with a
    previous profile point within ``relocalise_inlier_m``), the previous profile's KD-tree
    and the thinned target (m) it was counted on."""

    displacement: Displacement2D
    icp: IcpResult
    support: int
    tree: cKDTree
    target: NDArray[np.float64]


class CornerTracker:
    """Keeps the previous frame and turns corner features into displacements (module doc)."""

    def __init__(
        self,
        tracker_config: TrackerConfig | None = None,
        icp_config: IcpConfig | None = None,
        edge_sigma_m: float = 0.01,
    ) -> None:
        self._cfg = TrackerConfig() if tracker_config is None else tracker_config
        self._icp_cfg = IcpConfig() if icp_config is None else icp_config
        fallback: dict[str, float] = {"normal_neighbours": self._cfg.fallback_normal_neighbours}
        if self._cfg.fallback_max_correspondence_m is not None:
            fallback["max_correspondence_m"] = self._cfg.fallback_max_correspondence_m
        self._fallback_icp_cfg = self._icp_cfg.model_copy(update=fallback)
        self._edge_cov_m2 = np.eye(2) * edge_sigma_m**2
        self._prev: _Frame | None = None
        self._next_id = 0
        self._frames_without_seeded = 0  # frames since the IMU-seeded ICP last gave a result
        # frames left on which a seeded displacement is checked against the search (it follows
        # a searched one: the IMU may still be wrong)
        self._verify_seeded = 0
        self._last_displacement: Displacement2D | None = None  # the previous frame's output

    def reset(self) -> None:
        """Forget the previous frame (track ids keep increasing)."""
        self._prev = None

    def _rotate_previous(self, angle_rad: float) -> None:
        """Re-express the previous frame in a ground frame turned by rot_y(``angle_rad``)
        about the camera (the estimator corrected its pitch since that frame), so that the
        next ICP compares two slices rotated alike."""
        if self._prev is None or angle_rad == 0.0:
            return
        R = rot_y_xz(angle_rad)  # (x, z) -> (c x + s z, -s x + c z)
        prev = self._prev
        corner = prev.corner
        if corner is not None:
            edge = corner.edge_xz_m @ R.T
            dz = float(edge[1] - corner.edge_xz_m[1])
            corner = dataclasses.replace(
                corner,
                feature_points_xz_m=corner.feature_points_xz_m @ R.T,
                mean_xz_m=corner.mean_xz_m @ R.T,
                edge_xz_m=edge,
                upper_height_m=corner.upper_height_m + dz,
                lower_height_m=corner.lower_height_m + dz,
            )
        self._prev = _Frame(prev.timestamp_s, prev.profile_xz_m @ R.T, corner, prev.track_id)

    def _new_id(self) -> int:
        self._next_id += 1
        return self._next_id - 1

    def update(
        self,
        timestamp_s: float,
        profile_xz_m: NDArray[np.float64],
        corner: CornerFeature | None,
        predicted_delta_xz_m: NDArray[np.float64] | None = None,
        predicted_cov_m2: NDArray[np.float64] | None = None,
        ground_turn_rad: float = 0.0,
    ) -> TrackerOutput:
        """Associate this frame's corner with the previous frame's and measure the displacement.

        Args:
            timestamp_s: frame time, seconds.
            profile_xz_m: (N, 2) smoothed profile relative to the camera, ground axes, metres.
            corner: this frame's corner feature, or None.
            predicted_delta_xz_m: (2,) IMU-predicted camera displacement since the previous
                frame (ground axes, metres), or None for the paper's mean-difference gating.
            predicted_cov_m2: (2, 2) its covariance; default ``default_prediction_sigma_m``^2 I.
            ground_turn_rad: rad; the ground frame was turned by rot_y(``ground_turn_rad``)
                since the previous frame (a pitch correction): the previous frame is
                re-expressed in it first.

        Returns:
            TrackerOutput; the frame becomes the previous frame for the next call.
        """
        self._rotate_previous(ground_turn_rad)
        out = self._associate(
            timestamp_s,
            corner,
            self._prev,
            predicted_delta_xz_m,
            predicted_cov_m2,
            np.asarray(profile_xz_m, float),
        )
        if predicted_delta_xz_m is not None:
            out = self._relocalise_if_lost(
                timestamp_s,
                np.asarray(profile_xz_m, float),
                out,
                np.asarray(predicted_delta_xz_m, dtype=float),
                self._prediction_cov(predicted_cov_m2),
            )
        self._last_displacement = out.displacement
        self._prev = _Frame(timestamp_s, np.asarray(profile_xz_m, float), corner, out.track_id)
        return out

    def _source(
        self, prev: _Frame, target: NDArray[np.float64], T0: NDArray[np.float64]
    ) -> tuple[NDArray[np.float64], cKDTree | None]:
        """ICP source: previous features, or the part of the previous profile that the target
        (moved back by T0) can reach: its bounding box grown by the correspondence distance
        plus ``source_margin_m``. Cropping keeps the KD-tree small (tens of points). The tree
        is None when the compiled ICP runs (it needs none; its numpy fallback builds one)."""
        if self._cfg.icp_target == "features":
            assert prev.corner is not None
            pts = prev.corner.feature_points_xz_m
            return pts, _source_tree(pts)
        grow = self._icp_cfg.max_correspondence_m + self._cfg.source_margin_m
        prof = prev.profile_xz_m
        kernels = compiled_kernels()
        if kernels is not None and target.shape[0] and target.ndim == prof.ndim == 2:
            # the same points in one compiled call (tests/test_frontend_fastpaths.py)
            pts = kernels.source_crop(
                np.ascontiguousarray(prof, dtype=float),
                np.ascontiguousarray(target, dtype=float),
                float(T0[0]),
                float(T0[1]),
                float(grow),
            )
        else:
            pts = _source_crop_reference(prof, target, T0, grow)
        if pts.shape[0] == 0:
            pts = prof[:1]  # ICP will find no correspondences and say so
        return pts, _source_tree(pts)

    def _associate(
        self,
        t: float,
        corner: CornerFeature | None,
        prev: _Frame | None,
        pred: NDArray[np.float64] | None,
        pred_cov: NDArray[np.float64] | None,
        profile: NDArray[np.float64] | None = None,
    ) -> TrackerOutput:
        cfg = self._cfg
        if corner is None:
            if cfg.profile_fallback and pred is not None and profile is not None:
                return self._profile_icp(t, profile, prev, pred, pred_cov)
            return TrackerOutput(None, None, None, "no corner in this frame", None, False)
        prev_corner = None if prev is None else prev.corner
        gap = self._gap_problem(t, prev)
        if gap is not None:
            return self._without_displacement(t, corner, None, gap)
        assert prev is not None

        if prev.profile_xz_m.shape[0] == 0:
            return self._without_displacement(t, corner, None, "previous frame has no profile")
        if pred is None:
            return self._paper_association(t, corner, prev)

        pred = np.asarray(pred, dtype=float)
        P = self._prediction_cov(pred_cov)
        T0 = -pred  # 1. IMU-seeded initial guess
        if cfg.icp_target == "features":
            if prev_corner is None:
                return self._without_displacement(t, corner, None, "no corner in previous frame")
            if not self._is_same(corner, prev_corner, T0):
                return self._without_displacement(t, corner, None, "corner changed (features)")
        target = corner.feature_points_xz_m
        if prev_corner is None and cfg.corner_overlap_check:
            # 2a. a corner the previous frame did not hold: only the part of its window that
            #     frame saw can register (a nosing entering the view would slide onto the
            #     surface next to it); too little of it -> the profile fallback below
            seen = self._seen_before(target, T0, prev)
            if seen is not None and int(seen.sum()) < cfg.min_correspondences:
                return self._unseen_corner(t, corner, prev, pred, pred_cov, profile)
            if seen is not None:
                target = target[seen]
        src, tree = self._source(prev, target, T0)  # 2. previous profile
        icp = icp_translation_2d(src, target, T0, self._icp_cfg, tree)
        bad = self._quality_problem(icp)  # 4. ICP quality
        T, C = icp.translation_xz_m, icp.cov_m2
        same_icp = prev_corner is not None and self._is_same(corner, prev_corner, T)
        if (
            cfg.edge_x_without_face
            and same_icp
            and prev_corner is not None
            and not self._has_face(corner)
            and not self._has_face(prev_corner)
        ):
            # 2b. no riser below the edge: x from the edge points, z from ICP
            T = np.array([corner.edge_xz_m[0] - prev_corner.edge_xz_m[0], T[1]])
            C = np.diag([2.0 * cfg.edge_x_sigma_m**2, C[1, 1]])
        d2, gate = self._gate(T, C, pred, P)  # 3. gate
        bad = bad or gate
        if (
            bad is None
            and cfg.corner_check
            and same_icp
            and prev_corner is not None
            and corner.has_face
            and prev_corner.has_face
        ):
            # 3b. both nosings placed from their faces: their difference is a second,
            #     independent displacement; ICP pulled elsewhere (by the borders of a missing
            #     band that moves with the camera) disagrees with it
            v = T - corner.edge_xz_m + prev_corner.edge_xz_m
            d2c = _mahalanobis2(v, C, 2.0 * cfg.corner_check_sigma_m**2)
            if d2c > cfg.gate_chi2:
                bad = f"ICP disagrees with the nosing displacement (Mahalanobis^2 {d2c:.1f})"
            elif d2c > cfg.corner_inflate_chi2:
                C = C + np.outer(v, v)  # the claim covers the disagreement it shows
        T_assoc = T0 if bad is not None else T
        same = prev_corner is not None and self._is_same(corner, prev_corner, T_assoc)  # 5.
        track_id = prev.track_id if same and prev.track_id is not None else self._new_id()
        obs = CornerObservation(t, track_id, corner.edge_xz_m.copy(), self._edge_cov(corner))
        if bad is not None:
            if cfg.profile_fallback and profile is not None:
                # 8. the corner window failed (too few points, RMS, gate): the whole profile
                #    may still register; the corner observation is kept either way
                alt = self._profile_icp(t, profile, prev, pred, pred_cov)
                if alt.displacement is not None:
                    return dataclasses.replace(
                        alt, observation=obs, track_id=track_id, same_corner=same
                    )
            return TrackerOutput(None, obs, icp, bad, track_id, same, d2)
        disp = Displacement2D(prev.timestamp_s, t, -T, C)
        return TrackerOutput(disp, obs, icp, None, track_id, same, d2)

    def _relocalise_if_lost(
        self,
        t: float,
        profile: NDArray[np.float64],
        out: TrackerOutput,
        pred_m: NDArray[np.float64],
        pred_cov_m2: NDArray[np.float64],
    ) -> TrackerOutput:
        """Lost-track search (``relocalise_after_frames``): after that many frames in a row
        without a seeded displacement, a frame whose seeded registration failed again gets
        the unseeded search's displacement, if it finds an unambiguous one that the IMU's
        prediction (``pred_m``, covariance ``pred_cov_m2``, m / m^2) does not rival; the
        seeded displacements that follow a searched one are checked against the search
        (:meth:`_verified`)."""
        n = self._cfg.relocalise_after_frames
        if out.displacement is not None:
            self._frames_without_seeded = 0
            if self._verify_seeded > 0:
                return self._verified(t, profile, out)
            return out
        self._frames_without_seeded += 1
        paper = not self._cfg.profile_fallback or self._cfg.icp_target != "profile"
        if n is None or paper or self._prev is None:
            return out  # (the search is a whole-profile registration: none in paper modes)
        if self._frames_without_seeded <= n:
            return out
        if self._gap_problem(t, self._prev) is not None:
            return out
        found = self._relocalise(t, profile, self._prev)
        if found is None or self._prediction_rivals(found, pred_m, pred_cov_m2):
            return out
        disp, icp = found.displacement, found.icp
        self._verify_seeded = self._cfg.relocalise_check_frames
        return dataclasses.replace(out, displacement=disp, icp=icp, reason=None, relocalised=True)

    def _prediction_rivals(
        self, found: _Search, pred_m: NDArray[np.float64], pred_cov_m2: NDArray[np.float64]
    ) -> bool:
        """Is the IMU's predicted displacement (m) a second solution the profiles cannot
        tell from the search's: disagreeing beyond their covariances, with at least
        ``relocalise_support_ratio`` of its support? The search is for an IMU that has
        lost track, whose prediction no part of the profile supports (after a knock: none
        of 50 points); where the seeded registration failed for another reason (a partial
        overlap in a fast swing), the prediction is about as well supported as any answer."""
        cfg = self._cfg
        d = -np.asarray(found.displacement.delta_xz_m, dtype=float) + pred_m
        cov = found.displacement.cov_m2 + pred_cov_m2
        if _mahalanobis2(d, cov, 0.0) <= cfg.gate_chi2:
            return False  # the same answer
        n_pred = _support(found.tree, found.target, -pred_m, cfg.relocalise_inlier_m)
        return n_pred >= cfg.relocalise_support_ratio * found.support

    def _search_window(self, t: float, prev: _Frame) -> tuple[NDArray[np.float64], float]:
        """Centre (T, m) and radius (m) of the search's grid. After a visual displacement
        that ended at ``prev``: vision's own constant-velocity prediction, within what
        ``relocalise_max_accel_mps2`` can change over the interval (0.5 a dt^2), so that a
        stair's period (0.32 m along the slope) stays out of reach even at 15 fps. Otherwise
        around no motion, within ``relocalise_max_speed_mps`` x the interval."""
        cfg = self._cfg
        dt = t - prev.timestamp_s
        last = self._last_displacement
        if last is not None and abs(float(last.t1_s) - prev.timestamp_s) < 1e-9:
            v = np.asarray(last.delta_xz_m, dtype=float) / float(last.t1_s - last.t0_s)
            radius = 0.5 * cfg.relocalise_max_accel_mps2 * dt * dt
            return -v * dt, max(radius, 2.0 * cfg.relocalise_grid_m)
        return np.zeros(2), max(cfg.relocalise_max_speed_mps * dt, cfg.relocalise_grid_m)

    def _verified(
        self, t: float, profile: NDArray[np.float64], out: TrackerOutput
    ) -> TrackerOutput:
        """A seeded displacement right after a searched one: the IMU that was wrong may still
        be (a knock lasting several frames), and ICP from a wrong seed can settle in a wrong
        basin that agrees with it, or measure one axis only and let the IMU carry the other.
        For up to ``relocalise_check_frames`` frames the search runs too; if it is
        unambiguous and disagrees with the seeded result beyond their covariances with
        clearly more support (the seeded translation's below ``relocalise_support_ratio``
        of it), or measures more (smaller covariance trace), it replaces it (and the next
        frame is checked again); otherwise the checks end."""
        assert out.displacement is not None
        self._verify_seeded -= 1
        found = None if self._prev is None else self._relocalise(t, profile, self._prev)
        if found is not None:
            disp, icp = found.displacement, found.icp
            seeded = out.displacement
            v = np.asarray(disp.delta_xz_m) - np.asarray(seeded.delta_xz_m)
            disagree = _mahalanobis2(v, disp.cov_m2 + seeded.cov_m2, 0.0) > self._cfg.gate_chi2
            # two answers: the search's only if clearly more of this frame's profile
            # supports it (the same count; the ambiguity test's ratio)
            r = self._cfg.relocalise_inlier_m
            T_seeded = -np.asarray(seeded.delta_xz_m, dtype=float)
            n_seeded = _support(found.tree, found.target, T_seeded, r)
            # a seeded result that leaves an axis unmeasured (a riser alone: no z) lets the
            # IMU carry that axis through the fault; the search measured it
            more = np.trace(disp.cov_m2) < np.trace(seeded.cov_m2)
            clearly = n_seeded < self._cfg.relocalise_support_ratio * found.support
            if (disagree and clearly) or (not disagree and more):
                return dataclasses.replace(out, displacement=disp, icp=icp, relocalised=True)
        self._verify_seeded = 0
        return out

    def _relocalise(self, t: float, profile: NDArray[np.float64], prev: _Frame) -> _Search | None:
        """The displacement since ``prev`` without the IMU seed: the translation grid of
        :meth:`_search_window` scored by support (target points with a previous profile point
        within ``relocalise_inlier_m``), ICP of the whole profile from its best separated
        candidates, and the best-supported result if no other one with comparable support
        disagrees with it beyond their covariances (None otherwise), as a :class:`_Search`."""
        from scipy.spatial import cKDTree

        cfg = self._cfg
        target = grid_thin(profile, cfg.fallback_grid_m) if cfg.fallback_grid_m > 0 else profile
        src = prev.profile_xz_m
        if min(target.shape[0], src.shape[0]) < cfg.min_correspondences:
            return None
        tree = cKDTree(src)
        centre, radius = self._search_window(t, prev)
        seeds = _grid_seeds(
            tree, target, centre, radius, cfg.relocalise_grid_m, cfg.relocalise_inlier_m
        )
        found: list[tuple[int, NDArray[np.float64], NDArray[np.float64], IcpResult]] = []
        for T0 in seeds[:4]:
            if _support(tree, target, T0, cfg.relocalise_inlier_m) < cfg.min_correspondences:
                break  # seeds come best first
            icp = icp_translation_2d(src, target, T0, self._fallback_icp_cfg, tree)
            if self._quality_problem(icp) is not None:
                continue
            T = icp.translation_xz_m
            if np.max(np.abs(T - centre)) > radius + cfg.relocalise_grid_m:
                continue  # ICP walked out of the window (to the next stair period, say)
            found.append((_support(tree, target, T, cfg.relocalise_inlier_m), T, icp.cov_m2, icp))
        if not found:
            return None
        found.sort(key=lambda f: -f[0])
        best_n, T, C, icp = found[0]
        if best_n < cfg.relocalise_min_share * target.shape[0]:
            return None  # a partial overlap: most of the profile does not confirm it
        for n_other, T_other, C_other, _ in found[1:]:
            if n_other < cfg.relocalise_support_ratio * best_n:
                continue
            if _mahalanobis2(T_other - T, C + C_other, 0.0) > cfg.gate_chi2:
                return None  # two answers the profiles cannot tell apart
        return _Search(Displacement2D(prev.timestamp_s, t, -T, C), icp, best_n, tree, target)

    def _unseen_corner(
        self,
        t: float,
        corner: CornerFeature,
        prev: _Frame,
        pred: NDArray[np.float64],
        pred_cov: NDArray[np.float64] | None,
        profile: NDArray[np.float64] | None,
    ) -> TrackerOutput:
        """A new corner whose window the previous frame did not see: its observation (a new
        track) with the profile fallback's displacement, if that registers."""
        reason = "corner window not seen in the previous frame"
        if self._cfg.profile_fallback and profile is not None:
            alt = self._profile_icp(t, profile, prev, pred, pred_cov)
            if alt.displacement is not None:
                track_id = self._new_id()
                edge = corner.edge_xz_m.copy()
                obs = CornerObservation(t, track_id, edge, self._edge_cov(corner))
                return dataclasses.replace(
                    alt, observation=obs, track_id=track_id, same_corner=False
                )
        return self._without_displacement(t, corner, None, reason)

    def _gap_problem(self, t: float, prev: _Frame | None) -> str | None:
        """Why there is no previous frame to register against at ``t`` (s), or None."""
        if prev is None:
            return "no previous frame"
        if not (0.0 < t - prev.timestamp_s <= self._cfg.max_frame_gap_s):
            return "frame gap too large"
        return None

    def _prediction_cov(self, pred_cov: NDArray[np.float64] | None) -> NDArray[np.float64]:
        """The IMU prediction's covariance (m^2), ``default_prediction_sigma_m``^2 I if none."""
        if pred_cov is None:
            return np.eye(2) * self._cfg.default_prediction_sigma_m**2
        return np.asarray(pred_cov, dtype=float)

    def _gate(
        self,
        T: NDArray[np.float64],
        C: NDArray[np.float64],
        pred: NDArray[np.float64],
        P: NDArray[np.float64],
    ) -> tuple[float, str | None]:
        """Step 3: Mahalanobis^2 of the ICP displacement -T (covariance C) against the IMU
        prediction (covariance P), and the rejection reason if it exceeds ``gate_chi2``."""
        cfg = self._cfg
        d2 = _mahalanobis2(-T - pred, P + C, cfg.gate_sigma_floor_m**2)
        if d2 > cfg.gate_chi2:
            return d2, f"ICP disagrees with the IMU prediction (Mahalanobis^2 {d2:.1f})"
        return d2, None

    def _edge_cov(self, corner: CornerFeature) -> NDArray[np.float64]:
        """Covariance of the corner observation, m^2: ``edge_sigma_m`` per axis, and x widened
        to ``faceless_edge_x_sigma_m`` for a near-end corner no face line supports (its x is
        the end of the tread, which a missing band moves by centimetres)."""
        cov = self._edge_cov_m2.copy()
        if corner.side == "near" and not corner.has_face:
            cov[0, 0] = max(cov[0, 0], self._cfg.faceless_edge_x_sigma_m**2)
        return cov

    def _has_face(self, corner: CornerFeature) -> bool:
        """True if the feature window holds a face (riser / obstacle side) below the edge."""
        below = corner.feature_points_xz_m[:, 1] < corner.edge_xz_m[1] - 0.01
        return int(np.count_nonzero(below)) >= self._cfg.min_face_points

    def _profile_icp(
        self,
        t: float,
        profile: NDArray[np.float64],
        prev: _Frame | None,
        pred: NDArray[np.float64],
        pred_cov: NDArray[np.float64] | None,
    ) -> TrackerOutput:
        """No corner: ICP of the whole (thinned) profile against the previous profile, seeded
        by the IMU prediction and gated like the corner ICP. Floors constrain z, risers x;
        unobservable directions get the capped variance, so the filter ignores them."""
        cfg = self._cfg
        gap = self._gap_problem(t, prev)
        if gap is not None:
            return TrackerOutput(None, None, None, f"no corner in this frame; {gap}", None, False)
        assert prev is not None
        target = grid_thin(profile, cfg.fallback_grid_m) if cfg.fallback_grid_m > 0 else profile
        # fallback_full_target: register every point of the profile, but claim the
        # information of the thinned one (its pairs are that many times denser, not
        # independent: kNN-smoothed neighbours)
        density = 1.0
        if cfg.fallback_full_target and target.shape[0]:
            density = profile.shape[0] / target.shape[0]
            target = profile
        if target.shape[0] < cfg.min_correspondences or prev.profile_xz_m.shape[0] == 0:
            return TrackerOutput(
                None, None, None, "no corner in this frame; profile too short", None, False
            )
        pred = np.asarray(pred, dtype=float)
        T0 = -pred
        seen = self._seen_before(target, T0, prev)
        if seen is not None and int(seen.sum()) >= cfg.min_correspondences:
            target = target[seen]
        src, tree = self._source(prev, target, T0)
        normals = SourceNormals()  # the restart check's ICP reuses the source normals
        icp = icp_translation_2d(src, target, T0, self._fallback_icp_cfg, tree, normals)
        if density > 1.0:
            cov = _scaled_cov(icp.cov_m2, density, self._fallback_icp_cfg.max_variance_m2)
            icp = dataclasses.replace(icp, cov_m2=cov)
        bad = self._quality_problem(icp)
        P = self._prediction_cov(pred_cov)
        d2, gate = self._gate(icp.translation_xz_m, icp.cov_m2, P=P, pred=pred)
        bad = bad or gate
        if bad is not None:
            return TrackerOutput(None, None, icp, f"profile ICP: {bad}", None, False, d2)
        T, C = icp.translation_xz_m, icp.cov_m2
        if _is_straight(icp, cfg.fallback_straight_ratio):  # nothing fixes the slide along it
            T, C = _drop_weakest(T, C, T0, self._fallback_icp_cfg.max_variance_m2)
        elif cfg.fallback_restart_check:
            C = self._restart_check(src, target, T0, P, tree, icp, normals)
        disp = Displacement2D(prev.timestamp_s, t, -T, C)
        return TrackerOutput(disp, None, icp, None, None, False, d2)

    def _restart_check(
        self,
        src: NDArray[np.float64],
        target: NDArray[np.float64],
        T0: NDArray[np.float64],
        P: NDArray[np.float64],
        tree: cKDTree | None,
        icp: IcpResult,
        normals: SourceNormals | None = None,
    ) -> NDArray[np.float64]:
        """Does the profile determine the answer, or the seed? ICP again from the seed moved by
        two prediction sigmas (at most half the correspondence distance) along the direction
        the result claims to know least; if the two answers differ by more than the claimed
        covariance allows (Mahalanobis^2 above ``corner_inflate_chi2``), the claim is widened
        by that difference (C + d d^T), as for the nosing check. A short, noisy far floor
        (1.5 m away, z noise ~1 cm) gives PCA normals tilted at random, which the
        point-to-line covariance reads as x information:
        downstair with IMU spikes s2, a displacement 1.6 cm off in x claiming 0.36 cm, which
        the filter's uncertain velocity turned into a 5 cm jump."""
        C = icp.cov_m2
        u = np.linalg.eigh(C)[1][:, 1]  # the least-known direction of the claim
        # within ICP's capture range: a seed moved farther than half the correspondence
        # distance can leave a well-measured riser's basin, which would look like ambiguity
        reach = 0.5 * self._fallback_icp_cfg.max_correspondence_m
        if self._cfg.fallback_restart_shift == "reach":
            shift = reach
        else:
            shift = min(2.0 * float(np.sqrt(max(float(u @ P @ u), 0.0))), reach)
        seed = T0 + shift * u
        icp2 = icp_translation_2d(src, target, seed, self._fallback_icp_cfg, tree, normals)
        d = icp2.translation_xz_m - icp.translation_xz_m
        if _mahalanobis2(d, C, 0.0) > self._cfg.corner_inflate_chi2:
            C = C + np.outer(d, d)
        return C

    def _seen_before(
        self, target: NDArray[np.float64], T0: NDArray[np.float64], prev: _Frame
    ) -> NDArray[np.bool_] | None:
        """Which ``target`` points (m, this frame), moved back by the IMU seed ``T0``, fall
        inside the previous profile's x extent shrunk by ``fallback_overlap_margin_m``: surface
        the previous frame never saw has no counterpart there. None if the margin is off."""
        margin = self._cfg.fallback_overlap_margin_m
        if margin is None:
            return None
        back_x = target[:, 0] - T0[0]
        px = prev.profile_xz_m[:, 0]
        return (back_x >= px.min() + margin) & (back_x <= px.max() - margin)

    def _paper_association(self, t: float, corner: CornerFeature, prev: _Frame) -> TrackerOutput:
        """Paper: same corner if the feature means are close; ICP from the mean difference."""
        if prev.corner is None:
            return self._without_displacement(t, corner, None, "no corner in previous frame")
        shift = corner.mean_xz_m - prev.corner.mean_xz_m
        if np.linalg.norm(shift) > self._cfg.same_corner_gate_m:
            return self._without_displacement(t, corner, None, "corner changed (mean gate)")
        src, tree = self._source(prev, corner.feature_points_xz_m, shift)
        icp = icp_translation_2d(src, corner.feature_points_xz_m, shift, self._icp_cfg, tree)
        track_id = prev.track_id if prev.track_id is not None else self._new_id()
        obs = CornerObservation(t, track_id, corner.edge_xz_m.copy(), self._edge_cov(corner))
        bad = self._quality_problem(icp)
        if bad is not None:
            return TrackerOutput(None, obs, icp, bad, track_id, True)
        disp = Displacement2D(prev.timestamp_s, t, -icp.translation_xz_m, icp.cov_m2)
        return TrackerOutput(disp, obs, icp, None, track_id, True)

    def _is_same(self, corner: CornerFeature, prev_corner: CornerFeature, T: NDArray) -> bool:
        moved_back = corner.mean_xz_m - T
        v = moved_back - prev_corner.mean_xz_m
        # np.linalg.norm of a vector is sqrt(v.dot(v)): the same float without its wrapper
        gap_m = math.sqrt(float(v.dot(v)))
        return gap_m <= self._cfg.same_corner_gate_m

    def _quality_problem(self, icp: IcpResult) -> str | None:
        if icp.n_correspondences < self._cfg.min_correspondences:
            return f"too few ICP correspondences ({icp.n_correspondences})"
        if icp.rms_m > self._cfg.max_rms_m:
            return f"ICP RMS too large ({icp.rms_m * 1e3:.1f} mm)"
        return None

    def _without_displacement(
        self, t: float, corner: CornerFeature, icp: IcpResult | None, reason: str
    ) -> TrackerOutput:
        track_id = self._new_id()
        obs = CornerObservation(t, track_id, corner.edge_xz_m.copy(), self._edge_cov(corner))
        return TrackerOutput(None, obs, icp, reason, track_id, False)


def _is_straight(icp: IcpResult, ratio: float | None) -> bool:
    """Do the matched points lie on one straight line (False if the test is off, ``ratio``
    None)? Both frames' matched points (the source moved by T) get one total-least-squares
    line; its mean squared perpendicular distance is compared with the noise the pairs show
    along its normal (half the mean squared pair residual: two noisy points per pair). A
    straight profile (a floor, a ramp, one tread) leaves those close; a riser or a step edge
    puts points centimetres off the line."""
    if ratio is None or icp.n_correspondences < 3:
        return False
    pt = icp.target_points_xz_m
    ps = icp.matched_source_xz_m + icp.translation_xz_m
    pts = np.vstack([pt, ps])
    c = pts - pts.mean(axis=0)
    w, V = np.linalg.eigh(c.T @ c / pts.shape[0])
    r = (pt - ps) @ V[:, 0]
    noise = max(float(r @ r) / (2 * r.size), 1e-12)
    return float(w[0]) <= ratio * noise


def _scaled_cov(C: NDArray[np.float64], factor: float, cap_m2: float) -> NDArray[np.float64]:
    """C x ``factor`` with its eigenvalues capped at ``cap_m2`` (an unobservable direction
    keeps the cap, as ICP gives it)."""
    w, V = np.linalg.eigh(C)
    w = np.minimum(w * factor, np.maximum(w, cap_m2))
    return (V * w) @ V.T


def _drop_weakest(
    T: NDArray[np.float64], C: NDArray[np.float64], T0: NDArray[np.float64], cap_m2: float
) -> tuple[NDArray[np.float64], NDArray[np.float64]]:
    """T and C with the least-informed direction u of C (along a straight profile: the
    normals' mean is its normal) declared unobservable, as ICP treats a degenerate one: T
    keeps the seed ``T0``'s component along u, C gets ``cap_m2`` along u and keeps its own
    variance across it. Unchanged if C already has the cap along u."""
    w, V = np.linalg.eigh(C)
    if float(w[1]) >= cap_m2:
        return T, C
    u, n = V[:, 1], V[:, 0]
    return T + u * float(u @ (T0 - T)), float(w[0]) * np.outer(n, n) + cap_m2 * np.outer(u, u)


def _source_crop_reference(
    prof: NDArray[np.float64], target: NDArray[np.float64], T0: NDArray[np.float64], grow: float
) -> NDArray[np.float64]:
    """The points of ``prof`` inside the bounding box of ``target - T0`` grown by ``grow``
    (m), in input order (numpy path of ``compiled.source_crop``)."""
    moved = target - T0
    mx, mz = moved[:, 0], moved[:, 1]
    px, pz = prof[:, 0], prof[:, 1]
    inside = (px >= mx.min() - grow) & (px <= mx.max() + grow)
    inside &= (pz >= mz.min() - grow) & (pz <= mz.max() + grow)
    return prof[inside]


def _source_tree(pts: NDArray[np.float64]) -> cKDTree | None:
    """KD-tree of the ICP source for the numpy ICP path; None when the compiled one runs."""
    if compiled_kernels() is not None:
        return None
    from scipy.spatial import cKDTree

    return cKDTree(pts)


def _support(tree: cKDTree, target: NDArray[np.float64], T: NDArray[np.float64], r: float) -> int:
    """How many ``target`` points (m), moved back by T (target ~= T + source), have a source
    point of ``tree`` within ``r`` (m)."""
    d, _ = tree.query(target - T, distance_upper_bound=r)
    return int(np.count_nonzero(np.isfinite(d)))


def _grid_seeds(
    tree: cKDTree,
    target: NDArray[np.float64],
    centre: NDArray[np.float64],
    radius: float,
    step: float,
    r: float,
) -> list[NDArray[np.float64]]:
    """Translations T on a square grid of spacing ``step`` within ``radius`` (m) of
    ``centre``, best supported first (:func:`_support`), each at least two grid steps from
    every better one (the separated local maxima of the support)."""
    axis = np.arange(-radius, radius + 0.5 * step, step)
    gx, gz = np.meshgrid(axis, axis, indexing="ij")
    grid = np.stack([gx.ravel(), gz.ravel()], axis=1) + np.asarray(centre, dtype=float)
    moved = (target[None, :, :] - grid[:, None, :]).reshape(-1, 2)
    d, _ = tree.query(moved, distance_upper_bound=r)
    score = np.isfinite(d).reshape(grid.shape[0], target.shape[0]).sum(axis=1)
    seeds: list[NDArray[np.float64]] = []
    for i in np.argsort(-score, kind="stable"):
        if score[i] == 0:
            break
        if all(np.max(np.abs(grid[i] - s)) >= 2 * step - 1e-12 for s in seeds):
            seeds.append(grid[i])
            if len(seeds) == 8:
                break
    return seeds
