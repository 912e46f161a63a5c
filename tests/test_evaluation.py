"""Evaluation: association, ATE/APE/RPE against known answers and against evo."""

from __future__ import annotations

import numpy as np
import pytest

from vio_graph.errors import EvaluationError
from vio_graph.evaluation import (
    PAPER_TOE_ATE_CM,
    TrialAte,
    align,
    ape,
    associate,
    ate_per_axis,
    markdown_table,
    rpe,
    summarise,
    umeyama_alignment,
)
from vio_graph.geometry import quat_wxyz_from_matrix, rot_y, rot_z
from vio_graph.recording.streams import Trajectory
from vio_graph.recording.tum import write_tum


def sagittal_ref(rate_hz: float, duration_s: float = 4.0, t0: float = 10.0) -> Trajectory:
    """A smooth stair-like camera path sampled at ``rate_hz``."""
    t = t0 + np.arange(0.0, duration_s + 1e-9, 1.0 / rate_hz)
    s = t - t0
    x = 0.3 * s + 0.02 * np.sin(5 * s)
    z = 0.5 + 0.147 * s / 1.2 + 0.03 * np.sin(4 * s)
    xz = np.column_stack([x, z])
    return Trajectory.from_xz(t, xz)


def perturbed(traj: Trajectory, offset_xyz, seed: int = 0, sigma: float = 0.01) -> Trajectory:
    rng = np.random.default_rng(seed)
    noise = sigma * rng.standard_normal(traj.position_m.shape)
    noise[:, 1] = 0.0
    return Trajectory(
        traj.timestamp_s.copy(), traj.position_m + offset_xyz + noise, traj.quat_wxyz.copy()
    )


# ----------------------------------------------------------------------------- association
def test_association_interpolates_linear_ground_truth_exactly():
    t_ref = np.arange(0.0, 2.0 + 1e-9, 1 / 120)
    ref = Trajectory.from_xz(t_ref, np.column_stack([1.0 + 0.5 * t_ref, -0.25 * t_ref]))
    t_est = np.arange(0.013, 1.9, 1 / 30)
    est = Trajectory.from_xz(t_est, np.zeros((t_est.size, 2)))
    pair = associate(est, ref, max_diff_s=0.01)
    assert len(pair.est) == t_est.size
    np.testing.assert_allclose(
        pair.ref.xz_m, np.column_stack([1 + 0.5 * t_est, -0.25 * t_est]), atol=1e-12
    )
    np.testing.assert_array_equal(pair.ref.timestamp_s, t_est)


def test_association_does_not_bridge_gaps_and_honours_offset():
    t_ref = np.arange(0.0, 2.0 + 1e-9, 1 / 120)
    gap = (t_ref > 0.5) & (t_ref < 0.8)
    ref = Trajectory.from_xz(t_ref[~gap], np.column_stack([t_ref, t_ref])[~gap])
    t_est = np.arange(0.0, 2.0, 1 / 30)
    est = Trajectory.from_xz(t_est, np.zeros((t_est.size, 2)))
    pair = associate(est, ref, max_diff_s=0.01)
    kept_t = pair.est.timestamp_s
    assert not np.any((kept_t > 0.51) & (kept_t < 0.79))
    assert np.any(kept_t < 0.5) and np.any(kept_t > 0.8)
    # estimate clock 100 s ahead of the mocap clock
    est_late = Trajectory.from_xz(t_est + 100.0, np.zeros((t_est.size, 2)))
    with pytest.raises(EvaluationError, match="no matching timestamps"):
        associate(est_late, ref)
    pair = associate(est_late, ref, offset_s=-100.0)
    np.testing.assert_allclose(pair.ref.xz_m[:, 0], pair.est.timestamp_s - 100.0, atol=1e-9)


# ------------------------------------------------------------------------------------ ATE
def test_ate_first_anchor_removes_the_start_offset_and_reports_axes():
    ref = sagittal_ref(30.0)
    n = len(ref)
    e = np.zeros((n, 3))
    e[1:, 0] = 0.02 * np.where(np.arange(1, n) % 2 == 0, 1.0, -1.0)
    e[1:, 2] = 0.01
    est = Trajectory(
        ref.timestamp_s.copy(), ref.position_m + [1.0, 0.0, -2.0] + e, ref.quat_wxyz.copy()
    )
    res = ate_per_axis(est, ref)
    np.testing.assert_allclose(res.translation_m, [-1.0, 0.0, 2.0], atol=1e-12)
    np.testing.assert_allclose(res.errors_xyz_m, e, atol=1e-12)
    assert res.rmse_x_m == pytest.approx(0.02 * np.sqrt((n - 1) / n), abs=1e-12)
    assert res.rmse_z_m == pytest.approx(0.01 * np.sqrt((n - 1) / n), abs=1e-12)
    assert res.rmse_x_cm == pytest.approx(100 * res.rmse_x_m)
    assert res.rmse_total_m == pytest.approx(np.hypot(res.rmse_x_m, res.rmse_z_m), abs=1e-12)
    # mask: only the second half counts, the anchor stays the first sample
    mask = np.arange(n) >= n // 2
    res_m = ate_per_axis(est, ref, mask=mask)
    np.testing.assert_allclose(res_m.translation_m, res.translation_m)
    assert res_m.stats.n == mask.sum()
    assert res_m.rmse_z_m == pytest.approx(0.01, abs=1e-12)
    with pytest.raises(EvaluationError):
        ate_per_axis(est, ref, mask=np.zeros(n, bool))
    with pytest.raises(EvaluationError, match="associate"):
        ate_per_axis(est, sagittal_ref(120.0))


def _write_pair(tmp_path, est, ref):
    p_est, p_ref = tmp_path / "est.tum", tmp_path / "ref.tum"
    write_tum(p_est, est)
    write_tum(p_ref, ref)
    return p_est, p_ref


def _evo_ape(p_est, p_ref, *, align_origin=False, align_=False, correct_scale=False):
    from evo.core import metrics, sync
    from evo.tools import file_interface

    ref = file_interface.read_tum_trajectory_file(str(p_ref))
    est = file_interface.read_tum_trajectory_file(str(p_est))
    ref, est = sync.associate_trajectories(ref, est, max_diff=0.001)
    if align_origin:
        est.align_origin(ref)
    if align_ or correct_scale:
        est.align(ref, correct_scale=correct_scale)
    m = metrics.APE(metrics.PoseRelation.translation_part)
    m.process_data((ref, est))
    return m, est, ref


def _ours(p_est, p_ref):
    from vio_graph.recording.tum import read_tum

    return associate(read_tum(p_est), read_tum(p_ref), max_diff_s=0.01)


def test_ate_matches_evo_ape_with_align_origin(tmp_path):
    ref = sagittal_ref(120.0)
    est = perturbed(
        Trajectory(ref.timestamp_s[::4], ref.position_m[::4], ref.quat_wxyz[::4]), [0.3, 0.0, -0.1]
    )
    p_est, p_ref = _write_pair(tmp_path, est, ref)
    m, est_evo, ref_evo = _evo_ape(p_est, p_ref, align_origin=True)
    pair = _ours(p_est, p_ref)
    res = ate_per_axis(pair.est, pair.ref, anchor="first")
    assert res.stats.n == len(est)
    np.testing.assert_allclose(np.linalg.norm(res.errors_xyz_m, axis=1), m.error, atol=1e-9)
    assert res.rmse_total_m == pytest.approx(m.get_all_statistics()["rmse"], abs=1e-9)
    diff = est_evo.positions_xyz - ref_evo.positions_xyz
    assert res.rmse_x_m == pytest.approx(np.sqrt(np.mean(diff[:, 0] ** 2)), abs=1e-9)
    assert res.rmse_z_m == pytest.approx(np.sqrt(np.mean(diff[:, 2] ** 2)), abs=1e-9)
    # evo's align_origin also rotates by the first orientations; ours does too with "origin"
    R = rot_y(0.3) @ rot_z(0.2)
    q = np.tile(quat_wxyz_from_matrix(R), (len(est), 1))
    est_rot = Trajectory(est.timestamp_s, est.position_m, q)
    p_est, p_ref = _write_pair(tmp_path, est_rot, ref)
    m, _, _ = _evo_ape(p_est, p_ref, align_origin=True)
    pair = _ours(p_est, p_ref)
    res_o = ape(pair.est, pair.ref, alignment="origin")
    np.testing.assert_allclose(np.linalg.norm(res_o.errors_xyz_m, axis=1), m.error, atol=1e-9)


@pytest.mark.parametrize("kind, scale", [("se3", False), ("sim3", True)])
def test_aligned_ape_matches_evo(tmp_path, kind, scale):
    ref = sagittal_ref(30.0)
    est = perturbed(ref, [0.3, 0.0, -0.1], seed=3)
    p_est, p_ref = _write_pair(tmp_path, est, ref)
    m, _, _ = _evo_ape(p_est, p_ref, align_=True, correct_scale=scale)
    pair = _ours(p_est, p_ref)
    res = ape(pair.est, pair.ref, alignment=kind)
    assert res.stats.rmse == pytest.approx(m.get_all_statistics()["rmse"], abs=1e-9)


def test_umeyama_and_se2_recover_known_transforms():
    rng = np.random.default_rng(1)
    x = rng.normal(size=(3, 50))
    R_true = rot_y(0.4) @ rot_z(-0.3)
    t_true = np.array([0.5, -1.0, 2.0])
    R, t, c = umeyama_alignment(x, 1.7 * R_true @ x + t_true[:, None], with_scale=True)
    np.testing.assert_allclose(R, R_true, atol=1e-12)
    np.testing.assert_allclose(t, t_true, atol=1e-12)
    assert c == pytest.approx(1.7, abs=1e-12)
    # sagittal: estimate = ref rotated about y and shifted; se2 alignment undoes it exactly
    ref = sagittal_ref(30.0)
    est_p = (ref.position_m - [0.2, 0.0, 0.1]) @ rot_y(-0.25).T
    est = Trajectory(ref.timestamp_s, est_p, ref.quat_wxyz)
    res = ape(est, ref, alignment="se2")
    assert res.stats.max < 1e-12
    np.testing.assert_allclose(res.alignment.rotation, rot_y(0.25), atol=1e-12)
    assert ape(est, ref, alignment="translation").stats.rmse > 0.01
    assert align(est, ref, "none").scale == 1.0


# ------------------------------------------------------------------------------------ RPE
def test_rpe_of_a_constant_drift_is_the_drift_times_delta():
    ref = sagittal_ref(30.0)
    drift = np.array([0.05, 0.0, -0.02])  # m/s
    s = ref.timestamp_s - ref.timestamp_s[0]
    est = Trajectory(ref.timestamp_s, ref.position_m + np.outer(s, drift), ref.quat_wxyz)
    for delta in (0.1, 1.0):
        res = rpe(est, ref, delta)
        dt = ref.timestamp_s[res.pairs[:, 1]] - ref.timestamp_s[res.pairs[:, 0]]
        np.testing.assert_allclose(dt, delta, atol=1e-9)
        np.testing.assert_allclose(res.errors_xyz_m, np.outer(dt, drift), atol=1e-12)
        assert res.rmse_x_m == pytest.approx(0.05 * delta, rel=1e-9)
    assert rpe(est, ref, 1.0, all_pairs=False).pairs.shape[0] == 4
    with pytest.raises(EvaluationError):
        rpe(est, ref, 100.0)


def test_rpe_matches_evo_in_frames(tmp_path):
    from evo.core import metrics

    ref = sagittal_ref(30.0)
    est = perturbed(ref, [0.3, 0.0, -0.1], seed=5)
    p_est, p_ref = _write_pair(tmp_path, est, ref)
    m, est_evo, ref_evo = _evo_ape(p_est, p_ref)
    r = metrics.RPE(
        metrics.PoseRelation.translation_part,
        delta=3,
        delta_unit=metrics.Unit.frames,
        all_pairs=True,
    )
    r.process_data((ref_evo, est_evo))
    pair = _ours(p_est, p_ref)
    res = rpe(pair.est, pair.ref, 3 / 30.0)
    np.testing.assert_allclose(np.linalg.norm(res.errors_xyz_m, axis=1), r.error, atol=1e-9)


# --------------------------------------------------------------------------------- tables
def test_summary_table_has_mean_sd_and_paper_numbers():
    trials = [
        TrialAte("upstair", f"t{i}", x, z) for i, (x, z) in enumerate([(0.02, 0.01), (0.04, 0.03)])
    ]
    trials.append(TrialAte("level", "t0", 0.01, 0.02))
    s = summarise(trials)
    assert [e.experiment for e in s] == ["upstair", "level"]
    assert s[0].x_mean_cm == pytest.approx(3.0)
    assert s[0].x_sd_cm == pytest.approx(np.sqrt(2.0))
    assert s[0].z_mean_cm == pytest.approx(2.0)
    assert np.isnan(s[1].x_sd_cm)
    md = markdown_table(s)
    assert "| upstair | 2 | 3.00 ± 1.41 | 2.96 ± 0.92 | 2.00 ± 1.41 | 2.16 ± 0.46 |" in md
    assert "| level | 1 | 1.00 | — | 2.00 | — |" in md
    assert PAPER_TOE_ATE_CM["prosthesis_upstair"]["x"] == (4.14, 0.85)
    with pytest.raises(EvaluationError):
        summarise([])


def test_generated_doc_keeps_its_hand_written_tail(tmp_path) -> None:
    from vio_graph.io_utils import write_generated_doc

    doc = tmp_path / "results.md"
    write_generated_doc(doc, "# Results\n\n| a |\n")  # new file: generated part only
    assert doc.read_text() == "# Results\n\n| a |\n"
    doc.write_text(doc.read_text() + "\n## Reading (written by hand)\n- note 1\n")
    write_generated_doc(doc, "# Results\n\n| b |\n")
    text = doc.read_text()
    assert "| b |" in text and "| a |" not in text
    assert text.endswith("## Reading (written by hand)\n- note 1\n")
