"""Landmarks in the SP-ESKF (corners, stance ankle) and the stance detector: known answers."""

from __future__ import annotations

import numpy as np
import pytest

from vio_graph.errors import EstimationError
from vio_graph.filter import FilterConfig, SagittalEskf
from vio_graph.filter.stance import StanceDetector
from vio_graph.geometry import GRAVITY_MPS2, cross3
from vio_graph.types import Displacement2D, ImuSample, LandmarkKey

UPRIGHT = np.array([1.0, 0.0, 0.0, 0.0])
LANDMARK_XZ_M = np.array([0.8, -0.3])


def _static_imu(t: float, bias_x_mps2: float = 0.0) -> ImuSample:
    """An upright IMU at rest (true camera fixed at the origin), with an x bias."""
    return ImuSample(t, np.array([bias_x_mps2, 0.0, GRAVITY_MPS2]), np.zeros(3), UPRIGHT)


def _run(with_landmark: bool, duration_s: float = 3.0) -> tuple[SagittalEskf, float]:
    """Camera at rest, biased accelerometer (0.2 m/s^2 in x), a corner seen every 1/30 s."""
    f = SagittalEskf(FilterConfig(init_accel_bias_sigma_mps2=1e-3))
    f.initialise(0.0, (0.0, 0.0), P0=np.diag([1e-4, 1e-4, 1e-4, 1e-4, 1e-6, 1e-6, 1e-6, 1e-6]))
    max_err = 0.0
    for k in range(1, int(duration_s * 100) + 1):
        t = k / 100.0
        f.propagate(_static_imu(t, 0.2))
        if with_landmark and k % 3 == 0:
            f.update_landmark(LandmarkKey("corner", 0), LANDMARK_XZ_M, np.eye(2) * 1e-6, t)
        max_err = max(max_err, float(np.linalg.norm(f.state.p_xz_m)))
    return f, max_err


def test_landmark_bounds_drift_of_a_biased_imu() -> None:
    _, err_free = _run(with_landmark=False)
    f, err_lm = _run(with_landmark=True)
    # dead reckoning: 0.5 * 0.2 * 3^2 = 0.9 m; with the corner in view a few mm at most
    assert err_free == pytest.approx(0.9, rel=0.05)
    assert err_lm < 0.01
    assert np.allclose(f.landmark_xz(LandmarkKey("corner", 0)), LANDMARK_XZ_M, atol=0.01)


def test_first_sight_augments_with_position_uncertainty_and_drop_marginalises() -> None:
    f = SagittalEskf()
    f.initialise(0.0, (1.0, 2.0))
    n0 = f._P.shape[0]
    P_pp = f.state.cov_position_m2
    V = np.diag([4e-4, 1e-4])
    assert f.update_landmark("L", (0.5, -0.2), V) is False  # first sight: no information
    assert np.allclose(f.landmark_xz("L"), [1.5, 1.8])
    i = n0
    assert np.allclose(f._P[i : i + 2, i : i + 2], P_pp + V)
    assert np.allclose(f._P[0:2, i : i + 2], P_pp)  # correlated with the position error
    assert f.landmark_keys == ("L",)
    # a second, consistent sight does not move the state
    assert f.update_landmark("L", (0.5, -0.2), V) is True
    assert np.allclose(f.state.p_xz_m, [1.0, 2.0])
    f.drop_landmark("L")
    assert f._P.shape[0] == n0 and f.landmark_keys == ()
    with pytest.raises(EstimationError):
        f.landmark_xz("L")


def test_landmark_and_clone_coexist_with_displacements() -> None:
    """A displacement after a landmark is still fused against the clone (block order)."""
    f = SagittalEskf()
    f.initialise(0.0, (0.0, 0.0))
    f.update_landmark("L", (1.0, 0.0), np.eye(2) * 1e-4)
    for k in range(1, 4):
        f.propagate(_static_imu(k / 100.0))
    assert f.update_displacement(Displacement2D(0.0, 0.03, np.zeros(2), np.eye(2) * 1e-6))
    assert f.update_landmark("L", (1.0, 0.0), np.eye(2) * 1e-4, 0.03)
    assert np.allclose(f.state.p_xz_m, 0.0, atol=1e-3)


def test_stance_detector_quiet_at_rest_and_not_in_swing() -> None:
    ankle_in_imu = np.array([0.0, 0.0, -0.3])
    d = StanceDetector(ankle_in_imu, accel_threshold_mps2=1.0, window_s=0.1)
    R = np.eye(2)
    g = (0.0, -GRAVITY_MPS2)
    for k in range(20):  # at rest
        d.add_imu(k / 100.0, (0.0, 0.0, GRAVITY_MPS2), np.zeros(3), R, g)
    assert d.quiet()
    # shank rotating about the ANKLE at a constant 2 rad/s (stance roll-over): the ankle
    # does not accelerate, so the IMU's centripetal term is exactly cancelled by the lever arm
    w = np.array([0.0, 2.0, 0.0])
    f_imu = np.array([0.0, 0.0, GRAVITY_MPS2]) - cross3(w, cross3(w, ankle_in_imu))
    for k in range(20, 40):
        d.add_imu(k / 100.0, f_imu, w, R, g)
    assert d.quiet()
    # swing: 3 m/s^2 forward acceleration
    for k in range(40, 45):
        d.add_imu(k / 100.0, (3.0, 0.0, GRAVITY_MPS2), np.zeros(3), R, g)
    assert not d.quiet()


def test_cross3_matches_numpy() -> None:
    rng = np.random.default_rng(3)
    for _ in range(100):
        a, b = rng.normal(size=3), rng.normal(size=3)
        assert np.array_equal(cross3(a, b), np.cross(a, b))


def test_ungated_landmark_accepts_what_the_gate_rejects() -> None:
    """Stance anchors are fused without the gate (FilterConfig.stance_gate=False)."""
    for gate, expected in ((True, False), (False, True)):
        f = SagittalEskf()
        f.initialise(0.0, (0.0, 0.0))
        f.update_landmark("A", (0.0, -0.4), np.eye(2) * 1e-6)
        # 20 cm inconsistent with a 1 mm state: far outside the 99.9 % gate
        assert f.update_landmark("A", (-0.2, -0.4), np.eye(2) * 1e-6, gate=gate) is expected


def test_a_corner_seen_again_under_a_new_track_is_the_same_landmark() -> None:
    """The swinging shank looks at one nosing, another, then the first again; the front end
    gives the reappearance a new track id. Within corner_reidentify_radius_m of a remembered
    corner (and clearly nearest) it is re-identified; far away or ambiguous it is new."""
    from vio_graph.filter.corner_landmarks import CornerLandmarks
    from vio_graph.types import CornerObservation

    fc = FilterConfig()
    f = SagittalEskf(fc)
    f.initialise(0.0, np.zeros(2))
    camera = f.state.p_xz_m
    corners = CornerLandmarks(
        fc.corner_reidentify_radius_m, fc.corner_memory_s, fc.max_corner_landmarks
    )
    cov = np.eye(2) * 1e-4

    def obs(track: int, rel) -> CornerObservation:
        return CornerObservation(0.0, track, np.asarray(rel, float), cov)

    # two remembered nosings one stair step apart (0.28 m, 0.147 m)
    assert corners.key(obs(1, [0.50, -0.40]), camera, f) == LandmarkKey("corner", 1)
    f.update_landmark(LandmarkKey("corner", 1), [0.50, -0.40], cov, 0.0)
    assert corners.key(obs(2, [0.78, -0.253]), camera, f) == LandmarkKey("corner", 2)
    f.update_landmark(LandmarkKey("corner", 2), [0.78, -0.253], cov, 0.0)
    # track 3 sees nosing 1 again, 3 cm off: re-identified, and stays so for the track
    assert corners.key(obs(3, [0.53, -0.40]), camera, f) == LandmarkKey("corner", 1)
    assert corners.key(obs(3, [0.70, -0.30]), camera, f) == LandmarkKey("corner", 1)
    # a corner 20 cm from both: new
    assert corners.key(obs(4, [0.64, -0.20]), camera, f) == LandmarkKey("corner", 4)
    # switched off: every track is new
    off = CornerLandmarks(None, fc.corner_memory_s, fc.max_corner_landmarks)
    assert off.key(obs(5, [0.50, -0.40]), camera, f) == LandmarkKey("corner", 5)


def test_velocity_observation_corrects_a_velocity_error_and_is_gated() -> None:
    """The still ankle's velocity (update_velocity): one observation removes most of a 1 m/s
    error when the filter admits its velocity is uncertain; a confident filter gates it out
    unless told not to."""
    f = SagittalEskf()
    f.initialise(0.0, (0.0, 0.0), v_xz=(1.0, 0.0), P0=np.diag([1e-4, 1e-4, 1.0, 1.0] + [1e-6] * 4))
    assert f.update_velocity((0.0, 0.0), np.eye(2) * 0.05**2, 0.0) is True
    assert np.linalg.norm(f.state.v_xz_mps) < 0.01
    assert f.state.P[2, 2] < 0.05**2
    g = SagittalEskf()
    g.initialise(0.0, (0.0, 0.0), v_xz=(1.0, 0.0), P0=np.diag([1e-4] * 4 + [1e-6] * 4))
    assert g.update_velocity((0.0, 0.0), np.eye(2) * 0.05**2, 0.0) is False
    assert g.state.v_xz_mps[0] == pytest.approx(1.0)
    assert g.update_velocity((0.0, 0.0), np.eye(2) * 0.05**2, 0.0, gate=False) is True
    # the Kalman gain of a 1 cm/s state against a 5 cm/s observation
    assert g.state.v_xz_mps[0] == pytest.approx(1.0 - 1e-4 / (1e-4 + 0.05**2))


@pytest.mark.parametrize("at_frame", [False, True])
def test_filter_starts_at_the_first_frame_when_asked(at_frame: bool) -> None:
    """filter.start_at_first_frame: the filter's origin is the first depth frame (no IMU
    interval before it whose velocity a later update could re-write), else the first IMU
    sample, propagated to the frame."""
    from tests.conftest import tiny_metadata, tiny_streams
    from vio_graph.config import PipelineConfig
    from vio_graph.estimator import OnlineEstimator, RigGeometry
    from vio_graph.types import DepthFrame

    meta = tiny_metadata()
    imu, _, _, t_frames, frames = tiny_streams(meta)
    base = PipelineConfig()
    cfg = base.model_copy(
        update={"filter": base.filter.model_copy(update={"start_at_first_frame": at_frame})}
    )
    est = OnlineEstimator(cfg, RigGeometry.from_metadata(meta))
    t_frame = float(t_frames[1])  # the first frame comes 1/30 s in: 3 IMU samples before it
    for i in range(imu.timestamp_s.size):
        if imu.timestamp_s[i] > t_frame:
            break
        est.add_imu(
            ImuSample(imu.timestamp_s[i], imu.accel_mps2[i], imu.gyro_radps[i], imu.quat_wxyz[i])
        )
    assert est._filter_started is (not at_frame)
    depth, conf = frames[1]
    est.add_frame(DepthFrame(0, t_frame, depth, conf))
    state = est.filter.state
    expected_t = t_frame if at_frame else float(imu.timestamp_s[imu.timestamp_s <= t_frame][-1])
    assert state.timestamp_s == pytest.approx(expected_t)
    if at_frame:
        assert np.allclose(state.p_xz_m, 0.0) and np.allclose(state.v_xz_mps, 0.0)


def test_dropping_a_middle_landmark_keeps_the_other_blocks_exactly() -> None:
    """Marginalising a block between others removes its two rows and columns and copies the
    rest bit for bit, C-ordered (the np.ix_ gather it replaces), on a correlated covariance."""
    f = SagittalEskf()
    f.initialise(0.0, (0.0, 0.0))
    for j, xz in enumerate([(0.5, -0.2), (0.9, -0.3), (1.2, 0.1)]):
        f.update_landmark(f"L{j}", xz, np.eye(2) * 1e-4)
        f.propagate(_static_imu(0.01 * (j + 1)))
        f.update_landmark(f"L{j}", np.add(xz, 1e-3), np.eye(2) * 1e-4, 0.01 * (j + 1))
    P = f._P.copy()
    i = f._aug_index("L1")
    keep = np.r_[0:i, i + 2 : P.shape[0]]
    f.drop_landmark("L1")
    assert np.array_equal(f._P, P[np.ix_(keep, keep)]) and f._P.flags.c_contiguous
    assert f.landmark_keys == ("L0", "L2") and np.any(P[0:2, i : i + 2])


def _corner_chain_x_error(extra_sigma_m: float) -> float:
    """Camera moving at 0.5 m/s; visual displacements each 0.3 mm long in x (claimed 1.4 mm:
    a slow visual-odometry drift); a new corner every 0.3 m, seen for 1 s from 0.6 m to
    0.1 m ahead with 1 mm errors, weighted like the estimator does it (the front end's
    1 cm edge sigma, plus ``extra_sigma_m`` in quadrature). Returns the final x error (m)."""
    rng = np.random.default_rng(3)
    f = SagittalEskf(FilterConfig(init_accel_bias_sigma_mps2=1e-3))
    v = 0.5
    f.initialise(0.0, (0.0, 0.0), (v, 0.0))
    edge_cov = np.eye(2) * 0.01**2 + np.eye(2) * extra_sigma_m**2
    disp_cov = np.eye(2) * 0.0014**2
    corners = np.arange(0.6, 20.0, 0.3)
    t_prev = 0.0
    for k in range(1, 30 * 20 + 1):
        t = k / 30.0
        for j in range(1, 4):  # 100 Hz IMU at constant velocity
            f.propagate(_static_imu(t_prev + j * (t - t_prev) / 3))
        x = v * t
        d = Displacement2D(t_prev, t, np.array([v * (t - t_prev) + 3e-4, 0.0]), disp_cov)
        f.update_displacement(d)
        ahead = corners[(corners - x > 0.1) & (corners - x < 0.6)]
        if ahead.size:
            c = float(ahead[0])  # one corner a frame, the nearest
            rel = np.array([c - x, -0.3]) + rng.normal(0.0, 0.001, 2)
            f.update_landmark(LandmarkKey("corner", int(round(c * 10))), rel, edge_cov, t)
        for key in f.landmark_keys:  # forget corners behind the camera
            if key.id / 10 < x + 0.1 and key.id / 10 != (float(ahead[0]) if ahead.size else -1):
                f.drop_landmark(key)
        t_prev = t
    return abs(float(f.state.p_xz_m[0]) - v * t_prev)


def test_corner_landmarks_hold_x_against_visual_odometry_drift() -> None:
    """The corner chain hands x from corner to corner; with the filter's earlier extra 1 cm
    on top of the front end's corner sigma the displacements' drift carried x instead
    (the 2-minute ascent, docs/method.md section 2). Without any corner the drift is 18 cm;
    here 6.9 cm with the front end's sigma alone, 9.9 cm with the extra 1 cm."""
    err_default = _corner_chain_x_error(FilterConfig().corner_landmark_sigma_m)
    err_extra = _corner_chain_x_error(0.01)
    assert FilterConfig().corner_landmark_sigma_m == 0.0
    assert err_default < 0.08
    assert err_default < 0.8 * err_extra


def test_landmark_lookups_by_kind_and_key_agree_with_landmark_keys() -> None:
    """landmark_keys_of_kind and has_landmark (the landmark memories' per-frame lookups)
    give what filtering ``landmark_keys`` gives, with the clone and other kinds in the state,
    before and after a landmark in the middle is dropped."""
    f = SagittalEskf()
    f.initialise(0.0, (0.0, 0.0))
    keys = [LandmarkKey("corner", 3), LandmarkKey("level", 1), LandmarkKey("corner", 1)]
    keys.append(LandmarkKey("ankle", 0))
    f.clone_position(0.0)
    for j, key in enumerate(keys):
        f.update_landmark(key, (0.1 * j, -0.2), np.eye(2) * 1e-4)
    for dropped in (None, keys[0]):
        if dropped is not None:
            f.drop_landmark(dropped)
        for kind in ("corner", "level", "ankle"):
            want = [k for k in f.landmark_keys if k.kind == kind]
            assert f.landmark_keys_of_kind(kind) == want
        for key in [*keys, LandmarkKey("corner", 9)]:
            assert f.has_landmark(key) == (key in f.landmark_keys)
    assert f.landmark_keys_of_kind("corner") == [LandmarkKey("corner", 1)]
    assert not f.has_landmark("clone")  # the clone is not a landmark
