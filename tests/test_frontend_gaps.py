"""Corners at the nosing despite a missing band of tread behind it; terrain class from the
geometry of one frame (levels and the vertical faces between them)."""

from __future__ import annotations

import numpy as np
import pytest

from vio_graph.frontend.config import CornerConfig, TerrainConfig
from vio_graph.frontend.corners import extract_corner
from vio_graph.frontend.smoothing import smooth_profile
from vio_graph.frontend.synthetic import (
    drop_tread_band,
    raycast_profile,
    stair_edges,
    stair_polyline,
)
from vio_graph.frontend.terrain import classify_terrain, find_faces, find_levels
from vio_graph.types import TerrainKind

CAM_HEIGHT_M = 0.45


def _stair_view(overhang_m: float, gap_m: float, cam_x_m: float, seed: int):
    """Smoothed noisy stair-up profile (camera-relative), true nosing tips (camera-relative)
    and the raw (unsmoothed) profile after the band removal."""
    poly = stair_polyline("stair_up", start_x_m=0.6, nosing_overhang_m=overhang_m)
    cam = np.array([cam_x_m, CAM_HEIGHT_M])
    raw = raycast_profile(
        poly, cam, pitch_down_rad=0.7, noise_m=0.004, rng=np.random.default_rng(seed), n_rays=800
    )
    if gap_m > 0:
        raw = drop_tread_band(raw, cam, poly, gap_m)
    return smooth_profile(raw), stair_edges(poly) - cam, raw


def test_synthetic_overhang_and_band_are_where_asked() -> None:
    """The generator itself: the nosing tip moves by the overhang, the band is removed."""
    poly = stair_polyline("stair_up", start_x_m=0.6, n_steps=2, nosing_overhang_m=0.02)
    np.testing.assert_allclose(stair_edges(poly), [[0.58, 0.147], [0.86, 0.294]])
    _, tips, raw = _stair_view(0.0, 0.05, 0.0, seed=0)
    tip = tips[0]
    on_tread = np.abs(raw[:, 1] - tip[1]) < 0.015
    behind = raw[on_tread, 0] - tip[0]
    assert not np.any((behind > 0.0) & (behind < 0.05))
    assert np.any((behind > 0.05) & (behind < 0.08))  # the tread resumes after the band


@pytest.mark.parametrize("overhang_m", [0.0, 0.015, 0.03])
@pytest.mark.parametrize("gap_m", [0.0, 0.02, 0.04, 0.06])
def test_corner_is_at_the_nosing_with_and_without_a_missing_band(
    overhang_m: float, gap_m: float
) -> None:
    errors = []
    for cam_x_m, seed in [(-0.2, 1), (-0.05, 2), (0.1, 3), (0.25, 4)]:
        profile, tips, _ = _stair_view(overhang_m, gap_m, cam_x_m, seed)
        corner = extract_corner(profile, np.random.default_rng(0), terrain=TerrainKind.STAIR_UP)
        assert corner is not None and corner.has_face
        err = np.linalg.norm(tips - corner.edge_xz_m, axis=1)
        errors.append(err.min())
        tip = tips[np.argmin(err)]
        if gap_m > 0:  # premise: the raw tread resumes only after the band
            _, _, raw = _stair_view(overhang_m, gap_m, cam_x_m, seed)
            tread = raw[(np.abs(raw[:, 1] - tip[1]) < 0.01) & (raw[:, 0] > tip[0] + 0.003)]
            assert tread[:, 0].min() - tip[0] > gap_m - 0.005
    assert max(errors) < 0.01  # within 1 cm of the nosing tip on every view


def test_a_riser_band_is_not_taken_for_the_tread() -> None:
    """Camera close below a nosing, tread cut short by the view and a 6 cm band: a 4 cm band
    across the riser holds more points than the tread. The corner must stay on the tread
    height (or not be given), never in the middle of the riser."""
    for seed in range(3):
        profile, tips, _ = _stair_view(0.0, 0.06, 0.40, seed)
        corner = extract_corner(profile, np.random.default_rng(0), terrain=TerrainKind.STAIR_UP)
        if corner is not None:
            assert np.linalg.norm(tips - corner.edge_xz_m, axis=1).min() < 0.01


def test_no_face_below_a_tread_end_is_reported_and_widened() -> None:
    """A tread seen from above without anything below its near end: the corner keeps the
    tread end, says no face supports it, and the tracker's observation of it has a wide x
    sigma (the end of the tread may be a band's border); ``near_edge_needs_face`` drops it."""
    from vio_graph.frontend.tracker import CornerTracker

    rng = np.random.default_rng(3)
    x_low, x_high = np.linspace(-0.1, 0.15, 60), np.linspace(0.30, 0.60, 70)
    pts = np.vstack(
        [
            np.column_stack([x_low, -0.45 + rng.normal(0, 0.002, x_low.size)]),
            np.column_stack([x_high, -0.30 + rng.normal(0, 0.002, x_high.size)]),
        ]
    )
    profile = smooth_profile(pts)
    strict = CornerConfig(near_edge_needs_face=True)
    assert extract_corner(profile, np.random.default_rng(0), strict, TerrainKind.STAIR_UP) is None
    corner = extract_corner(profile, np.random.default_rng(0), terrain=TerrainKind.STAIR_UP)
    assert corner is not None and not corner.has_face
    obs = CornerTracker().update(0.0, profile, corner).observation
    assert obs is not None
    assert np.sqrt(obs.cov_m2[0, 0]) == pytest.approx(0.03)
    assert np.sqrt(obs.cov_m2[1, 1]) == pytest.approx(0.01)
    assert corner.edge_xz_m[0] == pytest.approx(0.30, abs=0.01)


# --- terrain class from levels and faces ------------------------------------------------------


def _polyline_points(
    vertices: list[tuple[float, float]], seed: int, noise_m: float = 0.002, spacing_m: float = 0.003
) -> np.ndarray:
    """Noisy points along a polyline (camera-relative), then grid thinning + kNN smoothing."""
    rng = np.random.default_rng(seed)
    v = np.asarray(vertices, dtype=float)
    parts = []
    for a, b in zip(v[:-1], v[1:], strict=True):
        n = max(2, int(np.linalg.norm(b - a) / spacing_m))
        t = np.linspace(0.0, 1.0, n, endpoint=False)[:, None]
        parts.append(a + t * (b - a))
    pts = np.vstack(parts)
    return smooth_profile(pts + rng.normal(0.0, noise_m, pts.shape))


# camera-relative views a low shank camera has of a 11.5 cm x 28 cm stair during a slow
# step-to-step ascent (the frames that were classified LEVEL / UNKNOWN before)
VIEWS = {
    # one tread, the next riser rising at its far end, the tread above out of view
    "tread_then_rising_riser": ([(0.14, -0.21), (0.38, -0.21), (0.38, -0.10)], "stair_up"),
    # a short piece of the lower tread, the riser, the tread above
    "riser_at_the_near_end": (
        [(-0.03, -0.48), (0.01, -0.48), (0.01, -0.365), (0.29, -0.365)],
        "stair_up",
    ),
    # treads too oblique to return: one riser, then only separate risers
    "floor_and_risers_only": ([(0.53, -0.25), (0.81, -0.25), (0.81, -0.14)], "stair_up"),
    "level_floor": ([(0.2, -0.40), (0.9, -0.40)], "level"),
}


@pytest.mark.parametrize("name", list(VIEWS))
def test_terrain_class_from_one_level_and_a_face(name: str) -> None:
    vertices, truth = VIEWS[name]
    for seed in range(3):
        profile = _polyline_points(vertices, seed)
        if name == "floor_and_risers_only":  # add two more bare risers farther up
            extra = [
                _polyline_points([(1.09, -0.135), (1.09, -0.02)], seed + 10),
                _polyline_points([(1.37, -0.02), (1.37, 0.095)], seed + 20),
            ]
            profile = np.vstack([profile, *extra])
        kind, _ = classify_terrain(profile)
        assert kind == TerrainKind(truth), (name, seed)
        # with faces switched off the same frames were LEVEL / UNKNOWN (the old behaviour)
        old, _ = classify_terrain(profile, TerrainConfig(use_faces=False))
        if truth == "stair_up":
            assert old in (TerrainKind.LEVEL, TerrainKind.UNKNOWN)


def test_faces_have_the_right_position_and_direction() -> None:
    profile = _polyline_points([(0.14, -0.21), (0.38, -0.21), (0.38, -0.10)], seed=0)
    cfg = TerrainConfig()
    faces = find_faces(profile, find_levels(profile, cfg), cfg)
    assert len(faces) == 1
    assert faces[0].x_m == pytest.approx(0.38, abs=0.01) and faces[0].direction == 1
    # mirrored in x (a drop at the far end of a tread, going away): direction -1
    mirrored = profile * [-1.0, 1.0]
    faces = find_faces(mirrored, find_levels(mirrored, cfg), cfg)
    assert len(faces) == 1 and faces[0].direction == -1


def test_a_wall_stays_unknown() -> None:
    """A floor and a 0.6 m vertical face: a wall, not a riser."""
    profile = _polyline_points([(0.2, -0.40), (0.6, -0.40), (0.6, 0.20)], seed=0)
    cfg = TerrainConfig()
    faces = find_faces(profile, find_levels(profile, cfg), cfg)
    assert len(faces) == 1 and faces[0].direction == 0
    assert classify_terrain(profile)[0] == TerrainKind.UNKNOWN


# --- tracker: a displacement dominated by the missing band -------------------------------------


def _gap_view(camera_xz: np.ndarray, gap_m: float, skirt_m: float, seed: int):
    """Stair-up profile with a band of ``gap_m`` missing behind every nosing and, at the far
    border of the first nosing's band, a skirt of ``skirt_m`` of leftover mixed pixels on the
    line of sight (they move with the camera, not with the stair). Returns the profile and its
    corner."""
    poly = stair_polyline("stair_up", start_x_m=0.6, n_steps=6)
    tip = stair_edges(poly)[0]
    raw = raycast_profile(
        poly,
        camera_xz,
        pitch_down_rad=0.7,
        noise_m=0.002,
        rng=np.random.default_rng(seed),
        n_rays=800,
    )
    raw = drop_tread_band(raw, camera_xz, poly, gap_m)
    if skirt_m > 0:
        border = tip + [gap_m, 0.0] - camera_xz
        ray = border / np.linalg.norm(border)
        raw = np.vstack([raw, border - np.outer(np.linspace(0.0, skirt_m, 25), ray)])
    profile = smooth_profile(raw)
    return profile, extract_corner(profile, np.random.default_rng(0), terrain=TerrainKind.STAIR_UP)


@pytest.mark.parametrize("skirt_m", [0.0, 0.05])
def test_tracker_with_bands_at_different_places_claims_an_honest_covariance(
    skirt_m: float,
) -> None:
    """Two views of the same stair, bands of 3 and 6 cm (so the band's borders are at
    different places on the stair), known displacement. Without leftovers the displacement is
    right to 3 mm; with a skirt on the line of sight ICP is pulled in z by ~2 cm while its own
    covariance claims ~3 mm: the nosing check must make the claim cover the error
    (NEES below the chi-square 99 % point) or reject the displacement."""
    from vio_graph.frontend.config import TrackerConfig
    from vio_graph.frontend.tracker import CornerTracker

    c0, delta = np.array([0.1, 0.45]), np.array([0.05, 0.02])
    p0, f0 = _gap_view(c0, 0.03, skirt_m, seed=1)
    p1, f1 = _gap_view(c0 + delta, 0.06, skirt_m, seed=2)
    assert f0 is not None and f1 is not None and f0.has_face and f1.has_face
    outs = {}
    for check in (False, True):
        tracker = CornerTracker(TrackerConfig(corner_check=check))
        tracker.update(0.0, p0, f0)
        outs[check] = tracker.update(1 / 30, p1, f1, delta + [0.01, -0.005], np.eye(2) * 0.02**2)
    unchecked, checked = outs[False], outs[True]
    assert unchecked.displacement is not None
    err = unchecked.displacement.delta_xz_m - delta
    nees_unchecked = float(err @ np.linalg.solve(unchecked.displacement.cov_m2, err))
    if skirt_m == 0.0:
        assert np.linalg.norm(err) < 0.003 and nees_unchecked < 9.21
        assert checked.displacement is not None
        np.testing.assert_allclose(
            checked.displacement.delta_xz_m, unchecked.displacement.delta_xz_m
        )
        return
    assert abs(err[1]) > 0.01 and nees_unchecked > 20.0  # premise: wrong and over-confident
    if checked.displacement is not None:
        e = checked.displacement.delta_xz_m - delta
        assert float(e @ np.linalg.solve(checked.displacement.cov_m2, e)) < 9.21
    else:
        assert "nosing displacement" in (checked.reason or "")
