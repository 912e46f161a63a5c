"""Stance that cannot pin the estimate: vision arbitrates the stance hypothesis."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

from vio_graph.config import PipelineConfig
from vio_graph.filter.gating import chi2_2dof_quantile, chi2_quantile
from vio_graph.filter.stance import FootRotationTest, StanceConsistencyTest, StanceDetector
from vio_graph.pipeline import run_recording
from vio_graph.types import Displacement2D

FPS = 30.0
U_SHANK_M = np.array([-0.07, -0.38])  # ankle minus camera in the shank frame


def _lever(theta_rad: float) -> np.ndarray:
    c, s = np.cos(theta_rad), np.sin(theta_rad)
    return np.array([c * U_SHANK_M[0] + s * U_SHANK_M[1], -s * U_SHANK_M[0] + c * U_SHANK_M[1]])


def _run_test(ankle_xz_m, theta_rad, noise_m=0.001, seed=0) -> list[bool]:
    """Feed a StanceConsistencyTest the displacements a camera on this shank would see."""
    rng = np.random.default_rng(seed)
    test = StanceConsistencyTest(chi2_2dof_quantile(0.999), 0.002 * 0.39, 0.002)
    cov = np.eye(2) * noise_m**2
    out = []
    cam_prev = None
    for k, (ankle, th) in enumerate(zip(ankle_xz_m, theta_rad, strict=True)):
        lever = _lever(th)
        cam = np.asarray(ankle) - lever
        d = None
        if cam_prev is not None:
            delta = cam - cam_prev + rng.normal(0, noise_m, 2)
            d = Displacement2D((k - 1) / FPS, k / FPS, delta, cov)
        out.append(test.test(k / FPS, lever, d))
        cam_prev = cam
    return out


def test_a_still_ankle_passes_while_the_shank_turns() -> None:
    n = 90  # 3 s of stance with the shank rolling over the ankle by 30 deg
    theta = np.radians(np.linspace(-10, 20, n))
    ok = _run_test(np.zeros((n, 2)), theta)
    assert np.mean(ok) > 0.98


def test_a_slow_swing_is_refused_within_a_few_centimetres() -> None:
    """A swing at 0.1-0.3 m/s, slow enough that an acceleration detector calls it stance."""
    n = 45
    speed = np.linspace(0.1, 0.3, n)  # m/s along x, with a 1:3 rise
    ankle = np.cumsum(np.outer(speed / FPS, [0.95, 0.3]), axis=0)
    ok = _run_test(ankle, np.radians(np.linspace(0, 8, n)))
    first_refusal = ok.index(False)
    moved_cm = 100 * np.hypot(*(ankle[first_refusal] - ankle[0]))
    assert moved_cm < 3.0, moved_cm


def test_no_displacement_leaves_the_hypothesis_standing() -> None:
    test = StanceConsistencyTest(13.8, 0.001, 0.002)
    assert test.test(0.0, _lever(0.0), None)
    # a displacement that does not start at the previous frame cannot be tested either
    d = Displacement2D(0.5, 0.533, np.array([0.3, 0.0]), np.eye(2) * 1e-6)
    assert test.test(0.533, _lever(0.0), d)


def _config(**filter_fields) -> PipelineConfig:
    base = PipelineConfig()
    f = base.filter.model_copy(update=filter_fields)
    out = base.output.model_copy(update={"rerun": False, "plots": False})
    return base.model_copy(update={"filter": f, "output": out})


@pytest.mark.slow
def test_a_detector_that_flags_every_frame_cannot_pin_the_filter(
    short_upstair: Path, tmp_path: Path
) -> None:
    """The acceleration detector is made to call every frame a stance (threshold 100 m/s^2):
    without the vision test the anchor pins the ankle and the filter loses the trial; with it
    the estimate stays close to the default run's."""
    ate = {}
    for name, cfg in {
        "default": _config(),
        "always": _config(stance_accel_threshold_mps2=100.0),
        "always_untested": _config(
            stance_accel_threshold_mps2=100.0, stance_test=False, stance_gate=False
        ),
    }.items():
        res = run_recording(short_upstair, tmp_path / name, cfg, progress=False, visualize=False)
        toe = res.metrics["ate_cm"]["filter"]["toe"]
        ate[name] = max(toe["x"], toe["z"])
        if name == "always":
            h = res.metrics["health"]
            assert h["stance"]["vision_refused"] > 0
    assert ate["always"] < max(2.0 * ate["default"], 2.0), ate
    assert ate["always_untested"] > 2.0 * ate["always"], ate


def _via_points(scen):
    """The scenario with the via-point swing (the simulator's default before 2026-12-05)."""
    return scen.model_copy(
        update={"gait": scen.gait.model_copy(update={"swing_model": "via_points"})}
    )


@pytest.mark.slow
def test_fast_cadence_stances_correct_the_velocity(tmp_path: Path) -> None:
    """Step over step at 1.5x the cadence: the accelerometer clips at a push-off (16 g) and the
    next foot-flat lasts 0.15 s on a level landing, where vision measures no forward motion.
    The stance anchor needs two frames of one stance; the stance velocity observation
    corrects the velocity from the first one (seed 1000 of the sweep: toe x 10.3 -> 1.7 cm).
    The via-point swing (the default before 2026-12-05), whose push-off clips; with the
    joint-space swing nothing clips and the stance velocity matters less (2.7 -> 2.5 cm)."""
    from vio_graph.sim import simulate
    from vio_graph.sweep import condition_by_name, condition_scenario

    scen = _via_points(condition_scenario(condition_by_name("cadence_1.5")))
    # a stress trial: its push-off clips the accelerometer (30 g at 1 kHz), beyond the
    # simulator's plausibility bound on purpose
    scen = scen.model_copy(
        update={"gait": scen.gait.model_copy(update={"max_shank_specific_force_g": None})}
    )
    rec = simulate(scen, 1000, tmp_path / "rec")
    ate = {}
    for name, sigma in {"with": 0.05, "without": None}.items():
        cfg = _config(stance_velocity_sigma_mps=sigma)
        res = run_recording(rec, tmp_path / name, cfg, progress=False, visualize=False)
        ate[name] = res.metrics["ate_cm"]["filter"]["toe"]["x"]
        if name == "with":
            assert res.metrics["health"]["stance"]["velocity_fused"] > 20
    assert ate["with"] < 3.0, ate
    assert ate["without"] > 2.0 * ate["with"], ate


# --- the foot-rotation test (FootRotationTest) -----------------------------------------------
HEEL_M = float(np.hypot(0.055, 0.068))  # ankle to heel of the able-bodied rig (m)


def _foot_test() -> FootRotationTest:
    # the defaults: stance_pitch_sigma_rad 0.002, stance_slip_sigma_m 0.0005, p = 0.999
    return FootRotationTest(chi2_quantile(0.999, 1), HEEL_M, 0.002, 0.0005)


def test_a_foot_flattening_about_its_heel_is_not_a_still_ankle() -> None:
    """Loading response: the foot comes down from -15 deg to flat at 1 rad/s about its heel
    (the ankle moves ~9 cm/s); every frame of it is refused, the flat foot after it passes."""
    rng = np.random.default_rng(0)
    n_turn = int(np.radians(15) / 1.0 * FPS)  # 7 frames at 30 fps
    pitch = np.r_[np.radians(-15) + np.arange(n_turn) / FPS, np.zeros(30)]
    pitch += rng.normal(0, np.radians(0.05), pitch.size)  # encoder + IMU pitch noise
    test = _foot_test()
    ok = []
    for p in pitch:
        ok.append(test.test(float(p)))
        if not ok[-1]:
            test.reset()  # the caller ends the stance
    assert not any(ok[1:n_turn]), ok[:n_turn]  # the first call has nothing to compare with
    assert all(ok[n_turn + 1 :]), ok[n_turn:]
    # what it would have cost: the ankle travels HEEL_M x 15 deg = 2.3 cm
    assert HEEL_M * np.radians(15) > 0.02


def test_a_flat_foot_under_a_turning_shank_passes() -> None:
    """Foot-flat while the shank rolls 30 deg over it: shank pitch and ankle angle change
    together, the foot pitch does not (2 s of stance, encoder and IMU noise)."""
    rng = np.random.default_rng(1)
    shank = np.radians(np.linspace(-10, 20, 60))
    ankle = -shank + rng.normal(0, np.radians(0.05), shank.size)
    test = _foot_test()
    assert all(test.test(float(s + a)) for s, a in zip(shank, ankle, strict=True))


def test_without_an_ankle_angle_the_foot_test_stands() -> None:
    test = _foot_test()
    assert test.test(None) and test.test(0.0) and test.test(None)
    assert test.test(0.0) and not test.test(0.1)  # 0.1 rad: 8.8 mm of ankle motion


@pytest.mark.slow
def test_a_trial_starting_in_a_loading_response_is_not_held_back(tmp_path: Path) -> None:
    """Slow step-to-step sweep condition, seed 1000, first 3 s: the trial starts as the
    instrumented foot comes down about its heel (toe 7 cm -> 0 in 0.3 s, the ankle 2 cm
    forward and 1 cm down) with ankle accelerations under the detector's threshold. Without
    the foot test the anchor took that as stance and held the filter 2 cm behind the truth
    for the rest of the trial; with it the stance starts once the foot is flat."""
    from vio_graph.sim import simulate
    from vio_graph.sweep import condition_by_name, condition_scenario

    scenario = condition_scenario(condition_by_name("sts_slow_30fps"))
    scenario = scenario.model_copy(update={"duration_s": 3.0})
    rec = simulate(scenario, 1000, tmp_path / "rec")
    err = {}
    for name, on in {"with": True, "without": False}.items():
        res = run_recording(
            rec, tmp_path / name, _config(stance_foot_test=on), progress=False, visualize=False
        )
        err[name] = res.metrics["ate_cm"]["filter"]["camera"]["x"]
        if on:
            assert res.metrics["health"]["stance"]["foot_refused"] >= 3
    assert err["with"] < 0.8, err
    assert err["without"] > 1.5, err


@pytest.mark.slow
def test_an_anchor_does_not_follow_a_turn_of_the_attitude(tmp_path: Path) -> None:
    """Camera 8 cm below the knee, optical axis along the shank: the level-surface pitch offset
    converges by ~1 deg during the first stance and keeps moving by tenths of a degree
    later. An anchor kept across such a turn drags the camera by the turn times the 0.36 m
    camera-ankle lever (sweep seed 1001: filter toe x 2.7 cm with the height landmarks, 3.3 cm
    before them); restarting the anchor when the turn exceeds the anchor's own sigma keeps it
    at 2.1 cm (1.9 cm before).

    Both runs keep the vision override unconditional (stance_override_needs_power off): the
    run without the restart has one override whose displacements could not see the
    disagreement, and refusing it (the default since 2026-12-05) takes that run from 1.98
    to 1.28 cm, which hides the restart's own effect this test is about (with the restart:
    1.09 cm either way)."""
    from vio_graph.sim import simulate
    from vio_graph.sweep import condition_by_name, condition_scenario

    scen = condition_scenario(condition_by_name("camera_8cm_0deg"))
    rec = simulate(scen, 1001, tmp_path / "rec")
    ate = {}
    for on in (True, False):
        cfg = _config(stance_attitude_reanchor=on, stance_override_needs_power=False)
        res = run_recording(rec, tmp_path / str(on), cfg, progress=False, visualize=False)
        ate[on] = res.metrics["ate_cm"]["filter"]["toe"]["x"]
        if on:
            assert res.metrics["health"]["stance"]["attitude_reanchors"] > 0
    assert ate[True] < 2.5, ate
    assert ate[False] > 1.2 * ate[True], ate


@pytest.mark.slow
def test_a_restarted_anchor_stays_one_stance_for_the_smoothers(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    """The anchor restart is the filter's: over one run of anchored frames the stance
    observations the smoothers receive keep one stance id, while the filter restarts its
    anchor inside such runs (camera 8 cm below the knee, 4 s of sweep seed 1001)."""
    from vio_graph.estimator import OnlineEstimator
    from vio_graph.recording.reader import Recording
    from vio_graph.replay import Replay
    from vio_graph.sim import simulate
    from vio_graph.sweep import condition_by_name, condition_scenario
    from vio_graph.viz.rerun_logger import NullVisualizer

    scen = condition_scenario(condition_by_name("camera_8cm_0deg"))
    scen = scen.model_copy(update={"duration_s": 4.0})
    rec = Recording.open(simulate(scen, 1001, tmp_path / "rec"))
    records = []
    process = OnlineEstimator.process_frame

    def keep(self, *args, **kwargs):
        record = process(self, *args, **kwargs)
        records.append((record.in_stance, record.stance, dict(self.stance_stats)))
        return record

    monkeypatch.setattr(OnlineEstimator, "process_frame", keep)
    Replay(rec, PipelineConfig(), {"filter"}, NullVisualizer()).run()
    assert records[-1][2]["attitude_reanchors"] > 0
    stances_with_a_restart = 0
    ids: list[int] = []
    restarts_at_onset = 0
    for in_stance, obs, stats in records:
        if in_stance and obs is not None:
            if not ids:
                restarts_at_onset = stats["attitude_reanchors"]
            ids.append(obs.stance_id)
            continue
        if ids:  # a stance ended
            assert len(set(ids)) == 1, ids  # one stance, one id
            stances_with_a_restart += int(stats["attitude_reanchors"] > restarts_at_onset)
        ids = []
    assert stances_with_a_restart > 0


@pytest.mark.parametrize("reference", [False, True])
def test_a_repaired_imu_packet_does_not_end_a_quiet_window(reference: bool) -> None:
    """A standing shank (gravity only, no rotation) with one packet whose gyro the fault
    monitor predicted 0.5 rad/s off (a repaired spike): taken as a measurement, the
    finite-difference angular acceleration (50 rad/s^2) over the 0.4 m ankle lever reads as
    ~20 m/s^2 at the ankle and the window is no longer quiet for 0.1 s; marked untrusted
    (ImuSample.accel_held) it gives no vote and the stance stands."""

    def run(trusted_spike: bool) -> list[bool]:
        det = StanceDetector((0.0, 0.0, -0.4), 2.0, 0.1)
        add = det.add_imu_reference if reference else det.add_imu
        quiet = []
        for k in range(60):
            t = 0.01 * k
            spike = k == 30
            gyro = (0.0, 0.5, 0.0) if spike else (0.0, 0.0, 0.0)
            add(
                t,
                (0.0, 0.0, 9.81),
                gyro,
                np.eye(2),
                (0.0, -9.81),
                trusted=trusted_spike or not spike,
            )
            quiet.append(det.quiet())
        return quiet

    as_measured, untrusted = run(True), run(False)
    assert all(untrusted[15:])  # quiet from a full window on, the repaired packet included
    assert not all(as_measured[30:42])  # the same packet as a measurement breaks the window


def _keyframes_per_stance(rec, stance_keyframes: int, monkeypatch) -> list[tuple[int, int]]:
    """(anchored frames, keyframes among them) for each run of anchored frames of a replay
    with ``keyframes.stance_keyframes`` = ``stance_keyframes``."""
    from vio_graph.estimator import OnlineEstimator
    from vio_graph.replay import Replay
    from vio_graph.viz.rerun_logger import NullVisualizer

    frames: list[tuple[bool, bool]] = []
    process = OnlineEstimator.process_frame

    def keep(self, *args, **kwargs):
        record = process(self, *args, **kwargs)
        frames.append((record.stance is not None, record.is_keyframe))
        return record

    base = PipelineConfig()
    kf = base.keyframes.model_copy(update={"stance_keyframes": stance_keyframes})
    with monkeypatch.context() as patch:
        patch.setattr(OnlineEstimator, "process_frame", keep)
        Replay(rec, base.model_copy(update={"keyframes": kf}), {"filter"}, NullVisualizer()).run()
    runs: list[tuple[int, int]] = []
    n = n_kf = 0
    for anchored, is_kf in [*frames, (False, False)]:
        if anchored:
            n, n_kf = n + 1, n_kf + int(is_kf)
        elif n:
            runs.append((n, n_kf))
            n = n_kf = 0
    return runs


@pytest.mark.slow
def test_stance_keyframes_put_every_short_stance_into_the_graphs(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    """IMU at 50 Hz, step over step (sweep seed 1001): the trial's last stance (9.79-9.88 s,
    4 frames, on the top landing) falls between the keyframes at 9.65 s (interval) and 9.92 s
    (after it), so the graphs never saw it and their x ran away (toe x 4 cm). With
    keyframes.stance_keyframes = 2 each stance's first two anchored frames are keyframes; the
    filter's stances are the same. The via-point swing (the trial as measured; the
    default before 2026-12-05)."""
    from vio_graph.recording.reader import Recording
    from vio_graph.sim import simulate
    from vio_graph.sweep import condition_by_name, condition_scenario

    scen = _via_points(condition_scenario(condition_by_name("imu_50hz")))
    rec = Recording.open(simulate(scen, 1001, tmp_path / "rec"))
    before = _keyframes_per_stance(rec, 0, monkeypatch)
    after = _keyframes_per_stance(rec, 2, monkeypatch)
    assert [n for n, _ in before] == [n for n, _ in after]  # the filter is unchanged
    assert before[-1][1] == 0, before  # the last stance: no keyframe
    assert any(k < min(n, 2) for n, k in before), before
    assert all(k >= min(n, 2) for n, k in after), after


def test_a_blind_displacement_gives_the_override_no_power() -> None:
    """A displacement whose x is unobservable (sigma 1 m) passes the stance test along x
    whatever the ankle does (here 3 cm); the chain it starts cannot side with the anchor
    against an x disagreement (resolves False), while an informative chain can."""
    lever = np.array([0.0, -0.4])
    blind = StanceConsistencyTest(13.8, 0.001, 0.002)
    sharp = StanceConsistencyTest(13.8, 0.001, 0.002)
    for test, sx, dx in ((blind, 1.0, 0.03), (sharp, 0.003, 0.0)):
        test.test(0.0, lever, None)
        d = Displacement2D(0.0, 0.033, np.array([dx, 0.0]), np.diag([sx**2, 0.003**2]))
        assert test.test(0.033, lever, d)
    assert not blind.resolves(np.array([0.10, 0.0]))
    assert blind.resolves(np.array([0.0, 0.10]))  # its z was measured
    assert sharp.resolves(np.array([0.10, 0.0]))


def test_the_weighted_chain_ignores_a_blind_link() -> None:
    """Summed, one x-blind link blinds the since-onset chain's x for the rest of the stance;
    weighted by inverse covariance, the later sharp links still catch a slow x drift."""
    lever = np.array([0.0, -0.4])
    res = {}
    for weighted in (False, True):
        test = StanceConsistencyTest(13.8, 0.0005, 0.002, weighted_chain=weighted)
        test.test(0.0, lever, None)
        sx = [1.0] + [0.0025] * 4
        ok = []
        for k, s in enumerate(sx):  # the ankle drifts 0.7 cm a frame in x
            d = Displacement2D(
                0.033 * k, 0.033 * (k + 1), np.array([0.007, 0.0]), np.diag([s**2, 0.0025**2])
            )
            ok.append(test.test(0.033 * (k + 1), lever, d))
        res[weighted] = ok
    assert all(res[False])
    assert not all(res[True])
