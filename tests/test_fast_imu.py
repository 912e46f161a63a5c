"""The per-IMU-sample fast path (filter/fast_imu.py and the scalar propagate / attitude /
stance code) against the numpy references it replaced: same functions to 1e-12, and the
same estimator run (filter, IMU-only, ICP-only paths, filter state) to 1e-9 m."""

from __future__ import annotations

import dataclasses
from pathlib import Path

import numpy as np
import pytest
from scipy.spatial.transform import Rotation

import vio_graph.estimator as estimator_mod
from vio_graph.config import PipelineConfig
from vio_graph.filter import fast_imu
from vio_graph.filter.attitude import AttitudeTracker, with_pitch_offset
from vio_graph.filter.eskf import SagittalEskf, sagittal_rotation
from vio_graph.filter.imu_faults import ImuFaultMonitor
from vio_graph.filter.stance import StanceDetector
from vio_graph.filter.time_offset import ClockModel
from vio_graph.geometry import (
    matrix_from_quat_wxyz,
    quat_wxyz_from_matrix,
    remove_yaw,
    rot_y,
    rot_z,
)
from vio_graph.recording import Recording
from vio_graph.replay import Replay
from vio_graph.types import ImuSample
from vio_graph.viz.rerun_logger import NullVisualizer


def _quats(n: int, seed: int = 0) -> np.ndarray:
    """Random orientations, half of them shank-like (yaw, pitch up to +-120 deg, small roll),
    unnormalised to check the normalisation too."""
    rng = np.random.default_rng(seed)
    out = []
    for i in range(n):
        if i % 2:
            q = rng.normal(size=4)
        else:
            R = (
                rot_z(rng.uniform(-np.pi, np.pi))
                @ rot_y(rng.uniform(-2.1, 2.1))
                @ Rotation.from_euler("x", rng.normal(0, 0.1)).as_matrix()
            )
            q = quat_wxyz_from_matrix(R)
        out.append(q * rng.uniform(0.5, 2.0))
    return np.array(out)


def test_closed_forms_match_the_numpy_references() -> None:
    rng = np.random.default_rng(1)
    for q in _quats(2000):
        np.testing.assert_allclose(
            np.reshape(fast_imu.quat_matrix(q), (3, 3)), matrix_from_quat_wxyz(q), atol=1e-14
        )
        np.testing.assert_allclose(
            fast_imu.sagittal_rotation_fast(q), sagittal_rotation(q), atol=1e-12
        )
        m = fast_imu.quat_matrix(q)
        np.testing.assert_allclose(
            np.reshape(fast_imu.remove_yaw_mat3(m), (3, 3)),
            remove_yaw(np.reshape(m, (3, 3))),
            atol=1e-14,
        )
        b = rng.normal(0.0, 0.1)
        ref = quat_wxyz_from_matrix(with_pitch_offset(matrix_from_quat_wxyz(q), b))
        got = fast_imu.pitch_offset_quat(q, b)
        if abs(ref[0]) < 1e-6:  # w ~ 0: q and -q are both "w >= 0"
            got, ref = got * np.sign(got @ ref), ref
        np.testing.assert_allclose(got, ref, atol=1e-12)
        R = matrix_from_quat_wxyz(q)
        np.testing.assert_allclose(
            fast_imu.matrix_rotvec(R), Rotation.from_matrix(R).as_rotvec(), atol=1e-12
        )
    for R in Rotation.random(3000, random_state=3).as_matrix():  # every Shepperd branch
        m = tuple(R.ravel().tolist())
        assert np.array_equal(fast_imu.mat3_quat(m), quat_wxyz_from_matrix(R))  # bit for bit
    for b in (-0.4, 0.0, 1e-3, 2.5):
        np.testing.assert_allclose(np.reshape(fast_imu.rot_y_mat3(b), (3, 3)), rot_y(b), atol=0)
    for scale in (0.0, 1e-9, 1e-4, 0.3, 3.0):
        v = rng.normal(size=3) * scale
        np.testing.assert_allclose(
            fast_imu.rotvec_matrix(*v), Rotation.from_rotvec(v).as_matrix(), atol=1e-15
        )
        R = Rotation.from_rotvec(v).as_matrix()  # log then exp gives R back (|v| may be > pi)
        np.testing.assert_allclose(
            fast_imu.rotvec_matrix(*fast_imu.matrix_rotvec(R)), R, atol=1e-13
        )


def _fit_with_np_mean(model: ClockModel, t: float) -> float:
    """ClockModel._fit as written with np.mean (before its means were taken as one add.reduce
    and a division), for the bit-for-bit comparison below."""
    n = model._n
    ts = model._buf[model._pos - n : model._pos]
    if n >= 20:
        half = 0.5 * (n - 1)
        my = float(ts.mean())
        sxy = float((model._ar[:n] - half) @ (ts - my))
        icpt = my + (sxy / (n * (n * n - 1) / 12.0)) * half
    else:
        icpt = float(np.mean(ts + model.period_s * (n - 1 - model._ar[:n])))
    return t if abs(icpt - t) < 1e-6 else float(icpt)


def test_clock_fit_is_bit_for_bit_the_np_mean_formulation() -> None:
    """The clock line's means without np.mean's dispatch give the same floats, bit for bit,
    from the first stamps (nominal period) to full windows, across a gap."""
    rng = np.random.default_rng(11)
    stamps = 3.0 + np.cumsum(0.01 + rng.normal(0.0, 0.002, 700))
    stamps[400:] += 0.3
    model = ClockModel(0.01, 120, 5.0)
    model._kernels = None  # the Python path (the compiled one sums x-y in another order)
    fitted = model._fit
    checked = []

    def both(t: float) -> float:
        out = fitted(t)
        assert out == _fit_with_np_mean(model, t)
        checked.append(model._n)
        return out

    model._fit = both  # type: ignore[method-assign]
    moved = sum(model.correct(t) != t for t in stamps)
    assert min(checked) < 20 <= max(checked) == 120 and moved > 300


@pytest.mark.parametrize("jitter_s", [0.0, 1e-9, 3e-8, 1e-7, 2e-3])
def test_compiled_clock_skips_the_fit_only_where_it_keeps_the_stamp(
    jitter_s: float, monkeypatch: pytest.MonkeyPatch
) -> None:
    """compiled_imu.clock_correct skips the O(window) line fit when the steps between the
    line's stamps are close enough to the nominal period that the fit must keep the stamp:
    every output equals what the full fit (compiled_imu.clock_line at every stamp) gives,
    bit for bit, on stamps on the nominal line (float rounding only), with jitter below,
    around and above the skip bound, across a gap and after the window fills."""
    monkeypatch.setenv("VIO_GRAPH_COMPILED", "1")
    k = fast_imu.imu_kernels()
    if k is None:
        pytest.skip("numba not installed")
    rng = np.random.default_rng(8)
    period, window, tol = 0.01, 200, 1e-6
    stamps = 1234.5 + period * np.arange(1200) + rng.uniform(-jitter_s, jitter_s, 1200)
    stamps[700:] += 0.5  # a gap: the line starts over
    model = ClockModel(period, window, 5.0)
    assert model._st is not None
    last, kept = None, 0
    for t in stamps:
        out = model.correct(float(t))
        pos, n = int(model._st[k.CLK_POS]), int(model._st[k.CLK_N])
        icpt = k.clock_line(model._buf, pos, n, period, 20)
        want = t if abs(icpt - t) < tol else icpt
        if last is not None and want <= last:
            want = t if t > last else last + 0.5 * period
        assert out == want
        kept += out == t
        last = out
    assert model.n_gaps == 1
    if jitter_s <= 3e-8:
        assert kept == stamps.size  # the skip's answer: the stamps as recorded
    if jitter_s >= 2e-3:
        assert kept < stamps.size / 10


@pytest.mark.parametrize("compiled", ["0", "1"])
def test_clock_fit_and_fault_monitor_equal_their_references(
    compiled: str, monkeypatch: pytest.MonkeyPatch
) -> None:
    monkeypatch.setenv("VIO_GRAPH_COMPILED", compiled)  # scalar Python / numba kernels
    """The clock model's closed-form line fit against np.polyfit on jittered stamps with a gap,
    and the IMU fault monitor's scalar path against its numpy reference on a swinging shank
    with saturated and corrupted samples (both paths must fire)."""
    rng = np.random.default_rng(4)
    stamps = 5.0 + np.cumsum(0.01 + rng.normal(0.0, 0.002, 1500))
    stamps[900:] += 0.4  # a gap: the line starts over
    fast, ref = ClockModel(0.01, 200, 5.0), ClockModel(0.01, 200, 5.0)
    ref._fit = ref._fit_reference  # type: ignore[method-assign]
    out_f = np.array([fast.correct(t) for t in stamps])
    out_r = np.array([ref.correct(t) for t in stamps])
    assert fast.n_gaps == 1 and np.count_nonzero(out_f != stamps) > 1000  # the fit moved them
    np.testing.assert_allclose(out_f, out_r, rtol=0, atol=1e-12)
    for model in (fast, ref):  # a stamp going backwards: dropped and reported by both
        assert model.correct(stamps[-1] - 0.05) is None
    rep_f, rep_r = fast.report(), ref.report()
    assert (
        rep_f["gap_list"] == rep_r["gap_list"]
        and rep_f["backwards_list"] == rep_r["backwards_list"]
    )
    assert rep_f["correction_rms_s"] == pytest.approx(
        rep_r["correction_rms_s"], rel=1e-9, abs=1e-15
    )

    samples = _swinging_samples(400, seed=5)
    for k in (50, 51, 200):  # corrupt packets: gyro and accelerometer off
        s = samples[k]
        samples[k] = dataclasses.replace(s, gyro_radps=s.gyro_radps + 3.0, accel_mps2=-s.accel_mps2)
    cfg = PipelineConfig().filter.imu_faults
    mon_f = ImuFaultMonitor(cfg, accel_range_mps2=9.9, gyro_range_radps=6.0)
    mon_r = ImuFaultMonitor(cfg, accel_range_mps2=9.9, gyro_range_radps=6.0)
    for s in samples:
        a, b = mon_f.process(s), mon_r.process_reference(s)
        for field in ("accel_mps2", "gyro_radps", "quat_wxyz"):
            np.testing.assert_allclose(getattr(a, field), getattr(b, field), atol=1e-12)
        assert a.accel_extra_sigma_mps2 == b.accel_extra_sigma_mps2
        assert a.gyro_extra_sigma_radps == b.gyro_extra_sigma_radps
        assert a.accel_held == b.accel_held
    assert mon_f.report() == mon_r.report()
    assert mon_f.n_gyro_repaired >= 3 and mon_f.n_accel_saturated > 0
    assert mon_f.max_gyro_d2 == pytest.approx(mon_r.max_gyro_d2, rel=1e-9)


def _swinging_samples(n: int = 600, seed: int = 2) -> list[ImuSample]:
    """A shank swinging +-60 deg at 1 Hz while walking, 100 Hz, with noise."""
    rng = np.random.default_rng(seed)
    out = []
    for k in range(n):
        t = 0.01 * k
        pitch = 1.05 * np.sin(2 * np.pi * t)
        R = rot_z(0.3) @ rot_y(pitch)
        accel = R.T @ np.array([0.4 * np.cos(t), 0.0, 9.81]) + rng.normal(0, 0.05, 3)
        gyro = np.array([0.0, 1.05 * 2 * np.pi * np.cos(2 * np.pi * t), 0.0])
        out.append(ImuSample(t, accel, gyro + rng.normal(0, 0.01, 3), quat_wxyz_from_matrix(R)))
    return out


@pytest.mark.parametrize("compiled", ["0", "1"])
def test_propagate_attitude_and_stance_equal_their_references(
    compiled: str, monkeypatch: pytest.MonkeyPatch
) -> None:
    monkeypatch.setenv("VIO_GRAPH_COMPILED", compiled)  # scalar Python / numba kernels
    samples = _swinging_samples()
    T = np.eye(4)
    T[:3, 3] = (0.05, 0.02, -0.1)  # lever arm on, so the tangential / centripetal terms count
    fast, ref = SagittalEskf(imu_T_cam=T), SagittalEskf(imu_T_cam=T)
    att_f, att_r = AttitudeTracker(), AttitudeTracker()
    st_f = StanceDetector((0.0, 0.0, -0.3), 2.0, 0.2)
    st_r = StanceDetector((0.0, 0.0, -0.3), 2.0, 0.2)
    for f in (fast, ref):
        f.initialise(0.0, (0.0, 0.0))
    for s in samples[1:]:
        fast.propagate(s)
        ref.propagate_reference(s)
        att_f.add(s)
        att_r.add_reference(s)
        R2 = sagittal_rotation(s.quat_wxyz)
        if st_f.compiled:
            a_f = st_f.add_imu_quat(
                s.timestamp_s, s.accel_mps2, s.gyro_radps, s.quat_wxyz, (0.0, -9.81)
            )
        else:
            a_f = st_f.add_imu(s.timestamp_s, s.accel_mps2, s.gyro_radps, R2, (0.0, -9.81))
        a_r = st_r.add_imu_reference(s.timestamp_s, s.accel_mps2, s.gyro_radps, R2, (0.0, -9.81))
        assert a_f == pytest.approx(a_r, abs=1e-12)
    sf, sr = fast.state, ref.state
    assert abs(sf.p_xz_m).max() > 0.5  # it moved: the comparison is not of zeros
    np.testing.assert_allclose(sf.p_xz_m, sr.p_xz_m, atol=1e-9)
    np.testing.assert_allclose(sf.v_xz_mps, sr.v_xz_mps, atol=1e-9)
    np.testing.assert_allclose(fast._P, ref._P, rtol=1e-9, atol=1e-15)
    np.testing.assert_allclose(att_f.R_world_imu_at(6.0), att_r.R_world_imu_at(6.0), atol=1e-12)


@pytest.mark.parametrize("vendor_sigma", [None, "auto"])
def test_a_whole_replay_equals_the_reference_path(
    short_upstair: Path, monkeypatch: pytest.MonkeyPatch, vendor_sigma: str | None
) -> None:
    """The filter, IMU-only and ICP-only answers of a replay (front end, level aiding and
    stance anchor included) with the scalar fast path, with the compiled kernels
    (filter/compiled_imu.py, numba) and with every numpy reference swapped in.

    A simulated trial, not the tiny synthetic recording: on the latter's noise-free, exactly
    level geometry a 2e-15 change of the attitude (the rounding difference of the two
    paths) moved the filter's answer by 1.6 mm, a discrete decision flipping on an exact tie;
    on the simulated trials the answers agree to 1e-13 m. ``vendor_sigma`` "auto": the pull
    about the pitch axis weighed by the vendor's estimated pitch error (a pitch gain other
    than the roll and heading one in every kernel)."""
    rec = Recording.open(short_upstair)
    assert PipelineConfig().filter.strapdown_attitude == "tracked"  # the default path is covered
    cfg = PipelineConfig()
    att = cfg.filter.attitude.model_copy(update={"vendor_pitch_sigma_deg": vendor_sigma})
    cfg = cfg.model_copy(update={"filter": cfg.filter.model_copy(update={"attitude": att})})

    def run() -> dict[str, np.ndarray]:
        rp = Replay(rec, cfg, {"filter"}, NullVisualizer())
        if vendor_sigma is not None:
            pitch_taus.append(rp.online.attitude)
        log = rp.run()
        out = dict(log.camera_xz)
        out["P"] = rp.online.filter.state.P
        fused.append(rp.online.n_fused_samples)
        one_call.append(rp.online.n_one_call_samples)
        return out

    fused: list[int] = []
    one_call: list[int] = []
    pitch_taus: list[AttitudeTracker] = []  # the trackers, read after their replay
    monkeypatch.setenv("VIO_GRAPH_COMPILED", "0")  # the scalar Python closed forms
    fast = run()
    assert fused[-1] == 0 and one_call[-1] == 0
    monkeypatch.setenv("VIO_GRAPH_COMPILED", "1")  # the compiled kernels (filter/compiled_imu)
    compiled = run() if fast_imu.imu_kernels() is not None else None
    if compiled is not None:
        # nearly every sample took the one-call paths (compiled_imu.sample_step inside
        # compiled_imu.imu_input); the separate kernels they fuse give the same bits
        n_imu = int(np.sum(rec.imu.timestamp_s <= rec.frame_timestamps_s[-1]))
        assert fused[-1] > 0.9 * n_imu and one_call[-1] > 0.9 * n_imu
        with monkeypatch.context() as m:
            m.setattr(estimator_mod.OnlineEstimator, "_init_one_call_input", lambda self: None)
            fused_step_only = run()
            assert one_call[-1] == 0 and fused[-1] > 0.9 * n_imu
            m.setattr(estimator_mod.OnlineEstimator, "_advance_imu_fused", lambda self, s: None)
            separate = run()
        for name in compiled:
            np.testing.assert_array_equal(separate[name], compiled[name], err_msg=name)
            np.testing.assert_array_equal(fused_step_only[name], compiled[name], err_msg=name)
    monkeypatch.setenv("VIO_GRAPH_COMPILED", "0")
    monkeypatch.setattr(SagittalEskf, "propagate", SagittalEskf.propagate_reference)
    monkeypatch.setattr(AttitudeTracker, "add", AttitudeTracker.add_reference)
    monkeypatch.setattr(StanceDetector, "add_imu", StanceDetector.add_imu_reference)
    monkeypatch.setattr(estimator_mod, "_sagittal_rotation", sagittal_rotation)
    monkeypatch.setattr(
        estimator_mod.OnlineEstimator,
        "R_world_imu",
        estimator_mod.OnlineEstimator.R_world_imu_reference,
    )
    monkeypatch.setattr(
        estimator_mod, "_pitch_offset_quat", estimator_mod.reference_pitch_offset_quat
    )
    monkeypatch.setattr(
        estimator_mod.OnlineEstimator,
        "_with_tracked_attitude",
        estimator_mod.OnlineEstimator._with_tracked_attitude_reference,
    )
    monkeypatch.setattr(ImuFaultMonitor, "process", ImuFaultMonitor.process_reference)
    monkeypatch.setattr(ClockModel, "_fit", ClockModel._fit_reference)
    ref = run()
    if vendor_sigma is not None:  # the pitch pull was weighed, differently from roll's
        assert all(a.pitch_time_constant_s > 2.0 * a.time_constant_s for a in pitch_taus)
    assert set(fast) == set(ref) and {"filter", "imu_only", "icp_only"} <= set(fast)
    assert np.ptp(fast["filter"][:, 0]) > 0.05  # the camera moved
    for got in (fast, compiled):
        if got is None:  # numba not installed
            continue
        for name in ref:
            if name == "P":
                np.testing.assert_allclose(got[name], ref[name], rtol=1e-9, atol=1e-15)
            else:
                np.testing.assert_allclose(got[name], ref[name], atol=1e-9, err_msg=name)


def test_the_one_call_sample_path_equals_the_separate_kernels_on_faulty_imu(
    short_upstair: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    """OnlineEstimator._advance_imu_fused (compiled_imu.sample_step) against the general path
    with the separate kernels, bit for bit, on an IMU stream with corrupted packets (the fault
    monitor repairs the gyro, holds the accelerometer and NextSampleRepair holds the packet
    back) and a clipped accelerometer (saturation prior and scale learner): the fused path
    must hand every sample it cannot take to the general path unchanged."""
    monkeypatch.setenv("VIO_GRAPH_COMPILED", "1")
    if fast_imu.imu_kernels() is None:
        pytest.skip("numba not installed")
    from vio_graph.estimator import OnlineEstimator, RigGeometry
    from vio_graph.replay import replay_order

    rec = Recording.open(short_upstair)
    rig = dataclasses.replace(RigGeometry.from_metadata(rec.metadata), accel_range_mps2=14.0)
    kinds, idx = replay_order(rec)

    def sample(i: int) -> ImuSample:
        s = rec.imu.sample(i)
        acc = np.clip(s.accel_mps2, -14.0, 14.0)  # clipped at the declared range
        if i in (120, 121, 200):  # corrupt packets (200: its neighbours unclipped)
            return dataclasses.replace(s, gyro_radps=s.gyro_radps + 3.0, accel_mps2=-acc)
        return dataclasses.replace(s, accel_mps2=acc)

    def run() -> tuple[OnlineEstimator, list[np.ndarray], list[np.ndarray]]:
        est = OnlineEstimator(PipelineConfig(), rig)
        cams, quats = [], []
        for kind, i in zip(kinds, idx, strict=True):
            if kind == 0:
                step = est.add_imu(sample(int(i)))
                if step is not None:
                    quats.append(step.corrected.quat_wxyz)
            elif kind == 1:
                est.add_joints(rec.joints.sample(int(i)))
            elif est.initialised:
                cams.append(est.add_frame(rec.frame(int(i)))[0].camera_xz_m)
        return est, cams, quats

    fused, cams_f, quats_f = run()
    with monkeypatch.context() as m:
        m.setattr(OnlineEstimator, "_init_one_call_input", lambda self: None)
        m.setattr(OnlineEstimator, "_advance_imu_fused", lambda self, s: None)
        separate, cams_s, quats_s = run()
    assert fused.imu_faults.n_gyro_repaired >= 3 and fused.imu_faults.n_accel_saturated > 10
    assert fused.imu_repair is not None and fused.imu_repair.n_repaired >= 1
    assert 0 < fused.n_fused_samples < len(quats_f) and separate.n_fused_samples == 0
    np.testing.assert_array_equal(np.array(cams_f), np.array(cams_s))
    np.testing.assert_array_equal(np.array(quats_f), np.array(quats_s))
    np.testing.assert_array_equal(fused.filter.state.P, separate.filter.state.P)
    assert fused.fault_report() == separate.fault_report()
    assert fused.health_report() == separate.health_report()


def test_the_one_call_input_equals_the_separate_calls_on_faulty_imu_and_clock(
    short_upstair: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    """OnlineEstimator._add_imu_one_call (compiled_imu.imu_input: IMU clock model, fault check
    and the fused sample step in one call) against the separate calls, bit for bit, on an IMU
    stream with stamp jitter, a gap, stamps that go backwards, corrupted packets and a clipped
    accelerometer: every sample the kernel cannot finish must continue on the general path
    exactly where it stopped (clock and fault reports included)."""
    monkeypatch.setenv("VIO_GRAPH_COMPILED", "1")
    if fast_imu.imu_kernels() is None:
        pytest.skip("numba not installed")
    from vio_graph.estimator import OnlineEstimator, RigGeometry
    from vio_graph.replay import replay_order

    rec = Recording.open(short_upstair)
    rig = dataclasses.replace(RigGeometry.from_metadata(rec.metadata), accel_range_mps2=14.0)
    kinds, idx = replay_order(rec)
    jitter = np.random.default_rng(3).uniform(-1.5e-3, 1.5e-3, rec.imu.timestamp_s.size)

    def sample(i: int) -> ImuSample | None:
        if 400 <= i < 406:  # a gap of six samples
            return None
        s = rec.imu.sample(i)
        t = s.timestamp_s + jitter[i]
        if i in (300, 301):  # stamps at or before the previous one (dropped)
            t = rec.imu.timestamp_s[299] + jitter[299] - 1e-3 * (i - 299)
        acc = np.clip(s.accel_mps2, -14.0, 14.0)  # clipped at the declared range
        if i in (120, 121, 200):  # corrupt packets (200: its neighbours unclipped)
            return dataclasses.replace(
                s, timestamp_s=t, gyro_radps=s.gyro_radps + 3.0, accel_mps2=-acc
            )
        return dataclasses.replace(s, timestamp_s=t, accel_mps2=acc)

    def run() -> tuple[OnlineEstimator, list[np.ndarray], list[np.ndarray]]:
        est = OnlineEstimator(PipelineConfig(), rig)
        cams, steps = [], []
        for kind, i in zip(kinds, idx, strict=True):
            if kind == 0:
                s = sample(int(i))
                step = None if s is None else est.add_imu(s)
                if step is not None:
                    steps.append(
                        np.r_[
                            step.shank.timestamp_s,
                            step.shank.accel_mps2,
                            step.shank.gyro_radps,
                            step.corrected.timestamp_s,
                            step.corrected.quat_wxyz,
                            step.corrected.accel_extra_sigma_mps2,
                            step.corrected.gyro_extra_sigma_radps,
                        ]
                    )
            elif kind == 1:
                est.add_joints(rec.joints.sample(int(i)))
            elif est.initialised:
                cams.append(est.add_frame(rec.frame(int(i)))[0].camera_xz_m)
        return est, cams, steps

    one_call, cams_o, steps_o = run()
    with monkeypatch.context() as m:
        m.setattr(OnlineEstimator, "_init_one_call_input", lambda self: None)
        m.setattr(OnlineEstimator, "_advance_imu_fused", lambda self, s: None)
        separate, cams_s, steps_s = run()
    rep = one_call.fault_report()
    assert rep["timestamps"]["imu"]["gaps"] >= 1 and rep["timestamps"]["imu"]["backwards"] == 2
    assert rep["timestamps"]["imu"]["correction_rms_s"] > 1e-4  # the clock line smoothed
    assert one_call.imu_faults.n_gyro_repaired >= 3 and one_call.imu_faults.n_accel_saturated > 10
    assert 0 < one_call.n_one_call_samples < len(steps_o) and separate.n_one_call_samples == 0
    np.testing.assert_array_equal(np.array(steps_o), np.array(steps_s))
    np.testing.assert_array_equal(np.array(cams_o), np.array(cams_s))
    np.testing.assert_array_equal(one_call.filter.state.P, separate.filter.state.P)
    assert rep == separate.fault_report()
    assert one_call.health_report() == separate.health_report()
    assert one_call.imu_faults.max_gyro_d2 == separate.imu_faults.max_gyro_d2


def test_steps_with_a_deferred_corrected_sample_give_the_same_smoothers(
    short_upstair: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    """The compiled path hands ``ImuStep.with_quat`` steps (the corrected sample built only
    when asked for) and the smoothers read the shank sample's fields with the corrected
    orientation instead of building it: the filter, fixed-lag and batch answers equal, bit
    for bit, those of a run where every step's corrected sample is built and fed as a sample
    (``feed_imu(step.corrected)``, the reference), and a built sample equals the sample with
    the orientation replaced."""
    monkeypatch.setenv("VIO_GRAPH_COMPILED", "1")
    if fast_imu.imu_kernels() is None:
        pytest.skip("numba not installed")
    from vio_graph.protocol import ImuStep
    from vio_graph.smoother.interface import KeyframeSmootherBase

    rec = Recording.open(short_upstair)
    lazy_steps: list[int] = []

    def run() -> dict[str, np.ndarray]:
        rp = Replay(rec, PipelineConfig(), {"filter", "smoother", "batch"}, NullVisualizer())
        inner = rp.online.add_imu

        def add_imu(sample: ImuSample) -> ImuStep | None:
            step = inner(sample)
            if step is not None and step.shank_but_quat:
                lazy_steps.append(1)
                built = step.corrected
                assert built is step.corrected  # built once
                want = dataclasses.replace(step.shank, quat_wxyz=step.corrected_quat_wxyz)
                for f in dataclasses.fields(ImuSample):
                    assert np.array_equal(getattr(built, f.name), getattr(want, f.name))
                # a step of the same sample, as the reference smoother input gets it
                if reference:
                    step = ImuStep(shank=step.shank, corrected=step.corrected)
            return step

        rp.online.add_imu = add_imu  # type: ignore[method-assign]
        return dict(rp.run().camera_xz)

    reference = False
    lazy = run()
    n_lazy = len(lazy_steps)
    reference = True
    with monkeypatch.context() as m:
        m.setattr(KeyframeSmootherBase, "add_imu", lambda self, step: self.feed_imu(step.corrected))
        ref = run()
    n_imu = int(np.sum(rec.imu.timestamp_s <= rec.frame_timestamps_s[-1]))
    assert n_lazy > 0.9 * n_imu  # nearly every step deferred its corrected sample
    assert {"filter", "smoother", "batch"} <= set(lazy) and set(lazy) == set(ref)
    for name in ref:
        np.testing.assert_array_equal(lazy[name], ref[name], err_msg=name)
