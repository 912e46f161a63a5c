"""Case sets of ``vio-graph robustness --cases``."""

from __future__ import annotations

from typer.testing import CliRunner

from vio_graph.cli import app
from vio_graph.robustness import (
    FAULT_CASES,
    IMU_CASES,
    KNOCK_CASES,
    OCCLUDER_CASES,
    SATURATION_CASES,
    SPIKE_CASES,
)


def test_saturation_cases_are_the_clean_and_saturation_rows_of_the_imu_sweep() -> None:
    names = [(c.name, c.severity) for c in SATURATION_CASES]
    assert names == [
        ("clean", "-"),
        ("IMU accel saturation", "4 g"),
        ("IMU accel saturation", "3 g"),
    ]
    assert SATURATION_CASES[0].sim_faults == {}
    # the same faults (4 g = 39.2 m/s^2, 3 g = 29.4 m/s^2) as the rows of the full IMU sweep
    assert all(c in IMU_CASES for c in SATURATION_CASES)
    assert SATURATION_CASES[1].sim_faults == {"imu_accel_saturation_mps2": 39.2}
    assert SATURATION_CASES[2].sim_faults == {"imu_accel_saturation_mps2": 29.4}


def test_unknown_case_set_is_refused(tmp_path) -> None:
    res = CliRunner().invoke(app, ["robustness", "--cases", "satur", "--out", str(tmp_path)])
    assert res.exit_code != 0
    assert "use all, imu, offsets, saturation, spikes, knock or occluder" in str(res.exception)
    assert not any(tmp_path.iterdir())  # nothing simulated


def test_knock_cases_are_the_clean_and_knock_rows_of_the_imu_sweep() -> None:
    names = [(c.name, c.severity) for c in KNOCK_CASES]
    assert names == [("clean", "-"), ("IMU knock", "0.1 s x 60 m/s^2")]
    assert all(c in IMU_CASES for c in KNOCK_CASES)
    assert KNOCK_CASES[1].sim_faults == {"imu_knock_start_s": 2.0}


def test_occluder_cases_are_the_clean_and_occluder_rows_of_the_full_sweep() -> None:
    names = [(c.name, c.severity) for c in OCCLUDER_CASES]
    assert names == [("clean", "-"), ("occluding foot in view", "1 s")]
    assert all(c in FAULT_CASES for c in OCCLUDER_CASES)
    assert OCCLUDER_CASES[1].sim_faults == {"occluder_start_s": 3.0, "occluder_duration_s": 1.0}


def test_spike_cases_are_the_clean_and_spike_rows_of_the_imu_sweep() -> None:
    names = [(c.name, c.severity) for c in SPIKE_CASES]
    assert names == [("clean", "-"), ("IMU spikes", "2 Hz")]
    assert all(c in IMU_CASES for c in SPIKE_CASES)
    assert SPIKE_CASES[1].sim_faults == {"imu_spike_rate_hz": 2.0}
