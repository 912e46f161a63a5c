"""Pixels that move with the camera (an occluding foot close to the lens) are no terrain."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

from vio_graph.config import PipelineConfig
from vio_graph.frontend import VisualFrontend
from vio_graph.frontend.camera_fixed import (
    CameraFixedFilter,
    OnsetTracker,
    motion_from_ground,
    motion_from_ground_reference,
)
from vio_graph.frontend.config import FrontendConfig
from vio_graph.frontend.synthetic import (
    camera_rotation,
    pico_flexx_K,
    render_depth,
    stair_polyline,
)
from vio_graph.health import HealthMonitor
from vio_graph.types import DepthFrame

K = pico_flexx_K()
POLY = stair_polyline("stair_up", start_x_m=0.5)
SIGMA_M = 0.003


def _blob(shape: tuple[int, int]) -> tuple[np.ndarray, np.ndarray]:
    """The simulator's occluder (vio_graph/sim/faults.py): an elliptic dome over the lower
    centre of the image, 0.25 m from the lens at its top, 4 cm deeper at its rim."""
    h, w = shape
    v, u = np.mgrid[0:h, 0:w]
    r2 = ((u - 0.5 * w) / (0.45 * w)) ** 2 + ((v - 0.8 * h) / (0.3 * h)) ** 2
    return r2 < 1.0, 0.25 + 0.04 * r2


def _frame(cam_xz, pitch_rad: float, seed: int, blob: bool = True):
    rng = np.random.default_rng(seed)
    R = camera_rotation(pitch_rad)
    depth, conf = render_depth(POLY, np.asarray(cam_xz, float), R, K, noise_m=0.002, rng=rng)
    inside = np.zeros(depth.shape, dtype=bool)
    if blob:
        inside, z = _blob(depth.shape)
        z = z + rng.normal(0.0, 0.002, z.shape)
        depth = np.where(inside, z, depth).astype(np.float32)
        conf = np.where(inside, 200, conf).astype(np.uint8)
    return depth, conf, R, inside


# a swing: 4 cm forward, 1 cm up and 5 degrees of pitch between two frames at 30 fps
POSE_A = ((0.0, 0.45), 0.60)
POSE_B = ((0.04, 0.46), 0.55)
COV = np.eye(2) * 0.0015**2


def _update(f: CameraFixedFilter, frame, delta) -> np.ndarray:
    depth, conf, R, _ = frame
    return f.update(depth, conf > 0, K, R, np.asarray(delta, float), COV, SIGMA_M, 0.005)


def test_a_blob_that_moves_with_the_camera_is_found_and_terrain_is_not() -> None:
    a, b = _frame(*POSE_A, seed=1), _frame(*POSE_B, seed=2)
    f = CameraFixedFilter()
    assert not _update(f, a, [0.0, 0.0]).any()  # first frame: nothing to compare with
    mask = _update(f, b, np.subtract(POSE_B[0], POSE_A[0]))
    inside, valid = b[3], b[0] > 0
    assert mask[inside].mean() > 0.99
    assert not mask[valid & ~inside].any()


def test_without_motion_nothing_is_new_but_a_found_blob_stays_out() -> None:
    a, b = _frame(*POSE_A, seed=1), _frame(*POSE_B, seed=2)
    c = _frame(*POSE_B, seed=3)  # stance: the camera stays where it was
    # a camera that does not move cannot tell the blob from terrain: nothing is removed
    still = CameraFixedFilter()
    _update(still, b, [0.0, 0.0])
    assert not _update(still, c, [0.0, 0.0]).any()
    # once seen to move with the camera, the blob stays out while its depth does not change
    f = CameraFixedFilter()
    _update(f, a, [0.0, 0.0])
    _update(f, b, np.subtract(POSE_B[0], POSE_A[0]))
    mask = _update(f, c, [0.0, 0.0])
    inside, valid = c[3], c[0] > 0
    assert mask[inside].mean() > 0.99
    assert not mask[valid & ~inside].any()
    # the blob leaves the view: its pixels are terrain again
    d = _frame(*POSE_B, seed=4, blob=False)
    assert not _update(f, d, [0.0, 0.0]).any()


def test_occlusion_onset_status_per_pixel() -> None:
    """Known answers of OnsetTracker (speckle agreement 3 % + 1 cm, 3 of them for a drop; the
    status survives 6 sigma of noise): first valid = onset; a 20 cm drop from 1 m = onset; a
    mm of noise keeps it; a 5 cm change (terrain moving under the camera) ends it; an invalid
    frame changes nothing (a ToF gap makes no onset)."""
    t = OnsetTracker(3.0, 0.03, 0.01, 6.0)
    d0 = np.array([[1.0, 1.0, 1.0, 0.0]])
    assert t.update(d0, SIGMA_M).tolist() == [[True, True, True, False]]
    assert t.update([[1.001, 0.95, 1.0, 0.0]], SIGMA_M).tolist() == [[True, False, True, False]]
    assert t.update([[1.0, 0.95, 0.8, 0.6]], SIGMA_M).tolist() == [[True, False, True, True]]
    gap = t.update(np.zeros((1, 4)), SIGMA_M).tolist()
    assert gap == [[True, False, True, True]]
    assert t.update([[1.0, 0.95, 0.8, 0.6]], SIGMA_M).tolist() == [[True, False, True, True]]
    assert t.update([[1.05, 0.5, 0.8, 0.6]], SIGMA_M).tolist() == [[False, True, True, True]]


def test_a_surface_without_an_occlusion_onset_is_not_removed() -> None:
    """The blob's pixels pass the camera-fixed test on the third frame, but their depth came
    there by 3 cm (a change terrain makes, not the drop of an object covering the terrain):
    with the onset requirement nothing is removed; without it the blob is, as is the blob
    that did drop onto the terrain (it entered the view on the second frame)."""
    a, b = _frame(*POSE_A, seed=1), _frame(*POSE_B, seed=2)
    inside = b[3]
    early = (np.where(inside, a[0] + 0.03, a[0]).astype(np.float32), a[1], a[2], a[3])
    entering = _frame(*POSE_B, seed=5, blob=False)
    for onset, history, removed in (
        (3.0, early, False),
        (None, early, True),
        (3.0, entering, True),
    ):
        f = CameraFixedFilter(onset_drop_tols=onset)
        _update(f, history, [0.0, 0.0])
        _update(f, a, np.subtract(POSE_A[0], POSE_B[0]) if history is entering else [0, 0])
        mask = _update(f, b, np.subtract(POSE_B[0], POSE_A[0]))
        assert (mask[inside].mean() > 0.99) == removed
        assert not mask[~inside].any()


def test_confirm_frames_returns_a_blob_found_on_consecutive_frames_only() -> None:
    """With confirm_frames=2 the blob found on the swing frame is not returned yet, and is
    returned on the next frame, where it is held (stance); a detection that is not repeated
    (the blob gone on the next frame) is never returned."""
    a, b = _frame(*POSE_A, seed=1), _frame(*POSE_B, seed=2)
    c = _frame(*POSE_B, seed=3)
    gone = _frame(*POSE_B, seed=4, blob=False)
    for nxt, found in ((c, True), (gone, False)):
        f = CameraFixedFilter(confirm_frames=2)
        _update(f, a, [0.0, 0.0])
        assert not _update(f, b, np.subtract(POSE_B[0], POSE_A[0])).any()
        assert f.holding
        mask = _update(f, nxt, [0.0, 0.0])
        assert (mask[b[3]].mean() > 0.99) == found
        assert not mask[~b[3]].any()


def test_an_imu_that_reports_no_motion_removes_nothing() -> None:
    """The test needs the IMU to say the camera moved: with a zero prediction the blob is
    consistent with a static world, and terrain whose depth changed is never a candidate."""
    a, b = _frame(*POSE_A, seed=1), _frame(*POSE_B, seed=2)
    f = CameraFixedFilter()
    _update(f, a, [0.0, 0.0])
    b_unturned = (b[0], b[1], a[2], b[3])  # the IMU's attitude did not turn either
    assert not _update(f, b_unturned, [0.0, 0.0]).any()


def test_the_default_removes_and_the_shipped_configs_choose() -> None:
    from vio_graph.config import load_config

    default = PipelineConfig().frontend.camera_fixed
    assert default.enabled and default.drop_pixels and default.onset_drop_tols is not None
    configs = Path(__file__).resolve().parents[1] / "configs"
    assert load_config(configs / "camera_fixed.yaml").frontend.camera_fixed == default
    report = load_config(configs / "camera_fixed_report_only.yaml").frontend.camera_fixed
    assert report.enabled and not report.drop_pixels


def test_front_end_drops_the_near_lens_blob_from_the_profile() -> None:
    a, b = _frame(*POSE_A, seed=1), _frame(*POSE_B, seed=2)
    delta = np.subtract(POSE_B[0], POSE_A[0])
    profiles = {}
    for enabled in (True, False):
        cfg = FrontendConfig.model_validate(
            {"camera_fixed": {"drop_pixels": enabled, "idle_check_every_frames": 1}}
        )
        fe = VisualFrontend(cfg)
        fe.process(DepthFrame(0, 0.0, a[0], a[1]), K, a[2], None, None)
        res = fe.process(DepthFrame(1, 1 / 30, b[0], b[1]), K, b[2], delta, COV)
        profiles[enabled] = res.profile_xz_m
        assert res.n_camera_fixed > 1000  # found either way, dropped with drop_pixels
    near = {k: np.linalg.norm(p, axis=1) < 0.32 for k, p in profiles.items()}
    assert near[False].sum() > 20  # the blob is in the slice without the test ...
    assert not near[True].any()  # ... and gone with it
    assert len(profiles[True]) > 50  # the terrain beyond the blob is kept
    assert profiles[True][:, 0].max() > 0.5


@pytest.mark.parametrize("every", [1, 3])
def test_report_only_mode_tests_every_nth_frame_until_it_finds_a_surface(every: int) -> None:
    """Report-only (drop_pixels off): with no pixel held, only every ``every``-th frame is
    tested (the others are remembered as the previous image); once the blob is found,
    every frame is tested while it stays. The blob is in view from frame 0 (no previous
    frame): found at frame ``every`` (1 for every frame), then on every frame."""
    poses = [POSE_A if k % 2 == 0 else POSE_B for k in range(8)]
    frames = [_frame(*p, seed=k + 1) for k, p in enumerate(poses)]
    fe = VisualFrontend(
        FrontendConfig.model_validate(
            {"camera_fixed": {"drop_pixels": False, "idle_check_every_frames": every}}
        )
    )
    found = []
    for k, (depth, conf, R, _) in enumerate(frames):
        delta = None if k == 0 else np.subtract(poses[k][0], poses[k - 1][0])
        res = fe.process(DepthFrame(k, k / 30, depth, conf), K, R, delta, None if k == 0 else COV)
        found.append(res.n_camera_fixed > 1000)
    assert found == [k >= every for k in range(8)]


def test_health_reports_frames_with_camera_fixed_pixels() -> None:
    h = HealthMonitor()
    for k in range(10):
        h.add_frame(
            k / 30,
            np.array([0.01 * k, 0.0]),
            None,
            False,
            False,
            camera_fixed_pixels=500 if 3 <= k < 7 else 0,
        )
    rep = h.report()
    cf = rep["camera_fixed"]
    assert cf["frames"] == 4 and cf["max_pixels"] == 500
    assert cf["first_s"] == pytest.approx(0.1) and cf["longest_run_s"] == pytest.approx(0.1)
    assert any("moved with the camera" in w for w in rep["warnings"])
    clean = HealthMonitor()
    clean.add_frame(0.0, np.zeros(2), None, False, False)
    assert clean.report()["camera_fixed"]["frames"] == 0


def test_health_does_not_warn_on_camera_fixed_pixels_of_single_frames() -> None:
    """Detections that are not repeated on the next frame (the test's chance coincidences)
    are counted but not warned about; two consecutive frames are."""
    for pattern, warned in (({2, 6}, False), ({2, 3}, True)):
        h = HealthMonitor()
        for k in range(10):
            h.add_frame(
                k / 30,
                np.array([0.01 * k, 0.0]),
                None,
                False,
                False,
                camera_fixed_pixels=60 if k in pattern else 0,
            )
        rep = h.report()
        assert rep["camera_fixed"]["frames"] == 2
        assert rep["camera_fixed"]["longest_run_frames"] == (2 if warned else 1)
        assert any("moved with the camera" in w for w in rep["warnings"]) == warned


@pytest.fixture(scope="module")
def occluded_upstair(tmp_path_factory: pytest.TempPathFactory) -> Path:
    """The 4 s upstair trial of conftest.short_upstair (seed 3) with the simulator's
    occluding foot from 1 s to 2 s (a swing, then a stance)."""
    from vio_graph.sim import load_scenario, simulate

    cfg = load_scenario("upstair").model_copy(update={"duration_s": 4.0})
    faults = cfg.faults.model_copy(update={"occluder_start_s": 1.0, "occluder_duration_s": 1.0})
    cfg = cfg.model_copy(update={"faults": faults})
    return simulate(cfg, seed=3, out_dir=tmp_path_factory.mktemp("rec") / "occ")


def test_filter_error_over_an_occluding_foot_stays_bounded(
    occluded_upstair: Path, tmp_path: Path
) -> None:
    """Known answer: the true camera path. Without the camera-fixed test the filter's camera
    error reaches 6.4 cm in the occluded second and stays at 4.7 cm (toe ATE x 3.8 cm); the
    clean trial's error there is about 1 cm. With it: 2.3 cm at most, 1.4 cm after (toe ATE
    x 0.9 cm)."""
    from vio_graph.pipeline import run_recording
    from vio_graph.recording.reader import Recording
    from vio_graph.recording.tum import read_tum

    cfg = PipelineConfig()  # the removal is the default
    res = run_recording(
        occluded_upstair,
        tmp_path / "r",
        cfg,
        modes=("filter",),
        visualize=False,
        progress=False,
    )
    est = read_tum(tmp_path / "r" / "trajectories" / "filter_camera.tum")
    gt = Recording.open(occluded_upstair).groundtruth.trajectories["camera"]
    err = np.linalg.norm(est.xz_m - np.array([gt.xz_at(t) for t in est.timestamp_s]), axis=1)
    window = (est.timestamp_s >= 1.0) & (est.timestamp_s < 2.5)
    assert err[window].max() < 0.035
    assert err[est.timestamp_s >= 2.5].max() < 0.025
    cf = res.metrics["health"]["camera_fixed"]
    assert cf["frames"] > 20 and 0.9 < cf["first_s"] < 1.2 and 1.9 < cf["last_s"] < 2.1
    assert any("moved with the camera" in w for w in res.metrics["health"]["warnings"])


def test_report_only_mode_leaves_the_estimate_as_it_was(
    occluded_upstair: Path, tmp_path: Path
) -> None:
    """With drop_pixels off the camera-fixed pixels are counted and warned about, and the
    estimate is the one without the test; the default (removal) changes it."""
    from vio_graph.pipeline import run_recording

    metrics = {}
    for name, cf in (
        ("report", {"drop_pixels": False}),
        ("off", {"enabled": False, "drop_pixels": False}),
        ("default", {}),
    ):
        cfg = PipelineConfig.model_validate({"frontend": {"camera_fixed": cf}})
        metrics[name] = run_recording(
            occluded_upstair,
            tmp_path / name,
            cfg,
            modes=("filter",),
            visualize=False,
            progress=False,
        ).metrics
    for name in ("report", "default"):
        assert metrics[name]["health"]["camera_fixed"]["frames"] > 20
        assert any("moved with the camera" in w for w in metrics[name]["health"]["warnings"])
    assert metrics["off"]["health"]["camera_fixed"]["frames"] == 0
    assert metrics["report"]["ate_cm"]["filter"] == metrics["off"]["ate_cm"]["filter"]
    assert metrics["default"]["ate_cm"]["filter"] != metrics["off"]["ate_cm"]["filter"]


def test_compiled_surface_labels_and_rim_equal_scipys(monkeypatch: pytest.MonkeyPatch) -> None:
    """``compiled.label4`` numbers the 4-connected components as ``scipy.ndimage.label`` does
    (the same label image), :func:`dilate4` is ``binary_dilation`` with its default structure,
    and ``surface_majority`` on the kernels returns scipy's path's pixels: random masks of
    several densities (one component, many, none; touching the borders) and depth images
    with edges."""
    from scipy import ndimage

    from vio_graph.frontend import icp as icp_module
    from vio_graph.frontend.camera_fixed import dilate4, surface_majority

    monkeypatch.setenv(icp_module.COMPILED_ENV, "1")
    kernels = icp_module.compiled_kernels()
    assert kernels is not None
    rng = np.random.default_rng(5)
    n_kept = 0
    for case in range(60):
        h, w = int(rng.integers(1, 40)), int(rng.integers(1, 60))
        img = rng.random((h, w)) < [0.0, 0.2, 0.5, 0.6, 0.9, 1.0][case % 6]
        labels, n = kernels.label4(img)
        ref, n_ref = ndimage.label(img)
        assert n == n_ref and np.array_equal(labels, ref)
        assert np.array_equal(dilate4(img), ndimage.binary_dilation(img))
        depth = 1.0 + np.cumsum(rng.normal(0.0, 0.01, (h, w)), axis=1)
        depth[rng.random((h, w)) < 0.1] += 0.2  # depth edges
        same = rng.random((h, w)) < 0.8
        mask = same & (rng.random((h, w)) < 0.6)
        got = surface_majority(mask, depth, same, 0.03, 0.01, 5)
        monkeypatch.setenv(icp_module.COMPILED_ENV, "0")
        want = surface_majority(mask, depth, same, 0.03, 0.01, 5)
        monkeypatch.setenv(icp_module.COMPILED_ENV, "1")
        assert np.array_equal(got, want)
        n_kept += int(got.sum())
    assert n_kept > 0


#: two consecutive frames of a simulated step-to-step descent at 15 fps (held-out trial AA of
#: docs/generalisation.md, seed 12001, t = 11.77 -> 11.83 s, the shank starting its swing),
#: with the camera motion the filter predicted between them: the lower tread just past a
#: nosing, newly revealed as the camera rises, keeps its depth at the same pixels
DISOCCLUSION = Path(__file__).parent / "data" / "camera_fixed_disocclusion.npz"


@pytest.mark.parametrize("compiled", ["0", "1"])
def test_terrain_revealed_behind_a_nosing_is_not_taken_for_an_object(
    compiled: str, monkeypatch: pytest.MonkeyPatch
) -> None:
    """Before the occlusion rule the test refused 66 pixels here (a false 'something moved
    with the camera' warning on a clean trial): moved into the previous frame they land on
    the nosing in front of them or on the pixels the ToF filter dropped there. Hidden behind a
    surface that is itself world-static, they are no evidence, and fewer than one surface's
    ``min_pixels`` remain refused. (An object fixed to the lens is still found under this
    rule: test_a_blob_that_moves_with_the_camera_is_found_and_terrain_is_not.)"""
    from vio_graph.frontend import camera_fixed as cf

    monkeypatch.setenv("VIO_GRAPH_COMPILED", compiled)
    d = np.load(DISOCCLUSION)
    motion = cf.CameraMotion(
        d["R_prev_cur"], d["t_prev_cur_m"], d["t_cov_m2"], float(d["rot_sigma_rad"])
    )
    args = (d["depth_prev_m"], d["depth_cur_m"], d["candidates"], d["K"], motion)
    got = cf.camera_fixed_mask(*args, float(d["depth_sigma_m"]), float(d["k_sigma"]))
    want = cf.camera_fixed_mask_reference(*args, float(d["depth_sigma_m"]), float(d["k_sigma"]))
    assert np.array_equal(got, want)
    assert int(got.sum()) < CameraFixedFilter().min_pixels


def test_compiled_onset_tracker_equals_numpy(monkeypatch: pytest.MonkeyPatch) -> None:
    """``compiled.onset_update`` gives OnsetTracker's numpy status, last depths and counts
    (fresh onsets; onsets of unchanged depth) on random depth sequences (drops, rises, noise,
    invalid pixels: zero, NaN, inf and negative; float32 and float64 images)."""
    from vio_graph.frontend import icp as icp_module

    n_onsets = 0
    for dtype in (np.float32, np.float64):
        trackers, counts = {}, {}
        for mode in ("0", "1"):
            monkeypatch.setenv(icp_module.COMPILED_ENV, mode)
            if mode == "1":
                assert icp_module.compiled_kernels() is not None
            t = OnsetTracker(2.0, 0.03, 0.01, 6.0)
            counts[mode] = []
            run = np.random.default_rng(3)
            depth = run.uniform(0.2, 2.0, (30, 40))
            for _ in range(25):
                step = run.choice(
                    [0.0, 0.002, 0.03, -0.3], size=depth.shape, p=[0.5, 0.3, 0.1, 0.1]
                )
                depth = np.clip(depth + step * run.standard_normal(depth.shape) ** 2, 0.1, 3.0)
                img = np.where(run.random(depth.shape) < 0.1, 0.0, depth).astype(dtype)
                img[run.random(depth.shape) < 0.02] = np.nan
                img[run.random(depth.shape) < 0.01] = np.inf
                img[run.random(depth.shape) < 0.01] = -0.5
                t.update(img, 0.003, 0.013)
                counts[mode].append((t.n_fresh, t.n_same))
            trackers[mode] = t
        a, b = trackers["0"], trackers["1"]
        assert np.array_equal(a.onset, b.onset)
        assert np.array_equal(a._last, b._last, equal_nan=True)
        assert counts["0"] == counts["1"]
        assert min(c[0] for c in counts["0"][1:]) > 0 and min(c[1] for c in counts["0"][1:]) > 0
        n_onsets += int(a.onset.sum())
    assert 0 < n_onsets < 2 * 30 * 40


def test_frames_where_the_test_cannot_remove_a_pixel_are_skipped_with_the_same_masks() -> None:
    """A surface leaves only with onset_share x min_pixels pixels in the onset status whose
    depth stayed since the previous frame; the filter skips the test on frames with fewer
    such pixels in the whole image and returns what the test returns: the same masks as a
    filter that tests every frame, over terrain whose every depth rises by 3 cm a frame (no
    pixel keeps an onset: skipped), a blob entering the view, found, held through a stance,
    and leaving it."""
    a, b = _frame(*POSE_A, seed=1, blob=False), _frame(*POSE_B, seed=2, blob=False)
    risen = [
        (np.where(a[0] > 0, a[0] + dz, 0.0).astype(np.float32),) + a[1:] for dz in (0.03, 0.06)
    ]
    frames = [
        a,
        *risen,
        _frame(*POSE_A, seed=3),
        _frame(*POSE_B, seed=4),
        _frame(*POSE_B, seed=5),
        b,
    ]
    moves = [(0.0, 0.0)] * 4 + [np.subtract(POSE_B[0], POSE_A[0])] + [(0.0, 0.0)] * 2
    skipping, testing = CameraFixedFilter(), CameraFixedFilter(skip_unable=False)
    found = []
    for fr, delta in zip(frames, moves, strict=True):
        got, want = _update(skipping, fr, delta), _update(testing, fr, delta)
        assert np.array_equal(got, want)
        found.append(bool(got[fr[3]].mean() > 0.99) if fr[3].any() else bool(got.any()))
    assert found == [False, False, False, False, True, True, False]
    assert skipping.n_skipped >= 2 and testing.n_skipped == 0
    assert skipping.n_tested + skipping.n_skipped == len(frames)


def test_a_walk_whose_onset_pixels_all_pass_as_terrain_skips_the_full_test() -> None:
    """On a walk over clean terrain thousands of pixels keep their onset and their depth
    from frame to frame (surfaces whose depth the motion hardly changes), but the test run
    on those pixels alone refuses none: the full test is skipped, and the masks are the
    same as testing every frame, the blob that enters the view found as before."""
    poses = [POSE_A, POSE_B, POSE_A, POSE_B, POSE_A, POSE_B, POSE_B, POSE_A]
    blob = [False, False, False, False, True, True, True, False]
    frames = [
        _frame(*p, seed=10 + i, blob=b) for i, (p, b) in enumerate(zip(poses, blob, strict=True))
    ]
    skipping, testing = CameraFixedFilter(), CameraFixedFilter(skip_unable=False)
    found = []
    for i, fr in enumerate(frames):
        delta = [0.0, 0.0] if i == 0 else np.subtract(poses[i][0], poses[i - 1][0])
        got, want = _update(skipping, fr, delta), _update(testing, fr, delta)
        assert np.array_equal(got, want)
        found.append(bool(got.any()))
    assert found == [False] * 5 + [True, True, False]
    assert skipping.n_skipped >= 4 and testing.n_skipped == 0


def test_motion_from_ground_is_its_numpy_reference_bit_for_bit() -> None:
    """motion_from_ground (the small steps on Python floats) returns the floats of its numpy
    formulation: random rotations, displacements over eight orders of magnitude, shares as
    Python and numpy floats, zero and signed-zero entries, and non-finite inputs."""
    rng = np.random.default_rng(7)

    def rotation(v: np.ndarray) -> np.ndarray:
        a = float(np.linalg.norm(v))
        k = v / a
        K = np.array([[0.0, -k[2], k[1]], [k[2], 0.0, -k[0]], [-k[1], k[0], 0.0]])
        return np.eye(3) + np.sin(a) * K + (1.0 - np.cos(a)) * K @ K

    cases = []
    for i in range(400):
        Rp = rotation(rng.normal(size=3))
        Rc = Rp @ rotation(rng.normal(size=3) * 10.0 ** rng.uniform(-6, 0))
        delta = rng.normal(size=2) * 10.0 ** rng.uniform(-6, 1)
        A = rng.normal(size=(2, 2)) * 10.0 ** rng.uniform(-6, -1)
        cov = A @ A.T
        share = [0.0, 0.05, np.float64(0.02), np.sqrt(2.0) * 0.001 / 0.033][i % 4]
        cases.append((Rp, Rc, delta, cov, float(rng.uniform(0, 0.01)), share))
    Rp, Rc = cases[0][0], cases[0][1]
    cases += [
        (Rp, Rp, np.zeros(2), np.zeros((2, 2)), 0.0, 0.0),  # no motion: angle from 1.0
        (Rp, Rc, np.array([0.01, -0.0]), np.array([[1e-6, -0.0], [-0.0, 1e-6]]), 0.0, 0.1),
        (Rp, Rc, np.array([np.nan, 0.0]), np.eye(2), 0.0, 0.05),
        (Rp, Rc, np.array([np.inf, 0.0]), np.eye(2), 0.0, 0.05),
        (Rp, Rc, np.array([0.01, 0.02]), np.array([[np.inf, 0.0], [0.0, 1.0]]), 0.0, 0.0),
        (Rp, Rc, [0.01, 0.02], [[1e-6, 0.0], [0.0, 1e-6]], 0.001, 0.0),  # lists
    ]
    for args in cases:
        with np.errstate(invalid="ignore"):  # (the NaN and inf cases)
            got, want = motion_from_ground(*args), motion_from_ground_reference(*args)
        for a, b in zip(
            (got.R_prev_cur, got.t_prev_cur_m, got.t_cov_m2, got.rot_sigma_rad),
            (want.R_prev_cur, want.t_prev_cur_m, want.t_cov_m2, want.rot_sigma_rad),
            strict=True,
        ):
            assert np.asarray(a).tobytes() == np.asarray(b).tobytes()
