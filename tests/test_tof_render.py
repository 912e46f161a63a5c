"""The ToF renderer's fast path against its reference form, bit for bit.

``TofCamera.render`` computes the 3-vector dot products and norms with explicit sums, the
3x3 min / max filter over shifted views and the float32 rays in place (to render a frame in
less time); recordings and everything evaluated on them depend on those images, so the fast
form must give the very same depth and confidence as the plain form it replaced, kept here
as ``_reference_render`` (``cast`` + numpy reductions + scipy.ndimage filters).
"""

from __future__ import annotations

import numpy as np
import pytest
from scipy.ndimage import maximum_filter, minimum_filter

from vio_graph.sim import load_scenario
from vio_graph.sim.tof import TofCamera, _extremes_3x3, axial_sigma_m
from vio_graph.sim.trial import _STREAMS, simulate_trial


def _reference_render(cam: TofCamera, position_m, R_world_cam, rng: np.random.Generator):
    """The renderer as it was written before the fast path (same draws, same order)."""
    c = cam.cfg
    u, v = cam._u, cam._v
    if c.noise and c.lateral_noise_px > 0:
        u = u + rng.normal(0, c.lateral_noise_px, u.shape)
        v = v + rng.normal(0, c.lateral_noise_px, v.shape)
    z, n_w, d_c = cam.cast(np.asarray(position_m, float), R_world_cam, u, v)
    hit = np.isfinite(z)
    z_true = np.where(hit, z, 0.0)
    d_w = d_c @ np.asarray(R_world_cam).T
    cos_inc = np.abs(np.sum(n_w * d_w, axis=-1)) / np.linalg.norm(d_w, axis=-1)
    incidence = np.arccos(np.clip(cos_inc, 0.0, 1.0))
    z = np.where(hit, z, 0.0)
    if c.noise:
        far = np.where(hit, z, 10.0)
        zmax, zmin = maximum_filter(far, size=3), minimum_filter(far, size=3)
        mixed = hit & (zmax - zmin > c.mixed_pixel_jump_m)
        mixed &= rng.random(z.shape) < c.mixed_pixel_probability
        w = rng.random(z.shape)
        z = np.where(mixed, w * zmin + (1 - w) * zmax, z)
    sigma = axial_sigma_m(z, incidence, c.axial_coeffs)
    if c.noise:
        z = z + sigma * rng.standard_normal(z.shape)
    valid = hit & (incidence < np.radians(c.max_incidence_deg)) & (sigma < c.max_noise_m)
    rng_m = z * np.linalg.norm(d_c, axis=-1)
    valid &= (rng_m >= c.min_range_m) & (rng_m <= c.max_range_m)
    if c.noise:
        valid &= ~cam._flying(np.where(valid, z, 0.0))
    if c.edge_gap_m is not None:
        band = cam.edge_gap_mask(
            np.asarray(position_m, float),
            R_world_cam,
            d_c,
            z_true,
            n_w,
            rng.uniform(*c.edge_gap_m, cam._terrain.edges_xz_m.shape[0]),
        )
        valid &= ~band
    depth = np.where(valid, z, 0.0).astype(np.float32)
    conf = np.where(valid, np.clip(np.round(255 * (1 - sigma / c.max_noise_m)), 1, 255), 0)
    return depth, conf.astype(np.uint8)


def _trial(scenario: str, seed: int, **camera):
    cfg = load_scenario(scenario)
    cfg = cfg.model_copy(update={"duration_s": 3.0, "camera": cfg.camera.model_copy(update=camera)})
    return simulate_trial(cfg, seed)


@pytest.mark.parametrize(
    ("scenario", "seed", "camera"),
    [
        ("upstair", 1, {}),
        ("upstair_long", 2, {}),
        ("downstair", 3, {}),
        ("obstacle", 4, {}),
        ("level", 5, {}),
        ("upstair", 6, {"noise": False}),
        ("upstair", 7, {"edge_gap_m": (0.005, 0.02)}),
        ("downstair", 8, {"lateral_noise_px": 0.0, "mixed_pixel_probability": 1.0}),
    ],
)
def test_render_equals_reference_bit_for_bit(scenario: str, seed: int, camera: dict) -> None:
    trial = _trial(scenario, seed, **camera)
    cam = trial.camera
    frames = np.linspace(0, trial.n_frames - 1, 12).astype(int)
    n_valid = 0
    for i in frames:
        pos, R = trial.camera_position_m[i], trial.R_world_cam[i]
        seed_seq = [seed, _STREAMS.index("tof"), int(i)]
        depth, conf = cam.render(pos, R, np.random.default_rng(seed_seq))
        ref_depth, ref_conf = _reference_render(cam, pos, R, np.random.default_rng(seed_seq))
        assert depth.dtype == np.float32 and conf.dtype == np.uint8
        np.testing.assert_array_equal(depth.view(np.uint32), ref_depth.view(np.uint32))
        np.testing.assert_array_equal(conf, ref_conf)
        n_valid += int(np.count_nonzero(depth))
    assert n_valid > 0.3 * frames.size * depth.size  # the frames do see the terrain


def test_render_frame_in_trial_matches_reference() -> None:
    """The frames a recording is written from (trial.render_frame: its own seeded stream)."""
    trial = _trial("upstair", 11)
    for i in (0, trial.n_frames // 2, trial.n_frames - 1):
        depth, conf = trial.render_frame(i)
        rng = np.random.default_rng([11, _STREAMS.index("tof"), int(trial.frame_source_index[i])])
        ref = _reference_render(trial.camera, trial.camera_position_m[i], trial.R_world_cam[i], rng)
        np.testing.assert_array_equal(depth, ref[0])
        np.testing.assert_array_equal(conf, ref[1])


def test_extremes_3x3_equal_scipy_filters() -> None:
    rng = np.random.default_rng(0)
    for shape in ((172, 224), (1, 5), (4, 1), (3, 3)):
        a = np.round(rng.normal(size=shape), 1)  # many ties
        a[rng.random(shape) < 0.1] = 10.0
        zmax, zmin = _extremes_3x3(a)
        np.testing.assert_array_equal(zmax, maximum_filter(a, size=3))
        np.testing.assert_array_equal(zmin, minimum_filter(a, size=3))
