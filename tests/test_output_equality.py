"""The faster output writers and the shared ground-truth association give the same text and
numbers as the straightforward per-row / per-mode code they replaced (kept here as the
reference)."""

from __future__ import annotations

import numpy as np
import pytest

from vio_graph.evaluation.association import associate
from vio_graph.evaluation.metrics import ape, ate_per_axis, rpe
from vio_graph.evaluation.run_metrics import evaluate_paths
from vio_graph.outputs import _safety_cells
from vio_graph.recording.streams import GroundTruth, Trajectory
from vio_graph.recording.tum import format_tum
from vio_graph.safety.online import SafetyEstimate, SafetyLog, csv_values


def _format_tum_reference(traj: Trajectory) -> str:
    q = traj.quat_wxyz
    rows = np.column_stack([traj.timestamp_s, traj.position_m, q[:, 1], q[:, 2], q[:, 3], q[:, 0]])
    lines = [
        f"{r[0]:.9f} {r[1]:.6f} {r[2]:.6f} {r[3]:.6f} {r[4]:.6f} {r[5]:.6f} {r[6]:.6f} {r[7]:.6f}"
        for r in rows
    ]
    return "# timestamp tx ty tz qx qy qz qw\n" + "\n".join(lines) + "\n"


def test_tum_text_is_the_per_row_formatting() -> None:
    rng = np.random.default_rng(3)
    t = np.cumsum(rng.uniform(0.01, 0.05, 400))
    xz = rng.normal(0.0, 2.0, (400, 2))
    xz[:5] = [[-0.0, 0.0], [-1e-9, 4e-7], [5e-7, -5e-7], [1234.5678915, -0.0000005], [1e-300, 2]]
    for traj in (Trajectory.from_xz(t, xz), Trajectory.from_xz(t[:0], xz[:0])):
        assert format_tum(traj) == _format_tum_reference(traj)
    # the columns that hold one value in every row are formatted once: any orientation, a
    # -0.0 among zeros, a NaN or inf column, one row, a time column with a repeat
    q = rng.normal(size=(400, 4))
    pos = np.column_stack([xz[:, 0], np.zeros(400), xz[:, 1]])
    pos[7, 1] = -0.0
    const = Trajectory.from_xz(t, xz)
    cases = [
        Trajectory(t, pos, q / np.linalg.norm(q, axis=1)[:, None]),
        Trajectory(t, np.column_stack([xz, np.full(400, np.nan)]), const.quat_wxyz),
        Trajectory(t, np.column_stack([xz, np.full(400, -np.inf)]), -const.quat_wxyz),
        Trajectory(t[:1], pos[:1], const.quat_wxyz[:1]),
        Trajectory(np.repeat(t[:200], 2), pos, const.quat_wxyz),
        Trajectory(np.full(400, 2.5), pos, const.quat_wxyz),
    ]
    for traj in cases:
        assert format_tum(traj) == _format_tum_reference(traj)


def _estimate(rng: np.random.Generator, k: int) -> SafetyEstimate:
    f = [float(v) for v in rng.normal(0.0, 0.1, 12)]
    f[k % 12] = float("nan")  # a NaN in a different column each frame
    return SafetyEstimate(
        f[0], abs(f[1]), rng.normal(size=(2, 2)), f[2], abs(f[3]), f[4], f[5], bool(k % 3 == 0),
        f[6], abs(f[7]), int(k % 5), f[8], f[9], bool(k % 4 == 1),
        np.array([f[10], f[11], float("nan") if k % 2 else 0.5, -0.0]),
        pose_consistency_scale=1.0 + f[10], map_consistency_scale=float("inf") if k == 7 else 1.0,
    )  # fmt: skip


def test_frames_csv_safety_cells_are_those_of_each_estimate() -> None:
    rng = np.random.default_rng(5)
    ests = [None if k in (0, 9, 10) else _estimate(rng, k) for k in range(30)]
    log = SafetyLog()
    for s in ests:
        log.append(s)
    n = len(ests) + 2  # two frames past the log: empty cells
    expected = [",".join(csv_values(ests[k] if k < len(ests) else None)) for k in range(n)]
    assert _safety_cells(log, n) == expected
    assert _safety_cells(ests, n) == expected  # a plain list takes the per-object path


def _evaluate_reference(gt, t_s, paths, visible):
    """evaluate_paths as it was: every mode associated with the truth on its own."""
    out = {"ate_cm": {}, "ate_cm_visible": {}, "ape": {}, "rpe": {}}
    for mode, bodies in paths.items():
        for body, xz in bodies.items():
            pair = associate(Trajectory.from_xz(t_s, xz), gt.trajectories[body], max_diff_s=0.02)
            e, r = pair.est, pair.ref
            a = ate_per_axis(e, r, anchor="first")
            out["ate_cm"][mode, body] = (a.rmse_x_cm, a.rmse_z_cm, a.rmse_total_cm)
            keep = np.interp(e.timestamp_s, t_s, visible.astype(float)) > 0.5
            av = ate_per_axis(e, r, anchor="first", mask=keep)
            out["ate_cm_visible"][mode, body] = (av.rmse_x_cm, av.rmse_z_cm, float(keep.mean()))
            ap = ape(e, r, alignment="translation")
            out["ape"][mode, body] = (100 * ap.rmse_x_m, 100 * ap.rmse_z_m)
            out["rpe"][mode, body] = tuple(100 * rpe(e, r, d).stats.rmse for d in (0.1, 1.0))
    return out


def test_shared_association_gives_every_mode_its_own_numbers() -> None:
    rng = np.random.default_rng(11)
    t_gt = np.arange(0.0, 6.0, 1 / 120)
    t_gt = np.delete(t_gt, np.arange(300, 330))  # a mocap gap: frames there are left out
    bodies = ("camera", "toe")
    truth = {b: np.column_stack([t_gt * (1 + i), np.sin(t_gt + i)]) for i, b in enumerate(bodies)}
    gt = GroundTruth(trajectories={b: Trajectory.from_xz(t_gt, xz) for b, xz in truth.items()})
    t_s = np.arange(0.01, 5.9, 1 / 30)
    visible = rng.random(t_s.size) < 0.6
    paths = {
        m: {b: Trajectory.from_xz(t_gt, truth[b]).xz_at(t_s) + rng.normal(0, s, (t_s.size, 2))
            for b in bodies}
        for m, s in (("filter", 0.01), ("smoother", 0.005), ("batch", 0.003))
    }  # fmt: skip
    got = evaluate_paths(gt, t_s, paths, visible)
    ref = _evaluate_reference(gt, t_s, paths, visible)
    for (mode, body), v in ref["ate_cm"].items():
        a = got["ate_cm"][mode][body]
        assert (a["x"], a["z"], a["total"]) == v
        av = got["ate_cm_visible"][mode][body]
        assert (av["x"], av["z"], av["fraction"]) == ref["ate_cm_visible"][mode, body]
        ap = got["ape_translation_aligned_cm"][mode][body]
        assert (ap["x"], ap["z"]) == ref["ape"][mode, body]
        assert (got["rpe_cm"]["0.1s"][mode][body], got["rpe_cm"]["1.0s"][mode][body]) == (
            ref["rpe"][mode, body]
        )
    assert got["ate_cm"]["batch"]["toe"]["total"] < got["ate_cm"]["filter"]["toe"]["total"]


@pytest.mark.parametrize("n", [0, 1])
def test_safety_cells_of_tiny_logs(n: int) -> None:
    log = SafetyLog()
    assert _safety_cells(log, n) == [",".join(csv_values(None))] * n


@pytest.mark.parametrize("seed", [0, 1])
def test_true_clearance_is_the_same_with_the_compiled_geometry(
    seed: int, monkeypatch: pytest.MonkeyPatch
) -> None:
    """The evaluation's true clearance per frame (true_safety) takes the compiled foot
    geometry when the run uses the compiled kernels: the same numbers, bit for bit."""
    pytest.importorskip("numba")
    from pathlib import Path

    from vio_graph.evaluation.safety import true_safety
    from vio_graph.recording.reader import Recording
    from vio_graph.safety.config import SafetyConfig

    rec = Recording.open(Path(__file__).resolve().parents[1] / "data" / "sample")
    t = np.asarray(rec.frame_timestamps_s, dtype=float)
    # the frame times and random times between them
    t = np.sort(np.r_[t, np.random.default_rng(seed).uniform(t[0], t[-1], 200)])
    landing = np.arange(t.size) % 17 == 0
    cfg = SafetyConfig(sole_thickness_m=0.05 * seed)
    monkeypatch.setenv("VIO_GRAPH_COMPILED", "0")
    ref = true_safety(rec.groundtruth, rec.metadata.terrain, t, landing, cfg)
    monkeypatch.setenv("VIO_GRAPH_COMPILED", "1")
    got = true_safety(rec.groundtruth, rec.metadata.terrain, t, landing, cfg)
    assert ref is not None and got is not None
    assert np.isfinite(ref["clearance_m"]).all()
    for key, value in ref.items():
        np.testing.assert_array_equal(got[key], value, err_msg=key)


def test_rig_anchor_keeps_a_first_frame_leg_error_in_that_frame() -> None:
    """A toe path exact but for a 5 mm z error on its first frame, the camera exact: the
    paper's anchor (the toe's own first sample) moves all N samples by 5 mm (RMSE 5 mm on N-1 of
    them), the rig anchor (the camera's offset) leaves it on the one frame (5 mm / sqrt(N)); an
    estimate offset as a whole (an arbitrary start) is removed by both."""
    t_gt = np.arange(0.0, 4.0, 1 / 120)
    truth = {
        "camera": np.column_stack([0.5 * t_gt, 0.45 + 0.02 * np.sin(3 * t_gt)]),
        "toe": np.column_stack([0.5 * t_gt + 0.1, 0.05 * np.abs(np.sin(2 * t_gt))]),
    }
    gt = GroundTruth(trajectories={b: Trajectory.from_xz(t_gt, xz) for b, xz in truth.items()})
    t_s = np.arange(0.0, 3.9, 1 / 30)
    start = np.array([1.0, -2.0])  # the estimator's own origin
    cam = Trajectory.from_xz(t_gt, truth["camera"]).xz_at(t_s) + start
    toe = Trajectory.from_xz(t_gt, truth["toe"]).xz_at(t_s) + start
    toe[0, 1] -= 0.005
    got = evaluate_paths(gt, t_s, {"filter": {"camera": cam, "toe": toe}}, None)
    n = t_s.size
    paper, rig = got["ate_cm"]["filter"]["toe"], got["ate_cm_rig"]["filter"]["toe"]
    assert paper["z"] == pytest.approx(0.5 * np.sqrt((n - 1) / n), rel=1e-6)
    assert rig["z"] == pytest.approx(0.5 / np.sqrt(n), rel=1e-6)
    assert rig["x"] == pytest.approx(0.0, abs=1e-9) and paper["x"] == pytest.approx(0.0, abs=1e-9)
    assert got["ate_cm_rig"]["filter"]["camera"]["z"] == pytest.approx(0.0, abs=1e-9)
    # without a camera path there is no rig anchor
    assert evaluate_paths(gt, t_s, {"filter": {"toe": toe}}, None)["ate_cm_rig"]["filter"] == {}
