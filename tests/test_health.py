"""Self-diagnosis: the estimator says when it is in trouble, and why."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest
from typer.testing import CliRunner

from vio_graph.cli import app
from vio_graph.health import HealthMonitor
from vio_graph.types import Displacement2D

from .test_imu_mounting import remount_imu

DT = 1 / 30


def _feed(monitor: HealthMonitor, fused_step_m: float, accept: bool, n: int = 150) -> None:
    """Vision says the camera moves 1 cm per frame along x; the fused path moves
    ``fused_step_m`` per frame."""
    cov = np.eye(2) * 1e-6
    for k in range(n):
        d = None if k == 0 else Displacement2D((k - 1) * DT, k * DT, np.array([0.01, 0.0]), cov)
        monitor.add_frame(k * DT, np.array([k * fused_step_m, 0.0]), d, accept, in_stance=False)


def test_a_consistent_filter_is_healthy() -> None:
    m = HealthMonitor()
    _feed(m, 0.01, accept=True)
    rep = m.report()
    assert rep["ok"] and not rep["warnings"]
    assert rep["fused_vs_visual"]["windows"] == 4 and rep["fused_vs_visual"]["departure_share"] == 0


def test_a_pinned_filter_is_reported_with_a_cause() -> None:
    m = HealthMonitor()
    _feed(m, 0.0, accept=False)  # the position stops advancing, the gate refuses vision
    rep = m.report(pitch_offset_deg=0.5)
    assert not rep["ok"] and rep["displacements_rejected_share"] == 1.0
    assert rep["fused_vs_visual"]["departure_share"] == 1.0
    assert rep["fused_vs_visual"]["max_departure_cm"] > 25
    assert len(rep["warnings"]) == 1 and "Likely cause" in rep["warnings"][0]
    m2 = HealthMonitor()
    _feed(m2, 0.0, accept=False)
    assert "imu_T_cam" in m2.report(pitch_offset_deg=8.0)["warnings"][0]


def test_level_surfaces_far_from_the_imu_gravity_warn_on_their_own() -> None:
    """Vision accepted, no departure: a level-surface correction of 8 deg still warns (a
    mounting error); 2.3 deg, the largest seen on correctly mounted simulated trials, does not."""
    m = HealthMonitor()
    _feed(m, 0.01, accept=True)
    assert not m.report(pitch_offset_deg=2.3)["warnings"]
    rep = m.report(pitch_offset_deg=-8.0)
    assert not rep["ok"] and len(rep["warnings"]) == 1
    assert "imu_T_cam" in rep["warnings"][0]


@pytest.mark.slow
def test_run_warns_on_a_recording_whose_imu_mount_is_misdeclared(
    short_upstair: Path, tmp_path: Path
) -> None:
    """The IMU is turned to the camera's axes but metadata.yaml still declares the shank-aligned
    mount: `vio-graph run` must print a warning line (the healthy recording must not)."""
    from vio_graph.recording import Recording

    R = Recording.open(short_upstair).metadata.extrinsics.imu_T_cam_matrix()[:3, :3].T
    bad = remount_imu(short_upstair, tmp_path / "bad", R, declare=False)
    runner = CliRunner()
    for rec, expect_warning in ((bad, True), (short_upstair, False)):
        res = runner.invoke(
            app, ["run", str(rec), "--out", str(tmp_path / f"res_{rec.name}"), "--no-rerun"]
        )
        assert res.exit_code == 0, res.output
        assert "health:" in res.output
        assert ("WARNING: the fused estimate is inconsistent" in res.output) == expect_warning, (
            res.output
        )


def test_one_window_far_off_is_a_jump_even_when_the_shares_are_low() -> None:
    """25 healthy windows and one in which the fused path jumps 20 cm away from vision: the
    departure share (4 %) and refusals (0 %) stay under their limits, the jump test warns."""
    m = HealthMonitor()
    cov = np.eye(2) * 1e-6
    n = 26 * 30 + 1
    for k in range(n):
        d = None if k == 0 else Displacement2D((k - 1) * DT, k * DT, np.array([0.01, 0.0]), cov)
        jump = 0.2 if k >= 400 else 0.0
        m.add_frame(k * DT, np.array([k * 0.01 + jump, 0.0]), d, True, in_stance=False)
    rep = m.report()
    fv = rep["fused_vs_visual"]
    assert fv["departure_share"] < m.limits.max_departure_share
    assert rep["displacements_rejected_share"] == 0.0
    assert fv["jump"] and not rep["ok"] and len(rep["warnings"]) == 1


def _feed_floor(
    monitor: HealthMonitor, x_var_m2: float, stance_every: int = 0, n: int = 150
) -> None:
    """Accepted displacements whose x variance is ``x_var_m2`` (1.0 = the ICP's cap for an
    unobservable direction: a floor); every ``stance_every``-th frame anchored in stance."""
    cov = np.diag([x_var_m2, 1e-6])
    for k in range(n):
        d = None if k == 0 else Displacement2D((k - 1) * DT, k * DT, np.array([0.01, 0.0]), cov)
        stance = bool(stance_every) and k % stance_every == 0
        monitor.add_frame(k * DT, np.array([k * 0.01, 0.0]), d, True, in_stance=stance)


def test_x_carried_by_the_imu_alone_is_reported() -> None:
    blind = HealthMonitor()
    _feed_floor(blind, x_var_m2=1.0)  # a floor only: x is never observed
    rep = blind.report()
    assert rep["x_blind"]["warned"] and not rep["ok"]
    assert rep["x_blind"]["share"] == pytest.approx(1.0, abs=0.02)
    assert rep["x_blind"]["longest_s"] == pytest.approx(149 * DT, abs=1e-9)
    assert len(rep["warnings"]) == 1 and "forward (x)" in rep["warnings"][0]

    seen = HealthMonitor()
    _feed_floor(seen, x_var_m2=1e-6)  # risers in view: x measured on every frame
    assert seen.report()["x_blind"]["share"] < 0.01 and seen.report()["ok"]  # frame 0 only

    anchored = HealthMonitor()
    _feed_floor(anchored, x_var_m2=1.0, stance_every=2)  # half the frames anchored
    rep = anchored.report()
    assert rep["x_blind"]["longest_s"] == pytest.approx(DT, abs=1e-9)
    assert rep["x_blind"]["share"] == pytest.approx(0.5, abs=0.02)
    assert rep["x_blind"]["warned"]  # above the 1/3 share
    sparse = HealthMonitor()
    _feed_floor(sparse, x_var_m2=1.0, stance_every=1)
    assert not sparse.report()["x_blind"]["warned"]


def test_displacements_the_filter_could_not_relate_are_not_counted_as_refused() -> None:
    """A displacement across a frame gap (stale) is neither accepted nor refused by the gate."""
    m = HealthMonitor()
    cov = np.eye(2) * 1e-6
    for k in range(60):
        d = None if k == 0 else Displacement2D((k - 1) * DT, k * DT, np.array([0.01, 0.0]), cov)
        stale = k % 2 == 0
        m.add_frame(
            k * DT, np.array([k * 0.01, 0.0]), d, accepted=not stale, in_stance=False, refused=False
        )
    assert m.report()["displacements_rejected_share"] == 0.0
    m2 = HealthMonitor()  # without the estimator's distinction every non-accepted one counts
    for k in range(60):
        d = None if k == 0 else Displacement2D((k - 1) * DT, k * DT, np.array([0.01, 0.0]), cov)
        m2.add_frame(k * DT, np.array([k * 0.01, 0.0]), d, accepted=k % 2 == 1, in_stance=False)
    assert m2.report()["displacements_rejected_share"] == pytest.approx(0.5, abs=0.02)


def test_a_drift_the_filters_own_covariance_allows_is_reported() -> None:
    """x blind for 0.5 s at a velocity sigma of 0.3 m/s (a clipped heel strike before a level
    floor): the filter's own account says x may be 15 cm off, and run says so; vision or a
    stance in between restarts the sum."""

    def feed(v_sigma: float, seen_every: int = 0, distrusted: int = 0) -> dict:
        m = HealthMonitor()
        floor, risers = np.diag([1.0, 1e-6]), np.eye(2) * 1e-6
        for k in range(56):  # 1.3 s of stairs (x measured), then 0.5 s of floor
            blind = k > 39
            cov = floor if blind else risers
            d = None if k == 0 else Displacement2D((k - 1) * DT, k * DT, np.zeros(2), cov)
            stance = blind and bool(seen_every) and (k - 40) % seen_every == 0
            m.add_frame(
                k * DT,
                np.zeros(2),
                d,
                True,
                stance,
                velocity_sigma_x_mps=v_sigma if blind else 0.01,
                distrusted_imu_samples=distrusted if k >= 40 else 0,  # clipped at 1.3 s
            )
        return m.report()

    rep = feed(0.3, distrusted=5)
    # 0.01 -> 0.3 m/s over the first blind frame, then 0.3 m/s over 15 frames
    assert rep["x_blind"]["max_drift_sigma_cm"] == pytest.approx(0.155 * 100 * DT + 30.0 * 15 * DT)
    assert not rep["x_blind"]["warned"]  # 16 of 56 frames: below the blind-share warning
    assert rep["x_blind"]["drift_warned"] and not rep["ok"]
    assert "15.5 cm" in rep["warnings"][0] and "5 saturated" in rep["warnings"][0]
    # the same covariance without distrusted IMU samples is left to the blind-share test
    rep = feed(0.3)
    assert rep["x_blind"]["max_drift_sigma_cm"] == pytest.approx(0.155 * 100 * DT + 30.0 * 15 * DT)
    assert not rep["x_blind"]["drift_warned"] and rep["ok"]
    # a filter that knows its velocity to 1 cm/s: 0.5 cm at most, no warning
    rep = feed(0.01, distrusted=5)
    assert not rep["x_blind"]["drift_warned"] and rep["ok"]
    # a stance every 5 frames, the first on the frame after the clipped samples: each sum
    # runs over the 5 frame periods up to an anchored frame (0.3 m/s * 5/30 s = 5 cm), and
    # only the first run (one period, 0.5 cm) held distrusted samples: no warning
    rep = feed(0.3, seen_every=5, distrusted=5)
    assert rep["x_blind"]["max_drift_sigma_cm"] == pytest.approx(30.0 * 5 * DT)
    assert rep["x_blind"]["max_drift_sigma_after_distrusted_imu_cm"] == pytest.approx(
        0.155 * 100 * DT
    )
    assert not rep["x_blind"]["drift_warned"]
