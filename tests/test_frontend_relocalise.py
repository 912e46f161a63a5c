"""Lost-track search (TrackerConfig.relocalise_after_frames): when the IMU prediction that
seeds ICP has gone wrong, the unseeded search finds the displacement again, refuses to guess
on a profile that repeats within its reach, and leaves a floor's slide unclaimed."""

from __future__ import annotations

import numpy as np

from vio_graph.frontend.config import IcpConfig, TrackerConfig
from vio_graph.frontend.smoothing import smooth_profile
from vio_graph.frontend.synthetic import raycast_profile, stair_polyline
from vio_graph.frontend.tracker import CornerTracker

STAIRS = stair_polyline("stair_up", start_x_m=0.6, n_steps=6)  # rise 0.147, tread 0.28
DT = 1 / 30
STEP = np.array([0.05, 0.03])  # camera displacement per frame (1.7 m/s along the stair)
WRONG = np.array([-0.12, -0.10])  # what a diverged IMU prediction adds to it


def _stair_view(camera_xz: np.ndarray, seed: int) -> np.ndarray:
    """Smoothed stair profile seen from ``camera_xz`` (points relative to the camera)."""
    prof = raycast_profile(
        STAIRS,
        camera_xz,
        pitch_down_rad=0.6,
        fov_rad=1.0,
        n_rays=1200,
        noise_m=0.002,
        rng=np.random.default_rng(seed),
    )
    return smooth_profile(prof)


def _run(cfg: TrackerConfig, views, pred: np.ndarray):
    tracker = CornerTracker(cfg)
    tracker.update(0.0, views[0], None)
    return [
        tracker.update(k * DT, v, None, pred, np.eye(2) * 0.02**2)
        for k, v in enumerate(views[1:], start=1)
    ]


def test_a_diverged_prediction_loses_the_track_and_the_search_finds_it_again() -> None:
    c0 = np.array([0.2, 0.55])
    views = [_stair_view(c0 + k * STEP, seed=k) for k in range(5)]
    pred = STEP + WRONG  # 16 cm off: beyond ICP's reach from the seed
    off = _run(TrackerConfig(relocalise_after_frames=None), views, pred)
    assert all(o.displacement is None for o in off)  # the premise: lost for good
    on = _run(TrackerConfig(relocalise_after_frames=2), views, pred)
    assert [o.displacement is None for o in on] == [True, True, False, False]
    for o in on[2:]:
        assert o.relocalised and o.reason is None
        d = o.displacement
        assert d is not None
        assert np.abs(d.delta_xz_m - STEP).max() < 0.004  # metres, against the truth
        assert np.sqrt(np.linalg.eigvalsh(d.cov_m2)).max() < 0.01  # a real measurement


def test_the_search_starts_at_the_first_failure_with_zero_frames() -> None:
    c0 = np.array([0.2, 0.55])
    views = [_stair_view(c0 + k * STEP, seed=10 + k) for k in range(3)]
    on = _run(TrackerConfig(relocalise_after_frames=0), views, STEP + WRONG)
    assert all(o.relocalised and o.displacement is not None for o in on)


def test_a_seeded_result_is_not_replaced_by_the_search() -> None:
    c0 = np.array([0.2, 0.55])
    views = [_stair_view(c0 + k * STEP, seed=20 + k) for k in range(3)]
    on = _run(TrackerConfig(relocalise_after_frames=0), views, STEP + 0.003)
    assert all(o.displacement is not None and not o.relocalised for o in on)


def _comb(camera_xz: np.ndarray, seed: int) -> np.ndarray:
    """A corrugated floor (triangle wave, 6 cm period, 3 cm deep) seen from ``camera_xz``:
    every shift by one period fits as well as the true one."""
    rng = np.random.default_rng(seed)
    x = np.arange(0.3, 1.2, 0.002) + camera_xz[0]
    z = np.abs(np.mod(x, 0.06) - 0.03)
    pts = np.column_stack([x, z + rng.normal(0.0, 0.001, x.size)])
    return pts - camera_xz


def test_a_profile_that_repeats_within_reach_is_ambiguous_and_gives_nothing() -> None:
    c0 = np.array([0.0, 0.5])
    views = [_comb(c0 + k * STEP, seed=k) for k in range(3)]
    on = _run(TrackerConfig(relocalise_after_frames=0), views, STEP + WRONG)
    assert all(o.displacement is None and not o.relocalised for o in on)


def _floor(camera_xz: np.ndarray, seed: int) -> np.ndarray:
    rng = np.random.default_rng(seed)
    x = np.linspace(0.2, 1.0, 400) + camera_xz[0]
    return np.column_stack([x, rng.normal(0.0, 0.002, x.size)]) - camera_xz


def test_on_a_floor_the_search_measures_z_and_claims_no_x() -> None:
    c0 = np.array([0.0, 0.5])
    views = [_floor(c0 + k * STEP, seed=k) for k in range(3)]
    on = _run(TrackerConfig(relocalise_after_frames=0), views, STEP + WRONG)
    for o in on:
        assert o.relocalised and o.displacement is not None
        d = o.displacement
        assert abs(d.delta_xz_m[1] - STEP[1]) < 0.002
        assert d.cov_m2[0, 0] > 0.99 * IcpConfig().max_variance_m2  # x: unobservable


def _with_unseen(view: np.ndarray) -> np.ndarray:
    """``view`` with two copies of it 1.5 and 3 m lower: surfaces the previous frame did not
    see, so that a third of the profile can be registered."""
    return np.vstack([view, view - [0.0, 1.5], view - [0.0, 3.0]])


def test_an_answer_that_registers_a_minority_of_the_profile_is_refused() -> None:
    c0 = np.array([0.2, 0.55])
    views = [_stair_view(c0, seed=30), _with_unseen(_stair_view(c0 + STEP, 31))]
    lenient = TrackerConfig(relocalise_after_frames=0, relocalise_min_share=0.05)
    found = _run(lenient, views, STEP + WRONG)[0]
    assert found.relocalised and found.displacement is not None  # it registers ...
    assert np.abs(found.displacement.delta_xz_m - STEP).max() < 0.004
    strict = _run(TrackerConfig(relocalise_after_frames=0), views, STEP + WRONG)[0]
    assert strict.displacement is None and not strict.relocalised  # ... a third of it


def test_an_imu_prediction_as_well_supported_as_the_answer_rivals_it() -> None:
    from scipy.spatial import cKDTree

    from vio_graph.frontend.tracker import Displacement2D, _Search

    c0 = np.array([0.0, 0.5])
    prev, cur = _comb(c0, seed=1), _comb(c0 + STEP, seed=2)
    tree = cKDTree(prev)
    answer = _Search(Displacement2D(0.0, DT, STEP, np.eye(2) * 1e-6), None, cur.shape[0], tree, cur)
    tracker = CornerTracker(TrackerConfig(relocalise_after_frames=0))
    cov = np.eye(2) * 0.002**2
    period = np.array([0.06, 0.0])  # the comb repeats: the prediction fits as well
    assert tracker._prediction_rivals(answer, STEP + period, cov)
    assert not tracker._prediction_rivals(answer, STEP + WRONG, cov)  # fits nothing
    assert not tracker._prediction_rivals(answer, STEP + 0.001, cov)  # the same answer
