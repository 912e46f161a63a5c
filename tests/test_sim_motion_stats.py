"""Known answers of benchmarks/sim_motion_stats.py (the simulator's motion check)."""

from __future__ import annotations

import shutil
import sys
from pathlib import Path

import numpy as np
import pytest

from vio_graph.errors import VioGraphError

sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "benchmarks"))
import sim_motion_stats  # noqa: E402


def test_constant_velocity_and_gravity_only(tiny_recording: Path) -> None:
    """The tiny recording's camera moves at (0.3, 0.1) m/s and its IMU reads gravity plus
    1 cm/s^2 of noise: speed sqrt(0.1) m/s everywhere, about 1 g, nothing above the limits."""
    m = sim_motion_stats.motion_stats(tiny_recording)
    assert m["peak_speed_mps"] == pytest.approx(np.sqrt(0.3**2 + 0.1**2), rel=1e-3)  # TUM rounding
    assert m["share_above_speed"] == 0.0
    assert m["force_p99_g"] == pytest.approx(1.0, abs=0.01)
    assert m["force_peak_g"] < 1.01
    assert m["share_above_4g"] == m["share_above_8g"] == 0.0


def test_a_recording_without_ground_truth_is_refused_by_name(
    tiny_recording: Path, tmp_path: Path, capsys
) -> None:
    bare = tmp_path / "bare"
    shutil.copytree(tiny_recording, bare)
    shutil.rmtree(bare / "groundtruth")
    with pytest.raises(VioGraphError, match="bare"):
        sim_motion_stats.motion_stats(bare)
    assert sim_motion_stats.main([str(bare)]) == 1
    assert "bare" in capsys.readouterr().err
