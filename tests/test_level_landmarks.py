"""Height landmarks: the level surfaces in the slice bound the filter's z on a long ascent.

One corner a frame cannot hand the camera height from nosing to nosing: a new corner is placed
where the displacements and the stance anchor put the camera, so their sub-millimetre per-step
biases add up over a long stair (filter toe z 6.7 cm after 2 minutes). Treads are in view
several at a time and for many frames, so as height landmarks (z only) they hand the height
over by co-observation.
"""

from __future__ import annotations

import numpy as np
import pytest

from vio_graph.config import PipelineConfig
from vio_graph.filter.config import FilterConfig
from vio_graph.filter.eskf import SagittalEskf
from vio_graph.recording import Recording
from vio_graph.replay import Replay
from vio_graph.types import Displacement2D, ImuSample, LandmarkKey
from vio_graph.viz.rerun_logger import NullVisualizer


def _still_imu(t: float) -> ImuSample:
    # a level IMU at rest: specific force +g up (IMU z = ground z)
    return ImuSample(t, np.array([0.0, 0.0, 9.81]), np.zeros(3), np.array([1.0, 0.0, 0.0, 0.0]))


def _walk(levels: bool, n_steps: int = 60, bias_m: float = 1e-3) -> float:
    """A camera climbing 1 cm a frame (30 fps); each displacement says 1 mm less in z (a
    biased visual odometry); a level surface every 10 cm of height is seen from 15 cm below
    it to 5 cm above it, so two are in view at once. Returns the final z error (m)."""
    cfg = FilterConfig(accel_noise_sigma_mps2=0.5)
    f = SagittalEskf(cfg)
    f.initialise(0.0, (0.0, 0.0), v_xz=(0.0, 0.3), P0=np.diag([1e-6] * 2 + [1e-2] * 2 + [1e-4] * 4))
    t, z_true, dt = 0.0, 0.0, 1.0 / 30.0
    for _ in range(n_steps):
        t0 = t
        for _ in range(4):  # IMU at 120 Hz; the camera moves at constant velocity
            t += dt / 4
            f.propagate(_still_imu(t))
        z_true += 0.01
        f.update_displacement(
            Displacement2D(t0, t, np.array([0.0, 0.01 - bias_m]), np.eye(2) * 2e-3**2)
        )
        if levels:
            for k in range(int(z_true / 0.1) - 1, int(z_true / 0.1) + 3):
                rel = 0.1 * k - z_true
                if -0.05 <= rel <= 0.15:
                    f.update_height_landmark(LandmarkKey("level", k), rel, 1e-3**2, t)
    return float(f.state.p_xz_m[1] - z_true)


def test_height_landmarks_hand_the_height_over_by_co_observation() -> None:
    """Known answer: 60 displacements 1 mm short leave 6 cm of z error without landmarks;
    with two level surfaces always in view the error stays at the millimetre level."""
    without = _walk(levels=False)
    assert without == pytest.approx(-0.06, abs=0.005)
    assert abs(_walk(levels=True)) < 0.005


def test_height_landmark_gate_and_first_sight() -> None:
    f = SagittalEskf(FilterConfig())
    f.initialise(0.0, (0.0, 1.0))
    key = LandmarkKey("level", 1)
    assert not f.update_height_landmark(key, -0.3, 1e-6, 0.0)  # first sight: augmented
    assert f.landmark_xz(key)[1] == pytest.approx(0.7)
    assert f.update_height_landmark(key, -0.301, 1e-6, 0.0)  # consistent: fused
    assert not f.update_height_landmark(key, -0.5, 1e-6, 0.0)  # 20 cm off: gated out
    assert f.state.n_landmark_rejected == 1


@pytest.mark.slow
def test_level_landmarks_bound_the_filter_z_on_a_long_ascent(tmp_path) -> None:
    """30 s of the 2-minute ascent (configs/upstair_long.yaml, seed 7): the filter's camera z
    RMSE (first-pose anchored) with the height landmarks against without them."""
    from vio_graph.sim import load_scenario, simulate

    cfg = load_scenario("upstair_long").model_copy(update={"duration_s": 30.0})
    rec = Recording.open(simulate(cfg, seed=7, out_dir=tmp_path / "rec"))
    gt = rec.groundtruth.trajectories["camera"]

    def z_rmse(level_landmarks: bool) -> float:
        pc = PipelineConfig()
        pc = pc.model_copy(
            update={"filter": pc.filter.model_copy(update={"level_landmarks": level_landmarks})}
        )
        replay = Replay(rec, pc, {"filter"}, NullVisualizer())
        log = replay.run()
        est = np.asarray(log.camera_xz["filter"])
        ref = gt.xz_at(np.asarray(log.t_s))
        err = (est - est[0]) - (ref - ref[0])
        return float(np.sqrt(np.mean(err[:, 1] ** 2)))

    # measured: 1.05 cm with, 1.70 cm without (the stance anchors' and displacements'
    # residual per-step biases are not all handed over: see docs/method.md)
    with_levels, without = z_rmse(True), z_rmse(False)
    assert with_levels < 0.012, with_levels
    assert with_levels < 0.8 * without, (with_levels, without)
