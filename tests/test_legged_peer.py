"""GTSAM's legged InEKF as a baseline mode (vio_graph/filter/legged_peer.py)."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

from vio_graph.errors import EstimationError, VioGraphError
from vio_graph.filter.legged_peer import GtsamLeggedPeer


def test_bad_lever_arm_is_refused() -> None:
    with pytest.raises(EstimationError, match="4x4"):
        GtsamLeggedPeer(np.eye(3))


def test_mode_is_named_only_never_part_of_all() -> None:
    from vio_graph.cli import _parse_modes

    assert "gtsam_legged" not in _parse_modes("all")
    assert _parse_modes("filter,gtsam_legged") == ("filter", "gtsam_legged")
    with pytest.raises(VioGraphError, match="unknown"):
        _parse_modes("filter,legged")


def test_peer_tracks_a_simulated_trial(short_upstair: Path, tmp_path: Path) -> None:
    """Leg odometry + IMU through GTSAM: far better than the IMU alone, worse than ours, and
    the filter's own path is untouched by running it."""
    from vio_graph.config import PipelineConfig
    from vio_graph.pipeline import run_recording

    cfg = PipelineConfig()
    with_peer = run_recording(
        short_upstair,
        tmp_path / "peer",
        cfg,
        modes=("filter", "gtsam_legged"),
        progress=False,
        visualize=False,
    )
    run_recording(short_upstair, tmp_path / "alone", cfg, progress=False, visualize=False)
    ate = with_peer.metrics["ate_cm"]
    peer = ate["gtsam_legged"]["camera"]
    assert peer["x"] < 0.2 * ate["imu_only"]["camera"]["x"]
    assert peer["x"] > ate["filter"]["camera"]["x"]
    assert with_peer.metrics["gtsam_legged"]["contact_frames"] > 0
    a = (tmp_path / "peer" / "trajectories" / "filter_camera.tum").read_bytes()
    b = (tmp_path / "alone" / "trajectories" / "filter_camera.tum").read_bytes()
    assert a == b
